#pragma once
// A residual batch (motion_device.h's ResidualJobs) computed on the CPU from what a device is
// given alone: the frames' trees and leaf normals, the batch's sources and motions, with
// icp_step's arithmetic and the errors added in point order, as the motion method and the GPU
// compute it. For tests of devices.
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_device.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace animseg_test {

// icp_step's surface error of a moved point (y, n) against frame t of `frames`.
inline double deviceSurfaceError(const pcl_animseg::segmentation::DeviceFrames& frames, int t,
                                 const double* y, const double* n) {
  namespace is = pcl_animseg::segmentation::icp_step;
  const auto& f = frames.frames[t];
  const double bound = (frames.clip + 1.5) * f.spacing;
  const float q[3] = {static_cast<float>(y[0]), static_cast<float>(y[1]), static_cast<float>(y[2])};
  float d2 = 0.0f;
  const int leaf =
      f.tree->nearestLeaf(q, std::nextafter(static_cast<float>(bound * bound), 1e30f), d2);
  double tp[3] = {0, 0, 0}, tn[3] = {0, 0, 0};
  for (int k = 0; leaf >= 0 && k < 3; ++k) {
    tp[k] = f.tree->leafPoints()[3 * leaf + k];
    tn[k] = f.leaf_normals[3 * leaf + k];
  }
  return is::surfaceError(leaf >= 0, d2, y, n, tp, tn, f.spacing, f.unoriented, frames.normal_cos,
                          frames.clip);
}

// Every job's RMS surface error (0 for a source without points).
inline std::vector<double> cpuResiduals(const pcl_animseg::segmentation::DeviceFrames& frames,
                                        const pcl_animseg::segmentation::ResidualJobs& b) {
  namespace is = pcl_animseg::segmentation::icp_step;
  std::vector<double> out;
  for (const auto& job : b.jobs) {
    const is::Rigid m = is::load(&b.motions[12 * static_cast<std::size_t>(job.motion)]);
    double sum = 0.0;
    const int first = b.source_begin[job.source], end = b.source_begin[job.source + 1];
    for (int i = first; i < end; ++i) {
      double y[3], n[3];
      is::apply(m, &b.points[6 * static_cast<std::size_t>(i)], y);
      is::rotate(m, &b.points[6 * static_cast<std::size_t>(i) + 3], n);
      sum += deviceSurfaceError(frames, job.frame, y, n);
    }
    out.push_back(end > first ? std::sqrt(sum / (end - first)) : 0.0);
  }
  return out;
}

// Every part fit of a batch (motion_device.h's PartFitJobs) as the motion method's icp() makes
// it: damped ICP with icp_step (the point-to-plane terms of the matches whose normals agree,
// added in point order about the moved source's centroid), the fit kept where its residual is
// at most r0, else the start; the poses (12 doubles each) in the jobs' order.
inline std::vector<double> cpuPartFits(const pcl_animseg::segmentation::DeviceFrames& frames,
                                       const pcl_animseg::segmentation::PartFitJobs& b) {
  namespace is = pcl_animseg::segmentation::icp_step;
  std::vector<double> poses;
  for (const auto& job : b.jobs) {
    const int first = b.source_begin[job.source], m = b.source_begin[job.source + 1] - first;
    const auto& f = frames.frames[job.frame];
    const is::Rigid init = is::load(&b.motions[12 * static_cast<std::size_t>(job.motion)]);
    is::Rigid T = init;
    const float max_d2 = static_cast<float>(job.max_dist * job.max_dist);
    std::vector<double> moved(3 * static_cast<std::size_t>(m));
    for (int it = 0; it < b.iterations; ++it) {
      double c[3] = {0, 0, 0};
      for (int i = 0; i < m; ++i) {
        is::apply(T, &b.points[6 * static_cast<std::size_t>(first + i)], &moved[3 * i]);
        for (int k = 0; k < 3; ++k) c[k] += moved[3 * i + k];
      }
      for (int k = 0; k < 3; ++k) c[k] /= static_cast<double>(std::max(1, m));
      double sums[is::kTerms] = {};
      int used = 0;
      for (int i = 0; i < m; ++i) {
        const float q[3] = {static_cast<float>(moved[3 * i]), static_cast<float>(moved[3 * i + 1]),
                            static_cast<float>(moved[3 * i + 2])};
        float d2 = 0.0f;
        const bool finite = std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]);
        const int leaf = finite ? f.tree->nearestLeaf(q, std::nextafter(max_d2, 1e30f), d2) : -1;
        if (leaf < 0) continue;
        double tp[3], tn[3], n[3];
        for (int k = 0; k < 3; ++k) {
          tp[k] = f.tree->leafPoints()[3 * leaf + k];
          tn[k] = f.leaf_normals[3 * leaf + k];
        }
        is::rotate(T, &b.points[6 * static_cast<std::size_t>(first + i) + 3], n);
        const double cs = is::dot3(n, tn);
        if ((f.unoriented ? std::fabs(cs) : cs) < frames.normal_cos) continue;
        ++used;
        double terms[is::kTerms];
        is::pointTerms(&moved[3 * i], c, tp, tn, terms);
        for (int q2 = 0; q2 < is::kTerms; ++q2) sums[q2] += terms[q2];
      }
      if (used < 6) break;
      double x[6];
      if (!is::solveStep(sums, x)) break;
      T = is::compose(is::stepMotion(x, c), T);
      if (is::converged(x, f.spacing)) break;
    }
    double sum = 0.0;
    for (int i = 0; i < m; ++i) {
      double y[3], n[3];
      is::apply(T, &b.points[6 * static_cast<std::size_t>(first + i)], y);
      is::rotate(T, &b.points[6 * static_cast<std::size_t>(first + i) + 3], n);
      sum += deviceSurfaceError(frames, job.frame, y, n);
    }
    const double r = m > 0 ? std::sqrt(sum / m) : 0.0;
    poses.resize(poses.size() + 12);
    is::store(r <= job.r0 ? T : init, &poses[poses.size() - 12]);
  }
  return poses;
}

}  // namespace animseg_test
