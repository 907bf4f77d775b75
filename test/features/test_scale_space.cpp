// MLSScaleSpace: level 0 close to the input, unit normals oriented like the input, point order
// kept, exact behaviour under uniform scaling, and the bad inputs of issue 3.
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/neighbourhood.h>
#include <pcl_animseg/features/scale_space.h>

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include "features/bumpy_surface.h"

using namespace pcl_animseg;
using Cloud = PointCloudSequence::Cloud;

namespace {

ScaleSpace build(const Cloud::Ptr& cloud, double h = 2.0, int levels = 5) {
  MLSScaleSpace mls;
  mls.setInputCloud(cloud);
  mls.setScale(h);
  mls.setNumberOfLevels(levels);
  ScaleSpace ss;
  mls.compute(ss);
  return ss;
}

}  // namespace

TEST(ScaleSpace, LevelZeroStaysWithinHalfASpacing) {
  auto cloud = test::bumpySphere(8000, 1);
  const ScaleSpace ss = build(cloud);
  ASSERT_EQ(ss.levels.size(), 5u);
  EXPECT_NEAR(ss.spacing, meanSpacing(*cloud), 1e-9 * ss.spacing);
  double sum = 0.0, worst = 0.0;
  for (std::size_t j = 0; j < cloud->size(); ++j) {
    const double d = ((*ss.levels[0])[j].getVector3fMap() - (*cloud)[j].getVector3fMap()).norm();
    sum += d;
    worst = std::max(worst, d);
  }
  RecordProperty("mean_level0_shift_spacings", std::to_string(sum / cloud->size() / ss.spacing));
  EXPECT_LT(worst, 0.5 * ss.spacing);
  EXPECT_LT(sum / cloud->size(), 0.1 * ss.spacing);
}

TEST(ScaleSpace, NormalsAreUnitAndOrientedLikeTheInput) {
  auto cloud = test::bumpySphere(6000, 2);
  const ScaleSpace ss = build(cloud);
  for (std::size_t i = 0; i < ss.levels.size(); ++i) {
    double mean_dot = 0.0;
    for (std::size_t j = 0; j < cloud->size(); ++j) {
      const Eigen::Vector3f n = (*ss.levels[i])[j].getNormalVector3fMap();
      ASSERT_NEAR(n.norm(), 1.0f, 1e-4f);
      const float dot = n.dot((*cloud)[j].getNormalVector3fMap());
      ASSERT_GT(dot, 0.0f) << "level " << i << " point " << j;
      mean_dot += dot;
    }
    mean_dot /= cloud->size();
    if (i == 0) {
      EXPECT_GT(mean_dot, 0.995);
    }
  }
}

TEST(ScaleSpace, KeepsPointOrderAndSmoothsMoreAtLargerScales) {
  auto cloud = test::bumpySphere(6000, 3);
  const ScaleSpace ss = build(cloud);
  ASSERT_EQ(ss.scales.size(), 5u);
  double prev_shift = 0.0;
  for (std::size_t i = 0; i < ss.levels.size(); ++i) {
    ASSERT_EQ(ss.levels[i]->size(), cloud->size());
    if (i > 0) {
      EXPECT_GT(ss.scales[i], ss.scales[i - 1]);
    }
    double shift = 0.0;
    for (std::size_t j = 0; j < cloud->size(); ++j) {
      const Eigen::Vector3f d =
          (*ss.levels[i])[j].getVector3fMap() - (*cloud)[j].getVector3fMap();
      // Points move along their normals only: level i point j is input point j.
      ASSERT_LT(d.norm(), ss.scales[i]);
      shift += d.norm();
    }
    EXPECT_GT(shift, prev_shift) << "level " << i;
    prev_shift = shift;
  }
  EXPECT_NEAR(ss.scales[0], 2.0 * ss.spacing, 1e-9);
  EXPECT_NEAR(ss.scales[4], 8.0 * ss.spacing, 1e-9);  // h k^4 with k = sqrt 2
}

TEST(ScaleSpace, UniformScalingScalesEveryLevel) {
  auto cloud = test::bumpySphere(4000, 4);
  const double s = 7.5;
  auto big = test::transformed(*cloud, Eigen::Isometry3d::Identity(), s);
  const ScaleSpace a = build(cloud), b = build(big);
  EXPECT_NEAR(b.spacing / a.spacing, s, 1e-4 * s);
  for (std::size_t i = 0; i < a.levels.size(); ++i) {
    double err = 0.0;
    for (std::size_t j = 0; j < cloud->size(); ++j)
      err = std::max<double>(err, ((*b.levels[i])[j].getVector3fMap() -
                                   s * (*a.levels[i])[j].getVector3fMap()).norm());
    EXPECT_LT(err, 1e-3 * b.spacing) << "level " << i;
  }
}

TEST(ScaleSpace, RejectsFramesTooSmallAndBadParameters) {
  auto tiny = test::bumpySphere(12, 5);
  EXPECT_THROW(build(tiny), Error);
  // 60 points: the largest disc (2 * 8 spacings) is wider than the frame.
  auto small = test::bumpySphere(60, 5);
  try {
    build(small);
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("too small for the chosen scales"), std::string::npos);
  }
  EXPECT_NO_THROW(build(small, 1.0, 2));
  auto cloud = test::bumpySphere(2000, 6);
  EXPECT_THROW(build(cloud, -1.0), Error);
  EXPECT_THROW(build(cloud, 2.0, 0), Error);
  MLSScaleSpace mls;
  ScaleSpace ss;
  EXPECT_THROW(mls.compute(ss), Error);  // no input
  mls.setInputCloud(cloud);
  mls.setScaleFactor(1.0);
  EXPECT_THROW(mls.compute(ss), Error);
  Cloud::Ptr bad(new Cloud(*cloud));
  (*bad)[5].x = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(build(bad), Error);
}

TEST(ScaleSpace, CoplanarFrameKeepsThePlane) {
  auto plane = test::heightField(
      3000, 7, [](double, double) { return 0.0; },
      [](double, double) { return Eigen::Vector2d::Zero(); });
  const ScaleSpace ss = build(plane);
  for (const auto& level : ss.levels)
    for (const auto& p : level->points) {
      ASSERT_NEAR(p.z, 0.0f, 1e-5f);
      ASSERT_GT(p.normal_z, 0.9999f);
    }
}

TEST(ScaleSpace, DuplicatePointsAreHarmless) {
  auto cloud = test::bumpySphere(3000, 8);
  Cloud::Ptr twice(new Cloud(*cloud));
  for (const auto& p : cloud->points) twice->push_back(p);
  // meanSpacing sees 0 for duplicates; featureSpacing skips them.
  EXPECT_NEAR(featureSpacing(*twice), meanSpacing(*cloud), 0.05 * meanSpacing(*cloud));
  const ScaleSpace ss = build(twice);
  const std::size_t n = cloud->size();
  for (std::size_t j = 0; j < n; j += 7) {
    const auto& a = (*ss.levels[2])[j];
    const auto& b = (*ss.levels[2])[j + n];
    ASSERT_LT((a.getVector3fMap() - b.getVector3fMap()).norm(), 1e-5f);
  }
  Cloud::Ptr same(new Cloud);
  for (int i = 0; i < 50; ++i) same->push_back((*cloud)[0]);
  EXPECT_THROW(build(same), Error);
}

TEST(ScaleSpace, MissingNormalsPointAwayFromTheCentroid) {
  auto cloud = test::bumpySphere(4000, 9);
  Cloud::Ptr bare(new Cloud(*cloud));
  for (auto& p : bare->points) p.getNormalVector3fMap().setZero();
  const ScaleSpace ss = build(bare);
  std::size_t agree = 0;
  for (std::size_t j = 0; j < cloud->size(); ++j) {
    const Eigen::Vector3f n = (*ss.levels[0])[j].getNormalVector3fMap();
    ASSERT_NEAR(n.norm(), 1.0f, 1e-4f);
    if (n.dot((*cloud)[j].getNormalVector3fMap()) > 0.9f) ++agree;
  }
  EXPECT_GT(agree, cloud->size() * 99 / 100);
}

TEST(Neighbourhoods, RowsAreSortedAndStartWithThePoint) {
  auto cloud = test::bumpySphere(2000, 10);
  const double s = meanSpacing(*cloud);
  const Neighbourhoods nb = radiusNeighbourhoods(*cloud, static_cast<float>(4 * s));
  ASSERT_EQ(nb.points(), cloud->size());
  for (std::size_t j = 0; j < cloud->size(); ++j) {
    ASSERT_GE(nb.count(j), 1);
    ASSERT_EQ(nb.row(j)[0], static_cast<int>(j));
    for (int a = 1; a < nb.count(j); ++a) ASSERT_LE(nb.sqrRow(j)[a - 1], nb.sqrRow(j)[a]);
  }
  EXPECT_EQ(nb.countWithin(0, 0.0f), 1);
}

namespace {

/** Rows by brute force: all j with |x_j - x_i| < r, the nearest `cap` - 1 besides i. */
void expectRowsMatchBruteForce(const Cloud& cloud, float r, int cap = 256) {
  const Neighbourhoods nb = radiusNeighbourhoods(cloud, r, cap);
  ASSERT_EQ(nb.points(), cloud.size());
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    ASSERT_EQ(nb.row(i)[0], static_cast<int>(i));
    std::vector<std::pair<float, int>> want;
    if (cloud[i].getVector3fMap().allFinite())
      for (std::size_t j = 0; j < cloud.size(); ++j) {
        if (j == i || !cloud[j].getVector3fMap().allFinite()) continue;
        const float d2 = (cloud[j].getVector3fMap() - cloud[i].getVector3fMap()).squaredNorm();
        if (d2 < r * r) want.emplace_back(d2, static_cast<int>(j));
      }
    std::sort(want.begin(), want.end());
    if (want.size() > static_cast<std::size_t>(cap - 1)) want.resize(cap - 1);
    ASSERT_EQ(nb.count(i), static_cast<int>(want.size()) + 1) << "row " << i;
    for (std::size_t a = 0; a < want.size(); ++a) {
      ASSERT_EQ(nb.row(i)[a + 1], want[a].second) << "row " << i;
      ASSERT_FLOAT_EQ(nb.sqrRow(i)[a + 1], want[a].first);
    }
  }
}

}  // namespace

TEST(Neighbourhoods, MatchBruteForceOnEveryPath) {
  // Dense cell table, with duplicate points (ties broken by index) and a NaN point (a row of
  // itself, in no other row).
  auto cloud = test::bumpySphere(1500, 11);
  for (int k = 0; k < 20; ++k) cloud->push_back((*cloud)[k * 7]);
  pcl::PointNormal nan_point;
  nan_point.x = nan_point.y = nan_point.z = std::numeric_limits<float>::quiet_NaN();
  cloud->push_back(nan_point);
  const float s = static_cast<float>(meanSpacing(*test::bumpySphere(1500, 11)));
  expectRowsMatchBruteForce(*cloud, 5.0f * s);
  // Rows capped at the nearest ones.
  expectRowsMatchBruteForce(*cloud, 8.0f * s, 12);
  // Far more cells than points (binary search over the sorted cells): a sparse diagonal.
  Cloud line;
  for (int k = 0; k < 300; ++k) {
    pcl::PointNormal p;
    p.x = 0.01f * k;
    p.y = 0.013f * k + 0.002f * (k % 3);
    p.z = 0.007f * k;
    line.push_back(p);
  }
  expectRowsMatchBruteForce(line, 0.02f);
  // A far outlier stretching the frame past 1e6 cells per axis (coarser cells).
  Cloud far(line);
  pcl::PointNormal o;
  o.x = 1.0e5f;
  o.y = o.z = 0.0f;
  far.push_back(o);
  expectRowsMatchBruteForce(far, 0.02f);
}
