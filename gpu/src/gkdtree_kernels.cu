// Gaussian kd-tree on the GPU (Adams et al. 2009; the paper's Sect. 3.3, after Zhou et al.'s
// GPU kd-tree build [31]): the same tree, samples and filter as the CPU reference
// (src/filters/gaussian_kdtree.cpp), so that both backends give the same mean-shift modes.
//
// Build: level-synchronous, as in [31]. The points stay put; a permutation keeps each active
// node's points contiguous. Per level: bounding boxes by a tiled reduction, the split decision per
// node (longest side, cut at the middle: the CPU rule), then a stable partition by one global
// prefix sum. The host drives the levels (a few tiny copies per level; the depth is tens).
// Distances that decide something discrete (leaf vs. split, blur cut-off) are summed in the CPU's
// order without fused multiply-add, so that both backends take the same decisions bit for bit.
#include "cuda_check.h"
#include "gkdtree_device.h"

#include <cub/device/device_scan.cuh>

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <numeric>

namespace pcl_animseg {
namespace gpu {
namespace detail {

namespace {

constexpr int kTile = 4096;  // points per block in the tiled reductions
constexpr int kThreads = 256;

struct Tile {
  int seg;
  int begin;
  int end;
};

// Order-preserving map float -> unsigned, so that atomicMin/Max on it are float min/max.
__device__ __forceinline__ unsigned floatToOrdered(float f) {
  const unsigned u = __float_as_uint(f);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}
__device__ __forceinline__ float orderedToFloat(unsigned u) {
  return __uint_as_float((u & 0x80000000u) ? (u & 0x7fffffffu) : ~u);
}

int blocksFor(long long n, int threads) { return static_cast<int>((n + threads - 1) / threads); }

// Bounding box of each segment's points: block = tile; threads as (group g, dimension k).
__global__ void boxKernel(const float* __restrict__ pts, const int* __restrict__ perm, int d,
                          const Tile* __restrict__ tiles, unsigned* box_lo, unsigned* box_hi) {
  __shared__ float s_lo[kThreads];
  __shared__ float s_hi[kThreads];
  const Tile t = tiles[blockIdx.x];
  const int groups = blockDim.x / d;
  const int g = threadIdx.x / d, k = threadIdx.x % d;
  float lo = FLT_MAX, hi = -FLT_MAX;
  if (g < groups) {
    for (int p = t.begin + g; p < t.end; p += groups) {
      const float x = pts[static_cast<long long>(perm[p]) * d + k];
      lo = fminf(lo, x);
      hi = fmaxf(hi, x);
    }
  }
  s_lo[threadIdx.x] = lo;
  s_hi[threadIdx.x] = hi;
  __syncthreads();
  if (threadIdx.x < d) {
    for (int gg = 1; gg < groups; ++gg) {
      lo = fminf(lo, s_lo[gg * d + k]);
      hi = fmaxf(hi, s_hi[gg * d + k]);
    }
    atomicMin(&box_lo[t.seg * d + k], floatToOrdered(lo));
    atomicMax(&box_hi[t.seg * d + k], floatToOrdered(hi));
  }
}

// The CPU's split rule per segment: longest side (first on ties, as Eigen's maxCoeff), middle.
__global__ void decideKernel(const unsigned* box_lo, const unsigned* box_hi, int nseg, int d,
                             int* dim_out, float* cut_out, float* extent_out) {
  const int s = blockIdx.x * blockDim.x + threadIdx.x;
  if (s >= nseg) return;
  int best = 0;
  float ext = orderedToFloat(box_hi[s * d]) - orderedToFloat(box_lo[s * d]);
  for (int k = 1; k < d; ++k) {
    const float e = orderedToFloat(box_hi[s * d + k]) - orderedToFloat(box_lo[s * d + k]);
    if (e > ext) {
      ext = e;
      best = k;
    }
  }
  dim_out[s] = best;
  cut_out[s] = 0.5f * (orderedToFloat(box_lo[s * d + best]) + orderedToFloat(box_hi[s * d + best]));
  extent_out[s] = ext;
}

__global__ void flagKernel(const float* __restrict__ pts, const int* __restrict__ perm, int d,
                           const Tile* __restrict__ tiles, const int* __restrict__ seg_dim,
                           const float* __restrict__ seg_cut, int* flags) {
  const Tile t = tiles[blockIdx.x];
  const int dim = seg_dim[t.seg];
  const float cut = seg_cut[t.seg];
  for (int p = t.begin + threadIdx.x; p < t.end; p += blockDim.x)
    flags[p] = pts[static_cast<long long>(perm[p]) * d + dim] <= cut ? 1 : 0;
}

__global__ void gatherKernel(const int* scan, const int* seg_begin, const int* seg_end, int nseg,
                             int* left_count) {
  const int s = blockIdx.x * blockDim.x + threadIdx.x;
  if (s < nseg) left_count[s] = scan[seg_end[s]] - scan[seg_begin[s]];
}

// Stable partition of each splitting segment: left (flag 1) first. A segment whose points all
// fall on one side (float rounding on tiny extents) is split by count instead, as on the CPU.
__global__ void scatterKernel(const int* __restrict__ perm, const int* __restrict__ flags,
                              const int* __restrict__ scan, const Tile* __restrict__ tiles,
                              const int* __restrict__ seg_begin, const int* __restrict__ seg_left,
                              const int* __restrict__ seg_fallback, int* perm_out) {
  const Tile t = tiles[blockIdx.x];
  const int b = seg_begin[t.seg];
  if (seg_fallback[t.seg]) {
    for (int p = t.begin + threadIdx.x; p < t.end; p += blockDim.x) perm_out[p] = perm[p];
    return;
  }
  const int nl = seg_left[t.seg];
  const int base = scan[b];
  for (int p = t.begin + threadIdx.x; p < t.end; p += blockDim.x) {
    const int rank_left = scan[p] - base;
    const int dst = flags[p] ? b + rank_left : b + nl + (p - b - rank_left);
    perm_out[dst] = perm[p];
  }
}

// Sums over each segment in double (the CPU accumulates leaf means and splats in double). The
// values of point i are row i of `vals` (n x v), or [pts row i, 1] when vals is null.
__global__ void segmentSumKernel(const float* __restrict__ vals, const float* __restrict__ pts,
                                 const int* __restrict__ perm, int v, int d,
                                 const Tile* __restrict__ tiles, double* sums) {
  __shared__ double s_acc[kThreads];
  const Tile t = tiles[blockIdx.x];
  const int groups = blockDim.x / v;
  const int g = threadIdx.x / v, k = threadIdx.x % v;
  double acc = 0.0;
  if (g < groups) {
    for (int p = t.begin + g; p < t.end; p += groups) {
      const long long i = perm[p];
      acc += vals ? vals[i * v + k] : (k < d ? pts[i * d + k] : 1.0f);
    }
  }
  s_acc[threadIdx.x] = acc;
  __syncthreads();
  if (threadIdx.x < v) {
    for (int gg = 1; gg < groups; ++gg) acc += s_acc[gg * v + k];
    atomicAdd(&sums[static_cast<long long>(t.seg) * v + k], acc);
  }
}

__global__ void meanKernel(const double* sums, const int* leaf_begin, int m, int d,
                           float* samples) {
  const long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x;
  if (i >= static_cast<long long>(m) * d) return;
  const int l = static_cast<int>(i / d);
  samples[i] = static_cast<float>(sums[i] / (leaf_begin[l + 1] - leaf_begin[l]));
}

__global__ void leafOfPointKernel(const int* perm, const int* leaf_begin, int m,
                                  int* leaf_of_point) {
  const int l = blockIdx.x;
  if (l >= m) return;
  for (int p = leaf_begin[l] + threadIdx.x; p < leaf_begin[l + 1]; p += blockDim.x)
    leaf_of_point[perm[p]] = l;
}

// Blur: B_m = sum over samples l with |s_m - s_l|^2 <= r^2 of exp(-|s_m - s_l|^2 / 2) V_l, all
// pairs (M is N / sampling factor: small). Block = 32 target samples; sources stream through
// shared memory 32 at a time. The distance is summed in dimension order without FMA: the CPU's
// range search decides the same pairs.
constexpr int kBlurTargets = 32;
constexpr int kBlurSources = 16;  // keeps the static shared memory under 48 KB
constexpr int kBlurOutPerThread = (kBlurTargets * (kMaxValueDim + 1) + kThreads - 1) / kThreads;

__global__ void __launch_bounds__(kThreads)
    blurKernel(const float* __restrict__ samples, const double* __restrict__ splat, int m, int d,
               int v, float r2, float* out) {
  __shared__ float s_t[kBlurTargets * kMaxDim];
  __shared__ float s_s[kBlurSources * kMaxDim];
  __shared__ double s_w[kBlurTargets * kBlurSources];
  __shared__ double s_v[kBlurSources * kMaxValueDim];
  const int t0 = blockIdx.x * kBlurTargets;
  const int nt = min(kBlurTargets, m - t0);
  for (int i = threadIdx.x; i < nt * d; i += blockDim.x)
    s_t[i] = samples[static_cast<long long>(t0) * d + i];
  double acc[kBlurOutPerThread];
#pragma unroll
  for (int j = 0; j < kBlurOutPerThread; ++j) acc[j] = 0.0;
  for (int s0 = 0; s0 < m; s0 += kBlurSources) {
    const int ns = min(kBlurSources, m - s0);
    __syncthreads();
    for (int i = threadIdx.x; i < ns * d; i += blockDim.x)
      s_s[i] = samples[static_cast<long long>(s0) * d + i];
    for (int i = threadIdx.x; i < ns * v; i += blockDim.x)
      s_v[i] = splat[static_cast<long long>(s0) * v + i];
    __syncthreads();
    bool any = false;
    for (int pr = threadIdx.x; pr < kBlurTargets * kBlurSources; pr += blockDim.x) {
      const int a = pr / kBlurSources, b = pr % kBlurSources;
      double w = 0.0;
      if (a < nt && b < ns) {
        float d2 = 0.0f;
        for (int k = 0; k < d; ++k) {
          const float e = __fsub_rn(s_t[a * d + k], s_s[b * d + k]);
          d2 = __fadd_rn(d2, __fmul_rn(e, e));
        }
        if (d2 <= r2) w = exp(-0.5 * static_cast<double>(d2));
      }
      s_w[pr] = w;
      any = any || w != 0.0;
    }
    // Most source tiles are beyond the blur radius of every target: skip their products.
    if (!__syncthreads_or(any)) continue;
#pragma unroll
    for (int j = 0; j < kBlurOutPerThread; ++j) {
      const int o = threadIdx.x + j * kThreads;
      if (o < nt * v) {
        const int a = o / v, c = o % v;
        double sum = acc[j];
        for (int b = 0; b < ns; ++b) sum += s_w[a * kBlurSources + b] * s_v[b * v + c];
        acc[j] = sum;
      }
    }
  }
#pragma unroll
  for (int j = 0; j < kBlurOutPerThread; ++j) {
    const int o = threadIdx.x + j * kThreads;
    if (o < nt * v) out[static_cast<long long>(t0) * v + o] = static_cast<float>(acc[j]);
  }
}

// Slice, one warp per query: lanes hold the query's coordinates and the output's columns; the
// walk down the tree is the same for all lanes (lane 0 keeps the stack in shared memory). The
// importance samples are divided at each split exactly as in the CPU's sliceOne.
constexpr int kWarpsPerBlock = 8;
constexpr int kStack = kMaxDepth + 4;

struct SliceShared {
  int stack_node[kStack];
  int stack_count[kStack];
  int reached[kMaxSliceSamples];
  float dist[kMaxSliceSamples];
};

template <int C>
__device__ void sliceWarp(const GpuNode* __restrict__ nodes, int root,
                          const float* __restrict__ samples, const float* __restrict__ sv, int d,
                          int v, int slice_samples, float inv_h_sqrt2, float inv_2h2, float q0,
                          float q1, SliceShared& sh, float (&o)[C]) {
  const int lane = threadIdx.x & 31;
  int top = 0;
  if (lane == 0) {
    sh.stack_node[0] = root;
    sh.stack_count[0] = slice_samples;
  }
  int nreached = 0;
  top = 1;
  __syncwarp();
  while (top > 0) {
    --top;
    const int node = sh.stack_node[top];
    const int count = sh.stack_count[top];
    const GpuNode nd = nodes[node];
    __syncwarp();
    if (nd.dim < 0) {
      if (lane == 0) sh.reached[nreached] = nd.leaf;
      ++nreached;
      __syncwarp();
      continue;
    }
    const float lo_v = __shfl_sync(0xffffffffu, q0, nd.dim & 31);
    const float hi_v = __shfl_sync(0xffffffffu, q1, nd.dim & 31);
    const float qd = nd.dim < 32 ? lo_v : hi_v;
    const float p_left = 0.5f * erfcf((qd - nd.cut) * inv_h_sqrt2);
    const int n_left = static_cast<int>(lroundf(static_cast<float>(count) * p_left));
    if (lane == 0) {
      if (n_left > 0) {
        sh.stack_node[top] = nd.left;
        sh.stack_count[top] = n_left;
      }
      if (count - n_left > 0) {
        sh.stack_node[top + (n_left > 0)] = nd.right;
        sh.stack_count[top + (n_left > 0)] = count - n_left;
      }
    }
    top += (n_left > 0) + (count - n_left > 0);
    __syncwarp();
  }
  float dmin = FLT_MAX;
  for (int r = 0; r < nreached; ++r) {
    const float* s = samples + static_cast<long long>(sh.reached[r]) * d;
    float part = 0.0f;
    if (lane < d) part = (q0 - s[lane]) * (q0 - s[lane]);
    if (lane + 32 < d) part += (q1 - s[lane + 32]) * (q1 - s[lane + 32]);
#pragma unroll
    for (int off = 16; off > 0; off >>= 1) part += __shfl_xor_sync(0xffffffffu, part, off);
    if (lane == 0) sh.dist[r] = part;
    dmin = fminf(dmin, part);
  }
  __syncwarp();
#pragma unroll
  for (int j = 0; j < C; ++j) o[j] = 0.0f;
  double wsum = 0.0;
  for (int r = 0; r < nreached; ++r) {
    const float w = expf(-(sh.dist[r] - dmin) * inv_2h2);
    wsum += w;
    const float* f = sv + static_cast<long long>(sh.reached[r]) * v;
#pragma unroll
    for (int j = 0; j < C; ++j) {
      const int c = lane + 32 * j;
      if (c < v) o[j] += w * f[c];
    }
  }
  const float inv = static_cast<float>(1.0 / wsum);
#pragma unroll
  for (int j = 0; j < C; ++j) o[j] *= inv;
}

template <int C>
__global__ void __launch_bounds__(kWarpsPerBlock * 32)
    sliceKernel(const GpuNode* __restrict__ nodes, int root, const float* __restrict__ samples,
                const float* __restrict__ sv, int d, int v, int slice_samples, float inv_h_sqrt2,
                float inv_2h2, const float* __restrict__ queries,
                const float* __restrict__ metric, const int* __restrict__ rows, int nrows,
                int accumulate, float* __restrict__ out) {
  __shared__ SliceShared sh_all[kWarpsPerBlock];
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  const long long w = static_cast<long long>(blockIdx.x) * kWarpsPerBlock + warp;
  if (w >= nrows) return;
  const long long row = rows ? rows[w] : w;
  const float* q = queries + row * d;
  // The CPU scales each query by the metric (one float multiply) before filtering: same here.
  float q0 = lane < d ? q[lane] : 0.0f;
  float q1 = lane + 32 < d ? q[lane + 32] : 0.0f;
  if (metric) {
    if (lane < d) q0 *= metric[lane];
    if (lane + 32 < d) q1 *= metric[lane + 32];
  }
  float o[C];
  sliceWarp<C>(nodes, root, samples, sv, d, v, slice_samples, inv_h_sqrt2, inv_2h2, q0, q1,
               sh_all[warp], o);
#pragma unroll
  for (int j = 0; j < C; ++j) {
    const int c = lane + 32 * j;
    if (c < v) {
      if (accumulate)
        out[row * v + c] += o[j];
      else
        out[row * v + c] = o[j];
    }
  }
}

// Mean-shift update of runPaper (CPU): y <- out[0:d] / out[d] (Eq. 8 via Eq. 10), stop when the
// step, measured in the plain metric, is below the tolerance or the weight is not positive.
// Survivors are listed for the next step, split by query kind (keypoint or not).
__global__ void updateKernel(float* __restrict__ y, const float* __restrict__ out, int d,
                             const int* __restrict__ rows, int nrows,
                             const float* __restrict__ metric, const unsigned char* __restrict__ key,
                             float tol2, int* next_plain, int* next_key, int* counters) {
  const int warp = threadIdx.x >> 5, lane = threadIdx.x & 31;
  const long long w = static_cast<long long>(blockIdx.x) * kWarpsPerBlock + warp;
  if (w >= nrows) return;
  const int row = rows[w];
  const long long v = d + 1;
  const float den = out[row * v + d];
  if (!(den > 0.0f)) return;
  float* yr = y + static_cast<long long>(row) * d;
  float step2 = 0.0f;
  float n0 = 0.0f, n1 = 0.0f;
  if (lane < d) {
    n0 = out[row * v + lane] / den;
    const float e = (n0 - yr[lane]) * metric[lane];
    step2 += e * e;
  }
  if (lane + 32 < d) {
    n1 = out[row * v + lane + 32] / den;
    const float e = (n1 - yr[lane + 32]) * metric[lane + 32];
    step2 += e * e;
  }
#pragma unroll
  for (int off = 16; off > 0; off >>= 1) step2 += __shfl_xor_sync(0xffffffffu, step2, off);
  if (lane < d) yr[lane] = n0;
  if (lane + 32 < d) yr[lane + 32] = n1;
  if (lane == 0 && !(step2 < tol2)) {
    if (key && key[row])
      next_key[atomicAdd(&counters[1], 1)] = row;
    else
      next_plain[atomicAdd(&counters[0], 1)] = row;
  }
}

// rows x cols row-major -> cols x rows row-major, 32 x 32 tiles through shared memory.
__global__ void transposeKernel(const float* __restrict__ src, int rows, int cols,
                                float* __restrict__ dst) {
  __shared__ float tile[32][33];
  const int c0 = blockIdx.x * 32, r0 = blockIdx.y * 32;
  for (int i = threadIdx.y; i < 32; i += blockDim.y) {
    const int r = r0 + i, c = c0 + threadIdx.x;
    if (r < rows && c < cols) tile[i][threadIdx.x] = src[static_cast<long long>(r) * cols + c];
  }
  __syncthreads();
  for (int i = threadIdx.y; i < 32; i += blockDim.y) {
    const int c = c0 + i, r = r0 + threadIdx.x;
    if (r < rows && c < cols) dst[static_cast<long long>(c) * rows + r] = tile[threadIdx.x][i];
  }
}

__global__ void gatherRowsKernel(const float* __restrict__ src, int d, const int* __restrict__ idx,
                                 int ni, const float* __restrict__ metric, float* __restrict__ raw,
                                 float* __restrict__ scaled) {
  const long long e = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x;
  if (e >= static_cast<long long>(ni) * d) return;
  const int i = static_cast<int>(e / d), k = static_cast<int>(e % d);
  const float x = src[static_cast<long long>(idx[i]) * d + k];
  if (raw) raw[e] = x;
  if (scaled) scaled[e] = __fmul_rn(x, metric[k]);
}

__global__ void columnKernel(const float* __restrict__ src, int n, int v, int c,
                             float* __restrict__ dst) {
  const long long i = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x;
  if (i < n) dst[i] = src[i * v + c];
}

}  // namespace

void buildTree(const float* points, int n, int d, const filters::GaussianKdTreeParams& params,
               TreeDevice& tree) {
  if (d < 1 || d > kMaxDim) throw DeviceError("GPU Gaussian kd-tree: dimension must be 1..64");
  tree = TreeDevice();
  tree.n = n;
  tree.d = d;
  std::vector<int> iota(n);
  std::iota(iota.begin(), iota.end(), 0);
  tree.perm.upload(iota);
  DeviceArray<int> perm2(n), flags(n + 1), scan(n + 1);
  flags.setZero();
  std::size_t scan_tmp_bytes = 0;
  cudaSafeCall(cub::DeviceScan::ExclusiveSum(nullptr, scan_tmp_bytes, flags.ptr(), scan.ptr(),
                                             n + 1));
  DeviceMemory scan_tmp(std::max<std::size_t>(scan_tmp_bytes, 1));

  struct Seg {
    int node, begin, end, depth;
  };
  struct LeafSeg {
    int node, begin, end;
  };
  std::vector<Seg> active{{0, 0, n, 0}};
  std::vector<LeafSeg> leaves;
  tree.host_nodes.assign(1, GpuNode{-1, 0.0f, -1, -1, -1});
  const int min_points = std::max(2, params.min_leaf_points);

  DeviceArray<Tile> d_tiles;
  DeviceArray<unsigned> box_lo, box_hi;
  DeviceArray<int> seg_dim, seg_begin, seg_end, seg_left, seg_fallback;
  DeviceArray<float> seg_cut, seg_extent;
  std::vector<Tile> tiles;
  auto makeTiles = [&](const std::vector<Seg>& segs) {
    tiles.clear();
    for (int s = 0; s < static_cast<int>(segs.size()); ++s)
      for (int b = segs[s].begin; b < segs[s].end; b += kTile)
        tiles.push_back({s, b, std::min(segs[s].end, b + kTile)});
    d_tiles.upload(tiles);
  };

  while (!active.empty()) {
    // Cells too small or too deep are leaves without looking at their boxes.
    std::vector<Seg> cand;
    for (const Seg& s : active) {
      if (s.end - s.begin < min_points || s.depth >= kMaxDepth)
        leaves.push_back({s.node, s.begin, s.end});
      else
        cand.push_back(s);
    }
    if (cand.empty()) break;
    const int ns = static_cast<int>(cand.size());
    makeTiles(cand);
    // Empty boxes: all-ones bytes are the largest ordered key, zeros the smallest.
    box_lo.create(static_cast<std::size_t>(ns) * d);
    box_hi.create(static_cast<std::size_t>(ns) * d);
    cudaSafeCall(cudaMemset(box_lo.ptr(), 0xff, box_lo.sizeBytes()));
    box_hi.setZero();
    boxKernel<<<static_cast<int>(tiles.size()), kThreads>>>(points, tree.perm.ptr(), d,
                                                            d_tiles.ptr(), box_lo.ptr(),
                                                            box_hi.ptr());
    cudaCheckLaunch();
    seg_dim.create(ns);
    seg_cut.create(ns);
    seg_extent.create(ns);
    decideKernel<<<blocksFor(ns, 128), 128>>>(box_lo.ptr(), box_hi.ptr(), ns, d, seg_dim.ptr(),
                                              seg_cut.ptr(), seg_extent.ptr());
    cudaCheckLaunch();
    std::vector<int> h_dim;
    std::vector<float> h_cut, h_ext;
    seg_dim.download(h_dim);
    seg_cut.download(h_cut);
    seg_extent.download(h_ext);

    std::vector<Seg> split;
    std::vector<int> split_src;  // index into cand
    for (int s = 0; s < ns; ++s) {
      if (h_ext[s] <= params.leaf_extent)
        leaves.push_back({cand[s].node, cand[s].begin, cand[s].end});
      else {
        split.push_back(cand[s]);
        split_src.push_back(s);
      }
    }
    if (split.empty()) break;
    const int nsp = static_cast<int>(split.size());
    std::vector<int> sp_dim(nsp), sp_begin(nsp), sp_end(nsp);
    std::vector<float> sp_cut(nsp);
    for (int s = 0; s < nsp; ++s) {
      sp_dim[s] = h_dim[split_src[s]];
      sp_cut[s] = h_cut[split_src[s]];
      sp_begin[s] = split[s].begin;
      sp_end[s] = split[s].end;
    }
    seg_dim.upload(sp_dim);
    seg_cut.upload(sp_cut);
    seg_begin.upload(sp_begin);
    seg_end.upload(sp_end);
    makeTiles(split);
    flags.setZero();
    flagKernel<<<static_cast<int>(tiles.size()), kThreads>>>(points, tree.perm.ptr(), d,
                                                             d_tiles.ptr(), seg_dim.ptr(),
                                                             seg_cut.ptr(), flags.ptr());
    cudaCheckLaunch();
    cudaSafeCall(cub::DeviceScan::ExclusiveSum(scan_tmp.rawPtr(), scan_tmp_bytes, flags.ptr(),
                                               scan.ptr(), n + 1));
    seg_left.create(nsp);
    gatherKernel<<<blocksFor(nsp, 128), 128>>>(scan.ptr(), seg_begin.ptr(), seg_end.ptr(), nsp,
                                               seg_left.ptr());
    cudaCheckLaunch();
    std::vector<int> h_left;
    seg_left.download(h_left);
    std::vector<int> fallback(nsp, 0);
    for (int s = 0; s < nsp; ++s) {
      const int count = sp_end[s] - sp_begin[s];
      if (h_left[s] == 0 || h_left[s] == count) {
        fallback[s] = 1;
        h_left[s] = count / 2;
      }
    }
    seg_fallback.upload(fallback);
    cudaSafeCall(cudaMemcpy(perm2.ptr(), tree.perm.ptr(), sizeof(int) * n,
                            cudaMemcpyDeviceToDevice));
    scatterKernel<<<static_cast<int>(tiles.size()), kThreads>>>(
        tree.perm.ptr(), flags.ptr(), scan.ptr(), d_tiles.ptr(), seg_begin.ptr(),
        seg_left.ptr(), seg_fallback.ptr(), perm2.ptr());
    cudaCheckLaunch();
    std::swap(tree.perm, perm2);

    std::vector<Seg> next;
    for (int s = 0; s < nsp; ++s) {
      const Seg& p = split[s];
      const int mid = p.begin + h_left[s];
      const int l = static_cast<int>(tree.host_nodes.size());
      tree.host_nodes.push_back(GpuNode{-1, 0.0f, -1, -1, -1});
      tree.host_nodes.push_back(GpuNode{-1, 0.0f, -1, -1, -1});
      GpuNode& nd = tree.host_nodes[p.node];
      nd.dim = sp_dim[s];
      nd.cut = sp_cut[s];
      nd.left = l;
      nd.right = l + 1;
      next.push_back({l, p.begin, mid, p.depth + 1});
      next.push_back({l + 1, mid, p.end, p.depth + 1});
      tree.depth = std::max(tree.depth, p.depth + 1);
    }
    active.swap(next);
  }
  perm2.release();
  flags.release();
  scan.release();

  // Leaves numbered in depth-first order, left first: the CPU tree's sample order.
  std::vector<int> leaf_seg_of_node(tree.host_nodes.size(), -1);
  for (int i = 0; i < static_cast<int>(leaves.size()); ++i) leaf_seg_of_node[leaves[i].node] = i;
  std::vector<int> order;
  std::vector<int> stack{0};
  while (!stack.empty()) {
    const int node = stack.back();
    stack.pop_back();
    GpuNode& nd = tree.host_nodes[node];
    if (nd.dim < 0) {
      nd.leaf = static_cast<int>(order.size());
      order.push_back(leaf_seg_of_node[node]);
    } else {
      stack.push_back(nd.right);
      stack.push_back(nd.left);
    }
  }
  const int m = static_cast<int>(order.size());
  tree.m = m;
  tree.root = 0;
  // Regroup perm so that leaves follow their numbering (so leaf_begin is a prefix sum).
  std::vector<int> h_perm;
  tree.perm.download(h_perm);
  std::vector<int> new_perm(n), begin(m + 1, 0);
  for (int l = 0, pos = 0; l < m; ++l) {
    const LeafSeg& ls = leaves[order[l]];
    begin[l] = pos;
    std::copy(h_perm.begin() + ls.begin, h_perm.begin() + ls.end, new_perm.begin() + pos);
    pos += ls.end - ls.begin;
    begin[l + 1] = pos;
  }
  tree.perm.upload(new_perm);
  tree.leaf_begin.upload(begin);
  tree.nodes.upload(tree.host_nodes);

  // Samples: the mean of each leaf's points, in double.
  std::vector<Seg> leaf_segs(m);
  for (int l = 0; l < m; ++l) leaf_segs[l] = {l, begin[l], begin[l + 1], 0};
  makeTiles(leaf_segs);
  DeviceArray<double> sums(static_cast<std::size_t>(m) * d);
  sums.setZero();
  {
    // Each tile's segment index is the leaf index here (segments listed in leaf order).
    segmentSumKernel<<<static_cast<int>(tiles.size()), kThreads>>>(
        points, nullptr, tree.perm.ptr(), d, d, d_tiles.ptr(), sums.ptr());
    cudaCheckLaunch();
  }
  tree.samples.create(static_cast<std::size_t>(m) * d);
  meanKernel<<<blocksFor(static_cast<long long>(m) * d, kThreads), kThreads>>>(
      sums.ptr(), tree.leaf_begin.ptr(), m, d, tree.samples.ptr());
  cudaCheckLaunch();
  tree.leaf_of_point.create(n);
  leafOfPointKernel<<<m, 128>>>(tree.perm.ptr(), tree.leaf_begin.ptr(), m,
                                tree.leaf_of_point.ptr());
  cudaCheckLaunch();
  cudaSafeCall(cudaDeviceSynchronize());
}

void splatBlur(const TreeDevice& tree, const float* values, const float* homogeneous_points, int v,
               float blur_radius, DeviceArray<float>& sample_values) {
  if (v < 1 || v > kMaxValueDim)
    throw DeviceError("GPU Gaussian kd-tree: value dimension must be 1..128");
  if (v > kThreads) throw DeviceError("GPU Gaussian kd-tree: value dimension too large");
  const int m = tree.m, d = tree.d;
  std::vector<int> begin;
  tree.leaf_begin.download(begin);
  std::vector<Tile> tiles;
  for (int l = 0; l < m; ++l)
    for (int b = begin[l]; b < begin[l + 1]; b += kTile)
      tiles.push_back({l, b, std::min(begin[l + 1], b + kTile)});
  DeviceArray<Tile> d_tiles(tiles.data(), tiles.size());
  DeviceArray<double> splat(static_cast<std::size_t>(m) * v);
  splat.setZero();
  segmentSumKernel<<<static_cast<int>(tiles.size()), kThreads>>>(
      values, homogeneous_points, tree.perm.ptr(), v, d, d_tiles.ptr(), splat.ptr());
  cudaCheckLaunch();
  sample_values.create(static_cast<std::size_t>(m) * v);
  blurKernel<<<blocksFor(m, kBlurTargets), kThreads>>>(tree.samples.ptr(), splat.ptr(), m, d, v,
                                                      blur_radius * blur_radius,
                                                      sample_values.ptr());
  cudaCheckLaunch();
  cudaSafeCall(cudaDeviceSynchronize());
}

void slice(const TreeDevice& tree, const filters::GaussianKdTreeParams& params,
           const float* sample_values, int v, const float* queries, const float* metric,
           const int* rows, int nrows, bool accumulate, float* out) {
  if (params.slice_samples < 1 || params.slice_samples > kMaxSliceSamples)
    throw DeviceError("GPU Gaussian kd-tree: slice_samples must be 1..64");
  if (nrows == 0) return;
  const float inv_h_sqrt2 = 1.0f / (params.slice_sigma * std::sqrt(2.0f));
  const float inv_2h2 = 0.5f / (params.slice_sigma * params.slice_sigma);
  const int blocks = blocksFor(nrows, kWarpsPerBlock);
  const int threads = kWarpsPerBlock * 32;
#define PCL_ANIMSEG_SLICE(C)                                                                  \
  sliceKernel<C><<<blocks, threads>>>(tree.nodes.ptr(), tree.root, tree.samples.ptr(),        \
                                      sample_values, tree.d, v, params.slice_samples,         \
                                      inv_h_sqrt2, inv_2h2, queries, metric, rows, nrows,     \
                                      accumulate ? 1 : 0, out)
  if (v <= 32)
    PCL_ANIMSEG_SLICE(1);
  else if (v <= 64)
    PCL_ANIMSEG_SLICE(2);
  else if (v <= 96)
    PCL_ANIMSEG_SLICE(3);
  else
    PCL_ANIMSEG_SLICE(4);
#undef PCL_ANIMSEG_SLICE
  cudaCheckLaunch();
}

void meanShiftUpdate(float* y, const float* out, int d, const int* rows, int nrows,
                     const float* metric, const unsigned char* key, float tolerance,
                     int* next_plain, int* next_key, int* counters, int& n_plain, int& n_key) {
  cudaSafeCall(cudaMemset(counters, 0, 2 * sizeof(int)));
  if (nrows > 0) {
    updateKernel<<<blocksFor(nrows, kWarpsPerBlock), kWarpsPerBlock * 32>>>(
        y, out, d, rows, nrows, metric, key, tolerance * tolerance, next_plain, next_key,
        counters);
    cudaCheckLaunch();
  }
  int h[2] = {0, 0};
  cudaSafeCall(cudaMemcpy(h, counters, 2 * sizeof(int), cudaMemcpyDeviceToHost));
  n_plain = h[0];
  n_key = h[1];
}

void transpose(const float* src, int rows, int cols, float* dst) {
  if (rows <= 0 || cols <= 0) return;
  const dim3 grid(static_cast<unsigned>(blocksFor(cols, 32)),
                  static_cast<unsigned>(blocksFor(rows, 32)));
  transposeKernel<<<grid, dim3(32, 8)>>>(src, rows, cols, dst);
  cudaCheckLaunch();
}

void gatherRows(const float* src, int d, const int* idx, int ni, const float* metric, float* raw,
                float* scaled) {
  const long long e = static_cast<long long>(ni) * d;
  if (e == 0) return;
  gatherRowsKernel<<<blocksFor(e, 256), 256>>>(src, d, idx, ni, metric, raw, scaled);
  cudaCheckLaunch();
}

void column(const float* src, int n, int v, int c, float* dst) {
  if (n <= 0) return;
  columnKernel<<<blocksFor(n, 256), 256>>>(src, n, v, c, dst);
  cudaCheckLaunch();
}

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
