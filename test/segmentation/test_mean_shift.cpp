#include <pcl_animseg/error.h>
#include <pcl_animseg/segmentation/mean_shift.h>

#include <gtest/gtest.h>

#include "synthetic_parts.h"
// White-box: the kernel sums behind both backends (not installed).
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <random>
#include <thread>

#include "../../src/segmentation/mean_shift_internal.h"

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

// A chain of three moving boxes, and the motion method asked for 3 parts.
PointCloudSequence::Ptr boxChain() {
  return std::make_shared<PointCloudSequence>(
      animseg_test::makeBoxChain(6, 1500, false, 5).sequence);
}
seg::MeanShiftParams threePartsByMotion() {
  seg::MeanShiftParams p;
  p.method = seg::MeanShiftMethod::Motion;
  p.target_clusters = 3;
  return p;
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
      // The motion method queries the density only at edge ends and near each cluster's densest
      // point: both ends of a saddle's edge are queried, so each side's mode is at least as
      // dense as the saddle (persistence, Eq. 12, is never negative).
      if (method == seg::MeanShiftMethod::Motion) {
        EXPECT_GT(s.density, 0.0);
        EXPECT_LE(s.density, std::min(r.mode_density[s.a], r.mode_density[s.b]) + 1e-6);
      }
    }
    for (double d : r.mode_density) EXPECT_GT(d, 0.0);
    std::vector<pcl::PointIndices> pi;
    seg::MeanShiftSegmentation::toPointIndices(r, pi);
    std::size_t total = 0;
    for (const auto& c : pi) total += c.indices.size();
    EXPECT_EQ(total, seq->totalPoints());
  }
}

// The motion method fills the densities for the record only, querying them at the ends of the
// k-NN edges across parts and near each part's densest point: on a chain of three moving boxes
// every adjacent pair has a saddle, no saddle is denser than either side's mode, and the modes
// are the densest queried points (so at least as dense as any saddle of theirs). Asked for 3
// parts, the clustering merges two of the boxes in its first phase (sample level); a sliver
// of 7 or 15 reference points used to fill the third label, and since slivers no longer count
// as parts the result has 2 parts (docs/mean_shift_experiments.md, "Slivers do not count as
// parts").
TEST(MeanShift, MotionMethodSaddlesBelowBothModes) {
  const auto r = run(boxChain(), threePartsByMotion());
  ASSERT_GE(r.num_clusters, 2);
  ASSERT_LE(r.num_clusters, 3);
  // Every adjacent pair of parts has a saddle.
  ASSERT_GE(r.saddles.size(), static_cast<std::size_t>(r.num_clusters - 1));
  for (const auto& s : r.saddles) {
    EXPECT_GT(s.density, 0.0);
    EXPECT_LE(s.density, std::min(r.mode_density[s.a], r.mode_density[s.b]) + 1e-6);
  }
  for (double d : r.mode_density) EXPECT_GT(d, 0.0);
}

// The density record is optional for the motion method: without it the labels and the
// recorded merges are the same, the densities are 0 and there are no modes or saddles.
TEST(MeanShift, MotionMethodDensityRecordIsOptional) {
  const auto seq = boxChain();
  seg::MeanShiftParams p = threePartsByMotion();
  const auto with = run(seq, p);
  p.record_densities = false;
  const auto without = run(seq, p);
  ASSERT_GE(with.num_clusters, 2);
  EXPECT_EQ(without.num_clusters, with.num_clusters);
  EXPECT_EQ(without.labels, with.labels);
  EXPECT_FALSE(with.merges.empty());
  EXPECT_EQ(without.merges, with.merges);
  EXPECT_FALSE(with.saddles.empty());
  EXPECT_TRUE(without.saddles.empty());
  EXPECT_EQ(without.modes.rows(), 0);
  ASSERT_EQ(static_cast<int>(without.mode_density.size()), without.num_clusters);
  for (double d : without.mode_density) EXPECT_EQ(d, 0.0);
  for (double d : with.mode_density) EXPECT_GT(d, 0.0);
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
  p = seg::MeanShiftParams();
  p.crease_cost = -1.0;
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  p = seg::MeanShiftParams();
  p.border_smoothness = std::numeric_limits<double>::quiet_NaN();
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  p = seg::MeanShiftParams();
  p.refine_iterations = -1;
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  p = seg::MeanShiftParams();
  p.gkdtree.leaf_extent = 0.0f;
  EXPECT_THROW(run(seq, p), pcl_animseg::Error);
  p = seg::MeanShiftParams();
  p.gkdtree.min_leaf_points = 0;
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

// The Gaussian kd-tree's sampling factor N/M is reported, and a least cell size raises it; the
// exact backend and the motion method run no filter.
TEST(MeanShift, ReportsTheFiltersSamplingFactor) {
  auto seq = twoBlobs(4, 5);
  seg::MeanShiftParams p;
  p.method = seg::MeanShiftMethod::Paper;
  p.bandwidth = 0.2;
  const double plain = run(seq, p).sampling_factor;
  EXPECT_GT(plain, 1.0);
  p.gkdtree.min_leaf_points = 400;
  const seg::SegmentationResult big = run(seq, p);
  EXPECT_GE(big.sampling_factor, 200.0);
  EXPECT_GT(big.sampling_factor, plain);
  p.backend = seg::MeanShiftBackend::Exact;
  EXPECT_EQ(run(seq, p).sampling_factor, 0.0);
  EXPECT_EQ(run(seq, threePartsByMotion()).sampling_factor, 0.0);
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

namespace {

// The grouping as it was (every group against every kept mode): the reference for the indexed
// version on small inputs.
void groupModesBruteForce(const Eigen::MatrixXf& y, const Eigen::RowVectorXf& metric,
                          const Eigen::VectorXf& density, double radius, std::vector<int>& labels,
                          std::vector<int>& mode_rep) {
  const Eigen::Index n = y.rows();
  const Eigen::MatrixXf ys = y.array().rowwise() * metric.array();
  const float cell = static_cast<float>(radius / 5.0);
  std::map<std::vector<int>, int> cell_group;
  std::vector<int> group_of(n), group_rep;
  for (Eigen::Index i = 0; i < n; ++i) {
    std::vector<int> key(y.cols());
    for (Eigen::Index c = 0; c < y.cols(); ++c)
      key[c] = static_cast<int>(std::floor(ys(i, c) / cell));
    auto it = cell_group.find(key);
    if (it == cell_group.end()) {
      it = cell_group.emplace(key, static_cast<int>(group_rep.size())).first;
      group_rep.push_back(static_cast<int>(i));
    } else if (density[i] > density[group_rep[it->second]]) {
      group_rep[it->second] = static_cast<int>(i);
    }
    group_of[i] = it->second;
  }
  std::vector<int> order(group_rep.size());
  for (std::size_t g = 0; g < order.size(); ++g) order[g] = static_cast<int>(g);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) {
    return density[group_rep[a]] > density[group_rep[b]];
  });
  const float r2 = static_cast<float>(radius * radius);
  mode_rep.clear();
  std::vector<int> group_mode(group_rep.size(), -1);
  for (int g : order) {
    int found = -1;
    for (std::size_t m = 0; m < mode_rep.size() && found < 0; ++m)
      if ((ys.row(mode_rep[m]) - ys.row(group_rep[g])).squaredNorm() < r2)
        found = static_cast<int>(m);
    if (found < 0) {
      found = static_cast<int>(mode_rep.size());
      mode_rep.push_back(group_rep[g]);
    }
    group_mode[g] = found;
  }
  labels.resize(n);
  for (Eigen::Index i = 0; i < n; ++i) labels[i] = group_mode[group_of[i]];
}

}  // namespace

TEST(MeanShift, IndexedModeGroupingEqualsTheAllPairsScan) {
  // End points as mean shift leaves them: tight clumps at the modes plus scattered unconverged
  // points, in 12-D, with chains of clumps closer than the merge radius (order matters there).
  std::mt19937 rng(7);
  std::normal_distribution<float> g(0.0f, 1.0f);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  for (int trial = 0; trial < 4; ++trial) {
    const int d = 12, n = 3000;
    Eigen::MatrixXf centres(40, d);
    for (int c = 0; c < 40; ++c)
      for (int k = 0; k < d; ++k) centres(c, k) = (k < 3 ? 0.6f : 0.05f) * g(rng);
    Eigen::MatrixXf y(n, d);
    Eigen::VectorXf density(n);
    for (int i = 0; i < n; ++i) {
      const int c = static_cast<int>(u(rng) * 40) % 40;
      const float spread = u(rng) < 0.1f ? 0.3f : 0.002f;
      for (int k = 0; k < d; ++k) y(i, k) = centres(c, k) + spread * g(rng);
      density[i] = 1.0f + c + u(rng);
    }
    Eigen::RowVectorXf metric = Eigen::RowVectorXf::Constant(d, 4.0f);
    const double radius = 0.3 + 0.2 * trial;
    std::vector<int> la, ma, lb, mb;
    seg::groupModes(y, metric, density, radius, la, ma);
    groupModesBruteForce(y, metric, density, radius, lb, mb);
    EXPECT_EQ(la, lb) << "trial " << trial;
    EXPECT_EQ(ma, mb) << "trial " << trial;
    EXPECT_GT(ma.size(), 3u);
  }
  std::vector<int> l, m;
  EXPECT_THROW(seg::groupModes(Eigen::MatrixXf::Zero(3, 2), Eigen::RowVectorXf::Ones(2),
                               Eigen::VectorXf::Ones(2), 0.5, l, m),
               pcl_animseg::Error);
}

namespace {

// A joint space of plain 6-D points (unit metric, no keypoints): `blob` points within about one
// bandwidth of the origin, then `spread` points uniformly in a cube of side `side` bandwidths.
seg::detail::JointSpace kernelSpace(int blob, int spread, float side, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 0.4f);
  std::uniform_real_distribution<float> u(-0.5f * side, 0.5f * side);
  seg::detail::JointSpace s;
  s.z.resize(blob + spread, 6);
  for (int i = 0; i < blob + spread; ++i)
    for (int k = 0; k < 6; ++k) s.z(i, k) = i < blob ? g(rng) : u(rng);
  s.metric_plain = s.metric_key = Eigen::RowVectorXf::Ones(6);
  s.keypoint.assign(blob + spread, 0);
  s.offsets = {0, static_cast<std::size_t>(blob + spread)};
  return s;
}

// The refinement's exact sums (a cache margin: neighbour lists kept between steps, long lists
// and dense data summed by chunks of the data in parallel) against the plain exact backend's
// (a tree search per query), over three steps: a first, a small move that reuses the lists, and
// a move beyond the margin that renews them. Also the same bits with one thread and with two.
// Returns the densities at the queries' first positions.
Eigen::VectorXf expectCachedSumsExact(const seg::detail::JointSpace& space, int queries,
                                      unsigned seed) {
  const Eigen::Index n = space.z.rows();
  Eigen::MatrixXf values(n, 7);
  values << space.z, Eigen::VectorXf::Ones(n);
  seg::MeanShiftParams p;
  p.backend = seg::MeanShiftBackend::Exact;
  const seg::detail::JointKernelSum plain(space, values, p);
  const seg::detail::JointKernelSum cached(space, values, p, 0.5f);
  const seg::detail::JointKernelSum cached1(space, values, p, 0.5f);
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  Eigen::MatrixXf y(queries, 6);
  std::vector<int> rows(queries);
  for (int r = 0; r < queries; ++r) {
    rows[r] = r;
    y.row(r) = space.z.row((r * 7919) % n);  // in the blob and among the spread points
  }
  Eigen::VectorXf density;
  for (const float move : {0.0f, 0.1f, 1.5f}) {
    for (int r = 0; r < queries; ++r)
      for (int k = 0; k < 6; ++k) y(r, k) += move * g(rng) / std::sqrt(6.0f);
    Eigen::MatrixXf a(queries, 7), b(queries, 7), c(queries, 7);
    plain.evaluate(y, rows, {}, a);
    // Two threads against one, whatever the machine's core count.
    const int threads = omp_get_max_threads();
    omp_set_num_threads(2);
    cached.evaluate(y, rows, {}, b);
    omp_set_num_threads(1);
    cached1.evaluate(y, rows, {}, c);
    omp_set_num_threads(threads);
    if (density.size() == 0) density = a.col(6);
    for (int r = 0; r < queries; ++r) {
      for (int k = 0; k < 7; ++k) {
        EXPECT_NEAR(b(r, k), a(r, k), 1e-5f * std::max(1.0f, std::abs(a(r, k))))
            << "query " << r << ", value " << k << ", move " << move;
        EXPECT_EQ(b(r, k), c(r, k)) << "query " << r << ", value " << k << ": threads matter";
      }
    }
  }
  return density;
}

}  // namespace

// Dense data (a query's lists would hold most points): every query scans the whole data.
TEST(MeanShiftKernelSums, CachedSumsAreExactOnDenseData) {
  const Eigen::VectorXf f = expectCachedSumsExact(kernelSpace(6000, 0, 0.0f, 3), 24, 4);
  EXPECT_GT(f.minCoeff(), 500.0f);  // thousands of points within 3 of every query
}

// Sparse data: each query sums its own short neighbour list.
TEST(MeanShiftKernelSums, CachedSumsAreExactOnSparseData) {
  const Eigen::VectorXf f = expectCachedSumsExact(kernelSpace(0, 20000, 12.0f, 5), 24, 6);
  EXPECT_GE(f.minCoeff(), 1.0f);  // each query sits on a data point...
  EXPECT_LT(f.maxCoeff(), 50.0f);  // ...with few others near it
}

// A dense blob in sparse data: the blob's queries have lists longer than the chunk threshold
// (summed by chunks of the data, part scanned and part from the list), the others short ones.
TEST(MeanShiftKernelSums, CachedSumsAreExactWithLongAndShortLists) {
  const Eigen::VectorXf f = expectCachedSumsExact(kernelSpace(12000, 36000, 14.0f, 7), 24, 8);
  EXPECT_GT(f.maxCoeff(), 1000.0f);  // queries in the blob
  EXPECT_LT(f.minCoeff(), 50.0f);    // queries among the spread points
}

namespace {

// Exact sums summed point by point (no keypoints), counting its calls.
class BruteForceSums : public seg::DeviceExactSums {
 public:
  BruteForceSums(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric, int* calls)
      : z_(z), metric_(metric), calls_(calls) {}
  void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows, const std::vector<char>&,
                Eigen::MatrixXf& out) override {
    ++*calls_;
    for (int r : rows) {
      Eigen::VectorXd acc = Eigen::VectorXd::Zero(z_.cols() + 1);
      for (Eigen::Index j = 0; j < z_.rows(); ++j) {
        const double d2 = (q.row(r) - z_.row(j)).cwiseProduct(metric_).squaredNorm();
        if (!(d2 < 9.0)) continue;
        const double w = std::exp(-0.5 * d2);
        acc.head(z_.cols()) += w * z_.row(j).transpose().cast<double>();
        acc[z_.cols()] += w;
      }
      out.row(r) = acc.transpose().cast<float>();
    }
  }

 private:
  Eigen::MatrixXf z_;
  Eigen::RowVectorXf metric_;
  int* calls_;
};

// A device whose only work is exact sums: its filter "iteration" leaves every point where it is
// (so that the refinement's exact steps do all of the mean shift) and its densities are exact.
class ExactSumsDevice : public seg::MeanShiftDeviceBackend {
 public:
  std::string name() const override { return "exact sums device"; }
  void seekModes(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric,
                 const Eigen::RowVectorXf& key_metric, const std::vector<char>& keypoint,
                 const seg::MeanShiftParams& params, Eigen::MatrixXf& y,
                 Eigen::VectorXf& density) override {
    y = z;
    this->density(z, metric, key_metric, keypoint, params, z, {}, density);
  }
  void density(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric,
               const Eigen::RowVectorXf&, const std::vector<char>&, const seg::MeanShiftParams&,
               const Eigen::MatrixXf& q, const std::vector<char>&, Eigen::VectorXf& out) override {
    int ignored = 0;
    BruteForceSums sums(z, metric, &ignored);
    std::vector<int> rows(q.rows());
    std::iota(rows.begin(), rows.end(), 0);
    Eigen::MatrixXf o(q.rows(), z.cols() + 1);
    sums.evaluate(q, rows, {}, o);
    out = o.col(z.cols());
  }
  std::unique_ptr<seg::DeviceExactSums> exactSums(const Eigen::MatrixXf& z,
                                                  const Eigen::RowVectorXf& metric,
                                                  const Eigen::RowVectorXf&,
                                                  const std::vector<char>&) override {
    if (!offer_sums) return nullptr;
    return std::make_unique<BruteForceSums>(z, metric, &calls);
  }
  int calls = 0;
  bool offer_sums = true;
};

/** Whether two labellings are the same partition of the points. */
bool samePartition(const seg::SegmentationResult& a, const seg::SegmentationResult& b) {
  std::map<int, int> ab, ba;
  for (std::size_t t = 0; t < a.labels.size(); ++t)
    for (std::size_t j = 0; j < a.labels[t].size(); ++j) {
      const int x = a.labels[t][j], y = b.labels[t][j];
      if (ab.emplace(x, y).first->second != y) return false;
      if (ba.emplace(y, x).first->second != x) return false;
    }
  return true;
}

}  // namespace

// A device's exact sums (MeanShiftDeviceBackend::exactSums) run the exact backend's iteration and
// the Gaussian kd-tree backend's exact refinement: the same clusters as the same steps summed on
// the CPU.
TEST(MeanShift, DeviceExactSumsRunTheExactSteps) {
  const auto seq = twoBlobs(3, 7);
  seg::MeanShiftParams p;
  p.method = seg::MeanShiftMethod::Paper;
  p.bandwidth = 0.3;
  auto segment = [&](const std::shared_ptr<ExactSumsDevice>& device) {
    seg::MeanShiftSegmentation ms;
    ms.setInputSequence(seq);
    ms.setParams(p);
    if (device) ms.setDeviceBackend(device);
    seg::SegmentationResult r;
    ms.segment(r);
    EXPECT_EQ(ms.deviceUsed(), device ? "exact sums device" : "cpu");
    return r;
  };
  auto expectSame = [](const seg::SegmentationResult& a, const seg::SegmentationResult& b) {
    EXPECT_GE(a.num_clusters, 2);
    EXPECT_EQ(a.num_clusters, b.num_clusters);
    EXPECT_TRUE(samePartition(a, b));
    ASSERT_EQ(a.mode_density.size(), b.mode_density.size());
    for (std::size_t c = 0; c < a.mode_density.size(); ++c)
      EXPECT_NEAR(a.mode_density[c], b.mode_density[c], 1e-3 * b.mode_density[c]);
  };
  {
    SCOPED_TRACE("exact backend");
    p.backend = seg::MeanShiftBackend::Exact;
    auto device = std::make_shared<ExactSumsDevice>();
    const seg::SegmentationResult on_device = segment(device);
    EXPECT_GT(device->calls, 2);  // the iteration's steps went through it
    expectSame(on_device, segment(nullptr));
  }
  {
    // The device's "filter" leaves the points where they are: the refinement's exact steps do
    // all of the mean shift, summed on the device or (a device without exact sums) on the CPU.
    SCOPED_TRACE("Gaussian kd-tree backend, exact refinement");
    p.backend = seg::MeanShiftBackend::GaussianKdTree;
    auto device = std::make_shared<ExactSumsDevice>();
    auto without = std::make_shared<ExactSumsDevice>();
    without->offer_sums = false;
    const seg::SegmentationResult on_device = segment(device);
    EXPECT_GT(device->calls, 2);
    expectSame(on_device, segment(without));
    EXPECT_EQ(without->calls, 0);
  }
}

// The caller's work beside the motion method's chains (setBesideChains): it runs once,
// on a thread of its own, and the labels are those of a run without it.
TEST(MeanShift, WorkBesideTheDeviceChainsRunsOnItsOwnThread) {
  const auto seq = boxChain();
  const seg::SegmentationResult plain = run(seq, threePartsByMotion());
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  ms.setParams(threePartsByMotion());
  int runs = 0;
  std::thread::id where;
  ms.setBesideChains([&] {
    ++runs;
    where = std::this_thread::get_id();
  });
  seg::SegmentationResult r;
  ms.segment(r);
  EXPECT_EQ(runs, 1);
  EXPECT_NE(where, std::this_thread::get_id());
  EXPECT_EQ(r.labels, plain.labels);
  // The paper method has no chains of tracks: the work does not run.
  seg::MeanShiftParams paper;
  paper.method = seg::MeanShiftMethod::Paper;
  ms.setParams(paper);
  ms.segment(r);
  EXPECT_EQ(runs, 1);
}
