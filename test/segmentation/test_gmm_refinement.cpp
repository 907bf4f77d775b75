#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/io/normals.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <random>
#include <thread>

#include "cpu_rigid_device.h"
#include "synthetic_parts.h"

using pcl_animseg::segmentation::GMMBoundaryRefinement;
using pcl_animseg::segmentation::RefinementParams;
using pcl_animseg::segmentation::SegmentationResult;

namespace {

struct Outcome {
  double error_before, error_after, ari_before, ari_after;
};

Outcome run(const animseg_test::TubeChain& chain, const RefinementParams& params, int parts) {
  SegmentationResult in;
  in.labels = chain.shifted;
  in.num_clusters = parts;
  GMMBoundaryRefinement refine;
  refine.setInputSequence(&chain.sequence);
  refine.setParams(params);
  SegmentationResult out;
  refine.refine(in, out);
  Outcome o;
  o.error_before = animseg_test::boundaryError(chain.sequence, chain.truth, chain.shifted);
  o.error_after = animseg_test::boundaryError(chain.sequence, chain.truth, out.labels);
  const std::vector<int> truth = animseg_test::pooled(chain.truth);
  o.ari_before =
      pcl_animseg::evaluation::adjustedRandIndex(animseg_test::pooled(chain.shifted), truth);
  o.ari_after = pcl_animseg::evaluation::adjustedRandIndex(animseg_test::pooled(out.labels), truth);
  std::cout << "boundary error " << o.error_before << " -> " << o.error_after << ", pooled ARI "
            << o.ari_before << " -> " << o.ari_after << ", iterations "
            << refine.getStats().iterations << ", |W| " << refine.getStats().band_points
            << ", models " << refine.getStats().models << std::endl;
  EXPECT_EQ(out.num_clusters, parts);
  return o;
}

}  // namespace

// Two tubes meeting at a mitred elbow (a crease), the initial boundary shifted by 2.5 spacings
// in every frame, as a coarse clustering would leave it.
TEST(GMMRefinement, ElbowBoundaryErrorDropsPooled) {
  const auto chain = animseg_test::makeTubeChain({1.0, 1.0}, {1.0}, 6, 6000, 2.5, 1);
  const Outcome o = run(chain, RefinementParams(), 2);
  EXPECT_GT(o.error_before, 0.2);
  EXPECT_LE(o.error_after, 0.7 * o.error_before);
  EXPECT_GE(o.ari_after, o.ari_before);
}

TEST(GMMRefinement, ElbowBoundaryErrorDropsPerFrame) {
  const auto chain = animseg_test::makeTubeChain({1.0, 1.0}, {1.1}, 4, 6000, -2.5, 2);
  RefinementParams params;
  params.pool_frames = false;
  const Outcome o = run(chain, params, 2);
  EXPECT_LE(o.error_after, 0.7 * o.error_before);
  EXPECT_GE(o.ari_after, o.ari_before);
}

// The iterating path (the default is one pass): a boundary shifted by 5 spacings is beyond one
// band's reach (L_r 4), so later passes, with bands rebuilt from the new labels, must go on
// moving it and stop by themselves before the cap.
TEST(GMMRefinement, SeveralPassesReachFurtherThanOne) {
  const auto chain = animseg_test::makeTubeChain({1.0, 1.0}, {1.0}, 4, 6000, 5.0, 5);
  RefinementParams one;
  RefinementParams many;
  many.max_iterations = 12;
  const Outcome o1 = run(chain, one, 2);
  GMMBoundaryRefinement refine;
  refine.setInputSequence(&chain.sequence);
  refine.setParams(many);
  SegmentationResult in, out;
  in.labels = chain.shifted;
  in.num_clusters = 2;
  refine.refine(in, out);
  const double e_many = animseg_test::boundaryError(chain.sequence, chain.truth, out.labels);
  std::cout << "one pass " << o1.error_after << ", " << refine.getStats().iterations << " passes "
            << e_many << std::endl;
  EXPECT_GT(refine.getStats().iterations, 1);
  EXPECT_LT(refine.getStats().iterations, many.max_iterations);
  EXPECT_LT(e_many, o1.error_after);
}

// Three and four parts: joints bent different ways, boundaries shifted toward different sides.
TEST(GMMRefinement, ChainOfFourParts) {
  const auto chain =
      animseg_test::makeTubeChain({0.8, 0.7, 0.9, 0.6}, {0.9, -1.0, 1.2}, 5, 9000, 2.0, 3);
  const Outcome o = run(chain, RefinementParams(), 4);
  EXPECT_LE(o.error_after, 0.7 * o.error_before);
  EXPECT_GE(o.ari_after, o.ari_before);
}

TEST(GMMRefinement, CorrectLabelsStayCorrect) {
  const auto chain = animseg_test::makeTubeChain({1.0, 1.0}, {1.0}, 4, 5000, 0.0, 4);
  const Outcome o = run(chain, RefinementParams(), 2);
  EXPECT_LE(o.error_after, o.error_before + 0.03);
  EXPECT_GE(o.ari_after, o.ari_before - 0.005);
}

namespace {

struct KneeOutcome {
  double error_before, error_after;
  std::size_t snapped;
};

KneeOutcome refineKnee(const animseg_test::Knee& knee, const RefinementParams& params,
                       const std::vector<std::vector<int>>& labels) {
  SegmentationResult in, out;
  in.labels = labels;
  in.num_clusters = 2;
  GMMBoundaryRefinement refine;
  refine.setInputSequence(&knee.sequence);
  refine.setParams(params);
  refine.refine(in, out);
  KneeOutcome o{animseg_test::boundaryError(knee.sequence, knee.truth, labels),
                animseg_test::boundaryError(knee.sequence, knee.truth, out.labels),
                refine.getStats().snapped};
  std::cout << "boundary error " << o.error_before << " -> " << o.error_after << ", " << o.snapped
            << " points snapped" << std::endl;
  return o;
}

}  // namespace

// A knee whose cap (a sphere about the joint) went with the shin: the motions fit it with either
// bone and the normals of the cap and the shin are alike, so only the fold where the shin leaves
// the cap tells where the border belongs. The fold snap (on by default) must bring the cap back;
// without it the GMMs leave most of it with the shin. Boundary error measured: 0.48 -> 0.42
// without the snap, 0.48 -> 0.02 with it (0.46 -> 0.11 with estimated normals, next test).
TEST(GMMRefinement, FoldSnapBringsAKneeCapBackToItsBone) {
  const auto knee = animseg_test::makeKnee(5, 6000, 0.2, 0.13, 5.0, 11);
  RefinementParams off;
  off.fold_snap_band = 0.0;
  const KneeOutcome without = refineKnee(knee, off, knee.capped);
  const KneeOutcome with = refineKnee(knee, RefinementParams(), knee.capped);
  EXPECT_GT(without.error_before, 0.3);
  EXPECT_EQ(without.snapped, 0u);
  EXPECT_GT(with.snapped, 0u);
  EXPECT_LE(with.error_after, 0.1 * with.error_before);
  EXPECT_LE(with.error_after, 0.2 * without.error_after);
}

// The same with normals estimated from the points (PCA over 10 neighbours), which round the
// crease off over a few spacings, as on a scan.
TEST(GMMRefinement, FoldSnapWorksWithEstimatedNormals) {
  auto knee = animseg_test::makeKnee(5, 6000, 0.2, 0.13, 5.0, 12);
  for (std::size_t t = 0; t < knee.sequence.size(); ++t)
    pcl_animseg::io::estimateNormals(*knee.sequence.frame(t), 10, {});
  const KneeOutcome with = refineKnee(knee, RefinementParams(), knee.capped);
  EXPECT_LE(with.error_after, 0.5 * with.error_before);
}

// Borders that are already on the fold, and borders on a smooth surface (one straight capsule, no
// fold anywhere), are not the snap's business: it must move (almost) nothing.
TEST(GMMRefinement, FoldSnapLeavesBordersWithoutAFoldAlone) {
  const auto knee = animseg_test::makeKnee(4, 6000, 0.2, 0.13, 0.0, 13);
  const KneeOutcome right = refineKnee(knee, RefinementParams(), knee.truth);
  std::size_t points = 0;
  for (const auto& f : knee.truth) points += f.size();
  EXPECT_LE(right.snapped, points / 200);
  EXPECT_LE(right.error_after, right.error_before + 0.02);
  const auto leg = animseg_test::makeKnee(4, 6000, 0.2, 0.2, 3.0, 14, true);
  const KneeOutcome smooth = refineKnee(leg, RefinementParams(), leg.capped);
  EXPECT_GT(smooth.error_before, 0.1);
  EXPECT_EQ(smooth.snapped, 0u);
}

TEST(GMMRefinement, RejectsInconsistentInput) {
  const auto chain = animseg_test::makeTubeChain({1.0, 1.0}, {1.0}, 2, 2000, 0.0, 5);
  GMMBoundaryRefinement refine;
  SegmentationResult in, out;
  in.labels = chain.truth;
  in.num_clusters = 2;
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);  // no sequence
  refine.setInputSequence(&chain.sequence);
  in.labels[1].pop_back();
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  in.labels = chain.truth;
  RefinementParams bad;
  bad.outer_band = bad.narrow_band;
  refine.setParams(bad);
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  bad = RefinementParams();
  bad.motion_tolerance = -0.1;
  refine.setParams(bad);
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  for (int frames : {-1, 1}) {
    bad = RefinementParams();
    bad.motion_frames = frames;
    refine.setParams(bad);
    EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error) << frames;
  }
  bad = RefinementParams();
  bad.fold_angle_deg = 180.0;
  refine.setParams(bad);
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  bad = RefinementParams();
  bad.fold_snap_band = -1.0;
  refine.setParams(bad);
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  bad = RefinementParams();
  bad.fold_snap_angle_deg = 0.0;
  refine.setParams(bad);
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  bad = RefinementParams();
  bad.max_iterations = 0;
  refine.setParams(bad);
  EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error);
  // Model knobs that would fail only after the bands (or divide by a zero patch size).
  for (int which = 0; which < 7; ++which) {
    bad = RefinementParams();
    if (which == 0) bad.components = 0;
    if (which == 1) bad.components = 65;
    if (which == 2) bad.gmm_regularization = 0.0;
    if (which == 3) bad.patch_size = 0.0;
    if (which == 4) bad.patch_radius = -1.0;
    if (which == 5) bad.max_training_points = -1;
    if (which == 6) bad.min_training_points = 0;
    refine.setParams(bad);
    EXPECT_THROW(refine.refine(in, out), pcl_animseg::Error) << which;
  }
  // A single part has no boundary: nothing changes.
  for (auto& f : in.labels) std::fill(f.begin(), f.end(), 0);
  in.num_clusters = 1;
  refine.setParams(RefinementParams());
  refine.refine(in, out);
  EXPECT_EQ(out.labels, in.labels);
}

namespace {

// Three tubes, 5 frames, the borders shifted: the input of the device and spacing tests.
struct ShiftedChain {
  animseg_test::TubeChain chain =
      animseg_test::makeTubeChain({1.0, 1.0, 0.8}, {1.0, 0.7}, 5, 6000, 2.0, 4);
  SegmentationResult in;
  ShiftedChain() {
    in.labels = chain.shifted;
    in.num_clusters = 3;
  }
  SegmentationResult refinedBy(GMMBoundaryRefinement& r) const {
    r.setInputSequence(&chain.sequence);
    SegmentationResult out;
    r.refine(in, out);
    return out;
  }
};

}  // namespace

// The input parts' motions through a device (in batches, one frame position of all parts at a
// time): the same labels and motions as on the CPU, bit for bit.
TEST(GMMRefinement, DeviceFitsGiveTheSameResult) {
  const ShiftedChain c;
  GMMBoundaryRefinement cpu;
  const SegmentationResult expected = c.refinedBy(cpu);
  animseg_test::CpuRigidDevice dev;
  GMMBoundaryRefinement on_device;
  on_device.setRigidFitDevice(&dev);
  SegmentationResult got = c.refinedBy(on_device);
  EXPECT_EQ(got.labels, expected.labels);
  ASSERT_EQ(on_device.getMotions().size(), cpu.getMotions().size());
  for (std::size_t p = 0; p < cpu.getMotions().size(); ++p)
    for (std::size_t t = 0; t < cpu.getMotions()[p].frames.size(); ++t) {
      const auto& a = on_device.getMotions()[p].frames[t];
      const auto& b = cpu.getMotions()[p].frames[t];
      EXPECT_TRUE(a.rotation == b.rotation && a.translation == b.translation) << p << " " << t;
    }
  EXPECT_GE(dev.fits, 3 * 4);  // every part in every frame but the first
  EXPECT_LE(dev.batches, 4);   // one batch per frame position
  // Every frame's neighbour lists in one call, then the verdicts' nearest patch seeds and training
  // points in one (k = 1, against the models' trees), then the motion check's residuals in one,
  // against the frames' trees.
  EXPECT_EQ(dev.knn_k, (std::vector<int>{RefinementParams().boundary_k + 1, 1}));
  // The trees were uploaded once, for all three (the fold snap's distances around the border
  // points in one call after the motion check), and freed after the last.
  EXPECT_EQ(dev.keeps, 1);
  EXPECT_EQ(dev.knn_on_calls, 1);
  EXPECT_EQ(dev.motion_calls, 1);
  EXPECT_EQ(dev.least_calls, 1);
  EXPECT_EQ(dev.mixture_calls, 1);              // every model's fits in one call
  EXPECT_GT(on_device.getStats().snapped, 0u);  // the snap moved points: its distances mattered
  EXPECT_EQ(on_device.getStats().snapped, cpu.getStats().snapped);
  EXPECT_TRUE(dev.kept.empty());
  // The motions' fits ran on a thread of their own (beside the first bands); the lists, on this
  // one.
  EXPECT_NE(dev.fit_thread, std::this_thread::get_id());
  EXPECT_EQ(dev.knn_thread, std::this_thread::get_id());
  // Devices that offer less (`offer` switched off): the cores do the rest, the same result.
  auto refinedWithout = [&](bool animseg_test::CpuRigidDevice::*offer) {
    animseg_test::CpuRigidDevice device;
    device.*offer = false;
    on_device.setRigidFitDevice(&device);
    EXPECT_EQ(c.refinedBy(on_device).labels, expected.labels);
    on_device.setRigidFitDevice(nullptr);
    return device;
  };
  // Without the k-NN: the lists on the CPU.
  const auto fits_only = refinedWithout(&animseg_test::CpuRigidDevice::offer_knn);
  EXPECT_EQ(fits_only.knn_calls, 0);
  // Searching but keeping no trees: the lists' search uploads them, the motion check and the
  // fold snap's distances run on the cores.
  const auto no_keep = refinedWithout(&animseg_test::CpuRigidDevice::offer_keep);
  EXPECT_EQ(no_keep.knn_k, (std::vector<int>{RefinementParams().boundary_k + 1, 1}));
  EXPECT_EQ(no_keep.knn_on_calls, 0);
  EXPECT_EQ(no_keep.motion_calls, 0);
  EXPECT_EQ(no_keep.least_calls, 0);
  // Keeping trees but offering no motion check: the cores score it.
  const auto no_check = refinedWithout(&animseg_test::CpuRigidDevice::offer_motion);
  EXPECT_EQ(no_check.knn_on_calls, 1);
  EXPECT_EQ(no_check.motion_calls, 0);
  EXPECT_EQ(no_check.least_calls, 1);
  // Keeping trees but offering no distances around the border points: the cores find them.
  const auto no_least = refinedWithout(&animseg_test::CpuRigidDevice::offer_least);
  EXPECT_EQ(no_least.motion_calls, 1);
  EXPECT_EQ(no_least.least_calls, 0);
  // Not fitting mixtures: the cores fit them.
  const auto no_mixtures = refinedWithout(&animseg_test::CpuRigidDevice::offer_mixtures);
  EXPECT_EQ(no_mixtures.mixture_calls, 0);
}

// The motion check as a device computes it (CpuRigidDevice::cpuMotionResiduals, the arithmetic
// the GPU's kernel runs) against the refinement's own on the cores: on the refinement test's
// chain the same labels (above); here the residuals themselves, term by term, for copies near
// and far from any point and for motions marked invalid.
TEST(GMMRefinement, MotionCheckOnTheDeviceIsTheCoresBitForBit) {
  namespace seg = pcl_animseg::segmentation;
  const int frames = 4;
  const animseg_test::MotionCheckCase mc = animseg_test::randomMotionCheck(5, frames, 3, 200, 50, 300);
  const auto& trees = mc.trees;
  const seg::MotionCheckJobs& jobs = mc.jobs;
  const std::vector<float> got = animseg_test::CpuRigidDevice::cpuMotionResiduals(trees, jobs);
  // The refinement's loop on the cores, written out as it runs there: the copies' nearest points
  // by FlatKdTree3::knn (k = 1), point and normal by row.
  std::vector<std::size_t> first(frames + 1, 0);
  for (int t = 0; t < frames; ++t) first[t + 1] = first[t] + trees[t].size();
  int capped = 0, differ = 0;
  for (std::size_t r = 0; r < jobs.part.size(); ++r) {
    double sum = 0.0;
    int n = 0;
    for (int t : jobs.scored) {
      const std::size_t lt = static_cast<std::size_t>(jobs.part[r]) * frames + t;
      if (t == jobs.own[r] || !jobs.valid[lt]) continue;
      double y[3];
      seg::icp_step::apply(seg::icp_step::load(&jobs.motions[12 * lt]), &jobs.starts[3 * r], y);
      const float q[3] = {static_cast<float>(y[0]), static_cast<float>(y[1]),
                          static_cast<float>(y[2])};
      std::vector<int> rows;
      std::vector<float> d2;
      if (trees[t].knn(q, 1, rows, d2) != 1) continue;
      const std::vector<float>& pts = trees[t].leafPoints();
      const std::vector<int>& leaf_rows = trees[t].leafRows();
      const std::size_t leaf = static_cast<std::size_t>(
          std::find(leaf_rows.begin(), leaf_rows.end(), rows[0]) - leaf_rows.begin());
      const double p[3] = {pts[3 * leaf], pts[3 * leaf + 1], pts[3 * leaf + 2]};
      const float* nf = &jobs.normals[3 * (first[t] + rows[0])];
      const double nd[3] = {nf[0], nf[1], nf[2]};
      const double e = seg::motion_check::term(y, p, nd, jobs.spacing[t], jobs.cap);
      capped += e == jobs.cap;
      sum += e;
      ++n;
    }
    differ += got[r] != seg::motion_check::residual(sum, n);
  }
  EXPECT_EQ(differ, 0);
  EXPECT_GT(capped, 0);
}

// The frames prepared ahead on another thread (prepareFrames, as the pipeline does beside the
// motion method's clustering): every point's lists in that one call, of which refine() views
// the labelled ones, and the same labels as refine() alone gives; released by refine(). A
// preparation for another sequence, or one whose device failed, is not used: the same labels.
TEST(GMMRefinement, FramesPreparedAheadGiveTheSameResult) {
  ShiftedChain c;
  // Some points unlabelled: the prepared lists are every point's, refine()'s its labelled ones'.
  for (auto& frame : c.in.labels)
    for (std::size_t j = 0; j < frame.size(); j += 37) frame[j] = -1;
  GMMBoundaryRefinement alone;
  const SegmentationResult expected = c.refinedBy(alone);
  ASSERT_NE(expected.labels, c.in.labels);  // the refinement moves points

  animseg_test::CpuRigidDevice dev;
  GMMBoundaryRefinement prepared;
  prepared.setInputSequence(&c.chain.sequence);
  prepared.setRigidFitDevice(&dev);
  EXPECT_TRUE(prepared.preparedSpacings().empty());
  std::thread ahead([&] { prepared.prepareFrames(); });
  ahead.join();
  EXPECT_EQ(dev.knn_k, std::vector<int>{RefinementParams().boundary_k + 1});
  EXPECT_NE(dev.knn_thread, std::this_thread::get_id());
  EXPECT_EQ(prepared.preparedSpacings(), pcl_animseg::meanSpacings(c.chain.sequence));
  EXPECT_EQ(c.refinedBy(prepared).labels, expected.labels);
  // refine() only scored the motion check, in the trees the preparation kept on the device,
  // and released the rest.
  EXPECT_EQ(dev.knn_k, (std::vector<int>{RefinementParams().boundary_k + 1,
                                         1}));  // and the verdicts' searches
  EXPECT_EQ(dev.keeps, 1);
  EXPECT_EQ(dev.knn_on_calls, 1);
  EXPECT_EQ(dev.motion_calls, 1);
  EXPECT_TRUE(prepared.preparedSpacings().empty());

  // Another sequence's trees kept on the same device since the preparation: refine() does not
  // search those; its motion check runs on the cores. The same labels.
  const ShiftedChain second;
  GMMBoundaryRefinement first_prepared, second_prepared;
  animseg_test::CpuRigidDevice shared;
  first_prepared.setInputSequence(&c.chain.sequence);
  first_prepared.setRigidFitDevice(&shared);
  first_prepared.prepareFrames();
  second_prepared.setInputSequence(&second.chain.sequence);
  second_prepared.setRigidFitDevice(&shared);
  second_prepared.prepareFrames();
  EXPECT_EQ(c.refinedBy(first_prepared).labels, expected.labels);
  EXPECT_EQ(shared.keeps, 2);
  EXPECT_EQ(shared.knn_on_calls, 2);  // the two preparations' lists
  EXPECT_EQ(shared.knn_k, (std::vector<int>{RefinementParams().boundary_k + 1,
                                            RefinementParams().boundary_k + 1, 1}));
  EXPECT_EQ(shared.motion_calls, 0);

  // Prepared for another sequence: refine() searches its own lists.
  const ShiftedChain other;
  animseg_test::CpuRigidDevice dev2;
  GMMBoundaryRefinement moved_on;
  moved_on.setRigidFitDevice(&dev2);
  moved_on.setInputSequence(&other.chain.sequence);
  moved_on.prepareFrames();
  EXPECT_EQ(c.refinedBy(moved_on).labels, expected.labels);
  EXPECT_EQ(dev2.knn_k, (std::vector<int>{RefinementParams().boundary_k + 1,
                                          RefinementParams().boundary_k + 1, 1}));
  EXPECT_EQ(dev2.motion_calls, 1);

  // A device whose k-NN fails while preparing: no error there; refine() searches on its own.
  animseg_test::CpuRigidDevice failing;
  failing.fail_knn = true;
  GMMBoundaryRefinement after_failure;
  after_failure.setInputSequence(&c.chain.sequence);
  after_failure.setRigidFitDevice(&failing);
  EXPECT_NO_THROW(after_failure.prepareFrames());
  EXPECT_FALSE(after_failure.preparedSpacings().empty());
  failing.fail_knn = false;
  EXPECT_EQ(c.refinedBy(after_failure).labels, expected.labels);
  EXPECT_EQ(failing.knn_k, (std::vector<int>{RefinementParams().boundary_k + 1, 1}));
  EXPECT_EQ(failing.motion_calls, 1);
}

// Spacings given by the caller (the pipeline measures them once) are the ones measured: the
// same result; spacings of another frame count are an error, and others than measured are used.
TEST(GMMRefinement, SpacingsGivenAreUsed) {
  const ShiftedChain c;
  GMMBoundaryRefinement measured;
  const SegmentationResult expected = c.refinedBy(measured);
  GMMBoundaryRefinement given;
  given.setSpacings(pcl_animseg::meanSpacings(c.chain.sequence));
  EXPECT_EQ(c.refinedBy(given).labels, expected.labels);
  given.setSpacings(std::vector<double>(c.chain.sequence.size() + 1, 0.01));
  EXPECT_THROW(c.refinedBy(given), pcl_animseg::Error);
  // Bands ten times narrower: fewer points can move.
  std::vector<double> narrow = pcl_animseg::meanSpacings(c.chain.sequence);
  for (double& s : narrow) s *= 0.1;
  given.setSpacings(narrow);
  EXPECT_NE(c.refinedBy(given).labels, expected.labels);
}

// The motion check over a few frames spread evenly (motion_frames) instead of all of them: on a
// sequence of 12 frames, 4 give nearly the same labels and still cut the boundary error; a cap at
// or above the frame count changes nothing.
TEST(GMMRefinement, MotionCheckOverFewerFrames) {
  const auto chain = animseg_test::makeTubeChain({1.0, 1.0}, {1.0}, 12, 3000, 2.5, 6);
  RefinementParams all;
  all.motion_frames = 0;
  RefinementParams capped = all;
  capped.motion_frames = 4;
  RefinementParams above = all;
  above.motion_frames = 12;
  SegmentationResult in;
  in.labels = chain.shifted;
  in.num_clusters = 2;
  auto refined = [&](const RefinementParams& p) {
    GMMBoundaryRefinement r;
    r.setInputSequence(&chain.sequence);
    r.setParams(p);
    SegmentationResult out;
    r.refine(in, out);
    return out.labels;
  };
  const auto a = refined(all), c = refined(capped), b = refined(above);
  EXPECT_EQ(b, a);
  const double before = animseg_test::boundaryError(chain.sequence, chain.truth, chain.shifted);
  const double err_all = animseg_test::boundaryError(chain.sequence, chain.truth, a);
  const double err_capped = animseg_test::boundaryError(chain.sequence, chain.truth, c);
  std::cout << "boundary error " << before << " -> " << err_all << " (every frame), " << err_capped
            << " (4 frames)" << std::endl;
  EXPECT_LE(err_capped, 0.7 * before);
  EXPECT_LE(err_capped, err_all + 0.02);
  EXPECT_GE(
      pcl_animseg::evaluation::adjustedRandIndex(animseg_test::pooled(a), animseg_test::pooled(c)),
      0.97);
}
