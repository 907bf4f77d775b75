// Tracked samples + trajectory clustering (see motion_tracking.h).
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/motion_tracking.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <queue>
#include <set>
#include <string>

namespace pcl_animseg {
namespace segmentation {

namespace {

using Cloud = PointCloudSequence::Cloud;
using Pose = Eigen::Isometry3d;

// Points whose normals disagree by more than this (cosine) are not matched: on thin parts
// (fingers, legs) the nearest point may lie on the opposite side.
constexpr double kNormalCos = 0.3;
// Residual distances are clipped at this many point spacings, so that one lost point does not
// dominate a fit's score.
constexpr double kClip = 4.0;

struct Frame {
  Cloud::Ptr cloud;
  pcl::KdTreeFLANN<pcl::PointNormal> tree;
  double spacing = 1.0;
};

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

/** RMS over the source of the clipped distance to the nearest point of the frame with a
 * compatible normal (in the frame's spacings). */
double residual(const Source& src, const Pose& T, const Frame& f) {
  if (src.p.cols() == 0) return 0.0;
  std::vector<int> idx(1);
  std::vector<float> d2(1);
  const double clip2 = kClip * kClip;
  const double inv_s2 = 1.0 / (f.spacing * f.spacing);
  double sum = 0.0;
  const Eigen::Matrix3d R = T.linear();
  for (Eigen::Index i = 0; i < src.p.cols(); ++i) {
    double e = clip2;
    if (f.tree.nearestKSearch(toPoint(T * src.p.col(i)), 1, idx, d2) == 1) {
      const auto& t = (*f.cloud)[idx[0]];
      const double c = (R * src.n.col(i)).dot(Eigen::Vector3d(t.normal_x, t.normal_y, t.normal_z));
      if (c > kNormalCos) e = std::min(clip2, d2[0] * inv_s2);
    }
    sum += e;
  }
  return std::sqrt(sum / static_cast<double>(src.p.cols()));
}

/** Damped point-to-plane ICP (plus a weak point-to-point term against sliding on symmetric
 * surfaces), linearised about the moved source's centroid for conditioning. The Levenberg
 * damping keeps the directions the source does not constrain (rotation about and translation
 * along a capsule) near the initial pose, which comes from a neighbour on the same part. */
Pose icp(const Source& src, const Pose& init, const Frame& f, int iterations, double max_dist) {
  Pose T = init;
  std::vector<int> idx(1);
  std::vector<float> d2(1);
  const double max_d2 = max_dist * max_dist;
  for (int it = 0; it < iterations; ++it) {
    const Eigen::Matrix3d R = T.linear();
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (Eigen::Index i = 0; i < src.p.cols(); ++i) c += T * src.p.col(i);
    c /= static_cast<double>(std::max<Eigen::Index>(1, src.p.cols()));
    Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> b = Eigen::Matrix<double, 6, 1>::Zero();
    int used = 0;
    for (Eigen::Index i = 0; i < src.p.cols(); ++i) {
      const Eigen::Vector3d yw = T * src.p.col(i);
      if (f.tree.nearestKSearch(toPoint(yw), 1, idx, d2) != 1) continue;
      if (d2[0] > max_d2) continue;
      const auto& t = (*f.cloud)[idx[0]];
      const Eigen::Vector3d tn(t.normal_x, t.normal_y, t.normal_z);
      if ((R * src.n.col(i)).dot(tn) < kNormalCos) continue;
      const Eigen::Vector3d tp(t.x, t.y, t.z);
      const Eigen::Vector3d y = yw - c;
      ++used;
      Eigen::Matrix<double, 6, 1> J;
      J.head<3>() = y.cross(tn);
      J.tail<3>() = tn;
      const double r = (yw - tp).dot(tn);
      A.noalias() += J * J.transpose();
      b.noalias() += J * r;
      Eigen::Matrix<double, 3, 6> Jp;
      Jp.block<3, 3>(0, 0) << 0, y.z(), -y.y(), -y.z(), 0, y.x(), y.y(), -y.x(), 0;
      Jp.block<3, 3>(0, 3).setIdentity();
      A.noalias() += 0.1 * Jp.transpose() * Jp;
      b.noalias() += 0.1 * Jp.transpose() * (yw - tp);
    }
    if (used < 6) break;
    const double tr_rot = A.block<3, 3>(0, 0).trace() / 3.0 + 1e-12;
    const double tr_tr = A.block<3, 3>(3, 3).trace() / 3.0 + 1e-12;
    for (int k = 0; k < 3; ++k) A(k, k) += 0.02 * tr_rot, A(k + 3, k + 3) += 0.02 * tr_tr;
    const Eigen::Matrix<double, 6, 1> x = A.ldlt().solve(-b);
    if (!x.allFinite()) break;
    const Eigen::Vector3d w = x.head<3>();
    const double angle = w.norm();
    Eigen::Matrix3d dR = Eigen::Matrix3d::Identity();
    if (angle > 1e-12) dR = Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
    // y' = dR (y - c) + c + dt.
    Pose D = Pose::Identity();
    D.linear() = dR;
    D.translation() = c - dR * c + x.tail<3>();
    T = D * T;
    if (angle < 1e-4 && x.tail<3>().norm() < 1e-3 * f.spacing) break;
  }
  return T;
}

/** Symmetric k-NN graph over a set of 3-D points. */
std::vector<std::vector<int>> knnGraphOf(const Eigen::Matrix3Xd& pts, int k) {
  const int n = static_cast<int>(pts.cols());
  Cloud::Ptr c(new Cloud);
  c->resize(n);
  for (int i = 0; i < n; ++i) (*c)[i] = toPoint(pts.col(i));
  std::vector<std::set<int>> nb(n);
  if (n > 1) {
    pcl::KdTreeFLANN<pcl::PointNormal> tree;
    tree.setInputCloud(c);
    std::vector<int> idx;
    std::vector<float> d2;
    for (int i = 0; i < n; ++i) {
      tree.nearestKSearch((*c)[i], std::min(k + 1, n), idx, d2);
      for (int j : idx)
        if (j != i) nb[i].insert(j), nb[j].insert(i);
    }
  }
  std::vector<std::vector<int>> g(n);
  for (int i = 0; i < n; ++i) g[i].assign(nb[i].begin(), nb[i].end());
  return g;
}

}  // namespace

std::vector<int> farthestPointSamples(const Cloud& cloud, int count, unsigned seed) {
  const int n = static_cast<int>(cloud.size());
  std::vector<int> out;
  if (n == 0 || count <= 0) return out;
  std::vector<Eigen::Vector3d> p(n);
  for (int i = 0; i < n; ++i) p[i] = Eigen::Vector3d(cloud[i].x, cloud[i].y, cloud[i].z);
  // A simple LCG step of the seed picks the start, identically on every platform.
  out.push_back(static_cast<int>((1103515245u * seed + 12345u) % static_cast<unsigned>(n)));
  std::vector<double> dmin(n, std::numeric_limits<double>::max());
  while (static_cast<int>(out.size()) < count) {
    const Eigen::Vector3d s = p[out.back()];
    int far = 0;
    for (int i = 0; i < n; ++i) {
      dmin[i] = std::min(dmin[i], (p[i] - s).squaredNorm());
      if (dmin[i] > dmin[far]) far = i;
    }
    if (dmin[far] <= 0.0) break;
    out.push_back(far);
  }
  return out;
}

SampleTracks trackSamples(const PointCloudSequence& seq, const MotionTrackingParams& params,
                          Progress* progress) {
  const int T = static_cast<int>(seq.size());
  if (T == 0) throw Error("motion tracking: the sequence has no frames");
  const int ref = params.reference_frame < 0 ? 0 : params.reference_frame;
  if (ref >= T)
    throw Error("motion tracking: reference frame " + std::to_string(ref) +
                " but the sequence has " + std::to_string(T) + " frames");
  if (params.neighbourhood < 6 || params.sample_neighbours < 1 || params.icp_iterations < 1)
    throw Error(
        "motion tracking: neighbourhood must be >= 6, sample_neighbours and "
        "icp_iterations >= 1");
  std::vector<Frame> frames(T);
  for (int t = 0; t < T; ++t) {
    frames[t].cloud = seq.frame(t);
    if (frames[t].cloud->empty())
      throw Error("motion tracking: frame " + std::to_string(t) + " has no points");
    frames[t].tree.setInputCloud(frames[t].cloud);
    frames[t].spacing = std::max(meanSpacing(*frames[t].cloud), 1e-9);
  }
  const Cloud& rc = *frames[ref].cloud;
  const int n0 = static_cast<int>(rc.size());
  const int want = params.samples > 0 ? params.samples : std::clamp(n0 / 8, 16, 1000);
  SampleTracks tr;
  tr.reference_frame = ref;
  tr.spacing = frames[ref].spacing;
  tr.sample_points = farthestPointSamples(rc, std::min(want, n0), params.seed);
  const int S = static_cast<int>(tr.sample_points.size());
  Eigen::Matrix3Xd p0(3, S);
  for (int s = 0; s < S; ++s) {
    const auto& q = rc[tr.sample_points[s]];
    p0.col(s) = Eigen::Vector3d(q.x, q.y, q.z);
  }
  tr.graph = knnGraphOf(p0, params.sample_neighbours);
  // Each sample's ICP source: its k nearest reference points (reference geometry: no drift).
  std::vector<Source> src(S);
  tr.neighbourhoods.resize(S);
  {
    const int k = std::min(params.neighbourhood, n0);
#pragma omp parallel
    {
      std::vector<int> idx;
      std::vector<float> d2;
#pragma omp for schedule(static)
      for (int s = 0; s < S; ++s) {
        frames[ref].tree.nearestKSearch(rc[tr.sample_points[s]], k, idx, d2);
        std::sort(idx.begin(), idx.end());
        src[s] = sourceOf(rc, idx, static_cast<std::size_t>(k));
        tr.neighbourhoods[s] = idx;
      }
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
  std::vector<Pose> global(T, Pose::Identity());
  if (progress) progress->begin("tracking samples", static_cast<std::size_t>(T));
  int done = 0;
  for (int dir : {+1, -1}) {
    for (int t = ref + dir; t >= 0 && t < T; t += dir) {
      const Frame& f = frames[t];
      const int tp = t - dir, tpp = t - 2 * dir;
      const bool has_pp = tpp >= 0 && tpp < T && (tpp - ref) * dir >= 0;
      // Global pose: the previous one and a constant-velocity guess, the better kept.
      {
        std::vector<Pose> inits{global[tp]};
        if (has_pp) inits.push_back(global[tp] * global[tpp].inverse() * global[tp]);
        double best = std::numeric_limits<double>::max();
        for (const Pose& init : inits) {
          const Pose cand = icp(whole, init, f, 30, 10.0 * f.spacing);
          const double r = residual(whole, cand, f);
          if (r < best) best = r, global[t] = cand;
        }
      }
      // Root: the sample best explained by the global pose.
      std::vector<double> groot(S);
#pragma omp parallel for schedule(static)
      for (int s = 0; s < S; ++s) groot[s] = residual(probe[s], global[t], f);
      const int root =
          static_cast<int>(std::min_element(groot.begin(), groot.end()) - groot.begin());
      // BFS levels from the root (unreached components start from their own best sample).
      std::vector<int> level(S, -1);
      std::vector<std::vector<int>> levels;
      std::vector<int> order(S);
      std::iota(order.begin(), order.end(), 0);
      std::stable_sort(order.begin(), order.end(),
                       [&](int a, int b) { return groot[a] < groot[b]; });
      order.insert(order.begin(), root);
      for (int start : order) {
        if (level[start] >= 0) continue;
        std::vector<int> cur{start};
        level[start] = static_cast<int>(levels.size());
        while (!cur.empty()) {
          levels.push_back(cur);
          std::vector<int> next;
          for (int s : cur)
            for (int o : tr.graph[s])
              if (level[o] < 0) level[o] = static_cast<int>(levels.size()), next.push_back(o);
          std::sort(next.begin(), next.end());
          cur.swap(next);
        }
      }
      std::vector<Pose>& pose = tr.poses[t];
      std::vector<double> res(S, 0.0);
      std::vector<char> solved(S, 0);
      for (const std::vector<int>& lv : levels) {
#pragma omp parallel for schedule(dynamic, 1)
        for (std::size_t li = 0; li < lv.size(); ++li) {
          const int s = lv[li];
          std::vector<Pose> cands{tr.poses[tp][s], global[t]};
          if (has_pp)
            cands.push_back(tr.poses[tp][s] * tr.poses[tpp][s].inverse() * tr.poses[tp][s]);
          for (int o : tr.graph[s])
            if (solved[o] && level[o] < level[s]) cands.push_back(pose[o]);
          // Score every start cheaply, refine the two best: ICP from all would triple the cost
          // for the same answer.
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
          res[s] = best;
        }
        for (int s : lv) solved[s] = 1;
      }
      tr.residual[t] = std::accumulate(res.begin(), res.end(), 0.0) / S;
      if (progress) progress->update(static_cast<std::size_t>(++done));
    }
  }
  tr.positions.resize(T);
  for (int t = 0; t < T; ++t) {
    tr.positions[t].resize(3, S);
    for (int s = 0; s < S; ++s) tr.positions[t].col(s) = tr.poses[t][s] * p0.col(s);
  }
  if (progress) progress->end(std::to_string(S) + " samples");
  return tr;
}

namespace {

std::vector<Frame> makeFrames(const PointCloudSequence& seq) {
  const int T = static_cast<int>(seq.size());
  std::vector<Frame> frames(T);
  for (int t = 0; t < T; ++t) {
    frames[t].cloud = seq.frame(t);
    if (frames[t].cloud->empty())
      throw Error("motion tracking: frame " + std::to_string(t) + " has no points");
    frames[t].tree.setInputCloud(frames[t].cloud);
    frames[t].spacing = std::max(meanSpacing(*frames[t].cloud), 1e-9);
  }
  return frames;
}

}  // namespace

TrajectoryClusters clusterTrajectories(const PointCloudSequence& seq, const SampleTracks& tr,
                                       const MotionTrackingParams& params) {
  const int S = static_cast<int>(tr.sample_points.size());
  const int T = static_cast<int>(tr.poses.size());
  const int ref = tr.reference_frame;
  TrajectoryClusters out;
  if (S == 0) return out;
  const std::vector<Frame> frames = makeFrames(seq);
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
  // Enough points to score a pose on a part; more only costs time.
  constexpr std::size_t kSourcePoints = 32;

  // Each group's residual under its own pose, per frame (half of every evaluation's work).
  std::vector<std::vector<double>> self(S, std::vector<double>(T, 0.0));
  auto selfResidual = [&](int g) {
    const Source sg = sourceOf(rc, points[g], kSourcePoints);
    for (int t = 0; t < T; ++t) self[g][t] = t == ref ? 0.0 : residual(sg, pose[g][t], frames[t]);
  };
#pragma omp parallel for schedule(dynamic, 8)
  for (int g = 0; g < S; ++g) selfResidual(g);

  // Cost of merging A and B, per frame: the better of the two groups' poses, scored by the worse
  // of A's and B's surface residuals under it (each side on its own, so that a small limb cannot
  // hide in a large torso's average); worst frame. Scoring poses by surface residuals, not by
  // sample positions, makes the cost blind to a sample sliding along a capsule, which a local
  // neighbourhood cannot see. Taking the better pose makes it robust to a sample lost in a frame.
  struct Eval {
    double cost = 0.0;
    std::vector<Pose> pose;
  };
  auto evaluate = [&](int a, int b) {
    const Source sa = sourceOf(rc, points[a], kSourcePoints);
    const Source sb = sourceOf(rc, points[b], kSourcePoints);
    Eval e;
    e.pose.resize(T);
    for (int t = 0; t < T; ++t) {
      if (t == ref) {
        e.pose[t] = pose[a][t];
        continue;
      }
      const double ca = std::max(self[a][t], residual(sb, pose[a][t], frames[t]));
      const double cb = std::max(residual(sa, pose[b][t], frames[t]), self[b][t]);
      e.pose[t] = ca <= cb ? pose[a][t] : pose[b][t];
      e.cost = std::max(e.cost, std::min(ca, cb));
    }
    return e;
  };
  std::map<std::pair<int, int>, Eval> edges;
  {
    std::vector<std::pair<int, int>> pairs;
    for (int s = 0; s < S; ++s)
      for (int o : tr.graph[s])
        if (s < o) pairs.push_back({s, o});
    std::vector<Eval> c(pairs.size());
#pragma omp parallel for schedule(dynamic, 16)
    for (std::size_t i = 0; i < pairs.size(); ++i) c[i] = evaluate(pairs[i].first, pairs[i].second);
    for (std::size_t i = 0; i < pairs.size(); ++i) edges[pairs[i]] = std::move(c[i]);
  }
  const int min_size = std::max(1, params.min_group_samples);
  auto merge = [&](int a, int b) {
    // b joins a.
    pose[a] = edges[{std::min(a, b), std::max(a, b)}].pose;
    members[a].insert(members[a].end(), members[b].begin(), members[b].end());
    members[b].clear();
    std::vector<int> u;
    std::set_union(points[a].begin(), points[a].end(), points[b].begin(), points[b].end(),
                   std::back_inserter(u));
    points[a].swap(u);
    points[b].clear();
    selfResidual(a);
    alive[b] = 0;
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
    const std::vector<int> nb(nbrs.begin(), nbrs.end());
    std::vector<Eval> c(nb.size());
#pragma omp parallel for schedule(dynamic, 1)
    for (std::size_t i = 0; i < nb.size(); ++i) c[i] = evaluate(a, nb[i]);
    for (std::size_t i = 0; i < nb.size(); ++i)
      edges[{std::min(a, nb[i]), std::max(a, nb[i])}] = std::move(c[i]);
  };
  auto cheapest = [&](auto pred) {
    auto best = edges.end();
    for (auto it = edges.begin(); it != edges.end(); ++it)
      if (pred(it->first) && (best == edges.end() || it->second.cost < best->second.cost))
        best = it;
    return best;
  };
  auto any = [](const std::pair<int, int>&) { return true; };
  auto countAlive = [&]() {
    int c = 0;
    for (int s = 0; s < S; ++s) c += alive[s];
    return c;
  };
  // Phase 1: merge until the stopping point.
  while (!edges.empty()) {
    const auto best = cheapest(any);
    if (params.target_clusters > 0 ? countAlive() <= params.target_clusters
                                   : best->second.cost > params.threshold)
      break;
    const auto [a, b] = best->first;
    merge(a, b);
  }
  // Tiny groups (a lost sample or two) join their cheapest neighbour whatever the cost.
  for (;;) {
    const auto best = cheapest([&](const std::pair<int, int>& e) {
      return static_cast<int>(members[e.first].size()) < min_size ||
             static_cast<int>(members[e.second].size()) < min_size;
    });
    if (best == edges.end()) break;
    const auto [a, b] = best->first;
    merge(a, b);
  }
  // Snapshot: final ids in order of each group's smallest sample.
  std::vector<int> id(S, -1);
  out.group.assign(S, -1);
  for (int s = 0; s < S; ++s) {
    if (!alive[s]) continue;
    const int lo = *std::min_element(members[s].begin(), members[s].end());
    id[s] = lo;  // provisional key
  }
  std::vector<int> roots;
  for (int s = 0; s < S; ++s)
    if (alive[s]) roots.push_back(s);
  std::sort(roots.begin(), roots.end(), [&](int x, int y) { return id[x] < id[y]; });
  std::vector<int> group_min(S, -1);
  for (std::size_t g = 0; g < roots.size(); ++g) {
    group_min[roots[g]] = static_cast<int>(g);
    for (int s : members[roots[g]]) out.group[s] = static_cast<int>(g);
    out.poses.push_back(pose[roots[g]]);
  }
  out.groups = static_cast<int>(roots.size());
  // Phase 2: the coarser hierarchy.
  while (!edges.empty()) {
    const auto best = cheapest(any);
    const auto [a, b] = best->first;
    const double c = best->second.cost;
    out.merges.push_back(
        {std::min(group_min[a], group_min[b]), std::max(group_min[a], group_min[b]), c});
    group_min[a] = std::min(group_min[a], group_min[b]);
    merge(a, b);
  }
  return out;
}

void segmentByTracking(const PointCloudSequence& seq, const MotionTrackingParams& params,
                       std::vector<int>& flat, int& num_clusters, std::vector<ClusterMerge>& merges,
                       Progress* progress) {
  const SampleTracks tr = trackSamples(seq, params, progress);
  if (progress) progress->begin("clustering trajectories", 0);
  const TrajectoryClusters tc = clusterTrajectories(seq, tr, params);
  if (progress) progress->end(std::to_string(tc.groups) + " parts");
  if (progress) progress->begin("part motions and labels", 0);
  const int T = static_cast<int>(seq.size());
  const int ref = tr.reference_frame;
  const int nc = tc.groups;
  const std::vector<Frame> frames = makeFrames(seq);
  const Cloud& rc = *frames[ref].cloud;
  const int n0 = static_cast<int>(rc.size());
  const int S = static_cast<int>(tr.sample_points.size());

  // Reference labels: the nearest sample's group.
  std::vector<int> label(n0, 0);
  {
    Cloud::Ptr sc(new Cloud);
    sc->resize(S);
    for (int s = 0; s < S; ++s) (*sc)[s] = rc[tr.sample_points[s]];
    pcl::KdTreeFLANN<pcl::PointNormal> st;
    st.setInputCloud(sc);
    std::vector<int> idx;
    std::vector<float> d2;
    for (int i = 0; i < n0; ++i)
      if (st.nearestKSearch(rc[i], 1, idx, d2) == 1) label[i] = tc.group[idx[0]];
  }
  // Part motions: the group's pose or the Kabsch fit of its samples, refined by ICP of the part's
  // reference points (a whole part is far better conditioned than a sample's neighbourhood); the
  // better kept.
  std::vector<std::vector<Pose>> motion(nc, std::vector<Pose>(T, Pose::Identity()));
  {
    std::vector<std::vector<int>> pts(nc), smp(nc);
    for (int i = 0; i < n0; ++i) pts[label[i]].push_back(i);
    for (int s = 0; s < S; ++s) smp[tc.group[s]].push_back(s);
#pragma omp parallel for schedule(dynamic, 1)
    for (int c = 0; c < nc; ++c) {
      const Source src = sourceOf(rc, pts[c], 400);
      const Eigen::Index m = static_cast<Eigen::Index>(smp[c].size());
      Eigen::Matrix3Xd a(3, m), b(3, m);
      for (int t = 0; t < T; ++t) {
        if (t == ref) continue;
        for (Eigen::Index k = 0; k < m; ++k)
          a.col(k) = tr.positions[ref].col(smp[c][k]), b.col(k) = tr.positions[t].col(smp[c][k]);
        const evaluation::RigidFit fit = evaluation::kabsch(a, b);
        Pose init = Pose::Identity();
        init.linear() = fit.rotation;
        init.translation() = fit.translation;
        if (residual(src, tc.poses[c][t], frames[t]) < residual(src, init, frames[t]))
          init = tc.poses[c][t];
        const Pose cand = icp(src, init, frames[t], 10, 4.0 * frames[t].spacing);
        motion[c][t] =
            residual(src, cand, frames[t]) <= residual(src, init, frames[t]) ? cand : init;
      }
    }
  }
  // Every reference point moves to the part (its own or a neighbour's) whose motion keeps it on
  // the surface best over all frames: the nearest-sample labels are coarse at joints.
  {
    const int kk = std::min(params.point_neighbours + 1, n0);
    std::vector<int> relabel(label);
#pragma omp parallel
    {
      std::vector<int> idx;
      std::vector<float> d2;
#pragma omp for schedule(dynamic, 64)
      for (int i = 0; i < n0; ++i) {
        frames[ref].tree.nearestKSearch(rc[i], kk, idx, d2);
        std::set<int> cands;
        for (int j : idx) cands.insert(label[j]);
        if (cands.size() < 2) continue;
        const Source one = sourceOf(rc, std::vector<int>{i}, 1);
        double best = std::numeric_limits<double>::max();
        for (int c : cands) {
          double sum = 0.0;
          for (int t = 0; t < T; ++t) {
            const double r = residual(one, motion[c][t], frames[t]);
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
      const Pose& M = motion[label[i]][t];
      const Eigen::Vector3d p = M * Eigen::Vector3d(rc[i].x, rc[i].y, rc[i].z);
      const Eigen::Vector3d nn =
          M.linear() * Eigen::Vector3d(rc[i].normal_x, rc[i].normal_y, rc[i].normal_z);
      auto& q = (*moved)[i];
      q = toPoint(p);
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
                  q.normal_z * fc[j].normal_z >
              kNormalCos) {
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
  if (progress) progress->end(std::to_string(num_clusters) + " parts");
}

}  // namespace segmentation
}  // namespace pcl_animseg
