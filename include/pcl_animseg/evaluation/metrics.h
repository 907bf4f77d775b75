#pragma once
/** \file metrics.h Scores of a decomposition: ARI, temporal consistency, rigidity (free fns). */
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace evaluation {

/** \brief Adjusted Rand index (Hubert & Arabie) between two labelings of the same points.
 * Points where either label is negative are ignored. 1 for identical partitions (up to renaming);
 * returns 1 when both have a single cluster, and 0 for fewer than two points. */
double adjustedRandIndex(const std::vector<int>& a, const std::vector<int>& b);

/** \brief Best rigid transform (Kabsch, no scaling) with dst ≈ R * src + t; `rms` is the
 * root-mean-square residual. Columns are points. R is always a proper rotation (det +1, the
 * reflection case is fixed). With fewer than 3 (or collinear) points the fit is still optimal but
 * not unique; with none it is the identity. Throws Error when src and dst differ in size. */
struct RigidFit {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  double rms = 0.0;
};
RigidFit kabsch(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst);

/** \brief Number of distinct non-negative labels. */
int countParts(const std::vector<int>& labels);

/** \brief Rigidity error of a labelling when all frames share one vertex order: for each predicted
 * part, the Kabsch fit from frame 0 to every frame; RMS residual over all points and frames divided
 * by frame 0's bounding-box diagonal. positions[t] is 3 x N (same N for every frame); labels is one
 * labelling of the N vertices (e.g. frame 0's) — points with label < 0 are ignored. */
double rigidityError(const std::vector<Eigen::Matrix3Xd>& positions,
                     const std::vector<int>& labels);

/** \brief How one true part is covered by the predicted parts, over all points of all frames:
 * the predicted part that holds most of its points (ties to the lower label) and how well the
 * two agree. Two true parts with the same `predicted` were merged; a low recall means the true
 * part was split or spread over its neighbours. Points where either label is negative are not
 * counted. */
struct PartMatch {
  int truth = -1;
  std::size_t points = 0;  ///< the true part's counted points
  int predicted = -1;      ///< -1 only for a true part without counted points
  double recall = 0.0;     ///< share of the true part's points in `predicted`
  double precision = 0.0;  ///< share of `predicted`'s points that belong to the true part
  double iou = 0.0;        ///< shared points / points in either part
};

/** \brief PartMatch of every true part, by true label ascending (pred[t] and truth[t] of the
 * same length, else Error). */
std::vector<PartMatch> matchParts(const std::vector<std::vector<int>>& pred,
                                  const std::vector<std::vector<int>>& truth);

/** \brief Everything animseg_eval reports. */
struct Report {
  double pooled_ari = 0.0;        ///< ARI over all points of all frames (rewards coherence)
  double mean_frame_ari = 0.0;    ///< mean over frames of the per-frame ARI
  std::vector<double> frame_ari;  ///< per frame
  int predicted_parts = 0;        ///< distinct labels over the whole sequence
  int true_parts = 0;
  double rigidity_error = -1.0;  ///< -1 when vertex order is not shared
  /** Fraction of vertices whose predicted label is the same in every frame; -1 when the frames
   * do not share a vertex order (then "the same vertex" has no meaning). */
  double label_consistency = -1.0;
  std::size_t points = 0;  ///< points scored (both labels >= 0)
  std::vector<PartMatch> parts;  ///< matchParts(pred, truth)
  /** \brief The report as a JSON object (keys as the fields above; `parts` an array of objects
   * with the keys of PartMatch). */
  std::string toJson() const;
};

/** \brief Scores predicted against true labels, frame by frame (pred[t], truth[t] same length);
 * `positions` (optional, 3 x N per frame, all with the same N as every pred[t]) enables the
 * rigidity error (of frame 0's predicted labelling) and the label consistency. Throws Error on a
 * length mismatch. */
Report evaluate(const std::vector<std::vector<int>>& pred,
                const std::vector<std::vector<int>>& truth,
                const std::vector<Eigen::Matrix3Xd>& positions = {});

}  // namespace evaluation
}  // namespace pcl_animseg
