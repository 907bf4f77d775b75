#pragma once
/** \file motion_device.h The motion method's fits and residuals handed to a device.
 *
 * Step 2 of motion_tracking.h fits, for every frame t and tracked sample s, the pose that carries
 * the sample's reference neighbourhood onto frame t: its starts are scored on a fifth of the
 * neighbourhood, the two best refined by damped point-to-plane ICP, the better fit kept. The
 * CPU runs these fits as a task graph; a device (the CUDA module's gpu::MotionTracking) gets them
 * here as waves: every fit of a wave depends only on fits of earlier waves. Step 3 scores merges
 * by residuals (RMS surface errors) of many sources under many motions, and moves points between
 * parts by their costs (surface errors summed over the frames) under many motions: a device
 * computes either as one batch.
 *
 * The device computes with the CPU's arithmetic (icp_step.h) and adds in the CPU's order, so its
 * poses and residuals are the CPU's bit for bit, and so are the labels downstream. The
 * segmentation module never links a device library: it only sees this interface.
 */
#include <pcl_animseg/flat_kdtree.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief The frames of a sequence as a device sees them. */
struct DeviceFrames {
  /** \brief One frame: its kd-tree (over the frame's points) and the normals of the tree's
   * points in the tree's leaf order (FlatKdTree3::leafPoints), 3 floats each. */
  struct Frame {
    const FlatKdTree3* tree = nullptr;
    std::vector<float> leaf_normals;
    double spacing = 1.0;     ///< mean point spacing
    bool unoriented = false;  ///< normals compared by |n . n'| (their sign is a guess)
    /** Where set, the normals in place of leaf_normals, not copied (they must outlive the
     * call that is given the frames): the rigid motions' 940 part surfaces at 800k. */
    const std::vector<float>* leaf_normals_of = nullptr;
    /** The normals: *leaf_normals_of where set, else leaf_normals. */
    const std::vector<float>& normals() const {
      return leaf_normals_of ? *leaf_normals_of : leaf_normals;
    }
  };
  std::vector<Frame> frames;
  double normal_cos = 0.3;  ///< points whose normals' cosine is below this are not matched
  double clip = 4.0;        ///< surface errors are clipped at clip^2 (spacings^2)
};

/** \brief Everything the tracking's per-sample poses depend on besides the frames. */
struct SampleTrackingProblem {
  int samples = 0;  ///< S; task t * S + s is sample s in frame t
  int icp_iterations = 8;
  /** Each sample's ICP source and its probe (the points that score the starts), reference
   * coordinates: positions and normals, one column per point. */
  std::vector<Eigen::Matrix3Xd> source_p, source_n, probe_p, probe_n;
  std::vector<std::vector<int>> graph;    ///< sample adjacency
  std::vector<std::vector<int>> level;    ///< level[t][s]: s's BFS level in frame t
  std::vector<int> before;                ///< per frame: the frame before it (-1: the reference)
  std::vector<int> two_before;            ///< per frame: the frame two before it, or -1
  std::vector<Eigen::Isometry3d> global;  ///< the whole body's pose in every frame
  /** The fits in dependency order: every task of waves[w] depends only on tasks of earlier
   * waves (and on the reference frame, whose poses are the identity). */
  std::vector<std::vector<int>> waves;
};

/** \brief Residuals for a device to compute: job j is the RMS surface error (in spacings) of
 * source jobs[j].source moved by motion jobs[j].motion against frame jobs[j].frame. */
struct ResidualJobs {
  struct Job {
    int source;
    int motion;
    int frame;
  };
  std::vector<double> points;        ///< 6 per point: position, normal (reference coordinates)
  std::vector<int> source_begin{0};  ///< source k: points source_begin[k] .. source_begin[k+1]-1
  std::vector<double> motions;       ///< 12 per motion: the rotation row by row, the translation
  std::vector<Job> jobs;
};

/** \brief Point costs for a device to compute: job j is the sum over the frames but the
 * reference of the squared surface error (spacings^2) of point jobs[j].point moved by motion
 * jobs[j].motion's pose in each frame, added in frame order. With `per_frame` the answer is the
 * errors themselves instead of their sum: T values per job (frame order, 0 for the reference
 * frame), job after job. */
struct PointCostJobs {
  struct Job {
    int point;
    int motion;
  };
  int reference_frame = 0;
  bool per_frame = false;
  std::vector<double> points;   ///< 6 per point: position, normal (reference coordinates)
  std::vector<double> motions;  ///< per motion, per frame, 12: the rotation row by row, then t
  std::vector<Job> jobs;
};

/** \brief Part fits for a device to compute: job j is the motion method's ICP
 * (motion_tracking.cpp's icp(), `iterations` steps, matches within jobs[j].max_dist) of source
 * jobs[j].source from motion jobs[j].motion against frame jobs[j].frame, kept when its residual is
 * at most jobs[j].r0 and otherwise the start returned. */
struct PartFitJobs {
  struct Job {
    int source;
    int motion;
    int frame;
    double r0;
    double max_dist;
  };
  int iterations = 8;
  std::vector<double> points;        ///< 6 per point: position, normal (reference coordinates)
  std::vector<int> source_begin{0};  ///< source k: points source_begin[k] .. source_begin[k+1]-1
  std::vector<double> motions;       ///< 12 per motion: the rotation row by row, the translation
  std::vector<Job> jobs;
};

/** \brief Starts to score and the part fits they decide, for a device to make in one call
 * (MotionDevice::scoreAndFit; the chained fits' score batch and the fit batch that follows it).
 * Job j scores its starts, motions jobs[j].first .. first + count - 1 (residuals()' value of its
 * source under each in its frame); with its base (a start scored before: score base_score at
 * place base_place; none where base_place < 0), the winner is the first of the lowest score by
 * place (`places`: each start's place, rising within a job; a score must be below the largest
 * double to win, and place 0 wins where none does: score_fit.h's scoreFitWinner). Where the
 * winner is one of the job's starts, the job is partFits()' job from it (r0 its score). */
struct ScoreFitJobs {
  struct Job {
    int source;
    int frame;
    int first, count;
    double base_score;
    int base_place;
    double max_dist;
  };
  int iterations = 8;
  std::vector<double> points;        ///< 6 per point: position, normal (reference coordinates)
  std::vector<int> source_begin{0};  ///< source k: points source_begin[k] .. source_begin[k+1]-1
  std::vector<double> motions;       ///< 12 per start: the rotation row by row, the translation
  std::vector<int> places;           ///< per start
  std::vector<Job> jobs;
};

/** \brief MotionDevice::nearestMoved's answer for a point that a tie leaves to the caller. */
constexpr int kMovedUndecided = -2;

/** \brief The reference frame's points carried into every frame by their parts' motions, for a
 * device to label every frame's points by (the motion method's last labelling): each point of
 * frame t takes the label of the copy nearest to it, among its `k` nearest copies in frame t the
 * first whose normal agrees with the point's, else of the nearest one. */
struct MovedCopies {
  /** The reference points that move (their indices; nearby points next to each other makes a
   * device's search faster): each frame holds a copy of each, in this order. */
  std::vector<int> order;
  int k = 8;  ///< the nearest copies looked through for an agreeing normal (1..8)
  /** Agreeing normals: a cosine (its absolute value in a frame with unoriented normals, see
   * DeviceFrames::Frame) above this, the cosine computed in float as
   * (nx * nx' + ny * ny') + nz * nz'. */
  double normal_cos = 0.3;
  /** Writes every frame's copies: frame t's copy of order[i] at out + 8 * (t * n + i), n =
   * order.size(): x, y, z, 0, then its normal, 0 (copies that are not finite are left out of
   * the search). Called once; the caller may write the frames side by side. */
  std::function<void(float* out)> fill;
};

/** \brief Appends a motion in the devices' layout (ResidualJobs::motions,
 * PointCostJobs::motions): 12 doubles, the rotation row by row, then the translation. */
inline void appendMotion(const Eigen::Isometry3d& a, std::vector<double>& out) {
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) out.push_back(a.linear()(i, j));
  for (int i = 0; i < 3; ++i) out.push_back(a.translation()(i));
}

/** \brief The motion stored at `p` in that layout. */
inline Eigen::Isometry3d motionAt(const double* p) {
  Eigen::Isometry3d a = Eigen::Isometry3d::Identity();
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) a.linear()(i, j) = p[3 * i + j];
  for (int i = 0; i < 3; ++i) a.translation()(i) = p[9 + i];
  return a;
}

/** \brief Appends points in the devices' layout (ResidualJobs::points, PointCostJobs::points):
 * 6 doubles each, the position, then the normal. */
inline void appendPoints(const Eigen::Matrix3Xd& p, const Eigen::Matrix3Xd& n,
                         std::vector<double>& out) {
  for (Eigen::Index i = 0; i < p.cols(); ++i) {
    for (int k = 0; k < 3; ++k) out.push_back(p(k, i));
    for (int k = 0; k < 3; ++k) out.push_back(n(k, i));
  }
}

/** \brief A device for the motion method's fits and residuals (see the file comment). Every
 * method throws Error on a device failure (no device, out of memory, kernel fault): never a
 * silent wrong result. */
class MotionDevice {
 public:
  virtual ~MotionDevice() = default;
  /** \brief For logs, e.g. "gpu (NVIDIA H100 80GB HBM3)". */
  virtual std::string name() const = 0;
  /** \brief Whether the device is still starting on a thread of its own (a GPU's driver and
   * context start beside the first CPU work: 0.2-0.35 s on the H100 machine). The CPU work
   * before the first call then leaves it a core. */
  virtual bool starting() const { return false; }
  /** \brief Copies the frames to the device; the calls below use them until the next call. */
  virtual void setFrames(const DeviceFrames& frames) = 0;
  /** \brief Fits every task of every wave: poses[t][s] (reference -> frame t; the entries of the
   * reference frame are read as the identity) and residual[t][s] (RMS surface error of the kept
   * fit, in spacings). Both come sized T x S. */
  virtual void trackSamples(const SampleTrackingProblem& problem,
                            std::vector<std::vector<Eigen::Isometry3d>>& poses,
                            std::vector<std::vector<double>>& residual) = 0;
  /** \brief trackSamples() as the frames come, so that their fits run while the caller still
   * finds the global poses and levels of later frames (the motion method's chain of whole-body
   * ICPs on the cores): beginSamples() with the problem without `level` and `waves` (`global`
   * sized T: the reference frame's entry, the one without a frame before, is read there, the
   * others as trackFrames() gives them), then trackFrames() with every other frame once, each
   * after its `before` and `two_before` (in an earlier call or earlier in the same call), then
   * endSamples(). The same poses and residuals as trackSamples() with all the levels. A frame's
   * fits go in level order (a sample after its neighbours of lower level), a valid order for
   * trackSamples()' waves. Call all three from one thread. The default keeps the frames and calls
   * trackSamples() in endSamples(); a device that overrides them starts a call's fits in
   * trackFrames() and returns at once. Throws Error on a frame out of range, given twice, given
   * before a frame it starts from, or without a level per sample. */
  virtual void beginSamples(const SampleTrackingProblem& problem);
  virtual void trackFrames(const std::vector<int>& frames,
                           const std::vector<Eigen::Isometry3d>& global,
                           const std::vector<std::vector<int>>& level);
  virtual void endSamples(std::vector<std::vector<Eigen::Isometry3d>>& poses,
                          std::vector<std::vector<double>>& residual);
  /** \brief One residual per job, in job order. */
  virtual void residuals(const ResidualJobs& jobs, std::vector<double>& out) = 0;
  /** \brief One point cost per job, in job order (T per job with PointCostJobs::per_frame). */
  virtual void pointCosts(const PointCostJobs& jobs, std::vector<double>& out) = 0;
  /** \brief One pose per job (12 doubles each, in job order). */
  virtual void partFits(const PartFitJobs& jobs, std::vector<double>& poses) = 0;
  /** \brief partFits(), and the residual of each job's pose (its source under that pose in the
   * job's frame, residuals()' value) into `residual`, in job order. The default asks residuals()
   * for them after the fits; a device that scores the fit's result anyway (the CUDA module's)
   * returns that score, the same bits, without the second call. */
  virtual void partFitsWithResiduals(const PartFitJobs& jobs, std::vector<double>& poses,
                                     std::vector<double>& residual);
  /** \brief ScoreFitJobs in one call: `scores`, one per start (in start order); `fitted`, per
   * job, the winner's index among its starts (-1: the base or an unscored place won, nothing
   * fitted); `poses`, 12 per job, the fit where fitted[j] >= 0 (else the identity). The default
   * asks residuals() and then partFits(); a device that scores and fits in one round trip (the
   * CUDA module's) gives the same bits. */
  virtual void scoreAndFit(const ScoreFitJobs& jobs, std::vector<double>& scores,
                           std::vector<int>& fitted, std::vector<double>& poses);
  /** \brief MovedCopies' labelling searched on the device: for each frame t (setFrames' frames),
   * for each point of its tree in leaf order (FlatKdTree3::leafPoints), the index (one of
   * `moved.order`) of the copy that labels it, -1 where frame t has no copies, or
   * kMovedUndecided where a tie decides it that only the caller's search can break. The k
   * nearest copies are those of FlatKdTree3::knn: by squared distance ((dx^2 + dy^2) + dz^2 in
   * float), equal distances by the lower index; but where the k-th and the (k+1)-th are at the
   * same distance, knn keeps the one it visits first, so a pick that depends on which is
   * undecided. `pick` holds the frames one after the other. Returns
   * false, leaving `pick` alone, where the device does not offer it (the default): the caller
   * then searches on the cores. Throws Error on a device failure. */
  virtual bool nearestMoved(const MovedCopies& moved, std::vector<int>& pick);
  /** \brief A second device on the same frames that another thread may call while this one is
   * called (its own buffers and queue; the same results), or null where the device offers none
   * (the default: the callers then take turns). It uses this device's frames: it must not
   * outlive this device, nor be called after setFrames() on this one. */
  virtual std::unique_ptr<MotionDevice> fork() { return nullptr; }

 protected:
  /** \brief The default beginSamples() .. endSamples(): the problem, and the frames given so far
   * (each frame's tasks in level order, appended as its waves). */
  SampleTrackingProblem streamed_;
  std::vector<char> streamed_frame_;  ///< per frame: given (or the reference)
  /** \brief Starts the streamed state: `kept` (the parts of the problem a device keeps; the
   * default, all of it) without levels and waves, and no frame given but the reference. */
  void startStreamed(SampleTrackingProblem kept);
  /** \brief Checks a frame for trackFrames() against the problem and the frames given so far
   * (`given`: per frame, given or the reference) and returns its tasks in level order (a sample
   * after its neighbours of lower level, ties by sample). Throws Error. */
  static std::vector<int> frameTasks(const SampleTrackingProblem& problem,
                                     const std::vector<char>& given, int t,
                                     const std::vector<int>& level);
};

}  // namespace segmentation
}  // namespace pcl_animseg
