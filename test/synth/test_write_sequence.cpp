#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/frame_readers.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/synth/articulated.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>

#include "temp_dir.h"

namespace sy = pcl_animseg::synth;
namespace fs = std::filesystem;

namespace {
using animseg_test::TempDir;
}  // namespace

TEST(WriteSequence, PointFramesRoundTrip) {
  sy::SynthParams p;
  p.plan = sy::BodyPlan::Spider;
  p.frames = 3;
  p.points = 800;
  const auto frames = sy::generate(p);
  TempDir tmp;
  const std::string dir = (tmp.dir() / "seq").string();
  sy::writeSequence(dir, frames);

  const auto paths = pcl_animseg::io::listSequence(dir);
  ASSERT_EQ(paths.size(), 3u);
  const auto seq = pcl_animseg::io::loadSequence(dir);
  ASSERT_EQ(seq.size(), 3u);
  for (std::size_t t = 0; t < 3; ++t) {
    EXPECT_EQ(seq.name(t), sy::frameName(t, 3));
    ASSERT_EQ(seq.frame(t)->size(), frames[t].cloud->size());
    EXPECT_TRUE(seq.faces(t).empty());
    for (std::size_t i = 0; i < frames[t].cloud->size(); i += 37) {
      const auto& a = (*seq.frame(t))[i];
      const auto& b = (*frames[t].cloud)[i];
      EXPECT_FLOAT_EQ(a.x, b.x);
      EXPECT_FLOAT_EQ(a.z, b.z);
      EXPECT_NEAR(a.normal_x, b.normal_x, 1e-6);  // the file's true normals are kept
    }
    EXPECT_EQ(pcl_animseg::io::loadLabels(dir + "/" + seq.name(t) + ".gt"), frames[t].labels);
  }
}

namespace {
/** The shipped fixture `dir` must still be what the generator makes with `p` (see
 * datasets/README.md): same point counts, labels and faces; positions equal up to float
 * rounding (libm may differ in the last bit between platforms). */
void expectFixtureMatches(const std::string& dir, const sy::SynthParams& p) {
  const auto frames = sy::generate(p);
  const auto paths = pcl_animseg::io::listSequence(dir);
  ASSERT_EQ(paths.size(), frames.size()) << dir;
  for (std::size_t t = 0; t < frames.size(); ++t) {
    const std::string base = dir + "/" + sy::frameName(t, frames.size());
    const auto raw = pcl_animseg::io::readRawFrame(base + ".ply");
    ASSERT_EQ(raw.points.size(), frames[t].cloud->size()) << base;
    EXPECT_EQ(raw.faces.size(), frames[t].faces.size()) << base;
    EXPECT_EQ(pcl_animseg::io::loadLabels(base + ".gt"), frames[t].labels) << base;
    float worst = 0.0f;
    for (std::size_t i = 0; i < raw.points.size(); ++i)
      worst = std::max(worst, (raw.points[i] - (*frames[t].cloud)[i].getVector3fMap()).norm());
    EXPECT_LT(worst, 1e-4f) << base;
  }
}
}  // namespace

TEST(ShippedDatasets, MatchTheGenerator) {
  const std::string root = std::string(PCL_ANIMSEG_SOURCE_DIR) + "/datasets";
  sy::SynthParams q;
  q.plan = sy::BodyPlan::Quadruped;
  q.frames = 12;
  q.points = 1500;
  q.point_variation = 0.2;
  q.seed = 1;
  expectFixtureMatches(root + "/quadruped_points", q);
  sy::SynthParams h;
  h.plan = sy::BodyPlan::Hand;
  h.frames = 8;
  h.mesh = true;
  h.mesh_resolution = 10;
  h.seed = 1;
  expectFixtureMatches(root + "/hand_mesh", h);
}

TEST(WriteSequence, MeshFramesKeepVertexOrderAndFaces) {
  sy::SynthParams p;
  p.plan = sy::BodyPlan::Hand;
  p.frames = 2;
  p.mesh = true;
  p.mesh_resolution = 8;
  const auto frames = sy::generate(p);
  TempDir tmp;
  sy::writeSequence(tmp.dir().string(), frames);
  for (std::size_t t = 0; t < frames.size(); ++t) {
    const auto raw =
        pcl_animseg::io::readRawFrame((tmp.dir() / (sy::frameName(t, 2) + ".ply")).string());
    ASSERT_EQ(raw.points.size(), frames[t].cloud->size());
    ASSERT_EQ(raw.faces.size(), frames[t].faces.size());
    for (std::size_t i = 0; i < raw.points.size(); i += 11)
      EXPECT_EQ(raw.points[i], (*frames[t].cloud)[i].getVector3fMap());
    for (std::size_t k = 0; k < raw.faces.size(); k += 13)
      EXPECT_EQ(raw.faces[k].vertices, frames[t].faces[k].vertices);
  }
}

// io::saveSequenceLabels writes the frames side by side: every frame's .labels (every level, in
// input order), .pcd and .ply, progress once per frame counting up, and an error of one frame
// (its .labels path taken by a directory) rethrown after the others were written.
TEST(WriteSequence, SaveSequenceLabelsWritesEveryFrame) {
  sy::SynthParams p;
  p.plan = sy::BodyPlan::Quadruped;
  p.frames = 9;
  p.points = 600;
  const auto seq = sy::toSequence(sy::generate(p));
  std::vector<std::vector<std::vector<int>>> levels(2);
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const std::size_t n = seq.frame(t)->size();
    levels[0].emplace_back(n);
    levels[1].emplace_back(n);
    for (std::size_t j = 0; j < n; ++j) {
      levels[0][t][j] = static_cast<int>((j + t) % 5);
      levels[1][t][j] = static_cast<int>((j + t) % 5) / 2;
    }
  }
  TempDir tmp;
  const std::string dir = (tmp.dir() / "out").string();
  std::vector<std::size_t> reported;
  pcl_animseg::io::saveSequenceLabels(dir, seq, levels, /*ply=*/true,
                                      [&](std::size_t done) { reported.push_back(done); });
  ASSERT_EQ(reported.size(), seq.size());
  for (std::size_t k = 0; k < reported.size(); ++k) EXPECT_EQ(reported[k], k + 1);
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const std::string base = dir + "/" + seq.name(t);
    EXPECT_EQ(pcl_animseg::io::loadLabels(base + ".labels", 0), seq.toInputOrder(t, levels[0][t]));
    EXPECT_EQ(pcl_animseg::io::loadLabels(base + ".labels", 1), seq.toInputOrder(t, levels[1][t]));
    EXPECT_TRUE(fs::exists(base + ".pcd")) << base;
    EXPECT_TRUE(fs::exists(base + ".ply")) << base;
  }
  // Without `ply` no .ply is written.
  const std::string plain = (tmp.dir() / "plain").string();
  pcl_animseg::io::saveSequenceLabels(plain, seq, levels);
  EXPECT_TRUE(fs::exists(plain + "/" + seq.name(0) + ".pcd"));
  EXPECT_FALSE(fs::exists(plain + "/" + seq.name(0) + ".ply"));
  // A frame that cannot be written: the error comes back, the other frames are written.
  const std::string bad = (tmp.dir() / "bad").string();
  fs::create_directories(bad + "/" + seq.name(4) + ".labels");
  EXPECT_THROW(pcl_animseg::io::saveSequenceLabels(bad, seq, levels), pcl_animseg::Error);
  EXPECT_TRUE(fs::exists(bad + "/" + seq.name(8) + ".labels"));
  // Levels that miss a frame: an error, not a crash.
  levels[1].pop_back();
  EXPECT_THROW(pcl_animseg::io::saveSequenceLabels((tmp.dir() / "short").string(), seq, levels),
               std::exception);
}
