#include <pcl_animseg/error.h>
#include <pcl_animseg/io/frame_readers.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/visualization/labelled_sequence.h>

#include <pcl/PCLPointCloud2.h>

#include <algorithm>
#include <cstring>
#include <filesystem>
#include <map>

namespace pcl_animseg {
namespace visualization {

namespace fs = std::filesystem;

namespace {

/** The NAME of every NAME.labels in `dir`, in natural order. */
std::vector<std::string> labelNames(const std::string& dir) {
  std::vector<std::string> names;
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return names;
  for (const auto& e : fs::directory_iterator(dir, ec))
    if (e.is_regular_file(ec) && e.path().extension() == ".labels")
      names.push_back(e.path().stem().string());
  std::sort(names.begin(), names.end(), io::naturalLess);
  return names;
}

/** One field of a PCD blob as doubles (any numeric type; integers keep their bit pattern as
 * signed values, so a label written as uint32 max reads back as -1). Empty when absent. */
std::vector<double> field(const pcl::PCLPointCloud2& blob, const std::string& name) {
  std::vector<double> out;
  for (const auto& f : blob.fields) {
    if (f.name != name) continue;
    const std::size_t n = static_cast<std::size_t>(blob.width) * blob.height;
    out.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
      const std::uint8_t* p = &blob.data[i * blob.point_step + f.offset];
      switch (f.datatype) {
        case pcl::PCLPointField::FLOAT32: { float v; std::memcpy(&v, p, 4); out[i] = v; break; }
        case pcl::PCLPointField::FLOAT64: { double v; std::memcpy(&v, p, 8); out[i] = v; break; }
        case pcl::PCLPointField::INT32:
        case pcl::PCLPointField::UINT32: {
          std::int32_t v;
          std::memcpy(&v, p, 4);
          out[i] = v;
          break;
        }
        case pcl::PCLPointField::INT16:
        case pcl::PCLPointField::UINT16: {
          std::int16_t v;
          std::memcpy(&v, p, 2);
          out[i] = v;
          break;
        }
        case pcl::PCLPointField::INT8: out[i] = static_cast<std::int8_t>(*p); break;
        default: out[i] = *p; break;
      }
    }
    break;
  }
  return out;
}

pcl::PCLPointCloud2 readBlob(const std::string& path) {
  std::error_code ec;
  if (!fs::is_regular_file(path, ec)) throw Error("missing file '" + path + "'");
  // The checked reader: PCL's own crashes on some corrupt files (docs/reliability.md).
  return io::readPCDCloud(path);
}

/** Points of an OUT .pcd with their level-0 label. */
PointCloudSequence::Cloud::Ptr readLabelledPCD(const std::string& path, std::vector<int>& labels) {
  const pcl::PCLPointCloud2 blob = readBlob(path);
  const auto x = field(blob, "x"), y = field(blob, "y"), z = field(blob, "z");
  if (x.empty() || y.empty() || z.empty())
    throw Error("PCD file '" + path + "' has no x y z fields");
  const auto nx = field(blob, "normal_x"), ny = field(blob, "normal_y"),
             nz = field(blob, "normal_z"), l = field(blob, "label");
  PointCloudSequence::Cloud::Ptr cloud(new PointCloudSequence::Cloud);
  cloud->resize(x.size());
  labels.assign(x.size(), -1);
  for (std::size_t i = 0; i < x.size(); ++i) {
    pcl::PointNormal& p = (*cloud)[i];
    p.x = static_cast<float>(x[i]);
    p.y = static_cast<float>(y[i]);
    p.z = static_cast<float>(z[i]);
    p.normal_x = nx.empty() ? 0.f : static_cast<float>(nx[i]);
    p.normal_y = ny.empty() ? 0.f : static_cast<float>(ny[i]);
    p.normal_z = nz.empty() ? 0.f : static_cast<float>(nz[i]);
    if (!l.empty()) labels[i] = static_cast<int>(l[i]);
  }
  return cloud;
}

/** For each PCD point (with level-0 label `pcd_labels[j]`), its row in a labels file whose
 * level-0 column is `rows`: the next row in order with the same label. Dropped input points are
 * rows of -1 between them, so the walk skips them. */
std::vector<std::size_t> matchRows(const std::vector<int>& pcd_labels, const std::vector<int>& rows,
                                   const std::string& what) {
  std::vector<std::size_t> map(pcd_labels.size());
  if (pcd_labels.size() == rows.size()) {
    for (std::size_t j = 0; j < map.size(); ++j) map[j] = j;
    return map;
  }
  if (pcd_labels.size() > rows.size())
    throw Error(what + ": the PCD has " + std::to_string(pcd_labels.size()) +
                " points but the labels file only " + std::to_string(rows.size()) + " rows");
  std::size_t r = 0;
  for (std::size_t j = 0; j < pcd_labels.size(); ++j) {
    while (r < rows.size() && rows[r] != pcd_labels[j]) ++r;
    if (r == rows.size())
      throw Error(what + ": the PCD's points do not match the rows of the labels file");
    map[j] = r++;
  }
  return map;
}

std::vector<OverlayKeypoint> readKeypoints(const std::string& out_dir, const std::string& name) {
  std::vector<OverlayKeypoint> kps;
  std::error_code ec;
  for (const std::string& path :
       {out_dir + "/" + name + ".keypoints.pcd", out_dir + "/keypoints/" + name + ".pcd"}) {
    if (!fs::is_regular_file(path, ec)) continue;
    const pcl::PCLPointCloud2 blob = readBlob(path);
    const auto x = field(blob, "x"), y = field(blob, "y"), z = field(blob, "z"),
               s = field(blob, "scale");
    if (x.empty()) throw Error("keypoints file '" + path + "' has no x y z fields");
    kps.resize(x.size());
    for (std::size_t i = 0; i < x.size(); ++i) {
      kps[i].position = Eigen::Vector3f(static_cast<float>(x[i]), static_cast<float>(y[i]),
                                        static_cast<float>(z[i]));
      kps[i].scale = s.empty() ? 0.f : static_cast<float>(s[i]);
    }
    break;
  }
  return kps;
}

/** levels[l][j] = columns[l][map[j]]. */
std::vector<std::vector<int>> pick(const std::vector<std::vector<int>>& columns,
                                   const std::vector<std::size_t>& map) {
  std::vector<std::vector<int>> levels(columns.size(), std::vector<int>(map.size()));
  for (std::size_t l = 0; l < columns.size(); ++l)
    for (std::size_t j = 0; j < map.size(); ++j) levels[l][j] = columns[l][map[j]];
  return levels;
}

}  // namespace

std::vector<std::pair<int, std::size_t>> LabelledSequence::partCounts(int level) const {
  std::map<int, std::size_t> counts;
  for (const auto& f : frames)
    if (level >= 0 && level < static_cast<int>(f.levels.size()))
      for (int l : f.levels[level])
        if (l >= 0) ++counts[l];
  return {counts.begin(), counts.end()};
}

LabelledSequence loadLabelledSequence(const std::string& out_dir, const std::string& frames) {
  std::error_code ec;
  if (!fs::is_directory(out_dir, ec))
    throw Error("'" + out_dir + "' is not a directory (expected the OUT directory of animseg)");
  const std::vector<std::string> names = labelNames(out_dir);
  if (names.empty())
    throw Error("no .labels files in '" + out_dir + "' (expected the OUT directory of animseg)");

  // Where the geometry comes from: OUT itself, another OUT directory, or the input sequence.
  std::string geometry_dir = out_dir;
  PointCloudSequence input;
  bool from_input = false;
  if (!frames.empty()) {
    if (!labelNames(frames).empty()) {
      geometry_dir = frames;
    } else {
      input = io::loadSequence(frames);
      from_input = true;
    }
  }

  LabelledSequence seq;
  seq.frames.resize(names.size());
  std::map<std::string, std::size_t> input_by_name;
  if (from_input)
    for (std::size_t t = 0; t < input.size(); ++t) input_by_name[input.name(t)] = t;
  if (from_input && input.size() != names.size())
    throw Error("'" + frames + "' has " + std::to_string(input.size()) + " frames but '" + out_dir +
                "' has labels for " + std::to_string(names.size()));

  for (std::size_t t = 0; t < names.size(); ++t) {
    LabelledFrame& f = seq.frames[t];
    f.name = names[t];
    const std::string labels_path = out_dir + "/" + names[t] + ".labels";
    const auto columns = io::loadLabelColumns(labels_path);
    if (columns.empty()) throw Error("labels file '" + labels_path + "' is empty");
    const std::size_t rows = columns[0].size();
    std::vector<std::size_t> map;
    if (from_input) {
      // Match by frame name; fall back to order when the names differ (renamed copies).
      const auto it = input_by_name.find(names[t]);
      const std::size_t i = it != input_by_name.end() ? it->second : t;
      if (input.inputSize(i) != rows)
        throw Error("frame '" + input.source(i) + "' has " + std::to_string(input.inputSize(i)) +
                    " input points but '" + labels_path + "' has " + std::to_string(rows) +
                    " rows: --frames is not the sequence this decomposition was made from");
      f.cloud = input.frame(i);
      const auto& index = input.inputIndex(i);
      map.resize(f.cloud->size());
      for (std::size_t j = 0; j < map.size(); ++j)
        map[j] = index.empty() ? j : static_cast<std::size_t>(index[j]);
    } else {
      const std::string pcd = geometry_dir + "/" + names[t] + ".pcd";
      std::vector<int> pcd_labels;
      f.cloud = readLabelledPCD(pcd, pcd_labels);
      // The PCD's labels are those of its own directory's level 0.
      const std::vector<int> own_rows =
          geometry_dir == out_dir
              ? columns[0]
              : io::loadLabelColumns(geometry_dir + "/" + names[t] + ".labels").at(0);
      if (own_rows.size() != rows)
        throw Error("'" + geometry_dir + "/" + names[t] + ".labels' has " +
                    std::to_string(own_rows.size()) + " rows but '" + labels_path + "' " +
                    std::to_string(rows));
      map = matchRows(pcd_labels, own_rows, "'" + pcd + "'");
    }
    f.levels = pick(columns, map);
    if (t > 0 && f.levels.size() != seq.frames[0].levels.size())
      throw Error("'" + labels_path + "' has " + std::to_string(f.levels.size()) +
                  " levels but the first frame " + std::to_string(seq.frames[0].levels.size()));
    f.keypoints = readKeypoints(out_dir, names[t]);
  }
  return seq;
}

LabelledSequence makeLabelledSequence(const PointCloudSequence& sequence,
                                      const std::vector<std::vector<std::vector<int>>>& labels) {
  LabelledSequence seq;
  seq.frames.resize(sequence.size());
  for (std::size_t t = 0; t < sequence.size(); ++t) {
    LabelledFrame& f = seq.frames[t];
    f.name = sequence.name(t);
    f.cloud = sequence.frame(t);
    for (std::size_t l = 0; l < labels.size(); ++l) {
      if (labels[l].size() != sequence.size() || labels[l][t].size() != f.cloud->size())
        throw Error("labels of level " + std::to_string(l) + " do not match frame '" + f.name +
                    "'");
      f.levels.push_back(labels[l][t]);
    }
  }
  return seq;
}

}  // namespace visualization
}  // namespace pcl_animseg
