#pragma once
/** \file rigid_motion.h The rigid motion of every part, frame 0 -> frame t, without
 * correspondences.
 *
 * What a rigging or skinning user needs from a decomposition (the paper's rigid-bone application):
 * for each part, the rotation and translation that best map its points in frame 0 onto the same
 * part in frame t. Frames share no vertex order, so the fit is ICP (point-to-point passes, then
 * point-to-plane), chained along the sequence: frame t starts from frame t-1's transform (on a
 * sequence of more than 49 frames, through key frames: chained_fit.h, chainFrames). The
 * passes are those of PCL's IterativeClosestPoint and IterativeClosestPointWithNormals (which
 * ran them before), written out in segmentation/icp_step.h's arithmetic so that a RigidFitDevice
 * (the CUDA module's gpu::RigidFits) gives the same motions bit for bit.
 * The RMS residual (nearest-neighbour distance after alignment) is a quality measure that needs no
 * ground truth: a part that is not rigid, or not one part, shows a large residual.
 */
#include <pcl_animseg/math/gmm.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_device.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <cmath>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief x_t ≈ rotation * x_0 + translation for the part's points. */
struct RigidTransform {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  /** RMS nearest-neighbour distance from the transformed frame-0 points to the part in frame t. */
  double rms = 0.0;
  /** False when the part has too few points in frame 0 or in frame t (then rotation/translation
   * carry the last valid estimate, for chaining, and rms is -1). */
  bool valid = false;

  Eigen::Vector3d apply(const Eigen::Vector3d& p) const { return rotation * p + translation; }
  RigidTransform inverse() const;
};

namespace detail {
/** \brief `a` in icp_step's layout (the rotation row by row, then the translation), as the
 * shared arithmetic and the devices take it. */
icp_step::Rigid toRigid(const RigidTransform& a);
}  // namespace detail

/** \brief Knobs of RigidMotionEstimation (one struct so tools and --config map onto it). */
struct RigidMotionParams {
  /** Parts are subsampled (evenly, deterministic) to at most this many source points. */
  int max_points = 3000;
  /** Parts with fewer points than this in a frame get no transform there. */
  int min_points = 6;
  int max_iterations = 40;
  /** Correspondence rejection distance of the final ICP pass, in units of the target frame's mean
   * spacing. A first pass uses `coarse_distance` x the part's bounding-box diagonal (so that large
   * motions between consecutive frames are still captured), a second a sixth of that. */
  double max_correspondence_spacings = 4.0;
  double coarse_distance = 0.25;
  /** Convergence: an iteration that moves the part by less than this many spacings, or that
   * improves the mean squared error by less than this relative amount. */
  double transformation_epsilon = 0.01;
  double relative_mse_epsilon = 1e-5;
  /** A part's chain of fits along the frames (each frame from the fit of the frame before) goes
   * through key frames on a side of frame 0 longer than this many frames (chainFrames): at 48
   * frames key frames 4 apart, so that a GPU fits all parts in 14 batches one after the other
   * instead of 47; at 20 frames 2 apart. The refinement's motions use it too. 800k humanoid on
   * an H200: the refinement 0.30-0.32 -> 0.26-0.32 s, the rigid motions 0.14-0.15 ->
   * 0.11-0.12 s. Generated 48-frame sequences, 4000 points: the whole pipeline's pooled ARI
   * 0.9571 -> 0.9573 (4 plans x seeds 2-3; none moved by more than 0.0012), the level-0
   * transforms' mean RMS within 2% either way; the refinement alone (seeds 5 and 8) its boundary
   * error 0.1083 -> 0.1090 and ARI 0.9470 -> 0.9464 (5 of 8 a little worse, none better). A side
   * of up to this many frames is one chain of single steps, as the tracking's (kMaxChainSteps,
   * 48). */
  int max_chain_steps = 12;
};

/** \brief The rotation (radians) below which a step of the rigid motions' ICP counts as
 * converged: PCL's DefaultConvergenceCriteria's, cos >= 0.99999. */
inline double rigidStepMaxTurn() { return std::acos(0.99999); }

/** \brief One ICP fit of the rigid motions for a device: source `source` onto surface `surface`
 * from `start` (a pose as 12 doubles: the rotation row by row, then the translation), with the
 * target frame's mean spacing and the source's bounding-box diagonal; `wide`: with the wide
 * point-to-point passes first (RigidMotionParams). */
struct RigidFitJob {
  int source = 0;
  int surface = 0;
  double start[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};
  double spacing = 1.0;
  double part_diag = 0.0;
  bool wide = true;
};

/** \brief A score of a pose for a device (RigidFitDevice::scores): how well `pose` (12 doubles,
 * as RigidFitJob::start) lays `probes` of source `source`'s points, spread over it, onto surface
 * `surface` (rigidScore). */
struct RigidScoreJob {
  int source = 0;
  int surface = 0;
  int probes = 0;
  double pose[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};
};

/** \brief The refinement's motion check for a device (RigidFitDevice::motionResiduals):
 * residual r's point x0 (starts[3r..]) carried by part part[r]'s motion into every frame u of
 * `scored` but own[r] where that motion is valid, each copy y (icp_step::apply, in double) scored
 * against the nearest point of frame u to y as floats (FlatKdTree3::nearest without a bound;
 * none for a non-finite y) by motion_check::term, with that point's normal (`normals`: 3 per row
 * of each frame's tree, the frames one after the other) and spacing[u], capped at `cap`; the
 * terms added in the order of `scored`; the residual motion_check::residual of their sum. */
struct MotionCheckJobs {
  std::vector<double> starts;   ///< 3 per residual
  std::vector<int> part, own;   ///< per residual
  std::vector<double> motions;  ///< per part and frame (part-major): 12 each, icp_step::store's
  std::vector<char> valid;      ///< per part and frame
  std::vector<int> scored;      ///< frames, ascending
  std::vector<double> spacing;  ///< per frame
  std::vector<float> normals;   ///< 3 per tree row, frame after frame
  double cap = 0.0;
};

/** \brief A mixture to fit on a device (RigidFitDevice::fitMixtures): its points (N x 3) and
 * its start, math::gmmStart's, which the fit replaces. */
struct MixtureFitJob {
  const Eigen::MatrixX3d* points = nullptr;
  math::GaussianMixture* gmm = nullptr;
};

/** \brief Where RigidMotionEstimation's ICP fits run when not on the CPU (the CUDA module's
 * gpu::RigidFits). A device must give the CPU's results bit for bit: the same passes in the same
 * arithmetic (segmentation/icp_step.h) and order, and the same nearest points (a copy of each
 * surface's FlatKdTree3). Errors are thrown as pcl_animseg::Error. */
class RigidFitDevice {
 public:
  virtual ~RigidFitDevice() = default;
  virtual std::string name() const = 0;
  /** \brief The surfaces that the fits which follow match against: each a part's points in one
   * frame, given as a DeviceFrames::Frame (its tree and the normals in leaf order; a frame
   * without nodes is empty). Only the trees and normals are used. */
  virtual void setSurfaces(const DeviceFrames& surfaces) = 0;
  /** \brief The sources of the fits that follow: x, y, z (double) per point. */
  virtual void setSources(const std::vector<const std::vector<double>*>& sources) = 0;
  /** \brief Every job's fit (12 doubles each in `poses`) and its RMS nearest-point distance. */
  virtual void fit(const std::vector<RigidFitJob>& jobs, const RigidMotionParams& params,
                   std::vector<double>& poses, std::vector<double>& rms) = 0;
  /** \brief FlatKdTree3::knn of many queries at once (the same rows in the same order):
   * query q (x, y, z at queries[3q]) against `*trees[tree_of[q]]`, its k (>= 1; k = 1 is
   * FlatKdTree3::nearest without a bound) nearest rows into rows[k q ..], how many in count[q]
   * (none for a non-finite query). The squared distances are the caller's to compute
   * (FlatKdTree3::distance2: the same values), which halves what comes back. Returns false when
   * the device does not offer it (the default; the caller searches on the CPU). */
  virtual bool knn(const std::vector<const FlatKdTree3*>& trees, int k,
                   const std::vector<float>& queries, const std::vector<int>& tree_of,
                   std::vector<int>& rows, std::vector<int>& count) {
    (void)trees, (void)k, (void)queries, (void)tree_of, (void)rows, (void)count;
    return false;
  }
  /** \brief Keeps copies of `trees` on the device for the knnOn() calls that follow, in place of
   * any kept before; returns their token (> 0), or 0 where the device does not offer it (the
   * default). A caller that searches the same trees again saves their packing and upload. */
  virtual long long keepKnnTrees(const std::vector<const FlatKdTree3*>& trees) {
    (void)trees;
    return 0;
  }
  /** \brief knn() against the trees kept under `token` (keepKnnTrees); false where they are no
   * longer kept, or the device does not offer it (the caller then calls knn()). */
  virtual bool knnOn(long long token, int k, const std::vector<float>& queries,
                     const std::vector<int>& tree_of, std::vector<int>& rows,
                     std::vector<int>& count) {
    (void)token, (void)k, (void)queries, (void)tree_of, (void)rows, (void)count;
    return false;
  }
  /** \brief Frees the trees kept under `token`, if they still are (their device memory). */
  virtual void dropKnnTrees(long long token) { (void)token; }
  /** \brief The refinement's motion check (MotionCheckJobs) against the trees kept under
   * `token`, one per frame: each residual into out[r]. Returns false where the trees are no
   * longer kept or the device does not offer it (the default): the caller scores on the CPU,
   * with the same bits. */
  virtual bool motionResiduals(long long token, const MotionCheckJobs& jobs,
                               std::vector<float>& out) {
    (void)token, (void)jobs, (void)out;
    return false;
  }
  /** \brief FlatKdTree3::within from many queries against the trees kept under `token`
   * (keepKnnTrees): query q (x, y, z at queries[3q]) walks tree tree_of[q] with the bound
   * bound2[tree_of[q]] (strictly below, as within), and every row of every kept tree gets the
   * least squared distance (FlatKdTree3::distance2's value) of the queries that reach it, or
   * +infinity, in out[first + row] (the kept trees' rows one tree after the other). A non-finite
   * query reaches nothing. Returns false where the trees are no longer kept or the device does
   * not offer it (the default): the caller searches on the CPU, with the same values. */
  virtual bool leastDistances(long long token, const std::vector<float>& queries,
                              const std::vector<int>& tree_of, const std::vector<float>& bound2,
                              std::vector<float>& out) {
    (void)token, (void)queries, (void)tree_of, (void)bound2, (void)out;
    return false;
  }
  /** \brief math::gmmEM of each job's points from its start (*gmm, math::gmmStart's), the fit
   * into *gmm, with the same bits as on the cores. Returns false where the device does not offer
   * it or a job has more components than it takes (the default: the caller fits on the cores);
   * throws pcl_animseg::Error where a covariance is not positive definite, as gmmEM does. */
  virtual bool fitMixtures(const std::vector<MixtureFitJob>& jobs,
                           const math::GMMOptions& options) {
    (void)jobs, (void)options;
    return false;
  }
  /** \brief rigidScore of each job (RigidScoreJob) into out[j], against the surfaces and
   * sources of the last setSurfaces and setSources. Returns false where the device does not
   * offer it (the default): the caller scores on the CPU, with the same bits. */
  virtual bool scores(const std::vector<RigidScoreJob>& jobs, std::vector<double>& out) {
    (void)jobs, (void)out;
    return false;
  }
};

/** \brief How far a pose lays a source onto a surface, as the rigid motions choose between a
 * fit's starts: the root mean square, over `probes` points of the source (x, y, z per point; of
 * its n points, point k n / probes for k = 0 .. probes - 1), of the squared distance from the
 * point moved by `pose` (icp_step::apply, in double, then to float) to its nearest point of
 * `tree` (FlatKdTree3::nearest without a bound; 0 where it finds none), added in probe order in
 * double. 0 for no probes. */
double rigidScore(const std::vector<double>& source, int probes, const FlatKdTree3& tree,
                  const double* pose);

/** \brief The CPU's fit of one job, which a RigidFitDevice reproduces: the source (x, y, z per
 * point) aligned onto a surface given as a device sees it (its tree and the normals in the tree's
 * leaf order) by RigidMotionEstimation's ICP passes; `pose` receives 12 doubles, `rms` the RMS
 * nearest-point distance. */
void fitRigidJob(const std::vector<double>& source, const FlatKdTree3& tree,
                 const std::vector<float>& leaf_normals, const RigidFitJob& job,
                 const RigidMotionParams& params, double* pose, double& rms);

/** \brief Transforms of one part in every frame (frames[t]; frames[0] is the identity). */
struct PartMotion {
  int part = -1;
  std::size_t points_frame0 = 0;
  std::vector<RigidTransform> frames;
};

/** \brief Motions of one hierarchy level (level 0 = finest). */
struct LevelMotion {
  int level = 0;
  std::vector<PartMotion> parts;
};

/** \brief Point-to-plane ICP of every part from frame 0 to each frame, chained along time. */
class RigidMotionEstimation {
 public:
  using Ptr = std::shared_ptr<RigidMotionEstimation>;
  using ConstPtr = std::shared_ptr<const RigidMotionEstimation>;

  void setInputSequence(const PointCloudSequence* sequence) { sequence_ = sequence; }
  void setParams(const RigidMotionParams& params) { params_ = params; }
  /** \brief Where the ICP fits run: a device (not owned; it must outlive the calls), or nullptr
   * (the default) for the CPU. The results are the same bits either way; a device's failure is
   * thrown. */
  void setDevice(RigidFitDevice* device) { device_ = device; }
  RigidFitDevice* getDevice() const { return device_; }
  /** \brief The frames' mean point spacings as meanSpacings() measures them, when the caller
   * has them already: they are not measured again. Empty (the default): measured. compute() and
   * computeLevels() throw Error when their count is not the frame count. */
  void setSpacings(std::vector<double> spacings) { spacings_ = std::move(spacings); }
  const RigidMotionParams& getParams() const { return params_; }

  /** \brief Starts for the fits of the first labelling's parts (compute()'s labels, or level 0 of
   * computeLevels()): part p's motion in frame t also starts from `init[p].frames[t]` where that
   * is valid, whichever of it and the previous frame's motion fits the part better (RMS
   * nearest-point distance). Meant for the motions of nearly the same labels, such as those the
   * refinement computed for its input (GMMBoundaryRefinement::getMotions(); the refinement moves
   * only the borders): then a part's frames are fitted in parallel, with the same result as one
   * after the other. Parts beyond init's size, and every other labelling, are fitted as without.
   * An empty vector (the default) clears them. */
  void setInitialMotions(std::vector<PartMotion> init) { init_ = std::move(init); }
  const std::vector<PartMotion>& getInitialMotions() const { return init_; }

  /** \brief Motions of parts 0..num_parts-1 given labels[t][j] (kept-point order, -1 ignored).
   * `num_parts` <= 0 means max label + 1. Parts run in parallel (OpenMP). */
  std::vector<PartMotion> compute(const std::vector<std::vector<int>>& labels,
                                  int num_parts = 0) const;

  /** \brief compute(), with `beside()` run on the calling thread while the fits run. With a
   * device, the parts' targets are built first (on every core); then the fits, a chain of
   * device calls with little host work, run on a thread of their own (one OpenMP thread), and
   * beside() runs meanwhile with one OpenMP thread fewer. Without one, beside() runs first. The
   * same motions as compute(). beside() must not change the labels, nor call the device (it is
   * not made for calls from two threads). An exception of either is thrown once both have
   * ended. */
  std::vector<PartMotion> computeBeside(const std::vector<std::vector<int>>& labels, int num_parts,
                                        const std::function<void()>& beside) const;

  /** \brief Motions of the parts of every level: levels[l][t][j] as in compute(); num_parts[l]
   * as compute()'s num_parts (empty: max label + 1 of each level). A part whose points are
   * exactly one part's of the level before (in every frame: a part no merge touched) takes that
   * part's motion without a second ICP, which is what compute() would give it. A merged part of
   * a nested level (every part of the level before lies within one of its parts, as the
   * hierarchy's levels do) is fitted in each frame on its own: the same ICP passes as a chained
   * fit, started from the least-squares rigid map of its frame-0 points onto where its
   * children's motions carry them instead of from the previous frame (so its frames run in
   * parallel: the coarse levels' few large parts had been one long serial chain each; not the
   * same bits as compute(), about as good a fit). Other parts are chained fits, those of all
   * levels in one parallel loop.
   * max_levels > 0: only the first max_levels levels (finest first), without copying them. */
  std::vector<LevelMotion> computeLevels(const std::vector<std::vector<std::vector<int>>>& levels,
                                         const std::vector<int>& num_parts = {},
                                         std::size_t max_levels = 0) const;

 private:
  /** Checks one labelling against the input sequence (frame count, labels per frame) and returns
   * its part count: num_parts if > 0, else its largest label + 1. */
  int checkedPartCount(const std::vector<std::vector<int>>& labels, int num_parts) const;

  /** Parts of several labellings (sets[s], checked, with num_parts[s] resolved by
   * checkedPartCount) in one parallel loop;
   * a part with fit[s][part] == 0 is left for the caller (only its id is set). spacing[t]: frame
   * t's mean point spacing; frame0_points[s][part]: the part's points in frame 0. */
  std::vector<std::vector<PartMotion>> computeParts(
      const std::vector<const std::vector<std::vector<int>>*>& sets,
      const std::vector<int>& num_parts, const std::vector<std::vector<char>>& fit,
      const std::vector<double>& spacing,
      const std::vector<std::vector<std::size_t>>& frame0_points,
      const std::function<void()>* beside = nullptr) const;

  const PointCloudSequence* sequence_ = nullptr;
  RigidMotionParams params_;
  /** The spacings given (setSpacings), checked against the frame count, or measured. */
  std::vector<double> frameSpacings() const;

  std::vector<PartMotion> init_;
  RigidFitDevice* device_ = nullptr;
  std::vector<double> spacings_;
};

/** \brief Writes transforms.json (atomically):
 * `{"frames": [names], "levels": [{"level": L, "parts": [{"part": p, "points_frame0": n,
 *   "transforms": [{"frame": t, "rotation": [[r00,r01,r02],[..],[..]], "translation": [x,y,z],
 *   "rms": r}, ...]}]}]}`; a transform that could not be estimated is written as null. */
void writeTransformsJson(const std::string& path, const PointCloudSequence& sequence,
                         const std::vector<LevelMotion>& levels);

}  // namespace segmentation
}  // namespace pcl_animseg
