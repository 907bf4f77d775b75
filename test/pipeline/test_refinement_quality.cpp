// GMM boundary refinement on a generated articulated sequence (issue: the refinement must never
// lower the pooled ARI). Lives with the pipeline tests because it needs the synth module.
#include <gtest/gtest.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl_animseg/synth/articulated.h>

#include "segmentation/synthetic_parts.h"

#include <cstdio>
#include <cstdlib>
#include <map>
#include <memory>
#include <string>

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

namespace {

/** Each predicted part renamed to the true part it overlaps most (pooled over all frames), so
 * that a "wrong label" means a point on the wrong side of a boundary, not another numbering. */
std::vector<std::vector<int>> toTruthIds(const std::vector<std::vector<int>>& labels,
                                         const std::vector<std::vector<int>>& truth) {
  std::map<std::pair<int, int>, long> overlap;
  for (std::size_t t = 0; t < labels.size(); ++t)
    for (std::size_t i = 0; i < labels[t].size(); ++i) ++overlap[{labels[t][i], truth[t][i]}];
  std::map<int, std::pair<long, int>> best;  // predicted -> (count, true part)
  for (const auto& [key, count] : overlap) {
    auto& b = best[key.first];
    if (count > b.first) b = {count, key.second};
  }
  std::vector<std::vector<int>> out(labels);
  for (auto& f : out)
    for (int& l : f) l = best[l].second;
  return out;
}

}  // namespace

// The motion method's labels of a walking humanoid (3000 points per frame, seed 6), refined with
// the default parameters: the boundary error must not grow and the pooled ARI must not drop.
// With the four passes the refinement used to make, later passes pushed borders on into the
// side they had entered: boundary error 0.115 -> 0.125 and ARI 0.932 -> 0.923; one pass gives
// 0.115 -> 0.113 and 0.932 -> 0.932.
TEST(RefinementQuality, HumanoidBordersDoNotDriftAcrossJoints) {
  synth::SynthParams sp;
  sp.plan = synth::BodyPlan::Humanoid;
  sp.frames = 20;
  sp.points = 3000;
  sp.point_variation = 0.2;
  sp.seed = 6;
  const auto frames = synth::generate(sp);
  auto seq = std::make_shared<pcl_animseg::PointCloudSequence>(synth::toSequence(frames));
  std::vector<std::vector<int>> truth;
  for (const auto& f : frames) truth.push_back(f.labels);
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  seg::MeanShiftParams mp;
  mp.target_clusters = synth::partCount(sp.plan);
  ms.setParams(mp);
  seg::SegmentationResult in, out;
  ms.segment(in);
  seg::GMMBoundaryRefinement refine;
  refine.setInputSequence(seq.get());
  refine.refine(in, out);
  const double e0 = animseg_test::boundaryError(*seq, truth, toTruthIds(in.labels, truth));
  const double e1 = animseg_test::boundaryError(*seq, truth, toTruthIds(out.labels, truth));
  const double a0 = pcl_animseg::evaluation::evaluate(in.labels, truth).pooled_ari;
  const double a1 = pcl_animseg::evaluation::evaluate(out.labels, truth).pooled_ari;
  std::printf("boundary error %.4f -> %.4f, pooled ARI %.4f -> %.4f, %d pass(es)\n", e0, e1, a0,
              a1, refine.getStats().iterations);
  EXPECT_GT(e0, 0.05);  // there is something to refine
  EXPECT_LE(e1, e0);
  EXPECT_GE(a1, a0 - 0.001);
}

// Measurement (docs/mean_shift_experiments.md): the boundary error (points within 3 spacings of a
// true boundary with a wrong label) and the pooled ARI of the default motion segmentation at the
// true part count, before and after the refinement. PLANS (comma-separated), POINTS, SEED; and
// NARROW, OUTER, TOLERANCE, RATIO, SPATIAL, ITERATIONS for the refinement's parameters.
TEST(RefinementQuality, DISABLED_ThroughThePipeline) {
  const char* plans = std::getenv("PLANS");
  const std::string list = plans ? plans : "quadruped,humanoid,spider,hand";
  const char* points = std::getenv("POINTS");
  const char* seed = std::getenv("SEED");
  std::size_t pos = 0;
  while (pos < list.size()) {
    const std::size_t comma = std::min(list.find(',', pos), list.size());
    synth::SynthParams sp;
    sp.plan = synth::bodyPlanFromString(list.substr(pos, comma - pos));
    pos = comma + 1;
    sp.frames = 20;
    sp.points = points ? std::atoi(points) : 2000;
    sp.point_variation = 0.2;
    sp.seed = seed ? static_cast<unsigned>(std::atoi(seed)) : 3u;
    const auto frames = synth::generate(sp);
    auto seq = std::make_shared<pcl_animseg::PointCloudSequence>(synth::toSequence(frames));
    std::vector<std::vector<int>> truth;
    for (const auto& f : frames) truth.push_back(f.labels);
    seg::MeanShiftSegmentation ms;
    ms.setInputSequence(seq);
    seg::MeanShiftParams mp;
    mp.target_clusters = synth::partCount(sp.plan);
    ms.setParams(mp);
    seg::SegmentationResult in, out;
    ms.segment(in);
    seg::GMMBoundaryRefinement refine;
    refine.setInputSequence(seq.get());
    seg::RefinementParams rp;
    auto env = [](const char* name, double fallback) {
      const char* v = std::getenv(name);
      return v ? std::atof(v) : fallback;
    };
    rp.narrow_band = env("NARROW", rp.narrow_band);
    rp.outer_band = env("OUTER", rp.outer_band);
    rp.motion_tolerance = env("TOLERANCE", rp.motion_tolerance);
    rp.min_log_ratio = env("RATIO", rp.min_log_ratio);
    rp.spatial_weight = env("SPATIAL", rp.spatial_weight);
    rp.max_iterations = static_cast<int>(env("ITERATIONS", rp.max_iterations));
    refine.setParams(rp);
    refine.refine(in, out);
    const double e0 = animseg_test::boundaryError(*seq, truth, toTruthIds(in.labels, truth));
    const double e1 = animseg_test::boundaryError(*seq, truth, toTruthIds(out.labels, truth));
    std::printf("%-10s %d pts: boundary error %.3f -> %.3f (%.0f%% fewer), ARI %.3f -> %.3f\n",
                synth::toString(sp.plan).c_str(), sp.points, e0, e1, 100.0 * (1.0 - e1 / e0),
                pcl_animseg::evaluation::evaluate(in.labels, truth).pooled_ari,
                pcl_animseg::evaluation::evaluate(out.labels, truth).pooled_ari);
    std::fflush(stdout);
    if (std::getenv("DIAG")) {
      const auto tin = toTruthIds(in.labels, truth), tout = toTruthIds(out.labels, truth);
      long hist_in[6] = {0}, hist_out[6] = {0};
      for (std::size_t t = 0; t < seq->size(); ++t) {
        const auto& f = seq->frame(t);
        const double s = pcl_animseg::meanSpacing(*f);
        pcl::KdTreeFLANN<pcl::PointNormal> tree;
        tree.setInputCloud(f);
        std::vector<int> idx;
        std::vector<float> d2;
        auto boundaryOf = [&](const std::vector<int>& lab) {
          pcl::PointCloud<pcl::PointNormal>::Ptr b(new pcl::PointCloud<pcl::PointNormal>);
          for (std::size_t j = 0; j < f->size(); ++j) {
            tree.nearestKSearch((*f)[j], 8, idx, d2);
            for (std::size_t k = 1; k < idx.size(); ++k)
              if (lab[idx[k]] != lab[j] && d2[k] < 9 * s * s) { b->push_back((*f)[j]); break; }
          }
          return b;
        };
        auto tb = boundaryOf(truth[t]);
        auto pb = boundaryOf(in.labels[t]);
        pcl::KdTreeFLANN<pcl::PointNormal> ttree, ptree;
        ttree.setInputCloud(tb);
        ptree.setInputCloud(pb);
        for (std::size_t j = 0; j < f->size(); ++j) {
          ttree.nearestKSearch((*f)[j], 1, idx, d2);
          if (std::sqrt(d2[0]) > 3 * s) continue;
          ptree.nearestKSearch((*f)[j], 1, idx, d2);
          const double d = std::sqrt(d2[0]) / s;
          const int bin = d < 2 ? 0 : d < 4 ? 1 : d < 6 ? 2 : d < 10 ? 3 : d < 20 ? 4 : 5;
          if (tin[t][j] != truth[t][j]) ++hist_in[bin];
          if (tout[t][j] != truth[t][j]) ++hist_out[bin];
        }
      }
      std::printf("  wrong near a true boundary, by distance to the unrefined boundary "
                  "(<2 <4 <6 <10 <20 >=20 spacings):\n  before");
      for (long h : hist_in) std::printf(" %ld", h);
      std::printf("\n  after ");
      for (long h : hist_out) std::printf(" %ld", h);
      std::printf("\n");
    }
  }
}
