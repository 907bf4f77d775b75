#pragma once
/** \file neighbourhood.h Fixed-radius neighbourhoods of a frame, searched once and shared by the
 * scale space, the keypoint detector and the signature (the MLS projection keeps the point order,
 * so the neighbourhoods of the input are valid on every level). */
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace pcl_animseg {

/** \brief Neighbours of every point within `radius`, in compressed rows, each row sorted by
 * distance (the point itself first). */
struct Neighbourhoods {
  float radius = 0.0f;
  std::vector<std::size_t> offsets;  ///< size N + 1
  std::vector<int> indices;
  std::vector<float> sqr_distances;

  std::size_t points() const { return offsets.empty() ? 0 : offsets.size() - 1; }
  int count(std::size_t i) const { return static_cast<int>(offsets[i + 1] - offsets[i]); }
  const int* row(std::size_t i) const { return indices.data() + offsets[i]; }
  const float* sqrRow(std::size_t i) const { return sqr_distances.data() + offsets[i]; }
  /** \brief How many of row i's neighbours lie within radius r (rows are sorted). */
  int countWithin(std::size_t i, float r) const;
};

/** \brief The uniform grid that radiusNeighbourhoods searches: cells of the radius (coarser where
 * a few far-off points stretch the frame to more than 1e6 cells an axis), from `origin`. A point
 * p lies in cell c = floor((p - origin) * inv_cell), whose key is ((c_x + 1) ny + c_y + 1) nz +
 * c_z + 1; keys are below `cells`. */
struct NeighbourGrid {
  Eigen::Vector3f origin = Eigen::Vector3f::Zero();
  float inv_cell = 0.0f;
  std::int64_t ny = 0, nz = 0, cells = 0;
};

/** \brief The grid of radiusNeighbourhoods(cloud, radius) (its finite points only). */
NeighbourGrid neighbourGrid(const PointCloudSequence::Cloud& cloud, float radius);

/** \brief Searches the neighbours of every point of `cloud` within `radius` (one kd-tree,
 * OpenMP over points). At most `max_neighbours` (the nearest) are kept per point, which bounds the
 * cost where many points coincide. */
Neighbourhoods radiusNeighbourhoods(const PointCloudSequence::Cloud& cloud, float radius,
                                    int max_neighbours = 256);

/** \brief The frame's mean point spacing as pcl_animseg::meanSpacing measures it, except that
 * coincident points (duplicates, e.g. mesh vertices split at seams) are skipped: the distance
 * used is the one to the nearest point that is not at the same place. Throws Error when all
 * points coincide. Equal to meanSpacing() on clouds without duplicates. */
double featureSpacing(const PointCloudSequence::Cloud& cloud, std::size_t max_samples = 2000);

}  // namespace pcl_animseg
