// DoGKeypoint: extrema on the bumps, repeatability under rigid motion + resampling, invariance
// to uniform scaling, boundary and ridge rejection, bad input; computeSequenceFeatures.
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/progress.h>

#include <gtest/gtest.h>

#include <cmath>

#include "features/bumpy_surface.h"

using namespace pcl_animseg;
using Cloud = PointCloudSequence::Cloud;

namespace {

DoGKeypoint::KeypointCloud detect(const Cloud::Ptr& cloud, double unit, double edge_ratio = 10.0,
                                  int levels = 5) {
  MLSScaleSpace mls;
  mls.setInputCloud(cloud);
  mls.setSpacing(unit);
  mls.setNumberOfLevels(levels);
  ScaleSpace ss;
  mls.compute(ss);
  DoGKeypoint dog;
  dog.setScaleSpace(ss);
  dog.setEdgeRatio(edge_ratio);
  DoGKeypoint::KeypointCloud kp;
  dog.compute(kp);
  return kp;
}

double unitOf(std::initializer_list<Cloud::Ptr> clouds) {
  PointCloudSequence seq;
  for (const auto& c : clouds) seq.addFrame(c, "f");
  return sequenceSpacing(seq);
}

/** Fraction of the keypoints of `a` with a keypoint of `b` within `dist`. */
double repeatability(const DoGKeypoint::KeypointCloud& a, const DoGKeypoint::KeypointCloud& b,
                     double dist) {
  if (a.empty()) return 0.0;
  std::size_t hit = 0;
  for (const auto& p : a) {
    for (const auto& q : b)
      if ((p.getVector3fMap() - q.getVector3fMap()).norm() <= dist) {
        ++hit;
        break;
      }
  }
  return static_cast<double>(hit) / a.size();
}

}  // namespace

TEST(DoGKeypoint, FindsTheBumps) {
  auto cloud = test::bumpySphere(10000, 20);
  const auto kp = detect(cloud, unitOf({cloud}));
  ASSERT_GT(kp.size(), 6u);
  // Most bumps and dents have a keypoint near their apex.
  int found = 0;
  for (const auto& b : test::defaultBumps()) {
    const Eigen::Vector3d apex = b.centre * test::bumpRadius(test::defaultBumps(), b.centre, nullptr);
    for (const auto& p : kp)
      if ((p.getVector3fMap().cast<double>() - apex).norm() < 0.5 * b.width) {
        ++found;
        break;
      }
  }
  EXPECT_GE(found, 9);
  for (const auto& p : kp) {
    ASSERT_GE(p.index, 0);
    ASSERT_LT(p.index, static_cast<int>(cloud->size()));
    ASSERT_GE(p.level, 1);
    ASSERT_LE(p.level, 3);  // levels 1 .. L-2 of the L-1 = 4 differences
    ASSERT_GT(p.scale, 0.0f);
    ASSERT_GE(std::fabs(p.response), 0.04f);
  }
}

struct Repeatability {
  double a_in_b, b_in_a;
  std::size_t ka, kb;
};

Repeatability repeatabilityForSeed(unsigned seed) {
  auto a = test::bumpySphere(10000, seed);
  const Eigen::Isometry3d T = test::someMotion();
  auto b = test::transformed(*test::bumpySphere(12000, seed + 1000), T);
  const double unit = unitOf({a, b});
  const auto ka = detect(a, unit);
  auto kb = detect(b, unit);
  const Eigen::Isometry3d inv = T.inverse();
  for (auto& p : kb.points)
    p.getVector3fMap() = (inv * p.getVector3fMap().cast<double>()).cast<float>();
  const double spacing = meanSpacing(*a);
  return {repeatability(ka, kb, spacing), repeatability(kb, ka, spacing), ka.size(), kb.size()};
}

class DoGRepeatability : public ::testing::TestWithParam<unsigned> {};

TEST_P(DoGRepeatability, RepeatableUnderRigidMotionAndResampling) {
  const Repeatability r = repeatabilityForSeed(GetParam());
  RecordProperty("repeatability_a_in_b", std::to_string(r.a_in_b));
  RecordProperty("repeatability_b_in_a", std::to_string(r.b_in_a));
  RecordProperty("keypoints", std::to_string(r.ka) + "/" + std::to_string(r.kb));
  // The sphere has 12 bumps and dents: about one keypoint each, no flood of noise extrema
  // (a detector that finds almost nothing would make the fractions below meaningless).
  EXPECT_GE(r.ka, 8u);
  EXPECT_GE(r.kb, 8u);
  EXPECT_LE(r.ka, 15u);
  EXPECT_LE(r.kb, 15u);
  // Issue 3 asks for >= 80%. Over 30 seeds (21, 31, ..., 311): mean 0.95, single seeds
  // 0.82-1.00 with ~12 keypoints each (mean 0.61, seeds 0.27-0.82, ~10.5 keypoints before the
  // area-weighted refit of the position, the extrema taken per level and the two-ring border
  // test; 0.50 before the median contrast). Of the 37 in 707 keypoints without a counterpart
  // within one spacing, 15 are features found in one sampling only and 22 lie 1-3 spacings
  // from theirs (median distance to the bump's apex 0.22 spacing, 0.40 before). A floor per
  // seed here, the pooled value in PooledOverSeeds.
  EXPECT_GE(r.a_in_b, 0.70);
  EXPECT_GE(r.b_in_a, 0.70);
}

INSTANTIATE_TEST_SUITE_P(Seeds, DoGRepeatability, ::testing::Values(21u, 31u, 41u));

TEST(DoGRepeatability, PooledOverSeeds) {
  // Pooled over 6 seeds (both directions): 0.95 for these (0.61 before the refit of the
  // position, 0.42-0.53 before the median contrast); the 30-seed mean is 0.95.
  double sum = 0.0;
  int count = 0;
  for (unsigned seed : {21u, 31u, 41u, 51u, 61u, 71u}) {
    const Repeatability r = repeatabilityForSeed(seed);
    sum += r.a_in_b + r.b_in_a;
    count += 2;
  }
  const double pooled = sum / count;
  RecordProperty("pooled_repeatability", std::to_string(pooled));
  EXPECT_GE(pooled, 0.88);
}

TEST(DoGKeypoint, InvariantToUniformScaling) {
  auto a = test::bumpySphere(8000, 23);
  auto big = test::transformed(*a, Eigen::Isometry3d::Identity(), 42.0);
  const auto ka = detect(a, unitOf({a})), kb = detect(big, unitOf({big}));
  ASSERT_FALSE(ka.empty());
  std::size_t same = 0;
  for (const auto& p : ka)
    for (const auto& q : kb)
      if (p.index == q.index && p.level == q.level) {
        ++same;
        EXPECT_NEAR(q.scale, 42.0f * p.scale, 1e-3f * q.scale);
        EXPECT_NEAR(q.response, p.response, 1e-3f * std::fabs(p.response) + 1e-5f);
        break;
      }
  EXPECT_GE(same, ka.size() * 95 / 100);
}

TEST(DoGKeypoint, RejectsOpenBordersAndRidges) {
  // Bumps straddling the border of an open patch, and one long ridge across it.
  auto f = [](double x, double y) {
    // Feature sizes (0.04-0.05) inside the scale range (0.02-0.07 at 12k points).
    return 0.04 * std::exp(-((x - 1.0) * (x - 1.0) + y * y) / (2 * 0.0025)) +
           0.04 * std::exp(-(x * x + (y + 1.0) * (y + 1.0)) / (2 * 0.0025)) +
           0.035 * std::exp(-(x + 0.3) * (x + 0.3) / (2 * 0.0016)) +
           0.04 * std::exp(-((x - 0.4) * (x - 0.4) + (y - 0.4) * (y - 0.4)) / (2 * 0.0016));
  };
  auto g = [&](double x, double y) {
    const double e = 1e-6;
    return Eigen::Vector2d((f(x + e, y) - f(x - e, y)) / (2 * e), (f(x, y + e) - f(x, y - e)) / (2 * e));
  };
  auto patch = test::heightField(12000, 24, f, g);
  const double unit = unitOf({patch});
  const double spacing = meanSpacing(*patch);
  auto nearBorder = [&](const PointKeypoint& p) {
    return std::max(std::fabs(p.x), std::fabs(p.y)) > 1.0 - 4.0 * spacing;
  };
  auto onRidge = [&](const PointKeypoint& p) {
    return std::fabs(p.x + 0.3) < 0.15 && std::fabs(p.y) < 0.8;
  };
  const auto kp = detect(patch, unit);
  const auto loose = detect(patch, unit, 1e9);
  int ridge = 0, ridge_loose = 0, blob = 0;
  for (const auto& p : kp) {
    EXPECT_FALSE(nearBorder(p)) << p;
    ridge += onRidge(p);
    blob += (Eigen::Vector2f(p.x - 0.4f, p.y - 0.4f).norm() < 0.1f);
  }
  for (const auto& p : loose) ridge_loose += onRidge(p);
  RecordProperty("ridge_keypoints", std::to_string(ridge) + " vs " + std::to_string(ridge_loose));
  // The edge test removes most ridge extrema; on sparse random samples noise along the crest
  // lets some through (see the note in dog_keypoint.h).
  EXPECT_GT(ridge_loose, 0);  // the test would be vacuous otherwise
  EXPECT_LE(ridge, ridge_loose * 2 / 3);
  EXPECT_GE(blob, 1);         // the interior bump is still found
}

// A refine device gets every refined keypoint's job, consistent (its disc, frame and scale), and
// its answers are what the detector keeps: "moved too far" for all leaves no keypoint; "stayed
// at the fitted position" gives the same keypoints (the same response and level) at other
// positions than the cores' own steps, each one on its nearest frame point's tangent plane.
TEST(DoGKeypoint, ARefineDeviceGetsEveryKeypointAndItsAnswersAreKept) {
  class FakeDevice : public KeypointRefineDevice {
   public:
    explicit FakeDevice(bool within) : within_(within) {}
    void refine(KeypointRefineJobs& jobs) const override {
      const std::size_t nk = jobs.scales.size();
      jobs_ += nk;
      EXPECT_EQ(jobs.disc_begin.size(), nk + 1);
      EXPECT_EQ(jobs.frames.size(), 12 * nk);
      EXPECT_EQ(jobs.maximum.size(), nk);
      EXPECT_EQ(jobs.samples.size(), 4 * std::size_t{jobs.disc_begin.back()});
      EXPECT_GT(jobs.h0, 0.0);
      for (std::size_t k = 0; k < nk; ++k) {
        EXPECT_GT(jobs.disc_begin[k + 1], jobs.disc_begin[k] + 10) << "a disc of samples";
        EXPECT_GT(jobs.scales[k], 0.0f);
        // The first sample is the keypoint's own point: within 3 h0 of the fitted position.
        const float* l = jobs.samples.data() + 4 * std::size_t{jobs.disc_begin[k]};
        EXPECT_LT(std::hypot(l[0], l[1]), 3.0 * jobs.h0);
        EXPECT_GT(l[3], 0.0f) << "area weight";
        // The tangent axes are unit vectors.
        const float* f = jobs.frames.data() + 12 * k;
        EXPECT_NEAR(std::sqrt(f[3] * f[3] + f[4] * f[4] + f[5] * f[5]), 1.0, 1e-5);
        EXPECT_NEAR(f[3] * f[6] + f[4] * f[7] + f[5] * f[8], 0.0, 1e-5);
      }
      jobs.y.assign(2 * nk, 0.0f);
      jobs.ok.assign(nk, within_ ? 1 : 0);
    }
    mutable std::size_t jobs_ = 0;

   private:
    bool within_;
  };
  auto cloud = test::bumpySphere(10000, 20);
  MLSScaleSpace mls;
  mls.setInputCloud(cloud);
  mls.setSpacing(unitOf({cloud}));
  ScaleSpace ss;
  mls.compute(ss);
  DoGKeypoint dog;
  dog.setScaleSpace(ss);
  DoGKeypoint::KeypointCloud cores, none, stayed;
  dog.compute(cores);
  ASSERT_GT(cores.size(), 6u);
  FakeDevice far_away(false), at_fit(true);
  dog.setRefineDevice(&far_away);
  dog.compute(none);
  EXPECT_TRUE(none.empty());
  EXPECT_GE(far_away.jobs_, cores.size());
  dog.setRefineDevice(&at_fit);
  dog.compute(stayed);
  EXPECT_EQ(at_fit.jobs_, far_away.jobs_);
  ASSERT_GE(stayed.size(), cores.size() - cores.size() / 5);
  std::size_t moved = 0;
  for (const auto& k : stayed) {
    ASSERT_GE(k.index, 0);
    ASSERT_LT(k.index, static_cast<int>(cloud->size()));
    // On the plane through the input point with level 0's normal.
    const Eigen::Vector3f nq = ss.levels[0]->points[k.index].getNormalVector3fMap();
    EXPECT_NEAR((k.getVector3fMap() - (*cloud)[k.index].getVector3fMap()).dot(nq), 0.0, 1e-5);
    bool same = false;
    for (const auto& c : cores) same = same || (c.getVector3fMap() == k.getVector3fMap());
    moved += !same;
  }
  EXPECT_GT(moved, stayed.size() / 2) << "the device's positions are used, not the cores'";
}

TEST(DoGKeypoint, BadInputAndDegenerateFrames) {
  auto cloud = test::bumpySphere(3000, 25);
  EXPECT_THROW(detect(cloud, unitOf({cloud}), 10.0, 3), Error);  // needs >= 4 levels
  DoGKeypoint dog;
  DoGKeypoint::KeypointCloud kp;
  EXPECT_THROW(dog.compute(kp), Error);
  // A flat frame has no extrema above the contrast threshold: no keypoints, no error.
  auto plane = test::heightField(
      3000, 26, [](double, double) { return 0.0; },
      [](double, double) { return Eigen::Vector2d::Zero(); });
  EXPECT_TRUE(detect(plane, unitOf({plane})).empty());
  // Doubled points: one of each duplicate pair may be a keypoint, never both.
  Cloud::Ptr twice(new Cloud(*cloud));
  for (const auto& p : cloud->points) twice->push_back(p);
  const auto k2 = detect(twice, unitOf({twice}));
  const auto k1 = detect(cloud, unitOf({cloud}));
  EXPECT_GT(k2.size(), 0u);
  EXPECT_LE(k2.size(), k1.size() + 3);
}

TEST(Multiscale, SequenceFeatures) {
  PointCloudSequence seq;
  seq.addFrame(test::bumpySphere(5000, 27), "a");
  seq.addFrame(test::transformed(*test::bumpySphere(6500, 28), test::someMotion()), "b");
  MultiscaleParams p;
  p.keep_smoothed = true;
  Progress progress(true);
  const SequenceFeatures f = computeSequenceFeatures(seq, p, &progress);
  ASSERT_EQ(f.signatures.size(), 2u);
  for (std::size_t t = 0; t < 2; ++t) {
    EXPECT_EQ(f.signatures[t].rows(), static_cast<long>(seq.frame(t)->size()));
    EXPECT_EQ(f.signatures[t].cols(), 24);
    EXPECT_GT(f.keypoints[t].size(), 5u);
    EXPECT_EQ(f.keypoint_scale[t].size(), f.keypoints[t].size());
    EXPECT_EQ(f.keypoint_response[t].size(), f.keypoints[t].size());
    EXPECT_EQ(f.smoothed[t]->size(), seq.frame(t)->size());
  }
  std::vector<std::string> stages;
  for (const auto& s : progress.timings()) stages.push_back(s.first);
  EXPECT_EQ(stages, (std::vector<std::string>{"scale_space", "keypoints", "signature"}));
  PointCloudSequence bad;
  bad.addFrame(test::bumpySphere(10, 29), "tiny");
  try {
    computeSequenceFeatures(bad, p);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("frame 'tiny'"), std::string::npos);
  }
}
