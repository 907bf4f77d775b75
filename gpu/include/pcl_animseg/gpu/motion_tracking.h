#pragma once
/** \file motion_tracking.h The motion method's fits and residuals on the current CUDA device.
 *
 * \code
 * pcl_animseg::gpu::MotionTracking gpu_motion;
 * pcl_animseg::segmentation::MotionTrackingParams params;
 * params.device = &gpu_motion;   // segmentByTracking fits and scores on the GPU
 * \endcode
 *
 * gpu::MeanShiftBackend owns one (MeanShiftDeviceBackend::motionDevice), so that
 * `animseg --device gpu|auto` runs the default method's tracking, merge scores and point costs
 * on the GPU. One warp fits one (frame, sample) pose, one kernel launch fits a wave of them; one
 * thread computes one point's error of a residual batch (one warp one residual in very large
 * batches), one thread one point cost. The arithmetic and the order of
 * every sum are the CPU's (segmentation/icp_step.h): the results are the CPU's bit for bit.
 */
#include <pcl_animseg/segmentation/motion_device.h>

#include <memory>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace gpu {

namespace detail {
struct FrameStore;
struct FrameArrays;
class TrackingStream;
}

/** \brief segmentation::MotionDevice on the current CUDA device. */
class MotionTracking : public segmentation::MotionDevice {
 public:
  MotionTracking();
  ~MotionTracking() override;
  std::string name() const override;
  /** \brief While the GPU's check (gpuAvailable) runs on another thread. */
  bool starting() const override;
  /** \brief Throws Error on frames without a tree. The frames are packed here and uploaded by
   * the first call that needs them (which throws Error on a CUDA failure or when no usable GPU
   * is present, see requireGpu). */
  void setFrames(const segmentation::DeviceFrames& frames) override;
  /** \brief Throws Error on a CUDA failure, no frames set, or a problem whose arrays do not
   * match. */
  void trackSamples(const segmentation::SampleTrackingProblem& problem,
                    std::vector<std::vector<Eigen::Isometry3d>>& poses,
                    std::vector<std::vector<double>>& residual) override;
  /** \brief The frames' fits as they come: beginSamples() uploads the problem (it waits for the
   * GPU's start), each trackFrames() queues its frames' copies and one kernel for their fits on
   * the calling thread's stream and returns at once, endSamples() waits and downloads
   * (MotionDevice's contract: the same poses as trackSamples()). Throws Error on a CUDA failure, no
   * frames set, a problem whose arrays do not match, or a frame out of order. */
  void beginSamples(const segmentation::SampleTrackingProblem& problem) override;
  void trackFrames(const std::vector<int>& frames, const std::vector<Eigen::Isometry3d>& global,
                   const std::vector<std::vector<int>>& level) override;
  void endSamples(std::vector<std::vector<Eigen::Isometry3d>>& poses,
                  std::vector<std::vector<double>>& residual) override;
  void residuals(const segmentation::ResidualJobs& jobs, std::vector<double>& out) override;
  void pointCosts(const segmentation::PointCostJobs& jobs, std::vector<double>& out) override;
  void partFits(const segmentation::PartFitJobs& jobs, std::vector<double>& poses) override;
  /** \brief partFits() with the score that each fit computes of its result returned (and the
   * start's, where the start is kept): one call, the residuals() values. */
  void partFitsWithResiduals(const segmentation::PartFitJobs& jobs, std::vector<double>& poses,
                             std::vector<double>& residual) override;
  /** \brief The starts scored and the winners fitted in one call (a block or a warp a job: the
   * residuals() and partFits() values, the same bits as the default's two calls). */
  void scoreAndFit(const segmentation::ScoreFitJobs& jobs, std::vector<double>& scores,
                   std::vector<int>& fitted, std::vector<double>& poses) override;
  /** \brief Every frame's points against their copies of the reference, a warp per 32 points
   * (tiles of copies whose box is too far from the points' box are skipped). Throws Error on a
   * CUDA failure or no frames set. */
  bool nearestMoved(const segmentation::MovedCopies& moved, std::vector<int>& pick) override;
  /** \brief A MotionTracking on this one's frames (uploaded now if pending) with its own batch
   * buffers: its calls from another thread run beside this one's on the GPU (each host thread
   * queues on a stream of its own). Throws Error where no frames were set or on a CUDA failure. */
  std::unique_ptr<segmentation::MotionDevice> fork() override;
  /** \brief Seconds of the last trackSamples on the device (uploads, kernels, downloads), or
   * of the last beginSamples .. endSamples. */
  double lastDeviceSeconds() const { return device_seconds_; }
  /** \brief Waves of the last trackSamples (one kernel), or kernels of the last beginSamples ..
   * endSamples (one per trackFrames). */
  int lastWaves() const { return waves_; }
  /** \brief Residual batches of at most this many source points in all (the default 2^21) run
   * a thread per point and then a thread per job for the sums; larger ones a warp per job. The
   * same residuals either way. */
  void setPointParallelLimit(long long points) { point_parallel_limit_ = points; }

 private:
  /** The frames on the device, after uploading the pending ones (null: none were set). */
  detail::FrameStore* store();
  /** partFits(), with each kept pose's residual where `residual` is given. */
  void fitParts(const segmentation::PartFitJobs& jobs, std::vector<double>& poses,
                std::vector<double>* residual);

  std::unique_ptr<detail::FrameArrays> pending_;  ///< set, not uploaded yet
  std::unique_ptr<detail::FrameStore> frames_;
  std::unique_ptr<detail::TrackingStream> stream_;  ///< beginSamples .. endSamples
  std::vector<int> depth_;  ///< per task given: its longest chain of fits (the reference's: 0)
  double device_seconds_ = 0.0;
  int waves_ = 0;
  long long point_parallel_limit_ = 1LL << 21;
};

}  // namespace gpu
}  // namespace pcl_animseg
