// Refinement, hierarchy and per-part rigid motion on an 800k-point sequence (10 frames x 80k
// points, a chain of 6 mitred tubes). The goal: refinement + hierarchy <= 20% of the
// pipeline's total time on such a sequence.
#include <benchmark/benchmark.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/segmentation/hierarchy.h>
#include <pcl_animseg/segmentation/rigid_motion.h>

#include "../test/segmentation/synthetic_parts.h"

namespace seg = pcl_animseg::segmentation;

namespace {

const animseg_test::TubeChain& data() {
  static const animseg_test::TubeChain chain = animseg_test::makeTubeChain(
      {1.0, 0.8, 0.9, 0.7, 0.8, 0.6}, {0.9, -0.8, 1.0, -1.1, 0.7}, 10, 80000, 2.5, 7);
  return chain;
}

seg::SegmentationResult initial() {
  seg::SegmentationResult r;
  r.labels = data().shifted;
  r.num_clusters = 6;
  r.mode_density = {1.0, 0.9, 0.95, 0.85, 0.92, 0.88};
  for (int c = 0; c + 1 < 6; ++c) r.saddles.push_back({c, c + 1, 0.3 + 0.05 * c});
  return r;
}

void BM_Refine(benchmark::State& state) {
  const auto& chain = data();
  seg::RefinementParams params;
  params.pool_frames = state.range(0) != 0;
  const seg::SegmentationResult in = initial();
  for (auto _ : state) {
    seg::GMMBoundaryRefinement refine;
    refine.setInputSequence(&chain.sequence);
    refine.setParams(params);
    seg::SegmentationResult out;
    refine.refine(in, out);
    state.counters["iterations"] = refine.getStats().iterations;
    state.counters["band_W"] = static_cast<double>(refine.getStats().band_points);
  }
  state.counters["points"] = static_cast<double>(chain.sequence.totalPoints());
}
BENCHMARK(BM_Refine)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond)->Iterations(1);

void BM_Hierarchy(benchmark::State& state) {
  // Over-segmented input (every tube cut in 4 along the chain by point order): 24 clusters.
  seg::SegmentationResult in = initial();
  in.num_clusters = 24;
  in.mode_density.assign(24, 1.0);
  in.saddles.clear();
  for (int c = 0; c + 1 < 24; ++c) in.saddles.push_back({c, c + 1, (c + 1) % 4 ? 0.9 : 0.3});
  for (auto& f : in.labels)
    for (std::size_t j = 0; j < f.size(); ++j) f[j] = f[j] * 4 + static_cast<int>(j % 4);
  for (auto _ : state) {
    seg::PersistenceHierarchy h;
    seg::HierarchyResult out;
    h.compute(in, out);
    state.counters["levels"] = out.levels();
  }
}
BENCHMARK(BM_Hierarchy)->Unit(benchmark::kMillisecond)->Iterations(1);

void BM_RigidMotion(benchmark::State& state) {
  const auto& chain = data();
  for (auto _ : state) {
    seg::RigidMotionEstimation est;
    est.setInputSequence(&chain.sequence);
    benchmark::DoNotOptimize(est.compute(chain.truth));
  }
}
BENCHMARK(BM_RigidMotion)->Unit(benchmark::kMillisecond)->Iterations(1);

}  // namespace

BENCHMARK_MAIN();
