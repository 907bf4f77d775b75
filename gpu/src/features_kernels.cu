// The multi-scale features of a block of frames on the device: the frames' neighbour rows (a
// uniform grid, as radiusNeighbourhoods), the MLS diffusion of MLSScaleSpace, and the signatures
// of SignatureEstimation. Each kernel follows its CPU counterpart operation by operation (this
// file is compiled without fused multiply-adds), so the rows are the CPU's bit for bit and the
// levels and signatures agree to the last bits of the library functions (exp, atan2, cos, sin:
// the CPU's and CUDA's differ in the last bit now and then).
#include <pcl_animseg/features/mls_projection.h>
#include <pcl_animseg/keypoints/dog_refinement.h>

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cstdint>
#include <cstring>
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include "cuda_check.h"
#include "features_device.h"

namespace pcl_animseg {
namespace gpu {
namespace detail {
namespace {

constexpr int kWarpsPerBlock = 8;
constexpr int kRowBuffer = 256;  // a warp's sort buffer: the cap of a row (rows of <= 256)
constexpr int kMaxD = 64;        // signature dimension R' S'
constexpr int kMaxS = 32;        // directions S
constexpr int kMaxSp = 16;       // angular frequencies S'

__device__ inline int frameOf(const FeatureFrame* frames, int nframes, int i) {
  int lo = 0, hi = nframes - 1;
  while (lo < hi) {
    const int mid = (lo + hi + 1) / 2;
    if (frames[mid].begin <= i)
      lo = mid;
    else
      hi = mid - 1;
  }
  return lo;
}

// ---------------------------------------------------------------------------------------------
// Neighbour rows (neighbourhood.cpp: radiusNeighbourhoods).

__device__ inline void cellOf(const FeatureFrame& f, float x, float y, float z, int c[3]) {
  c[0] = static_cast<int>(floorf((x - f.ox) * f.inv_cell));
  c[1] = static_cast<int>(floorf((y - f.oy) * f.inv_cell));
  c[2] = static_cast<int>(floorf((z - f.oz) * f.inv_cell));
}

__device__ inline long long cellKey(const FeatureFrame& f, long long ix, long long iy,
                                    long long iz) {
  return f.key_base + (ix * f.ny + iy) * f.nz + iz;
}

__global__ void keysKernel(int n, const float* xyz, const FeatureFrame* frames, int nframes,
                           long long* keys, int* vals) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const FeatureFrame& f = frames[frameOf(frames, nframes, i)];
  int c[3];
  cellOf(f, xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2], c);
  keys[i] = cellKey(f, c[0] + 1, c[1] + 1, c[2] + 1);
  vals[i] = i;
}

__global__ void gatherSortedKernel(int n, const float* xyz, const int* order, float* sorted_xyz) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const int p = order[i];
  sorted_xyz[3 * i] = xyz[3 * p];
  sorted_xyz[3 * i + 1] = xyz[3 * p + 1];
  sorted_xyz[3 * i + 2] = xyz[3 * p + 2];
}

__device__ inline int lowerBound(const long long* keys, int n, long long v) {
  int lo = 0, hi = n;
  while (lo < hi) {
    const int mid = (lo + hi) >> 1;
    if (keys[mid] < v)
      lo = mid + 1;
    else
      hi = mid;
  }
  return lo;
}

__device__ inline unsigned long long packed(float d2, int index) {
  return (static_cast<unsigned long long>(__float_as_uint(d2)) << 32) |
         static_cast<unsigned int>(index);
}

/** Calls visit(key) on every neighbour of point i within the radius (the point excluded), each
 * lane on its share; `ranges` are the 9 runs of sorted positions (lane r < 9 holds run r). */
template <typename Visit>
__device__ inline void forCandidates(int i, float x, float y, float z, float r2, int lane_begin,
                                     int lane_end, const float* sorted_xyz, const int* order,
                                     Visit visit) {
  const int lane = threadIdx.x & 31;
  for (int r = 0; r < 9; ++r) {
    const int b = __shfl_sync(0xffffffffu, lane_begin, r);
    const int e = __shfl_sync(0xffffffffu, lane_end, r);
    for (int base = b; base < e; base += 32) {
      const int a = base + lane;
      bool hit = false;
      unsigned long long key = 0;
      if (a < e) {
        const float ex = sorted_xyz[3 * a] - x, ey = sorted_xyz[3 * a + 1] - y,
                    ez = sorted_xyz[3 * a + 2] - z;
        const float dd = ex * ex + ey * ey + ez * ez;
        const int q = order[a];
        if (dd < r2 && q != i) {
          hit = true;
          key = packed(dd, q);
        }
      }
      visit(hit, key);
    }
  }
}

/** Counts (Fill = false) or writes (Fill = true) the rows, one warp a point. */
template <bool Fill>
__global__ void rowsKernel(int n, const float* xyz, const FeatureFrame* frames, int nframes,
                           const long long* sorted_keys, const float* sorted_xyz, const int* order,
                           int cap, long long* counts, const long long* offsets, int* out_idx,
                           float* out_d2) {
  __shared__ unsigned long long buffers[kWarpsPerBlock][kRowBuffer];
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  const int i = blockIdx.x * kWarpsPerBlock + warp;
  if (i >= n) return;  // whole warps leave together
  const FeatureFrame& f = frames[frameOf(frames, nframes, i)];
  const float x = xyz[3 * i], y = xyz[3 * i + 1], z = xyz[3 * i + 2];
  int c[3];
  cellOf(f, x, y, z, c);
  int lane_begin = 0, lane_end = 0;
  if (lane < 9) {
    const long long lo = cellKey(f, c[0] + lane / 3, c[1] + lane % 3, c[2]);
    lane_begin = lowerBound(sorted_keys, n, lo);
    lane_end = lowerBound(sorted_keys, n, lo + 3);
  }
  // How many neighbours there are in all.
  int total = 0;
  forCandidates(
      i, x, y, z, f.radius2, lane_begin, lane_end, sorted_xyz, order,
      [&](bool hit, unsigned long long) { total += __popc(__ballot_sync(0xffffffffu, hit)); });
  const int keep = min(total, cap - 1);
  if (!Fill) {
    if (lane == 0) counts[i] = keep + 1;
    return;
  }
  // The `keep` smallest (distance, index) keys: all of them, or those up to the keep-th
  // smallest, found bit by bit (points with more than cap - 1 neighbours: duplicates, dense
  // spots).
  unsigned long long limit = ~0ull;
  if (total > keep) {
    unsigned long long result = 0;
    int rank = keep;  // 1-based rank of the key sought among those matching `result` so far
    for (int bit = 63; bit >= 0; --bit) {
      int zeros = 0;
      forCandidates(i, x, y, z, f.radius2, lane_begin, lane_end, sorted_xyz, order,
                    [&](bool hit, unsigned long long key) {
                      const bool high_same =
                          bit == 63 || (key >> (bit + 1)) == (result >> (bit + 1));
                      const bool match = hit && high_same && !((key >> bit) & 1ull);
                      zeros += __popc(__ballot_sync(0xffffffffu, match));
                    });
      if (zeros < rank) {
        rank -= zeros;
        result |= 1ull << bit;
      }
    }
    limit = result;
  }
  unsigned long long* buf = buffers[warp];
  for (int t = lane; t < kRowBuffer; t += 32) buf[t] = ~0ull;
  __syncwarp();
  int filled = 0;
  forCandidates(i, x, y, z, f.radius2, lane_begin, lane_end, sorted_xyz, order,
                [&](bool hit, unsigned long long key) {
                  const bool take = hit && key <= limit;
                  const unsigned mask = __ballot_sync(0xffffffffu, take);
                  if (take) buf[filled + __popc(mask & ((1u << lane) - 1u))] = key;
                  filled += __popc(mask);
                });
  __syncwarp();
  // Bitonic sort of the buffer (padding keys are the largest).
  for (int size = 2; size <= kRowBuffer; size <<= 1)
    for (int stride = size >> 1; stride > 0; stride >>= 1) {
      for (int t = lane; t < kRowBuffer / 2; t += 32) {
        const int a = 2 * t - (t & (stride - 1));
        const int b = a + stride;
        const bool up = (a & size) == 0;
        const unsigned long long va = buf[a], vb = buf[b];
        if ((va > vb) == up) {
          buf[a] = vb;
          buf[b] = va;
        }
      }
      __syncwarp();
    }
  const long long off = offsets[i];
  if (lane == 0) {
    out_idx[off] = i;
    out_d2[off] = 0.0f;
  }
  for (int t = lane; t < keep; t += 32) {
    const unsigned long long key = buf[t];
    out_idx[off + 1 + t] = static_cast<int>(key & 0xffffffffull);
    out_d2[off + 1 + t] = __uint_as_float(static_cast<unsigned int>(key >> 32));
  }
}

// ---------------------------------------------------------------------------------------------
// One MLS diffusion step (scale_space.cpp: projectOnce, both through mls::project), one thread a
// point. `curvature` may be null (steps whose curvature no level keeps).

__global__ void projectKernel(int n, const FeatureFrame* frames, int nframes,
                              const long long* offsets, const int* rows, const float* sqr,
                              const float* src, const float* ref, bool exact, float* dst,
                              float* dst_normals, float* curvature) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= n) return;
  const FeatureFrame& f = frames[frameOf(frames, nframes, j)];
  const long long off = offsets[j];
  const int count = static_cast<int>(offsets[j + 1] - off);
  const float* d2 = sqr + off;
  const float step_r2 = f.step_radius * f.step_radius;
  int m = 0;  // the row's entries inside the step's support (the CPU's countWithin)
  while (m < count && d2[m] <= step_r2) ++m;
  const float inv_h2 = f.inv_h2;
  // The CPU's weights are expf of the same float argument: exp in double, rounded.
  const mls::Projection r = mls::project(
      src, 3, j, rows + off, m,
      [d2, inv_h2](int a) { return static_cast<float>(exp(static_cast<double>(-d2[a] * inv_h2))); },
      Eigen::Vector3f(ref[3 * j], ref[3 * j + 1], ref[3 * j + 2]), exact);
  for (int k = 0; k < 3; ++k) {
    dst[3 * j + k] = r.x(k);
    dst_normals[3 * j + k] = r.n(k);
  }
  if (curvature) curvature[j] = r.curvature;
}

/** Level l of the block: positions and normals, 6 floats a point. */
__global__ void storeLevelKernel(int n, const float* xyz, const float* normals, float* level) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= n) return;
  for (int k = 0; k < 3; ++k) {
    level[6 * j + k] = xyz[3 * j + k];
    level[6 * j + 3 + k] = normals[3 * j + k];
  }
}

// ---------------------------------------------------------------------------------------------
// Signatures (signature.cpp: SignatureEstimation::compute, DiscSignature::compute).

/** The signature's normals (multiscale_common.cpp: signatureInput): the frame's own, unit, or
 * level 0's where the frame has none. */
__global__ void signatureNormalsKernel(int n, const float* normals, const float* level0,
                                       float* out) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= n) return;
  const Eigen::Vector3f nv(normals[3 * j], normals[3 * j + 1], normals[3 * j + 2]);
  Eigen::Vector3f r;
  if (!(mls::finite(nv(0)) && mls::finite(nv(1)) && mls::finite(nv(2))) || nv.squaredNorm() < 0.25f)
    r = Eigen::Vector3f(level0[6 * j + 3], level0[6 * j + 4], level0[6 * j + 5]);
  else
    r = nv.normalized();
  for (int k = 0; k < 3; ++k) out[3 * j + k] = r(k);
}

struct DiscTables {
  const float *a, *b, *aa, *ab, *bb, *aaa, *aab, *abb, *bbb;  // Q each, q = k R + l
  const float *ang_cos, *ang_sin;                             // S' x S
  const float *rad_cos, *rad_sin;                             // R' x R
};

struct SignatureArgs {
  int n, nframes, maxfit, R, S, Rp, Sp;
  const FeatureFrame* frames;
  const long long* offsets;
  const int* rows;
  const float* sqr;
  const float* xyz;
  const float* normals;  // signatureNormalsKernel's
  DiscTables tab;
  float* out;  // n x D
};

/** The points of the disc in row order: visit(a, b, z, w, ga, gb) (NaN ga: no slope). */
struct DiscPoints {
  const SignatureArgs* s;
  const int* row;
  int cnt, m;  // row entries within rho, entries used (thinned to maxfit)
  Eigen::Vector3f p, n, u, v;
  double inv_rho;

  template <typename Visit>
  __device__ void forEach(Visit visit) const {
    const double nan = __longlong_as_double(0x7ff8000000000000ll);
    for (int t = 0; t < m; ++t) {
      const int q = m == cnt ? row[t] : row[static_cast<long long>(t) * cnt / m];
      const Eigen::Vector3f pq(s->xyz[3 * q], s->xyz[3 * q + 1], s->xyz[3 * q + 2]);
      const Eigen::Vector3f d = pq - p;
      const double a = d.dot(u) * inv_rho, b = d.dot(v) * inv_rho;
      const double r2 = a * a + b * b;
      if (r2 > 1.0) continue;
      const double z = d.dot(n) * inv_rho;
      const double w = exp(-2.0 * r2);
      const Eigen::Vector3f nq(s->normals[3 * q], s->normals[3 * q + 1], s->normals[3 * q + 2]);
      const double nn = nq.dot(n);
      double ga = nan, gb = nan;
      if (nn > 0.3) {
        ga = -nq.dot(u) / nn;
        gb = -nq.dot(v) / nn;
      }
      visit(a, b, z, w, ga, gb);
    }
  }
};

template <int NC>
__device__ inline void monomials(double a, double b, double* phi) {
  phi[0] = 1.0;
  if (NC > 1) {
    phi[1] = a;
    phi[2] = b;
  }
  if (NC > 3) {
    phi[3] = a * a;
    phi[4] = a * b;
    phi[5] = b * b;
  }
  if (NC > 6) {
    phi[6] = a * a * a;
    phi[7] = a * a * b;
    phi[8] = a * b * b;
    phi[9] = b * b * b;
  }
}

template <int NC>
__device__ inline void monomialGrad(double a, double b, double* da, double* db) {
  for (int i = 0; i < NC; ++i) da[i] = db[i] = 0.0;
  if (NC > 1) {
    da[1] = 1.0;
    db[2] = 1.0;
  }
  if (NC > 3) {
    da[3] = 2.0 * a;
    da[4] = b;
    db[4] = a;
    db[5] = 2.0 * b;
  }
  if (NC > 6) {
    da[6] = 3.0 * a * a;
    da[7] = 2.0 * a * b;
    da[8] = b * b;
    db[7] = a * a;
    db[8] = 2.0 * a * b;
    db[9] = 3.0 * b * b;
  }
}

/** Eigen's LDLT with diagonal pivoting (Cholesky/LDLT.h, unblocked, lower), on an NC x NC
 * symmetric matrix M (full storage, overwritten), then the solve. With kFitChecks it returns
 * false where the CPU's fitHeight rejects the fit: factorisation failed, not positive, or
 * near-singular. Without, it is M.ldlt().solve(v) as it is (an all-zero matrix gives 0, a zero
 * pivot a zero component) and returns true. */
template <int NC, bool kFitChecks = true>
__device__ bool ldltSolve(double (&M)[NC][NC], double (&v)[NC]) {
  int transp[NC];
  int sign = 0;  // 0 zero, 1 positive semi-definite, 2 negative, 3 indefinite
  bool found_zero_pivot = false, ret = true;
  double temp[NC];
  for (int k = 0; k < NC; ++k) {
    int big = k;
    double best = fabs(M[k][k]);
    for (int i = k + 1; i < NC; ++i)
      if (fabs(M[i][i]) > best) {
        best = fabs(M[i][i]);
        big = i;
      }
    transp[k] = big;
    if (k != big) {
      for (int c = 0; c < k; ++c) {
        const double t = M[k][c];
        M[k][c] = M[big][c];
        M[big][c] = t;
      }
      for (int r = big + 1; r < NC; ++r) {
        const double t = M[r][k];
        M[r][k] = M[r][big];
        M[r][big] = t;
      }
      const double t = M[k][k];
      M[k][k] = M[big][big];
      M[big][big] = t;
      for (int i = k + 1; i < big; ++i) {
        const double t2 = M[i][k];
        M[i][k] = M[big][i];
        M[big][i] = t2;
      }
    }
    if (k > 0) {
      for (int i = 0; i < k; ++i) temp[i] = M[i][i] * M[k][i];
      double s = 0.0;
      for (int i = 0; i < k; ++i) s = i == 0 ? M[k][i] * temp[i] : s + M[k][i] * temp[i];
      M[k][k] -= s;
      for (int r = k + 1; r < NC; ++r) {
        double acc = 0.0;
        for (int i = 0; i < k; ++i) acc = i == 0 ? M[r][i] * temp[i] : acc + M[r][i] * temp[i];
        M[r][k] -= acc;
      }
    }
    const double akk = M[k][k];
    const bool valid = fabs(akk) > 0.0;
    if (k == 0 && !valid) {
      // All-zero diagonal: the CPU's fit fails (minCoeff test); Eigen's solve gives 0.
      for (int i = 0; i < NC; ++i) v[i] = 0.0;
      return !kFitChecks;
    }
    if (valid)
      for (int r = k + 1; r < NC; ++r) M[r][k] /= akk;
    else
      for (int r = k + 1; r < NC; ++r) ret = ret && M[r][k] == 0.0;
    if (found_zero_pivot && valid)
      ret = false;
    else if (!valid)
      found_zero_pivot = true;
    if (sign == 1) {
      if (akk < 0.0) sign = 3;
    } else if (sign == 2) {
      if (akk > 0.0) sign = 3;
    } else if (sign == 0) {
      if (akk > 0.0)
        sign = 1;
      else if (akk < 0.0)
        sign = 2;
    }
  }
  if (kFitChecks) {
    if (!ret || !(sign == 1 || sign == 0)) return false;
    double dmin = M[0][0], dmax = M[0][0];
    for (int k = 1; k < NC; ++k) {
      dmin = fmin(dmin, M[k][k]);
      dmax = fmax(dmax, M[k][k]);
    }
    if (!(dmin > 1e-7 * dmax)) return false;
  }
  // x = P^T L^-T D^-1 L^-1 P v
  for (int k = 0; k < NC; ++k) {
    const double t = v[k];
    v[k] = v[transp[k]];
    v[transp[k]] = t;
  }
  for (int i = 0; i < NC; ++i)
    for (int j = 0; j < i; ++j) v[i] -= M[i][j] * v[j];
  for (int i = 0; i < NC; ++i)
    v[i] = fabs(M[i][i]) > 2.2250738585072014e-308 ? v[i] / M[i][i] : 0.0;
  for (int i = NC - 1; i >= 0; --i)
    for (int j = i + 1; j < NC; ++j) v[i] -= M[j][i] * v[j];
  for (int k = NC - 1; k >= 0; --k) {
    const double t = v[k];
    v[k] = v[transp[k]];
    v[transp[k]] = t;
  }
  if (kFitChecks)
    for (int k = 0; k < NC; ++k)
      if (!isfinite(v[k])) return false;
  return true;
}

/** signature.cpp's fitHeight<NC>: the weighted least-squares height field with matched slopes. */
template <int NC>
__device__ bool fitHeight(const DiscPoints& disc, double (&coef)[10]) {
  double A[NC][NC];
  double rhs[NC];
  for (int r = 0; r < NC; ++r) {
    rhs[r] = 0.0;
    for (int c = 0; c < NC; ++c) A[r][c] = 0.0;
  }
  double sw = 0.0;
  disc.forEach([&](double a, double b, double z, double wi, double ga, double gb) {
    double phi[NC], da[NC], db[NC];
    monomials<NC>(a, b, phi);
    sw += wi;
    if (ga == ga) {
      monomialGrad<NC>(a, b, da, db);
      for (int r = 0; r < NC; ++r) {
        const double pr = wi * phi[r], ar = wi * da[r], br = wi * db[r];
        for (int c = 0; c <= r; ++c) A[r][c] += pr * phi[c] + ar * da[c] + br * db[c];
        rhs[r] += pr * z + ar * ga + br * gb;
      }
    } else {
      for (int r = 0; r < NC; ++r) {
        const double pr = wi * phi[r];
        for (int c = 0; c <= r; ++c) A[r][c] += pr * phi[c];
        rhs[r] += pr * z;
      }
    }
  });
  for (int r = 0; r < NC; ++r)
    for (int c = 0; c < r; ++c) A[c][r] = A[r][c];
  for (int r = 0; r < NC; ++r) A[r][r] += 1e-10 * sw;
  if (!ldltSolve<NC>(A, rhs)) return false;
  for (int i = 0; i < 10; ++i) coef[i] = i < NC ? rhs[i] : 0.0;
  return true;
}

__global__ void signatureKernel(SignatureArgs s) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= s.n) return;
  const FeatureFrame& f = s.frames[frameOf(s.frames, s.nframes, j)];
  const int D = s.Rp * s.Sp;
  float* out = s.out + static_cast<long long>(j) * D;
  for (int d = 0; d < D; ++d) out[d] = 0.0f;

  DiscPoints disc;
  disc.s = &s;
  const long long off = s.offsets[j];
  const int count = static_cast<int>(s.offsets[j + 1] - off);
  disc.row = s.rows + off;
  const float rho2 = f.rho * f.rho;
  int cnt = 0;
  while (cnt < count && s.sqr[off + cnt] <= rho2) ++cnt;
  disc.cnt = cnt;
  disc.m = cnt > s.maxfit ? s.maxfit : cnt;
  disc.p = Eigen::Vector3f(s.xyz[3 * j], s.xyz[3 * j + 1], s.xyz[3 * j + 2]);
  disc.n =
      Eigen::Vector3f(s.normals[3 * j], s.normals[3 * j + 1], s.normals[3 * j + 2]).normalized();
  // defaultTangent(n): n x e, e the axis of n's smallest |component| (the first of equals).
  {
    const Eigen::Vector3f an = disc.n.cwiseAbs();
    int a = 0;
    if (an(1) < an(a)) a = 1;
    if (an(2) < an(a)) a = 2;
    Eigen::Vector3f e = Eigen::Vector3f::Zero();
    e(a) = 1.0f;
    disc.u = disc.n.cross(e).normalized();
  }
  disc.v = disc.n.cross(disc.u);
  disc.inv_rho = 1.0 / f.rho_d;

  int m = 0;  // points in the disc
  disc.forEach([&](double, double, double, double, double, double) { ++m; });
  double c[10];
  bool ok = false;
  if (m >= 16) ok = fitHeight<10>(disc, c);
  if (!ok && m >= 8) ok = fitHeight<6>(disc, c);
  if (!ok && m >= 3) ok = fitHeight<3>(disc, c);
  if (!ok) return;

  float cf[10];
  for (int i = 0; i < 10; ++i) cf[i] = static_cast<float>(c[i]);
  const int R = s.R, S = s.S, Rp = s.Rp, Sp = s.Sp;
  const DiscTables& t = s.tab;
  double acc_re[kMaxD], acc_im[kMaxD];
  for (int d = 0; d < D; ++d) acc_re[d] = acc_im[d] = 0.0;
  // Ring by ring: the ring's S samples (sampleNormals), their angular DFT (rf, jf per angular
  // frequency), and its terms of the radial DFT, each sum in the CPU's order.
  for (int l = 0; l < R; ++l) {
    float sk[kMaxS];
    for (int k = 0; k < S; ++k) {
      const int q = k * R + l;
      const float a = t.a[q], b = t.b[q], aa = t.aa[q], ab = t.ab[q], bb = t.bb[q];
      const float z = cf[1] * a + cf[2] * b + cf[3] * aa + cf[4] * ab + cf[5] * bb +
                      cf[6] * t.aaa[q] + cf[7] * t.aab[q] + cf[8] * t.abb[q] + cf[9] * t.bbb[q];
      const float za =
          cf[1] + 2.0f * cf[3] * a + cf[4] * b + 3.0f * cf[6] * aa + 2.0f * cf[7] * ab + cf[8] * bb;
      const float zb =
          cf[2] + cf[4] * a + 2.0f * cf[5] * b + cf[7] * aa + 2.0f * cf[8] * ab + 3.0f * cf[9] * bb;
      const float sq = z - za * a - zb * b;
      const float den2 = fmaxf((1.0f + za * za + zb * zb) * (aa + bb + z * z), 1e-30f);
      sk[k] = __fdiv_rn(sq, __fsqrt_rn(den2));
    }
    for (int fa = 0; fa < Sp; ++fa) {
      float rf = 0.0f, jf = 0.0f;
      for (int k = 0; k < S; ++k) {
        rf += t.ang_cos[fa * S + k] * sk[k];
        jf += t.ang_sin[fa * S + k] * sk[k];
      }
      for (int fr = 0; fr < Rp; ++fr) {
        const float tc = t.rad_cos[fr * R + l], ts = t.rad_sin[fr * R + l];
        acc_re[fr * Sp + fa] += rf * tc - jf * ts;
        acc_im[fr * Sp + fa] += rf * ts + jf * tc;
      }
    }
  }
  const double norm = 1.0 / (static_cast<double>(R) * S);
  for (int d = 0; d < D; ++d)
    out[d] = static_cast<float>(sqrt(acc_re[d] * acc_re[d] + acc_im[d] * acc_im[d]) * norm);
}

// ---------------------------------------------------------------------------------------------
// Keypoint refinement (dog_keypoint.cpp: newtonSteps), a block per keypoint. Each Newton step
// evaluates R on the 3 x 3 grid one grid point at a time: the block's threads add the disc's
// moments (the CPU's float and double expressions per sample), a tree of partial sums adds the
// threads' (so the sums' order differs from the CPU's), thread 0 solves and steps.

constexpr int kRefineThreads = 128;

__device__ double interceptOf(const double* m) {
  double M[3][3] = {{m[0], m[1], m[2]}, {m[1], m[3], m[4]}, {m[2], m[4], m[5]}};
  double v[3] = {m[6], m[7], m[8]};
  ldltSolve<3, false>(M, v);
  return v[0];
}

__global__ void __launch_bounds__(kRefineThreads)
    refineKernel(int nk, double h0, const std::uint32_t* disc_begin, const float4* samples,
                 const float* frames, const float* scales, const char* maximum, float* y_out,
                 char* ok_out) {
  const int k = blockIdx.x;
  if (k >= nk) return;
  __shared__ double s_part[kRefineThreads / 32][18];
  __shared__ double s_val[9];
  __shared__ float s_y[2];
  __shared__ float s_step;
  __shared__ int s_go;
  const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
  const unsigned b0 = disc_begin[k], b1 = disc_begin[k + 1];
  const float scale = scales[k];
  const double ha = dog_refinement::kInnerScale * scale,
               hb = dog_refinement::kOuterScale * scale;
  const float inv_b2 = static_cast<float>(1.0 / (hb * hb));
  const double inv_hb = 1.0 / hb;
  if (tid == 0) {
    s_y[0] = 0.0f;
    s_y[1] = 0.0f;
    s_step = static_cast<float>(0.5 * h0);
    s_go = 1;
  }
  __syncthreads();
  bool ok = true;
  for (int it = 0; it < dog_refinement::kNewtonSteps; ++it) {
    const float y0 = s_y[0], y1 = s_y[1], step = s_step;
    const float c = expf(-step * step * inv_b2);
    for (int g = 0; g < 9; ++g) {
      const int gx = g / 3, gy = g % 3;
      double acc[18];
#pragma unroll
      for (int i = 0; i < 18; ++i) acc[i] = 0.0;
      for (unsigned s = b0 + tid; s < b1; s += kRefineThreads) {
        const float4 l = samples[s];
        const float da = l.x - y0, db = l.y - y1, z = l.z;
        const float base = expf(-(da * da + db * db + z * z) * inv_b2) * l.w;
        const float ex = expf(2.0f * step * da * inv_b2), ey = expf(2.0f * step * db * inv_b2);
        const float fx = gx == 0 ? c / ex : (gx == 1 ? 1.0f : c * ex);
        const float fy = gy == 0 ? c / ey : (gy == 1 ? 1.0f : c * ey);
        const float eb = base * fx * fy;
        const float r = eb / l.w, r2 = r * r;
        const float ea = r2 * r2 * l.w;
        const double a = (da - (gx - 1) * step) * inv_hb, b = (db - (gy - 1) * step) * inv_hb;
        const double t[9] = {1.0, a, b, a * a, a * b, b * b, z, a * z, b * z};
#pragma unroll
        for (int i = 0; i < 9; ++i) {
          acc[i] += eb * t[i];
          acc[9 + i] += ea * t[i];
        }
      }
#pragma unroll
      for (int i = 0; i < 18; ++i) {
        double v = acc[i];
        for (int off = 16; off > 0; off >>= 1) v += __shfl_down_sync(0xffffffffu, v, off);
        if (lane == 0) s_part[warp][i] = v;
      }
      __syncthreads();
      if (tid == 0) {
        double m[18];
        for (int i = 0; i < 18; ++i) {
          m[i] = s_part[0][i];
          for (int w = 1; w < kRefineThreads / 32; ++w) m[i] += s_part[w][i];
        }
        s_val[g] = (interceptOf(m) - interceptOf(m + 9)) / ha;
      }
      __syncthreads();
    }
    if (tid == 0) {
      // The quadratic through the 9 values, then the step (newtonSteps, line by line).
      double A[6][6] = {}, rhs[6] = {};
      for (int gx = -1; gx <= 1; ++gx)
        for (int gy = -1; gy <= 1; ++gy) {
          const double phi[6] = {
              1.0, double(gx), double(gy), double(gx * gx), double(gx * gy), double(gy * gy)};
          for (int i = 0; i < 6; ++i) {
            for (int j = 0; j < 6; ++j) A[i][j] += phi[i] * phi[j];
            rhs[i] += s_val[3 * (gx + 1) + (gy + 1)] * phi[i];
          }
        }
      ldltSolve<6, false>(A, rhs);
      const double* co = rhs;
      bool finite = true;
      for (int i = 0; i < 6; ++i) finite = finite && isfinite(co[i]);
      int go = 0;
      if (finite) {
        const double h00 = 2.0 * co[3], h01 = co[4], h11 = 2.0 * co[5];
        const double g0 = co[1], g1 = co[2];
        const bool is_max = maximum[k] != 0;
        const double det = h00 * h11 - h01 * h01, tr = h00 + h11;
        double st0 = 0.0, st1 = 0.0;
        bool stepped = true;
        if (det > 0.0 && (is_max ? tr < 0.0 : tr > 0.0)) {
          const double inv = 1.0 / det;  // Eigen's 2 x 2 inverse: cofactors times 1 / det
          const double i00 = h11 * inv, i01 = -h01 * inv, i10 = -h01 * inv, i11 = h00 * inv;
          st0 = -i00 * g0 + -i01 * g1;
          st1 = -i10 * g0 + -i11 * g1;
        } else {
          const double gn = sqrt(g0 * g0 + g1 * g1);
          if (gn > 0.0) {
            const double sgn = is_max ? 1.0 : -1.0;
            st0 = sgn * (g0 / gn);
            st1 = sgn * (g1 / gn);
          } else {
            stepped = false;
          }
        }
        if (stepped) {
          double sn = sqrt(st0 * st0 + st1 * st1);
          if (sn > 1.5) {
            const double f = 1.5 / sn;
            st0 *= f;
            st1 *= f;
            sn = sqrt(st0 * st0 + st1 * st1);
          }
          const float y0n = s_y[0] + step * static_cast<float>(st0);
          const float y1n = s_y[1] + step * static_cast<float>(st1);
          s_y[0] = y0n;
          s_y[1] = y1n;
          const float* f = frames + 12 * static_cast<long long>(k);
          float d2 = 0.0f;
          for (int c3 = 0; c3 < 3; ++c3) {
            const float e = f[c3] + y0n * f[3 + c3] + y1n * f[6 + c3] - f[9 + c3];
            d2 += e * e;
          }
          ok = sqrtf(d2) <= static_cast<float>(3.0 * h0);
          go = ok && !(step * sn < dog_refinement::kConverged * h0);
          if (go && sn < 0.5) s_step = step * 0.5f;
        }
      }
      s_go = go;
    }
    __syncthreads();
    if (!s_go) break;
  }
  if (tid == 0) {
    y_out[2 * k] = s_y[0];
    y_out[2 * k + 1] = s_y[1];
    ok_out[k] = ok ? 1 : 0;
  }
}

inline int blocksFor(long long n, int per_block) {
  return static_cast<int>((n + per_block - 1) / per_block);
}

}  // namespace

struct FeatureBlock::Impl {
  int n = 0, levels = 0, D = 0;
  DeviceArray<FeatureFrame> frames;
  DeviceArray<float> xyz, normals, ref;
  DeviceArray<long long> offsets;
  DeviceArray<int> rows;
  DeviceArray<float> sqr;
  DeviceArray<float> level_data;  // levels x n x 6
  DeviceArray<float> curvature0;
  DeviceArray<float> signatures;
};

FeatureBlock::FeatureBlock() : impl_(new Impl) {}
FeatureBlock::~FeatureBlock() { delete impl_; }

void FeatureBlock::launch(const FeatureBlockArgs& args) {
  Impl& d = *impl_;
  const int n = args.n;
  d.n = n;
  d.levels = static_cast<int>(args.steps_per_level.size());
  const int nframes = static_cast<int>(args.frames.size());
  if (n <= 0 || nframes == 0) return;
  if (args.signatures && (args.angular > kMaxS || args.angular_freqs > kMaxSp ||
                          args.radial_freqs * args.angular_freqs > kMaxD))
    throw DeviceError("GPU features: the signature layout is larger than the GPU kernel's limits");
  d.frames.upload(args.frames);
  d.xyz.upload(args.xyz, 3 * static_cast<std::size_t>(n));
  d.normals.upload(args.normals, 3 * static_cast<std::size_t>(n));
  d.ref.upload(args.ref, 3 * static_cast<std::size_t>(n));
  const int tb = 256;

  // 1. The grid: keys, sorted with their points.
  {
    DeviceArray<long long> keys(n), sorted_keys(n);
    DeviceArray<int> vals(n), order(n);
    keysKernel<<<blocksFor(n, tb), tb>>>(n, d.xyz.ptr(), d.frames.ptr(), nframes, keys.ptr(),
                                         vals.ptr());
    cudaCheckLaunch();
    std::size_t temp_bytes = 0;
    cudaSafeCall(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, keys.ptr(), sorted_keys.ptr(),
                                                 vals.ptr(), order.ptr(), n));
    DeviceMemory temp(std::max<std::size_t>(temp_bytes, 1));
    cudaSafeCall(cub::DeviceRadixSort::SortPairs(temp.rawPtr(), temp_bytes, keys.ptr(),
                                                 sorted_keys.ptr(), vals.ptr(), order.ptr(), n));
    keys.release();
    vals.release();
    DeviceArray<float> sorted_xyz(3 * static_cast<std::size_t>(n));
    gatherSortedKernel<<<blocksFor(n, tb), tb>>>(n, d.xyz.ptr(), order.ptr(), sorted_xyz.ptr());
    cudaCheckLaunch();

    // 2. The rows: counts, offsets, then the rows themselves.
    DeviceArray<long long> counts(n);
    d.offsets.create(static_cast<std::size_t>(n) + 1);
    const int wb = blocksFor(n, kWarpsPerBlock), wt = 32 * kWarpsPerBlock;
    rowsKernel<false><<<wb, wt>>>(n, d.xyz.ptr(), d.frames.ptr(), nframes, sorted_keys.ptr(),
                                  sorted_xyz.ptr(), order.ptr(), args.cap, counts.ptr(), nullptr,
                                  nullptr, nullptr);
    cudaCheckLaunch();
    cudaSafeCall(cudaMemset(d.offsets.ptr(), 0, sizeof(long long)));
    temp_bytes = 0;
    cudaSafeCall(
        cub::DeviceScan::InclusiveSum(nullptr, temp_bytes, counts.ptr(), d.offsets.ptr() + 1, n));
    DeviceMemory scan_temp(std::max<std::size_t>(temp_bytes, 1));
    cudaSafeCall(cub::DeviceScan::InclusiveSum(scan_temp.rawPtr(), temp_bytes, counts.ptr(),
                                               d.offsets.ptr() + 1, n));
    long long entries = 0;
    cudaSafeCall(
        cudaMemcpy(&entries, d.offsets.ptr() + n, sizeof(long long), cudaMemcpyDeviceToHost));
    d.rows.create(static_cast<std::size_t>(entries));
    d.sqr.create(static_cast<std::size_t>(entries));
    rowsKernel<true><<<wb, wt>>>(n, d.xyz.ptr(), d.frames.ptr(), nframes, sorted_keys.ptr(),
                                 sorted_xyz.ptr(), order.ptr(), args.cap, nullptr, d.offsets.ptr(),
                                 d.rows.ptr(), d.sqr.ptr());
    cudaCheckLaunch();
  }

  // 3. The diffusion: n_i projections for level i, each from the last one's normals.
  d.level_data.create(static_cast<std::size_t>(d.levels) * 6 * n);
  d.curvature0.create(n);
  {
    DeviceArray<float> cur(3 * static_cast<std::size_t>(n)), next(3 * static_cast<std::size_t>(n));
    DeviceArray<float> ref(3 * static_cast<std::size_t>(n)),
        next_ref(3 * static_cast<std::size_t>(n));
    d.xyz.copyTo(cur);
    d.ref.copyTo(ref);
    int done = 0;
    for (int l = 0; l < d.levels; ++l) {
      while (done < args.steps_per_level[l]) {
        // Level 0 is one projection (n_0 = 1): its curvature is that of the first step.
        projectKernel<<<blocksFor(n, tb), tb>>>(n, d.frames.ptr(), nframes, d.offsets.ptr(),
                                                d.rows.ptr(), d.sqr.ptr(), cur.ptr(), ref.ptr(),
                                                done == 0, next.ptr(), next_ref.ptr(),
                                                done == 0 ? d.curvature0.ptr() : nullptr);
        cudaCheckLaunch();
        std::swap(cur, next);
        std::swap(ref, next_ref);
        ++done;
      }
      storeLevelKernel<<<blocksFor(n, tb), tb>>>(
          n, cur.ptr(), ref.ptr(), d.level_data.ptr() + static_cast<std::size_t>(l) * 6 * n);
      cudaCheckLaunch();
    }
  }

  // 4. Signatures.
  d.D = args.radial_freqs * args.angular_freqs;
  if (!args.signatures) return;
  DeviceArray<float> sig_normals(3 * static_cast<std::size_t>(n));
  signatureNormalsKernel<<<blocksFor(n, tb), tb>>>(n, d.normals.ptr(), d.level_data.ptr(),
                                                   sig_normals.ptr());
  cudaCheckLaunch();
  DeviceArray<float> tables;
  tables.upload(args.disc_tables);
  const int R = args.radial, S = args.angular, Rp = args.radial_freqs, Sp = args.angular_freqs;
  const std::size_t Q = static_cast<std::size_t>(R) * S;
  if (args.disc_tables.size() != 9 * Q + 2 * static_cast<std::size_t>(Sp) * S + 2 * Rp * R)
    throw DeviceError("GPU features: the signature tables have the wrong size");
  const float* tp = tables.ptr();
  DiscTables tab;
  const float** slots[] = {&tab.a,   &tab.b,   &tab.aa,  &tab.ab, &tab.bb,
                           &tab.aaa, &tab.aab, &tab.abb, &tab.bbb};
  for (const float** sl : slots) {
    *sl = tp;
    tp += Q;
  }
  tab.ang_cos = tp;
  tp += static_cast<std::size_t>(Sp) * S;
  tab.ang_sin = tp;
  tp += static_cast<std::size_t>(Sp) * S;
  tab.rad_cos = tp;
  tp += static_cast<std::size_t>(Rp) * R;
  tab.rad_sin = tp;
  d.signatures.create(static_cast<std::size_t>(n) * d.D);
  SignatureArgs s{};
  s.n = n;
  s.nframes = nframes;
  s.maxfit = args.max_fit_points;
  s.R = R;
  s.S = S;
  s.Rp = Rp;
  s.Sp = Sp;
  s.frames = d.frames.ptr();
  s.offsets = d.offsets.ptr();
  s.rows = d.rows.ptr();
  s.sqr = d.sqr.ptr();
  s.xyz = d.xyz.ptr();
  s.normals = sig_normals.ptr();
  s.tab = tab;
  s.out = d.signatures.ptr();
  signatureKernel<<<blocksFor(n, 128), 128>>>(s);
  cudaCheckLaunch();
  // The tables and normals are freed when this returns: wait for the kernel first.
  cudaSafeCall(cudaDeviceSynchronize());
}

void refineKeypoints(int nk, double h0, const std::uint32_t* disc_begin, const float* samples,
                     const float* frames, const float* scales, const char* maximum, float* y,
                     char* ok) {
  if (nk == 0) return;
  const std::size_t k = static_cast<std::size_t>(nk);
  DeviceArray<std::uint32_t> d_begin(disc_begin, k + 1);
  DeviceArray<float> d_samples(samples, 4 * std::size_t{disc_begin[k]});
  DeviceArray<float> d_frames(frames, 12 * k);
  DeviceArray<float> d_scales(scales, k);
  DeviceArray<char> d_max(maximum, k);
  DeviceArray<float> d_y(2 * k);
  DeviceArray<char> d_ok(k);
  refineKernel<<<nk, kRefineThreads>>>(
      nk, h0, d_begin.ptr(), reinterpret_cast<const float4*>(d_samples.ptr()), d_frames.ptr(),
      d_scales.ptr(), d_max.ptr(), d_y.ptr(), d_ok.ptr());
  cudaCheckLaunch();
  d_y.download(y);
  d_ok.download(ok);
}

void FeatureBlock::fetchLevel(int level, float* out) const {
  const Impl& d = *impl_;
  if (level < 0 || level >= d.levels) throw DeviceError("GPU features: no such level");
  cudaSafeCall(cudaMemcpy(out, d.level_data.ptr() + static_cast<std::size_t>(level) * 6 * d.n,
                          sizeof(float) * 6 * d.n, cudaMemcpyDeviceToHost));
}

void FeatureBlock::fetchCurvature(float* out) const { impl_->curvature0.download(out); }

void FeatureBlock::fetchSignatures(float* out) const { impl_->signatures.download(out); }

void FeatureBlock::fetchRows(std::vector<long long>& offsets, std::vector<int>& indices,
                             std::vector<float>& sqr_distances) const {
  impl_->offsets.download(offsets);
  impl_->rows.download(indices);
  impl_->sqr.download(sqr_distances);
}

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
