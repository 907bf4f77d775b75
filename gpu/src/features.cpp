// The host side of gpu::FeatureDevice: packs a block of frames for the kernels
// (features_kernels.cu), searches the keypoint detector's rows on the CPU meanwhile, and unpacks
// the levels and signatures.
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/features.h>

#include <chrono>
#include <climits>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>
#include <thread>

#include "features_device.h"

namespace pcl_animseg {
namespace gpu {
namespace {

/** Where the block's time goes, on stderr under ANIMSEG_MS_TIMING (profiling aid). */
class Laps {
 public:
  Laps() : on_(std::getenv("ANIMSEG_MS_TIMING") != nullptr), last_(Clock::now()) {}
  void lap(const char* what) {
    const auto now = Clock::now();
    if (on_)
      std::fprintf(stderr, "[gpu features] %-28s %8.3f s\n", what,
                   std::chrono::duration<double>(now - last_).count());
    last_ = now;
  }
  static double since(std::chrono::steady_clock::time_point t) {
    return std::chrono::duration<double>(Clock::now() - t).count();
  }
  bool on() const { return on_; }

 private:
  using Clock = std::chrono::steady_clock;
  bool on_;
  Clock::time_point last_;
};

}  // namespace

struct FeatureDevice::Impl {
  detail::FeatureBlock block;
  std::size_t first = 0;
  std::vector<long long> begin;  // each frame's first point in the block, and the block's size
  std::vector<float> radius;     // each frame's row radius
  int D = 0;
  std::vector<float> signatures;  // block points x D, row-major
};

FeatureDevice::FeatureDevice() : impl_(new Impl) {}
FeatureDevice::~FeatureDevice() = default;

void FeatureDevice::scaleSpaces(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                                const std::vector<ScaleSpacePlan>& plans, const MultiscaleParams& p,
                                bool rows, std::vector<ScaleSpace>& spaces) {
  Impl& d = *impl_;
  const std::size_t F = last - first;
  if (F == 0) return;
  Laps laps;
  if (plans.size() != F || last > seq.size() || spaces.size() < last)
    throw DeviceError("GPU features: the plans do not match the frames");
  d.first = first;
  d.begin.assign(F + 1, 0);
  for (std::size_t f = 0; f < F; ++f)
    d.begin[f + 1] = d.begin[f] + static_cast<long long>(seq.frame(first + f)->size());
  if (d.begin[F] > INT_MAX / 3)
    throw DeviceError("GPU features: a block of " + std::to_string(d.begin[F]) +
                      " points is too large for the GPU kernels; lower the block size");
  const int n = static_cast<int>(d.begin[F]);

  detail::FeatureBlockArgs args;
  args.n = n;
  std::vector<float> xyz(3 * static_cast<std::size_t>(n)), normals(xyz.size()), ref(xyz.size());
  args.frames.resize(F);
  std::vector<long long> cells(F);
  d.radius.assign(F, 0.0f);
#pragma omp parallel for schedule(dynamic, 1)
  for (long fl = 0; fl < static_cast<long>(F); ++fl) {
    const std::size_t f = static_cast<std::size_t>(fl);
    const auto& cloud = *seq.frame(first + f);
    const ScaleSpacePlan& pl = plans[f];
    const std::size_t b = static_cast<std::size_t>(d.begin[f]);
    for (std::size_t j = 0; j < cloud.size(); ++j) {
      for (int k = 0; k < 3; ++k) {
        xyz[3 * (b + j) + k] = cloud[j].data[k];
        normals[3 * (b + j) + k] = cloud[j].normal[k];
        ref[3 * (b + j) + k] = pl.ref[j](k);
      }
    }
    const NeighbourGrid grid = neighbourGrid(cloud, pl.radius);
    detail::FeatureFrame& ff = args.frames[f];
    ff.begin = static_cast<int>(b);
    ff.ox = grid.origin.x();
    ff.oy = grid.origin.y();
    ff.oz = grid.origin.z();
    ff.inv_cell = grid.inv_cell;
    ff.ny = grid.ny;
    ff.nz = grid.nz;
    cells[f] = grid.cells;
    ff.radius2 = pl.radius * pl.radius;
    ff.step_radius = pl.step_radius;
    ff.inv_h2 = pl.inv_h2;
    // SignatureEstimation at h = signature_h spacings: the disc's radius rho = 2h.
    ff.rho_d = 2.0 * (p.signature_h * pl.spacing);
    ff.rho = static_cast<float>(ff.rho_d);
    d.radius[f] = pl.radius;
  }
  long long key_base = 0;
  for (std::size_t f = 0; f < F; ++f) {
    args.frames[f].key_base = key_base;
    key_base += cells[f];
  }
  args.xyz = xyz.data();
  args.normals = normals.data();
  args.ref = ref.data();
  args.steps_per_level = plans[0].counts;
  args.radial = p.layout.radial;
  args.angular = p.layout.angular;
  args.radial_freqs = p.layout.radial_freqs;
  args.angular_freqs = p.layout.angular_freqs;
  args.disc_tables = DiscSignature(p.layout).tables();
  d.D = p.layout.dimension();
  laps.lap("pack");

  // The device's work runs on a thread of its own while the cores search the rows that the
  // keypoint detector reads (the device keeps its rows: copying them back would cost more).
  std::exception_ptr device_error, cpu_error;
  double device_s = 0.0, rows_s = 0.0;
  std::thread device_thread([&] {
    try {
      const auto t0 = std::chrono::steady_clock::now();
      d.block.launch(args);
      device_s = Laps::since(t0);
    } catch (...) {
      device_error = std::current_exception();
    }
  });
  const auto rows_t0 = std::chrono::steady_clock::now();
  if (rows) {
#pragma omp parallel for schedule(dynamic, 1)
    for (long fl = 0; fl < static_cast<long>(F); ++fl) {
      try {
        const std::size_t f = static_cast<std::size_t>(fl);
        spaces[first + f].neighbourhoods = std::make_shared<Neighbourhoods>(
            radiusNeighbourhoods(*seq.frame(first + f), plans[f].radius));
      } catch (...) {
#pragma omp critical(gpu_features_error)
        if (!cpu_error) cpu_error = std::current_exception();
      }
    }
  }
  rows_s = Laps::since(rows_t0);
  device_thread.join();
  if (laps.on())
    std::fprintf(stderr, "[gpu features] device %.3f s (%d points), rows on the cores %.3f s\n",
                 device_s, n, rows_s);
  laps.lap("device and rows");
  if (device_error) std::rethrow_exception(device_error);
  if (cpu_error) std::rethrow_exception(cpu_error);

  // The levels, one at a time.
  const int L = static_cast<int>(plans[0].counts.size());
  std::vector<float> level(6 * static_cast<std::size_t>(n)), curvature(n);
  d.block.fetchCurvature(curvature.data());
  for (std::size_t f = 0; f < F; ++f) {
    ScaleSpace& ss = spaces[first + f];
    ss.spacing = plans[f].spacing;
    ss.scales = plans[f].scales;
    ss.input = seq.frame(first + f);
    ss.levels.assign(L, nullptr);
  }
  for (int l = 0; l < L; ++l) {
    d.block.fetchLevel(l, level.data());
#pragma omp parallel for schedule(dynamic, 1)
    for (long fl = 0; fl < static_cast<long>(F); ++fl) {
      const std::size_t f = static_cast<std::size_t>(fl);
      const std::size_t b = static_cast<std::size_t>(d.begin[f]);
      PointCloudSequence::Cloud::Ptr cloud(new PointCloudSequence::Cloud(*seq.frame(first + f)));
      for (std::size_t j = 0; j < cloud->size(); ++j) {
        pcl::PointNormal& q = (*cloud)[j];
        const float* v = level.data() + 6 * (b + j);
        q.x = v[0];
        q.y = v[1];
        q.z = v[2];
        q.normal_x = v[3];
        q.normal_y = v[4];
        q.normal_z = v[5];
        q.curvature = l == 0 ? curvature[b + j] : 0.0f;
      }
      spaces[first + f].levels[l] = cloud;
    }
  }
  laps.lap("levels");
  d.signatures.resize(static_cast<std::size_t>(n) * d.D);
  d.block.fetchSignatures(d.signatures.data());
  laps.lap("signatures");
}

void FeatureDevice::signature(std::size_t t, Eigen::MatrixXf& out) const {
  const Impl& d = *impl_;
  if (t < d.first || t + 1 >= d.first + d.begin.size())
    throw DeviceError("GPU features: frame " + std::to_string(t) + " is not in the last block");
  const std::size_t f = t - d.first;
  const long long rows = d.begin[f + 1] - d.begin[f];
  out = Eigen::Map<const Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
      d.signatures.data() + static_cast<std::size_t>(d.begin[f]) * d.D, rows, d.D);
}

Neighbourhoods FeatureDevice::rows(std::size_t t) const {
  const Impl& d = *impl_;
  if (t < d.first || t + 1 >= d.first + d.begin.size())
    throw DeviceError("GPU features: frame " + std::to_string(t) + " is not in the last block");
  const std::size_t f = t - d.first;
  std::vector<long long> offsets;
  std::vector<int> indices;
  std::vector<float> sqr;
  d.block.fetchRows(offsets, indices, sqr);
  Neighbourhoods nb;
  nb.radius = d.radius[f];
  const long long b = d.begin[f], e = d.begin[f + 1];
  const long long o0 = offsets[b];
  for (long long j = b; j <= e; ++j)
    nb.offsets.push_back(static_cast<std::size_t>(offsets[j] - o0));
  for (long long a = o0; a < offsets[e]; ++a) {
    nb.indices.push_back(indices[a] - static_cast<int>(b));
    nb.sqr_distances.push_back(sqr[a]);
  }
  return nb;
}

void FeatureDevice::Refiner::refine(KeypointRefineJobs& jobs) const {
  const std::size_t nk = jobs.scales.size();
  if (jobs.disc_begin.size() != nk + 1 || jobs.frames.size() != 12 * nk ||
      jobs.maximum.size() != nk || jobs.samples.size() != 4 * std::size_t{jobs.disc_begin.back()})
    throw DeviceError("GPU keypoints: inconsistent refinement jobs");
  if (nk > static_cast<std::size_t>(INT_MAX))
    throw DeviceError("GPU keypoints: too many keypoints");
  jobs.y.assign(2 * nk, 0.0f);
  jobs.ok.assign(nk, 1);
  detail::refineKeypoints(static_cast<int>(nk), jobs.h0, jobs.disc_begin.data(),
                          jobs.samples.data(), jobs.frames.data(), jobs.scales.data(),
                          jobs.maximum.data(), jobs.y.data(), jobs.ok.data());
}

}  // namespace gpu
}  // namespace pcl_animseg
