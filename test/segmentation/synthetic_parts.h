#pragma once
// Small articulated test sequences with exact ground truth, made inside the tests so that they do
// not depend on the synth module: a chain of mitred tubes (parts meet at creases, like an elbow)
// and a chain of boxes moved rigidly (shared vertex order in "mesh" mode).
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

namespace animseg_test {

using Cloud = pcl_animseg::PointCloudSequence::Cloud;

struct TubeChain {
  pcl_animseg::PointCloudSequence sequence;
  std::vector<std::vector<int>> truth;
  /** Labels with every joint's boundary shifted by `shift` (world units) along the mitre normal. */
  std::vector<std::vector<int>> shifted;
};

/** Appends point x with normal n, both moved by `global`. */
inline void appendMoved(Cloud& cloud, const Eigen::Affine3d& global, const Eigen::Vector3d& x,
                        const Eigen::Vector3d& n) {
  pcl::PointNormal p;
  p.getVector3fMap() = (global * x).cast<float>();
  p.getNormalVector3fMap() = (global.linear() * n).cast<float>();
  p.curvature = 0;
  cloud.push_back(p);
}

/** Chain of `lengths.size()` tubes of radius r joined by mitres; joint k bends by
 * bend0[k] + amp * sin(...) in frame t; the whole chain also moves rigidly. Point mode: each
 * frame is sampled anew with points * (1 ± 0.2) points. */
inline TubeChain makeTubeChain(const std::vector<double>& lengths, const std::vector<double>& bend0,
                               int frames, int points, double shift_spacings, unsigned seed,
                               double radius = 0.2) {
  TubeChain out;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const int parts = static_cast<int>(lengths.size());
  double total_len = 0.0;
  for (double l : lengths) total_len += l;
  const double kPi = 3.14159265358979323846;
  for (int t = 0; t < frames; ++t) {
    std::vector<double> bend(parts, 0.0);
    for (int k = 0; k + 1 < parts; ++k) bend[k] = bend0[k] + 0.35 * std::sin(0.7 * t + 1.3 * k);
    // Part frames in the chain's xz plane.
    std::vector<Eigen::Vector3d> start(parts + 1), dir(parts), side(parts);
    double alpha = 0.0;
    start[0] = Eigen::Vector3d::Zero();
    for (int i = 0; i < parts; ++i) {
      dir[i] = Eigen::Vector3d(std::sin(alpha), 0, std::cos(alpha));
      side[i] = Eigen::Vector3d(std::cos(alpha), 0, -std::sin(alpha));
      start[i + 1] = start[i] + lengths[i] * dir[i];
      if (i + 1 < parts) alpha += bend[i];
    }
    std::vector<Eigen::Vector3d> mitre(parts);  // mitre normal at the end of part i
    for (int i = 0; i + 1 < parts; ++i) mitre[i] = (dir[i] + dir[i + 1]).normalized();
    const Eigen::Affine3d global =
        Eigen::Translation3d(0.3 * t, 0.1 * std::sin(0.5 * t), 0.05 * t) *
        Eigen::AngleAxisd(0.15 * t, Eigen::Vector3d(0.3, 1, 0.2).normalized());
    const int n = static_cast<int>(points * (0.8 + 0.4 * u01(rng)));
    Cloud::Ptr cloud(new Cloud);
    std::vector<int> truth, shifted;
    // Spacing of a uniform sample of the tube surface (for the boundary shift).
    const double area = 2.0 * kPi * radius * total_len;
    const double spacing = 0.5 * std::sqrt(area / n) * 1.07;
    const double shift = shift_spacings * spacing;
    const double ext = radius * 2.0;
    while (static_cast<int>(cloud->size()) < n) {
      // Pick a part by length, then a uniform point on its (extended) tube.
      double r = u01(rng) * total_len;
      int i = 0;
      while (i + 1 < parts && r > lengths[i]) r -= lengths[i++];
      const double s = -ext + u01(rng) * (lengths[i] + 2 * ext);
      const double phi = 2 * kPi * u01(rng);
      const Eigen::Vector3d nrm =
          std::cos(phi) * side[i] + std::sin(phi) * Eigen::Vector3d::UnitY();
      const Eigen::Vector3d x = start[i] + s * dir[i] + radius * nrm;
      if (i + 1 < parts && (x - start[i + 1]).dot(mitre[i]) > 0) continue;
      if (i > 0 && (x - start[i]).dot(mitre[i - 1]) < 0) continue;
      int sh = i;
      if (i + 1 < parts && (x - start[i + 1]).dot(mitre[i]) > -shift) sh = i + 1;
      if (i > 0 && (x - start[i]).dot(mitre[i - 1]) < -shift) sh = i - 1;
      appendMoved(*cloud, global, x, nrm);
      truth.push_back(i);
      shifted.push_back(sh);
    }
    out.sequence.addFrame(cloud, "f" + std::to_string(t));
    out.truth.push_back(truth);
    out.shifted.push_back(shifted);
  }
  return out;
}

/** A knee: a thigh capsule (radius `r_thigh`, axis from the joint up, length 1) whose rounded end
 * is a sphere about the joint, and a thinner shin capsule (radius `r_shin`, length 0.9) leaving
 * that sphere at a concave crease; the knee bends by 0.6 + 0.3 sin(0.9 t) radians and the whole
 * leg moves rigidly. Point mode, exact normals. `truth`: 0 thigh, 1 shin. `capped`: the thigh's
 * cap points within `cap_spacings` of the crease (over the sphere) labelled shin, the error that
 * the motions leave there (the cap is a sphere about the joint, so it fits both bones' motions).
 * With r_shin == r_thigh and `straight` the leg is one straight capsule (no crease) and `capped`
 * moves the border `cap_spacings` up the thigh. */
struct Knee {
  pcl_animseg::PointCloudSequence sequence;
  std::vector<std::vector<int>> truth, capped;
};

inline Knee makeKnee(int frames, int points, double r_thigh, double r_shin, double cap_spacings,
                     unsigned seed, bool straight = false) {
  Knee out;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const double kPi = 3.14159265358979323846;
  const double len[2] = {1.0, 0.9}, r[2] = {r_thigh, r_shin};
  // A uniform point on capsule i (axis a -> a + l d), with its outward normal.
  auto onCapsule = [&](const Eigen::Vector3d& a, const Eigen::Vector3d& d, double l, double rad,
                       Eigen::Vector3d& x, Eigen::Vector3d& n) {
    Eigen::Vector3d u = d.unitOrthogonal(), v = d.cross(u);
    const double cyl = 2 * kPi * rad * l, sph = 4 * kPi * rad * rad;
    if (u01(rng) * (cyl + sph) < cyl) {
      const double phi = 2 * kPi * u01(rng);
      n = std::cos(phi) * u + std::sin(phi) * v;
      x = a + u01(rng) * l * d + rad * n;
    } else {
      const double z = 2 * u01(rng) - 1, phi = 2 * kPi * u01(rng), s = std::sqrt(1 - z * z);
      n = z * d + s * (std::cos(phi) * u + std::sin(phi) * v);
      x = (z >= 0 ? a + l * d : a) + rad * n;
    }
  };
  auto inside = [](const Eigen::Vector3d& x, const Eigen::Vector3d& a, const Eigen::Vector3d& d,
                   double l, double rad) {
    const double s = std::clamp((x - a).dot(d), 0.0, l);
    return (x - (a + s * d)).norm() < rad * (1.0 - 1e-9);
  };
  const double area = 2 * kPi * (r[0] * len[0] + r[1] * len[1]) + 4 * kPi * r[0] * r[0];
  for (int t = 0; t < frames; ++t) {
    const double bend = straight ? 0.0 : 0.6 + 0.3 * std::sin(0.9 * t);
    const Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
    const Eigen::Vector3d down(std::sin(bend), 0.0, -std::cos(bend));
    const Eigen::Vector3d axis[2] = {up, down};
    const Eigen::Affine3d global =
        Eigen::Translation3d(0.2 * t, 0.1 * std::sin(0.5 * t), 0.05 * t) *
        Eigen::AngleAxisd(0.15 * t, Eigen::Vector3d(0.3, 1, 0.2).normalized());
    const int n = static_cast<int>(points * (0.8 + 0.4 * u01(rng)));
    const double spacing = 0.5 * std::sqrt(area / n) * 1.07;  // as makeTubeChain's
    // The crease: the shin leaves the thigh's sphere where sin(angle from the shin axis) equals
    // r_shin / r_thigh.
    const double crease = std::asin(std::min(1.0, r[1] / r[0]));
    Cloud::Ptr cloud(new Cloud);
    std::vector<int> truth, capped;
    const double total = 2 * kPi * r[0] * len[0] + 4 * kPi * r[0] * r[0] + 2 * kPi * r[1] * len[1] +
                         4 * kPi * r[1] * r[1];
    while (static_cast<int>(cloud->size()) < n) {
      const double a0 = 2 * kPi * r[0] * len[0] + 4 * kPi * r[0] * r[0];
      const int i = u01(rng) * total < a0 ? 0 : 1;
      Eigen::Vector3d x, nrm;
      onCapsule(Eigen::Vector3d::Zero(), axis[i], len[i], r[i], x, nrm);
      if (inside(x, Eigen::Vector3d::Zero(), axis[1 - i], len[1 - i], r[1 - i])) continue;
      int label = i;
      if (i == 0 && x.dot(up) < 0.0) {
        // On the thigh's cap: over the sphere from the crease.
        const double from_axis = std::acos(std::clamp(x.normalized().dot(down), -1.0, 1.0));
        if (straight) {
          if (x.dot(up) > -cap_spacings * spacing) label = 1;
        } else if ((from_axis - crease) * r[0] < cap_spacings * spacing) {
          label = 1;
        }
      } else if (straight && i == 0 && x.dot(up) < cap_spacings * spacing) {
        label = 1;
      }
      appendMoved(*cloud, global, x, nrm);
      truth.push_back(i);
      capped.push_back(label);
    }
    out.sequence.addFrame(cloud, "f" + std::to_string(t));
    out.truth.push_back(truth);
    out.capped.push_back(capped);
  }
  return out;
}

/** The points of frame `f` with one of their 7 nearest neighbours, closer than 3 spacings `s`,
 * in another part of `labels`. */
inline Cloud::Ptr boundaryPoints(const Cloud::Ptr& f,
                                 const pcl::KdTreeFLANN<pcl::PointNormal>& tree,
                                 const std::vector<int>& labels, double s) {
  Cloud::Ptr boundary(new Cloud);
  std::vector<int> idx;
  std::vector<float> d2;
  for (std::size_t j = 0; j < f->size(); ++j) {
    tree.nearestKSearch((*f)[j], 8, idx, d2);
    for (std::size_t k = 1; k < idx.size(); ++k)
      if (labels[idx[k]] != labels[j] && d2[k] < 9 * s * s) {
        boundary->push_back((*f)[j]);
        break;
      }
  }
  return boundary;
}

/** Fraction of points within `radius_spacings` spacings of a true boundary whose label is wrong. */
inline double boundaryError(const pcl_animseg::PointCloudSequence& seq,
                            const std::vector<std::vector<int>>& truth,
                            const std::vector<std::vector<int>>& labels,
                            double radius_spacings = 3.0) {
  std::size_t near = 0, wrong = 0;
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const Cloud::Ptr& f = seq.frame(t);
    const double s = pcl_animseg::meanSpacing(*f);
    pcl::KdTreeFLANN<pcl::PointNormal> tree;
    tree.setInputCloud(f);
    const Cloud::Ptr boundary = boundaryPoints(f, tree, truth[t], s);
    if (boundary->empty()) continue;
    pcl::KdTreeFLANN<pcl::PointNormal> btree;
    btree.setInputCloud(boundary);
    std::vector<int> idx;
    std::vector<float> d2;
    for (std::size_t j = 0; j < f->size(); ++j) {
      btree.nearestKSearch((*f)[j], 1, idx, d2);
      if (std::sqrt(d2[0]) <= radius_spacings * s) {
        ++near;
        wrong += labels[t][j] != truth[t][j];
      }
    }
  }
  return near ? static_cast<double>(wrong) / static_cast<double>(near) : 0.0;
}

/** All frames' labels concatenated (for pooled ARI). */
inline std::vector<int> pooled(const std::vector<std::vector<int>>& labels) {
  std::vector<int> out;
  for (const auto& f : labels) out.insert(out.end(), f.begin(), f.end());
  return out;
}

struct BoxChain {
  pcl_animseg::PointCloudSequence sequence;
  std::vector<std::vector<int>> truth;
  /** motion[part][t]: world pose of the part in frame t (local -> world). */
  std::vector<std::vector<Eigen::Affine3d>> pose;
};

/** A chain of boxes of different sizes (no symmetry that would make ICP ambiguous), each moving
 * rigidly. mesh = true: the same local samples every frame (shared vertex order); otherwise each
 * frame is sampled anew. */
inline BoxChain makeBoxChain(int frames, int points, bool mesh, unsigned seed) {
  const std::vector<Eigen::Vector3d> dims = {{0.5, 0.3, 1.2}, {0.3, 0.4, 0.9}, {0.25, 0.2, 0.6}};
  const int parts = static_cast<int>(dims.size());
  BoxChain out;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  auto sampleBox = [&](const Eigen::Vector3d& d, int n, std::vector<Eigen::Vector3d>& pts,
                       std::vector<Eigen::Vector3d>& nrm) {
    const double areas[3] = {d.y() * d.z(), d.x() * d.z(), d.x() * d.y()};
    const double total = 2 * (areas[0] + areas[1] + areas[2]);
    for (int k = 0; k < n; ++k) {
      double r = u01(rng) * total;
      int face = 0;
      while (face < 5 && r > areas[face / 2]) r -= areas[face / 2], ++face;
      const int axis = face / 2;
      const double sign = face % 2 ? 1.0 : -1.0;
      Eigen::Vector3d p(d.x() * (u01(rng) - 0.5), d.y() * (u01(rng) - 0.5), d.z() * u01(rng));
      Eigen::Vector3d nn = Eigen::Vector3d::Zero();
      nn[axis] = sign;
      p[axis] = axis == 2 ? (sign > 0 ? d.z() : 0.0) : sign * 0.5 * d[axis];
      pts.push_back(p);
      nrm.push_back(nn);
    }
  };
  std::vector<std::vector<Eigen::Vector3d>> local_p(parts), local_n(parts);
  for (int t = 0; t < frames; ++t) {
    std::vector<Eigen::Affine3d> poses(parts);
    Eigen::Affine3d acc = Eigen::Translation3d(0.2 * t, -0.1 * t, 0.05 * std::sin(0.4 * t)) *
                          Eigen::AngleAxisd(0.12 * t, Eigen::Vector3d::UnitZ()) *
                          Eigen::AngleAxisd(0.05 * t, Eigen::Vector3d::UnitX());
    for (int i = 0; i < parts; ++i) {
      poses[i] = acc;
      const double bend = 0.4 + 0.3 * std::sin(0.6 * t + i);
      acc = acc * Eigen::Translation3d(0, 0, dims[i].z()) *
            Eigen::AngleAxisd(bend, Eigen::Vector3d::UnitY()) *
            Eigen::AngleAxisd(0.2 * std::sin(0.3 * t + 2 * i), Eigen::Vector3d::UnitZ());
    }
    if (!mesh || t == 0) {
      const int n = mesh ? points : static_cast<int>(points * (0.8 + 0.4 * u01(rng)));
      for (int i = 0; i < parts; ++i) {
        local_p[i].clear();
        local_n[i].clear();
        sampleBox(dims[i], n / parts, local_p[i], local_n[i]);
      }
    }
    Cloud::Ptr cloud(new Cloud);
    std::vector<int> truth;
    for (int i = 0; i < parts; ++i)
      for (std::size_t k = 0; k < local_p[i].size(); ++k) {
        const Eigen::Vector3d x = poses[i] * local_p[i][k];
        const Eigen::Vector3d nn = poses[i].linear() * local_n[i][k];
        pcl::PointNormal p;
        p.x = x.x(), p.y = x.y(), p.z = x.z();
        p.normal_x = nn.x(), p.normal_y = nn.y(), p.normal_z = nn.z();
        p.curvature = 0;
        cloud->push_back(p);
        truth.push_back(i);
      }
    out.sequence.addFrame(cloud, "f" + std::to_string(t));
    out.truth.push_back(truth);
    out.pose.resize(parts);
    for (int i = 0; i < parts; ++i) out.pose[i].push_back(poses[i]);
  }
  return out;
}

}  // namespace animseg_test
