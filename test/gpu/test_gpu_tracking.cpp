// The motion method's sample tracking on the GPU (gpu::MotionTracking) against the CPU: the same
// arithmetic (segmentation/icp_step.h) with the same sums in the same order, so the same poses
// bit for bit, and so the same labels. Skips when no usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/gpu/motion_tracking.h>
#include <pcl_animseg/gpu/rigid_fits.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/segmentation/motion_device.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/segmentation/rigid_motion.h>
#include <pcl_animseg/sequence.h>
#include <pcl_animseg/synth/articulated.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <thread>
#include <vector>

#include "pipeline/sequence_params.h"
#include "segmentation/cpu_moved_nearest.h"
#include "segmentation/cpu_residuals.h"
#include "segmentation/synthetic_parts.h"

namespace gpu = pcl_animseg::gpu;
namespace seg = pcl_animseg::segmentation;
namespace synth = pcl_animseg::synth;

namespace {

// A generated sequence of the tests below.
struct SequenceCase {
  synth::BodyPlan plan;
  int frames, points;
};

pcl_animseg::PointCloudSequence::Ptr generated(synth::BodyPlan plan, int frames, int points,
                                               unsigned seed) {
  return std::make_shared<pcl_animseg::PointCloudSequence>(
      synth::toSequence(synth::generate(animseg_test::sequenceParams(plan, frames, points, seed))));
}

// A tracking problem of S samples in 4 frames, a chain from frame 0, whose fits are of zero
// points (the order of the tasks is what the tests below look at).
seg::SampleTrackingProblem fourFrameProblem(int S) {
  seg::SampleTrackingProblem p;
  p.samples = S;
  for (int s = 0; s < S; ++s) {
    p.source_p.push_back(Eigen::Matrix3Xd::Zero(3, 8));
    p.source_n.push_back(Eigen::Matrix3Xd::Zero(3, 8));
    p.probe_p.push_back(Eigen::Matrix3Xd::Zero(3, 2));
    p.probe_n.push_back(Eigen::Matrix3Xd::Zero(3, 2));
  }
  p.graph.assign(S, {});
  p.before = {-1, 0, 1, 2};
  p.two_before = {-1, -1, 0, 1};
  p.global.assign(4, Eigen::Isometry3d::Identity());
  return p;
}

// A device whose frames are those of a 4-frame humanoid (set by a tracking run), and the run's
// sample count, for the tests of the order the device takes its tasks in.
class GpuTrackingOrder : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string why;
    if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
    const auto seq = generated(synth::BodyPlan::Humanoid, 4, 3000, 7);
    seg::MotionTrackingParams params;
    params.device = &device;
    S = static_cast<int>(seg::trackSamples(*seq, params).sample_points.size());
  }
  gpu::MotionTracking device;
  int S = 0;
};

}  // namespace

TEST(GpuTracking, PosesAreTheCpusBitForBit) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  // The third: 100 frames, tracked through key frames 3 apart (chained_fit.h,
  // chainFrames), each frame between from the one before.
  const SequenceCase cases[] = {{synth::BodyPlan::Humanoid, 16, 4000},
                                {synth::BodyPlan::Hand, 16, 4000},
                                {synth::BodyPlan::Humanoid, 100, 600}};
  for (const auto& c : cases) {
    const auto plan = c.plan;
    const auto seq = generated(plan, c.frames, c.points, 7);
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
        "%s, %d frames: %d sample poses, %d kernels, %.4f s on the device; %d differ from the "
        "CPU's (largest offset %.2e spacings)\n",
        synth::toString(plan).c_str(), c.frames, poses, device.lastWaves(),
        device.lastDeviceSeconds(), differ, worst);
    EXPECT_EQ(differ, 0);
    EXPECT_EQ(dev.residual, cpu.residual);
  }
}

// The device takes the tracking's tasks in the waves' order, each after the poses it starts
// from: a problem whose waves put a task before one of those is refused with an error, not left
// waiting.
TEST_F(GpuTrackingOrder, WavesOutOfOrderAreAnError) {
  seg::SampleTrackingProblem p = fourFrameProblem(S);
  p.level.assign(4, {});
  // Frame 2's tasks before frame 1's, which they start from.
  std::vector<int> w1, w2, w3;
  for (int s = 0; s < S; ++s)
    w1.push_back(2 * S + s), w2.push_back(1 * S + s), w3.push_back(3 * S + s);
  p.waves = {w1, w2, w3};
  std::vector<std::vector<Eigen::Isometry3d>> poses;
  std::vector<std::vector<double>> residual;
  EXPECT_THROW(device.trackSamples(p, poses, residual), pcl_animseg::Error);
  // In order, the same problem runs.
  p.waves = {w2, w1, w3};
  EXPECT_NO_THROW(device.trackSamples(p, poses, residual));
}

// The frames given as they come (beginSamples .. endSamples): a frame before one it starts from,
// or twice, is refused with an error, not left waiting; in order they run.
TEST_F(GpuTrackingOrder, StreamedFramesOutOfOrderAreAnError) {
  seg::SampleTrackingProblem p = fourFrameProblem(S);
  const std::vector<int> flat(S, 0);
  const Eigen::Isometry3d I = Eigen::Isometry3d::Identity();
  EXPECT_THROW(device.trackFrames({1}, {I}, {flat}), pcl_animseg::Error);  // not begun
  device.beginSamples(p);
  EXPECT_THROW(device.trackFrames({2}, {I}, {flat}), pcl_animseg::Error);
  EXPECT_NO_THROW(device.trackFrames({1, 2}, {I, I}, {flat, flat}));
  EXPECT_THROW(device.trackFrames({1}, {I}, {flat}), pcl_animseg::Error);
  EXPECT_NO_THROW(device.trackFrames({3}, {I}, {flat}));
  std::vector<std::vector<Eigen::Isometry3d>> poses;
  std::vector<std::vector<double>> residual;
  EXPECT_NO_THROW(device.endSamples(poses, residual));
  EXPECT_EQ(poses.size(), 4u);
  EXPECT_EQ(device.lastWaves(), 2);  // a kernel per call that gave frames
}

TEST(GpuTracking, MotionMethodLabelsAreTheCpus) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  // The last: 70 frames, every chain through key frames 2 apart (chainFrames).
  const SequenceCase cases[] = {{synth::BodyPlan::Humanoid, 20, 4000},
                                {synth::BodyPlan::Quadruped, 20, 4000},
                                {synth::BodyPlan::Hand, 20, 4000},
                                {synth::BodyPlan::Spider, 20, 4000},
                                {synth::BodyPlan::Humanoid, 70, 1000}};
  for (const auto& c : cases) {
    const auto plan = c.plan;
    const auto seq = generated(plan, c.frames, c.points, 8);
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
    std::printf("%s, %d frames: CPU %d parts, GPU tracking %d parts, ARI %.4f\n",
                synth::toString(plan).c_str(), c.frames, expected.num_clusters, got.num_clusters,
                ari);
    EXPECT_EQ(got.num_clusters, expected.num_clusters);
    EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels));
  }
}

// Every frame's labels by the moved reference (MotionDevice::nearestMoved) on the GPU: the
// contract's picks bit for bit (cpu_moved_nearest.h, whose picks are the cores' search's where it
// decides), with ties of every kind planted (makeMovedCase), in small and large frames; and no
// copies, no labels.
TEST(GpuTracking, NearestMovedIsTheContractsPickForEveryPoint) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const SequenceCase cases[] = {{synth::BodyPlan::Humanoid, 4, 3000},
                                {synth::BodyPlan::Hand, 3, 20000}};
  for (const auto& sc : cases) {
    const auto seq = generated(sc.plan, sc.frames, sc.points, 11);
    animseg_test::MovedCase c;
    animseg_test::makeMovedCase(*seq, c);
    gpu::MotionTracking device;
    device.setFrames(c.frames);
    std::vector<int> pick;
    ASSERT_TRUE(device.nearestMoved(c.copies, pick));
    const std::vector<int> spec = animseg_test::movedNearestBySpec(c.frames, c.copies);
    ASSERT_EQ(pick.size(), spec.size());
    std::size_t differ = 0, undecided = 0;
    for (std::size_t i = 0; i < spec.size(); ++i) {
      differ += pick[i] != spec[i];
      undecided += pick[i] == seg::kMovedUndecided;
    }
    std::printf("%s, %d frames x %d points: %zu picks differ, %zu undecided\n",
                synth::toString(sc.plan).c_str(), sc.frames, sc.points, differ, undecided);
    EXPECT_EQ(differ, 0u);
    EXPECT_GT(undecided, 0u);
    // No copies: no label anywhere.
    seg::MovedCopies none;
    none.fill = [](float*) {};
    ASSERT_TRUE(device.nearestMoved(none, pick));
    EXPECT_EQ(pick, std::vector<int>(spec.size(), -1));
  }
}

// The rigid motions' fits on the GPU (gpu::RigidFits) against the CPU: every level's motions the
// same bits, level 0 from starts of its own (as the pipeline passes the refinement's), a coarser
// level nested in it (its merged parts from their children), and plain chains (compute()).
TEST(GpuTracking, RigidMotionsAreTheCpusBitForBit) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  // The third: 70 frames, the chains through key frames 2 apart (chained_fit.h, chainFrames).
  const SequenceCase cases[] = {{synth::BodyPlan::Humanoid, 16, 4000},
                                {synth::BodyPlan::Hand, 16, 4000},
                                {synth::BodyPlan::Humanoid, 70, 800}};
  for (const auto& c : cases) {
    const auto plan = c.plan;
    synth::SynthParams sp;
    sp.plan = plan;
    sp.frames = c.frames;
    sp.points = c.points;
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
    // Every cluster size (0: chosen per batch) gives the same bits: a fit's ranges, split among
    // 1-8 blocks, are added in the same order.
    for (int cluster : {0, 1, 2, 4, 8}) {
      gpu::RigidFits device;
      device.setClusterSize(cluster);
      est.setDevice(&device);
      const auto dev = est.computeLevels(levels);
      const auto dev_chained = est.compute(levels[1]);
      est.setDevice(nullptr);
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
      std::printf(
          "%s, %d frames, cluster %d (last batch %d blocks per fit): %d transforms, %lld GPU "
          "fits in %lld batches, %lld batches of the starts' scores; %d differ from the "
          "CPU's\n",
          synth::toString(plan).c_str(), c.frames, cluster, device.lastClusterSize(), transforms,
          device.fits(), device.batches(), device.scoreBatches(), differ);
      EXPECT_EQ(differ, 0) << synth::toString(plan) << ", cluster " << cluster;
      EXPECT_GT(device.fits(), 0);
      EXPECT_GT(device.scoreBatches(), 0);  // level 0's starts scored on the GPU
      if (cluster > 0) {
        EXPECT_LE(device.lastClusterSize(), cluster);
        EXPECT_GE(device.lastClusterSize(), 1);
      }
    }
  }
}

// A source of 12 000 points (max_points raised for it): a block's ranges hold 12 000 or 6 000
// points, more than 23 searches per thread, with the same bits on one block and on two.
TEST(GpuTracking, RigidFitsOfLargeSourcesAreTheCpus) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const synth::SynthParams sp =
      animseg_test::sequenceParams(synth::BodyPlan::Humanoid, 4, 12000, 3);
  const auto frames = synth::generate(sp);
  const pcl_animseg::PointCloudSequence seq = synth::toSequence(frames);
  std::vector<std::vector<int>> whole;
  for (const auto& f : frames) whole.emplace_back(f.labels.size(), 0);  // one part: the body
  seg::RigidMotionParams p;
  p.max_points = 20000;
  seg::RigidMotionEstimation est;
  est.setInputSequence(&seq);
  est.setParams(p);
  const auto cpu = est.compute(whole);
  ASSERT_EQ(cpu.size(), 1u);
  for (int cluster : {1, 2}) {
    gpu::RigidFits device;
    device.setClusterSize(cluster);
    est.setDevice(&device);
    const auto dev = est.compute(whole);
    est.setDevice(nullptr);
    ASSERT_EQ(dev.size(), 1u);
    ASSERT_EQ(dev[0].frames.size(), cpu[0].frames.size());
    int valid = 0;
    for (std::size_t t = 0; t < cpu[0].frames.size(); ++t) {
      const auto &x = dev[0].frames[t], &y = cpu[0].frames[t];
      valid += x.valid;
      EXPECT_TRUE(x.valid == y.valid && x.rotation == y.rotation &&
                  x.translation == y.translation && x.rms == y.rms)
          << "frame " << t << ", cluster " << cluster;
    }
    EXPECT_GE(valid, sp.frames - 1);  // frame 0 is the reference
    EXPECT_EQ(device.lastClusterSize(), cluster);
    EXPECT_GT(device.fits(), 0);
  }
}

// One device's surfaces set again and again: 80 000 points (1.3 MB of points alone: their buffers
// are page-locked after the upload, for the next), twice as many (the buffers grow, so they are
// unlocked first, then locked anew), the first again (the grown buffers, still locked, hold them:
// the upload goes from locked memory). Every labelling's motions are the CPU's bit for bit.
TEST(GpuTracking, SurfacesSetAgainOnOneDeviceGiveTheCpusMotions) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  gpu::RigidFits device;
  seg::RigidMotionParams p;
  p.max_points = 300;
  for (int frames : {8, 16, 8}) {
    const auto generated_frames =
        synth::generate(animseg_test::sequenceParams(synth::BodyPlan::Humanoid, frames, 10000, 4));
    const pcl_animseg::PointCloudSequence seq = synth::toSequence(generated_frames);
    ASSERT_GE(seq.totalPoints(), 80000u);
    std::vector<std::vector<int>> labels;
    for (const auto& f : generated_frames) labels.push_back(f.labels);
    seg::RigidMotionEstimation est;
    est.setInputSequence(&seq);
    est.setParams(p);
    const auto cpu = est.compute(labels);
    const long long fits_before = device.fits();
    est.setDevice(&device);
    const auto dev = est.compute(labels);
    ASSERT_EQ(dev.size(), cpu.size());
    int transforms = 0, differ = 0;
    for (std::size_t part = 0; part < cpu.size(); ++part) {
      ASSERT_EQ(dev[part].frames.size(), cpu[part].frames.size());
      for (std::size_t t = 0; t < cpu[part].frames.size(); ++t) {
        const auto &x = dev[part].frames[t], &y = cpu[part].frames[t];
        ++transforms;
        differ += !(x.valid == y.valid && x.rotation == y.rotation &&
                    x.translation == y.translation && (x.rms == y.rms || !x.valid));
      }
    }
    std::printf("%d frames x 10000 points: %d transforms, %d differ from the CPU's\n", frames,
                transforms, differ);
    EXPECT_EQ(differ, 0) << frames << " frames";
    EXPECT_GT(device.fits(), fits_before);  // fitted on this device, not left to the cores
  }
}

// Residual batches on the GPU both ways (a thread per point with the sums after, and a warp per
// job: setPointParallelLimit(0)) against the CPU's residual of each job from the same frames:
// the same bits. The sources run from none to thousands of points, as a merge's parts do.
// A 4-frame humanoid's frames as a device takes them, and sources cut from frame 0 (0, 1, 37, 500
// and 3000 points) under four motions (the identity and small turns and shifts): every (source,
// motion, frame) a residual job.
struct SourcesOnFrames {
  SourcesOnFrames() {
    seq = generated(synth::BodyPlan::Humanoid, 4, 6000, 5);
    trees.resize(seq->size());
    for (std::size_t t = 0; t < seq->size(); ++t) {
      const auto& cloud = *seq->frame(t);
      std::vector<float> xyz;
      for (const auto& p : cloud) xyz.insert(xyz.end(), {p.x, p.y, p.z});
      trees[t].build(xyz.data(), cloud.size());
      seg::DeviceFrames::Frame f;
      f.tree = &trees[t];
      for (int row : trees[t].leafRows())
        f.leaf_normals.insert(f.leaf_normals.end(),
                              {cloud[row].normal_x, cloud[row].normal_y, cloud[row].normal_z});
      f.spacing = pcl_animseg::meanSpacing(cloud);
      frames.frames.push_back(f);
    }
    const auto& f0 = *seq->frame(0);
    for (int n : {0, 1, 37, 500, 3000}) {
      for (int i = 0; i < n; ++i) {
        const auto& p = f0[(i * 7) % f0.size()];
        b.points.insert(b.points.end(), {p.x, p.y, p.z, p.normal_x, p.normal_y, p.normal_z});
      }
      b.source_begin.push_back(static_cast<int>(b.points.size() / 6));
    }
    for (int k = 0; k < 4; ++k) {
      const Eigen::Matrix3d r =
          Eigen::AngleAxisd(0.05 * k, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) b.motions.push_back(r(i, j));
      b.motions.insert(b.motions.end(), {0.01 * k, -0.005 * k, 0.0});
    }
    for (int src = 0; src < 5; ++src)
      for (int m = 0; m < 4; ++m)
        for (int t = 0; t < static_cast<int>(seq->size()); ++t) b.jobs.push_back({src, m, t});
  }
  pcl_animseg::PointCloudSequence::Ptr seq;
  std::vector<pcl_animseg::FlatKdTree3> trees;
  seg::DeviceFrames frames;
  seg::ResidualJobs b;
};

TEST(GpuTracking, ResidualBatchesAreTheCpusBothWays) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const SourcesOnFrames data;
  const seg::DeviceFrames& frames = data.frames;
  const seg::ResidualJobs& b = data.b;
  // The CPU's residual of each job from the same frames (motion_tracking.cpp's residual).
  const std::vector<double> cpu = animseg_test::cpuResiduals(frames, b);
  gpu::MotionTracking device;
  device.setFrames(frames);
  std::vector<double> by_point, by_warp;
  device.residuals(b, by_point);
  device.setPointParallelLimit(0);
  device.residuals(b, by_warp);
  ASSERT_EQ(by_point.size(), b.jobs.size());
  int differ_point = 0, differ_warp = 0;
  for (std::size_t j = 0; j < cpu.size(); ++j) {
    differ_point += by_point[j] != cpu[j];
    differ_warp += by_warp[j] != cpu[j];
  }
  std::printf("%zu residuals: %d differ from the CPU's by point, %d by warp\n", cpu.size(),
              differ_point, differ_warp);
  EXPECT_EQ(differ_point, 0);
  EXPECT_EQ(differ_warp, 0);
  // Not all zero: the turned sources lie off the surfaces.
  EXPECT_GT(*std::max_element(cpu.begin(), cpu.end()), 0.0);
  // A fork of the device (the frames shared, its own buffers) called from another thread while
  // the device is called from this one, batch after batch: every batch is still the CPU's.
  device.setPointParallelLimit(1LL << 21);
  const std::unique_ptr<seg::MotionDevice> fork = device.fork();
  ASSERT_NE(fork, nullptr);
  int differ_fork = 0, differ_here = 0;
  std::thread beside([&] {
    std::vector<double> out;
    for (int round = 0; round < 50; ++round) {
      fork->residuals(b, out);
      differ_fork += out != cpu;
    }
  });
  std::vector<double> out;
  for (int round = 0; round < 50; ++round) {
    device.residuals(b, out);
    differ_here += out != cpu;
  }
  beside.join();
  EXPECT_EQ(differ_fork, 0);
  EXPECT_EQ(differ_here, 0);
}

// Residual batches of every size a run makes, in the order sizes come in a run (small ones
// between large ones), each the CPU's, bit for bit. The device keeps page-locked buffers for a
// batch's inputs and results; one of 1-4 MiB goes pageable while a larger buffer grows on a
// thread of its own (a later batch takes it when it is ready), and larger ones (the motion
// method's one-off sample edges and first dissolve costs at 800k) always go pageable. Whichever
// way each batch goes, its results must be its own.
TEST(GpuTracking, ResidualBatchesOfEverySizeAreTheCpus) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const SourcesOnFrames data;
  // The jobs of the small sources (0, 1 and 37 points), repeated: the batches' sizes grow with
  // their jobs, and the CPU's residual of each job is computed once.
  seg::ResidualJobs base = data.b;
  base.jobs.clear();
  for (const seg::ResidualJobs::Job& j : data.b.jobs)
    if (j.source < 3) base.jobs.push_back(j);
  const std::vector<double> cpu = animseg_test::cpuResiduals(data.frames, base);
  gpu::MotionTracking device;
  device.setFrames(data.frames);
  // 48 jobs a repeat: results of 8 bytes and inputs of 12-16 bytes a job, so 100 repeats are
  // about 40 KB of results, 4 000 about 1.5 MB (3 MB of inputs), 15 000 about 5.8 MB (11 MB).
  const int repeats[] = {100, 4000, 15000, 4000, 100, 4000, 15000, 100, 4000, 4000};
  int batches = 0;
  for (const bool by_point : {true, false}) {
    device.setPointParallelLimit(by_point ? (1LL << 30) : 0);
    for (int r : repeats) {
      seg::ResidualJobs b = base;
      b.jobs.clear();
      for (int k = 0; k < r; ++k) b.jobs.insert(b.jobs.end(), base.jobs.begin(), base.jobs.end());
      std::vector<double> out;
      device.residuals(b, out);
      ASSERT_EQ(out.size(), b.jobs.size());
      long differ = 0;
      for (std::size_t j = 0; j < out.size(); ++j) differ += out[j] != cpu[j % cpu.size()];
      EXPECT_EQ(differ, 0) << r << " repeats, " << (by_point ? "by point" : "by warp");
      ++batches;
    }
  }
  std::printf("%d residual batches of %zu to %zu jobs: the CPU's\n", batches,
              48 * static_cast<std::size_t>(100), 48 * static_cast<std::size_t>(15000));
  // Some residuals are not zero, and they differ between jobs: a batch's results in the wrong
  // places would show.
  EXPECT_GT(*std::max_element(cpu.begin(), cpu.end()), *std::min_element(cpu.begin(), cpu.end()));
  EXPECT_EQ(cpu.size(), 48u);
}

// Part fits on the GPU are the CPU's (cpuPartFits), bit for bit, on blocks of both widths: a
// batch whose sources have at most 128 points (a block of 128 threads a fit, one round of
// points per iteration), and one with sources of 500 and 3000 points (a block of 512 threads a
// fit: the labels' part motions fit sources of up to 400 points), the starts under four motions.
TEST(GpuTracking, PartFitsAreTheCpusOnBlocksOfBothWidths) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const SourcesOnFrames data;
  gpu::MotionTracking device;
  device.setFrames(data.frames);
  for (const bool large : {false, true}) {
    seg::PartFitJobs fits;
    fits.points = data.b.points;
    fits.source_begin = data.b.source_begin;
    fits.motions = data.b.motions;
    fits.iterations = 10;
    for (const auto& r : data.b.jobs) {
      const int m = data.b.source_begin[r.source + 1] - data.b.source_begin[r.source];
      if ((m > 128) != large) continue;
      fits.jobs.push_back({r.source, r.motion, r.frame, std::numeric_limits<double>::infinity(),
                           4.0 * data.frames.frames[r.frame].spacing});
    }
    ASSERT_FALSE(fits.jobs.empty());
    const std::vector<double> cpu = animseg_test::cpuPartFits(data.frames, fits);
    std::vector<double> gpu_poses;
    device.partFits(fits, gpu_poses);
    ASSERT_EQ(gpu_poses.size(), cpu.size());
    int differ = 0, moved = 0;
    for (std::size_t j = 0; j < fits.jobs.size(); ++j) {
      differ +=
          !std::equal(cpu.begin() + 12 * j, cpu.begin() + 12 * (j + 1), gpu_poses.begin() + 12 * j);
      moved += !std::equal(cpu.begin() + 12 * j, cpu.begin() + 12 * (j + 1),
                           fits.motions.begin() + 12 * fits.jobs[j].motion);
    }
    std::printf("%zu part fits of %s sources: %d differ from the CPU's (%d moved from the start)\n",
                fits.jobs.size(), large ? "500 and 3000-point" : "0 to 37-point", differ, moved);
    EXPECT_EQ(differ, 0) << large;
    EXPECT_GT(moved, 0) << large;  // the fits did something
  }
}

// The CPU's residuals and part fits as a device (cpu_residuals.h), so that MotionDevice's default
// scoreAndFit (a residual batch, the winners, a part-fit batch) is the reference.
class CpuPartDevice : public seg::MotionDevice {
 public:
  std::string name() const override { return "cpu"; }
  void setFrames(const seg::DeviceFrames& frames) override { frames_ = frames; }
  void trackSamples(const seg::SampleTrackingProblem&, std::vector<std::vector<Eigen::Isometry3d>>&,
                    std::vector<std::vector<double>>&) override {}
  void residuals(const seg::ResidualJobs& jobs, std::vector<double>& out) override {
    out = animseg_test::cpuResiduals(frames_, jobs);
  }
  void pointCosts(const seg::PointCostJobs&, std::vector<double>&) override {}
  void partFits(const seg::PartFitJobs& jobs, std::vector<double>& poses) override {
    poses = animseg_test::cpuPartFits(frames_, jobs);
  }

 private:
  seg::DeviceFrames frames_;
};

// Starts scored and the winners fitted in one call (MotionTracking::scoreAndFit) give the CPU's
// scores, winners and poses bit for bit: bases before, between and after the starts, bases that
// win and bases that cannot, ties (one start twice), jobs without starts; sources of 0 to 37
// points (a block of 128 threads a job), of 500 and 3000 (512), and a batch of more than 512 jobs
// (a warp a job).
TEST(GpuTracking, ScoredPartFitsAreTheCpusInOneCall) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const SourcesOnFrames data;
  gpu::MotionTracking device;
  device.setFrames(data.frames);
  CpuPartDevice cpu;
  cpu.setFrames(data.frames);
  const int frames = static_cast<int>(data.frames.frames.size());
  // The CPU's residual of source s under motion m in frame t, for bases that tie with a start.
  auto residualOf = [&](int s, int m, int t) {
    seg::ResidualJobs r;
    r.points = data.b.points;
    r.source_begin = data.b.source_begin;
    r.motions = data.b.motions;
    r.jobs.push_back({s, m, t});
    return animseg_test::cpuResiduals(data.frames, r)[0];
  };
  for (const int kind : {0, 1, 2}) {  // small sources, large ones, small ones many times over
    seg::ScoreFitJobs sf;
    sf.points = data.b.points;
    sf.source_begin = data.b.source_begin;
    sf.iterations = 8;
    auto job = [&](int s, int t, std::vector<std::pair<int, int>> motion_place, int base_place,
                   double base_score) {
      seg::ScoreFitJobs::Job j;
      j.source = s;
      j.frame = t;
      j.first = static_cast<int>(sf.places.size());
      j.count = static_cast<int>(motion_place.size());
      j.base_place = base_place;
      j.base_score = base_score;
      j.max_dist = 4.0 * data.frames.frames[t].spacing;
      for (const auto& [m, place] : motion_place) {
        sf.motions.insert(sf.motions.end(), data.b.motions.begin() + 12 * m,
                          data.b.motions.begin() + 12 * (m + 1));
        sf.places.push_back(place);
      }
      sf.jobs.push_back(j);
    };
    const double kMax = std::numeric_limits<double>::max();
    const int repeats = kind == 2 ? 40 : 1;
    for (int rep = 0; rep < repeats; ++rep)
      for (int s = kind == 1 ? 3 : 0; s < (kind == 1 ? 5 : 3); ++s)
        for (int t = 0; t < frames; ++t) {
          job(s, t, {{0, 0}, {1, 1}}, -1, 0.0);
          job(s, t, {{1, 1}, {3, 3}}, 0, 1e-9);  // a base first that wins but for a 0
          job(s, t, {{2, 0}, {2, 2}}, 1, kMax);  // a tie (place 0 wins); a base that cannot
          job(s, t, {}, 0, 0.5);                 // nothing to score: the base wins
          job(s, t, {{3, 1}}, -1, 0.0);          // the start at place 1, none at 0
          job(s, t, {{0, 2}, {1, 3}}, 0, residualOf(s, 1, t));  // a base tied with a start
          job(s, t, {{(s + t) % 4, 0}, {1, 2}, {2, 3}}, 1, residualOf(s, (s + t + 1) % 4, t));
        }
    std::vector<double> cs, gs, cp, gp;
    std::vector<int> cf, gf;
    cpu.scoreAndFit(sf, cs, cf, cp);
    device.scoreAndFit(sf, gs, gf, gp);
    ASSERT_EQ(gs.size(), sf.places.size());
    ASSERT_EQ(gf.size(), sf.jobs.size());
    ASSERT_EQ(gp.size(), 12 * sf.jobs.size());
    int scores_differ = 0, winners_differ = 0, poses_differ = 0, fitted = 0, base_won = 0,
        moved = 0;
    for (std::size_t k = 0; k < cs.size(); ++k) scores_differ += gs[k] != cs[k];
    for (std::size_t j = 0; j < sf.jobs.size(); ++j) {
      winners_differ += gf[j] != cf[j];
      if (cf[j] < 0) {
        ++base_won;
        continue;
      }
      ++fitted;
      poses_differ +=
          !std::equal(cp.begin() + 12 * j, cp.begin() + 12 * (j + 1), gp.begin() + 12 * j);
      moved += !std::equal(cp.begin() + 12 * j, cp.begin() + 12 * (j + 1),
                           sf.motions.begin() + 12 * (sf.jobs[j].first + cf[j]));
    }
    std::printf(
        "%zu scored part fits (%s): %d scores, %d winners, %d of %d poses differ from the "
        "CPU's (%d bases won, %d fits moved)\n",
        sf.jobs.size(), kind == 1 ? "500 and 3000-point sources" : "0 to 37-point sources",
        scores_differ, winners_differ, poses_differ, fitted, base_won, moved);
    EXPECT_EQ(scores_differ, 0) << kind;
    EXPECT_EQ(winners_differ, 0) << kind;
    EXPECT_EQ(poses_differ, 0) << kind;
    EXPECT_GT(base_won, 0) << kind;
    EXPECT_GT(fitted, 0) << kind;
    EXPECT_GT(moved, 0) << kind;
    if (kind == 2) {
      EXPECT_GT(sf.jobs.size(), 512u);
    }
  }
}

// A part fit's score of its own result (MotionTracking::partFitsWithResiduals, one call) is what
// a residual batch gives for the pose kept, bit for bit: the fit's result, or the start where the
// fit scored above r0; the poses are partFits()'.
TEST(GpuTracking, PartFitsScoreWhatTheyKeepAsTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const SourcesOnFrames data;
  seg::PartFitJobs fits;
  fits.points = data.b.points;
  fits.source_begin = data.b.source_begin;
  fits.motions = data.b.motions;
  fits.iterations = 8;
  for (std::size_t j = 0; j < data.b.jobs.size(); ++j) {
    const auto& r = data.b.jobs[j];
    // Every third job keeps the start unless its fit scores 0 (r0 = 0), the others the fit.
    const double r0 = j % 3 == 0 ? 0.0 : std::numeric_limits<double>::infinity();
    fits.jobs.push_back(
        {r.source, r.motion, r.frame, r0, 4.0 * data.frames.frames[r.frame].spacing});
  }
  gpu::MotionTracking device;
  device.setFrames(data.frames);
  std::vector<double> poses, with_res, res;
  device.partFits(fits, poses);
  device.partFitsWithResiduals(fits, with_res, res);
  ASSERT_EQ(poses.size(), 12 * fits.jobs.size());
  EXPECT_EQ(with_res, poses);
  ASSERT_EQ(res.size(), fits.jobs.size());
  // The CPU's residual of each job's kept pose.
  seg::ResidualJobs kept;
  kept.points = fits.points;
  kept.source_begin = fits.source_begin;
  kept.motions = poses;
  int starts_kept = 0;
  for (std::size_t j = 0; j < fits.jobs.size(); ++j) {
    kept.jobs.push_back({fits.jobs[j].source, static_cast<int>(j), fits.jobs[j].frame});
    starts_kept += std::equal(poses.begin() + 12 * j, poses.begin() + 12 * (j + 1),
                              fits.motions.begin() + 12 * fits.jobs[j].motion);
  }
  const std::vector<double> cpu = animseg_test::cpuResiduals(data.frames, kept);
  int differ = 0;
  for (std::size_t j = 0; j < cpu.size(); ++j) differ += res[j] != cpu[j];
  std::printf("%zu part fits (%d kept their start): %d scores differ from the CPU's\n",
              fits.jobs.size(), starts_kept, differ);
  EXPECT_EQ(differ, 0);
  // Both branches ran: starts kept (r0 = 0) and fits kept; and the scores are not all zero.
  EXPECT_GT(starts_kept, 0);
  EXPECT_LT(starts_kept, static_cast<int>(fits.jobs.size()));
  EXPECT_GT(*std::max_element(cpu.begin(), cpu.end()), 0.0);
}
