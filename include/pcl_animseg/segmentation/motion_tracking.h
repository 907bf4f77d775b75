#pragma once
/** \file motion_tracking.h Near-rigid parts of a sequence without correspondences, from tracked
 * surface samples (the motion method of MeanShiftSegmentation; beyond the paper).
 *
 * 1. Samples: farthest-point sampling of the reference frame (about one per 8 points).
 * 2. Tracking: every sample carries its reference-frame neighbourhood (its k nearest reference
 *    points) and a pose per frame, reference -> frame t, found by point-to-plane ICP of that
 *    neighbourhood against frame t. Because the source is always the reference geometry, errors
 *    do not accumulate from frame to frame; only the initialisation is chained. Large joint
 *    motions (a galloping leg turns ~20 degrees per frame) defeat an ICP started from the
 *    previous pose, so the samples of a frame are solved in breadth-first order over the sample
 *    k-NN graph, from the sample that the whole-frame ICP explains best (the torso), and each one
 *    starts from several candidates: the poses already found for its neighbours in THIS frame,
 *    its own previous pose, a constant-velocity prediction and the whole-frame pose; the
 *    lowest-residual fit wins. A rotation is thus discovered progressively down a limb. The ICP
 *    is damped, so a direction the neighbourhood does not constrain (along a capsule) keeps the
 *    neighbour's motion instead of sliding.
 * 3. Clustering: the samples now have a pose (and so a position) in every frame. Groups of
 *    samples are merged agglomeratively over the sample graph; the cost of merging A and B is,
 *    in the worst frame, the better of A's and B's pose scored by the worse of A's and B's
 *    surface residuals under it (point spacings). Surface residuals, unlike sample positions,
 *    do not see a sample slide along a capsule (which its neighbourhood cannot fix); each side
 *    scored on its own keeps a small limb from hiding in a large torso's average; the better of
 *    two poses forgives a sample lost in one frame. Merging stops at a threshold or at a target
 *    count; later merges form the hierarchy.
 * 4. Labels: each reference point takes the label of its nearest sample, then moves to the part
 *    (among those of its neighbours) whose rigid motion keeps it on the surface best over all
 *    frames; every point of every frame takes the label of the nearest reference point moved by
 *    its part's motion (with a compatible normal).
 */
#include <pcl_animseg/segmentation/segmentation_result.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <vector>

namespace pcl_animseg {
class Progress;
namespace segmentation {

/** \brief Knobs of the tracked-sample decomposition. */
struct MotionTrackingParams {
  /** Number of tracked samples; 0: one per 8 reference points, in [16, 1000]. */
  int samples = 0;
  /** Reference points in a sample's neighbourhood (the ICP source). */
  int neighbourhood = 60;
  /** Neighbours of a sample in the sample graph (BFS order, candidate poses, merge adjacency). */
  int sample_neighbours = 8;
  int icp_iterations = 8;
  /** Merging stops when the cheapest merge costs more than this (point spacings). */
  double threshold = 2.0;
  /** When > 0, merge until this many parts instead (threshold ignored). */
  int target_clusters = 0;
  /** Groups with fewer samples than this are merged into a neighbour whatever the cost. */
  int min_group_samples = 2;
  /** Reference frame (-1: the first). */
  int reference_frame = -1;
  /** k of the reference-frame k-NN graph used when relabelling points at part borders. */
  int point_neighbours = 10;
  unsigned seed = 1;
};

/** \brief Trajectories of the tracked samples. */
struct SampleTracks {
  int reference_frame = 0;
  std::vector<int> sample_points;                     ///< reference-frame index per sample
  std::vector<std::vector<Eigen::Isometry3d>> poses;  ///< poses[t][s]: reference -> frame t
  std::vector<Eigen::Matrix3Xd> positions;            ///< positions[t].col(s)
  std::vector<double> residual;                       ///< mean ICP residual per frame (spacings)
  std::vector<std::vector<int>> graph;                ///< sample k-NN graph (symmetric)
  std::vector<std::vector<int>> neighbourhoods;       ///< ICP source of each sample (sorted)
  double spacing = 1.0;                               ///< reference-frame point spacing
};

/** \brief Farthest-point sampling of `count` points of a cloud, starting from a point chosen by
 * `seed`; returns indices (fewer when the cloud has fewer distinct points). */
std::vector<int> farthestPointSamples(const PointCloudSequence::Cloud& cloud, int count,
                                      unsigned seed);

/** \brief Steps 1-2: samples and their poses in every frame. Throws Error on bad parameters. */
SampleTracks trackSamples(const PointCloudSequence& seq, const MotionTrackingParams& params,
                          Progress* progress = nullptr);

/** \brief Step 3: sample groups (group[s] in 0..groups-1, ordered by first sample) and the merges
 * after the stopping point (in group ids, cheapest first). */
struct TrajectoryClusters {
  std::vector<int> group;
  int groups = 0;
  std::vector<ClusterMerge> merges;
  std::vector<std::vector<Eigen::Isometry3d>> poses;  ///< poses[g][t]: the group's motion
};
TrajectoryClusters clusterTrajectories(const PointCloudSequence& seq, const SampleTracks& tracks,
                                       const MotionTrackingParams& params);

/** \brief All steps: flattened labels of every point of every frame (0..num_clusters-1), the part
 * count and the coarser merges. */
void segmentByTracking(const PointCloudSequence& seq, const MotionTrackingParams& params,
                       std::vector<int>& flat_labels, int& num_clusters,
                       std::vector<ClusterMerge>& merges, Progress* progress = nullptr);

}  // namespace segmentation
}  // namespace pcl_animseg
