#pragma once
// Test surfaces for the multi-scale features: a sphere with Gaussian bumps and dents (real
// extrema at several sizes), sampled uniformly by area with exact normals, and an open bumpy
// height field. Header-only, shared by test/features and test/keypoints.
#include <pcl_animseg/sequence.h>

#include <Eigen/Geometry>

#include <cmath>
#include <random>
#include <vector>

namespace pcl_animseg {
namespace test {

struct Bump {
  Eigen::Vector3d centre;  // unit direction
  double amplitude;
  double width;
};

inline std::vector<Bump> defaultBumps() {
  // Fixed, well separated directions (from a Fibonacci sphere), amplitudes and widths.
  std::vector<Bump> b;
  const int nb = 12;
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < nb; ++i) {
    const double y = 1.0 - 2.0 * (i + 0.5) / nb;
    const double r = std::sqrt(1.0 - y * y);
    const double th = golden * i;
    Eigen::Vector3d c(r * std::cos(th), y, r * std::sin(th));
    // Widths inside the scale range of the default scale space (2..8 spacings at ~10k points),
    // so that D has real extrema in scale; one in three is a dent.
    const double w = 0.06 + 0.015 * (i % 3);
    const double amp = ((i % 3 == 2) ? -0.7 : 0.8) * w;
    b.push_back({c.normalized(), amp, w});
  }
  return b;
}

/** Radius r(d) and its tangential gradient on the unit sphere. */
inline double bumpRadius(const std::vector<Bump>& bumps, const Eigen::Vector3d& d,
                         Eigen::Vector3d* grad) {
  double r = 1.0;
  Eigen::Vector3d g = Eigen::Vector3d::Zero();
  for (const Bump& b : bumps) {
    const Eigen::Vector3d e = d - b.centre;
    const double f = b.amplitude * std::exp(-e.squaredNorm() / (2.0 * b.width * b.width));
    r += f;
    g += -f * e / (b.width * b.width);
  }
  if (grad) *grad = g - g.dot(d) * d;
  return r;
}

/** N points uniform by area on the bumpy sphere, exact outward normals. */
inline PointCloudSequence::Cloud::Ptr bumpySphere(std::size_t n, unsigned seed,
                                                  const std::vector<Bump>& bumps = defaultBumps()) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> gauss(0.0, 1.0);
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  PointCloudSequence::Cloud::Ptr cloud(new PointCloudSequence::Cloud);
  // Area element of x = r(d) d relative to the unit sphere: r sqrt(r^2 + |grad r|^2).
  const double jmax = 1.6 * std::sqrt(1.6 * 1.6 + 4.0);
  while (cloud->size() < n) {
    Eigen::Vector3d d(gauss(rng), gauss(rng), gauss(rng));
    d.normalize();
    Eigen::Vector3d g;
    const double r = bumpRadius(bumps, d, &g);
    const double j = r * std::sqrt(r * r + g.squaredNorm());
    if (uni(rng) * jmax > j) continue;
    const Eigen::Vector3d x = r * d;
    const Eigen::Vector3d nrm = (d - g / r).normalized();
    pcl::PointNormal p;
    p.getVector3fMap() = x.cast<float>();
    p.getNormalVector3fMap() = nrm.cast<float>();
    p.curvature = 0.0f;
    cloud->push_back(p);
  }
  return cloud;
}

/** Open patch [-1,1]^2 of z = f(x, y), uniform by area (rejection), exact upward normals. */
template <typename F, typename G>
PointCloudSequence::Cloud::Ptr heightField(std::size_t n, unsigned seed, F f, G grad) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> uni(-1.0, 1.0), u01(0.0, 1.0);
  PointCloudSequence::Cloud::Ptr cloud(new PointCloudSequence::Cloud);
  while (cloud->size() < n) {
    const double x = uni(rng), y = uni(rng);
    const Eigen::Vector2d g = grad(x, y);
    const double j = std::sqrt(1.0 + g.squaredNorm());
    if (u01(rng) * 3.0 > j) continue;
    pcl::PointNormal p;
    p.x = static_cast<float>(x);
    p.y = static_cast<float>(y);
    p.z = static_cast<float>(f(x, y));
    p.getNormalVector3fMap() = Eigen::Vector3d(-g.x(), -g.y(), 1.0).normalized().cast<float>();
    cloud->push_back(p);
  }
  return cloud;
}

/** The cloud moved by `T` (normals rotated) and scaled by s about the origin. */
inline PointCloudSequence::Cloud::Ptr transformed(const PointCloudSequence::Cloud& in,
                                                  const Eigen::Isometry3d& T, double s = 1.0) {
  PointCloudSequence::Cloud::Ptr out(new PointCloudSequence::Cloud(in));
  const Eigen::Matrix3d R = T.rotation();
  for (auto& p : out->points) {
    p.getVector3fMap() = (s * (T * p.getVector3fMap().cast<double>())).cast<float>();
    p.getNormalVector3fMap() = (R * p.getNormalVector3fMap().cast<double>()).cast<float>();
  }
  return out;
}

inline Eigen::Isometry3d someMotion() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.rotate(Eigen::AngleAxisd(0.9, Eigen::Vector3d(1.0, -2.0, 0.5).normalized()));
  T.pretranslate(Eigen::Vector3d(3.0, -1.5, 7.25));
  return T;
}

}  // namespace test
}  // namespace pcl_animseg
