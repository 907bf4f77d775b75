// computeSequenceFeatures in blocks of frames (bounded scale-space memory): the result must not
// depend on the block size, and each stage is recorded once with its time summed over blocks.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/features/signature.h>
#include <pcl_animseg/keypoints/dog_keypoint.h>
#include <pcl_animseg/progress.h>

#include "features/bumpy_surface.h"

using namespace pcl_animseg;

TEST(Multiscale, BlocksOfFramesGiveTheSameFeatures) {
  PointCloudSequence seq;
  for (unsigned t = 0; t < 4; ++t)
    seq.addFrame(test::transformed(*test::bumpySphere(3000 + 400 * t, 40 + t), test::someMotion()),
                 "f" + std::to_string(t));
  MultiscaleParams whole;
  Progress quiet(true);
  const SequenceFeatures a = computeSequenceFeatures(seq, whole, &quiet);
  MultiscaleParams blocks = whole;
  blocks.block_points = 5000;  // frames of 3000-4200 points: one frame per block
  Progress progress(true);
  const SequenceFeatures b = computeSequenceFeatures(seq, blocks, &progress);
  ASSERT_EQ(a.signatures.size(), 4u);
  ASSERT_EQ(b.signatures.size(), 4u);
  for (std::size_t t = 0; t < 4; ++t) {
    ASSERT_EQ(a.signatures[t].rows(), static_cast<long>(seq.frame(t)->size()));
    EXPECT_EQ(a.signatures[t], b.signatures[t]) << "frame " << t;
    EXPECT_EQ(a.keypoints[t], b.keypoints[t]) << "frame " << t;
    EXPECT_EQ(a.keypoint_response[t], b.keypoint_response[t]) << "frame " << t;
  }
  // Four blocks ran each stage four times: one record per stage, in order.
  std::vector<std::string> stages;
  for (const auto& s : progress.timings()) stages.push_back(s.first);
  EXPECT_EQ(stages, (std::vector<std::string>{"scale_space", "keypoints", "signature"}));
  blocks.block_points = 0;
  EXPECT_THROW(computeSequenceFeatures(seq, blocks), Error);
}

namespace {

/** A FeatureDevice that computes on the CPU with the library's own classes from the plans it is
 * given, and records the blocks it saw: the wiring of computeSequenceFeatures to a device. */
class CpuFeatureDevice : public FeatureDevice {
 public:
  std::vector<std::pair<std::size_t, std::size_t>> blocks;
  void scaleSpaces(const PointCloudSequence& seq, std::size_t first, std::size_t last,
                   const std::vector<ScaleSpacePlan>& plans, const MultiscaleParams& p, bool rows,
                   std::vector<ScaleSpace>& spaces) override {
    blocks.emplace_back(first, last);
    ASSERT_EQ(plans.size(), last - first);
    for (std::size_t t = first; t < last; ++t) {
      MLSScaleSpace mls;
      configureScaleSpace(mls, seq.frame(t), p, plans[t - first].spacing);
      mls.compute(spaces[t]);
      // What the plan says is what compute() used.
      EXPECT_EQ(spaces[t].scales, plans[t - first].scales);
      EXPECT_EQ(spaces[t].neighbourhoods->radius, plans[t - first].radius);
      EXPECT_EQ(plans[t - first].ref.size(), seq.frame(t)->size());
      if (!rows) spaces[t].neighbourhoods.reset();
      SignatureEstimation se;
      se.setInputCloud(signatureInput(*seq.frame(t), *spaces[t].levels[0]));
      se.setNeighbourhoods(spaces[t].neighbourhoods);
      se.setScale(p.signature_h * spaces[t].spacing);
      se.setLayout(p.layout);
      if (sig_.size() <= t) sig_.resize(t + 1);
      se.compute(sig_[t]);
    }
  }
  void signature(std::size_t t, Eigen::MatrixXf& out) const override { out = sig_.at(t); }

 private:
  std::vector<Eigen::MatrixXf> sig_;
};

}  // namespace

TEST(Multiscale, AFeatureDeviceGetsEveryBlockAndItsResultsAreUsed) {
  PointCloudSequence seq;
  for (unsigned t = 0; t < 3; ++t)
    seq.addFrame(test::bumpySphere(3000 + 500 * t, 60 + t), "f" + std::to_string(t));
  MultiscaleParams p;
  p.block_points = 7000;  // blocks {0, 1} and {2}
  p.keep_smoothed = true;
  const SequenceFeatures cpu = computeSequenceFeatures(seq, p);
  CpuFeatureDevice device;
  Progress progress(true);
  const SequenceFeatures dev = computeSequenceFeatures(seq, p, &progress, &device);
  EXPECT_EQ(device.blocks, (std::vector<std::pair<std::size_t, std::size_t>>{{0, 2}, {2, 3}}));
  for (std::size_t t = 0; t < 3; ++t) {
    EXPECT_EQ(cpu.signatures[t], dev.signatures[t]) << "frame " << t;
    EXPECT_EQ(cpu.keypoints[t], dev.keypoints[t]) << "frame " << t;
    ASSERT_TRUE(dev.smoothed[t]);
    EXPECT_EQ(dev.smoothed[t]->size(), seq.frame(t)->size());
  }
  std::size_t kp = 0;
  for (const auto& k : dev.keypoints) kp += k.size();
  EXPECT_GT(kp, 0u);
  // A frame the scale space refuses is refused before the device is called, naming the frame.
  PointCloudSequence bad = seq;
  PointCloudSequence::Cloud::Ptr tiny(new PointCloudSequence::Cloud);
  for (int i = 0; i < 10; ++i) tiny->push_back((*seq.frame(0))[i]);
  bad.addFrame(tiny, "tiny");
  CpuFeatureDevice unused;
  try {
    computeSequenceFeatures(bad, p, nullptr, &unused);
    FAIL() << "a frame of 10 points was accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("frame 'tiny'"), std::string::npos) << e.what();
  }
}

namespace {

/** A keypoint refinement that fails, as a device's (DeviceError) or as a malformed input's
 * (Error). */
class FailingRefiner : public KeypointRefineDevice {
 public:
  explicit FailingRefiner(bool device) : device_(device) {}
  void refine(KeypointRefineJobs&) const override {
    if (device_) throw DeviceError("GPU keypoints: the kernel failed (test)");
    throw Error("a malformed refinement job (test)");
  }

 private:
  bool device_;
};

class FailingRefineDevice : public CpuFeatureDevice {
 public:
  explicit FailingRefineDevice(bool device) : refiner_(device) {}
  const KeypointRefineDevice* keypointRefiner() const override { return &refiner_; }

 private:
  FailingRefiner refiner_;
};

}  // namespace

// A device's failure inside a frame's work is thrown as the device's (DeviceError, its message
// as it is), so that the pipeline falls back to the CPU on it; any other failure there is the
// frame's (a plain Error naming the frame), which no fall-back hides.
TEST(Multiscale, ADeviceErrorInAFrameStaysTheDevicesAndOtherErrorsNameTheFrame) {
  PointCloudSequence seq;
  for (unsigned t = 0; t < 2; ++t)
    seq.addFrame(test::bumpySphere(3000 + 500 * t, 70 + t), "f" + std::to_string(t));
  const MultiscaleParams p;
  FailingRefineDevice gpu(true);
  try {
    computeSequenceFeatures(seq, p, nullptr, &gpu);
    FAIL() << "the device's failure was not thrown";
  } catch (const DeviceError& e) {
    EXPECT_STREQ(e.what(), "GPU keypoints: the kernel failed (test)");
  }
  FailingRefineDevice input(false);
  try {
    computeSequenceFeatures(seq, p, nullptr, &input);
    FAIL() << "the frame's failure was not thrown";
  } catch (const DeviceError& e) {
    FAIL() << "a frame's failure was thrown as the device's: " << e.what();
  } catch (const Error& e) {
    EXPECT_EQ(std::string(e.what()), "frame 'f0': a malformed refinement job (test)");
  }
}
