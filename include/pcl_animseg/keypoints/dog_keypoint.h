#pragma once
/** \file dog_keypoint.h Multi-scale feature points: extrema of the level difference (Sec. 3.1). */
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/point_types.h>

#include <pcl/point_cloud.h>

#include <memory>
#include <vector>

namespace pcl_animseg {

/** \brief Detects the scale-space extrema of the normal difference between adjacent levels.
 *
 * "Normal difference" is read as in Li and Guskov [17]: the displacement between two adjacent
 * levels along the normal, D_i(x) = n_i(x) . (L(x, h_{i+1}) - L(x, h_i)) / h_i (Eq. 1 projected
 * on the normal). Dividing by h_i makes D dimensionless, hence invariant to a uniform scaling, and
 * scale-normalised like SIFT's DoG (a feature of size w responds most at h ~ w). It is signed:
 * smoothing moves a bump inwards and a dent outwards, so bumps are minima and dents maxima.
 *
 * D is taken relative to its median over the frame on each level (the contrast): the overall
 * curvature of the object adds to every point a D that grows with the scale, and features are
 * what stands out of it. A point j is a keypoint at level i (1 <= i <= levels - 2) when D_i(j) is
 * larger (or smaller) than D at all its neighbours (within 2 h_0) on level i and at them and
 * itself on levels i-1 and i+1 (only i-1 for the top level; ties go to the lower index, so one of
 * two duplicate points can still be a keypoint), and |D_i(j)| >= the minimum response (SIFT's
 * contrast threshold). Then, as SIFT does with its 3x3 pixel Hessian, a quadratic D(a, b) is
 * fitted by weighted least squares, over the neighbourhood in the tangent plane (a, b) of the
 * point, to D_{i+1} (less sampling noise than D_i, same extremum; D_i at the top level); its
 * Hessian H gives:
 *  - the edge test: reject unless det H > 0 with the sign of an extremum and
 *    tr(H)^2 / det(H) < (r + 1)^2 / r (ratio of principal curvatures of D below r, r = 10);
 *    ridges and rings (e.g. the flank of a round bump) have one near-zero curvature and fail;
 *  - the sub-sample position x + a* u + b* v with (a*, b*) = -H^-1 grad (rejected when it lies
 *    farther than 2 h_0, i.e. the extremum is not at this sample).
 * Finally, of keypoints closer than 2 h_0 to each other (one feature seen on two levels, or a
 * noise extremum on a feature's flank) only the one with the largest |response| is kept.
 * Boundary points (open borders of scans) are rejected with the angular-gap criterion of
 * pcl::BoundaryEstimation: the neighbours projected on the tangent plane leave an angular gap
 * larger than the boundary angle (pi/2).
 *
 * Known limits: on sparse random samples, noise along a ridge crest can still give a curvature
 * ratio below r (the test removes about half of the ridge extrema there); the sub-sample
 * position is limited by the sampling noise of D (~0.4 mean spacings median error at ~10k points
 * per frame, 0.1 at 40k), so that ~40% of the keypoints of a resampled copy lie farther than one
 * mean spacing from their counterpart.
 *
 * Output: pcl_animseg::PointKeypoint with the refined position, scale h_i (world units), signed
 * response (the contrast D_i(j) minus the level's median), the index of the frame point and the
 * level; sorted by (level, index). */
class DoGKeypoint {
 public:
  using KeypointCloud = pcl::PointCloud<PointKeypoint>;
  using Ptr = std::shared_ptr<DoGKeypoint>;
  using ConstPtr = std::shared_ptr<const DoGKeypoint>;

  /** \brief The levels to search (from MLSScaleSpace); at least 4 levels are needed. */
  void setScaleSpace(const ScaleSpace& scale_space) { scale_space_ = scale_space; }
  const ScaleSpace& getScaleSpace() const { return scale_space_; }
  /** \brief Minimum contrast |D - median D| of a keypoint (SIFT's contrast threshold, 0.04; D
   * is dimensionless): weaker extrema are sampling noise or the faint rings around features and
   * do not repeat on a resampled copy. */
  void setMinResponse(double t) { min_response_ = t; }
  double getMinResponse() const { return min_response_; }
  /** \brief Largest ratio r of the principal curvatures of D (SIFT's edge threshold, 10). */
  void setEdgeRatio(double r) { edge_ratio_ = r; }
  double getEdgeRatio() const { return edge_ratio_; }
  /** \brief Angular gap (radians) above which a point is on an open border (pi/2). */
  void setBoundaryAngle(double a) { boundary_angle_ = a; }
  double getBoundaryAngle() const { return boundary_angle_; }

  /** \brief Detects the keypoints. Throws Error with fewer than 4 levels. */
  void compute(KeypointCloud& keypoints) const;

  /** \brief The normal differences D_i for i = 0 .. levels - 2 (one vector per level pair). */
  static std::vector<std::vector<float>> normalDifferences(const ScaleSpace& scale_space);

 private:
  ScaleSpace scale_space_;
  double min_response_ = 0.04;
  double edge_ratio_ = 10.0;
  double boundary_angle_ = 1.5707963267948966;
};

}  // namespace pcl_animseg
