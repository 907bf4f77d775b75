#pragma once
/** \file chained_fit.h Per-frame fits chained along a sequence, with the frames in parallel. */
#include <cstddef>
#include <limits>
#include <vector>

namespace pcl_animseg {
namespace segmentation {

/** \brief One start of a frame's fit, and whether it depends on the fits of earlier frames. */
template <class Pose>
struct ChainStart {
  Pose pose;
  bool chained = false;
};

/** \brief Fits every frame 0..T-1 but `ref` (which gets `identity`), in order away from `ref`
 * (ref+1, ref+2, ..., then ref-1, ref-2, ...), each from the first of its starts with the lowest
 * score.
 *
 * - `starts(t, dir, fits)` returns frame t's starts in their order (a std::vector of
 *   ChainStart<Pose>; at least one). With `fits` null it must return only the unchained ones (the same poses in
 *   the same relative order); otherwise `(*fits)[t - dir]`, `(*fits)[t - 2 * dir]`, ... are final
 *   and the chained starts may use them.
 * - `score(t, pose)` scores a start (lower is better).
 * - `fitFrom(t, pose, score)` returns the fit from the winning start and its score.
 *
 * With `parallel` (and score and fitFrom pure functions of their arguments) the result is the
 * same, computed with the frames side by side: every frame is first fitted from the best of its
 * unchained starts, in parallel; then, frame by frame along the chain, the chained starts are
 * scored too, and only a frame whose winner is a chained start is fitted again. A chain is
 * otherwise serial: in the motion method a merged part's 48 frames were one thread's work while
 * the other cores waited. Written by us: the speculation is specific to this fit. */
template <class Pose, class Starts, class Score, class FitFrom>
std::vector<Pose> fitAlongChain(int T, int ref, const Pose& identity, Starts starts, Score score,
                                FitFrom fitFrom, bool parallel) {
  std::vector<Pose> fit(T > 0 ? T : 0, identity);
  constexpr double kNone = std::numeric_limits<double>::max();
  if (!parallel) {
    for (int dir : {+1, -1})
      for (int t = ref + dir; t >= 0 && t < T; t += dir) {
        const auto s = starts(t, dir, &fit);
        std::size_t best = 0;
        double r0 = kNone;
        for (std::size_t k = 0; k < s.size(); ++k) {
          const double r = score(t, s[k].pose);
          if (r < r0) r0 = r, best = k;
        }
        fit[t] = fitFrom(t, s[best].pose, r0);
      }
    return fit;
  }
  // Frame t's fit from its best unchained start (spec_k among the unchained, scored spec_r).
  std::vector<Pose> spec(fit.size(), identity);
  std::vector<double> spec_r(fit.size(), kNone);
  std::vector<std::size_t> spec_k(fit.size(), 0);
#pragma omp parallel for schedule(dynamic, 1)
  for (int t = 0; t < T; ++t) {
    if (t == ref) continue;
    const auto s = starts(t, t > ref ? +1 : -1, nullptr);
    if (s.empty()) continue;
    for (std::size_t k = 0; k < s.size(); ++k) {
      const double r = score(t, s[k].pose);
      if (r < spec_r[t]) spec_r[t] = r, spec_k[t] = k;
    }
    spec[t] = fitFrom(t, s[spec_k[t]].pose, spec_r[t]);
  }
  // An unchained start that lost to spec_k cannot win against it: it scores above it, or the same
  // and later in the order.
  constexpr double kLost = std::numeric_limits<double>::infinity();
  for (int dir : {+1, -1})
    for (int t = ref + dir; t >= 0 && t < T; t += dir) {
      const auto s = starts(t, dir, &fit);
      std::size_t best = 0, unchained = 0;
      double r0 = kNone;
      for (std::size_t k = 0; k < s.size(); ++k) {
        double r;
        if (s[k].chained)
          r = score(t, s[k].pose);
        else
          r = unchained++ == spec_k[t] ? spec_r[t] : kLost;
        if (r < r0) r0 = r, best = k;
      }
      fit[t] = s[best].chained ? fitFrom(t, s[best].pose, r0) : spec[t];
    }
  return fit;
}

}  // namespace segmentation
}  // namespace pcl_animseg
