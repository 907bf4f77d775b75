#pragma once
/** \file sample_tracking.h The motion method's sample tracking on the current CUDA device.
 *
 * \code
 * pcl_animseg::gpu::SampleTracking gpu_tracking;
 * pcl_animseg::segmentation::MotionTrackingParams params;
 * params.device = &gpu_tracking;   // trackSamples / segmentByTracking fit the poses on the GPU
 * \endcode
 *
 * gpu::MeanShiftBackend owns one (MeanShiftDeviceBackend::sampleTracking), so that
 * `animseg --device gpu|auto` runs the default method's tracking on the GPU. One warp fits one
 * (frame, sample) pose, one kernel launch fits a wave of them (tracking_device.h). The fits are
 * the CPU's, summed in another order: poses agree to rounding, not bit for bit.
 */
#include <pcl_animseg/segmentation/tracking_device.h>

#include <string>
#include <vector>

namespace pcl_animseg {
namespace gpu {

/** \brief segmentation::SampleTrackingDevice on the current CUDA device. */
class SampleTracking : public segmentation::SampleTrackingDevice {
 public:
  std::string name() const override;
  /** \brief Throws Error on a CUDA failure or a problem whose arrays do not match. */
  void solve(const segmentation::SampleTrackingProblem& problem,
             std::vector<std::vector<Eigen::Isometry3d>>& poses,
             std::vector<std::vector<double>>& residual) override;
  /** \brief Seconds of the last solve on the device (uploads, kernels, downloads). */
  double lastDeviceSeconds() const { return device_seconds_; }
  /** \brief Kernel launches (waves) of the last solve. */
  int lastWaves() const { return waves_; }

 private:
  double device_seconds_ = 0.0;
  int waves_ = 0;
};

}  // namespace gpu
}  // namespace pcl_animseg
