#include <pcl/common/centroid.h>
#include <pcl/features/normal_3d.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/normals.h>
#include <pcl_animseg/union_find.h>

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <functional>
#include <queue>
#include <tuple>
#include <unordered_map>
#include <vector>

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
  return static_cast<double>(a.normal_x) * b.normal_x +
         static_cast<double>(a.normal_y) * b.normal_y +
         static_cast<double>(a.normal_z) * b.normal_z;
}

/** How well the normals of two near points agree once b's is mirrored across the plane midway
 * between the points (normal to the step e from a to b): n_a . n_b - 2 (e . n_a)(e . n_b). On a
 * sphere of any radius the mirrored normal is exactly a's, so it is 1 for consistent outward
 * normals. On the two sides of a thin sheet (a finger: a point's k nearest can include the far
 * side), where consistent normals point away from each other, it is near +1 too, while the plain
 * dot product (near -1) would make Hoppe's propagation flip the far side. Two points at the same
 * position: the plain dot product. */
double mirroredAgreement(const pcl::PointNormal& a, const pcl::PointNormal& b) {
  const Eigen::Vector3d d = (b.getVector3fMap() - a.getVector3fMap()).cast<double>();
  const double len = d.norm();
  if (!(len > 0.0)) return dotN(a, b);
  const Eigen::Vector3d e = d / len;
  return dotN(a, b) - 2.0 * e.dot(a.getNormalVector3fMap().cast<double>()) *
                          e.dot(b.getNormalVector3fMap().cast<double>());
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

namespace {

/** The k nearest neighbours of every point (itself included, -1 padded), row i at [i*k, i*k+k).
 * One search serves both the PCA normals and the orientation graph. */
std::vector<int> nearestNeighbours(const PointCloudSequence::Cloud& cloud, int k) {
  const std::size_t n = cloud.size();
  std::vector<int> knn(n * static_cast<std::size_t>(k), -1);
  PointCloudSequence::Cloud::Ptr copy(new PointCloudSequence::Cloud(cloud));
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(copy);
  const int nn = static_cast<int>(n);
#pragma omp parallel
  {
    std::vector<int> idx;
    std::vector<float> d2;
#pragma omp for schedule(static)
    for (int i = 0; i < nn; ++i) {
      const int found = tree.nearestKSearch(cloud[i], k, idx, d2);
      for (int a = 0; a < found && a < k; ++a) knn[static_cast<std::size_t>(i) * k + a] = idx[a];
    }
  }
  return knn;
}

/** The second step of orientNormals (normals.h): the spanning tree decides each sign by one
 * edge, and one misleading edge (two sheets closer than the spacing, an arm against the torso)
 * flips a whole limb. Here the edges of the graph vote: removing a tree edge cuts the tree in
 * two, and the sum S of the agreements a_ij of the graph edges across that cut says whether
 * flipping the subtree below it would make the normals agree better (S < 0). The most negative
 * subtrees that do not nest are flipped, the sums are computed again, and so on until none is
 * negative (the total agreement rises every round, so this ends; capped all the same). S for
 * every tree edge at once: an edge (i, j) crosses exactly the tree edges on the path from i to j,
 * so a_ij is added at i and j and subtracted twice at their lowest common ancestor (Tarjan's
 * offline algorithm), and S is the sum over the subtree. The voters are each point's
 * kRepairNeighbours nearest (fewer than the tree's graph: memory and time, same result on the
 * generated bodies). Written by us (no kept library orients normals by cuts). Subtrees that hold
 * a fixed normal are never flipped. `order`: the component's points, each after its parent (-1
 * for a root); `pos`: scratch of the cloud's size. */
void repairSubtrees(PointCloudSequence::Cloud& cloud, const std::vector<int>& knn, int k,
                    const std::vector<int>& order, const std::vector<int>& parent,
                    const std::vector<char>& fixed, std::vector<int>& pos) {
  constexpr int kRepairNeighbours = 8;
  const int m = static_cast<int>(order.size());
  if (m < 3) return;
  for (int a = 0; a < m; ++a) pos[order[a]] = a;      // point -> place in order
  const int kv = std::min(k, kRepairNeighbours + 1);  // knn rows start with the point itself
  auto lists = [&](int i, int j) {
    for (int c = 0; c < kv; ++c)
      if (knn[static_cast<std::size_t>(i) * k + c] == j) return true;
    return false;
  };
  // The voters' graph (each undirected edge once), as adjacency over places.
  std::vector<int> adj_start(m + 1, 0), adj;
  {
    std::vector<std::pair<int, int>> edges;
    edges.reserve(static_cast<std::size_t>(m) * kRepairNeighbours);
    for (int a = 0; a < m; ++a) {
      const int i = order[a];
      for (int c = 0; c < kv; ++c) {
        const int j = knn[static_cast<std::size_t>(i) * k + c];
        if (j < 0 || j == i || (j < i && lists(j, i))) continue;
        edges.emplace_back(a, pos[j]);  // the graph's edges stay within the component
        ++adj_start[a + 1];
        ++adj_start[pos[j] + 1];
      }
    }
    for (int a = 0; a < m; ++a) adj_start[a + 1] += adj_start[a];
    adj.resize(adj_start[m]);
    std::vector<int> fill(adj_start.begin(), adj_start.end() - 1);
    for (const auto& [a, b] : edges) {
      adj[fill[a]++] = b;
      adj[fill[b]++] = a;
    }
  }
  // The tree in places; the roots hang off a virtual root m.
  std::vector<int> up(m + 1, m);
  for (int a = 0; a < m; ++a) up[a] = parent[order[a]] < 0 ? m : pos[parent[order[a]]];
  std::vector<int> child_start(m + 2, 0), children(m);
  for (int a = 0; a < m; ++a) ++child_start[up[a] + 1];
  for (int a = 0; a <= m; ++a) child_start[a + 1] += child_start[a];
  {
    std::vector<int> fill(child_start.begin(), child_start.end() - 1);
    for (int a = 0; a < m; ++a) children[fill[up[a]]++] = a;
  }
  // Tarjan's offline lowest common ancestors over an iterative depth-first search. An edge is
  // taken when the later of its two ends finishes; the edges are stored in that order (the
  // later end `finished[f]` owns [edge_start[f], edge_start[f + 1])), with the other end, the
  // ancestor and the agreement. The entry order gives each subtree as a range:
  // subtree(a) = by_tin[tin[a] .. tin[a] + size[a]).
  std::vector<int> finished, edge_start{0}, other, lca, uf(m + 1), anc(m + 1), tin(m + 1, 0),
      by_tin(m);
  std::vector<char> done(m + 1, 0);
  std::vector<float> agreement;
  finished.reserve(m);
  edge_start.reserve(m + 1);
  other.reserve(adj.size() / 2);
  lca.reserve(adj.size() / 2);
  agreement.reserve(adj.size() / 2);
  auto find = [&](int x) { return findRoot(uf, x); };
  {
    int entered = 0;
    std::vector<std::pair<int, int>> stack{{m, child_start[m]}};
    uf[m] = anc[m] = m;
    while (!stack.empty()) {
      auto& [u, next] = stack.back();
      if (next < child_start[u + 1]) {
        const int v = children[next++];
        uf[v] = anc[v] = v;
        tin[v] = entered;
        by_tin[entered++] = v;
        stack.emplace_back(v, child_start[v]);  // invalidates u and next
        continue;
      }
      const int w = u;
      stack.pop_back();
      if (w == m) break;
      done[w] = 1;
      finished.push_back(w);
      for (int e = adj_start[w]; e < adj_start[w + 1]; ++e) {
        const int v = adj[e];
        if (!done[v] || v == w) continue;
        other.push_back(v);
        lca.push_back(anc[find(v)]);
        agreement.push_back(
            static_cast<float>(mirroredAgreement(cloud[order[w]], cloud[order[v]])));
      }
      edge_start.push_back(static_cast<int>(other.size()));
      const int pw = stack.back().first;  // w's subtree joins its parent's set
      uf[find(w)] = find(pw);
      anc[find(pw)] = pw;
    }
  }
  adj = std::vector<int>();  // not needed any more
  std::vector<int> fixed_below(m + 1, 0), size(m + 1, 1);
  for (int a = 0; a < m; ++a) fixed_below[a] = !fixed.empty() && fixed[order[a]];
  for (int a = m - 1; a >= 0; --a) {
    fixed_below[up[a]] += fixed_below[a];
    size[up[a]] += size[a];
  }
  std::vector<signed char> sign(m, 1);  // a flip only changes the agreements' signs
  std::vector<double> sum(m + 1);
  // The agreement sums of every subtree's cut; returns the graph's total agreement.
  auto cutSums = [&]() {
    std::fill(sum.begin(), sum.end(), 0.0);
    double total = 0.0;
    for (int f = 0; f < m; ++f) {
      const int u = finished[f];
      for (int q = edge_start[f]; q < edge_start[f + 1]; ++q) {
        const int v = other[q];
        const double agree = sign[u] * sign[v] * agreement[q];
        total += agree;
        sum[u] += agree;
        sum[v] += agree;
        sum[lca[q]] -= 2.0 * agree;
      }
    }
    for (int a = m - 1; a >= 0; --a) sum[up[a]] += sum[a];
    return total;
  };
  auto flipSubtree = [&](int a) {
    for (int r = tin[a]; r < tin[a] + size[a]; ++r) sign[by_tin[r]] = -sign[by_tin[r]];
  };
  // Fenwick trees over the entry order: the chosen subtrees' roots, and their ranges.
  std::vector<int> roots_at(m + 2), ranges_at(m + 2);
  auto add = [](std::vector<int>& t, int i, int d) {
    for (++i; i < static_cast<int>(t.size()); i += i & -i) t[i] += d;
  };
  auto prefix = [](const std::vector<int>& t, int i) {  // sum over [0, i)
    int r = 0;
    for (; i > 0; i -= i & -i) r += t[i];
    return r;
  };
  std::vector<std::pair<double, int>> candidates;
  std::vector<int> chosen;
  constexpr int kMaxRounds = 64;
  double total = cutSums();  // the sums always belong to the current signs
  for (int round = 0; round < kMaxRounds; ++round) {
    candidates.clear();
    for (int a = 0; a < m; ++a)  // a flip must win at least half an edge's worth
      if (up[a] != m && fixed_below[a] == 0 && sum[a] < -0.5) candidates.emplace_back(sum[a], a);
    if (candidates.empty()) break;
    std::sort(candidates.begin(), candidates.end());
    // The most negative subtrees that do not nest in one another, flipped at once; if edges
    // between them make that no better than before, only the most negative one.
    std::fill(roots_at.begin(), roots_at.end(), 0);
    std::fill(ranges_at.begin(), ranges_at.end(), 0);
    chosen.clear();
    for (const auto& [s, a] : candidates) {
      if (prefix(ranges_at, tin[a] + 1) > 0) continue;  // inside one
      if (prefix(roots_at, tin[a] + size[a]) - prefix(roots_at, tin[a]) > 0) continue;  // holds one
      chosen.push_back(a);
      add(roots_at, tin[a], 1);
      add(ranges_at, tin[a], 1);
      add(ranges_at, tin[a] + size[a], -1);
    }
    for (int a : chosen) flipSubtree(a);
    const double after = cutSums();
    if (chosen.size() > 1 && after <= total) {
      for (int a : chosen) flipSubtree(a);
      flipSubtree(chosen.front());
      total = cutSums();
    } else {
      total = after;
    }
  }
  for (int a = 0; a < m; ++a)
    if (sign[a] < 0) flip(cloud[order[a]]);
}

/** Hoppe's propagation over the symmetric kNN graph (see orientNormals in normals.h). */
void orientWithGraph(PointCloudSequence::Cloud& cloud, const std::vector<int>& knn, int k,
                     const std::vector<char>& fixed) {
  const std::size_t n = cloud.size();
  auto isFixed = [&](std::size_t i) { return !fixed.empty() && fixed[i]; };
  // Symmetric adjacency in CSR form (an edge may appear twice; harmless for Prim).
  std::vector<std::size_t> start(n + 1, 0);
  for (std::size_t i = 0; i < n; ++i)
    for (int a = 0; a < k; ++a) {
      const int j = knn[i * k + a];
      if (j < 0 || static_cast<std::size_t>(j) == i) continue;
      ++start[i + 1];
      ++start[j + 1];
    }
  for (std::size_t i = 0; i < n; ++i) start[i + 1] += start[i];
  std::vector<int> adj(start[n]);
  {
    std::vector<std::size_t> fill(start.begin(), start.end() - 1);
    for (std::size_t i = 0; i < n; ++i)
      for (int a = 0; a < k; ++a) {
        const int j = knn[i * k + a];
        if (j < 0 || static_cast<std::size_t>(j) == i) continue;
        adj[fill[i]++] = j;
        adj[fill[j]++] = static_cast<int>(i);
      }
  }

  struct Entry {
    float cost;
    int to, from;
    // Ties broken by index so that the result does not depend on heap internals.
    bool operator>(const Entry& o) const {
      return std::tie(cost, to, from) > std::tie(o.cost, o.to, o.from);
    }
  };
  std::vector<char> in_component(n, 0), visited(n, 0);
  std::vector<int> members, order, parent(n, -1), pos(n, -1);
  std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> heap;
  auto visit = [&](int i) {
    visited[i] = 1;
    for (std::size_t e = start[i]; e < start[i + 1]; ++e) {
      const int j = adj[e];
      if (!visited[j])
        heap.push(
            {static_cast<float>(1.0 - std::abs(mirroredAgreement(cloud[i], cloud[j]))), j, i});
    }
  };
  for (std::size_t first = 0; first < n; ++first) {
    if (in_component[first]) continue;
    members.assign(1, static_cast<int>(first));
    in_component[first] = 1;
    for (std::size_t q = 0; q < members.size(); ++q)
      for (std::size_t e = start[members[q]]; e < start[members[q] + 1]; ++e)
        if (!in_component[adj[e]]) {
          in_component[adj[e]] = 1;
          members.push_back(adj[e]);
        }
    bool has_fixed = false;
    for (int i : members) has_fixed = has_fixed || isFixed(i);
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (int i : members) c += cloud[i].getVector3fMap().cast<double>();
    c /= static_cast<double>(members.size());

    order.clear();
    if (has_fixed) {
      for (int i : members)
        if (isFixed(i)) {
          order.push_back(i);
          visit(i);
        }
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
      if (cloud[seed].getNormalVector3fMap().cast<double>().dot(out) < 0.0) flip(cloud[seed]);
      order.push_back(seed);
      visit(seed);
    }
    while (!heap.empty()) {
      const Entry e = heap.top();
      heap.pop();
      if (visited[e.to]) continue;
      if (mirroredAgreement(cloud[e.from], cloud[e.to]) < 0.0) flip(cloud[e.to]);
      parent[e.to] = e.from;
      order.push_back(e.to);
      visit(e.to);
    }
    repairSubtrees(cloud, knn, k, order, parent, fixed, pos);
    if (!has_fixed) {
      // The seed alone decides little when it sits on noise; the majority decides (closed
      // surfaces: outward).
      double mean = 0.0;
      for (int i : members)
        mean += (cloud[i].getVector3fMap().cast<double>() - c)
                    .dot(cloud[i].getNormalVector3fMap().cast<double>());
      if (mean < 0.0)
        for (int i : members) flip(cloud[i]);
    }
  }
}

int graphK(int k, std::size_t n) { return std::min<int>(std::max(k, 3) + 1, static_cast<int>(n)); }

}  // namespace

void orientNormals(PointCloudSequence::Cloud& cloud, int k, const std::vector<char>& fixed) {
  const std::size_t n = cloud.size();
  if (n == 0) return;
  if (!fixed.empty() && fixed.size() != n)
    throw Error("orientNormals: the fixed mask does not match the cloud");
  const int kk = graphK(k, n);
  orientWithGraph(cloud, nearestNeighbours(cloud, kk), kk, fixed);
}

void estimateNormals(PointCloudSequence::Cloud& cloud, int k, const std::vector<char>& known) {
  const std::size_t n = cloud.size();
  if (n == 0) return;
  if (!known.empty() && known.size() != n)
    throw Error("estimateNormals: the known mask does not match the cloud");
  std::vector<int> todo;
  for (std::size_t i = 0; i < n; ++i)
    if (known.empty() || !known[i]) todo.push_back(static_cast<int>(i));
  if (todo.empty()) return;
  if (n < 3) throw Error("cannot estimate normals from fewer than 3 points");

  // The k nearest neighbours (the point itself included, as pcl::NormalEstimation does) give the
  // PCA normal; the same search, one wider, gives the orientation graph.
  const int kn = std::min<int>(std::max(k, 3), static_cast<int>(n));
  const int kk = graphK(k, n);
  const std::vector<int> knn = nearestNeighbours(cloud, kk);
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (const auto& p : cloud) c += p.getVector3fMap().cast<double>();
  c /= static_cast<double>(n);
  const int nt = static_cast<int>(todo.size());
#pragma omp parallel
  {
    pcl::Indices nb;
    Eigen::Matrix3f cov;
    Eigen::Vector4f centroid;
#pragma omp for schedule(static)
    for (int a = 0; a < nt; ++a) {
      const int i = todo[a];
      nb.clear();
      for (int b = 0; b < kn; ++b) {
        const int j = knn[static_cast<std::size_t>(i) * kk + b];
        if (j >= 0) nb.push_back(j);
      }
      auto& p = cloud[i];
      float nx = NAN, ny = NAN, nz = NAN, curv = 0.0f;
      // The same PCA as pcl::NormalEstimation::computePointNormal (smallest eigenvector).
      if (nb.size() >= 3 && pcl::computeMeanAndCovarianceMatrix(cloud, nb, cov, centroid) > 0)
        pcl::solvePlaneParameters(cov, nx, ny, nz, curv);
      p.normal_x = nx;
      p.normal_y = ny;
      p.normal_z = nz;
      p.curvature = std::isfinite(curv) ? curv : 0.0f;
      if (!finiteNormal(p) || p.getNormalVector3fMap().squaredNorm() < 1e-12f) {
        // A degenerate neighbourhood (duplicates, a line): any direction is as good as another;
        // the radial one at least orients sensibly.
        Eigen::Vector3d r = p.getVector3fMap().cast<double>() - c;
        if (r.norm() < 1e-12) r = Eigen::Vector3d::UnitZ();
        setNormal(p, r.normalized());
      }
    }
  }
  orientWithGraph(cloud, knn, kk, known);
}

}  // namespace io
}  // namespace pcl_animseg
