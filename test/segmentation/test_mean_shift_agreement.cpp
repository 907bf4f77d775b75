// The Gaussian kd-tree backend against the exact one (issue: ARI >= 0.95 between them), on a
// generated sequence of moving capsules (a body and four limbs swinging about their joints),
// sampled afresh in every frame with +-20% points.
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/segmentation/mean_shift.h>

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

namespace seg = pcl_animseg::segmentation;
using pcl_animseg::PointCloudSequence;

namespace {

struct Capsule {
  Eigen::Vector3d a, b;  // axis end points
  double radius;
};

/** A point uniformly on the surface of a capsule (cylinder + two hemispheres), with its normal. */
void sampleCapsule(const Capsule& c, std::mt19937& rng, Eigen::Vector3d& p, Eigen::Vector3d& n) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::normal_distribution<double> g(0.0, 1.0);
  const Eigen::Vector3d axis = c.b - c.a;
  const double len = axis.norm();
  const Eigen::Vector3d dir = axis / len;
  const double cyl = 2.0 * M_PI * c.radius * len, sph = 4.0 * M_PI * c.radius * c.radius;
  if (u(rng) * (cyl + sph) < cyl) {
    const Eigen::Vector3d e1 = dir.unitOrthogonal(), e2 = dir.cross(e1);
    const double phi = 2.0 * M_PI * u(rng);
    n = std::cos(phi) * e1 + std::sin(phi) * e2;
    p = c.a + u(rng) * axis + c.radius * n;
  } else {
    n = Eigen::Vector3d(g(rng), g(rng), g(rng)).normalized();
    p = (n.dot(dir) > 0 ? c.b : c.a) + c.radius * n;
  }
}

/** Body + 4 limbs; limbs swing by up to `swing` radians about their hip over the sequence, the
 * whole figure walks `drift` per frame along x. truth: the capsule of each point. */
PointCloudSequence::Ptr walkingFigure(int frames, int points, double swing, double drift,
                                      unsigned seed, std::vector<int>& truth) {
  auto seq = std::make_shared<PointCloudSequence>();
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  truth.clear();
  for (int t = 0; t < frames; ++t) {
    const double phase = 2.0 * M_PI * t / frames;
    const Eigen::Vector3d shift(drift * t, 0.0, 0.0);
    std::vector<Capsule> parts;
    parts.push_back({Eigen::Vector3d(-1.0, 0, 1.2) + shift, Eigen::Vector3d(1.0, 0, 1.2) + shift,
                     0.35});
    const double hips[4][2] = {{-0.8, 0.4}, {-0.8, -0.4}, {0.8, 0.4}, {0.8, -0.4}};
    for (int l = 0; l < 4; ++l) {
      const double ang = swing * std::sin(phase + (l % 2 ? M_PI : 0.0) + (l / 2) * 0.5);
      const Eigen::Vector3d hip = Eigen::Vector3d(hips[l][0], hips[l][1], 0.85) + shift;
      const Eigen::Vector3d foot = hip + Eigen::Vector3d(std::sin(ang), 0.0, -std::cos(ang)) * 0.9;
      parts.push_back({hip, foot, 0.14});
    }
    std::vector<double> area;
    double total = 0.0;
    for (const auto& c : parts) {
      const double a = 2.0 * M_PI * c.radius * (c.b - c.a).norm() + 4.0 * M_PI * c.radius * c.radius;
      area.push_back(a);
      total += a;
    }
    const int n = static_cast<int>(points * (0.8 + 0.4 * u(rng)));
    PointCloudSequence::Cloud::Ptr cloud(new PointCloudSequence::Cloud);
    for (int i = 0; i < n; ++i) {
      double r = u(rng) * total;
      int k = 0;
      while (k + 1 < static_cast<int>(parts.size()) && r > area[k]) r -= area[k++];
      Eigen::Vector3d p, nrm;
      sampleCapsule(parts[k], rng, p, nrm);
      pcl::PointNormal q;
      q.x = static_cast<float>(p.x());
      q.y = static_cast<float>(p.y());
      q.z = static_cast<float>(p.z());
      q.normal_x = static_cast<float>(nrm.x());
      q.normal_y = static_cast<float>(nrm.y());
      q.normal_z = static_cast<float>(nrm.z());
      cloud->push_back(q);
      truth.push_back(k);
    }
    seq->addFrame(cloud, "f" + std::to_string(t));
  }
  return seq;
}

std::vector<int> pooled(const seg::SegmentationResult& r) {
  std::vector<int> out;
  for (const auto& f : r.labels) out.insert(out.end(), f.begin(), f.end());
  return out;
}

seg::SegmentationResult runPaper(const PointCloudSequence::Ptr& seq, seg::MeanShiftBackend b,
                                 const seg::MeanShiftParams& base) {
  seg::MeanShiftParams p = base;
  p.method = seg::MeanShiftMethod::Paper;
  p.backend = b;
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(seq);
  ms.setParams(p);
  seg::SegmentationResult r;
  ms.segment(r);
  return r;
}

}  // namespace

TEST(MeanShiftAgreement, GaussianKdTreeAgreesWithExact) {
  std::vector<int> truth;
  auto seq = walkingFigure(10, 700, 0.3, 0.03, 11, truth);
  // The issue asks for ARI >= 0.95. The reference is the exact backend run to convergence (300
  // iterations: with the default 60 it stops on slopes, 63 / 20 clusters instead of 32 / 5); the
  // Gaussian kd-tree backend runs with the stage's defaults (cells of its tree iterated, 150
  // exact refinement steps per group of end points). Reached: about 0.87 / 0.83 (see
  // docs/mean_shift_experiments.md); the bounds hold that, so that a regression shows. With
  // MeanShiftParams::exact_borders the goal is reached (0.9956 / 0.9901).
  const double bandwidths[2] = {0.1, 0.2}, floor_ari[2] = {0.84, 0.80};
  for (int b = 0; b < 2; ++b) {
    const double bandwidth = bandwidths[b];
    seg::MeanShiftParams p;  // the stage's defaults, Gaussian kd-tree included
    p.bandwidth = bandwidth;
    seg::MeanShiftParams converged = p;
    converged.max_iterations = 300;
    const auto exact = runPaper(seq, seg::MeanShiftBackend::Exact, converged);
    const auto gkd = runPaper(seq, seg::MeanShiftBackend::GaussianKdTree, p);
    const double ari = pcl_animseg::evaluation::adjustedRandIndex(pooled(exact), pooled(gkd));
    std::printf("bandwidth %.2f: exact %d clusters, gkdtree %d clusters, ARI between %.4f\n",
                bandwidth, exact.num_clusters, gkd.num_clusters, ari);
    EXPECT_GE(ari, floor_ari[b]) << "bandwidth " << bandwidth;
    EXPECT_GE(exact.num_clusters, 2);
    // With exact trajectories for the border points the goal is reached.
    seg::MeanShiftParams borders = p;
    borders.exact_borders = true;
    const auto gkd_borders = runPaper(seq, seg::MeanShiftBackend::GaussianKdTree, borders);
    const double ari_borders =
        pcl_animseg::evaluation::adjustedRandIndex(pooled(exact), pooled(gkd_borders));
    std::printf("bandwidth %.2f: gkdtree with exact borders %d clusters, ARI to exact %.4f\n",
                bandwidth, gkd_borders.num_clusters, ari_borders);
    EXPECT_GE(ari_borders, 0.95) << "bandwidth " << bandwidth;
  }
}

// Parameter sweep used to choose the defaults (not part of CI: run with
// --gtest_also_run_disabled_tests).
TEST(MeanShiftAgreement, DISABLED_Sweep) {
  auto envf = [](const char* name, double def) {
    const char* e = std::getenv(name);
    return e ? std::atof(e) : def;
  };
  std::vector<int> truth;
  auto seq = walkingFigure(10, 700, envf("SWEEP_SWING", 0.3), envf("SWEEP_DRIFT", 0.03), 11, truth);
  seg::MeanShiftParams p;
  p.bandwidth = envf("SWEEP_BW", 0.1);
  p.max_iterations = static_cast<int>(envf("SWEEP_IT", 60));
  const auto exact = runPaper(seq, seg::MeanShiftBackend::Exact, p);
  std::printf("exact: %d clusters, ARI to truth %.3f\n", exact.num_clusters,
              pcl_animseg::evaluation::adjustedRandIndex(pooled(exact), truth));
  for (float leaf : {1.0f, 0.5f})
    for (float sigma : {0.5f, 1.0f})
      for (int refine : {0, 10, 40}) {
        seg::MeanShiftParams q = p;
        q.gkdtree.leaf_extent = leaf;
        q.gkdtree.slice_sigma = sigma;
        q.refine_iterations = refine;
        const auto gkd = runPaper(seq, seg::MeanShiftBackend::GaussianKdTree, q);
        std::printf("leaf %.2f sigma %.1f refine %2d: %3d clusters ARI %.4f (truth %.3f)\n", leaf,
                    sigma, refine, gkd.num_clusters,
                    pcl_animseg::evaluation::adjustedRandIndex(pooled(exact), pooled(gkd)),
                    pcl_animseg::evaluation::adjustedRandIndex(pooled(gkd), truth));
        std::fflush(stdout);
      }
}

TEST(MeanShiftAgreement, DISABLED_ExactSensitivity) {
  std::vector<int> truth;
  auto seq = walkingFigure(10, 700, 0.3, 0.03, 11, truth);
  for (double bandwidth : {0.1, 0.2}) {
    seg::MeanShiftParams p;
    p.bandwidth = bandwidth;
    p.max_iterations = 300;
    const auto ref = runPaper(seq, seg::MeanShiftBackend::Exact, p);
    std::printf("bw %.2f exact: %d clusters, truth ARI %.4f\n", bandwidth, ref.num_clusters,
                pcl_animseg::evaluation::adjustedRandIndex(pooled(ref), truth));
    for (double f : {0.99, 1.01, 0.98, 1.02}) {
      seg::MeanShiftParams q = p;
      q.bandwidth = bandwidth * f;
      const auto r = runPaper(seq, seg::MeanShiftBackend::Exact, q);
      std::printf("  x%.2f: %d clusters, ARI to exact %.4f, truth %.4f\n", f, r.num_clusters,
                  pcl_animseg::evaluation::adjustedRandIndex(pooled(ref), pooled(r)),
                  pcl_animseg::evaluation::adjustedRandIndex(pooled(r), truth));
      std::fflush(stdout);
    }
    seg::MeanShiftParams g = p;
    g.max_iterations = 60;
    const auto gkd = runPaper(seq, seg::MeanShiftBackend::GaussianKdTree, g);
    std::printf("  gkdtree: %d clusters, ARI to exact %.4f, truth %.4f\n", gkd.num_clusters,
                pcl_animseg::evaluation::adjustedRandIndex(pooled(ref), pooled(gkd)),
                pcl_animseg::evaluation::adjustedRandIndex(pooled(gkd), truth));
    std::fflush(stdout);
  }
}
