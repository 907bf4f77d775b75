// The motion method's sample tracking on the GPU (gpu::MotionTracking) against the CPU: the same
// arithmetic (segmentation/icp_step.h) with the same sums in the same order, so the same poses
// bit for bit, and so the same labels. Skips when no usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/gpu/motion_tracking.h>
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

TEST(GpuTracking, PosesAreTheCpusBitForBit) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  for (auto plan : {synth::BodyPlan::Humanoid, synth::BodyPlan::Hand}) {
    const auto seq = generated(plan, 16, 4000, 7);
    seg::MotionTrackingParams params;
    const seg::SampleTracks cpu = seg::trackSamples(*seq, params);
    gpu::MotionTracking device;
    params.device = &device;
    const seg::SampleTracks dev = seg::trackSamples(*seq, params);
    ASSERT_EQ(dev.positions.size(), cpu.positions.size());
    // How far each sample lands from where the CPU put it, in point spacings, and how many poses
    // differ in any bit.
    double worst = 0.0;
    int differ = 0, poses = 0;
    for (std::size_t t = 0; t < cpu.poses.size(); ++t)
      for (std::size_t s = 0; s < cpu.poses[t].size(); ++s) {
        ++poses;
        differ += dev.poses[t][s].matrix() != cpu.poses[t][s].matrix();
        worst = std::max(worst,
                         (dev.positions[t].col(s) - cpu.positions[t].col(s)).norm() / cpu.spacing);
      }
    std::printf(
        "%s: %d sample poses, %d waves, %.4f s on the device; %d differ from the CPU's "
        "(largest offset %.2e spacings)\n",
        synth::toString(plan).c_str(), poses, device.lastWaves(), device.lastDeviceSeconds(),
        differ, worst);
    EXPECT_EQ(differ, 0);
    EXPECT_EQ(dev.residual, cpu.residual);
  }
}

TEST(GpuTracking, MotionMethodLabelsAreTheCpus) {
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
    EXPECT_EQ(got.num_clusters, expected.num_clusters);
    EXPECT_EQ(flatLabels(got), flatLabels(expected));
  }
}
