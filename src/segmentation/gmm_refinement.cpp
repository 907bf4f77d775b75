#include <omp.h>
#include <pcl/point_types.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/math/gmm.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_check.h>
#include <pcl_animseg/segmentation/rigid_motion.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <memory>
#include <numeric>
#include <queue>
#include <set>
#include <tuple>

#include "mean_shift_internal.h"
#include "surface_fold.h"

namespace pcl_animseg {
namespace segmentation {

namespace {

using Cloud = PointCloudSequence::Cloud;
using XYZCloud = pcl::PointCloud<pcl::PointXYZ>;

// A point of some pair's band in some frame.
struct BandPoint {
  int frame;
  int index;
  int pair;    // dense pair id
  int side;    // 0: label == pair's a (F), 1: label == pair's b (B)
  float dist;  // distance to the pair's boundary, in spacings
};

struct Pair {
  int a, b;
};

// The GMMs of one side of one pair within one pooling group: local patch models plus a
// pair-wide fallback, and the training points (for the optional spatial term).
struct SideModel {
  std::vector<Eigen::Vector3d> train_pos, train_nrm;
  std::vector<Eigen::Vector3d> boundary_pos;
  XYZCloud::Ptr seeds{new XYZCloud};
  std::vector<math::GaussianMixture> patch;
  std::vector<char> patch_ok;
  math::GaussianMixture whole;
  bool whole_ok = false;
  pcl_animseg::KdTree<pcl::PointXYZ> seed_tree, train_tree;
  XYZCloud::Ptr train_cloud{new XYZCloud};
};

pcl::PointXYZ toXYZ(const Eigen::Vector3d& p) {
  return pcl::PointXYZ(static_cast<float>(p.x()), static_cast<float>(p.y()),
                       static_cast<float>(p.z()));
}

// The motions an input came with (SegmentationResult::motions) as PartMotions, valid where the
// part has min_points points in frame 0 and in frame t, as RigidMotionEstimation decides (its
// rms is not measured: 0 where valid, -1 elsewhere, as there).
std::vector<PartMotion> givenMotions(const std::vector<std::vector<Eigen::Isometry3d>>& motions,
                                     const std::vector<std::vector<int>>& labels, int num_labels,
                                     int min_points) {
  const std::size_t frames = labels.size();
  std::vector<std::vector<int>> count(num_labels, std::vector<int>(frames, 0));
  for (std::size_t t = 0; t < frames; ++t)
    for (int l : labels[t])
      if (l >= 0) ++count[l][t];
  std::vector<PartMotion> parts(num_labels);
  for (int l = 0; l < num_labels; ++l) {
    parts[l].part = l;
    parts[l].points_frame0 = static_cast<std::size_t>(count[l][0]);
    parts[l].frames.resize(frames);
    for (std::size_t t = 0; t < frames; ++t) {
      RigidTransform& r = parts[l].frames[t];
      r.rotation = motions[l][t].linear();
      r.translation = motions[l][t].translation();
      r.valid = count[l][0] >= min_points && count[l][t] >= min_points;
      r.rms = r.valid ? 0.0 : -1.0;
    }
  }
  return parts;
}

// Evenly spread subset of at most `cap` of the given indices (deterministic).
std::vector<int> subsample(const std::vector<int>& idx, int cap) {
  if (static_cast<int>(idx.size()) <= cap) return idx;
  std::vector<int> out(cap);
  for (int k = 0; k < cap; ++k) out[k] = idx[static_cast<std::size_t>(k) * idx.size() / cap];
  return out;
}

// Each labelled point's k nearest points of its frame (itself included, closest first), found
// once: the boundary scan, the fold test of the reassignment and the fold snap all ask for them.
class NeighbourLists {
 public:
  void build(const Cloud& cloud, const pcl_animseg::KdTree<pcl::PointNormal>& tree, int k,
             const std::vector<int>& lab) {
    k_ = k;
    const std::size_t n = cloud.size();
    idx_.assign(n * k, -1);
    d2_.assign(n * k, 0.0f);
    count_.assign(n, 0);
    std::vector<int> idx;
    std::vector<float> d2;
    for (std::size_t j = 0; j < n; ++j) {
      if (lab[j] < 0) continue;
      count_[j] = tree.nearestKSearch(cloud[j], k, idx, d2);
      std::copy(idx.begin(), idx.end(), idx_.begin() + j * k);
      std::copy(d2.begin(), d2.end(), d2_.begin() + j * k);
    }
  }
  /** The device's k-NN of every point of every frame (one call for all frames, the frames
   * one after the other): k slots per query, each a point's index in its frame's cloud (the
   * device gives rows of the frames' flat trees; everyPointLists maps them once, ahead, so
   * that a list's reader does not). */
  struct DeviceLists {
    int k = 0;
    std::vector<int> rows, count;
    // The device that searched them and its token for the frames' trees, kept there for later
    // searches (RigidFitDevice::keepKnnTrees; null and 0: not kept).
    RigidFitDevice* device = nullptr;
    long long trees = 0;
  };
  /** The same lists as a view into `lists`, whose queries `first`, `first` + 1, ... are this
   * frame's points. */
  void view(std::shared_ptr<const DeviceLists> lists, std::size_t first, const Cloud& cloud) {
    lists_ = std::move(lists);
    cloud_ = &cloud;
    k_ = lists_->k;
    first_ = first;
  }
  /** Point j's neighbours (cloud indices, the nearest first, point j itself among them), as
   * get() gives them, without their distances: where `count` is returned. */
  const int* indices(std::size_t j, int& count) const {
    if (lists_) {
      const std::size_t q = first_ + j;
      count = lists_->count[q];
      return &lists_->rows[q * k_];
    }
    count = count_[j];
    return &idx_[j * k_];
  }
  bool empty() const { return count_.empty() && !lists_; }
  /** The lists of point j (a labelled point) into idx and d2, as nearestKSearch gives them. */
  void get(std::size_t j, std::vector<int>& idx, std::vector<float>& d2) const {
    if (lists_) {
      const std::size_t q = first_ + j;
      const int c = lists_->count[q];
      const int* r = &lists_->rows[q * k_];
      idx.resize(c);
      d2.resize(c);
      // The distances as the tree's search computes them (the same floats).
      const auto& x = (*cloud_)[j];
      const float qx[3] = {x.x, x.y, x.z};
      for (int i = 0; i < c; ++i) {
        idx[i] = r[i];
        const auto& y = (*cloud_)[idx[i]];
        const float py[3] = {y.x, y.y, y.z};
        d2[i] = FlatKdTree3::distance2(qx, py);
      }
      return;
    }
    idx.assign(idx_.begin() + j * k_, idx_.begin() + j * k_ + count_[j]);
    d2.assign(d2_.begin() + j * k_, d2_.begin() + j * k_ + count_[j]);
  }

 private:
  int k_ = 0;
  std::vector<int> idx_, count_;
  std::vector<float> d2_;
  std::shared_ptr<const DeviceLists> lists_;
  const Cloud* cloud_ = nullptr;
  std::size_t first_ = 0;
};

using Trees = std::vector<pcl_animseg::KdTree<pcl::PointNormal>>;

// Frame indices, the most work first (ties in frame order). A loop over 48 frames on 16 cores
// is three frames a core: taken in frame order, a large frame started last kept the other cores
// waiting; largest first, a greedy schedule ends within 4/3 of the best one. Each frame writes
// its own results, so the order changes no result.
std::vector<int> mostWorkFirst(const std::vector<std::size_t>& work) {
  std::vector<int> order(work.size());
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return work[a] > work[b]; });
  return order;
}

// Each frame's kd-tree, the frames side by side.
Trees frameTrees(const PointCloudSequence& seq) {
  Trees trees(seq.size());
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < static_cast<int>(seq.size()); ++t) trees[t].setInputCloud(seq.frame(t));
  return trees;
}

// The frames' mean spacings measured with their trees (meanSpacings' values).
std::vector<double> treeSpacings(const PointCloudSequence& seq, const Trees& trees) {
  return meanSpacings(seq,
                      [&](std::size_t t) -> const KdTree<pcl::PointNormal>& { return trees[t]; });
}

// Every point's k nearest points of its frame in one device call (a point's nearest points do
// not depend on the other queries; the refinement views those of its labelled points); null
// where the device does not offer the k-NN. Throws Error where the device fails.
std::shared_ptr<const NeighbourLists::DeviceLists> everyPointLists(RigidFitDevice& device,
                                                                   const PointCloudSequence& seq,
                                                                   const Trees& trees, int k) {
  const std::size_t frames = seq.size();
  std::vector<std::size_t> first(frames + 1, 0);  // each frame's first query
  for (std::size_t t = 0; t < frames; ++t) first[t + 1] = first[t] + seq.frame(t)->size();
  std::vector<float> queries(3 * first[frames]);
  std::vector<int> tree_of(first[frames]);
  std::vector<const FlatKdTree3*> flat(frames);
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < static_cast<int>(frames); ++t) {
    flat[t] = &trees[t].flatTree();
    const Cloud& cloud = *seq.frame(t);
    for (std::size_t j = 0, q = first[t]; j < cloud.size(); ++j, ++q) {
      queries[3 * q] = cloud[j].x, queries[3 * q + 1] = cloud[j].y, queries[3 * q + 2] = cloud[j].z;
      tree_of[q] = t;
    }
  }
  auto lists = std::make_shared<NeighbourLists::DeviceLists>();
  lists->k = k;
  // The trees kept on the device where it offers that: the motion check searches them again.
  const long long kept = device.keepKnnTrees(flat);
  if (kept ? !device.knnOn(kept, k, queries, tree_of, lists->rows, lists->count)
           : !device.knn(flat, k, queries, tree_of, lists->rows, lists->count))
    return nullptr;
  if (kept) lists->device = &device, lists->trees = kept;
  if (lists->count.size() != tree_of.size() || lists->rows.size() != tree_of.size() * k)
    throw Error("refinement: the device's k-NN lists do not match their queries");
  // Rows of the flat trees into cloud indices, once (each reader of the lists did it per read).
  int bad = 0;
#pragma omp parallel for schedule(dynamic) reduction(| : bad)
  for (int t = 0; t < static_cast<int>(frames); ++t) {
    const int rows = static_cast<int>(trees[t].size());
    for (std::size_t q = first[t]; q < first[t + 1]; ++q) {
      const int c = lists->count[q];
      if (c < 0 || c > k) {
        bad = 1;
        continue;
      }
      int* r = &lists->rows[q * k];
      for (int i = 0; i < c; ++i) {
        if (r[i] < 0 || r[i] >= rows) {
          bad = 1;
          break;
        }
        r[i] = trees[t].cloudIndex(r[i]);
      }
    }
  }
  if (bad) throw Error("refinement: the device's k-NN lists name points out of range");
  return lists;
}

// The fold snap's surface graph of one frame: each labelled point's boundary_k nearest within
// boundary_max_distance (adj, -1 past the last), edge lengths in spacings, and the border points
// (a neighbour of another label).
struct SnapGraph {
  std::vector<int> adj;
  std::vector<float> len;
  std::vector<char> border;
};

SnapGraph snapGraph(const Cloud& cloud, const NeighbourLists& knn, double spacing,
                    const RefinementParams& p, const std::vector<int>& lab) {
  const int n = static_cast<int>(cloud.size());
  const int k = p.boundary_k;
  const float max_d2 = static_cast<float>(std::pow(p.boundary_max_distance * spacing, 2));
  SnapGraph g;
  g.adj.assign(static_cast<std::size_t>(n) * k, -1);
  g.len.assign(static_cast<std::size_t>(n) * k, 0.0f);
  g.border.assign(n, 0);
  std::vector<int> idx;
  std::vector<float> d2;
  for (int j = 0; j < n; ++j) {
    if (lab[j] < 0) continue;
    knn.get(j, idx, d2);
    int e = 0;
    for (std::size_t q = 0; q < idx.size() && e < k; ++q) {
      if (idx[q] == j || d2[q] > max_d2 || lab[idx[q]] < 0) continue;
      const std::size_t slot = static_cast<std::size_t>(j) * k + e++;
      g.adj[slot] = idx[q];
      g.len[slot] = static_cast<float>(std::sqrt(d2[q]) / spacing);
      if (lab[idx[q]] != lab[j]) g.border[j] = 1;
    }
  }
  return g;
}

// The squared distance that puts a point in the fold snap's band: 1.0201 band^2 (a little beyond
// the band: the same bands as a search bounded by the band itself).
float snapNear2(const RefinementParams& p, double spacing) {
  const double near = p.fold_snap_band * spacing;
  return static_cast<float>(1.0201 * near * near);
}

// The bound of the search around the border points (FlatKdTree3::within's, strictly below):
// snapNear2 inclusive.
float snapNearBound(const RefinementParams& p, double spacing) {
  return std::nextafter(snapNear2(p, spacing), std::numeric_limits<float>::max());
}

// Each point's least squared distance to a border point of `g`, below snapNearBound (else
// +infinity): the frame's points near each border point (the border points are few, and a band
// around them holds a small part of the frame): finding the band was 46% of the fold snap's CPU
// time at 800k, most of it a search of the border points' tree from every point; 41% now
// (0.443 -> 0.349 CPU s on 16 threads). The same squared distances ((b - x)^2 is (x - b)^2 in
// float), the same bound (inclusive, as KdTree::nearest's), the same least one. With a device,
// one call for every frame instead (foldSnaps in refine(): 0.70 -> 0.59 CPU s of the snap on the
// H200 machine at 800k, its lap 0.050 -> 0.043 s).
std::vector<float> nearBorder(const Cloud& cloud, const pcl_animseg::KdTree<pcl::PointNormal>& tree,
                              const SnapGraph& g, float near_bound) {
  const int n = static_cast<int>(cloud.size());
  std::vector<float> near_d2(n, std::numeric_limits<float>::infinity());
  const FlatKdTree3& ft = tree.flatTree();
  for (int b = 0; b < n; ++b) {
    if (!g.border[b]) continue;
    const float q[3] = {cloud[b].x, cloud[b].y, cloud[b].z};
    if (!std::isfinite(q[0]) || !std::isfinite(q[1]) || !std::isfinite(q[2])) continue;
    ft.within(q, near_bound, [&](float d2, int row) {
      float& m = near_d2[tree.cloudIndex(row)];
      m = std::min(m, d2);
    });
  }
  return near_d2;
}

// The fold snap of one frame (RefinementParams::fold_snap_*); returns the points it moved.
// Written by us: a Dijkstra that keeps each point's three nearest parts over the frame's k-NN
// surface graph (no kept library has a multi-label one), run twice: once from the border points
// for the band, then from the parts' points just beyond the band into it. `graph` and
// `near_given`, where given, are snapGraph's and nearBorder's results for these labels (the
// latter from a device: RigidFitDevice::leastDistances); else they are found here.
std::size_t foldSnap(const Cloud& cloud, const pcl_animseg::KdTree<pcl::PointNormal>& tree,
                     const NeighbourLists& knn, double spacing, const RefinementParams& p,
                     std::vector<int>& lab, double* band_seconds = nullptr,
                     const SnapGraph* graph = nullptr,
                     const std::vector<float>* near_given = nullptr) {
  const auto t_begin =
      band_seconds ? std::chrono::steady_clock::now() : std::chrono::steady_clock::time_point();
  const int n = static_cast<int>(cloud.size());
  const int k = p.boundary_k;
  // The surface graph: each point's k nearest within boundary_max_distance, edge cost in
  // spacings (length plus the fold penalty). An edge's fold (an acos and two norms) is computed
  // when the search first crosses it (foldOf): most edges lie outside the band and never are.
  SnapGraph own;
  if (!graph) own = snapGraph(cloud, knn, spacing, p, lab);
  const SnapGraph& g = graph ? *graph : own;
  const std::vector<int>& adj = g.adj;
  const std::vector<float>& len = g.len;
  const std::vector<char>& border = g.border;
  std::vector<float> fold(adj.size(), -1.0f);
  // 1. The band: points within fold_snap_band of a border point (straight-line distance, as W).
  const float band = static_cast<float>(p.fold_snap_band);
  std::vector<float> to_border(n, std::numeric_limits<float>::infinity());
  Cloud::Ptr border_points(new Cloud);
  for (int j = 0; j < n; ++j)
    if (border[j]) border_points->push_back(cloud[j]);
  if (border_points->empty()) return 0;
  pcl_animseg::KdTree<pcl::PointNormal> border_tree;
  border_tree.setInputCloud(border_points);
  // Only distances up to two bands matter (below: a part's core starts at half its farthest
  // point's distance, capped at the band), so the searches are bounded a little beyond that;
  // `far` marks the parts with a point beyond it, whose cap is the band.
  //
  // Only a distance within the band decides whether a point is in it (reach_of is at most the
  // band), so every point is searched within the band first (a search of a quarter of the area).
  // The points beyond it matter only for their part's cap: they are searched within two bands,
  // a part's only until one of them is farther (then its cap is the band whatever the others'
  // distances). The same distances within the band, the same caps.
  int labels_here = 0;
  for (int j = 0; j < n; ++j) labels_here = std::max(labels_here, lab[j] + 1);
  std::vector<char> far(labels_here, 0);
  const double bound = 2.0 * (p.fold_snap_band * spacing);
  const float near2 = snapNear2(p, spacing);
  const float bound2 = static_cast<float>(1.0201 * bound * bound);
  // The distances within the band from the other side (nearBorder, or the caller's).
  std::vector<float> near_own;
  if (!near_given) near_own = nearBorder(cloud, tree, g, snapNearBound(p, spacing));
  const std::vector<float>& near_d2 = near_given ? *near_given : near_own;
  std::vector<int> beyond;
  for (int j = 0; j < n; ++j) {
    if (lab[j] < 0) continue;
    if (near_d2[j] <= near2)
      to_border[j] = static_cast<float>(std::sqrt(near_d2[j]) / spacing);
    else
      beyond.push_back(j);
  }
  for (int j : beyond) {
    if (far[lab[j]]) continue;
    float nd2;
    if (border_tree.nearest(cloud[j].x, cloud[j].y, cloud[j].z, bound2, nd2) >= 0)
      to_border[j] = static_cast<float>(std::sqrt(nd2) / spacing);
    else
      far[lab[j]] = 1;
  }
  if (band_seconds)
    *band_seconds +=
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t_begin).count();
  // 2. Every band point's three nearest parts, reached from the points just beyond the band; a
  // path costs its length plus fold_snap_penalty per degree of inward folding, and each point
  // keeps, per part, the degrees of folding on its cheapest path.
  constexpr int kKeep = 3;
  struct Reach {
    int part = -1;
    float folded = 0.0f;
  };
  struct Step {
    float cost;
    int point, part;
    float folded;  // degrees
  };
  // The queue's order: cheapest first, ties by point, part and degrees (std::tuple's order of
  // the four, written out: 10% less time than the tuple's comparisons on one core).
  auto later = [](const Step& a, const Step& b) {
    if (a.cost != b.cost) return a.cost > b.cost;
    if (a.point != b.point) return a.point > b.point;
    if (a.part != b.part) return a.part > b.part;
    return a.folded > b.folded;
  };
  std::priority_queue<Step, std::vector<Step>, decltype(later)> paths(later);
  std::vector<Reach> reach(static_cast<std::size_t>(n) * kKeep);
  std::vector<unsigned char> settled(n, 0);
  // A part thinner than two bands (a fingertip of few points) would have no core: its core
  // starts halfway to its farthest point from a border instead.
  std::vector<float> reach_of(labels_here, 0.0f);
  for (int j = 0; j < n; ++j)
    if (lab[j] >= 0 && std::isfinite(to_border[j]))
      reach_of[lab[j]] = std::max(reach_of[lab[j]], to_border[j]);
  for (int l = 0; l < labels_here; ++l)
    reach_of[l] = far[l] ? band : std::min(band, 0.5f * reach_of[l]);
  auto inBand = [&](int j) { return lab[j] >= 0 && to_border[j] <= reach_of[lab[j]]; };
  for (int j = 0; j < n; ++j) {
    if (lab[j] < 0 || inBand(j)) continue;
    for (int e = 0; e < k; ++e) {
      const int v = adj[static_cast<std::size_t>(j) * k + e];
      if (v < 0) break;
      if (inBand(v)) {
        paths.push(Step{0.0f, j, lab[j], 0.0f});
        break;
      }
    }
  }
  auto foldOf = [&](int u, std::size_t slot) {
    if (fold[slot] < 0.0f)
      fold[slot] = static_cast<float>(std::max(
          0.0, detail::foldDegrees(cloud[u], cloud[adj[slot]]) - p.fold_snap_dead_zone_deg));
    return fold[slot];
  };
  const float per_degree = static_cast<float>(p.fold_snap_penalty);
  // Per point, the cheapest queued path of up to kPending parts: a path that would pop after
  // one of its own part queued for the same point is not queued (it could only lose).
  struct Pending {
    int part = -1;
    float cost = 0.0f, folded = 0.0f;
  };
  constexpr int kPending = 4;
  std::vector<Pending> pending(static_cast<std::size_t>(n) * kPending);
  while (!paths.empty()) {
    const auto [d, u, part, folded] = paths.top();
    paths.pop();
    if (settled[u] >= kKeep) continue;
    bool seen = false;
    for (int r = 0; r < settled[u]; ++r)
      seen = seen || reach[static_cast<std::size_t>(u) * kKeep + r].part == part;
    if (seen) continue;
    reach[static_cast<std::size_t>(u) * kKeep + settled[u]++] = Reach{part, folded};
    for (int e = 0; e < k; ++e) {
      const std::size_t slot = static_cast<std::size_t>(u) * k + e;
      const int v = adj[slot];
      if (v < 0) break;
      if (inBand(v) && settled[v] < kKeep) {
        bool reached = false;  // a path of this part settled there already: this one would lose
        for (int r = 0; r < settled[v]; ++r)
          reached = reached || reach[static_cast<std::size_t>(v) * kKeep + r].part == part;
        if (reached) continue;
        const float f = foldOf(u, slot);
        const float cost = d + len[slot] + per_degree * f, deg = folded + f;
        // A path of this part queued for v already that pops first wins over this one.
        Pending* q = &pending[static_cast<std::size_t>(v) * kPending];
        Pending* own = nullptr;   // this part's queued path to v
        Pending* free = nullptr;  // else an unused entry
        for (int r = 0; r < kPending && !own; ++r) {
          if (q[r].part == part)
            own = &q[r];
          else if (q[r].part < 0 && !free)
            free = &q[r];
        }
        if (own && std::tie(own->cost, own->folded) <= std::tie(cost, deg)) continue;
        if (own || free) *(own ? own : free) = Pending{part, cost, deg};
        paths.push(Step{cost, v, part, deg});
      }
    }
  }
  // 3. A point moves when its own part reaches it only across a fold at least
  // fold_snap_angle_deg deeper than another part's path (Jacobi: all decisions from the labels
  // before the snap). Lengths do not count here: where the band's edges lie is arbitrary.
  std::vector<std::pair<int, int>> moves;
  for (int j = 0; j < n; ++j) {
    if (!inBand(j)) continue;
    float own = std::numeric_limits<float>::infinity(), other = own;
    int to = -1;
    for (int r = 0; r < settled[j]; ++r) {
      const Reach& q = reach[static_cast<std::size_t>(j) * kKeep + r];
      if (q.part == lab[j])
        own = q.folded;
      else if (q.folded < other)
        other = q.folded, to = q.part;
    }
    if (to >= 0 && std::isfinite(own) && own - other >= p.fold_snap_angle_deg)
      moves.emplace_back(j, to);
  }
  for (const auto& [j, l] : moves) lab[j] = l;
  return moves.size();
}

}  // namespace

void validate(const RefinementParams& p) {
  if (!(p.narrow_band > 0.0) || !(p.outer_band > p.narrow_band))
    throw Error("GMM refinement: need 0 < narrow band L_r < outer band L_R (got " +
                std::to_string(p.narrow_band) + ", " + std::to_string(p.outer_band) + ")");
  if (p.boundary_k < 2) throw Error("GMM refinement: boundary_k must be >= 2");
  if (p.max_iterations < 1)
    throw Error("GMM refinement: iterations must be >= 1 (got " + std::to_string(p.max_iterations) +
                ")");
  if (!(p.fold_angle_deg >= 0.0 && p.fold_angle_deg < 180.0))
    throw Error("GMM refinement: fold_angle_deg must be in [0, 180) (got " +
                std::to_string(p.fold_angle_deg) + ")");
  if (!(p.fold_snap_band >= 0.0) || !(p.fold_snap_penalty >= 0.0) ||
      !(p.fold_snap_angle_deg > 0.0) || !(p.fold_snap_dead_zone_deg >= 0.0))
    throw Error(
        "GMM refinement: need fold snap band >= 0, penalty >= 0, angle > 0 and dead zone >= 0 "
        "(got " +
        std::to_string(p.fold_snap_band) + ", " + std::to_string(p.fold_snap_penalty) + ", " +
        std::to_string(p.fold_snap_angle_deg) + ", " + std::to_string(p.fold_snap_dead_zone_deg) +
        ")");
  if (p.motion_frames < 0 || p.motion_frames == 1)
    throw Error("GMM refinement: need motion_frames 0 (every frame) or >= 2 (got " +
                std::to_string(p.motion_frames) + ")");
  if (p.components < 1 || p.components > 64 || !(p.gmm_regularization > 0.0) ||
      p.gmm_max_iterations < 1)
    throw Error(
        "GMM refinement: need 1-64 components, a regularization > 0 and >= 1 EM iteration "
        "(got " +
        std::to_string(p.components) + ", " + std::to_string(p.gmm_regularization) + ", " +
        std::to_string(p.gmm_max_iterations) + ")");
  if (!(p.patch_size > 0.0) || !(p.patch_radius > 0.0) || p.min_training_points < 1 ||
      p.max_training_points < 1)
    throw Error("GMM refinement: need patch size and radius > 0 and training points >= 1 (got " +
                std::to_string(p.patch_size) + ", " + std::to_string(p.patch_radius) + ", " +
                std::to_string(p.min_training_points) + ", " +
                std::to_string(p.max_training_points) + ")");
  if (!(p.motion_tolerance >= 0.0) || !(p.motion_cap > 0.0))
    throw Error("GMM refinement: need motion_tolerance >= 0 and motion_cap > 0 (got " +
                std::to_string(p.motion_tolerance) + ", " + std::to_string(p.motion_cap) + ")");
}

struct GMMBoundaryRefinement::Prepared {
  const PointCloudSequence* sequence = nullptr;
  std::vector<std::size_t> sizes;  // each frame's point count
  std::vector<pcl_animseg::KdTree<pcl::PointNormal>> trees;
  std::vector<double> spacings;
  // Every point's nearest points, the frames one after the other (null: none were searched).
  std::shared_ptr<const NeighbourLists::DeviceLists> lists;
};

void GMMBoundaryRefinement::prepareFrames() {
  prepared_.reset();
  if (!sequence_ || sequence_->empty()) return;
  detail::StageTimer timer("refine");
  auto prep = std::make_shared<Prepared>();
  const std::size_t frames = sequence_->size();
  prep->sequence = sequence_;
  for (std::size_t t = 0; t < frames; ++t) prep->sizes.push_back(sequence_->frame(t)->size());
  prep->trees = frameTrees(*sequence_);
  prep->spacings = treeSpacings(*sequence_, prep->trees);
  if (device_ && params_.max_iterations > 0 && params_.boundary_k >= 2) {
    try {
      prep->lists = everyPointLists(*device_, *sequence_, prep->trees, params_.boundary_k + 1);
    } catch (const Error&) {
      // refine() searches again, and a device that fails there is reported there.
    }
  }
  prepared_ = std::move(prep);
  timer.lap("frames prepared ahead (trees, spacings, neighbour lists)");
}

std::vector<double> GMMBoundaryRefinement::preparedSpacings() const {
  return prepared_ ? prepared_->spacings : std::vector<double>();
}

void GMMBoundaryRefinement::refine(const SegmentationResult& input, SegmentationResult& output) {
  if (!sequence_ || sequence_->empty()) throw Error("GMM refinement: no input sequence");
  const RefinementParams& p = params_;
  validate(p);
  const std::size_t frames = sequence_->size();
  if (input.labels.size() != frames)
    throw Error("GMM refinement: labels for " + std::to_string(input.labels.size()) +
                " frames, sequence has " + std::to_string(frames));
  for (std::size_t t = 0; t < frames; ++t)
    if (input.labels[t].size() != sequence_->frame(t)->size())
      throw Error("GMM refinement: frame " + std::to_string(t) + " has " +
                  std::to_string(input.labels[t].size()) + " labels for " +
                  std::to_string(sequence_->frame(t)->size()) + " points");
  const int num_labels = std::max(input.num_clusters, detail::largestLabel(input.labels) + 1);
  // The per-frame loops below take the frames with the most work first (mostWorkFirst).
  auto sizesOf = [&](const auto& per_frame) {
    std::vector<std::size_t> n(frames);
    for (std::size_t t = 0; t < frames; ++t) n[t] = per_frame[t].size();
    return n;
  };
  const std::vector<int> by_size = mostWorkFirst(sizesOf(input.labels));
  output = input;
  stats_ = RefinementStats();
  motions_.clear();
  std::vector<std::vector<int>>& labels = output.labels;
  std::size_t total_points = sequence_->totalPoints();

  detail::StageTimer timer("refine");
  if (!spacings_.empty() && spacings_.size() != frames)
    throw Error("refinement: " + std::to_string(spacings_.size()) + " spacings for " +
                std::to_string(frames) + " frames");
  // What prepareFrames() built for this sequence, taken over (and released with this call).
  std::shared_ptr<Prepared> prep = std::move(prepared_);
  auto sameFrames = [&](const Prepared& pr) {
    if (pr.sequence != sequence_ || pr.sizes.size() != frames) return false;
    for (std::size_t t = 0; t < frames; ++t)
      if (pr.sizes[t] != sequence_->frame(t)->size()) return false;
    return true;
  };
  if (prep && !sameFrames(*prep)) prep.reset();
  const bool prepared_lists = prep && prep->lists && prep->lists->k == p.boundary_k + 1;
  const Trees trees = prep ? std::move(prep->trees) : frameTrees(*sequence_);
  // The spacings given, or measured from the trees (meanSpacings' values).
  const std::vector<double> spacing = !spacings_.empty() ? spacings_
                                      : prep             ? prep->spacings
                                                         : treeSpacings(*sequence_, trees);
  timer.lap(prep ? "trees (prepared)" : "trees");
  double mean_spacing = 0.0;
  for (double s : spacing) mean_spacing += s / static_cast<double>(frames);

  // Per part and frame, the map from frame t into frame 0 (identity when not pooling). Estimated
  // once from the initial labels: the refinement changes only a thin band, which ICP's
  // correspondence rejection ignores anyway.
  std::vector<std::vector<RigidTransform>> to_ref(num_labels, std::vector<RigidTransform>(frames));
  const bool pool = p.pool_frames && frames > 1;
  const bool check_motion = p.motion_check && frames > 1;
  std::vector<PartMotion> parts;
  const bool given = p.input_motions &&
                     input.motions.size() == static_cast<std::size_t>(num_labels) &&
                     std::all_of(input.motions.begin(), input.motions.end(),
                                 [&](const auto& m) { return m.size() == frames; });
  // Motion residual of point j of frame t under part l's rigid motion: the point is carried to
  // every other frame and scored by its distance to that frame's surface (point-to-plane, blind to
  // the different sampling of the frames, or what the point-to-point distance exceeds a spacing,
  // so that sliding off the end of a part counts), in spacings, capped, averaged over frames
  // (at most motion_frames of them, spread evenly: `scored`).
  // The motions are fixed for the whole refinement, so each (point, part) is scored once.
  std::vector<std::size_t> scored;
  {
    const std::size_t cap = static_cast<std::size_t>(p.motion_frames);
    if (cap == 0 || frames <= cap) {
      for (std::size_t u = 0; u < frames; ++u) scored.push_back(u);
    } else {
      for (std::size_t k = 0; k < cap; ++k) scored.push_back(k * (frames - 1) / (cap - 1));
    }
  }

  // After the first pass, only points near the previous boundary can become boundary points: a
  // label changes only inside W, so a new boundary point is a changed point or a neighbour of one.
  // This keeps the kNN scan, the costliest step, to the band in later iterations.
  std::vector<std::vector<char>> candidate(frames);
  std::vector<NeighbourLists> knn(frames);  // built by the first boundary scan
  const double candidate_reach = p.narrow_band + p.boundary_max_distance + 1.0;
  const bool restrict_scan = p.outer_band >= candidate_reach;

  // With a device that offers it, every frame's lists in one k-NN call (the same lists; on the
  // cores they were a fifth of the refinement's CPU time at 800k), which the frames' lists view.
  std::shared_ptr<const NeighbourLists::DeviceLists> lists;  // set by deviceLists()
  auto deviceLists = [&]() {
    // Every point's lists, searched ahead (prepareFrames) or now; the frames' views.
    lists = prepared_lists ? prep->lists
                           : everyPointLists(*device_, *sequence_, trees, p.boundary_k + 1);
    prep.reset();
    for (std::size_t t = 0, first = 0; lists && t < frames; first += sequence_->frame(t++)->size())
      knn[t].view(lists, first, *sequence_->frame(t));
    timer.lap(prepared_lists ? "neighbour lists (prepared)" : "neighbour lists (device)");
  };

  // 1. Boundary points and bands, frame by frame (labels are joint, so pair ids agree); false
  // when there is no boundary.
  std::map<std::pair<int, int>, int> pair_id;
  std::vector<Pair> pairs;
  std::vector<std::vector<BandPoint>> band(frames);
  std::vector<std::vector<std::tuple<int, int, int>>> boundary(frames);  // (index, a, b)
  std::vector<std::vector<int>> pairs_of;                                // the pairs of each label
  std::vector<std::vector<std::pair<int, int>>> frame_pairs(frames);
  int num_pairs = 0;
  auto findBands = [&]() {
    timer.lap("before the bands");
    pair_id.clear();
    pairs.clear();
    band.assign(frames, {});
    boundary.assign(frames, {});
#pragma omp parallel for schedule(dynamic)
    for (int i = 0; i < static_cast<int>(frames); ++i) {
      const int t = by_size[i];
      const Cloud& cloud = *sequence_->frame(t);
      const std::vector<int>& lab = labels[t];
      const double s = spacing[t];
      const float max_d2 = static_cast<float>(std::pow(p.boundary_max_distance * s, 2));
      if (knn[t].empty()) knn[t].build(cloud, trees[t], p.boundary_k + 1, lab);
      std::vector<int> idx;
      std::vector<float> d2;
      for (std::size_t j = 0; j < cloud.size(); ++j) {
        if (lab[j] < 0 || (!candidate[t].empty() && !candidate[t][j])) continue;
        // Most points have no neighbour of another label: their lists' distances are not needed.
        {
          int c = 0;
          const int* nb = knn[t].indices(j, c);
          bool mixed = false;
          for (int k = 1; k < c && !mixed; ++k) mixed = lab[nb[k]] >= 0 && lab[nb[k]] != lab[j];
          if (!mixed) continue;
        }
        knn[t].get(j, idx, d2);
        // The most frequent other label among the near neighbours names the pair.
        int other = -1, best = 0;
        for (std::size_t k = 1; k < idx.size(); ++k) {
          const int m = lab[idx[k]];
          if (m < 0 || m == lab[j] || d2[k] > max_d2) continue;
          int c = 0;
          for (std::size_t q = 1; q < idx.size(); ++q) c += lab[idx[q]] == m && d2[q] <= max_d2;
          if (c > best) best = c, other = m;
        }
        if (other >= 0)
          boundary[t].emplace_back(static_cast<int>(j), std::min(lab[j], other),
                                   std::max(lab[j], other));
      }
      // The frame's pairs in the order they first appear.
      std::vector<std::pair<int, int>>& seen = frame_pairs[t];
      seen.clear();
      std::set<std::pair<int, int>> known;
      for (const auto& [j, a, b] : boundary[t])
        if (known.emplace(a, b).second) seen.emplace_back(a, b);
    }
    timer.lap("bands: boundary points");
    // Pair ids in order of first appearance over the frames in order: the frames' own lists
    // joined (one map insertion per boundary point was a serial pass over all of them).
    for (std::size_t t = 0; t < frames; ++t)
      for (const auto& [a, b] : frame_pairs[t])
        if (pair_id.emplace(std::make_pair(a, b), static_cast<int>(pairs.size())).second)
          pairs.push_back(Pair{a, b});
    if (pairs.empty()) return false;
    num_pairs = static_cast<int>(pairs.size());
    // Pairs of each label, to look up only the boundaries a point could move across.
    pairs_of.assign(num_labels, {});
    for (int q = 0; q < num_pairs; ++q) {
      pairs_of[pairs[q].a].push_back(q);
      pairs_of[pairs[q].b].push_back(q);
    }

#pragma omp parallel for schedule(dynamic)
    for (int i = 0; i < static_cast<int>(frames); ++i) {
      const int t = by_size[i];
      const Cloud& cloud = *sequence_->frame(t);
      const std::vector<int>& lab = labels[t];
      const double s = spacing[t];
      std::vector<Cloud::Ptr> bcloud(num_pairs);
      Cloud::Ptr all(new Cloud);
      for (const auto& [j, a, b] : boundary[t]) {
        const int q = pair_id.at({a, b});
        if (!bcloud[q]) bcloud[q].reset(new Cloud);
        bcloud[q]->push_back(cloud[j]);
        all->push_back(cloud[j]);
      }
      if (all->empty()) continue;
      pcl_animseg::KdTree<pcl::PointNormal> all_tree;
      all_tree.setInputCloud(all);
      std::vector<pcl_animseg::KdTree<pcl::PointNormal>> btree(num_pairs);
      for (int q = 0; q < num_pairs; ++q)
        if (bcloud[q]) btree[q].setInputCloud(bcloud[q]);
      const double reach = p.outer_band * s;
      // Searches bounded a little beyond the distance that decides prune far sooner, and find
      // the same nearest point whenever it is within that distance: the same bands.
      auto bound2 = [](double d) { return static_cast<float>(1.0201 * d * d); };
      for (std::size_t j = 0; j < cloud.size(); ++j) {
        const int l = lab[j];
        if (l < 0) continue;
        const auto& x = cloud[j];
        float nd2;
        if (all_tree.nearest(x.x, x.y, x.z, bound2(reach), nd2) < 0) continue;
        if (std::sqrt(nd2) > reach) continue;
        int best_q = -1;
        double best_d = reach;
        for (int q : pairs_of[l]) {
          if (!bcloud[q] || btree[q].nearest(x.x, x.y, x.z, bound2(best_d), nd2) < 0) continue;
          const double d = std::sqrt(nd2);
          if (d <= best_d) best_d = d, best_q = q;
        }
        if (best_q < 0) continue;
        band[t].push_back(BandPoint{t, static_cast<int>(j), best_q, l == pairs[best_q].a ? 0 : 1,
                                    static_cast<float>(best_d / s)});
      }
      if (restrict_scan) {
        candidate[t].assign(cloud.size(), 0);
        for (const BandPoint& bp : band[t])
          if (bp.dist <= candidate_reach) candidate[t][bp.index] = 1;
      }
    }

    timer.lap("bands");
    return true;
  };

  // The parts' motions. Their fits on a device are a chain of calls (one frame after the other)
  // that leaves the cores idle, and the first pass's boundary and bands do not need them: with
  // a device, those run beside the fits (RigidMotionEstimation::computeBeside), the same
  // results. The neighbour lists (one device call) come first: beside the fits, each fit call
  // waited for them (800k humanoid: the fits' chain 0.074 s alone, 0.148 s beside the lists).
  if ((device_ || prepared_lists) && p.max_iterations > 0) deviceLists();
  bool first_bands = false, have_pairs = false;
  if ((pool || check_motion) && given) {
    parts = givenMotions(input.motions, labels, num_labels, RigidMotionParams().min_points);
  } else if (pool || check_motion) {
    RigidMotionEstimation motion;
    RigidMotionParams mp;
    // 500 points per part are plenty for a rigid fit: against 1500, the 800k-point humanoid's
    // motions take 2.0 s instead of 4.1 s, and at 8000 points per frame (seed 3, four plans)
    // the boundary errors and ARIs after refinement stay within 0.002 / 0.001.
    mp.max_points = 500;
    motion.setParams(mp);
    motion.setInputSequence(sequence_);
    motion.setSpacings(spacing);
    motion.setDevice(device_);
    if (device_ && p.max_iterations > 0) {
      parts = motion.computeBeside(labels, num_labels, [&] {
        have_pairs = findBands();
        first_bands = true;
      });
    } else {
      parts = motion.compute(labels, num_labels);
    }
  }
  if (pool)
    for (int l = 0; l < num_labels && !parts.empty(); ++l)
      for (std::size_t t = 0; t < frames; ++t) to_ref[l][t] = parts[l].frames[t].inverse();
  timer.lap("motions");
  motions_ = parts;

  // The fold snap of every frame (foldSnap), each frame's task starting with before(t) (the last
  // pass's changes: the snap reads only its own frame's labels, so one loop over the frames
  // instead of two, each ending on its slowest frame); returns the points moved. With the
  // frames' trees kept on the device (the neighbour lists' search), the distances around the
  // border points (nearBorder, 41% of the snap's CPU time at 800k) are one device call for all
  // frames between the frames' graphs and the rest of their snaps: the same distances.
  auto foldSnaps = [&](const auto& before) {
    std::size_t snapped = 0;
    double snap_cpu = 0.0, snap_band_cpu = 0.0;
    auto timed = [&](auto&& f) {
      const auto t0 =
          timer.on() ? std::chrono::steady_clock::now() : std::chrono::steady_clock::time_point();
      f();
      if (timer.on()) {
        const double sec =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
#pragma omp atomic
        snap_cpu += sec;
      }
    };
    auto snapOne = [&](int t, const SnapGraph* graph, const std::vector<float>* near) {
      double band_sec = 0.0;
      const std::size_t moved = foldSnap(*sequence_->frame(t), trees[t], knn[t], spacing[t], p,
                                         labels[t], timer.on() ? &band_sec : nullptr, graph, near);
      if (timer.on()) {
#pragma omp atomic
        snap_band_cpu += band_sec;
      }
      return moved;
    };
    const bool on_device = device_ && lists && lists->device == device_ && lists->trees > 0;
    double device_sec = -1.0;
    if (!on_device) {
#pragma omp parallel for schedule(dynamic) reduction(+ : snapped)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_size[i];
        before(t);
        timed([&] { snapped += snapOne(t, nullptr, nullptr); });
      }
    } else {
      // Each frame's graph and its border points, the queries against its kept tree (tree t is
      // frame t's; rows one tree after the other).
      std::vector<SnapGraph> graph(frames);
      std::vector<std::vector<float>> border_xyz(frames);
#pragma omp parallel for schedule(dynamic)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_size[i];
        before(t);
        timed([&] {
          const Cloud& cloud = *sequence_->frame(t);
          graph[t] = snapGraph(cloud, knn[t], spacing[t], p, labels[t]);
          for (std::size_t j = 0; j < cloud.size(); ++j)
            if (graph[t].border[j])
              border_xyz[t].insert(border_xyz[t].end(), {cloud[j].x, cloud[j].y, cloud[j].z});
        });
      }
      const auto t0 = std::chrono::steady_clock::now();
      std::vector<float> queries, bound2(frames);
      std::vector<int> tree_of;
      for (std::size_t t = 0; t < frames; ++t) {
        bound2[t] = snapNearBound(p, spacing[t]);
        queries.insert(queries.end(), border_xyz[t].begin(), border_xyz[t].end());
        tree_of.insert(tree_of.end(), border_xyz[t].size() / 3, static_cast<int>(t));
      }
      std::vector<float> least;
      const bool got = device_->leastDistances(lists->trees, queries, tree_of, bound2, least);
      std::vector<std::size_t> row0(frames + 1, 0);
      for (std::size_t t = 0; t < frames; ++t) row0[t + 1] = row0[t] + trees[t].size();
      if (got && least.size() != row0[frames])
        throw Error("refinement: the device's border distances do not match the frames");
      std::vector<std::vector<float>> near(got ? frames : 0);
      device_sec = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
#pragma omp parallel for schedule(dynamic) reduction(+ : snapped)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_size[i];
        timed([&] {
          if (got) {  // rows to the frame's points (unreached and unlabelled: +infinity)
            near[t].assign(sequence_->frame(t)->size(), std::numeric_limits<float>::infinity());
            for (std::size_t r = 0; r < trees[t].size(); ++r)
              near[t][trees[t].cloudIndex(static_cast<int>(r))] = least[row0[t] + r];
          }
          snapped += snapOne(t, &graph[t], got ? &near[t] : nullptr);
          graph[t] = SnapGraph();  // the frame's graph, no longer needed
        });
      }
    }
    if (timer.on()) {
      std::fprintf(stderr,
                   "[refine] fold snap: %.3f CPU s on %d threads (finding its band %.3f CPU s)\n",
                   snap_cpu, omp_get_max_threads(), snap_band_cpu);
      if (device_sec >= 0.0)
        std::fprintf(stderr, "[refine] fold snap: the border points' distances (device) %.3f s\n",
                     device_sec);
    }
    return snapped;
  };
  bool snapped_all = false;  // the fold snap ran in the last iteration's loop over the frames
  for (int iter = 0; iter < p.max_iterations; ++iter) {
    if (iter > 0 || !first_bands) have_pairs = findBands();
    if (!have_pairs) break;
    // 2. Models per (group, pair, side). A group is the whole sequence when pooling, else a frame.
    const int groups = pool ? 1 : static_cast<int>(frames);
    std::vector<SideModel> models(static_cast<std::size_t>(groups) * num_pairs * 2);
    auto modelIndex = [&](int g, int q, int side) {
      return (static_cast<std::size_t>(g) * num_pairs + q) * 2 + side;
    };
    auto canon = [&](int label, int t, const Eigen::Vector3d& x, const Eigen::Vector3d& n,
                     Eigen::Vector3d& cx, Eigen::Vector3d& cn) {
      const RigidTransform& r = to_ref[label][t];
      cx = r.apply(x);
      cn = r.rotation * n;
    };
    // Each frame's boundary and training points in the reference frame, the frames side by
    // side; then each model's, frame after frame (the order a serial loop gives them).
    struct Placed {
      int model;
      bool train;  // a training point (position and normal); else a boundary point
      Eigen::Vector3d pos, nrm;
    };
    std::vector<std::vector<Placed>> placed(frames);
    const std::vector<int> by_band = mostWorkFirst(sizesOf(band));
#pragma omp parallel for schedule(dynamic)
    for (int i = 0; i < static_cast<int>(frames); ++i) {
      const int t = by_band[i];
      const int g = pool ? 0 : t;
      const Cloud& cloud = *sequence_->frame(t);
      std::vector<Placed>& out = placed[t];
      for (const auto& [j, a, b] : boundary[t]) {
        const int q = pair_id.at({a, b});
        Eigen::Vector3d cx, cn;
        const Eigen::Vector3d x = cloud[j].getVector3fMap().cast<double>();
        const Eigen::Vector3d n = cloud[j].getNormalVector3fMap().cast<double>();
        canon(a, t, x, n, cx, cn);
        out.push_back(Placed{static_cast<int>(modelIndex(g, q, 0)), false, cx, cn});
        canon(b, t, x, n, cx, cn);
        out.push_back(Placed{static_cast<int>(modelIndex(g, q, 1)), false, cx, cn});
      }
      for (const BandPoint& bp : band[t]) {
        if (bp.dist <= p.narrow_band || bp.dist < p.training_min_distance) continue;
        Eigen::Vector3d cx, cn;
        canon(labels[t][bp.index], t, cloud[bp.index].getVector3fMap().cast<double>(),
              cloud[bp.index].getNormalVector3fMap().cast<double>(), cx, cn);
        const double len = cn.norm();
        if (!(len > 0.0)) continue;
        out.push_back(
            Placed{static_cast<int>(modelIndex(g, bp.pair, bp.side)), true, cx, cn / len});
      }
    }
    // Each model's points gathered from the frames in order, the models side by side: each
    // frame's entries sorted by model first (stable: the frame's order kept within a model).
    auto byModel = [](const Placed& x, const Placed& y) { return x.model < y.model; };
#pragma omp parallel for schedule(dynamic)
    for (int i = 0; i < static_cast<int>(frames); ++i)
      std::stable_sort(placed[by_band[i]].begin(), placed[by_band[i]].end(), byModel);
#pragma omp parallel for schedule(dynamic)
    for (int mi = 0; mi < static_cast<int>(models.size()); ++mi) {
      SideModel& m = models[mi];
      const Placed key{mi, false, {}, {}};
      std::vector<std::pair<std::size_t, std::size_t>> range(frames);
      std::size_t train = 0, bound = 0;
      for (std::size_t t = 0; t < frames; ++t) {
        const auto [lo, hi] = std::equal_range(placed[t].begin(), placed[t].end(), key, byModel);
        range[t] = {static_cast<std::size_t>(lo - placed[t].begin()),
                    static_cast<std::size_t>(hi - placed[t].begin())};
        for (auto e = lo; e != hi; ++e) (e->train ? train : bound) += 1;
      }
      m.train_pos.reserve(train);
      m.train_nrm.reserve(train);
      m.boundary_pos.reserve(bound);
      for (std::size_t t = 0; t < frames; ++t)
        for (std::size_t e = range[t].first; e < range[t].second; ++e) {
          const Placed& x = placed[t][e];
          if (x.train) {
            m.train_pos.push_back(x.pos);
            m.train_nrm.push_back(x.nrm);
          } else {
            m.boundary_pos.push_back(x.pos);
          }
        }
    }
    timer.lap("models: training points");
    const double patch = p.patch_size * mean_spacing;
    const float radius = static_cast<float>(p.patch_radius * mean_spacing);
    // radiusSearch's bound for `radius`: its square (in double, then float), inclusive.
    const float patch_bound =
        std::nextafter(static_cast<float>(static_cast<double>(radius) * radius),
                       std::numeric_limits<float>::infinity());
    math::GMMOptions gopt;
    gopt.components = p.components;
    gopt.max_iterations = p.gmm_max_iterations;
    gopt.regularization = p.gmm_regularization;
    gopt.seed = p.seed;
    // The normals a fit trains on: those of `idx`, at most max_training_points of them.
    auto trainingOf = [&](const SideModel& m, const std::vector<int>& idx) {
      const std::vector<int> use = subsample(idx, p.max_training_points);
      Eigen::MatrixX3d x(use.size(), 3);
      for (std::size_t k = 0; k < use.size(); ++k) x.row(k) = m.train_nrm[use[k]].transpose();
      return x;
    };
    // First each model's seeds and training points of its patches, then every fit (a model's
    // whole one and its patches') in one parallel loop: a few large models with many patches
    // kept most of 16 cores waiting when each model fitted its patches in turn.
    auto trained = [&](const SideModel& m) {
      return static_cast<int>(m.train_nrm.size()) >= p.min_training_points;
    };
    std::vector<std::vector<std::vector<int>>> patch_points(models.size());
    // The models with the most training points first (mostWorkFirst; each writes its own).
    std::vector<std::size_t> model_work(models.size());
    for (std::size_t mi = 0; mi < models.size(); ++mi) model_work[mi] = models[mi].train_pos.size();
    const std::vector<int> by_model = mostWorkFirst(model_work);
#pragma omp parallel for schedule(dynamic)
    for (int i = 0; i < static_cast<int>(models.size()); ++i) {
      const int mi = by_model[i];
      SideModel& m = models[mi];
      if (!trained(m)) continue;
      for (const Eigen::Vector3d& x : m.train_pos) m.train_cloud->push_back(toXYZ(x));
      m.train_tree.setInputCloud(m.train_cloud);
      // Patch seeds: centroids of the boundary points in a voxel grid of the patch size.
      std::map<std::tuple<long, long, long>, std::pair<Eigen::Vector3d, int>> cells;
      for (const Eigen::Vector3d& x : m.boundary_pos) {
        auto& c = cells[{static_cast<long>(std::floor(x.x() / patch)),
                         static_cast<long>(std::floor(x.y() / patch)),
                         static_cast<long>(std::floor(x.z() / patch))}];
        if (c.second == 0) c.first.setZero();
        c.first += x;
        ++c.second;
      }
      std::vector<int> idx;
      for (const auto& [key, c] : cells) {
        const Eigen::Vector3d seed = c.first / static_cast<double>(c.second);
        m.seeds->push_back(toXYZ(seed));
        // The training points within `radius` (inclusive, as radiusSearch), in index order:
        // radiusSearch's set without its sort by distance (a third of the patches' time).
        idx.clear();
        const pcl::PointXYZ sp = toXYZ(seed);
        const float q[3] = {sp.x, sp.y, sp.z};
        if (std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]) && radius >= 0.0f)
          m.train_tree.flatTree().within(
              q, patch_bound, [&](float, int row) { idx.push_back(m.train_tree.cloudIndex(row)); });
        std::sort(idx.begin(), idx.end());
        const bool ok = static_cast<int>(idx.size()) >= p.min_training_points;
        patch_points[mi].push_back(ok ? idx : std::vector<int>());
        m.patch_ok.push_back(ok);
      }
      m.patch.resize(m.patch_ok.size());
      if (!m.seeds->empty()) m.seed_tree.setInputCloud(m.seeds);
    }
    timer.lap("models: patches");
    std::vector<std::pair<int, int>> fits;  // (model, patch), patch -1: the model's whole fit
    for (int mi = 0; mi < static_cast<int>(models.size()); ++mi) {
      if (!trained(models[mi])) continue;
      fits.push_back({mi, -1});
      for (int k = 0; k < static_cast<int>(models[mi].patch_ok.size()); ++k)
        if (models[mi].patch_ok[k]) fits.push_back({mi, k});
    }
    // Largest first (each fit has its own output): a few large fits started last kept the
    // other cores waiting.
    auto fitPoints = [&](const std::pair<int, int>& f) {
      const std::size_t n =
          f.second < 0 ? models[f.first].train_nrm.size() : patch_points[f.first][f.second].size();
      return std::min(n, static_cast<std::size_t>(p.max_training_points));
    };
    std::stable_sort(fits.begin(), fits.end(),
                     [&](const auto& a, const auto& b) { return fitPoints(a) > fitPoints(b); });
    // Each fit's points and start (math::gmmStart), then their EMs: with a device that offers
    // it, all in one call (the same bits as fitGMM on the cores; there they were 0.5 CPU s at
    // 800k, 0.031 s of the refinement).
    std::vector<Eigen::MatrixX3d> fit_x(fits.size());
    std::vector<math::GaussianMixture*> fit_out(fits.size());
#pragma omp parallel for schedule(dynamic)
    for (int f = 0; f < static_cast<int>(fits.size()); ++f) {
      const auto [mi, k] = fits[f];
      SideModel& m = models[mi];
      std::vector<int> all;
      if (k < 0) {
        all.resize(m.train_nrm.size());
        for (std::size_t q = 0; q < all.size(); ++q) all[q] = static_cast<int>(q);
      }
      fit_x[f] = trainingOf(m, k >= 0 ? patch_points[mi][k] : all);
      fit_out[f] = k >= 0 ? &m.patch[k] : &m.whole;
      *fit_out[f] = math::gmmStart(fit_x[f], gopt);
    }
    bool fitted_on_device = false;
    if (device_) {
      std::vector<MixtureFitJob> jobs(fits.size());
      for (std::size_t f = 0; f < fits.size(); ++f) jobs[f] = {&fit_x[f], fit_out[f]};
      fitted_on_device = device_->fitMixtures(jobs, gopt);
    }
    if (!fitted_on_device) {
#pragma omp parallel for schedule(dynamic)
      for (int f = 0; f < static_cast<int>(fits.size()); ++f)
        math::gmmEM(fit_x[f], gopt, *fit_out[f]);
    }
    for (const auto& [mi, k] : fits)
      if (k < 0) models[mi].whole_ok = true;
    const int fitted = static_cast<int>(fits.size());
    if (iter == 0) stats_.models = fitted;

    timer.lap("models: fits");
    // 3. Reassign W points by the larger p_c (Eq. 11), with hysteresis; all decisions use the
    // labels of this iteration (Jacobi), so the result does not depend on the visiting order.
    std::vector<std::vector<std::pair<int, int>>> changes(frames);
    std::size_t band_w = 0;
    // True when every point of `target` among the near neighbours of point j lies across an
    // inward fold (normals converging, turned by more than fold_angle_deg); false when there is
    // none or one on a smooth or outward-curving surface.
    constexpr double kPi = 3.14159265358979323846;
    const double fold_cos = p.fold_angle_deg > 0.0 ? std::cos(p.fold_angle_deg * kPi / 180.0) : 1.0;
    auto acrossFold = [&](int t, int j, int target) {
      const Cloud& cloud = *sequence_->frame(t);
      const float max_d2 = static_cast<float>(std::pow(p.boundary_max_distance * spacing[t], 2));
      std::vector<int> nn;
      std::vector<float> nd2;
      knn[t].get(j, nn, nd2);
      bool seen = false;
      for (std::size_t k = 0; k < nn.size(); ++k) {
        if (labels[t][nn[k]] != target || nd2[k] > max_d2) continue;
        seen = true;
        if (detail::inwardFoldCos(cloud[j], cloud[nn[k]]) >= fold_cos) return false;
      }
      return seen;
    };
    // 3a. The GMMs' verdicts (Eq. 11): the W points whose other side is more likely by
    // min_log_ratio, in band order: (point, own label, other label).
    std::vector<std::vector<std::array<int, 3>>> verdict(frames);
    // One side of a W point: its model, its position and unit normal in the reference frame.
    struct Side {
      int model = -1;
      Eigen::Vector3d cx, cn;
    };
    // Side `side` of band point bp of frame t; false where its model has no fit or the normal
    // is degenerate (the point gets no verdict).
    auto sideOf = [&](int t, const BandPoint& bp, int side, Side& out) {
      const Pair& pr = pairs[bp.pair];
      out.model = modelIndex(pool ? 0 : t, bp.pair, side);
      if (!models[out.model].whole_ok) return false;
      const Cloud& cloud = *sequence_->frame(t);
      const Eigen::Vector3d x = cloud[bp.index].getVector3fMap().cast<double>();
      const Eigen::Vector3d n = cloud[bp.index].getNormalVector3fMap().cast<double>();
      canon(side == 0 ? pr.a : pr.b, t, x, n, out.cx, out.cn);
      const double len = out.cn.norm();
      if (!(len > 0.0)) return false;
      out.cn /= len;
      return true;
    };
    // Its log-likelihood (Eq. 11) given its nearest patch seed (a seed index, -1 without
    // seeds) and its squared distance to the nearest training point (spatial_weight > 0).
    auto logpOf = [&](int t, const Side& sd, int seed, float train_d2) {
      const SideModel& m = models[sd.model];
      const math::GaussianMixture* gmm = &m.whole;
      if (seed >= 0 && m.patch_ok[seed]) gmm = &m.patch[seed];
      double logp = gmm->logPdf(sd.cn);
      if (p.spatial_weight > 0.0) logp -= p.spatial_weight * std::sqrt(train_d2) / spacing[t];
      return logp;
    };
    // A W point's verdict from its two sides' log-likelihoods.
    auto decide = [&](int t, const BandPoint& bp, const double* logp) {
      const Pair& pr = pairs[bp.pair];
      const int own = bp.side;
      const int lab[2] = {pr.a, pr.b};
      if (logp[1 - own] - logp[own] > p.min_log_ratio)
        verdict[t].push_back({bp.index, lab[own], lab[1 - own]});
    };
    // With a device that offers k-NN, the sides' two nearest-point searches (the patch seed,
    // the training point) for every frame in one call (the same rows: the same verdicts); on the
    // cores they were most of the verdicts' 0.35 CPU s at 800k.
    bool verdicts_done = false;
    if (device_) {
      std::vector<std::vector<std::pair<int, std::array<Side, 2>>>> sides(frames);  // (band, sides)
#pragma omp parallel for schedule(dynamic) reduction(+ : band_w)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_band[i];
        for (std::size_t b = 0; b < band[t].size(); ++b) {
          const BandPoint& bp = band[t][b];
          if (bp.dist > p.narrow_band) continue;
          ++band_w;
          std::array<Side, 2> sd;
          if (sideOf(t, bp, 0, sd[0]) && sideOf(t, bp, 1, sd[1]))
            sides[t].push_back({static_cast<int>(b), sd});
        }
      }
      // The models' trees: seeds (where there are any) and training points (where used).
      std::vector<const FlatKdTree3*> trees_q;
      std::vector<int> seed_tree(models.size(), -1), train_tree(models.size(), -1);
      for (std::size_t mi = 0; mi < models.size(); ++mi) {
        if (!models[mi].whole_ok) continue;
        if (!models[mi].seeds->empty()) {
          seed_tree[mi] = static_cast<int>(trees_q.size());
          trees_q.push_back(&models[mi].seed_tree.flatTree());
        }
        if (p.spatial_weight > 0.0) {
          train_tree[mi] = static_cast<int>(trees_q.size());
          trees_q.push_back(&models[mi].train_tree.flatTree());
        }
      }
      // Per side, its seed query then its training-point query (where its model has them).
      std::vector<std::size_t> first(frames + 1, 0);
      auto queriesOf = [&](const Side& sd) {
        return (seed_tree[sd.model] >= 0 ? 1 : 0) + (train_tree[sd.model] >= 0 ? 1 : 0);
      };
      for (std::size_t t = 0; t < frames; ++t) {
        std::size_t n = 0;
        for (const auto& [b, sd] : sides[t]) n += queriesOf(sd[0]) + queriesOf(sd[1]);
        first[t + 1] = first[t] + n;
      }
      std::vector<float> queries(3 * first[frames]);
      std::vector<int> tree_of(first[frames]);
#pragma omp parallel for schedule(dynamic)
      for (int t = 0; t < static_cast<int>(frames); ++t) {
        std::size_t q = first[t];
        for (const auto& [b, sd] : sides[t])
          for (const Side& x : sd)
            for (int tree : {seed_tree[x.model], train_tree[x.model]}) {
              if (tree < 0) continue;
              const pcl::PointXYZ c = toXYZ(x.cx);
              queries[3 * q] = c.x, queries[3 * q + 1] = c.y, queries[3 * q + 2] = c.z;
              tree_of[q++] = tree;
            }
      }
      std::vector<int> rows, count;
      if (device_->knn(trees_q, 1, queries, tree_of, rows, count)) {
        if (rows.size() != tree_of.size() || count.size() != tree_of.size())
          throw Error("refinement: the device's nearest points do not match their queries");
        verdicts_done = true;
#pragma omp parallel for schedule(dynamic)
        for (int i = 0; i < static_cast<int>(frames); ++i) {
          const int t = by_band[i];
          std::size_t q = first[t];
          for (const auto& [b, sd] : sides[t]) {
            double logp[2];
            bool ok = true;
            for (int side = 0; side < 2; ++side) {
              const Side& x = sd[side];
              const SideModel& m = models[x.model];
              int seed = -1;
              float d2 = 0.0f;
              if (seed_tree[x.model] >= 0) {
                ok = ok && count[q] == 1;
                if (ok) seed = m.seed_tree.cloudIndex(rows[q]);
                ++q;
              }
              if (train_tree[x.model] >= 0) {
                ok = ok && count[q] == 1;
                if (ok) {
                  const pcl::PointXYZ c = toXYZ(x.cx),
                                      y = (*m.train_cloud)[static_cast<std::size_t>(
                                          m.train_tree.cloudIndex(rows[q]))];
                  const float a[3] = {c.x, c.y, c.z}, bq[3] = {y.x, y.y, y.z};
                  d2 = FlatKdTree3::distance2(a, bq);
                }
                ++q;
              }
              if (ok) logp[side] = logpOf(t, x, seed, d2);
            }
            if (ok) decide(t, band[t][b], logp);
          }
        }
      }
    }
    if (!verdicts_done) {
      band_w = 0;
#pragma omp parallel for schedule(dynamic) reduction(+ : band_w)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_band[i];
        std::vector<int> idx(1);
        std::vector<float> d2(1);
        for (const BandPoint& bp : band[t]) {
          if (bp.dist > p.narrow_band) continue;
          ++band_w;
          double logp[2];
          bool ok = true;
          for (int side = 0; side < 2 && ok; ++side) {
            Side sd;
            ok = sideOf(t, bp, side, sd);
            if (!ok) break;
            const SideModel& m = models[sd.model];
            int seed = -1;
            float train_d2 = 0.0f;
            if (!m.seeds->empty()) {
              ok = m.seed_tree.nearestKSearch(toXYZ(sd.cx), 1, idx, d2) == 1;
              if (ok) seed = idx[0];
            }
            if (ok && p.spatial_weight > 0.0) {
              ok = m.train_tree.nearestKSearch(toXYZ(sd.cx), 1, idx, d2) == 1;
              if (ok) train_d2 = d2[0];
            }
            if (ok) logp[side] = logpOf(t, sd, seed, train_d2);
          }
          if (ok) decide(t, bp, logp);
        }
      }
    }
    // 3b. The motion residuals of those points under their own and the other part's motion.
    // Each is the mean term of the point's copies carried to the scored frames (1.6 M copies and
    // their nearest points at 800k): with a device that offers it, the copies, their nearest
    // points and the terms in one call against the trees the lists' search kept there
    // (RigidFitDevice::motionResiduals; before, the copies' nearest points came back from the
    // device and the terms were added here, 0.026 s in all); the same bits either way.
    timer.lap("reassignment: verdicts");
    const std::vector<int> by_verdicts = mostWorkFirst(sizesOf(verdict));
    std::vector<std::vector<std::array<float, 2>>> motion_res(frames);
    if (check_motion) {
      // Residual r = first[t] + 2 v + k: verdict v of frame t under its own part's motion
      // (k = 0) and the other's (k = 1), from the point carried into the reference frame by that
      // part (motion_check.h; a device scores them all in one call, else the cores).
      std::vector<std::size_t> first(frames + 1, 0);
      for (std::size_t t = 0; t < frames; ++t) first[t + 1] = first[t] + 2 * verdict[t].size();
      const std::size_t residuals = first[frames];
      MotionCheckJobs jobs;
      jobs.starts.resize(3 * residuals);
      jobs.part.resize(residuals);
      jobs.own.resize(residuals);
#pragma omp parallel for schedule(dynamic)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_verdicts[i];
        const Cloud& cloud = *sequence_->frame(t);
        for (std::size_t v = 0; v < verdict[t].size(); ++v)
          for (int k = 0; k < 2; ++k) {
            const std::size_t r = first[t] + 2 * v + k;
            const int l = verdict[t][v][1 + k];
            const Eigen::Vector3d x0 = parts[l].frames[t].inverse().apply(
                cloud[verdict[t][v][0]].getVector3fMap().cast<double>());
            for (int c = 0; c < 3; ++c) jobs.starts[3 * r + c] = x0[c];
            jobs.part[r] = l;
            jobs.own[r] = t;
          }
      }
      const std::size_t pf = static_cast<std::size_t>(num_labels) * frames;
      jobs.motions.assign(12 * pf, 0.0);
      jobs.valid.assign(pf, 0);
      for (int l = 0; l < num_labels && l < static_cast<int>(parts.size()); ++l)
        for (std::size_t u = 0; u < frames && u < parts[l].frames.size(); ++u) {
          const std::size_t lu = static_cast<std::size_t>(l) * frames + u;
          jobs.valid[lu] = parts[l].frames[u].valid;
          icp_step::store(detail::toRigid(parts[l].frames[u]), &jobs.motions[12 * lu]);
        }
      jobs.scored.assign(scored.begin(), scored.end());
      jobs.spacing = spacing;
      jobs.cap = p.motion_cap;
      std::vector<float> res;
      bool on_device = false;
      if (device_ && residuals > 0 && lists && lists->device == device_) {
        // Against the trees the lists' search kept on this device, with every row's normal
        // (where another caller's trees have replaced them there, the device declines and the
        // cores score them).
        std::vector<std::size_t> row0(frames + 1, 0);
        for (std::size_t t = 0; t < frames; ++t) row0[t + 1] = row0[t] + trees[t].size();
        jobs.normals.resize(3 * row0[frames]);
#pragma omp parallel for schedule(dynamic)
        for (int t = 0; t < static_cast<int>(frames); ++t) {
          const Cloud& cloud = *sequence_->frame(t);
          for (std::size_t r = 0; r < trees[t].size(); ++r) {
            const pcl::PointNormal& q = cloud[trees[t].cloudIndex(static_cast<int>(r))];
            float* out = &jobs.normals[3 * (row0[t] + r)];
            out[0] = q.normal_x, out[1] = q.normal_y, out[2] = q.normal_z;
          }
        }
        on_device = device_->motionResiduals(lists->trees, jobs, res);
        if (on_device && res.size() != residuals)
          throw Error("refinement: the device's motion residuals do not match their points");
      }
      if (!on_device) {
        res.assign(residuals, 0.0f);
#pragma omp parallel
        {
          std::vector<int> idx(1);
          std::vector<float> d2(1);
          // A copy's nearest point in its frame's tree, with that point's normal.
          auto nearest = [&](int u, const float* q, double* at, double* nrm) {
            pcl::PointNormal y;
            y.x = q[0], y.y = q[1], y.z = q[2];
            if (trees[u].nearestKSearch(y, 1, idx, d2) <= 0) return false;
            const pcl::PointNormal& np = (*sequence_->frame(u))[idx[0]];
            at[0] = np.x, at[1] = np.y, at[2] = np.z;
            nrm[0] = np.normal_x, nrm[1] = np.normal_y, nrm[2] = np.normal_z;
            return true;
          };
#pragma omp for schedule(dynamic, 256)
          for (long r = 0; r < static_cast<long>(residuals); ++r)
            res[r] = motion_check::residualOf(
                &jobs.starts[3 * r], jobs.part[r], jobs.own[r], jobs.scored.data(),
                static_cast<int>(jobs.scored.size()), static_cast<int>(frames),
                jobs.motions.data(), jobs.valid.data(), jobs.spacing.data(), jobs.cap, nearest);
        }
      }
#pragma omp parallel for schedule(dynamic)
      for (int i = 0; i < static_cast<int>(frames); ++i) {
        const int t = by_verdicts[i];
        motion_res[t].resize(verdict[t].size());
        for (std::size_t v = 0; v < verdict[t].size(); ++v)
          for (int k = 0; k < 2; ++k) motion_res[t][v][k] = res[first[t] + 2 * v + k];
      }
    }
    timer.lap("reassignment: motion residuals");
    // 3c. The motion check (the other part's motion must explain the point about as well as its
    // own) and the fold check, in band order; then the frame's changes. In the last iteration
    // each frame's fold snap (below) follows at once in the same loop: it reads only its own
    // frame's labels (one loop over the frames instead of two, each ending on its slowest frame).
    const bool snap_here = p.fold_snap_band > 0.0 && iter + 1 == p.max_iterations;
    auto applyChanges = [&](int t) {
      for (std::size_t v = 0; v < verdict[t].size(); ++v) {
        const auto [j, own, other] = verdict[t][v];
        if (check_motion && motion_res[t][v][1] > (1.0 + p.motion_tolerance) * motion_res[t][v][0])
          continue;
        if (fold_cos < 1.0 && acrossFold(t, j, other)) continue;
        changes[t].emplace_back(j, other);
      }
      for (const auto& [j, l] : changes[t]) labels[t][j] = l;
    };
    std::size_t snapped = 0;
    if (snap_here) {
      snapped = foldSnaps(applyChanges);
    } else {
#pragma omp parallel for schedule(dynamic)
      for (int i = 0; i < static_cast<int>(frames); ++i) applyChanges(by_verdicts[i]);
    }
    if (snap_here) stats_.snapped = snapped;
    if (iter == 0) stats_.band_points = band_w;
    std::size_t changed = 0;
    for (std::size_t t = 0; t < frames; ++t) changed += changes[t].size();
    stats_.iterations = iter + 1;
    stats_.changed.push_back(changed);
    if (snap_here) {
      snapped_all = true;
      timer.lap("reassignment and fold snap");
    }
    if (static_cast<double>(changed) <= p.min_changed_fraction * static_cast<double>(total_points))
      break;
  }
  // The trees the lists' search kept on the device are not searched again.
  if (lists && lists->device) lists->device->dropKnnTrees(lists->trees);
  if (p.fold_snap_band > 0.0 && !snapped_all) {  // the iterations stopped early, or none ran
    timer.lap("reassignment");
    stats_.snapped = foldSnaps([](int) {});
    timer.lap("fold snap");
  }
}

}  // namespace segmentation
}  // namespace pcl_animseg
