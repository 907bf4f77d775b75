// libFuzzer target: the --config JSON parser (configArguments in src/common/tool_common.cpp) with
// animseg-like options, followed by the same boost::program_options parse that runTool does.
// The source is included so the fuzzer can reach the function in its anonymous namespace; the
// fuzz library leaves tool_common.cpp out for that reason.
#include "../src/common/tool_common.cpp"

#include "fuzz_common.h"

namespace {

po::options_description animsegLikeOptions() {
  po::options_description od("options");
  od.add_options()("input,i", po::value<std::string>(), "in")("output,o", po::value<std::string>(),
                                                               "out")(
      "levels", po::value<int>()->default_value(3), "")("bandwidth",
                                                        po::value<double>()->default_value(0.1), "")(
      "weights", po::value<std::string>()->default_value("1,1,1,1"), "")(
      "seed", po::value<unsigned>()->default_value(1), "")(
      "png", po::value<std::string>()->implicit_value(""), "")("no-refine", "")("quiet,q", "")(
      "config", po::value<std::string>(), "");
  return od;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const po::options_description od = animsegLikeOptions();
  const std::string path = fuzz::writeInput(data, size, "config.json");
  fuzz::expectOnlyErrors([&] {
    const auto args = pcl_animseg::tools::configArguments(path, od);
    try {
      po::variables_map vm;
      po::store(po::command_line_parser(args).options(od).run(), vm);
      po::notify(vm);
      if (vm.count("weights"))
        pcl_animseg::tools::parseNumberList(vm["weights"].as<std::string>(), 4, "--weights");
    } catch (const po::error&) {
      // runTool turns these into Error.
    }
  });
  return 0;
}
