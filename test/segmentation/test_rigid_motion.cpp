#include <gtest/gtest.h>
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/segmentation/rigid_motion.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>

#include "cpu_rigid_device.h"
#include "synthetic_parts.h"

using animseg_test::Cloud;
using pcl_animseg::segmentation::PartMotion;
using pcl_animseg::segmentation::RigidMotionEstimation;

namespace {

// Largest distance between the two transforms' images of the part's frame-0 points.
double maxDeviation(const Cloud& frame0, const std::vector<int>& labels, int part,
                    const Eigen::Matrix3d& r1, const Eigen::Vector3d& t1, const Eigen::Matrix3d& r2,
                    const Eigen::Vector3d& t2) {
  double worst = 0.0;
  for (std::size_t j = 0; j < frame0.size(); ++j) {
    if (labels[j] != part) continue;
    const Eigen::Vector3d p = frame0[j].getVector3fMap().cast<double>();
    worst = std::max(worst, ((r1 * p + t1) - (r2 * p + t2)).norm());
  }
  return worst;
}

// Mesh mode (shared vertex order): in every frame, `motion` (of the true part `part`) must map
// the part's frame-0 points to within 1% of the frame-0 bounding-box diagonal of where the Kabsch
// fit from the known correspondences maps them, with a residual under 0.5% of it.
void expectMatchesKabsch(const animseg_test::BoxChain& chain, int part, const PartMotion& motion,
                         const std::string& what) {
  const Cloud& f0 = *chain.sequence.frame(0);
  const double diag = pcl_animseg::boundingBoxDiagonal(f0);
  std::vector<int> idx;
  for (std::size_t j = 0; j < f0.size(); ++j)
    if (chain.truth[0][j] == part) idx.push_back(static_cast<int>(j));
  Eigen::Matrix3Xd src(3, idx.size());
  for (std::size_t k = 0; k < idx.size(); ++k)
    src.col(k) = f0[idx[k]].getVector3fMap().cast<double>();
  ASSERT_TRUE(motion.frames[0].valid) << what;
  for (std::size_t t = 1; t < chain.sequence.size(); ++t) {
    const Cloud& ft = *chain.sequence.frame(t);
    Eigen::Matrix3Xd dst(3, idx.size());
    for (std::size_t k = 0; k < idx.size(); ++k)
      dst.col(k) = ft[idx[k]].getVector3fMap().cast<double>();
    const auto fit = pcl_animseg::evaluation::kabsch(src, dst);
    const auto& m = motion.frames[t];
    ASSERT_TRUE(m.valid) << what << " frame " << t;
    EXPECT_LT(maxDeviation(f0, chain.truth[0], part, m.rotation, m.translation, fit.rotation,
                           fit.translation),
              0.01 * diag)
        << what << " frame " << t;
    EXPECT_LT(m.rms, 0.005 * diag) << what << " frame " << t;
  }
}

}  // namespace

TEST(RigidMotion, MeshModeMatchesKabschFromCorrespondences) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(8, 6000, true, 3);
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const std::vector<PartMotion> motion = est.compute(chain.truth);
  ASSERT_EQ(motion.size(), 3u);
  for (int part = 0; part < 3; ++part)
    expectMatchesKabsch(chain, part, motion[part], "part " + std::to_string(part));
}

TEST(RigidMotion, PointModeRecoversTrueMotionWithoutCorrespondences) {
  // Every frame sampled anew: no vertex is shared, only the surfaces are.
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(8, 9000, false, 5);
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const std::vector<PartMotion> motion = est.compute(chain.truth);
  const Cloud& f0 = *chain.sequence.frame(0);
  const double diag = pcl_animseg::boundingBoxDiagonal(f0);
  const double spacing = pcl_animseg::meanSpacing(f0);
  for (int part = 0; part < 3; ++part)
    for (std::size_t t = 1; t < chain.sequence.size(); ++t) {
      const Eigen::Affine3d truth = chain.pose[part][t] * chain.pose[part][0].inverse();
      const auto& icp = motion[part].frames[t];
      ASSERT_TRUE(icp.valid);
      EXPECT_LT(maxDeviation(f0, chain.truth[0], part, icp.rotation, icp.translation,
                             truth.linear(), truth.translation()),
                0.01 * diag)
          << "part " << part << " frame " << t;
      // Residual of a correct fit of two samplings of the same surface: about a point spacing.
      EXPECT_LT(icp.rms, 2.0 * spacing);
    }
}

TEST(RigidMotion, WrongLabelsGiveLargeResidualAndMissingPartsAreInvalid) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(5, 6000, false, 9);
  // Everything as one part: not rigid, so the residual is far above the correct parts'.
  std::vector<std::vector<int>> one = chain.truth;
  for (auto& f : one) std::fill(f.begin(), f.end(), 0);
  // Part 3 exists only in frame 0 (a few points).
  std::vector<std::vector<int>> labels = chain.truth;
  for (int j = 0; j < 10; ++j) labels[0][j] = 3;
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const auto whole = est.compute(one);
  const auto parts = est.compute(labels);
  ASSERT_EQ(parts.size(), 4u);
  // Nearest-neighbour residuals saturate (a misaligned point still finds some neighbour), so the
  // gap is moderate; it is still clear at the frame of largest deformation.
  double whole_max = 0.0, parts_max = 0.0;
  for (std::size_t t = 1; t < 5; ++t) {
    whole_max = std::max(whole_max, whole[0].frames[t].rms);
    for (int p = 0; p < 3; ++p) parts_max = std::max(parts_max, parts[p].frames[t].rms);
  }
  EXPECT_GT(whole_max, 1.2 * parts_max);
  EXPECT_TRUE(parts[3].frames[0].valid);
  EXPECT_FALSE(parts[3].frames[1].valid);
  EXPECT_THROW(est.compute({labels[0]}), pcl_animseg::Error);

  // transforms.json is written and carries one entry per part and frame.
  const std::string path = ::testing::TempDir() + "/transforms_test.json";
  std::remove(path.c_str());
  pcl_animseg::segmentation::LevelMotion level;
  level.level = 0;
  level.parts = parts;
  pcl_animseg::segmentation::writeTransformsJson(path, chain.sequence, {level});
  std::ifstream in(path);
  ASSERT_TRUE(in.good());
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string json = ss.str();
  EXPECT_NE(json.find("\"frames\": [\"f0\", \"f1\""), std::string::npos);
  EXPECT_NE(json.find("\"rotation\": [["), std::string::npos);
  EXPECT_NE(json.find("null"), std::string::npos);  // part 3 in frames >= 1
  std::size_t count = 0;
  for (std::size_t p = json.find("\"rms\""); p != std::string::npos;
       p = json.find("\"rms\"", p + 1))
    ++count;
  EXPECT_EQ(count, 3u * 5u + 1u);
  std::remove(path.c_str());
}

namespace {
void expectSameMotion(const PartMotion& a, const PartMotion& b, const std::string& what) {
  EXPECT_EQ(a.part, b.part) << what;
  EXPECT_EQ(a.points_frame0, b.points_frame0) << what;
  ASSERT_EQ(a.frames.size(), b.frames.size()) << what;
  for (std::size_t t = 0; t < a.frames.size(); ++t) {
    EXPECT_EQ(a.frames[t].valid, b.frames[t].valid) << what << " frame " << t;
    EXPECT_EQ(a.frames[t].rms, b.frames[t].rms) << what << " frame " << t;
    EXPECT_TRUE(a.frames[t].rotation == b.frames[t].rotation) << what << " frame " << t;
    EXPECT_TRUE(a.frames[t].translation == b.frames[t].translation) << what << " frame " << t;
  }
}
}  // namespace

// A hierarchy's merged part that is rigid: box 0 cut in two at level 0 (its halves move as one),
// whole again at level 1. Fitted from its halves' motions, each frame on its own, it must move
// as the true box does: within 1% of the bounding-box diagonal of the Kabsch fit from the known
// correspondences (mesh mode), like a chained fit.
TEST(RigidMotion, MergedRigidPartMatchesKabschFromCorrespondences) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(8, 6000, true, 3);
  std::vector<std::vector<std::vector<int>>> levels(2, chain.truth);
  // Level 0: box 0's points with an odd index (the same in every frame: mesh mode) become part 3,
  // except in frame 2, where part 3 has no points (no motion there: the merged part must do with
  // part 0's).
  for (std::size_t t = 0; t < levels[0].size(); ++t)
    for (std::size_t j = 0; j < levels[0][t].size(); ++j)
      if (levels[0][t][j] == 0 && j % 2 == 1 && t != 2) levels[0][t][j] = 3;
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const auto all = est.computeLevels(levels);
  ASSERT_EQ(all.size(), 2u);
  ASSERT_EQ(all[1].parts.size(), 3u);
  ASSERT_EQ(all[0].parts.size(), 4u);
  EXPECT_FALSE(all[0].parts[3].frames[2].valid);
  const std::size_t box0_points =
      static_cast<std::size_t>(std::count(chain.truth[0].begin(), chain.truth[0].end(), 0));
  EXPECT_EQ(all[1].parts[0].points_frame0, box0_points);
  expectMatchesKabsch(chain, 0, all[1].parts[0], "merged box");
}

namespace {
double meanRms(const PartMotion& m) {
  double sum = 0.0;
  int n = 0;
  for (const auto& f : m.frames)
    if (f.valid) sum += f.rms, ++n;
  return n ? sum / n : -1.0;
}
}  // namespace

namespace {
// Three nested levels of a box chain: level 0 the truth, level 1 boxes 0 and 1 merged (as 0)
// with box 2 renamed 1, level 2 everything one part.
std::vector<std::vector<std::vector<int>>> nestedLevels(const animseg_test::BoxChain& chain) {
  std::vector<std::vector<std::vector<int>>> levels(3, chain.truth);
  for (auto& f : levels[1])
    for (int& l : f) l = l == 2 ? 1 : 0;
  for (auto& f : levels[2])
    for (int& l : f) l = 0;
  return levels;
}

// Every level's motions the same bits; `what` names the comparison in failures.
void expectSameLevels(const std::vector<pcl_animseg::segmentation::LevelMotion>& got,
                      const std::vector<pcl_animseg::segmentation::LevelMotion>& expected,
                      const std::string& what) {
  ASSERT_EQ(got.size(), expected.size()) << what;
  for (std::size_t l = 0; l < got.size(); ++l) {
    ASSERT_EQ(got[l].parts.size(), expected[l].parts.size()) << what << ", level " << l;
    for (std::size_t p = 0; p < got[l].parts.size(); ++p)
      expectSameMotion(got[l].parts[p], expected[l].parts[p],
                       what + ", level " + std::to_string(l) + " part " + std::to_string(p));
  }
}

// Starts from nearly the same labels, as the pipeline passes the refinement's motions: the
// motions of a coarser subsample (300 points per part).
std::vector<PartMotion> coarseMotions(const animseg_test::BoxChain& chain) {
  RigidMotionEstimation coarse;
  coarse.setInputSequence(&chain.sequence);
  pcl_animseg::segmentation::RigidMotionParams cp;
  cp.max_points = 300;
  coarse.setParams(cp);
  return coarse.compute(chain.truth);
}
}  // namespace

TEST(RigidMotion, EveryLevelFittedWithUnchangedPartsReused) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(5, 6000, false, 13);
  // Level 1: parts 0 and 1 merged, part 2 unchanged but renamed: its motion is the level-0 part
  // 2's. Level 2: everything one part. Level 3: like level 1, except that in frame 3 a few points
  // of part 1 join the renamed part: it is not the same point set any more and must be fitted,
  // not copied; and level 3 splits level 2's part, so it is not nested in level 2.
  std::vector<std::vector<std::vector<int>>> levels = nestedLevels(chain);
  levels.push_back(levels[1]);
  int moved = 0;
  for (std::size_t j = 0; j < chain.truth[3].size() && moved < 40; ++j)
    if (chain.truth[3][j] == 1) levels[3][3][j] = 1, ++moved;
  ASSERT_EQ(moved, 40);
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const auto all = est.computeLevels(levels);
  ASSERT_EQ(all.size(), levels.size());
  for (std::size_t l = 0; l < levels.size(); ++l) {
    EXPECT_EQ(all[l].level, static_cast<int>(l));
    const auto alone = est.compute(levels[l]);
    ASSERT_EQ(all[l].parts.size(), alone.size()) << "level " << l;
    for (std::size_t p = 0; p < alone.size(); ++p) {
      const std::string what = "level " + std::to_string(l) + " part " + std::to_string(p);
      // The finest level, and a level that is not nested in the one before, are chained fits
      // as compute() makes them. The merged parts of nested levels (level 1's part 0, level 2's
      // only part: unions of boxes that move differently, not rigid) start every frame from
      // their children's motions instead: not the same bits, but as good a fit.
      const bool merged = (l == 1 || l == 2) && p == 0;
      if (!merged) {
        if (!(l == 1 && p == 1)) expectSameMotion(all[l].parts[p], alone[p], what);
        continue;
      }
      std::printf("%s: mean RMS %.5f from the children's motions, %.5f chained\n", what.c_str(),
                  meanRms(all[l].parts[p]), meanRms(alone[p]));
      EXPECT_EQ(all[l].parts[p].points_frame0, alone[p].points_frame0) << what;
      for (const auto& f : all[l].parts[p].frames) EXPECT_TRUE(f.valid) << what;
      EXPECT_LE(meanRms(all[l].parts[p]), 1.1 * meanRms(alone[p])) << what;
    }
  }
  EXPECT_FALSE(all[3].parts[1].frames[3].translation == all[1].parts[1].frames[3].translation);
  EXPECT_THROW(est.computeLevels(levels, {3, 2}), pcl_animseg::Error);
  // Only the first two levels (what `animseg --transform-levels 2` asks for): the same motions.
  const auto first = est.computeLevels(levels, {}, 2);
  ASSERT_EQ(first.size(), 2u);
  for (std::size_t l = 0; l < first.size(); ++l)
    for (std::size_t p = 0; p < first[l].parts.size(); ++p)
      expectSameMotion(first[l].parts[p], all[l].parts[p],
                       "first two, level " + std::to_string(l) + " part " + std::to_string(p));
  // A label vector of the wrong length, in any level, is an error, not a read past the end.
  auto broken = levels;
  broken[2][1].pop_back();
  EXPECT_THROW(est.computeLevels(broken), pcl_animseg::Error);
  EXPECT_NO_THROW(est.computeLevels(broken, {}, 2));  // the broken level is not asked for
}

// Starts of their own in every frame (setInitialMotions, as the pipeline passes the refinement's
// motions): a part's frames are fitted in parallel, from the better of that start and the
// previous frame's motion. The result must match the Kabsch fit from the known correspondences
// as the chained fit does; be the same bits on 1 and 4 threads; recover where the given starts
// are wrong (the chained start wins there); and leave parts beyond the given ones chained.
TEST(RigidMotion, InitialMotionsStartEachFrame) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(8, 6000, true, 3);
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const std::vector<PartMotion> chained = est.compute(chain.truth);
  ASSERT_EQ(chained.size(), 3u);

  std::vector<PartMotion> init = coarseMotions(chain);
  // Wrong starts in every other frame of part 1 (turned by 90 degrees and shifted), and none
  // for part 2.
  for (std::size_t t = 1; t < init[1].frames.size(); t += 2) {
    init[1].frames[t].rotation =
        Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix() *
        init[1].frames[t].rotation;
    init[1].frames[t].translation += Eigen::Vector3d(0.3, -0.2, 0.1);
  }
  init.resize(2);
  est.setInitialMotions(init);
  ASSERT_EQ(est.getInitialMotions().size(), 2u);

  const int before = omp_get_max_threads();
  omp_set_num_threads(1);
  const std::vector<PartMotion> one = est.compute(chain.truth);
  omp_set_num_threads(4);
  const std::vector<PartMotion> four = est.compute(chain.truth);
  omp_set_num_threads(before);
  ASSERT_EQ(one.size(), 3u);
  for (int part = 0; part < 3; ++part) {
    const std::string what = "part " + std::to_string(part);
    expectMatchesKabsch(chain, part, one[part], what);
    expectSameMotion(one[part], four[part], what + ", 1 vs 4 threads");
  }
  // Part 2 had no starts: chained, as without them.
  expectSameMotion(one[2], chained[2], "part 2 without starts");
  // computeLevels takes them for level 0 as well.
  const auto levels = est.computeLevels({chain.truth});
  for (int part = 0; part < 3; ++part)
    expectSameMotion(levels[0].parts[part], one[part], "level 0 part " + std::to_string(part));
  // Cleared: chained again.
  est.setInitialMotions({});
  expectSameMotion(est.compute(chain.truth)[1], chained[1], "part 1 after clearing");
}

// A start's score (rigidScore): the RMS nearest-point distance of the probes (every few source
// points, point k n / probes) moved by the pose; all points when fewer than the probes asked for.
TEST(RigidMotion, ScoreIsTheProbesRmsNearestDistance) {
  // A 20 x 20 grid in the plane z = 0, spacing 0.1, as the surface; the source: the same points.
  std::vector<float> grid;
  std::vector<double> source;
  for (int i = 0; i < 20; ++i)
    for (int j = 0; j < 20; ++j) {
      grid.insert(grid.end(), {0.1f * i, 0.1f * j, 0.0f});
      source.insert(source.end(), {0.1f * i, 0.1f * j, 0.0f});
    }
  pcl_animseg::FlatKdTree3 tree;
  tree.build(grid.data(), 400);
  double pose[12] = {1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0};
  EXPECT_EQ(pcl_animseg::segmentation::rigidScore(source, 50, tree, pose), 0.0);
  // Lifted by 0.03: every probe's nearest point lies right below it.
  pose[11] = 0.03;
  EXPECT_NEAR(pcl_animseg::segmentation::rigidScore(source, 50, tree, pose), 0.03, 1e-6);
  // Shifted by 0.05 along x as well: every probe midway between two grid points.
  pose[9] = 0.05;
  EXPECT_NEAR(pcl_animseg::segmentation::rigidScore(source, 50, tree, pose),
              std::sqrt(0.03 * 0.03 + 0.05 * 0.05), 1e-6);
  // More probes than points: every point, once; none: 0.
  pose[9] = 0.0;
  EXPECT_NEAR(pcl_animseg::segmentation::rigidScore(source, 1000, tree, pose), 0.03, 1e-6);
  EXPECT_EQ(pcl_animseg::segmentation::rigidScore(source, 0, tree, pose), 0.0);
  // Moved by 1 along y: a point of row j (y = 0.1 j) lands on the grid for j < 10, 0.1 (j - 9)
  // beyond its last row otherwise. 200 probes of the 400 points are the points 2 k: rows 0, 2,
  // .., 18 alike, so the mean square is (0.1^2 + 0.3^2 + 0.5^2 + 0.7^2 + 0.9^2) / 10 (the
  // first 200 points, rows 0 .. 19, would give 0.1925).
  pose[10] = 1.0;
  pose[11] = 0.0;
  EXPECT_NEAR(pcl_animseg::segmentation::rigidScore(source, 200, tree, pose), std::sqrt(0.165),
              1e-5);
}

// Spacings given (measured once by the pipeline) give the motions of spacings measured here; a
// count other than the frame count is an error.
TEST(RigidMotion, SpacingsGivenAreTheMeasuredOnes) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(6, 4000, false, 5);
  RigidMotionEstimation est;
  est.setInputSequence(&chain.sequence);
  const std::vector<PartMotion> measured = est.compute(chain.truth);
  est.setSpacings(pcl_animseg::meanSpacings(chain.sequence));
  const std::vector<PartMotion> given = est.compute(chain.truth);
  ASSERT_EQ(given.size(), measured.size());
  for (std::size_t p = 0; p < given.size(); ++p)
    expectSameMotion(given[p], measured[p], "part " + std::to_string(p));
  est.setSpacings(std::vector<double>(2, 0.01));
  EXPECT_THROW(est.compute(chain.truth), pcl_animseg::Error);
  EXPECT_THROW(est.computeLevels({chain.truth}), pcl_animseg::Error);
}

// The fits through a device (in batches: the seeded parts' frames side by side, the chains one
// frame position of all parts at a time, a nested level's merged parts all at once) give the
// CPU's motions bit for bit, from what the device was given alone; a device's failure is thrown.
TEST(RigidMotion, DeviceFitsGiveTheCpuMotions) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(6, 4000, false, 5);
  // The merged parts of levels 1 and 2 are fitted from their children.
  const auto levels = nestedLevels(chain);
  RigidMotionEstimation cpu;
  cpu.setInputSequence(&chain.sequence);
  // Starts for level 0's parts 0 and 1 (the seeded chains); part 2 is an ordinary chain.
  std::vector<PartMotion> init = coarseMotions(chain);
  init.resize(2);
  cpu.setInitialMotions(init);
  const auto expected = cpu.computeLevels(levels);
  const auto chained = cpu.compute(levels[1]);  // level 1 as one labelling: chains only

  animseg_test::CpuRigidDevice dev;
  RigidMotionEstimation gpu_like = cpu;
  gpu_like.setDevice(&dev);
  EXPECT_EQ(gpu_like.getDevice(), &dev);
  const auto got = gpu_like.computeLevels(levels);
  expectSameLevels(got, expected, "on the device");
  const int frames = static_cast<int>(chain.sequence.size());
  std::printf("%d fits in %d batches, %d with the wide passes\n", dev.fits, dev.batches, dev.wide);
  EXPECT_GT(dev.fits, 3 * (frames - 1));  // the fits ran on the device
  EXPECT_LT(dev.batches, dev.fits);       // in batches
  EXPECT_GT(dev.wide, 0);                 // chained starts and merged parts: the wide passes
  EXPECT_LT(dev.wide, dev.fits);          // starts from init: without
  EXPECT_GT(dev.score_batches, 0);        // the seeded parts' starts scored there too

  const auto got_chained = gpu_like.compute(levels[1]);
  for (std::size_t p = 0; p < got_chained.size(); ++p)
    expectSameMotion(got_chained[p], chained[p], "chained part " + std::to_string(p));

  dev.fail = true;
  EXPECT_THROW(gpu_like.computeLevels(levels), pcl_animseg::Error);
}

// Merged parts of different levels whose children are all known are one batch (a wave): level
// 0 with part 2 split in two halves (2 and 3), level 1 merges parts 0 and 1, level 2 keeps that
// part (a copy) and merges the two halves, whose children are level 0's parts (copies at level
// 1). Both merged parts go to the device in one batch instead of one per level, with the CPU's
// motions bit for bit.
TEST(RigidMotion, MergedPartsOfSeveralLevelsInOneBatch) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(6, 4000, false, 5);
  std::vector<std::vector<std::vector<int>>> levels(3, chain.truth);
  for (std::size_t t = 0; t < chain.truth.size(); ++t) {
    int halves = 0;
    for (int& l : levels[0][t])
      if (l == 2 && (halves++ % 2)) l = 3;
    for (std::size_t j = 0; j < levels[0][t].size(); ++j) {
      const int l0 = levels[0][t][j];
      levels[1][t][j] = l0 <= 1 ? 0 : l0 - 1;  // {0, 1} -> 0, 2 -> 1, 3 -> 2
      levels[2][t][j] = l0 <= 1 ? 0 : 1;       // {0, 1} -> 0, {2, 3} -> 1
    }
  }
  RigidMotionEstimation cpu;
  cpu.setInputSequence(&chain.sequence);
  const auto expected = cpu.computeLevels(levels);
  animseg_test::CpuRigidDevice dev;
  RigidMotionEstimation on_device = cpu;
  on_device.setDevice(&dev);
  on_device.computeLevels({levels[0]});
  const int level0_batches = dev.batches;
  dev.batches = 0;
  const auto got = on_device.computeLevels(levels);
  EXPECT_EQ(dev.batches, level0_batches + 1);  // level 0's chains, then one wave
  expectSameLevels(got, expected, "chained level 0");
  // Level 2's part 0 is level 1's part 0.
  expectSameMotion(got[2].parts[0], got[1].parts[0], "level 2 part 0 (a copy)");

  // With starts of their own for every part of level 0 (as the pipeline passes the
  // refinement's), the merged parts are prepared beside the seeded fits: the same motions.
  RigidMotionEstimation coarse;
  coarse.setInputSequence(&chain.sequence);
  pcl_animseg::segmentation::RigidMotionParams cp;
  cp.max_points = 300;
  coarse.setParams(cp);
  cpu.setInitialMotions(coarse.compute(levels[0]));
  on_device.setInitialMotions(cpu.getInitialMotions());
  expectSameLevels(on_device.computeLevels(levels), cpu.computeLevels(levels), "seeded level 0");
}

// A 48-frame sequence: the parts' chains go through key frames (RigidMotionParams::
// max_chain_steps, 12: key frames 4 apart), so a device fits them in 14 batches one after the
// other instead of 47, the CPU's motions bit for bit; each part's motion in every frame still
// matches the Kabsch fit of its true correspondences, as the chain of single steps does.
TEST(RigidMotion, LongChainsGoThroughKeyFrames) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(48, 1500, true, 9);
  RigidMotionEstimation cpu;
  cpu.setInputSequence(&chain.sequence);
  ASSERT_EQ(cpu.getParams().max_chain_steps, 12);
  const std::vector<PartMotion> expected = cpu.compute(chain.truth);
  animseg_test::CpuRigidDevice dev;
  RigidMotionEstimation on_device = cpu;
  on_device.setDevice(&dev);
  const std::vector<PartMotion> got = on_device.compute(chain.truth);
  ASSERT_EQ(got.size(), expected.size());
  for (std::size_t p = 0; p < got.size(); ++p) {
    expectSameMotion(got[p], expected[p], "part " + std::to_string(p));
    expectMatchesKabsch(chain, static_cast<int>(p), got[p],
                        "key frames, part " + std::to_string(p));
  }
  EXPECT_EQ(dev.batches, 14);
  // Single steps: 47 batches, and the same accuracy.
  pcl_animseg::segmentation::RigidMotionParams single;
  single.max_chain_steps = 48;
  animseg_test::CpuRigidDevice dev_single;
  on_device.setParams(single);
  on_device.setDevice(&dev_single);
  const std::vector<PartMotion> stepwise = on_device.compute(chain.truth);
  EXPECT_EQ(dev_single.batches, 47);
  for (std::size_t p = 0; p < stepwise.size(); ++p)
    expectMatchesKabsch(chain, static_cast<int>(p), stepwise[p],
                        "single steps, part " + std::to_string(p));
}

// computeBeside: the caller's work runs on the calling thread while the fits run on a thread of
// their own (with a device), the same motions as compute(); an exception of either is thrown
// after both have ended; without a device the caller's work runs first.
TEST(RigidMotion, WorkBesideTheDeviceFits) {
  const animseg_test::BoxChain chain = animseg_test::makeBoxChain(6, 4000, false, 5);
  RigidMotionEstimation cpu;
  cpu.setInputSequence(&chain.sequence);
  const auto expected = cpu.compute(chain.truth);
  animseg_test::CpuRigidDevice dev;
  RigidMotionEstimation on_device = cpu;
  on_device.setDevice(&dev);
  int calls = 0;
  std::thread::id beside_thread;
  const auto got = on_device.computeBeside(chain.truth, 0, [&] {
    ++calls;
    beside_thread = std::this_thread::get_id();
  });
  EXPECT_EQ(calls, 1);
  EXPECT_EQ(beside_thread, std::this_thread::get_id());
  EXPECT_GT(dev.batches, 0);
  EXPECT_NE(dev.fit_thread, std::this_thread::get_id());  // the fits ran on another thread
  ASSERT_EQ(got.size(), expected.size());
  for (std::size_t p = 0; p < got.size(); ++p)
    expectSameMotion(got[p], expected[p], "part " + std::to_string(p));
  // Failures: the caller's work, the device's.
  EXPECT_THROW(
      on_device.computeBeside(chain.truth, 0, [] { throw pcl_animseg::Error("beside failed"); }),
      pcl_animseg::Error);
  dev.fail = true;
  calls = 0;
  EXPECT_THROW(on_device.computeBeside(chain.truth, 0, [&] { ++calls; }), pcl_animseg::Error);
  EXPECT_EQ(calls, 1);
  // Without a device: the caller's work, then the same motions.
  calls = 0;
  const auto plain = cpu.computeBeside(chain.truth, 0, [&] { ++calls; });
  EXPECT_EQ(calls, 1);
  for (std::size_t p = 0; p < plain.size(); ++p)
    expectSameMotion(plain[p], expected[p], "part " + std::to_string(p) + " (CPU)");
}
