#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/math/gmm.h>

#include <algorithm>
#include <cmath>
#include <random>

using pcl_animseg::math::fitGMM;
using pcl_animseg::math::GaussianMixture;
using pcl_animseg::math::GMMOptions;

namespace {

// Samples `n` points from each of the given Gaussians (mean, per-axis sigma).
Eigen::MatrixX3d sampleMixture(const std::vector<Eigen::Vector3d>& means,
                               const std::vector<Eigen::Vector3d>& sigmas,
                               const std::vector<int>& counts, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  int total = 0;
  for (int c : counts) total += c;
  Eigen::MatrixX3d x(total, 3);
  int row = 0;
  for (std::size_t k = 0; k < means.size(); ++k)
    for (int i = 0; i < counts[k]; ++i, ++row)
      for (int d = 0; d < 3; ++d) x(row, d) = means[k][d] + sigmas[k][d] * g(rng);
  return x;
}

}  // namespace

TEST(GMM, RecoversWellSeparatedComponents) {
  const std::vector<Eigen::Vector3d> means = {{0, 0, 1}, {1, 0, 0}, {0, 1, 0}, {-0.7, -0.7, 0}};
  const std::vector<Eigen::Vector3d> sigmas = {
      {0.05, 0.05, 0.02}, {0.02, 0.08, 0.03}, {0.04, 0.04, 0.04}, {0.03, 0.03, 0.06}};
  const std::vector<int> counts = {400, 300, 200, 100};
  const Eigen::MatrixX3d x = sampleMixture(means, sigmas, counts, 7);
  const GaussianMixture gmm = fitGMM(x, 4, 200, 3);
  ASSERT_EQ(gmm.size(), 4);
  EXPECT_TRUE(gmm.converged);
  for (std::size_t k = 0; k < means.size(); ++k) {
    // The fitted component nearest to each true mean matches it in mean, spread and weight.
    int best = 0;
    for (int c = 1; c < 4; ++c)
      if ((gmm.means[c] - means[k]).norm() < (gmm.means[best] - means[k]).norm()) best = c;
    EXPECT_LT((gmm.means[best] - means[k]).norm(), 0.02) << "component " << k;
    for (int d = 0; d < 3; ++d)
      EXPECT_NEAR(std::sqrt(gmm.covariances[best](d, d)), sigmas[k][d],
                  0.25 * sigmas[k][d] + 0.005);
    EXPECT_NEAR(gmm.weights[best], counts[k] / 1000.0, 0.02);
  }
}

TEST(GMM, DeterministicForASeed) {
  const Eigen::MatrixX3d x =
      sampleMixture({{0, 0, 0}, {1, 1, 1}}, {{0.3, 0.3, 0.3}, {0.3, 0.3, 0.3}}, {150, 150}, 11);
  const GaussianMixture a = fitGMM(x, 4, 50, 5);
  const GaussianMixture b = fitGMM(x, 4, 50, 5);
  ASSERT_EQ(a.size(), b.size());
  for (int c = 0; c < a.size(); ++c) EXPECT_EQ(a.means[c], b.means[c]);
  EXPECT_EQ(a.log_likelihood, b.log_likelihood);
}

TEST(GMM, ClassifiesBetterThanChanceAndLikelihoodIsNormalised) {
  // Two mixtures over clearly different normal directions: each point scores higher under its own.
  const Eigen::MatrixX3d f = sampleMixture({{0, 0, 1}}, {{0.05, 0.05, 0.01}}, {300}, 1);
  const Eigen::MatrixX3d b = sampleMixture({{1, 0, 0}}, {{0.01, 0.05, 0.05}}, {300}, 2);
  const GaussianMixture gf = fitGMM(f, 4, 100, 1);
  const GaussianMixture gb = fitGMM(b, 4, 100, 1);
  int right = 0;
  for (int i = 0; i < 300; ++i) {
    right += gf.logPdf(f.row(i).transpose()) > gb.logPdf(f.row(i).transpose());
    right += gb.logPdf(b.row(i).transpose()) > gf.logPdf(b.row(i).transpose());
  }
  EXPECT_EQ(right, 600);
  // The density integrates to ~1: Monte Carlo over a box around a single wide Gaussian.
  const Eigen::MatrixX3d w = sampleMixture({{0, 0, 0}}, {{1, 1, 1}}, {2000}, 3);
  const GaussianMixture gw = fitGMM(w, 1, 50, 0);
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-6.0, 6.0);
  double sum = 0.0;
  const int samples = 200000;
  for (int i = 0; i < samples; ++i)
    sum += std::exp(gw.logPdf(Eigen::Vector3d(u(rng), u(rng), u(rng))));
  EXPECT_NEAR(sum / samples * 12.0 * 12.0 * 12.0, 1.0, 0.05);
  const Eigen::VectorXd r = gf.responsibilities(Eigen::Vector3d(0, 0, 1));
  EXPECT_NEAR(r.sum(), 1.0, 1e-9);
}

TEST(GMM, DegenerateInputs) {
  // Identical points (a flat patch: every normal equal) must not give a singular covariance.
  Eigen::MatrixX3d same(50, 3);
  same.rowwise() = Eigen::RowVector3d(0, 0, 1);
  const GaussianMixture g = fitGMM(same, 4, 20, 0);
  EXPECT_GE(g.size(), 1);
  EXPECT_TRUE(std::isfinite(g.logPdf(Eigen::Vector3d(0, 0, 1))));
  // Fewer points than components.
  Eigen::MatrixX3d two(2, 3);
  two << 0, 0, 1, 1, 0, 0;
  EXPECT_LE(fitGMM(two, 4, 20, 0).size(), 2);
  EXPECT_THROW(fitGMM(Eigen::MatrixX3d(0, 3), 4, 20, 0), pcl_animseg::Error);
  GMMOptions bad;
  bad.regularization = 0.0;
  EXPECT_THROW(fitGMM(two, bad), pcl_animseg::Error);
}

// gmm_em's own exp and log (the same bits on the CPU and a GPU) against the C++ library's: within
// 2 ulp over EM's range (exp of -700..0, log of 1e-300..1e300, subnormals too), exact where
// the result is (exp(0) = 1, log(1) = 0), and the edges: exp(-inf) = 0, exp(nan) is nan,
// log(0) = -inf, log of a negative number is nan.
TEST(GMM, OwnExpAndLogAreWithinTwoUlp) {
  namespace em = pcl_animseg::math::gmm_em;
  auto ulps = [](double a, double b) {
    if (a == b) return 0.0;
    return std::fabs(a - b) / (std::nextafter(std::fabs(b), INFINITY) - std::fabs(b));
  };
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> ex(-700.0, 0.0), ex_pos(0.0, 709.0), lg(-690.0, 690.0);
  double worst_exp = 0.0, worst_log = 0.0;
  for (int i = 0; i < 200000; ++i) {
    const double x = i % 8 == 7 ? ex_pos(rng) : ex(rng);
    worst_exp = std::max(worst_exp, ulps(em::exp(x), std::exp(x)));
    const double y = std::exp(lg(rng));
    worst_log = std::max(worst_log, ulps(em::log(y), std::log(y)));
  }
  for (double y : {4.9e-324, 1e-310, 2.2e-308, 0.5, 0.7071067811865476, 1.4142135623730951, 2.0})
    worst_log = std::max(worst_log, ulps(em::log(y), std::log(y)));
  EXPECT_LE(worst_exp, 2.0);
  EXPECT_LE(worst_log, 2.0);
  EXPECT_GT(worst_exp + worst_log, 0.0);  // not the library's own (else the point is moot)
  EXPECT_EQ(em::exp(0.0), 1.0);
  EXPECT_EQ(em::log(1.0), 0.0);
  EXPECT_EQ(em::exp(-INFINITY), 0.0);
  EXPECT_TRUE(std::isnan(em::exp(NAN)));
  EXPECT_EQ(em::log(0.0), -INFINITY);
  EXPECT_TRUE(std::isnan(em::log(-1.0)));
  EXPECT_EQ(em::exp(710.0), INFINITY);
}
