#pragma once
/** \file segmentation_io.h What the stage tools hand each other besides labels: the mean shift's
 * mode densities and saddles (for animseg_hierarchy), and labels of a whole sequence.
 *
 * `segmentation.txt` (written by animseg_meanshift next to its NAME.labels, read by
 * animseg_refine / animseg_hierarchy) is line based; `#` starts a comment:
 *
 *     # pcl_animseg segmentation v1
 *     clusters K
 *     mode <id> <density> [<mode coordinate> ...]      (one line per cluster id 0..K-1)
 *     saddle <a> <b> <density>                         (one line per adjacent pair)
 */
#include <pcl_animseg/segmentation/segmentation_result.h>
#include <pcl_animseg/sequence.h>

#include <functional>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace io {

/** \brief Writes num_clusters, mode densities (and modes when present) and saddles. Atomic. */
void saveSegmentationInfo(const std::string& path, const segmentation::SegmentationResult& result);

/** \brief Reads a file written by saveSegmentationInfo into num_clusters, mode_density, modes
 * (empty when the file has no coordinates) and saddles; labels are left untouched. Throws Error
 * with the line number on a malformed file. */
void loadSegmentationInfo(const std::string& path, segmentation::SegmentationResult& result);

/** \brief Reads DIR/NAME.labels for every frame NAME of the sequence (column `column`, input
 * order) and returns them in kept-point order (labels[t][j]). Throws Error when a file is missing
 * or its length does not match the frame. */
std::vector<std::vector<int>> loadSequenceLabels(const std::string& dir,
                                                 const PointCloudSequence& sequence,
                                                 int column = 0);

/** \brief Writes DIR/NAME.labels (columns = levels[l][t] in kept-point order, expanded to input
 * order with -1 for dropped points), DIR/NAME.pcd (level 0) and, with `ply`, DIR/NAME.ply
 * (coloured by level-0 part) for every frame. The frames are written side by side, each file
 * atomically; `frames_done(n)` (optional) is called, one call at a time, after each frame with
 * the number of frames written so far. The first error is rethrown once the others have
 * finished. */
void saveSequenceLabels(const std::string& dir, const PointCloudSequence& sequence,
                        const std::vector<std::vector<std::vector<int>>>& levels,
                        bool ply = false,
                        const std::function<void(std::size_t)>& frames_done = nullptr);

}  // namespace io
}  // namespace pcl_animseg
