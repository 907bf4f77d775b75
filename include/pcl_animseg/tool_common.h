#pragma once
/** \file tool_common.h What every command-line tool shares: option parsing, --help/--quiet,
 * and the `error: ...` + exit 1 contract. Tools stay thin: all the work is in the library. */
#include <boost/program_options.hpp>

#include <functional>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace tools {

/** \brief Parsed options of a tool plus the two flags every tool has. */
struct ToolContext {
  boost::program_options::variables_map vm;
  bool quiet = false;
  bool verbose = false;
  /** Worker threads the tool runs with (--threads, else OpenMP's default). */
  int threads = 1;
  /** Path of the --config file that was applied (empty when none). */
  std::string config_path;
  /** Every option's effective value (command line, else config file, else default) as a JSON
   * object, so that outputs can print back exactly what was run. */
  std::string optionsJson() const;
};

/** \brief Runs a tool's body: adds --help/--quiet/--verbose/--config/--threads to `options`, parses
 * argv (unknown options and missing required ones are errors), prints help on --help, and turns
 * every exception into one line `error: <message>` on stderr with exit code 1. `usage` is the
 * synopsis.
 *
 * `--config FILE` is a JSON object whose keys are the tool's long option names (without dashes);
 * values are numbers, strings, booleans (for flags) or arrays (joined with commas, e.g.
 * "weights": [0.5, 0.5, 2, 1]). The command line wins over the file; an unknown key is an error. */
int runTool(int argc, char** argv, const std::string& name, const std::string& usage,
            boost::program_options::options_description options,
            const std::function<int(const ToolContext&)>& body);

/** \brief Escapes a string for a JSON string literal (without the quotes). */
std::string jsonEscape(const std::string& text);

/** \brief A JSON array of the strings, escaped: `["a", "b"]` (`[]` for none). */
std::string jsonStringArray(const std::vector<std::string>& items);

/** \brief Parses "a,b,c,d" into exactly `n` numbers; throws Error otherwise. */
std::vector<double> parseNumberList(const std::string& text, std::size_t n, const std::string& what);

}  // namespace tools
}  // namespace pcl_animseg
