// The exact Gauss transform on the GPU (gpu::GaussTransform) against sums in double on the CPU,
// the device's exact sums with the keypoint pair rule (MeanShiftBackend::exactSums), and the
// exact backend of the mean-shift stage on the device against the CPU's. Skips without a GPU.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/gauss_transform.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/synth/articulated.h>

#include <cmath>
#include <cstdio>
#include <random>

namespace gpu = pcl_animseg::gpu;
namespace seg = pcl_animseg::segmentation;

namespace {

/** n points in d dimensions around `clusters` centres `spread` apart (unit spread around each). */
Eigen::MatrixXf clustered(int n, int d, int clusters, float spread, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  Eigen::MatrixXf centres(clusters, d);
  for (int c = 0; c < clusters; ++c)
    for (int k = 0; k < d; ++k) centres(c, k) = spread * g(rng);
  Eigen::MatrixXf x(n, d);
  for (int i = 0; i < n; ++i)
    for (int k = 0; k < d; ++k) x(i, k) = centres(i % clusters, k) + g(rng);
  return x;
}

/** The sums in double, point by point. */
Eigen::MatrixXd reference(const Eigen::MatrixXf& x, const Eigen::MatrixXf& carried,
                          const Eigen::MatrixXf& q, float cutoff) {
  const int dx = static_cast<int>(x.cols()), dc = static_cast<int>(carried.cols());
  Eigen::MatrixXd out = Eigen::MatrixXd::Zero(q.rows(), dx + dc + 1);
  for (Eigen::Index r = 0; r < q.rows(); ++r)
    for (Eigen::Index j = 0; j < x.rows(); ++j) {
      const double d2 = (q.row(r).cast<double>() - x.row(j).cast<double>()).squaredNorm();
      if (!(d2 < static_cast<double>(cutoff) * cutoff)) continue;
      const double w = std::exp(-0.5 * d2);
      out.row(r).head(dx) += w * x.row(j).cast<double>();
      if (dc) out.row(r).segment(dx, dc) += w * carried.row(j).cast<double>();
      out(r, dx + dc) += w;
    }
  return out;
}

/** Largest error of `got` against `ref`, relative to the sum of |w x| of each entry's row (the
 * scale at which float sums round). */
double worstError(const Eigen::MatrixXf& got, const Eigen::MatrixXd& ref,
                  const Eigen::MatrixXf& q) {
  double worst = 0.0;
  for (Eigen::Index r = 0; r < ref.rows(); ++r) {
    const double scale =
        ref(r, ref.cols() - 1) * (1.0 + q.row(r).cwiseAbs().maxCoeff() + 3.0) + 1e-12;
    for (Eigen::Index c = 0; c < ref.cols(); ++c)
      worst = std::max(worst, std::abs(static_cast<double>(got(r, c)) - ref(r, c)) / scale);
  }
  return worst;
}

}  // namespace

TEST(GpuGaussTransform, MatchesDoubleSumsOnTheCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  for (int d : {6, 30}) {
    // Clusters far apart: most (query block, tile) pairs are beyond the cutoff and skipped.
    const Eigen::MatrixXf x = clustered(5000, d, 8, 6.0f, 11);
    gpu::GaussTransform gt;
    gt.setData(x);
    EXPECT_EQ(gt.size(), 5000u);
    EXPECT_EQ(gt.distanceDims(), d);
    // Many queries (one split) and few (the data spread over many blocks).
    for (int nq : {3000, 17}) {
      // Few queries: all near one centre (every 8th point), so their box skips the others.
      Eigen::MatrixXf q(nq, d);
      for (int r = 0; r < nq; ++r) q.row(r) = x.row(nq < 128 ? 8 * r : r);
      q += (0.3f / std::sqrt(static_cast<float>(d))) * clustered(nq, d, 1, 0.0f, 5);
      Eigen::MatrixXf got;
      gt.evaluate(q, got);
      const Eigen::MatrixXd ref = reference(x, Eigen::MatrixXf(), q, 3.0f);
      ASSERT_EQ(got.rows(), nq);
      ASSERT_EQ(got.cols(), d + 1);
      const double err = worstError(got, ref, q);
      const auto& st = gt.lastStats();
      std::printf(
          "d=%d queries=%d: worst relative error %.2e, splits %d, tiles visited %lld, "
          "skipped %lld, min weight sum %.3f\n",
          d, nq, err, st.splits, st.tiles_visited, st.tiles_skipped, ref.col(d).minCoeff());
      EXPECT_LT(err, 1e-5);
      EXPECT_GT(ref.col(d).minCoeff(), 0.5);  // every query has terms: the test sums something
      EXPECT_GT(st.tiles_skipped, 0);
      if (nq < 128) {
        EXPECT_GT(st.splits, 1);
      }
    }
  }
}

TEST(GpuGaussTransform, CarriedCoordinatesAndCutoff) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const Eigen::MatrixXf x = clustered(2000, 5, 3, 3.0f, 3);
  const Eigen::MatrixXf carried = clustered(2000, 2, 1, 0.0f, 4);
  const Eigen::MatrixXf q = x.topRows(300);
  for (float cutoff : {1.5f, 3.0f}) {
    gpu::GaussTransform gt;
    gt.setData(x, carried, cutoff);
    EXPECT_EQ(gt.carriedDims(), 2);
    Eigen::MatrixXf got;
    gt.evaluate(q, got);
    const Eigen::MatrixXd ref = reference(x, carried, q, cutoff);
    ASSERT_EQ(got.cols(), 8);
    EXPECT_LT(worstError(got, ref, q), 1e-5) << "cutoff " << cutoff;
  }
}

TEST(GpuGaussTransform, BadInputIsAnError) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  gpu::GaussTransform gt;
  Eigen::MatrixXf out;
  EXPECT_THROW(gt.evaluate(Eigen::MatrixXf::Zero(2, 3), out), pcl_animseg::Error);
  EXPECT_THROW(gt.setData(Eigen::MatrixXf(0, 3)), pcl_animseg::Error);
  EXPECT_THROW(gt.setData(Eigen::MatrixXf::Zero(10, 65)), pcl_animseg::Error);
  EXPECT_THROW(gt.setData(Eigen::MatrixXf::Zero(10, 3), Eigen::MatrixXf::Zero(9, 2)),
               pcl_animseg::Error);
  Eigen::MatrixXf bad = Eigen::MatrixXf::Zero(10, 3);
  bad(4, 1) = std::nanf("");
  EXPECT_THROW(gt.setData(bad), pcl_animseg::Error);
  gt.setData(Eigen::MatrixXf::Zero(10, 3));
  EXPECT_THROW(gt.evaluate(Eigen::MatrixXf::Zero(2, 4), out), pcl_animseg::Error);
  EXPECT_THROW(gt.evaluate(bad, out), pcl_animseg::Error);
  gt.evaluate(Eigen::MatrixXf::Zero(0, 3), out);  // no queries: no sums
  EXPECT_EQ(out.rows(), 0);
  gt.evaluate(Eigen::MatrixXf::Zero(1, 3), out);  // ten points at the query: weight 10
  EXPECT_NEAR(out(0, 3), 10.0, 1e-5);
}

// The device's exact sums of the joint space with the keypoint pair rule (Eq. 5 between two
// keypoints, Eq. 6 otherwise) and a dimension of weight 0, against the rule summed in double.
TEST(GpuGaussTransform, ExactSumsFollowThePairRule) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const int n = 3000, d = 10;
  Eigen::MatrixXf z = clustered(n, d, 4, 2.0f, 21) * 0.1f;
  std::vector<char> key(n, 0);
  for (int i = 0; i < n; i += 7) key[i] = 1;
  Eigen::RowVectorXf plain = Eigen::RowVectorXf::Constant(d, 5.0f), pair = plain;
  pair.tail(4).setConstant(9.0f);
  plain[5] = pair[5] = 0.0f;  // carried along, outside the distance
  gpu::MeanShiftBackend backend;
  auto sums = backend.exactSums(z, plain, pair, key);
  ASSERT_TRUE(sums);
  const int nq = 400;
  Eigen::MatrixXf q = z.topRows(nq);
  std::vector<char> qkey(key.begin(), key.begin() + nq);
  std::vector<int> rows;
  for (int r = 0; r < nq; r += 2) rows.push_back(r);  // every other row: the rest untouched
  Eigen::MatrixXf out = Eigen::MatrixXf::Constant(nq, d + 1, -7.0f);
  sums->evaluate(q, rows, qkey, out);
  double worst = 0.0;
  for (int r = 0; r < nq; ++r) {
    if (r % 2) {
      EXPECT_EQ(out(r, 0), -7.0f);
      continue;
    }
    Eigen::VectorXd ref = Eigen::VectorXd::Zero(d + 1);
    for (int j = 0; j < n; ++j) {
      const Eigen::RowVectorXf& m = qkey[r] && key[j] ? pair : plain;
      const double d2 = (q.row(r) - z.row(j)).cwiseProduct(m).cast<double>().squaredNorm();
      if (!(d2 < 9.0)) continue;
      const double w = std::exp(-0.5 * d2);
      ref.head(d) += w * z.row(j).transpose().cast<double>();
      ref[d] += w;
    }
    for (int c = 0; c <= d; ++c)
      worst = std::max(worst, std::abs(out(r, c) - ref[c]) / (ref[d] + 1e-12));
  }
  std::printf("pair rule: worst error relative to the weight sum %.2e\n", worst);
  EXPECT_LT(worst, 1e-5);
}

// The mean-shift stage's exact backend on the device against the CPU's exact backend.
TEST(GpuGaussTransform, ExactBackendAgreesWithCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  pcl_animseg::synth::SynthParams sp;
  sp.plan = pcl_animseg::synth::BodyPlan::Humanoid;
  sp.frames = 4;
  sp.points = 900;
  sp.seed = 5;
  const auto sequence = std::make_shared<pcl_animseg::PointCloudSequence>(
      pcl_animseg::synth::toSequence(pcl_animseg::synth::generate(sp)));
  seg::MeanShiftParams mp;
  mp.method = seg::MeanShiftMethod::Paper;
  mp.backend = seg::MeanShiftBackend::Exact;
  mp.bandwidth = 0.15;
  auto run = [&](bool on_gpu, seg::SegmentationResult& r) {
    seg::MeanShiftSegmentation ms;
    ms.setInputSequence(sequence);
    ms.setParams(mp);
    if (on_gpu) ms.setDeviceBackend(std::make_shared<gpu::MeanShiftBackend>());
    ms.segment(r);
    std::vector<int> out;
    for (const auto& frame : r.labels) out.insert(out.end(), frame.begin(), frame.end());
    return std::make_pair(out, ms.deviceUsed());
  };
  seg::SegmentationResult rc, rg;
  const auto [cpu_labels, cpu_used] = run(false, rc);
  const auto [gpu_labels, gpu_used] = run(true, rg);
  const double ari = pcl_animseg::evaluation::adjustedRandIndex(cpu_labels, gpu_labels);
  std::printf("exact backend: %zu points, CPU %d clusters, GPU (%s) %d clusters, ARI %.4f\n",
              cpu_labels.size(), rc.num_clusters, gpu_used.c_str(), rg.num_clusters, ari);
  EXPECT_EQ(cpu_used, "cpu");
  EXPECT_NE(gpu_used, "cpu");
  EXPECT_GT(rc.num_clusters, 1);
  EXPECT_GE(ari, 0.99);
  ASSERT_EQ(rc.mode_density.size(), rg.mode_density.size());
  for (std::size_t c = 0; c < rc.mode_density.size(); ++c)
    EXPECT_NEAR(rg.mode_density[c], rc.mode_density[c], 1e-3 * rc.mode_density[c]);
}
