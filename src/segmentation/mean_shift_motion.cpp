// The motion method of MeanShiftSegmentation (see mean_shift.h): patches of a reference frame,
// tracked rigidly through the sequence, merged by agreement of their motions.
#include "mean_shift_internal.h"

#include <pcl/kdtree/kdtree_flann.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/progress.h>

#include <Eigen/Dense>
#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <random>
#include <set>

namespace pcl_animseg {
namespace segmentation {
namespace detail {

namespace {

using Cloud = PointCloudSequence::Cloud;
using Transform = Eigen::Isometry3d;

struct Frame {
  Cloud::Ptr cloud;
  pcl::KdTreeFLANN<pcl::PointNormal> tree;
  double spacing = 1.0;
};

// Points whose normals disagree by more than this (cosine) are not matched: on thin parts
// (fingers, legs) the nearest point may lie on the opposite side.
constexpr double kNormalCos = 0.3;
// Distances are clipped at this many point spacings in residuals, so that one lost point does
// not dominate.
constexpr double kClip = 5.0;

struct Source {
  Eigen::Matrix3Xd p;
  Eigen::Matrix3Xd n;
};

Source sourceOf(const Cloud& ref, const std::vector<int>& idx, std::size_t max_points) {
  const std::size_t m = std::min(max_points, idx.size());
  Source s;
  s.p.resize(3, m);
  s.n.resize(3, m);
  for (std::size_t i = 0; i < m; ++i) {
    // Even stride, deterministic.
    const auto& q = ref[idx[i * idx.size() / m]];
    s.p.col(i) = Eigen::Vector3d(q.x, q.y, q.z);
    s.n.col(i) = Eigen::Vector3d(q.normal_x, q.normal_y, q.normal_z);
  }
  return s;
}

/** RMS over the source of the clipped distance to the nearest compatible target point, in
 * spacings of the target frame. */
double residual(const Source& src, const Transform& T, const Frame& f) {
  if (src.p.cols() == 0) return 0.0;
  std::vector<int> idx(1);
  std::vector<float> d2(1);
  const double clip2 = kClip * kClip;
  double sum = 0.0;
  const Eigen::Matrix3d R = T.linear();
  for (Eigen::Index i = 0; i < src.p.cols(); ++i) {
    const Eigen::Vector3d y = T * src.p.col(i);
    pcl::PointNormal q;
    q.x = static_cast<float>(y.x());
    q.y = static_cast<float>(y.y());
    q.z = static_cast<float>(y.z());
    double e = clip2;
    if (f.tree.nearestKSearch(q, 1, idx, d2) == 1) {
      const auto& t = (*f.cloud)[idx[0]];
      const double cosn = (R * src.n.col(i)).dot(Eigen::Vector3d(t.normal_x, t.normal_y, t.normal_z));
      if (cosn > kNormalCos) e = std::min(clip2, d2[0] / (f.spacing * f.spacing));
    }
    sum += e;
  }
  return std::sqrt(sum / src.p.cols());
}

/** Point-to-plane ICP (with a small point-to-point term against sliding along symmetric
 * surfaces) of the source onto the frame, starting from `init`. */
Transform icp(const Source& src, const Transform& init, const Frame& f, int iterations,
              double scale) {
  Transform T = init;
  std::vector<int> idx(1);
  std::vector<float> d2(1);
  double max_d = 0.15 * scale;
  std::vector<double> dists;
  for (int it = 0; it < iterations; ++it) {
    Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
    dists.clear();
    int used = 0;
    const Eigen::Matrix3d R = T.linear();
    for (Eigen::Index i = 0; i < src.p.cols(); ++i) {
      const Eigen::Vector3d y = T * src.p.col(i);
      pcl::PointNormal q;
      q.x = static_cast<float>(y.x());
      q.y = static_cast<float>(y.y());
      q.z = static_cast<float>(y.z());
      if (f.tree.nearestKSearch(q, 1, idx, d2) != 1) continue;
      const auto& t = (*f.cloud)[idx[0]];
      const Eigen::Vector3d tp(t.x, t.y, t.z), tn(t.normal_x, t.normal_y, t.normal_z);
      const double d = std::sqrt(d2[0]);
      dists.push_back(d);
      if (d > max_d || (R * src.n.col(i)).dot(tn) < kNormalCos) continue;
      ++used;
      Eigen::Matrix<double, 6, 1> J;
      J.head<3>() = y.cross(tn);
      J.tail<3>() = tn;
      const double r = (y - tp).dot(tn);
      A += J * J.transpose();
      b += J * r;
      // Point-to-point, weight 0.1: J = [-[y]x, I].
      Eigen::Matrix<double, 3, 6> Jp;
      Jp.block<3, 3>(0, 0) << 0, y.z(), -y.y(), -y.z(), 0, y.x(), y.y(), -y.x(), 0;
      Jp.block<3, 3>(0, 3).setIdentity();
      A += 0.1 * Jp.transpose() * Jp;
      b += 0.1 * Jp.transpose() * (y - tp);
    }
    if (used < 6) break;
    A.diagonal().array() += 1e-9 * A.trace();
    const Eigen::Matrix<double, 6, 1> x = A.ldlt().solve(-b);
    if (!x.allFinite()) break;
    const Eigen::Vector3d w = x.head<3>();
    Transform D = Transform::Identity();
    const double angle = w.norm();
    if (angle > 1e-12) D.linear() = Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
    D.translation() = x.tail<3>();
    T = D * T;
    // Tighten the inlier distance as the fit improves (3 x median, never below 2 spacings).
    std::nth_element(dists.begin(), dists.begin() + dists.size() / 2, dists.end());
    max_d = std::max(2.0 * f.spacing, std::min(max_d, 3.0 * dists[dists.size() / 2]));
    if (angle < 1e-5 && x.tail<3>().norm() < 1e-4 * f.spacing) break;
  }
  return T;
}

/** Tracks a source through all frames from the reference, frame to frame; at each frame the
 * ICP starts from the previous pose and from a constant-velocity prediction, and the better fit
 * is kept (a galloping leg reverses direction: neither guess is always right). */
std::vector<Transform> track(const Source& src, const std::vector<Frame>& frames, int ref,
                             int iterations, double scale) {
  const int T = static_cast<int>(frames.size());
  std::vector<Transform> traj(T, Transform::Identity());
  for (int dir : {+1, -1}) {
    for (int t = ref + dir; t >= 0 && t < T; t += dir) {
      const Transform prev = traj[t - dir];
      std::vector<Transform> inits{prev};
      const int t2 = t - 2 * dir;
      if (t2 >= 0 && t2 < T && t2 != t) inits.push_back((prev * traj[t2].inverse()) * prev);
      double best = std::numeric_limits<double>::max();
      for (const Transform& init : inits) {
        const Transform cand = icp(src, init, frames[t], iterations, scale);
        const double r = residual(src, cand, frames[t]);
        if (r < best) best = r, traj[t] = cand;
      }
    }
  }
  return traj;
}

/** Farthest-point seeds + a few k-means rounds in (position, normal) on the reference frame. */
std::vector<int> makePatches(const Cloud& ref, int k, unsigned seed) {
  const int n = static_cast<int>(ref.size());
  k = std::max(1, std::min(k, n));
  std::vector<Eigen::Vector3d> p(n), nr(n);
  for (int i = 0; i < n; ++i) {
    p[i] = Eigen::Vector3d(ref[i].x, ref[i].y, ref[i].z);
    nr[i] = Eigen::Vector3d(ref[i].normal_x, ref[i].normal_y, ref[i].normal_z);
  }
  std::mt19937 rng(seed);
  std::vector<int> seeds{static_cast<int>(rng() % n)};
  std::vector<double> dmin(n, std::numeric_limits<double>::max());
  while (static_cast<int>(seeds.size()) < k) {
    const Eigen::Vector3d s = p[seeds.back()];
    int far = 0;
    for (int i = 0; i < n; ++i) {
      dmin[i] = std::min(dmin[i], (p[i] - s).squaredNorm());
      if (dmin[i] > dmin[far]) far = i;
    }
    if (dmin[far] <= 0.0) break;  // fewer distinct points than patches
    seeds.push_back(far);
  }
  k = static_cast<int>(seeds.size());
  double radius2 = 0.0;  // squared FPS radius at the end = patch size
  for (int i = 0; i < n; ++i) radius2 = std::max(radius2, std::min(dmin[i], 1e300));
  if (k == 1) radius2 = 1.0;
  // Normal term: a normal turned by 90 degrees costs as much as half a patch radius squared.
  const double lambda = 0.25 * radius2;
  std::vector<Eigen::Vector3d> cp(k), cn(k);
  for (int c = 0; c < k; ++c) cp[c] = p[seeds[c]], cn[c] = nr[seeds[c]];
  std::vector<int> label(n, 0);
  for (int round = 0; round < 6; ++round) {
#pragma omp parallel for schedule(static)
    for (int i = 0; i < n; ++i) {
      double best = std::numeric_limits<double>::max();
      for (int c = 0; c < k; ++c) {
        const double d = (p[i] - cp[c]).squaredNorm() + lambda * (nr[i] - cn[c]).squaredNorm();
        if (d < best) best = d, label[i] = c;
      }
    }
    std::vector<Eigen::Vector3d> sp(k, Eigen::Vector3d::Zero()), sn(k, Eigen::Vector3d::Zero());
    std::vector<int> cnt(k, 0);
    for (int i = 0; i < n; ++i) sp[label[i]] += p[i], sn[label[i]] += nr[i], ++cnt[label[i]];
    for (int c = 0; c < k; ++c)
      if (cnt[c]) {
        cp[c] = sp[c] / cnt[c];
        cn[c] = sn[c].norm() > 1e-9 ? Eigen::Vector3d(sn[c].normalized()) : cn[c];
      }
  }
  // Compact ids (empty patches vanish), in order of first point.
  std::vector<int> id(k, -1);
  int next = 0;
  for (int i = 0; i < n; ++i) {
    if (id[label[i]] < 0) id[label[i]] = next++;
    label[i] = id[label[i]];
  }
  return label;
}

struct Cluster {
  std::vector<int> points;            // reference-frame indices
  std::vector<Transform> motion;      // per frame
  bool alive = true;
};

}  // namespace

void runMotion(const PointCloudSequence& seq, const MeanShiftParams& params,
               std::vector<int>& flat, int& num_clusters, std::vector<ClusterMerge>& merges,
               Progress* progress) {
  const int T = static_cast<int>(seq.size());
  const int ref = params.reference_frame < 0 ? 0 : params.reference_frame;
  if (ref >= T)
    throw Error("mean shift: reference frame " + std::to_string(ref) + " but the sequence has " +
                std::to_string(T) + " frames");
  const double raw_scale = sequenceScale(seq);
  if (!(raw_scale > 0.0)) {
    // Every point of every frame coincides: one part, nothing to track.
    flat.assign(seq.totalPoints(), 0);
    num_clusters = 1;
    return;
  }
  const double scale = raw_scale;
  std::vector<Frame> frames(T);
  for (int t = 0; t < T; ++t) {
    frames[t].cloud = seq.frame(t);
    frames[t].tree.setInputCloud(frames[t].cloud);
    frames[t].spacing = std::max(meanSpacing(*frames[t].cloud), 1e-6 * scale);
  }
  const Cloud& rc = *frames[ref].cloud;
  const int n0 = static_cast<int>(rc.size());
  const int k_patches = params.patches > 0
                            ? params.patches
                            : std::max(24, std::min(200, n0 / 25));
  if (progress) progress->begin("patches and tracking", 0);
  const std::vector<int> patch = makePatches(rc, k_patches, params.seed);
  const int np = *std::max_element(patch.begin(), patch.end()) + 1;
  std::vector<Cluster> cl(np);
  for (int i = 0; i < n0; ++i) cl[patch[i]].points.push_back(i);
#pragma omp parallel for schedule(dynamic, 1)
  for (int c = 0; c < np; ++c)
    cl[c].motion = track(sourceOf(rc, cl[c].points, 150), frames, ref, params.icp_iterations, scale);
  if (progress) progress->end(std::to_string(np) + " patches");
  // Adjacency of patches in the reference frame (k-NN edges, at least 2 of them).
  const int kk = params.neighbours;
  std::map<std::pair<int, int>, int> edges;
  {
    std::vector<int> idx;
    std::vector<float> d2;
    for (int i = 0; i < n0; ++i) {
      frames[ref].tree.nearestKSearch(rc[i], std::min(kk + 1, n0), idx, d2);
      for (int j : idx)
        if (patch[j] != patch[i])
          ++edges[{std::min(patch[i], patch[j]), std::max(patch[i], patch[j])}];
    }
  }
  std::set<std::pair<int, int>> adjacent;
  for (const auto& [e, c] : edges)
    if (c >= 2) adjacent.insert(e);

  // Cost of merging two clusters: per frame, the better of their two motions applied to the
  // union; averaged over frames.
  struct Eval {
    double cost = 0.0;
    std::vector<Transform> motion;
  };
  auto evaluate = [&](const Cluster& a, const Cluster& b) {
    std::vector<int> u = a.points;
    u.insert(u.end(), b.points.begin(), b.points.end());
    std::sort(u.begin(), u.end());
    const Source s = sourceOf(rc, u, 120);
    Eval e;
    e.motion.resize(T);
    for (int t = 0; t < T; ++t) {
      const double ra = residual(s, a.motion[t], frames[t]);
      const double rb = t == ref ? ra : residual(s, b.motion[t], frames[t]);
      e.motion[t] = ra <= rb ? a.motion[t] : b.motion[t];
      // Mean over frames: the worst frame alone was dominated by tracking failures (pooled ARI
      // 0.35 vs 0.51 on a generated quadruped).
      e.cost += std::min(ra, rb) / T;
    }
    return e;
  };
  std::map<std::pair<int, int>, Eval> cost;
  auto refresh = [&](const std::vector<std::pair<int, int>>& pairs) {
    std::vector<Eval> evals(pairs.size());
#pragma omp parallel for schedule(dynamic, 1)
    for (std::size_t i = 0; i < pairs.size(); ++i)
      evals[i] = evaluate(cl[pairs[i].first], cl[pairs[i].second]);
    for (std::size_t i = 0; i < pairs.size(); ++i) cost[pairs[i]] = std::move(evals[i]);
  };
  if (progress) progress->begin("merging by motion", 0);
  refresh(std::vector<std::pair<int, int>>(adjacent.begin(), adjacent.end()));
  int alive = np;
  bool stopped = false;
  std::vector<Cluster> snap;                 // the clusters when merging stopped
  std::vector<int> group_min(np, -1);        // alive cluster -> smallest final label in it
  auto takeSnapshot = [&]() {
    std::vector<int> ids;
    for (int c = 0; c < np; ++c)
      if (cl[c].alive) ids.push_back(c);
    // Final labels in order of each cluster's first reference point.
    std::sort(ids.begin(), ids.end(), [&](int x, int y) {
      return *std::min_element(cl[x].points.begin(), cl[x].points.end()) <
             *std::min_element(cl[y].points.begin(), cl[y].points.end());
    });
    for (std::size_t i = 0; i < ids.size(); ++i) {
      snap.push_back(cl[ids[i]]);
      group_min[ids[i]] = static_cast<int>(i);
    }
    stopped = true;
  };
  while (!cost.empty()) {
    auto best = cost.begin();
    for (auto it = cost.begin(); it != cost.end(); ++it)
      if (it->second.cost < best->second.cost) best = it;
    if (!stopped && (params.target_clusters > 0 ? alive <= params.target_clusters
                                                : best->second.cost > params.motion_threshold))
      takeSnapshot();
    const auto [a, b] = best->first;
    if (stopped) {
      merges.push_back({std::min(group_min[a], group_min[b]),
                        std::max(group_min[a], group_min[b]), best->second.cost});
      group_min[a] = std::min(group_min[a], group_min[b]);
    }
    // b joins a.
    cl[a].points.insert(cl[a].points.end(), cl[b].points.begin(), cl[b].points.end());
    cl[a].motion = std::move(best->second.motion);
    cl[b].alive = false;
    cl[b].points.clear();
    --alive;
    std::set<int> nbrs;
    for (auto it = cost.begin(); it != cost.end();) {
      const auto [x, y] = it->first;
      if (x == a || x == b || y == a || y == b) {
        const int o = (x == a || x == b) ? y : x;
        if (o != a && o != b) nbrs.insert(o);
        it = cost.erase(it);
      } else {
        ++it;
      }
    }
    std::vector<std::pair<int, int>> pairs;
    for (int o : nbrs) pairs.push_back({std::min(a, o), std::max(a, o)});
    refresh(pairs);
  }
  if (!stopped) takeSnapshot();
  if (progress) progress->end(std::to_string(snap.size()) + " parts");
  const int nc = static_cast<int>(snap.size());

  // Re-track every part as a whole (larger sources are better conditioned than patches),
  // starting from the motion found while merging; keep whichever fits better.
  if (progress) progress->begin("part motions and labels", 0);
#pragma omp parallel for schedule(dynamic, 1)
  for (int c = 0; c < nc; ++c) {
    const Source s = sourceOf(rc, snap[c].points, 400);
    for (int t = 0; t < T; ++t) {
      if (t == ref) continue;
      const Transform cand = icp(s, snap[c].motion[t], frames[t], params.icp_iterations, scale);
      if (residual(s, cand, frames[t]) < residual(s, snap[c].motion[t], frames[t]))
        snap[c].motion[t] = cand;
    }
  }
  std::vector<int> label(n0, -1);
  for (int c = 0; c < nc; ++c)
    for (int i : snap[c].points) label[i] = c;

  // Every reference point goes to the part (its own or a neighbour's) whose motion keeps it on
  // the surface best over all frames: patches straddling a joint are split where they bend.
  {
    std::vector<int> relabel(label);
#pragma omp parallel
    {
      std::vector<int> idx;
      std::vector<float> d2;
#pragma omp for schedule(dynamic, 64)
      for (int i = 0; i < n0; ++i) {
        frames[ref].tree.nearestKSearch(rc[i], std::min(kk + 1, n0), idx, d2);
        std::set<int> cands;
        for (int j : idx) cands.insert(label[j]);
        if (cands.size() < 2) continue;
        const Source one = sourceOf(rc, std::vector<int>{i}, 1);
        double best = std::numeric_limits<double>::max();
        for (int c : cands) {
          double sum = 0.0;
          for (int t = 0; t < T; ++t) {
            const double r = residual(one, snap[c].motion[t], frames[t]);
            sum += r * r;
          }
          if (sum < best - 1e-9 || (std::abs(sum - best) <= 1e-9 && c == label[i]))
            best = sum, relabel[i] = c;
        }
      }
    }
    label.swap(relabel);
  }

  // Labels of every frame: the nearest reference point moved by its part's motion, with a
  // compatible normal.
  const auto offsets = seq.offsets();
  flat.assign(seq.totalPoints(), -1);
  for (int t = 0; t < T; ++t) {
    const Cloud& fc = *frames[t].cloud;
    Cloud::Ptr moved(new Cloud);
    moved->resize(n0);
    for (int i = 0; i < n0; ++i) {
      const Transform& M = snap[label[i]].motion[t];
      const Eigen::Vector3d p = M * Eigen::Vector3d(rc[i].x, rc[i].y, rc[i].z);
      const Eigen::Vector3d nn =
          M.linear() * Eigen::Vector3d(rc[i].normal_x, rc[i].normal_y, rc[i].normal_z);
      auto& q = (*moved)[i];
      q.x = static_cast<float>(p.x());
      q.y = static_cast<float>(p.y());
      q.z = static_cast<float>(p.z());
      q.normal_x = static_cast<float>(nn.x());
      q.normal_y = static_cast<float>(nn.y());
      q.normal_z = static_cast<float>(nn.z());
    }
    pcl::KdTreeFLANN<pcl::PointNormal> mt;
    mt.setInputCloud(moved);
    const int n = static_cast<int>(fc.size());
    const int kq = std::min(8, n0);
#pragma omp parallel
    {
      std::vector<int> idx;
      std::vector<float> d2;
#pragma omp for schedule(static)
      for (int j = 0; j < n; ++j) {
        mt.nearestKSearch(fc[j], kq, idx, d2);
        int pick = idx.empty() ? -1 : idx[0];
        for (int m : idx) {
          const auto& q = (*moved)[m];
          if (q.normal_x * fc[j].normal_x + q.normal_y * fc[j].normal_y +
                  q.normal_z * fc[j].normal_z > kNormalCos) {
            pick = m;
            break;
          }
        }
        flat[offsets[t] + j] = pick < 0 ? -1 : label[pick];
      }
    }
  }
  // Compact labels (a part may have lost every point to its neighbours).
  std::vector<int> count(nc, 0), id(nc, -1);
  for (int l : flat)
    if (l >= 0) ++count[l];
  num_clusters = 0;
  for (int c = 0; c < nc; ++c)
    if (count[c] > 0) id[c] = num_clusters++;
  for (int& l : flat)
    if (l >= 0) l = id[l];
  std::vector<ClusterMerge> kept;
  for (const ClusterMerge& m : merges)
    if (id[m.a] >= 0 && id[m.b] >= 0) kept.push_back({id[m.a], id[m.b], m.cost});
  merges.swap(kept);
  if (progress) progress->end(std::to_string(num_clusters) + " parts");
}

}  // namespace detail
}  // namespace segmentation
}  // namespace pcl_animseg
