#include <pcl_animseg/error.h>
#include <pcl_animseg/features/neighbourhood.h>

#include <pcl/common/common.h>
#include <pcl_animseg/kdtree.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <utility>

namespace pcl_animseg {

int Neighbourhoods::countWithin(std::size_t i, float r) const {
  const float r2 = r * r;
  const float* b = sqrRow(i);
  const float* e = b + count(i);
  return static_cast<int>(std::upper_bound(b, e, r2) - b);
}

namespace {

/** Uniform grid of cell size >= the search radius: the points sorted by cell key (x major, z
 * minor), so that the three cells (ix, iy, iz - 1 .. iz + 1) of a column are one contiguous run
 * of the sorted arrays, found through a dense table of cell starts (or a binary search over the
 * sorted keys where the grid has many more cells than points). */
struct CellGrid {
  Eigen::Vector3f origin;
  float inv_cell = 0.0f;
  std::int64_t ny = 0, nz = 0;
  std::vector<std::int64_t> keys;  // sorted
  std::vector<int> order;          // point index of each sorted key
  std::vector<float> x, y, z;      // positions in sorted order
  std::vector<int> start;          // dense: first sorted position of each key (size cells + 1)

  std::int64_t key(std::int64_t ix, std::int64_t iy, std::int64_t iz) const {
    return (ix * ny + iy) * nz + iz;
  }
  Eigen::Array3i cell(const Eigen::Vector3f& p) const {
    return ((p - origin) * inv_cell).array().floor().cast<int>();
  }
  /** Sorted positions [first, last) of the keys lo..hi. */
  std::pair<std::size_t, std::size_t> run(std::int64_t lo, std::int64_t hi) const {
    if (!start.empty())
      return {static_cast<std::size_t>(start[lo]), static_cast<std::size_t>(start[hi + 1])};
    const auto b = std::lower_bound(keys.begin(), keys.end(), lo);
    const auto e = std::upper_bound(b, keys.end(), hi);
    return {static_cast<std::size_t>(b - keys.begin()), static_cast<std::size_t>(e - keys.begin())};
  }
};

}  // namespace

NeighbourGrid neighbourGrid(const PointCloudSequence::Cloud& cloud, float radius) {
  Eigen::Vector3f lo_corner = Eigen::Vector3f::Constant(std::numeric_limits<float>::max());
  Eigen::Vector3f hi_corner = -lo_corner;
  for (const auto& p : cloud.points)
    if (p.getVector3fMap().allFinite()) {
      lo_corner = lo_corner.cwiseMin(p.getVector3fMap());
      hi_corner = hi_corner.cwiseMax(p.getVector3fMap());
    }
  if (!(hi_corner.array() >= lo_corner.array()).all())
    lo_corner = hi_corner = Eigen::Vector3f::Zero();
  NeighbourGrid g;
  g.origin = lo_corner;
  // Cells of the search radius, or coarser where a few far-off points stretch the frame to more
  // than 1e6 cells per axis (keys stay in 64 bits; coarser cells are only slower).
  const float extent = (hi_corner - lo_corner).maxCoeff();
  const float cell = std::max(radius, std::isfinite(extent) ? extent * 1.0e-6f : radius);
  g.inv_cell = 1.0f / cell;
  const Eigen::Array3f ext = (hi_corner - lo_corner).array() * g.inv_cell;
  g.ny = ext.allFinite() ? static_cast<std::int64_t>(ext(1)) + 3 : 3;
  g.nz = ext.allFinite() ? static_cast<std::int64_t>(ext(2)) + 3 : 3;
  // Keys of finite points are < (nx + 2) ny nz with nx = ny * nz cells per x slab.
  g.cells = (static_cast<std::int64_t>(ext.allFinite() ? ext(0) : 0) + 3) * g.ny * g.nz;
  return g;
}

Neighbourhoods radiusNeighbourhoods(const PointCloudSequence::Cloud& cloud, float radius,
                                    int max_neighbours) {
  if (!(radius > 0.0f)) throw Error("neighbourhood radius must be positive");
  Neighbourhoods out;
  out.radius = radius;
  const std::size_t n = cloud.size();
  out.offsets.assign(n + 1, 0);
  if (n == 0) return out;
  const int cap = std::max(1, max_neighbours);

  // A uniform grid with cells of the search radius instead of a kd-tree: every neighbour of a
  // point lies in the 27 cells around it, and a fixed-radius search of ~30 neighbours per point
  // through pcl::KdTreeFLANN cost 7 us (allocations, copies), most of the scale space's time.
  const NeighbourGrid shape = neighbourGrid(cloud, radius);
  CellGrid grid;
  grid.origin = shape.origin;
  grid.inv_cell = shape.inv_cell;
  grid.ny = shape.ny;
  grid.nz = shape.nz;
  std::vector<char> finite(n);
  {
    std::vector<std::pair<std::int64_t, int>> kp(n);
    for (std::size_t i = 0; i < n; ++i) {
      finite[i] = cloud[i].getVector3fMap().allFinite();
      const Eigen::Array3i c =
          finite[i] ? grid.cell(cloud[i].getVector3fMap()) : Eigen::Array3i(-2, 0, 0);
      // Points with NaN coordinates get a key that no search reaches (and a row of themselves).
      kp[i] = {finite[i] ? grid.key(c(0) + 1, c(1) + 1, c(2) + 1) : -1, static_cast<int>(i)};
    }
    std::sort(kp.begin(), kp.end());
    grid.keys.resize(n);
    grid.order.resize(n);
    grid.x.resize(n);
    grid.y.resize(n);
    grid.z.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
      grid.keys[i] = kp[i].first;
      grid.order[i] = kp[i].second;
      const pcl::PointNormal& p = cloud[kp[i].second];
      grid.x[i] = p.x;
      grid.y[i] = p.y;
      grid.z[i] = p.z;
    }
  }
  const std::int64_t cells = shape.cells;
  if (cells <= 8 * static_cast<std::int64_t>(n) + 4096) {
    grid.start.assign(static_cast<std::size_t>(cells) + 1, 0);
    std::size_t a = 0;
    while (a < n && grid.keys[a] < 0) ++a;  // NaN points: not in the table
    for (std::int64_t k = 0; k <= cells; ++k) {
      while (a < n && grid.keys[a] < k) ++a;
      grid.start[static_cast<std::size_t>(k)] = static_cast<int>(a);
    }
  }
  const float r2 = radius * radius;

  // Contiguous chunks per thread, concatenated in thread order, keep rows in point order
  // without a second search pass or a vector per point.
  int threads = 1;
  std::vector<std::vector<int>> idx_parts;
  std::vector<std::vector<float>> d2_parts;
#pragma omp parallel
  {
#pragma omp single
    {
      threads = omp_get_num_threads();
      idx_parts.resize(threads);
      d2_parts.resize(threads);
    }
    const int t = omp_get_thread_num();
    const std::size_t begin = n * t / threads, end = n * (t + 1) / threads;
    // (squared distance bits, index) packed in one integer: non-negative floats order like
    // their bit patterns, so one integer sort orders by distance, then index.
    std::vector<std::uint64_t> row;
    auto& my_idx = idx_parts[t];
    auto& my_d2 = d2_parts[t];
    my_idx.reserve((end - begin) * 40);
    my_d2.reserve((end - begin) * 40);
    for (std::size_t i = begin; i < end; ++i) {
      const Eigen::Vector3f x = cloud[i].getVector3fMap();
      row.clear();
      const Eigen::Array3i c = finite[i] ? grid.cell(x) : Eigen::Array3i::Zero();
      for (int dx = 0; dx <= 2 && finite[i]; ++dx)
        for (int dy = 0; dy <= 2; ++dy) {
          const std::int64_t lo = grid.key(c(0) + dx, c(1) + dy, c(2));
          const auto r = grid.run(lo, lo + 2);
          for (std::size_t a = r.first; a < r.second; ++a) {
            const float ex = grid.x[a] - x.x(), ey = grid.y[a] - x.y(), ez = grid.z[a] - x.z();
            const float dd = ex * ex + ey * ey + ez * ez;
            if (dd < r2 && grid.order[a] != static_cast<int>(i)) {
              std::uint32_t bits;
              std::memcpy(&bits, &dd, 4);
              row.push_back((static_cast<std::uint64_t>(bits) << 32) |
                            static_cast<std::uint32_t>(grid.order[a]));
            }
          }
        }
      // Rows sorted by distance, the point itself first; ties by index (duplicates) so that
      // the rows do not depend on the search order; at most `cap` entries (the nearest).
      const std::size_t keep =
          std::min<std::size_t>(row.size(), static_cast<std::size_t>(cap - 1));
      if (keep < row.size())
        std::partial_sort(row.begin(), row.begin() + keep, row.end());
      else
        std::sort(row.begin(), row.end());
      my_idx.push_back(static_cast<int>(i));
      my_d2.push_back(0.0f);
      for (std::size_t a = 0; a < keep; ++a) {
        const std::uint32_t bits = static_cast<std::uint32_t>(row[a] >> 32);
        float dd;
        std::memcpy(&dd, &bits, 4);
        my_idx.push_back(static_cast<int>(row[a] & 0xffffffffu));
        my_d2.push_back(dd);
      }
      out.offsets[i + 1] = keep + 1;
    }
  }
  for (std::size_t i = 0; i < n; ++i) out.offsets[i + 1] += out.offsets[i];
  if (threads == 1) {  // e.g. inside a parallel loop over frames: no copy
    out.indices = std::move(idx_parts[0]);
    out.sqr_distances = std::move(d2_parts[0]);
    return out;
  }
  out.indices.reserve(out.offsets[n]);
  out.sqr_distances.reserve(out.offsets[n]);
  for (int t = 0; t < threads; ++t) {
    out.indices.insert(out.indices.end(), idx_parts[t].begin(), idx_parts[t].end());
    out.sqr_distances.insert(out.sqr_distances.end(), d2_parts[t].begin(), d2_parts[t].end());
  }
  return out;
}

double featureSpacing(const PointCloudSequence::Cloud& cloud, std::size_t max_samples) {
  using Cloud = PointCloudSequence::Cloud;
  const std::size_t n = cloud.size();
  if (n < 2) throw Error("cannot measure the point spacing of fewer than 2 points");
  pcl::PointNormal mn, mx;
  pcl::getMinMax3D(cloud, mn, mx);
  const double diag = (mx.getVector3fMap() - mn.getVector3fMap()).norm();
  if (!(diag > 0.0) || !std::isfinite(diag))
    throw Error("all " + std::to_string(n) + " points of the frame coincide: no spacing");
  // Coincident means closer than float resolution at this extent.
  const float eps2 = static_cast<float>(1e-6 * diag) * static_cast<float>(1e-6 * diag);
  Cloud::ConstPtr ptr(&cloud, [](const Cloud*) {});
  pcl_animseg::KdTree<pcl::PointNormal> tree(true);
  tree.setInputCloud(ptr);
  const std::size_t step = std::max<std::size_t>(1, n / std::max<std::size_t>(1, max_samples));
  std::vector<int> idx;
  std::vector<float> d2;
  double sum = 0.0;
  std::size_t count = 0;
  for (std::size_t i = 0; i < n; i += step) {
    for (int k = 2;; k *= 4) {
      const int kk = static_cast<int>(std::min<std::size_t>(k, n));
      const int found = tree.nearestKSearch(cloud[i], kk, idx, d2);
      int a = 0;
      while (a < found && d2[a] <= eps2) ++a;
      if (a < found) {
        sum += std::sqrt(static_cast<double>(d2[a]));
        ++count;
        break;
      }
      if (kk >= static_cast<int>(n)) break;
    }
  }
  if (count == 0) throw Error("all points of the frame coincide: the point spacing is zero");
  return sum / static_cast<double>(count);
}

}  // namespace pcl_animseg
