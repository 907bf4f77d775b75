// The motion method of MeanShiftSegmentation (see mean_shift.h): tracked samples + trajectory
// clustering (motion_tracking.h). This file maps the stage's parameters onto that module.
#include <pcl_animseg/segmentation/motion_tracking.h>

#include "mean_shift_internal.h"

namespace pcl_animseg {
namespace segmentation {
namespace detail {

namespace {

MotionTrackingParams motionTrackingParams(const MeanShiftParams& params) {
  MotionTrackingParams mp;
  // `patches` predates the tracked samples; a positive value now sets their number.
  mp.samples = params.patches;
  // The tracking cost is a worst frame, the old patch cost a mean over frames: about twice as
  // large for the same fit (quadruped: merges inside a part cost < 1.5, across a joint > 2.5), so
  // the old default of 1.5 maps onto 3.
  mp.threshold = 2.0 * params.motion_threshold;
  mp.crease_cost = params.crease_cost;
  mp.border_smoothness = params.border_smoothness;
  mp.dissolve_ratio = params.dissolve_ratio;
  mp.joint_weight = params.joint_weight;
  mp.sliver_fraction = params.sliver_fraction;
  mp.target_clusters = params.target_clusters;
  mp.reference_frame = params.reference_frame;
  mp.point_neighbours = params.neighbours;
  mp.seed = params.seed;
  return mp;
}

}  // namespace

void runMotion(const PointCloudSequence& seq, const MeanShiftParams& params, MotionDevice* tracking,
               std::vector<int>& flat, int& num_clusters, std::vector<ClusterMerge>& merges,
               std::vector<std::vector<Eigen::Isometry3d>>& motions, Progress* progress,
               const std::function<void()>& beside) {
  if (!(sequenceScale(seq) > 0.0)) {
    // Every point of every frame coincides: one part, nothing to track (and no point spacing).
    flat.assign(seq.totalPoints(), 0);
    num_clusters = 1;
    merges.clear();
    motions.assign(1, std::vector<Eigen::Isometry3d>(seq.size(), Eigen::Isometry3d::Identity()));
    return;
  }
  MotionTrackingParams mp = motionTrackingParams(params);
  mp.device = tracking;
  mp.beside_chains = beside;
  segmentByTracking(seq, mp, flat, num_clusters, merges, progress, &motions);
}

}  // namespace detail
}  // namespace segmentation
}  // namespace pcl_animseg
