// SignatureEstimation / DiscSignature (Eq. 2-3): invariance to the choice of (u, v), to rigid
// motions and to uniform scaling; stability under resampling; layout; bad input; PCD output.
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/scale_space.h>
#include <pcl_animseg/features/signature.h>

#include <pcl/io/pcd_io.h>
#include <pcl/kdtree/kdtree_flann.h>

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

#include "features/bumpy_surface.h"

using namespace pcl_animseg;
using Cloud = PointCloudSequence::Cloud;

namespace {

/** Level 0 of the scale space and the signatures of all its points at h = 3 spacings. */
struct Computed {
  ScaleSpace ss;
  Eigen::MatrixXf sig;
};

/** The reference spacing of a one-frame sequence. */
double unitOf(const Cloud::Ptr& cloud) {
  PointCloudSequence seq;
  seq.addFrame(cloud, "f");
  return sequenceSpacing(seq);
}

Computed signaturesOf(const Cloud::Ptr& cloud, const SignatureLayout& layout = SignatureLayout(),
                      double unit = 0.0) {
  Computed c;
  MLSScaleSpace mls;
  mls.setSpacing(unit > 0.0 ? unit : unitOf(cloud));
  mls.setInputCloud(cloud);
  mls.setNumberOfLevels(1);
  mls.setNeighbourhoodRadius(6.0);
  mls.compute(c.ss);
  SignatureEstimation se;
  se.setInputCloud(signatureInput(*cloud, *c.ss.levels[0]));
  se.setNeighbourhoods(c.ss.neighbourhoods);
  se.setScale(3.0 * c.ss.spacing);
  se.setLayout(layout);
  se.compute(c.sig);
  return c;
}

/** sqrt(sum |a - b|^2) / sqrt(sum |a|^2) over all rows. */
double relativeL2(const Eigen::MatrixXf& a, const Eigen::MatrixXf& b) {
  return (a - b).norm() / a.norm();
}

}  // namespace

TEST(Signature, InvariantToTheChoiceOfUV) {
  auto cloud = test::bumpySphere(8000, 11);
  Computed c = signaturesOf(cloud);
  const Cloud& L0 = *cloud;
  const auto& nb = *c.ss.neighbourhoods;
  const double rho = 6.0 * c.ss.spacing;
  DiscSignature disc;
  std::vector<std::complex<double>> scratch;
  double num = 0.0, den = 0.0, worst = 0.0;
  int points = 0;
  for (std::size_t j = 0; j < L0.size(); j += 10, ++points) {
    const Eigen::Vector3f n = L0[j].getNormalVector3fMap();
    const Eigen::Vector3f u0 = defaultTangent(n);
    // An arbitrary (not a multiple of 2 pi / S) rotation of the frame about n.
    const float angle = 0.37f + 0.61f * static_cast<float>(j % 10);
    const Eigen::Vector3f u1 = Eigen::AngleAxisf(angle, n) * u0;
    float a[24], b[24];
    const int cnt = nb.countWithin(j, static_cast<float>(rho));
    disc.compute(L0, nb.row(j), cnt, L0[j].getVector3fMap(), n, u0, rho, a, scratch);
    disc.compute(L0, nb.row(j), cnt, L0[j].getVector3fMap(), n, u1, rho, b, scratch);
    const Eigen::Map<Eigen::VectorXf> va(a, 24), vb(b, 24);
    num += (va - vb).squaredNorm();
    den += va.squaredNorm();
    worst = std::max<double>(worst, (va - vb).norm() / std::max(va.norm(), 1e-12f));
  }
  ASSERT_GE(points, 500);
  const double rel = std::sqrt(num / den);
  RecordProperty("uv_relative_l2", std::to_string(rel));
  EXPECT_LT(rel, 0.01);
  EXPECT_LT(worst, 0.05);
}

TEST(Signature, InvariantToRigidMotionAndUniformScaling) {
  auto cloud = test::bumpySphere(8000, 12);
  const Computed a = signaturesOf(cloud);
  const Computed moved = signaturesOf(test::transformed(*cloud, test::someMotion()));
  const Computed scaled = signaturesOf(test::transformed(*cloud, Eigen::Isometry3d::Identity(), 0.013));
  const double e_moved = relativeL2(a.sig, moved.sig), e_scaled = relativeL2(a.sig, scaled.sig);
  RecordProperty("rigid_relative_l2", std::to_string(e_moved));
  RecordProperty("scale_relative_l2", std::to_string(e_scaled));
  EXPECT_LT(e_moved, 0.01);
  EXPECT_LT(e_scaled, 0.01);
  EXPECT_GT(a.sig.norm(), 0.0f);
}

TEST(Signature, StableUnderResampling) {
  auto coarse = test::bumpySphere(8000, 13);
  auto fine = test::bumpySphere(12000, 14);
  // One sequence, one length unit: the scale is the same world length on both samplings.
  PointCloudSequence seq;
  seq.addFrame(coarse, "coarse");
  seq.addFrame(fine, "fine");
  const double unit = sequenceSpacing(seq);
  const Computed a = signaturesOf(coarse, SignatureLayout(), unit);
  const Computed b = signaturesOf(fine, SignatureLayout(), unit);
  pcl::KdTreeFLANN<pcl::PointNormal> tree;
  tree.setInputCloud(fine);
  std::vector<int> idx(1);
  std::vector<float> d2(1);
  double diff = 0.0, mag = 0.0;
  for (std::size_t j = 0; j < coarse->size(); ++j) {
    tree.nearestKSearch((*coarse)[j], 1, idx, d2);
    diff += (a.sig.row(j) - b.sig.row(idx[0])).norm();
    mag += a.sig.row(j).norm();
  }
  const double rel = diff / mag;
  RecordProperty("resampling_relative", std::to_string(rel));
  EXPECT_LT(rel, 0.10);
}

TEST(Signature, SphereHasNoAngularStructureAndPlaneIsZero) {
  test::Bump none{Eigen::Vector3d::UnitX(), 0.0, 0.2};
  auto sphere = test::bumpySphere(6000, 15, {none});
  const Computed s = signaturesOf(sphere);
  // Columns m > 0 (angular frequencies) vanish on a sphere; m = 0 does not.
  double ang = 0.0, radial = 0.0;
  for (int a = 0; a < 6; ++a)
    for (int m = 0; m < 4; ++m) (m == 0 ? radial : ang) += s.sig.col(a * 4 + m).squaredNorm();
  EXPECT_GT(radial, 0.0);
  EXPECT_LT(std::sqrt(ang / radial), 0.05);
  auto plane = test::heightField(
      4000, 16, [](double, double) { return 0.0; },
      [](double, double) { return Eigen::Vector2d::Zero(); });
  const Computed p = signaturesOf(plane);
  EXPECT_LT(p.sig.cwiseAbs().maxCoeff(), 1e-4f);
}

TEST(Signature, LayoutIsConfigurable) {
  auto cloud = test::bumpySphere(3000, 17);
  SignatureLayout l;
  l.radial = 16;
  l.angular = 16;
  l.radial_freqs = 4;
  l.angular_freqs = 5;
  const Computed c = signaturesOf(cloud, l);
  EXPECT_EQ(c.sig.cols(), 20);
  EXPECT_EQ(c.sig.rows(), static_cast<long>(cloud->size()));
  EXPECT_EQ(SignatureLayout().dimension(), 24);
  SignatureLayout bad;
  bad.angular_freqs = 6;  // > S/2 + 1 with S = 8
  EXPECT_THROW(signaturesOf(cloud, bad), Error);
  bad = SignatureLayout();
  bad.radial_freqs = 40;
  EXPECT_THROW(bad.validate(), Error);
}

TEST(Signature, BadInput) {
  auto cloud = test::bumpySphere(1000, 18);
  SignatureEstimation se;
  Eigen::MatrixXf out;
  EXPECT_THROW(se.compute(out), Error);  // no input
  se.setInputCloud(cloud);
  EXPECT_THROW(se.compute(out), Error);  // no scale
  se.setScale(0.1);
  Cloud::Ptr bare(new Cloud(*cloud));
  for (auto& p : bare->points) p.getNormalVector3fMap().setZero();
  se.setInputCloud(bare);
  EXPECT_THROW(se.compute(out), Error);  // missing normals
  // Isolated points (disc nearly empty) get a zero signature, not garbage.
  Cloud::Ptr sparse(new Cloud);
  for (int i = 0; i < 5; ++i) sparse->push_back((*cloud)[i * 100]);
  se.setInputCloud(sparse);
  se.setScale(1e-4);
  ASSERT_NO_THROW(se.compute(out));
  EXPECT_EQ(out.cwiseAbs().maxCoeff(), 0.0f);
}

TEST(Signature, PCDRoundTrip) {
  auto cloud = test::bumpySphere(2000, 19);
  const Computed c = signaturesOf(cloud);
  const std::vector<int> kp = {3, 77, 1500};
  const std::string path = testing::TempDir() + "animseg_signature_roundtrip.pcd";
  ASSERT_EQ(pcl::io::savePCDFile(path, signatureCloud(*cloud, c.sig, kp), Eigen::Vector4f::Zero(),
                                 Eigen::Quaternionf::Identity(), true),
            0);
  pcl::PointCloud<PointSignature24> back;
  ASSERT_EQ(pcl::io::loadPCDFile(path, back), 0);
  std::remove(path.c_str());
  ASSERT_EQ(back.size(), cloud->size());
  for (std::size_t j = 0; j < back.size(); j += 97)
    for (int d = 0; d < 24; ++d) ASSERT_EQ(back[j].signature[d], c.sig(j, d));
  EXPECT_EQ(back[77].keypoint, 1);
  EXPECT_EQ(back[78].keypoint, 0);
  const auto typed = signatureCloud24(*cloud, c.sig, kp);
  EXPECT_EQ(typed[1500].keypoint, 1);
}
