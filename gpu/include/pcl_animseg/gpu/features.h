#pragma once
/** \file features.h Section 3.1's scale space and signatures on the GPU
 * (pcl_animseg::FeatureDevice for computeSequenceFeatures). */
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>

#include <memory>

namespace pcl_animseg {
namespace gpu {

/** \brief Computes a block's scale spaces and signatures on the GPU, point by point as
 * MLSScaleSpace and SignatureEstimation do: the neighbour rows are the CPU's bit for bit (the same
 * grid, distances and order); levels and signatures agree with the CPU's up to the last bits of
 * exp, atan2, cos and sin, whose CUDA versions differ from the C library's now and then (a fit
 * near a threshold can then take another branch; see test_gpu_features for how close they are).
 * The CPU meanwhile searches the rows the keypoint detector needs. Levels above 0 carry no
 * curvature (0; the detector does not read it). Layouts with S > 32, S' > 16 or R' S' > 64 are
 * refused (Error). Throws Error on any CUDA failure (no GPU, out of memory). */
class FeatureDevice : public pcl_animseg::FeatureDevice {
 public:
  FeatureDevice();
  ~FeatureDevice() override;
  void scaleSpaces(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                   const std::vector<ScaleSpacePlan>& plans, const MultiscaleParams& p, bool rows,
                   std::vector<ScaleSpace>& spaces) override;
  void signature(std::size_t t, Eigen::MatrixXf& out) const override;
  /** \brief The keypoints' Newton steps on the device, a block of threads a keypoint. */
  const KeypointRefineDevice* keypointRefiner() const override { return &refiner_; }

  /** \brief The device's neighbour rows of the last block's frame t, as radiusNeighbourhoods
   * returns them (for tests). */
  Neighbourhoods rows(std::size_t t) const;

 private:
  class Refiner : public KeypointRefineDevice {
   public:
    void refine(KeypointRefineJobs& jobs) const override;
  };
  struct Impl;
  std::unique_ptr<Impl> impl_;
  Refiner refiner_;
};

}  // namespace gpu
}  // namespace pcl_animseg
