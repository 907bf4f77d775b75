#pragma once
// Internal, host only: DeviceFrames (trees with normals in leaf order) packed and uploaded for
// tracking_kernels.cu; the motion method's frames and the rigid motions' part surfaces alike.
#include <pcl_animseg/segmentation/motion_device.h>

#include <memory>
#include <string>
#include <vector>

#include "tracking_kernels.h"

namespace pcl_animseg {
namespace gpu {
namespace detail {

/** A tree's nodes, their indices made global (an inner node's children + node0, a leaf's points
 * + point0), into nodes[0 ..], and its points in leaf order as (x, y, z, 0) into points[0 ..]. */
void packTree(const FlatKdTree3& tree, int node0, int point0, TrackNode* nodes, float* points);

/** Packs `trees` side by side, the trees in parallel: each tree's nodes (packTree) into
 * `nodes`, its points into `points`, its root node (-1 when empty) into `root`. Returns each
 * tree's first point, with the total last (trees.size() + 1 entries). Every tree must be set. */
std::vector<int> packTrees(const std::vector<const FlatKdTree3*>& trees,
                           PackedVector<TrackNode>& nodes, PackedVector<float>& points,
                           std::vector<int>& root);

/** Packs `frames` for upload (host work only, no CUDA call); throws Error (naming items as
 * `what` + index) on a frame without a tree or with a normal count that does not match. */
FrameArrays packDeviceFrames(const segmentation::DeviceFrames& frames, const std::string& what);
/** The same into `out`, whose buffers are reused (resized without zeroing: a caller that packs
 * again and again keeps their pages, which the rigid motions' surfaces faulted in anew each
 * time, 30-40 MB at 800k). */
void packDeviceFrames(const segmentation::DeviceFrames& frames, const std::string& what,
                      FrameArrays& out);

/** Uploads packed frames; throws Error on a CUDA failure. The new store goes on with the call
 * statistics of `previous` (the store it replaces; null: none). */
std::unique_ptr<FrameStore> uploadPackedFrames(const FrameArrays& packed,
                                               const FrameStore* previous);

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
