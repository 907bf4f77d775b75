#pragma once
/** \file mean_shift_backend.h The CUDA engine behind segmentation::MeanShiftSegmentation.
 *
 * \code
 * #include <pcl_animseg/gpu/device.h>
 * #include <pcl_animseg/gpu/mean_shift_backend.h>
 * std::string why;
 * if (pcl_animseg::gpu::gpuAvailable(&why))
 *   ms.setDeviceBackend(pcl_animseg::gpu::makeMeanShiftBackend(), allow_cpu_fallback);
 * else
 *   log("GPU not used: " + why);   // or throw for --device gpu
 * ms.segment(result);              // ms.deviceUsed(), ms.fallbackReason() tell what happened
 * \endcode
 *
 * The paper method runs its iteration (gpu::MeanShift) and its densities on the device; the
 * motion method its tracking, residuals and point costs (gpu::MotionTracking) and densities. Kernel
 * sums use the Gaussian kd-tree with MeanShiftParams::gkdtree, exactly the CPU filter's tree, so
 * the labels agree with the CPU's gkdtree backend. Exact sums (the exact backend, the
 * refinement's exact steps, MeanShiftParams::exact_borders) run on the device as an exact Gauss
 * transform (gauss_transform.h); the stage's bookkeeping around them stays on the CPU. Every CUDA
 * failure throws pcl_animseg::Error.
 */
#include <pcl_animseg/gpu/mean_shift.h>
#include <pcl_animseg/gpu/motion_tracking.h>
#include <pcl_animseg/segmentation/mean_shift.h>

#include <memory>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace gpu {

/** \brief segmentation::MeanShiftDeviceBackend on the current CUDA device. */
class MeanShiftBackend : public segmentation::MeanShiftDeviceBackend {
 public:
  std::string name() const override;
  void seekModes(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                 const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
                 const segmentation::MeanShiftParams& params, Eigen::MatrixXf& y,
                 Eigen::VectorXf& density) override;
  void density(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
               const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
               const segmentation::MeanShiftParams& params, const Eigen::MatrixXf& queries,
               const std::vector<char>& query_key, Eigen::VectorXf& out) override;
  /** \brief The motion method's fits and residuals on this device (motion_tracking.h). */
  segmentation::MotionDevice* motionDevice() override { return &tracking_; }
  /** \brief Exact sums on this device (gpu::GaussTransform, one per point group of the pair
   * rule, as the CPU's JointKernelSum). */
  std::unique_ptr<segmentation::DeviceExactSums> exactSums(
      const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
      const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint) override;
  double samplingFactor() const override {
    return stats_.plain_samples ? static_cast<double>(stats_.plain_points) /
                                      static_cast<double>(stats_.plain_samples)
                                : 0.0;
  }
  /** \brief Timings and memory of the last seekModes. */
  const MeanShiftStats& lastStats() const { return stats_; }

 private:
  /** The density's filter trees and blurred weights of the last data (density() is called again
   * on the same joint space with other queries: the border rounds of exact_borders). */
  struct DensityCache;
  MeanShiftStats stats_;
  MotionTracking tracking_;
  std::shared_ptr<DensityCache> density_cache_;
};

/** \brief A MeanShiftBackend; throws Error when no usable GPU is present (check gpuAvailable
 * first to fall back quietly). With check_now false the GPU is checked by the backend's first
 * call that needs it instead (requireGpu: the same Error, thrown from the segmenter), so that a
 * probe running on another thread need not be waited for here. */
std::shared_ptr<segmentation::MeanShiftDeviceBackend> makeMeanShiftBackend(bool check_now = true);

}  // namespace gpu
}  // namespace pcl_animseg
