#pragma once
/** \file signature.h The local signature sigma(p, n, h) of Eq. 2-3, for every point of a frame. */
#include <pcl_animseg/features/neighbourhood.h>
#include <pcl_animseg/point_types.h>
#include <pcl_animseg/sequence.h>

#include <pcl/PCLPointCloud2.h>

#include <Eigen/Core>

#include <complex>
#include <memory>
#include <vector>

namespace pcl_animseg {

/** \brief Sizes of the signature: R x S disc samples, R' x S' kept Fourier magnitudes.
 *
 * Eq. 2 samples xi_kl = p + (2 l h / R)(cos(2 pi k / S) u + sin(2 pi k / S) v): the radius
 * index runs over R rings (out to 2h) and the angle index over S directions. (The paper's
 * index ranges "k = 1..R, l = 1..S" are swapped with respect to its own formula; we follow the
 * formula, as in Li and Guskov [17], whose statement "invariant to the choice of u and v if S is
 * sufficiently large" only makes sense with S angular.) */
struct SignatureLayout {
  int radial = 32;           ///< R: rings
  int angular = 8;           ///< S: directions per ring
  int radial_freqs = 6;      ///< R'
  int angular_freqs = 4;     ///< S'
  int dimension() const { return radial_freqs * angular_freqs; }
  /** \brief Throws Error unless 1 <= R' <= R, 1 <= S' <= S/2 + 1, S >= 2. */
  void validate() const;
};

/** \brief Evaluates sigma at single points; holds the DFT tables (build once, use from many
 * threads: compute() is const and needs only the caller's scratch buffer).
 *
 * The normal of the surface at each sample is that of a weighted least-squares cubic height field
 * z(a, b) fitted, in the frame (u, v, n), to the neighbours within the disc (Gaussian weights
 * exp(-2 r^2 / rho^2), rho = 2h). This is the "normal at the sample point" of a surface smoothed
 * at scale h without a kd-tree query per sample (R*S = 256 queries per point would cost more
 * than all the other stages together), and it is exactly covariant under rotations of (u, v),
 * rigid motions and uniform scaling. The fit falls back to a quadric, then a plane, when the
 * disc holds fewer than 16, then 8 points, and gives a zero signature with fewer than 3.
 *
 * s_kl is the fitted normal at xi_kl dotted with the unit direction from p to xi_kl (on the
 * fitted surface). The transform is a hand-written 2-D DFT (separable: along the angle, then the
 * radius; R, S are small so tables beat an FFT): s~(a, m) = sum_l sum_k s_lk e^{-2 pi i (a l / R
 * + m k / S)}, and sigma = |s~(a, m)| / (R S) for a < R', m < S'. A rotation of (u, v) by a
 * multiple of 2 pi / S only multiplies s~(a, m) by a phase, so the magnitudes are invariant;
 * for other angles, up to the (small) energy of angular frequencies above S - S'. Layout of sigma:
 * index a * S' + m (radial frequency major). */
class DiscSignature {
 public:
  explicit DiscSignature(const SignatureLayout& layout = SignatureLayout());
  const SignatureLayout& layout() const { return layout_; }
  /** \brief sigma at p with normal n and first tangent u (unit, orthogonal to n) over the points
   * `positions[idx[0..count)]`, disc radius rho = 2h. Writes layout().dimension() floats. */
  void compute(const PointCloudSequence::Cloud& positions, const int* idx, int count,
               const Eigen::Vector3f& p, const Eigen::Vector3f& n, const Eigen::Vector3f& u,
               double radius, float* out, std::vector<std::complex<double>>& scratch) const;
  /** \brief The sample and DFT tables, one after the other: the nine monomials a, b, a2, ab, b2,
   * a3, a2b, ab2, b3 of the R S samples (q = k R + l), then the angular cosines and sines
   * (S' x S each), then the radial ones (R' x R each). For the GPU's signature kernel. */
  std::vector<float> tables() const;

 private:
  SignatureLayout layout_;
  // The R x S sample positions (a, b) of the unit disc and their monomials up to degree 3, one
  // array per monomial, sample q = k R + l (angle major, so a ring's samples are strided and a
  // direction's are contiguous): the per-point work is then a few vectorisable passes.
  std::vector<float> a_, b_, aa_, ab_, bb_, aaa_, aab_, abb_, bbb_;
  std::vector<float> ang_cos_, ang_sin_;  // S' x S: e^{-2 pi i m k / S}
  std::vector<float> rad_cos_, rad_sin_;  // R' x R: e^{-2 pi i a l / R}
};

/** \brief A unit tangent orthogonal to n chosen from n alone (any choice is fine: sigma does not
 * depend on it, see DiscSignature). */
Eigen::Vector3f defaultTangent(const Eigen::Vector3f& n);

/** \brief Computes sigma(p, n, h) (Eq. 3) for every point of a frame at one scale h, with the
 * keypoints flagged. Input: the frame (positions and normals; normally level 0 of the scale
 * space). Every point gets a signature at the same h so that the mean shift compares like with
 * like; h is given in world units (the pipeline passes a multiple of the frame's spacing, which
 * is what makes sigma invariant to uniform scaling). OpenMP over points. */
class SignatureEstimation {
 public:
  using Cloud = PointCloudSequence::Cloud;
  using Ptr = std::shared_ptr<SignatureEstimation>;
  using ConstPtr = std::shared_ptr<const SignatureEstimation>;

  void setInputCloud(const Cloud::ConstPtr& cloud) { input_ = cloud; }
  const Cloud::ConstPtr& getInputCloud() const { return input_; }
  /** \brief Neighbourhoods of the input to reuse (their radius must be >= 2h); searched anew
   * when not set or too small. */
  void setNeighbourhoods(const std::shared_ptr<const Neighbourhoods>& nb) { neighbourhoods_ = nb; }
  /** \brief Scale h (world units); the disc of Eq. 2 has radius 2h. */
  void setScale(double h) { h_ = h; }
  double getScale() const { return h_; }
  void setLayout(const SignatureLayout& layout) { layout_ = layout; }
  const SignatureLayout& getLayout() const { return layout_; }
  /** \brief Indices of the keypoints (flagged in the PCD output). */
  void setKeypoints(const std::vector<int>& keypoints) { keypoints_ = keypoints; }
  const std::vector<int>& getKeypoints() const { return keypoints_; }
  /** \brief At most this many disc points enter a fit; denser discs are thinned evenly over
   * the distance-sorted neighbours (keeps the radial distribution, bounds the cost). */
  void setMaxFitPoints(int m) { max_fit_points_ = m; }
  int getMaxFitPoints() const { return max_fit_points_; }

  /** \brief N x D signatures, row j for point j. Throws Error on bad parameters. */
  void compute(Eigen::MatrixXf& signatures) const;

 private:
  Cloud::ConstPtr input_;
  std::shared_ptr<const Neighbourhoods> neighbourhoods_;
  double h_ = 0.0;
  SignatureLayout layout_;
  std::vector<int> keypoints_;
  int max_fit_points_ = 96;
};

/** \brief A PCD-ready cloud: x y z of `cloud`, the signature as one field `signature` with D
 * values, and an int field `keypoint` (1 for the given keypoints). Works for any D. */
pcl::PCLPointCloud2 signatureCloud(const PointCloudSequence::Cloud& cloud,
                                   const Eigen::MatrixXf& signatures,
                                   const std::vector<int>& keypoints);

/** \brief The same in the registered 24-D type (requires D == 24). */
pcl::PointCloud<PointSignature24> signatureCloud24(const PointCloudSequence::Cloud& cloud,
                                                   const Eigen::MatrixXf& signatures,
                                                   const std::vector<int>& keypoints);

}  // namespace pcl_animseg
