#include <pcl_animseg/error.h>
#include <pcl_animseg/features/scale_space.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>
#include <sstream>

namespace pcl_animseg {
namespace {

using Cloud = PointCloudSequence::Cloud;

bool validNormal(const pcl::PointNormal& p) {
  const Eigen::Vector3f n = p.getNormalVector3fMap();
  return n.allFinite() && n.squaredNorm() > 0.25f;
}

/** One weighted-plane MLS projection of every point of `src` (the diffusion step). `limit[j]` is
 * how many entries of row j are inside the step's support, `weights` the Gaussian weights of the
 * rows' entries (from the input distances), `ref` the normals whose orientation to keep. */
void projectOnce(const Cloud& src, const Neighbourhoods& nb, const std::vector<int>& limit,
                 const std::vector<float>& weights, const std::vector<Eigen::Vector3f>& ref,
                 bool exact, Cloud& dst) {
  const long n = static_cast<long>(src.size());
#pragma omp parallel for schedule(dynamic, 512)
  for (long jl = 0; jl < n; ++jl) {
    const std::size_t j = static_cast<std::size_t>(jl);
    const Eigen::Vector3f xj = src[j].getVector3fMap();
    const int* row = nb.row(j);
    const float* w = weights.data() + nb.offsets[j];
    const int m = limit[j];
    // Moments in float, relative to x_j (so that positions far from the origin lose no
    // precision; the offsets are a few spacings, a few dozen terms): the upper triangle only.
    // The double 3x3 outer products were most of a diffusion step.
    float sw_f = 0.0f, sx = 0.0f, sy = 0.0f, sz = 0.0f;
    float sxx = 0.0f, sxy = 0.0f, sxz = 0.0f, syy = 0.0f, syz = 0.0f, szz = 0.0f;
    for (int a = 0; a < m; ++a) {
      const float* q = src[row[a]].data;
      const float dx = q[0] - xj.x(), dy = q[1] - xj.y(), dz = q[2] - xj.z();
      const float wa = w[a];
      sw_f += wa;
      const float wx = wa * dx, wy = wa * dy, wz = wa * dz;
      sx += wx;
      sy += wy;
      sz += wz;
      sxx += wx * dx;
      sxy += wx * dy;
      sxz += wx * dz;
      syy += wy * dy;
      syz += wy * dz;
      szz += wz * dz;
    }
    const double sw = sw_f;
    const Eigen::Vector3d s1(sx, sy, sz);
    Eigen::Matrix3d s2;
    s2 << sxx, sxy, sxz, sxy, syy, syz, sxz, syz, szz;
    pcl::PointNormal& out = dst[j];
    out = src[j];
    Eigen::Vector3f nref = ref[j];
    bool projected = false;
    if (m >= 3 && sw > 0.0) {
      const double inv_sw = 1.0 / sw;
      const Eigen::Vector3d c = s1 * inv_sw;
      const Eigen::Matrix3d cov = s2 * inv_sw - c * c.transpose();
      const double tr = cov.trace();
      Eigen::Vector3d nn;
      double lmin = 0.0;
      bool ok = tr > 0.0;
      if (ok && exact) {
        Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
        es.computeDirect(cov);
        const Eigen::Vector3d ev = es.eigenvalues();
        // A plane needs two clearly non-zero spreads; on a line or a single spot keep the point.
        ok = ev(1) > 1e-10 * std::max(ev(2), 1e-300) && ev(2) > 0.0;
        nn = es.eigenvectors().col(0);
        lmin = ev(0);
      } else if (ok) {
        // Diffusion steps after the first: the normal moves little per step, so a few power
        // iterations on tr(C) I - C from the previous normal replace a full eigensolver (which
        // was most of the scale space's time); errors do not accumulate since each step
        // restarts from the last estimate.
        // M = I - C / tr has eigenvalues in [0, 1] with the largest >= 2/3, so the iterates
        // neither overflow nor underflow and one normalisation at the end suffices (divisions
        // and square roots per iteration were the step's bottleneck).
        const Eigen::Matrix3d M = Eigen::Matrix3d::Identity() - cov * (1.0 / tr);
        nn = nref.cast<double>();
        for (int it = 0; it < 4; ++it) nn = M * nn;
        nn.normalize();
        lmin = nn.dot(cov * nn);
        const double rest = tr - lmin;  // spread in the plane: must not be a line or a spot
        const Eigen::Vector3d a = nn.unitOrthogonal(), b = nn.cross(a);
        const double caa = a.dot(cov * a), cbb = b.dot(cov * b), cab = a.dot(cov * b);
        ok = rest > 0.0 && (caa * cbb - cab * cab) > 1e-10 * rest * rest && nn.allFinite();
      }
      if (ok) {
        if (nn.cast<float>().dot(nref) < 0.0f) nn = -nn;
        const Eigen::Vector3f x = xj + (c.dot(nn) * nn).cast<float>();
        out.getVector3fMap() = x;
        out.getNormalVector3fMap() = nn.normalized().cast<float>();
        out.curvature = static_cast<float>(lmin / tr);
        projected = true;
      }
    }
    if (!projected) {
      out.getNormalVector3fMap() = nref;
      out.curvature = 0.0f;
    }
  }
}

}  // namespace

std::vector<int> MLSScaleSpace::projectionCounts() const {
  std::vector<int> counts;
  int last = 0;
  for (int i = 0; i < levels_; ++i) {
    const int c = std::max(last + 1, static_cast<int>(std::lround(std::pow(k_, 2.0 * i))));
    counts.push_back(c);
    last = c;
  }
  return counts;
}

ScaleSpacePlan MLSScaleSpace::plan() const {
  ScaleSpacePlan plan;
  if (!input_) throw Error("MLSScaleSpace: no input cloud set");
  if (!(h_ > 0.0) || !std::isfinite(h_))
    throw Error("scale space: h must be a positive number of point spacings (got " +
                std::to_string(h_) + ")");
  if (!(k_ > 1.0) || !std::isfinite(k_) || k_ > 4.0)
    throw Error("scale space: the scale factor k must be in (1, 4] (got " + std::to_string(k_) +
                ")");
  if (levels_ < 1 || levels_ > 12)
    throw Error("scale space: the number of levels must be in 1..12 (got " +
                std::to_string(levels_) + ")");
  const Cloud& in = *input_;
  const std::size_t n = in.size();
  if (n < getMinPoints())
    throw Error("frame has " + std::to_string(n) + " points; the scale space needs at least " +
                std::to_string(getMinPoints()));
  for (const auto& p : in.points)
    if (!p.getVector3fMap().allFinite())
      throw Error("frame has a point with a NaN/Inf coordinate; drop such points when loading");

  const double spacing = spacing_ > 0.0 ? spacing_ : featureSpacing(in);
  const std::vector<int> counts = projectionCounts();
  const double h0 = h_ * spacing;
  const double hmax = h0 * std::sqrt(static_cast<double>(counts.back()));
  const double diag = boundingBoxDiagonal(in);
  if (2.0 * hmax > 0.5 * diag) {
    std::ostringstream os;
    os << "frame is too small for the chosen scales: the largest scale disc (2 h_max = "
       << 2.0 * hmax / spacing << " spacings) exceeds half the frame's extent ("
       << 0.5 * diag / spacing << " spacings, " << n
       << " points); lower the scale h, the factor k or the number of levels";
    throw Error(os.str());
  }

  plan.spacing = spacing;
  plan.h0 = h0;
  plan.step_radius = static_cast<float>(2.0 * h0);
  // 3 h0 at least: the keypoint tests (angular gap, quadratic fit of D) need ~30 neighbours even
  // on sparse random samples; a smaller row gives false open borders.
  plan.radius =
      std::max(static_cast<float>(3.0 * h0), static_cast<float>(neighbourhood_radius_ * spacing));
  plan.inv_h2 = static_cast<float>(1.0 / (h0 * h0));
  plan.counts = counts;
  for (int c : counts) plan.scales.push_back(h0 * std::sqrt(static_cast<double>(c)));

  // Orientation reference for level 0: the input normals; missing ones point away from the
  // centroid (documented fall-back, right for closed shapes).
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  for (const auto& p : in.points) centroid += p.getVector3fMap().cast<double>();
  centroid /= static_cast<double>(n);
  std::vector<Eigen::Vector3f>& ref = plan.ref;
  ref.resize(n);
  for (std::size_t j = 0; j < n; ++j) {
    if (validNormal(in[j])) {
      ref[j] = in[j].getNormalVector3fMap().normalized();
    } else {
      Eigen::Vector3f d = in[j].getVector3fMap() - centroid.cast<float>();
      ref[j] = d.squaredNorm() > 0.0f ? d.normalized() : Eigen::Vector3f::UnitZ();
    }
  }

  return plan;
}

void MLSScaleSpace::compute(ScaleSpace& output) const {
  ScaleSpacePlan plan = this->plan();
  const Cloud& in = *input_;
  const std::size_t n = in.size();
  const float step_radius = plan.step_radius;
  auto nb = std::make_shared<Neighbourhoods>(radiusNeighbourhoods(in, plan.radius));

  // Support and Gaussian weights of one projection step, from the input distances (points move
  // along their normals only, so these stay right to first order on every level).
  std::vector<int> limit(n);
  std::vector<float> weights(nb->indices.size());
  const float inv_h2 = plan.inv_h2;
  for (std::size_t j = 0; j < n; ++j) {
    limit[j] = nb->countWithin(j, step_radius);
    const float* d2 = nb->sqrRow(j);
    float* w = weights.data() + nb->offsets[j];
    for (int a = 0; a < nb->count(j); ++a) w[a] = std::exp(-d2[a] * inv_h2);
  }
  std::vector<Eigen::Vector3f>& ref = plan.ref;
  const std::vector<int>& counts = plan.counts;
  const double spacing = plan.spacing;
  const double h0 = plan.h0;

  output.spacing = spacing;
  output.input = input_;
  output.neighbourhoods = nb;
  output.scales.clear();
  output.levels.clear();
  Cloud::Ptr cur(new Cloud(in));
  int done = 0;
  for (int i = 0; i < levels_; ++i) {
    while (done < counts[i]) {
      Cloud::Ptr next(new Cloud(*cur));
      projectOnce(*cur, *nb, limit, weights, ref, done == 0, *next);
      for (std::size_t j = 0; j < n; ++j) ref[j] = (*next)[j].getNormalVector3fMap();
      cur = next;
      ++done;
    }
    output.levels.push_back(cur);
    output.scales.push_back(h0 * std::sqrt(static_cast<double>(counts[i])));
  }
}

}  // namespace pcl_animseg
