// The motion method's sample tracking on the GPU (segmentation/tracking_device.h): one warp per
// (frame, sample) fit, one kernel launch per wave of fits that depend only on earlier waves.
//
// Each warp does what the CPU's task does (src/segmentation/motion_tracking.cpp, trackSamplesOn
// step 3, with icp() and residual() there): score every start on the sample's probe, refine the
// two best by damped point-to-plane ICP of its neighbourhood, keep the fit of lower residual.
// The lanes share the points of a source; sums are reduced across the warp with xor shuffles,
// which leave the same bits in every lane, so every lane takes the same decisions and solves the
// same 6 x 6 system without a broadcast. Nearest points come from a copy of the frame's
// FlatKdTree3 with the same walk and the same float distances (no fused multiply-add), so a
// query finds the CPU's point; the sums run in another order than the CPU's, so poses agree to
// rounding. Written by us: no kept library fits many small ICPs at once on a GPU.
#include <pcl_animseg/gpu/device_array.h>

#include <cfloat>
#include <chrono>
#include <cmath>

#include "cuda_check.h"
#include "tracking_kernels.h"

namespace pcl_animseg {
namespace gpu {
namespace detail {

namespace {

constexpr int kWarp = 32;
constexpr int kWarpsPerBlock = 4;
constexpr int kMaxDepth = 64;  // FlatKdTree3's stack bound

struct Dev {
  const TrackNode* nodes;
  const float4* pts;
  const float4* nrm;
  const int* root;
  const double* spacing;
  const int* unoriented;
  const double* source;
  const int* source_begin;
  const double* probe;
  const int* probe_begin;
  const int* adj;
  const int* adj_begin;
  const int* level;
  const int* before;
  const int* two_before;
  const double* global;
  double* poses;
  double* residual;
  int S;
  int iterations;
  double normal_cos;
  double clip;
};

struct Pose {
  double r[9];
  double t[3];
};

__device__ Pose loadPose(const double* p) {
  Pose a;
  for (int k = 0; k < 9; ++k) a.r[k] = p[k];
  for (int k = 0; k < 3; ++k) a.t[k] = p[9 + k];
  return a;
}

__device__ void storePose(double* p, const Pose& a) {
  for (int k = 0; k < 9; ++k) p[k] = a.r[k];
  for (int k = 0; k < 3; ++k) p[9 + k] = a.t[k];
}

__device__ Pose mul(const Pose& a, const Pose& b) {
  Pose c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j)
      c.r[3 * i + j] =
          a.r[3 * i] * b.r[j] + a.r[3 * i + 1] * b.r[3 + j] + a.r[3 * i + 2] * b.r[6 + j];
    c.t[i] = a.r[3 * i] * b.t[0] + a.r[3 * i + 1] * b.t[1] + a.r[3 * i + 2] * b.t[2] + a.t[i];
  }
  return c;
}

__device__ Pose inverse(const Pose& a) {  // a rigid motion: R^T, -R^T t
  Pose b;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) b.r[3 * i + j] = a.r[3 * j + i];
  for (int i = 0; i < 3; ++i)
    b.t[i] = -(b.r[3 * i] * a.t[0] + b.r[3 * i + 1] * a.t[1] + b.r[3 * i + 2] * a.t[2]);
  return b;
}

__device__ void rotate(const Pose& a, const double* v, double* out) {
  for (int i = 0; i < 3; ++i)
    out[i] = a.r[3 * i] * v[0] + a.r[3 * i + 1] * v[1] + a.r[3 * i + 2] * v[2];
}

__device__ void apply(const Pose& a, const double* v, double* out) {
  rotate(a, v, out);
  for (int i = 0; i < 3; ++i) out[i] += a.t[i];
}

__device__ __forceinline__ double warpSum(double v) {
  for (int m = kWarp / 2; m > 0; m /= 2) v += __shfl_xor_sync(0xffffffffu, v, m);
  return v;
}

__device__ __forceinline__ int warpSum(int v) {
  for (int m = kWarp / 2; m > 0; m /= 2) v += __shfl_xor_sync(0xffffffffu, v, m);
  return v;
}

// FlatKdTree3::nearest (flat_kdtree.h) on the frame's copy: the nearest point with squared
// distance < bound2, or -1. Distances in the CPU's float order, without contraction.
__device__ int nearest(const Dev& d, int root, float qx, float qy, float qz, float bound2,
                       float& d2) {
  if (root < 0) return -1;
  struct Entry {
    int node;
    float min_d2;
  };
  Entry stack[kMaxDepth];
  int top = 0;
  float best = bound2;
  int best_i = -1;
  stack[top++] = {root, 0.0f};
  while (top > 0) {
    const Entry e = stack[--top];
    if (!(e.min_d2 < best)) continue;
    int n = e.node;
    TrackNode nd = d.nodes[n];
    while (nd.dim >= 0) {
      const float q = nd.dim == 0 ? qx : (nd.dim == 1 ? qy : qz);
      const float diff = __fsub_rn(q, nd.split);
      const float far_d2 = fmaxf(e.min_d2, __fmul_rn(diff, diff));
      if (far_d2 < best && top < kMaxDepth) stack[top++] = {diff < 0.0f ? nd.b : nd.a, far_d2};
      n = diff < 0.0f ? nd.a : nd.b;
      nd = d.nodes[n];
    }
    for (int i = nd.a; i < nd.b; ++i) {
      const float4 p = d.pts[i];
      const float d0 = __fsub_rn(qx, p.x), d1 = __fsub_rn(qy, p.y), dz = __fsub_rn(qz, p.z);
      const float dist =
          __fadd_rn(__fadd_rn(__fmul_rn(d0, d0), __fmul_rn(d1, d1)), __fmul_rn(dz, dz));
      if (dist < best) best = dist, best_i = i;
    }
  }
  if (best_i >= 0) d2 = best;
  return best_i;
}

// KdTree::nearest (kdtree.h): within sqrt(max_d2) inclusive, -1 for a non-finite query.
__device__ int nearestWithin(const Dev& d, int frame, const double* y, float max_d2, float& d2) {
  const float qx = static_cast<float>(y[0]), qy = static_cast<float>(y[1]),
              qz = static_cast<float>(y[2]);
  if (!isfinite(qx) || !isfinite(qy) || !isfinite(qz)) return -1;
  return nearest(d, d.root[frame], qx, qy, qz, nextafterf(max_d2, FLT_MAX), d2);
}

__device__ double normalCos(double c, const Dev& d, int frame) {
  return d.unoriented[frame] ? fabs(c) : c;
}

// motion_tracking.cpp's surfaceError: squared clipped surface error in spacings^2.
__device__ double surfaceError(const Dev& d, int frame, const double* y, const double* n) {
  const double clip2 = d.clip * d.clip;
  const double spacing = d.spacing[frame];
  const double bound = (d.clip + 1.5) * spacing;
  float d2;
  const int k = nearestWithin(d, frame, y, static_cast<float>(bound * bound), d2);
  if (k < 0) return clip2;
  const float4 tn = d.nrm[k];
  const float4 tp = d.pts[k];
  if (normalCos(n[0] * tn.x + n[1] * tn.y + n[2] * tn.z, d, frame) <= d.normal_cos) return clip2;
  const double inv_s = 1.0 / spacing;
  const double pl = ((y[0] - tp.x) * tn.x + (y[1] - tp.y) * tn.y + (y[2] - tp.z) * tn.z) * inv_s;
  const double far = fmax(0.0, sqrt(static_cast<double>(d2)) * inv_s - 1.5);
  return fmin(clip2, pl * pl + far * far);
}

// RMS surface error of a source (6 doubles per point) under a pose; the same in every lane.
__device__ double residual(const Dev& d, int frame, const double* src, int m, const Pose& T,
                           int lane) {
  if (m == 0) return 0.0;
  double sum = 0.0;
  for (int i = lane; i < m; i += kWarp) {
    double y[3], n[3];
    apply(T, src + 6 * i, y);
    rotate(T, src + 6 * i + 3, n);
    sum += surfaceError(d, frame, y, n);
  }
  return sqrt(warpSum(sum) / static_cast<double>(m));
}

// Upper triangle of a symmetric 6 x 6 matrix, row by row.
__device__ __forceinline__ int upper(int i, int j) { return i * 6 - i * (i - 1) / 2 + (j - i); }

// motion_tracking.cpp's icp(): damped point-to-plane ICP with a weak point-to-point term.
__device__ Pose icp(const Dev& d, int frame, const double* src, int m, const Pose& init,
                    double max_dist, int lane) {
  Pose T = init;
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  const double spacing = d.spacing[frame];
  for (int it = 0; it < d.iterations; ++it) {
    double c[3] = {0.0, 0.0, 0.0};
    for (int i = lane; i < m; i += kWarp) {
      double y[3];
      apply(T, src + 6 * i, y);
      for (int k = 0; k < 3; ++k) c[k] += y[k];
    }
    for (int k = 0; k < 3; ++k) c[k] = warpSum(c[k]) / static_cast<double>(m > 1 ? m : 1);
    double A[21], b[6];
    for (int k = 0; k < 21; ++k) A[k] = 0.0;
    for (int k = 0; k < 6; ++k) b[k] = 0.0;
    int used = 0;
    for (int i = lane; i < m; i += kWarp) {
      double yw[3], nr[3];
      apply(T, src + 6 * i, yw);
      float d2;
      const int k = nearestWithin(d, frame, yw, max_d2, d2);
      if (k < 0) continue;
      const float4 tnf = d.nrm[k], tpf = d.pts[k];
      const double tn[3] = {tnf.x, tnf.y, tnf.z}, tp[3] = {tpf.x, tpf.y, tpf.z};
      rotate(T, src + 6 * i + 3, nr);
      if (normalCos(nr[0] * tn[0] + nr[1] * tn[1] + nr[2] * tn[2], d, frame) < d.normal_cos)
        continue;
      const double y[3] = {yw[0] - c[0], yw[1] - c[1], yw[2] - c[2]};
      ++used;
      double J[6] = {y[1] * tn[2] - y[2] * tn[1],
                     y[2] * tn[0] - y[0] * tn[2],
                     y[0] * tn[1] - y[1] * tn[0],
                     tn[0],
                     tn[1],
                     tn[2]};
      const double r = (yw[0] - tp[0]) * tn[0] + (yw[1] - tp[1]) * tn[1] + (yw[2] - tp[2]) * tn[2];
      // Jp = [S | I], S = [[0, y.z, -y.y], [-y.z, 0, y.x], [y.y, -y.x, 0]].
      const double Jp[3][6] = {{0.0, y[2], -y[1], 1.0, 0.0, 0.0},
                               {-y[2], 0.0, y[0], 0.0, 1.0, 0.0},
                               {y[1], -y[0], 0.0, 0.0, 0.0, 1.0}};
      const double e[3] = {yw[0] - tp[0], yw[1] - tp[1], yw[2] - tp[2]};
      for (int a = 0; a < 6; ++a) {
        for (int bb = a; bb < 6; ++bb)
          A[upper(a, bb)] += J[a] * J[bb] + 0.1 * (Jp[0][a] * Jp[0][bb] + Jp[1][a] * Jp[1][bb] +
                                                   Jp[2][a] * Jp[2][bb]);
        b[a] += J[a] * r + 0.1 * (Jp[0][a] * e[0] + Jp[1][a] * e[1] + Jp[2][a] * e[2]);
      }
    }
    used = warpSum(used);
    for (int k = 0; k < 21; ++k) A[k] = warpSum(A[k]);
    for (int k = 0; k < 6; ++k) b[k] = warpSum(b[k]);
    if (used < 6) break;
    double M[6][6];
    for (int a = 0; a < 6; ++a)
      for (int bb = a; bb < 6; ++bb) M[a][bb] = M[bb][a] = A[upper(a, bb)];
    const double tr_rot = (M[0][0] + M[1][1] + M[2][2]) / 3.0 + 1e-12;
    const double tr_tr = (M[3][3] + M[4][4] + M[5][5]) / 3.0 + 1e-12;
    for (int k = 0; k < 3; ++k) M[k][k] += 0.02 * tr_rot, M[k + 3][k + 3] += 0.02 * tr_tr;
    // Cholesky of the damped (positive definite) system, then x = -M^-1 b.
    bool ok = true;
    for (int j = 0; j < 6 && ok; ++j) {
      double s = M[j][j];
      for (int k = 0; k < j; ++k) s -= M[j][k] * M[j][k];
      if (!(s > 0.0)) {
        ok = false;
        break;
      }
      M[j][j] = sqrt(s);
      for (int i = j + 1; i < 6; ++i) {
        double v = M[i][j];
        for (int k = 0; k < j; ++k) v -= M[i][k] * M[j][k];
        M[i][j] = v / M[j][j];
      }
    }
    if (!ok) break;
    double x[6];
    for (int i = 0; i < 6; ++i) {
      double v = -b[i];
      for (int k = 0; k < i; ++k) v -= M[i][k] * x[k];
      x[i] = v / M[i][i];
    }
    for (int i = 5; i >= 0; --i) {
      double v = x[i];
      for (int k = i + 1; k < 6; ++k) v -= M[k][i] * x[k];
      x[i] = v / M[i][i];
    }
    bool finite = true;
    for (int k = 0; k < 6; ++k) finite = finite && isfinite(x[k]);
    if (!finite) break;
    const double angle = sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]);
    Pose D;
    for (int k = 0; k < 9; ++k) D.r[k] = (k % 4 == 0) ? 1.0 : 0.0;
    if (angle > 1e-12) {  // Eigen's AngleAxis::toRotationMatrix
      const double ax = x[0] / angle, ay = x[1] / angle, az = x[2] / angle;
      const double s = sin(angle), co = cos(angle), o = 1.0 - co;
      D.r[0] = o * ax * ax + co;
      D.r[4] = o * ay * ay + co;
      D.r[8] = o * az * az + co;
      D.r[1] = o * ax * ay - s * az;
      D.r[3] = o * ax * ay + s * az;
      D.r[2] = o * ax * az + s * ay;
      D.r[6] = o * ax * az - s * ay;
      D.r[5] = o * ay * az - s * ax;
      D.r[7] = o * ay * az + s * ax;
    }
    // y' = dR (y - c) + c + dt.
    double rc[3];
    rotate(D, c, rc);
    for (int k = 0; k < 3; ++k) D.t[k] = c[k] - rc[k] + x[3 + k];
    T = mul(D, T);
    const double step = sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5]);
    if (angle < 1e-4 && step < 1e-3 * spacing) break;
  }
  return T;
}

// The start `c` of a task: 0 the previous pose, 1 the body's motion since the previous frame
// applied to it, 2 (when there is a frame two before) a constant-velocity guess, then the poses
// of the sample's graph neighbours of lower level in this frame (trackSamplesOn's order).
__device__ Pose start(const Dev& d, int t, int s, int c) {
  const int S = d.S, tp = d.before[t], tpp = d.two_before[t];
  const Pose prev = loadPose(d.poses + (static_cast<long long>(tp) * S + s) * kPoseDoubles);
  if (c == 0) return prev;
  if (c == 1)
    return mul(
        mul(loadPose(d.global + t * kPoseDoubles), inverse(loadPose(d.global + tp * kPoseDoubles))),
        prev);
  if (tpp >= 0) {
    if (c == 2)
      return mul(mul(prev, inverse(loadPose(d.poses +
                                            (static_cast<long long>(tpp) * S + s) * kPoseDoubles))),
                 prev);
    --c;
  }
  c -= 2;
  const int* lev = d.level + static_cast<long long>(t) * S;
  for (int j = d.adj_begin[s]; j < d.adj_begin[s + 1]; ++j) {
    const int o = d.adj[j];
    if (lev[o] < lev[s] && c-- == 0)
      return loadPose(d.poses + (static_cast<long long>(t) * S + o) * kPoseDoubles);
  }
  return prev;  // not reached: c < number of starts
}

__global__ void trackWave(Dev d, const int* __restrict__ tasks, int n) {
  const int w = (blockIdx.x * blockDim.x + threadIdx.x) / kWarp;
  const int lane = threadIdx.x % kWarp;
  if (w >= n) return;  // the whole warp
  const int task = tasks[w];
  const int S = d.S, t = task / S, s = task % S;
  const int* lev = d.level + static_cast<long long>(t) * S;
  int starts = d.two_before[t] >= 0 ? 3 : 2;
  for (int j = d.adj_begin[s]; j < d.adj_begin[s + 1]; ++j)
    if (lev[d.adj[j]] < lev[s]) ++starts;
  // The two best starts on the probe, ties to the earlier start (a stable sort's first two).
  const double* probe = d.probe + 6LL * d.probe_begin[s];
  const int pm = d.probe_begin[s + 1] - d.probe_begin[s];
  double s0 = DBL_MAX, s1 = DBL_MAX;
  int i0 = -1, i1 = -1;
  for (int c = 0; c < starts; ++c) {
    const double r = residual(d, t, probe, pm, start(d, t, s, c), lane);
    if (i0 < 0 || r < s0) {
      s1 = s0, i1 = i0;
      s0 = r, i0 = c;
    } else if (i1 < 0 || r < s1) {
      s1 = r, i1 = c;
    }
  }
  const double* src = d.source + 6LL * d.source_begin[s];
  const int m = d.source_begin[s + 1] - d.source_begin[s];
  double best = DBL_MAX;
  Pose best_pose = start(d, t, s, i0);
  const int tried[2] = {i0, i1};
  for (int k = 0; k < 2; ++k) {
    if (tried[k] < 0) continue;
    const Pose fit = icp(d, t, src, m, start(d, t, s, tried[k]), 4.0 * d.spacing[t], lane);
    const double r = residual(d, t, src, m, fit, lane);
    if (r < best) best = r, best_pose = fit;
  }
  if (lane == 0) {
    storePose(d.poses + static_cast<long long>(task) * kPoseDoubles, best_pose);
    d.residual[task] = best;
  }
}

}  // namespace

double runTracking(const TrackingArrays& in, std::vector<double>& poses,
                   std::vector<double>& residual) {
  const auto t0 = std::chrono::steady_clock::now();
  const long long TS = static_cast<long long>(in.frames) * in.samples;
  DeviceArray<TrackNode> nodes(in.nodes.data(), in.nodes.size());
  DeviceArray<float> pts(in.points.data(), in.points.size());
  DeviceArray<float> nrm(in.normals.data(), in.normals.size());
  DeviceArray<int> root(in.root.data(), in.root.size());
  DeviceArray<double> spacing(in.spacing.data(), in.spacing.size());
  DeviceArray<int> unoriented(in.unoriented.data(), in.unoriented.size());
  DeviceArray<double> source(in.source.data(), in.source.size());
  DeviceArray<int> source_begin(in.source_begin.data(), in.source_begin.size());
  DeviceArray<double> probe(in.probe.data(), in.probe.size());
  DeviceArray<int> probe_begin(in.probe_begin.data(), in.probe_begin.size());
  DeviceArray<int> adj(in.adjacency.data(), in.adjacency.size());
  DeviceArray<int> adj_begin(in.adjacency_begin.data(), in.adjacency_begin.size());
  DeviceArray<int> level(in.level.data(), in.level.size());
  DeviceArray<int> before(in.before.data(), in.before.size());
  DeviceArray<int> two_before(in.two_before.data(), in.two_before.size());
  DeviceArray<double> global(in.global.data(), in.global.size());
  DeviceArray<int> tasks(in.tasks.data(), in.tasks.size());
  // Every pose starts as the identity (the reference frame's stay so).
  poses.assign(static_cast<std::size_t>(TS) * kPoseDoubles, 0.0);
  for (long long i = 0; i < TS; ++i)
    for (int k = 0; k < 9; k += 4) poses[static_cast<std::size_t>(i) * kPoseDoubles + k] = 1.0;
  DeviceArray<double> d_poses(poses.data(), poses.size());
  DeviceArray<double> d_res(static_cast<std::size_t>(TS));
  d_res.setZero();

  Dev d;
  d.nodes = nodes.ptr();
  d.pts = reinterpret_cast<const float4*>(pts.ptr());
  d.nrm = reinterpret_cast<const float4*>(nrm.ptr());
  d.root = root.ptr();
  d.spacing = spacing.ptr();
  d.unoriented = unoriented.ptr();
  d.source = source.ptr();
  d.source_begin = source_begin.ptr();
  d.probe = probe.ptr();
  d.probe_begin = probe_begin.ptr();
  d.adj = adj.ptr();
  d.adj_begin = adj_begin.ptr();
  d.level = level.ptr();
  d.before = before.ptr();
  d.two_before = two_before.ptr();
  d.global = global.ptr();
  d.poses = d_poses.ptr();
  d.residual = d_res.ptr();
  d.S = in.samples;
  d.iterations = in.iterations;
  d.normal_cos = in.normal_cos;
  d.clip = in.clip;
  const int waves = static_cast<int>(in.wave_begin.size()) - 1;
  for (int w = 0; w < waves; ++w) {
    const int n = in.wave_begin[w + 1] - in.wave_begin[w];
    if (n <= 0) continue;
    const int threads = kWarp * kWarpsPerBlock;
    const int blocks = (n + kWarpsPerBlock - 1) / kWarpsPerBlock;
    trackWave<<<blocks, threads>>>(d, tasks.ptr() + in.wave_begin[w], n);
    cudaCheckLaunch();
  }
  cudaSafeCall(cudaDeviceSynchronize());
  d_poses.download(poses);
  residual.resize(static_cast<std::size_t>(TS));
  d_res.download(residual);
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
