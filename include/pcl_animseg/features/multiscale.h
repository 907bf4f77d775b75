#pragma once
/** \file multiscale.h Section 3.1 in one call: scale space, keypoints and signatures of every
 * frame of a sequence (what the mean shift consumes). */
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/features/signature.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <vector>

namespace pcl_animseg {
class Progress;
class KeypointRefineDevice;

/** \brief Knobs of the multi-scale features. Lengths are in units of the sequence's reference
 * spacing (sequenceSpacing): a multiple of it is the same world length in every frame, scales
 * with the object and does not depend on how densely a frame is sampled. */
struct MultiscaleParams {
  /** Smallest scale h of L(x, h) (Eq. 1), spacings. */
  double h = 2.0;
  /** Factor k between adjacent scales (Eq. 1). */
  double k = 1.41421356;
  /** Number of levels L(x, h) .. L(x, k^(levels-1) h); keypoints need >= 4. */
  int levels = 5;
  /** Minimum contrast |D - median D| of a keypoint (dimensionless, see DoGKeypoint). */
  double min_response = 0.04;
  /** SIFT edge ratio r. */
  double edge_ratio = 10.0;
  /** Keypoints are detected only when true (levels >= 4). */
  bool detect_keypoints = true;
  /** Scale h of the signature, spacings (the disc of Eq. 2 has radius 2h). */
  double signature_h = 3.0;
  /** Signature layout R, S, R', S' (defaults 32, 8, 6, 4: 24-D). */
  SignatureLayout layout;
  /** Keep level 0 of each frame in SequenceFeatures::smoothed. */
  bool keep_smoothed = false;
  /** Frames are processed in consecutive blocks of at most this many points (at least one
   * frame each): a frame's scale space (~500 bytes a point) exists only while its block runs,
   * so the features' working memory is bounded by the block, not the sequence. The result does
   * not depend on it. */
  std::size_t block_points = 1000000;
};

/** \brief The length unit of the features of a sequence: the mean spacing (featureSpacing) the
 * frames would have with the median point count, median over frames of s_t sqrt(N_t / N_med).
 * A frame's own mean spacing would shrink the scales of a densely sampled frame and make its
 * signatures incomparable with those of a sparse frame of the same object (the frames of a
 * point-cloud sequence have different point counts); s sqrt(N) ~ sqrt(surface area) does not
 * depend on the density, and is unchanged by near-rigid motion. Throws Error for frames whose
 * points all coincide. */
double sequenceSpacing(const PointCloudSequence& seq);

/** \brief Sets up `mls` for frame `cloud` as computeSequenceFeatures does: p's h, k and levels,
 * neighbourhoods wide enough for the signature disc, lengths in the sequence's `unit`. */
void configureScaleSpace(MLSScaleSpace& mls, const PointCloudSequence::Cloud::ConstPtr& cloud,
                         const MultiscaleParams& p, double unit);

/** \brief The cloud the signature is computed on: the frame's own points and normals (the most
 * accurate normals there are: the level-0 MLS normals are noisier on sparse random samples), with
 * level 0's normals where the frame has none (missing-normal fall-back). */
PointCloudSequence::Cloud::Ptr signatureInput(const PointCloudSequence::Cloud& frame,
                                              const PointCloudSequence::Cloud& level0);

/** \brief Per-frame outputs of computeSequenceFeatures. */
struct SequenceFeatures {
  std::vector<Eigen::MatrixXf> signatures;  ///< per frame, N_t x D (D = R' * S')
  std::vector<std::vector<int>> keypoints;  ///< per frame, indices of keypoints
  std::vector<std::vector<float>> keypoint_scale, keypoint_response;
  std::vector<PointCloudSequence::Cloud::Ptr> smoothed;  ///< level 0 per frame (may be empty)
};

/** \brief Somewhere else to compute the scale spaces and signatures of a block of frames: the
 * CUDA module's (gpu/features.h). The keypoints stay on the CPU, on the levels it returns.
 * Implementations follow MLSScaleSpace and SignatureEstimation point by point. */
class FeatureDevice {
 public:
  virtual ~FeatureDevice() = default;
  /** \brief The scale spaces of frames [first, last) of `seq` (`plans[t - first]` from their
   * MLSScaleSpace, already checked), into spaces[t]: levels, scales, spacing and input, and the
   * neighbourhoods when `rows` is set. It also computes the frames' signatures (`p`'s layout and
   * signature_h), which signature() then hands out. Throws Error on a device failure. */
  virtual void scaleSpaces(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                           const std::vector<ScaleSpacePlan>& plans, const MultiscaleParams& p,
                           bool rows, std::vector<ScaleSpace>& spaces) = 0;
  /** \brief Frame t's signatures (N_t x D), of the last scaleSpaces() call. Safe to call from
   * several threads. */
  virtual void signature(std::size_t t, Eigen::MatrixXf& out) const = 0;
  /** \brief Where DoGKeypoint runs its refinement's Newton steps (dog_keypoint.h); nullptr (the
   * default): on the cores. */
  virtual const KeypointRefineDevice* keypointRefiner() const { return nullptr; }
};

/** \brief Runs MLSScaleSpace, DoGKeypoint and SignatureEstimation on every frame (frames one
 * after the other, OpenMP over points inside). Progress stages: "scale_space", "keypoints",
 * "signature" (their times are summed over frames). Throws Error naming the frame on bad input.
 * A keypoint index appears once per frame even when detected at several levels (the strongest
 * |response| is kept). With a `device`, the scale spaces and signatures are computed there (the
 * "scale_space" stage then includes the signatures' time), and the keypoints' refinement where
 * it offers one (FeatureDevice::keypointRefiner). */
SequenceFeatures computeSequenceFeatures(const PointCloudSequence& seq, const MultiscaleParams& p,
                                         Progress* progress = nullptr,
                                         FeatureDevice* device = nullptr);

}  // namespace pcl_animseg
