#include <pcl_animseg/error.h>
#include <pcl_animseg/segmentation/hierarchy.h>
#include <pcl_animseg/union_find.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <numeric>
#include <utility>

#include "mean_shift_internal.h"

namespace pcl_animseg {
namespace segmentation {

int HierarchyResult::levelClosestTo(int parts) const {
  int best = 0;
  for (int l = 1; l < levels(); ++l)
    if (std::abs(num_parts[l] - parts) < std::abs(num_parts[best] - parts)) best = l;
  return best;
}

namespace {

struct UnionFind {
  std::vector<int> parent;
  explicit UnionFind(int n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int find(int x) { return findRoot(parent, x); }
};

}  // namespace

void PersistenceHierarchy::compute(const SegmentationResult& input, HierarchyResult& out) const {
  const int k = input.num_clusters;
  if (k < 0) throw Error("hierarchy: negative cluster count");
  if (static_cast<int>(input.mode_density.size()) != k)
    throw Error("hierarchy: " + std::to_string(input.mode_density.size()) + " mode densities for " +
                std::to_string(k) + " clusters");
  if (!(params_.step > 0.0)) throw Error("hierarchy: the threshold step must be positive");
  if (params_.initial_factor < 0.0) throw Error("hierarchy: the initial factor must be >= 0");
  const int largest = detail::largestLabel(input.labels);
  if (largest >= k)
    throw Error("hierarchy: label " + std::to_string(largest) + " >= cluster count " +
                std::to_string(k));
  const int num_frames = static_cast<int>(input.labels.size());
  // A level's labels: `map` applied to every labelled point, the frames side by side.
  auto relabel = [&](const std::vector<int>* map) {
    std::vector<std::vector<int>> labels(input.labels.size());
#pragma omp parallel for schedule(static)
    for (int t = 0; t < num_frames; ++t) {
      const std::vector<int>& in = input.labels[t];
      std::vector<int>& o = labels[t];
      o.resize(in.size());
      for (std::size_t j = 0; j < in.size(); ++j) o[j] = map && in[j] >= 0 ? (*map)[in[j]] : in[j];
    }
    return labels;
  };

  // Region densities and the highest saddle between each pair of adjacent regions.
  std::vector<double> density = input.mode_density;
  std::map<std::pair<int, int>, double> saddle;
  for (const Saddle& s : input.saddles) {
    if (s.a < 0 || s.b < 0 || s.a >= k || s.b >= k)
      throw Error("hierarchy: saddle between unknown clusters " + std::to_string(s.a) + " and " +
                  std::to_string(s.b));
    if (s.a == s.b) continue;
    const auto key = std::minmax(s.a, s.b);
    auto it = saddle.find(key);
    if (it == saddle.end())
      saddle.emplace(key, s.density);
    else
      it->second = std::max(it->second, s.density);
  }
  auto rawPersistence = [&density](int a, int b, double s) {
    // Eq. 12's numerator: the lower mode's height above the saddle (>= 0 by definition; a
    // saddle estimated above a mode is clamped).
    return std::max(0.0, std::min(density[a], density[b]) - s);
  };
  double norm = 0.0;
  for (const auto& [key, s] : saddle)
    norm = std::max(norm, rawPersistence(key.first, key.second, s));
  if (norm <= 0.0) norm = 1.0;
  out = HierarchyResult();
  double mean_rp = 0.0;
  for (const Saddle& s : input.saddles) {
    const double rp = s.a == s.b ? 0.0 : rawPersistence(s.a, s.b, s.density) / norm;
    out.persistence.push_back(rp);
    mean_rp += rp;
  }
  if (!input.saddles.empty()) mean_rp /= static_cast<double>(input.saddles.size());

  out.labels.push_back(relabel(nullptr));
  out.num_parts.push_back(k);
  out.thresholds.push_back(0.0);

  // The motion method records its own coarser merges (cheapest first, cost = rigid-motion
  // residual of the union): those replace the saddles. A merge's persistence is its cost over the
  // largest cost (in [0, 1] like Eq. 12's RP) and a level applies the recorded merges, in their
  // order, while the next one is below the level's threshold, so the levels stay nested and
  // follow the motion method's own decisions (density saddles in the joint space say little about
  // whether two pieces move together: on a 48-frame humanoid the 15-part level had a pooled ARI of
  // 0.67 by saddles, against 0.90 at the 29 parts below it).
  std::vector<double> merge_rp;
  for (const ClusterMerge& m : input.merges) {
    if (m.a < 0 || m.b < 0 || m.a >= k || m.b >= k)
      throw Error("hierarchy: merge of unknown clusters " + std::to_string(m.a) + " and " +
                  std::to_string(m.b));
    merge_rp.push_back(m.cost);
  }
  const bool by_merges = !merge_rp.empty();
  if (by_merges) {
    const double top = *std::max_element(merge_rp.begin(), merge_rp.end());
    double mean = 0.0;
    for (double& c : merge_rp) {
      c = top > 0.0 ? std::max(0.0, c) / top : 0.0;
      mean += c / static_cast<double>(merge_rp.size());
    }
    mean_rp = mean;
  }
  std::size_t next_merge = 0;

  UnionFind uf(k);
  std::vector<int> prev_level_label(k);  // level label of each input cluster at the last level
  std::iota(prev_level_label.begin(), prev_level_label.end(), 0);
  int regions = k;
  double threshold = params_.initial_factor * mean_rp;
  int guard = 0;
  while (regions > 1 && static_cast<int>(out.labels.size()) <= params_.max_levels &&
         (by_merges ? next_merge < merge_rp.size() : !saddle.empty()) && guard++ < 100000) {
    int merges = 0;
    while (by_merges && next_merge < merge_rp.size() && merge_rp[next_merge] < threshold) {
      const ClusterMerge& m = input.merges[next_merge++];
      const int ra = uf.find(m.a), rb = uf.find(m.b);
      if (ra == rb) continue;
      uf.parent[std::max(ra, rb)] = std::min(ra, rb);
      --regions;
      ++merges;
    }
    for (; !by_merges;) {
      // The weakest remaining pair (ties broken by cluster ids: deterministic).
      auto weakest = saddle.end();
      double weakest_rp = std::numeric_limits<double>::infinity();
      for (auto it = saddle.begin(); it != saddle.end(); ++it) {
        const double rp = rawPersistence(it->first.first, it->first.second, it->second) / norm;
        if (rp < weakest_rp) {
          weakest_rp = rp;
          weakest = it;
        }
      }
      if (weakest == saddle.end() || !(weakest_rp < threshold)) break;
      const int keep = weakest->first.first;  // the smaller root id survives
      const int gone = weakest->first.second;
      saddle.erase(weakest);
      uf.parent[gone] = keep;
      density[keep] = std::max(density[keep], density[gone]);
      // Re-key the merged region's saddles; towards each neighbour keep the highest pass.
      std::map<std::pair<int, int>, double> next;
      for (const auto& [key, s] : saddle) {
        int a = key.first == gone ? keep : key.first;
        int b = key.second == gone ? keep : key.second;
        if (a == b) continue;
        const auto nk = std::minmax(a, b);
        auto it = next.find(nk);
        if (it == next.end())
          next.emplace(nk, s);
        else
          it->second = std::max(it->second, s);
      }
      saddle.swap(next);
      --regions;
      ++merges;
    }
    if (merges > 0 || !params_.skip_identical_levels) {
      // Emit a level: compact region ids in order of their smallest input cluster.
      std::vector<int> root_label(k, -1);
      std::vector<int> level_label(k);
      int next_id = 0;
      for (int c = 0; c < k; ++c) {
        const int r = uf.find(c);
        if (root_label[r] < 0) root_label[r] = next_id++;
        level_label[c] = root_label[r];
      }
      std::vector<int> parent(out.num_parts.back(), -1);
      for (int c = 0; c < k; ++c) parent[prev_level_label[c]] = level_label[c];
      out.parent.push_back(std::move(parent));
      out.labels.push_back(relabel(&level_label));
      out.num_parts.push_back(next_id);
      out.thresholds.push_back(threshold);
      prev_level_label = level_label;
    }
    threshold += params_.step;
  }
}

}  // namespace segmentation
}  // namespace pcl_animseg
