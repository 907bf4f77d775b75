#pragma once
/** \file segmentation_result.h What the mean shift stage hands to refinement and hierarchy. */
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief A saddle between two adjacent clusters a and b (Sect. 5): the highest density found on
 * their common border. */
struct Saddle {
  int a = -1;
  int b = -1;
  double density = 0.0;
};

/** \brief One step of a merge hierarchy: the group holding label a and the group holding label b
 * become one (a and b are the smallest label of each group), at the given cost. */
struct ClusterMerge {
  int a = -1;
  int b = -1;
  double cost = 0.0;
};

/** \brief The same merge at exactly the same cost. */
inline bool operator==(const ClusterMerge& x, const ClusterMerge& y) {
  return x.a == y.a && x.b == y.b && x.cost == y.cost;
}
inline bool operator!=(const ClusterMerge& x, const ClusterMerge& y) { return !(x == y); }

/** \brief Result of clustering a whole sequence jointly.
 *
 * Labels are 0..num_clusters-1 and mean the same part in every frame. `labels[t][j]` is the
 * cluster of point j of frame t (kept-point order, as in PointCloudSequence), -1 if unassigned.
 */
struct SegmentationResult {
  std::vector<std::vector<int>> labels;
  int num_clusters = 0;
  /** Mode of each cluster in the joint feature space (rows = clusters). */
  Eigen::MatrixXf modes;
  /** Density f(y) at each cluster's mode (Eq. 4). */
  std::vector<double> mode_density;
  /** Saddle densities between adjacent clusters (each unordered pair once). */
  std::vector<Saddle> saddles;
  /** Coarser levels found by the motion method: the merges it would make after its stopping
   * point, cheapest first, down to one group per connected piece (empty for the paper's
   * method). Cost: rigid-motion residual of the union (mean over frames), in point spacings. */
  std::vector<ClusterMerge> merges;
  /** Paper method, Gaussian kd-tree backend: the filter's sampling factor N/M, points per cell
   * of its tree over the non-keypoint points (Sect. 3.3; the paper used 1024-8192; the pair
   * rule's small keypoint trees are left out). 0 when no filter ran. */
  double sampling_factor = 0.0;
  /** Motion method: each cluster's rigid motion from frame 0 to every frame, motions[c][t]
   * (x_t ~ motions[c][t] * x_0), the articulated part motions its labels were made with; empty
   * for the paper's method. The refinement can use them (RefinementParams::input_motions). */
  std::vector<std::vector<Eigen::Isometry3d>> motions;
};

}  // namespace segmentation
}  // namespace pcl_animseg
