#pragma once
/** \file mean_shift.h Joint clustering of all frames of a sequence (paper Sect. 3.2-3.3), and the
 * motion-coherent decomposition that is the default.
 *
 * Joint feature space (Eq. 5-6). Each point of each frame is z = (p / s, n, sigma): position
 * divided by the sequence scale s (mean bounding-box diagonal over frames, so that one bandwidth
 * serves every input), unit normal, and the signature when one is given. The squared distance is
 *     w2 |dp|^2 + w1 |dn|^2 + w4 |dsigma|^2      (Eq. 6)
 * and w3 instead of w4 when both points are keypoints (Eq. 5). The kernel is the Gaussian
 * exp(-dist^2 / (2 w^2)) with bandwidth w (Eq. 4). Because the weight of the signature term
 * depends on the PAIR, no single embedding reproduces Eq. 5-6 exactly; we realise it exactly as a
 * sum of two Gauss transforms: the data are split into non-keypoints and keypoints, and a query
 * started from a keypoint sums the non-keypoints under the w4 metric plus the keypoints under the
 * w3 metric, while any other query sums both sets under the w4 metric. Each set has its own
 * filter (kd-tree or Gaussian kd-tree) over its points scaled by sqrt(weights) / w. (Adding extra
 * dimensions sqrt(w3 - w4) * sigma for keypoints only would also give w3 between keypoints but
 * would push every keypoint away from the non-keypoints around it, which Eq. 6 does not.)
 *
 * Methods.
 *  - Paper: the mean shift of Eq. 8-10 over all points of all frames at once; modes closer than
 *    the merge radius are merged, clusters smaller than the minimum size are absorbed by the
 *    neighbouring cluster they share most k-NN edges with. It relies on a part staying close to
 *    itself in (p, n) from frame to frame, so parts that move a lot are split across frames.
 *  - Motion (default, beyond the paper): over-segment a reference frame into small patches
 *    (k-means in position + normal, seeded by farthest-point sampling), track every patch through
 *    the sequence with point-to-plane ICP from frame to frame (initialised by the previous
 *    motion and by a constant-velocity prediction, the better fit kept), merge spatially adjacent
 *    patches agglomeratively while one rigid motion explains both in every frame (cost: the
 *    mean over frames of the RMS distance from the moved union to the frame's surface, in units
 *    of the point spacing), re-track the merged parts, move every reference point to the part
 *    whose motion fits it best, and transfer labels to every frame along the part motions
 *    (nearest moved reference point with a compatible normal). The merges beyond the stopping
 *    threshold are recorded as a hierarchy (SegmentationResult::merges), and the parts' motions
 *    from frame 0 are kept (SegmentationResult::motions).
 * Both fill every other field of SegmentationResult; densities and saddles are the joint-space
 * density (Eq. 4) at the points, computed with the selected backend.
 */
#include <pcl/PointIndices.h>
#include <pcl_animseg/filters/gaussian_kdtree.h>
#include <pcl_animseg/segmentation/motion_device.h>
#include <pcl_animseg/segmentation/segmentation_result.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

namespace pcl_animseg {
class Progress;
namespace segmentation {

/** \brief How the kernel sums of Eq. 8 / Eq. 10 are evaluated. */
enum class MeanShiftBackend {
  Exact,          ///< FLANN kd-tree radius search (3 bandwidths) + exact Gaussian: the reference
  GaussianKdTree  ///< filters::GaussianKdTree (Adams et al. 2009); the paper method iterates
                  ///< the tree's cells (leaf means) and gives every point its cell's mode
};
/** \brief Which decomposition. */
enum class MeanShiftMethod {
  Paper,  ///< joint mean shift over all frames (Sect. 3.2)
  Motion  ///< patches + rigid tracking + merging by motion (default; see the file comment)
};

MeanShiftBackend meanShiftBackendFromString(const std::string& name);  ///< "exact" | "gkdtree"
MeanShiftMethod meanShiftMethodFromString(const std::string& name);    ///< "paper" | "motion"
std::string toString(MeanShiftBackend backend);
std::string toString(MeanShiftMethod method);

/** \brief All knobs of the stage (nanoflann style: one struct, defaults that work). */
struct MeanShiftParams {
  /** Bandwidth w (Eq. 4), in joint-space units (positions divided by the sequence scale). */
  double bandwidth = 0.1;
  double w1 = 0.5;  ///< normal weight (Eq. 5-6)
  double w2 = 0.5;  ///< position weight
  double w3 = 2.0;  ///< signature weight between two keypoints (Eq. 5)
  double w4 = 1.0;  ///< signature weight otherwise (Eq. 6)
  MeanShiftMethod method = MeanShiftMethod::Motion;
  MeanShiftBackend backend = MeanShiftBackend::GaussianKdTree;
  unsigned seed = 1;
  int max_iterations = 60;
  /** A trajectory stops when it moves less than this many bandwidths in one step. */
  double convergence = 1e-3;
  /** Gaussian kd-tree backend, paper method: after the approximate iteration, up to this many
   * exact mean-shift steps from each group of coinciding end points, trajectories that meet
   * going on as one (a hybrid: the filter does the long walk, exact sums over the data the last
   * steps, to convergence; see refineEndPoints in the source). 0: pure filter. */
  int refine_iterations = 150;
  /** Gaussian kd-tree backend, paper method: iterate the M cells of the filter's tree (each from
   * the mean of its points; every point takes its cell's end point) instead of the N points.
   * false: every point is iterated, as the GPU path does (the reference its tests compare with). */
  bool iterate_cells = true;
  /** Gaussian kd-tree backend, paper method: after the labels, every point on a border between
   * two clusters (a k-NN edge of its frame, either way, to another cluster) follows its own
   * exact trajectory from its own position (up to max(refine_iterations, max_iterations) exact
   * steps), and the end points are grouped and absorbed again; rounds follow the moved borders
   * until every border point has run (each point at most once). The labels then agree with the
   * exact backend's at its borders too (ARI 0.99 on the agreement test against 0.83-0.87
   * without), at the exact method's cost for the border points: on the paper method's clusters,
   * which interleave at the scale of a point's neighbours, that is most points (200k points at
   * w = 0.3: 165 s instead of 1.7 s on 2 cores; 800k on a device with exactSums: 6.2 s, ARI 0.97
   * to the exact backend on all points; docs/mean_shift_experiments.md). false: the filter's
   * borders. */
  bool exact_borders = false;
  /** Modes closer than this many bandwidths are one mode. */
  double merge_radius = 0.5;
  /** Clusters with fewer points (whole sequence) are absorbed by a neighbour; 0: 0.2% of the
   * points. */
  int min_cluster_size = 0;
  /** k of the within-frame k-NN graph (adjacency for absorption, saddles, patches). */
  int neighbours = 10;
  filters::GaussianKdTreeParams gkdtree;

  // Motion method.
  /** Tracked samples of the reference frame (MotionTrackingParams::samples); 0: one per 8
   * reference points, in [16, kMaxTrackedSamples] (motion_tracking.h). */
  int patches = 0;
  /** Merging stops when the cheapest merge's motion residual exceeds this (point spacings). */
  double motion_threshold = 1.25;
  /** Two parts that meet only across a sharp crease and move differently cost at least this
   * much to merge (point spacings of the tracking cost, MotionTrackingParams::crease_cost);
   * 0: no crease rule (motion alone). */
  double crease_cost = 3.25;
  /** Final borders between parts (MotionTrackingParams::border_smoothness): the cost of cutting
   * one surface-graph edge across a flat or convex surface, against the per-point motion fit;
   * folds that turn inwards are almost free to cut. 0: per-point reassignment, no border term. */
  double border_smoothness = 8.0;
  /** A part may dissolve into the parts it touches (each point to the one whose motion fits it)
   * when their motions explain it within this factor of its own motion's residual
   * (MotionTrackingParams::dissolve_ratio); 0: parts only merge pairwise. */
  double dissolve_ratio = 1.5;
  /** Part motions as an articulated body (MotionTrackingParams::joint_weight): the cost, per
   * point spacing, of a joint that a part's motion opens from its solved neighbour's beyond 4
   * spacings; 0: each part's motion by its own fit alone. */
  double joint_weight = 0.1;
  /** A part smaller than this fraction of the mean part size is a sliver, not a part
   * (MotionTrackingParams::sliver_fraction); 0: off. */
  double sliver_fraction = 0.1;
  /** When > 0, merge until exactly this many parts instead (threshold ignored). */
  int target_clusters = 0;
  /** Motion method: also record each cluster's densest point in the joint space, its density
   * and the saddle densities between adjacent clusters (Eq. 4), what the paper's
   * region-persistence hierarchy and `segmentation.txt` hold. The labels and the motion
   * method's own hierarchy (its recorded merges) do not use them: false skips them (modes
   * empty, densities 0, no saddles), unless no merges were recorded and there is more than one
   * cluster, where the hierarchy falls back on the saddles. animseg skips them: 2.5 s of a
   * 15.7 s run on a 200k-point humanoid (2 cores). */
  bool record_densities = true;
  int icp_iterations = 25;
  /** Reference frame of the motion method (-1: the first). */
  int reference_frame = -1;
};

/** \brief Exact kernel sums over a joint space on a device (MeanShiftDeviceBackend::exactSums):
 * what the CPU's exact backend sums, the data's Gaussians cut off at 3 bandwidths, with the
 * keypoint pair rule of Eq. 5. */
class DeviceExactSums {
 public:
  virtual ~DeviceExactSums() = default;
  /** \brief For r in rows: out.row(r) = sum_j exp(-d(q_r, z_j)^2 / 2) [z_j, 1] (Eq. 10's
   * homogeneous sums: out has D + 1 columns), d the metric of Eq. 6, or of Eq. 5 between two
   * keypoints (query_key[r]: query r is a keypoint; empty: none is). Other rows are untouched.
   * Throws Error on a device failure. */
  virtual void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                        const std::vector<char>& query_key, Eigen::MatrixXf& out) = 0;
};

/** \brief Splits the points 0 .. n-1 by their keypoint flag (`keypoint` empty: no point is a
 * keypoint): the others into `plain`, the keypoints into `key`, each in index order. Every
 * backend's groups (Eqs. 4-6: non-keypoints for every query, keypoints under the plain and the
 * pair metric) start from this split. */
template <class Index>
void splitByKeypoint(const std::vector<char>& keypoint, Index n, std::vector<Index>& plain,
                     std::vector<Index>& key) {
  plain.clear();
  key.clear();
  for (Index i = 0; i < n; ++i)
    (!keypoint.empty() && keypoint[static_cast<std::size_t>(i)] ? key : plain).push_back(i);
}

/** \brief Where the kernel sums of the stage run when not on the CPU: an engine object that a
 * device library implements (the CUDA module: gpu::makeMeanShiftBackend() in
 * <pcl_animseg/gpu/mean_shift_backend.h>) and the caller hands to
 * MeanShiftSegmentation::setDeviceBackend. The segmentation module itself never links a device
 * library. A device backend's filter is the Gaussian kd-tree (MeanShiftParams::gkdtree); where it
 * offers exact sums (exactSums), the exact backend (MeanShiftParams::backend) and the exact steps
 * of the Gaussian kd-tree backend (the refinement, MeanShiftParams::exact_borders) run on the
 * device too, and otherwise on the CPU. Every method throws Error on a device failure (no
 * device, out of memory, kernel fault): never a silent wrong result.
 *
 * The data are the joint space of Eq. 5-6: z (N x D raw features), the per-dimension metrics
 * sqrt(weight) / w of Eq. 6 (plain) and Eq. 5 (keypoint pairs), and the keypoint flags (empty:
 * no pair rule). */
class MeanShiftDeviceBackend {
 public:
  virtual ~MeanShiftDeviceBackend() = default;
  /** \brief For logs, e.g. "gpu (NVIDIA H100 80GB HBM3)". */
  virtual std::string name() const = 0;
  /** \brief The paper method's iteration: Eq. 9 from every row of z until the step is below
   * params.convergence or params.max_iterations; y (N x D) the end points, density (N) the
   * kernel sum at each end point (a keypoint's with the pair rule). The Gaussian kd-tree
   * backend's iteration (the stage runs the exact backend's through exactSums). */
  virtual void seekModes(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                         const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
                         const MeanShiftParams& params, Eigen::MatrixXf& y,
                         Eigen::VectorXf& density) = 0;
  /** \brief The density of Eq. 4 (kernel sum over all rows of z) at the rows of `queries`
   * (raw coordinates); query_key[r] says whether query r is a keypoint (empty: none is). With
   * the Gaussian kd-tree (params.backend), or exact sums for the exact backend. */
  virtual void density(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                       const Eigen::RowVectorXf& metric_key, const std::vector<char>& keypoint,
                       const MeanShiftParams& params, const Eigen::MatrixXf& queries,
                       const std::vector<char>& query_key, Eigen::VectorXf& out) = 0;
  /** \brief The motion method's fits, residuals and point costs on the same device
   * (motion_device.h), owned by this backend; nullptr (the default): the motion method runs on
   * the CPU. */
  virtual MotionDevice* motionDevice() { return nullptr; }
  /** \brief Exact kernel sums over the joint space (z, metrics, keypoint flags as above) on the
   * device, for the exact backend's iteration and the exact steps of the Gaussian kd-tree
   * backend; nullptr (the default): they run on the CPU. */
  virtual std::unique_ptr<DeviceExactSums> exactSums(const Eigen::MatrixXf& /*z*/,
                                                     const Eigen::RowVectorXf& /*metric_plain*/,
                                                     const Eigen::RowVectorXf& /*metric_key*/,
                                                     const std::vector<char>& /*keypoint*/) {
    return nullptr;
  }
  /** \brief The sampling factor N/M of the last seekModes' filter tree over the non-keypoint
   * points (SegmentationResult::sampling_factor); 0 when unknown. */
  virtual double samplingFactor() const { return 0.0; }
};

/** \brief Segments a whole sequence so that a label means the same part in every frame.
 *
 * \code
 * pcl_animseg::segmentation::MeanShiftSegmentation ms;
 * ms.setInputSequence(seq);
 * ms.setSignatures(features.signatures);   // optional
 * ms.setKeypoints(features.keypoints);     // optional
 * pcl_animseg::segmentation::SegmentationResult result;
 * ms.segment(result);
 * \endcode
 */
class MeanShiftSegmentation {
 public:
  using Ptr = std::shared_ptr<MeanShiftSegmentation>;
  using ConstPtr = std::shared_ptr<const MeanShiftSegmentation>;

  void setInputSequence(const PointCloudSequence::ConstPtr& sequence) { sequence_ = sequence; }
  PointCloudSequence::ConstPtr getInputSequence() const { return sequence_; }
  /** \brief Per-frame signatures sigma (N_t x D), optional. */
  void setSignatures(const std::vector<Eigen::MatrixXf>& signatures) { signatures_ = signatures; }
  /** \brief As above, taking the matrices over (no copy of N x D floats). */
  void setSignatures(std::vector<Eigen::MatrixXf>&& signatures) {
    signatures_ = std::move(signatures);
  }
  /** \brief Per-frame keypoint indices (into the frame's points), optional (Eq. 5 vs 6). */
  void setKeypoints(const std::vector<std::vector<int>>& keypoints) { keypoints_ = keypoints; }

  void setParams(const MeanShiftParams& params) { params_ = params; }
  const MeanShiftParams& getParams() const { return params_; }
  /** \brief Bandwidth w (Eq. 4). */
  void setBandwidth(double w) { params_.bandwidth = w; }
  double getBandwidth() const { return params_.bandwidth; }
  /** \brief Weights w1 (normal), w2 (position), w3 (signature, keypoint pairs), w4 (signature)
   * of Eq. 5-6. */
  void setWeights(double w1, double w2, double w3, double w4);
  void setBackend(MeanShiftBackend backend) { params_.backend = backend; }
  MeanShiftBackend getBackend() const { return params_.backend; }
  void setMethod(MeanShiftMethod method) { params_.method = method; }
  MeanShiftMethod getMethod() const { return params_.method; }
  void setSeed(unsigned seed) { params_.seed = seed; }
  void setMaxIterations(int n) { params_.max_iterations = n; }
  void setMergeRadius(double r) { params_.merge_radius = r; }
  void setMinClusterSize(int n) { params_.min_cluster_size = n; }
  void setProgress(Progress* progress) { progress_ = progress; }
  /** \brief Runs the kernel sums on a device (see MeanShiftDeviceBackend): the paper method
   * entirely (iteration and densities), the motion method its tracking, residuals and point
   * costs (when the backend offers it: motionDevice(); the CPU's results bit for bit) and
   * densities. nullptr: the CPU.
   * With `cpu_fallback`, a device failure (Error from the backend) is not fatal: the stage
   * reruns that part on the CPU and fallbackReason() says why; otherwise the Error propagates. */
  void setDeviceBackend(std::shared_ptr<MeanShiftDeviceBackend> backend,
                        bool cpu_fallback = false) {
    device_ = std::move(backend);
    cpu_fallback_ = cpu_fallback;
  }
  std::shared_ptr<MeanShiftDeviceBackend> getDeviceBackend() const { return device_; }
  /** \brief Work of the caller's that the motion method runs on a thread of its own beside its
   * chains of device calls, from the samples' poses on (MotionTrackingParams::beside_chains;
   * the pipeline: what the refinement needs of the frames). It must not throw; it may run more than
   * once (a device failure reruns the method on the CPU) or not at all (the paper method). */
  void setBesideChains(std::function<void()> work) { beside_chains_ = std::move(work); }
  /** \brief After segment(): "cpu", or the device backend's name when it did the work. */
  const std::string& deviceUsed() const { return device_used_; }
  /** \brief After segment(): why the device was left for the CPU (empty: it was not). */
  const std::string& fallbackReason() const { return fallback_reason_; }

  /** \brief Runs the selected method. Throws Error on bad parameters or input. */
  void segment(SegmentationResult& result);

  /** \brief PCL view: one PointIndices per cluster, indices into the flattened sequence
   * (PointCloudSequence::flatten / offsets). Runs segment() when needed. */
  void extract(std::vector<pcl::PointIndices>& clusters);

  /** \brief The result as PointIndices (see extract). */
  static void toPointIndices(const SegmentationResult& result,
                             std::vector<pcl::PointIndices>& clusters);

 private:
  void validate() const;
  PointCloudSequence::ConstPtr sequence_;
  std::vector<Eigen::MatrixXf> signatures_;
  std::vector<std::vector<int>> keypoints_;
  MeanShiftParams params_;
  Progress* progress_ = nullptr;
  std::shared_ptr<MeanShiftDeviceBackend> device_;
  bool cpu_fallback_ = false;
  std::function<void()> beside_chains_;
  std::string device_used_ = "cpu";
  std::string fallback_reason_;
};

/** \brief Mode grouping of the paper method (used by the CPU and the GPU path alike): end points
 * y (N x D, raw joint-space coordinates) falling in the same cell (a fifth of the merge radius,
 * in the plain metric) form a group represented by its densest point; groups are visited from the
 * densest and join the densest kept mode within `merge_radius` (plain metric), else become a mode.
 * labels[i] is the mode of point i (0..modes-1, modes in order of decreasing density); mode_rep[m]
 * is the point whose end point is mode m. One radius search per group in a kd-tree: about
 * O(N log N). Throws Error on mismatched sizes or a non-positive radius. */
void groupModes(const Eigen::MatrixXf& y, const Eigen::RowVectorXf& metric_plain,
                const Eigen::VectorXf& density, double merge_radius, std::vector<int>& labels,
                std::vector<int>& mode_rep);

/** \brief The sequence scale s: mean bounding-box diagonal over frames. */
double sequenceScale(const PointCloudSequence& sequence);

}  // namespace segmentation
}  // namespace pcl_animseg
