// Tracked samples + trajectory clustering (see motion_tracking.h).
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/packed_vector.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/chained_fit.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_device.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/segmentation/score_fit.h>
#include <pcl_animseg/segmentation/task_graph.h>

#include <Eigen/Dense>
#include <algorithm>
// Boost.Graph's iterators trip GCC 12's -Wmaybe-uninitialized inside Boost's own headers (an
// optional's storage it reads only once set): not this file's code, so silenced for them alone.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <array>
#include <boost/graph/adjacency_list.hpp>
#include <boost/graph/boykov_kolmogorov_max_flow.hpp>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <exception>
#include <functional>
#include <limits>
#include <map>
#include <mutex>
#include <numeric>
#include <queue>
#include <set>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#include "mean_shift_internal.h"
#include "surface_fold.h"

namespace pcl_animseg {
namespace segmentation {

namespace {

using Cloud = PointCloudSequence::Cloud;
using Pose = Eigen::Isometry3d;

// Points whose normals disagree by more than this (cosine) are not matched: on thin parts
// (fingers, legs) the nearest point may lie on the opposite side.
constexpr double kNormalCos = 0.3;
// Graph-cut borders: a surface-graph edge whose normals converge (a concave fold) costs
// exp(-(angle / kConcaveAngle)^2) of a flat edge to cut, so a 20-degree fold is almost free.
constexpr double kConcaveAngle = 10.0 * 3.14159265358979323846 / 180.0;
// Residual distances are clipped at this many point spacings, so that one lost point does not
// dominate a fit's score.
constexpr double kClip = 4.0;
/** Part motions: a joint (the centroid of the points where two parts meet, >= kJointPoints of
 * them) may open kJointGap spacings between the two parts' motions for free; beyond that each
 * spacing costs MotionTrackingParams::joint_weight on the residual's scale (RMS spacings). A
 * joint of a finger flexed by 70 degrees opens about 1-3 spacings; a part that jumped onto
 * another limb opens 10-40. */
constexpr int kJointPoints = 3;
constexpr double kJointGap = 4.0;
/** Two parts that meet only across a sharp crease "move differently" (MotionTrackingParams::
 * crease_cost) when merging them costs at least this fraction of the merge threshold. At 0.5 a
 * humanoid's pelvis (seed 9, 4000 points: cost 1.18 against a threshold of 2.5) merged into the
 * torso. A humanoid that does not move (motion 0) stays one part with 0.3, 0.4 or 0.5. */
constexpr double kCreaseMotion = 0.4;
/** Part motions: two reference points of different parts are in contact across a crease when
 * one is among the other's kContactNeighbours nearest, within kContactSpacings, and their
 * normals do not face each other (cosine above kFacingCos). */
constexpr int kContactNeighbours = 10;
constexpr double kContactSpacings = 3.0;
constexpr double kFacingCos = -0.3;

struct Frame {
  Cloud::Ptr cloud;
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  double spacing = 1.0;
  float error_bound2 = 0.0f;  ///< squared distance beyond which a surface error is clipped
  /** Normals whose sign is a guess (estimated from points: PointCloudSequence::normalsOriented
   * false): points of two frames are compared by |n . n'|, so that a limb whose normals the
   * orientation turned inwards in one frame is still tracked there. */
  bool unoriented = false;
};

/** The cosine of two normals as the frames allow: signed, or its absolute value when the
 * normals' orientation is a guess (Frame::unoriented). */
inline double normalCos(double c, const Frame& f) { return f.unoriented ? std::abs(c) : c; }

/** Every frame with its kd-tree and spacing; built once per segmentation and shared by the
 * steps. */
std::vector<Frame> makeFrames(const PointCloudSequence& seq) {
  const int T = static_cast<int>(seq.size());
  std::vector<Frame> frames(T);
  const bool unoriented = !seq.normalsOriented();
  for (int t = 0; t < T; ++t)
    if (seq.frame(t)->empty())
      throw Error("motion tracking: frame " + std::to_string(t) + " has no points");
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < T; ++t) {
    frames[t].cloud = seq.frame(t);
    frames[t].tree.setInputCloud(frames[t].cloud);
  }
  // Each frame's spacing from its own tree (meanSpacings' values, without a second tree).
  const std::vector<double> spacing =
      meanSpacings(seq, [&](std::size_t t) -> const pcl_animseg::KdTree<pcl::PointNormal>& {
        return frames[t].tree;
      });
  for (int t = 0; t < T; ++t) {
    frames[t].spacing = std::max(spacing[t], 1e-9);
    const double bound = (kClip + 1.5) * frames[t].spacing;
    frames[t].error_bound2 = static_cast<float>(bound * bound);
    frames[t].unoriented = unoriented;
  }
  return frames;
}

/** The frames as a device takes them (motion_device.h): each kd-tree with its points' normals
 * in the tree's leaf order. */
DeviceFrames deviceFrames(const std::vector<Frame>& frames) {
  DeviceFrames out;
  out.normal_cos = kNormalCos;
  out.clip = kClip;
  out.frames.resize(frames.size());
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < static_cast<int>(frames.size()); ++t) {
    const Frame& f = frames[t];
    DeviceFrames::Frame& d = out.frames[t];
    d.tree = &f.tree.flatTree();
    const std::vector<int>& rows = d.tree->leafRows();
    d.leaf_normals.resize(3 * rows.size());
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const auto& q = (*f.cloud)[f.tree.cloudIndex(rows[i])];
      d.leaf_normals[3 * i] = q.normal_x;
      d.leaf_normals[3 * i + 1] = q.normal_y;
      d.leaf_normals[3 * i + 2] = q.normal_z;
    }
    d.spacing = f.spacing;
    d.unoriented = f.unoriented;
  }
  return out;
}

struct Source {
  Eigen::Matrix3Xd p;
  Eigen::Matrix3Xd n;
};

Source sourceOf(const Cloud& ref, const std::vector<int>& idx, std::size_t max_points) {
  const std::size_t m = std::min(max_points, idx.size());
  Source s;
  s.p.resize(3, static_cast<Eigen::Index>(m));
  s.n.resize(3, static_cast<Eigen::Index>(m));
  for (std::size_t i = 0; i < m; ++i) {
    // Even stride: deterministic and spread over the whole set.
    const auto& q = ref[idx[i * idx.size() / m]];
    s.p.col(i) = Eigen::Vector3d(q.x, q.y, q.z);
    s.n.col(i) = Eigen::Vector3d(q.normal_x, q.normal_y, q.normal_z);
  }
  return s;
}

inline pcl::PointNormal toPoint(const Eigen::Vector3d& y) {
  pcl::PointNormal q;
  q.x = static_cast<float>(y.x());
  q.y = static_cast<float>(y.y());
  q.z = static_cast<float>(y.z());
  return q;
}

inline icp_step::Rigid toRigid(const Pose& a) {
  icp_step::Rigid r;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) r.r[3 * i + j] = a.linear()(i, j);
    r.t[i] = a.translation()(i);
  }
  return r;
}

inline Pose toPose(const icp_step::Rigid& r) {
  Pose a = Pose::Identity();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) a.linear()(i, j) = r.r[3 * i + j];
    a.translation()(i) = r.t[i];
  }
  return a;
}

/** The constant-velocity guess from the poses of the frames one and two before: the motion
 * between them applied once more (Eigen's arithmetic; the samples' starts compose theirs in
 * icp_step's, as their device does). */
inline Pose constantVelocity(const Pose& before, const Pose& two_before) {
  return before * two_before.inverse() * before;
}

/** a * b in icp_step's arithmetic (the tracking's starts; the same bits as its device). */
inline Pose compose(const Pose& a, const Pose& b) {
  return toPose(icp_step::compose(toRigid(a), toRigid(b)));
}
inline Pose inverse(const Pose& a) { return toPose(icp_step::inverse(toRigid(a))); }

/** Squared surface error of a moved point (position y, normal n) against a frame, in spacings^2
 * (icp_step::surfaceError): the distance to the nearest point's tangent plane, plus how far
 * beyond 1.5 spacings that point is; clipped at kClip^2, and kClip^2 when the normals disagree.
 * The tangent-plane distance does not see the sampling of the two clouds (a point-to-point
 * distance is ~1 spacing for a perfect fit), so small rigid deviations stand out. */
inline double surfaceError(const double* y, const double* n, const Frame& f) {
  // Beyond (kClip + 1.5) spacings the error is clip^2 whatever the nearest point is: the search
  // is bounded there.
  float d2 = 0.0f;
  const int k = f.tree.nearest(static_cast<float>(y[0]), static_cast<float>(y[1]),
                               static_cast<float>(y[2]), f.error_bound2, d2);
  double tp[3] = {0.0, 0.0, 0.0}, tn[3] = {0.0, 0.0, 0.0};
  if (k >= 0) {
    const auto& t = (*f.cloud)[k];
    tp[0] = t.x, tp[1] = t.y, tp[2] = t.z;
    tn[0] = t.normal_x, tn[1] = t.normal_y, tn[2] = t.normal_z;
  }
  return icp_step::surfaceError(k >= 0, d2, y, n, tp, tn, f.spacing, f.unoriented, kNormalCos,
                                kClip);
}
inline double surfaceError(const Eigen::Vector3d& y, const Eigen::Vector3d& n, const Frame& f) {
  return surfaceError(y.data(), n.data(), f);
}

/** A source this large, outside any parallel region (the whole body's ICP of the tracking),
 * is moved, matched and turned into per-point terms in parallel; the sums stay in point order,
 * so that the result is the same bit for bit on any number of threads. */
constexpr Eigen::Index kParallelSource = 256;
/** The whole body's ICP searches in parallel from this many points: its chain of frames runs
 * alone on the cores, and a frame of 2000 points has 250 samples (96k-point humanoid, 2 cores:
 * its global poses 0.116 s one thread, 0.069 s two; the same poses). Every other source keeps
 * kParallelSource: the samples' and parts' smaller ICPs below it ran twice as long in parallel. */
constexpr Eigen::Index kParallelWholeBody = 128;
bool searchInParallel(const Source& src, Eigen::Index at_least = kParallelSource) {
  return src.p.cols() >= at_least && !omp_in_parallel() && omp_get_max_threads() > 1;
}

/** A source point's ICP terms (icp_step::kTerms doubles) against its nearest point within
 * max_d2 of its moved position y, under the pose T about the centroid c; false where it has no
 * usable match (none, or normals that disagree). `match`, where given, holds the point's match
 * of the iteration before (-1: none), a guess that bounds the search (the same match), and
 * gets this one. */
inline bool matchTerms(const Source& src, Eigen::Index i, const double* y, const icp_step::Rigid& T,
                       const double* c, const Frame& f, float max_d2, double* terms,
                       int* match = nullptr) {
  float d2;
  const int k = f.tree.nearest(static_cast<float>(y[0]), static_cast<float>(y[1]),
                               static_cast<float>(y[2]), max_d2, match ? *match : -1, d2);
  if (match) *match = k;
  if (k < 0) return false;
  const auto& t = (*f.cloud)[k];
  const double tn[3] = {t.normal_x, t.normal_y, t.normal_z};
  const double tp[3] = {t.x, t.y, t.z};
  double n[3];
  icp_step::rotate(T, src.n.col(i).data(), n);
  if (normalCos(icp_step::dot3(n, tn), f) < kNormalCos) return false;
  icp_step::pointTerms(y, c, tp, tn, terms);
  return true;
}

/** The surface error (surfaceError) of source point i under the pose R. */
inline double pointError(const Source& src, Eigen::Index i, const icp_step::Rigid& R,
                         const Frame& f) {
  double y[3], n[3];
  icp_step::apply(R, src.p.col(i).data(), y);
  icp_step::rotate(R, src.n.col(i).data(), n);
  return surfaceError(y, n, f);
}

/** An ICP iteration's step from its summed terms (`used` points matched), about the centroid c:
 * T moved by it. False where the iterations stop: too few matches or no step (T unchanged), or
 * the step converged (T moved). */
inline bool takeStep(const double* sums, int used, const double* c, double spacing,
                     icp_step::Rigid& T) {
  double x[6];
  if (used < 6 || !icp_step::solveStep(sums, x)) return false;
  T = icp_step::compose(icp_step::stepMotion(x, c), T);
  return !icp_step::converged(x, spacing);
}

/** RMS over the source of the surface error (in the frame's spacings); the errors are added in
 * point order. A source that searches in parallel (searchInParallel) goes through residualsOf. */
std::vector<double> residualsOf(const Source& src, const std::vector<Pose>& poses, const Frame& f,
                                Eigen::Index parallel_from = kParallelSource);
double residual(const Source& src, const Pose& T, const Frame& f) {
  const Eigen::Index m = src.p.cols();
  if (m == 0) return 0.0;
  if (searchInParallel(src)) return residualsOf(src, {T}, f).front();
  const icp_step::Rigid R = toRigid(T);
  double sum = 0.0;
  for (Eigen::Index i = 0; i < m; ++i) sum += pointError(src, i, R, f);
  return std::sqrt(sum / static_cast<double>(m));
}

/** Damped point-to-plane ICP (plus a weak point-to-point term against sliding on symmetric
 * surfaces), linearised about the moved source's centroid for conditioning (icp_step.h: the
 * arithmetic, shared with the GPU's tracking). The Levenberg damping keeps the directions the
 * source does not constrain (rotation about and translation along a capsule) near the initial
 * pose, which comes from a neighbour on the same part. Every sum runs in point order. A source
 * that searches in parallel (searchInParallel) goes through icpFromStarts. */
std::vector<Pose> icpFromStarts(const Source& src, const std::vector<Pose>& inits, const Frame& f,
                                int iterations, double max_dist,
                                Eigen::Index parallel_from = kParallelSource);
Pose icp(const Source& src, const Pose& init, const Frame& f, int iterations, double max_dist) {
  if (searchInParallel(src)) return icpFromStarts(src, {init}, f, iterations, max_dist).front();
  icp_step::Rigid T = toRigid(init);
  const Eigen::Index m = src.p.cols();
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  Eigen::Matrix3Xd moved(3, m);  // the source under T, once per iteration
  for (int it = 0; it < iterations; ++it) {
    double c[3] = {0.0, 0.0, 0.0};
    for (Eigen::Index i = 0; i < m; ++i) {
      icp_step::apply(T, src.p.col(i).data(), moved.col(i).data());
      for (int k = 0; k < 3; ++k) c[k] += moved(k, i);
    }
    const double count = static_cast<double>(std::max<Eigen::Index>(1, m));
    for (int k = 0; k < 3; ++k) c[k] /= count;
    double sums[icp_step::kTerms] = {};
    int used = 0;
    for (Eigen::Index i = 0; i < m; ++i) {
      double terms[icp_step::kTerms];
      if (!matchTerms(src, i, moved.col(i).data(), T, c, f, max_d2, terms)) continue;
      ++used;
      for (int q = 0; q < icp_step::kTerms; ++q) sums[q] += terms[q];
    }
    if (!takeStep(sums, used, c, f.spacing, T)) break;
  }
  return toPose(T);
}

/** icp() from several starts. For a source that searches in parallel (searchInParallel), each
 * iteration moves, matches and turns into terms the points of every start still running in one
 * parallel loop, and each start's sums run in point order: each result is the one-thread icp()'s
 * from that start, bit for bit, and a start stops where it stops. (The tracking's whole-body ICP
 * has two starts per frame: one after the other they paid the start and end of each parallel
 * loop twice per iteration, in a chain along the frames.) Otherwise one icp() after the other. */
std::vector<Pose> icpFromStarts(const Source& src, const std::vector<Pose>& inits, const Frame& f,
                                int iterations, double max_dist, Eigen::Index parallel_from) {
  const std::size_t n = inits.size();
  std::vector<Pose> out;
  // Below kParallelSource icp() runs one thread: no call back here.
  if (!searchInParallel(src, std::min(parallel_from, kParallelSource))) {
    for (const Pose& p : inits) out.push_back(icp(src, p, f, iterations, max_dist));
    return out;
  }
  const Eigen::Index m = src.p.cols();
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  std::vector<icp_step::Rigid> T(n);
  for (std::size_t c = 0; c < n; ++c) T[c] = toRigid(inits[c]);
  std::vector<char> running(n, 1);
  std::vector<std::array<double, 3>> centroid(n);
  std::vector<char> usable(n * static_cast<std::size_t>(m));
  std::vector<double> point_terms(usable.size() * icp_step::kTerms);
  // Each point's match of the iteration before: it bounds the next search (the same matches;
  // the whole-body ICP 8% faster on 2 cores at 800k; the small ICPs of icp() above were 2.5%
  // slower with it, so they search without).
  std::vector<int> match(usable.size(), -1);
  std::vector<std::array<double, icp_step::kTerms>> sums_of(n);
  std::vector<int> used_of(n, 0);
  std::vector<int> act;
  for (int it = 0; it < iterations; ++it) {
    act.clear();
    for (std::size_t c = 0; c < n; ++c)
      if (running[c]) act.push_back(static_cast<int>(c));
    if (act.empty()) break;
    const Eigen::Index items = static_cast<Eigen::Index>(act.size()) * m;
    const int na = static_cast<int>(act.size());
    const double count = static_cast<double>(std::max<Eigen::Index>(1, m));
    // One team per iteration: each start's centroid, the matches and terms, then each start's
    // sums. A sum is one column (a start's coordinate or term) added in point order, the columns
    // side by side: the same sums as one thread's, which the team waited for (the tracking's
    // whole-body ICP: 54 000 additions per iteration, 0.01 s of its 0.34 s on 2 cores). A
    // centroid column moves its own coordinate of every point (applied(): apply()'s
    // coordinate), and a match its own point: a loop of moves before them cost the team a
    // barrier per iteration (1 100 iterations a run at 800k).
    constexpr int kCols = icp_step::kTerms + 1;  // the terms, then the count of usable points
#pragma omp parallel
    {
#pragma omp for schedule(static)
      for (int x = 0; x < na * 3; ++x) {
        const int c = act[x / 3], k = x % 3;
        double ct = 0.0;
        for (Eigen::Index i = 0; i < m; ++i) ct += icp_step::applied(T[c], src.p.col(i).data(), k);
        centroid[c][k] = ct / count;
      }
#pragma omp for schedule(static)
      for (Eigen::Index q = 0; q < items; ++q) {
        const int c = act[q / m];
        const Eigen::Index i = q % m;
        const std::size_t slot = static_cast<std::size_t>(c) * m + i;
        double y[3];
        icp_step::apply(T[c], src.p.col(i).data(), y);
        usable[slot] = matchTerms(src, i, y, T[c], centroid[c].data(), f, max_d2,
                                  &point_terms[slot * icp_step::kTerms], &match[slot])
                           ? 1
                           : 0;
      }
#pragma omp for schedule(static) nowait  // the team's end waits for it
      for (int x = 0; x < na * kCols; ++x) {
        const int c = act[x / kCols], q = x % kCols;
        const std::size_t first = static_cast<std::size_t>(c) * m;
        if (q == icp_step::kTerms) {
          int used = 0;
          for (Eigen::Index i = 0; i < m; ++i) used += usable[first + i];
          used_of[c] = used;
          continue;
        }
        double sum = 0.0;
        for (Eigen::Index i = 0; i < m; ++i)
          if (usable[first + i]) sum += point_terms[(first + i) * icp_step::kTerms + q];
        sums_of[c][q] = sum;
      }
    }
    for (int c : act) {
      if (!takeStep(sums_of[c].data(), used_of[c], centroid[c].data(), f.spacing, T[c]))
        running[c] = 0;
    }
  }
  for (std::size_t c = 0; c < n; ++c) out.push_back(toPose(T[c]));
  return out;
}

/** residual() of several poses of one source. For a source that searches in parallel, all the
 * errors in one parallel loop, each pose's added in point order (the one-thread residual()'s
 * bits); otherwise one residual() after the other. */
std::vector<double> residualsOf(const Source& src, const std::vector<Pose>& poses, const Frame& f,
                                Eigen::Index parallel_from) {
  const std::size_t n = poses.size();
  std::vector<double> out;
  const Eigen::Index m = src.p.cols();
  if (m == 0 || !searchInParallel(src, std::min(parallel_from, kParallelSource))) {
    for (const Pose& p : poses) out.push_back(residual(src, p, f));
    return out;
  }
  std::vector<icp_step::Rigid> R(n);
  for (std::size_t c = 0; c < n; ++c) R[c] = toRigid(poses[c]);
  std::vector<double> e(n * static_cast<std::size_t>(m));
  const Eigen::Index items = static_cast<Eigen::Index>(e.size());
#pragma omp parallel for schedule(static)
  for (Eigen::Index q = 0; q < items; ++q) {
    e[q] = pointError(src, q % m, R[static_cast<std::size_t>(q / m)], f);
  }
  for (std::size_t c = 0; c < n; ++c) {
    double sum = 0.0;
    for (Eigen::Index i = 0; i < m; ++i) sum += e[c * m + i];
    out.push_back(std::sqrt(sum / static_cast<double>(m)));
  }
  return out;
}

/** Breadth-first levels over a graph (adjacency lists of node ids), started from each node of
 * `starts` in turn that is not reached yet (its level follows the last one of the component
 * before); returns each node's level (-1: unreached). */
template <class Graph>
std::vector<int> bfsLevels(const Graph& graph, const std::vector<int>& starts) {
  std::vector<int> level(graph.size(), -1);
  int levels = 0;
  for (int start : starts) {
    if (level[start] >= 0) continue;
    std::vector<int> cur{start};
    level[start] = levels;
    while (!cur.empty()) {
      ++levels;
      std::vector<int> next;
      for (int v : cur)
        for (int o : graph[v])
          if (level[o] < 0) level[o] = levels, next.push_back(o);
      cur.swap(next);
    }
  }
  return level;
}

/** A task graph (runTaskGraph) of one task per (frame, node): task k * n + v is node v of a graph
 * of n nodes in frame chain.order[k] (chainFrames). It depends on the same node in the frame
 * before (its ChainStep), and on its graph neighbours of lower level(t, v) in the same frame;
 * priorities in the order of a serial run (frame, then level). */
template <class Graph, class Level>
void frameTaskGraph(const ChainFrames& chain, const Graph& graph, Level level,
                    std::vector<std::vector<int>>& successors, std::vector<long>& priority) {
  const std::vector<int>& order = chain.order;
  const int F = static_cast<int>(order.size()), n = static_cast<int>(graph.size());
  successors.assign(static_cast<std::size_t>(F) * n, {});
  priority.assign(successors.size(), 0);
  std::vector<int> at(chain.step.size(), -1);  // position of each frame in order
  for (int k = 0; k < F; ++k) at[order[k]] = k;
  std::vector<std::vector<int>> next(F);  // the positions of the frames started from each
  for (int k = 0; k < F; ++k) {
    const int b = chain.step[order[k]].before;
    if (b >= 0 && at[b] >= 0) next[at[b]].push_back(k);
  }
  // Each frame's tasks on their own (47 000 lists at 800k, made serially before the device's
  // first call).
#pragma omp parallel for schedule(static)
  for (int k = 0; k < F; ++k) {
    const int t = order[k];
    for (int v = 0; v < n; ++v) {
      const int task = k * n + v;
      priority[task] = static_cast<long>(k) * (n + 1) + level(t, v);
      for (int kn : next[k]) successors[task].push_back(kn * n + v);
      for (int o : graph[v])
        if (level(t, v) < level(t, o)) successors[task].push_back(k * n + o);
    }
  }
}

/** Connected components of a graph (adjacency lists of node ids), numbered in the order in which
 * `order` reaches them (every node must be in `order`); comp[v] is v's component. Returns the
 * number of components. */
template <class Graph>
int connectedComponents(const Graph& graph, const std::vector<int>& order, std::vector<int>& comp) {
  comp.assign(graph.size(), -1);
  int n = 0;
  for (int start : order) {
    if (comp[start] >= 0) continue;
    std::vector<int> stack{start};
    comp[start] = n;
    while (!stack.empty()) {
      const int v = stack.back();
      stack.pop_back();
      for (int o : graph[v])
        if (comp[o] < 0) comp[o] = n, stack.push_back(o);
    }
    ++n;
  }
  return n;
}

/** Points whose neighbourhood is concave (MotionTrackingParams::concave_crease_depth): the
 * centroid of the point's kConcaveNeighbours nearest points lies more than `depth` spacings
 * along its normal (outward: the loader orients estimated normals so). Where two parts of a body
 * meet, the surface folds inwards (the minima rule); estimated normals turn across such a fold
 * over two or three spacings, so no single edge shows it, but a wider neighbourhood rises there
 * on both sides. On a generated humanoid's plain clouds these points form a band around the
 * waist that leaves 0-2 of 64 surface-graph edges between torso and pelvis (0.1 spacings).
 * All flags are cleared when more than kConcaveMaxFraction of the points are flagged: a region
 * whose normals the orientation turned inwards looks concave everywhere (a noisy quadruped's two
 * right legs, 28% of its points), and cutting it out of the graph left one part. Written by us:
 * PCL has curvature estimates but no concavity test on oriented normals. */
constexpr int kConcaveNeighbours = 16;
constexpr double kConcaveMaxFraction = 0.2;
std::vector<char> concavePoints(const Cloud& cloud,
                                const pcl_animseg::KdTree<pcl::PointNormal>& tree, double spacing,
                                double depth) {
  const int n = static_cast<int>(cloud.size());
  std::vector<char> concave(n, 0);
  if (!(depth > 0.0) || n < 3) return concave;
  const int k = std::min(kConcaveNeighbours, n);
  long count = 0;
#pragma omp parallel reduction(+ : count)
  {
    std::vector<int> idx;
    std::vector<float> d2;
#pragma omp for schedule(static)
    for (int i = 0; i < n; ++i) {
      tree.nearestKSearch(cloud[i], k, idx, d2);
      if (idx.empty()) continue;
      Eigen::Vector3d c = Eigen::Vector3d::Zero();
      for (int j : idx) c += cloud[j].getVector3fMap().cast<double>();
      c /= static_cast<double>(idx.size());
      const double h = (c - cloud[i].getVector3fMap().cast<double>())
                           .dot(cloud[i].getNormalVector3fMap().cast<double>());
      concave[i] = h > depth * spacing;
      count += concave[i];
    }
  }
  if (static_cast<double>(count) > kConcaveMaxFraction * n)
    std::fill(concave.begin(), concave.end(), 0);
  return concave;
}

/** Surface graph of a cloud: each point linked to its k nearest points that lie within
 * `max_dist` and have a compatible normal (symmetric). Unlike a plain k-NN graph it does not
 * bridge the gap between two limbs that nearly touch (facing sides have opposite normals), so
 * neighbourhoods and adjacency grown over it stay on one surface sheet. Points flagged in
 * `no_edges` (concavePoints, for estimated normals) get no edge. */
std::vector<std::vector<int>> surfaceGraphOf(const Cloud& cloud,
                                             const pcl_animseg::KdTree<pcl::PointNormal>& tree,
                                             int k, double max_dist, bool unoriented,
                                             const std::vector<char>& no_edges = {}) {
  const int n = static_cast<int>(cloud.size());
  std::vector<std::vector<int>> g(n);
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  const int kk = std::min(k + 1, n);
  const bool cut = no_edges.size() == static_cast<std::size_t>(n);
#pragma omp parallel
  {
    std::vector<int> idx;
    std::vector<float> d2;
#pragma omp for schedule(static)
    for (int i = 0; i < n; ++i) {
      tree.nearestKSearch(cloud[i], kk, idx, d2);
      const auto& a = cloud[i];
      for (std::size_t m = 0; m < idx.size(); ++m) {
        const int j = idx[m];
        if (j == i || d2[m] > max_d2) continue;
        if (cut && (no_edges[i] || no_edges[j])) continue;
        const auto& b = cloud[j];
        const float ab =
            a.normal_x * b.normal_x + a.normal_y * b.normal_y + a.normal_z * b.normal_z;
        if (!unoriented) {
          if (ab < 0.5f) continue;
        } else {
          // Signs are a guess: alike up to sign, and the step between the points lies in both
          // tangent planes (a step across the gap to a facing sheet goes along the normals).
          if (std::abs(ab) < 0.5f) continue;
          const Eigen::Vector3f e = (b.getVector3fMap() - a.getVector3fMap()).normalized();
          if (std::abs(e.dot(a.getNormalVector3fMap())) > 0.6f ||
              std::abs(e.dot(b.getNormalVector3fMap())) > 0.6f)
            continue;
        }
        g[i].push_back(j);
      }
    }
  }
  // Symmetrise.
  std::vector<std::vector<int>> sym(g);
  for (int i = 0; i < n; ++i)
    for (int j : g[i]) sym[j].push_back(i);
  for (auto& v : sym) {
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end()), v.end());
  }
  return sym;
}

/** The `count` points geodesically nearest to `start` over the surface graph (Dijkstra), sorted
 * by index. Fewer when its component is smaller. */
std::vector<int> geodesicNeighbourhood(const Cloud& cloud, const std::vector<std::vector<int>>& g,
                                       int start, int count) {
  std::vector<int> out;
  std::map<int, double> dist;
  using Item = std::pair<double, int>;
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> q;
  std::set<int> done;
  q.push({0.0, start});
  dist[start] = 0.0;
  auto pos = [&](int i) { return Eigen::Vector3d(cloud[i].x, cloud[i].y, cloud[i].z); };
  while (!q.empty() && static_cast<int>(out.size()) < count) {
    const auto [d, i] = q.top();
    q.pop();
    if (!done.insert(i).second) continue;
    out.push_back(i);
    for (int j : g[i]) {
      if (done.count(j)) continue;
      const double nd = d + (pos(i) - pos(j)).norm();
      auto it = dist.find(j);
      if (it == dist.end() || nd < it->second) {
        dist[j] = nd;
        q.push({nd, j});
      }
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

/** Geodesic Voronoi cells of the samples over the surface graph (multi-source Dijkstra): the
 * owning sample of every point (-1 where unreached). */
std::vector<int> geodesicOwners(const Cloud& cloud, const std::vector<std::vector<int>>& g,
                                const std::vector<int>& samples) {
  const int n = static_cast<int>(cloud.size());
  std::vector<int> owner(n, -1);
  std::vector<double> dist(n, std::numeric_limits<double>::max());
  using Item = std::pair<double, std::pair<int, int>>;  // distance, (point, owner)
  std::priority_queue<Item, std::vector<Item>, std::greater<Item>> q;
  for (std::size_t s = 0; s < samples.size(); ++s) {
    dist[samples[s]] = 0.0;
    q.push({0.0, {samples[s], static_cast<int>(s)}});
  }
  auto pos = [&](int i) { return Eigen::Vector3d(cloud[i].x, cloud[i].y, cloud[i].z); };
  while (!q.empty()) {
    const auto [d, item] = q.top();
    q.pop();
    const auto [i, s] = item;
    if (owner[i] >= 0) continue;
    owner[i] = s;
    for (int j : g[i]) {
      if (owner[j] >= 0) continue;
      const double nd = d + (pos(i) - pos(j)).norm();
      if (nd < dist[j]) {
        dist[j] = nd;
        q.push({nd, {j, s}});
      }
    }
  }
  return owner;
}

/** Sample adjacency from the Voronoi cells: two samples are neighbours when a surface-graph edge
 * joins their cells. Components left apart only by a crease or a near contact (their samples
 * within `join_distance`) are joined at their closest samples; pieces farther apart stay apart
 * (a part is connected), so the hierarchy ends with one part per separate piece. */
std::vector<std::vector<int>> cellGraphOf(const std::vector<std::vector<int>>& g,
                                          const std::vector<int>& owner,
                                          const Eigen::Matrix3Xd& sample_pos,
                                          double join_distance) {
  const int S = static_cast<int>(sample_pos.cols());
  std::vector<std::set<int>> nb(S);
  for (std::size_t i = 0; i < g.size(); ++i) {
    if (owner[i] < 0) continue;
    for (int j : g[i])
      if (owner[j] >= 0 && owner[j] != owner[i]) nb[owner[i]].insert(owner[j]);
  }
  std::vector<int> order(S);
  std::iota(order.begin(), order.end(), 0);
  std::vector<int> comp;
  const int nc = connectedComponents(nb, order, comp);
  if (nc > 1) {
    // Closest sample pair of every pair of components.
    const double lim2 = join_distance * join_distance;
    std::map<std::pair<int, int>, std::pair<double, std::pair<int, int>>> closest;
    for (int a = 0; a < S; ++a)
      for (int b = a + 1; b < S; ++b) {
        if (comp[a] == comp[b]) continue;
        const double d = (sample_pos.col(a) - sample_pos.col(b)).squaredNorm();
        if (d > lim2) continue;
        const auto key = std::make_pair(std::min(comp[a], comp[b]), std::max(comp[a], comp[b]));
        auto it = closest.find(key);
        if (it == closest.end() || d < it->second.first) closest[key] = {d, {a, b}};
      }
    for (const auto& [key, v] : closest) {
      nb[v.second.first].insert(v.second.second);
      nb[v.second.second].insert(v.second.first);
    }
  }
  std::vector<std::vector<int>> out(S);
  for (int s = 0; s < S; ++s) out[s].assign(nb[s].begin(), nb[s].end());
  return out;
}

}  // namespace

std::vector<int> MotionDevice::frameTasks(const SampleTrackingProblem& problem,
                                          const std::vector<char>& given, int t,
                                          const std::vector<int>& level) {
  const int T = static_cast<int>(problem.before.size()), S = problem.samples;
  const std::string what = "streamed sample tracking: frame " + std::to_string(t);
  if (t < 0 || t >= T || given.size() != static_cast<std::size_t>(T) ||
      problem.two_before.size() != static_cast<std::size_t>(T))
    throw Error(what + " is not a frame of the problem");
  if (given[t]) throw Error(what + " given twice (or it is the reference)");
  const int tp = problem.before[t], tpp = problem.two_before[t];
  if (tp < 0 || tp >= T || !given[tp] || tpp >= T || (tpp >= 0 && !given[tpp]))
    throw Error(what + " given before a frame it starts from");
  if (level.size() != static_cast<std::size_t>(S))
    throw Error(what + ": one level per sample expected");
  // The samples by level, in sample order within a level (a counting sort: the stable sort's
  // order; levels are BFS levels, in [0, S) when every sample was reached).
  std::vector<int> order;
  if (std::all_of(level.begin(), level.end(), [&](int l) { return l >= 0 && l < S; })) {
    order = orderByKey(level, S);
  } else {
    order.resize(S);
    std::iota(order.begin(), order.end(), 0);
    std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return level[a] < level[b]; });
  }
  for (int& s : order) s += t * S;
  return order;
}

void MotionDevice::startStreamed(SampleTrackingProblem kept) {
  streamed_ = std::move(kept);
  streamed_.level.assign(streamed_.before.size(), {});
  streamed_.waves.clear();
  streamed_frame_.assign(streamed_.before.size(), 0);
  for (std::size_t t = 0; t < streamed_.before.size(); ++t)
    streamed_frame_[t] = streamed_.before[t] < 0;
}

void MotionDevice::beginSamples(const SampleTrackingProblem& problem) { startStreamed(problem); }

bool MotionDevice::nearestMoved(const MovedCopies&, std::vector<int>&) { return false; }

void MotionDevice::partFitsWithResiduals(const PartFitJobs& jobs, std::vector<double>& poses,
                                         std::vector<double>& residual) {
  partFits(jobs, poses);
  if (poses.size() != 12 * jobs.jobs.size())
    throw Error("motion method: the device returned " + std::to_string(poses.size() / 12) +
                " part fits for " + std::to_string(jobs.jobs.size()));
  ResidualJobs scores;
  scores.points = jobs.points;
  scores.source_begin = jobs.source_begin;
  scores.motions = poses;
  for (std::size_t j = 0; j < jobs.jobs.size(); ++j)
    scores.jobs.push_back({jobs.jobs[j].source, static_cast<int>(j), jobs.jobs[j].frame});
  residuals(scores, residual);
}

void MotionDevice::scoreAndFit(const ScoreFitJobs& jobs, std::vector<double>& scores,
                               std::vector<int>& fitted, std::vector<double>& poses) {
  ResidualJobs r;
  r.points = jobs.points;
  r.source_begin = jobs.source_begin;
  r.motions = jobs.motions;
  for (const ScoreFitJobs::Job& j : jobs.jobs)
    for (int k = 0; k < j.count; ++k) r.jobs.push_back({j.source, j.first + k, j.frame});
  residuals(r, scores);
  if (scores.size() != r.jobs.size())
    throw Error("motion method: the device returned " + std::to_string(scores.size()) +
                " residuals for " + std::to_string(r.jobs.size()) + " starts");
  PartFitJobs f;
  f.iterations = jobs.iterations;
  f.points = jobs.points;
  f.source_begin = jobs.source_begin;
  f.motions = jobs.motions;
  fitted.assign(jobs.jobs.size(), -1);
  std::vector<std::size_t> of;
  for (std::size_t j = 0; j < jobs.jobs.size(); ++j) {
    const ScoreFitJobs::Job& job = jobs.jobs[j];
    double r0;
    fitted[j] =
        scoreFitWinner(scores.data() + job.first, jobs.places.data() + job.first,
                       static_cast<std::size_t>(job.count), job.base_score, job.base_place, r0);
    if (fitted[j] < 0) continue;
    f.jobs.push_back({job.source, job.first + fitted[j], job.frame, r0, job.max_dist});
    of.push_back(j);
  }
  poses.assign(12 * jobs.jobs.size(), 0.0);
  for (std::size_t j = 0; j < jobs.jobs.size(); ++j)
    poses[12 * j] = poses[12 * j + 4] = poses[12 * j + 8] = 1.0;
  if (f.jobs.empty()) return;
  std::vector<double> fit;
  partFits(f, fit);
  if (fit.size() != 12 * f.jobs.size())
    throw Error("motion method: the device returned " + std::to_string(fit.size() / 12) +
                " part fits for " + std::to_string(f.jobs.size()));
  for (std::size_t i = 0; i < of.size(); ++i)
    std::copy(fit.begin() + 12 * i, fit.begin() + 12 * (i + 1), poses.begin() + 12 * of[i]);
}

void MotionDevice::trackFrames(const std::vector<int>& frames,
                               const std::vector<Eigen::Isometry3d>& global,
                               const std::vector<std::vector<int>>& level) {
  if (global.size() != frames.size() || level.size() != frames.size())
    throw Error("streamed sample tracking: one global pose and levels per frame expected");
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const int t = frames[i];
    const std::vector<int> tasks = frameTasks(streamed_, streamed_frame_, t, level[i]);
    streamed_frame_[t] = 1;
    streamed_.level[t] = level[i];
    if (static_cast<std::size_t>(t) < streamed_.global.size()) streamed_.global[t] = global[i];
    // A wave per level: a fit reads its neighbours' of lower levels in this frame, and the
    // frames before this one's, all in earlier waves.
    for (std::size_t k = 0; k < tasks.size(); ++k) {
      const int s = tasks[k] % streamed_.samples;
      if (k == 0 || level[i][s] != level[i][tasks[k - 1] % streamed_.samples])
        streamed_.waves.emplace_back();
      streamed_.waves.back().push_back(tasks[k]);
    }
  }
}

void MotionDevice::endSamples(std::vector<std::vector<Eigen::Isometry3d>>& poses,
                              std::vector<std::vector<double>>& residual) {
  trackSamples(streamed_, poses, residual);
  streamed_ = SampleTrackingProblem();
  streamed_frame_.clear();
}

std::vector<int> farthestPointSamples(const Cloud& cloud, int count, unsigned seed,
                                      const std::vector<char>& skip) {
  const int n = static_cast<int>(cloud.size());
  std::vector<int> out;
  if (n == 0 || count <= 0) return out;
  std::vector<Eigen::Vector3d> p(n);
  for (int i = 0; i < n; ++i) p[i] = Eigen::Vector3d(cloud[i].x, cloud[i].y, cloud[i].z);
  // A simple LCG step of the seed picks the start, identically on every platform.
  int start = static_cast<int>((1103515245u * seed + 12345u) % static_cast<unsigned>(n));
  // Points in `skip` (no surface-graph edge: a sample there would be a part of one point that
  // never merges) are never picked: their distance stays below every other point's.
  const bool skipping = skip.size() == static_cast<std::size_t>(n);
  for (int k = 0; skipping && skip[start] && k < n; ++k) start = (start + 1) % n;
  if (skipping && skip[start]) return out;
  out.push_back(start);
  std::vector<double> dmin(n, std::numeric_limits<double>::max());
  if (skipping)
    for (int i = 0; i < n; ++i)
      if (skip[i]) dmin[i] = -1.0;
  // Each step updates every point's distance to the samples and picks the first point of the
  // largest (as one scan in point order does): the threads scan contiguous slices, each keeps
  // the first largest of its slice, and the slices' winners are compared in slice order, so the
  // samples are the same on any number of threads. One thread scanned 16 667 points 1000 times:
  // 13 ms on this box, 25-30 ms on the GPU machine's cores, before the device's first call.
  const int threads = n >= 4096 && !omp_in_parallel() ? omp_get_max_threads() : 1;
  // Each slice's winner and its distance (copied: the owner updates its distances in the next
  // step while others may still compare), in two buffers that alternate step by step, so that
  // one barrier per step separates writing and reading: every thread then picks the same sample
  // from the winners (before: a barrier and a `single` with its own barrier, 2000 barriers for
  // 1000 samples before the GPU's first call).
  std::vector<int> slice_best(2 * static_cast<std::size_t>(threads), -1);
  std::vector<double> slice_d(slice_best.size(), 0.0);
  const std::size_t wanted = static_cast<std::size_t>(count);
#pragma omp parallel num_threads(threads) if (threads > 1)
  {
    const int tid = omp_get_thread_num(), nt = omp_get_num_threads();
    const int lo = static_cast<int>(static_cast<long long>(n) * tid / nt),
              hi = static_cast<int>(static_cast<long long>(n) * (tid + 1) / nt);
    int last = out.back();
    std::size_t taken = out.size();
    for (; taken < wanted; ++taken) {
      const Eigen::Vector3d s = p[last];
      int far = lo < hi ? lo : -1;
      for (int i = lo; i < hi; ++i) {
        dmin[i] = std::min(dmin[i], (p[i] - s).squaredNorm());
        if (dmin[i] > dmin[far]) far = i;
      }
      const std::size_t buf = (taken & 1) * static_cast<std::size_t>(nt);
      slice_best[buf + tid] = far;
      slice_d[buf + tid] = far >= 0 ? dmin[far] : 0.0;
#pragma omp barrier
      int best = -1;
      double best_d = 0.0;
      for (int t = 0; t < nt; ++t)
        if (slice_best[buf + t] >= 0 && (best < 0 || slice_d[buf + t] > best_d))
          best = slice_best[buf + t], best_d = slice_d[buf + t];
      if (best < 0 || best_d <= 0.0) break;
      if (tid == 0) out.push_back(best);
      last = best;
    }
  }
  return out;
}

namespace {

// The caller's work beside the device's chains (MotionTrackingParams::beside_chains), or the
// hierarchy's merges beside the part motions and labels, on a thread of its own from start() on;
// run at once where no thread can be started. join() waits for it and throws what it threw;
// going out of scope without join() (a step of the caller's threw) waits and drops that.
class BesideThread {
 public:
  BesideThread() = default;
  void start(const std::function<void()>& work) {
    if (!work || thread_.joinable()) return;
    auto guarded = [this, work] {
      try {
        work();
      } catch (...) {
        failed_ = std::current_exception();
      }
    };
    try {
      thread_ = std::thread(guarded);
    } catch (const std::system_error&) {
      guarded();
    }
  }
  void join() {
    wait();
    if (failed_) std::rethrow_exception(std::exchange(failed_, nullptr));
  }
  ~BesideThread() { wait(); }
  BesideThread(const BesideThread&) = delete;
  BesideThread& operator=(const BesideThread&) = delete;

 private:
  void wait() {
    if (thread_.joinable()) thread_.join();
  }
  std::thread thread_;
  std::exception_ptr failed_;
};

// A device in front of another: every call forwarded to it through around(), which the devices
// below define (SharedDevice takes turns, TimedDevice counts and times).
class DeviceInFront : public MotionDevice {
 public:
  explicit DeviceInFront(MotionDevice& device) : device_(device) {}
  std::string name() const override { return device_.name(); }
  bool starting() const override { return device_.starting(); }
  void setFrames(const DeviceFrames& frames) override {
    around([&] { device_.setFrames(frames); });
  }
  void trackSamples(const SampleTrackingProblem& problem,
                    std::vector<std::vector<Eigen::Isometry3d>>& poses,
                    std::vector<std::vector<double>>& residual) override {
    around([&] { device_.trackSamples(problem, poses, residual); });
  }
  void residuals(const ResidualJobs& jobs, std::vector<double>& out) override {
    around([&] { device_.residuals(jobs, out); });
  }
  void pointCosts(const PointCostJobs& jobs, std::vector<double>& out) override {
    around([&] { device_.pointCosts(jobs, out); });
  }
  void partFits(const PartFitJobs& jobs, std::vector<double>& poses) override {
    around([&] { device_.partFits(jobs, poses); });
  }
  void partFitsWithResiduals(const PartFitJobs& jobs, std::vector<double>& poses,
                             std::vector<double>& residual) override {
    around([&] { device_.partFitsWithResiduals(jobs, poses, residual); });
  }
  void scoreAndFit(const ScoreFitJobs& jobs, std::vector<double>& scores, std::vector<int>& fitted,
                   std::vector<double>& poses) override {
    around([&] { device_.scoreAndFit(jobs, scores, fitted, poses); });
  }
  bool nearestMoved(const MovedCopies& moved, std::vector<int>& pick) override {
    bool offered = false;
    around([&] { offered = device_.nearestMoved(moved, pick); });
    return offered;
  }

 protected:
  /** Makes the call `call` (one of the device's) in this device's way. */
  virtual void around(const std::function<void()>& call) = 0;
  MotionDevice& device_;
};

// A device that two threads of the motion method share (the hierarchy's merges beside the part
// motions and labels, where the device offers no fork): their calls one at a time, as a device
// expects (MotionDevice serves one caller at a time). Each thread's calls and results are its
// own, so the results are the same as one after the other.
class SharedDevice : public DeviceInFront {
 public:
  using DeviceInFront::DeviceInFront;

 private:
  void around(const std::function<void()>& call) override {
    const std::lock_guard<std::mutex> lock(mutex_);
    call();
  }
  std::mutex mutex_;
};

// A device's calls counted and timed (ANIMSEG_MS_TIMING: the clustering's laps say how much of
// each went to device calls, and how many).
class TimedDevice : public DeviceInFront {
 public:
  using DeviceInFront::DeviceInFront;
  std::unique_ptr<MotionDevice> fork() override { return device_.fork(); }
  /** "N calls, S s" since the last report. */
  std::string report() {
    char line[64];
    std::snprintf(line, sizeof(line), "%d device calls, %.3f s", calls_ - reported_calls_,
                  seconds_ - reported_seconds_);
    reported_calls_ = calls_;
    reported_seconds_ = seconds_;
    return line;
  }

 private:
  void around(const std::function<void()>& call) override {
    const auto t0 = std::chrono::steady_clock::now();
    call();
    seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    ++calls_;
  }
  int calls_ = 0, reported_calls_ = 0;
  double seconds_ = 0.0, reported_seconds_ = 0.0;
};

// While a device starts on a thread of its own (MotionDevice::starting), the OpenMP loops leave
// it a core. With every core in the team, the start displaced one of the team's threads, and
// each barrier of the whole-body ICPs waited for it: on the H100 machine's 16 cores the global
// poses took 0.165-0.33 s beside the GPU's start, 0.127-0.147 s with 15 threads (and 0.14-0.15 s
// on the CPU alone). The thread count does not change the results.
// recheck() between steps gives the core back once the device has started.
class SpareCoreWhileStarting {
 public:
  explicit SpareCoreWhileStarting(const MotionDevice* device) : device_(device) { recheck(); }
  ~SpareCoreWhileStarting() { release(); }
  SpareCoreWhileStarting(const SpareCoreWhileStarting&) = delete;
  SpareCoreWhileStarting& operator=(const SpareCoreWhileStarting&) = delete;

  /** One thread fewer while the device is still starting, every thread once it has started. */
  void recheck() {
    release();
    const int threads = omp_get_max_threads();
    if (device_ && threads > 2 && !omp_in_parallel() && device_->starting()) {
      saved_ = threads;
      omp_set_num_threads(threads - 1);
    }
  }
  /** Every thread again. */
  void release() {
    if (saved_ > 0) omp_set_num_threads(saved_);
    saved_ = 0;
  }

 private:
  const MotionDevice* device_;
  int saved_ = 0;
};

/** Residuals (residual()) of many sources under many motions against the frames, computed at
 * once: on the device when there is one (motion_device.h), else in one parallel loop; the same
 * values either way. Add the sources and motions, then the jobs; run() returns one residual per
 * job, in job order. */
class ResidualBatch {
 public:
  ResidualBatch(const std::vector<Frame>& frames, MotionDevice* device)
      : frames_(frames), device_(device) {}
  /** With a device, sources and motions go into the device's batch as they come (appendPoints,
   * appendMotion), and packed ones may be added as they are (addPackedSource, addPackedMotions). */
  bool packed() const { return device_ != nullptr; }
  /** Room for `sources` sources of `source_points` points each, `motions` motions and `jobs`
   * jobs (a batch that knows its size: growing the packed vectors as they come took about 9 ms
   * of phase 1's main thread at 800k, most of it in addPackedMotions). */
  void reserve(std::size_t sources, std::size_t source_points, std::size_t motions,
               std::size_t jobs) {
    if (device_) {
      d_.points.reserve(6 * sources * source_points);
      d_.source_begin.reserve(sources + 1);
      d_.motions.reserve(12 * motions);
    } else {
      sources_.reserve(sources);
      motions_.reserve(motions);
    }
    d_.jobs.reserve(jobs);
  }
  int addSource(Source s) {
    if (device_) {
      appendPoints(s.p, s.n, d_.points);
      d_.source_begin.push_back(static_cast<int>(d_.points.size() / 6));
      return static_cast<int>(d_.source_begin.size()) - 2;
    }
    sources_.push_back(std::move(s));
    return static_cast<int>(sources_.size()) - 1;
  }
  int addMotion(const Pose& p) {
    if (device_) {
      appendMotion(p, d_.motions);
      return motions() - 1;
    }
    motions_.push_back(p);
    return static_cast<int>(motions_.size()) - 1;
  }
  /** A source as appendPoints packs it (packed() batches only). */
  int addPackedSource(const std::vector<double>& points) {
    d_.points.insert(d_.points.end(), points.begin(), points.end());
    d_.source_begin.push_back(static_cast<int>(d_.points.size() / 6));
    return static_cast<int>(d_.source_begin.size()) - 2;
  }
  /** `count` motions as appendMotion packs them (packed() batches only); returns the first's
   * index. */
  int addPackedMotions(const double* m, int count) {
    const int first = motions();
    d_.motions.insert(d_.motions.end(), m, m + 12 * static_cast<std::size_t>(count));
    return first;
  }
  int motions() const {
    return device_ ? static_cast<int>(d_.motions.size() / 12) : static_cast<int>(motions_.size());
  }
  /** Returns the job's index. */
  int add(int source, int motion, int frame) {
    d_.jobs.push_back({source, motion, frame});
    return static_cast<int>(d_.jobs.size()) - 1;
  }

  std::vector<double> run() const {
    std::vector<double> out(d_.jobs.size(), 0.0);
    if (device_) {
      device_->residuals(d_, out);
      return out;
    }
    detail::eachIndex(static_cast<long>(d_.jobs.size()), 16, [&](long j) {
      const ResidualJobs::Job& job = d_.jobs[j];
      out[j] = residual(sources_[job.source], motions_[job.motion], frames_[job.frame]);
    });
    return out;
  }

 private:
  const std::vector<Frame>& frames_;
  MotionDevice* device_;
  ResidualJobs d_;               // the jobs; with a device also the packed sources and motions
  std::vector<Source> sources_;  // without one
  std::vector<Pose> motions_;
};

// `before_poses`, where given, is called once the samples' poses are all that is left of the
// tracking (their fits leave the cores idle on a device).
SampleTracks trackSamplesOn(const PointCloudSequence& seq, const std::vector<Frame>& frames,
                            const MotionTrackingParams& params, Progress* progress,
                            const std::function<void()>& before_poses = {}) {
  const int T = static_cast<int>(seq.size());
  if (T == 0) throw Error("motion tracking: the sequence has no frames");
  const int ref = params.reference_frame < 0 ? 0 : params.reference_frame;
  if (ref >= T)
    throw Error("motion tracking: reference frame " + std::to_string(ref) +
                " is not in the sequence (frames 0-" + std::to_string(T - 1) + ")");
  if (params.neighbourhood < 6 || params.point_neighbours < 1 || params.icp_iterations < 1)
    throw Error(
        "motion tracking: neighbourhood must be >= 6, point_neighbours and icp_iterations "
        ">= 1");
  if (!(params.border_smoothness >= 0.0) || !std::isfinite(params.border_smoothness) ||
      params.border_hops < 1)
    throw Error("motion tracking: border smoothness must be a number >= 0 and border hops >= 1");
  if (!(params.dissolve_ratio >= 0.0) || !std::isfinite(params.dissolve_ratio))
    throw Error("motion tracking: dissolve ratio must be a number >= 0");
  if (!(params.joint_weight >= 0.0) || !std::isfinite(params.joint_weight))
    throw Error("motion tracking: joint weight must be a number >= 0");
  if (!(params.sliver_fraction >= 0.0 && params.sliver_fraction < 1.0))
    throw Error("motion tracking: sliver fraction must be in [0, 1)");
  detail::StageTimer timer;
  SpareCoreWhileStarting spare(params.device);
  const Cloud& rc = *frames[ref].cloud;
  const int n0 = static_cast<int>(rc.size());
  const int want = params.samples > 0 ? params.samples : std::clamp(n0 / 8, 16, kMaxTrackedSamples);
  SampleTracks tr;
  tr.reference_frame = ref;
  tr.spacing = frames[ref].spacing;
  // Reference points in concave bands get no surface-graph edge (estimated normals only).
  const std::vector<char> crease =
      frames[ref].unoriented
          ? concavePoints(rc, frames[ref].tree, frames[ref].spacing, params.concave_crease_depth)
          : std::vector<char>();
  tr.sample_points = farthestPointSamples(rc, std::min(want, n0), params.seed, crease);
  const int S = static_cast<int>(tr.sample_points.size());
  Eigen::Matrix3Xd p0(3, S);
  for (int s = 0; s < S; ++s) {
    const auto& q = rc[tr.sample_points[s]];
    p0.col(s) = Eigen::Vector3d(q.x, q.y, q.z);
  }
  // Neighbourhoods, cells and adjacency grow over the surface graph, not through space: two
  // limbs that nearly touch in the reference frame must not share a neighbourhood.
  tr.surface = surfaceGraphOf(rc, frames[ref].tree, std::max(params.point_neighbours, 6),
                              3.0 * frames[ref].spacing, frames[ref].unoriented, crease);
  tr.owner = geodesicOwners(rc, tr.surface, tr.sample_points);
  tr.graph = cellGraphOf(tr.surface, tr.owner, p0, 6.0 * frames[ref].spacing);
  // Each sample's ICP source: its geodesically nearest reference points (reference geometry: no
  // drift).
  std::vector<Source> src(S);
  tr.neighbourhoods.resize(S);
  {
    const int k = std::min(params.neighbourhood, n0);
#pragma omp parallel for schedule(dynamic, 4)
    for (int s = 0; s < S; ++s) {
      tr.neighbourhoods[s] = geodesicNeighbourhood(rc, tr.surface, tr.sample_points[s], k);
      src[s] = sourceOf(rc, tr.neighbourhoods[s], static_cast<std::size_t>(k));
    }
  }
  // A fifth of each neighbourhood scores the candidate starts (a bad start is obvious on few
  // points).
  std::vector<Source> probe(S);
  for (int s = 0; s < S; ++s)
    probe[s] = sourceOf(rc, tr.neighbourhoods[s],
                        std::max<std::size_t>(8, tr.neighbourhoods[s].size() / 5));
  // The whole frame's source for the global pose: the samples themselves (they cover it evenly).
  std::vector<int> all(tr.sample_points);
  std::sort(all.begin(), all.end());
  const Source whole = sourceOf(rc, all, all.size());

  tr.poses.assign(T, std::vector<Pose>(S, Pose::Identity()));
  tr.residual.assign(T, 0.0);
  // The frames in the order of a serial run: away from the reference, forwards first (through
  // key frames on a long side: chainFrames).
  const ChainFrames chain = chainFrames(T, ref);
  const std::vector<int>& frame_order = chain.order;
  const int F = static_cast<int>(frame_order.size());
  if (progress) progress->begin("tracking samples", static_cast<std::size_t>(T));
  timer.lap("tracking: samples, graphs, sources");
  std::vector<Pose> global(T, Pose::Identity());
  std::vector<std::vector<int>> level_of(T);
  std::vector<std::vector<double>> res(T, std::vector<double>(S, 0.0));
  // A frame's order of the samples (step 2 below): BFS levels over the sample graph from the
  // sample best explained by the global pose (unreached components start from their own best
  // sample), given the samples' residuals under it.
  auto levelsOf = [&](const double* groot) {
    const int root = static_cast<int>(std::min_element(groot, groot + S) - groot);
    std::vector<int> order(S);
    std::iota(order.begin(), order.end(), 0);
    std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return groot[a] < groot[b]; });
    order.insert(order.begin(), root);
    return bfsLevels(tr.graph, order);
  };
  // With a device, steps 2 and 3 run frame by frame beside step 1 (MotionDevice::beginSamples ..
  // endSamples): a thread of its own takes each frame as soon as the chain below has its global
  // pose, finds its levels (the samples' residuals under it: one device call) and starts its
  // samples' fits on the device, while the chain fits the next frames on the cores. Each fit
  // reads the same poses as in the CPU's task graph, so the same poses; before, the device
  // started after the whole chain (800k humanoid: 0.06 s after the GPU's start had ended), and
  // the samples' fits took 0.054-0.063 s after it.
  struct Streamed {
    std::mutex m;
    std::condition_variable cv;
    int published = 0;  // frames of frame_order whose global pose is known
    bool stop = false;
    std::exception_ptr failed;
    std::thread thread;
    void publish(int k, bool stopping = false) {
      {
        std::lock_guard<std::mutex> lock(m);
        published = std::max(published, k);
        stop = stop || stopping;
      }
      cv.notify_one();
    }
    ~Streamed() {
      if (!thread.joinable()) return;
      publish(0, true);
      thread.join();
    }
  } streamed;
  struct RestoreThreads {  // the chain's thread count, also where it throws
    int threads = 0;
    ~RestoreThreads() {
      if (threads > 0) omp_set_num_threads(threads);
    }
  } restore;
  if (params.device) {
    SampleTrackingProblem problem;
    problem.samples = S;
    problem.icp_iterations = params.icp_iterations;
    for (int s = 0; s < S; ++s) {
      problem.source_p.push_back(src[s].p);
      problem.source_n.push_back(src[s].n);
      problem.probe_p.push_back(probe[s].p);
      problem.probe_n.push_back(probe[s].n);
    }
    problem.graph = tr.graph;
    problem.before.assign(T, -1);
    problem.two_before.assign(T, -1);
    for (int t : frame_order) {
      problem.before[t] = chain.step[t].before;
      problem.two_before[t] = chain.step[t].two_before;
    }
    problem.global = global;
    timer.lap("tracking: device problem");
    spare.release();
    // The chain leaves a core to this thread (and to the device's start before it).
    const int all_threads = omp_get_max_threads();
    if (all_threads > 2) {
      restore.threads = all_threads;
      omp_set_num_threads(all_threads - 1);
    }
    streamed.thread = std::thread([&, problem = std::move(problem)] {
      MotionDevice& device = *params.device;
      bool begun = false;
      try {
        device.beginSamples(problem);
        begun = true;
        // The frames the chain has found since the last call, in one call each: their levels
        // (one residual batch), then their fits (one kernel on a GPU: the fits of a frame alone
        // left most of the device idle, 4 ms a frame against 1 ms in a run of many frames).
        for (int k = 0; k < F;) {
          int upto;
          {
            std::unique_lock<std::mutex> lock(streamed.m);
            streamed.cv.wait(lock, [&] { return streamed.published > k || streamed.stop; });
            upto = streamed.published;
          }
          if (upto <= k) break;  // the chain failed
          ResidualBatch batch(frames, params.device);
          for (int s = 0; s < S; ++s) batch.addSource(probe[s]);
          for (int j = k; j < upto; ++j) {
            const int t = frame_order[j], motion = batch.addMotion(global[t]);
            for (int s = 0; s < S; ++s) batch.add(s, motion, t);
          }
          const std::vector<double> groot = batch.run();
          std::vector<int> ts;
          std::vector<Pose> gs;
          std::vector<std::vector<int>> ls;
          for (int j = k; j < upto; ++j) {
            const int t = frame_order[j];
            level_of[t] = levelsOf(groot.data() + static_cast<std::size_t>(j - k) * S);
            ts.push_back(t);
            gs.push_back(global[t]);
            ls.push_back(level_of[t]);
          }
          device.trackFrames(ts, gs, ls);
          k = upto;
        }
        begun = false;
        device.endSamples(tr.poses, res);
      } catch (...) {
        streamed.failed = std::current_exception();
        if (begun) {
          try {  // leaves the device as it found it; the first error is the one reported
            device.endSamples(tr.poses, res);
          } catch (...) {
          }
        }
      }
    });
  } else {
    spare.recheck();  // the device may have started meanwhile
  }
  // 1. The whole body's pose in every frame, a chain along each direction: the previous one and
  //    a constant-velocity guess, the better kept (the body's source is large enough to search its
  //    nearest points in parallel: done serially these ICPs were a quarter of the tracking on 16
  //    cores). It depends on no sample's pose.
  for (int k = 0; k < F; ++k) {
    const int t = frame_order[k];
    const int tp = chain.step[t].before, tpp = chain.step[t].two_before;
    std::vector<Pose> inits{global[tp]};
    if (tpp >= 0) inits.push_back(constantVelocity(global[tp], global[tpp]));
    const std::vector<Pose> cands =
        icpFromStarts(whole, inits, frames[t], 30, 10.0 * frames[t].spacing, kParallelWholeBody);
    const std::vector<double> r = residualsOf(whole, cands, frames[t], kParallelWholeBody);
    double best = std::numeric_limits<double>::max();
    Pose pick = global[t];
    for (std::size_t c = 0; c < cands.size(); ++c)
      if (r[c] < best) best = r[c], pick = cands[c];
    global[t] = pick;
    if (params.device) streamed.publish(k + 1);
  }
  if (params.device) {
    if (restore.threads > 0) omp_set_num_threads(std::exchange(restore.threads, 0));
    timer.lap("tracking: global poses (levels and sample poses beside)");
    if (before_poses) before_poses();
    streamed.thread.join();
    if (streamed.failed) std::rethrow_exception(streamed.failed);
    if (progress) progress->update(static_cast<std::size_t>(F));
    timer.lap("tracking: sample poses, after the global poses");
  } else {
    timer.lap("tracking: global poses");
    spare.recheck();
    // 2. The samples' residuals under the global poses over all (frame, sample) pairs, then each
    //    frame's levels: a loop over the 47 frames alone left 15 threads with 3 or 4 frames each.
    std::vector<std::vector<double>> groots(F, std::vector<double>(S));
#pragma omp parallel
    {
#pragma omp for schedule(dynamic, 64)
      for (long x = 0; x < static_cast<long>(F) * S; ++x) {
        const int k = static_cast<int>(x / S), s = static_cast<int>(x % S), t = frame_order[k];
        groots[k][s] = residual(probe[s], global[t], frames[t]);
      }
#pragma omp for schedule(dynamic, 1)
      for (int k = 0; k < F; ++k) level_of[frame_order[k]] = levelsOf(groots[k].data());
    }
    timer.lap("tracking: levels");
    spare.release();
    // 3. Every (frame, sample) pose, each as soon as its own poses in the two frames before and
    //    its neighbours' of earlier levels in the same frame are known (a task graph: the levels
    //    of a frame, one after the other, left most of 16 cores waiting on their narrow first
    //    levels). Task k * S + s is sample s in frame_order[k].
    std::vector<std::vector<int>> successors;
    std::vector<long> priority;
    frameTaskGraph(
        chain, tr.graph, [&](int t, int s) { return level_of[t][s]; }, successors, priority);
    std::vector<int> left(F, S);
    int frames_done = 0;
    auto solve = [&](int task) {
      const int k = task / S, s = task % S, t = frame_order[k];
      const int tp = chain.step[t].before, tpp = chain.step[t].two_before;
      const Frame& f = frames[t];
      const std::vector<int>& level = level_of[t];
      std::vector<Pose>& pose = tr.poses[t];
      // The starts: the previous pose, the body's motion since the previous frame applied to it, a
      // constant-velocity guess, and the poses of the neighbours of earlier levels. Never the
      // global pose itself: it puts a sample where its part was in the reference frame relative to
      // the body, which in a walk is where the other leg is half a stride later; both legs fit
      // there equally well, and samples of a right shin continued on the left one (humanoid, 4000
      // points, seed 12: 28 of 31 samples).
      // (Composed in icp_step's arithmetic, as the tracking's device composes them.)
      std::vector<Pose> cands{tr.poses[tp][s],
                              compose(compose(global[t], inverse(global[tp])), tr.poses[tp][s])};
      if (tpp >= 0)
        cands.push_back(
            compose(compose(tr.poses[tp][s], inverse(tr.poses[tpp][s])), tr.poses[tp][s]));
      for (int o : tr.graph[s])
        if (level[o] < level[s]) cands.push_back(pose[o]);
      // Score every start cheaply, refine the two best: ICP from all would triple the cost for the
      // same answer.
      std::vector<std::pair<double, int>> score;
      for (std::size_t c = 0; c < cands.size(); ++c)
        score.push_back({residual(probe[s], cands[c], f), static_cast<int>(c)});
      std::stable_sort(score.begin(), score.end());
      double best = std::numeric_limits<double>::max();
      Pose best_pose = cands[score[0].second];
      for (std::size_t c = 0; c < std::min<std::size_t>(2, score.size()); ++c) {
        const Pose cand =
            icp(src[s], cands[score[c].second], f, params.icp_iterations, 4.0 * f.spacing);
        const double r = residual(src[s], cand, f);
        if (r < best) best = r, best_pose = cand;
      }
      pose[s] = best_pose;
      res[t][s] = best;
    };
    if (before_poses) before_poses();
    runTaskGraph(successors, priority, solve, [&](int task) {
      if (--left[task / S] == 0 && progress)
        progress->update(static_cast<std::size_t>(++frames_done));
    });
    timer.lap("tracking: sample poses");
  }
  for (int t : frame_order)
    tr.residual[t] = std::accumulate(res[t].begin(), res[t].end(), 0.0) / S;
  tr.positions.resize(T);
  for (int t = 0; t < T; ++t) {
    tr.positions[t].resize(3, S);
    for (int s = 0; s < S; ++s) tr.positions[t].col(s) = tr.poses[t][s] * p0.col(s);
  }
  if (progress)
    progress->end(std::to_string(S) + " samples" +
                  (params.device ? ", poses fitted on " + params.device->name() : std::string()));
  return tr;
}

/** Squared clipped surface distance of one reference point under a motion, summed over frames
 * (in spacings^2). */
double pointCost(const pcl::PointNormal& q, const std::vector<Frame>& frames, int ref,
                 const std::vector<Pose>& motion) {
  const double p[3] = {q.x, q.y, q.z}, n[3] = {q.normal_x, q.normal_y, q.normal_z};
  double sum = 0.0;
  for (std::size_t t = 0; t < frames.size(); ++t) {
    if (static_cast<int>(t) == ref) continue;
    const icp_step::Rigid m = toRigid(motion[t]);
    double y[3], r[3];
    icp_step::apply(m, p, y);
    icp_step::rotate(m, n, r);
    sum += surfaceError(y, r, frames[t]);
  }
  return sum;
}

/** Moves reference points between touching parts: a point takes, among the labels present in
 * its surface neighbourhood, the part whose motion keeps the neighbourhood on the surface best
 * over all frames (costs averaged over the point and its surface neighbours: one point's residual
 * is noisy). Labels < 0 and parts without a motion are left alone. Returns the points changed. */
/** Point costs (pointCost) of many (reference point, motion) pairs, computed at once: on the
 * device when there is one (motion_device.h), else in one parallel loop; the same values either
 * way. Add the motions (one pose per frame) and the jobs; run() returns one cost per job, in job
 * order. */
class PointCostBatch {
 public:
  PointCostBatch(const Cloud& rc, const std::vector<Frame>& frames, int ref, MotionDevice* device)
      : rc_(rc), frames_(frames), ref_(ref), device_(device) {}
  int addMotion(const std::vector<Pose>* motion) {
    motions_.push_back(motion);
    return static_cast<int>(motions_.size()) - 1;
  }
  void add(int point, int motion) { jobs_.push_back({point, motion}); }

  std::vector<double> run() const {
    std::vector<double> out(jobs_.size(), 0.0);
    if (device_ && !jobs_.empty()) {
      PointCostJobs d;
      d.reference_frame = ref_;
      std::vector<int> row(rc_.size(), -1);
      for (const PointCostJobs::Job& j : jobs_) {
        int& r = row[static_cast<std::size_t>(j.point)];
        if (r < 0) {
          r = static_cast<int>(d.points.size() / 6);
          const auto& q = rc_[static_cast<std::size_t>(j.point)];
          d.points.insert(d.points.end(), {q.x, q.y, q.z, q.normal_x, q.normal_y, q.normal_z});
        }
        d.jobs.push_back({r, j.motion});
      }
      for (const std::vector<Pose>* m : motions_) {
        if (m->size() != frames_.size()) throw Error("motion tracking: a motion without a frame");
        for (const Pose& p : *m) appendMotion(p, d.motions);
      }
      device_->pointCosts(d, out);
      return out;
    }
    detail::eachIndex(static_cast<long>(jobs_.size()), 32, [&](long j) {
      out[j] = pointCost(rc_[static_cast<std::size_t>(jobs_[j].point)], frames_, ref_,
                         *motions_[jobs_[j].motion]);
    });
    return out;
  }

 private:
  const Cloud& rc_;
  const std::vector<Frame>& frames_;
  int ref_;
  MotionDevice* device_;
  std::vector<const std::vector<Pose>*> motions_;
  std::vector<PointCostJobs::Job> jobs_;
};

int reassignByMotion(const Cloud& rc, const std::vector<std::vector<int>>& surface,
                     const std::vector<Frame>& frames, int ref,
                     const std::vector<std::vector<Pose>>& motion, std::vector<int>& label,
                     MotionDevice* device) {
  const int n = static_cast<int>(rc.size());
  // The points side by side, each writing its own entries (serially these loops were most of a
  // round's host time beside the device's point costs: 4 ms at 800k).
  // cand[i]: the labels around labelled point i (its own and its surface neighbours' that have a
  // motion), ascending and once each, where there are two or more.
  std::vector<std::vector<int>> cand(n);
#pragma omp parallel if (!omp_in_parallel())
  {
    std::vector<int> c;  // one buffer per thread instead of a std::set per point
#pragma omp for schedule(dynamic, 256)
    for (int i = 0; i < n; ++i) {
      if (label[i] < 0) continue;
      c.assign(1, label[i]);
      for (int j : surface[i])
        if (label[j] >= 0 && !motion[label[j]].empty()) c.push_back(label[j]);
      std::sort(c.begin(), c.end());
      c.erase(std::unique(c.begin(), c.end()), c.end());
      if (c.size() >= 2) cand[i] = c;
    }
  }
  // need[j]: the labels point j is scored under, for itself and for the points beside it: its own
  // candidates and those of the points whose neighbour it is. The surface graph is symmetric
  // (SampleTracks::surface), so those are j's own neighbours.
  std::vector<std::vector<int>> need(n);
#pragma omp parallel for schedule(dynamic, 256) if (!omp_in_parallel())
  for (int j = 0; j < n; ++j) {
    std::vector<int>& nd = need[j];
    nd = cand[j];
    for (int i : surface[j]) nd.insert(nd.end(), cand[i].begin(), cand[i].end());
    std::sort(nd.begin(), nd.end());
    nd.erase(std::unique(nd.begin(), nd.end()), nd.end());
  }
  std::vector<std::vector<std::pair<int, double>>> cost(n);
  PointCostBatch batch(rc, frames, ref, device);
  std::vector<int> motion_id(motion.size(), -1);
  for (int j = 0; j < n; ++j) {
    const auto& nd = need[j];
    for (int g : nd) {
      if (motion_id[g] < 0) motion_id[g] = batch.addMotion(&motion[g]);
      batch.add(j, motion_id[g]);
    }
  }
  const std::vector<double> costs = batch.run();
  std::size_t next = 0;
  for (int j = 0; j < n; ++j)
    for (int g : need[j]) cost[j].push_back({g, costs[next++]});
  auto costOf = [&](int j, int g) {
    for (const auto& [h, c] : cost[j])
      if (h == g) return c;
    return -1.0;
  };
  std::vector<int> out(label);
  int changed = 0;
#pragma omp parallel for schedule(dynamic, 64) reduction(+ : changed)
  for (int i = 0; i < n; ++i) {
    if (cand[i].empty()) continue;
    double best = std::numeric_limits<double>::max();
    int pick = label[i];
    for (int g : cand[i]) {
      double sum = costOf(i, g);
      int cnt = 1;
      for (int j : surface[i]) {
        const double c = costOf(j, g);
        if (c >= 0.0) sum += c, ++cnt;
      }
      const double avg = sum / cnt;
      if (avg < best - 1e-9 || (std::abs(avg - best) <= 1e-9 && g == label[i]))
        best = avg, pick = g;
    }
    if (pick != label[i]) out[i] = pick, ++changed;
  }
  label.swap(out);
  return changed;
}

/** A part held by fewer than max(5, 0.2%) of the reference points is a remnant, not a part: each
 * of its points takes the label of the first of its 16 nearest reference points that belongs to
 * a real part (it keeps its label where none does). Labels < 0 are left alone. Returns whether
 * any point changed. */
bool absorbRemnants(const Frame& ref_frame, std::vector<int>& label) {
  const Cloud& rc = *ref_frame.cloud;
  const int n0 = static_cast<int>(rc.size());
  const int min_points = std::max(5, n0 / 500);
  const int labels = label.empty() ? 0 : *std::max_element(label.begin(), label.end()) + 1;
  std::vector<int> count(std::max(labels, 0), 0);
  for (int l : label)
    if (l >= 0) ++count[l];
  auto real = [&](int l) { return l >= 0 && count[l] >= min_points; };
  const int kk = std::min(16, n0);
  std::vector<int> next(label);
  std::vector<int> idx;
  std::vector<float> d2;
  bool any = false;
  for (int i = 0; i < n0; ++i) {
    if (label[i] < 0 || real(label[i])) continue;
    ref_frame.tree.nearestKSearch(rc[i], kk, idx, d2);
    for (int j : idx)
      if (real(label[j])) {
        next[i] = label[j];
        any = true;
        break;
      }
  }
  label.swap(next);
  return any;
}

/** An s-t graph and its minimum cut by Boost's Boykov-Kolmogorov max-flow (the same algorithm as
 * PCL's grabcut::BoykovKolmogorov, which this used before: that one lives in libpcl_segmentation,
 * whose dependencies - PCL's features, filters, sample consensus, ml and search libraries - took
 * most of a program's start, relocating their symbols before main: `animseg --help` 0.17-0.23 s
 * on the H200 machine, docs/gpu.md, stop 52). A node is in the sink's tree when it can still
 * reach the sink through the residual graph: the same set for every maximum flow. */
class MinCutGraph {
 public:
  explicit MinCutGraph(std::size_t nodes) : g_(nodes) {}
  /** An edge u -> v of capacity `cap`, with its reverse of capacity 0. */
  void addEdge(int u, int v, double cap) {
    const auto uv = boost::add_edge(u, v, g_).first;
    const auto vu = boost::add_edge(v, u, g_).first;
    g_[uv].capacity = cap;
    g_[vu].capacity = 0.0;
    g_[uv].reverse = vu;
    g_[vu].reverse = uv;
  }
  void solve(int source, int sink) {
    boost::boykov_kolmogorov_max_flow(
        g_, boost::get(&Edge::capacity, g_), boost::get(&Edge::residual, g_),
        boost::get(&Edge::reverse, g_), boost::get(&Node::predecessor, g_),
        boost::get(&Node::color, g_), boost::get(&Node::distance, g_),
        boost::get(boost::vertex_index, g_), source, sink);
  }
  /** After solve(): Boost colours the sink's tree white, the source's black, free nodes gray. */
  bool inSinkTree(int u) const { return g_[u].color == boost::white_color; }

 private:
  using Traits = boost::adjacency_list_traits<boost::vecS, boost::vecS, boost::directedS>;
  struct Node {
    boost::default_color_type color = boost::gray_color;
    long distance = 0;
    Traits::edge_descriptor predecessor;
  };
  struct Edge {
    double capacity = 0.0;
    double residual = 0.0;
    Traits::edge_descriptor reverse;
  };
  boost::adjacency_list<boost::vecS, boost::vecS, boost::directedS, Node, Edge> g_;
};
#pragma GCC diagnostic pop

}  // namespace

namespace detail {

int alphaExpansions(const std::vector<std::vector<int>>& cand,
                    const std::vector<std::vector<double>>& unary,
                    const std::vector<std::vector<std::pair<int, double>>>& edges,
                    std::vector<int>& label, bool side_by_side) {
  const int n = static_cast<int>(cand.size());
  if (unary.size() != cand.size() || edges.size() != cand.size() || label.size() != cand.size())
    throw Error(
        "alpha expansions: one candidate list, unary list, edge list and label per point "
        "expected");
  for (int i = 0; i < n; ++i) {
    if (cand[i].size() >= 2 && unary[i].size() != cand[i].size())
      throw Error("alpha expansions: one unary cost per candidate expected");
    for (int l : cand[i])
      if (l < 0) throw Error("alpha expansions: a negative candidate label");
    for (const auto& e : edges[i])
      if (e.first <= i || e.first >= n)
        throw Error("alpha expansions: an edge must go to a later point of the set");
  }
  auto unaryOf = [&](int i, int l) {
    const auto it = std::lower_bound(cand[i].begin(), cand[i].end(), l);
    return unary[i][it - cand[i].begin()];
  };
  std::vector<int> labels_present;
  for (int i = 0; i < n; ++i)
    if (cand[i].size() >= 2)
      labels_present.insert(labels_present.end(), cand[i].begin(), cand[i].end());
  std::sort(labels_present.begin(), labels_present.end());
  labels_present.erase(std::unique(labels_present.begin(), labels_present.end()),
                       labels_present.end());
  // The points that may take each label (in point order), and the edges stored at a lower end:
  // an expansion visits only the points that may take alpha and the edges that touch them.
  std::vector<std::vector<int>> may_take(labels_present.empty() ? 0 : labels_present.back() + 1);
  for (int i = 0; i < n; ++i)
    if (cand[i].size() >= 2)
      for (int l : cand[i]) may_take[l].push_back(i);
  std::vector<std::vector<int>> lower_ends(n);  // for each point, the i < it of its edges
  for (int i = 0; i < n; ++i)
    for (const auto& e : edges[i]) lower_ends[e.first].push_back(i);
  // An expansion of alpha reads the labels of the points that may take it and of the other ends
  // of their edges, and writes only the former. Two expansions of which neither writes what the
  // other reads give the same labels in either order, or side by side. So each cycle's
  // expansions are a task graph (runTaskGraph): an expansion waits for every earlier one of the
  // cycle that it conflicts with, those of other parts of the body run side by side, each with
  // its own node numbering. The same labels as the expansions one after the other (800k
  // humanoid: 23 labels, a longest chain of 5; the expansions 0.023-0.036 -> 0.014-0.019 s).
  // Written by us: the conflicts are specific to this loop.
  const int nl = static_cast<int>(labels_present.size());
  std::vector<int> slot(may_take.size(), -1);
  for (int a = 0; a < nl; ++a) slot[labels_present[a]] = a;
  std::vector<char> conflict(static_cast<std::size_t>(nl) * nl, 0);
  for (int i = 0; i < n; ++i) {
    if (cand[i].size() < 2) continue;
    auto mark = [&](int j) {
      if (cand[j].size() < 2) return;
      for (int a : cand[i])
        for (int b : cand[j])
          if (a != b) {
            conflict[static_cast<std::size_t>(slot[a]) * nl + slot[b]] = 1;
            conflict[static_cast<std::size_t>(slot[b]) * nl + slot[a]] = 1;
          }
    };
    mark(i);
    for (const auto& e : edges[i]) mark(e.first);
  }
  // Each expansion's later conflicting ones, and the longest chain (what the timing reports).
  std::vector<std::vector<int>> successors(nl);
  std::vector<long> priority(nl);
  std::vector<int> depth(nl, 1);
  int longest = nl > 0 ? 1 : 0;
  for (int a = 0; a < nl; ++a) {
    priority[a] = a;
    for (int b = 0; b < a; ++b)
      if (conflict[static_cast<std::size_t>(a) * nl + b]) {
        successors[b].push_back(a);
        depth[a] = std::max(depth[a], depth[b] + 1);
      }
    longest = std::max(longest, depth[a]);
  }
  // One expansion of alpha with the thread's own node numbering (-1 outside, as it is left);
  // whether a label changed.
  auto expand = [&](int alpha, std::vector<int>& node, std::vector<int>& touched) {
    bool changed_any = false;
    // Nodes: points that may take alpha and do not hold it.
    std::vector<int> members;
    for (int i : may_take[alpha]) {
      if (label[i] != alpha) {
        node[i] = static_cast<int>(members.size());
        members.push_back(i);
      }
    }
    if (members.empty()) return false;
    // The points whose edges (stored at their lower end) touch a member, in point order: the
    // edges visited in the same order as a scan over all points, which skips the others.
    touched.clear();
    for (int i : members) {
      touched.push_back(i);
      for (int lo : lower_ends[i]) touched.push_back(lo);
    }
    std::sort(touched.begin(), touched.end());
    touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
    const int m = static_cast<int>(members.size());
    std::vector<double> e0(m), e1(m);
    for (int k = 0; k < m; ++k) {
      e0[k] = unaryOf(members[k], label[members[k]]);
      e1[k] = unaryOf(members[k], alpha);
    }
    // The s-t graph: nodes 0..m-1, the source m, the sink m + 1; every edge with its reverse.
    MinCutGraph graph(static_cast<std::size_t>(m) + 2);
    const int source = m, sink = m + 1;
    for (int i : touched)
      for (const auto& [j, w] : edges[i]) {
        const int ni = node[i], nj = node[j];
        if (ni < 0 && nj < 0) continue;
        if (ni >= 0 && nj >= 0) {
          // E(xi, xj), x = 1: take alpha. A = E00, B = E01, C = E10, D = E11 = 0.
          const double A = label[i] != label[j] ? w : 0.0;
          const double B = w;  // label[i] != alpha
          const double C = w;  // label[j] != alpha
          e1[ni] += C - A;
          e1[nj] += -C;  // D - C
          graph.addEdge(ni, nj, B + C - A);
        } else if (ni >= 0) {
          e0[ni] += label[i] != label[j] ? w : 0.0;
          e1[ni] += alpha != label[j] ? w : 0.0;
        } else {
          e0[nj] += label[j] != label[i] ? w : 0.0;
          e1[nj] += alpha != label[i] ? w : 0.0;
        }
      }
    for (int k = 0; k < m; ++k) {
      const double lo = std::min(e0[k], e1[k]);
      // Cut s->k when k takes alpha (sink side), k->t when it keeps its label.
      if (e1[k] - lo > 0.0) graph.addEdge(source, k, e1[k] - lo);
      if (e0[k] - lo > 0.0) graph.addEdge(k, sink, e0[k] - lo);
    }
    graph.solve(source, sink);
    for (int k = 0; k < m; ++k)
      if (graph.inSinkTree(k)) label[members[k]] = alpha, changed_any = true;
    for (int i : members) node[i] = -1;
    return changed_any;
  };
  std::vector<std::vector<int>> node(std::max(1, omp_get_max_threads()));
  std::vector<std::vector<int>> touched(node.size());
  std::vector<char> changed(nl, 0);
  for (int cycle = 0; cycle < 3; ++cycle) {
    std::fill(changed.begin(), changed.end(), 0);
    auto run = [&](int a) {
      const std::size_t me = static_cast<std::size_t>(omp_get_thread_num()) % node.size();
      if (node[me].empty()) node[me].assign(n, -1);
      changed[a] = expand(labels_present[a], node[me], touched[me]);
    };
    if (side_by_side && nl > 1)
      runTaskGraph(successors, priority, run, [](int) {});
    else
      for (int a = 0; a < nl; ++a) run(a);
    if (std::find(changed.begin(), changed.end(), 1) == changed.end()) break;
  }
  return longest;
}

}  // namespace detail

namespace {

/** Places the borders between parts by alpha-expansion (Boykov, Veksler, Zabih 2001) on the
 * reference frame's surface graph. Energy: per point, the mean over frames of its squared surface
 * error under its part's motion (pointCost / (T - 1), spacings^2); per surface-graph edge whose
 * ends take different parts, `smooth` times a weight that is 1 on flat or convex edges and
 * exp(-(angle / kConcaveAngle)^2) on concave ones (normals converging along the edge). Where the
 * motions tell the parts apart the data term decides; where they cannot (a joint's cap, a sphere
 * about the joint, fits both bones' motions; the pieces of a capsule fit any motion that slides
 * along it) the border takes the cheapest place, which is the concave fold where one part leaves
 * the other (the minima rule of part perception), not a seam across a smooth surface. Candidate
 * parts of a point: those within `hops` edges; a point with one candidate keeps its part. Each
 * expansion is one s-t minimum cut (Boost.Graph's Boykov-Kolmogorov max-flow, MinCutGraph); three
 * sweeps over the parts at most. Returns the points that changed part. */
int reassignByGraphCut(const Cloud& rc, const std::vector<std::vector<int>>& surface,
                       const std::vector<Frame>& frames, int ref,
                       const std::vector<std::vector<Pose>>& motion, std::vector<int>& label,
                       double smooth, int hops, MotionDevice* device) {
  const int n = static_cast<int>(rc.size());
  const int T = static_cast<int>(frames.size());
  if (T < 2 || n == 0) return 0;
  detail::StageTimer timer;
  // Candidates: the parts within `hops` edges (of a point with a part), ascending. Grown as
  // bit sets, a word per 64 parts (a sorted list per point and hop, copied, appended to,
  // sorted and made unique, took 0.007-0.012 s of the 800k humanoid's run on 16 cores).
  const int nc = static_cast<int>(motion.size());
  const std::size_t words = static_cast<std::size_t>(nc + 63) / 64;
  std::vector<std::uint64_t> bits(static_cast<std::size_t>(n) * words, 0), grown(bits.size(), 0);
  std::vector<char> has(n, 0);
  for (int i = 0; i < n; ++i)
    if (label[i] >= 0 && !motion[label[i]].empty()) {
      has[i] = 1;
      bits[static_cast<std::size_t>(i) * words + label[i] / 64] |= std::uint64_t{1}
                                                                   << (label[i] % 64);
    }
  for (int h = 0; h < hops; ++h) {
#pragma omp parallel for schedule(static)
    for (int i = 0; i < n; ++i) {
      std::uint64_t* g = &grown[static_cast<std::size_t>(i) * words];
      const std::uint64_t* b = &bits[static_cast<std::size_t>(i) * words];
      std::copy(b, b + words, g);
      if (!has[i]) continue;
      for (int j : surface[i]) {
        const std::uint64_t* o = &bits[static_cast<std::size_t>(j) * words];
        for (std::size_t w = 0; w < words; ++w) g[w] |= o[w];
      }
    }
    bits.swap(grown);
  }
  std::vector<std::vector<int>> cand(n);
#pragma omp parallel for schedule(static)
  for (int i = 0; i < n; ++i)
    for (std::size_t w = 0; w < words; ++w)
      for (std::uint64_t m = bits[static_cast<std::size_t>(i) * words + w]; m; m &= m - 1)
        cand[i].push_back(static_cast<int>(64 * w) + __builtin_ctzll(m));
  timer.lap("part borders: candidates");
  // Unary costs of the candidates.
  std::vector<std::vector<double>> unary(n);
  const double inv_frames = 1.0 / (T - 1);
  PointCostBatch batch(rc, frames, ref, device);
  std::vector<int> motion_id(motion.size(), -1);
  for (int i = 0; i < n; ++i) {
    if (cand[i].size() < 2) continue;
    for (int l : cand[i]) {
      if (motion_id[l] < 0) motion_id[l] = batch.addMotion(&motion[l]);
      batch.add(i, motion_id[l]);
    }
  }
  const std::vector<double> costs = batch.run();
  std::size_t next = 0;
  for (int i = 0; i < n; ++i) {
    if (cand[i].size() < 2) continue;
    unary[i].resize(cand[i].size());
    for (std::size_t k = 0; k < cand[i].size(); ++k) unary[i][k] = inv_frames * costs[next++];
  }
  timer.lap("part borders: unary costs");
  // Edge weights (each undirected edge once, i < j).
  std::vector<std::vector<std::pair<int, double>>> edges(n);
#pragma omp parallel for schedule(dynamic, 256)
  for (int i = 0; i < n; ++i)
    for (int j : surface[i]) {
      if (j <= i) continue;
      const float fold = detail::inwardFoldCos(rc[i], rc[j]);
      double w = 1.0;
      if (fold < 1.0f) {
        const double ang = std::acos(std::clamp(static_cast<double>(fold), -1.0, 1.0));
        w = std::exp(-(ang / kConcaveAngle) * (ang / kConcaveAngle));
      }
      edges[i].push_back({j, smooth * w});
    }
  timer.lap("part borders: edges");
  const std::vector<int> before(label);
  const int chain = detail::alphaExpansions(cand, unary, edges, label, true);
  if (timer.on())
    std::fprintf(stderr, "[mean shift] part borders: expansions' longest chain %d a cycle\n",
                 chain);
  timer.lap("part borders: expansions");
  int changed = 0;
  for (int i = 0; i < n; ++i) changed += label[i] != before[i];
  return changed;
}

/** After b joined a: drops every edge that touches a or b; returns a's and b's other former
 * neighbours. */
template <class Edge>
std::set<int> detachEdges(std::map<std::pair<int, int>, Edge>& edges, int a, int b) {
  std::set<int> nbrs;
  for (auto it = edges.begin(); it != edges.end();) {
    const auto [x, y] = it->first;
    if (x == a || x == b || y == a || y == b) {
      const int o = (x == a || x == b) ? y : x;
      if (o != a && o != b) nbrs.insert(o);
      it = edges.erase(it);
    } else {
      ++it;
    }
  }
  return nbrs;
}

/** After b joined a: scores the edges between a and its former neighbours again, together:
 * `evaluate` takes the list of pairs and returns their edges (one parallel loop over all their
 * frames: a merge has a handful of neighbours and a sequence tens of frames). */
template <class Edge, class EvaluateAll>
void rewireEdgesBatch(std::map<std::pair<int, int>, Edge>& edges, int a, int b,
                      EvaluateAll evaluate) {
  std::vector<std::pair<int, int>> list;
  for (int o : detachEdges(edges, a, b)) list.push_back({std::min(a, o), std::max(a, o)});
  const std::vector<Edge> scored = evaluate(list);
  for (std::size_t i = 0; i < list.size(); ++i) edges[list[i]] = scored[i];
}

/** Sources packed once for a motion device's batches over them (motion_device.h): residuals and
 * part fits, each batch sending only its poses and jobs. The same values as residual() and
 * icp() on the cores. */
class DeviceSourceBatches {
 public:
  DeviceSourceBatches(const std::vector<Source>& sources, int iterations, MotionDevice& device)
      : device_(device) {
    for (const Source& s : sources) {
      appendPoints(s.p, s.n, scores_.points);
      scores_.source_begin.push_back(static_cast<int>(scores_.points.size() / 6));
    }
    fits_.iterations = iterations;
    fits_.points = scores_.points;
    fits_.source_begin = scores_.source_begin;
  }
  /** A source under a pose in a frame. */
  struct Item {
    int source, frame;
    Pose pose;
  };
  /** residual(source, pose, frame) of every item. */
  std::vector<double> residuals(const std::vector<Item>& items) {
    scores_.motions.clear();
    scores_.jobs.clear();
    for (std::size_t j = 0; j < items.size(); ++j) {
      appendMotion(items[j].pose, scores_.motions);
      scores_.jobs.push_back({items[j].source, static_cast<int>(j), items[j].frame});
    }
    std::vector<double> out;
    device_.residuals(scores_, out);
    if (out.size() != items.size())
      throw Error("motion method: the device returned " + std::to_string(out.size()) +
                  " residuals for " + std::to_string(items.size()));
    return out;
  }
  /** A fit: icp(source, start, frame, iterations, max_dist), kept where its residual is at most
   * r0, else the start. */
  struct Fit {
    int source, frame;
    Pose start;
    double r0, max_dist;
  };
  /** The fits' poses; with `residual`, also each pose's residual (as residuals() gives it). */
  std::vector<Pose> fits(const std::vector<Fit>& jobs, std::vector<double>* residual = nullptr) {
    fits_.motions.clear();
    fits_.jobs.clear();
    for (std::size_t j = 0; j < jobs.size(); ++j) {
      appendMotion(jobs[j].start, fits_.motions);
      fits_.jobs.push_back(
          {jobs[j].source, static_cast<int>(j), jobs[j].frame, jobs[j].r0, jobs[j].max_dist});
    }
    std::vector<double> poses;
    if (residual) {
      device_.partFitsWithResiduals(fits_, poses, *residual);
      if (residual->size() != jobs.size())
        throw Error("motion method: the device returned " + std::to_string(residual->size()) +
                    " residuals for " + std::to_string(jobs.size()) + " part fits");
    } else {
      device_.partFits(fits_, poses);
    }
    if (poses.size() != 12 * jobs.size())
      throw Error("motion method: the device returned " + std::to_string(poses.size() / 12) +
                  " part fits for " + std::to_string(jobs.size()));
    std::vector<Pose> out(jobs.size());
    for (std::size_t j = 0; j < jobs.size(); ++j) out[j] = motionAt(&poses[12 * j]);
    return out;
  }
  /** fitChainsBatched's score batch and the fits it decides in one call (scoreAndFit), icp()
   * with `max_dist` of each frame as fits() makes them. */
  ChainScoreFitResult<Pose> scoreFits(const ChainScoreFit<Pose>& batch,
                                      const std::function<double(int)>& max_dist) {
    ScoreFitJobs& sf = score_fits_;
    sf.iterations = fits_.iterations;
    if (sf.points.empty()) {
      sf.points = scores_.points;
      sf.source_begin = scores_.source_begin;
    }
    sf.motions.clear();
    sf.places.clear();
    sf.jobs.clear();
    for (const ChainScore<Pose>& x : batch.starts) appendMotion(x.pose, sf.motions);
    sf.places = batch.place;
    for (const auto& it : batch.items)
      sf.jobs.push_back({it.chain, it.frame, static_cast<int>(it.first), static_cast<int>(it.count),
                         it.base_score, it.base_place, max_dist(it.frame)});
    ChainScoreFitResult<Pose> r;
    std::vector<double> poses;
    device_.scoreAndFit(sf, r.scores, r.fitted, poses);
    if (r.scores.size() != batch.starts.size() || r.fitted.size() != batch.items.size() ||
        poses.size() != 12 * batch.items.size())
      throw Error("motion method: the device returned " + std::to_string(r.scores.size()) +
                  " scores and " + std::to_string(poses.size() / 12) + " fits for " +
                  std::to_string(batch.starts.size()) + " starts of " +
                  std::to_string(batch.items.size()) + " frames");
    r.fits.resize(batch.items.size());
    for (std::size_t j = 0; j < batch.items.size(); ++j) r.fits[j] = motionAt(&poses[12 * j]);
    return r;
  }

 private:
  MotionDevice& device_;
  ScoreFitJobs score_fits_;
  ResidualJobs scores_;
  PartFitJobs fits_;
};

/** Motions of the parts of `label` (a part per reference point, -1: none; parts 0..nc-1), tracked
 * along the sequence as an articulated body: the frames in order away from the reference, the
 * parts of a frame in breadth-first order over the part adjacency (surface-graph edges and
 * contacts across creases) from the largest part, each started from the best of `init` (its
 * motion so far), the Kabsch fit of its samples (`sample_part`: the part of each tracked sample,
 * -1: none), its previous pose, a constant-velocity guess and, for every neighbour already
 * solved in this frame, the neighbour's motion since the previous frame applied to the part (a
 * lower leg follows its thigh), then refined by ICP of up to `max_points` of its reference
 * points. Candidates are scored by their residual plus `joint_weight` per spacing that a joint
 * with a solved neighbour opens beyond kJointGap (MotionTrackingParams::joint_weight). A part
 * without points keeps the identity. */
std::vector<std::vector<Pose>> trackParts(const std::vector<Frame>& frames, const SampleTracks& tr,
                                          const std::vector<int>& label, int nc,
                                          const std::vector<std::vector<Pose>>& init,
                                          const std::vector<int>& sample_part,
                                          std::size_t max_points, double joint_weight,
                                          MotionDevice* device) {
  detail::StageTimer timer;
  const int T = static_cast<int>(frames.size());
  const int ref = tr.reference_frame;
  const Cloud& rc = *frames[ref].cloud;
  const int n0 = static_cast<int>(rc.size());
  const int S = static_cast<int>(tr.sample_points.size());
  const bool has_surface = tr.surface.size() == static_cast<std::size_t>(n0);
  std::vector<std::vector<Pose>> motion(nc, std::vector<Pose>(T, Pose::Identity()));
  std::vector<std::vector<int>> pts(nc), smp(nc);
  for (int i = 0; i < n0; ++i)
    if (label[i] >= 0) pts[label[i]].push_back(i);
  for (int s = 0; s < S; ++s)
    if (sample_part[s] >= 0) smp[sample_part[s]].push_back(s);
  std::vector<Source> src(nc);
  for (int c = 0; c < nc; ++c) src[c] = sourceOf(rc, pts[c], max_points);
  std::vector<int> by_size(nc);
  std::iota(by_size.begin(), by_size.end(), 0);
  std::stable_sort(by_size.begin(), by_size.end(),
                   [&](int x, int y) { return pts[x].size() > pts[y].size(); });
  // Part adjacency and joints: the surface graph's edges between parts; and, between parts that
  // the surface graph leaves in different connected groups, contacts across a sharp crease:
  // points within 3 spacings (of the 10 nearest) whose normals do not face each other. A
  // humanoid's pelvis, torso and head meet at such creases; without them each group was tracked
  // on its own, with no joint to hold it (8000 points, seed 3: one frame fell to ARI 0.73). Only
  // between such groups: inside one, a contact across a crease is as often a limb touching the
  // body as a joint (counting those took a quadruped's right hind lower leg, seed 7, from 0.92 to
  // 0.76 of its points under one label). Two limbs that touch face each other.
  std::vector<std::vector<int>> contact(n0);
  std::vector<std::set<int>> adj(nc);
  if (has_surface) {
    for (int i = 0; i < n0; ++i)
      for (int j : tr.surface[i])
        if (label[i] >= 0 && label[j] >= 0 && label[i] != label[j]) {
          adj[label[i]].insert(label[j]);
          contact[i].push_back(j);
        }
    // Connected groups of parts over the surface graph.
    std::vector<int> group;
    connectedComponents(adj, by_size, group);
    const double r2 =
        kContactSpacings * kContactSpacings * frames[ref].spacing * frames[ref].spacing;
    // Each point's contacts found in parallel, then taken in point order as before.
    std::vector<std::vector<int>> across_of(n0);
#pragma omp parallel
    {
      std::vector<int> idx;
      std::vector<float> d2;
#pragma omp for schedule(dynamic, 256)
      for (int i = 0; i < n0; ++i) {
        if (label[i] < 0) continue;
        frames[ref].tree.nearestKSearch(rc[i], kContactNeighbours, idx, d2);
        const Eigen::Vector3d ni(rc[i].normal_x, rc[i].normal_y, rc[i].normal_z);
        for (std::size_t k = 0; k < idx.size(); ++k) {
          const int j = idx[k];
          if (d2[k] > r2 || label[j] < 0 || group[label[j]] == group[label[i]]) continue;
          const Eigen::Vector3d nj(rc[j].normal_x, rc[j].normal_y, rc[j].normal_z);
          if (ni.dot(nj) > kFacingCos) across_of[i].push_back(j);
        }
      }
    }
    for (int i = 0; i < n0; ++i)
      for (int j : across_of[i]) {
        adj[label[i]].insert(label[j]);
        adj[label[j]].insert(label[i]);
        contact[i].push_back(j);
        contact[j].push_back(i);
      }
    for (auto& v : contact) {
      std::sort(v.begin(), v.end());
      v.erase(std::unique(v.begin(), v.end()), v.end());
    }
  }
  const std::vector<int> level = bfsLevels(adj, by_size);  // from the largest part
  // Joints: the centroid of a part's reference points that border a neighbour. A continuous
  // surface keeps the border in place, so both parts' motions carry it to about the same
  // point; a part whose motion carries it far from where its solved neighbour put it has
  // jumped to another limb of the same shape (a finger onto the thumb beside it).
  std::vector<std::vector<std::pair<int, Eigen::Vector3d>>> joints(nc);
  if (has_surface && joint_weight > 0.0) {
    std::vector<std::map<int, std::pair<int, Eigen::Vector3d>>> acc(nc);
    for (int i = 0; i < n0; ++i) {
      const int c = label[i];
      if (c < 0) continue;
      std::set<int> seen;
      for (int j : contact[i])
        if (label[j] >= 0 && label[j] != c && seen.insert(label[j]).second) {
          auto& a = acc[c][label[j]];
          if (a.first == 0) a.second.setZero();
          ++a.first;
          a.second += Eigen::Vector3d(rc[i].x, rc[i].y, rc[i].z);
        }
    }
    for (int c = 0; c < nc; ++c)
      for (const auto& [h, a] : acc[c])
        if (a.first >= kJointPoints && level[h] < level[c])
          joints[c].push_back({h, a.second / static_cast<double>(a.first)});
  }
  // Every (frame, part) motion as its own task, run as soon as the part's motion in the frame
  // before and its solved neighbours' (earlier BFS levels) in the same frame are known
  // (runTaskGraph): a frame's levels one after the other, each level's few parts in parallel,
  // left most of 16 cores waiting. Task k * nc + c is part c in frame_order[k].
  const ChainFrames chain = chainFrames(T, ref);
  const std::vector<int>& frame_order = chain.order;
  std::vector<std::vector<int>> successors;
  std::vector<long> priority;
  frameTaskGraph(
      chain, adj, [&](int, int c) { return level[c]; }, successors, priority);
  timer.lap("part motions: adjacency");
  // Task `task`'s starts: the initial motion, the previous frame's, a constant-velocity guess,
  // the samples' rigid fit, and each solved neighbour's motion since the previous frame.
  auto startsOf = [&](int task) {
    const int t = frame_order[task / nc], c = task % nc;
    const int tp = chain.step[t].before, tpp = chain.step[t].two_before;
    std::vector<Pose> st{init[c][t], motion[c][tp]};
    if (tpp >= 0) st.push_back(constantVelocity(motion[c][tp], motion[c][tpp]));
    const Eigen::Index m = static_cast<Eigen::Index>(smp[c].size());
    if (m >= 3) {
      Eigen::Matrix3Xd a(3, m), b(3, m);
      for (Eigen::Index k = 0; k < m; ++k)
        a.col(k) = tr.positions[ref].col(smp[c][k]), b.col(k) = tr.positions[t].col(smp[c][k]);
      const evaluation::RigidFit fit = evaluation::kabsch(a, b);
      Pose k = Pose::Identity();
      k.linear() = fit.rotation;
      k.translation() = fit.translation;
      st.push_back(k);
    }
    for (int h : adj[c])
      if (level[h] < level[c]) st.push_back(motion[h][t] * motion[h][tp].inverse() * motion[c][tp]);
    return st;
  };
  // A pose's score from its residual: plus joint_weight per spacing that a joint opens beyond
  // kJointGap spacings from where the solved neighbour put it.
  auto scoreWith = [&](int c, int t, const Pose& P, double res) {
    double pen = 0.0;
    for (const auto& [h, j] : joints[c])
      pen += std::max(0.0, (P * j - motion[h][t] * j).norm() / frames[t].spacing - kJointGap);
    return res + joint_weight * pen;
  };
  // The starts ranked by score (stable: the first of equal scores first).
  auto ranked = [](const std::vector<double>& scores) {
    std::vector<std::pair<double, int>> score;
    for (std::size_t k = 0; k < scores.size(); ++k)
      score.push_back({scores[k], static_cast<int>(k)});
    std::stable_sort(score.begin(), score.end());
    return score;
  };
  constexpr int kRefined = 2;    // ICP from the two best starts: from all would triple the cost
  constexpr int kIterations = 10;
  auto solve = [&](int task) {
    const int t = frame_order[task / nc], c = task % nc;
    if (pts[c].empty()) return;
    const std::vector<Pose> st = startsOf(task);
    std::vector<double> scores(st.size());
    for (std::size_t k = 0; k < st.size(); ++k)
      scores[k] = scoreWith(c, t, st[k], residual(src[c], st[k], frames[t]));
    const auto score = ranked(scores);
    // The best start, replaced by an ICP refinement of one of the two best that fits better (in
    // rank order).
    double best = score[0].first;
    motion[c][t] = st[score[0].second];
    for (std::size_t k = 0; k < std::min<std::size_t>(kRefined, score.size()); ++k) {
      const Pose refined =
          icp(src[c], st[score[k].second], frames[t], kIterations, 4.0 * frames[t].spacing);
      const double r = scoreWith(c, t, refined, residual(src[c], refined, frames[t]));
      if (r < best) best = r, motion[c][t] = refined;
    }
  };
  if (!device || omp_in_parallel()) {  // a device serves one caller at a time
    runTaskGraph(successors, priority, solve, [](int) {});
    timer.lap("part motions: fits");
    return motion;
  }
  // On the device: the tasks wave after wave (each after the tasks it depends on), each wave's
  // start scores as one batch, then the ICPs with their results' scores as another, with the
  // same arithmetic as residual() and icp() (motion_device.h): the same motions as the task
  // graph on the cores, whose 16 threads waited on the frames' chain of small fits (0.23 s of
  // critical path at 800k).
  // Under ANIMSEG_MS_TIMING the device's calls counted and timed (TimedDevice).
  std::unique_ptr<TimedDevice> timed;
  if (timer.on()) timed = std::make_unique<TimedDevice>(*device);
  DeviceSourceBatches batches(src, kIterations, timed ? *timed : *device);
  int n_waves = 0;
  for (const std::vector<int>& wave_tasks : taskWaves(successors)) {
    ++n_waves;
    std::vector<int> wave;
    for (int task : wave_tasks)
      if (!pts[task % nc].empty()) wave.push_back(task);
    const int W = static_cast<int>(wave.size());
    if (W == 0) continue;
    std::vector<std::vector<Pose>> st(W);
#pragma omp parallel for schedule(dynamic, 1) if (W > 1)
    for (int w = 0; w < W; ++w) st[w] = startsOf(wave[w]);
    std::vector<DeviceSourceBatches::Item> starts;
    for (int w = 0; w < W; ++w)
      for (const Pose& P : st[w]) starts.push_back({wave[w] % nc, frame_order[wave[w] / nc], P});
    const std::vector<double> start_res = batches.residuals(starts);
    // Each task's two best starts, refined by ICP on the device (r0 infinite: the ICP's
    // result is kept whatever its residual, as icp() returns it).
    std::vector<std::vector<std::pair<double, int>>> score(W);
    std::vector<DeviceSourceBatches::Fit> fits;
    std::vector<int> fit_of;  // the task in the wave
    for (int w = 0, at = 0; w < W; ++w) {
      const int t = frame_order[wave[w] / nc], c = wave[w] % nc;
      std::vector<double> scores(st[w].size());
      for (std::size_t k = 0; k < st[w].size(); ++k, ++at)
        scores[k] = scoreWith(c, t, st[w][k], start_res[at]);
      score[w] = ranked(scores);
      for (std::size_t k = 0; k < std::min<std::size_t>(kRefined, score[w].size()); ++k) {
        fits.push_back({c, t, st[w][score[w][k].second], std::numeric_limits<double>::infinity(),
                        4.0 * frames[t].spacing});
        fit_of.push_back(w);
      }
    }
    // The refined poses with their residuals (one call: the device scores a fit's result).
    std::vector<double> refined_res;
    const std::vector<Pose> refined = batches.fits(fits, &refined_res);
    // As solve(): the best start, replaced by a refinement that scores lower, in rank order.
    for (std::size_t f = 0, w0 = 0; w0 < static_cast<std::size_t>(W); ++w0) {
      const int w = static_cast<int>(w0);
      const int t = frame_order[wave[w] / nc], c = wave[w] % nc;
      double best = score[w][0].first;
      motion[c][t] = st[w][score[w][0].second];
      for (; f < fit_of.size() && fit_of[f] == w; ++f) {
        const double r = scoreWith(c, t, refined[f], refined_res[f]);
        if (r < best) best = r, motion[c][t] = refined[f];
      }
    }
  }
  if (timed)
    std::fprintf(stderr, "[mean shift] part motions: %d waves, %s\n", n_waves,
                 timed->report().c_str());
  timer.lap("part motions: fits (device)");
  return motion;
}

// `with_parts`, where given, is called with the parts (everything but the merges above them)
// before this returns; with `merges_device` (a device that may be called beside the caller's:
// MotionDevice::fork, or a SharedDevice), the merges above them are made meanwhile on a thread of
// their own with it (the same merges: neither side changes what the other reads).
TrajectoryClusters clusterTrajectoriesOn(
    const std::vector<Frame>& frames, const SampleTracks& tr, const MotionTrackingParams& params_in,
    const std::function<void(const TrajectoryClusters&)>& with_parts = {},
    MotionDevice* merges_device = nullptr) {
  // A copy: the merges beside the caller's work switch to their own device.
  MotionTrackingParams params = params_in;
  const int S = static_cast<int>(tr.sample_points.size());
  const int T = static_cast<int>(tr.poses.size());
  const int ref = tr.reference_frame;
  TrajectoryClusters out;
  if (S == 0) return out;
  const Cloud& rc = *frames[ref].cloud;
  std::vector<std::vector<int>> members(S);
  std::vector<std::vector<int>> points(S);  // reference points of the group (sorted)
  std::vector<std::vector<Pose>> pose(S);   // per frame
  for (int s = 0; s < S; ++s) {
    members[s] = {s};
    points[s] = tr.neighbourhoods[s];
    pose[s].resize(T);
    for (int t = 0; t < T; ++t) pose[s][t] = tr.poses[t][s];
  }
  std::vector<char> alive(S, 1);
  detail::StageTimer timer;
  std::unique_ptr<TimedDevice> timed;
  if (timer.on() && params.device) {
    timed = std::make_unique<TimedDevice>(*params.device);
    params.device = timed.get();
  }
  // A lap, with the device calls since the last one (ANIMSEG_MS_TIMING).
  auto lapD = [&](const char* what) {
    if (timed) std::fprintf(stderr, "[mean shift] (%s: %s)\n", what, timed->report().c_str());
    timer.lap(what);
  };
  // Enough points to score a pose on a part; more only costs time.
  constexpr std::size_t kSourcePoints = 32;

  // Each group's residual under its own pose, per frame (half of every evaluation's work).
  std::vector<std::vector<double>> self(S, std::vector<double>(T, 0.0));

  // Cost of merging A and B, per frame: the better of the two groups' poses, scored by the worse
  // of A's and B's surface residuals under it (each side on its own, so that a small limb cannot
  // hide in a large torso's average); worst frame. Scoring poses by surface residuals, not by
  // sample positions, makes the cost blind to a sample sliding along a capsule, which a local
  // neighbourhood cannot see. Taking the better pose makes it robust to a sample lost in a frame.
  // The edge's pose per frame is edgeOf's a's or b's (from_b[t]): both stay as they were while
  // the edge does (a merge scores every edge of its groups again).
  struct Eval {
    double cost = 0.0;
    int a = -1, b = -1;
    std::vector<char> from_b;
  };
  // The edge (a, b) from b's residuals under a's poses (b_in_a[t]) and a's under b's, given
  // both groups' own residuals (self); the reference frame's entries are not read.
  // self_a: a's own residuals (self[a], or those of a merge not made yet).
  auto edgeOf = [&](int a, int b, const double* b_in_a, const double* a_in_b,
                    const double* self_a) {
    Eval e;
    e.a = a;
    e.b = b;
    e.from_b.assign(T, 0);
    for (int t = 0; t < T; ++t) {
      if (t == ref) continue;
      const double ca = std::max(self_a[t], b_in_a[t]);
      const double cb = std::max(a_in_b[t], self[b][t]);
      e.from_b[t] = !(ca <= cb);
      e.cost = std::max(e.cost, std::min(ca, cb));
    }
    return e;
  };
  // Every residual of a batch at once (ResidualBatch: the device's when there is one).
  // With a device, each group's source and poses as its batches pack them, kept while the
  // group's points and poses stay (a merge's batch packed its neighbours' again: most of the
  // host work between phase 1's device calls).
  std::vector<std::vector<double>> packed_src(S), packed_pose(S);
  auto packInto = [&](const std::vector<int>& pts, const std::vector<Pose>& poses,
                      std::vector<double>& src_out, std::vector<double>& pose_out) {
    src_out.clear();
    const Source src = sourceOf(rc, pts, kSourcePoints);
    appendPoints(src.p, src.n, src_out);
    pose_out.clear();
    for (int t = 0; t < T; ++t) appendMotion(poses[t], pose_out);
  };
  auto pack = [&](int g) { packInto(points[g], pose[g], packed_src[g], packed_pose[g]); };
  if (params.device) {
#pragma omp parallel for schedule(dynamic, 16)
    for (int g = 0; g < S; ++g) pack(g);
  }
  // A group's source and poses into a batch: the group's own, or those of a merge not made yet.
  auto addGroupOf = [&](ResidualBatch& batch, const std::vector<int>& pts,
                        const std::vector<Pose>& poses, const std::vector<double>& src_packed,
                        const std::vector<double>& pose_packed) {
    if (batch.packed())
      return std::make_pair(batch.addPackedSource(src_packed),
                            batch.addPackedMotions(pose_packed.data(), T));
    const int src = batch.addSource(sourceOf(rc, pts, kSourcePoints));
    const int mot = batch.motions();
    for (int t = 0; t < T; ++t) batch.addMotion(poses[t]);
    return std::make_pair(src, mot);
  };
  auto addGroup = [&](ResidualBatch& batch, int g) {
    return addGroupOf(batch, points[g], pose[g], packed_src[g], packed_pose[g]);
  };
  // A merge of b into a, prepared before it is made: the merged group's poses, points and packed
  // source, the groups its edges go to (`others`: detach(a, b)'s), and once evaluated
  // (evaluateMerges) its own residuals and those edges.
  struct Prepared {
    int a = -1, b = -1;
    std::vector<Pose> pose;
    std::vector<int> points;
    std::vector<double> packed_src, packed_pose;
    std::vector<int> others;
    std::vector<double> self;
    std::vector<Eval> scored;
  };
  // After a merge into a: a's own residuals and the edges to each of `others`; several merges
  // (that neither change nor read each other's groups) in one batch, their jobs side by side.
  auto evaluateMerges = [&](std::vector<Prepared>& merges) {
    ResidualBatch batch(frames, params.device);
    {
      std::size_t groups = 0, jobs = 0;
      for (const Prepared& m : merges) {
        groups += 1 + m.others.size();
        jobs += static_cast<std::size_t>(T - 1) * (1 + 2 * m.others.size());
      }
      batch.reserve(groups, kSourcePoints, groups * T, jobs);
    }
    std::vector<std::vector<int>> self_job(merges.size()), b_job(merges.size()),
        a_job(merges.size());
    for (std::size_t k = 0; k < merges.size(); ++k) {
      const Prepared& m = merges[k];
      const std::size_t no = m.others.size();
      const auto [sa, ma] = addGroupOf(batch, m.points, m.pose, m.packed_src, m.packed_pose);
      std::vector<std::pair<int, int>> ob(no);
      for (std::size_t i = 0; i < no; ++i) ob[i] = addGroup(batch, m.others[i]);
      // Per frame but the reference: a's own residual, then b's under a's pose and a's under
      // b's for every b (jobs in the order of a loop over the frames: each frame's tree stays
      // warm).
      self_job[k].assign(T, -1);
      b_job[k].assign(no * T, -1);
      a_job[k].assign(no * T, -1);
      for (int t = 0; t < T; ++t) {
        if (t == ref) continue;
        self_job[k][t] = batch.add(sa, ma + t, t);
        for (std::size_t i = 0; i < no; ++i) {
          b_job[k][i * T + t] = batch.add(ob[i].first, ma + t, t);
          a_job[k][i * T + t] = batch.add(sa, ob[i].second + t, t);
        }
      }
    }
    const std::vector<double> r = batch.run();
    std::vector<double> b_in_a(T, 0.0), a_in_b(T, 0.0);
    for (std::size_t k = 0; k < merges.size(); ++k) {
      Prepared& m = merges[k];
      m.self.assign(T, 0.0);
      for (int t = 0; t < T; ++t) m.self[t] = t == ref ? 0.0 : r[self_job[k][t]];
      const std::size_t no = m.others.size();
      m.scored.assign(no, Eval());
      for (std::size_t i = 0; i < no; ++i) {
        for (int t = 0; t < T; ++t)
          if (t != ref) {
            b_in_a[t] = r[b_job[k][i * T + t]];
            a_in_b[t] = r[a_job[k][i * T + t]];
          }
        m.scored[i] = edgeOf(m.a, m.others[i], b_in_a.data(), a_in_b.data(), m.self.data());
      }
    }
  };
  std::map<std::pair<int, int>, Eval> edges;
  {
    // Every group's own residuals and every edge's, in one batch.
    std::vector<std::pair<int, int>> pairs;
    for (int s = 0; s < S; ++s)
      for (int o : tr.graph[s])
        if (s < o) pairs.push_back({s, o});
    ResidualBatch batch(frames, params.device);
    batch.reserve(S, kSourcePoints, static_cast<std::size_t>(S) * T,
                  (S + 2 * pairs.size()) * static_cast<std::size_t>(T - 1));
    std::vector<std::pair<int, int>> of(S);
    for (int g = 0; g < S; ++g) of[g] = addGroup(batch, g);
    for (int g = 0; g < S; ++g)
      for (int t = 0; t < T; ++t)
        if (t != ref) batch.add(of[g].first, of[g].second + t, t);
    for (const auto& [a, b] : pairs)
      for (int t = 0; t < T; ++t)
        if (t != ref) {
          batch.add(of[b].first, of[a].second + t, t);
          batch.add(of[a].first, of[b].second + t, t);
        }
    const std::vector<double> r = batch.run();
    std::size_t k = 0;
    for (int g = 0; g < S; ++g)
      for (int t = 0; t < T; ++t)
        if (t != ref) self[g][t] = r[k++];
    std::vector<double> b_in_a(T, 0.0), a_in_b(T, 0.0);
    for (const auto& [a, b] : pairs) {
      for (int t = 0; t < T; ++t)
        if (t != ref) {
          b_in_a[t] = r[k++];
          a_in_b[t] = r[k++];
        }
      edges[{a, b}] = edgeOf(a, b, b_in_a.data(), a_in_b.data(), self[a].data());
    }
  }
  // The edges by cost, for phase 1's cheapest edge: (cost, a, b) ascending is the order in which
  // a scan of `edges` (keys ascending) keeps the first least cost. Entries go stale when their
  // edge is detached or scored again; cheapestQueued drops them as they come up. Scanning
  // `edges` for every merge was most of phase 1's host time.
  using Queued = std::tuple<double, int, int>;
  std::priority_queue<Queued, std::vector<Queued>, std::greater<Queued>> queue;
  for (const auto& [key, e] : edges) queue.emplace(e.cost, key.first, key.second);
  // Each group's neighbours (the keys of `edges` by group), so that a merge detaches its edges
  // without a scan of every edge (detachEdges: as much host time as the scan for the cheapest).
  std::vector<std::set<int>> adjacent(S);
  for (const auto& [key, e] : edges) {
    adjacent[key.first].insert(key.second);
    adjacent[key.second].insert(key.first);
  }
  // detachEdges(edges, a, b) by the neighbours: the same edges erased, the same set returned.
  auto detach = [&](int a, int b) {
    std::set<int> nbrs;
    for (int x : {a, b}) {
      for (int o : adjacent[x]) {
        edges.erase({std::min(x, o), std::max(x, o)});
        if (o == a || o == b) continue;
        nbrs.insert(o);
        adjacent[o].erase(x);
      }
      adjacent[x].clear();
    }
    return nbrs;
  };
  lapD("clustering: sample edges");
  const int min_size = std::max(1, params.min_group_samples);
  // A merge of b into a, prepared (its edges not scored yet): reads a's and b's groups and
  // their neighbours' ids, changes nothing.
  auto prepare = [&](int a, int b) {
    Prepared m;
    m.a = a;
    m.b = b;
    const Eval& e = edges.at({std::min(a, b), std::max(a, b)});
    m.pose.resize(T);
    for (int t = 0; t < T; ++t) m.pose[t] = pose[e.from_b[t] ? e.b : e.a][t];
    std::set_union(points[a].begin(), points[a].end(), points[b].begin(), points[b].end(),
                   std::back_inserter(m.points));
    if (params.device) packInto(m.points, m.pose, m.packed_src, m.packed_pose);
    std::set<int> nbrs;  // detach(a, b)'s
    for (int x : {a, b})
      for (int o : adjacent[x])
        if (o != a && o != b) nbrs.insert(o);
    m.others.assign(nbrs.begin(), nbrs.end());
    return m;
  };
  // Makes an evaluated merge (b joins a).
  auto commit = [&](Prepared& m) {
    const int a = m.a, b = m.b;
    pose[a].swap(m.pose);
    members[a].insert(members[a].end(), members[b].begin(), members[b].end());
    members[b].clear();
    points[a].swap(m.points);
    points[b].clear();
    alive[b] = 0;
    if (params.device) {
      packed_src[a].swap(m.packed_src);
      packed_pose[a].swap(m.packed_pose);
    }
    const std::set<int> nbrs = detach(a, b);
    if (!std::equal(nbrs.begin(), nbrs.end(), m.others.begin(), m.others.end()))
      throw Error("motion tracking: a merge prepared ahead found other neighbours");
    self[a] = m.self;
    for (std::size_t i = 0; i < m.others.size(); ++i) {
      const int x = std::min(a, m.others[i]), y = std::max(a, m.others[i]);
      queue.emplace(m.scored[i].cost, x, y);
      edges[{x, y}] = std::move(m.scored[i]);
      adjacent[a].insert(m.others[i]);
      adjacent[m.others[i]].insert(a);
    }
  };
  auto merge = [&](int a, int b) {
    std::vector<Prepared> one{prepare(a, b)};
    evaluateMerges(one);
    commit(one.front());
  };
  auto cheapest = [&](auto pred) {
    auto best = edges.end();
    for (auto it = edges.begin(); it != edges.end(); ++it)
      if (pred(it->first) && (best == edges.end() || it->second.cost < best->second.cost))
        best = it;
    return best;
  };
  // cheapest(any) without the scan: the same edge.
  auto cheapestQueued = [&]() {
    while (!queue.empty()) {
      const auto [c, a, b] = queue.top();
      const auto it = edges.find({a, b});
      if (it != edges.end() && it->second.cost == c) return it;
      queue.pop();
    }
    return edges.end();
  };
  auto countAlive = [&]() {
    int c = 0;
    for (int s = 0; s < S; ++s) c += alive[s];
    return c;
  };
  // Phase 1: samples merge into an over-segmentation. A sample's pose comes from a small
  // neighbourhood and is noisy; the decisions near the stopping point are left to phase 2, which
  // fits whole groups.
  const int over = params.target_clusters > 0
                       ? std::max(2 * params.target_clusters, params.target_clusters + 8)
                       : 0;
  auto tinyEdge = [&](const std::pair<int, int>& e) {
    return static_cast<int>(members[e.first].size()) < min_size ||
           static_cast<int>(members[e.second].size()) < min_size;
  };
  // Merges the cheapest edge while go(past) holds, `past`: the cheapest edge costs more than
  // the threshold. `tiny_first`: past the threshold, edges of tiny groups first (see below).
  //
  // Each merge's edges are scored in a batch of their own, a device call each (phase 1 makes
  // about 1000 at 800k), so merges are prepared ahead: with the chosen merge, the next ones in
  // the queue's order that neither change nor read the groups that the merges before them
  // change, up to max_ahead, in one batch. A merge made next is then taken as evaluated: its
  // groups, their neighbours and its edge are the same as when it was prepared, so the same scores.
  // The choice of each merge is made as before (the queue, `go`, the tiny edges), and where another
  // edge comes first (one of a merge's new edges is cheaper), the ones prepared are dropped.
  // At 800k: 859 merges in 255 batches (max_ahead 4: 315, 16: 234); phase 1 on the H100 0.073
  // -> 0.065 s (medians of 12 interleaved runs each). Only with a device, whose batch costs
  // about a call whatever its size: on the CPU every prepared merge's jobs cost their time
  // (phase 1 on 2 cores 2.0 s without, 3.3 s with). Written by us: the speculation is specific
  // to this greedy merging.
  const int max_ahead = params.device ? 8 : 1;
  constexpr int kLookAhead = 64;
  int merges_made = 0, batches = 0;
  // Appends to `ahead` (its first merge chosen) the merges that may follow it (see above).
  auto prepareAhead = [&](std::vector<Prepared>& ahead) {
    std::set<int> changed{ahead[0].a, ahead[0].b};
    std::vector<Queued> popped;
    while (!queue.empty() && static_cast<int>(ahead.size()) < max_ahead &&
           static_cast<int>(popped.size()) < kLookAhead) {
      popped.push_back(queue.top());
      queue.pop();
      const auto [c, x, y] = popped.back();
      const auto it = edges.find({x, y});
      if (it == edges.end() || it->second.cost != c) continue;  // stale
      if (x == ahead[0].a && y == ahead[0].b) continue;         // the chosen one
      // An edge of a group merged before it goes with that merge.
      if (changed.count(x) || changed.count(y)) continue;
      // One that reads a changed group is scored after it: none can be prepared past it.
      bool reads = false;
      for (int g : {x, y})
        for (int o : adjacent[g]) reads = reads || changed.count(o) > 0;
      if (reads) break;
      ahead.push_back(prepare(x, y));
      changed.insert(x);
      changed.insert(y);
    }
    for (const Queued& q : popped) queue.push(q);
  };
  auto mergeWhile = [&](auto go, bool tiny_first) {
    std::vector<Prepared> ahead;  // evaluated, to be made in order from ahead[next]
    std::size_t next = 0;
    while (!edges.empty()) {
      auto best = cheapestQueued();
      const bool past = best->second.cost > 0.5 * params.threshold;
      if (!go(past)) break;
      bool tiny = false;
      if (tiny_first && past) {
        const auto t = cheapest(tinyEdge);
        if (t != edges.end()) best = t, tiny = true;
      }
      const auto [a, b] = best->first;
      ++merges_made;
      if (next < ahead.size() && ahead[next].a == a && ahead[next].b == b) {
        commit(ahead[next++]);
        continue;
      }
      ahead.clear();
      next = 0;
      ahead.push_back(prepare(a, b));
      if (!tiny) prepareAhead(ahead);
      evaluateMerges(ahead);
      ++batches;
      commit(ahead[next++]);
    }
  };
  // Tiny groups (a lost sample or two) join their cheapest neighbour whatever the cost.
  auto joinTiny = [&]() {
    for (;;) {
      const auto best = cheapest(tinyEdge);
      if (best == edges.end()) break;
      const auto [a, b] = best->first;
      merge(a, b);
    }
  };
  if (params.target_clusters > 0) {
    // With a target, phase 1 stops at `over` groups, tiny ones counted. Where most of them were
    // tiny, their joins left fewer groups than the target (humanoid, 8000 points, seed 5, 500
    // samples, --parts 15: 30 groups, 25 of them single samples, 5 after their joins, 4 parts in
    // the end). Then the merges past the threshold are made again with the tiny groups joining
    // first, so that they do not take real groups' places. Only then: in the sweeps at the
    // default sample counts, joining them first throughout moved every run (means about the
    // same, fingers of the hand worse). The merges up to the threshold are the same either way,
    // so the state is kept from there (800k, --parts 15: 228 edges, 1.5 ms to copy on 2 cores,
    // against 1 905 edges and 6.7 ms at the start of phase 1).
    auto above = [&](bool) { return countAlive() > over; };
    mergeWhile([&](bool past) { return !past && countAlive() > over; }, false);
    const auto saved = std::make_tuple(members, points, pose, alive, self, edges, queue, adjacent,
                                       packed_src, packed_pose);
    mergeWhile(above, false);
    joinTiny();
    if (countAlive() < params.target_clusters) {
      if (timer.on())
        std::fprintf(stderr, "[mean shift] phase 1 again, tiny groups first (%d groups)\n",
                     countAlive());
      std::tie(members, points, pose, alive, self, edges, queue, adjacent, packed_src,
               packed_pose) = saved;
      mergeWhile(above, true);
      joinTiny();
    }
  } else {
    mergeWhile([](bool past) { return !past; }, false);
    joinTiny();
  }

  if (timer.on())
    std::fprintf(stderr, "[mean shift] phase 1: %d merges in %d batches\n", merges_made, batches);
  lapD("clustering: phase 1 merges");
  // Phase 2: the groups as whole parts. Each group's points are the geodesic cells of its samples
  // (disjoint), its motion per frame is refit by ICP of the whole group (far better conditioned
  // than a sample's neighbourhood), and the cost of merging A and B is the worst frame's residual
  // of the worse side under ONE motion fitted to A u B: "can a single rigid motion explain both".
  std::vector<int> roots;
  for (int s = 0; s < S; ++s)
    if (alive[s]) roots.push_back(s);
  std::sort(roots.begin(), roots.end(), [&](int x, int y) {
    return *std::min_element(members[x].begin(), members[x].end()) <
           *std::min_element(members[y].begin(), members[y].end());
  });
  const int G = static_cast<int>(roots.size());
  std::vector<int> gid(S, -1);
  for (int g = 0; g < G; ++g)
    for (int s : members[roots[g]]) gid[s] = g;
  std::vector<std::vector<int>> gpts(G);
  const int n0 = static_cast<int>(rc.size());
  if (tr.owner.size() == static_cast<std::size_t>(n0)) {
    for (int i = 0; i < n0; ++i)
      if (tr.owner[i] >= 0) gpts[gid[tr.owner[i]]].push_back(i);
  }
  for (int g = 0; g < G; ++g)
    if (gpts[g].empty()) gpts[g] = points[roots[g]];
  std::vector<std::vector<Pose>> gpose(G);
  for (int g = 0; g < G; ++g) gpose[g] = pose[roots[g]];

  constexpr std::size_t kPartPoints = 96;
  constexpr int kPartIcp = 8;
  // One motion per frame for a point set: from the best of the given starts, ICP, the better of
  // start and result kept.
  // The motions of several point sets (fitAlongChain for each): pts[c], with the starts ia[c]
  // and ib[c] (null: none). Frames in order away from the reference, so that the fit of the
  // previous frame is a start too: a part that a sample lost in one frame is found again from its
  // own motion. The starts of frame t: ia[t], the previous frame's fit, ib[t], a constant-velocity
  // guess. With many more sets than threads each is a serial chain and the sets run side by side;
  // otherwise all the sets' frames run side by side (fitAlongChains: the same fits, more work,
  // but a merge's or a dissolve's one to three parts keep 16 threads busy).
  // Where fitParts' time goes on a device (ANIMSEG_MS_TIMING): its calls, and in them the time
  // inside its batches (scores and fits: packing them and the device's calls), the rest being
  // the chains' own bookkeeping (fitChainsBatched) and the sources.
  struct PartFitTally {
    int calls = 0, chains = 0;
    double seconds = 0.0;
    BatchTally batches;
  } part_tally;
  auto reportPartFits = [&](const char* what) {
    if (timer.on() && params.device)
      std::fprintf(stderr,
                   "[mean shift] %s: %d part fit calls (%d chains), %.3f s, %.3f s of it in the "
                   "batches\n",
                   what, part_tally.calls, part_tally.chains, part_tally.seconds,
                   part_tally.batches.seconds);
    part_tally = PartFitTally();
  };
  // Whether fitParts runs on the device (a device serves one caller at a time, so not inside a
  // parallel region).
  auto partsOnDevice = [&] { return params.device && !omp_in_parallel(); };
  // `optional` (on a device): the last chains are optional (fitChainsBatched), `complete` says
  // which chains' fits are final.
  auto fitParts = [&](const std::vector<const std::vector<int>*>& pts,
                      const std::vector<const std::vector<Pose>*>& ia,
                      const std::vector<const std::vector<Pose>*>& ib, int optional = 0,
                      std::vector<char>* complete = nullptr) {
    struct Tally {  // the call's time, whichever way it returns
      PartFitTally& t;
      std::chrono::steady_clock::time_point t0;
      ~Tally() {
        t.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      }
    } tally{part_tally, std::chrono::steady_clock::now()};
    const int C = static_cast<int>(pts.size());
    ++part_tally.calls;
    part_tally.chains += C;
    std::vector<Source> src(C);
    for (int c = 0; c < C; ++c) src[c] = sourceOf(rc, *pts[c], kPartPoints);
    auto starts = [&](int c, int t, const ChainStep& step, const std::vector<Pose>* fit) {
      std::vector<ChainStart<Pose>> s{{(*ia[c])[t], false}};
      const int tp = step.before, tpp = step.two_before;
      if (fit) s.push_back({(*fit)[tp], true});
      if (ib[c]) s.push_back({(*ib[c])[t], false});
      if (fit && tpp >= 0) s.push_back({constantVelocity((*fit)[tp], (*fit)[tpp]), true});
      return s;
    };
    auto score = [&](int c, int t, const Pose& P) { return residual(src[c], P, frames[t]); };
    // ICP; the better of start and result kept.
    auto fitFrom = [&](int c, int t, const Pose& init, double r0) {
      const Pose cand = icp(src[c], init, frames[t], kPartIcp, 4.0 * frames[t].spacing);
      return residual(src[c], cand, frames[t]) <= r0 ? cand : init;
    };
    auto same = [](const Pose& p, const Pose& q) { return p.matrix() == q.matrix(); };
    if (!partsOnDevice()) {
      if (complete) complete->assign(static_cast<std::size_t>(C), 1);
      return fitChains(C, T, ref, Pose(Pose::Identity()), starts, score, fitFrom, same);
    }
    // On the device: the same steps with the fits in batches (fitChainsBatched), the sources
    // packed once; the same poses.
    DeviceSourceBatches batches(src, kPartIcp, *params.device);
    auto fitBatch = [&](const std::vector<ChainFit<Pose>>& jobs) {
      std::vector<DeviceSourceBatches::Fit> fits;
      for (const ChainFit<Pose>& j : jobs)
        fits.push_back({j.chain, j.frame, j.start, j.score, 4.0 * frames[j.frame].spacing});
      return batches.fits(fits);
    };
    // The starts' scores on the device too: residual batches, the same values as residual(),
    // over the same packed sources. Even a handful: scoring those on the cores instead (under 64)
    // was slower (mean-shift stage 1.11 s against 1.06 s at 800k, median of six).
    auto scoreBatch = [&](const std::vector<ChainScore<Pose>>& items) {
      std::vector<DeviceSourceBatches::Item> list;
      for (const ChainScore<Pose>& x : items) list.push_back({x.chain, x.frame, x.pose});
      return batches.residuals(list);
    };
    // Each score batch and the fits it decides in one device call (scoreAndFit): one round trip
    // where there were two.
    const std::function<ChainScoreFitResult<Pose>(const ChainScoreFit<Pose>&)> scoreFit =
        [&](const ChainScoreFit<Pose>& b) {
          return tallied(part_tally.batches, [&](const std::vector<ChainScore<Pose>>&) {
            return batches.scoreFits(b, [&](int t) { return 4.0 * frames[t].spacing; });
          })(b.starts);
        };
    return fitChainsBatched(C, T, ref, Pose(Pose::Identity()), starts,
                            tallied(part_tally.batches, scoreBatch),
                            tallied(part_tally.batches, fitBatch), same, true, 6, kMaxChainSteps,
                            C - optional, complete, params.fuse_score_fits ? &scoreFit : nullptr);
  };
  // Every group's motion from its own; `only_nonempty`: groups without points keep theirs.
  auto fitGroups = [&](bool only_nonempty) {
    std::vector<int> which;
    for (int g = 0; g < G; ++g)
      if (!only_nonempty || !gpts[g].empty()) which.push_back(g);
    std::vector<const std::vector<int>*> pts;
    std::vector<const std::vector<Pose>*> ia, ib(which.size(), nullptr);
    for (int g : which) pts.push_back(&gpts[g]), ia.push_back(&gpose[g]);
    std::vector<std::vector<Pose>> fit = fitParts(pts, ia, ib);
    for (std::size_t i = 0; i < which.size(); ++i) gpose[which[i]].swap(fit[i]);
  };
  fitGroups(false);
  reportPartFits("part fits");
  lapD("clustering: part fits");
  // Groups of phase 1 straddle joints where samples' poses were ambiguous: a few rounds of
  // moving points to the group whose motion explains them (with the motions refit) put the
  // borders where the motion changes before any group is scored as a whole.
  if (tr.surface.size() == static_cast<std::size_t>(n0)) {
    std::vector<int> plabel(n0, -1);
    for (int g = 0; g < G; ++g)
      for (int i : gpts[g]) plabel[i] = g;
    for (int round = 0; round < 3; ++round) {
      if (reassignByMotion(rc, tr.surface, frames, ref, gpose, plabel, params.device) == 0) break;
      for (auto& v : gpts) v.clear();
      for (int i = 0; i < n0; ++i)
        if (plabel[i] >= 0) gpts[plabel[i]].push_back(i);
      fitGroups(true);
    }
  }
  reportPartFits("border rounds");
  lapD("clustering: border rounds");

  // Groups that the border rounds left with a handful of points (their cells went to the parts
  // whose motions explain them) are remnants, not parts: their points join the part of their
  // nearest points of a real part. Left alive, they counted towards the target while holding
  // nothing (800k-point humanoid, seed 3: 7 of 15 parts held 1-22 of 16.6k reference points,
  // and the real parts were merged down to 8).
  {
    std::vector<int> plabel(n0, -1);
    for (int g = 0; g < G; ++g)
      for (int i : gpts[g]) plabel[i] = g;
    if (absorbRemnants(frames[ref], plabel)) {
      for (auto& v : gpts) v.clear();
      for (int i = 0; i < n0; ++i)
        if (plabel[i] >= 0) gpts[plabel[i]].push_back(i);
    }
  }

  lapD("clustering: remnants");
  struct PartEdge {
    double cost = 0.0;
    bool joined = false;  // a surface-graph edge joins the two parts
  };
  // Which part holds each reference point (kept current by the merges below).
  std::vector<int> part_of(n0, -1);
  for (int g = 0; g < G; ++g)
    for (int i : gpts[g]) part_of[i] = g;
  const bool has_surface = tr.surface.size() == static_cast<std::size_t>(n0);
  // Cost of merging A and B, per frame: the better of A's and B's own motions, scored by the
  // worse of the two sides' residuals under it; worst frame. No fit of A u B per edge: only the
  // merge that happens gets one. Two parts that meet only across a sharp crease (no edge of the
  // surface graph joins them: their normals turn by more than 60 degrees within 3 spacings) and
  // whose motions differ (cost at least kCreaseMotion of the threshold) cost at least
  // `crease_cost`: parts of a body meet at such creases (the minima rule of part perception), and
  // a small relative motion there (a pelvis under a torso) must not merge before the pieces of one
  // part do. A part rigidly attached across a crease (a hat on a head) merges as usual.
  const double crease_min = kCreaseMotion * params.threshold;
  // Several pairs at once: all their residuals form one batch (ResidualBatch: one parallel loop,
  // or the device), so that a merge's handful of neighbours keeps many cores busy.
  auto evaluatePairs = [&](const std::vector<std::pair<int, int>>& list) {
    const std::size_t np = list.size();
    ResidualBatch batch(frames, params.device);
    batch.reserve(2 * np, kPartPoints, 2 * np * T, 4 * np * static_cast<std::size_t>(T - 1));
    // Per pair and frame but the reference: A's and B's residuals under A's motion, then under
    // B's (four jobs from first[i * T + t]).
    std::vector<int> first(np * T, -1);
    for (std::size_t i = 0; i < np; ++i) {
      const auto [a, b] = list[i];
      const int sa = batch.addSource(sourceOf(rc, gpts[a], kPartPoints));
      const int sb = batch.addSource(sourceOf(rc, gpts[b], kPartPoints));
      const int ma = batch.motions();
      for (int t = 0; t < T; ++t) batch.addMotion(gpose[a][t]);
      const int mb = batch.motions();
      for (int t = 0; t < T; ++t) batch.addMotion(gpose[b][t]);
      for (int t = 0; t < T; ++t) {
        if (t == ref) continue;
        first[i * T + t] = batch.add(sa, ma + t, t);
        batch.add(sb, ma + t, t);
        batch.add(sa, mb + t, t);
        batch.add(sb, mb + t, t);
      }
    }
    const std::vector<double> r = batch.run();
    std::vector<double> cost(np * T, 0.0);
    for (std::size_t it = 0; it < np * T; ++it) {
      const int j = first[it];
      if (j < 0) continue;
      cost[it] = std::min(std::max(r[j], r[j + 1]), std::max(r[j + 2], r[j + 3]));
    }
    std::vector<PartEdge> out(np);
    for (std::size_t i = 0; i < np; ++i) {
      PartEdge& e = out[i];
      const auto [a, b] = list[i];
      for (int t = 0; t < T; ++t) e.cost = std::max(e.cost, cost[i * T + t]);
      if (has_surface) {
        const int small = gpts[a].size() <= gpts[b].size() ? a : b;
        const int other = small == a ? b : a;
        for (std::size_t k = 0; k < gpts[small].size() && !e.joined; ++k)
          for (int j : tr.surface[gpts[small][k]])
            if (part_of[j] == other) {
              e.joined = true;
              break;
            }
        if (params.crease_cost > 0.0 && e.cost < params.crease_cost && e.cost >= crease_min &&
            !e.joined)
          e.cost = params.crease_cost;
      }
    }
    return out;
  };
  std::map<std::pair<int, int>, PartEdge> pedges;
  {
    std::set<std::pair<int, int>> pairs;
    if (has_surface) {
      for (int i = 0; i < n0; ++i)
        for (int j : tr.surface[i]) {
          const int gi = part_of[i], gj = part_of[j];
          if (gi >= 0 && gj >= 0 && gi != gj) pairs.insert({std::min(gi, gj), std::max(gi, gj)});
        }
    }
    for (int s = 0; s < S; ++s)
      for (int o : tr.graph[s])
        if (gid[s] != gid[o] && !gpts[gid[s]].empty() && !gpts[gid[o]].empty())
          pairs.insert({std::min(gid[s], gid[o]), std::max(gid[s], gid[o])});
    const std::vector<std::pair<int, int>> list(pairs.begin(), pairs.end());
    const std::vector<PartEdge> c = evaluatePairs(list);
    for (std::size_t i = 0; i < list.size(); ++i) pedges[list[i]] = c[i];
  }
  lapD("clustering: part edges");
  std::vector<char> galive(G, 1);
  for (int g = 0; g < G; ++g) galive[g] = !gpts[g].empty();
  // Dissolving a part: a piece of phase 1 that straddles a joint has its own, compromise motion,
  // so merging it with either side costs as much as a true joint; but each of its points is
  // explained by one of the parts it touches. Its cost: its points (a source of up to
  // kPartPoints) each take the surface-joined neighbour whose motion fits it best over all
  // frames, and the worst frame's residual of the piece under those motions counts, on the
  // scale of a merge's cost. A part with fewer than two such neighbours is only ever merged.
  // The parts that share an edge with x (only surface-joined ones with joined_only), ascending.
  auto neighboursOf = [&](int x, bool joined_only = false) {
    std::vector<int> n;
    for (const auto& [k, e] : pedges)
      if ((k.first == x || k.second == x) && (e.joined || !joined_only))
        n.push_back(k.first == x ? k.second : k.first);
    return n;
  };
  auto dissolveCandidates = [&](int x) { return neighboursOf(x, true); };
  constexpr double kNoDissolve = std::numeric_limits<double>::infinity();
  // A part's worst-frame residual under its own motion, kept while its points and motion stay
  // (a merge or a dissolve next to it scores it again, but only its neighbours changed).
  std::vector<double> own_residual(G, 0.0);
  std::vector<char> own_known(G, 0);
  // The errors of a part's source points under a neighbour's motion (per point and frame, and
  // their sum over frames), kept while neither part's points nor motion change (`version`, bumped
  // with own_known): a merge or dissolve makes its neighbours score their dissolve again, but
  // only the changed neighbour's column is new. Filled in point order, as far as a score went.
  // Their storage is not zeroed when a column is made or reset: a point's entries are written
  // (the reference frame's as 0) before anything reads them, and zeroing them first took 7-11 ms
  // of the 800k part merges' main thread (64 MB a run, touched for the first time).
  struct ErrColumn {
    int ver_x = -1, ver_y = -1;
    Eigen::Index done = 0;
    PackedVector<double> e;    // [k * T + t], points 0..done-1 written
    PackedVector<double> sum;  // [k], the same
  };
  std::vector<int> version(G, 0);
  std::vector<std::map<int, ErrColumn>> err_cache(G);
  // x's column under neighbour y for a source of m points, reset when either part changed.
  auto columnOf = [&](int x, int y, Eigen::Index m) -> ErrColumn& {
    ErrColumn& c = err_cache[x][y];
    if (c.ver_x != version[x] || c.ver_y != version[y] ||
        c.sum.size() != static_cast<std::size_t>(m)) {
      c.ver_x = version[x];
      c.ver_y = version[y];
      c.done = 0;
      c.e.resize(static_cast<std::size_t>(m) * T);
      c.sum.resize(static_cast<std::size_t>(m));
    }
    return c;
  };
  // Point k of the source sx under neighbour y's motion, into column c.
  // (icp_step's arithmetic, as the device's per-frame point costs in fillColumns.)
  auto fillPoint = [&](ErrColumn& c, const Source& sx, int y, Eigen::Index k) {
    double sum = 0.0;
    for (int t = 0; t < T; ++t) {
      if (t == ref) {
        c.e[k * T + t] = 0.0;
        continue;
      }
      const icp_step::Rigid P = toRigid(gpose[y][t]);
      double py[3], ny[3];
      icp_step::apply(P, sx.p.col(k).data(), py);
      icp_step::rotate(P, sx.n.col(k).data(), ny);
      const double e = surfaceError(py, ny, frames[t]);
      c.e[k * T + t] = e;
      sum += e;
    }
    c.sum[k] = sum;
  };
  const int frames_scored = T - (ref >= 0 && ref < T ? 1 : 0);
  // Whether x could dissolve at all, with the neighbours that could take its points and its
  // source (dissolveCost's and fillColumns' one test).
  auto dissolveInput = [&](int x, std::vector<int>& nb, Source& sx) {
    if (!has_surface || !(params.dissolve_ratio > 0.0) || frames_scored < 1) return false;
    nb = dissolveCandidates(x);
    if (nb.size() < 2) return false;
    sx = sourceOf(rc, gpts[x], kPartPoints);
    return sx.p.cols() > 0;
  };
  auto dissolveCost = [&](int x) {
    std::vector<int> nb;
    Source sx;
    if (!dissolveInput(x, nb, sx)) return kNoDissolve;
    const Eigen::Index m = sx.p.cols();
    // Only a piece without a motion of its own dissolves: its neighbours' motions must explain
    // it about as well as its own does. A short true part between two joints (a neck, a
    // pelvis) fits its own motion far better (measured: 2.3 to 7.6 times) than the ends of
    // its neighbours' (each end fits, the middle does not); pieces straddling a joint 1.0-1.5.
    if (!own_known[x]) {
      double own = 0.0;
      for (int t = 0; t < T; ++t)
        if (t != ref) own = std::max(own, residual(sx, gpose[x][t], frames[t]));
      own_residual[x] = own;
      own_known[x] = 1;
    }
    const double limit = params.dissolve_ratio * own_residual[x];
    // The worst frame's mean is at least the mean over frames, so the running sum of each
    // point's best total bounds the cost from below: most parts are rejected early.
    const double give_up = limit * limit * static_cast<double>(m) * frames_scored;
    // col[y]: x's errors under neighbour y's motion (err_cache; this call's own thread is the
    // only one to touch x's columns).
    std::vector<ErrColumn*> col(nb.size());
    for (std::size_t y = 0; y < nb.size(); ++y) col[y] = &columnOf(x, nb[y], m);
    std::vector<int> pick(m, 0);
    double lower = 0.0;
    for (Eigen::Index k = 0; k < m; ++k) {
      double best = std::numeric_limits<double>::max();
      for (std::size_t y = 0; y < nb.size(); ++y) {
        ErrColumn& c = *col[y];
        if (c.done == k) {  // columns fill in point order: k is the next one
          fillPoint(c, sx, nb[y], k);
          c.done = k + 1;
        }
        if (c.sum[k] < best) best = c.sum[k], pick[k] = static_cast<int>(y);
      }
      lower += best;
      if (lower > give_up) return kNoDissolve;
    }
    // A piece never dissolves into parts that together are smaller than it (a torso into its
    // limbs).
    std::vector<char> takes(nb.size(), 0);
    for (Eigen::Index k = 0; k < m; ++k) takes[pick[k]] = 1;
    std::size_t taken_by = 0;
    for (std::size_t y = 0; y < nb.size(); ++y)
      if (takes[y]) taken_by += gpts[nb[y]].size();
    if (taken_by < gpts[x].size()) return kNoDissolve;
    double cost = 0.0;
    for (int t = 0; t < T; ++t) {
      if (t == ref) continue;
      double sum = 0.0;
      for (Eigen::Index k = 0; k < m; ++k) sum += col[pick[k]]->e[k * T + t];
      cost = std::max(cost, std::sqrt(sum / static_cast<double>(m)));
    }
    if (cost > limit) return kNoDissolve;
    return cost;
  };
  // Where the part merges' time goes (ANIMSEG_MS_TIMING): merge fits, edge scores, dissolve
  // costs, dissolves.
  double t_fit = 0.0, t_edges = 0.0, t_dcost = 0.0, t_dissolve = 0.0, t_dpts = 0.0, t_dfit = 0.0;
  int n_merges = 0, n_dissolves = 0;
  auto since = [](std::chrono::steady_clock::time_point t0) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  };
  std::vector<double> dcost(G, kNoDissolve);
  // On many threads a refresh first fills the columns its parts' scores read, whole, with every
  // (part, neighbour, block of points) and own-residual frame in one parallel loop; the scores
  // then only sum. Scored side by side with the early rejection instead, the slowest part's
  // serial loop held 16 threads (dissolve costs about 1 s of the 800k humanoid's 2 s of part
  // merges). Same values, so the same costs; on few threads the early rejection saves more.
  // With a device the errors are one batch of per-frame point costs and the own residuals one
  // batch of residuals (the same values again), also for the first scores.
  const bool prefill = params.device || omp_get_max_threads() >= 4;
  auto fillColumns = [&](const std::vector<int>& list) {
    struct Job {
      ErrColumn* c;
      const Source* sx;
      int y;
      Eigen::Index k0, k1;
    };
    std::vector<Source> src(list.size());
    std::vector<Job> jobs;
    std::vector<std::pair<std::size_t, int>> own_jobs;  // (index in list, frame)
    std::vector<std::vector<double>> own(list.size());
    constexpr Eigen::Index kBlock = 8;
    for (std::size_t i = 0; i < list.size(); ++i) {
      const int x = list[i];
      std::vector<int> nb;
      if (!galive[x] || !dissolveInput(x, nb, src[i])) continue;
      const Eigen::Index m = src[i].p.cols();
      if (!own_known[x]) {
        own[i].assign(T, 0.0);
        for (int t = 0; t < T; ++t)
          if (t != ref) own_jobs.push_back({i, t});
      }
      for (int y : nb) {
        ErrColumn& c = columnOf(x, y, m);
        for (Eigen::Index k0 = c.done; k0 < m; k0 += kBlock)
          jobs.push_back({&c, &src[i], y, k0, std::min(m, k0 + kBlock)});
      }
    }
    const std::size_t nj = jobs.size(), no = own_jobs.size();
    if (params.device) {
      PointCostJobs d;
      d.reference_frame = ref;
      d.per_frame = true;
      std::vector<int> first(list.size(), -1), motion_of(G, -1);
      for (const Job& b : jobs) {
        const std::size_t i = static_cast<std::size_t>(b.sx - src.data());
        if (first[i] < 0) {
          first[i] = static_cast<int>(d.points.size() / 6);
          appendPoints(src[i].p, src[i].n, d.points);
        }
        if (motion_of[b.y] < 0) {
          motion_of[b.y] = static_cast<int>(d.motions.size() / (12 * static_cast<std::size_t>(T)));
          for (const Pose& m : gpose[b.y]) appendMotion(m, d.motions);
        }
        for (Eigen::Index k = b.k0; k < b.k1; ++k)
          d.jobs.push_back({first[i] + static_cast<int>(k), motion_of[b.y]});
      }
      // The own residuals from the same batch: each of the part's source points under its own
      // motion, per frame (own_first[i]: its first job), then summed in point order here, as
      // residual() adds the same errors: the same values, one device call instead of two.
      std::vector<std::size_t> own_first(list.size(), 0);
      {
        std::vector<char> listed(list.size(), 0);
        for (const auto& own_job : own_jobs) {
          const std::size_t i = own_job.first;
          if (listed[i]) continue;
          listed[i] = 1;
          if (first[i] < 0) {
            first[i] = static_cast<int>(d.points.size() / 6);
            appendPoints(src[i].p, src[i].n, d.points);
          }
          const int x = list[i];
          if (motion_of[x] < 0) {
            motion_of[x] = static_cast<int>(d.motions.size() / (12 * static_cast<std::size_t>(T)));
            for (const Pose& m : gpose[x]) appendMotion(m, d.motions);
          }
          own_first[i] = d.jobs.size();
          for (Eigen::Index k = 0; k < src[i].p.cols(); ++k)
            d.jobs.push_back({first[i] + static_cast<int>(k), motion_of[x]});
        }
      }
      std::vector<double> e;
      if (!d.jobs.empty()) params.device->pointCosts(d, e);
      if (e.size() != d.jobs.size() * static_cast<std::size_t>(T))
        throw Error("motion tracking: the device's point errors are incomplete");
      // Into the columns, the jobs side by side (each writes its own points of its own column):
      // 64 MB of errors a run at 800k, copied on one thread between the device's calls.
      std::vector<std::size_t> q0(nj + 1, 0);
      for (std::size_t j = 0; j < nj; ++j)
        q0[j + 1] = q0[j] + static_cast<std::size_t>(jobs[j].k1 - jobs[j].k0);
      const bool wide = e.size() >= 65536;  // the copy is worth a team
#pragma omp parallel for schedule(static) if (wide)
      for (std::size_t j = 0; j < nj; ++j) {
        const Job& b = jobs[j];
        std::size_t q = q0[j];
        for (Eigen::Index k = b.k0; k < b.k1; ++k, ++q) {
          double sum = 0.0;
          for (int t = 0; t < T; ++t) {
            if (t == ref) {
              b.c->e[k * T + t] = 0.0;
              continue;
            }
            b.c->e[k * T + t] = e[q * T + t];
            sum += e[q * T + t];
          }
          b.c->sum[k] = sum;
        }
      }
      for (const auto& [i, t] : own_jobs) {
        const Eigen::Index m = src[i].p.cols();
        double sum = 0.0;
        for (Eigen::Index k = 0; k < m; ++k)
          sum += e[(own_first[i] + static_cast<std::size_t>(k)) * T + t];
        own[i][t] = m > 0 ? std::sqrt(sum / static_cast<double>(m)) : 0.0;
      }
    } else {
#pragma omp parallel for schedule(dynamic, 1)
      for (std::size_t j = 0; j < nj + no; ++j) {
        if (j < nj) {
          const Job& b = jobs[j];
          for (Eigen::Index k = b.k0; k < b.k1; ++k) fillPoint(*b.c, *b.sx, b.y, k);
        } else {
          const auto [i, t] = own_jobs[j - nj];
          own[i][t] = residual(src[i], gpose[list[i]][t], frames[t]);
        }
      }
    }
    for (const Job& b : jobs) b.c->done = std::max(b.c->done, b.k1);
    for (std::size_t i = 0; i < list.size(); ++i)
      if (!own[i].empty()) {
        own_residual[list[i]] = *std::max_element(own[i].begin(), own[i].end());
        own_known[list[i]] = 1;
      }
  };
  {
    std::vector<int> alive;
    for (int g = 0; g < G; ++g)
      if (galive[g]) alive.push_back(g);
    if (params.device) fillColumns(alive);
#pragma omp parallel for schedule(dynamic, 1)
    for (std::size_t i = 0; i < alive.size(); ++i) dcost[alive[i]] = dissolveCost(alive[i]);
  }
  auto refreshDissolve = [&](const std::set<int>& parts) {
    const auto t0 = std::chrono::steady_clock::now();
    const std::vector<int> list(parts.begin(), parts.end());
    if (prefill) fillColumns(list);
#pragma omp parallel for schedule(dynamic, 1)
    for (std::size_t i = 0; i < list.size(); ++i)
      dcost[list[i]] = galive[list[i]] ? dissolveCost(list[i]) : kNoDissolve;
    t_dcost += since(t0);
  };
  // Speculative merge fits (with a device). A merge's or a dissolve's part fits also fit the union
  // of the cheapest pair of parts that the step leaves as they are, as an optional chain
  // (fitChainsBatched): it rides in the same device batches, which are latency-bound, and adds
  // none, so the step waits no longer; it is given up where it would. When that pair merges
  // later with the same points and the same starts, its fit is taken as it is: the same poses,
  // since each chain of a batch is fitted as if alone. On the cores the optional chain would
  // cost its full work, so there is none. On the H200 at 800 417 points (humanoid, seed 1): 32
  // speculated, 23 complete, 20 of the 54 merges' fits taken from them; the merges' fits 0.035
  // -> 0.028 s, the part merges' device calls 792 -> 700, the hierarchy merges beside the labels
  // 0.068 -> 0.060 s.
  struct Speculated {
    std::vector<int> pts;      // the union
    std::vector<Pose> ia, ib;  // the two parts' motions when it was fitted (the starts)
    std::vector<Pose> fit;
  };
  std::map<std::pair<int, int>, Speculated> speculated;
  int spec_fits = 0, spec_complete = 0, spec_hits = 0;
  auto samePoses = [](const std::vector<Pose>& p, const std::vector<Pose>& q) {
    if (p.size() != q.size()) return false;
    for (std::size_t t = 0; t < p.size(); ++t)  // bit for bit (0.0 and -0.0 differ)
      if (std::memcmp(p[t].matrix().data(), q[t].matrix().data(), 16 * sizeof(double)) != 0)
        return false;
    return true;
  };
  // The union of a and b (a < b) and its starts, as mergeParts fits it.
  auto unionOf = [&](int a, int b) {
    std::vector<int> u;
    u.reserve(gpts[a].size() + gpts[b].size());
    std::set_union(gpts[a].begin(), gpts[a].end(), gpts[b].begin(), gpts[b].end(),
                   std::back_inserter(u));
    return u;
  };
  auto speculatedFit = [&](int a, int b, const std::vector<int>& u) -> const Speculated* {
    const auto it = speculated.find({a, b});
    if (it == speculated.end() || it->second.pts != u || !samePoses(it->second.ia, gpose[a]) ||
        !samePoses(it->second.ib, gpose[b]))
      return nullptr;
    return &it->second;
  };
  // The pairs to fit beside a step that changes the parts in `changing` (sorted): the cheapest
  // edges between two others, up to kSpeculated of them, but for those whose fits are known
  // already. Their unions and starts go into `specs`.
  // One: on the H200 at 800 417 points two or three a step took no less time (the part merges'
  // fits 0.028 s with one, 0.027 and 0.026 s with two and three), for 54 and 67 speculated fits
  // instead of 32.
  constexpr int kSpeculated = 1;
  auto pickSpeculation = [&](const std::vector<int>& changing,
                             std::vector<std::pair<std::pair<int, int>, Speculated>>& specs) {
    specs.clear();
    if (!params.speculate_merge_fits || !partsOnDevice()) return;
    std::vector<std::pair<double, std::pair<int, int>>> order;
    for (const auto& [k, e] : pedges) {
      if (std::binary_search(changing.begin(), changing.end(), k.first) ||
          std::binary_search(changing.begin(), changing.end(), k.second))
        continue;
      order.push_back({e.cost, k});
    }
    const std::size_t n = std::min(order.size(), static_cast<std::size_t>(kSpeculated));
    std::partial_sort(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(n), order.end());
    for (std::size_t i = 0; i < n; ++i) {
      const auto [c, d] = order[i].second;
      Speculated spec;
      spec.pts = unionOf(c, d);
      if (speculatedFit(c, d, spec.pts)) continue;
      spec.ia = gpose[c];
      spec.ib = gpose[d];
      specs.emplace_back(std::make_pair(c, d), std::move(spec));
    }
  };
  // The parts in `changed` get new points or motions: their pairs' speculated fits go.
  auto forgetSpeculations = [&](const std::vector<int>& changed) {
    for (auto it = speculated.begin(); it != speculated.end();)
      it = std::find(changed.begin(), changed.end(), it->first.first) != changed.end() ||
                   std::find(changed.begin(), changed.end(), it->first.second) != changed.end()
               ? speculated.erase(it)
               : std::next(it);
  };
  // A step's part fits (fitParts of pts, ia, ib) where the step changes the parts in `changing`
  // (sorted), with the speculated pairs beside them as optional chains: the step's own fits; the
  // changed parts' speculated fits dropped, the new complete ones kept.
  auto fitStep = [&](const std::vector<int>& changing, std::vector<const std::vector<int>*> pts,
                     std::vector<const std::vector<Pose>*> ia,
                     std::vector<const std::vector<Pose>*> ib) {
    std::vector<std::pair<std::pair<int, int>, Speculated>> specs;
    pickSpeculation(changing, specs);
    const std::size_t own = pts.size();
    for (auto& [pair, spec] : specs) {
      pts.push_back(&spec.pts);
      ia.push_back(&gpose[pair.first]);
      ib.push_back(&gpose[pair.second]);
    }
    std::vector<char> complete;
    std::vector<std::vector<Pose>> fit =
        fitParts(pts, ia, ib, static_cast<int>(specs.size()), &complete);
    forgetSpeculations(changing);
    for (std::size_t i = 0; i < specs.size(); ++i) {
      ++spec_fits;
      if (!complete[own + i]) continue;
      ++spec_complete;
      specs[i].second.fit.swap(fit[own + i]);
      speculated[specs[i].first] = std::move(specs[i].second);
    }
    fit.resize(own);
    return fit;
  };
  auto dissolvePart = [&](int x) {
    const std::vector<int> nb = dissolveCandidates(x);
    const std::vector<int>& px = gpts[x];
    // Each point's cost under each candidate's motion, averaged over its surface neighbours in
    // the part (one point's residual is noisy).
    auto t0 = std::chrono::steady_clock::now();
    std::vector<std::vector<double>> c(px.size(), std::vector<double>(nb.size()));
    {
      PointCostBatch batch(rc, frames, ref, params.device);
      for (int y : nb) batch.addMotion(&gpose[y]);
      for (std::size_t k = 0; k < px.size(); ++k)
        for (std::size_t y = 0; y < nb.size(); ++y) batch.add(px[k], static_cast<int>(y));
      const std::vector<double> costs = batch.run();
      for (std::size_t k = 0; k < px.size(); ++k)
        for (std::size_t y = 0; y < nb.size(); ++y) c[k][y] = costs[k * nb.size() + y];
    }
    std::vector<int> to(px.size(), nb[0]);
    for (std::size_t k = 0; k < px.size(); ++k) {
      std::vector<double> sum(c[k]);
      int cnt = 1;
      for (int j : tr.surface[px[k]]) {
        if (part_of[j] != x) continue;
        const std::size_t kj = static_cast<std::size_t>(
            std::lower_bound(px.begin(), px.end(), j) - px.begin());
        for (std::size_t y = 0; y < nb.size(); ++y) sum[y] += c[kj][y];
        ++cnt;
      }
      to[k] = nb[std::min_element(sum.begin(), sum.end()) - sum.begin()];
    }
    t_dpts += since(t0);
    std::set<int> receivers;
    for (std::size_t k = 0; k < px.size(); ++k) {
      part_of[px[k]] = to[k];
      receivers.insert(to[k]);
    }
    const std::vector<int> former = neighboursOf(x);
    std::set<int> affected(former.begin(), former.end());
    for (auto it = pedges.begin(); it != pedges.end();)
      it = (it->first.first == x || it->first.second == x) ? pedges.erase(it) : std::next(it);
    const std::vector<int> rec(receivers.begin(), receivers.end());
    std::vector<std::vector<int>> grown(rec.size());
    for (std::size_t r = 0; r < rec.size(); ++r) {
      std::vector<int> add;
      for (std::size_t k = 0; k < px.size(); ++k)
        if (to[k] == rec[r]) add.push_back(px[k]);
      std::set_union(gpts[rec[r]].begin(), gpts[rec[r]].end(), add.begin(), add.end(),
                     std::back_inserter(grown[r]));
    }
    // The receivers' frames side by side (fitParts): a dissolve has two or three receivers, too
    // few to keep many cores busy on their own.
    t0 = std::chrono::steady_clock::now();
    {
      std::vector<const std::vector<int>*> pts;
      std::vector<const std::vector<Pose>*> ia, ib(rec.size(), nullptr);
      for (std::size_t r = 0; r < rec.size(); ++r)
        pts.push_back(&grown[r]), ia.push_back(&gpose[rec[r]]);
      std::vector<int> changing(rec);
      changing.push_back(x);
      std::sort(changing.begin(), changing.end());
      std::vector<std::vector<Pose>> fit = fitStep(changing, pts, ia, ib);
      for (std::size_t r = 0; r < rec.size(); ++r) gpose[rec[r]].swap(fit[r]);
    }
    t_dfit += since(t0);
    for (std::size_t r = 0; r < rec.size(); ++r) {
      gpts[rec[r]].swap(grown[r]);
      own_known[rec[r]] = 0;
      ++version[rec[r]];
    }
    gpts[x].clear();
    galive[x] = 0;
    // The receivers' motions changed: their edges are scored again, and receivers that now
    // touch each other over the surface become neighbours.
    std::set<std::pair<int, int>> redo;
    for (int r : rec) {
      for (int o : neighboursOf(r)) redo.insert({std::min(r, o), std::max(r, o)});
      for (int i : gpts[r])
        for (int j : tr.surface[i]) {
          const int o = part_of[j];
          if (o >= 0 && o != r && galive[o]) redo.insert({std::min(r, o), std::max(r, o)});
        }
    }
    const std::vector<std::pair<int, int>> list(redo.begin(), redo.end());
    const std::vector<PartEdge> ec = evaluatePairs(list);
    for (std::size_t i = 0; i < list.size(); ++i) pedges[list[i]] = ec[i];
    for (int r : rec) {
      affected.insert(r);
      for (int o : neighboursOf(r)) affected.insert(o);
    }
    dcost[x] = kNoDissolve;
    affected.erase(x);
    refreshDissolve(affected);
  };
  bool refresh_dissolve = true;
  auto mergeParts = [&](int a, int b) {
    // The smaller id survives, so ids stay ordered by each group's first sample.
    if (b < a) std::swap(a, b);
    ++n_merges;
    auto t0 = std::chrono::steady_clock::now();
    std::vector<int> u = unionOf(a, b);
    if (const Speculated* known = speculatedFit(a, b, u)) {
      gpose[a] = known->fit;
      ++spec_hits;
      forgetSpeculations({a, b});
    } else {
      gpose[a].swap(fitStep({a, b}, {&u}, {&gpose[a]}, {&gpose[b]})[0]);
    }
    t_fit += since(t0);
    t0 = std::chrono::steady_clock::now();
    gpts[a].swap(u);
    own_known[a] = 0;
    ++version[a];
    for (int i : gpts[b]) part_of[i] = a;
    gpts[b].clear();
    galive[b] = 0;
    rewireEdgesBatch(pedges, a, b, evaluatePairs);
    t_edges += since(t0);
    if (refresh_dissolve) {
      // a's motion changed: a and the parts that touch it are scored again.
      const std::vector<int> touching = neighboursOf(a);
      std::set<int> affected(touching.begin(), touching.end());
      affected.insert(a);
      dcost[b] = kNoDissolve;
      refreshDissolve(affected);
    }
    return a;
  };
  auto cheapestPart = [&]() {
    auto best = pedges.end();
    for (auto it = pedges.begin(); it != pedges.end(); ++it)
      if (best == pedges.end() || it->second.cost < best->second.cost) best = it;
    return best;
  };
  int alive_parts = static_cast<int>(std::count(galive.begin(), galive.end(), 1));
  // Slivers (MotionTrackingParams::sliver_fraction): parts of fewer than `tiny` reference points
  // merge into their cheapest neighbour whatever the cost. With a target count they go first and
  // do not count towards it; without one, once the threshold stops the merges.
  const double sliver = params.sliver_fraction;
  std::size_t tiny = params.target_clusters > 0
                         ? static_cast<std::size_t>(sliver * n0 / params.target_clusters)
                         : 0;
  auto cheapestTiny = [&]() {
    auto best = pedges.end();
    for (auto it = pedges.begin(); it != pedges.end(); ++it)
      if ((gpts[it->first.first].size() < tiny || gpts[it->first.second].size() < tiny) &&
          (best == pedges.end() || it->second.cost < best->second.cost))
        best = it;
    return best;
  };
  while (!pedges.empty()) {
    if (tiny > 0) {
      const auto edge = cheapestTiny();
      if (edge != pedges.end()) {
        const auto [a, b] = edge->first;
        mergeParts(a, b);
        --alive_parts;
        continue;
      }
    }
    const auto best = cheapestPart();
    const int dx = static_cast<int>(std::min_element(dcost.begin(), dcost.end()) - dcost.begin());
    const bool dissolve = dcost[dx] < best->second.cost;
    if (params.target_clusters > 0
            ? alive_parts <= params.target_clusters
            : std::min(best->second.cost, dcost[dx]) > params.threshold) {
      if (tiny == 0 && params.target_clusters <= 0 && sliver > 0.0) {
        tiny = static_cast<std::size_t>(sliver * n0 / std::max(1, alive_parts));
        if (tiny > 0 && cheapestTiny() != pedges.end()) continue;
      }
      break;
    }
    if (dissolve) {
      const auto t0 = std::chrono::steady_clock::now();
      dissolvePart(dx);
      t_dissolve += since(t0);
      ++n_dissolves;
      --alive_parts;
      continue;
    }
    const auto [a, b] = best->first;
    mergeParts(a, b);
    --alive_parts;
  }
  if (timer.on())
    std::fprintf(stderr,
                 "[mean shift] part merges: %d merges (fits %.3f s, edges %.3f s), %d dissolves "
                 "(%.3f s: point costs %.3f s, fits %.3f s), dissolve costs %.3f s; %d fits "
                 "speculated, %d complete, %d taken\n",
                 n_merges, t_fit, t_edges, n_dissolves, t_dissolve, t_dpts, t_dfit, t_dcost,
                 spec_fits, spec_complete, spec_hits);
  reportPartFits("part merges");
  lapD("clustering: part merges");
  refresh_dissolve = false;
  // Snapshot: final ids in order of each group's first sample.
  std::vector<int> final_id(G, -1);
  for (int g = 0; g < G; ++g)
    if (galive[g]) final_id[g] = out.groups++;
  // Re-derive membership from the point sets: a phase-1 group belongs to the part holding its
  // points (its cells moved with it).
  {
    std::vector<int> part_of_point(n0, -1);
    for (int g = 0; g < G; ++g)
      if (galive[g])
        for (int i : gpts[g]) part_of_point[i] = final_id[g];
    out.group.assign(S, 0);
    for (int s = 0; s < S; ++s) {
      const int p = part_of_point[tr.sample_points[s]];
      out.group[s] = p >= 0 ? p : 0;
    }
    out.point_labels = part_of_point;
  }
  for (int g = 0; g < G; ++g)
    if (galive[g]) out.poses.push_back(gpose[g]);
  // The coarser hierarchy, in final ids (a merged pair is named by its smaller id).
  auto hierarchyMerges = [&](std::vector<ClusterMerge>& merges) {
    std::vector<int> name(final_id);
    while (!pedges.empty()) {
      const auto best = cheapestPart();
      const auto [a, b] = best->first;
      const double c = best->second.cost;
      merges.push_back({std::min(name[a], name[b]), std::max(name[a], name[b]), c});
      const int lo = std::min(name[a], name[b]);
      const int survivor = mergeParts(a, b);
      name[survivor] = lo;
    }
  };
  if (!with_parts || !merges_device) {
    hierarchyMerges(out.merges);
    reportPartFits("hierarchy merges");
    timer.lap("clustering: hierarchy merges");
    if (with_parts) with_parts(out);
    return out;
  }
  // With a device both are mostly chains of device calls, each leaving the device idle between
  // its calls: the merges run beside the caller's work with the parts (800k humanoid: 0.05 s of
  // merges beside 0.14 s of part motions and labels). They read only the clustering's state, the
  // caller only the parts copied out above.
  std::vector<ClusterMerge> merges;
  params.device = merges_device;
  BesideThread beside;
  beside.start([&] {
    // Its host work is light: a few threads for the loops it has (the count does not change the
    // results; restored where this runs on the caller's thread, also where it throws).
    struct Restore {
      int threads;
      ~Restore() { omp_set_num_threads(threads); }
    } restore{omp_get_max_threads()};
    omp_set_num_threads(std::min(4, restore.threads));
    const auto t0 = std::chrono::steady_clock::now();
    hierarchyMerges(merges);
    if (timer.on())
      std::fprintf(stderr, "[mean shift] hierarchy merges alone: %.3f s\n",
                   std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    reportPartFits("hierarchy merges");  // the one thread that fits parts now
  });
  with_parts(out);
  beside.join();  // the merges' device error, if any, is the stage's
  out.merges = std::move(merges);
  timer.lap("clustering: hierarchy merges, beside the parts' motions and labels");
  return out;
}

}  // namespace

SampleTracks trackSamples(const PointCloudSequence& seq, const MotionTrackingParams& params,
                          Progress* progress) {
  const std::vector<Frame> frames = makeFrames(seq);
  if (params.device) params.device->setFrames(deviceFrames(frames));
  return trackSamplesOn(seq, frames, params, progress);
}

TrajectoryClusters clusterTrajectories(const PointCloudSequence& seq, const SampleTracks& tr,
                                       const MotionTrackingParams& params) {
  if (tr.sample_points.empty()) return TrajectoryClusters();
  const std::vector<Frame> frames = makeFrames(seq);
  if (params.device) params.device->setFrames(deviceFrames(frames));
  return clusterTrajectoriesOn(frames, tr, params);
}

namespace {

// The parts' motions (motion[c][t], from the reference frame), the reference points' labels and
// every point's label (flat, at the frames' offsets; before the parts that lost every point are
// dropped) from the clustering's parts.
void labelByParts(const std::vector<Frame>& frames, const SampleTracks& tr,
                  const TrajectoryClusters& tc, const MotionTrackingParams& params,
                  const std::vector<std::size_t>& offsets, std::vector<std::vector<Pose>>& motion,
                  std::vector<int>& label, std::vector<int>& flat) {
  detail::StageTimer timer;
  const int T = static_cast<int>(frames.size());
  const int ref = tr.reference_frame;
  const int nc = tc.groups;
  const Cloud& rc = *frames[ref].cloud;
  const int n0 = static_cast<int>(rc.size());
  const int S = static_cast<int>(tr.sample_points.size());

  // Reference labels: the group of the sample whose geodesic cell holds the point (the nearest
  // sample where the surface graph did not reach).
  label.assign(n0, 0);
  {
    Cloud::Ptr sc(new Cloud);
    sc->resize(S);
    for (int s = 0; s < S; ++s) (*sc)[s] = rc[tr.sample_points[s]];
    pcl_animseg::KdTree<pcl::PointNormal> st;
    st.setInputCloud(sc);
    std::vector<int> idx;
    std::vector<float> d2;
    for (int i = 0; i < n0; ++i) {
      if (tc.point_labels.size() == static_cast<std::size_t>(n0) && tc.point_labels[i] >= 0)
        label[i] = tc.point_labels[i];
      else if (tr.owner.size() == static_cast<std::size_t>(n0) && tr.owner[i] >= 0)
        label[i] = tc.group[tr.owner[i]];
      else if (st.nearestKSearch(rc[i], 1, idx, d2) == 1)
        label[i] = tc.group[idx[0]];
    }
  }
  // Part motions, tracked along the sequence as an articulated body, each refined by ICP of up
  // to 400 of its reference points.
  motion = trackParts(frames, tr, label, nc, tc.poses, tc.group, 400, params.joint_weight,
                      params.device);
  timer.lap("labels: part motions");
  // The part motions are final now: the borders between parts are placed once more, by the
  // graph cut (motion fit plus a short border, cut where the surface folds inwards) or, with
  // border_smoothness 0, by moving each point to the neighbouring part whose motion keeps its
  // neighbourhood on the surface best over all frames.
  if (tr.surface.size() == static_cast<std::size_t>(n0)) {
    if (params.border_smoothness > 0.0) {
      reassignByGraphCut(rc, tr.surface, frames, ref, motion, label, params.border_smoothness,
                         params.border_hops, params.device);
    } else {
      for (int round = 0; round < 2; ++round)
        if (reassignByMotion(rc, tr.surface, frames, ref, motion, label, params.device) == 0) break;
    }
  }
  // A part left with a handful of reference points (an isolated point whose group was moved away
  // around it) is a remnant, not a part: its points join the label of their nearest points of
  // another, real part.
  absorbRemnants(frames[ref], label);
  timer.lap("labels: part borders");
  // Labels of every frame: the nearest reference point moved by its part's motion, with a
  // compatible normal. Frame t's copy of reference point i (the device's search and the cores'
  // read the same floats):
  auto copyOf = [&](int i, int t) {
    const Pose& M = motion[label[i]][t];
    const Eigen::Vector3d p = M * Eigen::Vector3d(rc[i].x, rc[i].y, rc[i].z);
    const Eigen::Vector3d nn =
        M.linear() * Eigen::Vector3d(rc[i].normal_x, rc[i].normal_y, rc[i].normal_z);
    pcl::PointNormal q = toPoint(p);
    q.normal_x = static_cast<float>(nn.x());
    q.normal_y = static_cast<float>(nn.y());
    q.normal_z = static_cast<float>(nn.z());
    return q;
  };
  const int kq = std::min(8, n0);
  // Frame t's points `which` (every point where null) labelled on the cores: the tree of the
  // frame's copies, then each point's search.
  auto labelOnCores = [&](int t, const std::vector<int>* which) {
    const Cloud& fc = *frames[t].cloud;
    std::vector<int> idx;
    std::vector<float> d2;
    Cloud::Ptr moved(new Cloud);
    moved->resize(n0);
    for (int i = 0; i < n0; ++i) (*moved)[i] = copyOf(i, t);
    pcl_animseg::KdTree<pcl::PointNormal> mt;
    mt.setInputCloud(moved);
    const int n = which ? static_cast<int>(which->size()) : static_cast<int>(fc.size());
    for (int w = 0; w < n; ++w) {
      const int j = which ? (*which)[w] : w;
      auto compatible = [&](int m) {
        const auto& q = (*moved)[m];
        return normalCos(q.normal_x * fc[j].normal_x + q.normal_y * fc[j].normal_y +
                             q.normal_z * fc[j].normal_z,
                         frames[t]) > kNormalCos;
      };
      // Usually the nearest point has a compatible normal: then it is the pick, found without
      // the k-NN search (unless another point lies at exactly its distance: the k-NN's order
      // of such ties decides, as before).
      float nd2;
      bool tied;
      const int first = mt.nearestFirst(fc[j], nd2, tied);
      if (first >= 0 && !tied && compatible(first)) {
        flat[offsets[t] + j] = label[first];
        continue;
      }
      mt.nearestKSearch(fc[j], kq, idx, d2);
      int pick = idx.empty() ? -1 : idx[0];
      for (int m : idx)
        if (compatible(m)) {
          pick = m;
          break;
        }
      flat[offsets[t] + j] = pick < 0 ? -1 : label[pick];
    }
  };
  // With a device that offers it, every frame's search there (MotionDevice::nearestMoved: 0.04 s
  // on 16 cores at 800k, most of it the frames' trees of their copies and the searches); the
  // points it leaves undecided (a tie at the k-th nearest copy, which the cores' search breaks by
  // the order it visits the tree's cells) are searched on the cores, as before.
  if (params.device) {
    MovedCopies mc;
    const FlatKdTree3& rt = frames[ref].tree.flatTree();
    mc.order.resize(rt.size());
    for (std::size_t i = 0; i < rt.size(); ++i)
      mc.order[i] = frames[ref].tree.cloudIndex(rt.leafRows()[i]);
    mc.k = kq;
    mc.normal_cos = kNormalCos;
    const long n = static_cast<long>(mc.order.size());
    mc.fill = [&](float* out) {
#pragma omp parallel for schedule(static)
      for (long x = 0; x < static_cast<long>(T) * n; ++x) {
        const pcl::PointNormal q = copyOf(mc.order[x % n], static_cast<int>(x / n));
        float* o = out + 8 * x;
        o[0] = q.x, o[1] = q.y, o[2] = q.z, o[3] = 0.0f;
        o[4] = q.normal_x, o[5] = q.normal_y, o[6] = q.normal_z, o[7] = 0.0f;
      }
    };
    std::vector<int> pick;
    if (params.device->nearestMoved(mc, pick)) {
      std::vector<std::size_t> first(T + 1, 0);
      for (int t = 0; t < T; ++t) first[t + 1] = first[t] + frames[t].tree.flatTree().size();
      if (pick.size() != first[T])
        throw Error("motion method: the device labelled " + std::to_string(pick.size()) +
                    " points of " + std::to_string(first[T]));
      bool bad = false;
      std::vector<std::vector<int>> undecided(T);
#pragma omp parallel for schedule(dynamic, 1) reduction(|| : bad)
      for (int t = 0; t < T; ++t) {
        const std::vector<int>& rows = frames[t].tree.flatTree().leafRows();
        for (std::size_t i = 0; i < rows.size(); ++i) {
          const int m = pick[first[t] + i], j = frames[t].tree.cloudIndex(rows[i]);
          if (m == kMovedUndecided) {
            undecided[t].push_back(j);
          } else if (m < -1 || m >= n0) {
            bad = true;
          } else {
            flat[offsets[t] + j] = m < 0 ? -1 : label[m];
          }
        }
      }
      if (bad) throw Error("motion method: the device named a reference point out of range");
      std::size_t left = 0;
      for (int t = 0; t < T; ++t) left += undecided[t].size();
      if (left > 0) {
#pragma omp parallel for schedule(dynamic, 1)
        for (int t = 0; t < T; ++t)
          if (!undecided[t].empty()) labelOnCores(t, &undecided[t]);
      }
      if (timer.on())
        std::fprintf(stderr,
                     "[mean shift] labels of every frame on %s, %zu points left to the cores\n",
                     params.device->name().c_str(), left);
      timer.lap("labels: every frame");
      return;
    }
  }
  // On the cores: the frames side by side (each built its tree of the moved reference serially
  // while 15 threads waited).
#pragma omp parallel for schedule(dynamic, 1)
  for (int t = 0; t < T; ++t) labelOnCores(t, nullptr);
  timer.lap("labels: every frame");
}

}  // namespace

void segmentByTracking(const PointCloudSequence& seq, const MotionTrackingParams& params,
                       std::vector<int>& flat, int& num_clusters, std::vector<ClusterMerge>& merges,
                       Progress* progress,
                       std::vector<std::vector<Eigen::Isometry3d>>* part_motions) {
  // The frames (kd-tree and spacing of each) are built once for the three steps.
  detail::StageTimer ftimer;
  SpareCoreWhileStarting spare(params.device);
  const std::vector<Frame> frames = makeFrames(seq);
  ftimer.lap("frames: trees and spacings");
  spare.recheck();
  if (params.device) params.device->setFrames(deviceFrames(frames));
  ftimer.lap("frames: device packing");
  spare.release();
  // The caller's work starts with the samples' poses: from there on the steps are mostly chains
  // of device calls and host steps between them.
  BesideThread beside;
  const SampleTracks tr =
      trackSamplesOn(seq, frames, params, progress, [&] { beside.start(params.beside_chains); });
  const int T = static_cast<int>(seq.size());
  // The parts' motions and labels, made as soon as the parts are known: with a device, the
  // hierarchy's merges above the parts run meanwhile (clusterTrajectoriesOn).
  std::vector<std::vector<Pose>> motion;
  std::vector<int> label;
  flat.assign(seq.totalPoints(), -1);
  // The merges' device: a fork of the device (its calls run beside the caller's on the device)
  // or, where it offers none, the device shared by both, their calls taking turns.
  std::unique_ptr<MotionDevice> forked;
  std::unique_ptr<SharedDevice> shared;
  MotionDevice* merges_device = nullptr;
  MotionTrackingParams cparams = params;
  if (params.device) {
    forked = params.device->fork();
    if (forked) {
      merges_device = forked.get();
    } else {
      shared = std::make_unique<SharedDevice>(*params.device);
      cparams.device = merges_device = shared.get();
    }
  }
  bool labelled = false;
  auto labelParts = [&](const TrajectoryClusters& parts) {
    if (progress) progress->end(std::to_string(parts.groups) + " parts");
    if (progress) progress->begin("part motions and labels", 0);
    labelByParts(frames, tr, parts, cparams, seq.offsets(), motion, label, flat);
    labelled = true;
  };
  if (progress) progress->begin("clustering trajectories", 0);
  const TrajectoryClusters tc =
      clusterTrajectoriesOn(frames, tr, cparams, labelParts, merges_device);
  if (!labelled) labelParts(tc);
  const int nc = tc.groups;
  // Compact labels (a part may have lost every point to its neighbours).
  std::vector<int> count(nc, 0), id(nc, -1);
  for (int l : flat)
    if (l >= 0) ++count[l];
  num_clusters = 0;
  for (int c = 0; c < nc; ++c)
    if (count[c] > 0) id[c] = num_clusters++;
  for (int& l : flat)
    if (l >= 0) l = id[l];
  // A merge involving a vanished part: the survivor stands for the group.
  merges.clear();
  std::vector<int> rep(nc);
  std::iota(rep.begin(), rep.end(), 0);
  std::vector<int> rep_id(nc);
  for (int c = 0; c < nc; ++c) rep_id[c] = id[c];
  for (const ClusterMerge& m : tc.merges) {
    const int a = rep_id[m.a], b = rep_id[m.b];
    const int lo = std::min(m.a, m.b);
    if (a >= 0 && b >= 0) merges.push_back({std::min(a, b), std::max(a, b), m.cost});
    rep_id[lo] = a >= 0 ? (b >= 0 ? std::min(a, b) : a) : b;
  }
  // The parts' motions from frame 0 (they were tracked from the reference frame).
  if (part_motions) {
    part_motions->assign(num_clusters, std::vector<Eigen::Isometry3d>(T));
    for (int c = 0; c < nc; ++c) {
      if (id[c] < 0) continue;
      const Pose from0 = motion[c][0].inverse();
      for (int t = 0; t < T; ++t) (*part_motions)[id[c]][t] = motion[c][t] * from0;
    }
  }
  if (progress) progress->end(std::to_string(num_clusters) + " parts");
  beside.join();  // the caller's work, which must not throw: if it did, that is an error here
}

}  // namespace segmentation
}  // namespace pcl_animseg
