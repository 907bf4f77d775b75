#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>

#include <random>

namespace ev = pcl_animseg::evaluation;

TEST(AdjustedRandIndex, IdenticalUpToRenamingIsOne) {
  const std::vector<int> a = {0, 0, 1, 1, 2, 2, 2, 3};
  const std::vector<int> b = {7, 7, 42, 42, 5, 5, 5, 100};
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex(a, a), 1.0);
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex(a, b), 1.0);
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex(b, a), 1.0);
}

TEST(AdjustedRandIndex, HandComputedExamples) {
  // a = {0,0,1,1}, b = {0,0,1,2}. Contingency cells: n(0,0)=2, n(1,1)=1, n(1,2)=1.
  //   index    = sum C(n_ij,2)              = 1
  //   sum_a    = C(2,2)+C(2,2)              = 2
  //   sum_b    = C(2,2)+C(1,2)+C(1,2)       = 1
  //   expected = sum_a*sum_b / C(4,2) = 2/6  = 1/3
  //   max      = (sum_a+sum_b)/2            = 3/2
  //   ARI      = (1 - 1/3) / (3/2 - 1/3)    = (2/3) / (7/6) = 4/7
  EXPECT_NEAR(ev::adjustedRandIndex({0, 0, 1, 1}, {0, 0, 1, 2}), 4.0 / 7.0, 1e-15);

  // a = {0,0,0,1,1,1}, b = {0,0,1,1,2,2}. Cells: n(0,0)=2, n(0,1)=1, n(1,1)=1, n(1,2)=2.
  //   index = 1+0+0+1 = 2;  sum_a = 3+3 = 6;  sum_b = 1+1+1 = 3;  C(6,2) = 15
  //   expected = 6*3/15 = 6/5;  max = 9/2
  //   ARI = (2 - 6/5) / (9/2 - 6/5) = (4/5) / (33/10) = 8/33
  EXPECT_NEAR(ev::adjustedRandIndex({0, 0, 0, 1, 1, 1}, {0, 0, 1, 1, 2, 2}), 8.0 / 33.0, 1e-15);

  // ARI is symmetric.
  EXPECT_NEAR(ev::adjustedRandIndex({0, 0, 1, 1, 2, 2}, {0, 0, 0, 1, 1, 1}), 8.0 / 33.0, 1e-15);
}

TEST(AdjustedRandIndex, NegativeLabelsAreIgnored) {
  // The -1 points would spoil the agreement if they were counted.
  const std::vector<int> a = {0, 0, 1, 1, -1, 0, 5};
  const std::vector<int> b = {3, 3, 4, 4, 3, -1, -2};
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex(a, b), 1.0);
  EXPECT_NEAR(ev::adjustedRandIndex({0, 0, 1, 1, -1, -1}, {0, 0, 1, 2, 0, 1}), 4.0 / 7.0, 1e-15);
}

TEST(AdjustedRandIndex, DegenerateCases) {
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex({}, {}), 0.0);
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex({3}, {4}), 0.0);
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex({1, 1, 1}, {2, 2, 2}), 1.0);
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex({1, 2, 3}, {4, 5, 6}), 1.0);
  // One cluster against all singletons: no pair agrees beyond chance.
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex({1, 1, 1, 1}, {1, 2, 3, 4}), 0.0);
  EXPECT_THROW(ev::adjustedRandIndex({1, 2}, {1}), pcl_animseg::Error);
}

TEST(AdjustedRandIndex, MillionsOfPoints) {
  // Pair counts reach ~4.5e12 here; the index must stay exact for a relabelled copy and near 0
  // for independent random labelings.
  const std::size_t n = 3000000;
  std::mt19937 rng(7);
  std::vector<int> a(n), b(n), c(n);
  for (std::size_t i = 0; i < n; ++i) {
    a[i] = static_cast<int>(rng() % 20);
    b[i] = 1000 - 3 * a[i];
    c[i] = static_cast<int>(rng() % 20);
  }
  EXPECT_DOUBLE_EQ(ev::adjustedRandIndex(a, b), 1.0);
  EXPECT_NEAR(ev::adjustedRandIndex(a, c), 0.0, 1e-3);
}

TEST(CountParts, IgnoresNegative) {
  EXPECT_EQ(ev::countParts({}), 0);
  EXPECT_EQ(ev::countParts({-1, -1}), 0);
  EXPECT_EQ(ev::countParts({4, 4, 9, -1, 0, 9}), 3);
}

namespace {
Eigen::Matrix3Xd randomPoints(int n, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  Eigen::Matrix3Xd p(3, n);
  for (int i = 0; i < n; ++i) p.col(i) = Eigen::Vector3d(u(rng), u(rng), 0.5 * u(rng));
  return p;
}
}  // namespace

TEST(Kabsch, RecoversKnownMotionExactly) {
  const Eigen::Matrix3Xd src = randomPoints(50, 3);
  const Eigen::Matrix3d r =
      Eigen::AngleAxisd(1.3, Eigen::Vector3d(0.3, -0.5, 0.8).normalized()).toRotationMatrix();
  const Eigen::Vector3d t(0.5, -2.0, 3.25);
  const Eigen::Matrix3Xd dst = (r * src).colwise() + t;
  const ev::RigidFit fit = ev::kabsch(src, dst);
  EXPECT_LT((fit.rotation - r).norm(), 1e-12);
  EXPECT_LT((fit.translation - t).norm(), 1e-12);
  EXPECT_LT(fit.rms, 1e-12);
}

TEST(Kabsch, RmsOfAKnownPerturbation) {
  // A square in z = 0 with a saddle-shaped offset ±d along z. The offset has zero mean and
  // sum p e^T = 0, so H = sum p p^T stays symmetric positive semidefinite: the best fit is the
  // true motion and the residual is exactly d at every point.
  const double d = 0.05;
  Eigen::Matrix3Xd src(3, 4), noisy(3, 4);
  src << 1, -1, 1, -1,  //
      1, -1, -1, 1,     //
      0, 0, 0, 0;
  noisy = src;
  noisy.row(2) << d, d, -d, -d;
  const Eigen::Matrix3d r = Eigen::AngleAxisd(0.7, Eigen::Vector3d::UnitY()).toRotationMatrix();
  const Eigen::Vector3d t(1, 2, 3);
  const ev::RigidFit fit = ev::kabsch(src, (r * noisy).colwise() + t);
  EXPECT_NEAR(fit.rms, d, 1e-12);
  EXPECT_LT((fit.rotation - r).norm(), 1e-12);
  EXPECT_LT((fit.translation - t).norm(), 1e-12);
}

TEST(Kabsch, ReflectionGivesAProperRotation) {
  const Eigen::Matrix3Xd src = randomPoints(30, 5);
  Eigen::Matrix3Xd mirrored = src;
  mirrored.row(0) *= -1.0;
  const ev::RigidFit fit = ev::kabsch(src, mirrored);
  EXPECT_NEAR(fit.rotation.determinant(), 1.0, 1e-12);
  EXPECT_GT(fit.rms, 0.05);
  EXPECT_THROW(ev::kabsch(src, src.leftCols(3)), pcl_animseg::Error);
  const ev::RigidFit empty = ev::kabsch(Eigen::Matrix3Xd(3, 0), Eigen::Matrix3Xd(3, 0));
  EXPECT_TRUE(empty.rotation.isIdentity());
}

namespace {
// Two blocks of points; block 1 rotates about the origin over the frames, block 0 translates.
std::vector<Eigen::Matrix3Xd> twoPartMotion(std::vector<int>& truth) {
  const Eigen::Matrix3Xd a = randomPoints(40, 11);
  const Eigen::Matrix3Xd b = (randomPoints(40, 12).array() + 3.0).matrix();
  truth.assign(80, 0);
  std::fill(truth.begin() + 40, truth.end(), 1);
  std::vector<Eigen::Matrix3Xd> frames;
  for (int t = 0; t < 5; ++t) {
    Eigen::Matrix3Xd f(3, 80);
    f.leftCols(40) = a.colwise() + Eigen::Vector3d(0.2 * t, 0, 0);
    f.rightCols(40) = Eigen::AngleAxisd(0.3 * t, Eigen::Vector3d::UnitZ()).toRotationMatrix() * b;
    frames.push_back(f);
  }
  return frames;
}
}  // namespace

TEST(RigidityError, ZeroForRigidPartsPositiveForWrongSplit) {
  std::vector<int> truth;
  const auto frames = twoPartMotion(truth);
  EXPECT_LT(ev::rigidityError(frames, truth), 1e-12);

  std::vector<int> merged(80, 0);
  EXPECT_GT(ev::rigidityError(frames, merged), 0.05);

  // A wrong cut: ten points of part 1 are given to part 0.
  std::vector<int> wrong = truth;
  for (int i = 40; i < 50; ++i) wrong[i] = 0;
  const double e = ev::rigidityError(frames, wrong);
  EXPECT_GT(e, 0.01);
  EXPECT_LT(e, ev::rigidityError(frames, merged));

  // Over-segmentation of a rigid part costs nothing.
  std::vector<int> over = truth;
  for (int i = 0; i < 20; ++i) over[i] = 7;
  EXPECT_LT(ev::rigidityError(frames, over), 1e-12);

  // Unlabelled points are ignored.
  std::vector<int> partial = wrong;
  for (int i = 40; i < 50; ++i) partial[i] = -1;
  EXPECT_LT(ev::rigidityError(frames, partial), 1e-12);

  EXPECT_THROW(ev::rigidityError(frames, std::vector<int>(79, 0)), pcl_animseg::Error);
}

TEST(Evaluate, PooledAriRewardsTemporalCoherence) {
  std::vector<int> truth_frame;
  const auto positions = twoPartMotion(truth_frame);
  const std::vector<std::vector<int>> truth(5, truth_frame);

  const ev::Report same = ev::evaluate(truth, truth, positions);
  EXPECT_DOUBLE_EQ(same.pooled_ari, 1.0);
  EXPECT_DOUBLE_EQ(same.mean_frame_ari, 1.0);
  EXPECT_EQ(same.predicted_parts, 2);
  EXPECT_EQ(same.true_parts, 2);
  EXPECT_EQ(same.points, 400u);
  EXPECT_LT(same.rigidity_error, 1e-12);
  EXPECT_DOUBLE_EQ(same.label_consistency, 1.0);

  // Every frame is perfect on its own, but frames 1.. swap the two labels: a decomposition that
  // is not coherent in time must lose pooled ARI.
  std::vector<std::vector<int>> swapped = truth;
  for (std::size_t t = 1; t < swapped.size(); ++t)
    for (int& l : swapped[t]) l = 1 - l;
  const ev::Report r = ev::evaluate(swapped, truth, positions);
  EXPECT_DOUBLE_EQ(r.mean_frame_ari, 1.0);
  EXPECT_LT(r.pooled_ari, 0.5);
  EXPECT_DOUBLE_EQ(r.label_consistency, 0.0);
  ASSERT_EQ(r.frame_ari.size(), 5u);

  const ev::Report no_pos = ev::evaluate(truth, truth);
  EXPECT_DOUBLE_EQ(no_pos.rigidity_error, -1.0);
  EXPECT_DOUBLE_EQ(no_pos.label_consistency, -1.0);

  const std::string json = r.toJson();
  for (const char* key :
       {"\"pooled_ari\"", "\"mean_frame_ari\"", "\"frame_ari\"", "\"predicted_parts\"",
        "\"true_parts\"", "\"rigidity_error\"", "\"label_consistency\"", "\"points\": 400"})
    EXPECT_NE(json.find(key), std::string::npos) << key;
  EXPECT_NE(no_pos.toJson().find("\"rigidity_error\": null"), std::string::npos);
}

TEST(Evaluate, MismatchesThrow) {
  EXPECT_THROW(ev::evaluate({{0, 1}}, {{0, 1}, {0, 1}}), pcl_animseg::Error);
  EXPECT_THROW(ev::evaluate({{0, 1, 1}}, {{0, 1}}), pcl_animseg::Error);
  EXPECT_THROW(ev::evaluate({{0, 1}}, {{0, 1}}, {Eigen::Matrix3Xd(3, 3)}), pcl_animseg::Error);
}

// Three true parts over two frames: part 0 found exactly, parts 1 and 2 merged into one
// predicted part, and a point of part 1 split off on its own; negative labels not counted.
TEST(MatchParts, NamesMergedAndSplitParts) {
  const std::vector<std::vector<int>> truth = {{0, 0, 1, 1, 2, -1}, {0, 0, 1, 1, 1, 2}};
  const std::vector<std::vector<int>> pred = {{7, 7, 4, 4, 4, 4}, {7, 7, 4, 9, 4, -1}};
  const std::vector<ev::PartMatch> m = ev::matchParts(pred, truth);
  ASSERT_EQ(m.size(), 3u);
  EXPECT_EQ(m[0].truth, 0);
  EXPECT_EQ(m[0].points, 4u);
  EXPECT_EQ(m[0].predicted, 7);
  EXPECT_DOUBLE_EQ(m[0].iou, 1.0);
  // Part 1: 5 points, 4 in predicted part 4 (which holds 5: part 1's 4 and part 2's 1).
  EXPECT_EQ(m[1].truth, 1);
  EXPECT_EQ(m[1].points, 5u);
  EXPECT_EQ(m[1].predicted, 4);
  EXPECT_DOUBLE_EQ(m[1].recall, 0.8);
  EXPECT_DOUBLE_EQ(m[1].precision, 0.8);
  EXPECT_DOUBLE_EQ(m[1].iou, 4.0 / 6.0);
  // Part 2: one counted point (the other's prediction is negative), in part 4 too: merged.
  EXPECT_EQ(m[2].points, 1u);
  EXPECT_EQ(m[2].predicted, 4);
  EXPECT_DOUBLE_EQ(m[2].recall, 1.0);
  EXPECT_DOUBLE_EQ(m[2].precision, 0.2);

  // A tie goes to the lower predicted label, whatever the order of the points.
  const std::vector<ev::PartMatch> tie = ev::matchParts({{5, 3, 5, 3}}, {{0, 0, 0, 0}});
  ASSERT_EQ(tie.size(), 1u);
  EXPECT_EQ(tie[0].predicted, 3);
  EXPECT_DOUBLE_EQ(tie[0].recall, 0.5);

  // evaluate() reports them, and the JSON lists them.
  const ev::Report r = ev::evaluate(pred, truth);
  ASSERT_EQ(r.parts.size(), 3u);
  EXPECT_EQ(r.parts[1].predicted, 4);
  const std::string json = r.toJson();
  EXPECT_NE(json.find("{\"truth\": 1, \"points\": 5, \"predicted\": 4, \"recall\": 0.8, "
                      "\"precision\": 0.8, \"iou\": 0.666666667}"),
            std::string::npos)
      << json;
  EXPECT_NE(ev::Report().toJson().find("\"parts\": [],"), std::string::npos);
  EXPECT_THROW(ev::matchParts({{0, 1}}, {{0}}), pcl_animseg::Error);
  EXPECT_THROW(ev::matchParts({{0}}, {{0}, {0}}), pcl_animseg::Error);
}
