#pragma once
/** \file gmm.h Gaussian mixture models in 3-D fitted by EM (free functions, Eigen in and out).
 *
 * The boundary refinement (Sect. 4 of the paper) models the normals of a small band with a
 * 4-component GMM. None of our dependencies offers GMM/EM (PCL, Eigen, FLANN, Boost; OpenCV's
 * cv::ml::EM is not a dependency), and the models are tiny (3-D, K = 4, a few hundred points),
 * so a small EM written out by hand (Eigen types in and out) is both the simplest and the
 * fastest option.
 */
#include <pcl_animseg/math/gmm_em.h>

#include <Eigen/Core>
#include <vector>

namespace pcl_animseg {
namespace math {

/** \brief Knobs of fitGMM. */
struct GMMOptions {
  int components = 4;        ///< K (the paper uses 4 per band)
  int max_iterations = 100;  ///< EM iterations at most
  double tolerance = 1e-6;   ///< stop when the mean log-likelihood gains less than this
  /** Added to every covariance's diagonal after each M step. Keeps a component on a flat patch
   * (all normals equal, zero variance) from collapsing to a singular covariance. */
  double regularization = 1e-4;
  unsigned seed = 0;  ///< seed of the k-means++ initialisation
};

/** \brief A fitted mixture: weights, means and full covariances of K 3-D Gaussians. */
struct GaussianMixture {
  std::vector<double> weights;
  std::vector<Eigen::Vector3d> means;
  std::vector<Eigen::Matrix3d> covariances;
  /** Inverse covariances and log normalisers (log w_k - 0.5 log|2π Σ_k|), cached for logPdf. */
  std::vector<Eigen::Matrix3d> precisions;
  std::vector<double> log_norms;
  /** Mean log-likelihood per point of the training data at the end. */
  double log_likelihood = 0.0;
  int iterations = 0;
  bool converged = false;

  int size() const { return static_cast<int>(weights.size()); }
  /** \brief log p(x) of the mixture (log-sum-exp over components). */
  double logPdf(const Eigen::Vector3d& x) const;
  /** \brief Posterior responsibilities of the components for x (sums to 1). */
  Eigen::VectorXd responsibilities(const Eigen::Vector3d& x) const;
};

/** \brief Fits a K-component GMM with full covariances to the rows of `points` (N x 3) by EM,
 * initialised by k-means++ seeding (deterministic for a seed). K is reduced to the number of
 * distinct points when there are fewer; throws pcl_animseg::Error for an empty input. */
GaussianMixture fitGMM(const Eigen::MatrixX3d& points, const GMMOptions& options = GMMOptions());

/** \brief Convenience overload with the common knobs. */
GaussianMixture fitGMM(const Eigen::MatrixX3d& points, int components, int max_iterations = 100,
                       unsigned seed = 0);

/** \brief Recomputes the cached precisions and log normalisers after editing a mixture (gmm_em's
 * arithmetic: a 3x3 Cholesky factor, our own log); throws pcl_animseg::Error where a covariance
 * is not positive definite or there are more than 64 components. */
void updateGMMCache(GaussianMixture& gmm);

/** \brief fitGMM's start: the k-means++ seeds, the weights, means and covariances of the nearest
 * seed's points, and their cache. fitGMM is gmmStart, then gmmEM. */
GaussianMixture gmmStart(const Eigen::MatrixX3d& points, const GMMOptions& options);

/** \brief fitGMM's EM from `gmm` (gmmStart's) on the points, on the cores (gmm_em.h's arithmetic,
 * the sums in point order: a device's fits give the same bits). */
void gmmEM(const Eigen::MatrixX3d& points, const GMMOptions& options, GaussianMixture& gmm);

/** \brief A mixture of at most gmm_em::kMaxDeviceComponents components in gmm_em's layout (its
 * cache included), for a device's fits; throws pcl_animseg::Error for more components. */
void toDeviceMixture(const GaussianMixture& g, gmm_em::Mixture<gmm_em::kMaxDeviceComponents>& out);
/** \brief The mixture back from gmm_em's layout (weights, means, covariances and cache; the
 * log-likelihood, iterations and convergence are the caller's). */
void fromDeviceMixture(const gmm_em::Mixture<gmm_em::kMaxDeviceComponents>& in, GaussianMixture& g);

}  // namespace math
}  // namespace pcl_animseg
