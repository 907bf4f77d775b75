#pragma once
/** \file launch_args.h What the `animseg` program (tools/animseg.cpp) reads of its command line
 * before it loads the pipeline, which parses it whole (Boost.Program_options). */
#include <cstddef>
#include <cstring>
#include <string>

namespace pcl_animseg {
namespace tools {

// Whether `arg` names option `name` ("--name" or "--name=VALUE", or the shorter prefix of
// "--name" that the option parser also accepts: "--dev"); `value` gets VALUE where given.
inline bool names(const char* arg, const char* name, std::string& value, bool& exact) {
  if (std::strncmp(arg, "--", 2) != 0 || arg[2] == '\0') return false;
  const char* a = arg + 2;
  const char* eq = std::strchr(a, '=');
  const std::size_t len = eq ? static_cast<std::size_t>(eq - a) : std::strlen(a);
  if (len > std::strlen(name) || std::strncmp(a, name, len) != 0) return false;
  exact = len == std::strlen(name);
  value = eq ? std::string(eq + 1) : std::string();
  return true;
}

// Whether the command line asks for a run that starts the GPU anyway, so that starting its
// driver now is only earlier: not --help, not --device cpu, and nothing this scan cannot read
// for sure, where the program decides itself (then the driver starts as before, in the
// program):
// - --device gpu:N, which first makes GPU N the only one visible (CUDA_VISIBLE_DEVICES);
// - --config FILE, which may name a device;
// - an option abbreviated to a prefix of --device or --config.
inline bool startsGpu(int argc, char** argv) {
  std::string device = "auto";
  for (int i = 1; i < argc; ++i) {
    const char* a = argv[i];
    if (std::strcmp(a, "-h") == 0) return false;
    std::string value;
    bool exact = false;
    if (names(a, "help", value, exact) || names(a, "config", value, exact)) return false;
    if (names(a, "device", value, exact)) {
      if (!exact) return false;
      if (std::strchr(a, '=')) {
        device = value;
      } else if (i + 1 < argc) {
        device = argv[++i];
      } else {
        return false;  // the program says what is missing
      }
    }
  }
  return device == "auto" || device == "gpu";
}

}  // namespace tools
}  // namespace pcl_animseg
