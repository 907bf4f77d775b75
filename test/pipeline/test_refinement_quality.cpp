// GMM boundary refinement on a generated articulated sequence (issue: the refinement must never
// lower the pooled ARI). Lives with the pipeline tests because it needs the synth module.
#include <gtest/gtest.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/synth/articulated.h>

#include <cstdio>
#include <cstdlib>
#include <map>
#include <memory>
#include <string>

#include "pipeline/sequence_params.h"
#include "segmentation/synthetic_parts.h"

namespace seg = pcl_animseg::segmentation;
namespace synth = pcl_animseg::synth;

// The true labels of a galloping quadruped (parts overlap at the joints, like a real body, so the
// two sides of a hip or shoulder have alike normals). Refining labels that are already right must
// leave them (nearly) right: with normals alone the refinement moved ~1900 points across the
// hips, shoulders and neck and the pooled ARI fell to 0.81; the motion check keeps it at 0.98.
TEST(RefinementQuality, TrueLabelsOfAQuadrupedStayTrue) {
  const synth::SynthParams sp =
      animseg_test::sequenceParams(synth::BodyPlan::Quadruped, 8, 1500, 3);
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

// The default motion segmentation of a generated sequence at its true part count, refined.
struct Refined {
  std::shared_ptr<pcl_animseg::PointCloudSequence> seq;
  std::vector<std::vector<int>> truth;
  seg::SegmentationResult in, out;
  std::vector<seg::PartMotion> motions;  // the refinement's (GMMBoundaryRefinement::getMotions)
  int passes = 0;
  double error_before = 0.0, error_after = 0.0;  // boundary error (synthetic_parts.h)
  double ari_before = 0.0, ari_after = 0.0;      // pooled
};

Refined refineMotionLabels(const synth::SynthParams& sp, const seg::RefinementParams& rp) {
  Refined r;
  const auto frames = synth::generate(sp);
  r.seq = std::make_shared<pcl_animseg::PointCloudSequence>(synth::toSequence(frames));
  for (const auto& f : frames) r.truth.push_back(f.labels);
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(r.seq);
  seg::MeanShiftParams mp;
  mp.target_clusters = synth::partCount(sp.plan);
  ms.setParams(mp);
  ms.segment(r.in);
  seg::GMMBoundaryRefinement refine;
  refine.setInputSequence(r.seq.get());
  refine.setParams(rp);
  refine.refine(r.in, r.out);
  r.passes = refine.getStats().iterations;
  r.motions = refine.getMotions();
  r.error_before = animseg_test::boundaryError(*r.seq, r.truth, toTruthIds(r.in.labels, r.truth));
  r.error_after = animseg_test::boundaryError(*r.seq, r.truth, toTruthIds(r.out.labels, r.truth));
  r.ari_before = pcl_animseg::evaluation::evaluate(r.in.labels, r.truth).pooled_ari;
  r.ari_after = pcl_animseg::evaluation::evaluate(r.out.labels, r.truth).pooled_ari;
  return r;
}

// Where the wrong points near a true boundary lie: a histogram of their distance to the border
// the refinement started from, before and after it.
void printWrongByDistance(const Refined& r) {
  const auto tin = toTruthIds(r.in.labels, r.truth), tout = toTruthIds(r.out.labels, r.truth);
  long hist_in[6] = {0}, hist_out[6] = {0};
  std::map<std::pair<int, int>, long> pair_in, pair_out;  // (true part, given part) -> count
  std::vector<int> idx;
  std::vector<float> d2;
  for (std::size_t t = 0; t < r.seq->size(); ++t) {
    const auto& f = r.seq->frame(t);
    const double s = pcl_animseg::meanSpacing(*f);
    pcl::KdTreeFLANN<pcl::PointNormal> tree, true_border, start_border;
    tree.setInputCloud(f);
    const auto true_points = animseg_test::boundaryPoints(f, tree, r.truth[t], s);
    const auto start_points = animseg_test::boundaryPoints(f, tree, r.in.labels[t], s);
    if (true_points->empty() || start_points->empty()) continue;  // nothing to measure from
    true_border.setInputCloud(true_points);
    start_border.setInputCloud(start_points);
    for (std::size_t j = 0; j < f->size(); ++j) {
      true_border.nearestKSearch((*f)[j], 1, idx, d2);
      if (std::sqrt(d2[0]) > 3 * s) continue;
      start_border.nearestKSearch((*f)[j], 1, idx, d2);
      const double d = std::sqrt(d2[0]) / s;
      const int bin = d < 2 ? 0 : d < 4 ? 1 : d < 6 ? 2 : d < 10 ? 3 : d < 20 ? 4 : 5;
      hist_in[bin] += tin[t][j] != r.truth[t][j];
      hist_out[bin] += tout[t][j] != r.truth[t][j];
      if (tin[t][j] != r.truth[t][j]) ++pair_in[{r.truth[t][j], tin[t][j]}];
      if (tout[t][j] != r.truth[t][j]) ++pair_out[{r.truth[t][j], tout[t][j]}];
    }
  }
  std::printf(
      "  wrong near a true boundary, by distance to the unrefined boundary "
      "(<2 <4 <6 <10 <20 >=20 spacings):\n  before");
  for (long h : hist_in) std::printf(" %ld", h);
  std::printf("\n  after ");
  for (long h : hist_out) std::printf(" %ld", h);
  std::printf("\n  wrong near a true boundary by (true part, given part): before -> after\n");
  std::map<std::pair<int, int>, long> all(pair_in);
  for (const auto& [key, count] : pair_out) all[key] += 0;
  for (const auto& [key, count] : all)
    if (count + pair_out[key] >= 40)
      std::printf("   %2d <- %2d: %5ld -> %5ld\n", key.first, key.second, count, pair_out[key]);
}

}  // namespace

// The motion method's labels of a walking humanoid (3000 points per frame, seed 6), refined with
// the default parameters: the boundary error must not grow and the pooled ARI must not drop.
// With the four passes the refinement used to make, later passes pushed borders on into the
// side they had entered: boundary error 0.115 -> 0.125 and ARI 0.932 -> 0.923; one pass gives
// 0.115 -> 0.107 and 0.932 -> 0.936, and with the fold snap since 0.115 -> 0.057 and
// 0.932 -> 0.973.
TEST(RefinementQuality, HumanoidBordersDoNotDriftAcrossJoints) {
  const Refined r = refineMotionLabels(
      animseg_test::sequenceParams(synth::BodyPlan::Humanoid, 20, 3000, 6), seg::RefinementParams());
  std::printf("boundary error %.4f -> %.4f, pooled ARI %.4f -> %.4f, %d pass(es)\n", r.error_before,
              r.error_after, r.ari_before, r.ari_after, r.passes);
  EXPECT_GT(r.error_before, 0.05);  // there is something to refine
  EXPECT_LE(r.error_after, r.error_before);
  EXPECT_GE(r.ari_after, r.ari_before - 0.001);
}

// The motion method hands its parts' motions on (SegmentationResult::motions): frame 0 is the
// identity, and each part's frame-0 points, carried by its motion, lie on the same part in every
// frame. With RefinementParams::input_motions the refinement takes them instead of fitting its
// own, and still halves the boundary error (0.115 -> 0.060; 0.057 with its own fits).
TEST(RefinementQuality, TheMotionMethodsOwnMotionsServeTheRefinement) {
  seg::RefinementParams rp;
  rp.input_motions = true;
  const Refined r =
      refineMotionLabels(animseg_test::sequenceParams(synth::BodyPlan::Humanoid, 20, 3000, 6), rp);
  const pcl_animseg::PointCloudSequence& seq = *r.seq;
  const seg::SegmentationResult& in = r.in;
  ASSERT_EQ(in.motions.size(), static_cast<std::size_t>(in.num_clusters));
  // Part c's points of frame t.
  auto partPoints = [&](int c, std::size_t t) {
    pcl::PointCloud<pcl::PointXYZ>::Ptr out(new pcl::PointCloud<pcl::PointXYZ>);
    for (std::size_t j = 0; j < seq.frame(t)->size(); ++j)
      if (in.labels[t][j] == c)
        out->push_back(
            pcl::PointXYZ((*seq.frame(t))[j].x, (*seq.frame(t))[j].y, (*seq.frame(t))[j].z));
    return out;
  };
  // Mean distance, in spacings, of each part's frame-0 points carried to frame t from the
  // nearest point of the same part there.
  double worst = 0.0, sum = 0.0;
  int n = 0;
  for (int c = 0; c < in.num_clusters; ++c) {
    ASSERT_EQ(in.motions[c].size(), seq.size());
    EXPECT_TRUE(in.motions[c][0].isApprox(Eigen::Isometry3d::Identity(), 1e-12)) << "part " << c;
    const auto p0 = partPoints(c, 0);
    for (std::size_t t = 1; t < seq.size(); ++t) {
      const auto pt = partPoints(c, t);
      if (p0->size() < 20 || pt->size() < 20) continue;
      pcl::KdTreeFLANN<pcl::PointXYZ> tree;
      tree.setInputCloud(pt);
      std::vector<int> idx;
      std::vector<float> d2;
      double d = 0.0;
      for (const auto& q : *p0) {
        const Eigen::Vector3d y = in.motions[c][t] * q.getVector3fMap().cast<double>();
        tree.nearestKSearch(pcl::PointXYZ(y.x(), y.y(), y.z()), 1, idx, d2);
        d += std::sqrt(d2[0]);
      }
      d /= static_cast<double>(p0->size()) * pcl_animseg::meanSpacing(*seq.frame(t));
      worst = std::max(worst, d), sum += d, ++n;
    }
  }
  ASSERT_GT(n, 0);
  std::printf("parts' frame-0 points carried by their motions: mean %.3f, worst %.3f spacings\n",
              sum / n, worst);
  // Different samplings alone put a point about half a spacing from its frame's nearest point
  // (measured: mean 1.02, worst 1.39 spacings).
  EXPECT_LT(sum / n, 1.5);
  EXPECT_LT(worst, 3.0);

  ASSERT_EQ(r.motions.size(), in.motions.size());
  for (std::size_t c = 0; c < r.motions.size(); ++c)
    for (std::size_t t = 0; t < seq.size(); ++t) {
      EXPECT_EQ(r.motions[c].frames[t].rotation, in.motions[c][t].linear()) << c << " " << t;
      EXPECT_EQ(r.motions[c].frames[t].translation, in.motions[c][t].translation())
          << c << " " << t;
    }
  std::printf("input motions: boundary error %.4f -> %.4f, pooled ARI %.4f -> %.4f\n",
              r.error_before, r.error_after, r.ari_before, r.ari_after);
  EXPECT_LE(r.error_after, 0.7 * r.error_before);
  EXPECT_GE(r.ari_after, r.ari_before - 0.001);
}

// The goal on every body plan (20 frames, 6000 points per frame, seeds 5 and 8): the
// motion method's labels at the true part count, refined with the defaults, have at least 30%
// fewer wrong points within 3 spacings of a true boundary, and a pooled ARI no lower than before.
// Measured: seed 5 65% / 73% / 39% / 46% fewer (quadruped / humanoid / spider / hand), seed 8
// 63% / 60% / 56% / 53%; over seeds 3-10 every run drops by 38% or more. The fold snap does most
// of it (knee caps, knuckles); without it the drops at 8000 points were 14-27% on the quadruped,
// the humanoid and the hand (docs/mean_shift_experiments.md).
TEST(RefinementQuality, BoundaryErrorDropsByAThirdOnEveryPlan) {
  for (const unsigned seed : {5u, 8u}) {
    for (const synth::BodyPlan plan : {synth::BodyPlan::Quadruped, synth::BodyPlan::Humanoid,
                                       synth::BodyPlan::Spider, synth::BodyPlan::Hand}) {
      const Refined r = refineMotionLabels(animseg_test::sequenceParams(plan, 20, 6000, seed),
                                           seg::RefinementParams());
      std::printf("%-10s seed %u: boundary error %.4f -> %.4f (%.0f%% fewer), ",
                  synth::toString(plan).c_str(), seed, r.error_before, r.error_after,
                  100.0 * (1.0 - r.error_after / r.error_before));
      std::printf("pooled ARI %.4f -> %.4f\n", r.ari_before, r.ari_after);
      const std::string what = synth::toString(plan) + " seed " + std::to_string(seed);
      EXPECT_GT(r.error_before, 0.03) << what;  // there is something to refine
      EXPECT_LE(r.error_after, 0.7 * r.error_before) << what;
      EXPECT_GE(r.ari_after, r.ari_before - 0.001) << what;
    }
  }
}

// Measurement (docs/mean_shift_experiments.md): the boundary error (points within 3 spacings of a
// true boundary with a wrong label) and the pooled ARI of the default motion segmentation at the
// true part count, before and after the refinement. PLANS (comma-separated), POINTS, FRAMES, SEED;
// and NARROW, OUTER, TOLERANCE, RATIO, SPATIAL, ITERATIONS, PATCH, PATCH_RADIUS, TRAINING_MIN and
// COMPONENTS, SNAP_*, INPUT_MOTIONS for the refinement's parameters; DIAG=1
// adds where the wrong points lie.
TEST(RefinementQuality, DISABLED_ThroughThePipeline) {
  const char* plans = std::getenv("PLANS");
  const std::string list = plans ? plans : "quadruped,humanoid,spider,hand";
  const char* points = std::getenv("POINTS");
  const char* seed = std::getenv("SEED");
  auto env = [](const char* name, double fallback) {
    const char* v = std::getenv(name);
    return v ? std::atof(v) : fallback;
  };
  seg::RefinementParams rp;
  rp.narrow_band = env("NARROW", rp.narrow_band);
  rp.outer_band = env("OUTER", rp.outer_band);
  rp.motion_tolerance = env("TOLERANCE", rp.motion_tolerance);
  rp.min_log_ratio = env("RATIO", rp.min_log_ratio);
  rp.spatial_weight = env("SPATIAL", rp.spatial_weight);
  rp.max_iterations = static_cast<int>(env("ITERATIONS", rp.max_iterations));
  rp.patch_size = env("PATCH", rp.patch_size);
  rp.patch_radius = env("PATCH_RADIUS", rp.patch_radius);
  rp.training_min_distance = env("TRAINING_MIN", rp.training_min_distance);
  rp.components = static_cast<int>(env("COMPONENTS", rp.components));
  rp.fold_snap_band = env("SNAP_BAND", rp.fold_snap_band);
  rp.fold_snap_penalty = env("SNAP_PENALTY", rp.fold_snap_penalty);
  rp.fold_snap_angle_deg = env("SNAP_ANGLE", rp.fold_snap_angle_deg);
  rp.fold_snap_dead_zone_deg = env("SNAP_DEAD", rp.fold_snap_dead_zone_deg);
  rp.input_motions = env("INPUT_MOTIONS", rp.input_motions ? 1.0 : 0.0) != 0.0;
  std::size_t pos = 0;
  while (pos < list.size()) {
    const std::size_t comma = std::min(list.find(',', pos), list.size());
    const synth::SynthParams sp = animseg_test::sequenceParams(
        synth::bodyPlanFromString(list.substr(pos, comma - pos)),
        static_cast<int>(env("FRAMES", 20)), points ? std::atoi(points) : 2000,
        seed ? static_cast<unsigned>(std::atoi(seed)) : 3u);
    pos = comma + 1;
    const Refined r = refineMotionLabels(sp, rp);
    std::printf("%-10s %d pts: boundary error %.3f -> %.3f (%.0f%% fewer), ARI %.3f -> %.3f\n",
                synth::toString(sp.plan).c_str(), sp.points, r.error_before, r.error_after,
                100.0 * (1.0 - r.error_after / r.error_before), r.ari_before, r.ari_after);
    if (std::getenv("DIAG")) printWrongByDistance(r);
    if (std::getenv("DIAG")) {  // each given part's largest true parts, before the refinement
      std::map<int, std::map<int, long>> overlap;
      for (std::size_t t = 0; t < r.truth.size(); ++t)
        for (std::size_t i = 0; i < r.truth[t].size(); ++i)
          ++overlap[r.in.labels[t][i]][r.truth[t][i]];
      for (const auto& [given, counts] : overlap) {
        std::printf("  given %2d:", given);
        for (const auto& [truth, count] : counts)
          if (count >= 100) std::printf(" %d:%ld", truth, count);
        std::printf("\n");
      }
    }
    std::fflush(stdout);
  }
}
