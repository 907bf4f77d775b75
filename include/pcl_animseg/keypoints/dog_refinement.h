#pragma once
/** \file dog_refinement.h The constants of DoGKeypoint's sub-sample localisation (see
 * dog_keypoint.h), shared by the CPU's refinement (dog_keypoint.cpp) and the device's Newton
 * steps (gpu/src/features_kernels.cu), so that the two cannot drift apart. Plain constants: no
 * PCL or Eigen, includable by CUDA code. */

namespace pcl_animseg {
namespace dog_refinement {

/** The pair of scales of the refit, relative to the keypoint's scale h_i. */
constexpr double kInnerScale = 1.6817928305074290;  // 2^(3/4)
constexpr double kOuterScale = 2.0 * kInnerScale;
/** How far (in outer scales) the disc of samples reaches. */
constexpr double kDiscRadius = 2.0;
/** Balancing passes of the area weights. */
constexpr int kAreaPasses = 3;
/** Newton iterations, and the step (in h0) that ends them. */
constexpr int kNewtonSteps = 6;
constexpr double kConverged = 0.025;

}  // namespace dog_refinement
}  // namespace pcl_animseg
