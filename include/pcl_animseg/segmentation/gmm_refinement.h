#pragma once
/** \file gmm_refinement.h Boundary smoothing by local normal-space GMMs (Sect. 4 of the paper). */
#include <pcl_animseg/segmentation/rigid_motion.h>
#include <pcl_animseg/segmentation/segmentation_result.h>
#include <pcl_animseg/sequence.h>

#include <memory>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief Knobs of GMMBoundaryRefinement. Distances are in units of each frame's mean point
 * spacing (pcl_animseg::meanSpacing), so they do not depend on scale or sampling density. */
struct RefinementParams {
  /** L_r: points within this distance of a boundary form the narrow band W (the points that may
   * change label). Must cover the error of the initial boundary. */
  double narrow_band = 4.0;
  /** L_R (> L_r): F = (L_R − L_r) ∩ D_F and B = (L_R − L_r) ∩ D_B. The paper uses 5–8 points of
   * width for F and B. */
  double outer_band = 10.0;
  /** Only F/B points farther than this from the boundary train the GMMs ("5 points" in the
   * paper), so that the initial boundary's errors do not leak into the models. F and B start at
   * L_r anyway; 4 (all of F and B) instead of 5, with the smaller patches below, measured on
   * generated sequences after the motion method (8000 points, seeds 3-6, one pass; mean
   * boundary-error drop quadruped / humanoid / spider / hand): 12 / 16 / 5: 24.5% / 10% / 28% /
   * 12%; 8 / 10 / 4: 27% / 14% / 32.5% / 13.5%, the pooled ARI after refinement higher on 14 of
   * the 16 runs, the same on one and lower on one (spider seed 4: 0.979 -> 0.976). */
  double training_min_distance = 4.0;
  /** A point is on a boundary when one of its `boundary_k` nearest neighbours, closer than
   * `boundary_max_distance`, carries another label. */
  int boundary_k = 8;
  double boundary_max_distance = 3.0;
  /** Components per GMM (the paper: 4) and the variance floor added to their covariances (unit
   * normals; 0.01 is about 6 degrees of spread, the noise of estimated normals). */
  int components = 4;
  double gmm_regularization = 0.01;
  int gmm_max_iterations = 50;
  /** Local models: the boundary of each pair of parts is cut into patches of about this size, each
   * with its own F and B GMMs trained within `patch_radius` of the patch (the paper: "the GMM is
   * computed on the neighbouring band of point x, not the whole band"). 8 and 10 (were 12 and
   * 16): see training_min_distance. */
  double patch_size = 8.0;
  double patch_radius = 10.0;
  /** A patch model needs this many training points, otherwise the pair-wide model is used. */
  int min_training_points = 24;
  /** Training points of a model are evenly subsampled to at most this many (speed). */
  int max_training_points = 1200;
  /** Eq. 11 with hysteresis: a W point changes side only when log p_c(x|other) − log
   * p_c(x|own) exceeds this. Where the two sides' normals are alike (a smooth boundary) the
   * likelihood ratio is noise, and the initial label is the better guess. 0 = the paper's rule. */
  double min_log_ratio = 1.0;
  /** Spatial term (0 = off, the paper's pure normal-space rule): adds
   * −spatial_weight · (distance to the side's nearest training point, in spacings) to each side's
   * log-likelihood. It keeps a W point from jumping to a side whose band is far away when
   * normals cannot tell the sides apart (capsule limbs: both sides of a knee have the same
   * normals). On generated sequences after the motion method (2000 points per frame, true part
   * count) the pooled ARI after refinement was, with 0 / 0.5 / 1: quadruped 0.80 / 0.91 / -,
   * humanoid 0.72 / 0.76 / 0.76, spider 0.73 / 0.76 / 0.76, hand 0.81 / 0.82 / 0.82. */
  double spatial_weight = 0.5;
  /** Motion check (beyond the paper; false = the paper's normal-space rule): a W point may take
   * the other label only when that part's rigid motion explains the point's trajectory about as
   * well as its own part's, r_other <= (1 + motion_tolerance) · r_own. r is the mean over the
   * other frames of the point's distance, once carried there by the part's rigid motion (the
   * point-to-plane ICP of the initial labels, as for pooling), to that frame's surface, in
   * spacings, each frame capped at `motion_cap`. Where the two sides' normals are alike (capsule
   * joints: hip, shoulder, neck) the GMMs prefer the wrong side with a large likelihood ratio,
   * which no hysteresis removes; the motion still tells the sides apart. The tolerance is relative
   * because the residual's noise grows with the motion (a galloping leg fits worse than a
   * torso). Pooled ARI on generated sequences after the motion method (20 frames of 2000
   * +-20% points, large motion, true part count; seed 3 / seed 7), unrefined -> normals only ->
   * with the check (0.35): humanoid 0.82 -> 0.76 -> 0.83 / 0.56 -> 0.56 -> 0.58, quadruped
   * 0.84 -> 0.91 -> 0.89 / 0.81 -> 0.86 -> 0.86, spider 0.69 -> 0.77 -> 0.75 / 0.78 -> 0.86 ->
   * 0.86, hand 0.83 -> 0.82 -> 0.83 / 0.79 -> 0.78 -> 0.79. */
  bool motion_check = true;
  double motion_tolerance = 0.35;
  double motion_cap = 5.0;
  /** The motion check's mean runs over at most this many frames, spread evenly over the
   * sequence (0: every frame). Each point is carried to every frame it counts, so without a cap
   * the check's cost grows with the square of the frame count: at 160 frames (1.6 M points) it
   * was the refinement's largest stage. Sequences of up to this many frames are unaffected. */
  int motion_frames = 48;
  /** Fold guard (beyond the paper): a W point does not take a label whose points near it (its
   * `boundary_k` nearest within `boundary_max_distance`) all lie across an inward fold of more
   * than `fold_angle_deg` (normals converging): a border on such a fold is where parts meet (the
   * minima rule), which the segmentation put there on purpose; normals alone cannot tell the
   * two sides of a shoulder apart. 0: off. */
  double fold_angle_deg = 20.0;
  /** Iterate (bands rebuilt from the new labels) until fewer than `min_changed_fraction` of all
   * points change, or `max_iterations`. One pass by default: after the motion method, later
   * passes moved the boundaries on into the wrong side more often than back. Boundary error drop
   * (points within 3 spacings of a true boundary with a wrong label) and pooled ARI, generated
   * sequences of 20 frames, 8000 points, seeds 3-6, quadruped / humanoid / spider / hand, mean
   * over the seeds, with the patches of 12 / 16 spacings of the time: 1 pass 24.5% / 10% / 28% /
   * 12%, ARI never lower than unrefined; 4 passes 23% / 2% / 14% / 11%, the humanoid's ARI lower
   * than unrefined at seeds 4 (0.966 -> 0.957) and 6 (0.948 -> 0.942). One pass is also 1.7x
   * faster (800k-point humanoid, 2 cores: 4.9 s -> 2.7 s). */
  int max_iterations = 1;
  double min_changed_fraction = 1e-4;
  /** Fold snap (beyond the paper), after the GMM passes. Within `fold_snap_band` of a border
   * each point is reached from the parts' points beyond the band over the frame's surface graph
   * (its `boundary_k` nearest within `boundary_max_distance`); a path costs its length plus
   * `fold_snap_penalty` per degree by which the surface folds inwards along it (each edge's turn
   * beyond `fold_snap_dead_zone_deg`, the noise of estimated normals). A point whose own part
   * reaches it only across at least `fold_snap_angle_deg` more inward folding than another part
   * does takes that part: the border moves onto the fold where one part leaves another (the
   * minima rule). A part thinner than two bands starts its core halfway to its point farthest
   * from a border. Neither the normals' GMMs nor the parts' motions can place it where a part's
   * end is a sphere about its joint (a knee cap fits both bones' motions). Distances in
   * spacings; 0: off. */
  double fold_snap_band = 8.0;
  double fold_snap_penalty = 0.5;
  double fold_snap_angle_deg = 10.0;
  double fold_snap_dead_zone_deg = 4.0;
  /** Build the bands and models jointly over all frames (temporal coherence, Sect. 4): each part's
   * points of every frame are brought into frame 0 by the part's rigid motion (point-to-plane ICP,
   * see rigid_motion.h) and a pair's GMMs pool the band points of every frame. When false, each
   * frame is refined on its own. */
  bool pool_frames = true;
  /** Where the parts' motions that pool the frames and check the motions come from. false (the
   * default): the point-to-plane ICP of each part of the input labels (RigidMotionEstimation, up
   * to 500 points per part, chained along the frames). true: the input's own motions where it
   * has them (SegmentationResult::motions; the motion method's articulated part motions, which
   * its labels were made with), no fit. Measured after the motion method (20 frames, 6000
   * points, seeds 3-10, four plans): the boundary error after refinement 0.0787 with the
   * input's motions against 0.0767 fitted (pooled ARI 0.9680 / 0.9685); the 800k humanoid's
   * refinement on the GPU machine 0.31-0.36 s against 0.38-0.41 s (its fits 0.09 s). Starting
   * the fits from the input's motions (frames in parallel) gave 0.0805 on seeds 3-5 (fitted
   * 0.0786, input's 0.0808) in 0.045 s. */
  bool input_motions = false;
  unsigned seed = 0;
};

/** \brief Throws pcl_animseg::Error for inconsistent parameters (what refine() checks first;
 * a pipeline can check them before its earlier stages run). */
void validate(const RefinementParams& params);

/** \brief What happened during refine(). */
struct RefinementStats {
  int iterations = 0;
  std::vector<std::size_t> changed;  ///< points relabelled per iteration
  std::size_t band_points = 0;       ///< |W| over all frames at the first iteration
  int models = 0;                    ///< GMMs fitted at the first iteration
  std::size_t snapped = 0;           ///< points moved by the fold snap (all frames)
};

/** \brief Refines the boundaries of a joint segmentation with local GMMs in normal space.
 *
 * For each pair of parts (a, b) that touch, boundary points are those with a near neighbour of
 * the other label; W, F and B are the bands above. The F and B models of a local patch are
 * 4-component GMMs of normals; each W point takes the side with the larger p_c (Eq. 11). Several
 * parts meeting at one place are handled pair by pair: a point belongs to the band of the pair
 * whose boundary is nearest to it and can only move to the other label of that pair.
 */
class GMMBoundaryRefinement {
 public:
  using Ptr = std::shared_ptr<GMMBoundaryRefinement>;
  using ConstPtr = std::shared_ptr<const GMMBoundaryRefinement>;

  void setInputSequence(const PointCloudSequence* sequence) { sequence_ = sequence; }
  void setParams(const RefinementParams& params) { params_ = params; }
  const RefinementParams& getParams() const { return params_; }
  /** \brief Where the ICP fits of the input parts' motions run (RigidMotionEstimation::setDevice;
   * not owned): the same results; nullptr (the default) for the CPU. */
  void setRigidFitDevice(RigidFitDevice* device) { device_ = device; }
  /** \brief The frames' mean point spacings as meanSpacings() measures them, when the caller
   * has them already (the pipeline measures once for the refinement and the rigid motions): they
   * are not measured again. Empty (the default): measured from the refinement's own kd-trees.
   * refine() throws Error when their count is not the frame count. */
  void setSpacings(std::vector<double> spacings) { spacings_ = std::move(spacings); }

  /** \brief Builds now what refine() needs of the frames alone, not of the labels: each frame's
   * kd-tree and mean spacing and, with a device (setRigidFitDevice), every point's boundary_k + 1
   * nearest points in one device call. A caller can run it on a thread of its own while an
   * earlier stage leaves the cores idle (the pipeline: beside the motion method's chains of
   * device calls); the next refine() of the same sequence then starts from them, with the same
   * results, and releases them. Without it refine() builds them itself. A device failure here is
   * not thrown: refine() then searches on its own and reports it. Not thread-safe with any other
   * call on this object. */
  void prepareFrames();
  /** \brief The mean spacings prepareFrames() measured (meanSpacings' values), until refine()
   * releases them; empty without. */
  std::vector<double> preparedSpacings() const;

  /** \brief Output is the input with refined labels (num_clusters, modes, densities and saddles
   * copied unchanged). Throws pcl_animseg::Error for labels that do not match the sequence or
   * inconsistent parameters. */
  void refine(const SegmentationResult& input, SegmentationResult& output);

  const RefinementStats& getStats() const { return stats_; }

  /** \brief The rigid motion of each part of refine()'s input labels (frame 0 -> frame t), which
   * pooled the frames and checked the motions: fitted (up to 500 points per part) or the input's
   * own (RefinementParams::input_motions; their rms is 0, not measured); empty when neither
   * ran. A good start for the motions of the refined labels
   * (RigidMotionEstimation::setInitialMotions): the refinement moves only the borders. */
  const std::vector<PartMotion>& getMotions() const { return motions_; }

 private:
  const PointCloudSequence* sequence_ = nullptr;
  RefinementParams params_;
  RefinementStats stats_;
  std::vector<PartMotion> motions_;
  RigidFitDevice* device_ = nullptr;
  std::vector<double> spacings_;
  struct Prepared;  ///< what prepareFrames() built (gmm_refinement.cpp)
  std::shared_ptr<Prepared> prepared_;
};

}  // namespace segmentation
}  // namespace pcl_animseg
