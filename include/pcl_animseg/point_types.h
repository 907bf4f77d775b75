#pragma once
/** \file point_types.h Registered point types of pcl_animseg, so that keypoints and signatures
 * can be stored in PCD files and opened in pcl_viewer. */
#include <pcl/point_types.h>
#include <pcl/register_point_struct.h>

#include <cstdint>
#include <ostream>

namespace pcl_animseg {

/** \brief A multi-scale (DoG) keypoint: its (sub-sample refined) position, the scale h of the
 * level it was found at (world units), its signed response D and the index of the frame point
 * it sits on. */
struct EIGEN_ALIGN16 PointKeypoint {
  PCL_ADD_POINT4D;
  float scale;
  float response;
  std::int32_t index;
  std::int32_t level;
  PCL_MAKE_ALIGNED_OPERATOR_NEW
};

/** \brief The default 24-D signature sigma(p, n, h) of Eq. 3 (R' = 6, S' = 4) at a point, with
 * the point's position and a flag that the point is a keypoint. */
struct EIGEN_ALIGN16 PointSignature24 {
  PCL_ADD_POINT4D;
  float signature[24];
  std::int32_t keypoint;
  PCL_MAKE_ALIGNED_OPERATOR_NEW
};

inline std::ostream& operator<<(std::ostream& os, const PointKeypoint& p) {
  return os << "(" << p.x << "," << p.y << "," << p.z << " - " << p.scale << "," << p.response
            << "," << p.index << "," << p.level << ")";
}

}  // namespace pcl_animseg

POINT_CLOUD_REGISTER_POINT_STRUCT(pcl_animseg::PointKeypoint,
                                  (float, x, x)(float, y, y)(float, z, z)(float, scale, scale)(
                                      float, response, response)(std::int32_t, index, index)(
                                      std::int32_t, level, level))

POINT_CLOUD_REGISTER_POINT_STRUCT(pcl_animseg::PointSignature24,
                                  (float, x, x)(float, y, y)(float, z, z)(
                                      float[24], signature, signature)(std::int32_t, keypoint,
                                                                       keypoint))
