#pragma once
// Test data for the Gaussian kd-tree's tests on the CPU and on the GPU: clustered points in d
// dimensions lying near a low-dimensional set (like the joint feature space of a surface
// sequence), and the relative error between two results.
#include <Eigen/Core>
#include <random>

namespace animseg_test {

/** n points in d dimensions: blobs along a random 3-D set, in units of the kernel's sigma. */
inline Eigen::MatrixXf makeBlobData(int n, int d, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> g(0.0f, 1.0f);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  Eigen::MatrixXf dirs(3, d);
  for (int i = 0; i < dirs.size(); ++i) dirs(i) = g(rng);
  Eigen::MatrixXf p(n, d);
  for (int i = 0; i < n; ++i) {
    const float a = 6.0f * u(rng), b = 6.0f * u(rng), c = 6.0f * u(rng);
    for (int k = 0; k < d; ++k)
      p(i, k) =
          a * dirs(0, k) / 2.0f + b * dirs(1, k) / 2.0f + c * dirs(2, k) / 2.0f + 0.05f * g(rng);
  }
  return p;
}

/** ||a - b|| / ||b|| (Frobenius). */
inline double relativeError(const Eigen::MatrixXf& a, const Eigen::MatrixXf& b) {
  return (a - b).norm() / b.norm();
}

}  // namespace animseg_test
