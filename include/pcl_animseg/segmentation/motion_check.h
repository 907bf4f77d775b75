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

/** \brief One residual (MotionCheckJobs' meaning): `x0` carried by the motion of part `l` into
 * every frame u of scored[0 .. n_scored) but `t` where valid[l frames + u] (motions: 12 per part
 * and frame, icp_step::load's), each copy as floats looked up by `nearest(u, q, p, n)` (true with
 * its nearest point p and that point's normal n, widened, where frame u has one; a non-finite
 * copy is not looked up), the terms added in the order of `scored`. The GPU's kernel, the
 * refinement's loop on the cores and the tests' CPU device each call it with their own search. */
template <class Nearest>
PCL_ANIMSEG_HD inline float residualOf(const double* x0, int l, int t, const int* scored,
                                       int n_scored, int frames, const double* motions,
                                       const char* valid, const double* spacing, double cap,
                                       Nearest nearest) {
  double sum = 0.0;
  int n = 0;
  for (int k = 0; k < n_scored; ++k) {
    const int u = scored[k];
    const long long lu = static_cast<long long>(l) * frames + u;
    if (u == t || !valid[lu]) continue;
    double y[3];
    icp_step::apply(icp_step::load(motions + 12 * lu), x0, y);
    const float q[3] = {static_cast<float>(y[0]), static_cast<float>(y[1]),
                        static_cast<float>(y[2])};
    if (!(std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]))) continue;
    double p[3], nrm[3];
    if (!nearest(u, q, p, nrm)) continue;
    sum += term(y, p, nrm, spacing[u], cap);
    ++n;
  }
  return residual(sum, n);
}

}  // namespace motion_check
}  // namespace segmentation
}  // namespace pcl_animseg
