#pragma once
/** \file sequence.h An animated object: T frames of oriented points, no correspondence. */
#include <pcl/Vertices.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include <cstddef>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace pcl_animseg {

/** \brief A sequence of T frames (Eq. 1's P = (P^1 .. P^T)), each a cloud of points with normals.
 *
 * Frames may have different point counts and no point-to-point correspondence. Each frame keeps
 * the map from its points back to the lines of its input file, because points with NaN/Inf
 * coordinates are dropped on load while outputs must stay aligned with the input (-1 for them).
 */
class PointCloudSequence {
 public:
  using Cloud = pcl::PointCloud<pcl::PointNormal>;
  using Ptr = std::shared_ptr<PointCloudSequence>;
  using ConstPtr = std::shared_ptr<const PointCloudSequence>;

  /** \brief Append a frame. `input_index[j]` is the input point of cloud point j (identity when
   * empty); `input_size` the number of points in the input (cloud size when 0). `faces` are the
   * mesh faces (indices into the cloud) for mesh frames, empty for point frames. */
  void addFrame(Cloud::Ptr cloud, const std::string& name, const std::string& source = "",
                std::vector<int> input_index = {}, std::size_t input_size = 0,
                std::vector<pcl::Vertices> faces = {});

  std::size_t size() const { return frames_.size(); }
  bool empty() const { return frames_.empty(); }

  const Cloud::Ptr& frame(std::size_t t) const { return frames_.at(t).cloud; }
  const std::string& name(std::size_t t) const { return frames_.at(t).name; }
  const std::string& source(std::size_t t) const { return frames_.at(t).source; }
  const std::vector<int>& inputIndex(std::size_t t) const { return frames_.at(t).input_index; }
  std::size_t inputSize(std::size_t t) const { return frames_.at(t).input_size; }
  const std::vector<pcl::Vertices>& faces(std::size_t t) const { return frames_.at(t).faces; }

  /** \brief How many of frame t's normals were estimated from the points (not read from the
   * file or a mesh); their orientation is only a guess (io::orientNormals). */
  std::size_t estimatedNormals(std::size_t t) const { return frames_.at(t).estimated_normals; }
  void setEstimatedNormals(std::size_t t, std::size_t count) {
    frames_.at(t).estimated_normals = count;
  }
  /** \brief False when some frame's normals were all estimated: their signs are a guess. A frame
   * with some normals from the input (a mesh with a few vertices in no face) is oriented from
   * those (io::estimateNormals seeds the orientation with them), so it counts as oriented. */
  bool normalsOriented() const;

  /** \brief Total number of (kept) points over all frames. */
  std::size_t totalPoints() const;
  /** \brief offsets()[t] is the index of frame t's first point when all frames are flattened;
   * offsets()[T] == totalPoints(). */
  std::vector<std::size_t> offsets() const;
  /** \brief The frame id of every point when flattened. */
  std::vector<int> frameIds() const;
  /** \brief All frames concatenated into one cloud (frame order). */
  Cloud::Ptr flatten() const;
  /** \brief Labels of frame t's kept points, expanded to input order with -1 for dropped points. */
  std::vector<int> toInputOrder(std::size_t t, const std::vector<int>& labels) const;

 private:
  struct FrameData {
    Cloud::Ptr cloud;
    std::string name;
    std::string source;
    std::vector<int> input_index;
    std::size_t input_size = 0;
    std::vector<pcl::Vertices> faces;
    std::size_t estimated_normals = 0;
  };
  std::vector<FrameData> frames_;
};

/** \brief Mean distance from each point to its nearest neighbour (the frame's "spacing"), from a
 * kd-tree over at most `max_samples` evenly chosen points; scales in the library are given in
 * units of it so that results do not change when a frame is scaled or resampled. */
double meanSpacing(const PointCloudSequence::Cloud& cloud, std::size_t max_samples = 2000);

template <typename PointT>
class KdTree;
/** \brief meanSpacing with a kd-tree over `cloud` that the caller has built anyway (the same
 * value, without building another). */
double meanSpacing(const PointCloudSequence::Cloud& cloud, const KdTree<pcl::PointNormal>& tree,
                   std::size_t max_samples = 2000);

/** \brief meanSpacing of every frame of a sequence, the frames in parallel. A frame that has no
 * spacing (fewer than 2 points, all points coinciding) throws pcl_animseg::Error naming the
 * frame. */
std::vector<double> meanSpacings(const PointCloudSequence& seq, std::size_t max_samples = 2000);

/** \brief meanSpacings with each frame's kd-tree given by the caller (`tree_of(t)`: over frame
 * t), which it has built anyway: the same values and errors, without building others. */
std::vector<double> meanSpacings(
    const PointCloudSequence& seq,
    const std::function<const KdTree<pcl::PointNormal>&(std::size_t)>& tree_of,
    std::size_t max_samples = 2000);

/** \brief Length of the axis-aligned bounding-box diagonal. */
double boundingBoxDiagonal(const PointCloudSequence::Cloud& cloud);

}  // namespace pcl_animseg
