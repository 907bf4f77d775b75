// computeSequenceFeatures in blocks of frames (bounded scale-space memory): the result must not
// depend on the block size, and each stage is recorded once with its time summed over blocks.
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/progress.h>

#include <gtest/gtest.h>

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
