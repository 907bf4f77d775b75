// gpu::FeatureDevice against the CPU's MLSScaleSpace, DoGKeypoint and SignatureEstimation: the
// neighbour rows bit for bit (also for points with more neighbours than a row holds), the levels
// and signatures to float rounding, the keypoints, and the labels of the paper method's mean
// shift on either's features. Frames of different sizes, one with its normals missing. Skips
// when no usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/features.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/pipeline.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/synth/articulated.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <set>
#include <string>
#include <vector>

#include "../features/bumpy_surface.h"

namespace gpu = pcl_animseg::gpu;
using pcl_animseg::PointCloudSequence;

namespace {

/** Four bumpy spheres of different sizes; frame 2 has no normals, frame 3 a spot of 300
 * coincident points (rows over the cap). */
PointCloudSequence testSequence() {
  PointCloudSequence seq;
  const std::size_t sizes[] = {6000, 7400, 5200, 6600};
  for (int t = 0; t < 4; ++t) {
    auto cloud = pcl_animseg::test::bumpySphere(sizes[t], 40 + t);
    if (t == 2)
      for (auto& p : cloud->points) p.normal_x = p.normal_y = p.normal_z = 0.0f;
    if (t == 3)
      for (int k = 0; k < 300; ++k) cloud->push_back((*cloud)[17]);
    seq.addFrame(cloud, "f" + std::to_string(t));
  }
  return seq;
}

double positionError(const pcl::PointNormal& a, const pcl::PointNormal& b) {
  return (a.getVector3fMap() - b.getVector3fMap()).norm();
}

double normalError(const pcl::PointNormal& a, const pcl::PointNormal& b) {
  return (a.getNormalVector3fMap() - b.getNormalVector3fMap()).norm();
}

}  // namespace

TEST(GpuFeatures, RowsAndLevelsAgreeWithTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const PointCloudSequence seq = testSequence();
  pcl_animseg::MultiscaleParams p;
  const double unit = pcl_animseg::sequenceSpacing(seq);
  std::vector<pcl_animseg::ScaleSpacePlan> plans;
  std::vector<pcl_animseg::ScaleSpace> cpu(seq.size()), dev(seq.size());
  for (std::size_t t = 0; t < seq.size(); ++t) {
    pcl_animseg::MLSScaleSpace mls;
    pcl_animseg::configureScaleSpace(mls, seq.frame(t), p, unit);
    plans.push_back(mls.plan());
    mls.compute(cpu[t]);
  }
  gpu::FeatureDevice device;
  device.scaleSpaces(seq, 0, seq.size(), plans, p, /*rows=*/true, dev);

  for (std::size_t t = 0; t < seq.size(); ++t) {
    // The rows: the same entries, distances and order as radiusNeighbourhoods (the CPU's own
    // rows, which the keypoints use, and the device's).
    const pcl_animseg::Neighbourhoods& a = *cpu[t].neighbourhoods;
    const pcl_animseg::Neighbourhoods b = device.rows(t);
    ASSERT_EQ(a.offsets, b.offsets) << "frame " << t;
    EXPECT_EQ(a.indices, b.indices) << "frame " << t;
    EXPECT_EQ(a.sqr_distances, b.sqr_distances) << "frame " << t;
    EXPECT_EQ(a.offsets, dev[t].neighbourhoods->offsets) << "frame " << t;
    if (t == 3) {
      EXPECT_EQ(a.count(17), 256) << "the coincident spot fills its rows";
    }

    ASSERT_EQ(dev[t].levels.size(), cpu[t].levels.size());
    EXPECT_EQ(dev[t].scales, cpu[t].scales);
    EXPECT_EQ(dev[t].spacing, cpu[t].spacing);
    const double tol = 1e-4 * cpu[t].spacing;
    for (std::size_t l = 0; l < cpu[t].levels.size(); ++l) {
      const auto& c = *cpu[t].levels[l];
      const auto& g = *dev[t].levels[l];
      ASSERT_EQ(c.size(), g.size());
      std::size_t far = 0, same = 0;
      double worst = 0.0, worst_n = 0.0;
      for (std::size_t j = 0; j < c.size(); ++j) {
        const double e = positionError(c[j], g[j]), en = normalError(c[j], g[j]);
        worst = std::max(worst, e);
        worst_n = std::max(worst_n, en);
        if (e > tol || en > 1e-3) ++far;
        if (e == 0.0 && en == 0.0) ++same;
        if (l == 0) {
          EXPECT_NEAR(c[j].curvature, g[j].curvature, 1e-4);
        }
      }
      std::printf(
          "frame %zu level %zu: %zu of %zu points the same bits, worst %.3g spacings "
          "%.3g normal, %zu beyond 1e-4 spacings\n",
          t, l, same, c.size(), worst / cpu[t].spacing, worst_n, far);
      // Only the library functions' last bits differ: a handful of points at most move more
      // than 1e-4 spacings (a projection near its rejection threshold), none by much.
      EXPECT_LE(far, c.size() / 500) << "frame " << t << " level " << l;
      EXPECT_LT(worst, 0.05 * cpu[t].spacing) << "frame " << t << " level " << l;
    }
  }
}

TEST(GpuFeatures, SignaturesAndKeypointsAgreeWithTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const PointCloudSequence seq = testSequence();
  pcl_animseg::MultiscaleParams p;
  p.keep_smoothed = true;
  const pcl_animseg::SequenceFeatures cpu = pcl_animseg::computeSequenceFeatures(seq, p);
  gpu::FeatureDevice device;
  pcl_animseg::Progress progress(true);
  const pcl_animseg::SequenceFeatures dev =
      pcl_animseg::computeSequenceFeatures(seq, p, &progress, &device);
  ASSERT_EQ(dev.signatures.size(), seq.size());
  std::size_t kp_cpu = 0, kp_both = 0, kp_dev = 0;
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const Eigen::MatrixXf& a = cpu.signatures[t];
    const Eigen::MatrixXf& b = dev.signatures[t];
    ASSERT_EQ(a.rows(), b.rows());
    ASSERT_EQ(a.cols(), b.cols());
    std::size_t far = 0, same = 0;
    double worst = 0.0, scale = 0.0;
    for (Eigen::Index j = 0; j < a.rows(); ++j) {
      const double e = (a.row(j) - b.row(j)).cwiseAbs().maxCoeff();
      scale = std::max(scale, static_cast<double>(a.row(j).cwiseAbs().maxCoeff()));
      worst = std::max(worst, e);
      if (e > 1e-4) ++far;
      if (e == 0.0) ++same;
    }
    std::printf(
        "frame %zu signatures: %zu of %zu the same bits, worst difference %.3g (largest "
        "value %.3g), %zu beyond 1e-4\n",
        t, same, static_cast<std::size_t>(a.rows()), worst, scale, far);
    EXPECT_LE(far, static_cast<std::size_t>(a.rows()) / 200) << "frame " << t;
    const std::set<int> kc(cpu.keypoints[t].begin(), cpu.keypoints[t].end());
    const std::set<int> kd(dev.keypoints[t].begin(), dev.keypoints[t].end());
    for (int k : kc) kp_both += kd.count(k);
    kp_cpu += kc.size();
    kp_dev += kd.size();
    ASSERT_TRUE(dev.smoothed[t]);
    EXPECT_EQ(dev.smoothed[t]->size(), seq.frame(t)->size());
  }
  std::printf("keypoints: CPU %zu, GPU %zu, at the same point %zu\n", kp_cpu, kp_dev, kp_both);
  EXPECT_GT(kp_cpu, 8u) << "the bumps give keypoints";
  EXPECT_GE(kp_both, kp_cpu * 9 / 10);
  EXPECT_LE(kp_dev, kp_cpu + kp_cpu / 10 + 1);
}

TEST(GpuFeatures, PaperMethodLabelsAgreeWithTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  pcl_animseg::synth::SynthParams sp;
  sp.plan = pcl_animseg::synth::BodyPlan::Quadruped;
  sp.frames = 6;
  sp.points = 3000;
  sp.seed = 5;
  const auto seq = std::make_shared<PointCloudSequence>(
      pcl_animseg::synth::toSequence(pcl_animseg::synth::generate(sp)));
  // The paper method's mean shift (on the CPU, where both runs iterate alike) on the CPU's
  // features and on the GPU's.
  const pcl_animseg::MultiscaleParams fp;
  const pcl_animseg::SequenceFeatures cpu = pcl_animseg::computeSequenceFeatures(*seq, fp);
  gpu::FeatureDevice device;
  const pcl_animseg::SequenceFeatures dev =
      pcl_animseg::computeSequenceFeatures(*seq, fp, nullptr, &device);
  EXPECT_EQ(cpu.keypoints, dev.keypoints);
  auto labelsOf = [&](const pcl_animseg::SequenceFeatures& f) {
    namespace seg = pcl_animseg::segmentation;
    seg::MeanShiftParams mp;
    mp.method = seg::MeanShiftMethod::Paper;
    seg::MeanShiftSegmentation ms;
    ms.setInputSequence(seq);
    ms.setParams(mp);
    ms.setSignatures(f.signatures);
    ms.setKeypoints(f.keypoints);
    seg::SegmentationResult result;
    ms.segment(result);
    std::vector<int> all;
    for (const auto& frame : result.labels) all.insert(all.end(), frame.begin(), frame.end());
    return all;
  };
  const double ari = pcl_animseg::evaluation::adjustedRandIndex(labelsOf(cpu), labelsOf(dev));
  std::printf(
      "paper method, quadruped: ARI between the labels on the CPU's and the GPU's "
      "features %.4f\n",
      ari);
  EXPECT_GE(ari, 0.99);

  // The pipeline puts them on the GPU with --device gpu, and says so.
  pcl_animseg::PipelineParams params;
  params.mean_shift.method = pcl_animseg::segmentation::MeanShiftMethod::Paper;
  params.device = "gpu";
  params.refine = false;
  params.motions = false;
  pcl_animseg::Progress progress(true);
  const pcl_animseg::PipelineResult r = pcl_animseg::runPipeline(*seq, params, progress);
  EXPECT_NE(
      std::find(r.notes.begin(), r.notes.end(), "scale space and signatures computed on the GPU"),
      r.notes.end());
  std::size_t kp = 0;
  for (const auto& k : cpu.keypoints) kp += k.size();
  EXPECT_EQ(r.keypoints, kp);
}

// The keypoints' Newton steps on the device against the cores', on the same (CPU) scale space:
// the same keypoints at the same frame points, positions to the last bits (the device adds each
// disc's sums in another order). Bumpy spheres (one without normals) and two humanoid frames
// (many keypoints a frame, near thin parts).
TEST(GpuFeatures, KeypointRefinementAgreesWithTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  PointCloudSequence seq = testSequence();
  pcl_animseg::synth::SynthParams sp;
  sp.plan = pcl_animseg::synth::BodyPlan::Humanoid;
  sp.frames = 2;
  sp.points = 12000;
  sp.seed = 3;
  const PointCloudSequence humanoid =
      pcl_animseg::synth::toSequence(pcl_animseg::synth::generate(sp));
  for (std::size_t t = 0; t < humanoid.size(); ++t)
    seq.addFrame(humanoid.frame(t), "h" + std::to_string(t));
  const pcl_animseg::MultiscaleParams p;
  const double unit = pcl_animseg::sequenceSpacing(seq);
  gpu::FeatureDevice device;
  ASSERT_NE(device.keypointRefiner(), nullptr);
  std::size_t total = 0, same_bits = 0;
  double worst = 0.0;
  for (std::size_t t = 0; t < seq.size(); ++t) {
    pcl_animseg::MLSScaleSpace mls;
    pcl_animseg::configureScaleSpace(mls, seq.frame(t), p, unit);
    pcl_animseg::ScaleSpace ss;
    mls.compute(ss);
    pcl_animseg::DoGKeypoint dog;
    dog.setScaleSpace(ss);
    pcl_animseg::DoGKeypoint::KeypointCloud on_cores, on_device;
    dog.compute(on_cores);
    dog.setRefineDevice(device.keypointRefiner());
    dog.compute(on_device);
    ASSERT_EQ(on_cores.size(), on_device.size()) << "frame " << t;
    for (std::size_t k = 0; k < on_cores.size(); ++k) {
      const auto& a = on_cores[k];
      const auto& b = on_device[k];
      EXPECT_EQ(a.index, b.index) << "frame " << t << " keypoint " << k;
      EXPECT_EQ(a.level, b.level);
      EXPECT_EQ(a.response, b.response);
      const double e = (a.getVector3fMap() - b.getVector3fMap()).norm() / ss.scales[0];
      worst = std::max(worst, e);
      same_bits += e == 0.0;
    }
    total += on_cores.size();
  }
  std::printf("keypoint refinement: %zu keypoints, %zu at the same bits, worst %.3g h0\n", total,
              same_bits, worst);
  EXPECT_GT(total, 40u);
  EXPECT_LT(worst, 1e-3);
}
