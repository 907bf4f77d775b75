#pragma once
/** \file motion_check.h The refinement's motion check, term by term, written once for the CPU and
 * the GPU (GMMBoundaryRefinement, and a RigidFitDevice's motionResiduals): a point carried by a
 * part's motion into another frame and scored against its nearest point there. The arithmetic of
 * icp_step.h (+, -, *, /, fabs and sqrt in an order spelled out), so that both give the same bits.
 * No Eigen: nvcc reads this. */
#include <pcl_animseg/segmentation/icp_step.h>

#include <cmath>

namespace pcl_animseg {
namespace segmentation {
namespace motion_check {

/** \brief The term of a copy `y` against its nearest point `p` with normal `n` (the cloud's
 * floats, widened), in spacings `s` of that frame: max(|(y - p) . n|, |y - p| - s) / s, at most
 * `cap` (std::max and std::min's choices, also for NaN). */
PCL_ANIMSEG_HD inline double term(const double* y, const double* p, const double* n, double s,
                                  double cap) {
  const double d[3] = {y[0] - p[0], y[1] - p[1], y[2] - p[2]};
  const double plane = std::fabs(icp_step::dot3(d, n));
  const double beyond = std::sqrt(icp_step::dot3(d, d)) - s;
  const double e = (plane < beyond ? beyond : plane) / s;
  return cap < e ? cap : e;
}

/** \brief A residual from the sum of its `n` terms: their mean as a float, 0 without any. */
PCL_ANIMSEG_HD inline float residual(double sum, int n) {
  return n > 0 ? static_cast<float>(sum / n) : 0.0f;
}

}  // namespace motion_check
}  // namespace segmentation
}  // namespace pcl_animseg
