#pragma once
/** \file kdtree.h A 3-D kd-tree for one-point-at-a-time queries from inside parallel loops. */
#include <pcl_animseg/error.h>

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

/** \brief FLANN's single kd-tree over the xyz of a cloud, with the query interface of
 * pcl::KdTreeFLANN (same index, same leaf size 15, same sorted results), minus its overhead.
 *
 * Written by us only as a thin layer over FLANN: every query of pcl::KdTreeFLANN goes through
 * flann::NNIndex::knnSearch, which opens an OpenMP parallel region (`num_threads(cores)`) for each
 * call and copies the result through heap-allocated matrices. For the single-point queries that
 * every stage here makes inside its own OpenMP loops, that was 3-4x the cost of the search
 * itself (200k 9-NN queries: 2.0 s against 0.55 s on the 2-core machine) and most of the
 * refinement's time went to libgomp and futex calls. This class calls
 * flann::KDTreeSingleIndex::findNeighbors directly. Points with a non-finite coordinate are left
 * out (as pcl::KdTreeFLANN does); results index the input cloud. Queries are const and
 * thread-safe. */
template <typename PointT>
class KdTree {
 public:
  using Cloud = pcl::PointCloud<PointT>;
  using CloudConstPtr = typename Cloud::ConstPtr;

  KdTree() = default;
  explicit KdTree(bool /*sorted, always true; for pcl::KdTreeFLANN compatibility*/) {}

  void setInputCloud(const CloudConstPtr& cloud) {
    cloud_ = cloud;
    index_.reset();
    data_.clear();
    map_.clear();
    if (!cloud) return;
    data_.reserve(3 * cloud->size());
    map_.reserve(cloud->size());
    for (std::size_t i = 0; i < cloud->size(); ++i) {
      const PointT& p = (*cloud)[i];
      if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) continue;
      data_.push_back(p.x);
      data_.push_back(p.y);
      data_.push_back(p.z);
      map_.push_back(static_cast<int>(i));
    }
    if (map_.empty()) return;
    index_ = std::make_unique<Index>(flann::Matrix<float>(data_.data(), map_.size(), 3),
                                     flann::KDTreeSingleIndexParams(15));
    index_->buildIndex();
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
    if (!index_ || k <= 0 || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z))
      return 0;
    const std::size_t kk = std::min<std::size_t>(static_cast<std::size_t>(k), map_.size());
    const float q[3] = {x, y, z};
    std::vector<std::size_t> idx;
    flann::KNNSimpleResultSet<float> result(kk);
    flannFindNeighbors(*index_, result, q, params_, idx, sqr_distances, true);
    indices.resize(idx.size());
    for (std::size_t i = 0; i < idx.size(); ++i) indices[i] = map_[idx[i]];
    return static_cast<int>(indices.size());
  }

  /** \brief The nearest point within sqrt(`max_sqr_distance`) (inclusive), or -1 when there is
   * none, an empty tree or a non-finite query; its squared distance in `sqr_distance`. The same
   * point as nearestKSearch(k = 1) whenever that one lies within the bound, without the heap
   * allocations of a general query, and the bound prunes the search: the motion method's
   * residuals and ICP make tens of millions of these. */
  int nearest(float x, float y, float z, float max_sqr_distance, float& sqr_distance) const {
    if (!index_ || !std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z) ||
        !(max_sqr_distance >= 0.0f))
      return -1;
    const float q[3] = {x, y, z};
    NearestResult result(std::nextafter(max_sqr_distance, std::numeric_limits<float>::max()));
    index_->findNeighbors(result, q, params_);
    if (result.index == kNone) return -1;
    sqr_distance = result.dist;
    return map_[result.index];
  }

  /** \brief All points within `radius` (at most `max_nn` of the closest when max_nn > 0),
   * closest first; returns how many. */
  int radiusSearch(const PointT& p, double radius, std::vector<int>& indices,
                   std::vector<float>& sqr_distances, unsigned int max_nn = 0) const {
    indices.clear();
    sqr_distances.clear();
    if (!index_ || !(radius >= 0.0) || !std::isfinite(p.x) || !std::isfinite(p.y) ||
        !std::isfinite(p.z))
      return 0;
    const float q[3] = {p.x, p.y, p.z};
    const float r2 = static_cast<float>(radius * radius);
    std::vector<std::size_t> idx;
    if (max_nn > 0) {
      const std::size_t cap = std::min<std::size_t>(max_nn, map_.size());
      flann::KNNRadiusResultSet<float> result(r2, cap);
      flannFindNeighbors(*index_, result, q, params_, idx, sqr_distances, true);
    } else {
      flann::RadiusResultSet<float> result(r2);
      flannFindNeighbors(*index_, result, q, params_, idx, sqr_distances, true);
    }
    indices.resize(idx.size());
    for (std::size_t i = 0; i < idx.size(); ++i) indices[i] = map_[idx[i]];
    return static_cast<int>(indices.size());
  }

 private:
  using Index = flann::KDTreeSingleIndex<flann::L2_Simple<float>>;
  static constexpr std::size_t kNone = static_cast<std::size_t>(-1);
  /** One nearest point under a bound: FLANN's result-set interface without a heap buffer
   * (KNNSimpleResultSet keeps a std::vector); same rule (strictly closer replaces). */
  struct NearestResult : flann::ResultSet<float> {
    explicit NearestResult(float bound) : dist(bound) {}
    bool full() const override { return true; }
    void addPoint(float d, std::size_t i) override {
      if (d < dist) dist = d, index = i;
    }
    float worstDist() const override { return dist; }
    float dist;
    std::size_t index = kNone;
  };
  CloudConstPtr cloud_;
  std::vector<float> data_;  ///< xyz of the finite points, the matrix FLANN indexes
  std::vector<int> map_;     ///< tree row -> index in the cloud
  std::unique_ptr<Index> index_;
  flann::SearchParams params_{-1, 0.0f, true};
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
