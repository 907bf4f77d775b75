// The command-line contract of `animseg_meanshift`: outputs in input order, segmentation.txt that
// the hierarchy stage reads, bad input.
#include <gtest/gtest.h>
#include <pcl_animseg/io/segmentation_io.h>

#include <fstream>

#include "tools/cli_util.h"

namespace fs = std::filesystem;
using namespace cli_test;

namespace {

// Three frames of one sphere (points + normals), the middle one with NaN points.
void makeSequence(const fs::path& dir) {
  fs::create_directories(dir);
  for (int t = 0; t < 3; ++t)
    writeSphereXYZ((dir / ("f" + std::to_string(t) + ".xyz")).string(), 250 + 30 * t, 0.05 * t,
                   3 + t, t == 1 ? 40 : 0);
}

}  // namespace

TEST(MeanShiftCli, WritesLabelsPcdAndSegmentationInfo) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  for (const char* method : {"paper", "motion"}) {
    const std::string out = tmp.str() + "/out_" + method;
    const RunResult r = run(tool("animseg_meanshift") + " --quiet --no-features --input " +
                                tmp.str() + "/in --output " + out + " --method " + method +
                                " --bandwidth 0.2",
                            tmp.dir());
    ASSERT_EQ(r.code, 0) << r.err;
    EXPECT_TRUE(r.err.empty()) << r.err;  // --quiet
    for (int t = 0; t < 3; ++t) {
      const std::string base = out + "/f" + std::to_string(t);
      ASSERT_TRUE(fs::exists(base + ".pcd")) << base;
      const std::string labels = slurp(base + ".labels");
      EXPECT_EQ(countLines(labels), 250 + 30 * t) << base;
      if (t == 1) {
        std::istringstream ls(labels);
        std::string line;
        for (int i = 0; std::getline(ls, line); ++i) {
          if (i % 40 == 39) {
            EXPECT_EQ(line, "-1") << "NaN point " << i;
          }
        }
      }
    }
    pcl_animseg::segmentation::SegmentationResult info;
    ASSERT_NO_THROW(pcl_animseg::io::loadSegmentationInfo(out + "/segmentation.txt", info));
    EXPECT_GE(info.num_clusters, 1);
    EXPECT_EQ(static_cast<int>(info.mode_density.size()), info.num_clusters);
  }
}

// The paper method's filter knobs reach the Gaussian kd-tree: one cell holding every point gives
// one cluster, and without the exact steps the filter's ripples leave more clusters.
TEST(MeanShiftCli, PaperOptionsReachTheFilter) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  auto clusters = [&](const std::string& extra) {
    const std::string out = tmp.str() + "/out";
    fs::remove_all(out);
    const RunResult r = run(tool("animseg_meanshift") + " --quiet --no-features --input " +
                                tmp.str() + "/in --output " + out +
                                " --method paper --bandwidth 0.1" + extra,
                            tmp.dir());
    EXPECT_EQ(r.code, 0) << extra << ": " << r.err;
    pcl_animseg::segmentation::SegmentationResult info;
    pcl_animseg::io::loadSegmentationInfo(out + "/segmentation.txt", info);
    return info.num_clusters;
  };
  const int plain = clusters("");
  EXPECT_EQ(clusters(" --cell-min-points 100000"), 1);
  EXPECT_GT(clusters(" --exact-steps 0"), plain);
  // --exact-borders reaches the stage: its border points run exact trajectories (logged with
  // their count), and a config file's true means the same.
  const std::string out = tmp.str() + "/borders";
  const std::string cmd = tool("animseg_meanshift") + " --no-features --input " + tmp.str() +
                          "/in --output " + out + " --method paper --bandwidth 0.1";
  const RunResult on = run(cmd + " --exact-borders", tmp.dir());
  EXPECT_EQ(on.code, 0) << on.err;
  EXPECT_NE(on.err.find("exact border trajectories"), std::string::npos) << on.err;
  EXPECT_NE(on.err.find(" points"), std::string::npos) << on.err;
  { std::ofstream(tmp.str() + "/borders.json") << "{\"exact-borders\": true}"; }
  fs::remove_all(out);
  const RunResult config = run(cmd + " --config " + tmp.str() + "/borders.json", tmp.dir());
  EXPECT_EQ(config.code, 0) << config.err;
  EXPECT_NE(config.err.find("exact border trajectories"), std::string::npos) << config.err;
  fs::remove_all(out);
  const RunResult off = run(cmd, tmp.dir());
  EXPECT_EQ(off.code, 0) << off.err;
  EXPECT_EQ(off.err.find("exact border trajectories"), std::string::npos) << off.err;
}

// --reference-frame: the motion method's parts are made on that frame's points; the last of
// three frames works as well as the first, and one past it is an error (BadInputIsOneErrorLine).
TEST(MeanShiftCli, ReferenceFrameOption) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  for (const char* ref : {"0", "2"}) {
    const std::string out = tmp.str() + "/out" + ref;
    const RunResult r = run(tool("animseg_meanshift") + " --quiet --no-features --input " +
                                tmp.str() + "/in --output " + out + " --reference-frame " + ref,
                            tmp.dir());
    ASSERT_EQ(r.code, 0) << ref << ": " << r.err;
    for (int t = 0; t < 3; ++t)
      EXPECT_EQ(countLines(slurp(out + "/f" + std::to_string(t) + ".labels")), 250 + 30 * t)
          << ref;
  }
  const RunResult past = run(tool("animseg_meanshift") + " --no-features --input " + tmp.str() +
                                 "/in --output " + tmp.str() + "/out3 --reference-frame 3",
                             tmp.dir());
  EXPECT_EQ(past.code, 1);
  EXPECT_NE(past.err.find("reference frame 3 is not in the sequence (frames 0-2)"),
            std::string::npos)
      << past.err;
}

TEST(MeanShiftCli, BadInputIsOneErrorLine) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  const std::string base = tool("animseg_meanshift") + " --no-features --input " + tmp.str() +
                           "/in --output " + tmp.str() + "/out";
  for (const std::string extra :
       {" --bandwidth 0", " --bandwidth -1", " --weights 1,2,3", " --weights 1,-1,1,1",
        " --method magic", " --backend magic", " --parts -2", " --motion-threshold 0",
        " --crease-cost -1", " --border-smoothness -1", " --dissolve-ratio -1", " --joint-weight -1", " --sliver-fraction 1", " --exact-steps -1", " --cell-extent 0",
        " --cell-min-points 0", " --reference-frame -1", " --reference-frame 3",
        " --no-such-option"}) {
    const RunResult r = run(base + extra, tmp.dir());
    EXPECT_EQ(r.code, 1) << extra;
    EXPECT_TRUE(isOneErrorLine(r.err)) << extra << ": " << r.err;
    EXPECT_FALSE(fs::exists(tmp.dir() / "out")) << extra;
  }
  const RunResult missing =
      run(tool("animseg_meanshift") + " --input " + tmp.str() + "/nope --output " + tmp.str() +
              "/out",
          tmp.dir());
  EXPECT_EQ(missing.code, 1);
  EXPECT_TRUE(isOneErrorLine(missing.err)) << missing.err;
  EXPECT_FALSE(fs::exists(tmp.dir() / "out"));
  const RunResult help = run(tool("animseg_meanshift") + " --help", tmp.dir());
  EXPECT_EQ(help.code, 0);
  EXPECT_NE(help.out.find("--backend"), std::string::npos);
}
