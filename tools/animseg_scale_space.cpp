// animseg_scale_space: the levels L(x, h), L(x, kh), ... of every frame (Sec. 3.1, Eq. 1) as PCD.
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
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
  return tools::runTool(
      argc, argv, "animseg_scale_space",
      "animseg_scale_space --input SEQ --output DIR [--scale-h H] [--scale-k K] [--scale-levels L]\n"
      "  writes DIR/NAME_L0.pcd .. NAME_L<L-1>.pcd (x y z normal_x normal_y normal_z curvature)",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        const auto [seq, out] = tools::loadFeatureToolInput(ctx.vm, progress);
        const double unit = sequenceSpacing(seq);
        progress.begin("scale_space", seq.size());
        for (std::size_t t = 0; t < seq.size(); ++t) {
          MLSScaleSpace mls;
          tools::setUpScaleSpace(ctx.vm, seq.frame(t), unit, mls);
          ScaleSpace ss;
          try {
            mls.compute(ss);
          } catch (const Error& e) {
            throw Error("frame '" + seq.name(t) + "': " + e.what());
          }
          for (std::size_t i = 0; i < ss.levels.size(); ++i)
            io::writeAtomically(out + "/" + seq.name(t) + "_L" + std::to_string(i) + ".pcd",
                                [&](const std::string& tmp) {
                                  if (pcl::io::savePCDFileBinary(tmp, *ss.levels[i]) != 0)
                                    throw Error("cannot write " + tmp);
                                });
          progress.update(t + 1);
        }
        progress.end();
        return 0;
      });
}
