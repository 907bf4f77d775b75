// animseg_keypoints: multi-scale DoG keypoints of every frame (Sec. 3.1) as PCD with
// x y z scale response index level fields (opens in pcl_viewer).
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/tool_common.h>

#include "scale_space_options.h"

#include <pcl/io/pcd_io.h>

namespace po = boost::program_options;
using namespace pcl_animseg;

int main(int argc, char** argv) {
  const MultiscaleParams d;
  po::options_description od = tools::featureToolOptions(d);
  od.add_options()
    ("min-response", po::value<double>()->default_value(d.min_response),
     "minimum |D| of a keypoint (contrast threshold)")
    ("edge-ratio", po::value<double>()->default_value(d.edge_ratio),
     "largest ratio of the principal curvatures of D (SIFT's r)");
  return tools::runTool(
      argc, argv, "animseg_keypoints",
      "animseg_keypoints --input SEQ --output DIR [--scale-h H] [--scale-k K] [--scale-levels L]\n"
      "  writes DIR/NAME_keypoints.pcd (x y z scale response index level)",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        const auto [seq, out] = tools::loadFeatureToolInput(ctx.vm, progress);
        const double unit = sequenceSpacing(seq);
        std::size_t total = 0;
        progress.begin("keypoints", seq.size());
        for (std::size_t t = 0; t < seq.size(); ++t) {
          DoGKeypoint::KeypointCloud kp;
          try {
            MLSScaleSpace mls;
            tools::setUpScaleSpace(ctx.vm, seq.frame(t), unit, mls);
            ScaleSpace ss;
            mls.compute(ss);
            DoGKeypoint dog;
            dog.setScaleSpace(ss);
            dog.setMinResponse(ctx.vm["min-response"].as<double>());
            dog.setEdgeRatio(ctx.vm["edge-ratio"].as<double>());
            dog.compute(kp);
          } catch (const Error& e) {
            throw Error("frame '" + seq.name(t) + "': " + e.what());
          }
          total += kp.size();
          io::writeAtomically(out + "/" + seq.name(t) + "_keypoints.pcd",
                              [&](const std::string& tmp) {
                                // pcl refuses to write an empty cloud; an empty file is valid.
                                if (kp.empty()) {
                                  pcl::PCDWriter w;
                                  if (w.writeASCII(tmp, kp) != 0) throw Error("cannot write " + tmp);
                                } else if (pcl::io::savePCDFileBinary(tmp, kp) != 0) {
                                  throw Error("cannot write " + tmp);
                                }
                              });
          progress.update(t + 1);
        }
        progress.end(std::to_string(total) + " keypoints");
        return 0;
      });
}
