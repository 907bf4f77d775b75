#include <pcl_animseg/progress.h>

#include <gtest/gtest.h>

TEST(Progress, RecordsStagesAndNestedSubStages) {
  pcl_animseg::Progress p(/*quiet=*/true);
  p.begin("load", 3);
  for (std::size_t i = 1; i <= 3; ++i) p.update(i);
  p.end();
  p.begin("mean_shift");
  p.begin("tracking");
  p.end();
  p.begin("clustering");
  p.end();
  p.end();
  const auto& t = p.timings();
  ASSERT_EQ(t.size(), 4u);
  EXPECT_EQ(t[0].first, "load");
  EXPECT_EQ(t[1].first, "mean_shift/tracking");
  EXPECT_EQ(t[2].first, "mean_shift/clustering");
  EXPECT_EQ(t[3].first, "mean_shift");
  // The parent's time covers its sub-stages.
  EXPECT_GE(t[3].second, t[1].second + t[2].second);
  EXPECT_EQ(p.end(), 0.0);  // nothing open: a no-op
  EXPECT_GE(p.elapsed(), t[3].second);
}

TEST(Progress, AStageRunAgainAddsToItsRecord) {
  pcl_animseg::Progress p(/*quiet=*/true);
  for (int block = 0; block < 3; ++block) {
    p.begin("scale_space");
    p.end();
    p.begin("keypoints");
    p.end();
  }
  const auto& t = p.timings();
  ASSERT_EQ(t.size(), 2u);
  EXPECT_EQ(t[0].first, "scale_space");
  EXPECT_EQ(t[1].first, "keypoints");
  EXPECT_GE(t[0].second, 0.0);
  EXPECT_GT(pcl_animseg::peakResidentMiB(), 1.0);  // a running test binary uses a few MiB
}
