#pragma once
/** \file motion_tracking.h Near-rigid parts of a sequence without correspondences, from tracked
 * surface samples (the motion method of MeanShiftSegmentation; beyond the paper).
 *
 * 1. Samples: farthest-point sampling of the reference frame (about one per 8 points), and the
 *    reference frame's surface graph (k nearest points within 3 spacings with compatible normals:
 *    unlike plain k-NN it does not bridge two limbs that nearly touch). Each sample owns its
 *    geodesic Voronoi cell; samples whose cells touch are neighbours.
 * 2. Tracking: every sample carries its geodesic neighbourhood (its k nearest reference points
 *    over the surface graph) and a pose per frame, reference -> frame t, found by point-to-plane
 *    ICP of that neighbourhood against frame t. Because the source is always the reference
 *    geometry, errors do not accumulate from frame to frame; only the initialisation is chained.
 *    Large joint motions (a galloping leg turns ~20 degrees per frame) defeat an ICP started from
 *    the previous pose, so the samples of a frame are solved in breadth-first order over the
 *    sample graph, from the sample that the whole-frame ICP explains best (the torso), and each
 *    one starts from several candidates: the poses already found for its neighbours in THIS
 *    frame, its own previous pose, a constant-velocity prediction and the whole-frame pose; the
 *    lowest-residual fit wins. The ICP is damped, so a direction the neighbourhood does not
 *    constrain (along a capsule) keeps the neighbour's motion instead of sliding. Such
 *    directions still drift a little at every step, so a side of the reference longer than 48
 *    frames is tracked through key frames (every ceil(n / 48)-th frame, at most every 4th, each
 *    from the key frame before), and the frames between each from the frame before it
 *    (chained_fit.h, chainFrames; the parts' motions of steps 3 and 4 follow the same chain).
 * 3. Clustering, in two phases. Residuals are surface errors: the distance to the nearest
 *    point's tangent plane (blind to the sampling of the two clouds and to a sample sliding along
 *    a capsule), in point spacings.
 *    a. Samples merge agglomeratively into an over-segmentation (twice the target count, or half
 *       the threshold); the cost of merging A and B is, in the worst frame, the better of A's and
 *       B's pose scored by the worse of A's and B's residuals under it.
 *    b. The groups become whole parts: points are their samples' cells, moved a few rounds to the
 *       neighbouring part whose motion explains them best over all frames (costs averaged over
 *       surface neighbourhoods), with each part's motion refit by ICP of the whole part, tracked
 *       along the sequence (a part lost in one frame is found again from its own previous and
 *       constant-velocity poses). Parts then merge while the better of A's and B's motions
 *       explains both sides (worst frame of the worse side) below the threshold, or down to the
 *       target count; the later merges form the hierarchy. Two parts that meet only across a
 *       sharp crease (no surface-graph edge joins them) and move differently cost at least
 *       `crease_cost`: parts of a body meet at creases, and a pelvis turning little under its
 *       torso must not merge before the pieces of one leg do. A piece that straddles a joint
 *       (its own motion a compromise, so costly to merge with either side) may instead dissolve
 *       into the parts it touches, each point to the part whose motion explains it
 *       (`dissolve_ratio`); dissolves and merges are taken cheapest first.
 * 4. Labels: the borders between the final parts are placed by a graph cut on the reference
 *    frame's surface graph (alpha-expansion): each point pays the mean squared surface error of
 *    its part's motion over the frames, each edge cut across a flat or convex surface pays
 *    `border_smoothness`, and an edge across a fold that turns inwards almost nothing. Where
 *    motion cannot tell two parts apart (a joint's cap, a sphere about the joint, fits both
 *    bones) the border goes to the fold where one part leaves the other (the minima rule).
 *    Every point of every frame then takes the label of the nearest reference point moved by
 *    its part's motion (with a compatible normal).
 */
#include <pcl_animseg/segmentation/segmentation_result.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <functional>
#include <utility>
#include <vector>

namespace pcl_animseg {
class Progress;
namespace segmentation {

class MotionDevice;

/** \brief The most tracked samples MotionTrackingParams::samples = 0 gives. */
constexpr int kMaxTrackedSamples = 1000;

/** \brief Knobs of the tracked-sample decomposition. */
struct MotionTrackingParams {
  /** Number of tracked samples; 0: one per 8 reference points, in [16, kMaxTrackedSamples]. */
  int samples = 0;
  /** Reference points in a sample's neighbourhood (the ICP source). */
  int neighbourhood = 60;
  int icp_iterations = 8;
  /** Merging stops when the cheapest merge costs more than this (point spacings). */
  double threshold = 2.0;
  /** Parts that meet only across a sharp crease (no edge of the surface graph between them) and
   * whose motions differ (merge cost at least 0.4 of the threshold) cost at least this much to
   * merge (point spacings; 0: no such rule). */
  double crease_cost = 3.25;
  /** Estimated normals (plain point clouds) blur creases, so no surface-graph edge is long
   * enough to cross one. For them a reference point is a crease point when its neighbourhood is
   * concave: the centroid of its 16 nearest points lies more than this far (point spacings)
   * along its normal, and a crease point has no surface-graph edge. Skipped for the frame when
   * more than a fifth of its points would be crease points (the normals' orientation is then in
   * doubt there). 0: off. Inputs with their own normals are not affected. */
  double concave_crease_depth = 0.1;
  /** Dissolving a part: a piece of the over-segmentation that straddles a joint has a
   * compromise motion of its own, so merging it with either side costs as much as merging two
   * true parts. Such a piece may instead dissolve into the parts it touches (each point to the
   * one whose motion fits it best) when the piece's worst-frame residual under those motions is
   * at most this factor of its residual under its own motion, and the dissolve competes with
   * the merges at that cost. A short true part between two joints (a neck, a pelvis) fits its
   * own motion 2.3-7.6 times better than its neighbours' on generated sequences, a straddling
   * piece 1.0-1.5 times. 0: parts only merge pairwise. */
  double dissolve_ratio = 1.5;
  /** Step 4's part motions, tracked as an articulated body: where two parts meet, the centroid of
   * the border (a joint) stays in place on a continuous surface, so both parts' motions carry it
   * to about the same point. A candidate motion that opens a joint with an already solved
   * neighbour by more than 4 spacings pays this much per further spacing on top of its residual
   * (RMS spacings). Without it a finger's motion could jump onto the thumb or a neighbouring
   * finger of the same shape in the frames where they come close (hand, seed 12: pooled ARI
   * 0.897 with 0, 0.944 with 0.1). 0: each part's own fit alone. */
  double joint_weight = 0.1;
  /** Step 3's part merges: a part of fewer reference points than this fraction of the mean part
   * size (the reference frame's points over target_clusters, or without a target over the parts
   * left when the threshold stops the merges) is a sliver that the border rounds left between
   * two parts, not a part. It merges into its cheapest neighbour whatever the cost, and with a
   * target it does not count towards it. Counted, slivers of 22, 47 and 22 of 8000 reference
   * points on a quadruped kept their place among the 12 parts asked for while true parts merged
   * (pooled ARI 0.785 with 0, 0.943 with 0.1). The smallest true part of the generated plans
   * has 0.29 of the mean. 0: off. */
  double sliver_fraction = 0.1;
  /** When > 0, merge until this many parts instead (threshold ignored). */
  int target_clusters = 0;
  /** Final borders between parts: the cost of one surface-graph edge cut across a flat or convex
   * surface, against the per-point motion fit (mean squared surface error over frames, in
   * spacings^2); cuts along concave folds are almost free. Solved by graph cuts (alpha-expansion).
   * 0: each point moves to the neighbouring part whose motion fits it best (no border term). */
  double border_smoothness = 8.0;
  /** Graph-cut borders: a point may take any part within this many surface-graph edges. */
  int border_hops = 8;
  /** Groups with fewer samples than this are merged into a neighbour whatever the cost. */
  int min_group_samples = 2;
  /** Reference frame (-1: the first). */
  int reference_frame = -1;
  /** k of the reference frame's surface graph (neighbourhoods, sample adjacency, relabelling at
   * part borders). */
  int point_neighbours = 10;
  unsigned seed = 1;
  /** Fits the tracking's poses and computes the merges' residuals and the points' costs on a
   * device (motion_device.h; not owned; trackSamples, clusterTrajectories and
   * segmentByTracking hand it the frames). nullptr: the CPU. The results are the CPU's bit for
   * bit. */
  MotionDevice* device = nullptr;
  /** With a device: each part merge's or dissolve's part fits also fit, as an optional chain of
   * the same device batches (fitChainsBatched), the union of the cheapest pair of parts the step
   * leaves as they are; when that pair merges next with the same points and starts, the merge
   * takes that fit. The same results either way (fewer device calls with it); off to compare. */
  bool speculate_merge_fits = true;
  /** With a device: each of the part fits' score batches and the fits it decides in one device
   * call (MotionDevice::scoreAndFit, fitChainsBatched's `scoreFit`) instead of two. The same
   * results either way; off to compare. */
  bool fuse_score_fits = true;
  /** The caller's own work, run on a thread of its own while the method's chains of device
   * calls and host steps leave most cores idle: segmentByTracking starts it when the samples'
   * poses are all that is left of the tracking (the clustering and the part motions follow) and
   * joins it before it returns. It must not throw. Empty (the default): none. */
  std::function<void()> beside_chains;
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
  /** Surface graph of the reference frame: k nearest points within 3 spacings with compatible
   * normals (symmetric); neighbourhoods and adjacency grow over it. */
  std::vector<std::vector<int>> surface;
  std::vector<int> owner;  ///< sample whose geodesic cell holds each reference point (-1: none)
  double spacing = 1.0;                               ///< reference-frame point spacing
};

namespace detail {
/** \brief The motion method's final borders (MotionTrackingParams::border_smoothness): up to 3
 * cycles of alpha expansions, each label in ascending order, until a cycle changes nothing.
 * Point i may take the labels `cand[i]` (ascending; fixed where it has fewer than two) at the
 * costs `unary[i]` (aligned with cand[i]); `edges[i]` holds the edges (j > i, weight) whose cut
 * costs the weight. `label` is the start and the result. With `side_by_side`, expansions that
 * neither read nor write each other's points run at once (the same labels as one after the
 * other, which is the reference without it). Returns the longest chain of expansions that wait
 * for each other in a cycle. */
int alphaExpansions(const std::vector<std::vector<int>>& cand,
                    const std::vector<std::vector<double>>& unary,
                    const std::vector<std::vector<std::pair<int, double>>>& edges,
                    std::vector<int>& label, bool side_by_side);
}  // namespace detail

/** \brief Farthest-point sampling of `count` points of a cloud, starting from a point chosen by
 * `seed`; returns indices (fewer when the cloud has fewer distinct points). Points with `skip[i]`
 * != 0 are never picked (`skip` empty or of another size: none skipped). */
std::vector<int> farthestPointSamples(const PointCloudSequence::Cloud& cloud, int count,
                                      unsigned seed, const std::vector<char>& skip = {});

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
  /** Part of every reference-frame point (-1 where the surface graph did not reach), after the
   * points were moved to the part whose motion explains them. */
  std::vector<int> point_labels;
};
TrajectoryClusters clusterTrajectories(const PointCloudSequence& seq, const SampleTracks& tracks,
                                       const MotionTrackingParams& params);

/** \brief All steps: flattened labels of every point of every frame (0..num_clusters-1), the part
 * count and the coarser merges; with `part_motions`, also each part's motion from frame 0 to
 * every frame ((*part_motions)[c][t], the articulated motions the labels were made with). */
void segmentByTracking(const PointCloudSequence& seq, const MotionTrackingParams& params,
                       std::vector<int>& flat_labels, int& num_clusters,
                       std::vector<ClusterMerge>& merges, Progress* progress = nullptr,
                       std::vector<std::vector<Eigen::Isometry3d>>* part_motions = nullptr);

}  // namespace segmentation
}  // namespace pcl_animseg
