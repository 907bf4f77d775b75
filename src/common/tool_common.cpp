#include <omp.h>
#include <pcl/console/print.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/tool_common.h>
#include <time.h>
#include <unistd.h>

#include <boost/property_tree/json_parser.hpp>
#include <boost/property_tree/ptree.hpp>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <sstream>

namespace po = boost::program_options;

namespace pcl_animseg {
namespace tools {

std::string jsonEscape(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\t': out += "\\t"; break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof(buf), "\\u%04x", static_cast<unsigned>(c));
          out += buf;
        } else {
          out += c;
        }
    }
  }
  return out;
}

std::string jsonStringArray(const std::vector<std::string>& items) {
  std::string out = "[";
  for (std::size_t i = 0; i < items.size(); ++i)
    out += (i ? ", \"" : "\"") + jsonEscape(items[i]) + "\"";
  return out + "]";
}

namespace {

// Turns the JSON config into "--key=value" arguments for the same parser as the command line, so
// that a config file and the command line mean exactly the same thing.
std::vector<std::string> configArguments(const std::string& path, const po::options_description& od) {
  namespace pt = boost::property_tree;
  pt::ptree tree;
  try {
    pt::read_json(path, tree);
  } catch (const pt::json_parser_error& e) {
    throw Error("config file '" + path + "': " + e.message() + " (line " + std::to_string(e.line()) +
                ")");
  }
  std::vector<std::string> args;
  for (const auto& kv : tree) {
    const std::string& key = kv.first;
    if (key.empty()) throw Error("config file '" + path + "' must hold a JSON object");
    if (key == "config") throw Error("config file '" + path + "' may not name another config");
    const po::option_description* d = od.find_nothrow(key, false);
    if (!d) throw Error("config file '" + path + "': unknown option '" + key + "'");
    std::string value;
    if (!kv.second.empty()) {  // an array: join its elements with commas
      for (const auto& el : kv.second) {
        if (!value.empty()) value += ",";
        value += el.second.get_value<std::string>();
      }
    } else {
      value = kv.second.get_value<std::string>();
    }
    if (d->semantic()->max_tokens() == 0) {  // a flag
      if (value == "true" || value == "1") args.push_back("--" + key);
      else if (value != "false" && value != "0")
        throw Error("config file '" + path + "': option '" + key + "' takes true or false");
    } else {
      args.push_back("--" + key + "=" + value);
    }
  }
  return args;
}

}  // namespace

std::string ToolContext::optionsJson() const {
  std::ostringstream os;
  os << "{";
  bool first = true;
  for (const auto& kv : vm) {
    if (kv.first == "help") continue;
    const auto& v = kv.second.value();
    std::string text;
    bool quote = true;
    if (const auto* s = boost::any_cast<std::string>(&v)) {
      text = *s;
      if (text.empty() && kv.second.defaulted() == false) {  // a bare flag that was given
        text = "true";
        quote = false;
      }
    }
    else if (const auto* d = boost::any_cast<double>(&v)) {
      std::ostringstream n;
      n.precision(10);
      n << *d;
      text = n.str();
      quote = false;
    } else if (const auto* i = boost::any_cast<int>(&v)) {
      text = std::to_string(*i);
      quote = false;
    } else if (const auto* u = boost::any_cast<unsigned>(&v)) {
      text = std::to_string(*u);
      quote = false;
    } else if (const auto* b = boost::any_cast<bool>(&v)) {
      text = *b ? "true" : "false";
      quote = false;
    } else if (v.empty()) {  // a bare flag (po::bool_switch-less)
      text = "true";
      quote = false;
    } else {
      text = "?";
    }
    os << (first ? "" : ", ") << "\"" << jsonEscape(kv.first) << "\": ";
    if (quote) os << "\"" << jsonEscape(text) << "\"";
    else os << text;
    first = false;
  }
  os << "}";
  return os.str();
}

namespace {

// Seconds since this process started (its start in /proc/self/stat, in clock ticks since boot,
// against the boot clock now); negative where the OS does not say.
double sinceProcessStart() {
  std::ifstream in("/proc/self/stat");
  std::string stat;
  if (!std::getline(in, stat)) return -1.0;
  // Field 22 (starttime), counted after the command's name, which ends at the last ')'.
  const auto close = stat.rfind(')');
  if (close == std::string::npos) return -1.0;
  std::istringstream fields(stat.substr(close + 1));
  std::string f;
  for (int k = 3; k <= 22; ++k)
    if (!(fields >> f)) return -1.0;
  const double ticks = static_cast<double>(sysconf(_SC_CLK_TCK));
  timespec now{};
  if (ticks <= 0.0 || clock_gettime(CLOCK_BOOTTIME, &now) != 0) return -1.0;
  return static_cast<double>(now.tv_sec) + 1e-9 * static_cast<double>(now.tv_nsec) -
         std::strtod(f.c_str(), nullptr) / ticks;
}

}  // namespace

int runTool(int argc, char** argv, const std::string& name, const std::string& usage,
            po::options_description options, const std::function<int(const ToolContext&)>& body) {
  // Under ANIMSEG_MS_TIMING, where a run's time goes outside its stages: before main (loading
  // and relocating the shared libraries), and after it (the C runtime's exit handlers, the CUDA
  // runtime's among them). Boot clock, 10 ms ticks for the start; and the monotonic clock where
  // main begins, to the microsecond, for a parent that read that clock when it started us.
  if (std::getenv("ANIMSEG_MS_TIMING")) {
    timespec mono{};
    clock_gettime(CLOCK_MONOTONIC, &mono);
    std::fprintf(stderr, "[process] main began %.3f s after the process started (monotonic %.6f)\n",
                 sinceProcessStart(),
                 static_cast<double>(mono.tv_sec) + 1e-9 * static_cast<double>(mono.tv_nsec));
    std::atexit([] {
      std::fprintf(stderr, "[process] exit handlers done %.3f s after the process started\n",
                   sinceProcessStart());
    });
  }
  struct Returned {
    ~Returned() {
      if (std::getenv("ANIMSEG_MS_TIMING"))
        std::fprintf(stderr, "[process] main returned %.3f s after the process started\n",
                     sinceProcessStart());
    }
  } returned;
  try {
    options.add_options()("help,h", "show this help and exit")(
        "quiet,q", "no progress or timing on stderr")("verbose,v", "more detail on stderr")(
        "config", po::value<std::string>(),
        "JSON file of options (keys = long option names; "
        "the command line wins)")(
        "threads", po::value<int>()->default_value(0),
        "worker threads; 0: OpenMP's default (OMP_NUM_THREADS, else every core). Results do "
        "not depend on it");
    ToolContext ctx;
    try {
      po::store(po::command_line_parser(argc, argv).options(options).run(), ctx.vm);
      if (ctx.vm.count("help")) {
        std::cout << "Usage: " << usage << "\n\n" << options << std::endl;
        return 0;
      }
      if (ctx.vm.count("config")) {
        ctx.config_path = ctx.vm["config"].as<std::string>();
        if (!std::ifstream(ctx.config_path))
          throw Error("cannot read config file '" + ctx.config_path + "'");
        const auto args = configArguments(ctx.config_path, options);
        // store() keeps values already present, so the command line wins over the file.
        po::store(po::command_line_parser(args).options(options).run(), ctx.vm);
      }
      po::notify(ctx.vm);
    } catch (const po::error& e) {
      throw Error(std::string(e.what()) + " (see " + name + " --help)");
    }
    const int threads = ctx.vm["threads"].as<int>();
    if (threads < 0)
      throw Error("--threads must be >= 0 (0: OpenMP's default), got " + std::to_string(threads));
    if (threads > 0) omp_set_num_threads(threads);
    ctx.threads = omp_get_max_threads();
    ctx.quiet = ctx.vm.count("quiet") > 0;
    ctx.verbose = ctx.vm.count("verbose") > 0 && !ctx.quiet;
    // PCL's own warnings (e.g. ICP on a part that left the view) are expected and handled by the
    // library; they would drown the progress lines, so only --verbose shows them.
    pcl::console::setVerbosityLevel(ctx.verbose ? pcl::console::L_WARN : pcl::console::L_ALWAYS);
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
