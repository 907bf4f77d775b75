// animseg_refine: GMM boundary refinement (Sect. 4) of the labels animseg_meanshift wrote.
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/tool_common.h>

#include <algorithm>
#include <filesystem>
#include <string>

namespace po = boost::program_options;
namespace seg = pcl_animseg::segmentation;

int main(int argc, char** argv) {
  seg::RefinementParams d;
  po::options_description od("Options");
  od.add_options()("input,i", po::value<std::string>()->required(),
                   "sequence (directory of frames or list file)")(
      "labels,l", po::value<std::string>()->required(),
      "directory with NAME.labels per frame (first column used) and, optionally, segmentation.txt")(
      "output,o", po::value<std::string>()->required(),
      "output directory: NAME.labels, NAME.pcd, segmentation.txt (copied through)")(
      "narrow-band", po::value<double>()->default_value(d.narrow_band),
      "L_r: width of the band W that may change label, in point spacings")(
      "outer-band", po::value<double>()->default_value(d.outer_band),
      "L_R: outer width of the training bands F and B, in point spacings")(
      "train-distance", po::value<double>()->default_value(d.training_min_distance),
      "only F/B points farther than this from the boundary train the GMMs (spacings)")(
      "min-log-ratio", po::value<double>()->default_value(d.min_log_ratio),
      "a point changes side only when log p(other)/p(own) exceeds this (0: the paper's Eq. 11)")(
      "spatial-weight", po::value<double>()->default_value(d.spatial_weight),
      "weight of the optional distance-to-band term (0: normals only)")(
      "motion-tolerance", po::value<double>()->default_value(d.motion_tolerance),
      "a point takes the other part only if that part's rigid motion explains its trajectory no "
      "worse than (1 + this) x its own part's")(
      "motion-frames", po::value<int>()->default_value(d.motion_frames),
      "the motion check averages over at most this many frames, spread evenly (0: every frame; "
      "its cost grows with the square of the frame count)")(
      "no-motion-check", po::bool_switch(),
      "the paper's rule: decide by normals alone, without the rigid-motion check")(
      "iterations", po::value<int>()->default_value(d.max_iterations),
      "refinement iterations at most")(
      "fold-snap", po::value<double>()->default_value(d.fold_snap_band),
      "after the GMM pass, points within this many spacings of a border move onto the inward "
      "fold where one part leaves the other (0: off)")(
      "fold-snap-angle", po::value<double>()->default_value(d.fold_snap_angle_deg),
      "degrees of inward folding that a point's own part must cross more than another part")(
      "per-frame", po::bool_switch(), "refine each frame on its own instead of pooling all frames")(
      "seed", po::value<unsigned>()->default_value(1), "random seed of the GMM initialisation");
  return pcl_animseg::tools::runTool(
      argc, argv, "animseg_refine",
      "animseg_refine --input SEQ --labels DIR --output DIR [--narrow-band Lr] [--outer-band LR]",
      od, [&](const pcl_animseg::tools::ToolContext& ctx) {
        pcl_animseg::Progress progress(ctx.quiet, ctx.verbose);
        seg::RefinementParams params;
        params.narrow_band = ctx.vm["narrow-band"].as<double>();
        params.outer_band = ctx.vm["outer-band"].as<double>();
        params.training_min_distance = ctx.vm["train-distance"].as<double>();
        params.min_log_ratio = ctx.vm["min-log-ratio"].as<double>();
        params.spatial_weight = ctx.vm["spatial-weight"].as<double>();
        params.motion_tolerance = ctx.vm["motion-tolerance"].as<double>();
        params.motion_check = !ctx.vm["no-motion-check"].as<bool>();
        params.motion_frames = ctx.vm["motion-frames"].as<int>();
        params.max_iterations = ctx.vm["iterations"].as<int>();
        params.fold_snap_band = ctx.vm["fold-snap"].as<double>();
        params.fold_snap_angle_deg = ctx.vm["fold-snap-angle"].as<double>();
        params.pool_frames = !ctx.vm["per-frame"].as<bool>();
        params.seed = ctx.vm["seed"].as<unsigned>();
        if (!(params.narrow_band > 0.0) || !(params.outer_band > params.narrow_band))
          throw pcl_animseg::Error("need 0 < --narrow-band < --outer-band");
        if (!(params.motion_tolerance >= 0.0))
          throw pcl_animseg::Error("--motion-tolerance must be >= 0");
        if (params.motion_frames < 0 || params.motion_frames == 1)
          throw pcl_animseg::Error("--motion-frames must be 0 (every frame) or >= 2");
        if (!(params.fold_snap_band >= 0.0) || !(params.fold_snap_angle_deg > 0.0))
          throw pcl_animseg::Error("need --fold-snap >= 0 and --fold-snap-angle > 0");

        const std::string label_dir = ctx.vm["labels"].as<std::string>();
        const std::string out_dir = ctx.vm["output"].as<std::string>();
        const pcl_animseg::PointCloudSequence seq = pcl_animseg::io::loadSequence(
            ctx.vm["input"].as<std::string>(), pcl_animseg::io::LoadOptions(), &progress);
        progress.begin("read labels");
        seg::SegmentationResult input;
        input.labels = pcl_animseg::io::loadSequenceLabels(label_dir, seq, 0);
        const std::string info = label_dir + "/segmentation.txt";
        const bool have_info = std::filesystem::exists(info);
        if (have_info) {
          pcl_animseg::io::loadSegmentationInfo(info, input);
        } else {
          for (const auto& f : input.labels)
            for (int l : f) input.num_clusters = std::max(input.num_clusters, l + 1);
        }
        progress.end(std::to_string(input.num_clusters) + " parts");

        progress.begin("refine");
        seg::GMMBoundaryRefinement refine;
        refine.setInputSequence(&seq);
        refine.setParams(params);
        seg::SegmentationResult output;
        refine.refine(input, output);
        std::size_t changed = 0;
        for (std::size_t c : refine.getStats().changed) changed += c;
        progress.end(std::to_string(refine.getStats().iterations) + " iterations, " +
                     std::to_string(changed) + " points relabelled by the GMMs, " +
                     std::to_string(refine.getStats().snapped) + " snapped onto folds");

        progress.begin("write", seq.size());
        pcl_animseg::io::saveSequenceLabels(out_dir, seq, {output.labels});
        if (have_info) pcl_animseg::io::saveSegmentationInfo(out_dir + "/segmentation.txt", output);
        progress.end();
        return 0;
      });
}
