#pragma once
/** \file icp_step.h The arithmetic of the motion method's ICP and surface error, written once for
 * the CPU and the GPU.
 *
 * The motion method (motion_tracking.cpp) and its device (the CUDA module's tracking kernels)
 * both call these functions, point by point, and add their results in point order, so that a
 * fit gives the same bits on either. Everything here is +, -, *, / and sqrt, which IEEE 754
 * rounds the same way on both (sin and cos, whose last bit differs between libraries, are our
 * own: sinCos), in an order spelled out term by term; the files that use it are compiled without
 * contraction into fused multiply-adds (`-ffp-contract=off`, nvcc `--fmad=false`). No Eigen: nvcc
 * reads this.
 */
#include <cmath>

#ifdef __CUDACC__
#define PCL_ANIMSEG_HD __host__ __device__
#else
#define PCL_ANIMSEG_HD
#endif

namespace pcl_animseg {
namespace segmentation {
namespace icp_step {

/** \brief A rigid motion: the rotation row by row, then the translation. */
struct Rigid {
  double r[9];
  double t[3];
};

/** \brief The motion stored at `p` as 12 doubles, the rotation row by row, then the translation
 * (the layout the devices take and return). */
PCL_ANIMSEG_HD inline Rigid load(const double* p) {
  Rigid a;
  for (int k = 0; k < 9; ++k) a.r[k] = p[k];
  for (int k = 0; k < 3; ++k) a.t[k] = p[9 + k];
  return a;
}

/** \brief Stores a motion at `p` in that layout. */
PCL_ANIMSEG_HD inline void store(const Rigid& a, double* p) {
  for (int k = 0; k < 9; ++k) p[k] = a.r[k];
  for (int k = 0; k < 3; ++k) p[9 + k] = a.t[k];
}

PCL_ANIMSEG_HD inline Rigid identity() {
  Rigid a{};
  a.r[0] = a.r[4] = a.r[8] = 1.0;
  return a;
}

PCL_ANIMSEG_HD inline double dot3(const double* a, const double* b) {
  return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2];
}

/** \brief out = R v. */
PCL_ANIMSEG_HD inline void rotate(const Rigid& a, const double* v, double* out) {
  for (int i = 0; i < 3; ++i) out[i] = dot3(a.r + 3 * i, v);
}

/** \brief Coordinate i of R v + t (apply()'s, for a caller that needs one coordinate). */
PCL_ANIMSEG_HD inline double applied(const Rigid& a, const double* v, int i) {
  return dot3(a.r + 3 * i, v) + a.t[i];
}

/** \brief out = R v + t. */
PCL_ANIMSEG_HD inline void apply(const Rigid& a, const double* v, double* out) {
  for (int i = 0; i < 3; ++i) out[i] = applied(a, v, i);
}

/** \brief a * b (b first). */
PCL_ANIMSEG_HD inline Rigid compose(const Rigid& a, const Rigid& b) {
  Rigid c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      const double col[3] = {b.r[j], b.r[3 + j], b.r[6 + j]};
      c.r[3 * i + j] = dot3(a.r + 3 * i, col);
    }
    c.t[i] = dot3(a.r + 3 * i, b.t) + a.t[i];
  }
  return c;
}

/** \brief The inverse of a rigid motion: R^T, -R^T t. */
PCL_ANIMSEG_HD inline Rigid inverse(const Rigid& a) {
  Rigid b;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) b.r[3 * i + j] = a.r[3 * j + i];
  for (int i = 0; i < 3; ++i) b.t[i] = -dot3(b.r + 3 * i, a.t);
  return b;
}

/** \brief Squared surface error of a moved point (position y, normal n) in spacings^2, given its
 * nearest point of the frame within (clip + 1.5) spacings (found: at squared distance d2,
 * position tp, normal tn): the distance to that point's tangent plane plus how far beyond 1.5
 * spacings it is, clipped at clip^2; clip^2 when there is none or the normals disagree (cosine
 * <= normal_cos, or its absolute value when the normals are `unoriented`). */
PCL_ANIMSEG_HD inline double surfaceError(bool found, float d2, const double* y, const double* n,
                                          const double* tp, const double* tn, double spacing,
                                          bool unoriented, double normal_cos, double clip) {
  const double clip2 = clip * clip;
  if (!found) return clip2;
  const double c = dot3(n, tn);
  if ((unoriented ? std::fabs(c) : c) <= normal_cos) return clip2;
  const double inv_s = 1.0 / spacing;
  const double e[3] = {y[0] - tp[0], y[1] - tp[1], y[2] - tp[2]};
  const double pl = dot3(e, tn) * inv_s;
  const double far = std::sqrt(static_cast<double>(d2)) * inv_s - 1.5;
  const double far_pos = far > 0.0 ? far : 0.0;
  const double v = pl * pl + far_pos * far_pos;
  return v < clip2 ? v : clip2;
}

/** Terms one matched point adds to the normal equations: the upper triangle of A (6 x 6, row by
 * row) and then b (6). */
constexpr int kTerms = 27;

/** Index of A(i, j), i <= j, in the terms. */
PCL_ANIMSEG_HD inline int upper(int i, int j) { return i * 6 - i * (i - 1) / 2 + (j - i); }

/** \brief The terms of one matched point: the moved point yw (about the moved source's
 * centroid c), its nearest point tp with normal tn. Point-to-plane residual (yw - tp) . tn with
 * the Jacobian J = [(yw - c) x tn, tn] (rotation about c, then translation), weighted by
 * `plane`, plus the point-to-point residual yw - tp weighted by `point`. The motion method uses
 * plane 1 and a weak point 0.1 (against sliding along symmetric surfaces: pointTerms below); the
 * rigid motions' passes use one or the other alone. A weight of 1 multiplies exactly, so
 * pointTerms gives the same bits as before the weights. */
PCL_ANIMSEG_HD inline void weightedTerms(const double* yw, const double* c, const double* tp,
                                         const double* tn, double plane, double point,
                                         double* terms) {
  const double y[3] = {yw[0] - c[0], yw[1] - c[1], yw[2] - c[2]};
  const double e[3] = {yw[0] - tp[0], yw[1] - tp[1], yw[2] - tp[2]};
  const double J[6] = {y[1] * tn[2] - y[2] * tn[1],
                       y[2] * tn[0] - y[0] * tn[2],
                       y[0] * tn[1] - y[1] * tn[0],
                       tn[0],
                       tn[1],
                       tn[2]};
  const double r = dot3(e, tn);
  // Jp = [S | I] with S w = w x y, the point-to-point Jacobian.
  const double Jp[3][6] = {{0.0, y[2], -y[1], 1.0, 0.0, 0.0},
                           {-y[2], 0.0, y[0], 0.0, 1.0, 0.0},
                           {y[1], -y[0], 0.0, 0.0, 0.0, 1.0}};
  for (int a = 0; a < 6; ++a) {
    const double ja[3] = {Jp[0][a], Jp[1][a], Jp[2][a]};
    for (int b = a; b < 6; ++b) {
      const double jb[3] = {Jp[0][b], Jp[1][b], Jp[2][b]};
      terms[upper(a, b)] = plane * (J[a] * J[b]) + point * dot3(ja, jb);
    }
    terms[21 + a] = plane * (J[a] * r) + point * dot3(ja, e);
  }
}

/** \brief The motion method's terms: point-to-plane plus a weak (0.1) point-to-point term. */
PCL_ANIMSEG_HD inline void pointTerms(const double* yw, const double* c, const double* tp,
                                      const double* tn, double* terms) {
  weightedTerms(yw, c, tp, tn, 1.0, 0.1, terms);
}

/** \brief The step x (rotation vector, then translation) from the summed terms: the normal
 * equations damped by 2% of the mean diagonal of each block (Levenberg: the directions the
 * source does not constrain stay near the start), solved by Cholesky. False when the system is
 * not positive definite or the step is not finite. */
PCL_ANIMSEG_HD inline bool solveStep(const double* sums, double* x) {
  double M[6][6];
  for (int a = 0; a < 6; ++a)
    for (int b = a; b < 6; ++b) M[a][b] = M[b][a] = sums[upper(a, b)];
  const double tr_rot = ((M[0][0] + M[1][1]) + M[2][2]) / 3.0 + 1e-12;
  const double tr_tr = ((M[3][3] + M[4][4]) + M[5][5]) / 3.0 + 1e-12;
  for (int k = 0; k < 3; ++k) {
    M[k][k] += 0.02 * tr_rot;
    M[k + 3][k + 3] += 0.02 * tr_tr;
  }
  for (int j = 0; j < 6; ++j) {  // M = L L^T, L in the lower triangle
    double s = M[j][j];
    for (int k = 0; k < j; ++k) s -= M[j][k] * M[j][k];
    if (!(s > 0.0)) return false;
    M[j][j] = std::sqrt(s);
    for (int i = j + 1; i < 6; ++i) {
      double v = M[i][j];
      for (int k = 0; k < j; ++k) v -= M[i][k] * M[j][k];
      M[i][j] = v / M[j][j];
    }
  }
  for (int i = 0; i < 6; ++i) {  // L z = -b
    double v = -sums[21 + i];
    for (int k = 0; k < i; ++k) v -= M[i][k] * x[k];
    x[i] = v / M[i][i];
  }
  for (int i = 5; i >= 0; --i) {  // L^T x = z
    double v = x[i];
    for (int k = i + 1; k < 6; ++k) v -= M[k][i] * x[k];
    x[i] = v / M[i][i];
  }
  for (int k = 0; k < 6; ++k)
    if (!std::isfinite(x[k])) return false;
  return true;
}

/** \brief sin and cos of `a` from +, * and exact halvings only, the same bits on every machine:
 * the angle is halved until it is at most 1/8, the Taylor series (to the 10th power: below one
 * ulp there) gives sin and cos, and the double-angle formulas undo the halvings (about one ulp
 * per doubling; a rotation step needs at most a few). */
PCL_ANIMSEG_HD inline void sinCos(double a, double& s, double& c) {
  int k = 0;
  while (std::fabs(a) > 0.125 && k < 64) a *= 0.5, ++k;
  const double a2 = a * a;
  s = a *
      (1.0 -
       a2 / 6.0 * (1.0 - a2 / 20.0 * (1.0 - a2 / 42.0 * (1.0 - a2 / 72.0 * (1.0 - a2 / 110.0)))));
  c = 1.0 -
      a2 / 2.0 * (1.0 - a2 / 12.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0 * (1.0 - a2 / 90.0))));
  for (; k > 0; --k) {
    const double s2 = 2.0 * s * c, c2 = c * c - s * s;
    s = s2, c = c2;
  }
}

/** \brief The motion of a step x about the centroid c: y' = dR (y - c) + c + x[3..5], where dR
 * rotates by |x[0..2]| about x[0..2] (the rotation vector's exponential, through the unit
 * quaternion of half the angle). */
PCL_ANIMSEG_HD inline Rigid stepMotion(const double* x, const double* c) {
  Rigid D = identity();
  const double angle = std::sqrt(dot3(x, x));
  if (angle > 1e-12) {
    double sh, ch;
    sinCos(0.5 * angle, sh, ch);
    const double f = sh / angle;
    const double w = ch, qx = x[0] * f, qy = x[1] * f, qz = x[2] * f;
    D.r[0] = 1.0 - 2.0 * (qy * qy + qz * qz);
    D.r[1] = 2.0 * (qx * qy - w * qz);
    D.r[2] = 2.0 * (qx * qz + w * qy);
    D.r[3] = 2.0 * (qx * qy + w * qz);
    D.r[4] = 1.0 - 2.0 * (qx * qx + qz * qz);
    D.r[5] = 2.0 * (qy * qz - w * qx);
    D.r[6] = 2.0 * (qx * qz - w * qy);
    D.r[7] = 2.0 * (qy * qz + w * qx);
    D.r[8] = 1.0 - 2.0 * (qx * qx + qy * qy);
  }
  double rc[3];
  rotate(D, c, rc);
  for (int k = 0; k < 3; ++k) D.t[k] = (c[k] - rc[k]) + x[3 + k];
  return D;
}

/** \brief The rigid motions' ICP adds its per-point values in kSumRanges contiguous ranges of
 * the source (rangeBegin), each in point order, then the ranges' sums in range order: the GPU
 * gives each range to a thread of the fit's block and gets the CPU's sums. */
constexpr int kSumRanges = 128;

/** \brief First point of range j (0 <= j <= kSumRanges) of n points: ranges of ceil(n /
 * kSumRanges) points, the last ones shorter or empty. */
PCL_ANIMSEG_HD inline int rangeBegin(int j, int n) {
  const int m = (n + kSumRanges - 1) / kSumRanges;
  const long long b = static_cast<long long>(j) * m;
  return b < n ? static_cast<int>(b) : n;
}

/** \brief One step of the rigid motions' ICP from its summed columns (the kTerms terms, the
 * matches' squared distances, their count) about the moved source's centroid c: T moved by the
 * solved step. Returns whether to go on: false with too few matches (T unchanged), no solution
 * (T unchanged), or once converged as PCL's DefaultConvergenceCriteria judge it (a step that
 * turns by less than max_turn and moves by less than max_move, or a mean squared distance that
 * changes by less than rel_mse of the last one; prev_mse carries it between steps, start at -1). */
PCL_ANIMSEG_HD inline bool rigidStep(const double* sums, const double* c, double max_turn,
                                     double max_move, double rel_mse, Rigid& T, double& prev_mse) {
  const double sse = sums[kTerms], used = sums[kTerms + 1];
  if (used < 6.0) return false;
  double x[6];
  if (!solveStep(sums, x)) return false;
  T = compose(stepMotion(x, c), T);
  const double mse = sse / used;
  const bool small = std::sqrt(dot3(x, x)) < max_turn && std::sqrt(dot3(x + 3, x + 3)) < max_move;
  const bool flat = prev_mse > 0.0 && std::fabs(mse - prev_mse) < rel_mse * prev_mse;
  if (small || flat) return false;
  prev_mse = mse;
  return true;
}

/** \brief Whether a step is small enough to stop: rotation below 1e-4 rad and translation below
 * 1e-3 spacings. */
PCL_ANIMSEG_HD inline bool converged(const double* x, double spacing) {
  return std::sqrt(dot3(x, x)) < 1e-4 && std::sqrt(dot3(x + 3, x + 3)) < 1e-3 * spacing;
}

}  // namespace icp_step
}  // namespace segmentation
}  // namespace pcl_animseg
