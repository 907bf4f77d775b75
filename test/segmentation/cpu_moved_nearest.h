#pragma once
// MotionDevice::nearestMoved (motion_device.h) on the CPU, two ways, for tests of devices: as the
// interface specifies it (every copy's squared distance, the k nearest by distance and index, a
// pick that a tie at the k-th nearest decides left undecided), and as the motion method's cores
// find it (a kd-tree of the frame's copies: nearestFirst, then knn).
#include <pcl/point_types.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/segmentation/motion_device.h>
#include <pcl_animseg/sequence.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

namespace animseg_test {

// Every frame's copies as MovedCopies::fill writes them (8 floats each, frame after frame).
inline std::vector<float> movedCopies(const pcl_animseg::segmentation::MovedCopies& m, int frames) {
  std::vector<float> out(8 * static_cast<std::size_t>(frames) * m.order.size());
  m.fill(out.data());
  return out;
}

// Whether copy `c` (8 floats) agrees with normal `n` in the motion method's float cosine.
inline bool movedAgrees(const float* c, const float* n, bool unoriented, double normal_cos) {
  const float x = c[4] * n[0] + c[5] * n[1] + c[6] * n[2];
  return (unoriented ? std::abs(static_cast<double>(x)) : static_cast<double>(x)) > normal_cos;
}

// The picks as the interface specifies them, by brute force.
inline std::vector<int> movedNearestBySpec(const pcl_animseg::segmentation::DeviceFrames& frames,
                                           const pcl_animseg::segmentation::MovedCopies& m) {
  const int T = static_cast<int>(frames.frames.size());
  const std::size_t n = m.order.size();
  const std::vector<float> copies = movedCopies(m, T);
  std::vector<int> pick;
  std::vector<std::pair<float, int>> all;  // (squared distance, reference index)
  std::vector<int> copy_of;                // reference index -> copy, for this frame
  for (int t = 0; t < T; ++t) {
    const auto& f = frames.frames[t];
    const std::vector<float>& pts = f.tree->leafPoints();
    const std::vector<float>& nrm = f.normals();
    const float* fc = &copies[8 * static_cast<std::size_t>(t) * n];
    for (std::size_t i = 0; i < f.tree->size(); ++i) {
      const float* q = &pts[3 * i];
      all.clear();
      for (std::size_t c = 0; c < n; ++c) {
        const float* p = fc + 8 * c;
        if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) continue;
        const float dx = q[0] - p[0], dy = q[1] - p[1], dz = q[2] - p[2];
        all.push_back({(dx * dx + dy * dy) + dz * dz, static_cast<int>(c)});
      }
      auto before = [&](const std::pair<float, int>& a, const std::pair<float, int>& b) {
        return a.first < b.first || (a.first == b.first && m.order[a.second] < m.order[b.second]);
      };
      const std::size_t keep = std::min<std::size_t>(all.size(), m.k + 1);
      std::partial_sort(all.begin(), all.begin() + keep, all.end(), before);
      const int kk = std::min<int>(m.k, static_cast<int>(all.size()));
      const bool tie = static_cast<int>(all.size()) > m.k && all[m.k - 1].first == all[m.k].first;
      int sure = kk;
      if (tie) {
        sure = 0;
        while (all[sure].first != all[m.k - 1].first) ++sure;
      }
      int p = kk > 0 ? m.order[all[0].second] : -1;
      bool found = false;
      for (int e = 0; e < std::min(kk, sure) && !found; ++e)
        if (movedAgrees(fc + 8 * all[e].second, &nrm[3 * i], f.unoriented, m.normal_cos))
          p = m.order[all[e].second], found = true;
      if (!found && tie) p = pcl_animseg::segmentation::kMovedUndecided;
      pick.push_back(p);
    }
  }
  return pick;
}

// The picks as the motion method's cores find them: each frame's copies in a kd-tree at their
// reference indices, the nearest copy where it is the only one at its distance and agrees, else
// the first agreeing of the k nearest (knn), else the nearest.
inline std::vector<int> movedNearestByTree(const pcl_animseg::segmentation::DeviceFrames& frames,
                                           const pcl_animseg::segmentation::MovedCopies& m) {
  using Cloud = pcl::PointCloud<pcl::PointNormal>;
  const int T = static_cast<int>(frames.frames.size());
  const std::size_t n = m.order.size();
  const std::vector<float> copies = movedCopies(m, T);
  int size = 0;
  for (int r : m.order) size = std::max(size, r + 1);
  std::vector<int> pick, idx;
  std::vector<float> d2;
  for (int t = 0; t < T; ++t) {
    const auto& f = frames.frames[t];
    Cloud::Ptr moved(new Cloud);
    pcl::PointNormal none;
    none.x = none.y = none.z = std::numeric_limits<float>::quiet_NaN();
    moved->resize(size, none);
    for (std::size_t c = 0; c < n; ++c) {
      const float* p = &copies[8 * (static_cast<std::size_t>(t) * n + c)];
      pcl::PointNormal& q = (*moved)[m.order[c]];
      q.x = p[0], q.y = p[1], q.z = p[2];
      q.normal_x = p[4], q.normal_y = p[5], q.normal_z = p[6];
    }
    moved->is_dense = false;
    pcl_animseg::KdTree<pcl::PointNormal> tree;
    tree.setInputCloud(moved);
    const std::vector<float>& pts = f.tree->leafPoints();
    const std::vector<float>& nrm = f.normals();
    for (std::size_t i = 0; i < f.tree->size(); ++i) {
      pcl::PointNormal q;
      q.x = pts[3 * i], q.y = pts[3 * i + 1], q.z = pts[3 * i + 2];
      auto agrees = [&](int r) {
        const pcl::PointNormal& c = (*moved)[r];
        const float cn[8] = {0, 0, 0, 0, c.normal_x, c.normal_y, c.normal_z, 0};
        return movedAgrees(cn, &nrm[3 * i], f.unoriented, m.normal_cos);
      };
      float nd2;
      bool tied;
      const int first = tree.nearestFirst(q, nd2, tied);
      if (first >= 0 && !tied && agrees(first)) {
        pick.push_back(first);
        continue;
      }
      tree.nearestKSearch(q, m.k, idx, d2);
      int p = idx.empty() ? -1 : idx[0];
      for (int r : idx)
        if (agrees(r)) {
          p = r;
          break;
        }
      pick.push_back(p);
    }
  }
  return pick;
}

// A labelling case for tests: a sequence's frames as a device is given them (their trees, leaf
// normals, spacings; the odd frames' normals unoriented), and the first frame's points carried
// into every frame by two motions (the points left and right of x = 0 turned about z by opposite
// angles, growing frame by frame), with ties planted: every 97th copy a duplicate of the next
// (two copies at the same distance from every point), ten copies at one place with their normals
// turned over (the k-th and the next nearest of the points around them at the same distance)
// and one copy that is not finite.
struct MovedCase {
  std::vector<pcl_animseg::KdTree<pcl::PointNormal>> trees;
  pcl_animseg::segmentation::DeviceFrames frames;
  pcl_animseg::segmentation::MovedCopies copies;
  std::vector<float> data;  // what copies.fill writes
};

inline void makeMovedCase(const pcl_animseg::PointCloudSequence& seq, MovedCase& c) {
  using Cloud = pcl::PointCloud<pcl::PointNormal>;
  const int T = static_cast<int>(seq.size());
  c.trees.resize(T);
  c.frames.frames.resize(T);
  for (int t = 0; t < T; ++t) {
    const Cloud::ConstPtr cloud = seq.frame(t);
    c.trees[t].setInputCloud(cloud);
    auto& f = c.frames.frames[t];
    f.tree = &c.trees[t].flatTree();
    for (int r : f.tree->leafRows()) {
      const pcl::PointNormal& q = (*cloud)[c.trees[t].cloudIndex(r)];
      f.leaf_normals.insert(f.leaf_normals.end(), {q.normal_x, q.normal_y, q.normal_z});
    }
    // The mean distance to the nearest other point, over every 10th point.
    double sum = 0.0;
    int count = 0;
    std::vector<int> idx;
    std::vector<float> d2;
    for (std::size_t i = 0; i < cloud->size(); i += 10)
      if (c.trees[t].nearestKSearch((*cloud)[i], 2, idx, d2) == 2) sum += std::sqrt(d2[1]), ++count;
    f.spacing = count > 0 ? sum / count : 1.0;
    f.unoriented = t % 2 == 1;
  }
  const Cloud& ref = *seq.frame(0);
  for (int r : c.trees[0].flatTree().leafRows()) c.copies.order.push_back(c.trees[0].cloudIndex(r));
  const std::size_t n = c.copies.order.size();
  c.data.assign(8 * static_cast<std::size_t>(T) * n, 0.0f);
  for (int t = 0; t < T; ++t)
    for (std::size_t i = 0; i < n; ++i) {
      const pcl::PointNormal& q = ref[c.copies.order[i]];
      const double a = 0.05 * t * (q.x > 0.0f ? 1.0 : -1.0), cs = std::cos(a), sn = std::sin(a);
      float* o = &c.data[8 * (static_cast<std::size_t>(t) * n + i)];
      o[0] = static_cast<float>(cs * q.x - sn * q.y);
      o[1] = static_cast<float>(sn * q.x + cs * q.y);
      o[2] = q.z + 0.01f * static_cast<float>(t);
      o[4] = static_cast<float>(cs * q.normal_x - sn * q.normal_y);
      o[5] = static_cast<float>(sn * q.normal_x + cs * q.normal_y);
      o[6] = q.normal_z;
    }
  for (int t = 0; t < T; ++t) {
    float* f = &c.data[8 * static_cast<std::size_t>(t) * n];
    for (std::size_t i = 0; i + 1 < n; i += 97)
      std::copy(f + 8 * (i + 1), f + 8 * (i + 2), f + 8 * i);
    if (n > 720) {
      for (int k = 4; k < 7; ++k) f[8 * 500 + k] = -f[8 * 500 + k];
      for (std::size_t i = 501; i < 510; ++i) std::copy(f + 8 * 500, f + 8 * 501, f + 8 * i);
      f[8 * 700] = std::numeric_limits<float>::quiet_NaN();
    }
  }
  c.copies.k = 8;
  c.copies.normal_cos = 0.3;
  c.copies.fill = [&c](float* out) { std::copy(c.data.begin(), c.data.end(), out); };
}

}  // namespace animseg_test
