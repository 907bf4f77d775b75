// Section 3.1 on a sequence of 48 frames x ~17k points (800k in all): scale space, keypoints and
// signatures together (per-stage times as counters), and pcl::MovingLeastSquares alone on the
// same frames (one level) for comparison.
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/progress.h>
#ifdef PCL_ANIMSEG_HAVE_CUDA
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/features.h>
#endif

#include <pcl/search/kdtree.h>
#include <pcl/surface/mls.h>

#include <benchmark/benchmark.h>

#include "../test/features/bumpy_surface.h"

using namespace pcl_animseg;

namespace {

const PointCloudSequence& sequence() {
  static PointCloudSequence seq = [] {
    PointCloudSequence s;
    for (int t = 0; t < 48; ++t) {
      // Different point counts per frame, as in the point-cloud datasets.
      const std::size_t n = 16000 + static_cast<std::size_t>((t * 397) % 2000);
      s.addFrame(test::bumpySphere(n, 100 + t), "f" + std::to_string(t));
    }
    return s;
  }();
  return seq;
}

/** Per-stage times, their total and the keypoints as the benchmark's counters. */
void countStages(benchmark::State& state, const Progress& progress, const SequenceFeatures& f) {
  benchmark::DoNotOptimize(f.signatures.data());
  double total = 0.0;
  for (const auto& s : progress.timings()) {
    state.counters[s.first + "_s"] = s.second;
    total += s.second;
  }
  std::size_t kp = 0;
  for (const auto& k : f.keypoints) kp += k.size();
  state.counters["total_s"] = total;
  state.counters["keypoints"] = static_cast<double>(kp);
}

void BM_Features(benchmark::State& state) {
  const PointCloudSequence& seq = sequence();
  MultiscaleParams p;
  for (auto _ : state) {
    Progress progress(true);
    SequenceFeatures f = computeSequenceFeatures(seq, p, &progress);
    countStages(state, progress, f);
    state.counters["points"] = static_cast<double>(seq.totalPoints());
  }
}
BENCHMARK(BM_Features)->Iterations(1)->Unit(benchmark::kSecond)->UseRealTime();

#ifdef PCL_ANIMSEG_HAVE_CUDA
/** The same on the GPU (gpu::FeatureDevice: scale spaces and signatures there, the keypoints and
 * their rows on the cores); skipped without a GPU. Run after BM_Features, so the GPU has started.
 */
void BM_FeaturesGpu(benchmark::State& state) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) {
    state.SkipWithError(("no usable GPU: " + why).c_str());
    return;
  }
  const PointCloudSequence& seq = sequence();
  MultiscaleParams p;
  for (auto _ : state) {
    gpu::FeatureDevice device;
    Progress progress(true);
    SequenceFeatures f = computeSequenceFeatures(seq, p, &progress, &device);
    countStages(state, progress, f);
    state.counters["peak_device_MiB"] = static_cast<double>(gpu::peakDeviceBytes()) / 1048576.0;
  }
}
BENCHMARK(BM_FeaturesGpu)->Iterations(3)->Unit(benchmark::kSecond)->UseRealTime();
#endif

/** pcl::MovingLeastSquares (order 2, normals, radius 2h as our level 0) on `frames` frames. */
void BM_PCLMovingLeastSquares(benchmark::State& state) {
  const PointCloudSequence& seq = sequence();
  const int frames = static_cast<int>(state.range(0));
  const double unit = sequenceSpacing(seq);
  for (auto _ : state) {
    for (int t = 0; t < frames; ++t) {
      pcl::MovingLeastSquares<pcl::PointNormal, pcl::PointNormal> mls;
      mls.setInputCloud(seq.frame(t));
      mls.setSearchMethod(pcl::search::KdTree<pcl::PointNormal>::Ptr(
          new pcl::search::KdTree<pcl::PointNormal>));
      mls.setPolynomialOrder(2);
      mls.setComputeNormals(true);
      mls.setSearchRadius(4.0 * unit);
      mls.setSqrGaussParam(4.0 * unit * unit);
      mls.setNumberOfThreads(2);
      pcl::PointCloud<pcl::PointNormal> out;
      mls.process(out);
      benchmark::DoNotOptimize(out.points.data());
    }
  }
  state.counters["frames"] = frames;
  state.counters["points"] = static_cast<double>(seq.totalPoints()) * frames / seq.size();
}
BENCHMARK(BM_PCLMovingLeastSquares)->Arg(48)->Iterations(1)->Unit(benchmark::kSecond)->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
