#pragma once
/** \file gaussian_kdtree.h The Gaussian kd-tree filter on the GPU: the same interface, tree,
 * samples and filter as the CPU reference pcl_animseg::filters::GaussianKdTree (see its header
 * for the algorithm), built and evaluated by CUDA kernels.
 *
 * Agreement with the CPU: the tree and its samples are the same (same split rule, leaves in the
 * same order; the means may differ in the last bit), the blur takes the same sample pairs (the
 * cut-off distance is summed in the same order without fused multiply-add), and the slice
 * divides its importance samples by the same rounded rule. Sums run in another order, so results
 * agree to float rounding, not bit for bit (and, very rarely, a rounded division of samples at a
 * split may fall the other way).
 *
 * Host API: Eigen matrices in and out, as the CPU class (N x d, one point per row). Limits:
 * d <= 64, value columns <= 128, slice_samples <= 64. Every CUDA failure throws
 * pcl_animseg::Error (no GPU, out of memory, kernel fault).
 */
#include <pcl_animseg/filters/gaussian_kdtree.h>

#include <Eigen/Core>

#include <cstddef>
#include <memory>
#include <vector>

namespace pcl_animseg {
namespace gpu {

namespace detail {
struct TreeDevice;
}

class GaussianKdTree {
 public:
  using Ptr = std::shared_ptr<GaussianKdTree>;
  using ConstPtr = std::shared_ptr<const GaussianKdTree>;
  using Params = filters::GaussianKdTreeParams;

  GaussianKdTree();
  explicit GaussianKdTree(const Params& params);
  ~GaussianKdTree();
  GaussianKdTree(GaussianKdTree&&) noexcept;
  GaussianKdTree& operator=(GaussianKdTree&&) noexcept;

  void setParams(const Params& params) { params_ = params; }
  const Params& getParams() const { return params_; }

  /** \brief Uploads N x d positions (already divided by the bandwidth) and builds the tree on the
   * GPU. Throws Error for an empty matrix, non-finite coordinates or d > 64. */
  void build(const Eigen::MatrixXf& positions);
  /** \brief Same, from n rows of d floats, row-major (one point after the other). */
  void build(const float* positions, int n, int d);

  /** \brief out (Q x v) = sum_j exp(-|q - p_j|^2/2) values_j (Eq. 10), splat + blur + slice. */
  void filter(const Eigen::MatrixXf& values, const Eigen::MatrixXf& queries,
              Eigen::MatrixXf& out) const;
  /** \brief Blurred sample values (M x v). */
  void splatBlur(const Eigen::MatrixXf& values, Eigen::MatrixXf& sample_values) const;
  /** \brief out (Q x v) interpolated from blurred sample values (M x v). */
  void slice(const Eigen::MatrixXf& sample_values, const Eigen::MatrixXf& queries,
             Eigen::MatrixXf& out) const;

  std::size_t numPoints() const;
  std::size_t numSamples() const;
  int dimension() const;
  /** \brief Depth of the tree (levels below the root). */
  int depth() const;
  double samplingFactor() const;
  /** \brief Sample (leaf) positions, d x M (downloaded). */
  Eigen::MatrixXf samples() const;
  /** \brief The leaf of every data point (downloaded). */
  std::vector<int> leafOfPoints() const;
  /** \brief Device bytes held by the tree. */
  std::size_t memoryBytes() const;

  /** \brief The device-side tree, for the GPU mean shift (internal type). */
  const detail::TreeDevice& device() const;

 private:
  void requireBuilt() const;
  Params params_;
  std::unique_ptr<detail::TreeDevice> tree_;
};

}  // namespace gpu
}  // namespace pcl_animseg
