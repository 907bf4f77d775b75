#pragma once
/** \file kdtree.h A 3-D kd-tree for one-point-at-a-time queries from inside parallel loops. */
#include <pcl_animseg/error.h>
#include <pcl_animseg/flat_kdtree.h>

#include <flann/flann.hpp>
#include <pcl/point_cloud.h>
#include <pcl/search/kdtree.h>

#include <cmath>
#include <limits>
#include <memory>
#include <vector>

namespace pcl_animseg {

/** \brief One query of a FLANN kd-tree through findNeighbors (not flann::Index's search calls,
 * which open an OpenMP region per call: see KdTree below), its result copied into `indices` and
 * `sqr_distances` (closest first when `sorted`). */
template <typename FlannIndex, typename ResultSet>
void flannFindNeighbors(const FlannIndex& index, ResultSet& result, const float* query,
                        const flann::SearchParams& params, std::vector<std::size_t>& indices,
                        std::vector<float>& sqr_distances, bool sorted) {
  index.findNeighbors(result, query, params);
  const std::size_t n = result.size();
  indices.resize(n);
  sqr_distances.resize(n);
  if (n) result.copy(indices.data(), sqr_distances.data(), n, sorted);
}

/** \brief One thread's exact, unsorted radius searches in a FLANN index, its result buffers kept
 * from one query to the next: `indices` / `sqr_distances` hold the last query's points. */
struct FlannRadiusSearch {
  std::vector<std::size_t> indices;
  std::vector<float> sqr_distances;
  flann::SearchParams params{flann::FLANN_CHECKS_UNLIMITED};
  FlannRadiusSearch() { params.sorted = false; }
  /** The points within squared distance `sqr_radius` of `query` (FLANN's L2 is squared). */
  template <typename FlannIndex>
  void operator()(const FlannIndex& index, const float* query, float sqr_radius) {
    flann::RadiusResultSet<float> result(sqr_radius);
    flannFindNeighbors(index, result, query, params, indices, sqr_distances, false);
  }
};

/** \brief A kd-tree over the xyz of a cloud with the query interface of pcl::KdTreeFLANN (same
 * sorted results), minus its overhead, for the single-point queries that every stage here makes
 * inside its own OpenMP loops.
 *
 * Why not pcl::KdTreeFLANN: every query goes through flann::NNIndex::knnSearch, which opens an
 * OpenMP parallel region (`num_threads(cores)`) per call and copies the result through
 * heap-allocated matrices: 3-4x the cost of the search itself (200k 9-NN queries: 2.0 s against
 * 0.55 s on the 2-core machine). Why not FLANN's KDTreeSingleIndex called directly, as this class
 * did before: its virtual result-set calls and recursive descent still made 3-D searches 48% of a
 * whole run; FlatKdTree3 (flat_kdtree.h) answers the same queries with the same points and
 * distances. Points with a non-finite coordinate are left out (as pcl::KdTreeFLANN does); results
 * index the input cloud. Queries are const and thread-safe. */
template <typename PointT>
class KdTree {
 public:
  using Cloud = pcl::PointCloud<PointT>;
  using CloudConstPtr = typename Cloud::ConstPtr;

  KdTree() = default;
  explicit KdTree(bool /*sorted, always true; for pcl::KdTreeFLANN compatibility*/) {}

  void setInputCloud(const CloudConstPtr& cloud) {
    cloud_ = cloud;
    map_.clear();
    std::vector<float> data;
    if (cloud) {
      data.reserve(3 * cloud->size());
      map_.reserve(cloud->size());
      for (std::size_t i = 0; i < cloud->size(); ++i) {
        const PointT& p = (*cloud)[i];
        if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) continue;
        data.push_back(p.x);
        data.push_back(p.y);
        data.push_back(p.z);
        map_.push_back(static_cast<int>(i));
      }
    }
    tree_.build(data.data(), map_.size());
  }

  const CloudConstPtr& getInputCloud() const { return cloud_; }
  /** \brief Number of points in the tree (the finite points of the cloud). */
  std::size_t size() const { return map_.size(); }

  /** \brief The k nearest points, closest first; returns how many were found (0 for an empty
   * tree or a non-finite query). */
  int nearestKSearch(const PointT& p, int k, std::vector<int>& indices,
                     std::vector<float>& sqr_distances) const {
    return nearestKSearch(p.x, p.y, p.z, k, indices, sqr_distances);
  }

  int nearestKSearch(float x, float y, float z, int k, std::vector<int>& indices,
                     std::vector<float>& sqr_distances) const {
    indices.clear();
    sqr_distances.clear();
    if (map_.empty() || k <= 0 || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z))
      return 0;
    const float q[3] = {x, y, z};
    tree_.knn(q, k, indices, sqr_distances);
    for (int& i : indices) i = map_[i];
    return static_cast<int>(indices.size());
  }

  /** \brief The nearest point within sqrt(`max_sqr_distance`) (inclusive), or -1 when there is
   * none, an empty tree or a non-finite query; its squared distance in `sqr_distance`. The same
   * point as nearestKSearch(k = 1) whenever that one lies within the bound, without allocation,
   * and the bound prunes the search: the motion method's residuals and ICP make tens of
   * millions of these. */
  int nearest(float x, float y, float z, float max_sqr_distance, float& sqr_distance) const {
    if (map_.empty() || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z) ||
        !(max_sqr_distance >= 0.0f))
      return -1;
    const float q[3] = {x, y, z};
    const int row =
        tree_.nearest(q, std::nextafter(max_sqr_distance, std::numeric_limits<float>::max()),
                      sqr_distance);
    return row < 0 ? -1 : map_[row];
  }

  /** \brief nearest(), the same point and distance, with a guess: `hint` (a cloud index, or -1
   * for none; a non-finite point is no guess), usually the query's nearest point a moment ago
   * (an ICP's match of the iteration before). The search is bounded by the guess's distance as
   * well: the walk is the same but leaves out cells farther than the guess, which cannot hold the
   * nearest point nor a tie visited before it, so the result is nearest()'s bit for bit. */
  int nearest(float x, float y, float z, float max_sqr_distance, int hint,
              float& sqr_distance) const {
    if (hint >= 0 && std::isfinite(x) && std::isfinite(y) && std::isfinite(z)) {
      const PointT& h = (*cloud_)[static_cast<std::size_t>(hint)];
      const float q[3] = {x, y, z}, p[3] = {h.x, h.y, h.z};
      max_sqr_distance = std::min(max_sqr_distance, FlatKdTree3::distance2(q, p));
    }
    return nearest(x, y, z, max_sqr_distance, sqr_distance);
  }

  /** \brief The nearest point (the lowest index among equal distances) and whether another
   * point lies at exactly the same distance (`tied`); -1 for an empty tree or a non-finite
   * query. Its squared distance in `sqr_distance`. Without a tie it is the first point of
   * nearestKSearch(p, k) for every k, found at the cost of a nearest-point search: for callers
   * that usually need only that one. */
  int nearestFirst(const PointT& p, float& sqr_distance, bool& tied) const {
    tied = false;
    if (map_.empty() || !std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z))
      return -1;
    const float q[3] = {p.x, p.y, p.z};
    const int row = tree_.nearestLowestRow(q, sqr_distance, tied);
    return row < 0 ? -1 : map_[row];
  }

  /** \brief All points within `radius` (at most `max_nn` of the closest when max_nn > 0),
   * closest first; returns how many. */
  int radiusSearch(const PointT& p, double radius, std::vector<int>& indices,
                   std::vector<float>& sqr_distances, unsigned int max_nn = 0) const {
    indices.clear();
    sqr_distances.clear();
    if (map_.empty() || !(radius >= 0.0) || !std::isfinite(p.x) || !std::isfinite(p.y) ||
        !std::isfinite(p.z))
      return 0;
    const float q[3] = {p.x, p.y, p.z};
    tree_.radius(q, static_cast<float>(radius * radius), max_nn, indices, sqr_distances);
    for (int& i : indices) i = map_[i];
    return static_cast<int>(indices.size());
  }

  /** \brief The tree itself (its rows are the finite points in cloud order: cloudIndex). */
  const FlatKdTree3& flatTree() const { return tree_; }
  /** \brief Index in the cloud of the tree's row `row`. */
  int cloudIndex(int row) const { return map_[static_cast<std::size_t>(row)]; }

 private:
  CloudConstPtr cloud_;
  std::vector<int> map_;  ///< tree row -> index in the cloud
  FlatKdTree3 tree_;
};

/** \brief A pcl::search::KdTree whose point queries go through KdTree above, for PCL
 * algorithms that take a search object (registration's correspondence estimation:
 * `icp.setSearchMethodTarget(tree, true)`). Only whole clouds: with an index subset it falls back
 * to PCL's own tree. */
template <typename PointT>
class SearchKdTree : public pcl::search::KdTree<PointT> {
 public:
  using Base = pcl::search::KdTree<PointT>;
  using typename Base::IndicesConstPtr;
  using typename Base::PointCloudConstPtr;
  using Ptr = std::shared_ptr<SearchKdTree<PointT>>;
  using Base::nearestKSearch;
  using Base::radiusSearch;

  SearchKdTree() : Base(true) {}

  void setInputCloud(const PointCloudConstPtr& cloud,
                     const IndicesConstPtr& indices = IndicesConstPtr()) override {
    own_ = !indices;
    if (!own_) return Base::setInputCloud(cloud, indices);
    this->input_ = cloud;
    this->indices_ = indices;
    fast_.setInputCloud(cloud);
  }

  int nearestKSearch(const PointT& point, int k, pcl::Indices& k_indices,
                     std::vector<float>& k_sqr_distances) const override {
    if (!own_) return Base::nearestKSearch(point, k, k_indices, k_sqr_distances);
    std::vector<int> idx;
    const int n = fast_.nearestKSearch(point, k, idx, k_sqr_distances);
    k_indices.assign(idx.begin(), idx.end());
    return n;
  }

  int radiusSearch(const PointT& point, double radius, pcl::Indices& k_indices,
                   std::vector<float>& k_sqr_distances, unsigned int max_nn = 0) const override {
    if (!own_) return Base::radiusSearch(point, radius, k_indices, k_sqr_distances, max_nn);
    std::vector<int> idx;
    const int n = fast_.radiusSearch(point, radius, idx, k_sqr_distances, max_nn);
    k_indices.assign(idx.begin(), idx.end());
    return n;
  }

 private:
  KdTree<PointT> fast_;
  bool own_ = true;
};

}  // namespace pcl_animseg
