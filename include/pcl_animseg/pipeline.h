#pragma once
/** \file pipeline.h The whole method of Fig. 1 as one call: what `animseg` runs. */
#include <pcl_animseg/sequence.h>

#include <Eigen/Geometry>

#include <map>
#include <string>
#include <vector>

namespace pcl_animseg {
class Progress;

/** \brief Every knob of the one-shot pipeline; `animseg` options and `--config` keys map onto it. */
struct PipelineParams {
  std::string device = "auto";  ///< auto | cpu | gpu (mean shift backend)
  int levels = 4;               ///< hierarchy levels above level 0, at most
  double bandwidth = 0.3;       ///< mean shift bandwidth w (Eq. 4), in normalised units
  double w1 = 0.5;              ///< normal weight (Eq. 5-6)
  double w2 = 0.5;              ///< position weight
  double w3 = 2.0;              ///< signature weight between keypoints
  double w4 = 1.0;              ///< signature weight otherwise
  std::string method = "default";  ///< segmentation method: default | paper
  unsigned seed = 1;
};

/** \brief Rigid motion of one part from frame 0 to frame t (DESIGN.md transforms.json). */
struct PartMotion {
  int part = -1;
  std::vector<Eigen::Matrix3d> rotation;     ///< per frame
  std::vector<Eigen::Vector3d> translation;  ///< per frame
  std::vector<double> rms;                   ///< per frame, same units as the input
};

/** \brief What a run produced. Labels are in kept-point order (PointCloudSequence); expand with
 * PointCloudSequence::toInputOrder for files. */
struct PipelineResult {
  /** levels[l][t][j]: part of point j of frame t at hierarchy level l (0 = finest). */
  std::vector<std::vector<std::vector<int>>> levels;
  std::vector<int> parts_per_level;
  /** Stage name -> seconds; stages that do not exist in this build are listed in `missing`. */
  std::vector<std::pair<std::string, double>> timings;
  std::vector<std::string> missing;
  std::string device_used = "cpu";
  std::size_t keypoints = 0;
  std::vector<std::size_t> keypoints_per_frame;
  std::vector<PartMotion> motions;  ///< level-0 parts
  std::vector<std::string> notes;   ///< fall-backs and warnings worth keeping in summary.json
};

/** \brief Runs scale space, keypoints, signatures, mean shift, refinement, hierarchy and rigid
 * motion on a loaded sequence. Throws Error on bad parameters. */
PipelineResult runPipeline(const PointCloudSequence& sequence, const PipelineParams& params,
                           Progress& progress);

/** \brief Checks parameters (bandwidth > 0, weights >= 0, known device/method, levels >= 0). */
void validate(const PipelineParams& params);

}  // namespace pcl_animseg
