// The CUDA engine behind MeanShiftSegmentation: gpu::MeanShift for the iteration, gpu trees for
// densities, with the keypoint pair rule of Eq. 5 realised by the same point groups as the CPU's
// JointKernelSum.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/gauss_transform.h>
#include <pcl_animseg/gpu/gaussian_kdtree.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <numeric>
#include <vector>

namespace pcl_animseg {
namespace gpu {

namespace {

/** The exact sums of the pair rule as the CPU's JointKernelSum groups them: the non-keypoints for
 * every query under the plain metric; the keypoints under the plain metric for plain queries and
 * under the pair metric (Eq. 5) for keypoint queries. A dimension whose metric is 0 is carried
 * along outside the distance. */
class ExactSums : public segmentation::DeviceExactSums {
 public:
  ExactSums(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
            const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint)
      : dim_(static_cast<int>(z.cols())) {
    if (metric_plain.size() != z.cols() || metric_key.size() != z.cols())
      throw DeviceError("GPU exact sums: metrics and data differ in dimension");
    if (!keypoint.empty() && keypoint.size() != static_cast<std::size_t>(z.rows()))
      throw DeviceError("GPU exact sums: keypoint flags must have one entry per point");
    std::vector<Eigen::Index> plain, key;
    segmentation::splitByKeypoint(keypoint, z.rows(), plain, key);
    add(z, plain, metric_plain, 0);
    add(z, key, metric_plain, 1);
    add(z, key, metric_key, 2);
  }
  ~ExactSums() override {
    if (calls_ && std::getenv("ANIMSEG_MS_TIMING"))
      std::fprintf(stderr,
                   "[gpu exact sums] %ld calls, %lld queries, %lld tiles summed, %lld skipped, "
                   "kernels %.3f s, calls %.3f s\n",
                   calls_, queries_, visited_, skipped_, kernel_s_, call_s_);
  }

  void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                const std::vector<char>& query_key, Eigen::MatrixXf& out) override {
    if (q.cols() != dim_ || out.cols() != dim_ + 1)
      throw DeviceError("GPU exact sums: queries or output of the wrong width");
    for (int r : rows) out.row(r).setZero();
    std::vector<int> plain_rows, key_rows;
    for (int r : rows) (!query_key.empty() && query_key[r] ? key_rows : plain_rows).push_back(r);
    for (const Group& g : groups_) {
      const std::vector<int>& rr =
          g.applies_to == 0 ? rows : (g.applies_to == 1 ? plain_rows : key_rows);
      if (rr.empty()) continue;
      const int dx = static_cast<int>(g.dist.size());
      // Buffers kept between calls (fresh pages for their 100 MB a call cost more than the
      // copies).
      const int dc = static_cast<int>(g.carried.size());
      const Eigen::Index nr = static_cast<Eigen::Index>(rr.size());
      if (queries_scaled_.size() < static_cast<std::size_t>(nr) * dx)
        queries_scaled_.resize(static_cast<std::size_t>(nr) * dx);
      if (sums_.size() < static_cast<std::size_t>(nr) * (dx + dc + 1))
        sums_.resize(static_cast<std::size_t>(nr) * (dx + dc + 1));
      Eigen::Map<Eigen::MatrixXf> qs(queries_scaled_.data(), nr, dx);
      const Eigen::Map<const Eigen::MatrixXf> sums(sums_.data(), nr, dx + dc + 1);
#pragma omp parallel for schedule(static)
      for (std::size_t r = 0; r < rr.size(); ++r)
        for (int k = 0; k < dx; ++k) qs(r, k) = q(rr[r], g.dist[k]) * g.scale[k];
      g.transform.evaluate(qs, sums_.data());
      const GaussTransformStats& st = g.transform.lastStats();
      ++calls_;
      queries_ += st.queries;
      visited_ += st.tiles_visited;
      skipped_ += st.tiles_skipped;
      kernel_s_ += st.kernel_seconds;
      call_s_ += st.seconds;
#pragma omp parallel for schedule(static)
      for (std::size_t r = 0; r < rr.size(); ++r) {
        // Back from the metric's units to the raw coordinates (the values of Eq. 10).
        for (int k = 0; k < dx; ++k) out(rr[r], g.dist[k]) += sums(r, k) / g.scale[k];
        for (int k = 0; k < dc; ++k) out(rr[r], g.carried[k]) += sums(r, dx + k);
        out(rr[r], dim_) += sums(r, dx + dc);
      }
    }
  }

 private:
  struct Group {
    GaussTransform transform;
    std::vector<int> dist, carried;  // dimensions in the distance / carried along
    std::vector<float> scale;        // the metric of each distance dimension
    int applies_to = 0;  // 0: every query, 1: plain queries only, 2: keypoint queries only
  };

  void add(const Eigen::MatrixXf& z, const std::vector<Eigen::Index>& idx,
           const Eigen::RowVectorXf& metric, int applies_to) {
    if (idx.empty()) return;
    Group g;
    g.applies_to = applies_to;
    for (int k = 0; k < dim_; ++k) {
      if (metric[k] > 0.0f) {
        g.dist.push_back(k);
        g.scale.push_back(metric[k]);
      } else {
        g.carried.push_back(k);
      }
    }
    if (g.dist.empty()) throw DeviceError("GPU exact sums: every weight of the metric is 0");
    const int dx = static_cast<int>(g.dist.size()), dc = static_cast<int>(g.carried.size());
    Eigen::MatrixXf x(idx.size(), dx), c(dc ? idx.size() : 0, dc);
#pragma omp parallel for schedule(static)
    for (std::size_t i = 0; i < idx.size(); ++i) {
      for (int k = 0; k < dx; ++k) x(i, k) = z(idx[i], g.dist[k]) * metric[g.dist[k]];
      for (int k = 0; k < dc; ++k) c(i, k) = z(idx[i], g.carried[k]);
    }
    g.transform.setData(x, c, 3.0f);
    groups_.push_back(std::move(g));
  }

  int dim_ = 0;
  std::vector<Group> groups_;
  std::vector<float> queries_scaled_, sums_;
  long calls_ = 0;
  long long queries_ = 0, visited_ = 0, skipped_ = 0;
  double kernel_s_ = 0.0, call_s_ = 0.0;
};

/** A 64-bit hash of `bytes` bytes (word by word, chunks in parallel, combined in order): the
 * density cache's key. */
std::uint64_t hashBytes(const void* data, std::size_t bytes, std::uint64_t seed) {
  constexpr std::size_t kChunk = std::size_t{1} << 20;
  const auto* p = static_cast<const unsigned char*>(data);
  const std::size_t chunks = (bytes + kChunk - 1) / kChunk;
  std::vector<std::uint64_t> part(chunks);
#pragma omp parallel for schedule(static)
  for (std::ptrdiff_t c = 0; c < static_cast<std::ptrdiff_t>(chunks); ++c) {
    const std::size_t lo = static_cast<std::size_t>(c) * kChunk;
    const std::size_t hi = std::min(bytes, lo + kChunk);
    std::uint64_t h = 0x9e3779b97f4a7c15ull ^ (hi - lo);
    std::size_t i = lo;
    for (; i + 8 <= hi; i += 8) {
      std::uint64_t w;
      std::memcpy(&w, p + i, 8);
      h = (h ^ w) * 0xff51afd7ed558ccdull;
      h ^= h >> 32;
    }
    for (; i < hi; ++i) h = (h ^ p[i]) * 0x100000001b3ull;
    part[c] = h;
  }
  std::uint64_t h = seed ^ bytes;
  for (std::uint64_t v : part) {
    h = (h ^ v) * 0xc4ceb9fe1a85ec53ull;
    h ^= h >> 29;
  }
  return h;
}

}  // namespace

struct MeanShiftBackend::DensityCache {
  std::uint64_t key = 0;
  // Per group of the pair rule (see density()): the tree and its blurred weights (none: empty).
  GaussianKdTree trees[3];
  Eigen::MatrixXf weights[3];
  bool built[3] = {false, false, false};
  std::unique_ptr<ExactSums> exact;  // the exact backend's sums (params.backend == Exact)
  // The iteration's trees and blurred values on the same data (seekModes): the same densities
  // without building the trees again.
  std::unique_ptr<MeanShift> iteration;
};

namespace {

std::uint64_t densityKey(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                         const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
                         const filters::GaussianKdTreeParams& g) {
  std::uint64_t h = hashBytes(z.data(), sizeof(float) * z.size(), 0x1234u + z.rows());
  h = hashBytes(metric_plain.data(), sizeof(float) * metric_plain.size(), h + z.cols());
  h = hashBytes(metric_key.data(), sizeof(float) * metric_key.size(), h);
  h = hashBytes(keypoint.data(), keypoint.size(), h + keypoint.size());
  const float fields[5] = {g.leaf_extent, static_cast<float>(g.min_leaf_points), g.blur_radius,
                           static_cast<float>(g.slice_samples), g.slice_sigma};
  return hashBytes(fields, sizeof fields, h);
}

}  // namespace

std::string MeanShiftBackend::name() const { return deviceLabel(); }

std::unique_ptr<segmentation::DeviceExactSums> MeanShiftBackend::exactSums(
    const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
    const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint) {
  requireGpu();
  if (z.rows() == 0) throw DeviceError("GPU exact sums: no data points");
  return std::make_unique<ExactSums>(z, metric_plain, metric_key, keypoint);
}

void MeanShiftBackend::seekModes(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                                 const Eigen::RowVectorXf& metric_key,
                                 const std::vector<char>& keypoint,
                                 const segmentation::MeanShiftParams& params, Eigen::MatrixXf& y,
                                 Eigen::VectorXf& density) {
  requireGpu();
  density_cache_.reset();  // the last data's device memory first
  auto ms = std::make_unique<MeanShift>();
  MeanShiftParams p;
  p.gkdtree = params.gkdtree;
  p.max_iterations = params.max_iterations;
  p.convergence = params.convergence;
  ms->setParams(p);
  ms->run(z, metric_plain, metric_key, keypoint, y, density);
  stats_ = ms->stats();
  // Its trees stay for the densities on the same data (the end points' after the exact steps,
  // the points', the border rounds').
  auto cache = std::make_shared<DensityCache>();
  cache->key = densityKey(z, metric_plain, metric_key, keypoint, params.gkdtree);
  cache->iteration = std::move(ms);
  density_cache_ = std::move(cache);
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr,
                 "[gpu mean shift] upload %.3f s, build %.3f s, splat + blur %.3f s, %d steps "
                 "%.3f s, density %.3f s, download %.3f s\n",
                 stats_.upload_s, stats_.build_s, stats_.splat_blur_s, stats_.iterations,
                 stats_.iterate_s, stats_.density_s, stats_.download_s);
}

void MeanShiftBackend::density(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                               const Eigen::RowVectorXf& metric_key,
                               const std::vector<char>& keypoint,
                               const segmentation::MeanShiftParams& params,
                               const Eigen::MatrixXf& queries, const std::vector<char>& query_key,
                               Eigen::VectorXf& out) {
  requireGpu();
  const Eigen::Index n = z.rows(), q = queries.rows();
  if (queries.cols() != z.cols())
    throw DeviceError("GPU density: queries and data differ in dimension");
  if (!keypoint.empty() && keypoint.size() != static_cast<std::size_t>(n))
    throw DeviceError("GPU density: keypoint flags must have one entry per point");
  if (!query_key.empty() && query_key.size() != static_cast<std::size_t>(q))
    throw DeviceError("GPU density: query flags must have one entry per query");
  out.setZero(q);
  if (q == 0) return;
  // The trees and blurred weights (or the exact sums' data) are kept for the next call on the
  // same data (the same values as making them again: they do not depend on the queries).
  const std::uint64_t key_now = densityKey(z, metric_plain, metric_key, keypoint, params.gkdtree);
  if (!density_cache_ || density_cache_->key != key_now) {
    density_cache_.reset();  // the old trees' device memory first
    density_cache_ = std::make_shared<DensityCache>();
    density_cache_->key = key_now;
  }
  DensityCache& cache = *density_cache_;
  if (params.backend == segmentation::MeanShiftBackend::Exact) {
    try {
      if (!cache.exact)
        cache.exact = std::make_unique<ExactSums>(z, metric_plain, metric_key, keypoint);
      std::vector<int> rows(static_cast<std::size_t>(q));
      std::iota(rows.begin(), rows.end(), 0);
      Eigen::MatrixXf res(q, z.cols() + 1);
      cache.exact->evaluate(queries, rows, query_key, res);
      out = res.col(z.cols());
    } catch (...) {
      density_cache_.reset();
      throw;
    }
    return;
  }
  if (cache.iteration) {
    cache.iteration->density(queries, query_key, out);
    return;
  }
  // Groups as on the CPU: non-keypoints for every query under the plain metric; keypoints under
  // the plain metric for plain queries and under the pair metric (Eq. 5) for keypoint queries.
  std::vector<Eigen::Index> plain, key;
  segmentation::splitByKeypoint(keypoint, n, plain, key);
  std::vector<Eigen::Index> qplain, qkey;  // keypoint queries only where there are keypoints
  const std::vector<char> none;
  segmentation::splitByKeypoint(keypoint.empty() ? none : query_key, q, qplain, qkey);
  auto add = [&](int slot, const std::vector<Eigen::Index>& data,
                 const std::vector<Eigen::Index>& rows, const Eigen::RowVectorXf& metric,
                 bool all_queries) {
    if (data.empty()) return;
    const std::size_t nr = all_queries ? static_cast<std::size_t>(q) : rows.size();
    if (nr == 0) return;
    if (!cache.built[slot]) {
      Eigen::MatrixXf x(data.size(), z.cols());
      for (std::size_t i = 0; i < data.size(); ++i) x.row(i) = z.row(data[i]).cwiseProduct(metric);
      cache.trees[slot] = GaussianKdTree(params.gkdtree);
      cache.trees[slot].build(x);
      cache.trees[slot].splatBlur(Eigen::MatrixXf::Ones(x.rows(), 1), cache.weights[slot]);
      cache.built[slot] = true;
    }
    Eigen::MatrixXf qs(nr, z.cols());
    for (std::size_t r = 0; r < nr; ++r)
      qs.row(r) =
          queries.row(all_queries ? static_cast<Eigen::Index>(r) : rows[r]).cwiseProduct(metric);
    Eigen::MatrixXf res;
    cache.trees[slot].slice(cache.weights[slot], qs, res);
    for (std::size_t r = 0; r < nr; ++r)
      out[all_queries ? static_cast<Eigen::Index>(r) : rows[r]] += res(r, 0);
  };
  try {
    add(0, plain, {}, metric_plain, true);
    add(1, key, qplain, metric_plain, false);
    add(2, key, qkey, metric_key, false);
  } catch (...) {
    density_cache_.reset();  // never keep a half-built entry
    throw;
  }
}

std::shared_ptr<segmentation::MeanShiftDeviceBackend> makeMeanShiftBackend(bool check_now) {
  if (check_now) requireGpu();
  return std::make_shared<MeanShiftBackend>();
}

}  // namespace gpu
}  // namespace pcl_animseg
