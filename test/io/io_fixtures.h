#pragma once
// Small shapes and independent, hand-written frame writers for the io tests (the library's own
// writers are tested against these, not against themselves).
#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "temp_dir.h"

namespace fixtures {

namespace fs = std::filesystem;

using animseg_test::TempDir;

struct Shape {
  std::vector<Eigen::Vector3f> points;
  std::vector<Eigen::Vector3f> normals;  // exact (analytic) outward normals
  std::vector<std::vector<int>> polys;   // empty for point sets
};

/** Points on a sphere (Fibonacci spiral: even, deterministic), with outward normals. */
inline Shape sampleSphere(int n, float radius = 1.0f,
                          const Eigen::Vector3f& center = Eigen::Vector3f(0.3f, -0.2f, 0.5f)) {
  Shape s;
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1.0 - 2.0 * (i + 0.5) / n;
    const double r = std::sqrt(1.0 - z * z);
    const double a = golden * i;
    const Eigen::Vector3f d(static_cast<float>(r * std::cos(a)),
                            static_cast<float>(r * std::sin(a)), static_cast<float>(z));
    s.points.push_back(center + radius * d);
    s.normals.push_back(d);
  }
  return s;
}

/** Points on a torus (major radius R, minor r) around the z axis, with outward normals. */
inline Shape sampleTorus(int nu, int nv, float R = 1.0f, float r = 0.35f) {
  Shape s;
  for (int i = 0; i < nu; ++i)
    for (int j = 0; j < nv; ++j) {
      // Offsets by half a step on alternate rings avoid a perfectly regular grid.
      const double u = 2 * M_PI * (i + 0.5 * (j % 2)) / nu, v = 2 * M_PI * j / nv;
      const Eigen::Vector3f ring(static_cast<float>(R * std::cos(u)),
                                 static_cast<float>(R * std::sin(u)), 0);
      const Eigen::Vector3f d(static_cast<float>(std::cos(v) * std::cos(u)),
                              static_cast<float>(std::cos(v) * std::sin(u)),
                              static_cast<float>(std::sin(v)));
      s.points.push_back(ring + r * d);
      s.normals.push_back(d);
    }
  return s;
}

/** A closed UV sphere: poles are single vertices, triangle fans at the poles and quads between
 * rings, wound counter-clockwise seen from outside (outward normals). */
inline Shape uvSphere(int rings, int segments, float radius = 1.0f,
                      const Eigen::Vector3f& center = Eigen::Vector3f(0.1f, 0.2f, -0.3f)) {
  Shape s;
  auto add = [&](const Eigen::Vector3f& d) {
    s.points.push_back(center + radius * d);
    s.normals.push_back(d);
  };
  add(Eigen::Vector3f(0, 0, 1));
  for (int i = 1; i < rings; ++i) {
    const double th = M_PI * i / rings;
    for (int j = 0; j < segments; ++j) {
      const double ph = 2 * M_PI * j / segments;
      add(Eigen::Vector3f(static_cast<float>(std::sin(th) * std::cos(ph)),
                          static_cast<float>(std::sin(th) * std::sin(ph)),
                          static_cast<float>(std::cos(th))));
    }
  }
  add(Eigen::Vector3f(0, 0, -1));
  const int bottom = static_cast<int>(s.points.size()) - 1;
  auto ring = [&](int i, int j) { return 1 + (i - 1) * segments + (j % segments); };
  for (int j = 0; j < segments; ++j) s.polys.push_back({0, ring(1, j), ring(1, j + 1)});
  for (int i = 1; i + 1 < rings; ++i)
    for (int j = 0; j < segments; ++j)
      s.polys.push_back({ring(i, j), ring(i + 1, j), ring(i + 1, j + 1), ring(i, j + 1)});
  for (int j = 0; j < segments; ++j)
    s.polys.push_back({ring(rings - 1, j), bottom, ring(rings - 1, j + 1)});
  return s;
}

inline std::string num(float v) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.9g", static_cast<double>(v));
  return buf;
}

inline void writeText(const std::string& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary);
  out << text;
}

inline void writeXYZ(const std::string& path, const Shape& s, bool normals) {
  std::ostringstream o;
  o << "# x y z" << (normals ? " nx ny nz" : "") << "\n";
  for (std::size_t i = 0; i < s.points.size(); ++i) {
    const auto& p = s.points[i];
    o << num(p.x()) << ' ' << num(p.y()) << ' ' << num(p.z());
    if (normals)
      o << ' ' << num(s.normals[i].x()) << ' ' << num(s.normals[i].y()) << ' '
        << num(s.normals[i].z());
    o << '\n';
  }
  writeText(path, o.str());
}

/** OBJ with faces written in the "a/t/n" form and, when `relative`, negative indices. */
inline void writeOBJ(const std::string& path, const Shape& s, bool relative = false) {
  std::ostringstream o;
  o << "# test mesh\no shape\n";
  for (const auto& p : s.points)
    o << "v " << num(p.x()) << ' ' << num(p.y()) << ' ' << num(p.z()) << '\n';
  o << "vt 0 0\nvn 0 0 1\n";
  const int n = static_cast<int>(s.points.size());
  for (const auto& f : s.polys) {
    o << 'f';
    for (int i : f) o << ' ' << (relative ? i - n : i + 1) << "/1/1";
    o << '\n';
  }
  writeText(path, o.str());
}

/** OFF / COFF (with an RGBA colour per vertex) / NOFF (with normals). */
inline void writeOFF(const std::string& path, const Shape& s, const std::string& keyword = "OFF") {
  std::ostringstream o;
  o << keyword << "\n# comment\n" << s.points.size() << ' ' << s.polys.size() << " 0\n";
  for (std::size_t i = 0; i < s.points.size(); ++i) {
    const auto& p = s.points[i];
    o << num(p.x()) << ' ' << num(p.y()) << ' ' << num(p.z());
    if (keyword.find('N') != std::string::npos)
      o << ' ' << num(s.normals[i].x()) << ' ' << num(s.normals[i].y()) << ' '
        << num(s.normals[i].z());
    if (keyword.find('C') != std::string::npos) o << " 255 0 0 255";
    o << '\n';
  }
  for (const auto& f : s.polys) {
    o << f.size();
    for (int i : f) o << ' ' << i;
    o << '\n';
  }
  writeText(path, o.str());
}

template <typename T>
void putBytes(std::string& buf, T v, bool big_endian) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  if (big_endian)  // test hosts are little endian
    for (std::size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(b[i], b[sizeof(T) - 1 - i]);
  buf.append(b, sizeof(T));
}

/** PLY: format "ascii", "binary_little_endian" or "binary_big_endian"; double coordinates when
 * `doubles` (exercises non-float fields). */
inline std::string plyBytes(const Shape& s, const std::string& format, bool normals, bool faces,
                            bool doubles = false) {
  std::ostringstream h;
  const char* t = doubles ? "double" : "float";
  h << "ply\nformat " << format << " 1.0\ncomment test\nelement vertex " << s.points.size() << '\n'
    << "property " << t << " x\nproperty " << t << " y\nproperty " << t << " z\n";
  if (normals) h << "property float nx\nproperty float ny\nproperty float nz\n";
  if (faces && !s.polys.empty())
    h << "element face " << s.polys.size() << "\nproperty list uchar int vertex_indices\n";
  h << "end_header\n";
  std::string out = h.str();
  const bool be = format == "binary_big_endian";
  if (format == "ascii") {
    std::ostringstream o;
    for (std::size_t i = 0; i < s.points.size(); ++i) {
      o << num(s.points[i].x()) << ' ' << num(s.points[i].y()) << ' ' << num(s.points[i].z());
      if (normals)
        o << ' ' << num(s.normals[i].x()) << ' ' << num(s.normals[i].y()) << ' '
          << num(s.normals[i].z());
      o << '\n';
    }
    if (faces)
      for (const auto& f : s.polys) {
        o << f.size();
        for (int i : f) o << ' ' << i;
        o << '\n';
      }
    return out + o.str();
  }
  for (std::size_t i = 0; i < s.points.size(); ++i) {
    for (int a = 0; a < 3; ++a) {
      if (doubles)
        putBytes(out, static_cast<double>(s.points[i][a]), be);
      else
        putBytes(out, s.points[i][a], be);
    }
    if (normals)
      for (int a = 0; a < 3; ++a) putBytes(out, s.normals[i][a], be);
  }
  if (faces)
    for (const auto& f : s.polys) {
      out.push_back(static_cast<char>(f.size()));
      for (int i : f) putBytes(out, static_cast<std::int32_t>(i), be);
    }
  return out;
}

inline void writePLY(const std::string& path, const Shape& s, const std::string& format,
                     bool normals, bool faces, bool doubles = false) {
  writeText(path, plyBytes(s, format, normals, faces, doubles));
}

inline void writePCD(const std::string& path, const Shape& s, bool normals, bool binary) {
  if (normals) {
    pcl::PointCloud<pcl::PointNormal> c;
    for (std::size_t i = 0; i < s.points.size(); ++i) {
      pcl::PointNormal p;
      p.getVector3fMap() = s.points[i];
      p.getNormalVector3fMap() = s.normals[i];
      p.curvature = 0;
      c.push_back(p);
    }
    c.is_dense = false;
    pcl::io::savePCDFile(path, c, binary);
  } else {
    pcl::PointCloud<pcl::PointXYZ> c;
    for (const auto& q : s.points) c.push_back(pcl::PointXYZ(q.x(), q.y(), q.z()));
    c.is_dense = false;
    pcl::io::savePCDFile(path, c, binary);
  }
}

}  // namespace fixtures
