#pragma once
/** \file scale_space.h Multi-scale representation L(x, h), L(x, kh), ... of a frame (Sec. 3.1). */
#include <pcl_animseg/features/neighbourhood.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <memory>
#include <vector>

namespace pcl_animseg {

/** \brief The levels of one frame: level i point j is input point j projected at scale h_i. */
struct ScaleSpace {
  using Cloud = PointCloudSequence::Cloud;
  /** The frame's mean spacing (world units); all scales below are multiples of it. */
  double spacing = 0.0;
  /** Effective scale h_i of each level, world units. */
  std::vector<double> scales;
  /** Positions and unit normals per level (input order kept). */
  std::vector<Cloud::Ptr> levels;
  /** The input frame the levels were computed from. */
  Cloud::ConstPtr input;
  /** Neighbourhoods of the input (rows sorted by distance), shared by the later stages. */
  std::shared_ptr<const Neighbourhoods> neighbourhoods;
};

/** \brief What MLSScaleSpace::compute derives from its parameters and the frame before it
 * projects (MLSScaleSpace::plan). */
struct ScaleSpacePlan {
  double spacing = 0.0;        ///< the frame's spacing, world units
  double h0 = 0.0;             ///< width of one projection, world units
  float step_radius = 0.0f;    ///< support of one projection (2 h0)
  float radius = 0.0f;         ///< radius of the shared neighbourhoods
  float inv_h2 = 0.0f;         ///< 1 / h0^2 of the projection weights
  std::vector<int> counts;     ///< projections n_i of each level
  std::vector<double> scales;  ///< h_i of each level
  /** Orientation reference of level 0's normals: the input normals, unit, or pointing away from
   * the centroid where a normal is missing. */
  std::vector<Eigen::Vector3f> ref;
};

/** \brief Builds the scale space of a frame by MLS projection (Sec. 3.1, "diffusion ... for point
 * set surfaces").
 *
 * We use our own MLS rather than pcl::MovingLeastSquares: PCL's resamples/reorders points (level
 * i point j must be input point j), searches its neighbours again for every level and fits a
 * polynomial per point per level, which is several times too slow for 800k points x 5 levels.
 * Ours is the simple weighted-plane MLS projection (weighted centroid c and PCA normal n with
 * Gaussian weights exp(-d^2/h0^2), point moved along n onto the plane), applied as a diffusion:
 * level i is n_i = round(k^(2i)) such projections at width h0 with the neighbour lists (and
 * weights) of the input, so that its effective scale is h_i = h0 * sqrt(n_i) ~ h0 k^i (Gaussian
 * widths add in quadrature). Points only move along their normals, so the input neighbourhoods
 * stay valid on every level and one kd-tree search per point serves all levels.
 *
 * Normals are oriented like the input normals (level 0) and like the previous level (level i).
 * Fall-back: points whose input normal is missing (zero or NaN) get level-0 normals oriented away
 * from the frame's centroid (right for closed shapes). Throws Error for frames with fewer than
 * getMinPoints() points, or whose largest scale disc 2 h_max exceeds half the frame's
 * bounding-box diagonal (the scales are then too large for the frame: lower h, k or levels). */
class MLSScaleSpace {
 public:
  using Cloud = PointCloudSequence::Cloud;
  using Ptr = std::shared_ptr<MLSScaleSpace>;
  using ConstPtr = std::shared_ptr<const MLSScaleSpace>;

  void setInputCloud(const Cloud::ConstPtr& cloud) { input_ = cloud; }
  const Cloud::ConstPtr& getInputCloud() const { return input_; }

  /** \brief Smallest scale h of L(x, h), in units of the frame's mean spacing. */
  void setScale(double h) { h_ = h; }
  double getScale() const { return h_; }
  /** \brief Constant multiplicative factor k between adjacent scales (Eq. 1). */
  void setScaleFactor(double k) { k_ = k; }
  double getScaleFactor() const { return k_; }
  /** \brief Number of levels L(x, h) .. L(x, k^(levels-1) h). */
  void setNumberOfLevels(int levels) { levels_ = levels; }
  int getNumberOfLevels() const { return levels_; }
  /** \brief Radius of the shared neighbourhoods in spacing units; at least 3h is always used.
   * Later stages that need wider neighbourhoods (the signature disc) ask for them here so the
   * frame is searched once. */
  void setNeighbourhoodRadius(double r) { neighbourhood_radius_ = r; }
  double getNeighbourhoodRadius() const { return neighbourhood_radius_; }
  /** \brief The frame's spacing in world units; 0 (default) measures it (featureSpacing). */
  void setSpacing(double s) { spacing_ = s; }
  double getSpacing() const { return spacing_; }
  static constexpr std::size_t getMinPoints() { return 20; }

  /** \brief Computes all levels. Throws Error on bad parameters or a frame too small. */
  void compute(ScaleSpace& output) const;

  /** \brief Checks the parameters and the frame as compute() does (the same errors) and returns
   * what its projections use; compute() itself starts with it, the GPU's features too. */
  ScaleSpacePlan plan() const;

  /** \brief Projection counts n_i per level for the current h, k, levels (exposed for tests). */
  std::vector<int> projectionCounts() const;

 private:
  Cloud::ConstPtr input_;
  double h_ = 2.0;
  double k_ = 1.41421356;
  int levels_ = 5;
  double neighbourhood_radius_ = 0.0;
  double spacing_ = 0.0;
};

}  // namespace pcl_animseg
