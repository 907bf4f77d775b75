#include <pcl/common/common.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/sequence.h>

#include <algorithm>
#include <exception>
#include <numeric>

namespace pcl_animseg {

void PointCloudSequence::addFrame(Cloud::Ptr cloud, const std::string& name, const std::string& source,
                                  std::vector<int> input_index, std::size_t input_size,
                                  std::vector<pcl::Vertices> faces) {
  if (!cloud) throw Error("frame '" + name + "' has no cloud");
  FrameData f;
  if (input_index.empty()) {
    input_index.resize(cloud->size());
    std::iota(input_index.begin(), input_index.end(), 0);
  }
  if (input_index.size() != cloud->size())
    throw Error("frame '" + name + "': input index size does not match the cloud");
  if (input_size == 0) input_size = cloud->size();
  for (int i : input_index)
    if (i < 0 || static_cast<std::size_t>(i) >= input_size)
      throw Error("frame '" + name + "': input index out of range");
  f.cloud = std::move(cloud);
  f.name = name;
  f.source = source;
  f.input_index = std::move(input_index);
  f.input_size = input_size;
  f.faces = std::move(faces);
  frames_.push_back(std::move(f));
}

bool PointCloudSequence::normalsOriented() const {
  for (const auto& f : frames_)
    if (f.estimated_normals > 0 && f.estimated_normals >= f.cloud->size()) return false;
  return true;
}

std::size_t PointCloudSequence::totalPoints() const {
  std::size_t n = 0;
  for (const auto& f : frames_) n += f.cloud->size();
  return n;
}

std::vector<std::size_t> PointCloudSequence::offsets() const {
  std::vector<std::size_t> off(frames_.size() + 1, 0);
  for (std::size_t t = 0; t < frames_.size(); ++t) off[t + 1] = off[t] + frames_[t].cloud->size();
  return off;
}

std::vector<int> PointCloudSequence::frameIds() const {
  std::vector<int> ids;
  ids.reserve(totalPoints());
  for (std::size_t t = 0; t < frames_.size(); ++t)
    ids.insert(ids.end(), frames_[t].cloud->size(), static_cast<int>(t));
  return ids;
}

PointCloudSequence::Cloud::Ptr PointCloudSequence::flatten() const {
  Cloud::Ptr out(new Cloud);
  out->reserve(totalPoints());
  for (const auto& f : frames_) *out += *f.cloud;
  return out;
}

std::vector<int> PointCloudSequence::toInputOrder(std::size_t t, const std::vector<int>& labels) const {
  const FrameData& f = frames_.at(t);
  if (labels.size() != f.cloud->size())
    throw Error("frame '" + f.name + "': " + std::to_string(labels.size()) + " labels for " +
                std::to_string(f.cloud->size()) + " points");
  std::vector<int> out(f.input_size, -1);
  for (std::size_t j = 0; j < labels.size(); ++j) out[f.input_index[j]] = labels[j];
  return out;
}

double meanSpacing(const PointCloudSequence::Cloud& cloud, std::size_t max_samples) {
  if (cloud.size() < 2) throw Error("cannot measure point spacing of fewer than 2 points");
  PointCloudSequence::Cloud::Ptr copy(new PointCloudSequence::Cloud(cloud));
  pcl_animseg::KdTree<pcl::PointNormal> tree;
  tree.setInputCloud(copy);
  return meanSpacing(cloud, tree, max_samples);
}

double meanSpacing(const PointCloudSequence::Cloud& cloud, const KdTree<pcl::PointNormal>& tree,
                   std::size_t max_samples) {
  if (cloud.size() < 2) throw Error("cannot measure point spacing of fewer than 2 points");
  const std::size_t n = cloud.size();
  const std::size_t step = std::max<std::size_t>(1, n / std::max<std::size_t>(1, max_samples));
  std::vector<int> idx(2);
  std::vector<float> d2(2);
  double sum = 0.0;
  std::size_t count = 0;
  for (std::size_t i = 0; i < n; i += step) {
    if (tree.nearestKSearch(cloud[i], 2, idx, d2) < 2) continue;
    // Duplicate points give 0 here; they are rare and only lower the spacing slightly.
    sum += std::sqrt(static_cast<double>(d2[1]));
    ++count;
  }
  if (count == 0 || sum <= 0.0) throw Error("all points coincide: the point spacing is zero");
  return sum / static_cast<double>(count);
}

namespace {

// measure(t) for every frame, the frames in parallel; a frame that has no spacing throws Error
// naming the frame.
template <class Measure>
std::vector<double> spacingsOf(const PointCloudSequence& seq, Measure measure) {
  const int T = static_cast<int>(seq.size());
  std::vector<double> spacing(seq.size(), 0.0);
  std::vector<std::string> error(seq.size());
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < T; ++t) {
    try {
      spacing[t] = measure(static_cast<std::size_t>(t));
    } catch (const std::exception& e) {
      error[t] = e.what();
    }
  }
  for (int t = 0; t < T; ++t)
    if (!error[t].empty()) throw Error("frame " + seq.name(t) + ": " + error[t]);
  return spacing;
}

}  // namespace

std::vector<double> meanSpacings(const PointCloudSequence& seq, std::size_t max_samples) {
  return spacingsOf(seq, [&](std::size_t t) { return meanSpacing(*seq.frame(t), max_samples); });
}

std::vector<double> meanSpacings(
    const PointCloudSequence& seq,
    const std::function<const KdTree<pcl::PointNormal>&(std::size_t)>& tree_of,
    std::size_t max_samples) {
  return spacingsOf(
      seq, [&](std::size_t t) { return meanSpacing(*seq.frame(t), tree_of(t), max_samples); });
}

double boundingBoxDiagonal(const PointCloudSequence::Cloud& cloud) {
  if (cloud.empty()) return 0.0;
  pcl::PointNormal mn, mx;
  pcl::getMinMax3D(cloud, mn, mx);
  return (mx.getVector3fMap() - mn.getVector3fMap()).norm();
}

}  // namespace pcl_animseg
