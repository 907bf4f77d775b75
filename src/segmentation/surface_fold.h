#pragma once
// Inward folds between two nearby surface points, shared by the motion method's graph-cut borders
// and the GMM refinement's fold guard and fold snap (all keep part borders on such folds: the
// minima rule).
#include <pcl/point_types.h>

#include <Eigen/Core>
#include <algorithm>
#include <cmath>

namespace pcl_animseg {
namespace segmentation {
namespace detail {

/** The cosine between the normals of a and b when the surface folds inwards between them (the
 * normals converge along a -> b), 1 otherwise (flat or outward-curving: no fold). */
inline float inwardFoldCos(const pcl::PointNormal& a, const pcl::PointNormal& b) {
  const Eigen::Vector3f na = a.getNormalVector3fMap(), nb = b.getNormalVector3fMap();
  if (!((na - nb).dot(a.getVector3fMap() - b.getVector3fMap()) < 0.0f)) return 1.0f;
  return na.dot(nb);
}

/** The angle in degrees between the normals of two near points unless the surface clearly curves
 * outwards between them (the change of normal points along the step from one to the other, as
 * on a ridge); the fold snap's measure. Unlike inwardFoldCos, a step that grazes an inward fold
 * (one running nearly along it, where the sign of (n_a - n_b) . (a - b) is noise) counts as
 * crossing it; else a path could cross the fold where it meets the crease at a shallow angle. */
inline double foldDegrees(const pcl::PointNormal& a, const pcl::PointNormal& b) {
  const Eigen::Vector3d na = a.getNormalVector3fMap().cast<double>(),
                        nb = b.getNormalVector3fMap().cast<double>();
  const Eigen::Vector3d dn = na - nb,
                        step = (a.getVector3fMap() - b.getVector3fMap()).cast<double>();
  const double scale = dn.norm() * step.norm();
  if (!(scale > 0.0) || dn.dot(step) >= 0.5 * scale) return 0.0;
  return std::acos(std::clamp(na.dot(nb), -1.0, 1.0)) * (180.0 / 3.14159265358979323846);
}

}  // namespace detail
}  // namespace segmentation
}  // namespace pcl_animseg
