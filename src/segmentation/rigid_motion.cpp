#include <omp.h>
#include <pcl/common/centroid.h>
#include <pcl/common/common.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/segmentation/chained_fit.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/rigid_motion.h>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <iomanip>
#include <limits>
#include <memory>
#include <sstream>
#include <thread>
#include <tuple>

#include "mean_shift_internal.h"

namespace pcl_animseg {
namespace segmentation {

using Cloud = PointCloudSequence::Cloud;

RigidTransform RigidTransform::inverse() const {
  RigidTransform r = *this;
  r.rotation = rotation.transpose();
  r.translation = -(r.rotation * translation);
  return r;
}

icp_step::Rigid detail::toRigid(const RigidTransform& a) {
  icp_step::Rigid r;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) r.r[3 * i + j] = a.rotation(i, j);
    r.t[i] = a.translation[i];
  }
  return r;
}

namespace {

using detail::toRigid;

RigidTransform fromRigid(const icp_step::Rigid& a) {
  RigidTransform r;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) r.rotation(i, j) = a.r[3 * i + j];
    r.translation[i] = a.t[i];
  }
  return r;
}

// The indices of a part's points, evenly subsampled to at most max_points (0: all;
// deterministic, spread over the whole part).
std::vector<int> partIndices(const std::vector<int>& labels, int part, std::size_t max_points) {
  std::vector<int> idx;
  for (std::size_t j = 0; j < labels.size(); ++j)
    if (labels[j] == part) idx.push_back(static_cast<int>(j));
  const std::size_t n = idx.size();
  const std::size_t keep = max_points > 0 ? std::min(n, max_points) : n;
  std::vector<int> out(keep);
  for (std::size_t k = 0; k < keep; ++k) out[k] = idx[k * n / keep];
  return out;
}

// The points `idx` of `frame`, in that order.
Cloud::Ptr cloudOf(const Cloud& frame, const std::vector<int>& idx) {
  Cloud::Ptr out(new Cloud);
  out->reserve(idx.size());
  for (int j : idx) out->push_back(frame[j]);
  return out;
}

Cloud::Ptr partCloud(const Cloud& frame, const std::vector<int>& labels, int part,
                     std::size_t max_points) {
  return cloudOf(frame, partIndices(labels, part, max_points));
}

// Dominant axis of a part (unit, sign arbitrary) and how dominant it is (λ1 / λ2).
std::pair<Eigen::Vector3d, double> principalAxis(const Cloud& cloud) {
  // Zero for an empty cloud, which PCL leaves unwritten.
  Eigen::Vector4f c = Eigen::Vector4f::Zero();
  Eigen::Matrix3f cov = Eigen::Matrix3f::Zero();
  pcl::computeMeanAndCovarianceMatrix(cloud, cov, c);
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3f> es(cov);
  const Eigen::Vector3f ev = es.eigenvalues();  // ascending
  return {es.eigenvectors().col(2).cast<double>(),
          ev[1] > 0.0f ? static_cast<double>(ev[2] / ev[1]) : 1e9};
}

// Points of each of a labelling's parts in frame 0.
std::vector<std::size_t> frame0Counts(const std::vector<std::vector<int>>& labels, int parts) {
  std::vector<std::size_t> counts(static_cast<std::size_t>(parts), 0);
  for (int l : labels[0])
    if (l >= 0 && l < parts) ++counts[l];
  return counts;
}

// A part's motion before any frame is fitted: no estimate anywhere, frame 0 the identity when the
// part has enough source points (returned).
bool startMotion(PartMotion& motion, std::size_t frames, std::size_t points_frame0,
                 const Cloud& source, int min_points) {
  motion.frames.assign(frames, RigidTransform());
  for (RigidTransform& r : motion.frames) r.rms = -1.0;
  motion.points_frame0 = points_frame0;
  if (static_cast<int>(source.size()) < min_points) return false;
  motion.frames[0].valid = true;
  motion.frames[0].rms = 0.0;
  return true;
}

// Frame t's start from the previous frame's motion, re-centred on this frame's part centroid: the
// rotation changes little between frames, the translation can change a lot. An elongated part
// (a limb) can turn a lot between frames; turning the previous estimate so that the part's long
// axis matches the new frame's gives ICP a start in the right basin (the roll about the axis is
// left to ICP). Blob-like parts skip this. c0, axis0, ratio0: the source's centroid and principal
// axis; ct, axis, ratio: the target's.
RigidTransform chainedGuess(const RigidTransform& prev, const Eigen::Vector3d& c0,
                            const Eigen::Vector3d& axis0, double ratio0, const Eigen::Vector3d& ct,
                            const Eigen::Vector3d& axis, double ratio) {
  RigidTransform guess = prev;
  if (ratio > 2.0 && ratio0 > 2.0) {
    const Eigen::Vector3d from = prev.rotation * axis0;
    const Eigen::Vector3d to = from.dot(axis) >= 0.0 ? axis : Eigen::Vector3d(-axis);
    guess.rotation = Eigen::Quaterniond::FromTwoVectors(from, to).toRotationMatrix() * prev.rotation;
  }
  guess.translation = ct - guess.rotation * c0;
  return guess;
}

// The transform of an ICP result with its residual; valid when the residual is finite.
RigidTransform fitted(const icp_step::Rigid& m, double rms) {
  RigidTransform r = fromRigid(m);
  r.rms = rms;
  r.valid = std::isfinite(rms);
  return r;
}

// A part's points in one frame, as an ICP target: the cloud, a tree over its positions and the
// normals in the tree's leaf order (what a RigidFitDevice is given).
struct Surface {
  Cloud::Ptr cloud;
  FlatKdTree3 tree;
  std::vector<float> leaf_normals;
  void build(Cloud::Ptr c) {
    cloud = std::move(c);
    std::vector<float> xyz;
    xyz.reserve(3 * cloud->size());
    for (const auto& q : *cloud) xyz.insert(xyz.end(), {q.x, q.y, q.z});
    tree.build(xyz.data(), cloud->size());
    leaf_normals.clear();
    leaf_normals.reserve(3 * cloud->size());
    for (int row : tree.leafRows()) {
      const auto& q = (*cloud)[row];
      leaf_normals.insert(leaf_normals.end(), {q.normal_x, q.normal_y, q.normal_z});
    }
  }
};

// A source's positions as x, y, z triples (double).
std::vector<double> sourceXyz(const Cloud& c) {
  std::vector<double> xyz;
  xyz.reserve(3 * c.size());
  for (const auto& q : c) xyz.insert(xyz.end(), {q.x, q.y, q.z});
  return xyz;
}

// RMS distance from the moved source to its nearest target points (no bound: every point
// counts, as PCL's Registration::getFitnessScore() measured it), NaN when a point finds none.
// Added by ranges (icp_step::rangeBegin), as the GPU adds them.
double fitness(const std::vector<double>& src, const FlatKdTree3& tree, const icp_step::Rigid& T) {
  const int n = static_cast<int>(src.size() / 3);
  if (n == 0) return std::numeric_limits<double>::quiet_NaN();
  double sum = 0.0;
  for (int j = 0; j < icp_step::kSumRanges; ++j) {
    double part = 0.0;
    for (int i = icp_step::rangeBegin(j, n), e = icp_step::rangeBegin(j + 1, n); i < e; ++i) {
      double y[3];
      icp_step::apply(T, &src[3 * static_cast<std::size_t>(i)], y);
      const float q[3] = {static_cast<float>(y[0]), static_cast<float>(y[1]),
                          static_cast<float>(y[2])};
      float d2 = 0.0f;
      if (tree.nearestLeaf(q, std::numeric_limits<float>::infinity(), d2) < 0)
        return std::numeric_limits<double>::quiet_NaN();
      part += d2;
    }
    sum += part;
  }
  return std::sqrt(sum / static_cast<double>(n));
}

// One ICP pass of the rigid motions from T: every source point matched to its nearest target
// point within max_dist; the step point-to-point (`plane` false: the wide passes, where
// point-to-plane's system is nearly singular on a limb) or point-to-plane, linearised about the
// moved source's centroid and solved damped (icp_step.h: the motion method's arithmetic, so that
// a device can give the same bits; the sums by ranges, icp_step::rangeBegin). Converged, as
// PCL's DefaultConvergenceCriteria judge it (icp_step::rigidStep), when a step turns by less
// than rigidStepMaxTurn() and moves by less than transformation_epsilon spacings, or the
// matches' mean squared distance changes by less than relative_mse_epsilon. Written by us in
// place of
// pcl::IterativeClosestPoint(WithNormals), whose sums a GPU could not reproduce; the passes are
// the same.
icp_step::Rigid icpPass(const std::vector<double>& src, const FlatKdTree3& tree,
                        const std::vector<float>& leaf_normals, icp_step::Rigid T, double max_dist,
                        int iterations, bool plane, double spacing, const RigidMotionParams& p) {
  const int n = static_cast<int>(src.size() / 3);
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  const double max_turn = rigidStepMaxTurn(), max_move = p.transformation_epsilon * spacing;
  std::vector<double> moved(src.size());
  double prev_mse = -1.0;
  constexpr int kCols = icp_step::kTerms + 2;  // the terms, the squared distances, the count
  for (int it = 0; it < iterations; ++it) {
    double c[3] = {0.0, 0.0, 0.0};
    for (int j = 0; j < icp_step::kSumRanges; ++j) {
      double part[3] = {0.0, 0.0, 0.0};
      for (int i = icp_step::rangeBegin(j, n), e = icp_step::rangeBegin(j + 1, n); i < e; ++i) {
        double* y = &moved[3 * static_cast<std::size_t>(i)];
        icp_step::apply(T, &src[3 * static_cast<std::size_t>(i)], y);
        for (int k = 0; k < 3; ++k) part[k] += y[k];
      }
      for (int k = 0; k < 3; ++k) c[k] += part[k];
    }
    for (int k = 0; k < 3; ++k) c[k] /= static_cast<double>(n > 0 ? n : 1);
    double sums[kCols] = {};
    for (int j = 0; j < icp_step::kSumRanges; ++j) {
      double part[kCols] = {};
      for (int i = icp_step::rangeBegin(j, n), e = icp_step::rangeBegin(j + 1, n); i < e; ++i) {
        const double* y = &moved[3 * static_cast<std::size_t>(i)];
        const float q[3] = {static_cast<float>(y[0]), static_cast<float>(y[1]),
                            static_cast<float>(y[2])};
        float d2 = 0.0f;
        const int k = tree.nearestLeaf(q, max_d2, d2);
        if (k < 0) continue;
        const float* a = &tree.leafPoints()[3 * static_cast<std::size_t>(k)];
        const float* b = &leaf_normals[3 * static_cast<std::size_t>(k)];
        const double tp[3] = {a[0], a[1], a[2]}, tn[3] = {b[0], b[1], b[2]};
        double terms[icp_step::kTerms];
        icp_step::weightedTerms(y, c, tp, tn, plane ? 1.0 : 0.0, plane ? 0.0 : 1.0, terms);
        for (int q2 = 0; q2 < icp_step::kTerms; ++q2) part[q2] += terms[q2];
        part[icp_step::kTerms] += d2;
        part[icp_step::kTerms + 1] += 1.0;
      }
      for (int q2 = 0; q2 < kCols; ++q2) sums[q2] += part[q2];
    }
    if (!icp_step::rigidStep(sums, c, max_turn, max_move, p.relative_mse_epsilon, T, prev_mse))
      break;
  }
  return T;
}

// ICP of a part's frame-0 points (source) onto the part in frame t (target) from `start`, with an
// annealed rejection distance: wide first passes capture a large motion between frames, the last
// pass uses a few point spacings so that neighbouring parts' points (mislabelled near a
// boundary) do not pull. The wide passes are point-to-point: point-to-plane's linear system is
// nearly singular on a limb (a tube slides along and spins about its axis) and can throw the
// estimate far off while correspondences are still poor. Returns the transform; `rms` its RMS
// nearest-point distance.
icp_step::Rigid alignPasses(const std::vector<double>& source, const FlatKdTree3& tree,
                            const std::vector<float>& leaf_normals, const icp_step::Rigid& start,
                            double spacing, double part_diag, const RigidMotionParams& p,
                            double& rms, bool wide) {
  const double fine = p.max_correspondence_spacings * spacing;
  const double coarse = std::max(fine, p.coarse_distance * part_diag);
  const double passes[2] = {coarse, std::max(fine, coarse / 6.0)};
  icp_step::Rigid m = start;
  for (double distance : passes) {
    if (!wide) break;
    m = icpPass(source, tree, leaf_normals, m, distance, std::max(1, p.max_iterations / 2), false,
                spacing, p);
  }
  m = icpPass(source, tree, leaf_normals, m, fine, p.max_iterations, false, spacing, p);
  rms = fitness(source, tree, m);
  // Final point-to-plane pass (sub-spacing accuracy on sampled surfaces); kept only when it
  // lowers the residual, so a degenerate part cannot make the estimate worse.
  const icp_step::Rigid plane =
      icpPass(source, tree, leaf_normals, m, fine, p.max_iterations, true, spacing, p);
  const double rms_plane = fitness(source, tree, plane);
  if (rms_plane <= rms) {
    m = plane;
    rms = rms_plane;
  }
  return m;
}

icp_step::Rigid alignPasses(const std::vector<double>& source, const Surface& target,
                            const icp_step::Rigid& start, double spacing, double part_diag,
                            const RigidMotionParams& p, double& rms, bool wide = true) {
  return alignPasses(source, target.tree, target.leaf_normals, start, spacing, part_diag, p, rms,
                     wide);
}

// A part's motion along the sequence, frame t from frame t-1: the ICP passes (alignPasses) start
// from the last valid estimate re-centred and turned onto the part in frame t (chainedGuess). A
// frame without enough points, or whose ICP fails, has no estimate and passes the last valid
// one on. With `init` (its frames[t] where valid) there is one more start in every frame: the
// better of the two by the RMS nearest-point distance of (up to kScorePoints of) the source
// under each, and a start from init skips the wide passes. With good starts in every frame (the
// motions of nearly the same labels) the chain is rarely needed, so the frames of all such parts
// run in parallel (fitAlongChains: the same result as one frame after the other).
class ChainedPart {
 public:
  // A link of the chain: frame t's estimate, and the last valid one up to t (what the next
  // frame's guess starts from).
  struct Link {
    RigidTransform fit, carry;
    bool from_init = false;
  };

  // Sets `motion` up (startMotion); the frames' targets are built by buildTarget (buildTargets:
  // every part's frames in one parallel loop).
  ChainedPart(const PointCloudSequence& seq, const RigidMotionParams& p,
              const std::vector<std::vector<int>>& labels, int part,
              const std::vector<double>& spacing, std::size_t points_frame0, const PartMotion* init,
              PartMotion& motion)
      : p_(p),
        spacing_(spacing),
        init_(init),
        motion_(motion),
        frames_(seq.size()),
        seq_(seq),
        labels_(labels),
        part_(part) {
    source_ = partCloud(*seq.frame(0), labels[0], part, p.max_points);
    active_ = startMotion(motion, frames_, points_frame0, *source_, p.min_points);
    if (!active_) return;
    seeded_ = init && init->frames.size() == frames_;
    Eigen::Vector4f c0f;
    pcl::compute3DCentroid(*source_, c0f);
    c0_ = c0f.head<3>().cast<double>();
    part_diag_ = boundingBoxDiagonal(*source_);
    std::tie(axis0_, ratio0_) = principalAxis(*source_);
    xyz0_ = sourceXyz(*source_);
    // Scoring is needed only to choose between two starts.
    constexpr std::size_t kScorePoints = 500;
    probes_ = seeded_ ? static_cast<int>(std::min(source_->size(), kScorePoints)) : 0;
    targets_.resize(frames_);
  }

  // Frame t's target (t >= 1, an active part): the part's points in frame t, their tree, centroid
  // and principal axis.
  // `points`, where given, are the part's points of frame t in index order (partIndices'),
  // found by the caller.
  void buildTarget(std::size_t t, const std::vector<int>* points = nullptr) {
    Target& g = targets_[t];
    g.surface.build(points ? cloudOf(*seq_.frame(t), *points)
                           : partCloud(*seq_.frame(t), labels_[t], part_, 0));
    const Cloud& cloud = *g.surface.cloud;
    g.usable = static_cast<int>(cloud.size()) >= p_.min_points;
    if (!g.usable) return;
    Eigen::Vector4f ct;
    pcl::compute3DCentroid(cloud, ct);
    g.centroid = ct.head<3>().cast<double>();
    std::tie(g.axis, g.ratio) = principalAxis(cloud);
  }

  bool active() const { return active_; }
  const std::vector<std::vector<int>>& labels() const { return labels_; }
  int part() const { return part_; }
  Link first() const { return {motion_.frames[0], motion_.frames[0], false}; }

  // Frame t's starts; `before`: the frame it is fitted after (chainFrames).
  std::vector<ChainStart<Link>> starts(int t, int before, const std::vector<Link>* fits) const {
    std::vector<ChainStart<Link>> s;
    if (seeded_ && init_->frames[t].valid)
      s.push_back({{init_->frames[t], init_->frames[t], true}, false});
    if (fits) {
      const Target& g = targets_[t];
      const RigidTransform& last = (*fits)[before].carry;
      const RigidTransform guess =
          g.usable ? chainedGuess(last, c0_, axis0_, ratio0_, g.centroid, g.axis, g.ratio) : last;
      s.push_back({{guess, last, false}, true});
    }
    return s;
  }

  // Whether frame t's starts are scored (else each scores 0), and by how many probes.
  bool scored(int t) const { return seeded_ && targets_[t].usable; }
  int probes() const { return probes_; }
  double score(int t, const Link& x) const {
    if (!scored(t)) return 0.0;
    double pose[12];
    icp_step::store(toRigid(x.fit), pose);
    return rigidScore(xyz0_, probes_, targets_[t].surface.tree, pose);
  }

  Link fitFrom(int t, const Link& start) const {
    if (!usable(t)) return unfitted(start);
    double rms = 0.0;
    const icp_step::Rigid m = alignPasses(xyz0_, targets_[t].surface, toRigid(start.fit),
                                          spacing_[t], part_diag_, p_, rms, !start.from_init);
    return withFit(start, m, rms);
  }

  // fitFrom in parts, for a device: whether frame t can be fitted, the job of a fit from
  // `start` (source and surface left to the caller), and the link of its result (or of none).
  bool usable(int t) const { return targets_[t].usable; }
  RigidFitJob job(int t, const Link& start) const {
    RigidFitJob j;
    icp_step::store(toRigid(start.fit), j.start);
    j.spacing = spacing_[t];
    j.part_diag = part_diag_;
    j.wide = !start.from_init;
    return j;
  }
  Link unfitted(const Link& start) const {
    Link out;
    out.carry = start.carry;
    out.fit = start.carry;
    out.fit.valid = false;
    out.fit.rms = -1.0;
    return out;
  }
  Link withFit(const Link& start, const icp_step::Rigid& m, double rms) const {
    Link out = unfitted(start);
    out.fit = fitted(m, rms);
    if (out.fit.valid) out.carry = out.fit;
    return out;
  }
  const Surface& surface(int t) const { return targets_[t].surface; }
  const std::vector<double>& source() const { return xyz0_; }

  static bool same(const Link& a, const Link& b) {
    auto sameTransform = [](const RigidTransform& x, const RigidTransform& y) {
      return x.rotation == y.rotation && x.translation == y.translation && x.valid == y.valid;
    };
    return sameTransform(a.fit, b.fit) && sameTransform(a.carry, b.carry);
  }

  void finish(const std::vector<Link>& chain) {
    for (std::size_t t = 1; t < frames_; ++t) motion_.frames[t] = chain[t].fit;
  }

 private:
  struct Target {
    Surface surface;
    bool usable = false;
    Eigen::Vector3d centroid = Eigen::Vector3d::Zero(), axis = Eigen::Vector3d::UnitX();
    double ratio = 1.0;
  };
  const RigidMotionParams& p_;
  const std::vector<double>& spacing_;
  const PartMotion* init_;
  PartMotion& motion_;
  std::size_t frames_;
  const PointCloudSequence& seq_;
  const std::vector<std::vector<int>>& labels_;
  int part_;
  Cloud::Ptr source_;
  std::vector<double> xyz0_;  // source_'s positions
  bool active_ = false, seeded_ = false;
  Eigen::Vector3d c0_ = Eigen::Vector3d::Zero(), axis0_ = Eigen::Vector3d::UnitX();
  double ratio0_ = 1.0, part_diag_ = 0.0;
  int probes_ = 0;  // rigidScore's probes (seeded parts only)
  std::vector<Target> targets_;
};

// The targets of every active part's frames (ChainedPart::buildTarget) in one parallel loop: a
// loop per part left most threads waiting at each loop's end (20 parts of 47 frames at 800k).
void buildTargets(const std::vector<std::unique_ptr<ChainedPart>>& parts, std::size_t frames) {
  // Each labelling's frames' points by part, in one pass over a frame's labels (a part's own
  // pass over the whole frame, 22 of them a frame at 800k, was a fifth of the targets' CPU time).
  std::vector<const std::vector<std::vector<int>>*> sets;
  std::vector<int> set_of(parts.size(), -1);
  for (std::size_t k = 0; k < parts.size(); ++k) {
    if (!parts[k]->active()) continue;
    const auto* l = &parts[k]->labels();
    const auto at = std::find(sets.begin(), sets.end(), l);
    set_of[k] = static_cast<int>(at - sets.begin());
    if (at == sets.end()) sets.push_back(l);
  }
  // points[s][t][part]: labelling s's points of frame t with that label, in index order.
  std::vector<std::vector<std::vector<std::vector<int>>>> points(
      sets.size(), std::vector<std::vector<std::vector<int>>>(frames));
  const long buckets = static_cast<long>(sets.size() * frames);
#pragma omp parallel for schedule(dynamic)
  for (long b = 0; b < buckets; ++b) {
    const std::size_t s = static_cast<std::size_t>(b) / frames,
                      t = static_cast<std::size_t>(b) % frames;
    if (t == 0) continue;
    const std::vector<int>& lab = (*sets[s])[t];
    std::vector<std::vector<int>>& out = points[s][t];
    for (std::size_t j = 0; j < lab.size(); ++j) {
      if (lab[j] < 0) continue;
      if (static_cast<std::size_t>(lab[j]) >= out.size()) out.resize(lab[j] + 1);
      out[lab[j]].push_back(static_cast<int>(j));
    }
  }
  const std::vector<int> none;
  std::vector<std::pair<std::size_t, std::size_t>> items;  // (part, frame)
  for (std::size_t k = 0; k < parts.size(); ++k)
    if (parts[k]->active())
      for (std::size_t t = 1; t < frames; ++t) items.push_back({k, t});
  const long n = static_cast<long>(items.size());
#pragma omp parallel for schedule(dynamic)
  for (long i = 0; i < n; ++i) {
    const auto [k, t] = items[i];
    const std::vector<std::vector<int>>& by_part = points[set_of[k]][t];
    const std::size_t part = static_cast<std::size_t>(parts[k]->part());
    parts[k]->buildTarget(t, part < by_part.size() ? &by_part[part] : &none);
  }
}

// One computation's fits on a device: its sources and surfaces uploaded once (by id, in the
// order added), then batches of jobs.
class DeviceFits {
 public:
  explicit DeviceFits(RigidFitDevice& device) : device_(device) {}
  int addSource(const std::vector<double>& xyz) {
    sources_.push_back(&xyz);
    return static_cast<int>(sources_.size()) - 1;
  }
  int addSurface(const Surface& s) {
    DeviceFrames::Frame f;
    f.tree = &s.tree;
    f.leaf_normals_of = &s.leaf_normals;  // the surfaces outlive upload(): not copied
    surfaces_.frames.push_back(f);
    return static_cast<int>(surfaces_.frames.size()) - 1;
  }
  void upload() {
    device_.setSurfaces(surfaces_);
    device_.setSources(sources_);
    surfaces_ = DeviceFrames();  // the device has its copy
  }
  void fit(const std::vector<RigidFitJob>& jobs, const RigidMotionParams& p,
           std::vector<icp_step::Rigid>& poses, std::vector<double>& rms) {
    std::vector<double> flat;
    device_.fit(jobs, p, flat, rms);
    if (flat.size() != 12 * jobs.size() || rms.size() != jobs.size())
      throw Error("rigid motion: the device returned " + std::to_string(rms.size()) + " fits for " +
                  std::to_string(jobs.size()));
    poses.resize(jobs.size());
    for (std::size_t j = 0; j < jobs.size(); ++j) poses[j] = icp_step::load(&flat[12 * j]);
  }

 private:
  RigidFitDevice& device_;
  std::vector<const std::vector<double>*> sources_;
  DeviceFrames surfaces_;
};

// The parts of `parts` that have a motion to fit.
std::vector<ChainedPart*> activeOf(const std::vector<std::unique_ptr<ChainedPart>>& parts) {
  std::vector<ChainedPart*> act;
  for (const auto& c : parts)
    if (c->active()) act.push_back(c.get());
  return act;
}

// The sources (by chain) and surfaces (chain * frames + t) of the chains `act` on a device.
std::unique_ptr<DeviceFits> uploadChains(const std::vector<ChainedPart*>& act, int frames,
                                         RigidFitDevice& device) {
  auto dev = std::make_unique<DeviceFits>(device);
  for (ChainedPart* c : act) {
    dev->addSource(c->source());
    for (int t = 0; t < frames; ++t) dev->addSurface(c->surface(t));
  }
  dev->upload();
  return dev;
}

// The chains of several parts with every fit on a device, in batches (fitChainsBatched: the
// same links as fitChains and the serial chains). speculate: the frames of all chains side by
// side (parts with a start of their own in every frame); otherwise one frame position of every
// chain per batch.
// `uploaded`: uploadChains(act, ...)'s, or null (uploaded here).
std::vector<std::vector<ChainedPart::Link>> fitOnDevice(const std::vector<ChainedPart*>& act,
                                                        int frames, RigidFitDevice& device,
                                                        const RigidMotionParams& p, bool speculate,
                                                        DeviceFits* uploaded) {
  using Link = ChainedPart::Link;
  using Clock = std::chrono::steady_clock;
  auto since = [](Clock::time_point t0) {
    return std::chrono::duration<double>(Clock::now() - t0).count();
  };
  const auto t_begin = Clock::now();
  std::unique_ptr<DeviceFits> own;
  if (!uploaded) own = uploadChains(act, frames, device);
  DeviceFits& dev = uploaded ? *uploaded : *own;
  const double t_upload = since(t_begin);
  auto fitBatch = [&](const std::vector<ChainFit<Link>>& jobs) {
    std::vector<Link> out(jobs.size());
    std::vector<RigidFitJob> fits;
    std::vector<std::size_t> at;
    for (std::size_t j = 0; j < jobs.size(); ++j) {
      const ChainedPart& c = *act[jobs[j].chain];
      out[j] = c.unfitted(jobs[j].start);
      if (!c.usable(jobs[j].frame)) continue;
      RigidFitJob f = c.job(jobs[j].frame, jobs[j].start);
      f.source = jobs[j].chain;
      f.surface = jobs[j].chain * frames + jobs[j].frame;
      fits.push_back(f);
      at.push_back(j);
    }
    if (fits.empty()) return out;
    std::vector<icp_step::Rigid> poses;
    std::vector<double> rms;
    dev.fit(fits, p, poses, rms);
    for (std::size_t k = 0; k < at.size(); ++k)
      out[at[k]] = act[jobs[at[k]].chain]->withFit(jobs[at[k]].start, poses[k], rms[k]);
    return out;
  };
  // The starts' scores on the device where it offers them (the same bits: rigidScore), against
  // the surfaces and sources uploaded for the fits; else on the cores (800k: 2182 starts of up
  // to 500 probes each, 0.012 s of the seeded fits' 0.047 s on 16 cores).
  auto scoreBatch = [&](const std::vector<ChainScore<Link>>& items) {
    std::vector<double> out(items.size(), 0.0);
    std::vector<RigidScoreJob> jobs;
    std::vector<std::size_t> at;
    for (std::size_t j = 0; j < items.size(); ++j) {
      const ChainedPart& c = *act[items[j].chain];
      if (!c.scored(items[j].frame)) continue;  // scores 0
      RigidScoreJob s;
      s.source = items[j].chain;
      s.surface = items[j].chain * frames + items[j].frame;
      s.probes = c.probes();
      icp_step::store(toRigid(items[j].pose.fit), s.pose);
      jobs.push_back(s);
      at.push_back(j);
    }
    if (jobs.empty()) return out;
    std::vector<double> r;
    if (!device.scores(jobs, r)) {
      auto score = [&](int c, int t, const Link& x) { return act[c]->score(t, x); };
      return scoreEach(items, score);
    }
    if (r.size() != jobs.size())
      throw Error("rigid motion: the device returned " + std::to_string(r.size()) + " scores for " +
                  std::to_string(jobs.size()));
    for (std::size_t k = 0; k < at.size(); ++k) out[at[k]] = r[k];
    return out;
  };
  // Where the time goes (ANIMSEG_MS_TIMING): the fit batches and the score batches.
  detail::StageTimer timer("rigid motion");
  BatchTally fit_tally, score_tally;
  // Speculative rounds cost a device little and save batches of step 3.
  auto out = fitChainsBatched(
      static_cast<int>(act.size()), frames, 0, act.front()->first(),
      [&](int c, int t, const ChainStep& step, const std::vector<Link>* fits) {
        return act[c]->starts(t, step.before, fits);
      },
      tallied(score_tally, scoreBatch), tallied(fit_tally, fitBatch), ChainedPart::same, speculate,
      speculate ? 6 : 0, p.max_chain_steps);
  if (timer.on())
    std::fprintf(stderr,
                 "[rigid motion] %zu chains: surfaces and sources uploaded %.3f s, %d fit batches "
                 "(%zu fits, %.3f s), %d score batches (%zu starts, %.3f s), %.3f s in all\n",
                 act.size(), t_upload, fit_tally.calls, fit_tally.items, fit_tally.seconds,
                 score_tally.calls, score_tally.items, score_tally.seconds, since(t_begin));
  return out;
}

// The motions of several parts (fitChained each), their frames side by side (fitChains).
// `uploaded`: with a device, uploadChains' for these parts, or null.
void fitChainedParts(std::vector<std::unique_ptr<ChainedPart>>& parts, std::size_t frames,
                     RigidFitDevice* device, const RigidMotionParams& p, bool speculate,
                     DeviceFits* uploaded = nullptr) {
  const std::vector<ChainedPart*> act = activeOf(parts);
  if (act.empty()) return;
  using Link = ChainedPart::Link;
  if (device) {
    const auto chains = fitOnDevice(act, static_cast<int>(frames), *device, p, speculate, uploaded);
    for (std::size_t c = 0; c < act.size(); ++c) act[c]->finish(chains[c]);
    return;
  }
  const std::vector<std::vector<Link>> chains = fitChains(
      static_cast<int>(act.size()), static_cast<int>(frames), 0, act.front()->first(),
      [&](int c, int t, const ChainStep& step, const std::vector<Link>* fits) {
        return act[c]->starts(t, step.before, fits);
      },
      [&](int c, int t, const Link& x) { return act[c]->score(t, x); },
      [&](int c, int t, const Link& x, double) { return act[c]->fitFrom(t, x); }, ChainedPart::same,
      p.max_chain_steps);
  for (std::size_t c = 0; c < act.size(); ++c) act[c]->finish(chains[c]);
}

// One part's motion, the frames one after the other (inside a parallel loop over parts).
void fitChained(const PointCloudSequence& seq, const RigidMotionParams& p,
                const std::vector<std::vector<int>>& labels, int part,
                const std::vector<double>& spacing, std::size_t points_frame0, PartMotion& motion) {
  ChainedPart c(seq, p, labels, part, spacing, points_frame0, nullptr, motion);
  if (!c.active()) return;
#pragma omp parallel for schedule(dynamic)
  for (std::size_t t = 1; t < seq.size(); ++t) c.buildTarget(t);
  using Link = ChainedPart::Link;
  c.finish(fitAlongChain(
      static_cast<int>(seq.size()), 0, c.first(),
      [&](int t, const ChainStep& step, const std::vector<Link>* fits) {
        return c.starts(t, step.before, fits);
      },
      [&](int t, const Link& x) { return c.score(t, x); },
      [&](int t, const Link& x, double) { return c.fitFrom(t, x); }, ChainedPart::same, false,
      p.max_chain_steps));
}

// Merged parts of one nested level to fit from their children (fitFromChildren): `merged` lists
// the parts of `cur` to fit; every one of their points is labelled in `prev` with a part of
// `children` (or unlabelled, then unused). Their motions go to (*out)[b].
struct MergedSet {
  const std::vector<std::vector<int>>* prev = nullptr;
  const std::vector<std::vector<int>>* cur = nullptr;
  const std::vector<PartMotion>* children = nullptr;
  std::vector<int> merged;
  const std::vector<std::size_t>* frame0_points = nullptr;
  std::vector<PartMotion>* out = nullptr;
};

// What fitFromChildren needs of sets' merged parts before their children's motions are known
// (it reads only the labels, so it can be made beside other work): each part's source (its
// frame-0 points, up to max_points) with each point's child, and per (part, frame t >= 1) job
// the part's points in frame t as a surface where there are enough. Parts in the sets' order.
struct MergedPrep {
  std::vector<std::pair<std::size_t, int>> items;  // (set, part)
  std::vector<Cloud::Ptr> sources;
  std::vector<std::vector<int>> source_child;
  std::vector<char> active;  // enough source points (startMotion)
  std::vector<double> part_diag;
  std::vector<std::vector<double>> xyz;
  std::vector<Surface> surfaces;  // per job: item * (frames - 1) + t - 1
  std::vector<char> usable;       // per job: the surface was built
};

MergedPrep prepareMerged(const PointCloudSequence& seq, const RigidMotionParams& p,
                         const std::vector<MergedSet>& sets) {
  const std::size_t frames = seq.size();
  MergedPrep m;
  for (std::size_t s = 0; s < sets.size(); ++s)
    for (int b : sets[s].merged) m.items.push_back({s, b});
  const std::size_t np = m.items.size();
  m.sources.resize(np);
  m.source_child.resize(np);
  m.active.assign(np, 0);
  m.part_diag.assign(np, 0.0);
  m.xyz.resize(np);
  for (std::size_t k = 0; k < np; ++k) {
    const MergedSet& set = sets[m.items[k].first];
    const int b = m.items[k].second;
    m.sources[k].reset(new Cloud);
    for (int j : partIndices((*set.cur)[0], b, p.max_points)) {
      m.sources[k]->push_back((*seq.frame(0))[j]);
      m.source_child[k].push_back((*set.prev)[0][j]);
    }
    m.active[k] = static_cast<int>(m.sources[k]->size()) >= p.min_points;
    if (m.active[k]) m.part_diag[k] = boundingBoxDiagonal(*m.sources[k]);
    m.xyz[k] = sourceXyz(*m.sources[k]);
  }
  const int jobs = frames > 1 ? static_cast<int>(np * (frames - 1)) : 0;
  m.surfaces.resize(jobs);
  m.usable.assign(jobs, 0);
#pragma omp parallel for schedule(dynamic)
  for (int job = 0; job < jobs; ++job) {
    const std::size_t k = static_cast<std::size_t>(job) / (frames - 1);
    const std::size_t t = static_cast<std::size_t>(job) % (frames - 1) + 1;
    if (!m.active[k]) continue;
    Cloud::Ptr target =
        partCloud(*seq.frame(t), (*sets[m.items[k].first].cur)[t], m.items[k].second, 0);
    if (static_cast<int>(target->size()) < p.min_points) continue;
    m.surfaces[job].build(target);
    m.usable[job] = 1;
  }
  return m;
}

// The motions of merged parts of nested levels from those of the levels below (children), each
// frame on its own: the ICP passes of a chained fit (alignPasses) start from the least-squares
// rigid map (Umeyama, Eigen) of the part's frame-0 points onto where their children's motions
// carry them, instead of from the previous frame's result. The parts of several sets (levels
// whose children are all known) in one batch: each fit depends on its own part alone. `prep`:
// prepareMerged(seq, p, sets)'s.
void fitFromChildren(const PointCloudSequence& seq, const RigidMotionParams& p,
                     const std::vector<double>& spacing, const std::vector<MergedSet>& sets,
                     const MergedPrep& prep, RigidFitDevice* device) {
  const std::size_t frames = seq.size();
  const auto& items = prep.items;
  const std::size_t np = items.size();
  for (std::size_t k = 0; k < np; ++k) {
    const MergedSet& set = sets[items[k].first];
    const int b = items[k].second;
    startMotion((*set.out)[b], frames, (*set.frame0_points)[b], *prep.sources[k], p.min_points);
  }
  // Every (part, frame) on its own: no chain along the sequence, so the frames run in parallel
  // (the chained ICPs of a coarse level's few large parts were one long serial job each).
  // With a device, every job's start first, then one batch.
  const int jobs = static_cast<int>(prep.surfaces.size());
  std::vector<RigidFitJob> fits(device ? jobs : 0);
  std::vector<char> ready(device ? jobs : 0, 0);
#pragma omp parallel for schedule(dynamic)
  for (int job = 0; job < jobs; ++job) {
    const std::size_t k = static_cast<std::size_t>(job) / (frames - 1);
    const std::size_t t = static_cast<std::size_t>(job) % (frames - 1) + 1;
    const MergedSet& set = sets[items[k].first];
    PartMotion& motion = (*set.out)[items[k].second];
    if (!motion.frames[0].valid || !prep.usable[job]) continue;
    const Cloud& source = *prep.sources[k];
    Eigen::Matrix3Xd from(3, source.size()), to(3, source.size());
    Eigen::Index n = 0;
    const std::vector<PartMotion>& children = *set.children;
    for (std::size_t i = 0; i < source.size(); ++i) {
      const int a = prep.source_child[k][i];
      if (a < 0 || a >= static_cast<int>(children.size())) continue;
      const std::vector<RigidTransform>& ca = children[a].frames;
      if (ca.size() != frames || !ca[t].valid) continue;
      from.col(n) = source[i].getVector3fMap().cast<double>();
      to.col(n) = ca[t].apply(from.col(n));
      ++n;
    }
    if (n < 3) continue;
    const Eigen::Matrix4d map = Eigen::umeyama(from.leftCols(n), to.leftCols(n), false);
    if (!map.allFinite()) continue;
    RigidTransform start;
    start.rotation = map.topLeftCorner<3, 3>();
    start.translation = map.topRightCorner<3, 1>();
    if (device) {
      RigidFitJob& f = fits[job];
      icp_step::store(toRigid(start), f.start);
      f.source = static_cast<int>(k);
      f.spacing = spacing[t];
      f.part_diag = prep.part_diag[k];
      ready[job] = 1;
      continue;
    }
    double rms = 0.0;
    const icp_step::Rigid m = alignPasses(prep.xyz[k], prep.surfaces[job], toRigid(start),
                                          spacing[t], prep.part_diag[k], p, rms);
    motion.frames[t] = fitted(m, rms);
  }
  if (device) {
    DeviceFits dev(*device);
    for (std::size_t k = 0; k < np; ++k) dev.addSource(prep.xyz[k]);
    std::vector<RigidFitJob> batch;
    std::vector<int> at;
    for (int job = 0; job < jobs; ++job) {
      if (!ready[job]) continue;
      fits[job].surface = dev.addSurface(prep.surfaces[job]);
      batch.push_back(fits[job]);
      at.push_back(job);
    }
    dev.upload();
    if (!batch.empty()) {
      std::vector<icp_step::Rigid> poses;
      std::vector<double> rms;
      dev.fit(batch, p, poses, rms);
      for (std::size_t j = 0; j < at.size(); ++j) {
        const std::size_t k = static_cast<std::size_t>(at[j]) / (frames - 1);
        const std::size_t t = static_cast<std::size_t>(at[j]) % (frames - 1) + 1;
        (*sets[items[k].first].out)[items[k].second].frames[t] = fitted(poses[j], rms[j]);
      }
    }
  }
  // As for chained fits, a frame without an estimate carries the last valid one.
  for (const auto& [s, b] : items) {
    PartMotion& m = (*sets[s].out)[b];
    for (std::size_t t = 1; t < frames; ++t)
      if (!m.frames[t].valid) {
        m.frames[t] = m.frames[t - 1];
        m.frames[t].valid = false;
        m.frames[t].rms = -1.0;
      }
  }
}

}  // namespace

double rigidScore(const std::vector<double>& source, int probes, const FlatKdTree3& tree,
                  const double* pose) {
  const std::size_t n = source.size() / 3;
  const std::size_t m = probes > 0 ? std::min(n, static_cast<std::size_t>(probes)) : 0;
  if (m == 0) return 0.0;
  const icp_step::Rigid T = icp_step::load(pose);
  double sum = 0.0;
  for (std::size_t k = 0; k < m; ++k) {
    double y[3];
    icp_step::apply(T, &source[3 * (k * n / m)], y);
    const float q[3] = {static_cast<float>(y[0]), static_cast<float>(y[1]),
                        static_cast<float>(y[2])};
    float d2 = 0.0f;
    tree.nearest(q, std::numeric_limits<float>::infinity(), d2);
    sum += d2;
  }
  return std::sqrt(sum / static_cast<double>(m));
}

void fitRigidJob(const std::vector<double>& source, const FlatKdTree3& tree,
                 const std::vector<float>& leaf_normals, const RigidFitJob& job,
                 const RigidMotionParams& params, double* pose, double& rms) {
  icp_step::store(alignPasses(source, tree, leaf_normals, icp_step::load(job.start), job.spacing,
                              job.part_diag, params, rms, job.wide),
                  pose);
}

int RigidMotionEstimation::checkedPartCount(const std::vector<std::vector<int>>& labels,
                                            int num_parts) const {
  if (!sequence_ || sequence_->empty()) throw Error("rigid motion: no input sequence");
  const std::size_t frames = sequence_->size();
  if (labels.size() != frames)
    throw Error("rigid motion: " + std::to_string(labels.size()) +
                " label frames for a sequence of " + std::to_string(frames) + " frames");
  for (std::size_t t = 0; t < frames; ++t)
    if (labels[t].size() != sequence_->frame(t)->size())
      throw Error("rigid motion: frame " + std::to_string(t) + " has " +
                  std::to_string(labels[t].size()) + " labels for " +
                  std::to_string(sequence_->frame(t)->size()) + " points");
  return num_parts > 0 ? num_parts : detail::largestLabel(labels) + 1;
}

namespace {

// A spinning thread's pause (x86's PAUSE, which also leaves the core's resources to another
// thread of it); elsewhere none.
inline void spinPause() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#endif
}

// fits() on a thread of its own with one OpenMP thread (a chain of device calls), and beside()
// on the calling thread with one OpenMP thread fewer; both are waited for, then the first
// exception (fits' first) is thrown.
template <class Fits>
void fitBeside(const std::function<void()>& beside, Fits fits) {
  std::exception_ptr failed_fits, failed_beside;
  std::atomic<bool> fitted{false};
  std::thread worker([&] {
    try {
      omp_set_num_threads(1);
      fits();
    } catch (...) {
      failed_fits = std::current_exception();
    }
    fitted.store(true, std::memory_order_release);
  });
  const int threads = omp_get_max_threads();
  if (threads > 2) omp_set_num_threads(threads - 1);
  try {
    beside();
  } catch (...) {
    failed_beside = std::current_exception();
  }
  // The caller's team (one thread fewer than the cores; the fits' thread has the last) stays
  // awake until the fits are done. Asleep there (libgomp's threads sleep after a few
  // milliseconds of spinning), the parallel loops right after the fits ran several times slower
  // in a quarter to a third of the runs on the GPU machine's virtual CPUs: the rigid motions'
  // merged parts 0.03-0.04 s instead of 0.01 s (docs/gpu.md, stop 55). Not where the threads
  // outnumber the cores (--threads above them): there the spinning would take the fits' thread's
  // turns.
  if (threads > 2 && threads <= omp_get_num_procs()) {
#pragma omp parallel
    while (!fitted.load(std::memory_order_acquire)) spinPause();
  }
  if (threads > 2) omp_set_num_threads(threads);
  worker.join();
  if (failed_fits) std::rethrow_exception(failed_fits);
  if (failed_beside) std::rethrow_exception(failed_beside);
}

}  // namespace

std::vector<PartMotion> RigidMotionEstimation::compute(const std::vector<std::vector<int>>& labels,
                                                       int num_parts) const {
  const int np = checkedPartCount(labels, num_parts);
  return computeParts({&labels}, {np}, {{}}, frameSpacings(), {frame0Counts(labels, np)}).front();
}

std::vector<PartMotion> RigidMotionEstimation::computeBeside(
    const std::vector<std::vector<int>>& labels, int num_parts,
    const std::function<void()>& beside) const {
  const int np = checkedPartCount(labels, num_parts);
  return computeParts({&labels}, {np}, {{}}, frameSpacings(), {frame0Counts(labels, np)}, &beside)
      .front();
}

std::vector<double> RigidMotionEstimation::frameSpacings() const {
  if (spacings_.empty()) return meanSpacings(*sequence_);
  if (spacings_.size() != sequence_->size())
    throw Error("rigid motion: " + std::to_string(spacings_.size()) + " spacings for " +
                std::to_string(sequence_->size()) + " frames");
  return spacings_;
}

std::vector<LevelMotion> RigidMotionEstimation::computeLevels(
    const std::vector<std::vector<std::vector<int>>>& all_levels, const std::vector<int>& num_parts,
    std::size_t max_levels) const {
  // The first max_levels levels (0: all), by pointer: no copy of the labels.
  const std::size_t nl =
      max_levels > 0 ? std::min(max_levels, all_levels.size()) : all_levels.size();
  if (!num_parts.empty() && num_parts.size() != all_levels.size())
    throw Error("rigid motion: " + std::to_string(num_parts.size()) + " part counts for " +
                std::to_string(all_levels.size()) + " levels");
  std::vector<const std::vector<std::vector<int>>*> sets;
  for (std::size_t l = 0; l < nl; ++l) sets.push_back(&all_levels[l]);
  const auto levels = [&](std::size_t l) -> const std::vector<std::vector<int>>& {
    return *sets[l];
  };
  // One pass over each level's labels: checked against the sequence, and its part count.
  std::vector<int> np(nl, 0);
  for (std::size_t l = 0; l < nl; ++l)
    np[l] = checkedPartCount(levels(l), num_parts.empty() ? 0 : num_parts[l]);
  // source[l][b]: the part of level l - 1 whose points are exactly b's in every frame, or -1;
  // such a part is not fitted but copied (levels in order, so a chain of copies resolves).
  std::vector<std::vector<int>> source(nl);
  std::vector<std::vector<char>> fit(nl);
  std::vector<std::vector<int>> merged(nl);  // parts fitted from their children's motions
  std::vector<std::vector<int>> parent(nl);  // of a nested level's parts: to[a] of the next one
  for (std::size_t l = 1; l < nl; ++l) {
    const auto& prev = levels(l - 1);
    const auto& cur = levels(l);
    const int na = np[l - 1], nb = np[l];
    // from[b]: the one part of the level before that all of b's points come from (-2: none yet,
    // -3: several, or unlabelled points); to[a] likewise for a's points.
    std::vector<int> from(static_cast<std::size_t>(nb), -2), to(static_cast<std::size_t>(na), -2);
    bool same_shape = prev.size() == cur.size();
    for (std::size_t t = 0; same_shape && t < cur.size(); ++t)
      same_shape = prev[t].size() == cur[t].size();
    // Each frame's from / to, the frames side by side, then joined: a part's entry is its one
    // source if every frame that has it agrees, else -3; the same as one pass over all points.
    // Labels with huge ids (a hand-written labelling) take that one pass instead of tables of
    // frames x parts.
    const int nf = static_cast<int>(cur.size());
    const bool by_frame =
        static_cast<long long>(nf) * (static_cast<long long>(na) + nb) <= (1LL << 22);
    // One frame's points into from / to (f, g): a part's entry becomes its source, or -3.
    auto scanFrame = [&](int t, int* f, int* g) {
      for (std::size_t j = 0; j < cur[t].size(); ++j) {
        const int a = prev[t][j], b = cur[t][j];
        if (b >= 0 && b < nb) {
          int& s = f[b];
          s = (a < 0 || a >= na) ? -3 : (s == -2 || s == a) ? a : -3;
        }
        if (a >= 0 && a < na) {
          int& m = g[a];
          m = (b < 0 || b >= nb) ? -3 : (m == -2 || m == b) ? b : -3;
        }
      }
    };
    if (same_shape && !by_frame) {
      for (int t = 0; t < nf; ++t) scanFrame(t, from.data(), to.data());
    } else if (same_shape) {
      std::vector<int> frame_from(static_cast<std::size_t>(nf) * nb, -2),
          frame_to(static_cast<std::size_t>(nf) * na, -2);
#pragma omp parallel for schedule(static)
      for (int t = 0; t < nf; ++t)
        scanFrame(t, frame_from.data() + static_cast<std::size_t>(t) * nb,
                  frame_to.data() + static_cast<std::size_t>(t) * na);
      auto join = [](int& s, int v) { s = v == -2 ? s : (s == -2 || s == v) ? v : -3; };
      for (int t = 0; t < nf; ++t) {
        for (int b = 0; b < nb; ++b)
          join(from[b], frame_from[static_cast<std::size_t>(t) * nb + b]);
        for (int a = 0; a < na; ++a) join(to[a], frame_to[static_cast<std::size_t>(t) * na + a]);
      }
    }
    source[l].assign(static_cast<std::size_t>(nb), -1);
    fit[l].assign(static_cast<std::size_t>(nb), 1);
    if (same_shape)
      for (int b = 0; b < nb; ++b)
        if (from[b] >= 0 && to[from[b]] == b) source[l][b] = from[b], fit[l][b] = 0;
    // A nested level (every part of the level before lies within one part of this one, as the
    // hierarchy's levels do): its merged parts start from their children's motions instead of
    // a chained ICP of their own (fitFromChildren), after the level before is done.
    const bool nested =
        same_shape && std::none_of(to.begin(), to.end(), [](int m) { return m == -3; });
    for (int b = 0; nested && b < nb; ++b)
      if (fit[l][b]) merged[l].push_back(b), fit[l][b] = 0;
    if (nested) parent[l - 1] = to;
  }
  // Computed once, for the chained fits and the fits from children alike.
  const std::vector<double> spacing = frameSpacings();
  std::vector<std::vector<std::size_t>> frame0_points(nl);
  for (std::size_t l = 0; l < nl; ++l) frame0_points[l] = frame0Counts(levels(l), np[l]);
  detail::StageTimer timer("rigid motion");
  // The merged parts in waves: a part's wave follows those of its children (0: fitted by
  // computeParts; a copy: its source's), and the parts of a wave, whatever their level, are one
  // batch (the 800k humanoid's four levels of merged parts were four batches one after the
  // other, 0.006 s each). The same motions: each part's fit reads only its children's.
  std::vector<std::vector<int>> wave(nl);
  int waves = 0;
  for (std::size_t l = 0; l < nl; ++l) {
    wave[l].assign(static_cast<std::size_t>(np[l]), 0);
    if (l == 0) continue;
    for (int b = 0; b < np[l]; ++b)
      if (source[l][b] >= 0) wave[l][b] = wave[l - 1][source[l][b]];
    for (int b : merged[l]) {
      int w = 0;
      for (int a = 0; a < np[l - 1]; ++a)
        if (a < static_cast<int>(parent[l - 1].size()) && parent[l - 1][a] == b)
          w = std::max(w, wave[l - 1][a]);
      wave[l][b] = w + 1;
      waves = std::max(waves, w + 1);
    }
  }
  std::vector<LevelMotion> out(nl);
  std::vector<std::vector<MergedSet>> wave_sets(waves + 1);
  for (int w = 1; w <= waves; ++w)
    for (std::size_t l = 1; l < nl; ++l) {
      MergedSet set;
      for (int b : merged[l])
        if (wave[l][b] == w) set.merged.push_back(b);
      if (set.merged.empty()) continue;
      set.prev = &levels(l - 1);
      set.cur = &levels(l);
      set.children = &out[l - 1].parts;
      set.frame0_points = &frame0_points[l];
      set.out = &out[l].parts;
      wave_sets[w].push_back(std::move(set));
    }
  // The merged parts' sources and surfaces read only the labels: with a device they are made
  // beside its fits of level 0, which leave the cores idle (800k: 376 surfaces of large parts).
  std::vector<MergedPrep> prep(waves + 1);
  auto prepareWaves = [&] {
    for (int w = 1; w <= waves; ++w) prep[w] = prepareMerged(*sequence_, params_, wave_sets[w]);
  };
  bool prepared = false;
  const std::function<void()> beside = [&] {
    prepareWaves();
    prepared = true;
  };
  std::vector<std::vector<PartMotion>> parts =
      computeParts(sets, np, fit, spacing, frame0_points, device_ && waves > 0 ? &beside : nullptr);
  if (!prepared) prepareWaves();
  timer.lap("chained parts");
  for (std::size_t l = 0; l < nl; ++l) {
    out[l].level = static_cast<int>(l);
    out[l].parts = std::move(parts[l]);
  }
  // Copies whose source is known after wave w, level by level (a chain of copies resolves).
  std::vector<std::vector<char>> copied(nl);
  auto copyUpTo = [&](int w) {
    for (std::size_t l = 1; l < nl; ++l) {
      copied[l].resize(source[l].size(), 0);
      for (std::size_t b = 0; b < source[l].size(); ++b)
        if (source[l][b] >= 0 && !copied[l][b] && wave[l][b] <= w) {
          out[l].parts[b] = out[l - 1].parts[source[l][b]];
          out[l].parts[b].part = static_cast<int>(b);
          copied[l][b] = 1;
        }
    }
  };
  copyUpTo(0);
  for (int w = 1; w <= waves; ++w) {
    fitFromChildren(*sequence_, params_, spacing, wave_sets[w], prep[w], device_);
    copyUpTo(w);
    timer.lap("merged parts of a wave");
  }
  return out;
}

std::vector<std::vector<PartMotion>> RigidMotionEstimation::computeParts(
    const std::vector<const std::vector<std::vector<int>>*>& sets,
    const std::vector<int>& num_parts, const std::vector<std::vector<char>>& fit,
    const std::vector<double>& spacing, const std::vector<std::vector<std::size_t>>& frame0_points,
    const std::function<void()>* beside) const {
  std::vector<std::vector<PartMotion>> out(sets.size());
  // (labelling, part) pairs to fit: the parts of every labelling in one parallel loop, so that a
  // few large parts of several levels run side by side.
  std::vector<std::pair<std::size_t, int>> jobs;
  for (std::size_t s = 0; s < sets.size(); ++s) {
    const int np = num_parts[s];
    out[s].resize(np);
    for (int part = 0; part < np; ++part) {
      out[s][part].part = part;
      if (fit[s].empty() || fit[s][part]) jobs.push_back({s, part});  // else the caller's
    }
  }
  // Largest parts first: the coarse levels' merged parts are few, large and not rigid (their
  // ICPs run to the iteration cap), and started last they ran alone on an idle machine (800k
  // humanoid, --parts 15, 2 cores: rigid motions 17.8 s -> 13.7 s; same results, each part's
  // fit is independent of the others).
  std::stable_sort(jobs.begin(), jobs.end(), [&](const auto& x, const auto& y) {
    return frame0_points[x.first][x.second] > frame0_points[y.first][y.second];
  });
  const RigidMotionParams p = params_;
  // The first labelling's parts with a start of their own in every frame (setInitialMotions) run
  // with all their frames side by side (fitChainedParts); the others are chains, side by side.
  // The device's fits of `chained` on a thread of their own beside `beside` (fitBeside), their
  // sources and surfaces uploaded before the fork, on every core: on the fits' thread (one core)
  // their packing took 0.025 s of the refinement's 0.060 s of chains at 800k, against 0.007 s.
  auto fitOnDeviceBeside = [&](std::vector<std::unique_ptr<ChainedPart>>& chained, bool speculate,
                               detail::StageTimer& timer, const char* uploaded_lap) {
    const std::vector<ChainedPart*> act = activeOf(chained);
    std::unique_ptr<DeviceFits> up;
    if (!act.empty()) up = uploadChains(act, static_cast<int>(sequence_->size()), *device_);
    timer.lap(uploaded_lap);
    fitBeside(*beside, [&] {
      fitChainedParts(chained, sequence_->size(), device_, p, speculate, up.get());
    });
  };
  std::vector<std::pair<std::size_t, int>> seeded;
  bool beside_done = false;  // `beside` ran (with the seeded parts' fits)
  if (!init_.empty() && !sets.empty()) {
    auto first = [&](const std::pair<std::size_t, int>& j) {
      return j.first == 0 && static_cast<std::size_t>(j.second) < init_.size();
    };
    std::copy_if(jobs.begin(), jobs.end(), std::back_inserter(seeded), first);
    jobs.erase(std::remove_if(jobs.begin(), jobs.end(), first), jobs.end());
  }
  {
    detail::StageTimer timer("rigid motion");
    std::vector<std::unique_ptr<ChainedPart>> chained;
    for (const auto& [s, part] : seeded)
      chained.push_back(std::make_unique<ChainedPart>(*sequence_, p, *sets[s], part, spacing,
                                                      frame0_points[s][part], &init_[part],
                                                      out[s][part]));
    buildTargets(chained, sequence_->size());
    timer.lap("seeded: targets");
    // The caller's work beside the device's fits when no chains follow them.
    if (beside && device_ && jobs.empty() && !activeOf(chained).empty()) {
      fitOnDeviceBeside(chained, true, timer, "seeded: sources and surfaces uploaded");
      beside_done = true;
      timer.lap("seeded: fits, beside the caller's work");
    } else {
      fitChainedParts(chained, sequence_->size(), device_, p, true);
      timer.lap("seeded: fits");
    }
  }
  if (device_) {  // the chains side by side, one frame position of all of them per batch
    detail::StageTimer timer("rigid motion");
    std::vector<std::unique_ptr<ChainedPart>> chained;
    for (const auto& [s, part] : jobs)
      chained.push_back(std::make_unique<ChainedPart>(
          *sequence_, p, *sets[s], part, spacing, frame0_points[s][part], nullptr, out[s][part]));
    buildTargets(chained, sequence_->size());
    timer.lap("chains: targets");
    if (beside && !beside_done) {
      fitOnDeviceBeside(chained, false, timer, "chains: sources and surfaces uploaded");
      timer.lap("chains: fits, beside the caller's work");
    } else {
      fitChainedParts(chained, sequence_->size(), device_, p, false);
      timer.lap("chains: fits");
    }
    return out;
  }
  if (beside && !beside_done) (*beside)();  // on the CPU, before the fits: every core busy
#pragma omp parallel for schedule(dynamic)
  for (std::size_t job = 0; job < jobs.size(); ++job) {
    const auto [s, part] = jobs[job];
    fitChained(*sequence_, p, *sets[s], part, spacing, frame0_points[s][part], out[s][part]);
  }
  return out;
}

void writeTransformsJson(const std::string& path, const PointCloudSequence& sequence,
                         const std::vector<LevelMotion>& levels) {
  std::ostringstream s;
  s << std::setprecision(9);
  auto escape = [](const std::string& in) {
    std::string o;
    for (char c : in) {
      if (c == '"' || c == '\\') {
        o += '\\';
        o += c;
      } else if (static_cast<unsigned char>(c) < 0x20) {
        char buf[8];
        std::snprintf(buf, sizeof(buf), "\\u%04x", c);
        o += buf;
      } else {
        o += c;
      }
    }
    return o;
  };
  auto num = [&s](double v) {
    if (std::isfinite(v))
      s << v;
    else
      s << "null";
  };
  s << "{\n  \"frames\": [";
  for (std::size_t t = 0; t < sequence.size(); ++t)
    s << (t ? ", " : "") << '"' << escape(sequence.name(t)) << '"';
  s << "],\n  \"levels\": [";
  for (std::size_t li = 0; li < levels.size(); ++li) {
    s << (li ? "," : "") << "\n    {\"level\": " << levels[li].level << ", \"parts\": [";
    const auto& parts = levels[li].parts;
    for (std::size_t pi = 0; pi < parts.size(); ++pi) {
      s << (pi ? "," : "") << "\n      {\"part\": " << parts[pi].part
        << ", \"points_frame0\": " << parts[pi].points_frame0 << ", \"transforms\": [";
      for (std::size_t t = 0; t < parts[pi].frames.size(); ++t) {
        const RigidTransform& r = parts[pi].frames[t];
        s << (t ? "," : "") << "\n        ";
        if (!r.valid) {
          s << "null";
          continue;
        }
        s << "{\"frame\": " << t << ", \"rotation\": [";
        for (int i = 0; i < 3; ++i) {
          s << (i ? ", " : "") << '[';
          for (int j = 0; j < 3; ++j) {
            if (j) s << ", ";
            num(r.rotation(i, j));
          }
          s << ']';
        }
        s << "], \"translation\": [";
        for (int i = 0; i < 3; ++i) {
          if (i) s << ", ";
          num(r.translation[i]);
        }
        s << "], \"rms\": ";
        num(r.rms);
        s << '}';
      }
      s << "]}";
    }
    s << "]}";
  }
  s << "\n  ]\n}\n";
  io::writeTextAtomically(path, s.str());
}

}  // namespace segmentation
}  // namespace pcl_animseg
