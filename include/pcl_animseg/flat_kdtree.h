#pragma once
/** \file flat_kdtree.h An exact 3-D kd-tree for single-point queries in hot loops. */
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <numeric>
#include <utility>
#include <vector>

namespace pcl_animseg {

/** \brief A static kd-tree over 3-D points: exact nearest-within-a-bound, k nearest and radius
 * queries, const and thread-safe, no allocation in the nearest-point query.
 *
 * Written by us, not taken from FLANN: FLANN's KDTreeSingleIndex answers every query through its
 * abstract ResultSet (two virtual calls per point examined) and a recursive descent. The motion
 * method, the refinement and the rigid motions make tens of millions of single-point queries in
 * 3-D, which took 48% of a whole run (perf, 200k-point humanoid). This tree keeps the points of
 * a leaf contiguous, descends with an explicit stack and inlines the distance; distances are
 * computed as FLANN's L2_Simple does ((dx² + dy²) + dz² in float), so a query returns the same
 * point and the same squared distance as FLANN's tree, up to which of several points at exactly
 * the same distance comes first.
 *
 * Rows are 0..n-1 in the order the points were given. */
class FlatKdTree3 {
 public:
  static constexpr int kLeafSize = 16;

  /** \brief Builds over `n` points given as x, y, z triples (`xyz` holds 3n floats, all
   * finite). The data are copied. */
  void build(const float* xyz, std::size_t n) {
    nodes_.clear();
    // The splits permute the points (each with its row) into leaf order.
    std::vector<BuildPoint> work(n);
    for (std::size_t i = 0; i < n; ++i)
      work[i] = BuildPoint{{xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]}, static_cast<int>(i)};
    nodes_.reserve(2 * (n / kLeafSize + 1));
    if (n > 0) buildNode(work.data(), 0, static_cast<int>(n));
    rows_.resize(n);
    pts_.resize(3 * n);
    for (std::size_t i = 0; i < n; ++i) {
      rows_[i] = work[i].row;
      for (int d = 0; d < 3; ++d) pts_[3 * i + d] = work[i].p[d];
    }
  }

  std::size_t size() const { return rows_.size(); }

  /** \brief Row of the nearest point with squared distance < `bound2` (strictly), or -1; its
   * squared distance in `d2`. */
  int nearest(const float q[3], float bound2, float& d2) const {
    const int i = nearestLeaf(q, bound2, d2);
    return i < 0 ? -1 : rows_[i];
  }

  /** \brief As nearest(), but the point's index in leaf order (leafPoints(), leafRows()). */
  int nearestLeaf(const float q[3], float bound2, float& d2) const {
    // visit() below does the same walk; this copy keeps `best` in a register (through visit's
    // callbacks a 200k-point run took 8.8 s instead of 8.2 s).
    if (nodes_.empty()) return -1;
    float best = bound2;
    int best_i = -1;
    StackEntry stack[kMaxDepth];
    int top = 0;
    stack[top++] = {0, 0.0f};
    while (top > 0) {
      const StackEntry e = stack[--top];
      if (!(e.min_d2 < best)) continue;
      int n = e.node;
      while (nodes_[n].dim >= 0) {
        const Node& nd = nodes_[n];
        const float diff = q[nd.dim] - nd.split;
        const float far_d2 = std::max(e.min_d2, diff * diff);
        if (far_d2 < best) stack[top++] = {diff < 0.0f ? nd.b : nd.a, far_d2};
        n = diff < 0.0f ? nd.a : nd.b;
      }
      const Node& leaf = nodes_[n];
      for (int i = leaf.a; i < leaf.b; ++i) {
        const float d = dist2(q, &pts_[3 * static_cast<std::size_t>(i)]);
        if (d < best) best = d, best_i = i;
      }
    }
    if (best_i < 0) return -1;
    d2 = best;
    return best_i;
  }

  /** \brief The k nearest rows, closest first (equal distances: lower row first, except for
   * k = 1, which is nearest() without a bound); returns how many (at most k and size()). */
  int knn(const float q[3], int k, std::vector<int>& rows, std::vector<float>& d2) const {
    rows.clear();
    d2.clear();
    if (nodes_.empty() || k <= 0) return 0;
    if (k == 1) {  // the common case (ICP correspondences): no heap
      float d;
      const int row = nearest(q, std::numeric_limits<float>::infinity(), d);
      if (row < 0) return 0;
      rows.push_back(row);
      d2.push_back(d);
      return 1;
    }
    const std::size_t kk = std::min<std::size_t>(static_cast<std::size_t>(k), size());
    std::vector<std::pair<float, int>>& heap = tlsHeap();  // sorted ascending, at most kk
    heap.clear();
    auto worst = [&]() {
      return heap.size() < kk ? std::numeric_limits<float>::infinity() : heap.back().first;
    };
    visit(q, worst, [&](float d, int row) {
      const std::pair<float, int> item{d, row};
      if (heap.size() == kk) {
        if (!(item < heap.back())) return;
        heap.pop_back();
      }
      heap.insert(std::upper_bound(heap.begin(), heap.end(), item), item);
    });
    rows.resize(heap.size());
    d2.resize(heap.size());
    for (std::size_t i = 0; i < heap.size(); ++i) d2[i] = heap[i].first, rows[i] = heap[i].second;
    return static_cast<int>(rows.size());
  }

  /** \brief Row of the nearest point, the lowest row among equal distances, and whether another
   * point lies at exactly that distance (`tied`); -1 for an empty tree. Its squared distance in
   * `d2`. Without a tie it is the first of knn(q, k) for every k (which, among ties, returns
   * what its walk keeps). */
  int nearestLowestRow(const float q[3], float& d2, bool& tied) const {
    // nearestLeaf's walk (kept as its own copy for the same reason), with cells as far as the
    // best still visited: they may hold a tie.
    tied = false;
    if (nodes_.empty()) return -1;
    float best = std::numeric_limits<float>::infinity();
    int best_row = -1;
    StackEntry stack[kMaxDepth];
    int top = 0;
    stack[top++] = {0, 0.0f};
    while (top > 0) {
      const StackEntry e = stack[--top];
      if (e.min_d2 > best) continue;  // a cell as far as the best may hold a lower row
      int n = e.node;
      while (nodes_[n].dim >= 0) {
        const Node& nd = nodes_[n];
        const float diff = q[nd.dim] - nd.split;
        const float far_d2 = std::max(e.min_d2, diff * diff);
        if (far_d2 <= best) stack[top++] = {diff < 0.0f ? nd.b : nd.a, far_d2};
        n = diff < 0.0f ? nd.a : nd.b;
      }
      const Node& leaf = nodes_[n];
      for (int i = leaf.a; i < leaf.b; ++i) {
        const float d = dist2(q, &pts_[3 * static_cast<std::size_t>(i)]);
        if (d < best) {
          best = d, best_row = rows_[i], tied = false;
        } else if (d == best) {
          tied = true;
          best_row = std::min(best_row, rows_[i]);
        }
      }
    }
    if (best_row >= 0) d2 = best;
    return best_row;
  }

  /** \brief Rows within squared distance `r2` (inclusive), closest first (equal distances:
   * lower row first); at most `max_nn` of the closest when max_nn > 0. */
  int radius(const float q[3], float r2, std::size_t max_nn, std::vector<int>& rows,
             std::vector<float>& d2) const {
    rows.clear();
    d2.clear();
    if (nodes_.empty()) return 0;
    std::vector<std::pair<float, int>>& found = tlsHeap();
    found.clear();
    const float limit = std::nextafter(r2, std::numeric_limits<float>::infinity());
    visit(q, [&]() { return limit; }, [&](float d, int row) { found.push_back({d, row}); });
    std::sort(found.begin(), found.end());
    if (max_nn > 0 && found.size() > max_nn) found.resize(max_nn);
    rows.resize(found.size());
    d2.resize(found.size());
    for (std::size_t i = 0; i < found.size(); ++i)
      d2[i] = found[i].first, rows[i] = found[i].second;
    return static_cast<int>(rows.size());
  }

  /** \brief Calls hit(d2, row) for every row at squared distance below `bound2` (strictly), in
   * no particular order: the rows nearest() would consider within that bound, without sorting
   * or storing them. */
  template <class Hit>
  void within(const float q[3], float bound2, Hit hit) const {
    if (nodes_.empty()) return;
    visit(
        q, [bound2]() { return bound2; }, hit);
  }

  /** \brief The squared distance as every query computes it ((dx² + dy²) + dz² in float): for
   * callers that get rows without distances (a device's k-NN) and need the same values. */
  static float distance2(const float q[3], const float* p) { return dist2(q, p); }

  /** \brief A node of the tree, for code that walks it elsewhere (a device copy): node 0 is the
   * root; an inner node's points with coordinate `dim` below `split` lie under `a`, above it
   * under `b` (equal: either side). */
  struct Node {
    float split = 0.0f;
    int dim = -1;  ///< -1: leaf
    int a = 0;     ///< inner: left child; leaf: first point (leaf order)
    int b = 0;     ///< inner: right child; leaf: end of its points
  };
  const std::vector<Node>& nodes() const { return nodes_; }
  /** \brief The points as x, y, z triples in leaf order. */
  const std::vector<float>& leafPoints() const { return pts_; }
  /** \brief Input row of each point in leaf order. */
  const std::vector<int>& leafRows() const { return rows_; }

 private:
  struct StackEntry {
    int node;
    float min_d2;
  };
  /** Balanced splits halve the points, so the depth is about log2(n / kLeafSize) + 1 and the
   * stack holds at most one entry per level. */
  static constexpr int kMaxDepth = 64;

  static float dist2(const float q[3], const float* p) {
    float r = 0.0f;
    const float d0 = q[0] - p[0];
    r += d0 * d0;
    const float d1 = q[1] - p[1];
    r += d1 * d1;
    const float d2 = q[2] - p[2];
    r += d2 * d2;
    return r;
  }

  static std::vector<std::pair<float, int>>& tlsHeap() {
    thread_local std::vector<std::pair<float, int>> v;
    return v;
  }

  /** Every point whose squared distance is below worst() (read again after each hit) goes to
   * hit(d2, row). */
  template <class Worst, class Hit>
  void visit(const float q[3], Worst worst, Hit hit) const {
    // A cell is at least as far as any plane that bounds it, in float too (rounding is
    // monotonic): it is skipped only when none of its points could be a hit. (The sum of the
    // squared offsets from all bounding planes prunes more, but cost more than it saved here:
    // most queries lie near the surface.)
    StackEntry stack[kMaxDepth];
    int top = 0;
    stack[top++] = {0, 0.0f};
    while (top > 0) {
      const StackEntry e = stack[--top];
      if (!(e.min_d2 < worst())) continue;
      int n = e.node;
      // Down to a leaf, the far sides pushed with the distance to their splitting plane.
      while (nodes_[n].dim >= 0) {
        const Node& nd = nodes_[n];
        const float diff = q[nd.dim] - nd.split;
        const float far_d2 = std::max(e.min_d2, diff * diff);
        if (far_d2 < worst()) stack[top++] = {diff < 0.0f ? nd.b : nd.a, far_d2};
        n = diff < 0.0f ? nd.a : nd.b;
      }
      const Node& leaf = nodes_[n];
      for (int i = leaf.a; i < leaf.b; ++i) {
        const float d = dist2(q, &pts_[3 * static_cast<std::size_t>(i)]);
        if (d < worst()) hit(d, rows_[i]);
      }
    }
  }

  /** A point while the tree is built: its coordinates and its input row. */
  struct BuildPoint {
    float p[3];
    int row;
  };

  /** Node over work[begin, end) (the points, permuted into leaf order as the splits go); returns
   * its index. Split on the widest side of the points' box, at the median. The points move with
   * their rows, so that the box and the selection read contiguous memory: the same comparisons
   * on the same sequence as selecting the rows by their coordinates, so the same leaf order
   * (48 trees of 16k points: 139-145 ms -> 121-123 ms). */
  int buildNode(BuildPoint* work, int begin, int end) {
    const int id = static_cast<int>(nodes_.size());
    nodes_.emplace_back();
    if (end - begin <= kLeafSize) {
      nodes_[id].a = begin;
      nodes_[id].b = end;
      return id;
    }
    float lo[3], hi[3];
    for (int d = 0; d < 3; ++d) lo[d] = hi[d] = work[begin].p[d];
    for (int i = begin + 1; i < end; ++i)
      for (int d = 0; d < 3; ++d) {
        const float v = work[i].p[d];
        lo[d] = std::min(lo[d], v);
        hi[d] = std::max(hi[d], v);
      }
    int dim = 0;
    for (int d = 1; d < 3; ++d)
      if (hi[d] - lo[d] > hi[dim] - lo[dim]) dim = d;
    const int mid = begin + (end - begin) / 2;
    // Ties broken by row: the same tree on every platform.
    std::nth_element(work + begin, work + mid, work + end,
                     [dim](const BuildPoint& x, const BuildPoint& y) {
                       return x.p[dim] < y.p[dim] || (x.p[dim] == y.p[dim] && x.row < y.row);
                     });
    // Left holds coordinates <= split, right >= split: the plane bounds both sides.
    const float split = work[mid].p[dim];
    const int left = buildNode(work, begin, mid);
    const int right = buildNode(work, mid, end);
    nodes_[id].dim = dim;
    nodes_[id].split = split;
    nodes_[id].a = left;
    nodes_[id].b = right;
    return id;
  }

  std::vector<Node> nodes_;
  std::vector<float> pts_;  ///< xyz in leaf order
  std::vector<int> rows_;   ///< leaf order -> input row
};

}  // namespace pcl_animseg
