#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/filters/gaussian_kdtree.h>

#include <cstdio>

#include "blob_data.h"

using pcl_animseg::filters::bruteForceGaussTransform;
using pcl_animseg::filters::GaussianKdTree;
using pcl_animseg::filters::GaussianKdTreeParams;
// The data: blobs along a random 3-D set (blob_data.h, shared with the GPU tree's test).
using animseg_test::makeBlobData;
using animseg_test::relativeError;

TEST(GaussianKdTree, MatchesBruteForceGaussTransform) {
  for (int d : {3, 8, 30}) {
    const Eigen::MatrixXf p = makeBlobData(4000, d, 7 + d);
    Eigen::MatrixXf values(p.rows(), 2);
    values.col(0).setOnes();
    values.col(1) = p.col(0);
    const Eigen::MatrixXf q = p.topRows(300);
    Eigen::MatrixXf exact, approx;
    bruteForceGaussTransform(p, values, q, exact);
    GaussianKdTreeParams params;
    params.leaf_extent = 0.5f;
    GaussianKdTree tree(params);
    tree.build(p);
    tree.filter(values, q, approx);
    std::printf("d=%d samples=%zu N/M=%.1f rel.error=%.4f\n", d, tree.numSamples(),
                tree.samplingFactor(), relativeError(approx, exact));
    EXPECT_LT(relativeError(approx, exact), 0.1) << "d = " << d << ", samples "
                                                   << tree.numSamples();
    // Mean shift only needs the ratio (Eq. 8 / Eq. 10): tighter.
    const Eigen::ArrayXf ratio_a = approx.col(1).array() / approx.col(0).array();
    const Eigen::ArrayXf ratio_e = exact.col(1).array() / exact.col(0).array();
    EXPECT_LT((ratio_a - ratio_e).abs().maxCoeff(), 0.3f) << "d = " << d;
    EXPECT_GT(tree.samplingFactor(), 1.0);
  }
}

TEST(GaussianKdTree, DefaultParamsAreCoarserButClose) {
  const Eigen::MatrixXf p = makeBlobData(20000, 30, 3);
  Eigen::MatrixXf values = Eigen::MatrixXf::Ones(p.rows(), 1);
  const Eigen::MatrixXf q = p.topRows(200);
  Eigen::MatrixXf exact, approx;
  bruteForceGaussTransform(p, values, q, exact);
  GaussianKdTree tree;
  tree.build(p);
  tree.filter(values, q, approx);
  std::printf("default: samples=%zu rel.error=%.4f\n", tree.numSamples(),
              relativeError(approx, exact));
  EXPECT_LT(relativeError(approx, exact), 0.2);
  EXPECT_LT(tree.numSamples(), p.rows() / 4);
}

TEST(GaussianKdTree, DeterministicAndIdenticalPoints) {
  Eigen::MatrixXf p = Eigen::MatrixXf::Constant(500, 5, 2.0f);
  GaussianKdTree tree;
  tree.build(p);
  EXPECT_EQ(tree.numSamples(), 1u);
  Eigen::MatrixXf values = Eigen::MatrixXf::Ones(500, 1), out;
  tree.filter(values, p.topRows(3), out);
  EXPECT_NEAR(out(0, 0), 500.0f, 1e-2f);

  const Eigen::MatrixXf data = makeBlobData(3000, 10, 1);
  GaussianKdTree a, b;
  a.build(data);
  b.build(data);
  Eigen::MatrixXf oa, ob;
  Eigen::MatrixXf vals = Eigen::MatrixXf::Ones(data.rows(), 1);
  a.filter(vals, data, oa);
  b.filter(vals, data, ob);
  EXPECT_TRUE(oa == ob);
}

TEST(GaussianKdTree, LeafContainingFindsTheLeafOfEveryDataPoint) {
  const Eigen::MatrixXf p = makeBlobData(3000, 30, 5);
  GaussianKdTree tree;
  tree.build(p);
  ASSERT_GT(tree.numSamples(), 1u);
  for (Eigen::Index j = 0; j < p.rows(); ++j) {
    const Eigen::VectorXf q = p.row(j).transpose();
    EXPECT_EQ(tree.leafContaining(q.data()), tree.leafOf(j)) << "point " << j;
  }
}

TEST(GaussianKdTree, BadInput) {
  GaussianKdTree tree;
  EXPECT_THROW(tree.build(Eigen::MatrixXf(0, 3)), pcl_animseg::Error);
  Eigen::MatrixXf p = Eigen::MatrixXf::Zero(10, 3);
  p(2, 1) = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(tree.build(p), pcl_animseg::Error);
  Eigen::MatrixXf out;
  EXPECT_THROW(tree.filter(Eigen::MatrixXf::Ones(10, 1), p, out), pcl_animseg::Error);
  tree.build(Eigen::MatrixXf::Random(10, 3));
  EXPECT_THROW(tree.filter(Eigen::MatrixXf::Ones(9, 1), p, out), pcl_animseg::Error);
  EXPECT_THROW(tree.filter(Eigen::MatrixXf::Ones(10, 1), Eigen::MatrixXf::Zero(2, 4), out),
               pcl_animseg::Error);
  GaussianKdTreeParams bad;
  bad.leaf_extent = 0.0f;
  GaussianKdTree t2(bad);
  EXPECT_THROW(t2.build(Eigen::MatrixXf::Random(10, 3)), pcl_animseg::Error);
}
