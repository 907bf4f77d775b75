// animseg_synth and animseg_eval end to end: the shipped fixtures' format, the error contract.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "cli_util.h"

using cli_test::run;
using cli_test::TempDir;
using cli_test::tool;
namespace fs = std::filesystem;

namespace {
/** Copies DIR/NAME.gt to PRED/NAME.labels, mapping each true label through `map`. */
template <class F>
void predictFromTruth(const fs::path& truth, const fs::path& pred, F map) {
  fs::create_directories(pred);
  for (const auto& e : fs::directory_iterator(truth)) {
    if (e.path().extension() != ".gt") continue;
    std::ifstream in(e.path());
    std::ofstream out(pred / (e.path().stem().string() + ".labels"));
    int l;
    while (in >> l) out << map(l) << " 0\n";
  }
}

/** Progress lines may come first (no --quiet); the error itself is exactly one last line. */
bool endsWithOneErrorLine(const std::string& err) {
  const std::size_t at = err.find("error: ");
  if (at == std::string::npos || err.find("error: ", at + 1) != std::string::npos) return false;
  if (at != 0 && err[at - 1] != '\n') return false;
  return cli_test::countLines(err.substr(at)) == 1 && err.back() == '\n';
}
}  // namespace

TEST(SynthEvalCli, PointSequencePerfectAndMergedPredictions) {
  TempDir tmp;
  const std::string seq = tmp.str() + "/seq";
  auto r = run(tool("animseg_synth") + " --output " + seq +
                   " --plan quadruped --frames 4 --points 600 --seed 5 --quiet",
               tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(r.err.empty());
  for (const char* f : {"f000.ply", "f000.gt", "f003.ply", "f003.gt", "synth.json"})
    EXPECT_TRUE(fs::exists(fs::path(seq) / f)) << f;
  EXPECT_FALSE(fs::exists(fs::path(seq) / "f004.ply"));

  predictFromTruth(seq, tmp.dir() / "perfect", [](int l) { return 100 + l; });
  r = run(tool("animseg_eval") + " --pred " + tmp.str() + "/perfect --truth " + seq, tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("pooled ARI          1.0000"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("n/a"), std::string::npos) << "point frames have no rigidity error";
  const std::string json = cli_test::slurp(tmp.str() + "/perfect/eval.json");
  EXPECT_NE(json.find("\"pooled_ari\": 1,"), std::string::npos) << json;
  EXPECT_NE(json.find("\"true_parts\": 12"), std::string::npos) << json;
  EXPECT_NE(json.find("\"part_names\": [\"torso\", \"neck\", \"head\""), std::string::npos) << json;

  // The neck predicted as the head: the table names the two as merged, by synth.json's names.
  predictFromTruth(seq, tmp.dir() / "merged", [](int l) { return l == 1 ? 2 : l; });
  r = run(tool("animseg_eval") + " --quiet --pred " + tmp.str() + "/merged --truth " + seq,
          tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("parts (pred/true)   11 / 12"), std::string::npos) << r.out;
  for (const char* row : {"\nneck ", "\nhead "}) {
    const std::size_t at = r.out.find(row);
    ASSERT_NE(at, std::string::npos) << row << "\n" << r.out;
    const std::string line = r.out.substr(at + 1, r.out.find('\n', at + 1) - at - 1);
    EXPECT_NE(line.find(std::string("merged with ") + (row[1] == 'n' ? "head" : "neck")),
              std::string::npos)
        << line;
    EXPECT_NE(line.find("1.0000"), std::string::npos) << line;  // recall
  }
  const std::size_t torso = r.out.find("\ntorso ");
  ASSERT_NE(torso, std::string::npos) << r.out;
  EXPECT_EQ(r.out.substr(torso + 1, r.out.find('\n', torso + 1) - torso - 1).find("merged"),
            std::string::npos);

  // Level 1 is all zeros: one predicted part.
  r = run(tool("animseg_eval") + " --pred " + tmp.str() + "/perfect --truth " + seq +
              " --level 1 --quiet --json " + tmp.str() + "/l1.json",
          tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(r.err.empty());
  EXPECT_NE(cli_test::slurp(tmp.str() + "/l1.json").find("\"predicted_parts\": 1,"),
            std::string::npos);
}

TEST(SynthEvalCli, MeshSequenceReportsRigidity) {
  TempDir tmp;
  const std::string seq = tmp.str() + "/mesh";
  auto r = run(tool("animseg_synth") + " --output " + seq +
                   " --plan snake --frames 3 --mesh --resolution 8 --quiet",
               tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  predictFromTruth(seq, tmp.dir() / "p", [](int l) { return l; });
  r = run(tool("animseg_eval") + " --pred " + tmp.str() + "/p --truth " + seq + " --quiet",
          tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.out.find("rigidity error      0.00000"), std::string::npos) << r.out;
  // Two true parts merged: not rigid any more.
  predictFromTruth(seq, tmp.dir() / "m", [](int l) { return l < 2 ? 0 : l; });
  r = run(tool("animseg_eval") + " --pred " + tmp.str() + "/m --truth " + seq + " --quiet",
          tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.out.find("rigidity error      0.00000"), std::string::npos) << r.out;
  EXPECT_EQ(cli_test::slurp(tmp.str() + "/m/eval.json").find("\"rigidity_error\": null"),
            std::string::npos);
}

TEST(SynthEvalCli, ErrorsAreOneLine) {
  TempDir tmp;
  const std::string seq = tmp.str() + "/seq";
  ASSERT_EQ(
      run(tool("animseg_synth") + " --output " + seq + " --frames 2 --points 100 --quiet", tmp.dir())
          .code,
      0);
  // A non-empty output directory is refused unless --force; --force replaces stale frames.
  auto r = run(tool("animseg_synth") + " --output " + seq + " --frames 1 --points 100", tmp.dir());
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(cli_test::isOneErrorLine(r.err)) << r.err;
  r = run(tool("animseg_synth") + " --output " + seq + " --frames 1 --points 100 --force --quiet",
          tmp.dir());
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(fs::exists(fs::path(seq) / "f000.ply"));
  EXPECT_FALSE(fs::exists(fs::path(seq) / "f001.ply"));

  for (const std::string& args :
       {" --output " + tmp.str() + "/x --plan octopus", " --output " + tmp.str() + "/x --frames 0",
        " --output " + tmp.str() + "/x --bogus", std::string(" --plan hand")}) {
    r = run(tool("animseg_synth") + args, tmp.dir());
    EXPECT_EQ(r.code, 1) << args;
    EXPECT_TRUE(cli_test::isOneErrorLine(r.err)) << args << ": " << r.err;
    EXPECT_FALSE(fs::exists(tmp.dir() / "x")) << args;
  }

  const std::string pred = tmp.str() + "/pred";
  fs::create_directories(pred);
  r = run(tool("animseg_eval") + " --pred " + pred + " --truth " + seq, tmp.dir());
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(endsWithOneErrorLine(r.err)) << r.err;
  EXPECT_NE(r.err.find("f000.labels"), std::string::npos) << r.err;
  {
    std::ofstream(pred + "/f000.labels") << "0\n1\n";  // too short
  }
  r = run(tool("animseg_eval") + " --pred " + pred + " --truth " + seq + " --quiet", tmp.dir());
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(cli_test::isOneErrorLine(r.err)) << r.err;
  EXPECT_NE(r.err.find("2 predicted labels"), std::string::npos) << r.err;
  r = run(tool("animseg_eval") + " --pred " + pred + " --truth " + seq + " --level 3 --quiet",
          tmp.dir());
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(cli_test::isOneErrorLine(r.err)) << r.err;
  r = run(tool("animseg_eval") + " --pred " + pred + " --truth " + seq + " --nope", tmp.dir());
  EXPECT_EQ(r.code, 1);
  EXPECT_TRUE(cli_test::isOneErrorLine(r.err)) << r.err;
}
