#pragma once
// Internal: the Gaussian kd-tree as it lives on the device, and the host functions that launch its
// kernels. No CUDA types here, so the Eigen-facing .cpp files stay plain C++.
#include <pcl_animseg/filters/gaussian_kdtree.h>
#include <pcl_animseg/gpu/device_array.h>

#include <cstddef>
#include <vector>

namespace pcl_animseg {
namespace gpu {
namespace detail {

// Same fields as the CPU tree's nodes: dim < 0 marks a leaf.
struct GpuNode {
  int dim;
  float cut;
  int left;
  int right;
  int leaf;
};

struct TreeDevice {
  int n = 0, d = 0, m = 0, root = -1, depth = 0;
  std::vector<GpuNode> host_nodes;
  DeviceArray<GpuNode> nodes;
  DeviceArray<float> samples;      // m x d, row-major
  DeviceArray<int> perm;           // n: point indices grouped by leaf
  DeviceArray<int> leaf_begin;     // m + 1: leaf l holds perm[leaf_begin[l] .. leaf_begin[l+1])
  DeviceArray<int> leaf_of_point;  // n
};

/** Device-to-device copy of raw bytes (throws Error on failure). */
void copyDeviceBytes(void* dst, const void* src, std::size_t bytes);

constexpr int kMaxDim = 64;
constexpr int kMaxValueDim = 128;
constexpr int kMaxSliceSamples = 64;
constexpr int kMaxDepth = 60;  // as the CPU tree

/** Builds the tree over n x d row-major device points (the CPU tree's rules, level by level). */
void buildTree(const float* points, int n, int d, const filters::GaussianKdTreeParams& params,
               TreeDevice& tree);

/** Splat (exact, per leaf, in double) and blur (all sample pairs within blur_radius). `values`
 * is n x v row-major on the device; when `homogeneous_points` is given instead (n x d), the values
 * are [p, 1] (v = d + 1) made on the fly. Result: m x v row-major floats. */
void splatBlur(const TreeDevice& tree, const float* values, const float* homogeneous_points, int v,
               float blur_radius, DeviceArray<float>& sample_values);

/** Slice rows (all when rows == nullptr) of queries (Q x d, row-major; each scaled by `metric`
 * when given) into out (Q x v, row-major; added to it when `accumulate`; rows not listed are
 * untouched). */
void slice(const TreeDevice& tree, const filters::GaussianKdTreeParams& params,
           const float* sample_values, int v, const float* queries, const float* metric,
           const int* rows, int nrows, bool accumulate, float* out);

/** Mean-shift update (Eq. 9) of the listed rows of y (n x d) from out (n x (d + 1)): the CPU's
 * runPaper rule. Rows still moving are written to next_plain / next_key (by key[row], when key is
 * given), their counts returned. `counters` is 2 ints of device scratch. */
void meanShiftUpdate(float* y, const float* out, int d, const int* rows, int nrows,
                     const float* metric, const unsigned char* key, float tolerance,
                     int* next_plain, int* next_key, int* counters, int& n_plain, int& n_key);

/** rows x cols row-major `src` -> cols x rows row-major `dst` (so a column-major Eigen matrix
 * n x d, which is d x n row-major, becomes n x d row-major with rows = d, cols = n). */
void transpose(const float* src, int rows, int cols, float* dst);

/** Rows idx[0 .. ni) of src (row-major, d columns) into raw (when given) and, multiplied by
 * metric[k] (one rounded float multiply, as Eigen's cwiseProduct on the CPU), into scaled (when
 * given); both ni x d row-major. */
void gatherRows(const float* src, int d, const int* idx, int ni, const float* metric, float* raw,
                float* scaled);

/** dst[i] = src[i * v + c] for i < n. */
void column(const float* src, int n, int v, int c, float* dst);

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
