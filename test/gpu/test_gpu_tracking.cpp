// The motion method's sample tracking on the GPU (gpu::MotionTracking) against the CPU: the same
// arithmetic (segmentation/icp_step.h) with the same sums in the same order, so the same poses
// bit for bit, and so the same labels. Skips when no usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/gpu/motion_tracking.h>
#include <pcl_animseg/gpu/rigid_fits.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/segmentation/rigid_motion.h>
#include <pcl_animseg/synth/articulated.h>

#include <algorithm>
#include <cstdio>
#include <memory>
#include <vector>

#include "segmentation/synthetic_parts.h"

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
    const double ari = pcl_animseg::evaluation::adjustedRandIndex(
        animseg_test::pooled(expected.labels), animseg_test::pooled(got.labels));
    std::printf("%s: CPU %d parts, GPU tracking %d parts, ARI %.4f\n",
                synth::toString(plan).c_str(), expected.num_clusters, got.num_clusters, ari);
    EXPECT_EQ(got.num_clusters, expected.num_clusters);
    EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels));
  }
}

// The rigid motions' fits on the GPU (gpu::RigidFits) against the CPU: every level's motions the
// same bits, level 0 from starts of its own (as the pipeline passes the refinement's), a coarser
// level nested in it (its merged parts from their children), and plain chains (compute()).
TEST(GpuTracking, RigidMotionsAreTheCpusBitForBit) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  for (auto plan : {synth::BodyPlan::Humanoid, synth::BodyPlan::Hand}) {
    synth::SynthParams sp;
    sp.plan = plan;
    sp.frames = 16;
    sp.points = 4000;
    sp.seed = 7;
    const auto frames = synth::generate(sp);
    const pcl_animseg::PointCloudSequence seq = synth::toSequence(frames);
    std::vector<std::vector<std::vector<int>>> levels(3);
    for (const auto& f : frames) {
      levels[0].push_back(f.labels);
      levels[1].push_back(f.labels);
      levels[2].push_back(f.labels);
      for (int& l : levels[1].back()) l /= 2;  // pairs of parts merged: nested in level 0
      for (int& l : levels[2].back()) l /= 6;
    }
    seg::RigidMotionEstimation coarse;
    coarse.setInputSequence(&seq);
    seg::RigidMotionParams cp;
    cp.max_points = 300;
    coarse.setParams(cp);
    seg::RigidMotionEstimation est;
    est.setInputSequence(&seq);
    est.setInitialMotions(coarse.compute(levels[0]));
    const auto cpu = est.computeLevels(levels);
    const auto cpu_chained = est.compute(levels[1]);
    gpu::RigidFits device;
    est.setDevice(&device);
    const auto dev = est.computeLevels(levels);
    const auto dev_chained = est.compute(levels[1]);
    int transforms = 0, differ = 0;
    auto compare = [&](const seg::PartMotion& a, const seg::PartMotion& b) {
      ASSERT_EQ(a.frames.size(), b.frames.size());
      for (std::size_t t = 0; t < a.frames.size(); ++t) {
        ++transforms;
        const auto &x = a.frames[t], &y = b.frames[t];
        differ += !(x.valid == y.valid && x.rotation == y.rotation &&
                    x.translation == y.translation && (x.rms == y.rms || !x.valid));
      }
    };
    ASSERT_EQ(dev.size(), cpu.size());
    for (std::size_t l = 0; l < cpu.size(); ++l) {
      ASSERT_EQ(dev[l].parts.size(), cpu[l].parts.size());
      for (std::size_t p = 0; p < cpu[l].parts.size(); ++p)
        compare(dev[l].parts[p], cpu[l].parts[p]);
    }
    ASSERT_EQ(dev_chained.size(), cpu_chained.size());
    for (std::size_t p = 0; p < cpu_chained.size(); ++p) compare(dev_chained[p], cpu_chained[p]);
    std::printf("%s: %d transforms, %lld GPU fits in %lld batches; %d differ from the CPU's\n",
                synth::toString(plan).c_str(), transforms, device.fits(), device.batches(), differ);
    EXPECT_EQ(differ, 0) << synth::toString(plan);
    EXPECT_GT(device.fits(), 0);
  }
}
