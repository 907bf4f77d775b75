#pragma once
/** \file mean_shift.h The paper's mean shift (Eq. 8-10, Sect. 3.3) on the GPU: every point of
 * every frame iterated to its mode with the GPU Gaussian kd-tree, then modes grouped.
 *
 * This mirrors the CPU path of segmentation::MeanShiftSegmentation (method "paper", backend
 * "gkdtree") step for step, so the two give the same clusters: the same joint-space data
 * (z raw, scaled per dimension by the metric of Eq. 5-6), the same kernel sums (one tree over the
 * non-keypoints, two over the keypoints for the pair rule of Eq. 5 when keypoints are given), the
 * same update and stopping rule (a point stops when its step, in the plain metric, is below
 * `convergence`), and the same mode grouping (groupModes).
 *
 * Host API: host matrices in and out (N x D, one point per row); all iterations stay on the
 * device. Throws pcl_animseg::Error on any CUDA failure (no GPU, out of memory, kernel fault):
 * check gpuAvailable() first, or catch and fall back to the CPU.
 */
#include <pcl_animseg/filters/gaussian_kdtree.h>

#include <Eigen/Core>

#include <cstddef>
#include <memory>
#include <vector>

namespace pcl_animseg {
namespace gpu {

struct MeanShiftParams {
  filters::GaussianKdTreeParams gkdtree;
  int max_iterations = 60;
  /** A trajectory stops when it moves less than this many bandwidths in one step. */
  double convergence = 1e-3;
};

/** \brief What one run did and cost (wall-clock seconds, device work included). */
struct MeanShiftStats {
  int iterations = 0;
  int not_converged = 0;
  std::size_t num_samples = 0;  ///< samples (leaves) over all trees
  std::size_t plain_points = 0;   ///< points of the tree over the non-keypoint points
  std::size_t plain_samples = 0;  ///< its samples (its N/M = plain_points / plain_samples)
  double upload_s = 0.0;
  double build_s = 0.0;         ///< kd-tree build(s)
  double splat_blur_s = 0.0;
  double iterate_s = 0.0;       ///< all mean-shift steps
  double density_s = 0.0;       ///< final density at the end points
  double download_s = 0.0;
  std::vector<double> step_s;   ///< per step
  std::vector<int> active;      ///< points moved in each step
  std::size_t peak_device_bytes = 0;
};

class MeanShift {
 public:
  MeanShift();
  ~MeanShift();
  MeanShift(MeanShift&&) noexcept;
  MeanShift& operator=(MeanShift&&) noexcept;

  void setParams(const MeanShiftParams& params) { params_ = params; }
  const MeanShiftParams& getParams() const { return params_; }

  /** \brief Runs Eq. 9 from every row of z to convergence.
   * \param[in] z N x D joint-space features (raw, not scaled), D <= 64
   * \param[in] metric_plain per-dimension factor sqrt(weight) / w (Eq. 6)
   * \param[in] metric_key the same with the keypoint-pair weight (Eq. 5); used only when
   *            `keypoint` is not empty
   * \param[in] keypoint per point: is it a keypoint (empty: no keypoint rule)
   * \param[out] y N x D end points (raw coordinates)
   * \param[out] density N: the kernel sum at each end point (the homogeneous weight of Eq. 10)
   */
  void run(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
           const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
           Eigen::MatrixXf& y, Eigen::VectorXf& density);

  const MeanShiftStats& stats() const { return stats_; }

  /** \brief The kernel sum of the last run's data (Eq. 4, the pair rule of Eq. 5 included) at
   * the rows of `queries` (N x D raw coordinates), from the run's trees and blurred values kept
   * on the device: the same values as a fresh Gaussian kd-tree over the same data (the blurred
   * weights are the homogeneous column of the run's values, exact counts in both). query_key[r]
   * says whether query r is a keypoint (empty: none is). Throws when no run has been made. */
  void density(const Eigen::MatrixXf& queries, const std::vector<char>& query_key,
               Eigen::VectorXf& out) const;
  /** \brief Whether a run's trees are kept for density(). */
  bool hasTrees() const { return state_ != nullptr; }

 private:
  struct State;
  MeanShiftParams params_;
  MeanShiftStats stats_;
  std::unique_ptr<State> state_;  // the last run's trees and blurred values, on the device
};

/** \brief Mode grouping of the CPU's paper method: forwards to segmentation::groupModes (host
 * code, about O(N log N)). End points falling in the
 * same cell (a fifth of the merge radius, in the plain metric) form a group represented by its
 * densest point; groups are visited from the densest and join the densest kept mode within
 * `merge_radius`, else become a mode. labels[i] is the mode of point i (0..modes-1, modes in order
 * of decreasing density); mode_rep[m] is the point whose end point is mode m. */
void groupModes(const Eigen::MatrixXf& y, const Eigen::RowVectorXf& metric_plain,
                const Eigen::VectorXf& density, double merge_radius, std::vector<int>& labels,
                std::vector<int>& mode_rep);

}  // namespace gpu
}  // namespace pcl_animseg
