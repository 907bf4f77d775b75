#pragma once
/** \file task_graph.h Tasks that depend on each other, run on every OpenMP thread. */
#include <omp.h>
#include <pcl_animseg/error.h>

#include <algorithm>
#include <condition_variable>
#include <cstddef>
#include <exception>
#include <mutex>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief Runs tasks 0..n-1 once each on the OpenMP threads, each as soon as every task it
 * depends on has finished (no barrier between "levels": a level with fewer tasks than threads
 * does not leave the other threads waiting for its slowest task).
 *
 * - `successors[i]`: the tasks that depend on task i (a task listed twice depends on i twice,
 *   which changes nothing).
 * - `priority[i]`: among the tasks ready to run, the smallest priority (then the smallest index)
 *   starts first. Give the order of a serial run, so that the tasks on the longest chain go
 *   first.
 * - `run(i)` runs task i, on any thread. The results are the same on any number of threads
 *   when `run` reads only what the tasks it depends on (and no others) have written.
 * - `finished(i)` is called after `run(i)`, one call at a time (under the graph's lock; for
 *   progress reports).
 *
 * An exception thrown by `run` stops the graph (tasks already running finish) and is rethrown
 * here; a cycle throws pcl_animseg::Error instead of waiting forever. Called inside a parallel
 * region it runs on that one thread. Written by us: OpenMP's `depend` clauses need the
 * dependencies at compile time or one task construct per edge, and Boost's graph library has no
 * executor. */
template <class Run, class Finished>
void runTaskGraph(const std::vector<std::vector<int>>& successors,
                  const std::vector<long>& priority, Run run, Finished finished) {
  const int n = static_cast<int>(successors.size());
  if (priority.size() != successors.size())
    throw Error("task graph: one priority per task expected");
  if (n == 0) return;
  std::vector<int> pending(n, 0);
  for (const std::vector<int>& s : successors)
    for (int j : s) {
      if (j < 0 || j >= n) throw Error("task graph: a successor out of range");
      ++pending[j];
    }
  // A min-heap on (priority, index).
  auto later = [&](int a, int b) {
    return priority[a] > priority[b] || (priority[a] == priority[b] && a > b);
  };
  std::vector<int> ready;
  for (int i = 0; i < n; ++i)
    if (pending[i] == 0) ready.push_back(i);
  std::make_heap(ready.begin(), ready.end(), later);
  std::mutex mutex;
  std::condition_variable wake;
  int done = 0, running = 0;
  bool stop = false;
  std::exception_ptr error;
#pragma omp parallel
  {
    std::unique_lock<std::mutex> lock(mutex);
    for (;;) {
      wake.wait(lock, [&] { return stop || done == n || !ready.empty() || running == 0; });
      if (stop || done == n) break;
      if (ready.empty()) {  // nothing runs, nothing is ready, tasks are left: a cycle
        stop = true;
        error = std::make_exception_ptr(Error("task graph: the dependencies form a cycle"));
        wake.notify_all();
        break;
      }
      std::pop_heap(ready.begin(), ready.end(), later);
      const int i = ready.back();
      ready.pop_back();
      ++running;
      lock.unlock();
      bool ok = true;
      try {
        run(i);
      } catch (...) {
        ok = false;
        lock.lock();
        if (!error) error = std::current_exception();
        stop = true;
      }
      if (ok) lock.lock();
      --running;
      if (ok) {
        ++done;
        finished(i);
        for (int j : successors[i])
          if (--pending[j] == 0) {
            ready.push_back(j);
            std::push_heap(ready.begin(), ready.end(), later);
          }
      }
      wake.notify_all();
    }
  }
  if (error) std::rethrow_exception(error);
}

/** \brief 0..n-1 (n = key.size()) ordered by key, ties in index order: a stable sort's order,
 * found by counting (the keys must lie in [0, keys): levels and depths of a task graph). */
inline std::vector<int> orderByKey(const std::vector<int>& key, int keys) {
  std::vector<int> first(static_cast<std::size_t>(std::max(keys, 0)) + 1, 0);
  for (int k : key) ++first[k + 1];
  for (int k = 0; k < keys; ++k) first[k + 1] += first[k];
  std::vector<int> order(key.size());
  for (int i = 0; i < static_cast<int>(key.size()); ++i) order[first[key[i]]++] = i;
  return order;
}

/** \brief The tasks of a graph (`successors` as for runTaskGraph) in waves: wave 0 holds the
 * tasks that depend on none, wave w those whose longest chain of dependencies has w tasks
 * before them; each wave in increasing task order. A device that runs a wave at once (one kernel
 * launch) needs only as many launches as the graph's longest chain. Throws Error on a cycle or
 * a successor out of range. */
inline std::vector<std::vector<int>> taskWaves(const std::vector<std::vector<int>>& successors) {
  const int n = static_cast<int>(successors.size());
  std::vector<int> pending(n, 0), wave_of(n, 0);
  for (const std::vector<int>& s : successors)
    for (int j : s) {
      if (j < 0 || j >= n) throw Error("task graph: a successor out of range");
      ++pending[j];
    }
  std::vector<int> order;  // Kahn's order: every task after the tasks it depends on
  order.reserve(n);
  for (int i = 0; i < n; ++i)
    if (pending[i] == 0) order.push_back(i);
  for (std::size_t k = 0; k < order.size(); ++k)
    for (int j : successors[order[k]]) {
      wave_of[j] = std::max(wave_of[j], wave_of[order[k]] + 1);
      if (--pending[j] == 0) order.push_back(j);
    }
  if (static_cast<int>(order.size()) != n) throw Error("task graph: the dependencies form a cycle");
  std::vector<std::vector<int>> waves;
  for (int i = 0; i < n; ++i) {
    if (wave_of[i] >= static_cast<int>(waves.size())) waves.resize(wave_of[i] + 1);
    waves[wave_of[i]].push_back(i);
  }
  return waves;
}

}  // namespace segmentation
}  // namespace pcl_animseg
