// The motion method's fits, residuals and point costs on the GPU (segmentation/motion_device.h):
// the tracking as one warp per (frame, sample) fit and one kernel launch per wave of fits that
// depend only on earlier waves; a residual batch as one thread per point and one per residual
// for the sums (one warp per residual in very large batches); a point-cost batch as one thread
// per (point, motion, frame).
//
// Each warp of the tracking does what the CPU's task does (src/segmentation/motion_tracking.cpp,
// trackSamplesOn step 3, with icp() and residual() there): score every start on the sample's
// probe, refine the two best by damped point-to-plane ICP of its neighbourhood, keep the fit of
// lower residual. The arithmetic is the CPU's (segmentation/icp_step.h, compiled without fused
// multiply-adds); the lanes compute their points' terms and the sums add them in point order
// (sum q by lane q, through shared memory), so every lane takes the CPU's decisions and solves
// the CPU's system. Nearest points come from a copy of the frame's FlatKdTree3 with the same
// walk and the same float distances, so a query finds the CPU's point: the results are the
// CPU's bit for bit. Written by us: no kept library fits many small ICPs at once on a GPU.
#include <cooperative_groups.h>
#include <math_constants.h>
#include <pcl_animseg/gpu/device_array.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_check.h>
#include <pcl_animseg/segmentation/score_fit.h>

#include <algorithm>
#include <cfloat>
#include <chrono>
#include <climits>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <thread>

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

namespace icp_step = segmentation::icp_step;
using icp_step::Rigid;

// Per warp: the values of up to 32 points (one per lane), added in point order by the lanes that
// own the sums (sum q by lane q), so that every sum runs in the CPU's order.
constexpr int kCols = icp_step::kTerms + 1;  // the terms, then whether the point counts
struct Scratch {
  double v[kWarp][kCols];
};

// The threads that compute one fit together, each with its row of the scratch per round of
// points: a warp (the many fits of the tracking, the residuals and large batches of part fits)
// or a whole block (small batches of part fits, GroupOfBlock). share() hands thread first + q's
// `mine` (q < count) to every thread's out[q].
struct WarpGroup {
  static constexpr int kSize = kWarp;
  int rank;
  double (*v)[kCols];
  __device__ WarpGroup(int lane, Scratch& sc) : rank(lane), v(sc.v) {}
  __device__ void sync() const { __syncwarp(); }
  __device__ void share(double mine, int count, double* out, int first = 0) const {
    for (int q = 0; q < count; ++q) out[q] = __shfl_sync(0xffffffffu, mine, first + q);
  }
};
// Half of a warp (16 lanes) as one group, with 16 scratch rows of its own. The two halves of a
// warp must run the same steps on the same number of points (two starts of one sample), so that
// their shuffles and warp barriers meet.
struct HalfWarp {
  static constexpr int kSize = kWarp / 2;
  int rank;
  double (*v)[kCols];
  __device__ void sync() const { __syncwarp(); }
  __device__ void share(double mine, int count, double* out, int first = 0) const {
    for (int q = 0; q < count; ++q) out[q] = __shfl_sync(0xffffffffu, mine, first + q, kSize);
  }
};
template <int N>
struct GroupOfBlock {
  static constexpr int kSize = N;
  int rank;
  double (*v)[kCols];  // N rows, shared
  double* slot;        // kCols, shared
  __device__ void sync() const { __syncthreads(); }
  __device__ void share(double mine, int count, double* out, int first = 0) const {
    if (rank >= first && rank < first + count) slot[rank - first] = mine;
    __syncthreads();
    for (int q = 0; q < count; ++q) out[q] = slot[q];
    __syncthreads();
  }
};

// A fit per block of kWideThreads threads instead of per warp for batches of at most
// kWideFitBatch part fits: a small batch is latency-bound, and a block searches a 96-point
// source in one round per ICP iteration where a warp needs three.
constexpr int kWideThreads = 128;
constexpr long long kWideFitBatch = 512;

// FlatKdTree3::distance2 (flat_kdtree.h): the squared distance of (qx, qy, qz) and p in the CPU's
// float order, without contraction.
__device__ float distance2(float qx, float qy, float qz, const float4& p) {
  const float d0 = __fsub_rn(qx, p.x), d1 = __fsub_rn(qy, p.y), dz = __fsub_rn(qz, p.z);
  return __fadd_rn(__fadd_rn(__fmul_rn(d0, d0), __fmul_rn(d1, d1)), __fmul_rn(dz, dz));
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
      const float dist = distance2(qx, qy, qz, d.pts[i]);
      if (dist < best) best = dist, best_i = i;
    }
  }
  if (best_i >= 0) d2 = best;
  return best_i;
}

// KdTree::nearest (kdtree.h): within sqrt(max_d2) inclusive, -1 for a non-finite query. With a
// guess (`hint`, a leaf index; -1: none), usually the point's match of the ICP iteration before,
// the search is bounded by the guess's distance as well (inclusive): the walk is the same but
// leaves out cells farther than the guess, which can hold neither the nearest point nor a tie
// met before it, so the result is the same (KdTree::nearest with a hint does the same on the
// CPU). Fewer cells are pushed and visited: the ICP's searches are its latency.
__device__ int nearestWithin(const Dev& d, int frame, const double* y, float max_d2, float& d2,
                             int hint = -1) {
  const float qx = static_cast<float>(y[0]), qy = static_cast<float>(y[1]),
              qz = static_cast<float>(y[2]);
  if (!isfinite(qx) || !isfinite(qy) || !isfinite(qz)) return -1;
  float bound = nextafterf(max_d2, FLT_MAX);
  if (hint >= 0) bound = fminf(bound, nextafterf(distance2(qx, qy, qz, d.pts[hint]), FLT_MAX));
  return nearest(d, d.root[frame], qx, qy, qz, bound, d2);
}

// motion_tracking.cpp's surfaceError: a moved point (y, n) against frame `frame`.
__device__ double surfaceErrorAt(const Dev& d, int frame, const double* y, const double* n) {
  const double spacing = d.spacing[frame];
  const double bound = (d.clip + 1.5) * spacing;
  float d2 = 0.0f;
  const int k = nearestWithin(d, frame, y, static_cast<float>(bound * bound), d2);
  double tp[3] = {0.0, 0.0, 0.0}, tn[3] = {0.0, 0.0, 0.0};
  if (k >= 0) {
    const float4 a = d.pts[k], b = d.nrm[k];
    tp[0] = a.x, tp[1] = a.y, tp[2] = a.z;
    tn[0] = b.x, tn[1] = b.y, tn[2] = b.z;
  }
  return icp_step::surfaceError(k >= 0, d2, y, n, tp, tn, spacing, d.unoriented[frame] != 0,
                                d.normal_cos, d.clip);
}

// Adds column q of the scratch rows 0..rows-1 that count, in row order, to `sum` (thread q).
// Eight rows' values are read before they are added: the additions stay one after the other in
// row order (the CPU's sum), but the reads no longer wait for them. The tracking's fits took 3%
// less time on the H200 (123 -> 120 us a task at 800k).
__device__ void addRows(const double (*v)[kCols], int rows, int q, double& sum) {
  int j = 0;
  for (; j + 8 <= rows; j += 8) {
    double a[8];
    bool counts[8];
#pragma unroll
    for (int k = 0; k < 8; ++k) {
      counts[k] = v[j + k][kCols - 1] != 0.0;
      a[k] = v[j + k][q];
    }
#pragma unroll
    for (int k = 0; k < 8; ++k)
      if (counts[k]) sum += a[k];
  }
  for (; j < rows; ++j)
    if (v[j][kCols - 1] != 0.0) sum += v[j][q];
}

// RMS surface error of a source (6 doubles per point) under a pose, the errors added in point
// order (motion_tracking.cpp's residual); the same in every thread of the group.
template <class Group>
__device__ double residual(const Dev& d, int frame, const double* src, int m, const Rigid& T,
                           const Group& g) {
  if (m == 0) return 0.0;
  double sum = 0.0;
  for (int base = 0; base < m; base += Group::kSize) {
    const int i = base + g.rank;
    if (i < m) {
      double y[3], n[3];
      icp_step::apply(T, src + 6 * i, y);
      icp_step::rotate(T, src + 6 * i + 3, n);
      g.v[g.rank][0] = surfaceErrorAt(d, frame, y, n);
      g.v[g.rank][kCols - 1] = 1.0;
    }
    g.sync();
    if (g.rank == 0) addRows(g.v, min(Group::kSize, m - base), 0, sum);
    g.sync();
  }
  double total;
  g.share(sum, 1, &total);
  return sqrt(total / static_cast<double>(m));
}

// motion_tracking.cpp's icp(): the same steps (icp_step.h), the same sums in the same order.
template <class Group>
__device__ Rigid icp(const Dev& d, int frame, const double* src, int m, const Rigid& init,
                     double max_dist, const Group& g) {
  Rigid T = init;
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  const double spacing = d.spacing[frame];
  const bool unoriented = d.unoriented[frame] != 0;
  const int me = g.rank;
  // Each of this thread's points' match of the iteration before (leaf indices; -1: none), the
  // first kIcpHints rounds of points.
  constexpr int kIcpHints = 8;
  int hint[kIcpHints];
  for (int r = 0; r < kIcpHints; ++r) hint[r] = -1;
  // Thread me's point i (of round `round`): its nearest point from yw (the point under T; k, d2),
  // the search bounded by its match of the iteration before.
  auto search = [&](int i, int round, double* yw, float& d2) {
    icp_step::apply(T, src + 6 * i, yw);
    const bool hinted = round < kIcpHints;
    const int k = nearestWithin(d, frame, yw, max_d2, d2, hinted ? hint[round] : -1);
    if (hinted) hint[round] = k;
    return k;
  };
  // Its terms about the centroid c into its scratch row, flagged where they count.
  auto terms = [&](int i, const double* yw, int k, const double* c) {
    g.v[me][kCols - 1] = 0.0;
    if (k < 0) return;
    const float4 p = d.pts[k], q = d.nrm[k];
    const double tp[3] = {p.x, p.y, p.z}, tn[3] = {q.x, q.y, q.z};
    double n[3];
    icp_step::rotate(T, src + 6 * i + 3, n);
    const double cs = icp_step::dot3(n, tn);
    if (!((unoriented ? fabs(cs) : cs) < d.normal_cos)) {  // the CPU's test, NaN too
      icp_step::pointTerms(yw, c, tp, tn, g.v[me]);
      g.v[me][kCols - 1] = 1.0;
    }
  };
  // The terms of a round's `rows` points (once every row is written), added in point order: term
  // q by thread q, the count of those that count by thread kTerms.
  auto addTerms = [&](int rows, double& sum, int& used) {
    g.sync();
    if (me < icp_step::kTerms) addRows(g.v, rows, me, sum);
    if (me == icp_step::kTerms)
      for (int j = 0; j < rows; ++j) used += g.v[j][kCols - 1] != 0.0;
    g.sync();
  };
  // A source of one round with three threads to spare (the samples' 60 points on 64 threads, the
  // part fits' 96 on 128): the spare threads add the centroid while the point threads search (a
  // search does not read the centroid, only the terms do). The same sums in the same order and
  // the same searches as the rounds below, so the same bits; the centroid's sums no longer
  // precede the searches.
  const bool spare = m + 3 <= Group::kSize;
  const int first_spare = Group::kSize - 3;
  for (int it = 0; it < d.iterations; ++it) {
    double c[3] = {0.0, 0.0, 0.0};
    double sum = 0.0;
    int used = 0;
    const double count = static_cast<double>(m > 1 ? m : 1);
    if (spare) {
      if (me < m) {
        icp_step::apply(T, src + 6 * me, g.v[me]);
        g.v[me][kCols - 1] = 1.0;
      }
      g.sync();
      double mine = 0.0, yw[3];
      float d2;
      int k = -1;
      if (me >= first_spare)
        addRows(g.v, m, me - first_spare, mine);
      else if (me < m)
        k = search(me, 0, yw, d2);
      g.share(mine, 3, c, first_spare);  // its barriers end the reads of the moved points
      for (int q = 0; q < 3; ++q) c[q] /= count;
      if (me < m) terms(me, yw, k, c);
      addTerms(m, sum, used);
    } else {
      // The moved source's centroid, summed in point order by threads 0-2.
      double mine = 0.0;
      for (int base = 0; base < m; base += Group::kSize) {
        const int i = base + me;
        if (i < m) {
          icp_step::apply(T, src + 6 * i, g.v[me]);
          g.v[me][kCols - 1] = 1.0;
        }
        g.sync();
        if (me < 3) addRows(g.v, min(Group::kSize, m - base), me, mine);
        g.sync();
      }
      g.share(mine, 3, c);
      for (int k = 0; k < 3; ++k) c[k] /= count;
      // The matched points' terms, round by round (addTerms).
      for (int base = 0, round = 0; base < m; base += Group::kSize, ++round) {
        const int i = base + me;
        if (i < m) {
          double yw[3];
          float d2;
          const int k = search(i, round, yw, d2);
          terms(i, yw, k, c);
        }
        addTerms(min(Group::kSize, m - base), sum, used);
      }
    }
    // sums[q] from thread q, the count from thread 27.
    double sums[icp_step::kTerms + 1];
    g.share(me == icp_step::kTerms ? static_cast<double>(used) : sum, icp_step::kTerms + 1, sums);
    if (static_cast<int>(sums[icp_step::kTerms]) < 6) break;
    double x[6];
    if (!icp_step::solveStep(sums, x)) break;
    T = icp_step::compose(icp_step::stepMotion(x, c), T);
    if (icp_step::converged(x, spacing)) break;
  }
  return T;
}

// The start `c` of a task: 0 the previous pose, 1 the body's motion since the previous frame
// applied to it, 2 (when there is a frame two before) a constant-velocity guess, then the poses
// of the sample's graph neighbours of lower level in this frame (trackSamplesOn's order).
// A pose another block wrote during this kernel (trackTasks): read from L2, past the SM's L1,
// which may hold a line of it from before the write.
__device__ Rigid loadWritten(const double* p) {
  Rigid a;
  for (int k = 0; k < 9; ++k) a.r[k] = __ldcg(p + k);
  for (int k = 0; k < 3; ++k) a.t[k] = __ldcg(p + 9 + k);
  return a;
}

__device__ Rigid start(const Dev& d, int t, int s, int c) {
  const int S = d.S, tp = d.before[t], tpp = d.two_before[t];
  const Rigid prev = loadWritten(d.poses + (static_cast<long long>(tp) * S + s) * kPoseDoubles);
  if (c == 0) return prev;
  if (c == 1)
    return icp_step::compose(
        icp_step::compose(icp_step::load(d.global + t * kPoseDoubles),
                          icp_step::inverse(icp_step::load(d.global + tp * kPoseDoubles))),
        prev);
  if (tpp >= 0) {
    if (c == 2)
      return icp_step::compose(
          icp_step::compose(
              prev, icp_step::inverse(loadWritten(d.poses + (static_cast<long long>(tpp) * S + s) *
                                                                kPoseDoubles))),
          prev);
    --c;
  }
  c -= 2;
  const int* lev = d.level + static_cast<long long>(t) * S;
  for (int j = d.adj_begin[s]; j < d.adj_begin[s + 1]; ++j) {
    const int o = d.adj[j];
    if (lev[o] < lev[s] && c-- == 0)
      return loadWritten(d.poses + (static_cast<long long>(t) * S + o) * kPoseDoubles);
  }
  return prev;  // not reached: c < number of starts
}

// One (frame, sample) pose (motion_tracking.cpp's trackSamplesOn, step 3) by a block, its
// independent steps side by side: the starts are scored by the block's warps a few at a time
// (thread 0 keeps the two best in start order, ties to the earlier start: a stable sort's first
// two), then the ICPs from the two best starts run on the two halves of the block, each half
// with a barrier of its own. The same arithmetic and sums as the CPU, so the same pose. One ICP
// after the other on a warp or a block was most of a wave's time: 800k humanoid, 349 waves of
// 47 000 tasks, 0.109 s -> 0.060 s on the H100 machine.
constexpr int kTrackWarps = 4;
constexpr int kTrackThreads = kTrackWarps * kWarp;

// Half of a block as one group (GroupOfBlock's interface): named barrier 1 + half.
struct HalfBlock {
  static constexpr int kSize = kTrackThreads / 2;
  int rank;
  int half;
  double (*v)[kCols];  // kSize rows, shared
  double* slot;        // kCols, shared
  __device__ void sync() const {
    asm volatile("bar.sync %0, %1;" ::"r"(1 + half), "r"(kSize) : "memory");
  }
  __device__ void share(double mine, int count, double* out, int first = 0) const {
    if (rank >= first && rank < first + count) slot[rank - first] = mine;
    sync();
    for (int q = 0; q < count; ++q) out[q] = slot[q];
    sync();
  }
};

// Pose i of n the identity, as icp_step::store lays a pose out.
__global__ void identityPoses(double* poses, long long n) {
  const long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x;
  if (i < n) icp_step::store(icp_step::identity(), poses + i * kPoseDoubles);
}

// Waits (thread 0) until task i's pose is written (done[i] set after a fence by its block).
__device__ void waitDone(const int* done, long long i) {
  while (*reinterpret_cast<const volatile int*>(done + i) == 0) __nanosleep(64);
}

// Every task, each as soon as the poses its starts read are written: the blocks take the tasks
// in the waves' order (a topological order) from a counter, and a block waits only for tasks
// taken before its own, which running blocks hold, so the chain always moves. Before, each wave
// was a kernel of its own and waited for its slowest task (349 waves at 800k).
__global__ void __launch_bounds__(kTrackThreads)
    trackTasks(Dev d, const int* __restrict__ order, int n, int* next, int* done) {
  __shared__ double rows[kTrackThreads][kCols];
  __shared__ double slot[2][kCols];
  __shared__ double scored[2 * kTrackWarps];
  __shared__ int pick[2];
  __shared__ double fit_r[2];
  __shared__ double fit_pose[2][kPoseDoubles];
  __shared__ int taken;
  for (;;) {
    if (threadIdx.x == 0) taken = atomicAdd(next, 1);
    __syncthreads();
    const int k = taken;
    __syncthreads();
    if (k >= n) return;
    const int task = order[k];
    const int S = d.S, t = task / S, s = task % S;
    if (threadIdx.x == 0) {
      const int tp = d.before[t], tpp = d.two_before[t];
      waitDone(done, static_cast<long long>(tp) * S + s);
      if (tpp >= 0) waitDone(done, static_cast<long long>(tpp) * S + s);
      const int* lv = d.level + static_cast<long long>(t) * S;
      for (int j = d.adj_begin[s]; j < d.adj_begin[s + 1]; ++j)
        if (lv[d.adj[j]] < lv[s]) waitDone(done, static_cast<long long>(t) * S + d.adj[j]);
      __threadfence();
    }
    __syncthreads();
    const int warp = threadIdx.x / kWarp, lane = threadIdx.x % kWarp;
    const int* lev = d.level + static_cast<long long>(t) * S;
    int starts = d.two_before[t] >= 0 ? 3 : 2;
    for (int j = d.adj_begin[s]; j < d.adj_begin[s + 1]; ++j)
      if (lev[d.adj[j]] < lev[s]) ++starts;
    // 1. The starts on the probe, two a warp (a half-warp each; the probe is about 12 points),
    //    2 * kTrackWarps at a time: up to 8 starts in one round, where a warp a start needed two
    //    rounds for more than 4 (4.3 starts a task on average at 800k; the starts took 18.1 ->
    //    17.1 us a task). Thread 0 keeps the two best in start order (ties to the earlier start).
    //    A half-warp without a start of its own, beside one that has a start, scores the first
    //    start again so that both halves meet at the same shuffles; its score is not used.
    const double* probe = d.probe + 6LL * d.probe_begin[s];
    const int pm = d.probe_begin[s + 1] - d.probe_begin[s];
    const int part = lane / HalfWarp::kSize;
    const HalfWarp hw{lane % HalfWarp::kSize, &rows[warp * kWarp + part * HalfWarp::kSize]};
    double s0 = DBL_MAX, s1 = DBL_MAX;
    int i0 = -1, i1 = -1;
    for (int base = 0; base < starts; base += 2 * kTrackWarps) {
      const int c = base + 2 * warp + part;
      if (base + 2 * warp < starts) {
        const double r = residual(d, t, probe, pm, start(d, t, s, c < starts ? c : 0), hw);
        if (hw.rank == 0) scored[2 * warp + part] = r;
      }
      __syncthreads();
      if (threadIdx.x == 0)
        for (int w = 0; w < 2 * kTrackWarps && base + w < starts; ++w) {
          const double r = scored[w];
          const int c2 = base + w;
          if (i0 < 0 || r < s0) {
            s1 = s0, i1 = i0;
            s0 = r, i0 = c2;
          } else if (i1 < 0 || r < s1) {
            s1 = r, i1 = c2;
          }
        }
      __syncthreads();
    }
    if (threadIdx.x == 0) pick[0] = i0, pick[1] = i1;
    __syncthreads();
    // 2. The ICP from each of the two best starts and its residual, side by side.
    const double* src = d.source + 6LL * d.source_begin[s];
    const int m = d.source_begin[s + 1] - d.source_begin[s];
    const int half = threadIdx.x / HalfBlock::kSize;
    const HalfBlock hb{static_cast<int>(threadIdx.x) % HalfBlock::kSize, half,
                       &rows[half * HalfBlock::kSize], slot[half]};
    const int mine = pick[half];
    if (mine >= 0) {
      const Rigid fit = icp(d, t, src, m, start(d, t, s, mine), 4.0 * d.spacing[t], hb);
      const double r = residual(d, t, src, m, fit, hb);
      if (hb.rank == 0) {
        fit_r[half] = r;
        icp_step::store(fit, fit_pose[half]);
      }
    }
    __syncthreads();
    if (threadIdx.x == 0) {
      double best = DBL_MAX;
      Rigid best_pose = start(d, t, s, pick[0]);
      for (int k = 0; k < 2; ++k) {
        if (pick[k] < 0) continue;
        if (fit_r[k] < best) best = fit_r[k], best_pose = icp_step::load(fit_pose[k]);
      }
      icp_step::store(best_pose, d.poses + static_cast<long long>(task) * kPoseDoubles);
      d.residual[task] = best;
      __threadfence();
      atomicExch(done + task, 1);
    }
  }
}

// One residual per warp (motion_tracking.cpp's residual of one job).
__global__ void residualJobs(Dev d, const double* __restrict__ points,
                             const int* __restrict__ source_begin,
                             const double* __restrict__ motions,
                             const ResidualJob* __restrict__ jobs, int n, double* out) {
  __shared__ Scratch scratch[kWarpsPerBlock];
  const int w = (blockIdx.x * blockDim.x + threadIdx.x) / kWarp;
  const int lane = threadIdx.x % kWarp;
  if (w >= n) return;  // the whole warp
  const ResidualJob job = jobs[w];
  const int b = source_begin[job.source], m = source_begin[job.source + 1] - b;
  const double r =
      residual(d, job.frame, points + 6LL * b, m,
               icp_step::load(motions + static_cast<long long>(job.motion) * kPoseDoubles),
               WarpGroup(lane, scratch[threadIdx.x / kWarp]));
  if (lane == 0) out[w] = r;
}

// A residual job of the point-parallel path: residualJob's fields and the index of its first
// point among the batch's points (the jobs' points one job after the other).
struct ResidualPointJob {
  int source;
  int motion;
  int frame;
  int first;
};

// The surface error of every point of every job, a thread per point (residual()'s error of the
// point, the same arithmetic): the job of point i is the last one whose first point is at most
// i (jobs without points are skipped by that rule).
__global__ void residualPointErrors(Dev d, const double* __restrict__ points,
                                    const int* __restrict__ source_begin,
                                    const double* __restrict__ motions,
                                    const ResidualPointJob* __restrict__ jobs, int n, int total,
                                    double* __restrict__ errors) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= total) return;
  int lo = 0, hi = n - 1;  // jobs[lo].first <= i: the last such job
  while (lo < hi) {
    const int mid = (lo + hi + 1) / 2;
    if (jobs[mid].first <= i)
      lo = mid;
    else
      hi = mid - 1;
  }
  const ResidualPointJob job = jobs[lo];
  const double* p = points + 6LL * (source_begin[job.source] + (i - job.first));
  const Rigid T = icp_step::load(motions + static_cast<long long>(job.motion) * kPoseDoubles);
  double y[3], nr[3];
  icp_step::apply(T, p, y);
  icp_step::rotate(T, p + 3, nr);
  errors[i] = surfaceErrorAt(d, job.frame, y, nr);
}

// Each job's errors added in point order and its RMS, residual()'s total (a thread per job).
__global__ void residualSums(const double* __restrict__ errors,
                             const ResidualPointJob* __restrict__ jobs, int n, int total,
                             double* __restrict__ out) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= n) return;
  const int b = jobs[j].first, e = j + 1 < n ? jobs[j + 1].first : total;
  if (e == b) {
    out[j] = 0.0;
    return;
  }
  double sum = 0.0;
  for (int i = b; i < e; ++i) sum += errors[i];
  out[j] = sqrt(sum / static_cast<double>(e - b));
}

// icp() of the m-point source `src` in `frame` from `init`, kept when its residual is at most r0,
// else `init`: the kept pose to `out`, and where `out_res` is given its residual (the fit's own
// score; the start's scored only where the start is kept). The residual is shared by the whole
// group (Group::share), so every thread takes the same branch.
template <class Group>
__device__ void fitFrom(const Dev& d, int frame, const double* src, int m, const Rigid& init,
                        double max_dist, double r0, double* out, double* out_res, const Group& g) {
  const Rigid cand = icp(d, frame, src, m, init, max_dist, g);
  const double r = residual(d, frame, src, m, cand, g);
  const bool kept = r <= r0;
  double kept_r = r;
  if (out_res && !kept) kept_r = residual(d, frame, src, m, init, g);
  if (g.rank == 0) {
    icp_step::store(kept ? cand : init, out);
    if (out_res) *out_res = kept_r;
  }
}

// One part fit (motion_tracking.cpp's fitParts, fitFrom: icp() from the job's motion, kept when
// its residual is at most r0) by a group of threads; the pose to `out`, and where `out_res` is
// given, the kept pose's residual to it (the fit's own score; the start's scored only where the
// start is kept). The residual is shared by the whole group (Group::share), so every thread
// takes the same branch.
template <class Group>
__device__ void partFit(const Dev& d, const double* points, const int* source_begin,
                        const double* motions, const PartFitJob& job, double* out, double* out_res,
                        const Group& g) {
  const int b = source_begin[job.source], m = source_begin[job.source + 1] - b;
  const double* src = points + 6LL * b;
  const Rigid init = icp_step::load(motions + static_cast<long long>(job.motion) * kPoseDoubles);
  fitFrom(d, job.frame, src, m, init, job.max_dist, job.r0, out, out_res, g);
}

// One part fit per warp (partFit).
__global__ void partFitJobs(Dev d, const double* __restrict__ points,
                            const int* __restrict__ source_begin,
                            const double* __restrict__ motions, const PartFitJob* __restrict__ jobs,
                            int n, double* out, double* out_res) {
  __shared__ Scratch scratch[kWarpsPerBlock];
  const int w = (blockIdx.x * blockDim.x + threadIdx.x) / kWarp;
  const int lane = threadIdx.x % kWarp;
  if (w >= n) return;  // the whole warp
  partFit(d, points, source_begin, motions, jobs[w], out + static_cast<long long>(w) * kPoseDoubles,
          out_res ? out_res + w : nullptr, WarpGroup(lane, scratch[threadIdx.x / kWarp]));
}

// One part fit per block of kWideThreads threads (partFit): the fit's points searched side by
// side in rounds of kWideThreads, the sums still in point order (the same poses).
__global__ void partFitJobsWide(Dev d, const double* __restrict__ points,
                                const int* __restrict__ source_begin,
                                const double* __restrict__ motions,
                                const PartFitJob* __restrict__ jobs, double* out, double* out_res) {
  __shared__ double rows[kWideThreads][kCols];
  __shared__ double slot[kCols];
  partFit(d, points, source_begin, motions, jobs[blockIdx.x],
          out + static_cast<long long>(blockIdx.x) * kPoseDoubles,
          out_res ? out_res + blockIdx.x : nullptr,
          GroupOfBlock<kWideThreads>{static_cast<int>(threadIdx.x), rows, slot});
}

// One part fit per block of kLargeThreads threads, for batches whose sources have more points
// than kWideThreads (the labels' part motions: up to 400 points a part): a source of up to
// kLargeThreads points is searched in one round per ICP iteration instead of four, its sums
// still added in point order (the same poses). The scratch rows (kLargeThreads x kCols doubles,
// 112 KiB) are dynamic shared memory; the launch bound keeps the registers within the SM's.
constexpr int kLargeThreads = 512;
constexpr std::size_t kLargeShared =
    (static_cast<std::size_t>(kLargeThreads) + 1) * kCols * sizeof(double);
__global__ void __launch_bounds__(kLargeThreads)
    partFitJobsLarge(Dev d, const double* __restrict__ points, const int* __restrict__ source_begin,
                     const double* __restrict__ motions, const PartFitJob* __restrict__ jobs,
                     double* out, double* out_res) {
  extern __shared__ double large_rows[];  // kLargeThreads rows, then the shared slot
  partFit(d, points, source_begin, motions, jobs[blockIdx.x],
          out + static_cast<long long>(blockIdx.x) * kPoseDoubles,
          out_res ? out_res + blockIdx.x : nullptr,
          GroupOfBlock<kLargeThreads>{
              static_cast<int>(threadIdx.x), reinterpret_cast<double(*)[kCols]>(large_rows),
              large_rows + static_cast<std::size_t>(kLargeThreads) * kCols});
}

// One score-and-fit job (runScoreFits) by a group of threads: its starts scored in start order
// (residual(), the score batch's values), the winner chosen by scoreFitWinner (score_fit.h, the
// host's rule), and where one of its starts wins, fitFrom's fit from it with r0 its score. Every
// thread computes the same scores (residual() shares them), so every thread takes the same
// branches. `out`: the pose (12 doubles), then the winner's index (a double).
template <class Group>
__device__ void scoreFit(const Dev& d, const double* points, const int* source_begin,
                         const double* motions, const ScoreFitJob& job, double* scores, double* out,
                         const Group& g) {
  const int b = source_begin[job.source], m = source_begin[job.source + 1] - b;
  const double* src = points + 6LL * b;
  double scored[kScoreFitStarts];
  for (int k = 0; k < job.count; ++k) {
    const Rigid T = icp_step::load(motions + static_cast<long long>(job.first + k) * kPoseDoubles);
    scored[k] = residual(d, job.frame, src, m, T, g);
    if (g.rank == 0) scores[job.first + k] = scored[k];
  }
  double r0;
  const int win = segmentation::scoreFitWinner(
      scored, job.place, static_cast<std::size_t>(job.count), job.base_score, job.base_place, r0);
  if (win < 0) {
    if (g.rank == 0) {
      icp_step::store(icp_step::identity(), out);
      out[kPoseDoubles] = -1.0;
    }
    return;
  }
  const Rigid init =
      icp_step::load(motions + static_cast<long long>(job.first + win) * kPoseDoubles);
  fitFrom(d, job.frame, src, m, init, job.max_dist, r0, out, nullptr, g);
  if (g.rank == 0) out[kPoseDoubles] = static_cast<double>(win);
}

// The three widths of partFitJobs, partFitJobsWide and partFitJobsLarge for score-and-fit jobs.
constexpr int kScoreFitOut = kPoseDoubles + 1;
__global__ void scoreFitJobs(Dev d, const double* __restrict__ points,
                             const int* __restrict__ source_begin,
                             const double* __restrict__ motions,
                             const ScoreFitJob* __restrict__ jobs, int n, double* scores,
                             double* out) {
  __shared__ Scratch scratch[kWarpsPerBlock];
  const int w = (blockIdx.x * blockDim.x + threadIdx.x) / kWarp;
  const int lane = threadIdx.x % kWarp;
  if (w >= n) return;  // the whole warp
  scoreFit(d, points, source_begin, motions, jobs[w], scores,
           out + static_cast<long long>(w) * kScoreFitOut,
           WarpGroup(lane, scratch[threadIdx.x / kWarp]));
}
__global__ void scoreFitJobsWide(Dev d, const double* __restrict__ points,
                                 const int* __restrict__ source_begin,
                                 const double* __restrict__ motions,
                                 const ScoreFitJob* __restrict__ jobs, double* scores,
                                 double* out) {
  __shared__ double rows[kWideThreads][kCols];
  __shared__ double slot[kCols];
  scoreFit(d, points, source_begin, motions, jobs[blockIdx.x], scores,
           out + static_cast<long long>(blockIdx.x) * kScoreFitOut,
           GroupOfBlock<kWideThreads>{static_cast<int>(threadIdx.x), rows, slot});
}
__global__ void __launch_bounds__(kLargeThreads)
    scoreFitJobsLarge(Dev d, const double* __restrict__ points,
                      const int* __restrict__ source_begin, const double* __restrict__ motions,
                      const ScoreFitJob* __restrict__ jobs, double* scores, double* out) {
  extern __shared__ double large_rows[];  // kLargeThreads rows, then the shared slot
  scoreFit(d, points, source_begin, motions, jobs[blockIdx.x], scores,
           out + static_cast<long long>(blockIdx.x) * kScoreFitOut,
           GroupOfBlock<kLargeThreads>{
               static_cast<int>(threadIdx.x), reinterpret_cast<double(*)[kCols]>(large_rows),
               large_rows + static_cast<std::size_t>(kLargeThreads) * kCols});
}

// Point costs (motion_tracking.cpp's pointCost), one (job, frame) per thread, frame-major
// (thread t * n + j: a warp searches one frame's tree for neighbouring jobs): the point's surface
// error under its motion's pose in frame t, 0 in the reference frame, into errors[t * n + j]. A
// thread per job searching every frame in turn left the GPU nearly idle on a merge's batch of a
// few thousand jobs.
__global__ void pointErrorJobs(Dev d, int frames, int ref, const double* __restrict__ points,
                               const double* __restrict__ motions,
                               const PointCostJob* __restrict__ jobs, int n,
                               double* __restrict__ errors) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= static_cast<long long>(n) * frames) return;
  const int t = static_cast<int>(i / n), j = static_cast<int>(i % n);
  if (t == ref) {
    errors[i] = 0.0;
    return;
  }
  const PointCostJob job = jobs[j];
  const double* p = points + 6LL * job.point;
  const Rigid m =
      icp_step::load(motions + (static_cast<long long>(job.motion) * frames + t) * kPoseDoubles);
  double y[3], nr[3];
  icp_step::apply(m, p, y);
  icp_step::rotate(m, p + 3, nr);
  errors[i] = surfaceErrorAt(d, t, y, nr);
}

// A job's errors (pointErrorJobs) as the CPU gives them: with per_frame each frame's error, job
// by job (`frames` per job); otherwise their sum over the frames but the reference, added in frame
// order.
__global__ void pointCostSums(const double* __restrict__ errors, int frames, int ref,
                              bool per_frame, int n, double* __restrict__ out) {
  const int j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= n) return;
  if (per_frame) {
    for (int t = 0; t < frames; ++t)
      out[static_cast<long long>(j) * frames + t] = errors[static_cast<long long>(t) * n + j];
    return;
  }
  double sum = 0.0;
  for (int t = 0; t < frames; ++t)
    if (t != ref) sum += errors[static_cast<long long>(t) * n + j];
  out[j] = sum;
}

// The rigid motions' ICP (rigid_motion.cpp: icpPass, fitness, alignPasses), one cluster of
// R blocks per fit (R = 1, 2, 4 or 8; thread block clusters, sm_90). The source's
// icp_step::kSumRanges ranges (icp_step::rangeBegin) are split among the cluster's blocks, each
// block the ranges [rank * 128 / R, (rank + 1) * 128 / R) and their points. A block searches its
// points' nearest surface points with all its threads (into the job's global scratch), then
// its range threads add their ranges' values in point order; every block gathers the other
// blocks' range sums through distributed shared memory and adds the 128 of each column in range
// order, the CPU's order, so every block of the cluster holds the CPU's totals and takes the
// CPU's step. The searches, most of an iteration's time with one block (a 3000-point source is
// 12 searches per thread), spread over R SMs; the sums' order does not depend on R.
constexpr int kRigidThreads = icp_step::kSumRanges;
constexpr int kRigidBlockThreads = 256;
constexpr int kRigidCols = icp_step::kTerms + 2;  // the terms, the squared distances, the count
static_assert(kRigidThreads % kRigidMaxCluster == 0, "a block's ranges are whole order groups");
// Dynamic shared memory of a block: two buffers of the ranges' sums (consecutive reductions
// alternate, so that a block writes a buffer only after every block read it the time before:
// a cluster barrier lies between), then the totals.
constexpr std::size_t kRigidSharedBytes =
    (2 * kRigidThreads * kRigidCols + kRigidCols) * sizeof(double);

struct RigidBlock {
  int rank = 0, R = 1;             // the block's rank in its cluster, the cluster's size
  int r0 = 0, r1 = kRigidThreads;  // its ranges
  int buf = 0;                     // the buffer of the next reduction
  double* smem = nullptr;
  int* match = nullptr;  // the job's scratch: per source point, its match and squared distance
  float* d2 = nullptr;
  __device__ double (*part(int b))[kRigidCols] {
    return reinterpret_cast<double (*)[kRigidCols]>(smem + b * kRigidThreads * kRigidCols);
  }
  __device__ double* total() { return smem + 2 * kRigidThreads * kRigidCols; }
  // This thread's range (global index), or -1.
  __device__ int range() const {
    const int j = r0 + static_cast<int>(threadIdx.x);
    return j < r1 ? j : -1;
  }
};

__device__ void clusterSync(const RigidBlock& rb) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  if (rb.R > 1) {
    cooperative_groups::this_cluster().sync();
    return;
  }
#endif
  __syncthreads();
}

// Columns 0..cols-1 of every range's sums (each block's range threads wrote theirs into buffer
// rb.buf) added in range order into rb.total(), in every block of the cluster; every thread
// reads the totals after.
__device__ void rangeTotals(RigidBlock& rb, int cols) {
  clusterSync(rb);
  double(*mine)[kRigidCols] = rb.part(rb.buf);
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  if (rb.R > 1) {
    cooperative_groups::cluster_group cluster = cooperative_groups::this_cluster();
    const int per = kRigidThreads / rb.R;
    for (int idx = threadIdx.x; idx < kRigidThreads * cols; idx += blockDim.x) {
      const int j = idx / cols, q = idx - j * cols, owner = j / per;
      if (owner != rb.rank) mine[j][q] = *cluster.map_shared_rank(&mine[j][q], owner);
    }
    __syncthreads();
  }
#endif
  const int q = threadIdx.x;
  if (q < cols) {
    double t = 0.0;
    for (int j = 0; j < kRigidThreads; ++j) t += mine[j][q];
    rb.total()[q] = t;
  }
  rb.buf ^= 1;
  __syncthreads();
}

// The nearest surface point (within bound2) of every point of the block's ranges under T, by all
// threads of the block, into the job's scratch; synchronised after. The threads take the points
// in `order` (rigidSearchOrder: near points side by side within each order group), so that the
// lanes of a warp walk the same branches of the tree.
__device__ void rigidMatches(const Dev& d, int root, const double* src, const int* order, int n,
                             const Rigid& T, float bound2, RigidBlock& rb) {
  const int s1 = icp_step::rangeBegin(rb.r1, n);
  for (int s = icp_step::rangeBegin(rb.r0, n) + static_cast<int>(threadIdx.x); s < s1;
       s += blockDim.x) {
    const int i = order[s];
    double y[3];
    icp_step::apply(T, src + 3 * i, y);
    float d2 = 0.0f;
    rb.match[i] = nearest(d, root, static_cast<float>(y[0]), static_cast<float>(y[1]),
                          static_cast<float>(y[2]), bound2, d2);
    rb.d2[i] = d2;
  }
  __syncthreads();
}

__device__ Rigid rigidPass(const Dev& d, int root, const double* src, const int* order, int n,
                           Rigid T, double max_dist, int iterations, bool plane, double spacing,
                           const RigidParams& p, RigidBlock& rb) {
  const float max_d2 = static_cast<float>(max_dist * max_dist);
  const double max_move = p.transformation_epsilon * spacing;
  const int j = rb.range();
  const int b = j >= 0 ? icp_step::rangeBegin(j, n) : 0,
            e = j >= 0 ? icp_step::rangeBegin(j + 1, n) : 0;
  double prev_mse = -1.0;
  for (int it = 0; it < iterations; ++it) {
    {
      double part[3] = {0.0, 0.0, 0.0};
      for (int i = b; i < e; ++i) {
        double y[3];
        icp_step::apply(T, src + 3 * i, y);
        for (int k = 0; k < 3; ++k) part[k] += y[k];
      }
      if (j >= 0)
        for (int k = 0; k < 3; ++k) rb.part(rb.buf)[j][k] = part[k];
    }
    rangeTotals(rb, 3);
    double c[3];
    for (int k = 0; k < 3; ++k) c[k] = rb.total()[k] / static_cast<double>(n > 0 ? n : 1);
    rigidMatches(d, root, src, order, n, T, max_d2, rb);
    if (j >= 0) {
      // Added in place in the buffer (this thread's row): no 25 doubles held in registers
      // beside the searches'.
      double* row = rb.part(rb.buf)[j];
      for (int q = 0; q < kRigidCols; ++q) row[q] = 0.0;
      for (int i = b; i < e; ++i) {
        const int k = rb.match[i];
        if (k < 0) continue;
        double y[3];
        icp_step::apply(T, src + 3 * i, y);
        const float4 a = d.pts[k], nb = d.nrm[k];
        const double tp[3] = {a.x, a.y, a.z}, tn[3] = {nb.x, nb.y, nb.z};
        double terms[icp_step::kTerms];
        icp_step::weightedTerms(y, c, tp, tn, plane ? 1.0 : 0.0, plane ? 0.0 : 1.0, terms);
        for (int q = 0; q < icp_step::kTerms; ++q) row[q] += terms[q];
        row[icp_step::kTerms] += rb.d2[i];
        row[icp_step::kTerms + 1] += 1.0;
      }
    }
    rangeTotals(rb, kRigidCols);
    double sums[kRigidCols];
    for (int q = 0; q < kRigidCols; ++q) sums[q] = rb.total()[q];
    if (!icp_step::rigidStep(sums, c, p.max_turn, max_move, p.relative_mse_epsilon, T, prev_mse))
      break;
  }
  return T;
}

// RMS distance from the moved source to its nearest surface points (no bound), NaN when a point
// finds none; added by ranges as on the CPU.
__device__ double rigidFitness(const Dev& d, int root, const double* src, const int* order, int n,
                               const Rigid& T, RigidBlock& rb) {
  if (n == 0) return CUDART_NAN;
  const int j = rb.range();
  rigidMatches(d, root, src, order, n, T, CUDART_INF_F, rb);
  if (j >= 0) {
    double sum = 0.0, missing = 0.0;
    for (int i = icp_step::rangeBegin(j, n), e = icp_step::rangeBegin(j + 1, n); i < e; ++i) {
      if (rb.match[i] < 0)
        missing += 1.0;
      else
        sum += rb.d2[i];
    }
    rb.part(rb.buf)[j][0] = sum;
    rb.part(rb.buf)[j][1] = missing;
  }
  rangeTotals(rb, 2);
  const double total = rb.total()[0], lost = rb.total()[1];
  if (lost > 0.0) return CUDART_NAN;
  return sqrt(total / static_cast<double>(n));
}

// One fit per cluster of `cluster` blocks (blockIdx.x / cluster is the job); a job's matches
// start at its scratch_begin in match / match_d2.
__global__ void __launch_bounds__(kRigidBlockThreads)
    rigidFitJobs(Dev d, const double* __restrict__ sources, const int* __restrict__ orders,
                 const RigidJob* __restrict__ jobs, int* match, float* match_d2, int cluster,
                 RigidParams p, double* poses, double* rms_out) {
  extern __shared__ double rigid_smem[];
  RigidBlock rb;
  rb.smem = rigid_smem;
  rb.R = cluster;
  const int job_index = blockIdx.x / cluster;
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
  rb.rank = cluster > 1 ? static_cast<int>(cooperative_groups::this_cluster().block_rank()) : 0;
#endif
  const int per = kRigidThreads / cluster;
  rb.r0 = rb.rank * per;
  rb.r1 = rb.r0 + per;
  const RigidJob job = jobs[job_index];
  rb.match = match + job.scratch_begin;
  rb.d2 = match_d2 + job.scratch_begin;
  const int root = d.root[job.surface];
  const double* src = sources + 3LL * job.source_begin;
  const int* order = orders + job.source_begin;
  const int n = job.source_count;
  const double fine = p.max_correspondence_spacings * job.spacing;
  const double coarse = fmax(fine, p.coarse_distance * job.part_diag);
  const double passes[2] = {coarse, fmax(fine, coarse / 6.0)};
  Rigid m = icp_step::load(job.start);
  if (job.wide)
    for (int k = 0; k < 2; ++k)
      m = rigidPass(d, root, src, order, n, m, passes[k], max(1, p.max_iterations / 2), false,
                    job.spacing, p, rb);
  m = rigidPass(d, root, src, order, n, m, fine, p.max_iterations, false, job.spacing, p, rb);
  double rms = rigidFitness(d, root, src, order, n, m, rb);
  const Rigid plane =
      rigidPass(d, root, src, order, n, m, fine, p.max_iterations, true, job.spacing, p, rb);
  const double rms_plane = rigidFitness(d, root, src, order, n, plane, rb);
  if (rms_plane <= rms) {
    m = plane;
    rms = rms_plane;
  }
  if (rb.rank == 0 && threadIdx.x == 0) {
    icp_step::store(m, poses + static_cast<long long>(job_index) * kPoseDoubles);
    rms_out[job_index] = rms;
  }
  // No block leaves while another may still read its shared memory.
  clusterSync(rb);
}

// rigid_motion.cpp's rigidScore, a block per job: the block's threads search the probes'
// nearest surface points (probe k is source point k n / probes), then one thread adds their
// squared distances in probe order, as the CPU does.
constexpr int kScoreThreads = 128;
__global__ void __launch_bounds__(kScoreThreads)
    rigidScoreJobs(Dev d, const double* __restrict__ sources,
                   const RigidScoreJob* __restrict__ jobs, double* out) {
  __shared__ float d2s[kRigidScoreMaxProbes];
  const RigidScoreJob job = jobs[blockIdx.x];
  const long long n = job.source_count;
  const int m = static_cast<int>(min(static_cast<long long>(job.probes), n));
  const Rigid T = icp_step::load(job.pose);
  const int root = d.root[job.surface];
  const double* src = sources + 3LL * job.source_begin;
  for (int k = threadIdx.x; k < m; k += blockDim.x) {
    double y[3];
    icp_step::apply(T, src + 3 * (static_cast<long long>(k) * n / m), y);
    float d2 = 0.0f;
    nearest(d, root, static_cast<float>(y[0]), static_cast<float>(y[1]), static_cast<float>(y[2]),
            CUDART_INF_F, d2);
    d2s[k] = d2;
  }
  __syncthreads();
  if (threadIdx.x != 0) return;
  double sum = 0.0;
  for (int k = 0; k < m; ++k) sum += d2s[k];
  out[blockIdx.x] = m > 0 ? sqrt(sum / static_cast<double>(m)) : 0.0;
}

Dev frameView(const FrameStore& store) {
  const FrameStore& f = store.shared ? *store.shared : store;
  Dev d{};
  d.nodes = f.nodes.ptr();
  d.pts = reinterpret_cast<const float4*>(f.points.ptr());
  d.nrm = reinterpret_cast<const float4*>(f.normals.ptr());
  d.root = f.root.ptr();
  d.spacing = f.spacing.ptr();
  d.unoriented = f.unoriented.ptr();
  d.normal_cos = f.normal_cos;
  d.clip = f.clip;
  return d;
}

// A batch buffer: grown (by half again) when too small, kept otherwise.
void grow(DeviceMemory& m, std::size_t bytes) {
  if (m.sizeBytes() < bytes) m.create(bytes + bytes / 2);
}
void put(DeviceMemory& m, const void* host, std::size_t bytes) {
  grow(m, bytes);
  m.uploadBytes(host, bytes);
}

// Where a batch's inputs lie in the store's job_in buffer.
template <class Job>
struct BatchView {
  const double* points = nullptr;
  const int* begin = nullptr;
  const double* motions = nullptr;
  const Job* list = nullptr;
};

// A batch's points, their sources' ranges (when the jobs name sources), motions and jobs
// packed into the store's staging buffer and uploaded with one copy, each part at a 16-byte
// boundary; the output buffer grown to `out_bytes`.
template <class Job>
BatchView<Job> putBatch(FrameStore& frames, const std::vector<double>& points,
                        const std::vector<int>* source_begin, const std::vector<double>& motions,
                        const std::vector<Job>& jobs, std::size_t out_bytes) {
  // Each part at the next 16-byte boundary.
  std::size_t used = 0;
  auto place = [&](std::size_t bytes) {
    const std::size_t at = (used + 15) & ~static_cast<std::size_t>(15);
    used = at + bytes;
    return at;
  };
  const std::size_t points_bytes = points.size() * sizeof(double);
  const std::size_t begin_bytes = source_begin ? source_begin->size() * sizeof(int) : 0;
  const std::size_t motions_bytes = motions.size() * sizeof(double);
  const std::size_t jobs_bytes = jobs.size() * sizeof(Job);
  const std::size_t at_points = place(points_bytes);
  const std::size_t at_begin = source_begin ? place(begin_bytes) : 0;
  const std::size_t at_motions = place(motions_bytes);
  const std::size_t at_jobs = place(jobs_bytes);
  unsigned char* st = frames.staging.forBatch(used);
  if (!st) {  // pageable: the copy below has returned when the buffer may be written again
    frames.pageable_in.resize(used);
    st = frames.pageable_in.data();
  }
  auto copy = [&](std::size_t at, const void* data, std::size_t bytes) {
    if (bytes) std::memcpy(st + at, data, bytes);
  };
  copy(at_points, points.data(), points_bytes);
  if (source_begin) copy(at_begin, source_begin->data(), begin_bytes);
  copy(at_motions, motions.data(), motions_bytes);
  copy(at_jobs, jobs.data(), jobs_bytes);
  grow(frames.job_in, used);
  // Asynchronous from pinned memory: the kernels that follow on the same stream wait for it, and
  // the staging is not written again before the batch's results are back (finishedResults).
  cudaSafeCall(cudaMemcpyAsync(frames.job_in.rawPtr(), st, used, cudaMemcpyHostToDevice, 0));
  grow(frames.job_out, out_bytes);
  const auto* base = static_cast<const unsigned char*>(frames.job_in.rawPtr());
  BatchView<Job> v;
  v.points = reinterpret_cast<const double*>(base + at_points);
  if (source_begin) v.begin = reinterpret_cast<const int*>(base + at_begin);
  v.motions = reinterpret_cast<const double*>(base + at_motions);
  v.list = reinterpret_cast<const Job*>(base + at_jobs);
  return v;
}

// Where a batch's last kernel writes its `bytes` of results: the store's pinned results buffer,
// mapped, so that they need no copy back (finishedResults gives them once the batch is done). A
// copy back cost a call 8 us more of its 34 (a round trip of two small kernels on the H100).
// A batch too large for that buffer (PinnedHost::forBatch) writes to device memory instead,
// which finishedResults copies back and lets go.
double* resultsOnHost(FrameStore& frames, std::size_t bytes) {
  frames.results_pageable = frames.results.forBatch(bytes) == nullptr;
  if (!frames.results_pageable) return static_cast<double*>(frames.results.devicePtr());
  // The exact size, and let go after the batch (finishedResults): these are one-offs, and
  // device memory is what the run's peak reports.
  frames.results_on_device.create(bytes);
  return static_cast<double*>(frames.results_on_device.rawPtr());
}

// A batch's results that its kernels wrote to resultsOnHost(), once everything queued is done
// (waits once; reports a kernel fault): the mapped buffer, `count` doubles, valid until the
// store's next batch (or, for a batch too large for it, their copy). Callers copy them out in one
// pass (assign): assigning zeros first and copying over them wrote every value twice (the part
// merges' per-frame point costs, 64 MB a run at 800k).
const double* finishedResults(FrameStore& frames, std::size_t count) {
  if (frames.yield_while_waiting)
    frames.yielding.wait();
  else
    cudaSafeCall(cudaStreamSynchronize(cudaStreamPerThread));
  if (!frames.results_pageable) return reinterpret_cast<const double*>(frames.results.data());
  frames.pageable_out.resize(count);
  cudaSafeCall(cudaMemcpyAsync(frames.pageable_out.data(), frames.results_on_device.rawPtr(),
                               count * sizeof(double), cudaMemcpyDeviceToHost,
                               cudaStreamPerThread));
  cudaSafeCall(cudaStreamSynchronize(cudaStreamPerThread));
  frames.results_on_device.release();
  return frames.pageable_out.data();
}

int blocksFor(long long warps) {
  return static_cast<int>((warps + kWarpsPerBlock - 1) / kWarpsPerBlock);
}

// The launch configuration of the rigid fits on `blocks` blocks in clusters of R (none for 1).
struct RigidLaunch {
  cudaLaunchConfig_t cfg{};
  cudaLaunchAttribute attr{};
  RigidLaunch(unsigned blocks, int R) {
    cfg.gridDim = dim3(blocks);
    cfg.blockDim = dim3(kRigidBlockThreads);
    cfg.dynamicSmemBytes = kRigidSharedBytes;
    attr.id = cudaLaunchAttributeClusterDimension;
    attr.val.clusterDim.x = static_cast<unsigned>(R);
    attr.val.clusterDim.y = attr.val.clusterDim.z = 1;
    cfg.attrs = R > 1 ? &attr : nullptr;
    cfg.numAttrs = R > 1 ? 1 : 0;
  }
  RigidLaunch(const RigidLaunch&) = delete;  // cfg points at attr
  RigidLaunch& operator=(const RigidLaunch&) = delete;
};

// How many clusters of R blocks of the rigid fits run at once on this device (0: clusters of R
// are not possible), measured once per store.
int rigidClusterLimit(FrameStore& store, int R) {
  int& known = store.rigid_clusters[R == 2 ? 0 : (R == 4 ? 1 : 2)];
  if (known >= 0) return known;
  known = 0;
  int device = 0, can = 0;
  cudaSafeCall(cudaGetDevice(&device));
  cudaSafeCall(cudaDeviceGetAttribute(&can, cudaDevAttrClusterLaunch, device));
  cudaFuncAttributes fa{};
  cudaSafeCall(cudaFuncGetAttributes(&fa, rigidFitJobs));
  if (!can || fa.binaryVersion < 90) return known;  // no clusters: one block per fit
  const RigidLaunch launch(static_cast<unsigned>(R), R);
  int clusters = 0;
  if (cudaOccupancyMaxActiveClusters(&clusters, rigidFitJobs, &launch.cfg) != cudaSuccess) {
    cudaGetLastError();  // a size this device cannot co-schedule: not used
    clusters = 0;
  }
  return known = clusters;
}

}  // namespace

int rigidClusterSize(FrameStore& store, int jobs, int max_points, int forced) {
  if (!store.rigid_shared_set) {
    cudaSafeCall(cudaFuncSetAttribute(rigidFitJobs, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                      static_cast<int>(kRigidSharedBytes)));
    store.rigid_shared_set = true;
  }
  if (forced > 0) {
    int R = 1;
    while (R * 2 <= std::min(forced, kRigidMaxCluster) && rigidClusterLimit(store, R * 2) > 0)
      R *= 2;
    return R;
  }
  // Enough blocks that each searches at most a point per thread, while every job's cluster runs
  // at once (a cluster that waits for another to finish costs more than it saves). Sources of
  // at most two points per thread stay on one block: there the cluster's barriers and gathers
  // cost more than the searches they share (the refinement's 500-point fits, 20 per batch:
  // 1.33 ms a batch on clusters of 2 against 1.24 ms on one block).
  int R = 1;
  if (max_points > 2 * kRigidBlockThreads)
    while (R < kRigidMaxCluster && static_cast<long long>(R) * kRigidBlockThreads < max_points)
      R *= 2;
  while (R > 1 && rigidClusterLimit(store, R) < jobs) R /= 2;
  return R;
}

void runRigidScores(FrameStore& surfaces, const DeviceArray<double>& sources,
                    const std::vector<RigidScoreJob>& jobs, std::vector<double>& out) {
  out.clear();
  if (jobs.empty()) return;
  for (const RigidScoreJob& j : jobs)
    if (j.probes > kRigidScoreMaxProbes)
      throw DeviceError("GPU rigid scores: more than " + std::to_string(kRigidScoreMaxProbes) +
                        " probes");
  put(surfaces.job_in, jobs.data(), jobs.size() * sizeof(RigidScoreJob));
  const Dev d = frameView(surfaces);
  double* res = resultsOnHost(surfaces, jobs.size() * sizeof(double));
  rigidScoreJobs<<<static_cast<unsigned>(jobs.size()), kScoreThreads>>>(
      d, sources.ptr(), static_cast<const RigidScoreJob*>(surfaces.job_in.rawPtr()), res);
  cudaCheckLaunch();
  const double* r = finishedResults(surfaces, jobs.size());
  out.assign(r, r + jobs.size());
}

void runRigidFits(FrameStore& surfaces, const DeviceArray<double>& sources,
                  const DeviceArray<int>& orders, const std::vector<RigidJob>& jobs,
                  const RigidParams& params, int cluster, std::vector<double>& poses,
                  std::vector<double>& rms) {
  poses.clear();
  rms.clear();
  if (jobs.empty()) return;
  if (cluster < 1 || cluster > kRigidMaxCluster || (cluster & (cluster - 1)) != 0)
    throw DeviceError("GPU rigid fits: a cluster of " + std::to_string(cluster) + " blocks");
  // Each job's matches after the jobs before it in the scratch.
  const std::size_t n = jobs.size();
  std::vector<RigidJob> list(jobs);
  long long total = 0;
  for (RigidJob& j : list) {
    j.scratch_begin = total;
    total += std::max(0, j.source_count);
  }
  put(surfaces.job_in, list.data(), n * sizeof(RigidJob));
  const std::size_t points = static_cast<std::size_t>(std::max(1LL, total));
  grow(surfaces.rigid_scratch, points * (sizeof(int) + sizeof(float)));
  const Dev d = frameView(surfaces);
  const auto* job_list = static_cast<const RigidJob*>(surfaces.job_in.rawPtr());
  int* match = static_cast<int*>(surfaces.rigid_scratch.rawPtr());
  float* match_d2 = reinterpret_cast<float*>(match + points);
  double* out = resultsOnHost(surfaces, n * (kPoseDoubles + 1) * sizeof(double));
  double* rms_out = out + n * kPoseDoubles;
  const RigidLaunch launch(static_cast<unsigned>(n * cluster), cluster);
  cudaSafeCall(cudaLaunchKernelEx(&launch.cfg, rigidFitJobs, d, sources.ptr(), orders.ptr(),
                                  job_list, match, match_d2, cluster, params, out, rms_out));
  cudaCheckLaunch();
  const double* r = finishedResults(surfaces, n * (kPoseDoubles + 1));
  poses.assign(r, r + n * kPoseDoubles);
  rms.assign(r + n * kPoseDoubles, r + n * (kPoseDoubles + 1));
}

// FlatKdTree3::visit (flat_kdtree.h) on the device: every point of the tree at `root` whose
// squared distance to (qx, qy, qz) is below worst() (read again after each hit) goes to
// hit(d2, leaf index); the same walk, distances in the CPU's float order, without contraction.
template <class Worst, class Hit>
__device__ void visitTree(const TrackNode* nodes, const float4* pts, int root, float qx, float qy,
                          float qz, Worst worst, Hit hit) {
  struct Entry {
    int node;
    float min_d2;
  };
  Entry stack[kMaxDepth];
  int top = 0;
  stack[top++] = {root, 0.0f};
  while (top > 0) {
    const Entry e = stack[--top];
    if (!(e.min_d2 < worst())) continue;
    int nidx = e.node;
    TrackNode nd = nodes[nidx];
    while (nd.dim >= 0) {
      const float qv = nd.dim == 0 ? qx : (nd.dim == 1 ? qy : qz);
      const float diff = __fsub_rn(qv, nd.split);
      const float far_d2 = fmaxf(e.min_d2, __fmul_rn(diff, diff));
      if (far_d2 < worst() && top < kMaxDepth) stack[top++] = {diff < 0.0f ? nd.b : nd.a, far_d2};
      nidx = diff < 0.0f ? nd.a : nd.b;
      nd = nodes[nidx];
    }
    for (int i = nd.a; i < nd.b; ++i) {
      const float d = distance2(qx, qy, qz, pts[i]);
      if (d < worst()) hit(d, i);
    }
  }
}

// FlatKdTree3::knn (flat_kdtree.h): its walk (visitTree) with its sorted heap of (d2, row) pairs,
// a query per thread.
__global__ void knnKernel(const TrackNode* nodes, const float4* pts, const int* rows,
                          const int* root, const int* size, const float* queries,
                          const int* tree_of, long long n, int k, int* out_rows, int* out_count) {
  const long long q = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (q >= n) return;
  const int t = tree_of[q];
  const int kk = min(k, size[t]);
  float hd[kMaxKnn];
  int hr[kMaxKnn];
  int filled = 0;
  const float qx = queries[3 * q], qy = queries[3 * q + 1], qz = queries[3 * q + 2];
  if (root[t] >= 0 && kk > 0 && isfinite(qx) && isfinite(qy) && isfinite(qz)) {
    auto worst = [&]() { return filled < kk ? CUDART_INF_F : hd[kk - 1]; };
    visitTree(nodes, pts, root[t], qx, qy, qz, worst, [&](float d, int i) {
      const int row = rows[i];
      // heap.insert(upper_bound(...)) after dropping the last when full, as on the CPU.
      if (filled == kk) {
        if (!(d < hd[kk - 1] || (d == hd[kk - 1] && row < hr[kk - 1]))) return;
        --filled;
      }
      int at = filled;
      while (at > 0 && (d < hd[at - 1] || (d == hd[at - 1] && row < hr[at - 1]))) {
        hd[at] = hd[at - 1];
        hr[at] = hr[at - 1];
        --at;
      }
      hd[at] = d;
      hr[at] = row;
      ++filled;
    });
  }
  for (int i = 0; i < k; ++i) out_rows[q * k + i] = i < filled ? hr[i] : -1;
  out_count[q] = filled;
}

// FlatKdTree3::knn with k = 1: nearest() without a bound (its walk, the first point found among
// equal distances), a query per thread; no point for an empty tree or a non-finite query.
__global__ void nearestKernel(const TrackNode* nodes, const float4* pts, const int* rows,
                              const int* root, const float* queries, const int* tree_of,
                              long long n, int* out_rows, int* out_count) {
  const long long q = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (q >= n) return;
  const float qx = queries[3 * q], qy = queries[3 * q + 1], qz = queries[3 * q + 2];
  int leaf = -1;
  if (isfinite(qx) && isfinite(qy) && isfinite(qz)) {
    Dev d{};
    d.nodes = nodes;
    d.pts = pts;
    float d2 = 0.0f;
    leaf = nearest(d, root[tree_of[q]], qx, qy, qz, CUDART_INF_F, d2);
  }
  out_rows[q] = leaf >= 0 ? rows[leaf] : -1;
  out_count[q] = leaf >= 0 ? 1 : 0;
}

// The refinement's motion check, a thread per residual: its copies one after the other in the
// order of `scored` (motion_check.h; the CPU's loop in GMMBoundaryRefinement), each copy's
// nearest point as nearestKernel finds it.
__global__ void motionCheckKernel(const TrackNode* nodes, const float4* pts, const int* rows,
                                  const int* root, const int* first, MotionCheckArrays in,
                                  float* out) {
  const int r = blockIdx.x * blockDim.x + threadIdx.x;
  if (r >= in.residuals) return;
  Dev d{};
  d.nodes = nodes;
  d.pts = pts;
  out[r] = segmentation::motion_check::residualOf(
      in.starts + 3LL * r, in.part[r], in.own[r], in.scored, in.n_scored, in.frames, in.motions,
      in.valid, in.spacing, in.cap, [&](int u, const float* q, double* p, double* n) {
        float d2 = 0.0f;
        const int leaf = nearest(d, root[u], q[0], q[1], q[2], CUDART_INF_F, d2);
        if (leaf < 0) return false;
        const float4 at = pts[leaf];
        const float* nf = in.normals + 3LL * (first[u] + rows[leaf]);
        p[0] = at.x, p[1] = at.y, p[2] = at.z;
        for (int c = 0; c < 3; ++c) n[c] = nf[c];
        return true;
      });
}

void runMotionCheck(const KnnStore& store, const MotionCheckArrays& in, float* out) {
  if (in.residuals <= 0) return;
  const std::size_t pf = static_cast<std::size_t>(in.parts) * in.frames;
  DeviceArray<double> starts(in.starts, 3 * static_cast<std::size_t>(in.residuals));
  DeviceArray<int> part(in.part, in.residuals), own(in.own, in.residuals);
  DeviceArray<double> motions(in.motions, 12 * pf);
  DeviceArray<char> valid(in.valid, pf);
  DeviceArray<int> scored(in.scored, in.n_scored);
  DeviceArray<double> spacing(in.spacing, in.frames);
  DeviceArray<float> normals(in.normals, in.normal_floats);
  DeviceArray<int> first(store.first.data(), store.first.size());
  DeviceArray<float> d_out(in.residuals);
  MotionCheckArrays dev = in;
  dev.starts = starts.ptr();
  dev.part = part.ptr();
  dev.own = own.ptr();
  dev.motions = motions.ptr();
  dev.valid = valid.ptr();
  dev.scored = scored.ptr();
  dev.spacing = spacing.ptr();
  dev.normals = normals.ptr();
  const int threads = 128;
  motionCheckKernel<<<(in.residuals + threads - 1) / threads, threads>>>(
      store.nodes.ptr(), reinterpret_cast<const float4*>(store.points.ptr()), store.rows.ptr(),
      store.root.ptr(), first.ptr(), dev, d_out.ptr());
  cudaCheckLaunch();
  d_out.download(out);
}

void uploadKnnTrees(const KnnTrees& trees, KnnStore& store) {
  store.trees = 0;
  store.first.assign(trees.size.size() + 1, 0);
  for (std::size_t t = 0; t < trees.size.size(); ++t)
    store.first[t + 1] = store.first[t] + trees.size[t];
  store.nodes.upload(trees.nodes.data(), trees.nodes.size());
  store.points.upload(trees.points.data(), trees.points.size());
  store.rows.upload(trees.rows);
  store.root.upload(trees.root);
  store.size.upload(trees.size);
  store.trees = static_cast<int>(trees.root.size());
}

void runKnn(const KnnStore& store, int k, const std::vector<float>& queries,
            const std::vector<int>& tree_of, std::vector<int>& rows, std::vector<int>& count) {
  const long long n = static_cast<long long>(tree_of.size());
  rows.resize(static_cast<std::size_t>(n) * k);
  count.resize(static_cast<std::size_t>(n));
  if (n == 0) return;
  // The queries' and results' buffers for this call alone: kept, they added their size to the
  // run's peak device memory (beside the motion method's).
  DeviceArray<float> d_queries(queries.data(), queries.size());
  DeviceArray<int> d_tree_of(tree_of.data(), tree_of.size());
  DeviceArray<int> d_rows(rows.size()), d_count(count.size());
  const auto* nodes = store.nodes.ptr();
  const auto* pts = reinterpret_cast<const float4*>(store.points.ptr());
  const float* q = d_queries.ptr();
  const int* of = d_tree_of.ptr();
  int* out_rows = d_rows.ptr();
  int* out_count = d_count.ptr();
  const int threads = 128;
  const long long blocks = (n + threads - 1) / threads;
  if (k == 1)
    nearestKernel<<<static_cast<unsigned>(blocks), threads>>>(
        nodes, pts, store.rows.ptr(), store.root.ptr(), q, of, n, out_rows, out_count);
  else
    knnKernel<<<static_cast<unsigned>(blocks), threads>>>(nodes, pts, store.rows.ptr(),
                                                          store.root.ptr(), store.size.ptr(), q, of,
                                                          n, k, out_rows, out_count);
  cudaCheckLaunch();
  d_rows.download(rows.data());
  d_count.download(count.data());
}

// Every element +infinity (its bits: no byte pattern of cudaMemset gives them).
__global__ void fillInfinity(unsigned* out, long long n) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) out[i] = 0x7f800000u;
}

// FlatKdTree3::within (flat_kdtree.h) from a query per thread: its walk bounded by the tree's
// bound2 (strictly below), each point reached keeping the least squared distance in its row's
// slot. Non-negative floats order as their bits, so an unsigned atomicMin keeps the least; the
// distances in the CPU's float order, without contraction.
__global__ void leastDistancesKernel(const TrackNode* nodes, const float4* pts, const int* rows,
                                     const int* root, const int* first, const float* queries,
                                     const int* tree_of, const float* bound2, long long n,
                                     unsigned* out) {
  const long long q = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (q >= n) return;
  const int t = tree_of[q];
  const float qx = queries[3 * q], qy = queries[3 * q + 1], qz = queries[3 * q + 2];
  if (root[t] < 0 || !isfinite(qx) || !isfinite(qy) || !isfinite(qz)) return;
  const float bound = bound2[t];
  unsigned* slot = out + first[t];
  visitTree(
      nodes, pts, root[t], qx, qy, qz, [bound]() { return bound; },
      [&](float d, int i) { atomicMin(slot + rows[i], __float_as_uint(d)); });
}

void runLeastDistances(const KnnStore& store, const std::vector<float>& queries,
                       const std::vector<int>& tree_of, const std::vector<float>& bound2,
                       std::vector<float>& out) {
  const long long rows = store.first.empty() ? 0 : store.first.back();
  out.assign(static_cast<std::size_t>(rows), std::numeric_limits<float>::infinity());
  const long long n = static_cast<long long>(tree_of.size());
  if (n == 0 || rows == 0) return;
  DeviceArray<float> d_queries(queries.data(), queries.size());
  DeviceArray<int> d_tree_of(tree_of.data(), tree_of.size());
  DeviceArray<float> d_bound2(bound2.data(), bound2.size());
  DeviceArray<int> d_first(store.first.data(), store.first.size());
  DeviceArray<unsigned> d_out(static_cast<std::size_t>(rows));
  const int threads = 128;
  fillInfinity<<<static_cast<unsigned>((rows + threads - 1) / threads), threads>>>(d_out.ptr(),
                                                                                   rows);
  cudaCheckLaunch();
  leastDistancesKernel<<<static_cast<unsigned>((n + threads - 1) / threads), threads>>>(
      store.nodes.ptr(), reinterpret_cast<const float4*>(store.points.ptr()), store.rows.ptr(),
      store.root.ptr(), d_first.ptr(), d_queries.ptr(), d_tree_of.ptr(), d_bound2.ptr(), n,
      d_out.ptr());
  cudaCheckLaunch();
  static_assert(sizeof(unsigned) == sizeof(float), "a float's bits in an unsigned");
  d_out.downloadBytes(out.data(), out.size() * sizeof(float));
}

namespace gmm_em = math::gmm_em;
constexpr int kMixtureThreads = 128;

// term(0) + term(1) + ... + term(n - 1), added in index order from 0.0 (gmm_em's sums are in
// point order), eight terms computed before they are added (as addRows).
template <class Term>
__device__ double orderedSum(int n, Term term) {
  double sum = 0.0;
  int i = 0;
  for (; i + 8 <= n; i += 8) {
    double a[8];
#pragma unroll
    for (int q = 0; q < 8; ++q) a[q] = term(i + q);
#pragma unroll
    for (int q = 0; q < 8; ++q) sum += a[q];
  }
  for (; i < n; ++i) sum += term(i);
  return sum;
}

// math::gmmEM of one job by a block: the E step a point per thread, then each sum of the M step
// by a thread of its own over the points in order (the CPU adds each of them in that order), and
// the steps between by thread 0, with gmm_em's arithmetic throughout.
__global__ void __launch_bounds__(kMixtureThreads)
    mixtureFits(const double* __restrict__ points, const MixtureJob* __restrict__ jobs,
                MixtureResult* results, double* resp, double* lse, int stride, int max_iterations,
                double tolerance, double reg) {
  const MixtureJob job = jobs[blockIdx.x];
  __shared__ gmm_em::Mixture<gmm_em::kMaxDeviceComponents> m;
  __shared__ double nk[gmm_em::kMaxDeviceComponents], sx[gmm_em::kMaxDeviceComponents][3];
  __shared__ double sc[gmm_em::kMaxDeviceComponents][6];
  __shared__ int stop;
  MixtureResult& out = results[blockIdx.x];
  if (threadIdx.x == 0) {
    m = out.m;
    out.log_likelihood = 0.0;
    out.iterations = 0;
    out.converged = 0;
    out.bad = -1;
    stop = 0;
  }
  __syncthreads();
  const int k = m.k, n = job.n;
  const double* p = points + 3 * job.first;
  double* r = resp + job.first * stride;  // k per point, point-major (stride >= k)
  double* l = lse + job.first;
  double prev = -CUDART_INF;
  for (int it = 0; it < max_iterations; ++it) {
    for (int i = threadIdx.x; i < n; i += blockDim.x)
      l[i] = gmm_em::responsibilities(m, p + 3LL * i, r + static_cast<long long>(i) * k);
    __syncthreads();
    if (threadIdx.x == 0) {
      const double ll = orderedSum(n, [&](int i) { return l[i]; }) / static_cast<double>(n);
      out.log_likelihood = ll;
      out.iterations = it + 1;
      if (ll - prev < tolerance && it > 0) {
        out.converged = 1;
        stop = 1;
      }
      prev = ll;
    }
    __syncthreads();
    if (stop) break;
    // nk[c] (thread 4c) and sx[c][d] (thread 4c + 1 + d), each over the points in order.
    if (threadIdx.x < 4 * k) {
      const int c = threadIdx.x / 4, d = threadIdx.x % 4 - 1;
      auto w = [&](int i) { return r[static_cast<long long>(i) * k + c]; };
      if (d < 0)
        nk[c] = orderedSum(n, w);
      else
        sx[c][d] = orderedSum(n, [&](int i) { return w(i) * p[3LL * i + d]; });
    }
    __syncthreads();
    if (threadIdx.x == 0) gmm_em::newMeans(m, nk, sx);
    __syncthreads();
    // sc[c][e] (thread 6c + e), addScatter's entry e over the points in order.
    if (threadIdx.x < 6 * k) {
      const int c = threadIdx.x / 6, e = threadIdx.x % 6;
      const int a = e < 3 ? e : (e == 5 ? 1 : 0), b = e < 3 ? e : (e == 3 ? 1 : 2);
      const double ma = m.mu[c][a], mb = m.mu[c][b];
      sc[c][e] = orderedSum(n, [&](int i) {
        const double w = r[static_cast<long long>(i) * k + c];
        const double da = p[3LL * i + a] - ma, db = p[3LL * i + b] - mb;
        return w * da * db;
      });
    }
    __syncthreads();
    if (threadIdx.x == 0) {
      const int bad = gmm_em::newCovariances(m, nk, sc, static_cast<double>(n), reg);
      if (bad >= 0) out.bad = bad, stop = 1;
    }
    __syncthreads();
    if (stop) break;
  }
  if (threadIdx.x == 0) out.m = m;
}

void runMixtureFits(const double* points, std::size_t n_points, const std::vector<MixtureJob>& jobs,
                    int max_iterations, double tolerance, double regularization,
                    std::vector<MixtureResult>& results) {
  if (jobs.empty()) return;
  int k = 1;  // the responsibilities' stride: the most components of any job
  for (const MixtureResult& r : results) k = std::max(k, r.m.k);
  DeviceArray<double> d_points(points, 3 * n_points);
  DeviceArray<MixtureJob> d_jobs(jobs.data(), jobs.size());
  DeviceArray<MixtureResult> d_results(results.data(), results.size());
  DeviceArray<double> d_resp(n_points * k), d_lse(n_points);
  mixtureFits<<<static_cast<unsigned>(jobs.size()), kMixtureThreads>>>(
      d_points.ptr(), d_jobs.ptr(), d_results.ptr(), d_resp.ptr(), d_lse.ptr(), k, max_iterations,
      tolerance, regularization);
  cudaCheckLaunch();
  d_results.download(results.data());
}

YieldingWait::~YieldingWait() {
  if (event_) cudaEventDestroy(static_cast<cudaEvent_t>(event_));
}

void YieldingWait::wait() {
  if (!event_) {
    cudaEvent_t e = nullptr;
    cudaSafeCall(cudaEventCreateWithFlags(&e, cudaEventDisableTiming));
    event_ = e;
  }
  const auto e = static_cast<cudaEvent_t>(event_);
  cudaSafeCall(cudaEventRecord(e, cudaStreamPerThread));
  cudaError_t state;
  while ((state = cudaEventQuery(e)) == cudaErrorNotReady) std::this_thread::yield();
  cudaSafeCall(state);
}

PinnedHost::Block PinnedHost::allocate(std::size_t bytes) {
  Block b;
  cudaSafeCall(cudaHostAlloc(&b.ptr, bytes, cudaHostAllocMapped));
  b.bytes = bytes;
  const cudaError_t e = cudaHostGetDevicePointer(&b.device, b.ptr, 0);
  if (e != cudaSuccess) {
    release(b);
    cudaSafeCall(e);
  }
  return b;
}

void PinnedHost::release(Block& b) {
  if (b.ptr) cudaFreeHost(b.ptr);
  b = Block();
}

void PinnedHost::adopt(Block& b) {
  if (b.bytes > block_.bytes) std::swap(b, block_);
  release(b);
}

PinnedHost::~PinnedHost() {
  if (grower_.joinable()) grower_.join();
  release(grown_);
  release(block_);
}

unsigned char* PinnedHost::reserve(std::size_t bytes) {
  if (bytes > block_.bytes || !block_.ptr) {
    release(block_);
    block_ = allocate(grownSize(bytes));
  }
  return data();
}

void PinnedHost::takeGrown() {
  grower_.join();
  grown_ready_.store(false, std::memory_order_relaxed);
  adopt(grown_);
}

unsigned char* PinnedHost::forBatch(std::size_t bytes) {
  if (grower_.joinable() && grown_ready_.load(std::memory_order_acquire)) takeGrown();
  if (block_.ptr && bytes <= block_.bytes) return data();
  if (bytes <= kGrowHere) return reserve(bytes);
  // Too large to page-lock here: this batch goes without. One of a size that comes again (the
  // part merges' refreshes, 1.1-1.8 MB at 800k) has a buffer grown for the next one on a thread
  // of its own; larger ones are one-offs (the sample edges' 8.9 MB of inputs, the first dissolve
  // costs' 14 MB of results), for which page-locking cost more than the copy it saves.
  if (bytes <= kGrowBeside) growBeside(bytes);
  return nullptr;
}

void PinnedHost::growBeside(std::size_t bytes) {
  if (grower_.joinable()) return;
  int device = 0;
  cudaSafeCall(cudaGetDevice(&device));
  const std::size_t want = grownSize(bytes);
  grower_ = std::thread([this, device, want] {
    try {  // on the caller's device: memory pinned for another one would not count as pinned
      cudaSafeCall(cudaSetDevice(device));
      grown_ = allocate(want);
    } catch (...) {  // the batches go without, as before
      grown_ = Block();
    }
    grown_ready_.store(true, std::memory_order_release);
  });
}

unsigned char* PinnedHost::awaitGrown(std::size_t bytes) {
  if (grower_.joinable()) takeGrown();
  return block_.ptr && bytes <= block_.bytes ? data() : nullptr;
}

HostLock& HostLock::operator=(HostLock&& o) noexcept {
  if (this != &o) {
    unlock();
    p_ = std::exchange(o.p_, nullptr);
    bytes_ = std::exchange(o.bytes_, 0);
  }
  return *this;
}

bool HostLock::lock(const void* p, std::size_t bytes) {
  if (p_ && p_ == p && bytes_ == bytes) return true;
  unlock();
  if (!p || bytes == 0) return false;
  void* q = const_cast<void*>(p);
  if (cudaHostRegister(q, bytes, cudaHostRegisterDefault) != cudaSuccess) {
    cudaGetLastError();  // not a sticky error: the copy goes pageable
    return false;
  }
  p_ = q;
  bytes_ = bytes;
  return true;
}

void HostLock::unlock() {
  if (!p_) return;
  if (cudaHostUnregister(p_) != cudaSuccess) cudaGetLastError();  // nothing left to undo
  p_ = nullptr;
  bytes_ = 0;
}

namespace {
// `n` elements from `host` into `a`, whose buffer is kept where it holds them (a store's frames
// replaced by others of no more points: no cudaFree, which waits for the device, and no
// cudaMalloc).
template <class T>
void uploadInto(DeviceArray<T>& a, const T* host, std::size_t n) {
  if (a.sizeBytes() < n * sizeof(T)) a.create(n);
  a.uploadBytes(host, n * sizeof(T));
}

// Buffers of at least this many bytes are worth locking (HostLock) for the copies to come.
constexpr std::size_t kLockedCopyBytes = std::size_t(1) << 20;

// `v`'s buffer page-locked through `lock` where it holds a large array: the whole buffer (its
// capacity), so that the array packed into it again, up to that size, finds it locked.
template <class Vector>
void lockLarge(const Vector& v, HostLock& lock) {
  using T = typename Vector::value_type;
  if (v.size() * sizeof(T) >= kLockedCopyBytes) lock.lock(v.data(), v.capacity() * sizeof(T));
}

}  // namespace

void lockFrameArrays(FrameArrays& in) {
  lockLarge(in.nodes, in.nodes_lock);
  lockLarge(in.points, in.points_lock);
  lockLarge(in.normals, in.normals_lock);
}

void uploadFrames(const FrameArrays& in, FrameStore& store) {
  store.frames = 0;  // no frames while they are replaced: a failed upload leaves none
  store.normal_cos = in.normal_cos;
  store.clip = in.clip;
  uploadInto(store.nodes, in.nodes.data(), in.nodes.size());
  uploadInto(store.root, in.root.data(), in.root.size());
  uploadInto(store.points, in.points.data(), in.points.size());
  uploadInto(store.normals, in.normals.data(), in.normals.size());
  uploadInto(store.spacing, in.spacing.data(), in.spacing.size());
  uploadInto(store.unoriented, in.unoriented.data(), in.unoriented.size());
  store.point0 = in.point0;
  store.frames = in.frames;
}

double runTracking(const FrameStore& frames, const TrackingArrays& in, std::vector<double>& poses,
                   std::vector<double>& residual) {
  TrackingStream stream(frames, in);
  stream.tasks(in.tasks.data(), in.tasks.size());
  return stream.end(poses, residual);
}

struct TrackingStream::Impl {
  std::chrono::steady_clock::time_point t0;
  const FrameStore& frames;
  int T, S, blocks = 1;
  DeviceArray<double> source, probe, global, poses, res;
  DeviceArray<int> source_begin, probe_begin, adj, adj_begin, level, before, two_before, tasks;
  DeviceArray<int> done, next;
  // Each frame's global pose, levels and tasks staged in pinned memory (a slot per frame: the
  // copies run after frame() has returned) for the copies that precede its kernel.
  PinnedHost staging;
  // The poses and residuals come back through pinned memory (a pageable download of 4.9 MB at
  // 800k took 4-5 ms after the last fit); page-locking it takes about as long, so it grows
  // beside the fits (growBeside). Without it (a failure) they come back pageable.
  PinnedHost results;
  std::size_t queued = 0;  // tasks given so far
  int launches = 0;
  Dev d{};
  Impl(const FrameStore& f, const TrackingArrays& in)
      : t0(std::chrono::steady_clock::now()), frames(f), T(f.frames), S(in.samples) {}
  std::size_t resultBytes() const {
    return static_cast<std::size_t>(T) * S * (kPoseDoubles + 1) * sizeof(double);
  }
  // A frame's slot of the staging: its global pose, then its levels. The tasks follow the T
  // slots, in call order.
  std::size_t slot() const {
    return kPoseDoubles * sizeof(double) + static_cast<std::size_t>(S) * sizeof(int);
  }
};

TrackingStream::TrackingStream(const FrameStore& frames, const TrackingArrays& in)
    : impl_(std::make_unique<Impl>(frames, in)) {
  Impl& m = *impl_;
  const long long TS = static_cast<long long>(m.T) * m.S;
  m.source.upload(in.source.data(), in.source.size());
  m.source_begin.upload(in.source_begin.data(), in.source_begin.size());
  m.probe.upload(in.probe.data(), in.probe.size());
  m.probe_begin.upload(in.probe_begin.data(), in.probe_begin.size());
  m.adj.upload(in.adjacency.data(), in.adjacency.size());
  m.adj_begin.upload(in.adjacency_begin.data(), in.adjacency_begin.size());
  m.level.upload(in.level.data(), in.level.size());
  m.before.upload(in.before.data(), in.before.size());
  m.two_before.upload(in.two_before.data(), in.two_before.size());
  m.global.upload(in.global.data(), in.global.size());
  m.tasks.create(static_cast<std::size_t>(std::max<long long>(TS, 1)));
  // Every pose starts as the identity (the reference frame's stay so), written on the device
  // (an upload of 4.5 MB of identities at 800k took 2-4 ms on the path after an idle GPU's
  // start), and the reference frame's are done.
  m.poses.create(static_cast<std::size_t>(std::max<long long>(TS, 1)) * kPoseDoubles);
  if (TS > 0) {
    identityPoses<<<static_cast<unsigned>((TS + 255) / 256), 256, 0, cudaStreamPerThread>>>(
        m.poses.ptr(), TS);
    cudaCheckLaunch();
  }
  m.res.create(static_cast<std::size_t>(std::max<long long>(TS, 1)));
  m.res.setZero();
  std::vector<int> done(static_cast<std::size_t>(TS), 0);
  for (int t = 0; t < m.T; ++t)
    if (in.before[t] < 0)
      for (int s = 0; s < m.S; ++s) done[static_cast<std::size_t>(t) * m.S + s] = 1;
  m.done.upload(done.data(), done.size());
  m.next.create(static_cast<std::size_t>(std::max(m.T, 1)));
  m.next.setZero();
  m.staging.reserve(static_cast<std::size_t>(m.T) *
                    (m.slot() + static_cast<std::size_t>(m.S) * sizeof(int)));
  if (TS > 0) m.results.growBeside(m.resultBytes());
  static_assert(kPoseDoubles * sizeof(double) % alignof(int) == 0, "staging slots stay aligned");
  m.d = frameView(frames);
  m.d.source = m.source.ptr();
  m.d.source_begin = m.source_begin.ptr();
  m.d.probe = m.probe.ptr();
  m.d.probe_begin = m.probe_begin.ptr();
  m.d.adj = m.adj.ptr();
  m.d.adj_begin = m.adj_begin.ptr();
  m.d.level = m.level.ptr();
  m.d.before = m.before.ptr();
  m.d.two_before = m.two_before.ptr();
  m.d.global = m.global.ptr();
  m.d.poses = m.poses.ptr();
  m.d.residual = m.res.ptr();
  m.d.S = m.S;
  m.d.iterations = in.iterations;
  int device = 0, sms = 0, per_sm = 0;
  cudaSafeCall(cudaGetDevice(&device));
  cudaSafeCall(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device));
  cudaSafeCall(
      cudaOccupancyMaxActiveBlocksPerMultiprocessor(&per_sm, trackTasks, kTrackThreads, 0));
  m.blocks = std::max(1, std::min(m.S, sms * std::max(per_sm, 1)));
}

TrackingStream::~TrackingStream() {
  // A stream ended by an error: its kernels finish before the arrays they use are freed.
  if (impl_) cudaStreamSynchronize(cudaStreamPerThread);
}

void TrackingStream::frames(const std::vector<int>& frames, const double* global, const int* level,
                            const int* tasks) {
  Impl& m = *impl_;
  if (m.S <= 0 || frames.empty()) return;
  const std::size_t S = static_cast<std::size_t>(m.S);
  const std::size_t slot = m.slot();
  unsigned char* base = m.staging.reserve(0);
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const std::size_t t = static_cast<std::size_t>(frames[i]);
    double* g = reinterpret_cast<double*>(base + t * slot);
    int* lv = reinterpret_cast<int*>(base + t * slot + kPoseDoubles * sizeof(double));
    std::memcpy(g, global + i * kPoseDoubles, kPoseDoubles * sizeof(double));
    std::memcpy(lv, level + i * S, S * sizeof(int));
    cudaSafeCall(cudaMemcpyAsync(m.global.ptr() + t * kPoseDoubles, g,
                                 kPoseDoubles * sizeof(double), cudaMemcpyHostToDevice,
                                 cudaStreamPerThread));
    cudaSafeCall(cudaMemcpyAsync(m.level.ptr() + t * S, lv, S * sizeof(int), cudaMemcpyHostToDevice,
                                 cudaStreamPerThread));
  }
  this->tasks(tasks, frames.size() * S);
}

void TrackingStream::tasks(const int* tasks, std::size_t n) {
  Impl& m = *impl_;
  if (n == 0) return;
  if (m.queued + n > static_cast<std::size_t>(m.T) * static_cast<std::size_t>(m.S))
    throw DeviceError("GPU tracking: more tasks than the frames hold");
  int* staged =
      reinterpret_cast<int*>(m.staging.reserve(0) + static_cast<std::size_t>(m.T) * m.slot()) +
      m.queued;
  std::memcpy(staged, tasks, n * sizeof(int));
  int* order = m.tasks.ptr() + m.queued;
  cudaSafeCall(
      cudaMemcpyAsync(order, staged, n * sizeof(int), cudaMemcpyHostToDevice, cudaStreamPerThread));
  // These fits in one kernel, after the earlier calls' (the stream's order): the blocks take
  // them in the given order (a topological one), each waiting for the poses its starts read, so
  // a block waits only for tasks taken before its own, which running blocks hold.
  const int count = static_cast<int>(n);
  trackTasks<<<std::max(1, std::min(count, m.blocks)), kTrackThreads, 0, cudaStreamPerThread>>>(
      m.d, order, count, m.next.ptr() + m.launches, m.done.ptr());
  cudaCheckLaunch();
  m.queued += n;
  ++m.launches;
}

double TrackingStream::end(std::vector<double>& poses, std::vector<double>& residual) {
  Impl& m = *impl_;
  const std::size_t TS = static_cast<std::size_t>(m.T) * m.S;
  poses.resize(TS * kPoseDoubles);
  residual.resize(TS);
  unsigned char* pinned = TS > 0 ? m.results.awaitGrown(m.resultBytes()) : nullptr;
  if (pinned) {
    double* host = reinterpret_cast<double*>(pinned);
    cudaSafeCall(cudaMemcpyAsync(host, m.poses.ptr(), TS * kPoseDoubles * sizeof(double),
                                 cudaMemcpyDeviceToHost, cudaStreamPerThread));
    cudaSafeCall(cudaMemcpyAsync(host + TS * kPoseDoubles, m.res.ptr(), TS * sizeof(double),
                                 cudaMemcpyDeviceToHost, cudaStreamPerThread));
    cudaSafeCall(cudaStreamSynchronize(cudaStreamPerThread));
    std::memcpy(poses.data(), host, TS * kPoseDoubles * sizeof(double));
    std::memcpy(residual.data(), host + TS * kPoseDoubles, TS * sizeof(double));
  } else {
    cudaSafeCall(cudaStreamSynchronize(cudaStreamPerThread));
    m.poses.download(poses);
    m.res.download(residual);
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - m.t0).count();
  impl_.reset();
  return seconds;
}

void runResiduals(FrameStore& frames, const std::vector<double>& points,
                  const std::vector<int>& source_begin, const std::vector<double>& motions,
                  const std::vector<ResidualJob>& jobs, long long point_parallel_limit,
                  std::vector<double>& out) {
  out.clear();
  if (jobs.empty()) return;
  const Dev d = frameView(frames);
  const long long n = static_cast<long long>(jobs.size());
  // Up to point_parallel_limit points in all (and below 2^31), a thread per point and then a
  // thread per job for the sums: a merge's few residuals over whole parts left a warp per job
  // searching thousands of points 32 at a time (150-270 us a batch). Larger batches (the sample
  // edges' hundreds of thousands of residuals) fill the GPU with a warp per job, without an
  // error per point.
  long long total = 0;
  for (const ResidualJob& j : jobs) total += source_begin[j.source + 1] - source_begin[j.source];
  if (total <= point_parallel_limit && total < (1LL << 31)) {
    std::vector<ResidualPointJob> list(jobs.size());
    int first = 0;
    for (std::size_t k = 0; k < jobs.size(); ++k) {
      const ResidualJob& j = jobs[k];
      list[k] = {j.source, j.motion, j.frame, first};
      first += source_begin[j.source + 1] - source_begin[j.source];
    }
    // job_out: every point's error; the results go to the host (resultsOnHost).
    const auto in = putBatch(frames, points, &source_begin, motions, list,
                             static_cast<std::size_t>(total) * sizeof(double));
    auto* errors = static_cast<double*>(frames.job_out.rawPtr());
    double* res = resultsOnHost(frames, jobs.size() * sizeof(double));
    constexpr int kThreads = 128;
    const int m = static_cast<int>(total), jn = static_cast<int>(n);
    if (m > 0) {
      residualPointErrors<<<(m + kThreads - 1) / kThreads, kThreads>>>(
          d, in.points, in.begin, in.motions, in.list, jn, m, errors);
      cudaCheckLaunch();
    }
    residualSums<<<(jn + kThreads - 1) / kThreads, kThreads>>>(errors, in.list, jn, m, res);
    cudaCheckLaunch();
    const double* r = finishedResults(frames, jobs.size());
    out.assign(r, r + jobs.size());
    return;
  }
  const auto in = putBatch(frames, points, &source_begin, motions, jobs, 0);
  residualJobs<<<blocksFor(n), kWarp * kWarpsPerBlock>>>(
      d, in.points, in.begin, in.motions, in.list, static_cast<int>(n),
      resultsOnHost(frames, jobs.size() * sizeof(double)));
  cudaCheckLaunch();
  const double* r = finishedResults(frames, jobs.size());
  out.assign(r, r + jobs.size());
}

// The threads of a batch of fits (runPartFits, runScoreFits): a small batch finishes sooner with
// a fit per block (of kLargeThreads where a source has more points than kWideThreads, else of
// kWideThreads); a large one fills the GPU with a fit per warp.
enum class FitWidth { kWarp, kWide, kLarge };
template <class Job>
FitWidth fitWidth(const std::vector<Job>& jobs, const std::vector<int>& source_begin) {
  if (static_cast<long long>(jobs.size()) > kWideFitBatch) return FitWidth::kWarp;
  int largest = 0;
  for (const Job& j : jobs)
    largest = std::max(largest, source_begin[j.source + 1] - source_begin[j.source]);
  return largest > kWideThreads ? FitWidth::kLarge : FitWidth::kWide;
}

// Lets `kernel` (a kLargeThreads kernel) use kLargeShared bytes of dynamic shared memory, once per
// store (`done`).
template <class Kernel>
void allowLargeShared(Kernel kernel, bool& done) {
  if (done) return;
  cudaSafeCall(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                    static_cast<int>(kLargeShared)));
  done = true;
}

// Launches a batch of fits (`in`, its jobs `jobs`) on the kernel of its width (fitWidth):
// `large` with kLargeShared bytes of shared memory (allowed once per store: `large_set`), `wide`,
// or `narrow` (a warp a job, which also takes the job count); each is given the frames, the
// batch's parts, then `out`.
template <class Job, class Large, class Wide, class Narrow, class... Out>
void launchFits(const Dev& d, const BatchView<Job>& in, const std::vector<Job>& jobs,
                const std::vector<int>& source_begin, Large large, bool& large_set, Wide wide,
                Narrow narrow, Out... out) {
  const long long n = static_cast<long long>(jobs.size());
  const FitWidth width = fitWidth(jobs, source_begin);
  if (width == FitWidth::kLarge) {
    allowLargeShared(large, large_set);
    large<<<static_cast<int>(n), kLargeThreads, kLargeShared>>>(d, in.points, in.begin, in.motions,
                                                                in.list, out...);
  } else if (width == FitWidth::kWide) {
    wide<<<static_cast<int>(n), kWideThreads>>>(d, in.points, in.begin, in.motions, in.list,
                                                out...);
  } else {
    narrow<<<blocksFor(n), kWarp * kWarpsPerBlock>>>(d, in.points, in.begin, in.motions, in.list,
                                                     static_cast<int>(n), out...);
  }
  cudaCheckLaunch();
}

void runPartFits(FrameStore& frames, const std::vector<double>& points,
                 const std::vector<int>& source_begin, const std::vector<double>& motions,
                 const std::vector<PartFitJob>& jobs, int iterations, std::vector<double>& poses,
                 std::vector<double>* residual) {
  poses.clear();
  if (residual) residual->clear();
  if (jobs.empty()) return;
  const auto in = putBatch(frames, points, &source_begin, motions, jobs, 0);
  Dev d = frameView(frames);
  d.iterations = iterations;
  // The poses, then (where asked for) the residuals, in one mapped results buffer.
  const std::size_t pose_count = jobs.size() * kPoseDoubles;
  const std::size_t res_count = residual ? jobs.size() : 0;
  double* out = resultsOnHost(frames, (pose_count + res_count) * sizeof(double));
  double* out_res = residual ? out + pose_count : nullptr;
  launchFits(d, in, jobs, source_begin, partFitJobsLarge, frames.large_fits_set, partFitJobsWide,
             partFitJobs, out, out_res);
  const double* r = finishedResults(frames, pose_count + res_count);
  poses.assign(r, r + pose_count);
  if (residual) residual->assign(r + pose_count, r + pose_count + res_count);
}

void runScoreFits(FrameStore& frames, const std::vector<double>& points,
                  const std::vector<int>& source_begin, const std::vector<double>& motions,
                  const std::vector<ScoreFitJob>& jobs, std::size_t starts, int iterations,
                  std::vector<double>& scores, std::vector<int>& fitted,
                  std::vector<double>& poses) {
  scores.clear();
  fitted.clear();
  poses.clear();
  if (jobs.empty()) return;
  const auto in = putBatch(frames, points, &source_begin, motions, jobs, 0);
  Dev d = frameView(frames);
  d.iterations = iterations;
  // Per job the pose and the winner (kScoreFitOut doubles), then the scores, in one mapped
  // results buffer.
  const std::size_t out_count = jobs.size() * kScoreFitOut;
  double* out = resultsOnHost(frames, (out_count + starts) * sizeof(double));
  double* out_scores = out + out_count;
  launchFits(d, in, jobs, source_begin, scoreFitJobsLarge, frames.large_score_fits_set,
             scoreFitJobsWide, scoreFitJobs, out_scores, out);
  const double* r = finishedResults(frames, out_count + starts);
  scores.assign(r + out_count, r + out_count + starts);
  fitted.resize(jobs.size());
  poses.resize(jobs.size() * kPoseDoubles);
  for (std::size_t j = 0; j < jobs.size(); ++j) {
    const double* o = r + j * kScoreFitOut;
    std::copy(o, o + kPoseDoubles, poses.begin() + static_cast<std::ptrdiff_t>(j * kPoseDoubles));
    fitted[j] = static_cast<int>(o[kPoseDoubles]);
  }
}

void runPointCosts(FrameStore& frames, int ref, bool per_frame, const std::vector<double>& points,
                   const std::vector<double>& motions, const std::vector<PointCostJob>& jobs,
                   std::vector<double>& out) {
  const std::size_t T = static_cast<std::size_t>(frames.frames);
  out.clear();
  if (jobs.empty()) return;
  const std::size_t count = jobs.size() * (per_frame ? T : 1);
  // job_out: every (job, frame)'s error; the results go to the host (resultsOnHost).
  const std::size_t errors = jobs.size() * T;
  const auto in = putBatch(frames, points, nullptr, motions, jobs, errors * sizeof(double));
  const Dev d = frameView(frames);
  const int n = static_cast<int>(jobs.size());
  auto* err = static_cast<double*>(frames.job_out.rawPtr());
  double* res = resultsOnHost(frames, count * sizeof(double));
  constexpr int kThreads = 128;
  pointErrorJobs<<<static_cast<int>((errors + kThreads - 1) / kThreads), kThreads>>>(
      d, frames.frames, ref, in.points, in.motions, in.list, n, err);
  cudaCheckLaunch();
  pointCostSums<<<(n + kThreads - 1) / kThreads, kThreads>>>(err, frames.frames, ref, per_frame, n,
                                                             res);
  cudaCheckLaunch();
  const double* r = finishedResults(frames, count);
  out.assign(r, r + count);
}

// --- MotionDevice::nearestMoved: every frame's points against the frame's moved copies --------
//
// Written by us (no kept library searches exact k nearest with the CPU tree's tie order on a
// GPU). A warp takes 32 consecutive points of a frame's tree (leaf order: near each other) and
// walks the copies in tiles of 32 (the caller's order: the reference tree's leaf order, so a
// tile is a small box too). Each lane keeps its point's nearest copies sorted by (squared
// distance, index); a tile is searched only where the box of the warp's points and the tile's
// box are near enough: first within a few spacings, then, for the lanes not yet sure of their
// list, farther.

constexpr int kMovedKeep = 9;  // the k <= 8 nearest, and the next one (a tie at the k-th)
constexpr int kMovedTile = 32;
constexpr int kMovedWarps = 8;

// Squared distance as FlatKdTree3's dist2: (dx^2 + dy^2) + dz^2 in float, without contraction.
__device__ __forceinline__ float movedDist2(float qx, float qy, float qz, float px, float py,
                                            float pz) {
  const float dx = __fsub_rn(qx, px), dy = __fsub_rn(qy, py), dz = __fsub_rn(qz, pz);
  return __fadd_rn(__fadd_rn(__fmul_rn(dx, dx), __fmul_rn(dy, dy)), __fmul_rn(dz, dz));
}

__device__ __forceinline__ bool movedFinite(const float4& p) {
  return isfinite(p.x) && isfinite(p.y) && isfinite(p.z);
}

// Per frame and tile: the box of its finite copies (min, max; empty: +inf, -inf).
__global__ void movedBoxes(const float4* __restrict__ copies, int n, int tiles, int frames,
                           float4* __restrict__ boxes) {
  const long long i = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= static_cast<long long>(tiles) * frames) return;
  const long long t = i / tiles;
  const int tile = static_cast<int>(i % tiles);
  float4 lo = make_float4(CUDART_INF_F, CUDART_INF_F, CUDART_INF_F, 0.0f);
  float4 hi = make_float4(-CUDART_INF_F, -CUDART_INF_F, -CUDART_INF_F, 0.0f);
  const int end = min(n, (tile + 1) * kMovedTile);
  for (int c = tile * kMovedTile; c < end; ++c) {
    const float4 p = copies[2 * (t * n + c)];
    if (!movedFinite(p)) continue;
    lo.x = fminf(lo.x, p.x), lo.y = fminf(lo.y, p.y), lo.z = fminf(lo.z, p.z);
    hi.x = fmaxf(hi.x, p.x), hi.y = fmaxf(hi.y, p.y), hi.z = fmaxf(hi.z, p.z);
  }
  boxes[2 * i] = lo;
  boxes[2 * i + 1] = hi;
}

// The squared gap between two boxes in movedDist2's arithmetic: rounding is monotonic, so no
// pair of points of the two boxes is nearer in movedDist2 than this.
__device__ __forceinline__ float boxGap2(const float* qlo, const float* qhi, const float4& lo,
                                         const float4& hi) {
  const float bl[3] = {lo.x, lo.y, lo.z}, bh[3] = {hi.x, hi.y, hi.z};
  float g[3];
  for (int d = 0; d < 3; ++d)
    g[d] = fmaxf(0.0f, fmaxf(__fsub_rn(bl[d], qhi[d]), __fsub_rn(qlo[d], bh[d])));
  return __fadd_rn(__fadd_rn(__fmul_rn(g[0], g[0]), __fmul_rn(g[1], g[1])), __fmul_rn(g[2], g[2]));
}

struct MovedArgs {
  const float4* pts;  // the frames' points, leaf order
  const float4* nrm;
  const int* point0;  // per frame, plus the end
  const int* warp0;   // per frame: its first warp, plus the end
  const int* unoriented;
  const double* spacing;
  int frames;
  const float4* copies;  // per frame, n copies: position, normal
  const int* order;      // the copies' reference indices
  const float4* boxes;   // per frame, per tile: min, max
  int n, tiles, k;
  double normal_cos;
  int* pick;  // per point, leaf order, frame after frame
};

__global__ void __launch_bounds__(kMovedWarps* kWarp) movedNearest(MovedArgs a) {
  __shared__ float4 tile_p[kMovedWarps][kMovedTile];
  __shared__ int tile_i[kMovedWarps][kMovedTile];
  const unsigned kAll = 0xffffffffu;
  const int warp = threadIdx.x / kWarp, lane = threadIdx.x % kWarp;
  const int gw = blockIdx.x * kMovedWarps + warp;
  if (gw >= a.warp0[a.frames]) return;  // the whole warp
  int t = 0;                            // the last frame whose first warp is at most gw
  for (int hi = a.frames - 1; t < hi;) {
    const int mid = (t + hi + 1) / 2;
    if (a.warp0[mid] <= gw)
      t = mid;
    else
      hi = mid - 1;
  }
  const int q = a.point0[t] + (gw - a.warp0[t]) * kWarp + lane;
  const bool active = q < a.point0[t + 1];
  const float4 p = active ? a.pts[q] : make_float4(0.0f, 0.0f, 0.0f, 0.0f);
  // The box of the warp's points.
  float qlo[3] = {active ? p.x : CUDART_INF_F, active ? p.y : CUDART_INF_F,
                  active ? p.z : CUDART_INF_F};
  float qhi[3] = {active ? p.x : -CUDART_INF_F, active ? p.y : -CUDART_INF_F,
                  active ? p.z : -CUDART_INF_F};
  for (int o = 16; o > 0; o /= 2)
    for (int d = 0; d < 3; ++d) {
      qlo[d] = fminf(qlo[d], __shfl_xor_sync(kAll, qlo[d], o));
      qhi[d] = fmaxf(qhi[d], __shfl_xor_sync(kAll, qhi[d], o));
    }
  const long long c0 = static_cast<long long>(t) * a.n;
  const float4* copies = a.copies + 2 * c0;
  const float4* boxes = a.boxes + 2 * static_cast<long long>(t) * a.tiles;
  float bd[kMovedKeep];
  int bi[kMovedKeep], bc[kMovedKeep];  // reference index, copy
#pragma unroll
  for (int e = 0; e < kMovedKeep; ++e) bd[e] = CUDART_INF_F, bi[e] = INT_MAX, bc[e] = -1;
  // Rounds: the tiles whose gap is in (done, reach]; a lane is sure of its list once its last
  // entry is within `reach` (a copy not searched yet is farther than reach). The first reach is
  // 4 spacings (the mean distance to the nearest point; the 9th nearest lies at about 3.4), each
  // next one sqrt(2) times farther: against 3 spacings and 4 times farther, 34% fewer tiles
  // searched at 800k (5.7 -> 4.7 ms on the H200).
  const float s = static_cast<float>(a.spacing[t]);
  float done = -1.0f, reach = 16.0f * s * s;
  if (!(reach > 0.0f)) reach = CUDART_INF_F;
  for (;;) {
    for (int base = 0; base < a.tiles; base += kWarp) {
      const int tl = base + lane;
      bool take = false;
      if (tl < a.tiles) {
        const float g = boxGap2(qlo, qhi, boxes[2 * tl], boxes[2 * tl + 1]);
        take = g > done && g <= reach;
      }
      unsigned mask = __ballot_sync(kAll, take);
      while (mask) {
        const int tile = base + __ffs(mask) - 1;
        mask &= mask - 1;
        const int c = tile * kMovedTile + lane;
        tile_p[warp][lane] =
            c < a.n ? copies[2LL * c] : make_float4(CUDART_NAN_F, CUDART_NAN_F, CUDART_NAN_F, 0.0f);
        tile_i[warp][lane] = c < a.n ? a.order[c] : INT_MAX;
        __syncwarp();
        if (active)
          for (int j = 0; j < kMovedTile; ++j) {
            const float4 cp = tile_p[warp][j];
            if (!movedFinite(cp)) continue;
            const float d2 = movedDist2(p.x, p.y, p.z, cp.x, cp.y, cp.z);
            const int key = tile_i[warp][j];
            if (!(d2 < bd[kMovedKeep - 1] ||
                  (d2 == bd[kMovedKeep - 1] && key < bi[kMovedKeep - 1])))
              continue;
            const int copy = tile * kMovedTile + j;
#pragma unroll
            for (int e = kMovedKeep - 1; e > 0; --e) {
              if (d2 < bd[e - 1] || (d2 == bd[e - 1] && key < bi[e - 1])) {
                bd[e] = bd[e - 1], bi[e] = bi[e - 1], bc[e] = bc[e - 1];
              } else if (d2 < bd[e] || (d2 == bd[e] && key < bi[e])) {
                bd[e] = d2, bi[e] = key, bc[e] = copy;
              }
            }
            if (d2 < bd[0] || (d2 == bd[0] && key < bi[0])) bd[0] = d2, bi[0] = key, bc[0] = copy;
          }
        __syncwarp();
      }
    }
    const bool sure = !active || bd[kMovedKeep - 1] <= reach;
    if (__all_sync(kAll, sure) || reach == CUDART_INF_F) break;
    done = reach;
    reach = reach < 1e30f ? 2.0f * reach : CUDART_INF_F;
  }
  if (!active) return;
  // The pick: the first of the k nearest with an agreeing normal (the CPU's float cosine), else
  // the nearest. A tie between the k-th and the next leaves the entries at the k-th's distance
  // to the order the CPU's tree visits them: a pick that needs them is undecided.
  // (Every index below is a constant after unrolling: the lists stay in registers.)
  const int k = a.k;
  int filled = 0;
  float dk = bd[0], dk1 = CUDART_INF_F;  // the k-th distance and the next
#pragma unroll
  for (int e = 0; e < kMovedKeep; ++e) {
    filled += bi[e] != INT_MAX;
    if (e == k - 1) dk = bd[e];
    if (e == k) dk1 = bd[e];
  }
  const int kk = min(k, filled);
  const bool boundary_tie = filled > k && dk == dk1;
  int first_at_dk = kMovedKeep;
#pragma unroll
  for (int e = kMovedKeep - 1; e >= 0; --e)
    if (bd[e] == dk) first_at_dk = e;
  const int sure_below = boundary_tie ? first_at_dk : kk;  // entries before it are the CPU's
  const float4 pn = a.nrm[q];
  const bool unoriented = a.unoriented[t] != 0;
  int pick = kk > 0 ? bi[0] : -1;
  bool found = false;
#pragma unroll
  for (int e = 0; e < kMovedKeep; ++e) {
    if (found || e >= kk || e >= sure_below) continue;
    const float4 cn = copies[2LL * bc[e] + 1];
    const float c =
        __fadd_rn(__fadd_rn(__fmul_rn(cn.x, pn.x), __fmul_rn(cn.y, pn.y)), __fmul_rn(cn.z, pn.z));
    const double cd = unoriented ? fabs(static_cast<double>(c)) : static_cast<double>(c);
    if (cd > a.normal_cos) pick = bi[e], found = true;
  }
  if (!found && boundary_tie) pick = kMovedUndecided;
  a.pick[q] = pick;
}

void runMovedNearest(FrameStore& frames, const std::vector<int>& order, int k, double normal_cos,
                     const std::function<void(float*)>& fill, std::vector<int>& pick) {
  const FrameStore& f = frames.shared ? *frames.shared : frames;
  const int T = f.frames;
  if (static_cast<int>(f.point0.size()) != T + 1)
    throw DeviceError("GPU labels: the frames' point ranges are missing");
  if (k < 1 || k > kMovedKeep - 1) throw DeviceError("GPU labels: k must be 1..8");
  const int n = static_cast<int>(order.size());
  const int tiles = (n + kMovedTile - 1) / kMovedTile;
  const int points = f.point0[T];
  pick.clear();
  if (points == 0) return;
  std::vector<int> warp0(T + 1, 0);
  for (int t = 0; t < T; ++t)
    warp0[t + 1] = warp0[t] + (f.point0[t + 1] - f.point0[t] + kWarp - 1) / kWarp;
  if (n == 0) {  // no copies: no label
    pick.assign(points, -1);
    return;
  }
  // Inputs in one block of host memory (the copies written there by the caller), up with one
  // copy: copies, order, point0, warp0 (the boxes have room on the device only). Pageable
  // memory, kept by the store: growing the pinned staging to the copies' 26 MB at 800k took
  // 0.016-0.020 s (page-locking them), against 1.5 ms for the copy from pageable memory.
  const std::size_t copies_bytes = 2 * sizeof(float4) * static_cast<std::size_t>(T) * n;
  const std::size_t order_bytes = sizeof(int) * static_cast<std::size_t>(n);
  const std::size_t ranges_bytes = sizeof(int) * 2 * static_cast<std::size_t>(T + 1);
  const std::size_t at_order = copies_bytes;
  const std::size_t at_ranges = (at_order + order_bytes + 15) & ~static_cast<std::size_t>(15);
  const std::size_t used = at_ranges + ranges_bytes;
  using Clock = std::chrono::steady_clock;
  const auto t0 = Clock::now();
  frames.moved_host.resize((used + sizeof(float) - 1) / sizeof(float));
  auto* st = reinterpret_cast<unsigned char*>(frames.moved_host.data());
  const auto t1 = Clock::now();
  fill(reinterpret_cast<float*>(st));
  const auto t2 = Clock::now();
  std::memcpy(st + at_order, order.data(), order_bytes);
  std::memcpy(st + at_ranges, f.point0.data(), sizeof(int) * (T + 1));
  std::memcpy(st + at_ranges + sizeof(int) * (T + 1), warp0.data(), sizeof(int) * (T + 1));
  const std::size_t boxes_bytes = 2 * sizeof(float4) * static_cast<std::size_t>(T) * tiles;
  const std::size_t at_boxes = (used + 15) & ~static_cast<std::size_t>(15);
  grow(frames.job_in, at_boxes + boxes_bytes);
  auto* base = static_cast<unsigned char*>(frames.job_in.rawPtr());
  // (From pageable memory the copy has returned when the buffer may be written again.)
  cudaSafeCall(cudaMemcpyAsync(base, st, used, cudaMemcpyHostToDevice, cudaStreamPerThread));
  MovedArgs a{};
  const Dev d = frameView(frames);
  a.pts = d.pts;
  a.nrm = d.nrm;
  a.point0 = reinterpret_cast<const int*>(base + at_ranges);
  a.warp0 = a.point0 + (T + 1);
  a.unoriented = d.unoriented;
  a.spacing = d.spacing;
  a.frames = T;
  a.copies = reinterpret_cast<const float4*>(base);
  a.order = reinterpret_cast<const int*>(base + at_order);
  a.boxes = reinterpret_cast<const float4*>(base + at_boxes);
  a.n = n;
  a.tiles = tiles;
  a.k = k;
  a.normal_cos = normal_cos;
  const std::size_t out_doubles = (sizeof(int) * static_cast<std::size_t>(points) + 7) / 8;
  a.pick = reinterpret_cast<int*>(resultsOnHost(frames, out_doubles * sizeof(double)));
  const long long box_threads = static_cast<long long>(T) * tiles;
  movedBoxes<<<static_cast<int>((box_threads + 127) / 128), 128, 0, cudaStreamPerThread>>>(
      a.copies, n, tiles, T, reinterpret_cast<float4*>(base + at_boxes));
  cudaCheckLaunch();
  movedNearest<<<(warp0[T] + kMovedWarps - 1) / kMovedWarps, kMovedWarps * kWarp, 0,
                 cudaStreamPerThread>>>(a);
  cudaCheckLaunch();
  const auto t3 = Clock::now();
  const auto* r = reinterpret_cast<const int*>(finishedResults(frames, out_doubles));
  const auto t4 = Clock::now();
  pick.assign(r, r + points);
  if (std::getenv("ANIMSEG_MS_TIMING")) {
    auto s = [](Clock::time_point a, Clock::time_point b) {
      return std::chrono::duration<double>(b - a).count();
    };
    std::fprintf(stderr,
                 "[gpu labels] host buffer %.4f s, copies %.4f s, launches %.4f s, search %.4f s, "
                 "picks %.4f s\n",
                 s(t0, t1), s(t1, t2), s(t2, t3), s(t3, t4), s(t4, Clock::now()));
  }
}

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
