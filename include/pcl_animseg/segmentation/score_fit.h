#pragma once
/** \file score_fit.h The winner of a score batch's frame, written once for the CPU and the GPU
 * (chained_fit.h's fitChainsBatched and MotionDevice::scoreAndFit; the CUDA module's score-and-fit
 * kernels read this). No Eigen, no OpenMP: nvcc reads this. */
#include <cfloat>
#include <cstddef>

#ifdef __CUDACC__
#define PCL_ANIMSEG_SCORE_FIT_HD __host__ __device__
#else
#define PCL_ANIMSEG_SCORE_FIT_HD
#endif

namespace pcl_animseg {
namespace segmentation {

/** \brief The winner of one frame's starts from their scores (`scores`, `place`: its `count`
 * scored starts, places rising) and its base (a start scored before, at place base_place with
 * score base_score; none where base_place < 0): the index among its scored starts of the first of
 * the lowest score by place, -1 where the base (or a place that is not scored) wins; `r0` its
 * score (the largest double where no score is below it, and then place 0 wins).
 * fitChainsBatched's choice. */
PCL_ANIMSEG_SCORE_FIT_HD inline int scoreFitWinner(const double* scores, const int* place,
                                                   std::size_t count, double base_score,
                                                   int base_place, double& r0) {
  r0 = DBL_MAX;
  int best_place = 0;
  bool base_done = base_place < 0;
  for (std::size_t k = 0; k <= count; ++k) {
    if (!base_done && (k == count || base_place < place[k])) {
      base_done = true;
      if (base_score < r0) r0 = base_score, best_place = base_place;
    }
    if (k < count && scores[k] < r0) r0 = scores[k], best_place = place[k];
  }
  for (std::size_t k = 0; k < count; ++k)
    if (place[k] == best_place) return static_cast<int>(k);
  return -1;
}

}  // namespace segmentation
}  // namespace pcl_animseg
