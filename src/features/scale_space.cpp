#include <pcl_animseg/error.h>
#include <pcl_animseg/features/mls_projection.h>
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
  // Point q's position is the first three floats of src[q] (pcl::PointNormal: 12 floats a point).
  const float* xyz = reinterpret_cast<const float*>(src.points.data());
  constexpr int stride = sizeof(pcl::PointNormal) / sizeof(float);
#pragma omp parallel for schedule(dynamic, 512)
  for (long jl = 0; jl < n; ++jl) {
    const std::size_t j = static_cast<std::size_t>(jl);
    const float* w = weights.data() + nb.offsets[j];
    const mls::Projection r = mls::project(
        xyz, stride, static_cast<int>(j), nb.row(j), limit[j], [w](int a) { return w[a]; }, ref[j],
        exact);
    pcl::PointNormal& out = dst[j];
    out = src[j];
    out.getVector3fMap() = r.x;
    out.getNormalVector3fMap() = r.n;
    out.curvature = r.curvature;
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
  output.spacing = plan.spacing;
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
  }
  output.scales = plan.scales;
}

}  // namespace pcl_animseg
