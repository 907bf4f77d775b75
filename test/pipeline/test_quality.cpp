// Quality of the default (motion) decomposition on generated articulated sequences: no
// correspondences, >= 10 parts, large joint motion, +-20% point-count variation. Lives with the
// pipeline tests because it needs the synth and evaluation modules.
#include <gtest/gtest.h>
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/io/normals.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/synth/articulated.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <map>
#include <string>
#include <utility>

#include "pipeline/sequence_params.h"
#include "temp_dir.h"

namespace seg = pcl_animseg::segmentation;
namespace synth = pcl_animseg::synth;
namespace ev = pcl_animseg::evaluation;
using animseg_test::sequenceParams;

namespace {

struct RunResult {
  double ari = 0.0;
  double frame_ari = 0.0;
  int clusters = 0;
  double seconds = 0.0;
  seg::SegmentationResult result;
};

std::vector<std::vector<int>> truthOf(const std::vector<synth::SynthFrame>& frames) {
  std::vector<std::vector<int>> truth;
  for (const auto& f : frames) truth.push_back(f.labels);
  return truth;
}

RunResult runOn(const std::vector<synth::SynthFrame>& frames, const seg::MeanShiftParams& params) {
  auto seq = std::make_shared<pcl_animseg::PointCloudSequence>(synth::toSequence(frames));
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  ms.setParams(params);
  RunResult r;
  const auto t0 = std::chrono::steady_clock::now();
  ms.segment(r.result);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const auto rep = ev::evaluate(r.result.labels, truthOf(frames));
  r.ari = rep.pooled_ari;
  r.frame_ari = rep.mean_frame_ari;
  r.clusters = r.result.num_clusters;
  return r;
}

/** The default stage on `frames` of `plan`, asked for the true part count. */
RunResult atTruePartCount(synth::BodyPlan plan, const std::vector<synth::SynthFrame>& frames) {
  seg::MeanShiftParams p;
  p.target_clusters = synth::partCount(plan);
  return runOn(frames, p);
}

// Points of the smallest part over all frames; `total` gets every labelled point.
long smallestPart(const RunResult& r, long& total) {
  std::vector<long> size(static_cast<std::size_t>(std::max(r.clusters, 0)), 0);
  total = 0;
  for (const auto& labels : r.result.labels)
    for (int l : labels)
      if (l >= 0 && l < r.clusters) ++size[l], ++total;
  return size.empty() ? 0 : *std::min_element(size.begin(), size.end());
}

int envInt(const char* name, int fallback) {
  const char* v = std::getenv(name);
  return v ? std::atoi(v) : fallback;
}

double envDouble(const char* name, double fallback) {
  const char* v = std::getenv(name);
  return v ? std::atof(v) : fallback;
}

/** The body plan and sequence of the diagnostics below: PLANS (one plan name), FRAMES, POINTS and
 * SEED from the environment. */
synth::BodyPlan diagnosticPlan() {
  const char* plan_name = std::getenv("PLANS");
  return synth::bodyPlanFromString(plan_name ? plan_name : "quadruped");
}

std::vector<synth::SynthFrame> diagnosticFrames(synth::BodyPlan plan) {
  return synth::generate(
      sequenceParams(plan, envInt("FRAMES", 20), envInt("POINTS", 1500), envInt("SEED", 3)));
}

/** True part of the point of `frame` nearest to `p` (brute force: a few hundred samples). */
int trueLabelAt(const synth::SynthFrame& frame, const Eigen::Vector3d& p) {
  const auto& c = *frame.cloud;
  double best = 1e300;
  int lab = -1;
  for (std::size_t j = 0; j < c.size(); ++j) {
    const double d = (Eigen::Vector3d(c[j].x, c[j].y, c[j].z) - p).squaredNorm();
    if (d < best) best = d, lab = frame.labels[j];
  }
  return lab;
}

/** The most common label of the true part `name` over all frames of `r`, and the share of the
 * part's points that carry it. */
std::pair<int, double> topLabel(synth::BodyPlan plan, const std::vector<synth::SynthFrame>& frames,
                                const RunResult& r, const std::string& name) {
  const std::vector<std::string> names = synth::partNames(plan);
  const int part = static_cast<int>(std::find(names.begin(), names.end(), name) - names.begin());
  std::map<int, long> count;
  long total = 0;
  for (std::size_t t = 0; t < frames.size(); ++t)
    for (std::size_t i = 0; i < frames[t].labels.size(); ++i)
      if (frames[t].labels[i] == part) ++count[r.result.labels[t][i]], ++total;
  std::pair<long, int> best{0, -1};
  for (const auto& [label, n] : count) best = std::max(best, std::make_pair(n, label));
  return {best.second, static_cast<double>(best.first) / static_cast<double>(std::max(1L, total))};
}

}  // namespace

// The quality goal (>= 10 parts, >= 20 frames, large motion, +-20% point counts, no
// correspondences) at the hierarchy level with the true part count. The pooled ARI reached is
// below the 0.90 goal at 2000 points per frame for the quadruped (measured: quadruped 0.888,
// spider 0.921; 0.857 and 0.918 on 2026-11-24, the same with and without the sliver rule; with
// --joint-weight 0.2 the quadruped gives 0.808, so the default stays 0.1; before the graph-cut
// borders 0.84 and 0.84, and the spider had 0.69 while the
// generator let its legs pass through each other); the bounds are the measured numbers minus a
// margin, so that a regression shows (see docs/mean_shift_experiments.md). A lower leg has ~1.5%
// of the points: with fewer than ~2000 points per frame it is too small for its own tracked
// neighbourhoods. The graph-cut borders must beat per-point borders (border_smoothness 0, 0.838
// on the quadruped) by a clear margin.
TEST(MotionQuality, QuadrupedAndSpiderAtTruePartCount) {
  const struct {
    synth::BodyPlan plan;
    double bound;
  } cases[] = {{synth::BodyPlan::Quadruped, 0.85}, {synth::BodyPlan::Spider, 0.87}};
  for (const auto& c : cases) {
    const auto frames = synth::generate(sequenceParams(c.plan, 20, 2000, 3));
    seg::MeanShiftParams p;
    p.target_clusters = synth::partCount(c.plan);
    const RunResult r = runOn(frames, p);
    std::printf("%s: pooled ARI %.3f, %d parts (truth %d), %.1f s\n",
                synth::toString(c.plan).c_str(), r.ari, r.clusters, synth::partCount(c.plan),
                r.seconds);
    EXPECT_GE(r.ari, c.bound) << synth::toString(c.plan);
    EXPECT_LE(r.clusters, synth::partCount(c.plan));
    // Parts that lose every point to their neighbours vanish, so fewer than asked is possible.
    EXPECT_GE(r.clusters, synth::partCount(c.plan) / 2);
    // Every point of every frame is labelled, and a label means one part throughout.
    ASSERT_EQ(r.result.labels.size(), frames.size());
    for (std::size_t t = 0; t < frames.size(); ++t) {
      ASSERT_EQ(r.result.labels[t].size(), frames[t].labels.size());
      for (int l : r.result.labels[t]) {
        EXPECT_GE(l, 0);
        EXPECT_LT(l, r.clusters);
      }
    }
    // The hierarchy continues down to one part per connected piece.
    EXPECT_FALSE(r.result.merges.empty());
    if (c.plan == synth::BodyPlan::Quadruped) {
      p.border_smoothness = 0.0;
      const RunResult per_point = runOn(frames, p);
      std::printf("quadruped, per-point borders: pooled ARI %.3f\n", per_point.ari);
      EXPECT_GE(r.ari, per_point.ari + 0.025);
    }
  }
}

// The humanoid's pelvis turns little under its torso (8-14 degrees), less than the residual
// noise of a small leg piece, so by motion alone pelvis, torso and head merged first. They meet at
// sharp creases, which make such a merge cost at least `crease_cost`. On this sequence the pooled
// ARI went from 0.562 (crease_cost = 0) to 0.830, and to 0.874 with the graph-cut borders; at 4000
// points per frame, seeds 3-8 gain 0.14 to 0.17 each from the crease rule.
TEST(MotionQuality, HumanoidTrunkPartsStaySeparate) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 20, 2000, 6));
  seg::MeanShiftParams p;
  p.target_clusters = synth::partCount(plan);
  const RunResult r = runOn(frames, p);
  std::printf("humanoid: pooled ARI %.3f, %d parts\n", r.ari, r.clusters);
  EXPECT_GE(r.ari, 0.82);
  const auto names = synth::partNames(plan);
  auto majority = [&](const std::string& part) {
    const int id = static_cast<int>(std::find(names.begin(), names.end(), part) - names.begin());
    std::vector<long> count(r.clusters, 0);
    for (std::size_t t = 0; t < frames.size(); ++t)
      for (std::size_t i = 0; i < frames[t].labels.size(); ++i)
        if (frames[t].labels[i] == id && r.result.labels[t][i] >= 0) ++count[r.result.labels[t][i]];
    return static_cast<int>(std::max_element(count.begin(), count.end()) - count.begin());
  };
  const int pelvis = majority("pelvis"), torso = majority("torso"), head = majority("head");
  EXPECT_NE(pelvis, torso);
  EXPECT_NE(torso, head);
  EXPECT_NE(pelvis, head);
}

// The crease rule must not split what moves rigidly: a body whose joints do not move (motion 0)
// is one part, creases or not (the humanoid gave 2 parts when every crease pair cost at least
// crease_cost, whatever its motion).
TEST(MotionQuality, RigidBodyWithCreasesIsOnePart) {
  for (auto plan : {synth::BodyPlan::Humanoid, synth::BodyPlan::Quadruped}) {
    auto sp = sequenceParams(plan, 10, 2000, 3);
    sp.motion = 0.0;
    const RunResult r = runOn(synth::generate(sp), seg::MeanShiftParams());
    EXPECT_EQ(r.clusters, 1) << synth::toString(plan);
  }
}

// The shipped demo sequence (12 frames of ~1500 points) once left a part of one point per frame
// (an isolated point whose group had moved away around it): every part must be a real one.
TEST(MotionQuality, NoRemnantPartsOnTheShippedQuadruped) {
  auto seq = std::make_shared<pcl_animseg::PointCloudSequence>(pcl_animseg::io::loadSequence(
      std::string(PCL_ANIMSEG_SOURCE_DIR) + "/datasets/quadruped_points"));
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  seg::MeanShiftParams p;
  ms.setParams(p);
  seg::SegmentationResult r;
  ms.segment(r);
  std::vector<std::size_t> count(r.num_clusters, 0);
  for (const auto& f : r.labels)
    for (int l : f)
      if (l >= 0) ++count[l];
  ASSERT_GE(r.num_clusters, 6);
  for (int c = 0; c < r.num_clusters; ++c)
    EXPECT_GE(count[c], seq->size() * 5) << "part " << c << " has " << count[c] << " points";
}

namespace {
/** The motion method's labels, part count and merges, run on `threads` OpenMP threads (0: as
 * set). */
struct TrackingRun {
  std::vector<int> labels;
  int parts = 0;
  std::vector<seg::ClusterMerge> merges;
};
TrackingRun runTracking(const pcl_animseg::PointCloudSequence& seq, int threads = 0,
                        const seg::MotionTrackingParams& params = seg::MotionTrackingParams()) {
  const int before = omp_get_max_threads();
  if (threads > 0) omp_set_num_threads(threads);
  TrackingRun r;
  seg::segmentByTracking(seq, params, r.labels, r.parts, r.merges);
  omp_set_num_threads(before);
  return r;
}
void expectSameRun(const TrackingRun& x, const TrackingRun& y) {
  EXPECT_EQ(x.labels, y.labels);
  EXPECT_EQ(x.parts, y.parts);
  EXPECT_EQ(x.merges, y.merges);
}
}  // namespace

TEST(MotionQuality, SameSeedSameLabels) {
  const auto frames = synth::generate(sequenceParams(synth::BodyPlan::Snake, 6, 500, 5));
  const auto seq = synth::toSequence(frames);
  expectSameRun(runTracking(seq), runTracking(seq));
}

// The merges, the tracking's whole-body ICPs and the part motions split their work over frames
// and (part, start) pairs, each result written to its own slot and reduced in a fixed order; a
// merged part's motion is fitted in every frame at once and then checked against the chain of
// frames (fitPart): the labels, merges and costs must not depend on how many threads ran them.
// The reference frame first (the default: one chain of frames) and in the middle (two chains);
// and a sequence long enough to be tracked through key frames (chainFrames).
TEST(MotionQuality, SameLabelsOnAnyThreadCount) {
  const auto frames = synth::generate(sequenceParams(synth::BodyPlan::Humanoid, 8, 1500, 4));
  const auto seq = synth::toSequence(frames);
  for (int reference : {-1, 4}) {
    seg::MotionTrackingParams mp;
    mp.reference_frame = reference;
    const TrackingRun one = runTracking(seq, 1, mp);
    EXPECT_GT(one.parts, 5) << "reference " << reference;  // a humanoid: the merges ran
    expectSameRun(one, runTracking(seq, 5, mp));
  }
  const auto long_seq =
      synth::toSequence(synth::generate(sequenceParams(synth::BodyPlan::Humanoid, 110, 400, 4)));
  const TrackingRun one = runTracking(long_seq, 1);
  EXPECT_GT(one.parts, 5) << "110 frames";
  expectSameRun(one, runTracking(long_seq, 5));
}

// The whole body's ICP of the tracking searches in parallel when its source (the samples) has 256
// points or more, from both of a frame's starts at once: every pose must be the one-thread run's
// bits (the runs above have fewer samples).
TEST(MotionQuality, TrackedPosesTheSameOnAnyThreadCount) {
  const auto seq =
      synth::toSequence(synth::generate(sequenceParams(synth::BodyPlan::Humanoid, 6, 2400, 4)));
  auto track = [&](int threads) {
    const int before = omp_get_max_threads();
    omp_set_num_threads(threads);
    seg::SampleTracks tr = seg::trackSamples(seq, seg::MotionTrackingParams());
    omp_set_num_threads(before);
    return tr;
  };
  const seg::SampleTracks one = track(1), four = track(4);
  ASSERT_GE(one.sample_points.size(), 256u);
  ASSERT_EQ(one.poses.size(), four.poses.size());
  int differ = 0;
  for (std::size_t t = 0; t < one.poses.size(); ++t)
    for (std::size_t s = 0; s < one.poses[t].size(); ++s)
      differ += one.poses[t][s].matrix() != four.poses[t][s].matrix();
  EXPECT_EQ(differ, 0);
  EXPECT_EQ(one.residual, four.residual);
}

// Normals estimated from plain points have a guessed orientation: a limb, or a whole frame, may
// come out turned inwards. When the sequence says its normals were estimated, the motion method
// compares the normals of two frames by |n . n'|, so turning every normal of two frames inwards
// must leave labels, part count and merges the same bits (frames 2 and 5: the reference frame's
// signs do matter, to its concave bands). With the normals taken as read from the input
// (oriented), the same flips cost the parts of those frames.
TEST(MotionQuality, GuessedNormalOrientationDoesNotMatter) {
  const auto frames = synth::generate(sequenceParams(synth::BodyPlan::Humanoid, 8, 1500, 4));
  const auto base = synth::toSequence(frames);
  auto copy = [&](bool flip, bool estimated) {
    pcl_animseg::PointCloudSequence out;
    for (std::size_t t = 0; t < base.size(); ++t) {
      pcl_animseg::PointCloudSequence::Cloud::Ptr c(
          new pcl_animseg::PointCloudSequence::Cloud(*base.frame(t)));
      if (flip && (t == 2 || t == 5))
        for (auto& p : *c) p.getNormalVector3fMap() = -p.getNormalVector3fMap();
      out.addFrame(c, base.name(t));
      if (estimated) out.setEstimatedNormals(t, c->size());
    }
    return out;
  };
  std::vector<int> truth;
  for (const auto& f : frames) truth.insert(truth.end(), f.labels.begin(), f.labels.end());
  const auto marked = copy(false, true);
  EXPECT_FALSE(marked.normalsOriented());
  EXPECT_TRUE(base.normalsOriented());
  // A few estimated normals (a mesh's vertices in no face) take their signs from the known ones.
  auto partly = copy(false, false);
  partly.setEstimatedNormals(3, 5);
  EXPECT_TRUE(partly.normalsOriented());
  const TrackingRun straight = runTracking(marked);
  const TrackingRun turned = runTracking(copy(true, true));
  expectSameRun(straight, turned);
  const TrackingRun oriented = runTracking(copy(true, false));
  const double ari = pcl_animseg::evaluation::adjustedRandIndex(straight.labels, truth);
  const double ari_oriented = pcl_animseg::evaluation::adjustedRandIndex(oriented.labels, truth);
  std::printf("pooled ARI %.4f; with two frames turned inwards and taken as oriented %.4f\n", ari,
              ari_oriented);
  EXPECT_GT(ari, 0.65);  // measured 0.716 (8 frames of 1500 points, parts by the threshold)
  EXPECT_LT(ari_oriented, ari - 0.2);  // measured 0.126
}

namespace {
/** The frames written as xyz files (positions only) and loaded back, so that the loader
 * estimates the normals; `truth` gets the true labels of all frames in order. */
pcl_animseg::PointCloudSequence loadAsPlainClouds(const std::vector<synth::SynthFrame>& frames,
                                                  std::vector<int>& truth) {
  animseg_test::TempDir dir;
  truth.clear();
  for (std::size_t t = 0; t < frames.size(); ++t) {
    std::ofstream out(dir / ("f" + std::to_string(100 + t) + ".xyz"));
    out.precision(9);
    for (const auto& p : *frames[t].cloud) out << p.x << " " << p.y << " " << p.z << "\n";
    truth.insert(truth.end(), frames[t].labels.begin(), frames[t].labels.end());
  }
  return pcl_animseg::io::loadSequence(dir.str());
}
}  // namespace

// A plain point cloud sequence (xyz files, no normals): the loader estimates the normals and
// marks them, and the motion method at the true part count must still find the parts. Before
// this stop a hand came out as one part this way (normals turned inwards on thin fingers).
TEST(MotionQuality, PlainPointCloudsWithoutNormals) {
  for (const auto plan : {synth::BodyPlan::Quadruped, synth::BodyPlan::Hand}) {
    const auto frames = synth::generate(sequenceParams(plan, 10, 2500, 8));
    std::vector<int> truth;
    const auto seq = loadAsPlainClouds(frames, truth);
    ASSERT_EQ(seq.size(), frames.size());
    EXPECT_FALSE(seq.normalsOriented());
    EXPECT_EQ(seq.estimatedNormals(0), seq.frame(0)->size());
    seg::MotionTrackingParams mp;
    mp.target_clusters = synth::partCount(plan);
    const TrackingRun r = runTracking(seq, 0, mp);
    const double ari = pcl_animseg::evaluation::adjustedRandIndex(r.labels, truth);
    std::printf("%s, normals estimated: %d parts, pooled ARI %.4f\n", synth::toString(plan).c_str(),
                r.parts, ari);
    EXPECT_GE(ari, 0.8) << synth::toString(plan);
  }
}

// A plain humanoid (positions only): its torso and pelvis barely move against each other, and
// with the files' normals the sharp crease between them keeps them apart. Estimated normals blur
// that crease; the concave band around the waist (MotionTrackingParams::concave_crease_depth)
// takes its place. Measured (20 frames of about 4000 points, seed 7): pooled ARI of the motion
// method 0.670 without the band and 0.846 with it (`animseg --parts 15`: 0.704 and 0.881).
TEST(MotionQuality, PlainHumanoidKeepsTorsoAndPelvisApart) {
  const auto frames = synth::generate(sequenceParams(synth::BodyPlan::Humanoid, 20, 4000, 7));
  std::vector<int> truth;
  const auto seq = loadAsPlainClouds(frames, truth);
  ASSERT_FALSE(seq.normalsOriented());
  double ari[2];
  for (int with = 0; with < 2; ++with) {
    seg::MotionTrackingParams mp;
    mp.target_clusters = synth::partCount(synth::BodyPlan::Humanoid);
    if (!with) mp.concave_crease_depth = 0.0;
    const TrackingRun r = runTracking(seq, 0, mp);
    ari[with] = pcl_animseg::evaluation::adjustedRandIndex(r.labels, truth);
    std::printf("plain humanoid, concave band %s: %d parts, pooled ARI %.4f\n", with ? "on" : "off",
                r.parts, ari[with]);
  }
  EXPECT_GE(ari[1], 0.8);
  EXPECT_GE(ari[1], ari[0] + 0.1);
}

// Normals estimated from the points alone (a plain point cloud) must point outwards everywhere,
// also where a limb lies against the body: there a point's nearest neighbours include the other
// sheet, a spanning tree orients the whole arm from one such edge, and the arm came out inside
// out. Humanoid, 20 frames of about 4000 points, seed 7: before the subtree repair
// (io::orientNormals) four frames had their right arm flipped (8-11% of the points, 2.4% in all);
// now at most 0.6% of a frame and 0.3% in all (the rest: single points at creases).
TEST(Normals, PlainHumanoidNormalsPointOutwards) {
  const auto frames = synth::generate(sequenceParams(synth::BodyPlan::Humanoid, 20, 4000, 7));
  std::size_t flipped = 0, total = 0;
  double worst = 0.0;
  for (const auto& f : frames) {
    pcl_animseg::PointCloudSequence::Cloud c;
    for (const auto& p : *f.cloud) {
      pcl::PointNormal q;
      q.getVector3fMap() = p.getVector3fMap();
      c.push_back(q);
    }
    pcl_animseg::io::estimateNormals(c, 16, {});
    std::size_t here = 0;
    for (std::size_t i = 0; i < c.size(); ++i)
      here += c[i].getNormalVector3fMap().dot((*f.cloud)[i].getNormalVector3fMap()) < 0.0f;
    worst = std::max(worst, static_cast<double>(here) / static_cast<double>(c.size()));
    flipped += here;
    total += c.size();
  }
  const double all = static_cast<double>(flipped) / static_cast<double>(total);
  std::printf("flipped normals: %.4f of all points, worst frame %.4f\n", all, worst);
  EXPECT_LE(worst, 0.02);
  EXPECT_LE(all, 0.006);
}

TEST(MotionQuality, RejectsBadParameters) {
  const auto frames = synth::generate(sequenceParams(synth::BodyPlan::Snake, 3, 200, 5));
  const auto seq = synth::toSequence(frames);
  seg::MotionTrackingParams mp;
  mp.reference_frame = 7;
  EXPECT_THROW(seg::trackSamples(seq, mp), pcl_animseg::Error);
  mp.reference_frame = -1;
  mp.neighbourhood = 2;
  EXPECT_THROW(seg::trackSamples(seq, mp), pcl_animseg::Error);
  mp.neighbourhood = 60;
  for (double w : {-0.1, std::numeric_limits<double>::quiet_NaN()}) {
    mp.joint_weight = w;
    EXPECT_THROW(seg::trackSamples(seq, mp), pcl_animseg::Error);
  }
  mp.joint_weight = 0.1;
  for (double f : {-0.1, 1.0, std::numeric_limits<double>::quiet_NaN()}) {
    mp.sliver_fraction = f;
    EXPECT_THROW(seg::trackSamples(seq, mp), pcl_animseg::Error);
  }
}

// Measurement harness for docs/mean_shift_experiments.md (PLANS, FRAMES, POINTS, SEED, METHOD,
// THRESHOLD, SAMPLES from the environment).
TEST(MotionQuality, DISABLED_Table) {
  const char* plans = std::getenv("PLANS");
  std::string list = plans ? plans : "quadruped,humanoid,spider,hand";
  const int frames_n = envInt("FRAMES", 20);
  const int points = envInt("POINTS", 1500);
  const unsigned seed = static_cast<unsigned>(envInt("SEED", 3));
  const char* method = std::getenv("METHOD");
  std::size_t pos = 0;
  while (pos < list.size()) {
    const std::size_t comma = std::min(list.find(',', pos), list.size());
    const auto plan = synth::bodyPlanFromString(list.substr(pos, comma - pos));
    pos = comma + 1;
    const auto frames = synth::generate(sequenceParams(plan, frames_n, points, seed));
    seg::MeanShiftParams p;
    if (method) p.method = seg::meanShiftMethodFromString(method);
    p.patches = envInt("SAMPLES", 0);
    p.motion_threshold = envDouble("THRESHOLD", p.motion_threshold);
    p.target_clusters = synth::partCount(plan);
    const RunResult at_truth = runOn(frames, p);
    p.target_clusters = 0;
    const RunResult own = runOn(frames, p);
    std::printf(
        "%-10s T=%d parts %2d | at truth: ARI %.3f (frame %.3f, %d clusters, %.1f s) | "
        "threshold: ARI %.3f (%d clusters, %.1f s)\n",
        synth::toString(plan).c_str(), frames_n, synth::partCount(plan), at_truth.ari,
        at_truth.frame_ari, at_truth.clusters, at_truth.seconds, own.ari, own.clusters,
        own.seconds);
    std::printf("  merges after threshold:");
    for (std::size_t i = 0; i < std::min<std::size_t>(8, own.result.merges.size()); ++i)
      std::printf(" %.2f", own.result.merges[i].cost);
    std::printf("\n");
    std::fflush(stdout);
  }
}

// A walking humanoid's legs swap places relative to the body every half stride. Tracked samples
// must stay on their own leg: a start from the whole body's pose had put 28 of the right shin's
// samples on the left shin at frame 11 of this sequence (80.5% of all samples on their part in the
// worst frame, up to 58 samples on the other leg; measured now: 91%, at most 6 on the other leg,
// where the legs pass close).
TEST(MotionQuality, WalkingLegsKeepTheirSamples) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 20, 4000, 12));
  const auto seq = synth::toSequence(frames);
  const seg::SampleTracks tr = seg::trackSamples(seq, seg::MotionTrackingParams());
  const std::vector<std::string> names = synth::partNames(plan);
  auto isLeg = [&](int part, const char* side) {
    return part >= 0 && names[part].rfind(std::string("leg_") + side, 0) == 0;
  };
  const int S = static_cast<int>(tr.sample_points.size());
  ASSERT_GT(S, 100);
  const int ref = tr.reference_frame;
  double worst = 1.0;
  int most_swapped = 0;
  for (std::size_t t = 0; t < frames.size(); ++t) {
    int on = 0, swapped = 0;
    for (int s = 0; s < S; ++s) {
      const int truth = frames[ref].labels[tr.sample_points[s]];
      const int lab = trueLabelAt(frames[t], tr.positions[t].col(s));
      on += lab == truth;
      swapped += (isLeg(truth, "r") && isLeg(lab, "l")) || (isLeg(truth, "l") && isLeg(lab, "r"));
    }
    worst = std::min(worst, static_cast<double>(on) / S);
    most_swapped = std::max(most_swapped, swapped);
  }
  std::printf(
      "humanoid seed 12: worst frame %.3f of samples on their part, at most %d on the "
      "other leg\n",
      worst, most_swapped);
  EXPECT_GE(worst, 0.88);
  EXPECT_LE(most_swapped, 10);
}

// A piece of the over-segmentation that straddles a joint has a compromise motion of its own, so
// merging it with either side costs as much as merging two true parts. On this quadruped the
// last merges down to the true part count took the neck apart and cut a lower leg in two while
// such pieces survived. A piece may now dissolve into the parts it touches (each point to the
// part whose motion fits it) when their motions explain it nearly as well as its own. Measured
// with dissolving off (dissolve_ratio 0): pooled ARI 0.860, neck 0.69 and right hind lower leg
// 0.48 in one part; on: 0.952, 0.77 and 0.90.
TEST(MotionQuality, PiecesAcrossAJointDissolve) {
  const auto plan = synth::BodyPlan::Quadruped;
  const auto frames = synth::generate(sequenceParams(plan, 20, 4000, 7));
  const RunResult r = atTruePartCount(plan, frames);
  const double neck = topLabel(plan, frames, r, "neck").second;
  const double leg = topLabel(plan, frames, r, "leg_br_lower").second;
  std::printf("quadruped seed 7: pooled ARI %.3f, neck %.2f and leg_br_lower %.2f in one part\n",
              r.ari, neck, leg);
  // Measured 0.952, 0.77 and 0.90 before slivers stopped counting as parts, 0.948, 0.77 and
  // 0.81 since (15% of the lower leg goes to the next part in the graph cut).
  EXPECT_GE(r.ari, 0.93);
  EXPECT_GE(neck, 0.74);
  EXPECT_GE(leg, 0.78);
}

// The hand's fingers lie side by side, a fifth of a spacing apart, and all look alike. Tracked as
// parts each on its own, the middle finger's motions jumped onto the thumb in frames 12-18 of
// this sequence (its proximal phalanx's joint with the palm opened by 38 spacings), and its
// points took the labels of the index, ring and thumb there: pooled ARI 0.897 (the stage with
// refinement; frame 12 alone 0.845). Part motions now pay for a joint that opens beyond 4
// spacings from the solved neighbour's motion: 0.944 (frame 12 0.956). The stage alone (below,
// without signatures or refinement): 0.876 -> 0.918, worst frame 0.811 -> 0.905.
TEST(MotionQuality, FingersDoNotJumpOntoTheNextFinger) {
  const auto plan = synth::BodyPlan::Hand;
  const auto frames = synth::generate(sequenceParams(plan, 20, 4000, 12));
  seg::MeanShiftParams p;
  p.target_clusters = synth::partCount(plan);
  const RunResult on = runOn(frames, p);
  p.joint_weight = 0.0;
  const RunResult off = runOn(frames, p);
  // The worst frame's ARI: a part that jumps shows in the frames where it jumped.
  auto worstFrame = [&](const RunResult& r) {
    double worst = 1.0;
    for (std::size_t t = 0; t < frames.size(); ++t)
      worst = std::min(worst, ev::adjustedRandIndex(r.result.labels[t], frames[t].labels));
    return worst;
  };
  const double won = worstFrame(on), woff = worstFrame(off);
  std::printf("hand seed 12: pooled ARI %.3f (joint term off: %.3f), worst frame %.3f (%.3f)\n",
              on.ari, off.ari, won, woff);
  EXPECT_GE(on.ari, 0.90);
  EXPECT_GE(on.ari, off.ari + 0.025);
  EXPECT_GE(won, 0.88);
  EXPECT_GE(won, woff + 0.05);
}

// A pelvis turns little under its torso: on this sequence merging the two cost 1.18 spacings,
// below half the merge threshold (2.5), so the crease rule, which then started at half of it,
// did not apply; the pelvis merged into the torso, a remnant of it stayed a part, and the pooled
// ARI at the true part count was 0.780 (the stage alone; 0.774 through the pipeline). The rule
// now starts at 0.4 of the threshold: 0.936 (0.929).
TEST(MotionQuality, PelvisStaysOffTheTorso) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 20, 4000, 9));
  const RunResult r = atTruePartCount(plan, frames);
  const auto pelvis = topLabel(plan, frames, r, "pelvis");
  const auto torso = topLabel(plan, frames, r, "torso");
  std::printf("humanoid seed 9: pooled ARI %.3f, pelvis %.2f in label %d, torso %.2f in %d\n",
              r.ari, pelvis.second, pelvis.first, torso.second, torso.first);
  EXPECT_NE(pelvis.first, torso.first);
  EXPECT_GE(pelvis.second, 0.9);
  EXPECT_GE(r.ari, 0.90);
}

// A humanoid's pelvis, torso and head meet at sharp creases, where the surface graph has no
// edge, so the part motions had no joint between those groups of parts to hold them. On this
// sequence frame 10 fell to ARI 0.73 (frame 11 0.86; pooled 0.906 for the stage alone, 0.908
// through the pipeline). Contacts across a crease between parts that the surface graph leaves
// apart now count as joints: pooled 0.932 (pipeline 0.934), worst frame 0.91.
TEST(MotionQuality, JointsAcrossCreasesHoldTheTrunk) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 20, 8000, 3));
  const RunResult r = atTruePartCount(plan, frames);
  double worst = 1.0;
  for (std::size_t t = 0; t < frames.size(); ++t)
    worst = std::min(worst, ev::adjustedRandIndex(r.result.labels[t], frames[t].labels));
  std::printf("humanoid 8000 points, seed 3: pooled ARI %.3f, worst frame %.3f\n", r.ari, worst);
  EXPECT_GE(r.ari, 0.92);
  EXPECT_GE(worst, 0.85);
}

// With many points per frame (1000 tracked samples), the border rounds of the clustering can take
// almost every point of a group; such a remnant still counted as a part, so the merges stopped
// at the asked count with several parts holding nothing. Here (16.7k points per frame) 6 of 15
// parts vanished from the labels: 9 parts, the smallest with 0.01% of the points, pooled ARI
// 0.563 (the 800k-point, 48-frame humanoid of the benchmark: 9 parts, 0.649). Remnants now give
// their points to the nearest real part before the merges: 15 parts, the smallest 0.54%, 0.711
// (0.945 at 800k points).
TEST(MotionQuality, ManyPointsNoEmptyParts) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 10, 16667, 3));
  const RunResult r = atTruePartCount(plan, frames);
  const int asked = synth::partCount(plan);
  long total = 0;
  const long smallest = smallestPart(r, total);
  std::printf("humanoid, 16.7k points per frame: %d parts (asked %d), smallest %.2f%% of the "
              "points, pooled ARI %.3f, %.1f s\n",
              r.clusters, asked, 100.0 * smallest / std::max(total, 1L), r.ari,
              r.seconds);
  EXPECT_GE(r.clusters, asked - 1);
  EXPECT_GE(smallest, total / 500);
}

// With a target, phase 1 stops at max(2N, N + 8) groups, single samples counted among them, and
// those then join a neighbour whatever the cost: on this humanoid (8000 points per frame, seed 5,
// 500 tracked samples, 15 parts asked) 25 of the 30 groups were single samples, 5 groups were left
// after their joins and the stage gave 4 parts (pooled ARI 0.15). Where the joins leave fewer
// groups than asked, phase 1 now runs again with the tiny groups joining first once the merges
// cost more than the threshold: 14 parts, 0.75 (a hard case still; with the default samples, 970
// here, phase 1 never runs twice).
TEST(MotionQuality, SingleSamplesDoNotTakeRealGroupsPlacesInPhaseOne) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 20, 8000, 5));
  seg::MeanShiftParams p;
  p.target_clusters = synth::partCount(plan);
  p.patches = 500;
  const RunResult r = runOn(frames, p);
  std::printf("humanoid, 8000 points per frame, seed 5, 500 samples: %d parts (asked %d), pooled "
              "ARI %.3f\n",
              r.clusters, p.target_clusters, r.ari);
  EXPECT_GE(r.clusters, p.target_clusters - 1);
  EXPECT_GE(r.ari, 0.7);
}

// Slivers: the border rounds of the clustering can leave a group with a few dozen reference points
// between two parts. With `--parts N` such a sliver counted as one of the N, so true parts merged
// in its place: on this quadruped (8000 points per frame, seed 4) slivers of 22, 47 and 22
// reference points kept their place, the neck split between torso and head, a hind leg merged
// knee and all, and the graph cut then emptied two slivers: 10 parts for 12 asked, pooled ARI
// 0.785 (the stage alone, 20 frames). A part of fewer than a tenth of the mean part size now
// merges first and does not count.
TEST(MotionQuality, SliversDoNotTakeTheirPlaceAmongTheParts) {
  const auto plan = synth::BodyPlan::Quadruped;
  const auto frames = synth::generate(sequenceParams(plan, 20, 8000, 4));
  const RunResult r = atTruePartCount(plan, frames);
  const int asked = synth::partCount(plan);
  long total = 0;
  const long smallest = smallestPart(r, total);
  const double neck = topLabel(plan, frames, r, "neck").second;
  seg::MeanShiftParams off;
  off.target_clusters = asked;
  off.sliver_fraction = 0.0;
  const RunResult counted = runOn(frames, off);
  std::printf("quadruped, 8000 points per frame, seed 4: %d parts (asked %d), smallest %.2f%% of "
              "the points, neck %.2f in one part, pooled ARI %.3f; slivers counted: %d parts, "
              "%.3f\n",
              r.clusters, asked, 100.0 * smallest / std::max(total, 1L), neck, r.ari,
              counted.clusters, counted.ari);
  EXPECT_GE(r.ari, counted.ari + 0.1);
  EXPECT_EQ(r.clusters, asked);
  EXPECT_GE(smallest * asked * 10, total);  // no part below a tenth of the mean
  EXPECT_GE(neck, 0.85);
  EXPECT_GE(r.ari, 0.92);
}

// Long sequences: a sample's pose is fitted in each frame from where it was in the frame before,
// and what its neighbourhood hardly constrains drifts a little at every step. Over 160 frames
// of one walk cycle (the generator's motion spans the sequence whatever its length) the drift
// made the pieces of one part explain each other worse than the threshold: this humanoid gave
// 21 parts for 15, pooled ARI 0.60, where the same cycle in 48 frames is fine. Tracked through
// key frames (no frame more than about 48 steps from the reference), it gives 14 parts, 0.87.
TEST(MotionQuality, LongSequencesDoNotDrift) {
  const auto plan = synth::BodyPlan::Humanoid;
  const auto frames = synth::generate(sequenceParams(plan, 160, 1500, 1));
  const RunResult r = runOn(frames, seg::MeanShiftParams());
  std::printf("humanoid, 160 frames of 1500 points, seed 1, default threshold: %d parts (%d "
              "true), pooled ARI %.3f\n",
              r.clusters, synth::partCount(plan), r.ari);
  EXPECT_LE(std::abs(r.clusters - synth::partCount(plan)), 2);
  EXPECT_GE(r.ari, 0.82);
}

// Diagnostics: how many tracked samples stay on their true part, per frame.
TEST(MotionQuality, DISABLED_Tracking) {
  const auto plan = diagnosticPlan();
  const auto frames = diagnosticFrames(plan);
  const auto seq = synth::toSequence(frames);
  seg::MotionTrackingParams mp;
  mp.samples = envInt("SAMPLES", 0);
  mp.neighbourhood = envInt("NBH", mp.neighbourhood);
  mp.icp_iterations = envInt("ITERS", mp.icp_iterations);
  mp.reference_frame = envInt("REF", 0);
  auto t0 = std::chrono::steady_clock::now();
  const seg::SampleTracks tr = seg::trackSamples(seq, mp);
  const double t_track =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const int S = static_cast<int>(tr.sample_points.size());
  std::vector<int> truth0(S);
  for (int s = 0; s < S; ++s) truth0[s] = frames[tr.reference_frame].labels[tr.sample_points[s]];
  std::printf("%d samples, tracking %.1f s, spacing %.4f\n", S, t_track, tr.spacing);
  for (std::size_t t = 0; t < frames.size(); ++t) {
    int ok = 0;
    std::map<std::pair<int, int>, int> off;  // (true part, part landed on) -> samples
    for (int s = 0; s < S; ++s) {
      const int lab = trueLabelAt(frames[t], tr.positions[t].col(s));
      ok += lab == truth0[s];
      if (lab != truth0[s]) ++off[{truth0[s], lab}];
    }
    if (envInt("OFF", 0)) {
      std::printf("  off part (true->landed:count):");
      for (const auto& [k, v] : off)
        if (v >= 2) std::printf(" %d->%d:%d", k.first, k.second, v);
      std::printf("\n");
    }
    // Residual of each sample under the Kabsch fit of its true part's samples.
    std::vector<double> err(S, 0.0);
    for (int part = 0; part < synth::partCount(plan); ++part) {
      std::vector<int> m;
      for (int s = 0; s < S; ++s)
        if (truth0[s] == part) m.push_back(s);
      if (m.size() < 3) continue;
      Eigen::Matrix3Xd a(3, m.size()), b(3, m.size());
      for (std::size_t k = 0; k < m.size(); ++k)
        a.col(k) = tr.positions[tr.reference_frame].col(m[k]), b.col(k) = tr.positions[t].col(m[k]);
      const auto fit = ev::kabsch(a, b);
      for (std::size_t k = 0; k < m.size(); ++k)
        err[m[k]] = ((fit.rotation * a.col(k) + fit.translation) - b.col(k)).norm() / tr.spacing;
    }
    std::sort(err.begin(), err.end());
    int bad = 0;
    for (double e : err) bad += e > 3.0;
    std::printf(
        "frame %2zu: on part %.3f, residual %.2f, part-fit err median %.2f p90 %.2f "
        ">3: %d\n",
        t, double(ok) / S, tr.residual[t], err[S / 2], err[S * 9 / 10], bad);
  }
  t0 = std::chrono::steady_clock::now();
  mp.target_clusters = synth::partCount(plan);
  const seg::TrajectoryClusters tc = seg::clusterTrajectories(seq, tr, mp);
  std::printf("clustering %.2f s, %d groups, sample ARI vs truth %.3f\n",
              std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(),
              tc.groups, ev::adjustedRandIndex(tc.group, truth0));
}

// Diagnostics: where the labels at the true part count go wrong (reference frame vs transfer),
// and which true parts each predicted part covers.
TEST(MotionQuality, DISABLED_Confusion) {
  const auto plan = diagnosticPlan();
  const auto frames = diagnosticFrames(plan);
  seg::MeanShiftParams p;
  p.target_clusters = envInt("TARGET", synth::partCount(plan));
  p.motion_threshold = envDouble("THRESHOLD", p.motion_threshold);
  p.joint_weight = envDouble("JOINT_WEIGHT", p.joint_weight);
  p.sliver_fraction = envDouble("SLIVER", p.sliver_fraction);
  const RunResult r = runOn(frames, p);
  const auto rep = ev::evaluate(r.result.labels, truthOf(frames));
  std::printf("pooled ARI %.3f, %d clusters, %.1f s; frame ARI:", r.ari, r.clusters, r.seconds);
  for (double a : rep.frame_ari) std::printf(" %.2f", a);
  std::printf("\n merges:");
  for (std::size_t i = 0; i < std::min<std::size_t>(12, r.result.merges.size()); ++i)
    std::printf(" %.2f", r.result.merges[i].cost);
  std::printf("\n");
  const int P = synth::partCount(plan);
  const auto names = synth::partNames(plan);
  std::vector<std::vector<long>> conf(P, std::vector<long>(r.clusters, 0));
  for (std::size_t t = 0; t < frames.size(); ++t)
    for (std::size_t i = 0; i < frames[t].labels.size(); ++i)
      if (r.result.labels[t][i] >= 0) ++conf[frames[t].labels[i]][r.result.labels[t][i]];
  for (int a = 0; a < P; ++a) {
    long tot = 0;
    for (long c : conf[a]) tot += c;
    std::printf("%-14s %6ld:", names[a].c_str(), tot);
    for (int c = 0; c < r.clusters; ++c)
      if (conf[a][c] * 50 > tot) std::printf(" L%d=%.0f%%", c, 100.0 * conf[a][c] / tot);
    std::printf("\n");
  }
}

// Diagnostics: purity of the sample groups at several part counts (TARGETS, comma-separated):
// whether a count's errors come from groups that straddle true parts or from merges.
TEST(MotionQuality, DISABLED_Purity) {
  const auto plan = diagnosticPlan();
  const auto frames = diagnosticFrames(plan);
  const auto seq = synth::toSequence(frames);
  seg::MotionTrackingParams mp;
  const seg::SampleTracks tr = seg::trackSamples(seq, mp);
  const int S = static_cast<int>(tr.sample_points.size());
  const int P = synth::partCount(plan);
  const auto names = synth::partNames(plan);
  std::vector<int> truth0(S);
  for (int s = 0; s < S; ++s) truth0[s] = frames[tr.reference_frame].labels[tr.sample_points[s]];
  const char* targets = std::getenv("TARGETS");
  std::string list = targets ? targets : std::to_string(P);
  std::size_t pos = 0;
  while (pos < list.size()) {
    const std::size_t comma = std::min(list.find(',', pos), list.size());
    mp.target_clusters = std::atoi(list.substr(pos, comma - pos).c_str());
    pos = comma + 1;
    const seg::TrajectoryClusters tc = seg::clusterTrajectories(seq, tr, mp);
    // Point-level purity in the reference frame.
    std::vector<std::vector<int>> conf(tc.groups, std::vector<int>(P, 0));
    const auto& lab0 = frames[0].labels;
    for (std::size_t i = 0; i < tc.point_labels.size(); ++i)
      if (tc.point_labels[i] >= 0) ++conf[tc.point_labels[i]][lab0[i]];
    long pure = 0, tot = 0;
    for (const auto& row : conf) {
      pure += *std::max_element(row.begin(), row.end());
      for (int c : row) tot += c;
    }
    std::vector<int> ref_pred(tc.point_labels.begin(), tc.point_labels.end());
    std::printf("target %d: %d groups, point purity %.3f, reference ARI %.3f\n", mp.target_clusters,
                tc.groups, double(pure) / tot, ev::adjustedRandIndex(ref_pred, lab0));
    for (int g = 0; g < tc.groups; ++g) {
      int rs = 0;
      for (int c : conf[g]) rs += c;
      std::printf("  G%-2d %5d:", g, rs);
      for (int p = 0; p < P; ++p)
        if (conf[g][p] * 20 > rs)
          std::printf(" %s=%.0f%%", names[p].c_str(), 100.0 * conf[g][p] / rs);
      std::printf("\n");
    }
  }
}
