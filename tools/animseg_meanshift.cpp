// animseg_meanshift: the joint mean shift stage (Sect. 3.2-3.3) on its own: a sequence in,
// NAME.labels + NAME.pcd per frame and segmentation.txt (modes, densities, saddles) out.
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/tool_common.h>

#include "motion_options.h"

#include <cmath>
#include <string>

namespace po = boost::program_options;
namespace seg = pcl_animseg::segmentation;

int main(int argc, char** argv) {
  const seg::MeanShiftParams d;
  po::options_description od("Options");
  od.add_options()("input,i", po::value<std::string>()->required(),
                   "sequence (directory of frames or list file)")(
      "output,o", po::value<std::string>()->required(),
      "output directory: NAME.labels, NAME.pcd per frame, segmentation.txt")(
      "bandwidth,w", po::value<double>()->default_value(d.bandwidth),
      "kernel bandwidth w (Eq. 4), in units of the sequence scale (mean bounding-box diagonal)")(
      "weights", po::value<std::string>()->default_value("0.5,0.5,2,1"),
      "w1,w2,w3,w4 of Eq. 5-6: normal, position, signature between keypoints, signature")(
      "method", po::value<std::string>()->default_value(seg::toString(d.method)),
      "motion (patches tracked and merged by rigid motion) or paper (joint mean shift)")(
      "backend", po::value<std::string>()->default_value(seg::toString(d.backend)),
      "kernel sums: exact (kd-tree + exact Gaussian) or gkdtree (Gaussian kd-tree filter)")(
      "parts", po::value<int>()->default_value(0),
      "motion method: merge until exactly N parts (0: stop at the motion threshold)");
  pcl_animseg::tools::addMotionOptions(od, d);
  pcl_animseg::tools::addPaperOptions(od, d);
  od.add_options()(
      "no-features", po::bool_switch(),
      "cluster on position and normal only (skip scale space, keypoints and signatures)")(
      "seed", po::value<unsigned>()->default_value(d.seed), "random seed");
  return pcl_animseg::tools::runTool(
      argc, argv, "animseg_meanshift",
      "animseg_meanshift --input SEQ --output DIR [--bandwidth w] [--weights w1,w2,w3,w4] "
      "[--method motion|paper] [--backend exact|gkdtree] [--parts N] [--motion-threshold T] "
      "[--crease-cost C] [--border-smoothness S] [--dissolve-ratio R] [--joint-weight J] "
      "[--sliver-fraction F] [--reference-frame R] [--exact-steps K] [--cell-extent E] "
      "[--cell-min-points M] [--no-features] [--seed S]",
      od, [&](const pcl_animseg::tools::ToolContext& ctx) {
        pcl_animseg::Progress progress(ctx.quiet, ctx.verbose);
        seg::MeanShiftParams params;
        params.bandwidth = ctx.vm["bandwidth"].as<double>();
        const auto w =
            pcl_animseg::tools::parseNumberList(ctx.vm["weights"].as<std::string>(), 4, "--weights");
        params.w1 = w[0];
        params.w2 = w[1];
        params.w3 = w[2];
        params.w4 = w[3];
        params.method = seg::meanShiftMethodFromString(ctx.vm["method"].as<std::string>());
        params.backend = seg::meanShiftBackendFromString(ctx.vm["backend"].as<std::string>());
        params.target_clusters = ctx.vm["parts"].as<int>();
        if (params.target_clusters < 0) throw pcl_animseg::Error("--parts must be >= 0");
        pcl_animseg::tools::readMotionOptions(ctx.vm, params);
        pcl_animseg::tools::readPaperOptions(ctx.vm, params);
        params.seed = ctx.vm["seed"].as<unsigned>();
        const std::string out_dir = ctx.vm["output"].as<std::string>();
        // Parameters are checked before the (slow) feature computation.
        if (!(params.bandwidth > 0.0))
          throw pcl_animseg::Error("--bandwidth must be positive (got " +
                                   std::to_string(params.bandwidth) + ")");
        for (double x : w)
          if (!(x >= 0.0)) throw pcl_animseg::Error("--weights must be non-negative");

        auto seq = std::make_shared<pcl_animseg::PointCloudSequence>(pcl_animseg::io::loadSequence(
            ctx.vm["input"].as<std::string>(), pcl_animseg::io::LoadOptions(), &progress));
        seg::MeanShiftSegmentation ms;
        ms.setInputSequence(seq);
        ms.setParams(params);
        ms.setProgress(&progress);
        if (!ctx.vm["no-features"].as<bool>()) {
          const pcl_animseg::SequenceFeatures f = pcl_animseg::computeSequenceFeatures(
              *seq, pcl_animseg::MultiscaleParams(), &progress);
          ms.setSignatures(f.signatures);
          ms.setKeypoints(f.keypoints);
        }
        progress.begin("mean_shift");
        seg::SegmentationResult result;
        ms.segment(result);
        progress.end(std::to_string(result.num_clusters) + " parts (" + seg::toString(params.method) +
                     ", " + seg::toString(params.backend) + ", " + ms.deviceUsed() +
                     (result.sampling_factor > 0.0
                          ? ", filter N/M " + std::to_string(std::lround(result.sampling_factor))
                          : std::string()) +
                     ")");

        progress.begin("write", seq->size());
        pcl_animseg::io::saveSequenceLabels(out_dir, *seq, {result.labels});
        pcl_animseg::io::saveSegmentationInfo(out_dir + "/segmentation.txt", result);
        progress.end();
        return 0;
      });
}
