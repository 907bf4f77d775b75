// animseg: the one-shot pipeline of Fig. 1 — a sequence in, temporally coherent near-rigid parts out.
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/pipeline.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/segmentation/rigid_motion.h>
#include <pcl_animseg/tool_common.h>
#include <pcl_animseg/visualization/contact_sheet.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <iomanip>
#include <iostream>
#include <sstream>
#include <string>

#include "motion_options.h"
#include "scale_space_options.h"

namespace po = boost::program_options;
using namespace pcl_animseg;

namespace {

std::string num(double v) {
  std::ostringstream os;
  os << std::setprecision(6) << v;
  return os.str();
}

std::string summaryJson(const tools::ToolContext& ctx, const std::string& input,
                        const PointCloudSequence& seq, const PipelineResult& r,
                        const std::vector<std::pair<std::string, double>>& timings, double total,
                        double steal, double other) {
  using tools::jsonEscape;
  std::ostringstream os;
  os << "{\n  \"input\": \"" << jsonEscape(input) << "\",\n";
  os << "  \"parameters\": " << ctx.optionsJson() << ",\n";
  os << "  \"device\": \"" << r.device_used << "\",\n";
  // Which GPU ran, by its PCI bus id (null on the CPU).
  os << "  \"device_pci_bus_id\": "
     << (r.device_pci_bus_id.empty() ? std::string("null")
                                     : "\"" + jsonEscape(r.device_pci_bus_id) + "\"")
     << ",\n";
  // How long the GPU took to start (negative, so null, on the CPU): an idle GPU starts slower.
  os << "  \"device_start_s\": "
     << (r.device_start_s >= 0.0 ? num(r.device_start_s) : std::string("null")) << ",\n";
  // Peak GPU memory of the run (null on the CPU).
  os << "  \"device_peak_mib\": ";
  if (r.device_used == "cpu")
    os << "null";
  else
    os << num(static_cast<double>(r.device_peak_bytes) / 1048576.0);
  os << ",\n";
  os << "  \"threads\": " << ctx.threads << ",\n";
  // CPU time the machine's host took from its CPUs during the stages (null where the OS does
  // not say): the timings below waited for it.
  os << "  \"cpu_steal_s\": " << (steal >= 0.0 ? num(steal) : std::string("null")) << ",\n";
  // CPU time the machine's other programs used during the stages (null where unknown): threads
  // of this run that shared the CPUs with them.
  os << "  \"other_programs_cpu_s\": " << (other >= 0.0 ? num(other) : std::string("null"))
     << ",\n";
  os << "  \"frames\": " << seq.size() << ",\n  \"points_per_frame\": [";
  for (std::size_t t = 0; t < seq.size(); ++t) os << (t ? ", " : "") << seq.inputSize(t);
  os << "],\n  \"total_points\": " << seq.totalPoints() << ",\n";
  os << "  \"normals_estimated\": " << r.normals_estimated << ",\n";
  os << "  \"keypoints\": " << r.keypoints << ",\n";
  // The Gaussian kd-tree's N/M (paper method, gkdtree backend); null when no filter ran.
  os << "  \"sampling_factor\": "
     << (r.sampling_factor > 0.0 ? num(r.sampling_factor) : std::string("null")) << ",\n";
  os << "  \"parts_per_level\": [";
  for (std::size_t l = 0; l < r.parts_per_level.size(); ++l)
    os << (l ? ", " : "") << r.parts_per_level[l];
  os << "],\n  \"notes\": " << tools::jsonStringArray(r.notes) << ",\n  \"timings_s\": {";
  // Every stage of DESIGN.md is listed; one that did not run (--no-refine, ...) is null, never a
  // made-up number.
  const char* stages[] = {"load", "scale_space", "keypoints", "signature", "mean_shift",
                          "refine", "hierarchy", "rigid_motion", "write"};
  bool first = true;
  for (const char* s : stages) {
    os << (first ? "" : ", ") << "\"" << s << "\": ";
    first = false;
    auto it = std::find_if(timings.begin(), timings.end(), [&](const auto& p) { return p.first == s; });
    if (it == timings.end()) os << "null";
    else os << num(it->second);
  }
  os << ", \"total\": " << num(total) << "}\n}\n";
  return os.str();
}

}  // namespace

int main(int argc, char** argv) {
  const PipelineParams defaults;
  const auto& msd = defaults.mean_shift;
  const auto w = [](double v) {
    std::ostringstream os;
    os << v;
    return os.str();
  };
  po::options_description od("Options");
  // clang-format off
  od.add_options()
    ("input,i", po::value<std::string>()->required(),
     "sequence: a directory of .obj/.ply/.off/.pcd/.xyz frames (natural order) or a list file")
    ("output,o", po::value<std::string>()->required(), "output directory")
    ("device", po::value<std::string>()->default_value("auto"),
     "auto|cpu|gpu|gpu:N: where the stages run (auto: a GPU when one works, else the cores; "
     "gpu:N: the machine's GPU N as nvidia-smi numbers them, or the N-th of CUDA_VISIBLE_DEVICES "
     "where that is set)")
    ("levels", po::value<int>()->default_value(defaults.levels),
     "hierarchy levels above level 0, at most (Sect. 5)")
    ("bandwidth", po::value<double>()->default_value(msd.bandwidth),
     "mean shift bandwidth w (Eq. 4), positions in units of the sequence size")
    ("weights", po::value<std::string>()->default_value(w(msd.w1) + "," + w(msd.w2) + "," + w(msd.w3) +
                                                        "," + w(msd.w4)),
     "w1,w2,w3,w4: normal, position, signature between keypoints, signature otherwise (Eq. 5-6)")
    ("method", po::value<std::string>()->default_value("motion"),
     "motion (default: patches tracked by ICP, merged by rigid motion) | paper (joint mean shift "
     "of Sect. 3.2 only)")
    ("backend", po::value<std::string>()->default_value("gkdtree"),
     "kernel sums: gkdtree (Gaussian kd-tree, Sect. 3.3) | exact (kd-tree, reference)")
    ("parts", po::value<int>()->default_value(0),
     "merge to exactly this many level-0 parts (0: stop at --motion-threshold)")
    ("patches", po::value<int>()->default_value(msd.patches),
     ("motion method: tracked samples of the reference frame (0: one per 8 points, at most " +
      std::to_string(pcl_animseg::segmentation::kMaxTrackedSamples) + ")")
         .c_str());
  // clang-format on
  tools::addMotionOptions(od, msd);
  tools::addPaperOptions(od, msd);
  tools::addScaleSpaceOptions(od, defaults.multiscale);
  od.add_options()("signature-h",
                   po::value<double>()->default_value(defaults.multiscale.signature_h),
                   "scale h of the signature (Eq. 2), in point spacings")(
      "narrow-band", po::value<double>()->default_value(defaults.refinement.narrow_band),
      "refinement: L_r, width of the band W (point spacings)")(
      "outer-band", po::value<double>()->default_value(defaults.refinement.outer_band),
      "refinement: L_R, outer width of the bands F and B (point spacings)")(
      "refine-iterations", po::value<int>()->default_value(defaults.refinement.max_iterations),
      "refinement: passes at most (bands rebuilt from the new labels each time)")(
      "fold-snap", po::value<double>()->default_value(defaults.refinement.fold_snap_band),
      "refinement: points within this many spacings of a border move onto the inward fold "
      "where one part leaves the other (0: off)")(
      "motion-frames", po::value<int>()->default_value(defaults.refinement.motion_frames),
      "refinement: its motion check averages over at most this many frames, spread evenly "
      "(0: every frame; the cost grows with the square of the frame count)")(
      "rp-step", po::value<double>()->default_value(defaults.hierarchy.step),
      "hierarchy: raise of the region-persistence threshold per level (0.05-0.1)")(
      "png", po::value<std::string>()->implicit_value(""),
      "also render a contact sheet of the result (headless) to FILE, default "
      "OUT/contact_sheet.png")("png-level", po::value<int>()->default_value(0),
                               "hierarchy level shown by --png")(
      "no-features", "skip scale space, keypoints and signatures (mean shift on p, n only)")(
      "no-refine", "skip the GMM boundary refinement")(
      "no-transforms", "skip the rigid motion per part (transforms.json lists no parts)")(
      "transform-levels", po::value<int>()->default_value(defaults.motion_levels),
      "rigid motions for this many levels, finest first (0: every level)")(
      "seed", po::value<unsigned>()->default_value(msd.seed),
      "random seed (results are deterministic)");
  return tools::runTool(
      argc, argv, "animseg",
      "animseg --input IN --output OUT [--device auto|cpu|gpu|gpu:N] [--levels L] [--bandwidth w]\n"
      "               [--weights w1,w2,w3,w4] [--seed S] [--config FILE]",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        const auto& vm = ctx.vm;
        PipelineParams params;
        const DeviceChoice device = parseDeviceChoice(vm["device"].as<std::string>());
        params.device = device.device;
        params.levels = vm["levels"].as<int>();
        auto& ms = params.mean_shift;
        ms.bandwidth = vm["bandwidth"].as<double>();
        const auto wt = tools::parseNumberList(vm["weights"].as<std::string>(), 4, "--weights");
        ms.w1 = wt[0];
        ms.w2 = wt[1];
        ms.w3 = wt[2];
        ms.w4 = wt[3];
        std::string method = vm["method"].as<std::string>();
        if (method == "default") method = "motion";
        ms.method = segmentation::meanShiftMethodFromString(method);
        ms.backend = segmentation::meanShiftBackendFromString(vm["backend"].as<std::string>());
        ms.target_clusters = vm["parts"].as<int>();
        ms.patches = vm["patches"].as<int>();
        tools::readMotionOptions(vm, ms);
        tools::readPaperOptions(vm, ms);
        ms.seed = vm["seed"].as<unsigned>();
        tools::readScaleSpaceOptions(vm, params.multiscale);
        params.multiscale.signature_h = vm["signature-h"].as<double>();
        params.refinement.narrow_band = vm["narrow-band"].as<double>();
        params.refinement.outer_band = vm["outer-band"].as<double>();
        params.refinement.max_iterations = vm["refine-iterations"].as<int>();
        params.refinement.fold_snap_band = vm["fold-snap"].as<double>();
        params.refinement.motion_frames = vm["motion-frames"].as<int>();
        params.hierarchy.step = vm["rp-step"].as<double>();
        params.features = !vm.count("no-features");
        params.refine = !vm.count("no-refine");
        params.motions = !vm.count("no-transforms");
        params.motion_levels = vm["transform-levels"].as<int>();
        validate(params);  // fail before the (long) load on a bad parameter
        // gpu:N: the process sees that GPU alone, as its device 0 (the library's threads all
        // run on device 0 of those visible). Set before the first CUDA call, which the warm-up
        // below makes; numbered as nvidia-smi does (CUDA's default order puts the fastest
        // first) unless the user chose an order or a list.
        std::string visible;
        if (device.gpu_index >= 0) {
          const char* current = std::getenv("CUDA_VISIBLE_DEVICES");
          visible = visibleDevicesFor(current, device.gpu_index);
          if (!current) ::setenv("CUDA_DEVICE_ORDER", "PCI_BUS_ID", /*overwrite=*/0);
          ::setenv("CUDA_VISIBLE_DEVICES", visible.c_str(), /*overwrite=*/1);
        }
        // The GPU's start (0.2-0.35 s) runs beside the loading and the first CPU work.
        const DeviceWarmUp warm_up(params.device);

        const std::string input = vm["input"].as<std::string>();
        const std::string out = vm["output"].as<std::string>();
        // Fig. 1, top to bottom.
        PointCloudSequence seq = io::loadSequence(input, io::LoadOptions(), &progress);
        progress.info("loaded " + std::to_string(seq.size()) + " frames, " +
                      std::to_string(seq.totalPoints()) + " points");

        // The host's steal over the stages (a virtual machine's CPUs given to other work) and the
        // other programs' CPU time, from one reading before and one after.
        const CpuReading cpu0 = readCpu();
        const auto run0 = std::chrono::steady_clock::now();
        PipelineResult r;
        try {
          r = runPipeline(seq, params, progress);
        } catch (const DeviceError& e) {
          // Which GPU was asked for: a number past the machine's last GPU leaves none visible.
          if (device.gpu_index < 0) throw;
          throw DeviceError(std::string(e.what()) +
                            " (--device gpu:" + std::to_string(device.gpu_index) +
                            ", CUDA_VISIBLE_DEVICES=" + visible + ")");
        }
        const double run_s =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - run0).count();
        const CpuReading cpu1 = readCpu();
        const double steal = cpuStealBetween(cpu0, cpu1);
        const std::string steal_note = hostStealNote(steal, run_s, onlineCpus());
        if (!steal_note.empty()) r.notes.push_back(steal_note);
        const double other = otherProgramsCpuBetween(cpu0, cpu1);
        const std::string other_note = otherProgramsNote(other, run_s, onlineCpus(), ctx.threads);
        if (!other_note.empty()) r.notes.push_back(other_note);

        progress.begin("write", seq.size());
        io::saveSequenceLabels(out, seq, r.levels, /*ply=*/true,
                               [&](std::size_t done) { progress.update(done); });
        segmentation::writeTransformsJson(out + "/transforms.json", seq, r.motions);
        progress.end();
        if (vm.count("png")) {
          progress.begin("png");
          std::string png = vm["png"].as<std::string>();
          if (png.empty()) png = out + "/contact_sheet.png";
          visualization::ContactSheetOptions opt;
          opt.level = std::min<int>(vm["png-level"].as<int>(), static_cast<int>(r.levels.size()) - 1);
          visualization::renderContactSheet(out, png, opt);
          progress.end(png);
        }
        const auto timings = progress.timings();
        io::writeTextAtomically(
            out + "/summary.json",
            summaryJson(ctx, input, seq, r, timings, progress.elapsed(), steal, other));

        // One screen at the end: what was decomposed, into what, and where the time went.
        std::ostringstream parts, sum;
        for (std::size_t l = 0; l < r.parts_per_level.size(); ++l)
          parts << (l ? " " : "") << r.parts_per_level[l];
        sum << "summary\n"
            << "  frames            " << seq.size() << "\n"
            << "  points            " << seq.totalPoints() << "\n"
            << "  keypoints         " << r.keypoints << "\n"
            << "  parts per level   " << parts.str() << "\n"
            << "  device            " << r.device_used
            << (r.device_used == "cpu"
                    ? std::string()
                    : " (" +
                          (r.device_start_s >= 0.0 ? "started in " + num(r.device_start_s) + " s, "
                                                   : std::string()) +
                          "peak " + num(static_cast<double>(r.device_peak_bytes) / 1048576.0) +
                          " MiB" +
                          (r.device_pci_bus_id.empty() ? "" : ", PCI " + r.device_pci_bus_id) + ")")
            << "\n"
            << "  threads           " << ctx.threads << "\n";
        if (steal >= 0.0) sum << "  host steal        " << num(steal) << " CPU s\n";
        if (other >= 0.0) sum << "  other programs    " << num(other) << " CPU s\n";
        for (const auto& st : timings) {
          if (st.first.find('/') != std::string::npos) continue;  // sub-stages: see --verbose log
          sum << "  " << std::left << std::setw(18) << (st.first + " (s)") << num(st.second) << "\n";
        }
        sum << "  " << std::left << std::setw(18) << "total (s)" << num(progress.elapsed()) << "\n"
            << "  output            " << out;
        progress.info(sum.str());
        for (const auto& n : r.notes) progress.info("  note: " + n);
        return 0;
      });
}
