// The exact Gauss transform's kernels (gauss_transform.h): a query per thread, the data a tile at
// a time through shared memory, tiles beyond the cutoff from the block's queries skipped by their
// boxes. Written by hand: no kept library offers a d-dimensional exact Gauss transform in CUDA.
#include <cfloat>

#include "cuda_check.h"
#include "gauss_transform_device.h"

namespace pcl_animseg {
namespace gpu {
namespace detail {

namespace {

constexpr int kThreads = kGaussTile;

template <int S>
constexpr int sharedBytes() {
  // the tile, the queries' box, then a double accumulator row per thread
  return kGaussTile * S * 4 + 2 * S * 4 + kThreads * (S + 1) * 8;
}

template <int S, bool CARRY>
__global__ void __launch_bounds__(kThreads)
    partialKernel(const float* __restrict__ x, const float* __restrict__ tile_lo,
                  const float* __restrict__ tile_hi, int tiles, int dx, const float* __restrict__ q,
                  int nq, int tiles_per_split, float cutoff2, double* __restrict__ partial,
                  unsigned long long* counters) {
  extern __shared__ __align__(16) unsigned char smem[];
  float* s_x = reinterpret_cast<float*>(smem);
  float* s_qlo = s_x + kGaussTile * S;
  float* s_qhi = s_qlo + S;
  double* s_acc = reinterpret_cast<double*>(s_qhi + S);
  const int tid = threadIdx.x;
  const int first = blockIdx.x * kThreads;
  const int r = first + tid;
  const bool live = r < nq;
  float qv[S];
#pragma unroll
  for (int k = 0; k < S; ++k) qv[k] = live ? q[static_cast<long long>(r) * S + k] : 0.0f;
  // The box of the block's queries (distance coordinates).
  const int count = min(kThreads, nq - first);
  for (int k = tid; k < S; k += kThreads) {
    float lo = FLT_MAX, hi = -FLT_MAX;
    if (k < dx)
      for (int m = 0; m < count; ++m) {
        const float v = q[static_cast<long long>(first + m) * S + k];
        lo = fminf(lo, v);
        hi = fmaxf(hi, v);
      }
    s_qlo[k] = lo;
    s_qhi[k] = hi;
  }
  double* acc = s_acc + tid * (S + 1);
  for (int c = 0; c <= S; ++c) acc[c] = 0.0;
  __syncthreads();
  const int t0 = blockIdx.y * tiles_per_split;
  const int t1 = min(tiles, t0 + tiles_per_split);
  unsigned long long visited = 0, skipped = 0;
  for (int t = t0; t < t1; ++t) {
    // Every thread finds the same gap, so the block takes or skips the tile as one.
    float gap2 = 0.0f;
    for (int k = 0; k < dx; ++k) {
      const float g = fmaxf(0.0f, fmaxf(tile_lo[static_cast<long long>(t) * S + k] - s_qhi[k],
                                        s_qlo[k] - tile_hi[static_cast<long long>(t) * S + k]));
      gap2 = fmaf(g, g, gap2);
    }
    if (gap2 >= cutoff2) {
      ++skipped;
      continue;
    }
    ++visited;
    __syncthreads();  // the previous tile is no longer read
    const float4* src =
        reinterpret_cast<const float4*>(x + static_cast<long long>(t) * kGaussTile * S);
    float4* dst = reinterpret_cast<float4*>(s_x);
    for (int i = tid; i < kGaussTile * S / 4; i += kThreads) dst[i] = src[i];
    __syncthreads();
    float facc[S + 1];
#pragma unroll
    for (int c = 0; c <= S; ++c) facc[c] = 0.0f;
    for (int j = 0; j < kGaussTile; ++j) {
      const float4* row = reinterpret_cast<const float4*>(s_x + j * S);
      float d2 = 0.0f;
#pragma unroll
      for (int k4 = 0; k4 < S / 4; ++k4) {
        const float4 v = row[k4];
        const float e[4] = {v.x, v.y, v.z, v.w};
#pragma unroll
        for (int c = 0; c < 4; ++c) {
          const int k = 4 * k4 + c;
          if (!CARRY || k < dx) {
            const float diff = qv[k] - e[c];
            d2 = fmaf(diff, diff, d2);
          }
        }
      }
      const float w = d2 < cutoff2 ? expf(-0.5f * d2) : 0.0f;
      if (__any_sync(0xffffffffu, w > 0.0f)) {
#pragma unroll
        for (int k4 = 0; k4 < S / 4; ++k4) {
          const float4 v = row[k4];
          facc[4 * k4] = fmaf(w, v.x, facc[4 * k4]);
          facc[4 * k4 + 1] = fmaf(w, v.y, facc[4 * k4 + 1]);
          facc[4 * k4 + 2] = fmaf(w, v.z, facc[4 * k4 + 2]);
          facc[4 * k4 + 3] = fmaf(w, v.w, facc[4 * k4 + 3]);
        }
        facc[S] += w;
      }
    }
#pragma unroll
    for (int c = 0; c <= S; ++c) acc[c] += static_cast<double>(facc[c]);
  }
  if (live) {
    double* out = partial + (static_cast<long long>(blockIdx.y) * nq + r) * (S + 1);
    for (int c = 0; c <= S; ++c) out[c] = acc[c];
  }
  if (tid == 0) {
    atomicAdd(counters, visited);
    atomicAdd(counters + 1, skipped);
  }
}

__global__ void finishKernel(const double* __restrict__ partial, int nq, int stride, int splits,
                             const int* __restrict__ order, int width, float* __restrict__ out) {
  const long long e = blockIdx.x * static_cast<long long>(blockDim.x) + threadIdx.x;
  if (e >= static_cast<long long>(nq) * (width + 1)) return;
  const int r = static_cast<int>(e / (width + 1)), c = static_cast<int>(e % (width + 1));
  const long long entries = static_cast<long long>(nq) * (stride + 1);
  const long long at = static_cast<long long>(r) * (stride + 1) + (c < width ? c : stride);
  double sum = 0.0;
  for (int s = 0; s < splits; ++s) sum += partial[s * entries + at];
  out[static_cast<long long>(c) * nq + order[r]] = static_cast<float>(sum);
}

template <int S, bool CARRY>
void launch(const float* x, const float* tile_lo, const float* tile_hi, int tiles, int dx,
            const float* q, int nq, int splits, float cutoff2, double* partial,
            unsigned long long* counters) {
  constexpr int bytes = sharedBytes<S>();
  cudaSafeCall(cudaFuncSetAttribute(partialKernel<S, CARRY>,
                                    cudaFuncAttributeMaxDynamicSharedMemorySize, bytes));
  const int per_split = (tiles + splits - 1) / splits;
  const dim3 grid((nq + kThreads - 1) / kThreads, splits);
  partialKernel<S, CARRY><<<grid, kThreads, bytes>>>(x, tile_lo, tile_hi, tiles, dx, q, nq,
                                                     per_split, cutoff2, partial, counters);
  cudaCheckLaunch();
}

}  // namespace

int gaussTransformSharedBytes(int stride) {
  switch (stride) {
    case 8:
      return sharedBytes<8>();
    case 16:
      return sharedBytes<16>();
    case 32:
      return sharedBytes<32>();
    default:
      return sharedBytes<64>();
  }
}

void gaussTransformPartial(const float* x, const float* tile_lo, const float* tile_hi, int tiles,
                           int stride, int dx, bool carried, const float* q, int nq, int splits,
                           float cutoff2, double* partial, unsigned long long* counters) {
  if (nq <= 0 || tiles <= 0) return;
#define ANIMSEG_GT_CASE(S)                                                                         \
  case S:                                                                                          \
    if (carried)                                                                                   \
      launch<S, true>(x, tile_lo, tile_hi, tiles, dx, q, nq, splits, cutoff2, partial, counters);  \
    else                                                                                           \
      launch<S, false>(x, tile_lo, tile_hi, tiles, dx, q, nq, splits, cutoff2, partial, counters); \
    break;
  switch (stride) {
    ANIMSEG_GT_CASE(8)
    ANIMSEG_GT_CASE(16)
    ANIMSEG_GT_CASE(32)
    ANIMSEG_GT_CASE(64)
    default:
      throw DeviceError("GPU Gauss transform: internal error, row stride " +
                        std::to_string(stride));
  }
#undef ANIMSEG_GT_CASE
}

DeviceClock::DeviceClock() {
  cudaEvent_t a = nullptr, b = nullptr;
  cudaSafeCall(cudaEventCreate(&a));
  if (cudaEventCreate(&b) != cudaSuccess) {
    cudaEventDestroy(a);
    cudaGetLastError();
    throw DeviceError("GPU: cudaEventCreate failed");
  }
  start_ = a;
  stop_ = b;
}

DeviceClock::~DeviceClock() {
  cudaEventDestroy(static_cast<cudaEvent_t>(start_));
  cudaEventDestroy(static_cast<cudaEvent_t>(stop_));
}

void DeviceClock::start() { cudaSafeCall(cudaEventRecord(static_cast<cudaEvent_t>(start_))); }

double DeviceClock::seconds() {
  cudaSafeCall(cudaEventRecord(static_cast<cudaEvent_t>(stop_)));
  cudaSafeCall(cudaEventSynchronize(static_cast<cudaEvent_t>(stop_)));
  float ms = 0.0f;
  cudaSafeCall(
      cudaEventElapsedTime(&ms, static_cast<cudaEvent_t>(start_), static_cast<cudaEvent_t>(stop_)));
  return 1e-3 * ms;
}

void gaussTransformFinish(const double* partial, int nq, int stride, int splits, const int* order,
                          int width, float* out) {
  const long long entries = static_cast<long long>(nq) * (width + 1);
  if (entries == 0) return;
  constexpr int threads = 256;
  finishKernel<<<static_cast<unsigned>((entries + threads - 1) / threads), threads>>>(
      partial, nq, stride, splits, order, width, out);
  cudaCheckLaunch();
}

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
