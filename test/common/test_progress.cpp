#include <gtest/gtest.h>
#include <pcl_animseg/progress.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>

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
  // readCpu() reads the same count with the busy time, one reading of /proc/stat for both.
  const pcl_animseg::CpuReading r0 = pcl_animseg::readCpu();
  const double c = pcl_animseg::cpuStealSeconds();
  const pcl_animseg::CpuReading r1 = pcl_animseg::readCpu();
  EXPECT_GE(r0.steal, b);
  EXPECT_LE(r0.steal, c);
  EXPECT_GE(r1.steal, c);
  EXPECT_GE(pcl_animseg::cpuStealBetween(r0, r1), 0.0);
  EXPECT_LE(pcl_animseg::cpuStealBetween(r0, r1), r1.steal - r0.steal + 1e-12);
  EXPECT_LT(pcl_animseg::cpuStealBetween(pcl_animseg::CpuReading(), r1), 0.0);  // unknown
}

// Between two readings: the steal's growth and the other programs' share of the busy time's,
// taken from the readings given (no reading of their own).
TEST(CpuReadings, DifferencesOfTwoReadings) {
  pcl_animseg::CpuReading a, b;
  a.machine_busy = 100.0, a.own = 10.0, a.steal = 5.0;
  b.machine_busy = 103.0, b.own = 11.5, b.steal = 5.25;
  EXPECT_DOUBLE_EQ(pcl_animseg::otherProgramsCpuBetween(a, b), 1.5);
  EXPECT_DOUBLE_EQ(pcl_animseg::cpuStealBetween(a, b), 0.25);
  // This process's time grew by more than the machine's count (ticks against microseconds):
  // none, never a negative share.
  b.own = 14.0;
  EXPECT_DOUBLE_EQ(pcl_animseg::otherProgramsCpuBetween(a, b), 0.0);
  // Any unknown reading: unknown.
  pcl_animseg::CpuReading unknown = b;
  unknown.machine_busy = -1.0;
  EXPECT_LT(pcl_animseg::otherProgramsCpuBetween(a, unknown), 0.0);
  unknown = b;
  unknown.steal = -1.0;
  EXPECT_LT(pcl_animseg::cpuStealBetween(a, unknown), 0.0);
  EXPECT_GE(pcl_animseg::otherProgramsCpuBetween(a, unknown), 0.0);  // the busy time is known
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

// The machine's busy time is the 1st, 2nd, 3rd, 6th and 7th numbers of /proc/stat's "cpu" line
// (user, nice, system, irq, softirq), not idle, iowait or steal.
TEST(OtherPrograms, ReadsTheCpuLinesBusyNumbers) {
  const std::string stat =
      "cpu  4705 356 584 3699176 23 23 7 250 0 0\n"
      "cpu0 1393 280 234 852248 13 0 0 125 0 0\n";
  EXPECT_DOUBLE_EQ(pcl_animseg::parseCpuBusy(stat, 100.0), (4705 + 356 + 584 + 23 + 7) / 100.0);
  EXPECT_DOUBLE_EQ(pcl_animseg::parseCpuBusy("cpu0 9 9 9 9 9 9 9\ncpu 1 2 3 100 200 4 5\n", 1.0),
                   15.0);
  EXPECT_LT(pcl_animseg::parseCpuBusy("cpu  4705 356 584 3699176 23 23\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuBusy("cpu  4705 x 584 3699176 23 23 0\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuBusy("cpu0 1 2 3 4 5 6 7\n", 100.0), 0.0);
  EXPECT_LT(pcl_animseg::parseCpuBusy("cpu  1 2 3 4 5 6 7\n", 0.0), 0.0);
}

// Another program's CPU time is counted: a child process that spins for 0.6 s of its own CPU
// time, while this one waits, is at least 0.3 CPU seconds of other programs' time, and this
// process's own spinning is not (its own CPU time is taken off). Each spins until its own CPU
// time has grown by as much (at most 20 s of wall time), whatever else the machine runs.
TEST(OtherPrograms, CountsAnotherProcesssTimeNotThisOnes) {
  const pcl_animseg::CpuReading start = pcl_animseg::readCpu();
  if (start.machine_busy < 0.0 || start.own < 0.0)
    GTEST_SKIP() << "this machine does not say its CPUs' busy time (/proc/stat, getrusage)";
  auto spin = [](double cpu_seconds) {
    const double own0 = pcl_animseg::processCpuSeconds();
    const auto t0 = std::chrono::steady_clock::now();
    volatile double x = 0.0;
    while (pcl_animseg::processCpuSeconds() - own0 < cpu_seconds &&
           std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() < 20.0)
      for (int i = 0; i < 100000; ++i) x = x + 1.0;
  };
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    spin(0.6);
    _exit(0);
  }
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  const double other = pcl_animseg::otherProgramsCpuSince(start);
  EXPECT_GE(other, 0.3);
  // This process spinning alone: its own time grows by as much, and is taken off.
  const pcl_animseg::CpuReading mine = pcl_animseg::readCpu();
  spin(0.6);
  EXPECT_GE(pcl_animseg::processCpuSeconds() - mine.own, 0.3);
  EXPECT_GE(pcl_animseg::otherProgramsCpuSince(mine), 0.0);
  EXPECT_LT(pcl_animseg::otherProgramsCpuSince(pcl_animseg::CpuReading()), 0.0);  // unknown
}

// At least 10% of the CPUs' time and 0.2 CPU seconds, where the run's threads did not fit beside
// the others, get a note that says how much, with what to do; less, or an unknown count, none.
TEST(OtherPrograms, NotesANotableShareWithTheRemedy) {
  using pcl_animseg::otherProgramsNote;
  // 16 CPU s of 32 CPUs over 1 s: 50%.
  const std::string note = otherProgramsNote(16.0, 1.0, 32, 32);
  EXPECT_NE(note.find("other programs used 50% of the CPUs' time"), std::string::npos) << note;
  EXPECT_NE(note.find("16.0 CPU seconds"), std::string::npos) << note;
  EXPECT_NE(note.find("this run's 32 threads shared 32 CPUs"), std::string::npos) << note;
  EXPECT_NE(note.find("--threads"), std::string::npos) << note;
  EXPECT_NE(note.find("OMP_WAIT_POLICY=passive"), std::string::npos) << note;
  EXPECT_TRUE(otherProgramsNote(1.5, 1.0, 16, 16).empty());   // 9%
  EXPECT_FALSE(otherProgramsNote(1.6, 1.0, 16, 16).empty());  // 10%
  EXPECT_TRUE(otherProgramsNote(0.19, 0.5, 2, 2).empty());    // 19%, but under 0.2 CPU s
  // Runs that fit beside the others: 10 CPUs busy on average beside 16 threads of 32 CPUs, 5
  // beside 8 of 16; 9 beside 8 of 16 do not fit.
  EXPECT_TRUE(otherProgramsNote(11.5, 1.15, 32, 16).empty());
  EXPECT_TRUE(otherProgramsNote(5.0, 1.0, 16, 8).empty());
  EXPECT_NE(otherProgramsNote(9.0, 1.0, 16, 8).find("this run's 8 threads shared 16 CPUs"),
            std::string::npos);
  EXPECT_TRUE(otherProgramsNote(-1.0, 1.0, 16, 16).empty());  // unknown
  EXPECT_TRUE(otherProgramsNote(5.0, 0.0, 16, 16).empty());   // no time
  EXPECT_TRUE(otherProgramsNote(5.0, 1.0, 0, 16).empty());    // no CPUs
}
