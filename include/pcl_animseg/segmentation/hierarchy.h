#pragma once
/** \file hierarchy.h Hierarchical decomposition by region persistence (Sect. 5 of the paper). */
#include <pcl_animseg/segmentation/segmentation_result.h>

#include <memory>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief Knobs of PersistenceHierarchy. */
struct HierarchyParams {
  /** First threshold RP_δ = initial_factor · mean(RP) (the paper: 0.4). */
  double initial_factor = 0.4;
  /** RP_δ is raised by this much per level (the paper: 0.05 to 0.1; RP is normalised to [0, 1]). */
  double step = 0.05;
  /** At most this many levels above level 0. */
  int max_levels = 16;
  /** When a raised threshold merges nothing, keep raising it (instead of emitting a level equal
   * to the previous one), so that every level has fewer parts than the one below. */
  bool skip_identical_levels = true;
};

/** \brief Levels A0 (input) .. Am of a nested decomposition. */
struct HierarchyResult {
  /** labels[level][frame][point]; level 0 is the input labels (compacted to 0..parts-1 only in
   * levels >= 1; level 0 keeps the input's label values). */
  std::vector<std::vector<std::vector<int>>> labels;
  /** Parts per level (level 0: the input's num_clusters). */
  std::vector<int> num_parts;
  /** parent[i][l] is the level-(i+1) label of level-i label l (size levels - 1). */
  std::vector<std::vector<int>> parent;
  /** RP_δ used to build each level (0 for level 0). */
  std::vector<double> thresholds;
  /** The region persistence (Eq. 12) of each input saddle, same order as the input saddles. */
  std::vector<double> persistence;

  int levels() const { return static_cast<int>(labels.size()); }
  /** \brief The level whose part count is closest to `parts` (the finest among ties). */
  int levelClosestTo(int parts) const;
};

/** \brief Merges weakly separated neighbouring clusters level by level (no re-clustering).
 *
 * Region persistence of adjacent clusters i, j with f(y_i) >= f(y_j) and saddle s_ij (Eq. 12):
 *   RP_ij = (f(y_j) - f(s_ij)) / max_{k,l} (f(y_l) - f(s_kl)).
 * A merged region takes the max of its members' mode densities and, towards a neighbour, the max
 * of its members' saddle densities (the highest pass between the two regions), so RP between
 * merged regions follows from the same formula. Within a level the weakest pair is merged first
 * and the affected persistences are recomputed (union-find), until none is below RP_δ.
 */
class PersistenceHierarchy {
 public:
  using Ptr = std::shared_ptr<PersistenceHierarchy>;
  using ConstPtr = std::shared_ptr<const PersistenceHierarchy>;

  void setParams(const HierarchyParams& params) { params_ = params; }
  const HierarchyParams& getParams() const { return params_; }

  /** \brief Builds the hierarchy from `input` (labels, num_clusters, mode_density, saddles).
   * When `input.merges` is not empty (the motion method's recorded coarser merges), the levels
   * apply those merges in their order instead, with the merge cost over the largest cost in
   * place of RP (same thresholds: initial_factor · mean, raised by step). Throws
   * pcl_animseg::Error on inconsistent input (a saddle or merge naming an unknown cluster, ...). */
  void compute(const SegmentationResult& input, HierarchyResult& output) const;

 private:
  HierarchyParams params_;
};

}  // namespace segmentation
}  // namespace pcl_animseg
