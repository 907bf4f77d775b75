// GPU mean shift: the CPU's runPaper loop with every step on the device.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/device_array.h>
#include <pcl_animseg/gpu/mean_shift.h>
#include <pcl_animseg/segmentation/mean_shift.h>

#include "gkdtree_device.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <memory>
#include <numeric>
#include <string>
#include <unordered_map>

namespace pcl_animseg {
namespace gpu {

namespace {
using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

struct Group {
  detail::TreeDevice tree;
  DeviceArray<float> sample_values;
  DeviceArray<float> metric;  // the metric its data and queries are scaled by
  int applies_to = 0;         // 0: every query, 1: plain queries, 2: keypoint queries
};

/** out (rows listed, nrows of them: np plain then nk keypoint queries; n x (d + 1) row-major) =
 * the kernel sums of every group that applies to each query, added in group order. */
void evaluateGroups(const std::vector<std::unique_ptr<Group>>& groups,
                    const filters::GaussianKdTreeParams& gp, int v, const float* queries,
                    const int* rows, int np, int nk, float* out) {
  for (const auto& g : groups) {
    const int* r = rows;
    int nr = np + nk;
    if (g->applies_to == 1) nr = np;
    if (g->applies_to == 2) r = rows + np, nr = nk;
    detail::slice(g->tree, gp, g->sample_values.ptr(), v, queries, g->metric.ptr(), r, nr, true,
                  out);
  }
}

/** A column-major host matrix (n x d) as n x d row-major on the device. */
void uploadRows(const Eigen::MatrixXf& m, DeviceArray<float>& rows) {
  const int n = static_cast<int>(m.rows()), d = static_cast<int>(m.cols());
  DeviceArray<float> cols(m.data(), m.size());
  rows.create(m.size());
  detail::transpose(cols.ptr(), d, n, rows.ptr());
}
}  // namespace

struct MeanShift::State {
  int d = 0;
  filters::GaussianKdTreeParams gkdtree;
  std::vector<std::unique_ptr<Group>> groups;
};

MeanShift::MeanShift() = default;
MeanShift::~MeanShift() = default;
MeanShift::MeanShift(MeanShift&&) noexcept = default;
MeanShift& MeanShift::operator=(MeanShift&&) noexcept = default;

void MeanShift::run(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                    const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
                    Eigen::MatrixXf& y, Eigen::VectorXf& density) {
  stats_ = MeanShiftStats();
  state_.reset();
  const int n = static_cast<int>(z.rows());
  const int d = static_cast<int>(z.cols());
  if (n == 0 || d == 0) throw DeviceError("GPU mean shift: no points");
  if (d > detail::kMaxDim)
    throw DeviceError("GPU mean shift: " + std::to_string(d) + " feature dimensions, at most " +
                      std::to_string(detail::kMaxDim) + " are supported");
  if (metric_plain.size() != d || (!keypoint.empty() && metric_key.size() != d))
    throw DeviceError("GPU mean shift: metric size differs from the feature dimension");
  if (!keypoint.empty() && static_cast<int>(keypoint.size()) != n)
    throw DeviceError("GPU mean shift: keypoint flags must have one entry per point");
  if (!z.allFinite()) throw DeviceError("GPU mean shift: non-finite features");
  if (params_.max_iterations < 1) throw DeviceError("GPU mean shift: max iterations must be >= 1");
  const filters::GaussianKdTreeParams& gp = params_.gkdtree;
  if (!(gp.leaf_extent > 0.0f) || gp.slice_samples < 1 ||
      gp.slice_samples > detail::kMaxSliceSamples || !(gp.slice_sigma > 0.0f) ||
      !(gp.blur_radius > 0.0f))
    throw DeviceError(
        "GPU mean shift: bad Gaussian kd-tree parameters (positive, slice_samples <= 64)");
  resetPeakDeviceBytes();

  auto t0 = Clock::now();
  // The features go up as they are (column-major) and are put in rows on the device.
  DeviceArray<float> d_z;  // raw features: the values [z, 1] (Eq. 10)
  uploadRows(z, d_z);
  DeviceArray<float> d_y;
  d_z.copyTo(d_y);
  // Active list: plain queries first, then keypoint queries (the groups slice sub-ranges).
  std::vector<int> plain, key;
  plain.reserve(n);
  segmentation::splitByKeypoint(keypoint, n, plain, key);
  const bool has_key = !key.empty();
  std::vector<int> order(plain);
  order.insert(order.end(), key.begin(), key.end());
  DeviceArray<int> active(order.data(), order.size()), next_plain(n), next_key(n), counters(2);
  DeviceArray<unsigned char> d_key;
  if (has_key) {
    std::vector<unsigned char> k(keypoint.begin(), keypoint.end());
    d_key.upload(k);
  }
  DeviceArray<float> d_metric_plain(metric_plain.data(), d);
  const int v = d + 1;
  DeviceArray<float> out(static_cast<std::size_t>(n) * v);
  stats_.upload_s = since(t0);

  // The groups of the CPU's JointKernelSum; their data gathered and scaled on the device.
  auto state = std::make_unique<State>();
  state->d = d;
  state->gkdtree = gp;
  auto make = [&](const std::vector<int>& idx, bool key_metric, int applies) {
    if (idx.empty()) return;
    auto tb = Clock::now();
    const Eigen::RowVectorXf& m = key_metric ? metric_key : metric_plain;
    const int ni = static_cast<int>(idx.size());
    auto g = std::make_unique<Group>();
    g->applies_to = applies;
    g->metric.upload(m.data(), d);
    DeviceArray<int> d_idx(idx.data(), idx.size());
    DeviceArray<float> draw(static_cast<std::size_t>(ni) * d);
    {
      DeviceArray<float> dx(static_cast<std::size_t>(ni) * d);
      detail::gatherRows(d_z.ptr(), d, d_idx.ptr(), ni, g->metric.ptr(), draw.ptr(), dx.ptr());
      detail::buildTree(dx.ptr(), ni, d, gp, g->tree);
    }
    stats_.build_s += since(tb);
    tb = Clock::now();
    detail::splatBlur(g->tree, nullptr, draw.ptr(), v, gp.blur_radius, g->sample_values);
    stats_.splat_blur_s += since(tb);
    stats_.num_samples += g->tree.m;
    if (applies == 0) {
      stats_.plain_points = static_cast<std::size_t>(ni);
      stats_.plain_samples = g->tree.m;
    }
    state->groups.push_back(std::move(g));
  };
  make(plain, false, 0);
  make(key, false, 1);  // Eq. 6 between a keypoint and a non-keypoint query
  make(key, true, 2);   // Eq. 5 between two keypoints

  auto evaluate = [&](const int* rows, int np, int nk) {
    out.setZero();
    evaluateGroups(state->groups, gp, v, d_y.ptr(), rows, np, nk, out.ptr());
  };

  t0 = Clock::now();
  int np = static_cast<int>(plain.size()), nk = static_cast<int>(key.size());
  const float tol = static_cast<float>(params_.convergence);
  for (int it = 0; it < params_.max_iterations && np + nk > 0; ++it) {
    const auto ts = Clock::now();
    evaluate(active.ptr(), np, nk);
    int np2 = 0, nk2 = 0;
    detail::meanShiftUpdate(d_y.ptr(), out.ptr(), d, active.ptr(), np + nk, d_metric_plain.ptr(),
                            has_key ? d_key.ptr() : nullptr, tol, next_plain.ptr(),
                            next_key.ptr(), counters.ptr(), np2, nk2);
    // Next active list: moved plain rows, then moved keypoint rows. Their order (atomic appends)
    // varies between runs but no result depends on it: each row is filtered on its own.
    std::swap(active, next_plain);
    if (nk2)
      detail::copyDeviceBytes(active.ptr() + np2, next_key.ptr(), sizeof(int) * nk2);
    np = np2;
    nk = nk2;
    stats_.iterations = it + 1;
    stats_.active.push_back(np + nk);
    stats_.step_s.push_back(since(ts));
  }
  stats_.not_converged = np + nk;
  stats_.iterate_s = since(t0);

  // Density at the end points (the CPU's last evaluate over all rows).
  t0 = Clock::now();
  active.upload(order);
  evaluate(active.ptr(), static_cast<int>(plain.size()), static_cast<int>(key.size()));
  synchronize();
  stats_.density_s = since(t0);

  // Down: the end points put back in columns on the device, and the density column alone.
  t0 = Clock::now();
  {
    DeviceArray<float> cols(static_cast<std::size_t>(n) * d);
    detail::transpose(d_y.ptr(), n, d, cols.ptr());
    y.resize(n, d);
    cols.download(y.data());
  }
  {
    DeviceArray<float> col(n);
    detail::column(out.ptr(), n, v, d, col.ptr());
    density.resize(n);
    col.download(density.data());
  }
  stats_.download_s = since(t0);
  stats_.peak_device_bytes = peakDeviceBytes();
  state_ = std::move(state);
}

void MeanShift::density(const Eigen::MatrixXf& queries, const std::vector<char>& query_key,
                        Eigen::VectorXf& out) const {
  if (!state_) throw DeviceError("GPU mean shift: density before a run");
  const int q = static_cast<int>(queries.rows()), d = state_->d, v = d + 1;
  if (queries.cols() != d) throw DeviceError("GPU density: queries and data differ in dimension");
  if (!query_key.empty() && query_key.size() != static_cast<std::size_t>(q))
    throw DeviceError("GPU density: query flags must have one entry per query");
  out.setZero(q);
  if (q == 0) return;
  DeviceArray<float> d_q;
  uploadRows(queries, d_q);
  // Plain queries first, then keypoint queries, as the iteration lists them.
  std::vector<int> rows, key_rows;
  rows.reserve(static_cast<std::size_t>(q));
  segmentation::splitByKeypoint(query_key, q, rows, key_rows);
  const int np = static_cast<int>(rows.size()), nk = static_cast<int>(key_rows.size());
  rows.insert(rows.end(), key_rows.begin(), key_rows.end());
  DeviceArray<int> d_rows(rows.data(), rows.size());
  DeviceArray<float> sums(static_cast<std::size_t>(q) * v);
  sums.setZero();
  evaluateGroups(state_->groups, state_->gkdtree, v, d_q.ptr(), d_rows.ptr(), np, nk, sums.ptr());
  DeviceArray<float> col(q);
  detail::column(sums.ptr(), q, v, d, col.ptr());
  col.download(out.data());
}

void groupModes(const Eigen::MatrixXf& y, const Eigen::RowVectorXf& metric_plain,
                const Eigen::VectorXf& density, double merge_radius, std::vector<int>& labels,
                std::vector<int>& mode_rep) {
  // One implementation for both paths, so that they cannot drift apart.
  segmentation::groupModes(y, metric_plain, density, merge_radius, labels, mode_rep);
}

}  // namespace gpu
}  // namespace pcl_animseg
