// The command-line contract of `animseg` (DESIGN.md): outputs, bad input, --config.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdlib>
#include <map>

#include "tools/cli_util.h"

namespace fs = std::filesystem;
using namespace cli_test;

namespace {

// Three frames of two spheres, with different point counts per frame.
void makeSequence(const fs::path& dir, int nan_every = 0) {
  fs::create_directories(dir);
  for (int t = 0; t < 3; ++t)
    writeSphereXYZ((dir / ("f" + std::to_string(t * 5) + ".xyz")).string(), 300 + 40 * t, 0.1 * t,
                   7 + t, nan_every);
}

}  // namespace

TEST(AnimsegCli, WritesEveryOutputInInputOrder) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in", 50);
  const RunResult r = run(tool("animseg") + " --input " + tmp.str() + "/in --output " + tmp.str() + "/out",
                    tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* name : {"f0", "f5", "f10"}) {
    const fs::path base = tmp.dir() / "out" / name;
    ASSERT_TRUE(fs::exists(base.string() + ".pcd")) << name;
    ASSERT_TRUE(fs::exists(base.string() + ".ply")) << name;
    const std::string labels = slurp(base.string() + ".labels");
    const int expected = name == std::string("f0") ? 300 : name == std::string("f5") ? 340 : 380;
    EXPECT_EQ(countLines(labels), expected) << name;
    // Every 50th input point was NaN: its line must say -1 in every column.
    std::istringstream ls(labels);
    std::string line;
    for (int i = 0; std::getline(ls, line); ++i)
      if (i % 50 == 49) {
        EXPECT_EQ(line.substr(0, 2), "-1") << name << " line " << i;
      }
  }
  const std::string summary = slurp((tmp.dir() / "out" / "summary.json").string());
  for (const char* key :
       {"\"timings_s\"", "\"load\"", "\"total\"", "\"points_per_frame\": [300, 340, 380]",
        "\"parts_per_level\"", "\"device\"", "\"parameters\"", "\"cpu_steal_s\": ",
        "\"other_programs_cpu_s\": ", "\"device_pci_bus_id\": ", "\"device_start_s\": "})
    EXPECT_NE(summary.find(key), std::string::npos) << key << " in " << summary;
  EXPECT_TRUE(fs::exists(tmp.dir() / "out" / "transforms.json"));
  // No temporary files are left behind.
  for (const auto& e : fs::directory_iterator(tmp.dir() / "out"))
    EXPECT_EQ(e.path().filename().string().find(".tmp"), std::string::npos) << e.path();
}

// The default motion method uses neither the paper's features nor their joint-space densities,
// so animseg does not compute them (a note says so); --method paper does. --exact-borders, which
// finishes the paper method's filter, is noted as not applied to the motion method.
TEST(AnimsegCli, FeaturesOnlyForThePaperMethod) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  for (const std::string method : {"motion", "paper"}) {
    const std::string out = tmp.str() + "/out_" + method;
    const RunResult r = run(tool("animseg") + " --quiet --exact-borders --method " + method +
                                " --input " + tmp.str() + "/in --output " + out,
                            tmp.dir());
    ASSERT_EQ(r.code, 0) << r.err;
    const std::string summary = slurp(out + "/summary.json");
    const bool skipped = summary.find("\"scale_space\": null") != std::string::npos;
    const bool noted = summary.find("features not computed") != std::string::npos;
    EXPECT_EQ(skipped, method == "motion") << summary;
    EXPECT_EQ(noted, method == "motion") << summary;
    EXPECT_EQ(summary.find("--exact-borders not applied") != std::string::npos, method == "motion")
        << summary;
    EXPECT_NE(summary.find("\"exact-borders\": true"), std::string::npos) << summary;
    EXPECT_NE(summary.find("\"mean_shift\": "), std::string::npos);
    // The GPU's peak memory: a number when the stage ran on it, null on the CPU.
    const bool on_cpu = summary.find("\"device\": \"cpu\"") != std::string::npos;
    EXPECT_EQ(summary.find("\"device_peak_mib\": null") != std::string::npos, on_cpu) << summary;
    EXPECT_NE(summary.find("\"device_peak_mib\": "), std::string::npos) << summary;
    // The Gaussian kd-tree's N/M: a number for the paper method (default backend), else null.
    EXPECT_EQ(summary.find("\"sampling_factor\": null") != std::string::npos, method == "motion")
        << summary;
    EXPECT_NE(summary.find("\"sampling_factor\": "), std::string::npos) << summary;
  }
}

// Plain point clouds (positions only) get estimated normals, which blur the creases between
// parts: summary.json counts them and a note says what that costs; inputs with normals get 0.
TEST(AnimsegCli, SaysWhenItEstimatedTheNormals) {
  TempDir tmp;
  makeSequence(tmp.dir() / "with");
  fs::create_directories(tmp.dir() / "plain");
  for (const auto& e : fs::directory_iterator(tmp.dir() / "with")) {  // the same points, xyz only
    std::istringstream in(slurp(e.path().string()));
    std::ofstream out(tmp.dir() / "plain" / e.path().filename());
    double x, y, z, nx, ny, nz;
    while (in >> x >> y >> z >> nx >> ny >> nz) out << x << " " << y << " " << z << "\n";
  }
  for (const std::string kind : {"with", "plain"}) {
    const std::string out = tmp.str() + "/out_" + kind;
    const RunResult r = run(tool("animseg") + " --quiet --no-transforms --input " + tmp.str() +
                                "/" + kind + " --output " + out,
                            tmp.dir());
    ASSERT_EQ(r.code, 0) << r.err;
    const std::string summary = slurp(out + "/summary.json");
    const bool plain = kind == "plain";
    EXPECT_NE(summary.find(plain ? "\"normals_estimated\": 1020," : "\"normals_estimated\": 0,"),
              std::string::npos)
        << summary;
    EXPECT_EQ(summary.find("normals estimated for 1020 of 1020 points") != std::string::npos, plain)
        << summary;
  }
}

// Where the build links the programs with jemalloc (cmake/Allocator.cmake), they allocate
// through it with transparent huge pages for the heap and its metadata (tools/jemalloc_conf.c):
// jemalloc's statistics at exit, asked for in the environment, show the options in force.
TEST(AnimsegCli, ProgramsAllocateThroughJemallocWithHugePages) {
#ifndef PCL_ANIMSEG_PROGRAMS_USE_JEMALLOC
  GTEST_SKIP() << "this build's programs use the C library's allocator";
#else
  TempDir tmp;
  const RunResult r = run("MALLOC_CONF=stats_print:true " + tool("animseg") + " --help", tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("jemalloc statistics"), std::string::npos) << r.err.substr(0, 400);
  EXPECT_NE(r.err.find("opt.thp: \"always\""), std::string::npos) << r.err.substr(0, 2000);
  EXPECT_NE(r.err.find("opt.metadata_thp: \"always\""), std::string::npos);
  // Without the request nothing of it is printed.
  const RunResult plain = run(tool("animseg") + " --help", tmp.dir());
  EXPECT_EQ(plain.err.find("jemalloc"), std::string::npos) << plain.err;
#endif
}

// animseg writes PNGs without a window: PCL's visualization library (VTK's rendering, OpenGL,
// X11, MPI), which only the interactive viewer needs, is not among the libraries it loads.
TEST(AnimsegCli, StartsWithoutTheViewersLibraries) {
  TempDir tmp;
  const auto loaded = [&](const std::string& name) {
    // The dynamic loader lists what a program would load, and runs none of it.
    const RunResult r = run("LD_TRACE_LOADED_OBJECTS=1 " + tool(name), tmp.dir());
    EXPECT_EQ(r.code, 0) << r.err;
    return r.out;
  };
  const std::string animseg = loaded("animseg");
  ASSERT_NE(animseg.find("libpcl_animseg_visualization"), std::string::npos) << animseg;
  EXPECT_EQ(animseg.find("libpcl_visualization"), std::string::npos) << animseg;
  EXPECT_EQ(animseg.find("libvtkRenderingOpenGL2"), std::string::npos) << animseg;
  EXPECT_EQ(animseg.find("libX11"), std::string::npos) << animseg;
  EXPECT_EQ(animseg.find("libmpi"), std::string::npos) << animseg;
  // The viewer does load them: the names above are the ones to look for.
  const std::string view = loaded("animseg_view");
  EXPECT_NE(view.find("libpcl_visualization"), std::string::npos) << view;
  EXPECT_NE(view.find("libvtkRenderingOpenGL2"), std::string::npos) << view;
  EXPECT_NE(view.find("libX11"), std::string::npos) << view;
  EXPECT_NE(view.find("libmpi"), std::string::npos) << view;
}

TEST(AnimsegCli, QuietPrintsNothing) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  const RunResult r = run(tool("animseg") + " --quiet --input " + tmp.str() + "/in --output " + tmp.str() +
                        "/out",
                    tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(r.err.empty()) << r.err;
}

TEST(AnimsegCli, ConfigFileValuesAreUsedAndCommandLineWins) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  std::ofstream(tmp.dir() / "cfg.json") << "{\"bandwidth\": 0.25, \"weights\": [0.5, 0.8, 2, 1], \"seed\": 9}";
  const RunResult r = run(tool("animseg") + " --quiet --config " + tmp.str() + "/cfg.json --seed 3 --input " +
                        tmp.str() + "/in --output " + tmp.str() + "/out",
                    tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string summary = slurp((tmp.dir() / "out" / "summary.json").string());
  EXPECT_NE(summary.find("\"bandwidth\": 0.25"), std::string::npos) << summary;
  EXPECT_NE(summary.find("\"weights\": \"0.5,0.8,2,1\""), std::string::npos) << summary;
  EXPECT_NE(summary.find("\"seed\": 3"), std::string::npos) << summary;
}

struct BadCase {
  std::string name;
  std::string args;  // {in} and {out} are replaced
};

class AnimsegBadInput : public ::testing::TestWithParam<BadCase> {};

TEST_P(AnimsegBadInput, OneErrorLineNonZeroExitNoOutput) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  fs::create_directories(tmp.dir() / "empty");
  fs::create_directories(tmp.dir() / "tiny");
  {
    std::ofstream f(tmp.dir() / "tiny" / "a.xyz");
    f << "0 0 0\n1 0 0\n0 1 0\n";
  }
  std::ofstream(tmp.dir() / "badcfg.json") << "{\"no_such_option\": 1}";
  std::ofstream(tmp.dir() / "brokencfg.json") << "{\"bandwidth\": ";
  std::string args = GetParam().args;
  auto replace = [&](const std::string& key, const std::string& value) {
    for (std::size_t p; (p = args.find(key)) != std::string::npos;) args.replace(p, key.size(), value);
  };
  replace("{tmp}", tmp.str());
  replace("{in}", tmp.str() + "/in");
  replace("{out}", tmp.str() + "/out");
  const RunResult r = run(tool("animseg") + " " + args, tmp.dir());
  EXPECT_EQ(r.code, 1) << GetParam().name;
  EXPECT_TRUE(isOneErrorLine(r.err)) << GetParam().name << ": '" << r.err << "'";
  EXPECT_FALSE(fs::exists(tmp.dir() / "out" / "summary.json")) << GetParam().name;
}

INSTANTIATE_TEST_SUITE_P(
    Cases, AnimsegBadInput,
    ::testing::Values(
        BadCase{"unknown_option", "--input {in} --output {out} --frobnicate"},
        BadCase{"missing_input", "--input {tmp}/nope --output {out}"},
        BadCase{"no_output_option", "--input {in}"},
        BadCase{"empty_dir", "--input {tmp}/empty --output {out}"},
        BadCase{"three_points", "--input {tmp}/tiny --output {out}"},
        BadCase{"bandwidth_zero", "--input {in} --output {out} --bandwidth 0"},
        BadCase{"negative_weight", "--input {in} --output {out} --weights 0.5,-1,2,1"},
        BadCase{"short_weights", "--input {in} --output {out} --weights 0.5,1"},
        BadCase{"bad_device", "--input {in} --output {out} --device tpu"},
        BadCase{"gpu_without_number", "--input {in} --output {out} --device gpu:"},
        BadCase{"gpu_negative_number", "--input {in} --output {out} --device gpu:-1"},
        BadCase{"gpu_number_and_text", "--input {in} --output {out} --device gpu:1x"},
        BadCase{"negative_transform_levels", "--input {in} --output {out} --transform-levels -1"},
        BadCase{"zero_refine_iterations", "--input {in} --output {out} --refine-iterations 0"},
        BadCase{"narrow_band_past_outer", "--input {in} --output {out} --narrow-band 12"},
        BadCase{"negative_fold_snap", "--input {in} --output {out} --fold-snap -1"},
        BadCase{"one_motion_frame", "--input {in} --output {out} --motion-frames 1"},
        BadCase{"negative_exact_steps", "--input {in} --output {out} --exact-steps -1"},
        BadCase{"negative_cell_extent", "--input {in} --output {out} --cell-extent -0.5"},
        BadCase{"zero_cell_min_points", "--input {in} --output {out} --cell-min-points 0"},
        BadCase{"unknown_config_key", "--config {tmp}/badcfg.json --input {in} --output {out}"},
        BadCase{"broken_config", "--config {tmp}/brokencfg.json --input {in} --output {out}"},
        BadCase{"missing_config", "--config {tmp}/none.json --input {in} --output {out}"}),
    [](const ::testing::TestParamInfo<BadCase>& i) { return i.param.name; });

// --device gpu:N picks one of the machine's GPUs. A number past the last one (here 97, or the
// third entry of a CUDA_VISIBLE_DEVICES list of two) is one error line that names it, with no
// output; without a GPU, gpu:0 is the same error as --device gpu. summary.json names the GPU that
// ran by its PCI bus id, null on the CPU.
TEST(AnimsegCli, DeviceGpuNPicksAGpuOrSaysWhichIsMissing) {
  TempDir tmp;
  makeSequence(tmp.dir() / "in");
  const std::string io = " --input " + tmp.str() + "/in --output " + tmp.str() + "/out";
  const RunResult far = run(tool("animseg") + " --quiet --device gpu:97" + io, tmp.dir());
  EXPECT_EQ(far.code, 1);
  EXPECT_TRUE(isOneErrorLine(far.err)) << far.err;
  EXPECT_NE(far.err.find("--device gpu:97, CUDA_VISIBLE_DEVICES=97"), std::string::npos) << far.err;
  EXPECT_FALSE(fs::exists(tmp.dir() / "out" / "summary.json"));
  const RunResult listed = run(
      "CUDA_VISIBLE_DEVICES=0,1 " + tool("animseg") + " --quiet --device gpu:2" + io, tmp.dir());
  EXPECT_EQ(listed.code, 1);
  EXPECT_TRUE(isOneErrorLine(listed.err)) << listed.err;
  EXPECT_NE(listed.err.find("GPU 2 was asked for, but CUDA_VISIBLE_DEVICES='0,1' leaves 2 GPUs"),
            std::string::npos)
      << listed.err;
  EXPECT_FALSE(fs::exists(tmp.dir() / "out" / "summary.json"));
  // GPU 0 of the machine, or of a list whose first entry is 0: with a GPU it runs there, without
  // one the error is --device gpu's, naming the GPU asked for.
  const std::string gpu = run(tool("animseg") + " --quiet --device gpu" + io, tmp.dir()).err;
  const bool have_gpu = gpu.empty();
  for (const std::string env : {"", "CUDA_VISIBLE_DEVICES=0 "}) {
    fs::remove_all(tmp.dir() / "out");
    const RunResult r = run(env + tool("animseg") + " --quiet --device gpu:0" + io, tmp.dir());
    const std::string summary = fs::exists(tmp.dir() / "out" / "summary.json")
                                    ? slurp((tmp.dir() / "out" / "summary.json").string())
                                    : std::string();
    if (have_gpu) {
      EXPECT_EQ(r.code, 0) << env << r.err;
      EXPECT_EQ(summary.find("\"device_pci_bus_id\": null"), std::string::npos) << summary;
      EXPECT_NE(summary.find("\"device_pci_bus_id\": \""), std::string::npos) << summary;
      EXPECT_NE(summary.find("\"device\": \"gpu:0\""), std::string::npos) << summary;
      // How long the GPU took to start: a number (its driver's start alone takes a while).
      const std::size_t at = summary.find("\"device_start_s\": ");
      ASSERT_NE(at, std::string::npos) << summary;
      const double start = std::atof(summary.c_str() + at + 18);
      EXPECT_GT(start, 0.0) << summary.substr(at, 40);
      EXPECT_LT(start, 60.0) << summary.substr(at, 40);
    } else {
      EXPECT_EQ(r.code, 1) << env;
      EXPECT_TRUE(isOneErrorLine(r.err)) << r.err;
      EXPECT_NE(r.err.find("no usable GPU"), std::string::npos) << r.err;
      EXPECT_NE(r.err.find("(--device gpu:0, CUDA_VISIBLE_DEVICES=0)"), std::string::npos) << r.err;
      EXPECT_TRUE(summary.empty()) << summary;
    }
  }
  // On the cores the field is null.
  fs::remove_all(tmp.dir() / "out");
  ASSERT_EQ(run(tool("animseg") + " --quiet --device cpu" + io, tmp.dir()).code, 0);
  const std::string on_cpu = slurp((tmp.dir() / "out" / "summary.json").string());
  EXPECT_NE(on_cpu.find("\"device_pci_bus_id\": null"), std::string::npos) << on_cpu;
  EXPECT_NE(on_cpu.find("\"device_start_s\": null"), std::string::npos) << on_cpu;
}

// Same input and seed: byte-identical labels, whatever the number of threads.
TEST(AnimsegCli, DeterministicAcrossThreadCounts) {
  TempDir tmp;
  const std::string in = tmp.str() + "/in";
  const RunResult g = run(tool("animseg_synth") + " --quiet --plan humanoid --frames 5 --points 700 "
                              "--seed 4 --output " + in, tmp.dir());
  ASSERT_EQ(g.code, 0) << g.err;
  std::vector<std::string> outs;
  for (const char* threads : {"1", "2"}) {
    const std::string out = tmp.str() + "/out" + threads;
    const RunResult r = run(std::string("OMP_NUM_THREADS=") + threads + " " + tool("animseg") +
                                " --quiet --seed 5 --input " + in + " --output " + out,
                            tmp.dir());
    ASSERT_EQ(r.code, 0) << r.err;
    outs.push_back(out);
  }
  int compared = 0;
  for (const auto& e : fs::directory_iterator(outs[0])) {
    if (e.path().extension() != ".labels") continue;
    const std::string a = slurp(e.path().string());
    ASSERT_FALSE(a.empty());
    EXPECT_EQ(a, slurp(outs[1] + "/" + e.path().filename().string())) << e.path().filename();
    ++compared;
  }
  EXPECT_EQ(compared, 5);
  // transforms.json: the same on any thread count, and one entry per level of the labels (one
  // column each), as animseg_hierarchy writes it.
  const std::string transforms = slurp(outs[0] + "/transforms.json");
  EXPECT_EQ(transforms, slurp(outs[1] + "/transforms.json"));
  std::istringstream first(slurp(outs[0] + "/f000.labels"));
  std::string first_line;
  std::getline(first, first_line);
  std::istringstream columns(first_line);
  int levels = 0;
  for (std::string v; columns >> v;) ++levels;
  int level_entries = 0;
  for (std::size_t p = transforms.find("{\"level\": "); p != std::string::npos;
       p = transforms.find("{\"level\": ", p + 1))
    ++level_entries;
  EXPECT_GE(levels, 2) << first_line;
  EXPECT_EQ(level_entries, levels) << transforms.substr(0, 200);
  // --transform-levels 1: the finest level's parts only, with the same transforms.
  const std::string out1 = tmp.str() + "/finest";
  const RunResult r = run(tool("animseg") + " --quiet --seed 5 --transform-levels 1 --input " + in +
                              " --output " + out1,
                          tmp.dir());
  ASSERT_EQ(r.code, 0) << r.err;
  const std::string finest = slurp(out1 + "/transforms.json");
  EXPECT_EQ(finest.find("{\"level\": 1"), std::string::npos);
  const std::size_t level1 = transforms.find(",\n    {\"level\": 1");
  ASSERT_NE(level1, std::string::npos);
  EXPECT_EQ(finest.substr(0, finest.find("\n  ]\n}")), transforms.substr(0, level1));
}

TEST(AnimsegCli, ThreadsChangeNothingButTheTimeAndABadCountIsAnError) {
  TempDir tmp;
  const RunResult g = run(tool("animseg_synth") +
                              " --quiet --plan humanoid --frames 6 --points 1500 "
                              "--seed 4 --output " +
                              tmp.str() + "/in",
                          tmp.dir());
  ASSERT_EQ(g.code, 0) << g.err;
  std::map<std::string, std::string> first;
  for (const int threads : {1, 3}) {
    const std::string out = tmp.str() + "/out" + std::to_string(threads);
    const RunResult r = run(tool("animseg") + " --quiet --threads " + std::to_string(threads) +
                                " --input " + tmp.str() + "/in --output " + out,
                            tmp.dir());
    ASSERT_EQ(r.code, 0) << r.err;
    const std::string summary = slurp(out + "/summary.json");
    EXPECT_NE(summary.find("\"threads\": " + std::to_string(threads) + ","), std::string::npos)
        << summary;
    std::map<std::string, std::string> files;
    for (const auto& e : fs::directory_iterator(out)) {
      const std::string name = e.path().filename().string();
      if (e.path().extension() == ".labels" || name == "transforms.json")
        files[name] = slurp(e.path().string());
    }
    ASSERT_EQ(files.size(), 7u);  // 6 label files and the transforms
    if (first.empty())
      first = files;
    else
      for (const auto& [name, text] : files) EXPECT_EQ(text, first[name]) << name;
  }
  const RunResult bad = run(
      tool("animseg") + " --threads -2 --input " + tmp.str() + "/in --output " + tmp.str() + "/bad",
      tmp.dir());
  EXPECT_EQ(bad.code, 1);
  EXPECT_NE(bad.err.find("error: --threads must be >= 0"), std::string::npos) << bad.err;
  EXPECT_EQ(std::count(bad.err.begin(), bad.err.end(), '\n'), 1) << bad.err;
  EXPECT_FALSE(fs::exists(tmp.dir() / "bad" / "summary.json"));
}
