#pragma once
// A RigidFitDevice on the CPU for tests: it copies what it is given (trees, normals in leaf
// order, sources), as a GPU uploads it, and fits each job from those copies with the CPU's
// arithmetic (fitRigidJob). What it records shows that the fits came in batches.
#include <pcl_animseg/error.h>
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_check.h>
#include <pcl_animseg/segmentation/rigid_motion.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>
#include <thread>
#include <vector>

namespace animseg_test {

class CpuRigidDevice : public pcl_animseg::segmentation::RigidFitDevice {
 public:
  std::string name() const override { return "cpu-test"; }
  void setSurfaces(const pcl_animseg::segmentation::DeviceFrames& s) override {
    trees.clear();
    normals.clear();
    for (const auto& f : s.frames) {
      trees.push_back(*f.tree);
      normals.push_back(f.normals());
    }
  }
  void setSources(const std::vector<const std::vector<double>*>& s) override {
    sources.clear();
    for (const auto* x : s) sources.push_back(*x);
  }
  void fit(const std::vector<pcl_animseg::segmentation::RigidFitJob>& jobs,
           const pcl_animseg::segmentation::RigidMotionParams& p, std::vector<double>& poses,
           std::vector<double>& rms) override {
    if (fail) throw pcl_animseg::Error("test device: kernel failed");
    ++batches;
    fit_thread = std::this_thread::get_id();
    fits += static_cast<int>(jobs.size());
    poses.assign(12 * jobs.size(), 0.0);
    rms.assign(jobs.size(), 0.0);
    for (std::size_t j = 0; j < jobs.size(); ++j) {
      const auto& job = jobs[j];
      wide += job.wide;
      pcl_animseg::segmentation::fitRigidJob(sources.at(job.source), trees.at(job.surface),
                                             normals.at(job.surface), job, p, &poses[12 * j],
                                             rms[j]);
    }
  }
  // The starts' scores from the copies (offer_scores), with rigidScore.
  bool scores(const std::vector<pcl_animseg::segmentation::RigidScoreJob>& jobs,
              std::vector<double>& out) override {
    if (!offer_scores) return false;
    if (fail) throw pcl_animseg::Error("test device: score kernel failed");
    ++score_batches;
    out.clear();
    for (const auto& j : jobs)
      out.push_back(pcl_animseg::segmentation::rigidScore(sources.at(j.source), j.probes,
                                                          trees.at(j.surface), j.pose));
    return true;
  }
  // The k-NN from copies of the trees (as a GPU uploads them), with FlatKdTree3::knn.
  bool knn(const std::vector<const pcl_animseg::FlatKdTree3*>& t, int k,
           const std::vector<float>& queries, const std::vector<int>& tree_of,
           std::vector<int>& rows, std::vector<int>& count) override {
    if (!offer_knn) return false;
    std::vector<pcl_animseg::FlatKdTree3> copies;
    for (const auto* x : t) copies.push_back(*x);
    search(copies, k, queries, tree_of, rows, count);
    return true;
  }
  // Copies of the trees kept for knnOn() (offer_keep), under a new token each time.
  long long keepKnnTrees(const std::vector<const pcl_animseg::FlatKdTree3*>& t) override {
    if (!offer_knn || !offer_keep) return 0;
    if (fail_knn) throw pcl_animseg::Error("test device: k-NN upload failed");
    kept.clear();
    for (const auto* x : t) kept.push_back(*x);
    return token = ++keeps;
  }
  bool knnOn(long long tok, int k, const std::vector<float>& queries,
             const std::vector<int>& tree_of, std::vector<int>& rows,
             std::vector<int>& count) override {
    if (!offer_knn || !offer_keep || tok <= 0 || tok != token) return false;
    search(kept, k, queries, tree_of, rows, count);
    ++knn_on_calls;
    return true;
  }
  void dropKnnTrees(long long tok) override {
    if (tok <= 0 || tok != token) return;
    kept.clear();
    token = 0;
  }
  // The motion check against the kept copies (offer_motion), as a GPU computes it: each copy's
  // nearest point by the copies' walk, its normal by its row (motion_check.h).
  bool motionResiduals(long long tok, const pcl_animseg::segmentation::MotionCheckJobs& jobs,
                       std::vector<float>& out) override {
    if (!offer_knn || !offer_keep || !offer_motion || tok <= 0 || tok != token) return false;
    out = cpuMotionResiduals(kept, jobs);
    ++motion_calls;
    return true;
  }
  // FlatKdTree3::within from each query against the kept copies (offer_least), each row's least
  // squared distance, as a GPU keeps it.
  bool leastDistances(long long tok, const std::vector<float>& queries,
                      const std::vector<int>& tree_of, const std::vector<float>& bound2,
                      std::vector<float>& out) override {
    if (!offer_knn || !offer_keep || !offer_least || tok <= 0 || tok != token) return false;
    out = cpuLeastDistances(kept, queries, tree_of, bound2);
    ++least_calls;
    return true;
  }
  // The mixtures' EM on the cores (offer_mixtures), as a GPU computes it (math::gmmEM).
  bool fitMixtures(const std::vector<pcl_animseg::segmentation::MixtureFitJob>& jobs,
                   const pcl_animseg::math::GMMOptions& options) override {
    if (!offer_mixtures) return false;
    for (const auto& j : jobs) pcl_animseg::math::gmmEM(*j.points, options, *j.gmm);
    ++mixture_calls;
    return true;
  }
  static std::vector<float> cpuLeastDistances(const std::vector<pcl_animseg::FlatKdTree3>& trees,
                                              const std::vector<float>& queries,
                                              const std::vector<int>& tree_of,
                                              const std::vector<float>& bound2) {
    std::vector<std::size_t> first(trees.size() + 1, 0);
    for (std::size_t t = 0; t < trees.size(); ++t) first[t + 1] = first[t] + trees[t].size();
    std::vector<float> out(first.back(), std::numeric_limits<float>::infinity());
    for (std::size_t q = 0; q < tree_of.size(); ++q) {
      const float* x = &queries[3 * q];
      if (!std::isfinite(x[0]) || !std::isfinite(x[1]) || !std::isfinite(x[2])) continue;
      const std::size_t t = static_cast<std::size_t>(tree_of.at(q));
      trees.at(t).within(x, bound2.at(t), [&](float d2, int row) {
        float& m = out[first[t] + static_cast<std::size_t>(row)];
        m = std::min(m, d2);
      });
    }
    return out;
  }
  static std::vector<float> cpuMotionResiduals(
      const std::vector<pcl_animseg::FlatKdTree3>& trees,
      const pcl_animseg::segmentation::MotionCheckJobs& jobs) {
    namespace seg = pcl_animseg::segmentation;
    const std::size_t frames = trees.size(), n = jobs.part.size();
    std::vector<std::size_t> first(frames + 1, 0);
    for (std::size_t t = 0; t < frames; ++t) first[t + 1] = first[t] + trees[t].size();
    if (jobs.normals.size() != 3 * first[frames])
      throw pcl_animseg::Error("test device: a normal per tree row expected");
    std::vector<float> out(n, 0.0f);
    auto nearest = [&](int u, const float* q, double* p, double* nrm) {
      float d2 = 0.0f;
      const int leaf = trees[u].nearestLeaf(q, std::numeric_limits<float>::infinity(), d2);
      if (leaf < 0) return false;
      const float* pf = &trees[u].leafPoints()[3 * static_cast<std::size_t>(leaf)];
      const float* nf = &jobs.normals[3 * (first[u] + trees[u].leafRows()[leaf])];
      for (int c = 0; c < 3; ++c) p[c] = pf[c], nrm[c] = nf[c];
      return true;
    };
    for (std::size_t r = 0; r < n; ++r)
      out[r] = seg::motion_check::residualOf(
          &jobs.starts[3 * r], jobs.part[r], jobs.own[r], jobs.scored.data(),
          static_cast<int>(jobs.scored.size()), static_cast<int>(frames), jobs.motions.data(),
          jobs.valid.data(), jobs.spacing.data(), jobs.cap, nearest);
    return out;
  }
  void search(const std::vector<pcl_animseg::FlatKdTree3>& copies, int k,
              const std::vector<float>& queries, const std::vector<int>& tree_of,
              std::vector<int>& rows, std::vector<int>& count) {
    if (fail_knn) throw pcl_animseg::Error("test device: k-NN kernel failed");
    ++knn_calls;
    knn_thread = std::this_thread::get_id();
    knn_k.push_back(k);
    const std::size_t n = tree_of.size();
    rows.assign(n * k, -1);
    count.assign(n, 0);
    std::vector<int> r;
    std::vector<float> d;
    for (std::size_t q = 0; q < n; ++q) {
      count[q] = copies.at(tree_of[q]).knn(&queries[3 * q], k, r, d);
      std::copy(r.begin(), r.end(), rows.begin() + q * k);
    }
  }
  bool offer_keep = true;    // keepKnnTrees / knnOn offered (with offer_knn)
  bool offer_motion = true;  // motionResiduals offered (with offer_keep)
  bool offer_least = true;   // leastDistances offered (with offer_keep)
  bool offer_mixtures = true;  // fitMixtures offered
  int keeps = 0, knn_on_calls = 0, motion_calls = 0, least_calls = 0, mixture_calls = 0;
  long long token = 0;
  std::vector<pcl_animseg::FlatKdTree3> kept;
  bool offer_knn = true, fail_knn = false;
  int knn_calls = 0;
  std::vector<int> knn_k;  // each call's k
  std::vector<pcl_animseg::FlatKdTree3> trees;
  std::vector<std::vector<float>> normals;
  std::vector<std::vector<double>> sources;
  int batches = 0, fits = 0, wide = 0, score_batches = 0;
  bool fail = false, offer_scores = true;
  std::thread::id fit_thread, knn_thread;  // of the last fit and k-NN calls
};

// Kept trees and a motion check over them for tests (RigidFitDevice::motionResiduals): `frames`
// trees of base + step t random points in [-1, 1]^3, each row with a random unit normal; every
// frame scored but frame frames / 2; per part and frame a rotation about a fixed axis and a
// shift, part 1's motion invalid in odd frames; `residuals` starts, every 7th far (30 times) from
// every point, so that all its terms are capped.
struct MotionCheckCase {
  std::vector<pcl_animseg::FlatKdTree3> trees;
  pcl_animseg::segmentation::MotionCheckJobs jobs;
};

inline MotionCheckCase randomMotionCheck(unsigned seed, int frames, int parts, int base, int step,
                                         int residuals) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  MotionCheckCase c;
  c.trees.resize(frames);
  auto& jobs = c.jobs;
  for (int t = 0; t < frames; ++t) {
    std::vector<float> xyz;
    const int n = base + step * t;
    for (int i = 0; i < 3 * n; ++i) xyz.push_back(u(rng));
    c.trees[t].build(xyz.data(), n);
    for (int i = 0; i < n; ++i) {  // by row: the order the points were given
      const float nx = u(rng), ny = u(rng), nz = u(rng);
      const float len = std::sqrt(nx * nx + ny * ny + nz * nz);
      jobs.normals.insert(jobs.normals.end(), {nx / len, ny / len, nz / len});
    }
    jobs.spacing.push_back(0.02 + 0.003 * t);
    if (t != frames / 2) jobs.scored.push_back(t);
  }
  for (int l = 0; l < parts; ++l)
    for (int t = 0; t < frames; ++t) {
      const Eigen::Matrix3d r =
          Eigen::AngleAxisd(0.2 * l - 0.15 * t, Eigen::Vector3d(3, -1, 2).normalized())
              .toRotationMatrix();
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) jobs.motions.push_back(r(i, j));
      for (int i = 0; i < 3; ++i) jobs.motions.push_back(0.05 * (t - l) - 0.02 * i);
      jobs.valid.push_back(!(l == 1 && t % 2 == 1));
    }
  jobs.cap = 3.0;
  for (int r = 0; r < residuals; ++r) {
    const double scale = r % 7 == 0 ? 30.0 : 1.0;
    jobs.starts.insert(jobs.starts.end(), {scale * u(rng), scale * u(rng), scale * u(rng)});
    jobs.part.push_back(r % parts);
    jobs.own.push_back((r / parts) % frames);
  }
  return c;
}

}  // namespace animseg_test
