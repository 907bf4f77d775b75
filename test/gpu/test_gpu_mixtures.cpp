// gpu::RigidFits::fitMixtures against math::gmmEM on the cores: the same bits for every number of
// every fit (weights, means, covariances, precisions, log normalisers, log-likelihood, iterations,
// convergence), on unit normals in a few clusters as the refinement fits them, for fits of 5 to
// 1200 points, fits that converge and fits that run to the iteration cap, and a fit whose points
// are fewer than its components. Skips when no usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/rigid_fits.h>
#include <pcl_animseg/math/gmm.h>

#include <limits>
#include <random>
#include <string>
#include <vector>

namespace gpu = pcl_animseg::gpu;
namespace math = pcl_animseg::math;

namespace {

// n unit normals around `clusters` directions, spread `spread`.
Eigen::MatrixX3d normals(unsigned seed, int n, int clusters, double spread) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::vector<Eigen::Vector3d> dirs;
  for (int c = 0; c < clusters; ++c)
    dirs.push_back(Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized());
  Eigen::MatrixX3d x(n, 3);
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d v =
        (dirs[i % clusters] + spread * Eigen::Vector3d(g(rng), g(rng), g(rng))).normalized();
    x.row(i) = v.transpose();
  }
  return x;
}

bool same(const math::GaussianMixture& a, const math::GaussianMixture& b) {
  if (a.size() != b.size() || a.log_likelihood != b.log_likelihood ||
      a.iterations != b.iterations || a.converged != b.converged)
    return false;
  for (int c = 0; c < a.size(); ++c)
    if (a.weights[c] != b.weights[c] || a.means[c] != b.means[c] ||
        a.covariances[c] != b.covariances[c] || a.precisions[c] != b.precisions[c] ||
        a.log_norms[c] != b.log_norms[c])
      return false;
  return true;
}

}  // namespace

TEST(GpuMixtures, SameFitsAsTheCores) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  std::vector<Eigen::MatrixX3d> xs;
  const int sizes[] = {5, 37, 120, 300, 700, 1200};
  for (int s = 0; s < 6; ++s)
    for (int rep = 0; rep < 8; ++rep)
      xs.push_back(normals(100 * s + rep, sizes[s], 2 + rep % 4, 0.05 + 0.05 * (rep % 3)));
  // Three distinct points only: fewer than the 4 components.
  Eigen::MatrixX3d few(30, 3);
  for (int i = 0; i < 30; ++i) few.row(i) = Eigen::RowVector3d(i % 3 == 0, i % 3 == 1, i % 3 == 2);
  xs.push_back(few);
  // -inf: no fit converges, every one runs to the cap.
  for (double tolerance : {1e-6, -std::numeric_limits<double>::infinity()}) {
    math::GMMOptions o;
    o.components = 4;
    o.max_iterations = 50;
    o.tolerance = tolerance;
    o.regularization = 1e-4;
    std::vector<math::GaussianMixture> cpu(xs.size()), dev(xs.size());
    std::vector<pcl_animseg::segmentation::MixtureFitJob> jobs;
    for (std::size_t j = 0; j < xs.size(); ++j) {
      o.seed = static_cast<unsigned>(j);
      cpu[j] = dev[j] = math::gmmStart(xs[j], o);
      math::gmmEM(xs[j], o, cpu[j]);
      jobs.push_back({&xs[j], &dev[j]});
    }
    gpu::RigidFits device;
    ASSERT_TRUE(device.fitMixtures(jobs, o));
    int differ = 0, converged = 0, capped = 0;
    for (std::size_t j = 0; j < xs.size(); ++j) {
      differ += !same(cpu[j], dev[j]);
      converged += cpu[j].converged;
      capped += cpu[j].iterations == o.max_iterations;
    }
    EXPECT_EQ(differ, 0) << differ << " of " << xs.size() << " fits differ (tolerance " << tolerance
                         << ")";
    if (tolerance > 0.0)
      EXPECT_GT(converged, 0);
    else
      EXPECT_EQ(capped, static_cast<int>(xs.size()));
    EXPECT_LE(cpu.back().size(), 3);  // the three points' fit
  }
  // More components than the device takes: declined (the caller fits on the cores); a job
  // without points: an error.
  math::GMMOptions nine;
  nine.components = 9;
  Eigen::MatrixX3d many = normals(7, 200, 9, 0.1);
  math::GaussianMixture g = math::gmmStart(many, nine);
  gpu::RigidFits device;
  EXPECT_FALSE(device.fitMixtures({{&many, &g}}, nine));
  Eigen::MatrixX3d none(0, 3);
  EXPECT_THROW(device.fitMixtures({{&none, &g}}, nine), pcl_animseg::Error);
}
