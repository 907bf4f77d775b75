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

// The host's steal is the 8th number of /proc/stat's "cpu" line (the sum over the CPUs), in
// clock ticks; anything else there is not a steal.
TEST(HostSteal, ReadsTheCpuLinesEighthNumber) {
  const std::string stat =
      "cpu  4705 356 584 3699176 23 23 0 250 0 0\n"
      "cpu0 1393 280 234 852248 13 0 0 125 0 0\n"
      "cpu1 3312 76 350 2846928 10 23 0 125 0 0\n"
      "intr 114930548 113199788 3 0 5 263 0 4 [...]\n";
  EXPECT_DOUBLE_EQ(pcl_animseg::parseCpuSteal(stat, 100.0), 2.5);
  EXPECT_DOUBLE_EQ(pcl_animseg::parseCpuSteal(stat, 1000.0), 0.25);
  // Only the sum's line counts, wherever it is.
  EXPECT_DOUBLE_EQ(pcl_animseg::parseCpuSteal("cpu0 1 2 3 4 5 6 7 8\ncpu 1 1 1 1 1 1 1 9\n", 1.0),
                   9.0);
  // A kernel that does not count it (7 numbers), words, negative numbers, no cpu line, no
  // clock: unknown.
  EXPECT_LT(pcl_animseg::parseCpuSteal("cpu  4705 356 584 3699176 23 23 0\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuSteal("cpu  4705 356 584 x 23 23 0 250\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuSteal("cpu  4705 356 584 3 23 23 0 -250\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuSteal("cpu0 1 2 3 4 5 6 7 8\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuSteal("", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuSteal("cpu  1 2 3 4 5 6 7 8\n", 0.0), 0.0);
}

// The machine's own count, where its kernel keeps one: a number that does not go down.
TEST(HostSteal, ThisMachinesCountOnlyGrows) {
  EXPECT_GE(pcl_animseg::onlineCpus(), 1);
  const double a = pcl_animseg::cpuStealSeconds();
  if (a < 0.0) GTEST_SKIP() << "this machine's kernel does not count steal (/proc/stat)";
  volatile double x = 0.0;
  for (int i = 0; i < 1000000; ++i) x = x + 1.0;
  const double b = pcl_animseg::cpuStealSeconds();
  EXPECT_GE(b, a);
  // The steal over a run: at least 0, and at most what the count grew by since its start.
  const double since = pcl_animseg::cpuStealSince(a);
  EXPECT_GE(since, 0.0);
  EXPECT_LE(since, pcl_animseg::cpuStealSeconds() - a);
  EXPECT_LT(pcl_animseg::cpuStealSince(-1.0), 0.0);  // an unknown start: unknown
}

// A share of the CPUs' time over 2%, and at least 5 clock ticks of it, gets a note that says
// how much; less, or an unknown steal, none.
TEST(HostSteal, NotesANotableShareOfTheCpusTime) {
  using pcl_animseg::hostStealNote;
  // 0.48 CPU s of 16 CPUs over 1 s: 3%.
  const std::string note = hostStealNote(0.48, 1.0, 16);
  EXPECT_NE(note.find("took 3.0% of its CPUs' time"), std::string::npos) << note;
  EXPECT_NE(note.find("0.48 CPU seconds of steal"), std::string::npos) << note;
  EXPECT_TRUE(hostStealNote(0.16, 1.0, 16).empty());  // 1%
  EXPECT_TRUE(hostStealNote(0.32, 1.0, 16).empty());  // exactly 2%
  EXPECT_TRUE(hostStealNote(0.04, 0.1, 2).empty());   // 20%, but 4 ticks
  EXPECT_FALSE(hostStealNote(0.05, 0.1, 2).empty());  // 25%, 5 ticks
  EXPECT_TRUE(hostStealNote(-1.0, 1.0, 16).empty());  // unknown
  EXPECT_TRUE(hostStealNote(0.5, 0.0, 16).empty());   // no time
  EXPECT_TRUE(hostStealNote(0.5, 1.0, 0).empty());    // no CPUs
}
