#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/segmentation_io.h>
#include <pcl_animseg/io/sequence_io.h>

#include <exception>
#include <fstream>
#include <iomanip>
#include <sstream>

namespace pcl_animseg {
namespace io {

void saveSegmentationInfo(const std::string& path, const segmentation::SegmentationResult& r) {
  if (static_cast<int>(r.mode_density.size()) != r.num_clusters)
    throw Error("segmentation info: " + std::to_string(r.mode_density.size()) +
                " mode densities for " + std::to_string(r.num_clusters) + " clusters");
  std::ostringstream s;
  s << std::setprecision(10);
  s << "# pcl_animseg segmentation v1\nclusters " << r.num_clusters << '\n';
  const bool with_modes = r.modes.rows() == r.num_clusters && r.modes.cols() > 0;
  for (int c = 0; c < r.num_clusters; ++c) {
    s << "mode " << c << ' ' << r.mode_density[c];
    if (with_modes)
      for (Eigen::Index d = 0; d < r.modes.cols(); ++d) s << ' ' << r.modes(c, d);
    s << '\n';
  }
  for (const auto& sd : r.saddles)
    s << "saddle " << sd.a << ' ' << sd.b << ' ' << sd.density << '\n';
  writeTextAtomically(path, s.str());
}

void loadSegmentationInfo(const std::string& path, segmentation::SegmentationResult& r) {
  std::ifstream in(path);
  if (!in) throw Error("cannot open segmentation info '" + path + "'");
  std::string line;
  int line_no = 0, clusters = -1;
  std::vector<double> density;
  std::vector<std::vector<double>> modes;
  std::vector<char> seen;
  std::vector<segmentation::Saddle> saddles;
  auto fail = [&](const std::string& why) {
    throw Error(path + ":" + std::to_string(line_no) + ": " + why);
  };
  while (std::getline(in, line)) {
    ++line_no;
    const auto hash = line.find('#');
    if (hash != std::string::npos) line.erase(hash);
    std::istringstream ls(line);
    std::string key;
    if (!(ls >> key)) continue;
    if (key == "clusters") {
      if (!(ls >> clusters) || clusters < 0) fail("expected 'clusters <count>'");
      density.assign(clusters, 0.0);
      modes.assign(clusters, {});
      seen.assign(clusters, 0);
    } else if (key == "mode") {
      int id;
      double d;
      if (clusters < 0) fail("'mode' before 'clusters'");
      if (!(ls >> id >> d)) fail("expected 'mode <id> <density> [coordinates]'");
      if (id < 0 || id >= clusters) fail("mode id " + std::to_string(id) + " out of range");
      density[id] = d;
      seen[id] = 1;
      double v;
      while (ls >> v) modes[id].push_back(v);
      if (!ls.eof()) fail("bad number in mode coordinates");
    } else if (key == "saddle") {
      segmentation::Saddle s;
      if (!(ls >> s.a >> s.b >> s.density)) fail("expected 'saddle <a> <b> <density>'");
      if (s.a < 0 || s.b < 0 || s.a >= clusters || s.b >= clusters)
        fail("saddle between unknown clusters");
      saddles.push_back(s);
    } else {
      fail("unknown keyword '" + key + "'");
    }
  }
  if (clusters < 0) throw Error(path + ": no 'clusters' line (is this a segmentation.txt?)");
  for (int c = 0; c < clusters; ++c)
    if (!seen[c]) throw Error(path + ": no 'mode' line for cluster " + std::to_string(c));
  r.num_clusters = clusters;
  r.mode_density = density;
  r.saddles = saddles;
  const std::size_t dim = clusters > 0 ? modes[0].size() : 0;
  bool uniform = dim > 0;
  for (const auto& m : modes) uniform = uniform && m.size() == dim;
  if (uniform) {
    r.modes.resize(clusters, static_cast<Eigen::Index>(dim));
    for (int c = 0; c < clusters; ++c)
      for (std::size_t d = 0; d < dim; ++d) r.modes(c, d) = static_cast<float>(modes[c][d]);
  } else {
    r.modes.resize(0, 0);
  }
}

std::vector<std::vector<int>> loadSequenceLabels(const std::string& dir,
                                                 const PointCloudSequence& sequence, int column) {
  std::vector<std::vector<int>> out(sequence.size());
  for (std::size_t t = 0; t < sequence.size(); ++t) {
    const std::string path = dir + "/" + sequence.name(t) + ".labels";
    const std::vector<int> input = loadLabels(path, column);
    if (input.size() != sequence.inputSize(t))
      throw Error(path + ": " + std::to_string(input.size()) + " labels for a frame of " +
                  std::to_string(sequence.inputSize(t)) +
                  " points (labels from another sequence?)");
    const std::vector<int>& index = sequence.inputIndex(t);
    out[t].resize(index.size());
    for (std::size_t j = 0; j < index.size(); ++j) out[t][j] = input[index[j]];
  }
  return out;
}

void saveSequenceLabels(const std::string& dir, const PointCloudSequence& sequence,
                        const std::vector<std::vector<std::vector<int>>>& levels, bool ply,
                        const std::function<void(std::size_t)>& frames_done) {
  if (levels.empty()) throw Error("no labels to save");
  ensureDirectory(dir);
  const long frames = static_cast<long>(sequence.size());
  std::exception_ptr error;
  std::size_t done = 0;
#pragma omp parallel for schedule(dynamic, 1)
  for (long t = 0; t < frames; ++t) {
    try {
      std::vector<std::vector<int>> columns;
      for (const auto& level : levels) columns.push_back(sequence.toInputOrder(t, level.at(t)));
      const std::string base = dir + "/" + sequence.name(t);
      saveLabels(base + ".labels", columns);
      saveLabelledPCD(base + ".pcd", *sequence.frame(t), levels[0][t]);
      if (ply) saveLabelledPLY(base + ".ply", *sequence.frame(t), levels[0][t]);
#pragma omp critical(save_sequence_labels)
      if (frames_done) frames_done(++done);
    } catch (...) {
#pragma omp critical(save_sequence_labels)
      if (!error) error = std::current_exception();
    }
  }
  if (error) std::rethrow_exception(error);
}

}  // namespace io
}  // namespace pcl_animseg
