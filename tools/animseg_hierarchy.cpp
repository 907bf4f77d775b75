// animseg_hierarchy: nested levels by region persistence (Sect. 5) and each part's rigid motion.
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/hierarchy.h>
#include <pcl_animseg/segmentation/rigid_motion.h>
#include <pcl_animseg/tool_common.h>

#include <string>

namespace po = boost::program_options;
namespace seg = pcl_animseg::segmentation;

int main(int argc, char** argv) {
  seg::HierarchyParams d;
  po::options_description od("Options");
  od.add_options()("input,i", po::value<std::string>()->required(),
                   "sequence (directory of frames or list file)")(
      "labels,l", po::value<std::string>()->required(),
      "directory with NAME.labels per frame (first column) and segmentation.txt (mode densities "
      "and saddles, as animseg_meanshift / animseg_refine write them)")(
      "segmentation", po::value<std::string>(), "segmentation.txt elsewhere than in --labels")(
      "output,o", po::value<std::string>()->required(),
      "output directory: NAME.labels (one column per level, finest first), NAME.pcd, "
      "transforms.json")("levels", po::value<int>()->default_value(d.max_levels),
                         "levels above level 0, at most")(
      "initial-factor", po::value<double>()->default_value(d.initial_factor),
      "first threshold RP_delta = factor * mean(RP) (Eq. 12)")(
      "step", po::value<double>()->default_value(d.step), "RP_delta increase per level (0.05-0.1)")(
      "no-transforms", po::bool_switch(), "do not estimate the parts' rigid motions");
  return pcl_animseg::tools::runTool(
      argc, argv, "animseg_hierarchy",
      "animseg_hierarchy --input SEQ --labels DIR --output DIR [--levels L] [--step s]", od,
      [&](const pcl_animseg::tools::ToolContext& ctx) {
        pcl_animseg::Progress progress(ctx.quiet, ctx.verbose);
        seg::HierarchyParams params;
        params.max_levels = ctx.vm["levels"].as<int>();
        params.initial_factor = ctx.vm["initial-factor"].as<double>();
        params.step = ctx.vm["step"].as<double>();
        if (params.max_levels < 0) throw pcl_animseg::Error("--levels must be >= 0");
        if (!(params.step > 0.0)) throw pcl_animseg::Error("--step must be positive");

        const std::string label_dir = ctx.vm["labels"].as<std::string>();
        const std::string out_dir = ctx.vm["output"].as<std::string>();
        const std::string info = ctx.vm.count("segmentation")
                                     ? ctx.vm["segmentation"].as<std::string>()
                                     : label_dir + "/segmentation.txt";
        const pcl_animseg::PointCloudSequence seq = pcl_animseg::io::loadSequence(
            ctx.vm["input"].as<std::string>(), pcl_animseg::io::LoadOptions(), &progress);
        progress.begin("read labels");
        seg::SegmentationResult input;
        pcl_animseg::io::loadSegmentationInfo(info, input);
        input.labels = pcl_animseg::io::loadSequenceLabels(label_dir, seq, 0);
        progress.end();

        progress.begin("hierarchy");
        seg::PersistenceHierarchy hierarchy;
        hierarchy.setParams(params);
        seg::HierarchyResult levels;
        hierarchy.compute(input, levels);
        std::string counts;
        for (int n : levels.num_parts) counts += (counts.empty() ? "" : " ") + std::to_string(n);
        progress.end(std::to_string(levels.levels()) + " levels, parts: " + counts);

        if (!ctx.vm["no-transforms"].as<bool>()) {
          progress.begin("rigid_motion");
          seg::RigidMotionEstimation motion;
          motion.setInputSequence(&seq);
          const std::vector<seg::LevelMotion> motions =
              motion.computeLevels(levels.labels, levels.num_parts);
          progress.end();
          pcl_animseg::io::ensureDirectory(out_dir);
          seg::writeTransformsJson(out_dir + "/transforms.json", seq, motions);
        }
        progress.begin("write", seq.size());
        pcl_animseg::io::saveSequenceLabels(out_dir, seq, levels.labels);
        progress.end();
        return 0;
      });
}
