// Mean shift stage benchmark (issue: 800k points x 30-D, Gaussian kd-tree backend <= 10 s on the
// 2-core CPU, >= 50x faster than exact, peak memory <= 2 GB).
//
//   bench_mean_shift [--points N] [--frames T] [--refine K] [--exact-every1 a] [--exact-every2 b]
//                    [--full 0|1] [--features synthetic|pipeline] [--plan P] [--bandwidth W]
//                    [--w4 W4] [--exact 0|1] [--min-leaf-points M] [--exact-borders 0|1|2]
//                    [--full-exact 0|1] [--device cpu|gpu]
//
// Runs MeanShiftSegmentation (paper method: every point iterated, so the cost is the kernel
// sums) on one of two 30-D inputs:
//  - synthetic (default): joint features that imitate an animated object as the GPU benchmark's
//    do: 10 rigid ellipsoid parts moving over T frames, normals, and a 24-D signature made of
//    random sinusoids of the surface position (6 + 24 = 30-D). These signatures crumple each
//    part's surface through 24 dimensions, so the data are sparse at the bandwidth (the filter's
//    cells hold N/M ~ 4 points at 800k and w = 0.1).
//  - pipeline: a generated articulated sequence (animseg_synth's body plan P, T frames, N/T
//    points a frame) with the pipeline's own features: scale space, DoG keypoints (the pair
//    rule of Eq. 5 applies) and the 24-D signatures of Sect. 3.1. Real signatures vary slowly
//    over a surface, so the data are dense: with the paper's bandwidth (w = 0.3) the filter's
//    cells hold N/M ~ 760 points at 800k, the paper's regime (1024-8192).
// --min-leaf-points M: the Gaussian kd-tree splits no cell of fewer than M points, so that N/M is
// at least about M/2 (the band is 1024-8192); on the subsamples M / k.
// --exact-borders 1: the Gaussian kd-tree runs with MeanShiftParams::exact_borders (border points
// follow exact trajectories); 2: the full run both without and with.
// --full-exact 1: the exact backend on all points too (with --device gpu: its sums on the GPU),
// and the ARI of each Gaussian kd-tree run to it.
// --device gpu: the stage with the CUDA backend (the filter, the exact sums and the densities on
// the GPU; where the CUDA module is built).
// Exact backend (--exact 0 skips it): too slow at 800k, so it runs on two per-frame subsamples and
// is extrapolated with the fitted power law (its cost grows faster than N: the neighbours within 3
// bandwidths grow with the density). Prints wall, user and system CPU time (the machine is shared:
// CPU time is the fairer number), peak RSS (getrusage) and, on the subsamples, the ARI between the
// two backends' labels. Plain program (not Google Benchmark): one run of each is what we record.
#include <pcl_animseg/evaluation/metrics.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/synth/articulated.h>
#ifdef PCL_ANIMSEG_HAVE_CUDA
#include <pcl_animseg/gpu/mean_shift_backend.h>
#endif

#include <sys/resource.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

namespace seg = pcl_animseg::segmentation;
using pcl_animseg::PointCloudSequence;

namespace {

struct Sample {
  PointCloudSequence::Ptr seq;
  std::vector<Eigen::MatrixXf> sig;
  std::vector<std::vector<int>> keypoints;  // empty: none
};

/** A generated articulated sequence with the pipeline's own features, computed on the whole
 * frames; every keep_every-th point of each frame is kept (with its signature and keypoint
 * flag), so that the subsamples are the full run's points. */
Sample makePipelineSequence(const std::string& plan, int n, int frames, int keep_every,
                            unsigned seed) {
  namespace synth = pcl_animseg::synth;
  synth::SynthParams sp;
  sp.plan = synth::bodyPlanFromString(plan);
  sp.frames = frames;
  sp.points = (n + frames - 1) / frames;
  sp.seed = seed;
  const PointCloudSequence full = synth::toSequence(synth::generate(sp));
  const pcl_animseg::SequenceFeatures f =
      pcl_animseg::computeSequenceFeatures(full, pcl_animseg::MultiscaleParams());
  Sample s;
  s.seq = std::make_shared<PointCloudSequence>();
  for (std::size_t t = 0; t < full.size(); ++t) {
    const auto& cloud = *full.frame(t);
    std::vector<char> key(cloud.size(), 0);
    for (int i : f.keypoints[t]) key[i] = 1;
    PointCloudSequence::Cloud::Ptr c(new PointCloudSequence::Cloud);
    std::vector<int> kept_keys;
    std::vector<int> rows;
    for (std::size_t i = 0; i < cloud.size(); i += keep_every) {
      if (key[i]) kept_keys.push_back(static_cast<int>(c->size()));
      c->push_back(cloud[i]);
      rows.push_back(static_cast<int>(i));
    }
    Eigen::MatrixXf m(rows.size(), f.signatures[t].cols());
    for (std::size_t r = 0; r < rows.size(); ++r) m.row(r) = f.signatures[t].row(rows[r]);
    s.sig.push_back(m);
    s.keypoints.push_back(kept_keys);
    s.seq->addFrame(c, full.name(t));
  }
  return s;
}

Sample makeSequence(int n, int frames, int keep_every, unsigned seed) {
  const int parts = 10, sd = 24;
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<Eigen::Vector3f> centre(parts), axes(parts), spin(parts);
  for (int k = 0; k < parts; ++k) {
    centre[k] = Eigen::Vector3f(u(rng), u(rng), u(rng)) * 0.8f;
    axes[k] = Eigen::Vector3f(0.25f + 0.1f * u(rng), 0.08f + 0.03f * u(rng), 0.08f + 0.03f * u(rng));
    spin[k] = Eigen::Vector3f(u(rng), u(rng), u(rng)).normalized();
  }
  Eigen::MatrixXf proj(sd, 6);
  for (int i = 0; i < proj.size(); ++i) proj(i) = 2.0f * g(rng);
  Sample s;
  s.seq = std::make_shared<PointCloudSequence>();
  const int per_frame = (n + frames - 1) / frames;
  for (int t = 0; t < frames; ++t) {
    PointCloudSequence::Cloud::Ptr c(new PointCloudSequence::Cloud);
    std::vector<Eigen::VectorXf> rows;
    for (int j = 0; j < per_frame && t * per_frame + j < n; ++j) {
      const int k = static_cast<int>(rng() % parts);
      Eigen::Vector3f dir(g(rng), g(rng), g(rng));
      dir.normalize();
      const Eigen::Vector3f local = dir.cwiseProduct(axes[k]);
      const Eigen::Vector3f nl = dir.cwiseQuotient(axes[k]).normalized();
      const Eigen::Matrix3f r =
          Eigen::AngleAxisf(0.6f * std::sin(0.3f * t + k), spin[k]).toRotationMatrix();
      const Eigen::Vector3f p = centre[k] + r * local + 0.005f * Eigen::Vector3f(g(rng), g(rng), 0);
      const Eigen::Vector3f nn = r * nl;
      Eigen::Matrix<float, 6, 1> a;
      a << local / 0.25f, nl;
      if (j % keep_every) continue;  // subsample after drawing: the same points as the full run
      pcl::PointNormal q;
      q.x = p.x();
      q.y = p.y();
      q.z = p.z();
      q.normal_x = nn.x();
      q.normal_y = nn.y();
      q.normal_z = nn.z();
      c->push_back(q);
      Eigen::VectorXf sg(sd);
      for (int cc = 0; cc < sd; ++cc) sg[cc] = 0.3f * std::sin(proj.row(cc).dot(a) + k);
      rows.push_back(sg);
    }
    Eigen::MatrixXf m(rows.size(), sd);
    for (std::size_t i = 0; i < rows.size(); ++i) m.row(i) = rows[i].transpose();
    s.sig.push_back(m);
    s.seq->addFrame(c, "f" + std::to_string(t));
  }
  return s;
}

double cpuSeconds() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return ru.ru_utime.tv_sec + 1e-6 * ru.ru_utime.tv_usec + ru.ru_stime.tv_sec +
         1e-6 * ru.ru_stime.tv_usec;
}
double peakRssMiB() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return ru.ru_maxrss / 1024.0;
}

struct Timing {
  double wall = 0.0, cpu = 0.0;
  int clusters = 0;
  std::vector<int> labels;  // flattened
};

Timing runStage(const Sample& s, seg::MeanShiftBackend backend, int refine, double bandwidth,
                double w4, int min_leaf_points, bool exact_borders = false, bool on_gpu = false) {
  seg::MeanShiftParams p;
  p.exact_borders = exact_borders;
  p.method = seg::MeanShiftMethod::Paper;
  p.backend = backend;
  p.refine_iterations = refine;
  p.bandwidth = bandwidth;
  p.w4 = w4;
  p.gkdtree.min_leaf_points = min_leaf_points;
  seg::MeanShiftSegmentation ms;
  ms.setInputSequence(s.seq);
  ms.setSignatures(s.sig);
  if (!s.keypoints.empty()) ms.setKeypoints(s.keypoints);
  ms.setParams(p);
  if (on_gpu) {
#ifdef PCL_ANIMSEG_HAVE_CUDA
    ms.setDeviceBackend(pcl_animseg::gpu::makeMeanShiftBackend());
#else
    throw std::runtime_error("--device gpu: built without the CUDA module");
#endif
  }
  seg::SegmentationResult r;
  const double c0 = cpuSeconds();
  const auto t0 = std::chrono::steady_clock::now();
  ms.segment(r);
  Timing t;
  t.wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  t.cpu = cpuSeconds() - c0;
  t.clusters = r.num_clusters;
  for (const auto& l : r.labels) t.labels.insert(t.labels.end(), l.begin(), l.end());
  return t;
}

const char* const kOptions[] = {
    "--points", "--frames",          "--refine",        "--exact-every1", "--exact-every2",
    "--full",   "--features",        "--plan",          "--bandwidth",    "--w4",
    "--exact",  "--min-leaf-points", "--exact-borders", "--full-exact",   "--device"};

/** Every argument is a known option followed by its value; anything else is an error. */
void checkArguments(int argc, char** argv) {
  for (int i = 1; i < argc; i += 2) {
    bool known = false;
    for (const char* o : kOptions) known = known || std::strcmp(argv[i], o) == 0;
    if (!known) {
      std::string list;
      for (const char* o : kOptions) list += std::string(list.empty() ? "" : " ") + o;
      throw std::runtime_error(std::string("unknown option '") + argv[i] + "' (options: " + list +
                               ")");
    }
    if (i + 1 >= argc) throw std::runtime_error(std::string(argv[i]) + " needs a value");
  }
}

const char* argText(int argc, char** argv, const char* name, const char* def) {
  for (int i = 1; i + 1 < argc; i += 2)
    if (std::strcmp(argv[i], name) == 0) return argv[i + 1];
  return def;
}
long argValue(int argc, char** argv, const char* name, long def) {
  const char* v = argText(argc, argv, name, nullptr);
  return v ? std::atol(v) : def;
}
double argReal(int argc, char** argv, const char* name, double def) {
  const char* v = argText(argc, argv, name, nullptr);
  return v ? std::atof(v) : def;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    std::setvbuf(stdout, nullptr, _IONBF, 0);
    checkArguments(argc, argv);
    const int n = static_cast<int>(argValue(argc, argv, "--points", 800000));
    const int frames = static_cast<int>(argValue(argc, argv, "--frames", 48));
    const int refine = static_cast<int>(
        argValue(argc, argv, "--refine", seg::MeanShiftParams().refine_iterations));
    const int sub1 = static_cast<int>(argValue(argc, argv, "--exact-every1", 80));
    const int sub2 = static_cast<int>(argValue(argc, argv, "--exact-every2", 40));
    const bool run_full = argValue(argc, argv, "--full", 1) != 0;
    const bool run_exact = argValue(argc, argv, "--exact", 1) != 0;
    const int borders_mode = static_cast<int>(argValue(argc, argv, "--exact-borders", 0));
    const bool borders = borders_mode == 1;
    const bool full_exact = argValue(argc, argv, "--full-exact", 0) != 0;
    const std::string device = argText(argc, argv, "--device", "cpu");
    if (device != "cpu" && device != "gpu") throw std::runtime_error("--device must be cpu or gpu");
    if (borders_mode < 0 || borders_mode > 2)
      throw std::runtime_error("--exact-borders must be 0, 1 or 2");
    const bool on_gpu = device == "gpu";
    const std::string features = argText(argc, argv, "--features", "synthetic");
    const std::string plan = argText(argc, argv, "--plan", "humanoid");
    const seg::MeanShiftParams defaults;
    const double bandwidth = argReal(argc, argv, "--bandwidth", defaults.bandwidth);
    const double w4 = argReal(argc, argv, "--w4", defaults.w4);
    const int min_leaf = static_cast<int>(
        argValue(argc, argv, "--min-leaf-points", defaults.gkdtree.min_leaf_points));
    if (features != "synthetic" && features != "pipeline")
      throw std::runtime_error("--features must be synthetic or pipeline");
    auto make = [&](int every) {
      return features == "pipeline" ? makePipelineSequence(plan, n, frames, every, 1)
                                    : makeSequence(n, frames, every, 1);
    };
    std::printf(
        "bench_mean_shift: %d points x 30-D, %d frames, paper method, %s features%s%s, "
        "w = %.3g, w4 = %.3g, device %s\n",
        n, frames, features.c_str(), features == "pipeline" ? " of a " : "",
        features == "pipeline" ? plan.c_str() : "", bandwidth, w4, device.c_str());
    if (run_full) {
      const Sample full = make(1);
      std::vector<Timing> runs;
      for (int b = 0; b < 2; ++b) {
        const bool with = borders_mode == 2 ? b == 1 : borders;
        if (b == 1 && borders_mode != 2) break;
        runs.push_back(runStage(full, seg::MeanShiftBackend::GaussianKdTree, refine, bandwidth, w4,
                                min_leaf, with, on_gpu));
        const Timing& g = runs.back();
        std::printf(
            "gkdtree (refine %d%s): wall %.2f s, user+sys %.2f s, %d clusters, peak RSS %.0f "
            "MiB\n",
            refine, with ? ", exact borders" : "", g.wall, g.cpu, g.clusters, peakRssMiB());
      }
      if (full_exact) {
        const Timing e =
            runStage(full, seg::MeanShiftBackend::Exact, 0, bandwidth, w4, 1, false, on_gpu);
        std::printf("exact, all points: wall %.2f s, user+sys %.2f s, %d clusters\n", e.wall, e.cpu,
                    e.clusters);
        for (std::size_t b = 0; b < runs.size(); ++b) {
          const bool with = borders_mode == 2 ? b == 1 : borders;
          std::printf("ARI gkdtree%s against exact: %.4f (wall ratio %.1fx)\n",
                      with ? " + exact borders" : "",
                      pcl_animseg::evaluation::adjustedRandIndex(e.labels, runs[b].labels),
                      e.wall / runs[b].wall);
        }
      }
    }
    if (!run_exact) {
      std::printf("peak RSS %.0f MiB\n", peakRssMiB());
      return 0;
    }
    // Exact on two subsamples (every k-th point of every frame), power-law extrapolation.
    double nn[2], cpu[2];
    const int every[2] = {sub1, sub2};
    for (int i = 0; i < 2; ++i) {
      const Sample s = make(every[i]);
      const Timing e =
          runStage(s, seg::MeanShiftBackend::Exact, 0, bandwidth, w4, 1, false, on_gpu);
      const Timing g = runStage(s, seg::MeanShiftBackend::GaussianKdTree, refine, bandwidth, w4,
                                std::max(1, min_leaf / every[i]),  // the full run's cells, thinned
                                borders, on_gpu);
      nn[i] = static_cast<double>(s.seq->totalPoints());
      cpu[i] = e.cpu;
      std::printf("subsample %.0f points: exact wall %.2f s user+sys %.2f s (%d clusters); "
                  "gkdtree wall %.2f s user+sys %.2f s (%d clusters); ARI between %.4f\n",
                  nn[i], e.wall, e.cpu, e.clusters, g.wall, g.cpu, g.clusters,
                  pcl_animseg::evaluation::adjustedRandIndex(e.labels, g.labels));
      if (e.clusters <= 12 && g.clusters <= 12) {  // where the two disagree
        std::vector<long> table(static_cast<std::size_t>(e.clusters) * g.clusters, 0);
        for (std::size_t i = 0; i < e.labels.size(); ++i)
          if (e.labels[i] >= 0 && g.labels[i] >= 0)
            ++table[static_cast<std::size_t>(e.labels[i]) * g.clusters + g.labels[i]];
        std::printf("  points by exact (rows) x gkdtree (columns) cluster:\n");
        for (int a = 0; a < e.clusters; ++a) {
          std::printf("   ");
          for (int b = 0; b < g.clusters; ++b)
            std::printf(" %7ld", table[static_cast<std::size_t>(a) * g.clusters + b]);
          std::printf("\n");
        }
      }
    }
    const double expo = std::log(cpu[1] / cpu[0]) / std::log(nn[1] / nn[0]);
    const double est = cpu[1] * std::pow(n / nn[1], expo);
    std::printf("exact extrapolated to %d points: user+sys %.0f s (exponent %.2f; linear lower "
                "bound %.0f s)\n",
                n, est, expo, cpu[1] * n / nn[1]);
    std::printf("peak RSS %.0f MiB\n", peakRssMiB());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}
