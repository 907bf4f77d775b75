#include <pcl_animseg/error.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>

#include <Eigen/Cholesky>

#include <omp.h>

#include <algorithm>
#include <cmath>

namespace pcl_animseg {
namespace {

/** A unit vector orthogonal to n, chosen from n alone (so the local frame is reproducible). */
Eigen::Vector3f someOrthogonal(const Eigen::Vector3f& n) {
  Eigen::Vector3f e = Eigen::Vector3f::Zero();
  int a = 0;
  n.cwiseAbs().minCoeff(&a);
  e(a) = 1.0f;
  return n.cross(e).normalized();
}

struct Candidate {
  int level;
  int index;
  bool maximum;
};

}  // namespace

std::vector<std::vector<float>> DoGKeypoint::normalDifferences(const ScaleSpace& ss) {
  std::vector<std::vector<float>> d;
  if (ss.levels.size() < 2) return d;
  const std::size_t n = ss.levels[0]->size();
  for (std::size_t i = 0; i + 1 < ss.levels.size(); ++i) {
    const auto& a = *ss.levels[i];
    const auto& b = *ss.levels[i + 1];
    const float inv_h = static_cast<float>(1.0 / ss.scales[i]);
    std::vector<float> di(n);
    for (std::size_t j = 0; j < n; ++j)
      di[j] = a[j].getNormalVector3fMap().dot(b[j].getVector3fMap() - a[j].getVector3fMap()) *
              inv_h;
    d.push_back(std::move(di));
  }
  return d;
}

void DoGKeypoint::compute(KeypointCloud& keypoints) const {
  const ScaleSpace& ss = scale_space_;
  keypoints.clear();
  if (ss.levels.size() < 4 || !ss.neighbourhoods || !ss.input)
    throw Error("DoG keypoints need a scale space of at least 4 levels (got " +
                std::to_string(ss.levels.size()) + ")");
  if (!(edge_ratio_ > 1.0)) throw Error("DoG keypoints: the edge ratio r must be > 1");
  const Neighbourhoods& nb = *ss.neighbourhoods;
  // Contrast of each level relative to its median: the surface's overall curvature gives every
  // point a D of the same sign that grows with the scale (-0.03 at the top level of the unit
  // sphere), so that with an absolute threshold the top level's noise-level extrema all pass.
  // The median is the typical response of the frame at that scale (unchanged by rigid motion,
  // uniform scaling and resampling); features are what stands out of it.
  auto D = normalDifferences(ss);
  for (auto& d : D) {
    std::vector<float> tmp(d);
    std::nth_element(tmp.begin(), tmp.begin() + tmp.size() / 2, tmp.end());
    const float med = tmp[tmp.size() / 2];
    for (float& x : d) x -= med;
  }
  const std::size_t n = ss.levels[0]->size();
  const int nlev = static_cast<int>(D.size());
  const float ext_radius = static_cast<float>(2.0 * ss.scales[0]);
  const float min_resp = static_cast<float>(min_response_);

  // 1. Scale-space extrema (parallel over points; each thread keeps its own list).
  std::vector<std::vector<Candidate>> parts;
#pragma omp parallel
  {
#pragma omp single
    parts.resize(omp_get_num_threads());
    auto& mine = parts[omp_get_thread_num()];
#pragma omp for schedule(static)
    for (long jl = 0; jl < static_cast<long>(n); ++jl) {
      const std::size_t j = static_cast<std::size_t>(jl);
      const int m = nb.countWithin(j, ext_radius);
      const int* row = nb.row(j);
      // Levels 1 .. L-1; the top one is compared with the level below only. D varies slowly
      // with the scale (a bump's D differs by a few percent over the searched range), so the
      // scale at which a feature peaks is decided by sampling noise: with the top level left
      // out, a feature whose peak fell there in one sampling and one level lower in another was
      // found in one frame only (a quarter of the keypoints did not repeat for this reason).
      // Level 0 (h0) stays out: its extrema are mostly sampling noise.
      for (int i = 1; i < nlev; ++i) {
        const float v = D[i][j];
        if (!(std::fabs(v) >= min_resp)) continue;
        bool is_max = true, is_min = true;
        for (int l = i - 1; l <= std::min(i + 1, nlev - 1) && (is_max || is_min); ++l) {
          for (int a = 0; a < m; ++a) {
            const int q = row[a];
            if (l == i && q == static_cast<int>(j)) continue;
            const float w = D[l][q];
            // Ties go to the lower index (duplicates), and the same point on the other levels
            // must be strictly beaten.
            const bool tie_win = (l == i) && q > static_cast<int>(j);
            if (!(v > w || (v == w && tie_win))) is_max = false;
            if (!(v < w || (v == w && tie_win))) is_min = false;
            if (!is_max && !is_min) break;
          }
        }
        if (is_max || is_min) mine.push_back({i, static_cast<int>(j), is_max});
      }
    }
  }
  std::vector<Candidate> cand;
  for (auto& p : parts) cand.insert(cand.end(), p.begin(), p.end());
  std::sort(cand.begin(), cand.end(), [](const Candidate& a, const Candidate& b) {
    return a.level != b.level ? a.level < b.level : a.index < b.index;
  });

  // 2. Boundary, edge and localisation tests per candidate.
  const auto& L0 = *ss.levels[0];
  const auto& in = *ss.input;
  const double edge_limit = (edge_ratio_ + 1.0) * (edge_ratio_ + 1.0) / edge_ratio_;
  std::vector<char> keep(cand.size(), 0);
  std::vector<PointKeypoint> found(cand.size());
#pragma omp parallel
  {
    std::vector<float> angles;
#pragma omp for schedule(dynamic, 16)
    for (long cl = 0; cl < static_cast<long>(cand.size()); ++cl) {
      const Candidate c = cand[cl];
      const std::size_t j = static_cast<std::size_t>(c.index);
      const Eigen::Vector3f p = L0[j].getVector3fMap();
      const Eigen::Vector3f nrm = L0[j].getNormalVector3fMap();
      const Eigen::Vector3f u = someOrthogonal(nrm);
      const Eigen::Vector3f v = nrm.cross(u);
      const int* row = nb.row(j);
      const int m = nb.count(j);
      const float eps = static_cast<float>(1e-6 * ss.spacing);

      // Open border: a large empty sector among the neighbours of the point (gap > boundary
      // angle), or a neighbour that is itself on the border (gap > 3/4 pi, strict enough that
      // random interior samples almost never pass): D is distorted up to a disc from the border.
      auto gapAt = [&](std::size_t c0) {
        const Eigen::Vector3f nc = L0[c0].getNormalVector3fMap();
        const Eigen::Vector3f uc = someOrthogonal(nc);
        const Eigen::Vector3f vc = nc.cross(uc);
        const int* rc = nb.row(c0);
        angles.clear();
        for (int a = 0; a < nb.count(c0); ++a) {
          const Eigen::Vector3f d = in[rc[a]].getVector3fMap() - in[c0].getVector3fMap();
          const float x = d.dot(uc), y = d.dot(vc);
          if (x * x + y * y > eps * eps) angles.push_back(std::atan2(y, x));
        }
        if (angles.size() < 5) return static_cast<float>(2.0 * M_PI);
        std::sort(angles.begin(), angles.end());
        float gap = angles.front() + 2.0f * static_cast<float>(M_PI) - angles.back();
        for (std::size_t a = 1; a < angles.size(); ++a)
          gap = std::max(gap, angles[a] - angles[a - 1]);
        return gap;
      };
      if (gapAt(j) > boundary_angle_) continue;
      bool border = false;
      for (int a = 1; a < m && !border; ++a)
        border = gapAt(static_cast<std::size_t>(row[a])) > 0.75 * M_PI;
      if (border) continue;

      // Quadratic fit in the tangent plane (coordinates in units of h_i) of the next coarser
      // difference D_{i+1} (D_i itself at the top level): its sampling noise is lower and the
      // sub-sample position it gives is ~20% closer to the feature's centre than D_i's on
      // randomly sampled surfaces; a feature's extremum is at the same place on both levels.
      const double hi = ss.scales[c.level];
      const float inv_h = static_cast<float>(1.0 / hi);
      Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
      Eigen::Matrix<double, 6, 1> rhs = Eigen::Matrix<double, 6, 1>::Zero();
      const std::vector<float>& Di = D[std::min(c.level + 1, nlev - 1)];
      for (int a = 0; a < m; ++a) {
        const int q = row[a];
        const Eigen::Vector3f d = (L0[q].getVector3fMap() - p) * inv_h;
        const double x = d.dot(u), y = d.dot(v);
        const double w = std::exp(-(x * x + y * y));
        Eigen::Matrix<double, 6, 1> phi;
        phi << 1.0, x, y, x * x, x * y, y * y;
        A.noalias() += w * phi * phi.transpose();
        rhs.noalias() += w * Di[q] * phi;
      }
      A.diagonal().array() += 1e-9 * A(0, 0);
      Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(A);
      if (ldlt.info() != Eigen::Success) continue;
      const Eigen::Matrix<double, 6, 1> co = ldlt.solve(rhs);
      if (!co.allFinite()) continue;
      Eigen::Matrix2d H;
      H << 2.0 * co(3), co(4), co(4), 2.0 * co(5);
      const Eigen::Vector2d g(co(1), co(2));
      const double det = H.determinant(), tr = H.trace();
      const bool is_max = c.maximum;
      if (!(det > 0.0) || (is_max ? tr >= 0.0 : tr <= 0.0)) continue;
      if (tr * tr / det >= edge_limit) continue;
      const Eigen::Vector2d off = -H.inverse() * g;
      if (!(off.norm() * hi <= ext_radius)) continue;
      const double resp = D[c.level][j];

      PointKeypoint& k = found[cl];
      k.getVector3fMap() = in[j].getVector3fMap() +
                           static_cast<float>(hi) * (static_cast<float>(off(0)) * u +
                                                     static_cast<float>(off(1)) * v);
      k.data[3] = 1.0f;
      k.scale = static_cast<float>(hi);
      k.response = static_cast<float>(resp);
      k.index = c.index;
      k.level = c.level;
      keep[cl] = 1;
    }
  }
  // One keypoint per feature: a keypoint closer than 2 h_0 to a stronger one (any level) is
  // the same feature seen on another level, or a noise extremum on its flank; keeping both
  // would only add keypoints that do not repeat.
  {
    std::vector<std::size_t> order;
    for (std::size_t a = 0; a < cand.size(); ++a)
      if (keep[a]) order.push_back(a);
    std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
      return std::fabs(found[a].response) > std::fabs(found[b].response);
    });
    std::vector<std::size_t> kept;
    for (std::size_t a : order) {
      for (std::size_t b : kept)
        if ((found[a].getVector3fMap() - found[b].getVector3fMap()).norm() < ext_radius) {
          keep[a] = 0;
          break;
        }
      if (keep[a]) kept.push_back(a);
    }
  }
  for (std::size_t a = 0; a < cand.size(); ++a)
    if (keep[a]) keypoints.push_back(found[a]);
  keypoints.width = static_cast<std::uint32_t>(keypoints.size());
  keypoints.height = 1;
  keypoints.is_dense = true;
}

}  // namespace pcl_animseg
