// GPU mean shift against the CPU MeanShiftSegmentation (paper method, Gaussian kd-tree backend).
// Skips when no usable GPU is present.
#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/mean_shift.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/synth/articulated.h>

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>

namespace gpu = pcl_animseg::gpu;
namespace seg = pcl_animseg::segmentation;

namespace {

// The joint space of Eq. 5-6 without signatures, built as the CPU stage builds it.
void jointSpace(const pcl_animseg::PointCloudSequence& sequence, const seg::MeanShiftParams& p,
                Eigen::MatrixXf& z, Eigen::RowVectorXf& metric) {
  const double s = seg::sequenceScale(sequence);
  z.resize(static_cast<Eigen::Index>(sequence.totalPoints()), 6);
  Eigen::Index i = 0;
  for (std::size_t t = 0; t < sequence.size(); ++t)
    for (const auto& pt : *sequence.frame(t)) {
      z(i, 0) = static_cast<float>(pt.x / s);
      z(i, 1) = static_cast<float>(pt.y / s);
      z(i, 2) = static_cast<float>(pt.z / s);
      Eigen::Vector3f nrm(pt.normal_x, pt.normal_y, pt.normal_z);
      if (!nrm.allFinite() || nrm.norm() < 1e-6f)
        nrm.setZero();
      else
        nrm.normalize();
      z.block<1, 3>(i, 3) = nrm.transpose();
      ++i;
    }
  metric.resize(6);
  metric.head(3).setConstant(static_cast<float>(std::sqrt(p.w2) / p.bandwidth));
  metric.tail(3).setConstant(static_cast<float>(std::sqrt(p.w1) / p.bandwidth));
}

/** A generated 6-frame sequence of `plan` (seed 5), about `points` points a frame. */
std::shared_ptr<pcl_animseg::PointCloudSequence> synthSequence(pcl_animseg::synth::BodyPlan plan,
                                                               int points) {
  pcl_animseg::synth::SynthParams sp;
  sp.plan = plan;
  sp.frames = 6;
  sp.points = points;
  sp.seed = 5;
  return std::make_shared<pcl_animseg::PointCloudSequence>(
      pcl_animseg::synth::toSequence(pcl_animseg::synth::generate(sp)));
}

/** A joint space (Eq. 5-6, no signatures) with keypoint flags on every step-th point from
 * `first` and a pair metric 1.5 times the plain one on the normals. */
struct PairSpace {
  Eigen::MatrixXf z;
  Eigen::RowVectorXf metric, pair;
  std::vector<char> key;
};
PairSpace pairSpace(pcl_animseg::synth::BodyPlan plan, int points, std::size_t first,
                    std::size_t step, const seg::MeanShiftParams& mp) {
  PairSpace s;
  jointSpace(*synthSequence(plan, points), mp, s.z, s.metric);
  s.key.assign(static_cast<std::size_t>(s.z.rows()), 0);
  for (std::size_t i = first; i < s.key.size(); i += step) s.key[i] = 1;
  s.pair = s.metric;
  s.pair.tail(3) *= 1.5f;
  return s;
}

}  // namespace

TEST(GpuMeanShift, AgreesWithCpuPaperMethod) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  for (auto plan : {pcl_animseg::synth::BodyPlan::Quadruped,
                    pcl_animseg::synth::BodyPlan::Humanoid}) {
    const auto sequence = synthSequence(plan, 3000);

    seg::MeanShiftParams mp;
    mp.method = seg::MeanShiftMethod::Paper;
    mp.backend = seg::MeanShiftBackend::GaussianKdTree;
    mp.min_cluster_size = 1;  // no absorption: compare the mode grouping itself
    // The GPU iterates every point through the filter, with no exact ending: so does the CPU
    // reference here.
    mp.iterate_cells = false;
    mp.refine_iterations = 0;
    seg::MeanShiftSegmentation cpu;
    cpu.setInputSequence(sequence);
    cpu.setParams(mp);
    seg::SegmentationResult result;
    cpu.segment(result);
    std::vector<int> cpu_labels;
    for (const auto& frame : result.labels)
      cpu_labels.insert(cpu_labels.end(), frame.begin(), frame.end());

    Eigen::MatrixXf z, y;
    Eigen::RowVectorXf metric;
    jointSpace(*sequence, mp, z, metric);
    gpu::MeanShiftParams gp;
    gp.gkdtree = mp.gkdtree;
    gp.max_iterations = mp.max_iterations;
    gp.convergence = mp.convergence;
    gpu::MeanShift ms;
    ms.setParams(gp);
    Eigen::VectorXf density;
    ms.run(z, metric, metric, {}, y, density);
    std::vector<int> gpu_labels, reps;
    gpu::groupModes(y, metric, density, mp.merge_radius, gpu_labels, reps);

    const double ari = pcl_animseg::evaluation::adjustedRandIndex(cpu_labels, gpu_labels);
    std::printf("%s: %zu points, CPU %d clusters, GPU %zu modes, %d iterations "
                "(%d not converged), %zu samples, ARI %.4f\n",
                pcl_animseg::synth::toString(plan).c_str(), cpu_labels.size(),
                result.num_clusters, reps.size(), ms.stats().iterations,
                ms.stats().not_converged, ms.stats().num_samples, ari);
    EXPECT_GE(ari, 0.99);
    EXPECT_EQ(static_cast<int>(reps.size()), result.num_clusters);
    // The filter's N/M as the pipeline reports it (points per cell), from the device backend.
    gpu::MeanShiftBackend backend;
    Eigen::MatrixXf yb;
    Eigen::VectorXf fb;
    backend.seekModes(z, metric, metric, {}, mp, yb, fb);
    std::printf("N/M: CPU %.2f, GPU %.2f\n", result.sampling_factor, backend.samplingFactor());
    EXPECT_GT(result.sampling_factor, 1.0);
    EXPECT_NEAR(backend.samplingFactor(), result.sampling_factor, 0.1 * result.sampling_factor);
    EXPECT_TRUE(y.allFinite());
    EXPECT_GT(density.minCoeff(), 0.0f);
  }
}

TEST(GpuMeanShift, BadInputIsAnError) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  gpu::MeanShift ms;
  Eigen::MatrixXf y;
  Eigen::VectorXf f;
  const Eigen::RowVectorXf m = Eigen::RowVectorXf::Ones(3);
  EXPECT_THROW(ms.run(Eigen::MatrixXf(0, 3), m, m, {}, y, f), pcl_animseg::Error);
  EXPECT_THROW(ms.run(Eigen::MatrixXf::Random(10, 4), m, m, {}, y, f), pcl_animseg::Error);
  EXPECT_THROW(ms.run(Eigen::MatrixXf::Random(10, 70), Eigen::RowVectorXf::Ones(70),
                      Eigen::RowVectorXf::Ones(70), {}, y, f),
               pcl_animseg::Error);
}

// MeanShiftParams::exact_borders behind the device backend: the device iterates every point and
// gives the densities, the border rounds' exact trajectories run on the CPU. The CPU doing the
// same (every point iterated) gives the same clusters.
TEST(GpuMeanShift, ExactBordersAgreeWithCpu) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  const auto sequence = synthSequence(pcl_animseg::synth::BodyPlan::Humanoid, 1500);
  seg::MeanShiftParams mp;
  mp.method = seg::MeanShiftMethod::Paper;
  mp.backend = seg::MeanShiftBackend::GaussianKdTree;
  mp.bandwidth = 0.2;
  mp.iterate_cells = false;
  mp.exact_borders = true;
  auto labelsOf = [&](bool on_gpu, std::string& used) {
    seg::MeanShiftSegmentation ms;
    ms.setInputSequence(sequence);
    ms.setParams(mp);
    if (on_gpu) ms.setDeviceBackend(std::make_shared<gpu::MeanShiftBackend>());
    seg::SegmentationResult r;
    ms.segment(r);
    used = ms.deviceUsed();
    std::vector<int> out;
    for (const auto& frame : r.labels) out.insert(out.end(), frame.begin(), frame.end());
    return out;
  };
  std::string cpu_used, gpu_used;
  const std::vector<int> cpu_labels = labelsOf(false, cpu_used);
  const std::vector<int> gpu_labels = labelsOf(true, gpu_used);
  const double ari = pcl_animseg::evaluation::adjustedRandIndex(cpu_labels, gpu_labels);
  std::printf("exact borders: %zu points, CPU (%s) against GPU (%s): ARI %.4f\n", cpu_labels.size(),
              cpu_used.c_str(), gpu_used.c_str(), ari);
  EXPECT_EQ(cpu_used, "cpu");
  EXPECT_NE(gpu_used, "cpu");
  EXPECT_GE(ari, 0.99);
}

// The backend keeps the density's trees for the next call on the same data: the same values as a
// fresh backend's, for other queries too, and new trees once the data change.
TEST(GpuMeanShift, DensityKeepsItsTreesOnlyForTheSameData) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  seg::MeanShiftParams mp;
  const PairSpace js = pairSpace(pcl_animseg::synth::BodyPlan::Quadruped, 1500, 0, 9, mp);
  const Eigen::MatrixXf& z = js.z;
  const Eigen::RowVectorXf &metric = js.metric, &pair = js.pair;
  const std::vector<char>& key = js.key;
  const Eigen::MatrixXf q1 = z.topRows(500), q2 = z.bottomRows(700);
  const std::vector<char> k1(key.begin(), key.begin() + 500), k2(key.end() - 700, key.end());
  auto fresh = [&](const Eigen::MatrixXf& data, const Eigen::MatrixXf& q,
                   const std::vector<char>& qk) {
    gpu::MeanShiftBackend b;
    Eigen::VectorXf f;
    b.density(data, metric, pair, key, mp, q, qk, f);
    return f;
  };
  gpu::MeanShiftBackend kept;
  Eigen::VectorXf f1, f2, f3;
  kept.density(z, metric, pair, key, mp, q1, k1, f1);
  kept.density(z, metric, pair, key, mp, q2, k2, f2);  // the kept trees
  EXPECT_TRUE(f1 == fresh(z, q1, k1));
  EXPECT_TRUE(f2 == fresh(z, q2, k2));
  Eigen::MatrixXf moved = z;
  moved.col(0).array() += 0.05f;  // other data: new trees
  kept.density(moved, metric, pair, key, mp, q2, k2, f3);
  EXPECT_TRUE(f3 == fresh(moved, q2, k2));
  EXPECT_FALSE(f3 == f2);
  EXPECT_GT(f2.minCoeff(), 0.0f);
}

// After seekModes the backend answers densities on the same data from the iteration's own trees
// and blurred values (their homogeneous column): the same bits as a fresh backend that builds
// the density's trees, at the end points and at other queries, keypoint queries included; and
// the iteration's end densities are those of its end points.
TEST(GpuMeanShift, DensityFromTheIterationsTreesIsAFreshTreesDensity) {
  std::string why;
  if (!gpu::gpuAvailable(&why)) GTEST_SKIP() << why;
  seg::MeanShiftParams mp;
  const PairSpace js = pairSpace(pcl_animseg::synth::BodyPlan::Humanoid, 2500, 3, 11, mp);
  const Eigen::MatrixXf& z = js.z;
  const Eigen::RowVectorXf &metric = js.metric, &pair = js.pair;
  const std::vector<char>& key = js.key;
  gpu::MeanShiftBackend iterated;
  Eigen::MatrixXf y;
  Eigen::VectorXf end_density;
  iterated.seekModes(z, metric, pair, key, mp, y, end_density);
  ASSERT_EQ(y.rows(), z.rows());
  ASSERT_EQ(y.cols(), z.cols());
  // The end points are not the start points (the iteration moved them), in columns as given.
  EXPECT_GT((y - z).cwiseAbs().maxCoeff(), 1e-3f);
  auto fresh = [&](const Eigen::MatrixXf& q, const std::vector<char>& qk) {
    gpu::MeanShiftBackend b;
    Eigen::VectorXf f;
    b.density(z, metric, pair, key, mp, q, qk, f);
    return f;
  };
  Eigen::VectorXf at_end, at_points, plain_queries;
  iterated.density(z, metric, pair, key, mp, y, key, at_end);
  iterated.density(z, metric, pair, key, mp, z, key, at_points);
  iterated.density(z, metric, pair, key, mp, z.topRows(900), {}, plain_queries);
  const Eigen::VectorXf fresh_end = fresh(y, key);
  EXPECT_TRUE(at_end == fresh_end);
  EXPECT_TRUE(at_points == fresh(z, key));
  EXPECT_TRUE(plain_queries == fresh(z.topRows(900), {}));
  EXPECT_TRUE(end_density == fresh_end);
  EXPECT_GT(at_points.minCoeff(), 0.0f);
  EXPECT_FALSE(at_points == at_end);
}
