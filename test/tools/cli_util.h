#pragma once
// Runs a built tool in a shell and captures its exit code, stdout and stderr (test helper).
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "temp_dir.h"

namespace cli_test {

struct RunResult {
  int code = -1;
  std::string out;
  std::string err;
};

inline std::string slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

inline std::string tool(const std::string& name) { return std::string(PCL_ANIMSEG_BIN_DIR) + "/" + name; }

/** Runs `command` (a shell command line) with stdout/stderr captured to files in `dir`. */
inline RunResult run(const std::string& command, const std::filesystem::path& dir) {
  const std::string o = (dir / "stdout.txt").string(), e = (dir / "stderr.txt").string();
  const int status = std::system((command + " >" + o + " 2>" + e + " </dev/null").c_str());
  RunResult r;
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.out = slurp(o);
  r.err = slurp(e);
  return r;
}

using animseg_test::TempDir;

/** Writes an XYZ point frame: a unit sphere at `cx` with `n` random points and outward normals;
 * `nan_every` > 0 turns every nan_every-th point into NaN coordinates. */
inline void writeSphereXYZ(const std::string& path, int n, double cx, unsigned seed, int nan_every = 0) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  std::ofstream f(path);
  for (int i = 0; i < n; ++i) {
    double x = g(rng), y = g(rng), z = g(rng);
    const double r = std::sqrt(x * x + y * y + z * z);
    x /= r;
    y /= r;
    z /= r;
    if (nan_every > 0 && i % nan_every == nan_every - 1) {
      f << "nan nan nan 0 0 1\n";
      continue;
    }
    f << x + cx << " " << y << " " << z << " " << x << " " << y << " " << z << "\n";
  }
}

inline int countLines(const std::string& text) {
  int n = 0;
  for (char c : text) n += c == '\n';
  return n;
}

/** Exactly one line of stderr starts with "error: ", and it is the last one (progress lines
 * of the stages that ran before the failure may precede it). */
inline bool isOneErrorLine(const std::string& err) {
  std::istringstream ss(err);
  std::string line, last;
  int errors = 0;
  while (std::getline(ss, line)) {
    if (line.rfind("error: ", 0) == 0) ++errors;
    last = line;
  }
  return errors == 1 && last.rfind("error: ", 0) == 0;
}

}  // namespace cli_test
