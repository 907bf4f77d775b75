// Atomic output under a forced abort: `animseg` is killed with SIGKILL at several moments (fixed
// delays, and as soon as it has started writing) and OUT must then hold only complete files: every
// NAME.labels has one line per input point, every NAME.pcd / NAME.ply loads with that many points,
// the JSON files parse. Killed runs may leave hidden temporaries (.NAME.tmp.PID, never a final
// name); the next run into the same OUT removes them.
#include "tools/cli_util.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <pcl_animseg/io/frame_readers.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>

#include <boost/property_tree/json_parser.hpp>
#include <boost/property_tree/ptree.hpp>
#include <chrono>
#include <map>
#include <thread>

extern char** environ;

namespace fs = std::filesystem;
using namespace cli_test;

namespace {

using Clock = std::chrono::steady_clock;

/** Starts `argv` with stdout/stderr to /dev/null; returns the pid. */
pid_t spawn(const std::vector<std::string>& args) {
  std::vector<char*> argv;
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 2, "/dev/null", O_WRONLY, 0);
  pid_t pid = -1;
  const int rc = posix_spawn(&pid, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  return rc == 0 ? pid : -1;
}

bool hasVisibleFile(const fs::path& dir) {
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir, ec))
    if (e.path().filename().string()[0] != '.') return true;
  return false;
}

/** What a kill left: whether the process had already exited by itself. */
struct KillResult {
  bool finished = false;
  int exit_code = -1;
};

/** Runs animseg; kills it after `delay`, or (when `on_first_output`) as soon as a visible file
 * appears in `out` plus `delay`. */
KillResult runAndKill(const std::vector<std::string>& args, const fs::path& out,
                      std::chrono::milliseconds delay, bool on_first_output) {
  const pid_t pid = spawn(args);
  EXPECT_GT(pid, 0);
  KillResult result;
  if (pid <= 0) return result;
  const auto start = Clock::now();
  auto deadline = on_first_output ? Clock::time_point::max() : start + delay;
  const auto give_up = start + std::chrono::seconds(40);
  int status = 0;
  while (true) {
    const pid_t w = waitpid(pid, &status, WNOHANG);
    if (w == pid) {  // it finished before we killed it: the outputs must be complete anyway
      result.finished = true;
      result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
      return result;
    }
    const auto now = Clock::now();
    if (on_first_output && deadline == Clock::time_point::max() && hasVisibleFile(out))
      deadline = now + delay;
    if (now >= deadline || now >= give_up) break;
    std::this_thread::sleep_for(std::chrono::microseconds(200));
  }
  kill(pid, SIGKILL);
  waitpid(pid, &status, 0);
  return result;
}

/** Number of points of every input frame, by name. */
std::map<std::string, std::size_t> inputSizes(const fs::path& in) {
  std::map<std::string, std::size_t> sizes;
  for (const auto& e : fs::directory_iterator(in))
    if (e.path().extension() == ".ply")
      sizes[e.path().stem().string()] = pcl_animseg::io::readPLY(e.path().string()).points.size();
  return sizes;
}

/** Every visible file in `out` is complete; returns how many were checked. */
int checkComplete(const fs::path& out, const std::map<std::string, std::size_t>& sizes) {
  int checked = 0;
  std::error_code ec;
  if (!fs::exists(out, ec)) return 0;
  for (const auto& e : fs::directory_iterator(out)) {
    const std::string name = e.path().filename().string();
    const std::string ext = e.path().extension().string();
    const std::string stem = e.path().stem().string();
    if (name[0] == '.') {
      // A killed run's temporary: hidden, with the temp marker, never a final name.
      EXPECT_NE(name.find(".tmp."), std::string::npos) << "unexpected hidden file " << name;
      continue;
    }
    SCOPED_TRACE(name);
    EXPECT_EQ(name.find(".tmp"), std::string::npos);
    ++checked;
    if ((ext == ".labels" || ext == ".pcd" || ext == ".ply") && !sizes.count(stem)) {
      ADD_FAILURE() << "output of an unknown frame";
      continue;
    }
    if (ext == ".labels") {
      const std::string text = slurp(e.path().string());
      EXPECT_TRUE(!text.empty() && text.back() == '\n');
      EXPECT_EQ(static_cast<std::size_t>(countLines(text)), sizes.at(stem));
    } else if (ext == ".pcd" || ext == ".ply") {
      pcl_animseg::io::RawFrame raw;
      EXPECT_NO_THROW(raw = pcl_animseg::io::readRawFrame(e.path().string()));
      EXPECT_EQ(raw.points.size(), sizes.at(stem));
    } else if (ext == ".json") {
      boost::property_tree::ptree tree;
      EXPECT_NO_THROW(boost::property_tree::read_json(e.path().string(), tree));
    } else {
      EXPECT_GT(fs::file_size(e.path()), 0u);
    }
  }
  return checked;
}

}  // namespace

TEST(AtomicKill, KilledRunsLeaveOnlyCompleteFiles) {
  TempDir tmp;
  const fs::path in = tmp.dir() / "in";
  const RunResult g = run(tool("animseg_synth") + " --quiet --plan humanoid --frames 4 --points 800 "
                              "--seed 11 --output " + in.string(), tmp.dir());
  ASSERT_EQ(g.code, 0) << g.err;
  const auto sizes = inputSizes(in);
  ASSERT_EQ(sizes.size(), 4u);
  const fs::path out = tmp.dir() / "out";
  const std::vector<std::string> args = {tool("animseg"), "--quiet", "--seed", "3", "--input",
                                         in.string(), "--output", out.string()};
  using std::chrono::milliseconds;
  struct Moment {
    milliseconds delay;
    bool on_first_output;
  };
  // Fixed delays land in loading / features / segmentation; the others in the write stage.
  const Moment moments[] = {{milliseconds(300), false}, {milliseconds(1000), false},
                            {milliseconds(2000), false}, {milliseconds(0), true},
                            {milliseconds(5), true},     {milliseconds(30), true}};
  int killed_while_writing = 0;
  for (const Moment& m : moments) {
    SCOPED_TRACE("kill after " + std::to_string(m.delay.count()) + " ms" +
                 (m.on_first_output ? " of writing" : ""));
    // Each kill gets a fresh OUT, except that the write-stage kills reuse it: a rerun over a killed
    // run's leftovers is what a user does.
    if (!m.on_first_output) fs::remove_all(out);
    const KillResult k = runAndKill(args, out, m.delay, m.on_first_output);
    if (k.finished) {
      EXPECT_EQ(k.exit_code, 0);
    }
    if (m.on_first_output && !k.finished) ++killed_while_writing;
    checkComplete(out, sizes);
  }
  EXPECT_GT(killed_while_writing, 0) << "no kill landed in the write stage";

  // A complete run into the same OUT: every output present and complete, no temporaries left.
  const RunResult r = run(tool("animseg") + " --quiet --seed 3 --input " + in.string() +
                              " --output " + out.string(), tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_GE(checkComplete(out, sizes), 4 * 3 + 2);  // NAME.labels/.pcd/.ply, summary, transforms
  for (const auto& e : fs::directory_iterator(out))
    EXPECT_EQ(e.path().filename().string().find(".tmp."), std::string::npos)
        << "stale temporary " << e.path().filename();
}
