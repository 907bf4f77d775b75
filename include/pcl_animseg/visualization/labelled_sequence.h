#pragma once
/** \file labelled_sequence.h A decomposition read back from disk (the OUT directory of `animseg`),
 * in the form the viewer and the contact sheet draw. */
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>

#include <string>
#include <vector>

namespace pcl_animseg {
namespace visualization {

/** \brief A keypoint to overlay: position and scale h (world units). */
struct OverlayKeypoint {
  Eigen::Vector3f position;
  float scale = 0.f;
};

/** \brief One frame: its points (with normals) and, per hierarchy level, a part label per point
 * (levels[l][j], aligned with cloud point j; -1 = unlabelled). */
struct LabelledFrame {
  std::string name;
  PointCloudSequence::Cloud::Ptr cloud;
  std::vector<std::vector<int>> levels;
  std::vector<OverlayKeypoint> keypoints;  ///< empty when no keypoints file was found
};

/** \brief A labelled sequence: frames in order, every frame with the same number of levels. */
struct LabelledSequence {
  std::vector<LabelledFrame> frames;

  std::size_t size() const { return frames.size(); }
  /** \brief Number of hierarchy levels (0 when empty). */
  int levels() const { return frames.empty() ? 0 : static_cast<int>(frames[0].levels.size()); }
  /** \brief Distinct labels >= 0 at `level` over all frames, with their point counts (sorted by
   * label). */
  std::vector<std::pair<int, std::size_t>> partCounts(int level) const;
};

/** \brief Reads the OUT directory of `animseg`: for every `NAME.labels` (natural order), the
 * label columns and the geometry.
 *
 * The geometry comes from `frames` when given — either the input sequence the decomposition was
 * computed from (a directory or list file, read with io::loadSequence, whose input index maps the
 * kept points onto the label rows exactly) or another OUT directory — and else from `OUT/NAME.pcd`.
 * A `.pcd` of OUT holds only the kept points while `.labels` has a row per input point, so its
 * points are matched to the rows in order, skipping rows whose level-0 label differs (dropped
 * points carry -1 on every level). Keypoints are taken from `OUT/NAME.keypoints.pcd` or
 * `OUT/keypoints/NAME.pcd` when present (fields x y z and, if present, scale). Throws Error with
 * the offending path when a file is missing or inconsistent. */
LabelledSequence loadLabelledSequence(const std::string& out_dir, const std::string& frames = "");

/** \brief Builds a LabelledSequence from a loaded sequence and its labels
 * (labels[level][frame][point], kept-point order as in PipelineResult::levels). */
LabelledSequence makeLabelledSequence(const PointCloudSequence& sequence,
                                      const std::vector<std::vector<std::vector<int>>>& labels);

}  // namespace visualization
}  // namespace pcl_animseg
