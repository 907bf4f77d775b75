#pragma once
// The generated sequences of the pipeline-level quality tests: an articulated body plan with
// large joint motion and +-20% points per frame (the issues' test conditions).
#include <pcl_animseg/synth/articulated.h>

namespace animseg_test {

inline pcl_animseg::synth::SynthParams sequenceParams(pcl_animseg::synth::BodyPlan plan,
                                                      int frames, int points, unsigned seed) {
  pcl_animseg::synth::SynthParams sp;
  sp.plan = plan;
  sp.frames = frames;
  sp.points = points;
  sp.point_variation = 0.2;
  sp.motion = 1.0;
  sp.seed = seed;
  return sp;
}

}  // namespace animseg_test
