#include <pcl_animseg/error.h>
#include <pcl_animseg/segmentation/mean_shift.h>

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace seg = pcl_animseg::segmentation;
using pcl_animseg::PointCloudSequence;

namespace {

// Two spheres apart, sampled afresh in every frame (different counts), moving slowly.
PointCloudSequence::Ptr twoBlobs(int frames, unsigned seed) {
  auto seq = std::make_shared<PointCloudSequence>();
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  for (int t = 0; t < frames; ++t) {
    PointCloudSequence::Cloud::Ptr c(new PointCloudSequence::Cloud);
    const int n = 300 + 20 * t;
    for (int i = 0; i < n; ++i) {
      Eigen::Vector3f d(g(rng), g(rng), g(rng));
      d.normalize();
      const float cx = (i % 2 ? 3.0f : 0.0f) + 0.05f * t;
      pcl::PointNormal p;
      p.x = cx + 0.5f * d.x();
      p.y = 0.5f * d.y();
      p.z = 0.5f * d.z();
      p.normal_x = d.x();
      p.normal_y = d.y();
      p.normal_z = d.z();
      c->push_back(p);
    }
    seq->addFrame(c, "f" + std::to_string(t));
  }
  return seq;
}

seg::SegmentationResult run(const PointCloudSequence::Ptr& seq, seg::MeanShiftParams p) {
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  ms.setParams(p);
  seg::SegmentationResult r;
  ms.segment(r);
  return r;
}

}  // namespace

TEST(MeanShift, SeparatesTwoBlobsAndFillsEveryField) {
  auto seq = twoBlobs(4, 1);
  for (auto method : {seg::MeanShiftMethod::Paper, seg::MeanShiftMethod::Motion}) {
    seg::MeanShiftParams p;
    p.method = method;
    p.bandwidth = 0.15;
    const auto r = run(seq, p);
    ASSERT_EQ(r.labels.size(), seq->size());
    ASSERT_GE(r.num_clusters, 2);
    EXPECT_EQ(r.modes.rows(), r.num_clusters);
    EXPECT_EQ(static_cast<int>(r.mode_density.size()), r.num_clusters);
    // The two spheres never share a label, in any frame.
    for (std::size_t t = 0; t < seq->size(); ++t) {
      ASSERT_EQ(r.labels[t].size(), seq->frame(t)->size());
      for (std::size_t j = 2; j < r.labels[t].size(); ++j) {
        EXPECT_GE(r.labels[t][j], 0);
        EXPECT_NE(r.labels[t][j], r.labels[0][1 - j % 2]) << "frame " << t;
      }
    }
    for (const auto& s : r.saddles) {
      EXPECT_NE(s.a, s.b);
      EXPECT_LE(s.density, std::max(r.mode_density[s.a], r.mode_density[s.b]) + 1e-6);
    }
    std::vector<pcl::PointIndices> pi;
    seg::MeanShiftSegmentation::toPointIndices(r, pi);
    std::size_t total = 0;
    for (const auto& c : pi) total += c.indices.size();
    EXPECT_EQ(total, seq->totalPoints());
  }
}

TEST(MeanShift, DeterministicForASeed) {
  auto seq = twoBlobs(3, 2);
  for (auto backend : {seg::MeanShiftBackend::Exact, seg::MeanShiftBackend::GaussianKdTree})
    for (auto method : {seg::MeanShiftMethod::Paper, seg::MeanShiftMethod::Motion}) {
      seg::MeanShiftParams p;
      p.backend = backend;
      p.method = method;
      EXPECT_EQ(run(seq, p).labels, run(seq, p).labels);
    }
}

TEST(MeanShift, BadInput) {
  auto seq = twoBlobs(2, 3);
  seg::MeanShiftParams p;
  p.bandwidth = 0.0;
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  p.bandwidth = -1.0;
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  p = seg::MeanShiftParams();
  p.w2 = -0.5;
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  EXPECT_THROW(run(std::make_shared<PointCloudSequence>(), seg::MeanShiftParams()),
               pcl_animseg::Error);
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  ms.setSignatures({Eigen::MatrixXf::Zero(3, 4)});
  seg::SegmentationResult r;
  EXPECT_THROW(ms.segment(r), pcl_animseg::Error);
  EXPECT_THROW(seg::meanShiftBackendFromString("gpu-magic"), pcl_animseg::Error);
  EXPECT_THROW(seg::meanShiftMethodFromString("nope"), pcl_animseg::Error);
}

TEST(MeanShift, OneFrameAndIdenticalPoints) {
  // One frame: well defined (the motion method has nothing to track; patches merge freely).
  auto one = twoBlobs(1, 4);
  for (auto method : {seg::MeanShiftMethod::Paper, seg::MeanShiftMethod::Motion}) {
    seg::MeanShiftParams p;
    p.method = method;
    const auto r = run(one, p);
    EXPECT_EQ(r.labels.size(), 1u);
    EXPECT_GE(r.num_clusters, 1);
  }
  // All points identical: one cluster.
  auto same = std::make_shared<PointCloudSequence>();
  for (int t = 0; t < 2; ++t) {
    PointCloudSequence::Cloud::Ptr c(new PointCloudSequence::Cloud);
    pcl::PointNormal q;
    q.x = q.y = q.z = 1.0f;
    q.normal_x = q.normal_y = 0.0f;
    q.normal_z = 1.0f;
    for (int i = 0; i < 50; ++i) c->push_back(q);
    same->addFrame(c, "s" + std::to_string(t));
  }
  for (auto method : {seg::MeanShiftMethod::Paper, seg::MeanShiftMethod::Motion}) {
    seg::MeanShiftParams p;
    p.method = method;
    const auto r = run(same, p);
    EXPECT_EQ(r.num_clusters, 1);
  }
}
