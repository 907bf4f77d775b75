// animseg: the one-shot pipeline of Fig. 1 — a sequence in, temporally coherent near-rigid parts out.
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/pipeline.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/tool_common.h>

#include <iomanip>
#include <iostream>
#include <sstream>

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
                        const std::vector<std::pair<std::string, double>>& timings, double total) {
  using tools::jsonEscape;
  std::ostringstream os;
  os << "{\n  \"input\": \"" << jsonEscape(input) << "\",\n";
  os << "  \"parameters\": " << ctx.optionsJson() << ",\n";
  os << "  \"device\": \"" << r.device_used << "\",\n";
  os << "  \"frames\": " << seq.size() << ",\n  \"points_per_frame\": [";
  for (std::size_t t = 0; t < seq.size(); ++t) os << (t ? ", " : "") << seq.inputSize(t);
  os << "],\n  \"total_points\": " << seq.totalPoints() << ",\n";
  os << "  \"keypoints\": " << r.keypoints << ",\n  \"parts_per_level\": [";
  for (std::size_t l = 0; l < r.parts_per_level.size(); ++l)
    os << (l ? ", " : "") << r.parts_per_level[l];
  os << "],\n  \"missing_stages\": [";
  for (std::size_t i = 0; i < r.missing.size(); ++i)
    os << (i ? ", " : "") << "\"" << r.missing[i] << "\"";
  os << "],\n  \"notes\": [";
  for (std::size_t i = 0; i < r.notes.size(); ++i)
    os << (i ? ", " : "") << "\"" << jsonEscape(r.notes[i]) << "\"";
  os << "],\n  \"timings_s\": {";
  // Every stage of DESIGN.md is listed; a missing one is null, never a made-up number.
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

std::string transformsJson(const PointCloudSequence& seq, const PipelineResult& r) {
  std::ostringstream os;
  os << std::setprecision(9);
  os << "{\n  \"frames\": [";
  for (std::size_t t = 0; t < seq.size(); ++t)
    os << (t ? ", " : "") << "\"" << tools::jsonEscape(seq.name(t)) << "\"";
  os << "],\n  \"parts\": [";
  for (std::size_t i = 0; i < r.motions.size(); ++i) {
    const PartMotion& m = r.motions[i];
    os << (i ? ",\n" : "\n") << "    {\"part\": " << m.part << ", \"frames\": [";
    for (std::size_t t = 0; t < m.rotation.size(); ++t) {
      const auto& R = m.rotation[t];
      const auto& tr = m.translation[t];
      os << (t ? ", " : "") << "{\"rotation\": [";
      for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b) os << (a || b ? ", " : "") << R(a, b);
      os << "], \"translation\": [" << tr.x() << ", " << tr.y() << ", " << tr.z()
         << "], \"rms\": " << m.rms[t] << "}";
    }
    os << "]}";
  }
  os << (r.motions.empty() ? "" : "\n  ") << "]\n}\n";
  return os.str();
}

}  // namespace

int main(int argc, char** argv) {
  po::options_description od("Options");
  od.add_options()
    ("input,i", po::value<std::string>()->required(),
     "sequence: a directory of .obj/.ply/.off/.pcd/.xyz frames (natural order) or a list file")
    ("output,o", po::value<std::string>()->required(), "output directory")
    ("device", po::value<std::string>()->default_value("auto"), "mean shift device: auto|cpu|gpu")
    ("levels", po::value<int>()->default_value(4), "hierarchy levels above level 0 (at most)")
    ("bandwidth", po::value<double>()->default_value(0.3), "mean shift bandwidth w (Eq. 4)")
    ("weights", po::value<std::string>()->default_value("0.5,0.5,2,1"),
     "w1,w2,w3,w4: normal, position, signature between keypoints, signature otherwise (Eq. 5-6)")
    ("method", po::value<std::string>()->default_value("default"),
     "segmentation method: default (motion-coherent) | paper (mean shift of the paper only)")
    ("seed", po::value<unsigned>()->default_value(1), "random seed (results are deterministic)");
  return tools::runTool(
      argc, argv, "animseg",
      "animseg --input IN --output OUT [--device auto|cpu|gpu] [--levels L] [--bandwidth w]\n"
      "               [--weights w1,w2,w3,w4] [--seed S] [--config FILE]",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        PipelineParams params;
        params.device = ctx.vm["device"].as<std::string>();
        params.levels = ctx.vm["levels"].as<int>();
        params.bandwidth = ctx.vm["bandwidth"].as<double>();
        const auto w = tools::parseNumberList(ctx.vm["weights"].as<std::string>(), 4, "--weights");
        params.w1 = w[0];
        params.w2 = w[1];
        params.w3 = w[2];
        params.w4 = w[3];
        params.method = ctx.vm["method"].as<std::string>();
        params.seed = ctx.vm["seed"].as<unsigned>();
        validate(params);  // fail before the (long) load on a bad parameter

        const std::string input = ctx.vm["input"].as<std::string>();
        const std::string out = ctx.vm["output"].as<std::string>();
        PointCloudSequence seq = io::loadSequence(input, io::LoadOptions(), &progress);
        progress.info("loaded " + std::to_string(seq.size()) + " frames, " +
                      std::to_string(seq.totalPoints()) + " points");

        PipelineResult r = runPipeline(seq, params, progress);

        progress.begin("write", seq.size());
        io::ensureDirectory(out);
        for (std::size_t t = 0; t < seq.size(); ++t) {
          std::vector<std::vector<int>> columns;
          for (const auto& level : r.levels) columns.push_back(seq.toInputOrder(t, level[t]));
          const std::string base = out + "/" + seq.name(t);
          io::saveLabels(base + ".labels", columns);
          io::saveLabelledPCD(base + ".pcd", *seq.frame(t), r.levels[0][t]);
          io::saveLabelledPLY(base + ".ply", *seq.frame(t), r.levels[0][t]);
          progress.update(t + 1);
        }
        io::writeTextAtomically(out + "/transforms.json", transformsJson(seq, r));
        progress.end();
        const auto timings = progress.timings();
        io::writeTextAtomically(out + "/summary.json",
                                summaryJson(ctx, input, seq, r, timings, progress.elapsed()));

        std::ostringstream parts;
        for (std::size_t l = 0; l < r.parts_per_level.size(); ++l)
          parts << (l ? " " : "") << r.parts_per_level[l];
        progress.info("animseg: " + std::to_string(seq.size()) + " frames, " +
                      std::to_string(seq.totalPoints()) + " points, parts per level [" + parts.str() +
                      "], device " + r.device_used + ", " + num(progress.elapsed()) + " s -> " + out);
        for (const auto& m : r.missing) progress.info("  stage not available in this build: " + m);
        return 0;
      });
}
