#include <pcl_animseg/error.h>
#include <pcl_animseg/tool_common.h>

#include <cmath>
#include <iostream>
#include <sstream>

namespace po = boost::program_options;

namespace pcl_animseg {
namespace tools {

int runTool(int argc, char** argv, const std::string& name, const std::string& usage,
            po::options_description options, const std::function<int(const ToolContext&)>& body) {
  try {
    options.add_options()("help,h", "show this help and exit")(
        "quiet,q", "no progress or timing on stderr")("verbose,v", "more detail on stderr");
    ToolContext ctx;
    try {
      po::store(po::command_line_parser(argc, argv).options(options).run(), ctx.vm);
      if (ctx.vm.count("help")) {
        std::cout << "Usage: " << usage << "\n\n" << options << std::endl;
        return 0;
      }
      po::notify(ctx.vm);
    } catch (const po::error& e) {
      throw Error(std::string(e.what()) + " (see " + name + " --help)");
    }
    ctx.quiet = ctx.vm.count("quiet") > 0;
    ctx.verbose = ctx.vm.count("verbose") > 0 && !ctx.quiet;
    return body(ctx);
  } catch (const std::bad_alloc&) {
    std::cerr << "error: out of memory" << std::endl;
  } catch (const std::exception& e) {
    std::string msg = e.what();
    for (char& c : msg)
      if (c == '\n') c = ' ';
    std::cerr << "error: " << msg << std::endl;
  }
  return 1;
}

std::vector<double> parseNumberList(const std::string& text, std::size_t n, const std::string& what) {
  std::vector<double> out;
  std::stringstream ss(text);
  std::string item;
  while (std::getline(ss, item, ',')) {
    std::size_t used = 0;
    double v = 0;
    try {
      v = std::stod(item, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    if (used == 0 || used != item.size() || !std::isfinite(v))
      throw Error(what + ": '" + item + "' is not a number");
    out.push_back(v);
  }
  if (out.size() != n)
    throw Error(what + ": expected " + std::to_string(n) + " comma-separated numbers, got '" + text +
                "'");
  return out;
}

}  // namespace tools
}  // namespace pcl_animseg
