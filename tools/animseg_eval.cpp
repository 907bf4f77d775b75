// animseg_eval: scores predicted part labels against ground truth (ARI, parts, rigidity error).
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/frame_readers.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/tool_common.h>

#include <algorithm>
#include <boost/property_tree/json_parser.hpp>
#include <boost/property_tree/ptree.hpp>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <sstream>

namespace po = boost::program_options;
namespace fs = std::filesystem;
using namespace pcl_animseg;

namespace {

std::string fixed(double v, int digits = 4) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", digits, v);
  return buf;
}

/** Positions of every frame in file order when the truth frames are meshes sharing one vertex
 * order (same vertex count, faces present); empty otherwise, with the reason in `why`. */
std::vector<Eigen::Matrix3Xd> sharedVertexPositions(const std::vector<std::string>& frames,
                                                    std::size_t labels, std::string& why,
                                                    Progress& progress) {
  std::vector<Eigen::Matrix3Xd> positions;
  progress.begin("positions", frames.size());
  for (std::size_t t = 0; t < frames.size(); ++t) {
    const std::string ext = fs::path(frames[t]).extension().string();
    if (ext == ".pcd" || ext == ".PCD" || ext == ".xyz" || ext == ".XYZ") {
      why = "point frames";
      return {};
    }
    const io::RawFrame raw = io::readRawFrame(frames[t]);
    if (raw.faces.empty()) {
      why = "point frames";
      return {};
    }
    if (raw.points.size() != labels || (t > 0 && static_cast<Eigen::Index>(raw.points.size()) != positions[0].cols())) {
      why = "vertex counts differ between frames";
      return {};
    }
    Eigen::Matrix3Xd m(3, raw.points.size());
    for (std::size_t i = 0; i < raw.points.size(); ++i) {
      if (!raw.points[i].allFinite()) {
        why = "non-finite vertices";
        return {};
      }
      m.col(i) = raw.points[i].cast<double>();
    }
    positions.push_back(std::move(m));
    progress.update(t + 1);
  }
  progress.end();
  return positions;
}

/** The true parts' names from the truth directory's synth.json (animseg_synth's "parts", index
 * = label); empty where there is no such file or list. */
std::vector<std::string> partNames(const std::string& truth, Progress& progress) {
  std::error_code ec;
  const fs::path path = fs::path(truth) / "synth.json";
  if (!fs::is_directory(truth, ec) || !fs::is_regular_file(path, ec)) return {};
  namespace pt = boost::property_tree;
  pt::ptree tree;
  try {
    pt::read_json(path.string(), tree);
  } catch (const pt::json_parser_error& e) {
    progress.debug("no part names: '" + path.string() + "': " + e.message());
    return {};
  }
  std::vector<std::string> names;
  if (const auto parts = tree.get_child_optional("parts"))
    for (const auto& el : *parts) names.push_back(el.second.get_value<std::string>());
  return names;
}

/** Per true part: its points, the predicted part holding most of them, recall, precision, IoU,
 * and the other true parts that went to the same predicted part (merged with it). */
std::string partTable(const std::vector<evaluation::PartMatch>& parts,
                      const std::vector<std::string>& names) {
  auto nameOf = [&](int label) {
    return label >= 0 && static_cast<std::size_t>(label) < names.size()
               ? names[static_cast<std::size_t>(label)]
               : std::to_string(label);
  };
  std::size_t width = 4;
  for (const auto& m : parts) width = std::max(width, nameOf(m.truth).size());
  std::ostringstream o;
  char line[256];
  std::snprintf(line, sizeof(line), "%-*s %8s  %5s  %6s  %9s  %6s\n", static_cast<int>(width),
                "part", "points", "pred", "recall", "precision", "IoU");
  o << line;
  for (const auto& m : parts) {
    std::string merged;
    for (const auto& other : parts)
      if (other.truth != m.truth && other.predicted == m.predicted)
        merged += (merged.empty() ? "  merged with " : ", ") + nameOf(other.truth);
    std::snprintf(line, sizeof(line), "%-*s %8zu  %5d  %s     %s  %s", static_cast<int>(width),
                  nameOf(m.truth).c_str(), m.points, m.predicted, fixed(m.recall).c_str(),
                  fixed(m.precision).c_str(), fixed(m.iou).c_str());
    o << line << merged << "\n";
  }
  return o.str();
}

}  // namespace

int main(int argc, char** argv) {
  po::options_description od("Options");
  od.add_options()
    ("pred,p", po::value<std::string>()->required(),
     "directory of predictions: NAME.labels per frame (as written by animseg)")
    ("truth,t", po::value<std::string>()->required(),
     "ground-truth sequence: a directory (or list file) of frames with NAME.gt beside each")
    ("json", po::value<std::string>(), "where to write the JSON report (default PRED/eval.json)")
    ("level", po::value<int>()->default_value(0),
     "column of the .labels files to score (0: finest level)");
  return tools::runTool(
      argc, argv, "animseg_eval",
      "animseg_eval --pred OUT --truth DIR [--json FILE] [--level L] [--quiet]", od,
      [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        const std::string pred_dir = ctx.vm["pred"].as<std::string>();
        const std::string truth = ctx.vm["truth"].as<std::string>();
        const int level = ctx.vm["level"].as<int>();
        if (level < 0) throw Error("--level must be >= 0 (got " + std::to_string(level) + ")");
        std::error_code ec;
        if (!fs::is_directory(pred_dir, ec))
          throw Error("--pred '" + pred_dir + "' is not a directory");
        const std::string json_path =
            ctx.vm.count("json") ? ctx.vm["json"].as<std::string>() : pred_dir + "/eval.json";

        const std::vector<std::string> frames = io::listSequence(truth);
        std::vector<std::string> names;
        std::vector<std::vector<int>> pred, gt;
        progress.begin("load", frames.size());
        for (std::size_t t = 0; t < frames.size(); ++t) {
          const std::string name = io::stem(frames[t]);
          const std::string gt_path = (fs::path(frames[t]).parent_path() / (name + ".gt")).string();
          const std::string pred_path = (fs::path(pred_dir) / (name + ".labels")).string();
          if (!fs::exists(gt_path, ec))
            throw Error("frame '" + name + "' has no ground truth: '" + gt_path + "' is missing");
          if (!fs::exists(pred_path, ec))
            throw Error("frame '" + name + "' has no prediction: '" + pred_path + "' is missing");
          const auto columns = io::loadLabelColumns(pred_path);
          if (level >= static_cast<int>(columns.size()))
            throw Error("'" + pred_path + "' has " + std::to_string(columns.size()) +
                        " level(s); --level " + std::to_string(level) + " does not exist");
          std::vector<int> truth_labels = io::loadLabels(gt_path, 0);
          if (columns[level].size() != truth_labels.size())
            throw Error("frame '" + name + "': " + std::to_string(columns[level].size()) +
                        " predicted labels in '" + pred_path + "' but " +
                        std::to_string(truth_labels.size()) + " true labels in '" + gt_path + "'");
          names.push_back(name);
          pred.push_back(columns[level]);
          gt.push_back(std::move(truth_labels));
          progress.update(t + 1);
        }
        progress.end();

        std::string why;
        const auto positions = sharedVertexPositions(frames, gt[0].size(), why, progress);
        progress.begin("score");
        const evaluation::Report r = evaluation::evaluate(pred, gt, positions);
        progress.end();

        std::ostringstream table;
        table << "frame        points     ARI\n";
        for (std::size_t t = 0; t < names.size(); ++t) {
          char line[160];
          std::snprintf(line, sizeof(line), "%-10s %8zu  %s\n", names[t].c_str(), gt[t].size(),
                        fixed(r.frame_ari[t]).c_str());
          table << line;
        }
        table << "pooled ARI          " << fixed(r.pooled_ari) << "\n";
        table << "mean frame ARI      " << fixed(r.mean_frame_ari) << "\n";
        table << "parts (pred/true)   " << r.predicted_parts << " / " << r.true_parts << "\n";
        if (r.rigidity_error >= 0) {
          table << "rigidity error      " << fixed(r.rigidity_error, 5) << "\n";
          table << "label consistency   " << fixed(r.label_consistency) << "\n";
        } else {
          table << "rigidity error      n/a (" << why << ")\n";
        }
        const std::vector<std::string> part_names = partNames(truth, progress);
        table << partTable(r.parts, part_names);
        std::cout << table.str() << std::flush;

        std::ostringstream js;
        js << "{\n  \"pred\": \"" << tools::jsonEscape(pred_dir) << "\",\n";
        js << "  \"truth\": \"" << tools::jsonEscape(truth) << "\",\n";
        js << "  \"level\": " << level << ",\n  \"frames\": " << tools::jsonStringArray(names)
           << ",\n  \"part_names\": "
           << (part_names.empty() ? "null" : tools::jsonStringArray(part_names)) << ",\n";
        // Report::toJson() is one object; its fields are spliced into this one.
        const std::string body = r.toJson();
        js << body.substr(body.find('{') + 2);
        io::writeTextAtomically(json_path, js.str());
        progress.info("animseg_eval: pooled ARI " + fixed(r.pooled_ari) + " over " +
                      std::to_string(r.points) + " points -> " + json_path);
        return 0;
      });
}
