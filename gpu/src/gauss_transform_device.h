#pragma once
// Internal: the exact Gauss transform's kernels (gauss_transform_kernels.cu), launched from the
// host class (gauss_transform.cpp). No CUDA types here.

namespace pcl_animseg {
namespace gpu {
namespace detail {

constexpr int kGaussTile = 128;  // data points per tile, and queries per block

/** Partial sums of the exact Gauss transform. x: tiles * kGaussTile rows of `stride` floats (the
 * distance coordinates first, dx of them, then the carried ones, zeros after; padding rows far
 * away), in tiles with their boxes (tile_lo / tile_hi: tiles x stride, distance coordinates
 * only). q: nq rows of `stride` floats. Block (b, s) sums the tiles of split s at the queries of
 * block b into partial[(s * nq + r) * (stride + 1) + c] (c = stride: the weight), doubles.
 * visited / skipped (device counters, 2 x unsigned long long) count the (block, tile) pairs.
 * stride is 8, 16, 32 or 64. */
void gaussTransformPartial(const float* x, const float* tile_lo, const float* tile_hi, int tiles,
                           int stride, int dx, bool carried, const float* q, int nq, int splits,
                           float cutoff2, double* partial, unsigned long long* counters);

/** The sums of each query row r of the partial kernel's order, added over the splits s in order
 * (partial[(s * nq + r) * (stride + 1) + c]), as floats in the caller's order and layout:
 * out[c * nq + order[r]] for the columns c < width (the data's coordinates) and c = width (the
 * weight, the partial sums' column `stride`); column-major, as Eigen's matrices. */
void gaussTransformFinish(const double* partial, int nq, int stride, int splits, const int* order,
                          int width, float* out);

/** Shared memory a block of the partial kernel needs (bytes). */
int gaussTransformSharedBytes(int stride);

/** Device time between start() and seconds() (CUDA events on the default stream; seconds()
 * waits for the work queued before it). */
class DeviceClock {
 public:
  DeviceClock();
  ~DeviceClock();
  DeviceClock(const DeviceClock&) = delete;
  DeviceClock& operator=(const DeviceClock&) = delete;
  void start();
  double seconds();

 private:
  void* start_ = nullptr;
  void* stop_ = nullptr;
};

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
