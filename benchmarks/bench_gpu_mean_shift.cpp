// GPU mean shift benchmark (Sect. 3.3): one mean-shift step and the whole run to convergence on
// N points x 30-D joint features (position, normal, a 24-D signature), the CPU Gaussian kd-tree
// on the same data in the same run for the ratio, and peak device memory.
//
//   bench_gpu_mean_shift [--points N] [--frames T] [--gpu 0|1] [--cpu 0|1] [--max-iterations K]
//
// The data imitate an animated object: rigid parts (ellipsoid surfaces) moving over T frames;
// the signature is a smooth function of the point's place on its part (rigid-invariant, as the
// paper's). Plain program (not Google Benchmark): one run of each is what we want to record.
#include <pcl_animseg/filters/gaussian_kdtree.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/gaussian_kdtree.h>
#include <pcl_animseg/gpu/mean_shift.h>

#include <Eigen/Geometry>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <numeric>
#include <random>
#include <string>
#include <vector>

namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// N x 30 raw joint features z = (p / s, n, sigma[24]).
Eigen::MatrixXf makeFeatures(int n, int frames, unsigned seed) {
  const int parts = 10, sd = 24;
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<Eigen::Vector3f> centre(parts), axes(parts), spin(parts);
  for (int k = 0; k < parts; ++k) {
    centre[k] = Eigen::Vector3f(u(rng), u(rng), u(rng)) * 0.8f;
    axes[k] = Eigen::Vector3f(0.25f + 0.1f * u(rng), 0.08f + 0.03f * u(rng),
                              0.08f + 0.03f * u(rng));
    spin[k] = Eigen::Vector3f(u(rng), u(rng), u(rng)).normalized();
  }
  Eigen::MatrixXf proj(sd, 6);
  for (int i = 0; i < proj.size(); ++i) proj(i) = 2.0f * g(rng);
  Eigen::MatrixXf z(n, 6 + sd);
  const int per_frame = (n + frames - 1) / frames;
  for (int i = 0; i < n; ++i) {
    const int t = i / per_frame, k = static_cast<int>(rng() % parts);
    Eigen::Vector3f dir(g(rng), g(rng), g(rng));
    dir.normalize();
    const Eigen::Vector3f local = dir.cwiseProduct(axes[k]);
    const Eigen::Vector3f nl = dir.cwiseQuotient(axes[k]).normalized();
    const Eigen::Matrix3f r =
        Eigen::AngleAxisf(0.6f * std::sin(0.3f * t + k), spin[k]).toRotationMatrix();
    const Eigen::Vector3f p = centre[k] + r * local + 0.005f * Eigen::Vector3f(g(rng), g(rng), 0);
    const Eigen::Vector3f nn = r * nl;
    z.block<1, 3>(i, 0) = p.transpose() / 2.0f;
    z.block<1, 3>(i, 3) = nn.transpose();
    Eigen::Matrix<float, 6, 1> a;
    a << local / 0.25f, nl;
    for (int c = 0; c < sd; ++c) z(i, 6 + c) = 0.3f * std::sin(proj.row(c).dot(a) + k);
  }
  return z;
}

long argValue(int argc, char** argv, const char* name, long def) {
  for (int i = 1; i + 1 < argc; ++i)
    if (std::strcmp(argv[i], name) == 0) return std::atol(argv[i + 1]);
  return def;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    const int n = static_cast<int>(argValue(argc, argv, "--points", 800000));
    const int frames = static_cast<int>(argValue(argc, argv, "--frames", 48));
    const bool cpu = argValue(argc, argv, "--cpu", 1) != 0;
    const bool use_gpu = argValue(argc, argv, "--gpu", 1) != 0;
    std::setvbuf(stdout, nullptr, _IONBF, 0);  // lines survive a time limit
    const int max_it = static_cast<int>(argValue(argc, argv, "--max-iterations", 60));
    std::string why;
    if (!pcl_animseg::gpu::gpuAvailable(&why)) {
      std::printf("no GPU: %s\n", why.c_str());
      return 0;
    }
    const auto info = pcl_animseg::gpu::deviceInfo();
    std::printf("device: %s (sm_%d%d, %d SMs, %.1f GiB)\n", info.name.c_str(), info.compute_major,
                info.compute_minor, info.multiprocessors, info.total_bytes / 1073741824.0);
    auto t0 = Clock::now();
    const Eigen::MatrixXf z = makeFeatures(n, frames, 1);
    // The stage's defaults: w = 0.1, w1 = w2 = 0.5, w4 = 1 (mean_shift.h).
    const double w = 0.1;
    Eigen::RowVectorXf metric(30);
    metric.head(6).setConstant(static_cast<float>(std::sqrt(0.5) / w));
    metric.tail(24).setConstant(static_cast<float>(1.0 / w));
    std::printf("data: %d points x %d dims, %d frames (generated in %.2f s)\n", n,
                static_cast<int>(z.cols()), frames, since(t0));

    pcl_animseg::gpu::MeanShiftParams params;
    params.max_iterations = max_it;
    if (use_gpu) {
    {
      // The tree alone first, so that its size is known even if a later stage is cut short.
      const Eigen::MatrixXf x = z.array().rowwise() * metric.array();
      pcl_animseg::gpu::GaussianKdTree tree(params.gkdtree);
      t0 = Clock::now();
      tree.build(x);
      std::printf("GPU tree: %zu samples (N/M %.1f), depth %d, built in %.1f ms\n",
                  tree.numSamples(), tree.samplingFactor(), tree.depth(), 1e3 * since(t0));
    }
    pcl_animseg::gpu::MeanShift ms;
    ms.setParams(params);
    Eigen::MatrixXf y;
    Eigen::VectorXf density;
    t0 = Clock::now();
    ms.run(z, metric, metric, {}, y, density);
    const double gpu_total = since(t0);
    const auto& st = ms.stats();
    std::printf("GPU: samples %zu (N/M %.1f), upload %.1f ms, build %.1f ms, splat+blur %.1f ms\n",
                st.num_samples, static_cast<double>(n) / st.num_samples, 1e3 * st.upload_s,
                1e3 * st.build_s, 1e3 * st.splat_blur_s);
    std::printf("GPU: first step (all %d points) %.2f ms; iterations %d, not converged %d\n", n,
                1e3 * st.step_s.at(0), st.iterations, st.not_converged);
    std::printf("GPU: steps (ms / active):");
    for (std::size_t i = 0; i < st.step_s.size(); ++i)
      std::printf(" %.2f/%d", 1e3 * st.step_s[i], i ? st.active[i - 1] : n);
    std::printf("\n");
    std::printf("GPU: iterate %.1f ms, density %.1f ms, download %.1f ms, total run %.1f ms\n",
                1e3 * st.iterate_s, 1e3 * st.density_s, 1e3 * st.download_s, 1e3 * gpu_total);
    std::printf("GPU: peak device memory %.1f MiB (library buffers)\n",
                st.peak_device_bytes / 1048576.0);
    std::vector<int> labels, reps;
    t0 = Clock::now();
    pcl_animseg::gpu::groupModes(y, metric, density, 0.5, labels, reps);
    std::printf("modes: %zu (grouping on the host %.1f ms)\n", reps.size(), 1e3 * since(t0));
    }

    if (cpu) {
      // The CPU backend on the same data: build, splat+blur and one full step (slice of all N).
      const Eigen::MatrixXf x = z.array().rowwise() * metric.array();
      Eigen::MatrixXf values(n, 31);
      values.leftCols(30) = z;
      values.col(30).setOnes();
      pcl_animseg::filters::GaussianKdTree tree(params.gkdtree);
      t0 = Clock::now();
      tree.build(x);
      const double cb = since(t0);
      std::printf("CPU tree: %zu samples, built in %.1f ms\n", tree.numSamples(), 1e3 * cb);
      t0 = Clock::now();
      Eigen::MatrixXf sv, out;
      tree.splatBlur(values, sv);
      const double cs = since(t0);
      t0 = Clock::now();
      tree.slice(sv, x, out);
      const double cstep = since(t0);
      std::printf("CPU (%d threads): samples %zu, build %.1f ms, splat+blur %.1f ms, one step "
                  "%.1f ms\n",
                  Eigen::nbThreads(), tree.numSamples(), 1e3 * cb, 1e3 * cs, 1e3 * cstep);
    }
    return 0;
  } catch (const std::exception& e) {
    std::printf("error: %s\n", e.what());
    return 1;
  }
}
