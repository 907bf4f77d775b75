#pragma once
/** \file articulated.h Articulated test sequences with known parts (ground truth we can trust). */
#include <pcl_animseg/sequence.h>

#include <string>
#include <vector>

namespace pcl_animseg {
namespace synth {

/** \brief Body plans: trees of rigid parts (capsules / ellipsoids / boxes) joined at joints. */
enum class BodyPlan { Quadruped, Humanoid, Spider, Snake, Hand };

/** \brief "quadruped", "humanoid", ... -> BodyPlan; throws Error for an unknown name. */
BodyPlan bodyPlanFromString(const std::string& name);
std::string toString(BodyPlan plan);
/** \brief All plans, for loops in tests and benchmarks. */
std::vector<BodyPlan> allBodyPlans();

struct SynthParams {
  BodyPlan plan = BodyPlan::Quadruped;
  int frames = 20;               ///< T
  int points = 4000;             ///< mean points per frame (point mode)
  double point_variation = 0.2;  ///< each frame gets points * (1 ± variation), uniformly drawn
  double noise = 0.0;            ///< Gaussian noise sigma, as a fraction of the bbox diagonal
  double motion = 1.0;           ///< joint-angle amplitude multiplier (1: large, gallop-like)
  double scale = 1.0;            ///< uniform scale of the whole body
  bool mesh = false;             ///< mesh mode: one triangulated surface, same vertex order every frame
  int mesh_resolution = 24;      ///< tessellation per part in mesh mode
  unsigned seed = 1;
};

/** \brief One generated frame: points with true normals, the true part of each point, and the
 * faces in mesh mode. */
struct SynthFrame {
  PointCloudSequence::Cloud::Ptr cloud;
  std::vector<int> labels;
  std::vector<pcl::Vertices> faces;
};

/** \brief Number of rigid parts of a plan. */
int partCount(BodyPlan plan);

/** \brief Generates the sequence; deterministic for a seed. */
std::vector<SynthFrame> generate(const SynthParams& params);

/** \brief The generated frames as a PointCloudSequence (names f000, f001, ...). */
PointCloudSequence toSequence(const std::vector<SynthFrame>& frames);

/** \brief Writes frames as DIR/fNNN.ply + DIR/fNNN.gt (creates DIR). */
void writeSequence(const std::string& dir, const std::vector<SynthFrame>& frames);

}  // namespace synth
}  // namespace pcl_animseg
