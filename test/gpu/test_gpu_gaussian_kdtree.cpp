// GPU device buffers and Gaussian kd-tree: against brute force and against the CPU tree.
// Every test skips when no usable GPU is present (CI compiles the CUDA code but has no GPU).
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/filters/gaussian_kdtree.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/device_array.h>
#include <pcl_animseg/gpu/gaussian_kdtree.h>

#include <cstdio>
#include <limits>
#include <numeric>

#include "blob_data.h"

namespace gpu = pcl_animseg::gpu;
namespace filters = pcl_animseg::filters;

namespace {

#define REQUIRE_GPU()                                  \
  do {                                                 \
    std::string why;                                   \
    if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why; \
  } while (0)

// The data: blobs along a random 3-D set (blob_data.h, shared with the CPU tree's test).
using animseg_test::makeBlobData;
using animseg_test::relativeError;

}  // namespace

TEST(GpuDevice, AvailabilityIsReportedWithoutThrowing) {
  std::string why;
  const bool ok = gpu::gpuAvailable(&why);
  if (!ok) {
    EXPECT_FALSE(why.empty());
    EXPECT_THROW(gpu::DeviceArray<float>(16), pcl_animseg::Error);
    GTEST_SKIP() << why;
  }
  const gpu::DeviceInfo info = gpu::deviceInfo();
  std::printf("GPU %d: %s, sm_%d%d, %d SMs, %.1f GiB (%.1f free)\n", info.id, info.name.c_str(),
              info.compute_major, info.compute_minor, info.multiprocessors,
              info.total_bytes / 1073741824.0, info.free_bytes / 1073741824.0);
  EXPECT_GT(info.total_bytes, 0u);
}

TEST(GpuDevice, DeviceArrayRoundTripAndAccounting) {
  REQUIRE_GPU();
  std::vector<int> host(100000);
  std::iota(host.begin(), host.end(), -7);
  const std::size_t before = gpu::allocatedDeviceBytes();
  {
    gpu::DeviceArray<int> a;
    a.upload(host);
    EXPECT_EQ(a.size(), host.size());
    EXPECT_EQ(gpu::allocatedDeviceBytes(), before + host.size() * sizeof(int));
    gpu::DeviceArray<int> b;
    a.copyTo(b);
    gpu::DeviceArray<int> c(std::move(b));
    EXPECT_TRUE(b.empty());
    std::vector<int> back;
    c.download(back);
    EXPECT_EQ(back, host);
    c.setZero();
    c.download(back);
    EXPECT_EQ(std::count(back.begin(), back.end(), 0), static_cast<long>(host.size()));
    EXPECT_GE(gpu::peakDeviceBytes(), before + 2 * host.size() * sizeof(int));
  }
  EXPECT_EQ(gpu::allocatedDeviceBytes(), before);
}

TEST(GpuDevice, OutOfMemoryIsAnError) {
  REQUIRE_GPU();
  try {
    gpu::DeviceArray<float> huge(std::size_t(1) << 42);  // 16 TiB
    FAIL() << "allocation of 16 TiB succeeded";
  } catch (const pcl_animseg::Error& e) {
    EXPECT_NE(std::string(e.what()).find("out of memory"), std::string::npos) << e.what();
  }
  // The device stays usable afterwards.
  gpu::DeviceArray<float> small(1024);
  small.setZero();
  gpu::synchronize();
}

TEST(GpuGaussianKdTree, SameTreeAndSamplesAsCpu) {
  REQUIRE_GPU();
  for (int d : {3, 8, 30}) {
    const Eigen::MatrixXf p = makeBlobData(5000, d, 11 + d);
    filters::GaussianKdTreeParams params;
    params.leaf_extent = 0.5f;
    filters::GaussianKdTree cpu(params);
    cpu.build(p);
    gpu::GaussianKdTree g(params);
    g.build(p);
    ASSERT_EQ(g.numSamples(), cpu.numSamples()) << "d = " << d;
    EXPECT_LT((g.samples() - cpu.samples()).cwiseAbs().maxCoeff(), 1e-5f) << "d = " << d;
    const std::vector<int> leaves = g.leafOfPoints();
    int differ = 0;
    for (Eigen::Index j = 0; j < p.rows(); ++j) differ += leaves[j] != cpu.leafOf(j);
    EXPECT_EQ(differ, 0) << "d = " << d;
  }
}

TEST(GpuGaussianKdTree, MatchesBruteForceAndCpu) {
  REQUIRE_GPU();
  for (int d : {3, 8, 30, 64}) {
    const Eigen::MatrixXf p = makeBlobData(4000, d, 7 + d);
    Eigen::MatrixXf values(p.rows(), 2);
    values.col(0).setOnes();
    values.col(1) = p.col(0);
    const Eigen::MatrixXf q = p.topRows(300);
    Eigen::MatrixXf exact, approx, cpu_out;
    filters::bruteForceGaussTransform(p, values, q, exact);
    filters::GaussianKdTreeParams params;
    params.leaf_extent = 0.5f;
    gpu::GaussianKdTree tree(params);
    tree.build(p);
    tree.filter(values, q, approx);
    filters::GaussianKdTree cpu(params);
    cpu.build(p);
    cpu.filter(values, q, cpu_out);
    std::printf("d=%d samples=%zu depth=%d rel.error vs exact=%.4f vs CPU=%.2e\n", d,
                tree.numSamples(), tree.depth(), relativeError(approx, exact),
                relativeError(approx, cpu_out));
    // The approximation's own error (the CPU tree's too) grows with d: 0.12 at d = 64.
    EXPECT_LT(relativeError(approx, exact), d <= 30 ? 0.1 : 0.15) << "d = " << d;
    EXPECT_LT(relativeError(approx, cpu_out), 1e-3) << "d = " << d;
  }
}

TEST(GpuGaussianKdTree, WideValuesAndBadInput) {
  REQUIRE_GPU();
  const Eigen::MatrixXf p = makeBlobData(2000, 5, 3);
  const Eigen::MatrixXf values = Eigen::MatrixXf::Random(p.rows(), 100);
  gpu::GaussianKdTree g;
  g.build(p);
  filters::GaussianKdTree cpu;
  cpu.build(p);
  Eigen::MatrixXf a, b;
  g.filter(values, p.topRows(50), a);
  cpu.filter(values, p.topRows(50), b);
  EXPECT_LT(relativeError(a, b), 1e-3);

  gpu::GaussianKdTree t;
  Eigen::MatrixXf out;
  EXPECT_THROW(t.build(Eigen::MatrixXf(0, 3)), pcl_animseg::Error);
  EXPECT_THROW(t.filter(Eigen::MatrixXf::Ones(10, 1), p, out), pcl_animseg::Error);
  EXPECT_THROW(t.build(Eigen::MatrixXf::Random(10, 65)), pcl_animseg::Error);
  Eigen::MatrixXf nan = Eigen::MatrixXf::Zero(10, 3);
  nan(3, 1) = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(t.build(nan), pcl_animseg::Error);
  t.build(Eigen::MatrixXf::Random(10, 3));
  EXPECT_THROW(t.filter(Eigen::MatrixXf::Ones(9, 1), p, out), pcl_animseg::Error);
  EXPECT_THROW(t.filter(Eigen::MatrixXf::Ones(10, 1), Eigen::MatrixXf::Zero(2, 4), out),
               pcl_animseg::Error);
}

TEST(GpuGaussianKdTree, IdenticalPointsAndDeterminism) {
  REQUIRE_GPU();
  gpu::GaussianKdTree tree;
  tree.build(Eigen::MatrixXf::Constant(500, 5, 2.0f));
  EXPECT_EQ(tree.numSamples(), 1u);
  Eigen::MatrixXf out;
  tree.filter(Eigen::MatrixXf::Ones(500, 1), Eigen::MatrixXf::Constant(3, 5, 2.0f), out);
  EXPECT_NEAR(out(0, 0), 500.0f, 1e-2f);
  const Eigen::MatrixXf data = makeBlobData(3000, 10, 1);
  gpu::GaussianKdTree a, b;
  a.build(data);
  b.build(data);
  Eigen::MatrixXf oa, ob;
  const Eigen::MatrixXf vals = Eigen::MatrixXf::Ones(data.rows(), 1);
  a.filter(vals, data, oa);
  b.filter(vals, data, ob);
  EXPECT_LT(relativeError(oa, ob), 1e-6);
}
