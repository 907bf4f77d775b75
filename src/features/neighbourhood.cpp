#include <pcl_animseg/error.h>
#include <pcl_animseg/features/neighbourhood.h>

#include <pcl/common/common.h>
#include <pcl/kdtree/kdtree_flann.h>

#include <omp.h>

#include <algorithm>
#include <cmath>

namespace pcl_animseg {

int Neighbourhoods::countWithin(std::size_t i, float r) const {
  const float r2 = r * r;
  const float* b = sqrRow(i);
  const float* e = b + count(i);
  return static_cast<int>(std::upper_bound(b, e, r2) - b);
}

Neighbourhoods radiusNeighbourhoods(const PointCloudSequence::Cloud& cloud, float radius,
                                    int max_neighbours) {
  using Cloud = PointCloudSequence::Cloud;
  if (!(radius > 0.0f)) throw Error("neighbourhood radius must be positive");
  Neighbourhoods out;
  out.radius = radius;
  const std::size_t n = cloud.size();
  out.offsets.assign(n + 1, 0);
  if (n == 0) return out;
  // The tree only reads the cloud; a non-owning pointer avoids copying the frame.
  Cloud::ConstPtr ptr(&cloud, [](const Cloud*) {});
  pcl::KdTreeFLANN<pcl::PointNormal> tree(true);
  tree.setInputCloud(ptr);

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
    std::vector<int> idx;
    std::vector<float> d2;
    auto& my_idx = idx_parts[t];
    auto& my_d2 = d2_parts[t];
    my_idx.reserve((end - begin) * 32);
    my_d2.reserve((end - begin) * 32);
    for (std::size_t i = begin; i < end; ++i) {
      int found = tree.radiusSearch(cloud[i], radius, idx, d2,
                                    static_cast<unsigned int>(std::max(1, max_neighbours)));
      // FLANN may not put the query first among coincident points; rows start with the point.
      int self = -1;
      for (int a = 0; a < found; ++a)
        if (idx[a] == static_cast<int>(i)) { self = a; break; }
      if (self < 0) {
        my_idx.push_back(static_cast<int>(i));
        my_d2.push_back(0.0f);
        if (found == max_neighbours && found > 0) --found;  // keep the row at most max long
      } else {
        my_idx.push_back(static_cast<int>(i));
        my_d2.push_back(0.0f);
      }
      for (int a = 0; a < found; ++a) {
        if (a == self) continue;
        my_idx.push_back(idx[a]);
        my_d2.push_back(d2[a]);
      }
      out.offsets[i + 1] = static_cast<std::size_t>(found + (self < 0 ? 1 : 0));
    }
  }
  for (std::size_t i = 0; i < n; ++i) out.offsets[i + 1] += out.offsets[i];
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
  pcl::KdTreeFLANN<pcl::PointNormal> tree(true);
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
