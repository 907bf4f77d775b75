#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/segmentation/hierarchy.h>

#include <cstdio>
#include <fstream>
#include <random>

#include "synthetic_parts.h"

using pcl_animseg::segmentation::HierarchyParams;
using pcl_animseg::segmentation::HierarchyResult;
using pcl_animseg::segmentation::PersistenceHierarchy;
using pcl_animseg::segmentation::Saddle;
using pcl_animseg::segmentation::SegmentationResult;

namespace {

// Over-segments the box chain's true parts into `pieces` slabs along each box's length, and
// gives the clusters densities like mean shift's: pieces of one rigid part are separated by
// shallow saddles (close to the modes), different parts by deep ones.
SegmentationResult overSegment(const animseg_test::BoxChain& chain, int pieces, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const std::vector<double> length = {1.2, 0.9, 0.6};
  const int parts = 3;
  SegmentationResult r;
  r.num_clusters = parts * pieces;
  for (std::size_t t = 0; t < chain.sequence.size(); ++t) {
    const auto& f = *chain.sequence.frame(t);
    std::vector<int> labels(f.size());
    for (std::size_t j = 0; j < f.size(); ++j) {
      const int p = chain.truth[t][j];
      const Eigen::Vector3d local =
          chain.pose[p][t].inverse() * f[j].getVector3fMap().cast<double>();
      const int piece =
          std::min(pieces - 1, std::max(0, static_cast<int>(local.z() / length[p] * pieces)));
      labels[j] = p * pieces + piece;
    }
    r.labels.push_back(labels);
  }
  for (int c = 0; c < r.num_clusters; ++c) r.mode_density.push_back(0.8 + 0.2 * u01(rng));
  for (int c = 0; c + 1 < r.num_clusters; ++c) {
    const bool same_part = (c + 1) % pieces != 0;
    const double lo = std::min(r.mode_density[c], r.mode_density[c + 1]);
    const double s = same_part ? lo * (0.85 + 0.1 * u01(rng)) : lo * (0.2 + 0.2 * u01(rng));
    r.saddles.push_back(Saddle{c, c + 1, s});
  }
  return r;
}

void expectNested(const HierarchyResult& h) {
  ASSERT_EQ(h.parent.size() + 1, h.labels.size());
  for (int l = 0; l + 1 < h.levels(); ++l) {
    EXPECT_GT(h.num_parts[l], h.num_parts[l + 1]) << "level " << l;
    ASSERT_EQ(static_cast<int>(h.parent[l].size()), h.num_parts[l]);
    for (std::size_t t = 0; t < h.labels[l].size(); ++t)
      for (std::size_t j = 0; j < h.labels[l][t].size(); ++j) {
        const int a = h.labels[l][t][j];
        if (a < 0) {
          EXPECT_LT(h.labels[l + 1][t][j], 0);
          continue;
        }
        // Every part of level l+1 is a union of parts of level l.
        ASSERT_EQ(h.labels[l + 1][t][j], h.parent[l][a]);
      }
    for (int p : h.parent[l]) {
      EXPECT_GE(p, 0);
      EXPECT_LT(p, h.num_parts[l + 1]);
    }
  }
}

}  // namespace

TEST(Hierarchy, NestedLevelsRecoverTruePartsFromOverSegmentation) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(4, 3000, false, 2);
  const std::vector<int> truth = animseg_test::pooled(chain.truth);
  for (unsigned seed = 1; seed <= 5; ++seed) {
    const SegmentationResult over = overSegment(chain, 2 + seed % 3, seed);
    PersistenceHierarchy h;
    HierarchyResult out;
    h.compute(over, out);
    expectNested(out);
    EXPECT_EQ(out.labels[0], over.labels);  // level 0 is the input
    EXPECT_EQ(out.num_parts.back(), 1);
    const int level = out.levelClosestTo(3);
    EXPECT_EQ(out.num_parts[level], 3) << "seed " << seed;
    EXPECT_GE(
        pcl_animseg::evaluation::adjustedRandIndex(animseg_test::pooled(out.labels[level]), truth),
        0.9)
        << "seed " << seed;
  }
}

TEST(Hierarchy, ThresholdsFollowEq12) {
  SegmentationResult r;
  r.num_clusters = 4;
  r.mode_density = {1.0, 0.9, 0.8, 0.5};
  r.saddles = {{0, 1, 0.85}, {1, 2, 0.2}, {2, 3, 0.45}};
  r.labels = {{0, 1, 2, 3}, {3, 2, 1, 0, -1}};
  HierarchyParams p;
  p.step = 0.1;
  PersistenceHierarchy h;
  h.setParams(p);
  HierarchyResult out;
  h.compute(r, out);
  // Raw persistences: 0.05, 0.6, 0.05 -> normalised by the max 0.6.
  ASSERT_EQ(out.persistence.size(), 3u);
  EXPECT_NEAR(out.persistence[0], 0.05 / 0.6, 1e-12);
  EXPECT_NEAR(out.persistence[1], 1.0, 1e-12);
  EXPECT_NEAR(out.persistence[2], 0.05 / 0.6, 1e-12);
  const double mean = (0.05 / 0.6 * 2 + 1.0) / 3.0;
  ASSERT_GE(out.levels(), 3);
  // 0.4 * mean = 0.156 > 0.083: both shallow pairs merge at level 1, the deep one later.
  EXPECT_NEAR(out.thresholds[1], 0.4 * mean, 1e-12);
  EXPECT_EQ(out.num_parts[1], 2);
  EXPECT_EQ(out.labels[1][0], (std::vector<int>{0, 0, 1, 1}));
  EXPECT_EQ(out.labels[1][1], (std::vector<int>{1, 1, 0, 0, -1}));
  EXPECT_EQ(out.num_parts.back(), 1);
  expectNested(out);
  // Merged regions: densities {1.0, 0.8}, saddle 0.2 -> raw 0.6 -> RP 1.0 merges only once the
  // threshold passes 1.0.
  EXPECT_GT(out.thresholds.back(), 1.0);
}

TEST(Hierarchy, RecordedMotionMergesReplaceTheSaddles) {
  // The motion method's recorded merges, cheapest first (a merged pair is named by its smaller
  // id): {2,3} at 1.0, {0,1} at 1.2, {0,2} at 4.0. The saddles say the opposite ({0,1} deepest):
  // with merges present they are not used.
  SegmentationResult r;
  r.num_clusters = 4;
  r.mode_density = {1.0, 0.9, 0.8, 0.5};
  r.saddles = {{0, 1, 0.1}, {1, 2, 0.89}, {2, 3, 0.49}};
  r.merges = {{2, 3, 1.0}, {0, 1, 1.2}, {0, 2, 4.0}};
  r.labels = {{0, 1, 2, 3}, {3, 2, 1, 0, -1}};
  HierarchyParams p;
  p.initial_factor = 1.0;  // first threshold = mean(0.25, 0.3, 1.0) = 0.517
  p.step = 0.1;
  PersistenceHierarchy h;
  h.setParams(p);
  HierarchyResult out;
  h.compute(r, out);
  expectNested(out);
  ASSERT_EQ(out.levels(), 3);
  EXPECT_EQ(out.num_parts[1], 2);
  EXPECT_EQ(out.labels[1][0], (std::vector<int>{0, 0, 1, 1}));
  EXPECT_EQ(out.labels[1][1], (std::vector<int>{1, 1, 0, 0, -1}));
  EXPECT_NEAR(out.thresholds[1], (0.25 + 0.3 + 1.0) / 3.0, 1e-12);
  EXPECT_EQ(out.num_parts[2], 1);
  // The merges are applied in their order: a cheap merge after an expensive one waits for it.
  r.merges = {{2, 3, 1.0}, {0, 2, 4.0}, {0, 1, 1.2}};
  h.compute(r, out);
  expectNested(out);
  EXPECT_EQ(out.num_parts[1], 3);
  r.merges = {{0, 7, 1.0}};
  EXPECT_THROW(h.compute(r, out), pcl_animseg::Error);
}

TEST(Hierarchy, RegionsWithoutSaddleNeverMergeAndBadInputThrows) {
  SegmentationResult r;
  r.num_clusters = 4;
  r.mode_density = {1.0, 0.9, 0.8, 0.7};
  r.saddles = {{0, 1, 0.5}, {2, 3, 0.6}};  // two separate components
  r.labels = {{0, 1, 2, 3}};
  PersistenceHierarchy h;
  HierarchyResult out;
  h.compute(r, out);
  expectNested(out);
  EXPECT_EQ(out.num_parts.back(), 2);
  EXPECT_NE(out.labels.back()[0][0], out.labels.back()[0][2]);

  HierarchyParams cap;
  cap.max_levels = 1;
  h.setParams(cap);
  h.compute(r, out);
  EXPECT_EQ(out.levels(), 2);

  SegmentationResult bad = r;
  bad.saddles.push_back({0, 7, 0.1});
  EXPECT_THROW(h.compute(bad, out), pcl_animseg::Error);
  bad = r;
  bad.mode_density.pop_back();
  EXPECT_THROW(h.compute(bad, out), pcl_animseg::Error);
  bad = r;
  bad.labels[0][0] = 9;
  EXPECT_THROW(h.compute(bad, out), pcl_animseg::Error);
}

TEST(Hierarchy, SegmentationInfoRoundTrip) {
  SegmentationResult r;
  r.num_clusters = 3;
  r.mode_density = {1.5, 0.25, 0.125};
  r.modes = Eigen::MatrixXf::Random(3, 4);
  r.saddles = {{0, 1, 0.2}, {1, 2, 0.1}};
  const std::string path = ::testing::TempDir() + "/segmentation_roundtrip.txt";
  pcl_animseg::io::saveSegmentationInfo(path, r);
  SegmentationResult back;
  pcl_animseg::io::loadSegmentationInfo(path, back);
  EXPECT_EQ(back.num_clusters, 3);
  EXPECT_EQ(back.mode_density, r.mode_density);
  ASSERT_EQ(back.saddles.size(), 2u);
  EXPECT_EQ(back.saddles[1].a, 1);
  EXPECT_EQ(back.saddles[1].b, 2);
  EXPECT_DOUBLE_EQ(back.saddles[1].density, 0.1);
  ASSERT_EQ(back.modes.rows(), 3);
  EXPECT_TRUE(back.modes.isApprox(r.modes, 1e-6f));
  {
    std::ofstream bad(path);
    bad << "clusters 2\nmode 0 1.0\nsaddle 0 5 0.3\n";
  }
  EXPECT_THROW(pcl_animseg::io::loadSegmentationInfo(path, back), pcl_animseg::Error);
  {
    std::ofstream bad(path);
    bad << "clusters 2\nmode 0 1.0\n";  // cluster 1 has no mode line
  }
  EXPECT_THROW(pcl_animseg::io::loadSegmentationInfo(path, back), pcl_animseg::Error);
  std::remove(path.c_str());
}
