#include <pcl_animseg/error.h>
#include <pcl_animseg/filters/gaussian_kdtree.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

namespace pcl_animseg {
namespace filters {

namespace {
// Depth guard: a cell is a leaf beyond it even when still wide (only reached by pathological
// inputs, e.g. huge coordinates with min_leaf_points = 1).
constexpr int kMaxDepth = 60;
}  // namespace

void GaussianKdTree::build(const Eigen::MatrixXf& positions) {
  if (positions.rows() == 0 || positions.cols() == 0)
    throw Error("Gaussian kd-tree: no points to build from (empty position matrix)");
  if (!positions.allFinite())
    throw Error("Gaussian kd-tree: positions contain NaN or Inf; drop invalid points first");
  if (!(params_.leaf_extent > 0.0f) || params_.slice_samples < 1 || !(params_.slice_sigma > 0.0f) ||
      !(params_.blur_radius > 0.0f))
    throw Error("Gaussian kd-tree: leaf_extent, slice_samples, slice_sigma and blur_radius must be "
                "positive");
  const Eigen::MatrixXf pts = positions.transpose();  // d x N: a point's coordinates contiguous
  const int n = static_cast<int>(pts.cols());
  nodes_.clear();
  nodes_.reserve(2 * static_cast<std::size_t>(n / std::max(1, params_.min_leaf_points)) + 1);
  leaf_of_point_.assign(n, -1);
  std::vector<int> idx(n);
  for (int i = 0; i < n; ++i) idx[i] = i;
  sample_list_.clear();
  root_ = buildNode(pts, idx, 0, n, 0);
  const int d = static_cast<int>(pts.rows());
  const int m = static_cast<int>(sample_list_.size());
  samples_.resize(d, m);
  for (int l = 0; l < m; ++l) samples_.col(l) = sample_list_[l];
  sample_list_.clear();
  sample_list_.shrink_to_fit();
  // Bounding boxes of the samples under each node, for the blur's range search.
  box_min_.resize(d, nodes_.size());
  box_max_.resize(d, nodes_.size());
  computeBoxes(root_);
}

int GaussianKdTree::buildNode(const Eigen::MatrixXf& pts, std::vector<int>& idx, int begin, int end,
                              int depth) {
  const int d = static_cast<int>(pts.rows());
  Eigen::VectorXf lo = Eigen::VectorXf::Constant(d, std::numeric_limits<float>::max());
  Eigen::VectorXf hi = Eigen::VectorXf::Constant(d, std::numeric_limits<float>::lowest());
  for (int i = begin; i < end; ++i) {
    lo = lo.cwiseMin(pts.col(idx[i]));
    hi = hi.cwiseMax(pts.col(idx[i]));
  }
  int dim = 0;
  const float extent = (hi - lo).maxCoeff(&dim);
  const int count = end - begin;
  const int node = static_cast<int>(nodes_.size());
  nodes_.emplace_back();
  if (extent <= params_.leaf_extent || count < std::max(2, params_.min_leaf_points) ||
      depth >= kMaxDepth) {
    Eigen::VectorXd mean = Eigen::VectorXd::Zero(d);
    for (int i = begin; i < end; ++i) mean += pts.col(idx[i]).cast<double>();
    mean /= count;
    const int leaf = static_cast<int>(sample_list_.size());
    sample_list_.push_back(mean.cast<float>());
    for (int i = begin; i < end; ++i) leaf_of_point_[idx[i]] = leaf;
    nodes_[node].leaf = leaf;
    return node;
  }
  const float cut = 0.5f * (lo[dim] + hi[dim]);
  const auto mid_it = std::partition(idx.begin() + begin, idx.begin() + end,
                                     [&](int i) { return pts(dim, i) <= cut; });
  int mid = static_cast<int>(mid_it - idx.begin());
  // Float rounding can put every point on one side when the extent is tiny; split by count then.
  if (mid == begin || mid == end) mid = begin + count / 2;
  const int left = buildNode(pts, idx, begin, mid, depth + 1);
  const int right = buildNode(pts, idx, mid, end, depth + 1);
  nodes_[node].dim = dim;
  nodes_[node].cut = cut;
  nodes_[node].left = left;
  nodes_[node].right = right;
  return node;
}

void GaussianKdTree::computeBoxes(int node) {
  const Node& nd = nodes_[node];
  if (nd.leaf >= 0) {
    box_min_.col(node) = samples_.col(nd.leaf);
    box_max_.col(node) = samples_.col(nd.leaf);
    return;
  }
  computeBoxes(nd.left);
  computeBoxes(nd.right);
  box_min_.col(node) = box_min_.col(nd.left).cwiseMin(box_min_.col(nd.right));
  box_max_.col(node) = box_max_.col(nd.left).cwiseMax(box_max_.col(nd.right));
}

int GaussianKdTree::leafContaining(const float* q) const {
  if (root_ < 0) throw Error("Gaussian kd-tree: build() must be called before a query");
  int node = root_;
  while (nodes_[node].leaf < 0)
    node = q[nodes_[node].dim] <= nodes_[node].cut ? nodes_[node].left : nodes_[node].right;
  return nodes_[node].leaf;
}

double GaussianKdTree::samplingFactor() const {
  return samples_.cols() ? static_cast<double>(leaf_of_point_.size()) / samples_.cols() : 0.0;
}

std::size_t GaussianKdTree::memoryBytes() const {
  return nodes_.size() * sizeof(Node) +
         sizeof(float) * (samples_.size() + box_min_.size() + box_max_.size()) +
         sizeof(int) * leaf_of_point_.size();
}

void GaussianKdTree::splatBlur(const Eigen::MatrixXf& values, Eigen::MatrixXf& sample_values) const {
  if (root_ < 0) throw Error("Gaussian kd-tree: build() must be called before filtering");
  if (static_cast<std::size_t>(values.rows()) != leaf_of_point_.size())
    throw Error("Gaussian kd-tree: values must have one row per data point");
  const int v = static_cast<int>(values.cols());
  const int m = static_cast<int>(samples_.cols());
  const int d = static_cast<int>(samples_.rows());
  // Splat: each point into its own cell (accumulated in double: millions of points).
  Eigen::MatrixXd splat = Eigen::MatrixXd::Zero(v, m);
  for (Eigen::Index j = 0; j < values.rows(); ++j)
    splat.col(leaf_of_point_[j]) += values.row(j).transpose().cast<double>();
  // Blur: exact Gaussian between samples within blur_radius.
  Eigen::MatrixXf blurred(v, m);
  const float r2 = params_.blur_radius * params_.blur_radius;
#pragma omp parallel
  {
    std::vector<int> stack;
    Eigen::VectorXd acc(v);
#pragma omp for schedule(dynamic, 16)
    for (int l = 0; l < m; ++l) {
      acc.setZero();
      const float* s = samples_.col(l).data();
      stack.assign(1, root_);
      while (!stack.empty()) {
        const int node = stack.back();
        stack.pop_back();
        float dist2 = 0.0f;
        const float* lo = box_min_.col(node).data();
        const float* hi = box_max_.col(node).data();
        for (int k = 0; k < d && dist2 <= r2; ++k) {
          const float e = s[k] < lo[k] ? lo[k] - s[k] : (s[k] > hi[k] ? s[k] - hi[k] : 0.0f);
          dist2 += e * e;
        }
        if (dist2 > r2) continue;
        const Node& nd = nodes_[node];
        if (nd.leaf >= 0) {
          acc += std::exp(-0.5 * dist2) * splat.col(nd.leaf);
        } else {
          stack.push_back(nd.left);
          stack.push_back(nd.right);
        }
      }
      blurred.col(l) = acc.cast<float>();
    }
  }
  sample_values = blurred.transpose();
}

void GaussianKdTree::sliceOne(const float* q, const Eigen::MatrixXf& sv, float* out,
                              std::vector<std::pair<int, int>>& stack,
                              std::vector<int>& reached, std::vector<float>& dist) const {
  const int d = static_cast<int>(samples_.rows());
  const int v = static_cast<int>(sv.rows());
  const float inv_h_sqrt2 = 1.0f / (params_.slice_sigma * std::sqrt(2.0f));
  reached.clear();
  stack.assign(1, {root_, params_.slice_samples});
  while (!stack.empty()) {
    const auto [node, count] = stack.back();
    stack.pop_back();
    const Node& nd = nodes_[node];
    if (nd.leaf >= 0) {
      reached.push_back(nd.leaf);
      continue;
    }
    // Gaussian mass of the slice kernel on the left of the cut, divided by rounding.
    const float p_left = 0.5f * std::erfc((q[nd.dim] - nd.cut) * inv_h_sqrt2);
    const int n_left = static_cast<int>(std::lround(count * p_left));
    if (n_left > 0) stack.push_back({nd.left, n_left});
    if (count - n_left > 0) stack.push_back({nd.right, count - n_left});
  }
  // Weights relative to the nearest reached sample, so that they never all underflow.
  const float inv_2h2 = 0.5f / (params_.slice_sigma * params_.slice_sigma);
  float dmin = std::numeric_limits<float>::max();
  dist.resize(reached.size());
  for (std::size_t r = 0; r < reached.size(); ++r) {
    const float* s = samples_.col(reached[r]).data();
    float d2 = 0.0f;
    for (int k = 0; k < d; ++k) d2 += (q[k] - s[k]) * (q[k] - s[k]);
    dist[r] = d2;
    dmin = std::min(dmin, d2);
  }
  double wsum = 0.0;
  for (int c = 0; c < v; ++c) out[c] = 0.0f;
  for (std::size_t r = 0; r < reached.size(); ++r) {
    const float w = std::exp(-(dist[r] - dmin) * inv_2h2);
    wsum += w;
    const float* f = sv.col(reached[r]).data();
    for (int c = 0; c < v; ++c) out[c] += w * f[c];
  }
  const float inv = static_cast<float>(1.0 / wsum);
  for (int c = 0; c < v; ++c) out[c] *= inv;
}

void GaussianKdTree::slice(const Eigen::MatrixXf& sample_values, const Eigen::MatrixXf& queries,
                           const std::vector<int>& rows, Eigen::MatrixXf& out) const {
  if (root_ < 0) throw Error("Gaussian kd-tree: build() must be called before filtering");
  if (sample_values.rows() != samples_.cols())
    throw Error("Gaussian kd-tree: sample values must have one row per sample");
  if (queries.cols() != samples_.rows())
    throw Error("Gaussian kd-tree: queries have " + std::to_string(queries.cols()) +
                " dimensions, the tree " + std::to_string(samples_.rows()));
  const int v = static_cast<int>(sample_values.cols());
  if (out.rows() != queries.rows() || out.cols() != v) out.setZero(queries.rows(), v);
  const Eigen::MatrixXf sv = sample_values.transpose();  // v x M
  const int nrows = static_cast<int>(rows.size());
#pragma omp parallel
  {
    std::vector<std::pair<int, int>> stack;
    std::vector<int> reached;
    std::vector<float> dist;
    Eigen::VectorXf q(queries.cols());
    Eigen::VectorXf o(v);
#pragma omp for schedule(dynamic, 256)
    for (int r = 0; r < nrows; ++r) {
      q = queries.row(rows[r]).transpose();
      sliceOne(q.data(), sv, o.data(), stack, reached, dist);
      out.row(rows[r]) = o.transpose();
    }
  }
}

void GaussianKdTree::slice(const Eigen::MatrixXf& sample_values, const Eigen::MatrixXf& queries,
                           Eigen::MatrixXf& out) const {
  std::vector<int> rows(queries.rows());
  for (std::size_t i = 0; i < rows.size(); ++i) rows[i] = static_cast<int>(i);
  out.setZero(queries.rows(), sample_values.cols());
  slice(sample_values, queries, rows, out);
}

void GaussianKdTree::filter(const Eigen::MatrixXf& values, const Eigen::MatrixXf& queries,
                            Eigen::MatrixXf& out) const {
  Eigen::MatrixXf sv;
  splatBlur(values, sv);
  slice(sv, queries, out);
}

void bruteForceGaussTransform(const Eigen::MatrixXf& positions, const Eigen::MatrixXf& values,
                              const Eigen::MatrixXf& queries, Eigen::MatrixXf& out) {
  if (positions.rows() != values.rows() || positions.cols() != queries.cols())
    throw Error("bruteForceGaussTransform: mismatched matrix sizes");
  out.setZero(queries.rows(), values.cols());
  const Eigen::MatrixXf p = positions.transpose();
  const Eigen::MatrixXf vals = values.transpose();
#pragma omp parallel for schedule(static)
  for (Eigen::Index i = 0; i < queries.rows(); ++i) {
    const Eigen::VectorXf q = queries.row(i).transpose();
    Eigen::VectorXd acc = Eigen::VectorXd::Zero(values.cols());
    for (Eigen::Index j = 0; j < p.cols(); ++j)
      acc += std::exp(-0.5 * static_cast<double>((p.col(j) - q).squaredNorm())) *
             vals.col(j).cast<double>();
    out.row(i) = acc.cast<float>().transpose();
  }
}

}  // namespace filters
}  // namespace pcl_animseg
