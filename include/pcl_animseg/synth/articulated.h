#pragma once
/** \file articulated.h Articulated test sequences with known parts (ground truth we can trust). */
#include <pcl_animseg/sequence.h>

#include <Eigen/Core>
#include <string>
#include <vector>

namespace pcl_animseg {
class Progress;
namespace synth {

/** \brief Body plans: trees of rigid parts (capsules / ellipsoids / boxes) joined at joints. */
enum class BodyPlan { Quadruped, Humanoid, Spider, Snake, Hand };

/** \brief "quadruped", "humanoid", ... -> BodyPlan; throws Error for an unknown name. */
BodyPlan bodyPlanFromString(const std::string& name);
std::string toString(BodyPlan plan);
/** \brief All plans, for loops in tests and benchmarks. */
std::vector<BodyPlan> allBodyPlans();

/** \brief Generator knobs. Lengths are in body units (a quadruped's torso is ~1.1 long). Point
 * mode samples the outer surface of the posed union of parts afresh every frame; mesh mode keeps
 * one tessellated surface per part whose vertices move rigidly with it. */
struct SynthParams {
  BodyPlan plan = BodyPlan::Quadruped;
  int frames = 20;               ///< T
  int points = 4000;             ///< mean points per frame (point mode)
  double point_variation = 0.2;  ///< each frame gets points * (1 ± variation), uniformly drawn
  double noise = 0.0;            ///< Gaussian noise sigma, as a fraction of the bbox diagonal
  double motion = 1.0;           ///< joint-angle amplitude multiplier (1: large, gallop-like)
  double scale = 1.0;            ///< uniform scale of the whole body
  bool mesh = false;         ///< mesh mode: one triangulated surface, same vertex order every frame
  int mesh_resolution = 24;  ///< tessellation per part in mesh mode
  unsigned seed = 1;
};

/** \brief One generated frame: points with true normals, the true part of each point, and the
 * faces in mesh mode. */
struct SynthFrame {
  PointCloudSequence::Cloud::Ptr cloud;
  std::vector<int> labels;
  std::vector<pcl::Vertices> faces;
  /** The centre of each part's shape in this frame (index = part id = label); a true normal points
   * away from it, which the tests use. */
  std::vector<Eigen::Vector3d> part_centres;
};

/** \brief Number of rigid parts of a plan. */
int partCount(BodyPlan plan);
/** \brief Names of the parts of a plan (index = label), e.g. "torso", "leg_fl_upper". */
std::vector<std::string> partNames(BodyPlan plan);

/** \brief Throws Error for bad parameters (frames < 1, points < 10, variation outside [0, 1),
 * negative noise or motion, scale <= 0, mesh_resolution outside [4, 256]). */
void validate(const SynthParams& params);

/** \brief Generates the sequence (after validate()); deterministic for a seed on every platform
 * (std::mt19937 with our own distributions). */
std::vector<SynthFrame> generate(const SynthParams& params);

/** \brief The generated frames as a PointCloudSequence (names f000, f001, ...). */
PointCloudSequence toSequence(const std::vector<SynthFrame>& frames);

/** \brief Frame names f000, f001, ... (more digits when there are more than 1000 frames). */
std::string frameName(std::size_t t, std::size_t frames);

/** \brief Writes frames as DIR/fNNN.ply (binary, with faces in mesh mode) + DIR/fNNN.gt (one
 * label per point), each file atomically; creates DIR. */
void writeSequence(const std::string& dir, const std::vector<SynthFrame>& frames,
                   Progress* progress = nullptr);

}  // namespace synth
}  // namespace pcl_animseg
