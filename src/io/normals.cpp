#include <pcl_animseg/error.h>
#include <pcl_animseg/io/normals.h>

#include <pcl/features/normal_3d_omp.h>
#include <pcl/kdtree/kdtree_flann.h>

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <queue>
#include <tuple>
#include <unordered_map>

namespace pcl_animseg {
namespace io {

namespace {

bool finiteNormal(const pcl::PointNormal& p) {
  return std::isfinite(p.normal_x) && std::isfinite(p.normal_y) && std::isfinite(p.normal_z);
}

void setNormal(pcl::PointNormal& p, const Eigen::Vector3d& n) {
  p.normal_x = static_cast<float>(n.x());
  p.normal_y = static_cast<float>(n.y());
  p.normal_z = static_cast<float>(n.z());
}

void flip(pcl::PointNormal& p) {
  p.normal_x = -p.normal_x;
  p.normal_y = -p.normal_y;
  p.normal_z = -p.normal_z;
}

double dotN(const pcl::PointNormal& a, const pcl::PointNormal& b) {
  return static_cast<double>(a.normal_x) * b.normal_x + static_cast<double>(a.normal_y) * b.normal_y +
         static_cast<double>(a.normal_z) * b.normal_z;
}

}  // namespace

std::vector<char> computeMeshNormals(PointCloudSequence::Cloud& cloud,
                                     const std::vector<pcl::Vertices>& faces) {
  const std::size_t n = cloud.size();
  std::vector<Eigen::Vector3d> acc(n, Eigen::Vector3d::Zero());
  std::unordered_map<std::uint64_t, int> edges;
  bool closed = !faces.empty();
  double volume6 = 0.0;  // six times the signed volume (divergence theorem)
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  for (const auto& p : cloud) origin += p.getVector3fMap().cast<double>();
  if (n > 0) origin /= static_cast<double>(n);

  for (const auto& f : faces) {
    const auto& v = f.vertices;
    if (v.size() < 3) continue;
    bool ok = true;
    for (auto i : v) ok = ok && i >= 0 && static_cast<std::size_t>(i) < n;
    if (!ok) throw Error("mesh face refers to a vertex that does not exist");
    for (std::size_t a = 0; a < v.size(); ++a) {
      auto i = static_cast<std::uint32_t>(v[a]);
      auto j = static_cast<std::uint32_t>(v[(a + 1) % v.size()]);
      if (i > j) std::swap(i, j);
      ++edges[(static_cast<std::uint64_t>(i) << 32) | j];
    }
    const Eigen::Vector3d p0 = cloud[v[0]].getVector3fMap().cast<double>() - origin;
    for (std::size_t a = 1; a + 1 < v.size(); ++a) {
      const Eigen::Vector3d p1 = cloud[v[a]].getVector3fMap().cast<double>() - origin;
      const Eigen::Vector3d p2 = cloud[v[a + 1]].getVector3fMap().cast<double>() - origin;
      // |cross| is twice the triangle's area: summing it is the area weighting.
      const Eigen::Vector3d c = (p1 - p0).cross(p2 - p0);
      acc[v[0]] += c;
      acc[v[a]] += c;
      acc[v[a + 1]] += c;
      volume6 += p0.dot(p1.cross(p2));
    }
  }
  for (const auto& e : edges) closed = closed && e.second == 2;
  // An inward-wound closed mesh has negative volume; its normals would all point inside.
  const double sign = (closed && volume6 < 0.0) ? -1.0 : 1.0;

  std::vector<char> has(n, 0);
  for (std::size_t i = 0; i < n; ++i) {
    const double len = acc[i].norm();
    if (len > 0.0 && std::isfinite(len)) {
      setNormal(cloud[i], sign * acc[i] / len);
      has[i] = 1;
    }
  }
  return has;
}

void orientNormals(PointCloudSequence::Cloud& cloud, int k, const std::vector<char>& fixed) {
  const std::size_t n = cloud.size();
  if (n == 0) return;
  if (!fixed.empty() && fixed.size() != n)
    throw Error("orientNormals: the fixed mask does not match the cloud");
  auto isFixed = [&](std::size_t i) { return !fixed.empty() && fixed[i]; };

  // Symmetric kNN graph (Hoppe's Riemannian graph without the EMST edges: with k ~ 16 the kNN
  // graph of a reasonably sampled surface is connected; separate components are handled below).
  std::vector<std::vector<int>> adj(n);
  if (n > 1) {
    PointCloudSequence::Cloud::Ptr copy(new PointCloudSequence::Cloud(cloud));
    pcl::KdTreeFLANN<pcl::PointNormal> tree;
    tree.setInputCloud(copy);
    const int kk = std::min<int>(std::max(k, 3) + 1, static_cast<int>(n));
    std::vector<int> idx;
    std::vector<float> d2;
    for (std::size_t i = 0; i < n; ++i) {
      if (tree.nearestKSearch(cloud[i], kk, idx, d2) <= 0) continue;
      for (int j : idx) {
        if (j == static_cast<int>(i)) continue;
        adj[i].push_back(j);
        adj[j].push_back(static_cast<int>(i));
      }
    }
    for (auto& a : adj) {
      std::sort(a.begin(), a.end());
      a.erase(std::unique(a.begin(), a.end()), a.end());
    }
  }

  std::vector<int> component(n, -1);
  std::vector<char> visited(n, 0);
  // (cost, index): ties broken by index so that the result does not depend on heap internals.
  using Entry = std::tuple<double, int, int>;  // cost, to, from
  for (std::size_t start = 0; start < n; ++start) {
    if (component[start] >= 0) continue;
    std::vector<int> members{static_cast<int>(start)};
    component[start] = static_cast<int>(start);
    for (std::size_t q = 0; q < members.size(); ++q)
      for (int j : adj[members[q]])
        if (component[j] < 0) {
          component[j] = static_cast<int>(start);
          members.push_back(j);
        }

    std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> heap;
    auto visit = [&](int i) {
      visited[i] = 1;
      for (int j : adj[i])
        if (!visited[j]) heap.emplace(1.0 - std::abs(dotN(cloud[i], cloud[j])), j, i);
    };
    bool has_fixed = false;
    for (int i : members)
      if (isFixed(i)) has_fixed = true;

    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int i : members) c += cloud[i].getVector3fMap().cast<double>();
    c /= static_cast<double>(members.size());

    if (has_fixed) {
      for (int i : members)
        if (isFixed(i)) visit(i);
    } else {
      int seed = members.front();
      double best = -1.0;
      for (int i : members) {
        const double d = (cloud[i].getVector3fMap().cast<double>() - c).squaredNorm();
        if (d > best) {
          best = d;
          seed = i;
        }
      }
      const Eigen::Vector3d out = cloud[seed].getVector3fMap().cast<double>() - c;
      const Eigen::Vector3d ns = cloud[seed].getNormalVector3fMap().cast<double>();
      if (ns.dot(out) < 0.0) flip(cloud[seed]);
      visit(seed);
    }
    while (!heap.empty()) {
      const auto [cost, to, from] = heap.top();
      (void)cost;
      heap.pop();
      if (visited[to]) continue;
      if (dotN(cloud[from], cloud[to]) < 0.0) flip(cloud[to]);
      visit(to);
    }

    if (!has_fixed) {
      double mean = 0.0;
      for (int i : members)
        mean += (cloud[i].getVector3fMap().cast<double>() - c)
                    .dot(cloud[i].getNormalVector3fMap().cast<double>());
      if (mean < 0.0)
        for (int i : members) flip(cloud[i]);
    }
  }
}

void estimateNormals(PointCloudSequence::Cloud& cloud, int k, const std::vector<char>& known) {
  const std::size_t n = cloud.size();
  if (n == 0) return;
  if (!known.empty() && known.size() != n)
    throw Error("estimateNormals: the known mask does not match the cloud");
  pcl::IndicesPtr todo(new pcl::Indices);
  for (std::size_t i = 0; i < n; ++i)
    if (known.empty() || !known[i]) todo->push_back(static_cast<int>(i));
  if (todo->empty()) return;
  if (n < 3) throw Error("cannot estimate normals from fewer than 3 points");

  PointCloudSequence::Cloud::Ptr copy(new PointCloudSequence::Cloud(cloud));
  pcl::NormalEstimationOMP<pcl::PointNormal, pcl::Normal> ne;
  ne.setInputCloud(copy);
  ne.setIndices(todo);
  ne.setKSearch(std::min<int>(std::max(k, 3), static_cast<int>(n)));
  pcl::PointCloud<pcl::Normal> normals;
  ne.compute(normals);
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (const auto& p : cloud) c += p.getVector3fMap().cast<double>();
  c /= static_cast<double>(n);
  for (std::size_t a = 0; a < todo->size(); ++a) {
    auto& p = cloud[(*todo)[a]];
    const auto& nn = normals[a];
    p.normal_x = nn.normal_x;
    p.normal_y = nn.normal_y;
    p.normal_z = nn.normal_z;
    p.curvature = std::isfinite(nn.curvature) ? nn.curvature : 0.0f;
    if (!finiteNormal(p) || p.getNormalVector3fMap().squaredNorm() < 1e-12f) {
      // A degenerate neighbourhood (duplicates, a line): any direction is as good as another;
      // the radial one at least orients sensibly.
      Eigen::Vector3d r = p.getVector3fMap().cast<double>() - c;
      if (r.norm() < 1e-12) r = Eigen::Vector3d::UnitZ();
      setNormal(p, r.normalized());
    }
  }
  orientNormals(cloud, k, known);
}

}  // namespace io
}  // namespace pcl_animseg
