// Writers: atomic files, labels, labelled PCD / PLY, savePLY round trips.
#include <gtest/gtest.h>
#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>

#include <cstdlib>
#include <iostream>
#include <set>
#include <stdexcept>

#include "io/io_fixtures.h"

using namespace pcl_animseg;
using fixtures::TempDir;
namespace fs = std::filesystem;

namespace {

void expectError(const std::function<void()>& f, const std::vector<std::string>& parts) {
  try {
    f();
    ADD_FAILURE() << "no Error thrown";
  } catch (const Error& e) {
    const std::string what = e.what();
    if (std::getenv("IO_TEST_SHOW_ERRORS")) std::cerr << "  message: " << what << "\n";
    for (const auto& p : parts)
      EXPECT_NE(what.find(p), std::string::npos) << "'" << p << "' not in: " << what;
  }
}

std::size_t entries(const std::string& dir) {
  return static_cast<std::size_t>(
      std::distance(fs::directory_iterator(dir), fs::directory_iterator()));
}

std::string readAll(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

PointCloudSequence::Cloud sphereCloud(int n) {
  const auto s = fixtures::sampleSphere(n);
  PointCloudSequence::Cloud c;
  for (std::size_t i = 0; i < s.points.size(); ++i) {
    pcl::PointNormal p;
    p.getVector3fMap() = s.points[i];
    p.getNormalVector3fMap() = s.normals[i];
    p.curvature = 0;
    c.push_back(p);
  }
  return c;
}

}  // namespace

TEST(AtomicFile, WritesAndReplaces) {
  TempDir dir;
  io::writeTextAtomically(dir / "a.txt", "one\n");
  EXPECT_EQ(readAll(dir / "a.txt"), "one\n");
  io::writeTextAtomically(dir / "a.txt", "two\n");
  EXPECT_EQ(readAll(dir / "a.txt"), "two\n");
  EXPECT_EQ(entries(dir.path()), 1u);
}

TEST(AtomicFile, ThrowingWriterLeavesNothing) {
  TempDir dir;
  std::string seen_tmp;
  EXPECT_THROW(io::writeAtomically(dir / "out.pcd",
                                   [&](const std::string& tmp) {
                                     seen_tmp = tmp;
                                     std::ofstream(tmp) << "half a file";
                                     throw std::runtime_error("disk on fire");
                                   }),
               std::runtime_error);
  EXPECT_EQ(fs::path(seen_tmp).parent_path(), fs::path(dir.path()));
  EXPECT_EQ(fs::path(seen_tmp).filename().string().rfind(".out.pcd.tmp.", 0), 0u);
  EXPECT_FALSE(fs::exists(dir / "out.pcd"));
  EXPECT_EQ(entries(dir.path()), 0u);

  // An existing file survives a failed rewrite untouched.
  io::writeTextAtomically(dir / "keep.txt", "old\n");
  EXPECT_THROW(io::writeAtomically(dir / "keep.txt",
                                   [](const std::string& tmp) {
                                     std::ofstream(tmp) << "new";
                                     throw Error("failed");
                                   }),
               Error);
  EXPECT_EQ(readAll(dir / "keep.txt"), "old\n");
  EXPECT_EQ(entries(dir.path()), 1u);
}

TEST(AtomicFile, ErrorsAreErrors) {
  TempDir dir;
  expectError([&] { io::writeTextAtomically(dir / "missing/sub/x.txt", "x"); }, {"x.txt"});
  expectError([&] { io::writeAtomically(dir / "y.txt", [](const std::string&) {}); },
              {"y.txt", "no file"});
  io::ensureDirectory(dir / "a/b/c");
  EXPECT_TRUE(fs::is_directory(dir / "a/b/c"));
  io::ensureDirectory(dir / "a/b/c");  // existing: fine
  io::writeTextAtomically(dir / "file", "x");
  expectError([&] { io::ensureDirectory(dir / "file"); }, {"file", "not a directory"});
  expectError([&] { io::ensureDirectory(dir / "file/sub"); }, {"file/sub"});
  EXPECT_EQ(entries(dir.path()), 2u);
}

TEST(Labels, ColumnsRoundTrip) {
  TempDir dir;
  const std::vector<std::vector<int>> cols{{0, 1, -1, 2, 7}, {0, 0, -1, 1, 1}, {0, 0, -1, 0, 0}};
  io::saveLabels(dir / "f.labels", cols);
  EXPECT_EQ(readAll(dir / "f.labels"), "0 0 0\n1 0 0\n-1 -1 -1\n2 1 0\n7 1 0\n");
  EXPECT_EQ(io::loadLabelColumns(dir / "f.labels"), cols);
  EXPECT_EQ(io::loadLabels(dir / "f.labels"), cols[0]);
  EXPECT_EQ(io::loadLabels(dir / "f.labels", 2), cols[2]);
  expectError([&] { io::loadLabels(dir / "f.labels", 3); }, {"f.labels", "3 column"});
  expectError([&] { io::saveLabels(dir / "g.labels", {{1, 2}, {1}}); }, {"g.labels", "column 1"});
  expectError([&] { io::saveLabels(dir / "g.labels", {}); }, {"g.labels"});
  EXPECT_FALSE(fs::exists(dir / "g.labels"));

  fixtures::writeText(dir / "gt.gt", "# ground truth\n3\n4\r\n5\n\n\n");
  EXPECT_EQ(io::loadLabels(dir / "gt.gt"), (std::vector<int>{3, 4, 5}));
  fixtures::writeText(dir / "bad1", "1 2\n3\n");
  expectError([&] { io::loadLabelColumns(dir / "bad1"); }, {"bad1", "line 2", "1 columns"});
  fixtures::writeText(dir / "bad2", "1\nx\n");
  expectError([&] { io::loadLabels(dir / "bad2"); }, {"bad2", "line 2", "not an integer"});
  fixtures::writeText(dir / "bad3", "1\n\n2\n");
  expectError([&] { io::loadLabels(dir / "bad3"); }, {"bad3", "line 2", "empty"});
  fixtures::writeText(dir / "bad4", "1.5\n");
  expectError([&] { io::loadLabels(dir / "bad4"); }, {"bad4", "line 1"});
  expectError([&] { io::loadLabels(dir / "none"); }, {"none"});
}

TEST(Labels, InputOrderRoundTripThroughALoadedFrame) {
  TempDir dir;
  auto s = fixtures::sampleSphere(120);
  s.points[5] = Eigen::Vector3f(NAN, 0, 0);
  s.points[60] = Eigen::Vector3f(0, INFINITY, 0);
  fixtures::writeXYZ(dir / "f7.xyz", s, true);
  const auto seq = io::loadSequence(dir.path());
  std::vector<int> labels(seq.frame(0)->size());
  for (std::size_t j = 0; j < labels.size(); ++j) labels[j] = (*seq.frame(0))[j].z > 0.5f ? 1 : 0;
  const auto in = seq.toInputOrder(0, labels);
  io::saveLabels(dir / (seq.name(0) + ".labels"), {in});
  const auto back = io::loadLabels(dir / "f7.labels");
  ASSERT_EQ(back.size(), 120u);
  for (int i = 0; i < 120; ++i) {
    if (i == 5 || i == 60)
      EXPECT_EQ(back[i], -1);
    else
      EXPECT_EQ(back[i], s.points[i].z() > 0.5f ? 1 : 0) << i;
  }
}

TEST(LabelledPCD, FieldsAndLabels) {
  TempDir dir;
  const auto c = sphereCloud(100);
  std::vector<int> labels(100);
  for (int i = 0; i < 100; ++i) labels[i] = i % 7 - 1;  // includes -1
  io::saveLabelledPCD(dir / "f.pcd", c, labels);
  EXPECT_EQ(entries(dir.path()), 1u);
  pcl::PCLPointCloud2 c2;
  ASSERT_EQ(pcl::io::loadPCDFile(dir / "f.pcd", c2), 0);
  std::vector<std::string> names;
  for (const auto& f : c2.fields) names.push_back(f.name);
  EXPECT_EQ(names,
            (std::vector<std::string>{"x", "y", "z", "normal_x", "normal_y", "normal_z", "label"}));
  EXPECT_EQ(c2.fields.back().datatype, pcl::PCLPointField::UINT32);
  EXPECT_NE(readAll(dir / "f.pcd").find("DATA binary\n"), std::string::npos);
  pcl::PointCloud<pcl::PointXYZLNormal> back;
  ASSERT_EQ(pcl::io::loadPCDFile(dir / "f.pcd", back), 0);
  ASSERT_EQ(back.size(), 100u);
  for (int i = 0; i < 100; ++i) {
    EXPECT_EQ(static_cast<int>(back[i].label), labels[i]);
    EXPECT_FLOAT_EQ(back[i].x, c[i].x);
    EXPECT_FLOAT_EQ(back[i].normal_z, c[i].normal_z);
  }
  expectError(
      [&] {
        io::saveLabelledPCD(dir / "g.pcd", c, {1, 2});
      },
      {"g.pcd", "2 labels for 100 points"});
  EXPECT_FALSE(fs::exists(dir / "g.pcd"));
}

TEST(LabelledPLY, ColoursAndLabels) {
  TempDir dir;
  const auto c = sphereCloud(50);
  std::vector<int> labels(50);
  for (int i = 0; i < 50; ++i) labels[i] = i % 5 - 1;
  io::saveLabelledPLY(dir / "f.ply", c, labels);
  const std::string bytes = readAll(dir / "f.ply");
  const std::size_t body = bytes.find("end_header\n") + 11;
  ASSERT_NE(body, std::string::npos + 11);
  EXPECT_NE(bytes.find("format binary_little_endian 1.0"), std::string::npos);
  EXPECT_NE(bytes.find("property int label"), std::string::npos);
  ASSERT_EQ(bytes.size() - body, 50u * (6 * 4 + 3 + 4));
  for (int i = 0; i < 50; ++i) {
    const char* p = bytes.data() + body + i * 31;
    float x;
    std::int32_t l;
    std::memcpy(&x, p, 4);
    std::memcpy(&l, p + 27, 4);
    EXPECT_FLOAT_EQ(x, c[i].x);
    EXPECT_EQ(l, labels[i]);
    unsigned char r, g, b;
    io::labelColor(labels[i], r, g, b);
    EXPECT_EQ(static_cast<unsigned char>(p[24]), r);
    EXPECT_EQ(static_cast<unsigned char>(p[26]), b);
  }
  // PCL reads it too (CloudCompare-style consumers do).
  pcl::PCLPointCloud2 c2;
  ASSERT_EQ(pcl::io::loadPLYFile(dir / "f.ply", c2), 0);
  EXPECT_EQ(c2.width * c2.height, 50u);
}

TEST(LabelColor, StableAndDistinct) {
  unsigned char r, g, b;
  io::labelColor(-1, r, g, b);
  EXPECT_TRUE(r == g && g == b);
  std::set<std::tuple<int, int, int>> seen;
  for (int l = 0; l < 64; ++l) {
    io::labelColor(l, r, g, b);
    seen.emplace(r, g, b);
    unsigned char r2, g2, b2;
    io::labelColor(l, r2, g2, b2);
    EXPECT_EQ(std::make_tuple(r, g, b), std::make_tuple(r2, g2, b2));
  }
  EXPECT_EQ(seen.size(), 64u);
  // Consecutive labels are far apart.
  for (int l = 0; l < 32; ++l) {
    unsigned char a[3], c[3];
    io::labelColor(l, a[0], a[1], a[2]);
    io::labelColor(l + 1, c[0], c[1], c[2]);
    int d = 0;
    for (int k = 0; k < 3; ++k) d += std::abs(int(a[k]) - int(c[k]));
    EXPECT_GT(d, 60) << l;
  }
}

TEST(SavePLY, RoundTripThroughLoader) {
  TempDir dir;
  const auto mesh = fixtures::uvSphere(10, 16);
  PointCloudSequence::Cloud c;
  for (std::size_t i = 0; i < mesh.points.size(); ++i) {
    pcl::PointNormal p;
    p.getVector3fMap() = mesh.points[i];
    p.getNormalVector3fMap() = mesh.normals[i];
    c.push_back(p);
  }
  std::vector<pcl::Vertices> faces;
  for (const auto& f : mesh.polys) {
    pcl::Vertices v;
    v.vertices.assign(f.begin(), f.end());
    faces.push_back(v);
  }
  for (bool binary : {true, false}) {
    SCOPED_TRACE(binary);
    io::savePLY(dir / "m.ply", c, faces, binary);
    PointCloudSequence seq;
    io::loadFrame(dir / "m.ply", seq);
    ASSERT_EQ(seq.frame(0)->size(), c.size());
    std::size_t tris = 0;
    for (const auto& f : faces) tris += f.vertices.size() - 2;
    EXPECT_EQ(seq.faces(0).size(), tris);
    for (std::size_t i = 0; i < c.size(); ++i) {
      EXPECT_FLOAT_EQ((*seq.frame(0))[i].x, c[i].x);
      EXPECT_GT((*seq.frame(0))[i].getNormalVector3fMap().dot(c[i].getNormalVector3fMap()), 0.98f);
    }
    io::savePLY(dir / "p.ply", c, {}, binary);
    PointCloudSequence pts;
    io::loadFrame(dir / "p.ply", pts);
    ASSERT_EQ(pts.frame(0)->size(), c.size());
    for (std::size_t i = 0; i < c.size(); ++i) {
      EXPECT_FLOAT_EQ((*pts.frame(0))[i].y, c[i].y);
      EXPECT_NEAR((*pts.frame(0))[i].normal_x, c[i].normal_x, 1e-6f);  // the file's normals
    }
  }
  std::vector<pcl::Vertices> bad(1);
  bad[0].vertices = {0, 1, 100000};
  expectError([&] { io::savePLY(dir / "bad.ply", c, bad); }, {"bad.ply", "100000"});
  EXPECT_FALSE(fs::exists(dir / "bad.ply"));
}
