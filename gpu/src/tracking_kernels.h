#pragma once
// Internal: the motion method's sample tracking on the GPU (sample_tracking.cpp packs a
// segmentation::SampleTrackingProblem into these plain arrays; tracking_kernels.cu fits them).
// No Eigen or PCL here: this header is read by nvcc.
#include <vector>

namespace pcl_animseg {
namespace gpu {
namespace detail {

/** A kd-tree node of FlatKdTree3 with its indices made global: an inner node's children index
 * TrackingArrays::nodes, a leaf's [a, b) index TrackingArrays::points. */
struct TrackNode {
  float split;
  int dim;  // -1: leaf
  int a;
  int b;
};

/** A pose as 12 doubles: the rotation row by row, then the translation. */
constexpr int kPoseDoubles = 12;

struct TrackingArrays {
  int frames = 0;
  int samples = 0;
  int iterations = 8;
  double normal_cos = 0.3;
  double clip = 4.0;
  std::vector<TrackNode> nodes;
  std::vector<int> root;                        // per frame: root node, -1 when empty
  std::vector<float> points;                    // 4 per point (x, y, z, 0), leaf order
  std::vector<float> normals;                   // 4 per point
  std::vector<double> spacing;                  // per frame
  std::vector<int> unoriented;                  // per frame
  std::vector<double> source, probe;            // 6 per point: position, normal
  std::vector<int> source_begin, probe_begin;   // per sample, plus the end
  std::vector<int> adjacency, adjacency_begin;  // sample graph, CSR
  std::vector<int> level;                       // frames x samples
  std::vector<int> before, two_before;          // per frame
  std::vector<double> global;                   // frames x 12
  std::vector<int> tasks, wave_begin;           // tasks t * samples + s by wave, CSR
};

/** Fits every task; poses (frames x samples x 12, the reference frame's entries the identity
 * on entry) and residual (frames x samples) are filled. Returns the seconds spent on the device
 * (uploads, kernels, downloads). Throws Error on a CUDA failure. */
double runTracking(const TrackingArrays& in, std::vector<double>& poses,
                   std::vector<double>& residual);

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
