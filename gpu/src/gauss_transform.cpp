// Host side of the exact Gauss transform (gauss_transform.h): argument checks, the kd order of
// data and queries, the tiles' boxes, copies.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/device_array.h>
#include <pcl_animseg/gpu/gauss_transform.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <string>
#include <utility>
#include <vector>

#include "gauss_transform_device.h"

namespace pcl_animseg {
namespace gpu {

namespace {

constexpr float kFar = 1e18f;  // padding rows: beyond any cutoff, and their square still finite
constexpr std::size_t kPartialBytes = std::size_t{256} << 20;  // the split sums of one call

/** The rows 0..n-1 of a matrix (its coordinate k of row i: at(i, k); the first `dims` compared)
 * ordered so that every run of `leaf` consecutive rows (from 0) is a cell of a kd-tree: each
 * cell is halved at a multiple of `leaf` rows by the median of its widest coordinate, the widths
 * measured on at most kWidthSample of its rows (the order only decides which tiles a block can
 * skip, not the sums; every row of every cell made the queries' order cost four times the
 * device's sums). */
template <typename At>
std::vector<int> kdOrder(const At& at, int n, int dims, int leaf) {
  std::vector<int> order(n);
  std::iota(order.begin(), order.end(), 0);
  std::vector<std::pair<int, int>> level{{0, n}}, next;
  while (!level.empty()) {
    next.assign(level.size() * 2, {0, 0});
#pragma omp parallel for schedule(dynamic, 1) if (level.size() > 1)
    for (std::ptrdiff_t c = 0; c < static_cast<std::ptrdiff_t>(level.size()); ++c) {
      const int lo = level[c].first, hi = level[c].second;
      if (hi - lo <= leaf) continue;
      constexpr int kWidthSample = 256;
      const int step = std::max(1, (hi - lo) / kWidthSample);
      std::vector<float> a(dims), b(dims);
      for (int k = 0; k < dims; ++k) a[k] = b[k] = at(order[lo], k);
      for (int i = lo + step; i < hi; i += step)
        for (int k = 0; k < dims; ++k) {
          a[k] = std::min(a[k], at(order[i], k));
          b[k] = std::max(b[k], at(order[i], k));
        }
      int best = 0;
      for (int k = 1; k < dims; ++k)
        if (b[k] - a[k] > b[best] - a[best]) best = k;
      const int cells = (hi - lo + leaf - 1) / leaf;
      const int mid = lo + cells / 2 * leaf;
      std::nth_element(order.begin() + lo, order.begin() + mid, order.begin() + hi,
                       [&](int i, int j) {
                         const float vi = at(i, best), vj = at(j, best);
                         return vi < vj || (vi == vj && i < j);
                       });
      next[2 * c] = {lo, mid};
      next[2 * c + 1] = {mid, hi};
    }
    level.clear();
    for (const auto& cell : next)
      if (cell.second - cell.first > leaf) level.push_back(cell);
  }
  return order;
}

int strideFor(int width) {
  for (int s : {8, 16, 32, 64})
    if (width <= s) return s;
  return 0;
}

using Clock = std::chrono::steady_clock;

}  // namespace

struct GaussTransform::Data {
  int n = 0, dx = 0, dc = 0, stride = 0, tiles = 0, multiprocessors = 1;
  float cutoff2 = 9.0f;
  DeviceArray<float> x, tile_lo, tile_hi;
  // Per call, kept between calls.
  mutable DeviceArray<float> q, sums;
  mutable DeviceArray<int> order;
  mutable DeviceArray<double> partial;
  mutable DeviceArray<unsigned long long> counters;
  mutable std::vector<float> host_sorted;
};

GaussTransform::GaussTransform() = default;
GaussTransform::~GaussTransform() = default;
GaussTransform::GaussTransform(GaussTransform&&) noexcept = default;
GaussTransform& GaussTransform::operator=(GaussTransform&&) noexcept = default;

std::size_t GaussTransform::size() const { return data_ ? static_cast<std::size_t>(data_->n) : 0; }
int GaussTransform::distanceDims() const { return data_ ? data_->dx : 0; }
int GaussTransform::carriedDims() const { return data_ ? data_->dc : 0; }

void GaussTransform::setData(const Eigen::MatrixXf& x, const Eigen::MatrixXf& carried,
                             float cutoff) {
  const Eigen::Index n = x.rows();
  const int dx = static_cast<int>(x.cols());
  const int dc = carried.size() ? static_cast<int>(carried.cols()) : 0;
  if (n == 0 || dx == 0) throw DeviceError("GPU Gauss transform: no data points");
  if (dc && carried.rows() != n)
    throw DeviceError("GPU Gauss transform: the carried coordinates need one row per data point");
  if (dx + dc > 64)
    throw DeviceError("GPU Gauss transform: " + std::to_string(dx + dc) +
                      " dimensions, at most 64 are supported");
  if (n > (Eigen::Index{1} << 30)) throw DeviceError("GPU Gauss transform: too many data points");
  if (!(cutoff > 0.0f) || !std::isfinite(cutoff))
    throw DeviceError("GPU Gauss transform: the cutoff must be positive");
  if (!x.allFinite() || (dc && !carried.allFinite()))
    throw DeviceError("GPU Gauss transform: the data contain NaN or Inf");
  requireGpu();
  auto d = std::make_unique<Data>();
  d->n = static_cast<int>(n);
  d->dx = dx;
  d->dc = dc;
  d->stride = strideFor(dx + dc);
  d->cutoff2 = cutoff * cutoff;
  d->multiprocessors = std::max(1, deviceInfo().multiprocessors);
  const int s = d->stride;
  const int tile = detail::kGaussTile;
  d->tiles = static_cast<int>((n + tile - 1) / tile);
  const std::vector<int> order = kdOrder([&](int i, int k) { return x(i, k); }, d->n, dx, tile);
  std::vector<float> tiled(static_cast<std::size_t>(d->tiles) * tile * s, 0.0f);
  std::vector<float> lo(static_cast<std::size_t>(d->tiles) * s, 0.0f), hi(lo.size(), 0.0f);
#pragma omp parallel for schedule(static)
  for (int t = 0; t < d->tiles; ++t) {
    float* blo = lo.data() + static_cast<std::size_t>(t) * s;
    float* bhi = hi.data() + static_cast<std::size_t>(t) * s;
    for (int k = 0; k < dx; ++k) {
      blo[k] = kFar;
      bhi[k] = -kFar;
    }
    for (int m = 0; m < tile; ++m) {
      const std::size_t i = static_cast<std::size_t>(t) * tile + m;
      float* dst = tiled.data() + i * s;
      if (i >= static_cast<std::size_t>(n)) {
        for (int k = 0; k < dx; ++k) dst[k] = kFar;
        continue;
      }
      const Eigen::Index src = order[i];
      for (int k = 0; k < dx; ++k) {
        dst[k] = x(src, k);
        blo[k] = std::min(blo[k], dst[k]);
        bhi[k] = std::max(bhi[k], dst[k]);
      }
      for (int k = 0; k < dc; ++k) dst[dx + k] = carried(src, k);
    }
  }
  d->x.upload(tiled);
  d->tile_lo.upload(lo);
  d->tile_hi.upload(hi);
  d->counters.create(2);
  data_ = std::move(d);
}

void GaussTransform::evaluate(const Eigen::Ref<const Eigen::MatrixXf>& q,
                              Eigen::MatrixXf& out) const {
  if (data_) out.resize(q.rows(), data_->dx + data_->dc + 1);
  evaluate(q, out.data());
}

void GaussTransform::evaluate(const Eigen::Ref<const Eigen::MatrixXf>& q, float* out) const {
  if (!data_) throw DeviceError("GPU Gauss transform: setData() must be called before evaluate()");
  const Data& d = *data_;
  if (q.cols() != d.dx)
    throw DeviceError("GPU Gauss transform: queries have " + std::to_string(q.cols()) +
                      " coordinates, the data " + std::to_string(d.dx));
  if (!q.allFinite()) throw DeviceError("GPU Gauss transform: the queries contain NaN or Inf");
  if (q.rows() > (Eigen::Index{1} << 30))
    throw DeviceError("GPU Gauss transform: too many queries");
  const auto start = Clock::now();
  const int nq = static_cast<int>(q.rows());
  const int s = d.stride;
  stats_ = GaussTransformStats();
  stats_.queries = nq;
  if (nq == 0) return;
  const std::vector<int> order =
      kdOrder([&](int i, int k) { return q(i, k); }, nq, d.dx, detail::kGaussTile);
  // The queries in that order, `s` floats a row (0 past the distance coordinates), in a host
  // buffer kept between calls (fresh pages for 100 MB a call cost more than filling them).
  std::vector<float>& sorted = d.host_sorted;
  sorted.resize(static_cast<std::size_t>(nq) * s);
#pragma omp parallel for schedule(static)
  for (int r = 0; r < nq; ++r) {
    float* row = sorted.data() + static_cast<std::size_t>(r) * s;
    for (int k = 0; k < d.dx; ++k) row[k] = q(order[r], k);
    std::fill(row + d.dx, row + s, 0.0f);
  }
  // Enough blocks to fill the device: few queries spread the data over more of them.
  const int blocks = (nq + detail::kGaussTile - 1) / detail::kGaussTile;
  const int wanted = (8 * d.multiprocessors + blocks - 1) / blocks;
  const std::size_t row_bytes = static_cast<std::size_t>(nq) * (s + 1) * sizeof(double);
  const int by_memory = static_cast<int>(std::max<std::size_t>(1, kPartialBytes / row_bytes));
  const int splits = std::max(1, std::min({wanted, std::max(1, d.tiles / 4), by_memory}));
  d.q.upload(sorted.data(), static_cast<std::size_t>(nq) * s);
  d.order.upload(order);
  d.partial.create(static_cast<std::size_t>(splits) * nq * (s + 1));
  d.counters.setZero();
  detail::DeviceClock clock;
  clock.start();
  detail::gaussTransformPartial(d.x.ptr(), d.tile_lo.ptr(), d.tile_hi.ptr(), d.tiles, s, d.dx,
                                d.dc > 0, d.q.ptr(), nq, splits, d.cutoff2, d.partial.ptr(),
                                d.counters.ptr());
  const int width = d.dx + d.dc;
  d.sums.create(static_cast<std::size_t>(nq) * (width + 1));
  detail::gaussTransformFinish(d.partial.ptr(), nq, s, splits, d.order.ptr(), width, d.sums.ptr());
  stats_.kernel_seconds = clock.seconds();
  d.sums.download(out);  // column-major, in the caller's row order
  unsigned long long counts[2] = {0, 0};
  d.counters.download(counts);
  stats_.tiles_visited = static_cast<long long>(counts[0]);
  stats_.tiles_skipped = static_cast<long long>(counts[1]);
  stats_.splits = splits;
  stats_.seconds = std::chrono::duration<double>(Clock::now() - start).count();
}

}  // namespace gpu
}  // namespace pcl_animseg
