#pragma once
/** \file gauss_transform.h The exact Gauss transform on the GPU: every data point's Gaussian,
 * summed at each query, with no filter between them.
 *
 *     out(r, :) = sum_j exp(-|q_r - x_j|^2 / 2) [x_j, c_j, 1]     over |q_r - x_j| < cutoff
 *
 * x_j are the coordinates that enter the distance, c_j coordinates carried along that do not
 * (a joint-space dimension whose weight is 0). These are the sums of the mean-shift stage's exact
 * backend (segmentation's JointKernelSum with MeanShiftBackend::Exact: a cutoff of 3 bandwidths,
 * Eq. 8-10 with the data scaled by their metric), and of its exact steps (the refinement and
 * MeanShiftParams::exact_borders). Written by hand: no kept library offers a d-dimensional exact
 * Gauss transform in CUDA.
 *
 * How it runs: the data are ordered once along a kd-tree (halving at the median of the widest
 * coordinate) into tiles of 128 points, each with its bounding box; each call orders its queries
 * the same way, and a block of 128 queries (a query per thread) reads the data a tile at a time
 * through shared memory, skipping the tiles whose box is beyond the cutoff from its queries' box.
 * Few queries spread the data over more blocks; their partial sums are added in a fixed order, so
 * a call's result does not depend on the device's scheduling. Sums are float within a tile and
 * double across tiles, returned as floats.
 *
 * \code
 * pcl_animseg::gpu::GaussTransform gt;
 * gt.setData(x);               // N x d, already scaled by the metric (d <= 64)
 * Eigen::MatrixXf sums;
 * gt.evaluate(queries, sums);  // Q x (d + 1): the weighted sums of x, then of 1
 * \endcode
 * Every CUDA failure throws pcl_animseg::Error.
 */
#include <Eigen/Core>
#include <cstddef>
#include <memory>

namespace pcl_animseg {
namespace gpu {

/** \brief What the last GaussTransform::evaluate did (for benchmarks and logs). */
struct GaussTransformStats {
  long long queries = 0;
  long long tiles_visited = 0;  ///< (query block, data tile) pairs summed
  long long tiles_skipped = 0;  ///< pairs skipped by their boxes
  int splits = 1;               ///< parts of the data each query's sums came in
  double kernel_seconds = 0.0;  ///< the device's sums (kernels only)
  double seconds = 0.0;         ///< the call, copies and the host's query order included
};

class GaussTransform {
 public:
  GaussTransform();
  ~GaussTransform();
  GaussTransform(GaussTransform&&) noexcept;
  GaussTransform& operator=(GaussTransform&&) noexcept;

  /** \brief The data: x (N x dx) the coordinates in the distance, carried (N x dc, or empty) the
   * coordinates summed along without entering it; dx >= 1, dx + dc <= 64. Terms with
   * |q - x| >= cutoff are left out. Throws Error on empty or non-finite data or bad sizes. */
  void setData(const Eigen::MatrixXf& x, const Eigen::MatrixXf& carried = Eigen::MatrixXf(),
               float cutoff = 3.0f);
  /** \brief out (Q x (dx + dc + 1)) = the sums above at the rows of q (Q x dx, the distance
   * coordinates). Throws Error before setData or on a bad width or non-finite queries. */
  void evaluate(const Eigen::Ref<const Eigen::MatrixXf>& q, Eigen::MatrixXf& out) const;
  /** \brief The same into `out`: Q x (dx + dc + 1) floats, column-major (a buffer the caller
   * keeps between calls). */
  void evaluate(const Eigen::Ref<const Eigen::MatrixXf>& q, float* out) const;

  std::size_t size() const;  ///< N
  int distanceDims() const;  ///< dx
  int carriedDims() const;   ///< dc
  const GaussTransformStats& lastStats() const { return stats_; }

 private:
  struct Data;
  std::unique_ptr<Data> data_;
  mutable GaussTransformStats stats_;
};

}  // namespace gpu
}  // namespace pcl_animseg
