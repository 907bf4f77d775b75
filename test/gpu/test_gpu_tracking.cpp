// The motion method's sample tracking on the GPU (gpu::SampleTracking) against the CPU: the same
// fits summed in another order, so poses agree to rounding and the labels agree. Skips when no
// usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/gpu/sample_tracking.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/synth/articulated.h>

#include <algorithm>
#include <cstdio>
#include <memory>
#include <vector>

namespace gpu = pcl_animseg::gpu;
namespace seg = pcl_animseg::segmentation;
namespace synth = pcl_animseg::synth;

namespace {

pcl_animseg::PointCloudSequence::Ptr generated(synth::BodyPlan plan, int frames, int points,
                                               unsigned seed) {
  synth::SynthParams sp;
  sp.plan = plan;
  sp.frames = frames;
  sp.points = points;
  sp.seed = seed;
  return std::make_shared<pcl_animseg::PointCloudSequence>(synth::toSequence(synth::generate(sp)));
}

std::vector<int> flatLabels(const seg::SegmentationResult& r) {
  std::vector<int> flat;
  for (const auto& f : r.labels) flat.insert(flat.end(), f.begin(), f.end());
  return flat;
}

}  // namespace

TEST(GpuTracking, PosesAgreeWithTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  for (auto plan : {synth::BodyPlan::Humanoid, synth::BodyPlan::Hand}) {
    const auto seq = generated(plan, 16, 4000, 7);
    seg::MotionTrackingParams params;
    const seg::SampleTracks cpu = seg::trackSamples(*seq, params);
    gpu::SampleTracking device;
    params.device = &device;
    const seg::SampleTracks dev = seg::trackSamples(*seq, params);
    ASSERT_EQ(dev.positions.size(), cpu.positions.size());
    // How far each sample lands from where the CPU put it, in point spacings.
    std::vector<double> off;
    for (std::size_t t = 0; t < cpu.positions.size(); ++t)
      for (Eigen::Index s = 0; s < cpu.positions[t].cols(); ++s)
        off.push_back((dev.positions[t].col(s) - cpu.positions[t].col(s)).norm() / cpu.spacing);
    std::sort(off.begin(), off.end());
    const double close =
        static_cast<double>(std::lower_bound(off.begin(), off.end(), 0.01) - off.begin()) /
        static_cast<double>(off.size());
    std::printf(
        "%s: %zu sample poses, %d waves, %.4f s on the device; offset from the CPU "
        "(spacings): median %.2e, 99th percentile %.2e, max %.2e; %.4f within 0.01\n",
        synth::toString(plan).c_str(), off.size(), device.lastWaves(), device.lastDeviceSeconds(),
        off[off.size() / 2], off[off.size() * 99 / 100], off.back(), close);
    EXPECT_LT(off[off.size() / 2], 1e-6);
    EXPECT_GE(close, 0.98);
    for (std::size_t t = 0; t < cpu.residual.size(); ++t)
      EXPECT_NEAR(dev.residual[t], cpu.residual[t], 0.05) << "frame " << t;
  }
}

TEST(GpuTracking, MotionMethodLabelsAgreeWithTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  for (auto plan : {synth::BodyPlan::Humanoid, synth::BodyPlan::Quadruped, synth::BodyPlan::Hand,
                    synth::BodyPlan::Spider}) {
    const auto seq = generated(plan, 20, 4000, 8);
    seg::MeanShiftParams params;
    params.method = seg::MeanShiftMethod::Motion;
    params.record_densities = false;
    seg::MeanShiftSegmentation cpu;
    cpu.setInputSequence(seq);
    cpu.setParams(params);
    seg::SegmentationResult expected;
    cpu.segment(expected);
    seg::MeanShiftSegmentation dev;
    dev.setInputSequence(seq);
    dev.setParams(params);
    dev.setDeviceBackend(gpu::makeMeanShiftBackend());
    seg::SegmentationResult got;
    dev.segment(got);
    EXPECT_NE(dev.deviceUsed().find("gpu"), std::string::npos) << dev.deviceUsed();
    const double ari =
        pcl_animseg::evaluation::adjustedRandIndex(flatLabels(expected), flatLabels(got));
    std::printf("%s: CPU %d parts, GPU tracking %d parts, ARI %.4f\n",
                synth::toString(plan).c_str(), expected.num_clusters, got.num_clusters, ari);
    EXPECT_GE(ari, 0.99);
  }
}
