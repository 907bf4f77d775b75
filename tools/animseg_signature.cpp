// animseg_signature: the signature sigma(p, n, h) of Eq. 2-3 for every point of every frame, with
// the keypoints flagged, as PCD (x y z signature[D] keypoint).
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>
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
    ("signature-h", po::value<double>()->default_value(d.signature_h),
     "scale h of the signature (disc radius 2h, Eq. 2), spacings")
    ("layout", po::value<std::string>()->default_value("32,8,6,4"), "R,S,R',S' (Eq. 2-3)");
  return tools::runTool(
      argc, argv, "animseg_signature",
      "animseg_signature --input SEQ --output DIR [--signature-h H] [--layout R,S,R',S']\n"
      "  writes DIR/NAME_signature.pcd (x y z signature[R'*S'] keypoint)",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        MultiscaleParams p;
        tools::readScaleSpaceOptions(ctx.vm, p);
        p.signature_h = ctx.vm["signature-h"].as<double>();
        const auto l = tools::parseNumberList(ctx.vm["layout"].as<std::string>(), 4, "--layout");
        for (double v : l)
          if (v != static_cast<int>(v)) throw Error("--layout takes 4 integers R,S,R',S'");
        p.layout.radial = static_cast<int>(l[0]);
        p.layout.angular = static_cast<int>(l[1]);
        p.layout.radial_freqs = static_cast<int>(l[2]);
        p.layout.angular_freqs = static_cast<int>(l[3]);
        p.layout.validate();
        const auto [seq, out] = tools::loadFeatureToolInput(ctx.vm, progress);
        const SequenceFeatures f = computeSequenceFeatures(seq, p, &progress);
        progress.begin("write", seq.size());
        for (std::size_t t = 0; t < seq.size(); ++t) {
          const pcl::PCLPointCloud2 cloud =
              signatureCloud(*seq.frame(t), f.signatures[t], f.keypoints[t]);
          io::writeAtomically(out + "/" + seq.name(t) + "_signature.pcd",
                              [&](const std::string& tmp) {
                                if (pcl::io::savePCDFile(tmp, cloud, Eigen::Vector4f::Zero(),
                                                         Eigen::Quaternionf::Identity(), true) != 0)
                                  throw Error("cannot write " + tmp);
                              });
          progress.update(t + 1);
        }
        progress.end();
        return 0;
      });
}
