#pragma once
/** \file dog_keypoint.h Multi-scale feature points: extrema of the level difference (Sec. 3.1). */
#include <pcl/point_cloud.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/point_types.h>

#include <cstdint>
#include <memory>
#include <vector>

namespace pcl_animseg {

/** \brief Detects the extrema of the normal difference between adjacent levels (scale space).
 *
 * "Normal difference" is read as in Li and Guskov [17]: the displacement between two adjacent
 * levels along the normal, D_i(x) = n_i(x) . (L(x, h_{i+1}) - L(x, h_i)) / h_i (Eq. 1 projected
 * on the normal). Dividing by h_i makes D dimensionless, hence invariant to a uniform scaling, and
 * scale-normalised like SIFT's DoG (a feature of size w responds most at h ~ w). It is signed:
 * smoothing moves a bump inwards and a dent outwards, so bumps are minima and dents maxima.
 *
 * D is taken relative to its median over the frame on each level (the contrast): the overall
 * curvature of the object adds to every point a D that grows with the scale, and features are
 * what stands out of it. A point j is a candidate at level i (1 <= i <= levels - 2) when D_i(j)
 * is larger (or smaller) than D_i at all its neighbours within 2 h_0 (ties go to the lower index,
 * so one of two duplicate points can still be a keypoint) and |D_i(j)| >= the minimum response
 * (SIFT's contrast threshold). Unlike SIFT, j need not also beat the levels above and below: D
 * varies by a few percent over the searched scales, so that test was decided by sampling noise
 * (with it, 14% of the keypoints of a resampled copy had no counterpart; 9% without it, 2% with
 * the border test below as well); the scale is chosen by the suppression below.
 * Then, as SIFT does with its 3x3 pixel Hessian, a quadratic D(a, b) is fitted by weighted least
 * squares, over the neighbourhood in the tangent plane (a, b) of the point, to D_{i+1}; its
 * Hessian H gives:
 *  - the edge test: reject unless det H > 0 with the sign of an extremum and
 *    tr(H)^2 / det(H) < (r + 1)^2 / r (ratio of principal curvatures of D below r, r = 10);
 *    ridges and rings (e.g. the flank of a round bump) have one near-zero curvature and fail;
 *  - a first sub-sample position x + a* u + b* v with (a*, b*) = -H^-1 grad (rejected when it
 *    lies farther than 2 h_0, i.e. the extremum is not at this sample).
 * Boundary points are rejected: a point within one neighbourhood (3 h_0) of a point on an open
 * border, i.e. one whose neighbours projected on its tangent plane leave an angular gap larger
 * than the boundary angle (pi/2), among its neighbours and among the points within two
 * neighbourhoods (the second test keeps random interior samples from looking like borders).
 * Of keypoints closer than 2 h_0 to each other (one feature seen on several levels, or a noise
 * extremum on its flank) only the one with the largest |response| is kept.
 *
 * Position (sub-sample localisation): D itself is too noisy on random samples for the extremum
 * to repeat within one mean spacing (a quadratic fit to it puts ~40% of the keypoints of a
 * resampled copy farther than one spacing from their counterpart). Each kept keypoint is
 * therefore moved to the extremum of a direct evaluation of the normal difference around it,
 * R(y) = (z_b(y) - z_a(y)) / h_a, where z_s(y) is the height above y (along the keypoint's
 * normal at the coarsest level) of the weighted local linear fit of the input points with a
 * Gaussian of width s, h_a = 2^(3/4) h_i and h_b = 2 h_a. The input points are used as they are
 * (the diffused levels carry the sampling noise of every diffusion step), each weighted by its
 * share of the surface (weights that make the kernel density of the sample uniform, from three
 * balancing passes a <- a / (K a) with K a compact kernel over the neighbourhoods), and the
 * linear fit removes what an unbalanced sample does on a slope. The extremum is found by Newton
 * steps on quadratic fits of R over a 3 x 3 grid. A keypoint whose extremum lies farther than
 * 3 h_0 from its point, or within a neighbourhood of an open border, is dropped, and the
 * suppression above is made again on the refined positions.
 *
 * Known limits: on sparse random samples, noise along a ridge crest can still give a curvature
 * ratio below r (the test removes about half of the ridge extrema there). The refined position
 * is the centre of a feature that is symmetric at its scale (a bump, a dent); of an asymmetric
 * one it is the extremum of R, which can differ from D's by a fraction of h_i. The refinement
 * (one pass over the samples within 2 h_b of each keypoint per Newton step) makes the detector
 * about 4x slower: ~8 ms instead of 2 ms of one core for a frame of 17k points, 12 keypoints.
 *
 * Output: pcl_animseg::PointKeypoint with the refined position (on the level-0 tangent plane of
 * the frame point nearest to the extremum, in general not a point of the frame), scale h_i
 * (world units), signed response (the contrast, D_i minus the level's median, at the detected
 * point), `index` that nearest frame point (which may differ from the detected point), and the
 * level; sorted by (level, detected point). */
/** \brief The Newton steps of DoGKeypoint's sub-sample refinement for a batch of keypoints, as
 * handed to a KeypointRefineDevice. Keypoint k's samples (its disc) are
 * samples[4 * disc_begin[k] .. 4 * disc_begin[k + 1]): tangent coordinates a, b, the height along
 * the keypoint's normal and the sample's area weight. frames[12 k ..]: the fitted position x0,
 * the tangent axes u, v and the position of the detected frame point (3 floats each). */
struct KeypointRefineJobs {
  double h0 = 0.0;                        ///< the scale space's smallest scale
  std::vector<std::uint32_t> disc_begin;  ///< K + 1 offsets (in samples)
  std::vector<float> samples;             ///< 4 per sample: a, b, z, area
  std::vector<float> frames;              ///< 12 per keypoint: x0, u, v, detected point
  std::vector<float> scales;              ///< the keypoint's scale h_i
  std::vector<char> maximum;              ///< is the keypoint a maximum of D
  // Results, one per keypoint.
  std::vector<float> y;  ///< 2 per keypoint: the extremum in (u, v) from x0
  std::vector<char> ok;  ///< 0 where the extremum moved more than 3 h0 from the detected point
};

/** \brief Runs the Newton steps of KeypointRefineJobs somewhere else than the calling thread (a
 * GPU): the same steps as the CPU's, with the sums over each disc possibly added in another
 * order (so the positions agree to the last bits, not bit for bit). Must be safe to call from
 * several threads at once; throws Error on a device failure. */
class KeypointRefineDevice {
 public:
  virtual ~KeypointRefineDevice() = default;
  virtual void refine(KeypointRefineJobs& jobs) const = 0;
};

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
  /** \brief Angular gap (radians) above which a point is on an open border (pi/2); keypoints
   * within one neighbourhood of such a point are rejected. */
  void setBoundaryAngle(double a) { boundary_angle_ = a; }
  double getBoundaryAngle() const { return boundary_angle_; }

  /** \brief Where the refinement's Newton steps run (nullptr, the default: on the calling
   * thread's cores). The device is not owned. */
  void setRefineDevice(const KeypointRefineDevice* device) { refine_device_ = device; }

  /** \brief Detects the keypoints. Throws Error with fewer than 4 levels. */
  void compute(KeypointCloud& keypoints) const;

  /** \brief The normal differences D_i for i = 0 .. levels - 2 (one vector per level pair). */
  static std::vector<std::vector<float>> normalDifferences(const ScaleSpace& scale_space);

 private:
  ScaleSpace scale_space_;
  double min_response_ = 0.04;
  double edge_ratio_ = 10.0;
  double boundary_angle_ = 1.5707963267948966;
  const KeypointRefineDevice* refine_device_ = nullptr;
};

}  // namespace pcl_animseg
