#pragma once
/** \file gmm_em.h The arithmetic of fitGMM's EM (gmm.h), written once for the CPU and the GPU.
 *
 * fitGMM on the cores and a device's fits (RigidFitDevice::fitMixtures, the CUDA module's kernel)
 * both call these functions, point by point, and add their results in point order, so that a
 * fit gives the same bits on either. Everything here is +, -, *, / and sqrt, which IEEE 754
 * rounds the same way on both, in an order spelled out term by term; exp and log, whose last bit
 * differs between libraries, are our own (about 1 ulp; written by us because the C++ library's
 * and CUDA's differ). The files that use it are compiled without contraction into fused
 * multiply-adds (`-ffp-contract=off`, nvcc `--fmad=false`). No Eigen: nvcc reads this.
 */
#include <cmath>
#include <cstdint>
#include <cstring>

#ifdef __CUDACC__
#define PCL_ANIMSEG_GMM_HD __host__ __device__
#else
#define PCL_ANIMSEG_GMM_HD
#endif

namespace pcl_animseg {
namespace math {
namespace gmm_em {

/** \brief Components a device's fit takes at most (fitGMM itself takes up to 64). */
constexpr int kMaxDeviceComponents = 8;
constexpr int kMaxComponents = 64;

PCL_ANIMSEG_GMM_HD inline double fromBits(std::uint64_t b) {
#ifdef __CUDA_ARCH__
  return __longlong_as_double(static_cast<long long>(b));
#else
  double d;
  std::memcpy(&d, &b, sizeof d);
  return d;
#endif
}
PCL_ANIMSEG_GMM_HD inline std::uint64_t toBits(double d) {
#ifdef __CUDA_ARCH__
  return static_cast<std::uint64_t>(__double_as_longlong(d));
#else
  std::uint64_t b;
  std::memcpy(&b, &d, sizeof b);
  return b;
#endif
}

/** \brief c[0] x^(n-1) + ... + c[n-1] by Horner's rule, one multiply and one add a step. */
PCL_ANIMSEG_GMM_HD inline double horner(const double* c, int n, double x) {
  double p = c[0];
  for (int k = 1; k < n; ++k) p = p * x + c[k];
  return p;
}

/** \brief e^x: x = k ln 2 + r (|r| <= ln 2 / 2, Cody-Waite), e^r by its Taylor series to r^13
 * (Horner), times 2^k built from its bits. 0 below -700 and for -inf (EM's far terms: their
 * share of a sum is nothing anyway), +inf above 709.7, NaN for NaN. */
PCL_ANIMSEG_GMM_HD inline double exp(double x) {
  if (x != x) return x;
  if (x < -700.0) return 0.0;
  if (x > 709.78) return fromBits(0x7ff0000000000000ULL);
  constexpr double kInvLn2 = 1.4426950408889634074;
  constexpr double kLn2Hi = 6.93147180369123816490e-01;  // 0x3fe62e42fee00000: k * hi exact
  constexpr double kLn2Lo = 1.90821492927058770002e-10;
  const double fk =
      static_cast<double>(static_cast<long long>(x * kInvLn2 + (x < 0.0 ? -0.5 : 0.5)));
  const double r = (x - fk * kLn2Hi) - fk * kLn2Lo;
  const double c[] = {1.0 / 6227020800.0,
                      1.0 / 479001600.0,
                      1.0 / 39916800.0,  // 1/13!, ...
                      1.0 / 3628800.0,
                      1.0 / 362880.0,
                      1.0 / 40320.0,
                      1.0 / 5040.0,
                      1.0 / 720.0,
                      1.0 / 120.0,
                      1.0 / 24.0,
                      1.0 / 6.0,
                      0.5,
                      1.0,
                      1.0};
  const double p = horner(c, 14, r);
  // 2^k for k in [-1010, 1024]: a normal number, k + 1023 in its exponent bits; 2^1024 as
  // 2^1023 * 2.
  const long long k = static_cast<long long>(fk);
  if (k > 1023) return p * fromBits(static_cast<std::uint64_t>(1023 + 1023) << 52) * 2.0;
  return p * fromBits(static_cast<std::uint64_t>(k + 1023) << 52);
}

/** \brief ln x: x = m 2^e with m in [sqrt(1/2), sqrt(2)) from its bits, ln m = 2 atanh(s) with
 * s = (m - 1) / (m + 1) by its series to s^21, then e ln 2 added in two parts. -inf for 0, NaN
 * below 0 and for NaN, +inf for +inf. */
PCL_ANIMSEG_GMM_HD inline double log(double x) {
  if (x != x || x < 0.0) return fromBits(0x7ff8000000000000ULL);
  if (x == 0.0) return -fromBits(0x7ff0000000000000ULL);
  std::uint64_t b = toBits(x);
  if ((b >> 52) == 0x7ff) return x;  // +inf
  long long e = 0;
  if ((b >> 52) == 0) {  // subnormal: scaled by 2^54 first
    x = x * 18014398509481984.0;
    b = toBits(x);
    e = -54;
  }
  e += static_cast<long long>(b >> 52) - 1023;
  double m = fromBits((b & 0x000fffffffffffffULL) | 0x3ff0000000000000ULL);  // [1, 2)
  if (m > 1.4142135623730951) {
    m = m * 0.5;
    ++e;
  }
  const double s = (m - 1.0) / (m + 1.0), s2 = s * s;
  const double c[] = {1.0 / 21.0, 1.0 / 19.0, 1.0 / 17.0, 1.0 / 15.0, 1.0 / 13.0, 1.0 / 11.0,
                      1.0 / 9.0,  1.0 / 7.0,  1.0 / 5.0,  1.0 / 3.0,  1.0};
  const double p = horner(c, 11, s2);
  const double lm = 2.0 * s * p;
  constexpr double kLn2Hi = 6.93147180369123816490e-01, kLn2Lo = 1.90821492927058770002e-10;
  const double fe = static_cast<double>(e);
  return fe * kLn2Hi + (fe * kLn2Lo + lm);
}

constexpr double kLog2Pi = 1.8378770664093453;

/** \brief A mixture's numbers as EM updates them: per component its weight, mean, covariance
 * (xx, yy, zz, xy, xz, yz), and the cache: the precision's (P00, P11, P22, 2 P01, 2 P02, 2 P12)
 * and log w - 0.5 log|2 pi S|. */
template <int K>
struct Mixture {
  static constexpr int kMax = K;
  int k = 0;
  double w[K];
  double mu[K][3];
  double cov[K][6];
  double pr[K][6];
  double lnorm[K];
};

/** \brief Component c's precision and log normaliser from its covariance and weight (a 3x3
 * Cholesky factor L, log|S| = 2 sum log L_ii, P = L^-T L^-1); false where the covariance is not
 * positive definite. */
PCL_ANIMSEG_GMM_HD inline bool cacheComponent(double w, const double* cv, double* pr,
                                              double& lnorm) {
  const double a00 = cv[0], a11 = cv[1], a22 = cv[2], a10 = cv[3], a20 = cv[4], a21 = cv[5];
  if (!(a00 > 0.0)) return false;
  const double l00 = std::sqrt(a00);
  const double l10 = a10 / l00, l20 = a20 / l00;
  const double d1 = a11 - l10 * l10;
  if (!(d1 > 0.0)) return false;
  const double l11 = std::sqrt(d1);
  const double l21 = (a21 - l20 * l10) / l11;
  const double d2 = (a22 - l20 * l20) - l21 * l21;
  if (!(d2 > 0.0)) return false;
  const double l22 = std::sqrt(d2);
  // M = L^-1 (lower): the diagonal's inverses, then the rest by forward substitution.
  const double m00 = 1.0 / l00, m11 = 1.0 / l11, m22 = 1.0 / l22;
  const double m10 = -(l10 * m00) / l11;
  const double m21 = -(l21 * m11) / l22;
  const double m20 = -(l20 * m00 + l21 * m10) / l22;
  // P = M^T M.
  const double p00 = (m00 * m00 + m10 * m10) + m20 * m20;
  const double p11 = m11 * m11 + m21 * m21;
  const double p22 = m22 * m22;
  const double p01 = m10 * m11 + m20 * m21;
  const double p02 = m20 * m22;
  const double p12 = m21 * m22;
  pr[0] = p00, pr[1] = p11, pr[2] = p22;
  pr[3] = 2.0 * p01, pr[4] = 2.0 * p02, pr[5] = 2.0 * p12;
  const double log_det = 2.0 * ((log(l00) + log(l11)) + log(l22));
  lnorm = log(w > 1e-300 ? w : 1e-300) - 0.5 * (3.0 * kLog2Pi + log_det);
  return true;
}

/** \brief Every component's cache (cacheComponent); the first component that is not positive
 * definite, or -1. */
template <class M>
PCL_ANIMSEG_GMM_HD inline int cache(M& g) {
  for (int c = 0; c < g.k; ++c)
    if (!cacheComponent(g.w[c], g.cov[c], g.pr[c], g.lnorm[c])) return c;
  return -1;
}

/** \brief Component c's log density term at point p (log w - 0.5 (p - mu)^T P (p - mu) + its
 * normaliser). */
template <class M>
PCL_ANIMSEG_GMM_HD inline double logTerm(const M& g, int c, const double* p) {
  const double d0 = p[0] - g.mu[c][0], d1 = p[1] - g.mu[c][1], d2 = p[2] - g.mu[c][2];
  const double* pr = g.pr[c];
  const double q = pr[0] * d0 * d0 + pr[1] * d1 * d1 + pr[2] * d2 * d2 + pr[3] * d0 * d1 +
                   pr[4] * d0 * d2 + pr[5] * d1 * d2;
  return g.lnorm[c] - 0.5 * q;
}

/** \brief The E step at one point: its responsibilities into r (k values; all 0 where no
 * component explains it) and its log-likelihood (log-sum-exp of the terms) returned. */
template <class M>
PCL_ANIMSEG_GMM_HD inline double responsibilities(const M& g, const double* p, double* r) {
  double v[M::kMax];
  double m = -fromBits(0x7ff0000000000000ULL);
  for (int c = 0; c < g.k; ++c) {
    v[c] = logTerm(g, c, p);
    m = v[c] > m ? v[c] : m;
  }
  if (!(m - m == 0.0)) {  // the largest term is not finite
    for (int c = 0; c < g.k; ++c) r[c] = 0.0;
    return m;
  }
  double s = 0.0;
  for (int c = 0; c < g.k; ++c) {
    r[c] = exp(v[c] - m);
    s += r[c];
  }
  const double inv = 1.0 / s;
  for (int c = 0; c < g.k; ++c) r[c] *= inv;
  return m + log(s);
}

/** \brief The M step's first sums at one point, added to nk[c] and sx[c][0..2]: the
 * responsibility, and it times each coordinate. */
PCL_ANIMSEG_GMM_HD inline void addMeans(int k, const double* p, const double* r, double* nk,
                                        double (*sx)[3]) {
  for (int c = 0; c < k; ++c) {
    nk[c] += r[c];
    for (int d = 0; d < 3; ++d) sx[c][d] += r[c] * p[d];
  }
}

/** \brief The M step's second sums at one point, about the new means mu: sc[c] += r (p - mu)
 * (p - mu)^T's six entries. */
PCL_ANIMSEG_GMM_HD inline void addScatter(int k, const double* p, const double* r,
                                          const double (*mu)[3], double (*sc)[6]) {
  for (int c = 0; c < k; ++c) {
    const double d0 = p[0] - mu[c][0], d1 = p[1] - mu[c][1], d2 = p[2] - mu[c][2];
    const double w = r[c];
    sc[c][0] += w * d0 * d0, sc[c][1] += w * d1 * d1, sc[c][2] += w * d2 * d2;
    sc[c][3] += w * d0 * d1, sc[c][4] += w * d0 * d2, sc[c][5] += w * d1 * d2;
  }
}

/** \brief The new means from the first sums (a component with nk < 1e-8 keeps its mean). */
template <class M>
PCL_ANIMSEG_GMM_HD inline void newMeans(M& g, const double* nk, const double (*sx)[3]) {
  for (int c = 0; c < g.k; ++c) {
    if (nk[c] < 1e-8) continue;
    for (int d = 0; d < 3; ++d) g.mu[c][d] = sx[c][d] / nk[c];
  }
}

/** \brief The M step's end: covariances sc / nk + reg, weights nk / n, normalised and kept
 * above 1e-12 (an empty component keeps its covariance), then the cache; the first component that
 * is not positive definite, or -1. */
template <class M>
PCL_ANIMSEG_GMM_HD inline int newCovariances(M& g, const double* nk, const double (*sc)[6],
                                             double n, double reg) {
  for (int c = 0; c < g.k; ++c) {
    if (nk[c] < 1e-8) continue;
    for (int d = 0; d < 6; ++d) g.cov[c][d] = sc[c][d] / nk[c] + (d < 3 ? reg : 0.0);
    g.w[c] = nk[c] / n;
  }
  double wsum = 0.0;
  for (int c = 0; c < g.k; ++c) wsum += g.w[c];
  for (int c = 0; c < g.k; ++c) {
    const double w = g.w[c] / wsum;
    g.w[c] = w > 1e-12 ? w : 1e-12;
  }
  return cache(g);
}

}  // namespace gmm_em
}  // namespace math
}  // namespace pcl_animseg
