#include <gtest/gtest.h>
#include <pcl/search/kdtree.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/synth/articulated.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <set>

namespace sy = pcl_animseg::synth;
using pcl_animseg::Error;

namespace {

Eigen::Vector3d pos(const pcl::PointNormal& p) { return p.getVector3fMap().cast<double>(); }
Eigen::Vector3d nrm(const pcl::PointNormal& p) { return p.getNormalVector3fMap().cast<double>(); }

sy::SynthParams pointParams(sy::BodyPlan plan) {
  sy::SynthParams p;
  p.plan = plan;
  p.frames = 5;
  p.points = 2500;
  p.point_variation = 0.2;
  p.seed = 3;
  return p;
}

/** Best rigid motion src -> dst (the test links only the synth module, so Eigen's Umeyama
 * stands in for evaluation::kabsch) and its RMS residual. */
Eigen::Matrix4d rigidFit(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst, double* rms) {
  const Eigen::Matrix4d m = Eigen::umeyama(src, dst, false);
  if (rms) {
    const Eigen::Matrix3Xd r =
        ((m.topLeftCorner<3, 3>() * src).colwise() + m.topRightCorner<3, 1>()) - dst;
    *rms = std::sqrt(r.squaredNorm() / static_cast<double>(src.cols()));
  }
  return m;
}

/** Largest per-part RMS residual of rigid fits from frame 0, over all frames and parts of
 * `labels`, relative to frame 0's bounding-box diagonal. */
double worstPartResidual(const std::vector<Eigen::Matrix3Xd>& positions,
                         const std::vector<int>& labels) {
  const double diag =
      (positions[0].rowwise().maxCoeff() - positions[0].rowwise().minCoeff()).norm();
  double worst = 0.0;
  const int parts = *std::max_element(labels.begin(), labels.end()) + 1;
  for (int k = 0; k < parts; ++k) {
    std::vector<int> idx;
    for (std::size_t i = 0; i < labels.size(); ++i)
      if (labels[i] == k) idx.push_back(static_cast<int>(i));
    Eigen::Matrix3Xd a(3, idx.size());
    for (std::size_t j = 0; j < idx.size(); ++j) a.col(j) = positions[0].col(idx[j]);
    for (std::size_t t = 1; t < positions.size(); ++t) {
      Eigen::Matrix3Xd b(3, idx.size());
      for (std::size_t j = 0; j < idx.size(); ++j) b.col(j) = positions[t].col(idx[j]);
      double rms = 0.0;
      rigidFit(a, b, &rms);
      worst = std::max(worst, rms / diag);
    }
  }
  return worst;
}

/** Fraction of points in the largest connected component of the "within `radius`" graph. */
double largestComponentFraction(const pcl_animseg::PointCloudSequence::Cloud::Ptr& cloud,
                                double radius) {
  pcl::search::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  std::vector<int> comp(cloud->size(), -1);
  std::size_t best = 0;
  int next = 0;
  for (std::size_t s = 0; s < cloud->size(); ++s) {
    if (comp[s] >= 0) continue;
    std::vector<int> stack = {static_cast<int>(s)}, idx;
    std::vector<float> d2;
    comp[s] = next;
    std::size_t count = 0;
    while (!stack.empty()) {
      const int q = stack.back();
      stack.pop_back();
      ++count;
      tree.radiusSearch((*cloud)[q], radius, idx, d2);
      for (int j : idx)
        if (comp[j] < 0) {
          comp[j] = next;
          stack.push_back(j);
        }
    }
    best = std::max(best, count);
    ++next;
  }
  return static_cast<double>(best) / static_cast<double>(cloud->size());
}

}  // namespace

TEST(Articulated, PartCountsAndNames) {
  EXPECT_EQ(sy::partCount(sy::BodyPlan::Quadruped), 12);
  EXPECT_GE(sy::partCount(sy::BodyPlan::Humanoid), 11);
  EXPECT_EQ(sy::partCount(sy::BodyPlan::Spider), 17);
  EXPECT_EQ(sy::partCount(sy::BodyPlan::Snake), 10);
  EXPECT_EQ(sy::partCount(sy::BodyPlan::Hand), 16);
  for (sy::BodyPlan plan : sy::allBodyPlans()) {
    const auto names = sy::partNames(plan);
    EXPECT_EQ(static_cast<int>(names.size()), sy::partCount(plan));
    EXPECT_EQ(std::set<std::string>(names.begin(), names.end()).size(), names.size());
    EXPECT_EQ(sy::bodyPlanFromString(sy::toString(plan)), plan);
  }
  EXPECT_EQ(sy::bodyPlanFromString("Spider"), sy::BodyPlan::Spider);
  EXPECT_THROW(sy::bodyPlanFromString("octopus"), Error);
  EXPECT_EQ(sy::frameName(7, 12), "f007");
  EXPECT_EQ(sy::frameName(7, 1000), "f007");
  EXPECT_EQ(sy::frameName(7, 1001), "f0007");
}

TEST(Articulated, BadParametersThrow) {
  sy::SynthParams p;
  p.frames = 0;
  EXPECT_THROW(sy::generate(p), Error);
  p = sy::SynthParams();
  p.points = 9;
  EXPECT_THROW(sy::generate(p), Error);
  p = sy::SynthParams();
  p.point_variation = 1.0;
  EXPECT_THROW(sy::generate(p), Error);
  p = sy::SynthParams();
  p.noise = -0.1;
  EXPECT_THROW(sy::generate(p), Error);
  p = sy::SynthParams();
  p.scale = 0.0;
  EXPECT_THROW(sy::generate(p), Error);
  p = sy::SynthParams();
  p.mesh = true;
  p.mesh_resolution = 2;
  EXPECT_THROW(sy::generate(p), Error);
}

class PointMode : public ::testing::TestWithParam<sy::BodyPlan> {};

TEST_P(PointMode, SurfaceSamplesOfAllPartsWithOutwardNormals) {
  const sy::SynthParams params = pointParams(GetParam());
  const auto frames = sy::generate(params);
  ASSERT_EQ(frames.size(), 5u);
  const int parts = sy::partCount(params.plan);
  std::set<std::size_t> sizes;
  for (const auto& f : frames) {
    ASSERT_TRUE(f.cloud);
    const std::size_t n = f.cloud->size();
    sizes.insert(n);
    EXPECT_GE(n, 2000u);
    EXPECT_LE(n, 3000u);
    ASSERT_EQ(f.labels.size(), n);
    EXPECT_TRUE(f.faces.empty());
    ASSERT_EQ(static_cast<int>(f.part_centres.size()), parts);

    std::vector<int> per_part(parts, 0);
    std::size_t outward = 0;
    for (std::size_t i = 0; i < n; ++i) {
      const int l = f.labels[i];
      ASSERT_GE(l, 0);
      ASSERT_LT(l, parts);
      ++per_part[l];
      const auto& p = (*f.cloud)[i];
      EXPECT_NEAR(nrm(p).norm(), 1.0, 1e-5);
      if (nrm(p).dot(pos(p) - f.part_centres[l]) > 0.0) ++outward;
    }
    // Every part keeps a visible share of its surface in every pose.
    for (int k = 0; k < parts; ++k) EXPECT_GE(per_part[k], 15) << "part " << k;
    EXPECT_EQ(outward, n);
    // Parts overlap at joints: the samples form one connected surface.
    const double spacing = pcl_animseg::meanSpacing(*f.cloud);
    EXPECT_GT(largestComponentFraction(f.cloud, 4.0 * spacing), 0.995);
  }
  EXPECT_GT(sizes.size(), 1u) << "point counts should vary between frames";
}

INSTANTIATE_TEST_SUITE_P(AllPlans, PointMode, ::testing::ValuesIn(sy::allBodyPlans()),
                         [](const testing::TestParamInfo<sy::BodyPlan>& i) {
                           return sy::toString(i.param);
                         });

TEST(Articulated, PointCountsStayWithinVariation) {
  sy::SynthParams p;
  p.plan = sy::BodyPlan::Snake;
  p.frames = 40;
  p.points = 200;
  p.point_variation = 0.3;
  const auto frames = sy::generate(p);
  std::size_t lo = 1000, hi = 0;
  for (const auto& f : frames) {
    lo = std::min(lo, f.cloud->size());
    hi = std::max(hi, f.cloud->size());
  }
  EXPECT_GE(lo, 140u);
  EXPECT_LE(hi, 260u);
  EXPECT_GT(hi - lo, 60u);  // the draw spans most of the range
  p.point_variation = 0.0;
  for (const auto& f : sy::generate(p)) EXPECT_EQ(f.cloud->size(), 200u);
}

TEST(Articulated, DeterministicPerSeed) {
  sy::SynthParams p = pointParams(sy::BodyPlan::Humanoid);
  p.noise = 0.002;
  const auto a = sy::generate(p);
  const auto b = sy::generate(p);
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t t = 0; t < a.size(); ++t) {
    ASSERT_EQ(a[t].cloud->size(), b[t].cloud->size());
    EXPECT_EQ(a[t].labels, b[t].labels);
    for (std::size_t i = 0; i < a[t].cloud->size(); ++i) {
      ASSERT_EQ(pos((*a[t].cloud)[i]), pos((*b[t].cloud)[i]));
      ASSERT_EQ(nrm((*a[t].cloud)[i]), nrm((*b[t].cloud)[i]));
    }
  }
  p.seed = 4;
  const auto c = sy::generate(p);
  bool differ = false;
  for (std::size_t t = 0; t < a.size() && !differ; ++t)
    differ =
        a[t].cloud->size() != c[t].cloud->size() || pos((*a[t].cloud)[0]) != pos((*c[t].cloud)[0]);
  EXPECT_TRUE(differ);
}

TEST(Articulated, NoiseHasTheRequestedSigma) {
  sy::SynthParams p = pointParams(sy::BodyPlan::Quadruped);
  p.frames = 2;
  const auto clean = sy::generate(p);
  p.noise = 0.01;
  const auto noisy = sy::generate(p);
  for (std::size_t t = 0; t < clean.size(); ++t) {
    ASSERT_EQ(clean[t].cloud->size(), noisy[t].cloud->size());
    const double diag = pcl_animseg::boundingBoxDiagonal(*clean[t].cloud);
    double sq = 0.0;
    for (std::size_t i = 0; i < clean[t].cloud->size(); ++i)
      sq += (pos((*clean[t].cloud)[i]) - pos((*noisy[t].cloud)[i])).squaredNorm();
    const double sigma = std::sqrt(sq / (3.0 * clean[t].cloud->size()));
    EXPECT_NEAR(sigma / (0.01 * diag), 1.0, 0.1);
  }
}

TEST(Articulated, GlobalMotionAndLargeJointMotion) {
  sy::SynthParams p = pointParams(sy::BodyPlan::Quadruped);
  p.frames = 8;
  p.mesh = true;
  p.mesh_resolution = 12;
  const auto frames = sy::generate(p);
  const double diag = pcl_animseg::boundingBoxDiagonal(*frames[0].cloud);
  // The torso (part 0) moves as a whole: frames are not trivially aligned.
  EXPECT_GT((frames[4].part_centres[0] - frames[0].part_centres[0]).norm(), 0.05 * diag);
  // A front upper leg swings relative to the torso by ±50° (gallop): from frame 0 (mid-swing) it
  // turns by about the amplitude.
  const auto rel = [&](std::size_t t, int part) {
    std::vector<int> idx;
    for (std::size_t i = 0; i < frames[t].labels.size(); ++i)
      if (frames[t].labels[i] == part) idx.push_back(static_cast<int>(i));
    Eigen::Matrix3Xd a(3, idx.size()), b(3, idx.size());
    std::vector<int> torso;
    for (std::size_t i = 0; i < frames[t].labels.size(); ++i)
      if (frames[t].labels[i] == 0) torso.push_back(static_cast<int>(i));
    Eigen::Matrix3Xd t0(3, torso.size()), t1(3, torso.size());
    for (std::size_t k = 0; k < torso.size(); ++k) {
      t0.col(k) = pos((*frames[0].cloud)[torso[k]]);
      t1.col(k) = pos((*frames[t].cloud)[torso[k]]);
    }
    for (std::size_t k = 0; k < idx.size(); ++k) {
      a.col(k) = pos((*frames[0].cloud)[idx[k]]);
      b.col(k) = pos((*frames[t].cloud)[idx[k]]);
    }
    const Eigen::Matrix3d rt = rigidFit(t0, t1, nullptr).topLeftCorner<3, 3>();
    const Eigen::Matrix3d rp = rigidFit(a, b, nullptr).topLeftCorner<3, 3>();
    return Eigen::AngleAxisd(rt.transpose() * rp).angle();
  };
  double max_angle = 0.0;
  for (std::size_t t = 1; t < frames.size(); ++t) max_angle = std::max(max_angle, rel(t, 4));
  EXPECT_GT(max_angle, 40.0 * M_PI / 180.0);
}

class MeshMode : public ::testing::TestWithParam<sy::BodyPlan> {};

TEST_P(MeshMode, ConstantTopologyAndRigidParts) {
  sy::SynthParams p;
  p.plan = GetParam();
  p.frames = 4;
  p.mesh = true;
  p.mesh_resolution = 10;
  const auto frames = sy::generate(p);
  const int parts = sy::partCount(p.plan);
  const std::size_t n = frames[0].cloud->size();
  ASSERT_GT(n, 0u);
  ASSERT_FALSE(frames[0].faces.empty());
  for (const auto& f : frames) {
    ASSERT_EQ(f.cloud->size(), n);
    ASSERT_EQ(f.labels, frames[0].labels);
    ASSERT_EQ(f.faces.size(), frames[0].faces.size());
    for (std::size_t k = 0; k < f.faces.size(); ++k)
      ASSERT_EQ(f.faces[k].vertices, frames[0].faces[k].vertices);
    // Faces wind counter-clockwise seen from outside: their normal agrees with the vertex normals.
    for (const auto& face : f.faces) {
      ASSERT_EQ(face.vertices.size(), 3u);
      const auto& a = (*f.cloud)[face.vertices[0]];
      const auto& b = (*f.cloud)[face.vertices[1]];
      const auto& c = (*f.cloud)[face.vertices[2]];
      const Eigen::Vector3d fn = (pos(b) - pos(a)).cross(pos(c) - pos(a));
      ASSERT_GT(fn.dot(nrm(a) + nrm(b) + nrm(c)), 0.0);
    }
    for (std::size_t i = 0; i < n; ++i) {
      EXPECT_NEAR(nrm((*f.cloud)[i]).norm(), 1.0, 1e-5);
      EXPECT_GT(nrm((*f.cloud)[i]).dot(pos((*f.cloud)[i]) - f.part_centres[f.labels[i]]), 0.0);
    }
  }
  std::set<int> present(frames[0].labels.begin(), frames[0].labels.end());
  EXPECT_EQ(static_cast<int>(present.size()), parts);
  // Each part moves rigidly; the whole does not.
  std::vector<Eigen::Matrix3Xd> positions;
  for (const auto& f : frames) {
    Eigen::Matrix3Xd m(3, n);
    for (std::size_t i = 0; i < n; ++i) m.col(i) = pos((*f.cloud)[i]);
    positions.push_back(m);
  }
  EXPECT_LT(worstPartResidual(positions, frames[0].labels), 1e-6);
  EXPECT_GT(worstPartResidual(positions, std::vector<int>(n, 0)), 0.01);
}

INSTANTIATE_TEST_SUITE_P(AllPlans, MeshMode, ::testing::ValuesIn(sy::allBodyPlans()),
                         [](const testing::TestParamInfo<sy::BodyPlan>& i) {
                           return sy::toString(i.param);
                         });

TEST(Articulated, ToSequence) {
  sy::SynthParams p;
  p.plan = sy::BodyPlan::Hand;
  p.frames = 3;
  p.points = 500;
  const auto frames = sy::generate(p);
  const auto seq = sy::toSequence(frames);
  ASSERT_EQ(seq.size(), 3u);
  EXPECT_EQ(seq.name(0), "f000");
  EXPECT_EQ(seq.name(2), "f002");
  EXPECT_EQ(seq.frame(1)->size(), frames[1].cloud->size());
}

// Legs of a real animal never pass through each other. The spider's adjacent legs swing in
// opposite phases about the vertical: with the old swing (37 degrees apart, +-25 each) they passed
// through each other, which no real sequence shows and no tracker can follow; now +-16. Lower legs of different legs, and
// upper legs away from the body where they start, must keep apart in every frame.
TEST(Articulated, SpiderLegsNeverCross) {
  sy::SynthParams p = pointParams(sy::BodyPlan::Spider);
  p.frames = 40;
  p.points = 6000;
  const auto frames = sy::generate(p);
  const auto names = sy::partNames(sy::BodyPlan::Spider);
  double closest = 1e9;
  for (const auto& f : frames) {
    const auto& c = *f.cloud;
    const Eigen::Vector3d body = f.part_centres[0];
    for (std::size_t a = 1; a < names.size(); ++a)
      for (std::size_t b = a + 1; b < names.size(); ++b) {
        // Upper and lower of one leg meet at the knee.
        if (names[a].substr(0, 6) == names[b].substr(0, 6)) continue;
        for (std::size_t i = 0; i < c.size(); ++i) {
          if (f.labels[i] != static_cast<int>(a) || (pos(c[i]) - body).norm() < 0.35) continue;
          for (std::size_t j = 0; j < c.size(); ++j)
            if (f.labels[j] == static_cast<int>(b) && (pos(c[j]) - body).norm() >= 0.35)
              closest = std::min(closest, (pos(c[i]) - pos(c[j])).norm());
        }
      }
  }
  std::printf("closest points of two legs: %.4f\n", closest);
  EXPECT_GT(closest, 0.03);  // 0.064 measured; 0.0009 with the old swing
}
