// runTaskGraph: every task once, after the tasks it depends on, the same results on any number of
// threads, errors rethrown, cycles refused.
#include <pcl_animseg/segmentation/task_graph.h>

#include <gtest/gtest.h>
#include <omp.h>

#include <atomic>
#include <cstdint>
#include <stdexcept>
#include <vector>

namespace {

using pcl_animseg::segmentation::runTaskGraph;

// A grid of `frames` x `width` tasks shaped like the tracking's: task (k, s) depends on (k-1, s)
// and on (k, s-1) and (k, s-2) (its "earlier levels").
std::vector<std::vector<int>> gridGraph(int frames, int width) {
  std::vector<std::vector<int>> succ(static_cast<std::size_t>(frames) * width);
  for (int k = 0; k < frames; ++k)
    for (int s = 0; s < width; ++s) {
      const int i = k * width + s;
      if (k + 1 < frames) succ[i].push_back(i + width);
      if (s + 1 < width) succ[i].push_back(i + 1);
      if (s + 2 < width) succ[i].push_back(i + 2);
    }
  return succ;
}

// Each task's value mixes its predecessors' values (order-sensitive, as floating-point sums are).
std::vector<std::uint64_t> runGrid(int frames, int width, int threads) {
  const auto succ = gridGraph(frames, width);
  std::vector<std::vector<int>> pred(succ.size());
  for (std::size_t i = 0; i < succ.size(); ++i)
    for (int j : succ[i]) pred[j].push_back(static_cast<int>(i));
  std::vector<long> priority(succ.size());
  for (std::size_t i = 0; i < succ.size(); ++i) priority[i] = static_cast<long>(i);
  std::vector<std::uint64_t> value(succ.size(), 0);
  const int before = omp_get_max_threads();
  omp_set_num_threads(threads);
  runTaskGraph(
      succ, priority,
      [&](int i) {
        std::uint64_t v = 1469598103934665603ull ^ static_cast<std::uint64_t>(i);
        for (int p : pred[i]) v = (v ^ value[p]) * 1099511628211ull;
        value[i] = v;
      },
      [](int) {});
  omp_set_num_threads(before);
  return value;
}

TEST(TaskGraph, EveryTaskRunsOnceAfterTheTasksItDependsOn) {
  const int frames = 12, width = 40;
  const auto succ = gridGraph(frames, width);
  const int n = static_cast<int>(succ.size());
  std::vector<long> priority(n);
  for (int i = 0; i < n; ++i) priority[i] = (i * 7919) % 101;  // an order unrelated to the edges
  std::atomic<int> clock{0};
  std::vector<int> started(n, -1), ended(n, -1), runs(n, 0);
  int finished_calls = 0;
  const int before = omp_get_max_threads();
  omp_set_num_threads(4);
  runTaskGraph(
      succ, priority,
      [&](int i) {
        started[i] = clock++;
        ++runs[i];
        volatile double x = 0;  // some work, so that tasks overlap
        for (int r = 0; r < 2000; ++r) x = x + r * 1e-9;
        ended[i] = clock++;
      },
      [&](int) { ++finished_calls; });
  omp_set_num_threads(before);
  EXPECT_EQ(finished_calls, n);
  for (int i = 0; i < n; ++i) {
    ASSERT_EQ(runs[i], 1) << "task " << i;
    for (int j : succ[i]) EXPECT_LT(ended[i], started[j]) << i << " -> " << j;
  }
}

TEST(TaskGraph, SameResultsOnAnyThreadCount) {
  const auto one = runGrid(20, 30, 1);
  EXPECT_EQ(runGrid(20, 30, 2), one);
  EXPECT_EQ(runGrid(20, 30, 7), one);
}

TEST(TaskGraph, ReadyTasksStartInPriorityOrder) {
  // No edges: on one thread the tasks run by priority, then by index.
  std::vector<std::vector<int>> succ(6);
  const std::vector<long> priority{5, 1, 3, 1, 0, 9};
  std::vector<int> order;
  const int before = omp_get_max_threads();
  omp_set_num_threads(1);
  runTaskGraph(succ, priority, [&](int i) { order.push_back(i); }, [](int) {});
  omp_set_num_threads(before);
  EXPECT_EQ(order, (std::vector<int>{4, 1, 3, 2, 0, 5}));
}

TEST(TaskGraph, AnErrorInATaskIsRethrownAndItsSuccessorsDoNotRun) {
  const auto succ = gridGraph(5, 10);
  std::vector<long> priority(succ.size(), 0);
  std::vector<std::atomic<int>> ran(succ.size());
  for (auto& r : ran) r = 0;
  EXPECT_THROW(runTaskGraph(
                   succ, priority,
                   [&](int i) {
                     ran[i] = 1;
                     if (i == 13) throw std::runtime_error("task 13 failed");
                   },
                   [](int) {}),
               std::runtime_error);
  EXPECT_EQ(ran[13 + 10].load(), 0);  // the same sample in the next frame
  EXPECT_EQ(ran[49].load(), 0);       // the last task
}

TEST(TaskGraph, ACycleIsAnErrorNotAHang) {
  std::vector<std::vector<int>> succ{{1}, {2}, {1}, {}};
  std::vector<long> priority(4, 0);
  EXPECT_THROW(runTaskGraph(succ, priority, [](int) {}, [](int) {}), pcl_animseg::Error);
  EXPECT_THROW(runTaskGraph(succ, std::vector<long>(3, 0), [](int) {}, [](int) {}),
               pcl_animseg::Error);
  EXPECT_THROW(runTaskGraph({{5}}, {0}, [](int) {}, [](int) {}), pcl_animseg::Error);
  // Nothing to do is fine.
  EXPECT_NO_THROW(runTaskGraph({}, {}, [](int) {}, [](int) {}));
}

}  // namespace
