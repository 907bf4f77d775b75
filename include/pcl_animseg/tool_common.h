#pragma once
/** \file tool_common.h What every command-line tool shares: option parsing, --help/--quiet,
 * and the `error: ...` + exit 1 contract. Tools stay thin: all the work is in the library. */
#include <boost/program_options.hpp>

#include <functional>
#include <string>

namespace pcl_animseg {
namespace tools {

/** \brief Parsed options of a tool plus the two flags every tool has. */
struct ToolContext {
  boost::program_options::variables_map vm;
  bool quiet = false;
  bool verbose = false;
};

/** \brief Runs a tool's body: adds --help/--quiet/--verbose to `options`, parses argv (unknown
 * options and missing required ones are errors), prints help on --help, and turns every exception
 * into one line `error: <message>` on stderr with exit code 1. `usage` is the synopsis line(s). */
int runTool(int argc, char** argv, const std::string& name, const std::string& usage,
            boost::program_options::options_description options,
            const std::function<int(const ToolContext&)>& body);

/** \brief Parses "a,b,c,d" into exactly `n` numbers; throws Error otherwise. */
std::vector<double> parseNumberList(const std::string& text, std::size_t n, const std::string& what);

}  // namespace tools
}  // namespace pcl_animseg
