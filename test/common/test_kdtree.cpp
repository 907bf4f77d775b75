// pcl_animseg::KdTree answers exactly as pcl::KdTreeFLANN (same points, same distances), NaN
// points left out, bounded nearest queries against brute force, queries from several threads;
// SearchKdTree inside PCL's ICP.
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_types.h>
#include <pcl/registration/icp.h>
#include <pcl_animseg/kdtree.h>

#include <gtest/gtest.h>

#include <algorithm>
#include <limits>
#include <random>

namespace {

using Cloud = pcl::PointCloud<pcl::PointNormal>;

Cloud::Ptr randomCloud(std::size_t n, unsigned seed, bool with_nan) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  Cloud::Ptr c(new Cloud);
  for (std::size_t i = 0; i < n; ++i) {
    pcl::PointNormal p;
    p.x = g(rng);
    p.y = g(rng);
    p.z = 0.3f * g(rng);
    p.normal_x = p.normal_y = 0.0f;
    p.normal_z = 1.0f;
    if (with_nan && i % 97 == 5) p.y = std::numeric_limits<float>::quiet_NaN();
    c->push_back(p);
  }
  return c;
}

// An integer grid of 12 x 12 x 4 points with duplicates (at later indices) and NaN points: queries
// at its points, cell centres and edge midpoints have 2, 4 or 8 nearest points at one distance.
Cloud::Ptr gridWithDuplicates() {
  Cloud::Ptr cloud(new Cloud);
  for (int x = 0; x < 12; ++x)
    for (int y = 0; y < 12; ++y)
      for (int z = 0; z < 4; ++z) {
        pcl::PointNormal p;
        p.x = static_cast<float>(x);
        p.y = static_cast<float>(y);
        p.z = static_cast<float>(z);
        cloud->push_back(p);
        if ((x * 7 + y * 3 + z) % 11 == 0) cloud->push_back(p);  // a duplicate, a later index
        if ((x + y + z) % 29 == 3) {
          p.y = std::numeric_limits<float>::quiet_NaN();
          cloud->push_back(p);
        }
      }
  return cloud;
}

}  // namespace

TEST(KdTree, SameAnswersAsPclKdTreeFlann) {
  const Cloud::Ptr cloud = randomCloud(5000, 1, true);
  const Cloud::Ptr queries = randomCloud(500, 2, false);
  pcl::KdTreeFLANN<pcl::PointNormal> ref;
  ref.setInputCloud(cloud);
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  EXPECT_LT(tree.size(), cloud->size());  // the NaN points are not in the tree
  std::vector<int> ia, ib;
  std::vector<float> da, db;
  for (const auto& q : queries->points) {
    for (int k : {1, 8, 40}) {
      ASSERT_EQ(ref.nearestKSearch(q, k, ia, da), tree.nearestKSearch(q, k, ib, db));
      EXPECT_EQ(ia, ib);
      EXPECT_EQ(da, db);
    }
    ASSERT_EQ(ref.radiusSearch(q, 0.2, ia, da), tree.radiusSearch(q, 0.2, ib, db));
    EXPECT_EQ(ia, ib);
    EXPECT_EQ(da, db);
    ASSERT_EQ(ref.radiusSearch(q, 0.3, ia, da, 5), tree.radiusSearch(q, 0.3, ib, db, 5));
    EXPECT_EQ(ia, ib);
  }
  for (int i : ib) EXPECT_TRUE(std::isfinite((*cloud)[i].y));
}

// The bounded query of the motion method: the nearest point within the bound (inclusive) or
// none, with FLANN's float distance, checked by brute force on queries near and far from a
// surface-like cloud (as the residuals of good and bad poses make them).
TEST(KdTree, BoundedNearestAgreesWithBruteForce) {
  const Cloud::Ptr cloud = randomCloud(4000, 6, true);
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  std::mt19937 rng(7);
  std::normal_distribution<float> g(0.0f, 1.0f);
  auto dist2 = [](const pcl::PointNormal& a, float x, float y, float z) {
    float r = 0.0f;
    r += (x - a.x) * (x - a.x);
    r += (y - a.y) * (y - a.y);
    r += (z - a.z) * (z - a.z);
    return r;
  };
  int found = 0, none = 0;
  for (int n = 0; n < 2000; ++n) {
    const float spread = n % 2 ? 0.05f : 1.0f;  // near the cloud's points, or anywhere
    const pcl::PointNormal& c = (*cloud)[static_cast<std::size_t>(n) % cloud->size()];
    const float x = (std::isfinite(c.y) ? c.x : 0.0f) + spread * g(rng);
    const float y = (std::isfinite(c.y) ? c.y : 0.0f) + spread * g(rng);
    const float z = (std::isfinite(c.y) ? c.z : 0.0f) + spread * g(rng);
    const float bound = n % 3 == 0 ? 0.01f : 0.25f;
    float best = std::numeric_limits<float>::infinity();
    for (const auto& p : cloud->points)
      if (std::isfinite(p.y)) best = std::min(best, dist2(p, x, y, z));
    float d2 = -1.0f;
    const int i = tree.nearest(x, y, z, bound, d2);
    if (best <= bound) {
      ASSERT_GE(i, 0) << n;
      EXPECT_EQ(d2, best) << n;
      EXPECT_EQ(dist2((*cloud)[i], x, y, z), best) << n;
      // Inclusive: the bound set to the nearest distance itself still finds it.
      EXPECT_EQ(tree.nearest(x, y, z, best, d2), i) << n;
      ++found;
    } else {
      EXPECT_EQ(i, -1) << n;
      ++none;
    }
  }
  EXPECT_GT(found, 500);  // both outcomes are exercised
  EXPECT_GT(none, 200);
  float unused = 0.0f;
  EXPECT_EQ(tree.nearest(std::numeric_limits<float>::quiet_NaN(), 0.0f, 0.0f, 1.0f, unused), -1);
}

// FlatKdTree3::within: every row strictly within the bound once, with nearest()'s squared
// distance, none beyond it; on a cloud with NaN points and on the grid with duplicates, whose
// points lie at exactly the bound from many queries (the fold snap's band takes the least of
// these from every border point instead of a search per point).
TEST(KdTree, WithinVisitsEveryRowBelowTheBoundOnce) {
  for (int c = 0; c < 2; ++c) {
    const Cloud::Ptr cloud = c == 0 ? randomCloud(3000, 8, true) : gridWithDuplicates();
    pcl_animseg::KdTree<pcl::PointNormal> tree;
    tree.setInputCloud(cloud);
    const pcl_animseg::FlatKdTree3& ft = tree.flatTree();
    std::mt19937 rng(9);
    std::uniform_real_distribution<float> u(-1.0f, 12.0f);
    std::size_t hits = 0, ties = 0;
    for (int n = 0; n < 300; ++n) {
      const pcl::PointNormal& at = (*cloud)[static_cast<std::size_t>(n * 7) % cloud->size()];
      float q[3] = {at.x, at.y, at.z};
      if (c == 0 && (n % 2 || !std::isfinite(at.y))) q[0] = u(rng) / 6.0f, q[1] = 0.0f, q[2] = 0.1f;
      if (c == 1 && n % 3 == 1) q[0] += 0.5f, q[1] += 0.5f;  // a cell's edge midpoint
      if (!std::isfinite(q[1])) continue;
      const float bound2 = c == 0 ? 0.04f : 2.0f;
      std::vector<int> seen(ft.size(), 0), leaf_of(ft.size());
      for (std::size_t i = 0; i < ft.size(); ++i) leaf_of[ft.leafRows()[i]] = static_cast<int>(i);
      float least = std::numeric_limits<float>::infinity();
      ft.within(q, bound2, [&](float d2, int row) {
        ++seen[row];
        EXPECT_LT(d2, bound2);
        EXPECT_EQ(d2, pcl_animseg::FlatKdTree3::distance2(
                          q, &ft.leafPoints()[3 * static_cast<std::size_t>(leaf_of[row])]));
        least = std::min(least, d2);
      });
      for (std::size_t i = 0; i < ft.size(); ++i) {
        const float d2 = pcl_animseg::FlatKdTree3::distance2(q, &ft.leafPoints()[3 * i]);
        const int row = ft.leafRows()[i];
        EXPECT_EQ(seen[row], d2 < bound2 ? 1 : 0) << c << " " << n << " row " << row;
        hits += d2 < bound2;
        ties += d2 == least;
      }
      // The least of them is nearest()'s distance within the bound.
      float nd2 = -1.0f;
      const int nearest = ft.nearest(q, bound2, nd2);
      if (std::isfinite(least)) {
        ASSERT_GE(nearest, 0);
        EXPECT_EQ(nd2, least);
      } else {
        EXPECT_EQ(nearest, -1);
      }
    }
    EXPECT_GT(hits, 300u) << c;
    if (c == 1) EXPECT_GT(ties, 300u);  // points at one distance, many at the bound itself
  }
}

// nearest() with a guess (an ICP's match of the iteration before): the point and distance of
// nearest() without one, whatever the guess (the true nearest point, a near one, a far one,
// beyond the bound, a NaN point), also among ties: the grid with duplicates, queried at its
// points, cell centres and edge midpoints and at random places.
TEST(KdTree, NearestWithAGuessIsNearest) {
  const Cloud::Ptr cloud = gridWithDuplicates();
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> u(-1.0f, 13.0f);
  std::uniform_int_distribution<int> any(0, static_cast<int>(cloud->size()) - 1);
  int tied_queries = 0, guesses = 0;
  for (int n = 0; n < 3000; ++n) {
    float q[3];
    if (n % 3 == 0) {  // on the grid's half steps: ties
      for (float& c : q)
        c = 0.5f * static_cast<float>(std::uniform_int_distribution<int>(0, 22)(rng));
    } else {
      for (float& c : q) c = u(rng);
    }
    const float bound = n % 5 == 0 ? 0.3f : 4.0f;
    float d_plain = -1.0f;
    const int plain = tree.nearest(q[0], q[1], q[2], bound, d_plain);
    std::vector<int> idx;
    std::vector<float> d2;
    tree.nearestKSearch(q[0], q[1], q[2], 2, idx, d2);
    tied_queries += d2.size() == 2 && d2[0] == d2[1];
    const int knn_first = idx.empty() ? -1 : idx[0];
    for (int hint : {-1, plain, knn_first, any(rng), any(rng)}) {
      float d = -1.0f;
      const int got = tree.nearest(q[0], q[1], q[2], bound, hint, d);
      ASSERT_EQ(got, plain) << n << " hint " << hint;
      if (plain >= 0) EXPECT_EQ(d, d_plain) << n;
      ++guesses;
    }
  }
  EXPECT_GT(tied_queries, 300);
  EXPECT_EQ(guesses, 15000);
}

// Several points at exactly the same place (duplicates in merged scans): every one of them is
// returned by the k-NN and radius queries, and the nearest is one of them.
TEST(KdTree, DuplicatePoints) {
  Cloud::Ptr cloud = randomCloud(300, 8, false);
  for (int r = 0; r < 40; ++r) cloud->push_back((*cloud)[17]);
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  std::vector<int> idx;
  std::vector<float> d2;
  ASSERT_EQ(tree.nearestKSearch((*cloud)[17], 41, idx, d2), 41);
  for (float d : d2) EXPECT_EQ(d, 0.0f);
  EXPECT_TRUE(std::is_sorted(idx.begin(), idx.end()));  // equal distances: lower index first
  EXPECT_EQ(idx.front(), 17);
  ASSERT_EQ(tree.radiusSearch((*cloud)[17], 1e-6, idx, d2), 41);
  float d = -1.0f;
  const int i = tree.nearest((*cloud)[17].x, (*cloud)[17].y, (*cloud)[17].z, 0.0f, d);
  EXPECT_TRUE(i == 17 || i >= 300) << i;
  EXPECT_EQ(d, 0.0f);
}

// nearestFirst: without a tie, the first point of every k-NN; with one (equal distances), it says
// so, and the k-NN's first lies at the same distance. An integer grid with duplicates and NaN
// points, queried at grid points, cell centres and edge midpoints (2, 4 and 8 equidistant
// points) and at random places.
TEST(KdTree, NearestFirstIsTheFirstOfTheKnn) {
  const Cloud::Ptr cloud = gridWithDuplicates();
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-1.0f, 12.0f);
  std::vector<pcl::PointNormal> queries;
  for (int x = 0; x < 11; ++x)
    for (int y = 0; y < 11; ++y)
      for (int z = 0; z < 3; ++z)
        for (float o : {0.0f, 0.5f}) {
          pcl::PointNormal q;
          q.x = static_cast<float>(x) + o;
          q.y = static_cast<float>(y) + o;
          q.z = static_cast<float>(z) + (x % 2 ? o : 0.0f);
          queries.push_back(q);
        }
  for (int i = 0; i < 2000; ++i) {
    pcl::PointNormal q;
    q.x = u(rng), q.y = u(rng), q.z = u(rng) / 3.0f;
    queries.push_back(q);
  }
  std::vector<int> idx;
  std::vector<float> d2;
  int ties = 0;
  for (const auto& q : queries)
    for (int k : {2, 8}) {
      ASSERT_EQ(tree.nearestKSearch(q, k, idx, d2), k);
      float d = -1.0f;
      bool tied = true;
      const int first = tree.nearestFirst(q, d, tied);
      EXPECT_EQ(d, d2[0]);
      EXPECT_EQ(tied, d2[0] == d2[1]) << q.x << " " << q.y << " " << q.z << " k " << k;
      if (tied)
        ++ties;
      else
        EXPECT_EQ(first, idx[0]) << q.x << " " << q.y << " " << q.z << " k " << k;
    }
  EXPECT_GT(ties, 500);  // ties are exercised
  EXPECT_LT(ties, static_cast<int>(queries.size()));  // and so are the others
  float d = 0.0f;
  bool tied = true;
  pcl::PointNormal nan_q;
  nan_q.x = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(tree.nearestFirst(nan_q, d, tied), -1);
  EXPECT_FALSE(tied);
  pcl_animseg::KdTree<pcl::PointNormal> empty;
  EXPECT_EQ(empty.nearestFirst(queries[0], d, tied), -1);
}

TEST(KdTree, EdgeCases) {
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  std::vector<int> idx;
  std::vector<float> d2;
  pcl::PointNormal q;
  q.x = q.y = q.z = 0.0f;
  EXPECT_EQ(tree.nearestKSearch(q, 3, idx, d2), 0);  // no cloud yet
  const Cloud::Ptr cloud = randomCloud(4, 3, false);
  tree.setInputCloud(cloud);
  EXPECT_EQ(tree.nearestKSearch(q, 10, idx, d2), 4);  // k larger than the cloud
  EXPECT_TRUE(std::is_sorted(d2.begin(), d2.end()));
  q.x = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(tree.nearestKSearch(q, 1, idx, d2), 0);
  EXPECT_EQ(tree.radiusSearch(q, 1.0, idx, d2), 0);
  Cloud::Ptr all_nan(new Cloud(*cloud));
  for (auto& p : all_nan->points) p.z = std::numeric_limits<float>::quiet_NaN();
  tree.setInputCloud(all_nan);
  q.x = 0.0f;
  EXPECT_EQ(tree.size(), 0u);
  EXPECT_EQ(tree.nearestKSearch(q, 1, idx, d2), 0);
}

TEST(KdTree, ThreadSafeQueries) {
  const Cloud::Ptr cloud = randomCloud(20000, 4, false);
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(cloud);
  std::vector<int> nearest(cloud->size(), -1);
#pragma omp parallel for
  for (int i = 0; i < static_cast<int>(cloud->size()); ++i) {
    std::vector<int> idx;
    std::vector<float> d2;
    tree.nearestKSearch((*cloud)[i], 1, idx, d2);
    nearest[i] = idx.empty() ? -1 : idx[0];
  }
  for (int i = 0; i < static_cast<int>(cloud->size()); ++i) EXPECT_EQ(nearest[i], i);
}

TEST(SearchKdTree, IcpFindsTheSameMotionAsWithPclsTree) {
  const Cloud::Ptr source = randomCloud(3000, 5, false);
  Eigen::Affine3f motion = Eigen::Affine3f::Identity();
  motion.translate(Eigen::Vector3f(0.05f, -0.03f, 0.02f));
  motion.rotate(Eigen::AngleAxisf(0.05f, Eigen::Vector3f::UnitZ()));
  Cloud::Ptr target(new Cloud);
  pcl::transformPointCloudWithNormals(*source, *target, motion);
  Cloud out;
  pcl::IterativeClosestPoint<pcl::PointNormal, pcl::PointNormal> a, b;
  for (auto* icp : {&a, &b}) {
    icp->setInputSource(source);
    icp->setInputTarget(target);
    icp->setMaximumIterations(50);
  }
  auto tree = std::make_shared<pcl_animseg::SearchKdTree<pcl::PointNormal>>();
  tree->setInputCloud(target);
  b.setSearchMethodTarget(tree, true);
  a.align(out);
  b.align(out);
  EXPECT_TRUE(a.getFinalTransformation().isApprox(b.getFinalTransformation(), 1e-6f));
  EXPECT_TRUE(b.getFinalTransformation().isApprox(motion.matrix(), 1e-3f));
  EXPECT_NEAR(a.getFitnessScore(), b.getFitnessScore(), 1e-9);
}
