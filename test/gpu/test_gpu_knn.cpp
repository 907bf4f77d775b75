// gpu::RigidFits::knn against FlatKdTree3::knn: the same rows, squared distances and order for
// every query (k = 1 too, FlatKdTree3's nearest point without a bound), on a grid (many points at
// exactly equal distances: the ties decide the order and which points make the last slots) and on
// scattered points, with trees smaller than k. And RigidFits::motionResiduals against the CPU's
// motion check on the same kept trees, and RigidFits::leastDistances (the fold snap's distances
// around the border points) against FlatKdTree3::within. Skips when no usable GPU is present.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/rigid_fits.h>

#include <cmath>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "segmentation/cpu_rigid_device.h"

namespace gpu = pcl_animseg::gpu;

namespace {

pcl_animseg::FlatKdTree3 treeOf(const std::vector<float>& xyz) {
  pcl_animseg::FlatKdTree3 t;
  t.build(xyz.data(), xyz.size() / 3);
  return t;
}

}  // namespace

TEST(GpuKnn, SameListsAsTheCpuTree) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float> grid, scattered, tiny{0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 2.f, 0.f};
  for (int x = 0; x < 30; ++x)
    for (int y = 0; y < 30; ++y)
      for (int z = 0; z < 4; ++z) grid.insert(grid.end(), {0.1f * x, 0.1f * y, 0.1f * z});
  for (int i = 0; i < 20000; ++i) scattered.insert(scattered.end(), {u(rng), u(rng), u(rng)});
  const std::vector<pcl_animseg::FlatKdTree3> trees{treeOf(grid), treeOf(scattered), treeOf(tiny)};
  const std::vector<const pcl_animseg::FlatKdTree3*> ptrs{&trees[0], &trees[1], &trees[2]};
  const std::vector<const std::vector<float>*> tree_points{&grid, &scattered, &tiny};
  // Queries: every grid point (ties everywhere), random points, and points of the tiny tree.
  std::vector<float> queries;
  std::vector<int> tree_of;
  for (std::size_t i = 0; i < grid.size(); i += 3) {
    queries.insert(queries.end(), {grid[i], grid[i + 1], grid[i + 2]});
    tree_of.push_back(0);
  }
  for (int i = 0; i < 5000; ++i) {
    queries.insert(queries.end(), {u(rng), u(rng), u(rng)});
    tree_of.push_back(i % 2 ? 1 : 0);
  }
  for (int i = 0; i < 10; ++i) {
    queries.insert(queries.end(), {u(rng), u(rng), 0.0f});
    tree_of.push_back(2);
  }
  gpu::RigidFits device;
  for (int k : {1, 2, 9, 16}) {  // k = 1: nearest() without a bound (the walk's first of ties)
    std::vector<int> rows, count;
    ASSERT_TRUE(device.knn(ptrs, k, queries, tree_of, rows, count));
    ASSERT_EQ(count.size(), tree_of.size());
    int differ = 0;
    std::vector<int> r;
    std::vector<float> d;
    for (std::size_t q = 0; q < tree_of.size(); ++q) {
      const int n = trees[tree_of[q]].knn(&queries[3 * q], k, r, d);
      bool same = count[q] == n;
      // The distances the caller computes (FlatKdTree3::distance2 of the query and the row's
      // point) are the tree's.
      const auto& pts = tree_points[tree_of[q]];
      for (int i = 0; same && i < n; ++i)
        same = rows[q * k + i] == r[i] &&
               pcl_animseg::FlatKdTree3::distance2(&queries[3 * q], &(*pts)[3 * r[i]]) == d[i];
      differ += !same;
    }
    EXPECT_EQ(differ, 0) << "k " << k << ": " << differ << " of " << tree_of.size()
                         << " lists differ";
  }
  // k outside 1..32: not offered, the caller searches on the CPU.
  std::vector<int> rows, count;
  EXPECT_FALSE(device.knn(ptrs, 0, queries, tree_of, rows, count));
  EXPECT_FALSE(device.knn(ptrs, 33, queries, tree_of, rows, count));
  std::vector<int> bad = tree_of;
  bad[0] = 3;
  EXPECT_THROW(device.knn(ptrs, 9, queries, bad, rows, count), pcl_animseg::Error);
  // Trees kept on the device (keepKnnTrees): the same lists from knnOn, call after call, and
  // after a knn() of other trees; a token whose trees were replaced is refused (the caller calls
  // knn()).
  const long long token = device.keepKnnTrees(ptrs);
  ASSERT_GT(token, 0);
  std::vector<int> again, again_count;
  for (int k : {9, 1}) {
    const long long kept = device.keepKnnTrees(ptrs);
    // A search of trees of its own (knn) leaves the kept ones kept.
    ASSERT_TRUE(device.knn(ptrs, k, queries, tree_of, rows, count));
    ASSERT_TRUE(device.knnOn(kept, k, queries, tree_of, again, again_count));
    EXPECT_EQ(again, rows);
    EXPECT_EQ(again_count, count);
    ASSERT_TRUE(device.knnOn(kept, k, queries, tree_of, again, again_count));
    EXPECT_EQ(again, rows);
  }
  EXPECT_FALSE(device.knnOn(token, 9, queries, tree_of, again, again_count));
  const long long dropped = device.keepKnnTrees(ptrs);
  device.dropKnnTrees(dropped);
  EXPECT_FALSE(device.knnOn(dropped, 9, queries, tree_of, again, again_count));
  EXPECT_THROW(device.knnOn(device.keepKnnTrees(ptrs), 9, queries, bad, again, again_count),
               pcl_animseg::Error);
}

// The refinement's motion check on the GPU (a thread per residual, each copy's nearest point in
// the kept trees) against the CPU's (CpuRigidDevice::cpuMotionResiduals, the refinement's loop on
// the cores: GMMRefinement.MotionCheckOnTheDeviceIsTheCoresBitForBit): the same floats for every
// residual, copies far from every point (capped) and motions marked invalid among them; a token
// that is no longer kept is declined, jobs that do not match the trees are an error.
TEST(GpuKnn, MotionCheckIsTheCpus) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  namespace seg = pcl_animseg::segmentation;
  const int parts = 4;
  const animseg_test::MotionCheckCase mc =
      animseg_test::randomMotionCheck(11, 6, parts, 3000, 500, 20000);
  const auto& trees = mc.trees;
  const seg::MotionCheckJobs& jobs = mc.jobs;
  const std::vector<float> expected = animseg_test::CpuRigidDevice::cpuMotionResiduals(trees, jobs);
  std::vector<const pcl_animseg::FlatKdTree3*> ptrs;
  for (const auto& t : trees) ptrs.push_back(&t);
  gpu::RigidFits device;
  const long long token = device.keepKnnTrees(ptrs);
  ASSERT_GT(token, 0);
  std::vector<float> got;
  ASSERT_TRUE(device.motionResiduals(token, jobs, got));
  ASSERT_EQ(got.size(), expected.size());
  int differ = 0, capped = 0, none = 0;
  for (std::size_t r = 0; r < got.size(); ++r) {
    differ += got[r] != expected[r];
    capped += expected[r] == static_cast<float>(jobs.cap);
    none += expected[r] == 0.0f;
  }
  EXPECT_EQ(differ, 0) << differ << " of " << got.size() << " residuals differ";
  EXPECT_GT(capped, 0);  // far copies: every term capped
  EXPECT_EQ(none, 0);
  // Jobs that do not match the kept trees: an error, not a wrong answer.
  seg::MotionCheckJobs short_normals = jobs;
  short_normals.normals.pop_back();
  EXPECT_THROW(device.motionResiduals(token, short_normals, got), pcl_animseg::Error);
  seg::MotionCheckJobs bad_part = jobs;
  bad_part.part[5] = parts;
  EXPECT_THROW(device.motionResiduals(token, bad_part, got), pcl_animseg::Error);
  // Trees no longer kept: declined (the caller scores on the CPU).
  device.dropKnnTrees(token);
  EXPECT_FALSE(device.motionResiduals(token, jobs, got));
}

// The fold snap's distances around the border points on the GPU (a query per thread, each row's
// least squared distance kept by an atomic minimum) against FlatKdTree3::within on the CPU
// (CpuRigidDevice::cpuLeastDistances, what the refinement's nearBorder computes): the same floats
// for every row of every tree, on a grid (many equal distances, rows exactly at the bound) and on
// scattered points, with non-finite queries (they reach nothing) and a tree no query reaches;
// a token no longer kept is declined, bounds or trees that do not match are an error.
TEST(GpuKnn, LeastDistancesAreTheCpus) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  std::mt19937 rng(13);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float> grid, scattered, lonely{5.f, 5.f, 5.f, 6.f, 5.f, 5.f};
  for (int x = 0; x < 40; ++x)
    for (int y = 0; y < 40; ++y)
      for (int z = 0; z < 3; ++z) grid.insert(grid.end(), {0.05f * x, 0.05f * y, 0.05f * z});
  for (int i = 0; i < 30000; ++i) scattered.insert(scattered.end(), {u(rng), u(rng), u(rng)});
  const std::vector<pcl_animseg::FlatKdTree3> trees{treeOf(grid), treeOf(scattered),
                                                    treeOf(lonely)};
  const std::vector<const pcl_animseg::FlatKdTree3*> ptrs{&trees[0], &trees[1], &trees[2]};
  // Queries: every 7th grid point (a border line's worth), random points, two non-finite ones.
  std::vector<float> queries;
  std::vector<int> tree_of;
  for (std::size_t i = 0; i < grid.size(); i += 3 * 7) {
    queries.insert(queries.end(), {grid[i], grid[i + 1], grid[i + 2]});
    tree_of.push_back(0);
  }
  for (int i = 0; i < 3000; ++i) {
    queries.insert(queries.end(), {u(rng), u(rng), u(rng)});
    tree_of.push_back(i % 3 ? 1 : 0);
  }
  const float nan = std::numeric_limits<float>::quiet_NaN();
  queries.insert(queries.end(), {nan, 0.f, 0.f, 0.f, std::numeric_limits<float>::infinity(), 0.f});
  tree_of.insert(tree_of.end(), {1, 0});
  // The grid's bound a little above 0.1^2 (squared distances of 0.1 exactly reached: strictly
  // below the bound), the scattered points' 0.02, the lonely tree's any (no query there).
  const std::vector<float> bound2{std::nextafter(0.01f, 1.0f), 0.02f, 1.0f};
  const std::vector<float> expected =
      animseg_test::CpuRigidDevice::cpuLeastDistances(trees, queries, tree_of, bound2);
  gpu::RigidFits device;
  const long long token = device.keepKnnTrees(ptrs);
  ASSERT_GT(token, 0);
  std::vector<float> got;
  ASSERT_TRUE(device.leastDistances(token, queries, tree_of, bound2, got));
  ASSERT_EQ(got.size(), expected.size());
  int differ = 0, reached = 0, zero = 0;
  for (std::size_t r = 0; r < got.size(); ++r) {
    differ += !(got[r] == expected[r]);
    reached += std::isfinite(expected[r]);
    zero += expected[r] == 0.0f;
  }
  EXPECT_EQ(differ, 0) << differ << " of " << got.size() << " rows differ";
  EXPECT_GT(reached, static_cast<int>(got.size()) / 4);  // the bounds reach many rows
  EXPECT_LT(reached, static_cast<int>(got.size()));      // and not all (the lonely tree)
  EXPECT_GT(zero, 0);                                    // the grid's queries are rows too
  // Bounds or trees that do not match the kept trees: an error, not a wrong answer.
  EXPECT_THROW(device.leastDistances(token, queries, tree_of, {0.01f, 0.02f}, got),
               pcl_animseg::Error);
  std::vector<int> bad = tree_of;
  bad[3] = 3;
  EXPECT_THROW(device.leastDistances(token, queries, bad, bound2, got), pcl_animseg::Error);
  // Trees no longer kept: declined (the caller searches on the CPU).
  device.dropKnnTrees(token);
  EXPECT_FALSE(device.leastDistances(token, queries, tree_of, bound2, got));
}
