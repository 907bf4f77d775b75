// Packs the rigid motions' fits (segmentation::RigidFitDevice) for tracking_kernels.cu.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/rigid_fits.h>
#include <pcl_animseg/segmentation/icp_step.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <system_error>
#include <tuple>
#include <utility>
#include <vector>

#include "frame_packing.h"
#include "tracking_kernels.h"

namespace pcl_animseg {
namespace gpu {

namespace detail {
struct RigidSources {
  DeviceArray<double> points;     // x, y, z per point, every source after the other
  DeviceArray<int> orders;        // each source's rigidSearchOrder, packed the same way
  std::vector<int> begin, count;  // per source, in points
};

std::vector<int> rigidSearchOrder(const std::vector<double>& xyz) {
  const int n = static_cast<int>(xyz.size() / 3);
  std::vector<int> order(n);
  for (int i = 0; i < n; ++i) order[i] = i;
  if (n == 0) return order;
  double lo[3], hi[3];
  for (int k = 0; k < 3; ++k) lo[k] = hi[k] = xyz[k];
  for (int i = 0; i < n; ++i)
    for (int k = 0; k < 3; ++k) {
      lo[k] = std::min(lo[k], xyz[3 * i + k]);
      hi[k] = std::max(hi[k], xyz[3 * i + k]);
    }
  // A point's Morton code: 10 bits per coordinate in the box, interleaved.
  auto spread = [](std::uint32_t v) {
    v &= 0x3ffu;
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    v = (v | (v << 2)) & 0x09249249u;
    return v;
  };
  std::vector<std::uint32_t> code(n);
  for (int i = 0; i < n; ++i) {
    std::uint32_t c = 0;
    for (int k = 0; k < 3; ++k) {
      const double ext = hi[k] - lo[k];
      const double u = ext > 0.0 ? (xyz[3 * i + k] - lo[k]) / ext : 0.0;
      const auto q = static_cast<std::uint32_t>(std::min(1023.0, std::max(0.0, u * 1023.0)));
      c |= spread(q) << k;
    }
    code[i] = c;
  }
  for (int g = 0; g < kRigidMaxCluster; ++g) {
    const int c0 = segmentation::icp_step::rangeBegin(
                  g * segmentation::icp_step::kSumRanges / kRigidMaxCluster, n),
              c1 = segmentation::icp_step::rangeBegin(
                  (g + 1) * segmentation::icp_step::kSumRanges / kRigidMaxCluster, n);
    std::stable_sort(order.begin() + c0, order.begin() + c1,
                     [&](int a, int b) { return code[a] < code[b]; });
  }
  return order;
}

// Where a job's source lies among the sources set (its first point and count), with the job's
// source and surface checked against those set; `what` names the call in the error.
std::pair<int, int> jobSource(const RigidSources& sources, const FrameStore& surfaces, int source,
                              int surface, const char* what) {
  const int n_sources = static_cast<int>(sources.begin.size());
  if (source < 0 || source >= n_sources || surface < 0 || surface >= surfaces.frames)
    throw DeviceError(std::string(what) + ": a job out of range");
  return {sources.begin[source], sources.count[source]};
}

// `trees` packed for a KnnStore: their nodes, points and roots, each tree's size and leaf rows;
// throws Error on a missing tree.
KnnTrees packKnnTrees(const std::vector<const FlatKdTree3*>& trees) {
  const int n_trees = static_cast<int>(trees.size());
  for (int t = 0; t < n_trees; ++t)
    if (!trees[t]) throw DeviceError("GPU k-NN: a tree is missing");
  KnnTrees packed;
  const std::vector<int> point0 = packTrees(trees, packed.nodes, packed.points, packed.root);
  packed.size.resize(n_trees);
  packed.rows.resize(point0.back());
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < n_trees; ++t) {
    packed.size[t] = static_cast<int>(trees[t]->size());
    std::copy(trees[t]->leafRows().begin(), trees[t]->leafRows().end(),
              packed.rows.begin() + point0[t]);
  }
  return packed;
}

// Queries against `trees` trees: three coordinates each, each one's tree in range; throws Error
// (`what` names the call) where not.
void checkQueries(const std::vector<float>& queries, const std::vector<int>& tree_of, int trees,
                  const std::string& what) {
  if (queries.size() != 3 * tree_of.size())
    throw DeviceError(what + "three coordinates per query expected");
  for (int t : tree_of)
    if (t < 0 || t >= trees) throw DeviceError(what + "a query's tree out of range");
}

}  // namespace detail

RigidFits::RigidFits() = default;
RigidFits::~RigidFits() {
  if (locking_.joinable()) locking_.join();
  if (surfaces_) detail::reportCalls(*surfaces_, "rigid fits");
}

std::string RigidFits::name() const { return deviceLabel(); }

void RigidFits::setSurfaces(const segmentation::DeviceFrames& surfaces) {
  // Into the store of the surfaces before: its device buffers where they hold the new surfaces,
  // its batch buffers and what it measured of the device are kept (a new store for each of the
  // rigid motions' computations cost 0.004-0.009 s of cudaFree and cudaMalloc at 800k).
  // Packed into the buffers of the packing before (their pages kept).
  if (locking_.joinable()) locking_.join();  // before the buffers are packed (or grown) again
  if (!packed_) packed_ = std::make_unique<detail::FrameArrays>();
  detail::packDeviceFrames(surfaces, "GPU rigid fits: surface", *packed_);
  if (!surfaces_) surfaces_ = std::make_unique<detail::FrameStore>();
  // From page-locked buffers where the surfaces before locked them (the rigid motions' seeded
  // surfaces at 800k: 5-6 -> 2-4 ms). They are locked beside the caller's work after this upload:
  // locked on the way, the refinement's first upload took 9-13 ms instead of 7-9 ms.
  detail::uploadFrames(*packed_, *surfaces_);
  detail::FrameArrays* packed = packed_.get();
  try {
    locking_ = std::thread([packed] { detail::lockFrameArrays(*packed); });
  } catch (const std::system_error&) {  // no thread: the next upload goes pageable
  }
}

void RigidFits::setSources(const std::vector<const std::vector<double>*>& sources) {
  auto s = std::make_unique<detail::RigidSources>();
  std::vector<double> flat;
  for (const std::vector<double>* x : sources) {
    if (!x || x->size() % 3 != 0)
      throw DeviceError("GPU rigid fits: a source is not x, y, z triples");
    s->begin.push_back(static_cast<int>(flat.size() / 3));
    s->count.push_back(static_cast<int>(x->size() / 3));
    flat.insert(flat.end(), x->begin(), x->end());
  }
  std::vector<int> orders(flat.size() / 3);
#pragma omp parallel for schedule(dynamic)
  for (int k = 0; k < static_cast<int>(sources.size()); ++k) {
    const std::vector<int> o = detail::rigidSearchOrder(*sources[k]);
    std::copy(o.begin(), o.end(), orders.begin() + s->begin[k]);
  }
  if (!flat.empty()) {
    s->points.upload(flat);
    s->orders.upload(orders);
  }
  sources_ = std::move(s);
}

void RigidFits::fit(const std::vector<segmentation::RigidFitJob>& jobs,
                    const segmentation::RigidMotionParams& params, std::vector<double>& poses,
                    std::vector<double>& rms) {
  if (!surfaces_ || !sources_) throw DeviceError("GPU rigid fits: no surfaces or sources were set");
  std::vector<detail::RigidJob> list;
  list.reserve(jobs.size());
  for (const segmentation::RigidFitJob& j : jobs) {
    detail::RigidJob r{};
    std::tie(r.source_begin, r.source_count) =
        detail::jobSource(*sources_, *surfaces_, j.source, j.surface, "GPU rigid fits");
    r.surface = j.surface;
    r.wide = j.wide ? 1 : 0;
    r.spacing = j.spacing;
    r.part_diag = j.part_diag;
    for (int k = 0; k < detail::kPoseDoubles; ++k) r.start[k] = j.start[k];
    list.push_back(r);
  }
  detail::RigidParams p{};
  p.max_iterations = params.max_iterations;
  p.max_correspondence_spacings = params.max_correspondence_spacings;
  p.coarse_distance = params.coarse_distance;
  p.transformation_epsilon = params.transformation_epsilon;
  p.relative_mse_epsilon = params.relative_mse_epsilon;
  p.max_turn = segmentation::rigidStepMaxTurn();
  const detail::CallTimer timer(*surfaces_, 3, list.size());
  int max_points = 0;
  for (const detail::RigidJob& r : list) max_points = std::max(max_points, r.source_count);
  const int cluster =
      detail::rigidClusterSize(*surfaces_, static_cast<int>(list.size()), max_points, cluster_);
  detail::runRigidFits(*surfaces_, sources_->points, sources_->orders, list, p, cluster, poses,
                       rms);
  last_cluster_ = cluster;
  fits_ += static_cast<long long>(jobs.size());
  ++batches_;
}

bool RigidFits::scores(const std::vector<segmentation::RigidScoreJob>& jobs,
                       std::vector<double>& out) {
  if (!surfaces_ || !sources_)
    throw DeviceError("GPU rigid scores: no surfaces or sources were set");
  // More probes than a block holds: the caller scores them on the CPU (the rigid motions ask
  // for 500).
  for (const segmentation::RigidScoreJob& j : jobs)
    if (j.probes > detail::kRigidScoreMaxProbes) return false;
  std::vector<detail::RigidScoreJob> list;
  list.reserve(jobs.size());
  for (const segmentation::RigidScoreJob& j : jobs) {
    detail::RigidScoreJob r{};
    std::tie(r.source_begin, r.source_count) =
        detail::jobSource(*sources_, *surfaces_, j.source, j.surface, "GPU rigid scores");
    r.surface = j.surface;
    r.probes = std::max(0, j.probes);
    for (int k = 0; k < detail::kPoseDoubles; ++k) r.pose[k] = j.pose[k];
    list.push_back(r);
  }
  detail::runRigidScores(*surfaces_, sources_->points, list, out);
  ++score_batches_;
  return true;
}

bool RigidFits::knn(const std::vector<const FlatKdTree3*>& trees, int k,
                    const std::vector<float>& queries, const std::vector<int>& tree_of,
                    std::vector<int>& rows, std::vector<int>& count) {
  if (k < 1 || k > detail::kMaxKnn) return false;
  const int n_trees = static_cast<int>(trees.size());
  // Uploaded for this search alone, beside the trees kept for knnOn() (a caller between two
  // searches of its kept trees, the refinement's verdicts between its lists and its motion
  // check, keeps them there).
  const auto t0 = std::chrono::steady_clock::now();
  const detail::KnnTrees packed = detail::packKnnTrees(trees);
  detail::checkQueries(queries, tree_of, n_trees, "GPU k-NN: ");
  requireGpu();
  detail::KnnStore store;
  detail::uploadKnnTrees(packed, store);
  detail::runKnn(store, k, queries, tree_of, rows, count);
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr, "[gpu k-NN] %d trees for one search, k %d, %zu queries: %.3f s\n", n_trees,
                 k, tree_of.size(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return true;
}

bool RigidFits::motionResiduals(long long token, const segmentation::MotionCheckJobs& jobs,
                                std::vector<float>& out) {
  if (token <= 0 || token != knn_token_ || !knn_) return false;
  const std::string what = "GPU motion check: ";
  const int frames = knn_->trees;
  const std::size_t residuals = jobs.part.size();
  if (frames <= 0 || jobs.spacing.size() != static_cast<std::size_t>(frames))
    throw DeviceError(what + "one spacing per kept tree expected");
  if (jobs.starts.size() != 3 * residuals || jobs.own.size() != residuals)
    throw DeviceError(what + "three coordinates and a frame per residual expected");
  if (jobs.valid.size() % static_cast<std::size_t>(frames) != 0 ||
      jobs.motions.size() != 12 * jobs.valid.size())
    throw DeviceError(what + "a motion and a flag per part and frame expected");
  const int parts = static_cast<int>(jobs.valid.size() / static_cast<std::size_t>(frames));
  if (jobs.normals.size() != 3 * static_cast<std::size_t>(knn_->first.back()))
    throw DeviceError(what + "three normal coordinates per point of the kept trees expected");
  for (int u : jobs.scored)
    if (u < 0 || u >= frames) throw DeviceError(what + "a scored frame out of range");
  for (std::size_t r = 0; r < residuals; ++r)
    if (jobs.part[r] < 0 || jobs.part[r] >= parts || jobs.own[r] < 0 || jobs.own[r] >= frames)
      throw DeviceError(what + "a residual's part or frame out of range");
  out.assign(residuals, 0.0f);
  const auto t0 = std::chrono::steady_clock::now();
  detail::MotionCheckArrays in{};
  in.starts = jobs.starts.data();
  in.part = jobs.part.data();
  in.own = jobs.own.data();
  in.residuals = static_cast<int>(residuals);
  in.motions = jobs.motions.data();
  in.valid = jobs.valid.data();
  in.parts = parts;
  in.frames = frames;
  in.scored = jobs.scored.data();
  in.n_scored = static_cast<int>(jobs.scored.size());
  in.spacing = jobs.spacing.data();
  in.normals = jobs.normals.data();
  in.normal_floats = jobs.normals.size();
  in.cap = jobs.cap;
  detail::runMotionCheck(*knn_, in, out.data());
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr, "[gpu k-NN] motion check, %zu residuals: %.3f s\n", residuals,
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return true;
}

bool RigidFits::leastDistances(long long token, const std::vector<float>& queries,
                               const std::vector<int>& tree_of, const std::vector<float>& bound2,
                               std::vector<float>& out) {
  if (token <= 0 || token != knn_token_ || !knn_) return false;
  const std::string what = "GPU least distances: ";
  detail::checkQueries(queries, tree_of, knn_->trees, what);
  if (bound2.size() != static_cast<std::size_t>(knn_->trees))
    throw DeviceError(what + "one bound per kept tree expected");
  const auto t0 = std::chrono::steady_clock::now();
  detail::runLeastDistances(*knn_, queries, tree_of, bound2, out);
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr, "[gpu k-NN] least distances, %zu queries: %.3f s\n", tree_of.size(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return true;
}

bool RigidFits::fitMixtures(const std::vector<segmentation::MixtureFitJob>& jobs,
                            const math::GMMOptions& options) {
  namespace gmm_em = math::gmm_em;
  for (const segmentation::MixtureFitJob& j : jobs) {
    if (!j.points || !j.gmm || j.points->rows() == 0)
      throw DeviceError("GPU mixtures: a job without points or a start");
    if (j.gmm->size() < 1 || j.gmm->size() > gmm_em::kMaxDeviceComponents) return false;
  }
  if (jobs.empty()) return true;
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<detail::MixtureJob> list(jobs.size());
  long long total = 0;
  for (std::size_t j = 0; j < jobs.size(); ++j) {
    list[j] = {total, static_cast<int>(jobs[j].points->rows())};
    total += list[j].n;
  }
  // Written whole below, on every core: not zeroed first (18 MB at 800k).
  std::unique_ptr<double[]> points(new double[3 * static_cast<std::size_t>(total)]);
  std::vector<detail::MixtureResult> results(jobs.size());
#pragma omp parallel for schedule(dynamic, 16)
  for (long j = 0; j < static_cast<long>(jobs.size()); ++j) {
    const Eigen::MatrixX3d& x = *jobs[j].points;
    double* out = &points[3 * static_cast<std::size_t>(list[j].first)];
    for (Eigen::Index i = 0; i < x.rows(); ++i)
      for (int d = 0; d < 3; ++d) out[3 * i + d] = x(i, d);
    math::toDeviceMixture(*jobs[j].gmm, results[j].m);
  }
  requireGpu();
  const auto t1 = std::chrono::steady_clock::now();
  detail::runMixtureFits(points.get(), static_cast<std::size_t>(total), list,
                         options.max_iterations, options.tolerance, options.regularization,
                         results);
  const double device_sec =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
  for (std::size_t j = 0; j < jobs.size(); ++j) {
    const detail::MixtureResult& r = results[j];
    if (r.bad >= 0)
      throw DeviceError("GMM component " + std::to_string(r.bad) +
                        " has a covariance that is not positive definite; increase the "
                        "regularization");
    math::GaussianMixture& g = *jobs[j].gmm;
    math::fromDeviceMixture(r.m, g);
    g.log_likelihood = r.log_likelihood;
    g.iterations = r.iterations;
    g.converged = r.converged != 0;
  }
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(
        stderr, "[gpu mixtures] %zu fits, %lld points: %.3f s (the device's part %.3f s)\n",
        jobs.size(), total,
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), device_sec);
  return true;
}

void RigidFits::dropKnnTrees(long long token) {
  if (token <= 0 || token != knn_token_) return;
  knn_.reset();
  knn_token_ = 0;
}

long long RigidFits::keepKnnTrees(const std::vector<const FlatKdTree3*>& trees) {
  const auto t0 = std::chrono::steady_clock::now();
  const int n_trees = static_cast<int>(trees.size());
  knn_token_ = 0;  // none kept until the upload succeeds
  const detail::KnnTrees packed = detail::packKnnTrees(trees);
  requireGpu();
  if (!knn_) knn_ = std::make_unique<detail::KnnStore>();
  detail::uploadKnnTrees(packed, *knn_);
  knn_token_ = ++knn_keeps_;
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr, "[gpu k-NN] %d trees packed and uploaded: %.3f s\n", n_trees,
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return knn_token_;
}

bool RigidFits::knnOn(long long token, int k, const std::vector<float>& queries,
                      const std::vector<int>& tree_of, std::vector<int>& rows,
                      std::vector<int>& count) {
  if (token <= 0 || token != knn_token_ || !knn_ || k < 1 || k > detail::kMaxKnn) return false;
  detail::checkQueries(queries, tree_of, knn_->trees, "GPU k-NN: ");
  const auto t0 = std::chrono::steady_clock::now();
  detail::runKnn(*knn_, k, queries, tree_of, rows, count);
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr, "[gpu k-NN] k %d, %zu queries: %.3f s\n", k, tree_of.size(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  return true;
}

}  // namespace gpu
}  // namespace pcl_animseg
