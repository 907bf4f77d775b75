// GMM boundary refinement on a generated articulated sequence (issue: the refinement must never
// lower the pooled ARI). Lives with the pipeline tests because it needs the synth module.
#include <gtest/gtest.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/synth/articulated.h>

#include <cstdio>

namespace seg = pcl_animseg::segmentation;
namespace synth = pcl_animseg::synth;


// The true labels of a galloping quadruped (parts overlap at the joints, like a real body, so the
// two sides of a hip or shoulder have alike normals). Refining labels that are already right must
// leave them (nearly) right: with normals alone the refinement moved ~1900 points across the
// hips, shoulders and neck and the pooled ARI fell to 0.81; the motion check keeps it at 0.98.
TEST(RefinementQuality, TrueLabelsOfAQuadrupedStayTrue) {
  synth::SynthParams sp;
  sp.plan = synth::BodyPlan::Quadruped;
  sp.frames = 8;
  sp.points = 1500;
  sp.point_variation = 0.2;
  sp.motion = 1.0;
  sp.seed = 3;
  const auto frames = synth::generate(sp);
  const pcl_animseg::PointCloudSequence seq = synth::toSequence(frames);
  seg::SegmentationResult in, out;
  for (const auto& f : frames) in.labels.push_back(f.labels);
  in.num_clusters = synth::partCount(sp.plan);
  seg::GMMBoundaryRefinement refine;
  refine.setInputSequence(&seq);
  refine.refine(in, out);
  std::size_t changed = 0;
  for (std::size_t c : refine.getStats().changed) changed += c;
  const double ari = pcl_animseg::evaluation::evaluate(out.labels, in.labels).pooled_ari;
  std::printf("pooled ARI after refining the truth %.4f, %zu points relabelled\n", ari, changed);
  EXPECT_GE(ari, 0.95);
  EXPECT_EQ(out.num_clusters, in.num_clusters);
}
