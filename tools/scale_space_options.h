#pragma once
// The scale-space options (Eq. 1) shared by animseg and the feature tools (animseg_scale_space,
// animseg_keypoints, animseg_signature): one place for their names, defaults and help.
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>

#include <boost/program_options.hpp>

namespace pcl_animseg {
namespace tools {

/** Adds --scale-h, --scale-k and --scale-levels with the defaults of `d`. */
inline void addScaleSpaceOptions(boost::program_options::options_description& od,
                                 const MultiscaleParams& d) {
  namespace po = boost::program_options;
  od.add_options()
    ("scale-h", po::value<double>()->default_value(d.h), "smallest scale h (Eq. 1), spacings")
    ("scale-k", po::value<double>()->default_value(d.k), "factor k between scales (Eq. 1)")
    ("scale-levels", po::value<int>()->default_value(d.levels), "number of levels (keypoints need >= 4)");
}

/** The options' scales into `p` (h, k, levels). */
inline void readScaleSpaceOptions(const boost::program_options::variables_map& vm,
                                  MultiscaleParams& p) {
  p.h = vm["scale-h"].as<double>();
  p.k = vm["scale-k"].as<double>();
  p.levels = vm["scale-levels"].as<int>();
}

/** An MLS scale space of `frame` at the options' scales, in units of `spacing`. */
inline void setUpScaleSpace(const boost::program_options::variables_map& vm,
                            const PointCloudSequence::Cloud::ConstPtr& frame, double spacing,
                            MLSScaleSpace& mls) {
  MultiscaleParams p;
  readScaleSpaceOptions(vm, p);
  mls.setInputCloud(frame);
  mls.setScale(p.h);
  mls.setScaleFactor(p.k);
  mls.setNumberOfLevels(p.levels);
  mls.setSpacing(spacing);
}

}  // namespace tools
}  // namespace pcl_animseg
