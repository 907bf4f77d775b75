#pragma once
// Inward folds between two nearby surface points, shared by the motion method's graph-cut borders
// and the GMM refinement's fold guard (both keep part borders on such folds: the minima rule).
#include <pcl/point_types.h>

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

}  // namespace detail
}  // namespace segmentation
}  // namespace pcl_animseg
