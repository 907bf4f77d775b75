#pragma once
/** \file mls_projection.h One weighted-plane MLS projection of one point (a diffusion step of
 * MLSScaleSpace), written once for the CPU (scale_space.cpp) and the GPU (the CUDA module's
 * feature kernels). Eigen's fixed-size types, its 3x3 direct eigensolver and unitOrthogonal()
 * compile for both; the files that use it are compiled without fused multiply-adds. */
#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#ifndef PCL_ANIMSEG_HD
#ifdef __CUDACC__
#define PCL_ANIMSEG_HD __host__ __device__
#else
#define PCL_ANIMSEG_HD
#endif
#endif

namespace pcl_animseg {
namespace mls {

/** \brief Where a point moves, its normal and its curvature lmin / tr (0 where not projected). */
struct Projection {
  Eigen::Vector3f x;
  Eigen::Vector3f n;
  float curvature;
};

/** \brief Whether v is neither infinite nor NaN (std::isfinite, for both compilers). */
PCL_ANIMSEG_HD inline bool finite(double v) { return v - v == 0.0; }

/** \brief Projects point j onto the weighted plane of its neighbours. Point q's position is the
 * three floats at xyz + stride q; `row` lists the m neighbours inside the step's support (the
 * point itself first) and weight(a) the Gaussian weight of row[a]; `nref` is the normal whose
 * orientation to keep. `exact`: a full eigensolver (the first step) rather than a few power
 * iterations from nref (the normal moves little per step). A point whose neighbours are a line
 * or a spot keeps its position and gets nref. */
template <typename Weight>
PCL_ANIMSEG_HD inline Projection project(const float* xyz, int stride, int j, const int* row, int m,
                                         Weight weight, const Eigen::Vector3f& nref, bool exact) {
  const float* pj = xyz + static_cast<long long>(stride) * j;
  const Eigen::Vector3f xj(pj[0], pj[1], pj[2]);
  // Moments in float, relative to x_j (so that positions far from the origin lose no
  // precision; the offsets are a few spacings, a few dozen terms): the upper triangle only.
  // The double 3x3 outer products were most of a diffusion step.
  float sw_f = 0.0f, sx = 0.0f, sy = 0.0f, sz = 0.0f;
  float sxx = 0.0f, sxy = 0.0f, sxz = 0.0f, syy = 0.0f, syz = 0.0f, szz = 0.0f;
  for (int a = 0; a < m; ++a) {
    const float* q = xyz + static_cast<long long>(stride) * row[a];
    const float dx = q[0] - xj.x(), dy = q[1] - xj.y(), dz = q[2] - xj.z();
    const float wa = weight(a);
    sw_f += wa;
    const float wx = wa * dx, wy = wa * dy, wz = wa * dz;
    sx += wx;
    sy += wy;
    sz += wz;
    sxx += wx * dx;
    sxy += wx * dy;
    sxz += wx * dz;
    syy += wy * dy;
    syz += wy * dz;
    szz += wz * dz;
  }
  Projection out{xj, nref, 0.0f};
  const double sw = sw_f;
  if (!(m >= 3 && sw > 0.0)) return out;
  const Eigen::Vector3d s1(sx, sy, sz);
  Eigen::Matrix3d s2;
  s2 << sxx, sxy, sxz, sxy, syy, syz, sxz, syz, szz;
  const double inv_sw = 1.0 / sw;
  const Eigen::Vector3d c = s1 * inv_sw;
  const Eigen::Matrix3d cov = s2 * inv_sw - c * c.transpose();
  const double tr = cov.trace();
  Eigen::Vector3d nn;
  double lmin = 0.0;
  bool ok = tr > 0.0;
  if (ok && exact) {
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
    es.computeDirect(cov);
    const Eigen::Vector3d ev = es.eigenvalues();
    // A plane needs two clearly non-zero spreads; on a line or a single spot keep the point.
    ok = ev(1) > 1e-10 * (ev(2) < 1e-300 ? 1e-300 : ev(2)) && ev(2) > 0.0;
    nn = es.eigenvectors().col(0);
    lmin = ev(0);
  } else if (ok) {
    // Diffusion steps after the first: the normal moves little per step, so a few power
    // iterations on tr(C) I - C from the previous normal replace a full eigensolver (which
    // was most of the scale space's time); errors do not accumulate since each step
    // restarts from the last estimate.
    // M = I - C / tr has eigenvalues in [0, 1] with the largest >= 2/3, so the iterates
    // neither overflow nor underflow and one normalisation at the end suffices (divisions
    // and square roots per iteration were the step's bottleneck).
    const Eigen::Matrix3d M = Eigen::Matrix3d::Identity() - cov * (1.0 / tr);
    nn = nref.cast<double>();
    for (int it = 0; it < 4; ++it) nn = M * nn;
    nn.normalize();
    lmin = nn.dot(cov * nn);
    const double rest = tr - lmin;  // spread in the plane: must not be a line or a spot
    const Eigen::Vector3d a = nn.unitOrthogonal(), b = nn.cross(a);
    const double caa = a.dot(cov * a), cbb = b.dot(cov * b), cab = a.dot(cov * b);
    ok = rest > 0.0 && (caa * cbb - cab * cab) > 1e-10 * rest * rest && finite(nn(0)) &&
         finite(nn(1)) && finite(nn(2));
  }
  if (ok) {
    if (nn.cast<float>().dot(nref) < 0.0f) nn = -nn;
    out.x = xj + (c.dot(nn) * nn).cast<float>();
    out.n = nn.normalized().cast<float>();
    out.curvature = static_cast<float>(lmin / tr);
  }
  return out;
}

}  // namespace mls
}  // namespace pcl_animseg
