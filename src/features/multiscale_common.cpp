// The pieces of multiscale.h that only need the features module (so its tests link without the
// keypoints module).
#include <pcl_animseg/error.h>
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/features/neighbourhood.h>

#include <algorithm>
#include <cmath>

namespace pcl_animseg {

double sequenceSpacing(const PointCloudSequence& seq) {
  if (seq.empty()) throw Error("the sequence has no frames");
  std::vector<double> sizes, counts;
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const auto& f = *seq.frame(t);
    if (f.size() < 2) throw Error("frame '" + seq.name(t) + "' has fewer than 2 points");
    double s = 0.0;
    try {
      s = featureSpacing(f);
    } catch (const Error& e) {
      throw Error("frame '" + seq.name(t) + "': " + e.what());
    }
    // s * sqrt(N) ~ sqrt(area): the same for any sampling density of the same surface.
    sizes.push_back(s * std::sqrt(static_cast<double>(f.size())));
    counts.push_back(static_cast<double>(f.size()));
  }
  auto median = [](std::vector<double> v) {
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    return v[v.size() / 2];
  };
  return median(sizes) / std::sqrt(median(counts));
}

PointCloudSequence::Cloud::Ptr signatureInput(const PointCloudSequence::Cloud& frame,
                                              const PointCloudSequence::Cloud& level0) {
  PointCloudSequence::Cloud::Ptr out(new PointCloudSequence::Cloud(frame));
  for (std::size_t j = 0; j < out->size(); ++j) {
    const Eigen::Vector3f n = (*out)[j].getNormalVector3fMap();
    if (!n.allFinite() || n.squaredNorm() < 0.25f)
      (*out)[j].getNormalVector3fMap() = level0[j].getNormalVector3fMap();
    else
      (*out)[j].getNormalVector3fMap() = n.normalized();
  }
  return out;
}

}  // namespace pcl_animseg
