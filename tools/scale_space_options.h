#pragma once
// The scale-space options (Eq. 1) shared by animseg and the feature tools (animseg_scale_space,
// animseg_keypoints, animseg_signature): one place for their names, defaults and help.
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>

#include <boost/program_options.hpp>
#include <string>

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

/** The feature tools' options: --input and --output, then the scale space's (defaults of `d`). */
inline boost::program_options::options_description featureToolOptions(const MultiscaleParams& d) {
  namespace po = boost::program_options;
  po::options_description od("Options");
  // clang-format off
  od.add_options()
    ("input,i", po::value<std::string>()->required(), "sequence (directory or list file)")
    ("output,o", po::value<std::string>()->required(), "output directory");
  // clang-format on
  addScaleSpaceOptions(od, d);
  return od;
}

/** What a feature tool starts from: its sequence (--input) and output directory (--output,
 * made here, after the sequence loaded). */
struct FeatureToolInput {
  PointCloudSequence seq;
  std::string out;
};
inline FeatureToolInput loadFeatureToolInput(const boost::program_options::variables_map& vm,
                                             Progress& progress) {
  FeatureToolInput in{io::loadSequence(vm["input"].as<std::string>(), io::LoadOptions(), &progress),
                      vm["output"].as<std::string>()};
  io::ensureDirectory(in.out);
  return in;
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
