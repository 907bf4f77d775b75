#pragma once
// The motion method's and the paper method's options shared by animseg and animseg_meanshift: one
// place for their names, defaults, help and checks.
#include <pcl_animseg/error.h>
#include <pcl_animseg/segmentation/mean_shift.h>

#include <boost/program_options.hpp>

#include <algorithm>
#include <cmath>

namespace pcl_animseg {
namespace tools {

/** Adds --motion-threshold, --crease-cost, --border-smoothness, --dissolve-ratio,
 * --joint-weight, --sliver-fraction and --reference-frame with the defaults of `d`. */
inline void addMotionOptions(boost::program_options::options_description& od,
                             const segmentation::MeanShiftParams& d) {
  namespace po = boost::program_options;
  od.add_options()
    ("motion-threshold", po::value<double>()->default_value(d.motion_threshold),
     "motion method: stop merging above this rigid-motion residual (point spacings)")
    ("crease-cost", po::value<double>()->default_value(d.crease_cost),
     "motion method: least cost of merging two parts that meet at a sharp crease and move "
     "differently (0: off)")
    ("border-smoothness", po::value<double>()->default_value(d.border_smoothness),
     "motion method: cost of a part border across a smooth surface, against the motion fit "
     "(borders prefer inward folds; 0: per-point borders)")
    ("dissolve-ratio", po::value<double>()->default_value(d.dissolve_ratio),
     "motion method: a part dissolves into the parts it touches when their motions explain it "
     "within this factor of its own motion's residual (0: pairwise merges only)")
    ("joint-weight", po::value<double>()->default_value(d.joint_weight),
     "motion method: cost per point spacing of a joint that a part's motion opens beyond 4 "
     "spacings from its neighbour's (keeps a finger from jumping onto the next; 0: off)")
    ("sliver-fraction", po::value<double>()->default_value(d.sliver_fraction),
     "motion method: a part smaller than this fraction of the mean part size is a sliver: it "
     "merges into a neighbour and does not count towards --parts (0: off; below 1)")
    ("reference-frame", po::value<int>()->default_value(std::max(0, d.reference_frame)),
     "motion method: the frame whose points are split into the parts and from which every frame "
     "is tracked (0-based, in the order of the input; pick one with the whole body in view)");
}

/** The options into `p`; throws Error (one line) for a value out of range, before any work. */
inline void readMotionOptions(const boost::program_options::variables_map& vm,
                              segmentation::MeanShiftParams& p) {
  p.motion_threshold = vm["motion-threshold"].as<double>();
  p.crease_cost = vm["crease-cost"].as<double>();
  p.border_smoothness = vm["border-smoothness"].as<double>();
  p.dissolve_ratio = vm["dissolve-ratio"].as<double>();
  p.joint_weight = vm["joint-weight"].as<double>();
  p.sliver_fraction = vm["sliver-fraction"].as<double>();
  p.reference_frame = vm["reference-frame"].as<int>();
  if (!(p.motion_threshold > 0.0)) throw Error("--motion-threshold must be positive");
  if (!(p.crease_cost >= 0.0)) throw Error("--crease-cost must be >= 0");
  if (!(p.border_smoothness >= 0.0)) throw Error("--border-smoothness must be >= 0");
  if (!(p.dissolve_ratio >= 0.0)) throw Error("--dissolve-ratio must be >= 0");
  if (!(p.joint_weight >= 0.0) || !std::isfinite(p.joint_weight))
    throw Error("--joint-weight must be a number >= 0");
  if (!(p.sliver_fraction >= 0.0 && p.sliver_fraction < 1.0))
    throw Error("--sliver-fraction must be in [0, 1)");
  if (p.reference_frame < 0) throw Error("--reference-frame must be >= 0");
}

/** Adds the paper method's Gaussian kd-tree knobs --exact-steps, --cell-extent,
 * --cell-min-points and --exact-borders with the defaults of `d`. */
inline void addPaperOptions(boost::program_options::options_description& od,
                            const segmentation::MeanShiftParams& d) {
  namespace po = boost::program_options;
  // clang-format off
  od.add_options()
    ("exact-steps", po::value<int>()->default_value(d.refine_iterations),
     "paper method, gkdtree backend: exact mean shift steps that finish the filter's iteration "
     "(0: the filter alone)")
    ("cell-extent", po::value<double>()->default_value(d.gkdtree.leaf_extent),
     "paper method, gkdtree backend: longest side of a filter cell, in bandwidths (Adams et "
     "al.'s eta; smaller: more cells, more accurate)")
    ("cell-min-points", po::value<int>()->default_value(d.gkdtree.min_leaf_points),
     "paper method, gkdtree backend: a filter cell of fewer points is not split (the sampling "
     "factor N/M is then at least about half of it; the paper used 1024-8192)")
    ("exact-borders",
     "paper method, gkdtree backend: points on a border between two clusters follow their own "
     "exact trajectories, so that the borders agree with the exact backend's; costs the exact "
     "method's time for those points (most points where clusters interleave)");
  // clang-format on
}

/** The paper options into `p`; throws Error (one line) for a value out of range. */
inline void readPaperOptions(const boost::program_options::variables_map& vm,
                             segmentation::MeanShiftParams& p) {
  p.refine_iterations = vm["exact-steps"].as<int>();
  p.exact_borders = vm.count("exact-borders") > 0;
  const double extent = vm["cell-extent"].as<double>();
  p.gkdtree.min_leaf_points = vm["cell-min-points"].as<int>();
  if (p.refine_iterations < 0) throw Error("--exact-steps must be >= 0");
  if (!(extent > 0.0) || !std::isfinite(extent)) throw Error("--cell-extent must be positive");
  if (p.gkdtree.min_leaf_points < 1) throw Error("--cell-min-points must be >= 1");
  p.gkdtree.leaf_extent = static_cast<float>(extent);
}

}  // namespace tools
}  // namespace pcl_animseg
