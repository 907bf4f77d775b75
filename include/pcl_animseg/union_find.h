#pragma once
/** \file union_find.h The root of an element in a forest of parent links (union-find). */
#include <vector>

namespace pcl_animseg {

/** \brief Follows `parent` from `x` to its root (parent[r] == r) and points every element on
 * the way straight at the root (path compression), so that long chains are walked once. Only
 * the links change, never which root an element belongs to. Written by us: Boost's
 * disjoint_sets needs its own rank and parent maps, and the callers keep plain index arrays. */
inline int findRoot(std::vector<int>& parent, int x) {
  int r = x;
  while (parent[r] != r) r = parent[r];
  while (parent[x] != r) {
    const int next = parent[x];
    parent[x] = r;
    x = next;
  }
  return r;
}

}  // namespace pcl_animseg
