#pragma once
// Pieces shared by the two methods of MeanShiftSegmentation (not installed).
#include <pcl_animseg/segmentation/mean_shift.h>

#include <Eigen/Core>

#include <chrono>
#include <memory>
#include <vector>

namespace pcl_animseg {
namespace segmentation {
namespace detail {

/** Stage timings of the mean-shift stage (and the refinement's, `prefix` "refine") on stderr
 * when the environment variable ANIMSEG_MS_TIMING is set (profiling aid; silent otherwise). */
class StageTimer {
 public:
  explicit StageTimer(const char* prefix = "mean shift");
  void restart();
  /** Prints the time since the last lap (or restart) under `stage`, then restarts. */
  void lap(const char* stage);
  /** Whether timings are printed (for other diagnostics of the same switch). */
  bool on() const { return on_; }

 private:
  bool on_;
  const char* prefix_;
  std::chrono::steady_clock::time_point last_;
};

/** The largest label of a labelling (per frame, per point), -1 where there is none; the frames
 * side by side (the refinement, the hierarchy and the rigid motions check their input with it:
 * a serial pass over every point of every level was a third of the hierarchy's stage at 800k). */
int largestLabel(const std::vector<std::vector<int>>& labels);

/** The joint feature space of Eq. 5-6 (see mean_shift.h). */
struct JointSpace {
  Eigen::MatrixXf z;                ///< N x D raw features (p / s, n, sigma)
  std::vector<char> keypoint;       ///< per point
  Eigen::RowVectorXf metric_plain;  ///< per-dimension factor sqrt(weight) / w, Eq. 6
  Eigen::RowVectorXf metric_key;    ///< the same with w3 on the signature, Eq. 5
  bool has_keypoints = false;
  double scale = 1.0;               ///< sequence scale s
  std::vector<std::size_t> offsets;
};

JointSpace buildJointSpace(const PointCloudSequence& seq, const std::vector<Eigen::MatrixXf>& sig,
                           const std::vector<std::vector<int>>& keypoints,
                           const MeanShiftParams& params);

/** Kernel sums sum_j K(y, z_j) values_j of Eq. 8 / 10 over all data points, with the keypoint
 * pair rule of Eq. 5 realised as a sum over two point sets. */
class JointKernelSum {
 public:
  /** exact_cache_margin > 0 (exact backend): each query row keeps its neighbour list within
   * 3 + margin bandwidths and reuses it while it moves less than the margin (same sums, fewer
   * tree searches: for the refinement's many small steps); long lists, and all the sums on data
   * too dense for lists, are summed by chunks of the data on all cores (the same sums for any
   * number of threads). plain_stride > 1: the sums over
   * the non-keypoint points use every plain_stride-th of them, weighted by how many each stands
   * for (densities for reporting only, see finishResult). */
  JointKernelSum(const JointSpace& space, const Eigen::MatrixXf& values,
                 const MeanShiftParams& params, float exact_cache_margin = 0.0f,
                 Eigen::Index plain_stride = 1);
  ~JointKernelSum();
  /** out.row(r) = sums at raw position y.row(r) for r in rows (others untouched); query_key[r]
   * says whether the query started from a keypoint (empty: none did). */
  void evaluate(const Eigen::MatrixXf& y, const std::vector<int>& rows,
                const std::vector<char>& query_key, Eigen::MatrixXf& out) const;
  int valueCount() const { return value_count_; }
  /** Releases the exact backend's neighbour lists of these rows (see the constructor). */
  void forget(const std::vector<int>& rows) const;
  /** Tree searches made so far by the exact backend (diagnostics). */
  long searches() const;
  /** The Gaussian kd-tree over all points in the plain metric, in input order, when the sums
   * use one (Gaussian kd-tree backend, no keypoint pair rule); nullptr otherwise. */
  const filters::GaussianKdTree* cellTree() const;
  /** Points per cell (N/M) of the Gaussian kd-tree over the non-keypoint points (the keypoints'
   * own small trees of the pair rule left out); 0 for the exact backend or without such points. */
  double samplingFactor() const;

  struct Backend;

 private:
  struct Group;
  std::vector<std::unique_ptr<Group>> groups_;
  const JointSpace& space_;
  int value_count_ = 0;
};

/** Within-frame k-NN graph: neighbours of flattened point i are graph[i*k .. i*k+k) (global
 * indices, -1 padding). */
std::vector<int> knnGraph(const PointCloudSequence& seq, int k);

/** Fills modes (when `modes_known` is false: the densest point of each cluster), mode densities
 * and saddles from the point labels (flattened, 0..C-1); densities on `device` when given. */
void finishResult(const JointSpace& space, const std::vector<int>& flat_labels, int num_clusters,
                  const std::vector<int>& graph, int k, const MeanShiftParams& params,
                  bool modes_known, SegmentationResult& result,
                  MeanShiftDeviceBackend* device = nullptr);
/** The same, reusing the kernel sums of the iteration (their last value column is the density,
 * the homogeneous coordinate of Eq. 10) and the density already known at every point. */
void finishResult(const JointSpace& space, const std::vector<int>& flat_labels, int num_clusters,
                  const std::vector<int>& graph, int k, const JointKernelSum& sums,
                  const Eigen::VectorXf& point_density, SegmentationResult& result);
/** The same with the exact backend's sums on a device (their columns: z, then the density). */
void finishResult(const JointSpace& space, const std::vector<int>& flat_labels, int num_clusters,
                  const std::vector<int>& graph, int k, DeviceExactSums& sums,
                  const Eigen::VectorXf& point_density, SegmentationResult& result);

/** The motion method; fills the flat labels, num_clusters, merges and the parts' motions from
 * frame 0 (segmentByTracking). `tracking` (nullptr: the CPU) fits the tracked samples' poses;
 * `beside` runs beside its chains (MotionTrackingParams::beside_chains). */
void runMotion(const PointCloudSequence& seq, const MeanShiftParams& params, MotionDevice* tracking,
               std::vector<int>& flat_labels, int& num_clusters, std::vector<ClusterMerge>& merges,
               std::vector<std::vector<Eigen::Isometry3d>>& motions, Progress* progress,
               const std::function<void()>& beside = {});

}  // namespace detail
}  // namespace segmentation
}  // namespace pcl_animseg
