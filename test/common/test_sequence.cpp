#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/sequence.h>

using pcl_animseg::PointCloudSequence;

namespace {
PointCloudSequence::Cloud::Ptr grid(int n, float step) {
  PointCloudSequence::Cloud::Ptr c(new PointCloudSequence::Cloud);
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      pcl::PointNormal p;
      p.x = i * step;
      p.y = j * step;
      p.z = 0;
      p.normal_x = p.normal_y = 0;
      p.normal_z = 1;
      c->push_back(p);
    }
  return c;
}
}  // namespace

TEST(PointCloudSequence, OffsetsFrameIdsAndFlatten) {
  PointCloudSequence seq;
  seq.addFrame(grid(4, 1.f), "a");
  seq.addFrame(grid(5, 1.f), "b");
  ASSERT_EQ(seq.size(), 2u);
  EXPECT_EQ(seq.totalPoints(), 41u);
  const auto off = seq.offsets();
  ASSERT_EQ(off.size(), 3u);
  EXPECT_EQ(off[1], 16u);
  EXPECT_EQ(off[2], 41u);
  const auto ids = seq.frameIds();
  EXPECT_EQ(ids[15], 0);
  EXPECT_EQ(ids[16], 1);
  EXPECT_EQ(seq.flatten()->size(), 41u);
}

TEST(PointCloudSequence, InputOrderKeepsDroppedPointsAsMinusOne) {
  PointCloudSequence seq;
  // 4 kept points that were input points 0, 2, 3, 5 of 6.
  seq.addFrame(grid(2, 1.f), "a", "", {0, 2, 3, 5}, 6);
  const auto out = seq.toInputOrder(0, {7, 8, 9, 10});
  EXPECT_EQ(out, (std::vector<int>{7, -1, 8, 9, -1, 10}));
  EXPECT_THROW(seq.toInputOrder(0, {1, 2}), pcl_animseg::Error);
  EXPECT_THROW(seq.addFrame(grid(2, 1.f), "b", "", {0, 1, 2, 9}, 6), pcl_animseg::Error);
}

TEST(PointCloudSequence, MeanSpacingAndDiagonal) {
  const auto c = grid(10, 0.5f);
  EXPECT_NEAR(pcl_animseg::meanSpacing(*c), 0.5, 1e-6);
  EXPECT_NEAR(pcl_animseg::boundingBoxDiagonal(*c), std::sqrt(2.0) * 4.5, 1e-5);
  PointCloudSequence::Cloud same;
  same.resize(5);
  for (auto& p : same) p.x = p.y = p.z = 1.f;
  EXPECT_THROW(pcl_animseg::meanSpacing(same), pcl_animseg::Error);
}

TEST(PointCloudSequence, MeanSpacingsOfEveryFrameAndTheFrameThatHasNone) {
  PointCloudSequence seq;
  for (int t = 0; t < 9; ++t) seq.addFrame(grid(6 + t, 0.1f * (t + 1)), "f" + std::to_string(t));
  const std::vector<double> s = pcl_animseg::meanSpacings(seq);
  ASSERT_EQ(s.size(), 9u);
  for (int t = 0; t < 9; ++t) EXPECT_EQ(s[t], pcl_animseg::meanSpacing(*seq.frame(t))) << t;
  EXPECT_NEAR(s[4], 0.5, 1e-6);
  // From trees the caller built: the same values.
  std::vector<pcl_animseg::KdTree<pcl::PointNormal>> trees(9);
  auto tree_of = [&](std::size_t t) -> const pcl_animseg::KdTree<pcl::PointNormal>& {
    return trees[t];
  };
  for (int t = 0; t < 9; ++t) {
    trees[t].setInputCloud(seq.frame(t));
    EXPECT_EQ(pcl_animseg::meanSpacing(*seq.frame(t), trees[t]), s[t]) << t;
    EXPECT_EQ(pcl_animseg::meanSpacing(*seq.frame(t), trees[t], 7),
              pcl_animseg::meanSpacing(*seq.frame(t), 7))
        << t;
  }
  EXPECT_EQ(pcl_animseg::meanSpacings(seq, tree_of), s);
  PointCloudSequence::Cloud::Ptr same(new PointCloudSequence::Cloud);
  same->resize(5);
  for (auto& p : *same) p.x = p.y = p.z = 1.f;
  seq.addFrame(same, "flat");
  trees.emplace_back();
  trees.back().setInputCloud(same);
  for (int with_trees = 0; with_trees < 2; ++with_trees) {
    try {
      with_trees ? pcl_animseg::meanSpacings(seq, tree_of) : pcl_animseg::meanSpacings(seq);
      FAIL() << "a frame of coinciding points has no spacing";
    } catch (const pcl_animseg::Error& e) {
      EXPECT_NE(std::string(e.what()).find("frame flat"), std::string::npos) << e.what();
    }
  }
}
