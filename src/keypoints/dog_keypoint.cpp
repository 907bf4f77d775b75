#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/keypoints/dog_refinement.h>

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <limits>

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

/** The largest angular gap among the points near point c, projected on its level-0 tangent
 * plane: its neighbours (within `ring`), or with two_rings theirs too. `ids` and `angles` are
 * scratch space. */
float angularGap(const ScaleSpace& ss, std::size_t c, float ring, bool two_rings,
                 std::vector<int>& ids, std::vector<float>& angles) {
  const Neighbourhoods& nb = *ss.neighbourhoods;
  const auto& in = *ss.input;
  const float eps = static_cast<float>(1e-6 * ss.spacing);
  const Eigen::Vector3f nc = ss.levels[0]->points[c].getNormalVector3fMap();
  const Eigen::Vector3f uc = someOrthogonal(nc);
  const Eigen::Vector3f vc = nc.cross(uc);
  const int* row = nb.row(c);
  const int m = nb.countWithin(c, ring);
  ids.assign(row, row + m);
  if (two_rings) {
    for (int a = 1; a < m; ++a) {
      const int* rq = nb.row(row[a]);
      ids.insert(ids.end(), rq, rq + nb.countWithin(row[a], ring));
    }
    std::sort(ids.begin(), ids.end());
    ids.erase(std::unique(ids.begin(), ids.end()), ids.end());
  }
  angles.clear();
  for (int q : ids) {
    const Eigen::Vector3f d = in[q].getVector3fMap() - in[c].getVector3fMap();
    const float x = d.dot(uc), y = d.dot(vc);
    if (x * x + y * y > eps * eps) angles.push_back(std::atan2(y, x));
  }
  if (angles.size() < 5) return static_cast<float>(2.0 * M_PI);
  std::sort(angles.begin(), angles.end());
  float gap = angles.front() + 2.0f * static_cast<float>(M_PI) - angles.back();
  for (std::size_t a = 1; a < angles.size(); ++a) gap = std::max(gap, angles[a] - angles[a - 1]);
  return gap;
}

/** Whether point j is within one row of an open border: it or one of its neighbours is on the
 * border, i.e. leaves an angular gap larger than `angle` among its neighbours and still among
 * the points within two rows. The second test is only made when the first finds a gap; without it,
 * the ~25 neighbours of a random interior sample leave such a gap often enough that 1 keypoint
 * in 20 was lost on closed surfaces, while a point on the border sees the same empty half-plane
 * at every distance. */
bool nearOpenBorder(const ScaleSpace& ss, std::size_t j, float ring, double angle,
                    std::vector<int>& ids, std::vector<float>& angles) {
  const Neighbourhoods& nb = *ss.neighbourhoods;
  const int* row = nb.row(j);
  const int m = nb.countWithin(j, ring);
  std::vector<int> mine(row, row + m);  // ids is overwritten below
  for (int q : mine) {
    const std::size_t c = static_cast<std::size_t>(q);
    if (angularGap(ss, c, ring, false, ids, angles) > angle &&
        angularGap(ss, c, ring, true, ids, angles) > angle)
      return true;
  }
  return false;
}

// Sub-sample localisation (see dog_keypoint.h): its constants are shared with the device.
using dog_refinement::kAreaPasses;
using dog_refinement::kConverged;
using dog_refinement::kDiscRadius;
using dog_refinement::kInnerScale;
using dog_refinement::kNewtonSteps;
using dog_refinement::kOuterScale;

/** Step 3 of refinePositions for one keypoint: Newton steps on R(y) = (z_b(y) - z_a(y)) / h_a,
 * where z_s(y) is the height above y, along the keypoint's normal at the coarsest level, of the
 * area-weighted local linear fit of the input points with a Gaussian of width s (the samples
 * themselves, exact, rather than the diffused levels; the linear fit removes the effect of an
 * unbalanced sample on a slope). Each step fits a quadratic to R on a 3 x 3 grid around the
 * estimate. `local` holds the disc's n samples (tangent a, b, height, area: 4 floats each); y
 * the extremum from x0 along (uu, vv). False when it moved more than 3 h0 from the detected
 * point pj. A device runs the same steps (gpu/src/features_kernels.cu: refineKernel). */
bool newtonSteps(const float* local, std::size_t n, float scale, bool is_max, double h0,
                 const Eigen::Vector3f& x0, const Eigen::Vector3f& uu, const Eigen::Vector3f& vv,
                 const Eigen::Vector3f& pj, Eigen::Vector2f& y) {
  const double ha = kInnerScale * scale, hb = kOuterScale * scale;
  const float inv_b2 = static_cast<float>(1.0 / (hb * hb));  // 1 / h_a^2 = 4 / h_b^2
  const float max_shift = static_cast<float>(3.0 * h0);
  // Intercept of the weighted linear fit z ~ c0 + c1 a + c2 b from its moments.
  auto intercept = [](const double* m) {
    // m: w, wa, wb, waa, wab, wbb, wz, waz, wbz
    Eigen::Matrix3d M;
    M << m[0], m[1], m[2], m[1], m[3], m[4], m[2], m[4], m[5];
    return M.ldlt().solve(Eigen::Vector3d(m[6], m[7], m[8]))(0);
  };
  // R at the 3 x 3 grid y + (gx, gy) step, in one pass over the disc: the Gaussian factors
  // into exp(-|d|^2 / h_b^2) exp(2 gx step d_a / h_b^2) exp(2 gy step d_b / h_b^2)
  // exp(-(gx^2 + gy^2) step^2 / h_b^2), three exponentials per point instead of nine.
  const double inv_hb = 1.0 / hb;
  auto gridR = [&](const Eigen::Vector2f& at, float step, double* val) {
    double mom[9][2][9] = {};
    const float c = std::exp(-step * step * inv_b2);
    for (std::size_t s = 0; s < n; ++s) {
      const float* l = local + 4 * s;
      const float da = l[0] - at(0), db = l[1] - at(1), z = l[2];
      const float base = std::exp(-(da * da + db * db + z * z) * inv_b2) * l[3];
      const float ex = std::exp(2.0f * step * da * inv_b2),
                  ey = std::exp(2.0f * step * db * inv_b2);
      const float fx[3] = {c / ex, 1.0f, c * ex}, fy[3] = {c / ey, 1.0f, c * ey};
      for (int gx = 0; gx < 3; ++gx)
        for (int gy = 0; gy < 3; ++gy) {
          const float eb = base * fx[gx] * fy[gy];
          const float r = eb / l[3], r2 = r * r;  // the inner Gaussian is the outer one ^4
          const float ea = r2 * r2 * l[3];
          const double a = (da - (gx - 1) * step) * inv_hb, b = (db - (gy - 1) * step) * inv_hb;
          const double t[9] = {1.0, a, b, a * a, a * b, b * b, z, a * z, b * z};
          double* mb = mom[3 * gx + gy][0];
          double* ma = mom[3 * gx + gy][1];
          for (int i = 0; i < 9; ++i) {
            mb[i] += eb * t[i];
            ma[i] += ea * t[i];
          }
        }
    }
    for (int g = 0; g < 9; ++g) val[g] = (intercept(mom[g][0]) - intercept(mom[g][1])) / ha;
  };
  y = Eigen::Vector2f::Zero();
  float step = static_cast<float>(0.5 * h0);
  bool ok = true;
  for (int it = 0; it < kNewtonSteps && ok; ++it) {
    Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> rhs = Eigen::Matrix<double, 6, 1>::Zero();
    double val[9];
    gridR(y, step, val);
    for (int gx = -1; gx <= 1; ++gx)
      for (int gy = -1; gy <= 1; ++gy) {
        Eigen::Matrix<double, 6, 1> phi;
        phi << 1.0, gx, gy, gx * gx, gx * gy, gy * gy;
        A.noalias() += phi * phi.transpose();
        rhs.noalias() += val[3 * (gx + 1) + (gy + 1)] * phi;
      }
    const Eigen::Matrix<double, 6, 1> co = A.ldlt().solve(rhs);
    if (!co.allFinite()) break;  // degenerate disc: keep the fitted position
    Eigen::Matrix2d H;
    H << 2.0 * co(3), co(4), co(4), 2.0 * co(5);
    const Eigen::Vector2d g(co(1), co(2));
    Eigen::Vector2d st;
    if (H.determinant() > 0.0 && (is_max ? H.trace() < 0.0 : H.trace() > 0.0))
      st = -H.inverse() * g;
    else if (g.norm() > 0.0)
      st = (is_max ? 1.0 : -1.0) * g.normalized();  // not yet near the extremum: walk uphill
    else
      break;
    if (st.norm() > 1.5) st *= 1.5 / st.norm();
    y += step * st.cast<float>();
    ok = (x0 + y(0) * uu + y(1) * vv - pj).norm() <= max_shift;
    if (step * st.norm() < kConverged * h0) break;
    if (st.norm() < 0.5) step *= 0.5f;
  }
  return ok;
}

/** Moves each keypoint in `which` to the extremum of a direct, area-weighted evaluation of the
 * normal difference around it and sets its index to the nearest frame point; clears keep[] for
 * those whose extremum lies farther than 3 h0 from their point or near an open border. */
void refinePositions(const ScaleSpace& ss, const std::vector<Candidate>& cand,
                     const std::vector<std::size_t>& which, double border_gap,
                     const KeypointRefineDevice* device, std::vector<PointKeypoint>& found,
                     std::vector<char>& keep) {
  if (which.empty()) return;
  const Neighbourhoods& nb = *ss.neighbourhoods;
  const auto& in = *ss.input;
  const auto& top = *ss.levels.back();
  const std::size_t n = in.size();
  const double h0 = ss.scales[0];
  const float ring = static_cast<float>(3.0 * h0);
  // Entries of row q within the ring (the whole row unless a later stage asked for wider ones).
  const bool whole_rows = nb.radius <= ring;
  auto ringCount = [&](int q) { return whole_rows ? nb.count(q) : nb.countWithin(q, ring); };

  // 1. The samples around each keypoint: breadth first over the rows, within kDiscRadius outer
  //    scales of its fitted position.
  const long nk = static_cast<long>(which.size());
  std::vector<std::vector<int>> discs(which.size());
#pragma omp parallel
  {
    std::vector<int> stamp;
#pragma omp for schedule(dynamic, 1)
    for (long k = 0; k < nk; ++k) {
      if (stamp.empty()) stamp.assign(n, -1);
      const PointKeypoint& kp = found[which[k]];
      const Eigen::Vector3f x0 = kp.getVector3fMap();
      const float reach = static_cast<float>(kDiscRadius * kOuterScale * kp.scale);
      const float reach2 = reach * reach;
      std::vector<int>& disc = discs[k];
      disc.push_back(kp.index);
      stamp[kp.index] = static_cast<int>(k);
      for (std::size_t pos = 0; pos < disc.size(); ++pos) {
        const int q = disc[pos];
        const int* row = nb.row(q);
        const int m = ringCount(q);
        for (int a = 0; a < m; ++a) {
          const int r = row[a];
          if (stamp[r] == static_cast<int>(k) ||
              (in[r].getVector3fMap() - x0).squaredNorm() > reach2)
            continue;
          stamp[r] = static_cast<int>(k);
          disc.push_back(r);
        }
      }
    }
  }

  // 2. Area weights: a random sample puts more points in some places than in others, and a
  //    plain kernel average over it is dominated by that noise. Each sample gets a weight a
  //    such that the a-weighted kernel density is about uniform: from a = 1, kAreaPasses times
  //    a <- a / (K a) with K(d) = (1 - d^2 / (3 h0)^2)^4 over the rows (a kernel-balanced
  //    estimate of each sample's share of the surface; this compact kernel, about a Gaussian of
  //    width 1.5 h0, did better than that Gaussian, and 3 passes better than 2). Only where the
  //    discs need it: pass p is evaluated on the discs dilated by kAreaPasses - p rows.
  std::vector<char> need(n, 0);
  std::vector<std::vector<int>> lists(kAreaPasses);
  for (const auto& disc : discs)
    for (int q : disc)
      if (!need[q]) {
        need[q] = kAreaPasses;
        lists[kAreaPasses - 1].push_back(q);
      }
  for (int p = kAreaPasses - 1; p > 0; --p)
    for (int s = p; s < kAreaPasses; ++s)
      for (int q : lists[s]) {
        const int* row = nb.row(q);
        const int m = ringCount(q);
        for (int a = 0; a < m; ++a)
          if (!need[row[a]]) {
            need[row[a]] = static_cast<char>(p);
            lists[p - 1].push_back(row[a]);
          }
      }
  // The kernel weights of the rows of those points, computed once for all passes.
  std::vector<int> all;
  for (int s = 0; s < kAreaPasses; ++s) all.insert(all.end(), lists[s].begin(), lists[s].end());
  std::vector<std::size_t> koff(all.size() + 1, 0);
  for (std::size_t t = 0; t < all.size(); ++t) koff[t + 1] = koff[t] + ringCount(all[t]);
  std::vector<float> kw(koff.back());
  const float inv_r2 = 1.0f / (ring * ring);
#pragma omp parallel for schedule(static)
  for (long t = 0; t < static_cast<long>(all.size()); ++t) {
    const float* d2 = nb.sqrRow(all[t]);
    for (std::size_t a = 0; a < koff[t + 1] - koff[t]; ++a) {
      const float s = std::max(0.0f, 1.0f - d2[a] * inv_r2), s2 = s * s;
      kw[koff[t] + a] = s2 * s2;
    }
  }
  std::vector<float> area(n, 1.0f), next(n, 1.0f);
  std::size_t first = 0;  // all[first ..] have need >= p
  for (int p = 1; p <= kAreaPasses; ++p) {
#pragma omp parallel for schedule(static)
    for (long t = static_cast<long>(first); t < static_cast<long>(all.size()); ++t) {
      const int* row = nb.row(all[t]);
      const float* w = kw.data() + koff[t];
      const int m = static_cast<int>(koff[t + 1] - koff[t]);
      float s = 0.0f;
      for (int a = 0; a < m; ++a) s += w[a] * area[row[a]];
      next[all[t]] = s > 0.0f ? area[all[t]] / s : area[all[t]];
    }
    for (std::size_t t = first; t < all.size(); ++t) area[all[t]] = next[all[t]];
    first += lists[p - 1].size();
  }

  // 3. Newton steps on R(y) = (z_b(y) - z_a(y)) / h_a (newtonSteps), on the cores or a device.
  //    The keypoint's frame: its normal at the coarsest level and two tangent axes.
  struct Frame {
    Eigen::Vector3f x0, uu, vv, nn;
  };
  std::vector<Frame> frames(which.size());
  for (long k = 0; k < nk; ++k) {
    const PointKeypoint& kp = found[which[k]];
    Frame& f = frames[k];
    f.nn = top[static_cast<std::size_t>(kp.index)].getNormalVector3fMap();
    f.uu = someOrthogonal(f.nn);
    f.vv = f.nn.cross(f.uu);
    f.x0 = kp.getVector3fMap();
  }
  // Tangent coordinates, height and area of keypoint k's disc samples, 4 floats each.
  auto localSamples = [&](long k, float* out) {
    const Frame& f = frames[k];
    for (int q : discs[k]) {
      const Eigen::Vector3f d = in[q].getVector3fMap() - f.x0;
      *out++ = d.dot(f.uu);
      *out++ = d.dot(f.vv);
      *out++ = d.dot(f.nn);
      *out++ = area[q];
    }
  };
  std::vector<Eigen::Vector2f> extremum(which.size(), Eigen::Vector2f::Zero());
  std::vector<char> within(which.size(), 1);
  if (device) {
    KeypointRefineJobs jobs;
    jobs.h0 = h0;
    jobs.disc_begin.assign(which.size() + 1, 0);
    for (long k = 0; k < nk; ++k)
      jobs.disc_begin[k + 1] = jobs.disc_begin[k] + static_cast<std::uint32_t>(discs[k].size());
    jobs.samples.resize(4 * static_cast<std::size_t>(jobs.disc_begin.back()));
    jobs.frames.resize(12 * which.size());
    jobs.scales.resize(which.size());
    jobs.maximum.resize(which.size());
#pragma omp parallel for schedule(dynamic, 4)
    for (long k = 0; k < nk; ++k) {
      localSamples(k, jobs.samples.data() + 4 * static_cast<std::size_t>(jobs.disc_begin[k]));
      const PointKeypoint& kp = found[which[k]];
      float* f = jobs.frames.data() + 12 * k;
      const Eigen::Vector3f pj = in[static_cast<std::size_t>(kp.index)].getVector3fMap();
      for (int c = 0; c < 3; ++c) {
        f[c] = frames[k].x0(c);
        f[3 + c] = frames[k].uu(c);
        f[6 + c] = frames[k].vv(c);
        f[9 + c] = pj(c);
      }
      jobs.scales[k] = kp.scale;
      jobs.maximum[k] = cand[which[k]].maximum ? 1 : 0;
    }
    device->refine(jobs);
    for (long k = 0; k < nk; ++k) {
      extremum[k] = Eigen::Vector2f(jobs.y[2 * k], jobs.y[2 * k + 1]);
      within[k] = jobs.ok[k];
    }
  } else {
#pragma omp parallel
    {
      std::vector<float> local;
#pragma omp for schedule(dynamic, 1)
      for (long k = 0; k < nk; ++k) {
        const PointKeypoint& kp = found[which[k]];
        local.resize(4 * discs[k].size());
        localSamples(k, local.data());
        const Eigen::Vector3f pj = in[static_cast<std::size_t>(kp.index)].getVector3fMap();
        within[k] = newtonSteps(local.data(), discs[k].size(), kp.scale, cand[which[k]].maximum, h0,
                                frames[k].x0, frames[k].uu, frames[k].vv, pj, extremum[k])
                        ? 1
                        : 0;
      }
    }
  }

  // 4. The extremum lies in the tangent plane of the coarsest level, which leaves the surface of
  //    a thin or strongly curved part: the position is put back onto the tangent plane (level
  //    0) of the frame point nearest to it, which becomes the keypoint's index.
#pragma omp parallel
  {
    std::vector<int> ids;
    std::vector<float> angles;
#pragma omp for schedule(dynamic, 1)
    for (long k = 0; k < nk; ++k) {
      const std::size_t idx = which[k];
      if (!within[k]) {
        keep[idx] = 0;
        continue;
      }
      PointKeypoint& kp = found[idx];
      const int j = kp.index;
      const Eigen::Vector2f& y = extremum[k];
      Eigen::Vector3f x = frames[k].x0 + y(0) * frames[k].uu + y(1) * frames[k].vv;
      float best = std::numeric_limits<float>::max();
      for (int q : discs[k]) {
        const float d2 = (in[q].getVector3fMap() - x).squaredNorm();
        if (d2 < best) {
          best = d2;
          kp.index = q;
        }
      }
      const Eigen::Vector3f nq = ss.levels[0]->points[kp.index].getNormalVector3fMap();
      x -= (x - in[kp.index].getVector3fMap()).dot(nq) * nq;
      kp.getVector3fMap() = x;
      // The extremum may have moved towards an open border (e.g. along a ridge that runs into it):
      // the border test again, at the new point.
      if (kp.index != j &&
          nearOpenBorder(ss, static_cast<std::size_t>(kp.index), ring, border_gap, ids, angles))
        keep[idx] = 0;
    }
  }
}

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
      di[j] =
          a[j].getNormalVector3fMap().dot(b[j].getVector3fMap() - a[j].getVector3fMap()) * inv_h;
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
  const float ring_radius = static_cast<float>(3.0 * ss.scales[0]);  // the rows' radius
  const double border_gap = boundary_angle_;
  const float min_resp = static_cast<float>(min_response_);

  // 1. Extrema of each level in space (parallel over points; each thread keeps its own list).
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
      // Levels 1 .. L-1 (level 0, h0, is mostly sampling noise). D varies slowly with the scale
      // (a bump's D differs by a few percent over the searched range), so whether D_i(j) also
      // beats the levels above and below is decided by sampling noise: with that test, features
      // found in one sampling were missed in the other (14% of the keypoints of a resampled copy
      // had no counterpart, 9% without it). Each level's extrema are kept instead and the scale
      // is chosen below, as the level of the strongest response among the keypoints of one
      // feature.
      for (int i = 1; i < nlev; ++i) {
        const float v = D[i][j];
        if (!(std::fabs(v) >= min_resp)) continue;
        bool is_max = true, is_min = true;
        for (int a = 0; a < m; ++a) {
          const int q = row[a];
          if (q == static_cast<int>(j)) continue;
          const float w = D[i][q];
          // Ties go to the lower index (duplicates).
          const bool tie_win = q > static_cast<int>(j);
          if (!(v > w || (v == w && tie_win))) is_max = false;
          if (!(v < w || (v == w && tie_win))) is_min = false;
          if (!is_max && !is_min) break;
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
    std::vector<int> ids;
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

      // Quadratic fit in the tangent plane (coordinates in units of h_i) of the next coarser
      // difference D_{i+1} (D_i itself at the top level): its sampling noise is lower and the
      // sub-sample position it gives is ~20% closer to the feature's centre than D_i's on
      // randomly sampled surfaces; a feature's extremum is at the same place on both levels.
      // This position only seeds refinePositions().
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

      // Open border (tested last, as the costliest test): D is distorted up to a disc from the
      // border.
      if (nearOpenBorder(ss, j, ring_radius, border_gap, ids, angles)) continue;

      const double resp = D[c.level][j];

      PointKeypoint& k = found[cl];
      k.getVector3fMap() = in[j].getVector3fMap() +
                           static_cast<float>(hi) *
                               (static_cast<float>(off(0)) * u + static_cast<float>(off(1)) * v);
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
  // would only add keypoints that do not repeat. Done on the fitted positions, and again on the
  // refined ones (two keypoints of one feature may converge there).
  auto suppress = [&]() {
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
    return kept;
  };
  const std::vector<std::size_t> kept = suppress();
  refinePositions(ss, cand, kept, border_gap, refine_device_, found, keep);
  suppress();
  for (std::size_t a = 0; a < cand.size(); ++a)
    if (keep[a]) keypoints.push_back(found[a]);
  keypoints.width = static_cast<std::uint32_t>(keypoints.size());
  keypoints.height = 1;
  keypoints.is_dense = true;
}

}  // namespace pcl_animseg
