#include <pcl_animseg/error.h>
#include <pcl_animseg/math/gmm.h>
#include <pcl_animseg/math/gmm_em.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>

namespace pcl_animseg {
namespace math {

namespace {

// log(sum_i exp(v[i])) as m + log(s), m the largest v[i] and s the sum of exp(v[i] - m); m
// itself where it is not finite. (The EM's own is gmm_em::responsibilities.)
double logSumExp(const double* v, int n) {
  double m = -std::numeric_limits<double>::infinity();
  for (int i = 0; i < n; ++i) m = std::max(m, v[i]);
  if (!std::isfinite(m)) return m;
  double s = 0.0;
  for (int i = 0; i < n; ++i) s += std::exp(v[i] - m);
  return m + std::log(s);
}

// k-means++ seeding (Arthur & Vassilvitskii): spreads the initial means so that EM starts
// near a good optimum; with std::mt19937 and our own uniform draw it is reproducible.
std::vector<Eigen::Vector3d> kmeansPlusPlus(const Eigen::MatrixX3d& x, int k, std::mt19937& rng) {
  const Eigen::Index n = x.rows();
  auto uniform = [&rng]() { return (rng() + 0.5) / 4294967296.0; };
  std::vector<Eigen::Vector3d> centers;
  centers.push_back(x.row(static_cast<Eigen::Index>(uniform() * n) % n).transpose());
  std::vector<double> d2(n);
  for (Eigen::Index i = 0; i < n; ++i) d2[i] = (x.row(i).transpose() - centers[0]).squaredNorm();
  while (static_cast<int>(centers.size()) < k) {
    double total = 0.0;
    for (double v : d2) total += v;
    if (total <= 0.0) break;  // fewer distinct points than k
    double r = uniform() * total;
    Eigen::Index pick = n - 1;
    for (Eigen::Index i = 0; i < n; ++i) {
      r -= d2[i];
      if (r <= 0.0) {
        pick = i;
        break;
      }
    }
    centers.push_back(x.row(pick).transpose());
    for (Eigen::Index i = 0; i < n; ++i)
      d2[i] = std::min(d2[i], (x.row(i).transpose() - centers.back()).squaredNorm());
  }
  return centers;
}

// A mixture's numbers into gmm_em's layout and back (the cache included).
template <int K>
void toEm(const GaussianMixture& g, gmm_em::Mixture<K>& m) {
  m.k = g.size();
  for (int c = 0; c < m.k; ++c) {
    m.w[c] = g.weights[c];
    for (int d = 0; d < 3; ++d) m.mu[c][d] = g.means[c][d];
    const Eigen::Matrix3d& s = g.covariances[c];
    const double cv[6] = {s(0, 0), s(1, 1), s(2, 2), s(0, 1), s(0, 2), s(1, 2)};
    for (int d = 0; d < 6; ++d) m.cov[c][d] = cv[d];
    if (static_cast<int>(g.precisions.size()) == m.k) {
      const Eigen::Matrix3d& q = g.precisions[c];
      const double pr[6] = {q(0, 0), q(1, 1), q(2, 2), 2.0 * q(0, 1), 2.0 * q(0, 2), 2.0 * q(1, 2)};
      for (int d = 0; d < 6; ++d) m.pr[c][d] = pr[d];
      m.lnorm[c] = g.log_norms[c];
    }
  }
}

template <int K>
void fromEm(const gmm_em::Mixture<K>& m, GaussianMixture& g) {
  g.weights.assign(m.k, 0.0);
  g.means.assign(m.k, Eigen::Vector3d::Zero());
  g.covariances.assign(m.k, Eigen::Matrix3d::Zero());
  g.precisions.assign(m.k, Eigen::Matrix3d::Zero());
  g.log_norms.assign(m.k, 0.0);
  for (int c = 0; c < m.k; ++c) {
    g.weights[c] = m.w[c];
    g.means[c] = Eigen::Vector3d(m.mu[c][0], m.mu[c][1], m.mu[c][2]);
    const double* v = m.cov[c];
    g.covariances[c] << v[0], v[3], v[4], v[3], v[1], v[5], v[4], v[5], v[2];
    const double* q = m.pr[c];  // the off-diagonal entries doubled: halved exactly
    g.precisions[c] << q[0], 0.5 * q[3], 0.5 * q[4], 0.5 * q[3], q[1], 0.5 * q[5], 0.5 * q[4],
        0.5 * q[5], q[2];
    g.log_norms[c] = m.lnorm[c];
  }
}

[[noreturn]] void notPositiveDefinite(int c) {
  throw Error("GMM component " + std::to_string(c) +
              " has a covariance that is not positive "
              "definite; increase the regularization");
}

}  // namespace

void updateGMMCache(GaussianMixture& gmm) {
  if (gmm.size() > gmm_em::kMaxComponents)
    throw Error("GMM components must be at most " + std::to_string(gmm_em::kMaxComponents));
  gmm_em::Mixture<gmm_em::kMaxComponents> m;
  toEm(gmm, m);
  const int bad = gmm_em::cache(m);
  if (bad >= 0) notPositiveDefinite(bad);
  fromEm(m, gmm);
}

void toDeviceMixture(const GaussianMixture& g, gmm_em::Mixture<gmm_em::kMaxDeviceComponents>& m) {
  if (g.size() > gmm_em::kMaxDeviceComponents)
    throw Error("a device's GMM takes at most " + std::to_string(gmm_em::kMaxDeviceComponents) +
                " components");
  toEm(g, m);
}

void fromDeviceMixture(const gmm_em::Mixture<gmm_em::kMaxDeviceComponents>& m, GaussianMixture& g) {
  fromEm(m, g);
}

double GaussianMixture::logPdf(const Eigen::Vector3d& x) const {
  double v[64];
  const int k = std::min(size(), 64);
  for (int c = 0; c < k; ++c) {
    const Eigen::Vector3d d = x - means[c];
    v[c] = log_norms[c] - 0.5 * d.dot(precisions[c] * d);
  }
  return logSumExp(v, k);
}

Eigen::VectorXd GaussianMixture::responsibilities(const Eigen::Vector3d& x) const {
  Eigen::VectorXd v(size());
  for (int c = 0; c < size(); ++c) {
    const Eigen::Vector3d d = x - means[c];
    v[c] = log_norms[c] - 0.5 * d.dot(precisions[c] * d);
  }
  const double lse = logSumExp(v.data(), size());
  return (v.array() - lse).exp().matrix();
}

GaussianMixture gmmStart(const Eigen::MatrixX3d& x, const GMMOptions& options) {
  const Eigen::Index n = x.rows();
  if (n == 0) throw Error("cannot fit a Gaussian mixture to zero points");
  if (options.components < 1 || options.components > 64)
    throw Error("GMM components must be between 1 and 64 (got " +
                std::to_string(options.components) + ")");
  if (!(options.regularization > 0.0)) throw Error("GMM regularization must be positive");
  std::mt19937 rng(options.seed);
  const int k_wanted = static_cast<int>(std::min<Eigen::Index>(options.components, n));
  const std::vector<Eigen::Vector3d> centers = kmeansPlusPlus(x, k_wanted, rng);
  const int k = static_cast<int>(centers.size());
  const Eigen::Matrix3d reg = options.regularization * Eigen::Matrix3d::Identity();

  // Global covariance: the fallback for a component that owns too few points to estimate one.
  const Eigen::RowVector3d mean_all = x.colwise().mean();
  const Eigen::MatrixX3d centred_all = x.rowwise() - mean_all;
  const Eigen::Matrix3d cov_all =
      centred_all.transpose() * centred_all / static_cast<double>(n) + reg;

  GaussianMixture gmm;
  gmm.weights.assign(k, 0.0);
  gmm.means = centers;
  gmm.covariances.assign(k, Eigen::Matrix3d::Zero());
  {
    // Initial parameters from the hard nearest-centre partition.
    std::vector<Eigen::Vector3d> sum(k, Eigen::Vector3d::Zero());
    std::vector<Eigen::Matrix3d> sq(k, Eigen::Matrix3d::Zero());
    std::vector<double> count(k, 0.0);
    for (Eigen::Index i = 0; i < n; ++i) {
      const Eigen::Vector3d p = x.row(i).transpose();
      int best = 0;
      double bd = std::numeric_limits<double>::infinity();
      for (int c = 0; c < k; ++c) {
        const double d = (p - centers[c]).squaredNorm();
        if (d < bd) {
          bd = d;
          best = c;
        }
      }
      sum[best] += p;
      sq[best] += p * p.transpose();
      count[best] += 1.0;
    }
    for (int c = 0; c < k; ++c) {
      gmm.weights[c] = std::max(count[c], 1.0) / static_cast<double>(n);
      if (count[c] >= 2.0) {
        gmm.means[c] = sum[c] / count[c];
        gmm.covariances[c] = sq[c] / count[c] - gmm.means[c] * gmm.means[c].transpose() + reg;
      } else {
        gmm.covariances[c] = cov_all;
      }
    }
    double wsum = 0.0;
    for (double w : gmm.weights) wsum += w;
    for (double& w : gmm.weights) w /= wsum;
  }
  updateGMMCache(gmm);
  return gmm;
}

void gmmEM(const Eigen::MatrixX3d& x, const GMMOptions& options, GaussianMixture& gmm) {
  const Eigen::Index n = x.rows();
  const int k = gmm.size();
  if (n == 0 || k < 1 || k > gmm_em::kMaxComponents)
    throw Error("GMM EM: no points, or no components or more than " +
                std::to_string(gmm_em::kMaxComponents));
  // EM over the points in one row-major array, gmm_em's arithmetic point by point, the sums in
  // point order (a device's fit adds in the same order: the same bits). The refinement's 1300
  // fits at 800k spent 0.05 s of 16 cores here.
  gmm_em::Mixture<gmm_em::kMaxComponents> m;
  toEm(gmm, m);
  std::vector<double> px(static_cast<std::size_t>(n) * 3);
  for (Eigen::Index i = 0; i < n; ++i)
    for (int d = 0; d < 3; ++d) px[3 * i + d] = x(i, d);
  std::vector<double> resp(static_cast<std::size_t>(n) * k);  // row-major: point i's k values
  double prev = -std::numeric_limits<double>::infinity();
  for (int it = 0; it < options.max_iterations; ++it) {
    // E step (log domain, so far-away points do not underflow to 0/0).
    double ll = 0.0;
    for (Eigen::Index i = 0; i < n; ++i)
      ll += gmm_em::responsibilities(m, &px[3 * i], &resp[static_cast<std::size_t>(i) * k]);
    ll /= static_cast<double>(n);
    gmm.log_likelihood = ll;
    gmm.iterations = it + 1;
    if (ll - prev < options.tolerance && it > 0) {
      gmm.converged = true;
      break;
    }
    prev = ll;
    // M step: each component's weight and mean, then its covariance about that mean.
    double nk[gmm_em::kMaxComponents] = {}, sx[gmm_em::kMaxComponents][3] = {};
    for (Eigen::Index i = 0; i < n; ++i)
      gmm_em::addMeans(k, &px[3 * i], &resp[static_cast<std::size_t>(i) * k], nk, sx);
    gmm_em::newMeans(m, nk, sx);
    double sc[gmm_em::kMaxComponents][6] = {};
    for (Eigen::Index i = 0; i < n; ++i)
      gmm_em::addScatter(k, &px[3 * i], &resp[static_cast<std::size_t>(i) * k], m.mu, sc);
    const int bad =
        gmm_em::newCovariances(m, nk, sc, static_cast<double>(n), options.regularization);
    if (bad >= 0) notPositiveDefinite(bad);
  }
  fromEm(m, gmm);
}

GaussianMixture fitGMM(const Eigen::MatrixX3d& x, const GMMOptions& options) {
  GaussianMixture gmm = gmmStart(x, options);
  gmmEM(x, options, gmm);
  return gmm;
}

GaussianMixture fitGMM(const Eigen::MatrixX3d& points, int components, int max_iterations,
                       unsigned seed) {
  GMMOptions o;
  o.components = components;
  o.max_iterations = max_iterations;
  o.seed = seed;
  return fitGMM(points, o);
}

}  // namespace math
}  // namespace pcl_animseg
