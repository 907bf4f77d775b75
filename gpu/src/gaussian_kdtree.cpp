// Host side of the GPU Gaussian kd-tree: Eigen in and out, layout changes, argument checks.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/gaussian_kdtree.h>

#include "gkdtree_device.h"

#include <cmath>
#include <string>

namespace pcl_animseg {
namespace gpu {

namespace {
using RowMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

void checkParams(const filters::GaussianKdTreeParams& p) {
  if (!(p.leaf_extent > 0.0f) || p.slice_samples < 1 || !(p.slice_sigma > 0.0f) ||
      !(p.blur_radius > 0.0f))
    throw DeviceError(
        "Gaussian kd-tree: leaf_extent, slice_samples, slice_sigma and blur_radius must be "
        "positive");
  if (p.slice_samples > detail::kMaxSliceSamples)
    throw DeviceError("GPU Gaussian kd-tree: slice_samples is at most " +
                      std::to_string(detail::kMaxSliceSamples));
}
}  // namespace

GaussianKdTree::GaussianKdTree() = default;
GaussianKdTree::GaussianKdTree(const Params& params) : params_(params) {}
GaussianKdTree::~GaussianKdTree() = default;
GaussianKdTree::GaussianKdTree(GaussianKdTree&&) noexcept = default;
GaussianKdTree& GaussianKdTree::operator=(GaussianKdTree&&) noexcept = default;

void GaussianKdTree::build(const Eigen::MatrixXf& positions) {
  const RowMatrix rm = positions;
  build(rm.data(), static_cast<int>(rm.rows()), static_cast<int>(rm.cols()));
}

void GaussianKdTree::build(const float* positions, int n, int d) {
  if (n <= 0 || d <= 0)
    throw DeviceError("Gaussian kd-tree: no points to build from (empty position matrix)");
  if (d > detail::kMaxDim)
    throw DeviceError("GPU Gaussian kd-tree: " + std::to_string(d) + " dimensions, at most " +
                      std::to_string(detail::kMaxDim) + " are supported");
  checkParams(params_);
  const std::size_t total = static_cast<std::size_t>(n) * d;
  for (std::size_t i = 0; i < total; ++i)
    if (!std::isfinite(positions[i]))
      throw DeviceError(
          "Gaussian kd-tree: positions contain NaN or Inf; drop invalid points first");
  DeviceArray<float> pts(positions, total);
  auto tree = std::make_unique<detail::TreeDevice>();
  detail::buildTree(pts.ptr(), n, d, params_, *tree);
  tree_ = std::move(tree);
}

void GaussianKdTree::requireBuilt() const {
  if (!tree_ || tree_->root < 0)
    throw DeviceError("Gaussian kd-tree: build() must be called before filtering");
}

void GaussianKdTree::splatBlur(const Eigen::MatrixXf& values, Eigen::MatrixXf& sample_values) const {
  requireBuilt();
  if (values.rows() != tree_->n)
    throw DeviceError("Gaussian kd-tree: values must have one row per data point");
  const int v = static_cast<int>(values.cols());
  if (v < 1 || v > detail::kMaxValueDim)
    throw DeviceError("GPU Gaussian kd-tree: values need 1.." +
                      std::to_string(detail::kMaxValueDim) + " columns");
  const RowMatrix rv = values;
  DeviceArray<float> d_vals(rv.data(), rv.size());
  DeviceArray<float> d_sv;
  detail::splatBlur(*tree_, d_vals.ptr(), nullptr, v, params_.blur_radius, d_sv);
  RowMatrix sv(tree_->m, v);
  d_sv.download(sv.data());
  sample_values = sv;
}

void GaussianKdTree::slice(const Eigen::MatrixXf& sample_values, const Eigen::MatrixXf& queries,
                           Eigen::MatrixXf& out) const {
  requireBuilt();
  checkParams(params_);
  if (sample_values.rows() != tree_->m)
    throw DeviceError("Gaussian kd-tree: sample values must have one row per sample");
  if (queries.cols() != tree_->d)
    throw DeviceError("Gaussian kd-tree: queries have " + std::to_string(queries.cols()) +
                      " dimensions, the tree " + std::to_string(tree_->d));
  const int v = static_cast<int>(sample_values.cols());
  if (v < 1 || v > detail::kMaxValueDim)
    throw DeviceError("GPU Gaussian kd-tree: sample values need 1.." +
                      std::to_string(detail::kMaxValueDim) + " columns");
  const RowMatrix rsv = sample_values;
  const RowMatrix rq = queries;
  DeviceArray<float> d_sv(rsv.data(), rsv.size()), d_q(rq.data(), rq.size());
  DeviceArray<float> d_out(static_cast<std::size_t>(rq.rows()) * v);
  detail::slice(*tree_, params_, d_sv.ptr(), v, d_q.ptr(), nullptr, nullptr,
                static_cast<int>(rq.rows()), false, d_out.ptr());
  RowMatrix o(rq.rows(), v);
  d_out.download(o.data());
  out = o;
}

void GaussianKdTree::filter(const Eigen::MatrixXf& values, const Eigen::MatrixXf& queries,
                            Eigen::MatrixXf& out) const {
  Eigen::MatrixXf sv;
  splatBlur(values, sv);
  slice(sv, queries, out);
}

std::size_t GaussianKdTree::numPoints() const { return tree_ ? tree_->n : 0; }
std::size_t GaussianKdTree::numSamples() const { return tree_ ? tree_->m : 0; }
int GaussianKdTree::dimension() const { return tree_ ? tree_->d : 0; }
int GaussianKdTree::depth() const { return tree_ ? tree_->depth : 0; }
double GaussianKdTree::samplingFactor() const {
  return tree_ && tree_->m ? static_cast<double>(tree_->n) / tree_->m : 0.0;
}

Eigen::MatrixXf GaussianKdTree::samples() const {
  requireBuilt();
  Eigen::MatrixXf s(tree_->d, tree_->m);  // column-major d x M = row-major M x d
  tree_->samples.download(s.data());
  return s;
}

std::vector<int> GaussianKdTree::leafOfPoints() const {
  requireBuilt();
  std::vector<int> l;
  tree_->leaf_of_point.download(l);
  return l;
}

std::size_t GaussianKdTree::memoryBytes() const {
  if (!tree_) return 0;
  return tree_->nodes.sizeBytes() + tree_->samples.sizeBytes() + tree_->perm.sizeBytes() +
         tree_->leaf_begin.sizeBytes() + tree_->leaf_of_point.sizeBytes();
}

const detail::TreeDevice& GaussianKdTree::device() const {
  requireBuilt();
  return *tree_;
}

}  // namespace gpu
}  // namespace pcl_animseg
