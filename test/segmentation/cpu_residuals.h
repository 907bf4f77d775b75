#pragma once
// A residual batch (motion_device.h's ResidualJobs) computed on the CPU from what a device is
// given alone: the frames' trees and leaf normals, the batch's sources and motions, with
// icp_step's arithmetic and the errors added in point order, as the motion method and the GPU
// compute it. For tests of devices.
#include <pcl_animseg/flat_kdtree.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/motion_device.h>

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

}  // namespace animseg_test
