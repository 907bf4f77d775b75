#pragma once
// Internal: the multi-scale features (scale space, signatures) of a block of frames on the device,
// and the host functions that launch their kernels. No CUDA, PCL or Eigen types here: features.cpp
// (plain C++) prepares the frames, these kernels do the per-point work.
#include <pcl_animseg/gpu/device_array.h>

#include <cstddef>
#include <cstdint>
#include <vector>

namespace pcl_animseg {
namespace gpu {
namespace detail {

/** One frame of a block, as the CPU's MLSScaleSpace and SignatureEstimation see it. */
struct FeatureFrame {
  int begin = 0;  ///< the frame's first point in the block (the next frame's begins its end)
  // The uniform grid of radiusNeighbourhoods (neighbourhood.cpp): origin, 1 / cell, the cells
  // along y and z, and the first key of this frame (frames' keys do not overlap).
  float ox = 0.0f, oy = 0.0f, oz = 0.0f, inv_cell = 0.0f;
  long long ny = 0, nz = 0, key_base = 0;
  float radius2 = 0.0f;      ///< the rows' radius, squared
  float step_radius = 0.0f;  ///< support of one MLS projection (2 h0)
  float inv_h2 = 0.0f;       ///< 1 / h0^2 of the projection weights
  float rho = 0.0f;          ///< signature disc radius 2h (float, as the CPU's countWithin)
  double rho_d = 0.0;        ///< the same in double (the disc coordinates)
};

/** Everything a block needs; arrays are host memory, 3 floats a point. */
struct FeatureBlockArgs {
  int n = 0;                       ///< points in the block
  const float* xyz = nullptr;      ///< input positions
  const float* normals = nullptr;  ///< input normals as loaded (may be missing: zero or NaN)
  const float* ref = nullptr;      ///< level-0 orientation references (scale_space.cpp)
  std::vector<FeatureFrame> frames;
  int cap = 256;                     ///< at most this many entries a row (the point included)
  std::vector<int> steps_per_level;  ///< projection counts n_i (MLSScaleSpace::projectionCounts)
  bool signatures = true;
  int max_fit_points = 96;
  int radial = 32, angular = 8, radial_freqs = 6, angular_freqs = 4;
  std::vector<float> disc_tables;  ///< DiscSignature::tables()
};

/** The device side of computeSequenceFeatures for one block. launch() queues the work and
 * returns; the fetches wait for it. Throws Error on any CUDA failure. */
class FeatureBlock {
 public:
  FeatureBlock();
  ~FeatureBlock();
  FeatureBlock(const FeatureBlock&) = delete;
  FeatureBlock& operator=(const FeatureBlock&) = delete;

  void launch(const FeatureBlockArgs& args);
  /** Level l's positions and normals, 6 floats a point (x y z nx ny nz), into `out`. */
  void fetchLevel(int level, float* out) const;
  /** Level 0's curvature (one float a point). */
  void fetchCurvature(float* out) const;
  /** n x D signatures, row-major. */
  void fetchSignatures(float* out) const;
  /** The rows (for tests): offsets (n + 1), indices and squared distances. */
  void fetchRows(std::vector<long long>& offsets, std::vector<int>& indices,
                 std::vector<float>& sqr_distances) const;

 private:
  struct Impl;
  Impl* impl_;
};

/** DoGKeypoint's Newton steps (dog_keypoint.cpp: newtonSteps) for nk keypoints on the device,
 * from KeypointRefineJobs' arrays in host memory: disc_begin (nk + 1 offsets), samples (4 floats
 * each), frames (12 floats a keypoint), scales and maximum (one a keypoint); results into y (2
 * a keypoint) and ok (1 a keypoint). Blocks until done; safe to call from several threads. */
void refineKeypoints(int nk, double h0, const std::uint32_t* disc_begin, const float* samples,
                     const float* frames, const float* scales, const char* maximum, float* y,
                     char* ok);

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
