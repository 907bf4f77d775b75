#include <pcl/PCLPointCloud2.h>
#include <pcl/io/pcd_io.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>

#include <cerrno>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>

namespace pcl_animseg {
namespace io {

namespace {

bool hostIsLittleEndian() {
  const std::uint32_t one = 1;
  unsigned char b;
  std::memcpy(&b, &one, 1);
  return b == 1;
}

template <typename T>
void putLE(std::string& buf, T value) {
  char bytes[sizeof(T)];
  std::memcpy(bytes, &value, sizeof(T));
  if (!hostIsLittleEndian())
    for (std::size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(bytes[i], bytes[sizeof(T) - 1 - i]);
  buf.append(bytes, sizeof(T));
}

void writeBytes(const std::string& final_path, const std::string& tmp, const std::string& data) {
  std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
  if (!out)
    throw Error("cannot write '" + final_path + "': cannot create '" + tmp +
                "': " + std::strerror(errno));
  out.write(data.data(), static_cast<std::streamsize>(data.size()));
  out.close();
  if (!out) throw Error("cannot write '" + final_path + "': write failed (disk full?)");
}

void checkLabels(const std::string& path, const PointCloudSequence::Cloud& cloud,
                 const std::vector<int>& labels) {
  if (labels.size() != cloud.size())
    throw Error("cannot write '" + path + "': " + std::to_string(labels.size()) + " labels for " +
                std::to_string(cloud.size()) + " points");
}

std::string fmt(float v) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.9g", static_cast<double>(v));
  return buf;
}

}  // namespace

void saveLabelledPCD(const std::string& path, const PointCloudSequence::Cloud& cloud,
                     const std::vector<int>& labels) {
  checkLabels(path, cloud, labels);
  pcl::PCLPointCloud2 c;
  const char* names[] = {"x", "y", "z", "normal_x", "normal_y", "normal_z", "label"};
  for (std::uint32_t i = 0; i < 7; ++i) {
    pcl::PCLPointField f;
    f.name = names[i];
    f.offset = 4 * i;
    f.datatype = i < 6 ? pcl::PCLPointField::FLOAT32 : pcl::PCLPointField::UINT32;
    f.count = 1;
    c.fields.push_back(f);
  }
  c.point_step = 28;
  c.width = static_cast<std::uint32_t>(cloud.size());
  c.height = 1;
  c.row_step = c.point_step * c.width;
  c.is_dense = true;
  c.is_bigendian = false;
  c.data.resize(static_cast<std::size_t>(c.row_step));
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    std::uint8_t* p = c.data.data() + i * c.point_step;
    const auto& q = cloud[i];
    const float v[6] = {q.x, q.y, q.z, q.normal_x, q.normal_y, q.normal_z};
    std::memcpy(p, v, sizeof(v));
    // Unlabelled (-1) becomes 0xFFFFFFFF: still its own label for pcl_viewer's label handler,
    // and it reads back as -1 through a cast to int32.
    const std::uint32_t l = static_cast<std::uint32_t>(labels[i]);
    std::memcpy(p + 24, &l, 4);
  }
  writeAtomically(path, [&](const std::string& tmp) {
    pcl::PCDWriter writer;
    if (cloud.empty()) {
      // PCL refuses to write an empty binary cloud; an ASCII header with no points is valid.
      if (writer.writeASCII(tmp, c) < 0) throw Error("cannot write '" + path + "'");
      return;
    }
    if (writer.writeBinary(tmp, c) < 0) throw Error("cannot write '" + path + "'");
  });
}

void labelColor(int label, unsigned char& r, unsigned char& g, unsigned char& b) {
  if (label < 0) {
    r = g = b = 128;
    return;
  }
  // Golden-ratio hue steps keep any run of consecutive labels far apart on the colour wheel;
  // saturation and value cycle with different periods so that labels a full turn apart differ.
  const double phi = 0.618033988749894848;
  double h = std::fmod(0.1 + label * phi, 1.0) * 6.0;
  const double s = (label % 3 == 0) ? 0.85 : (label % 3 == 1 ? 0.65 : 0.75);
  const double v = (label % 2 == 0) ? 0.95 : 0.8;
  const int sector = static_cast<int>(std::floor(h)) % 6;
  const double f = h - std::floor(h);
  const double p = v * (1 - s), q = v * (1 - s * f), t = v * (1 - s * (1 - f));
  double rr, gg, bb;
  switch (sector) {
    case 0:
      rr = v;
      gg = t;
      bb = p;
      break;
    case 1:
      rr = q;
      gg = v;
      bb = p;
      break;
    case 2:
      rr = p;
      gg = v;
      bb = t;
      break;
    case 3:
      rr = p;
      gg = q;
      bb = v;
      break;
    case 4:
      rr = t;
      gg = p;
      bb = v;
      break;
    default:
      rr = v;
      gg = p;
      bb = q;
      break;
  }
  r = static_cast<unsigned char>(std::lround(rr * 255.0));
  g = static_cast<unsigned char>(std::lround(gg * 255.0));
  b = static_cast<unsigned char>(std::lround(bb * 255.0));
}

void saveLabelledPLY(const std::string& path, const PointCloudSequence::Cloud& cloud,
                     const std::vector<int>& labels) {
  checkLabels(path, cloud, labels);
  std::ostringstream head;
  head << "ply\nformat binary_little_endian 1.0\ncomment pcl_animseg labelled frame\n"
       << "element vertex " << cloud.size() << "\n"
       << "property float x\nproperty float y\nproperty float z\n"
       << "property float nx\nproperty float ny\nproperty float nz\n"
       << "property uchar red\nproperty uchar green\nproperty uchar blue\n"
       << "property int label\nend_header\n";
  std::string data = head.str();
  data.reserve(data.size() + cloud.size() * 31);
  for (std::size_t i = 0; i < cloud.size(); ++i) {
    const auto& p = cloud[i];
    for (float v : {p.x, p.y, p.z, p.normal_x, p.normal_y, p.normal_z}) putLE(data, v);
    unsigned char r, g, b;
    labelColor(labels[i], r, g, b);
    data.push_back(static_cast<char>(r));
    data.push_back(static_cast<char>(g));
    data.push_back(static_cast<char>(b));
    putLE(data, static_cast<std::int32_t>(labels[i]));
  }
  writeAtomically(path, [&](const std::string& tmp) { writeBytes(path, tmp, data); });
}

void savePLY(const std::string& path, const PointCloudSequence::Cloud& cloud,
             const std::vector<pcl::Vertices>& faces, bool binary) {
  for (const auto& f : faces) {
    if (f.vertices.size() < 3 || f.vertices.size() > 255)
      throw Error("cannot write '" + path + "': a face has " + std::to_string(f.vertices.size()) +
                  " vertices (3..255 allowed)");
    for (auto i : f.vertices)
      if (i < 0 || static_cast<std::size_t>(i) >= cloud.size())
        throw Error("cannot write '" + path + "': a face refers to vertex " + std::to_string(i) +
                    " of " + std::to_string(cloud.size()));
  }
  std::ostringstream head;
  head << "ply\nformat " << (binary ? "binary_little_endian" : "ascii") << " 1.0\n"
       << "comment pcl_animseg\n"
       << "element vertex " << cloud.size() << "\n"
       << "property float x\nproperty float y\nproperty float z\n"
       << "property float nx\nproperty float ny\nproperty float nz\n";
  if (!faces.empty())
    head << "element face " << faces.size() << "\nproperty list uchar int vertex_indices\n";
  head << "end_header\n";
  std::string data = head.str();
  if (binary) {
    for (const auto& p : cloud)
      for (float v : {p.x, p.y, p.z, p.normal_x, p.normal_y, p.normal_z}) putLE(data, v);
    for (const auto& f : faces) {
      data.push_back(static_cast<char>(static_cast<unsigned char>(f.vertices.size())));
      for (auto i : f.vertices) putLE(data, static_cast<std::int32_t>(i));
    }
  } else {
    std::string line;
    for (const auto& p : cloud) {
      line = fmt(p.x) + ' ' + fmt(p.y) + ' ' + fmt(p.z) + ' ' + fmt(p.normal_x) + ' ' +
             fmt(p.normal_y) + ' ' + fmt(p.normal_z) + '\n';
      data += line;
    }
    for (const auto& f : faces) {
      data += std::to_string(f.vertices.size());
      for (auto i : f.vertices) data += ' ' + std::to_string(i);
      data += '\n';
    }
  }
  writeAtomically(path, [&](const std::string& tmp) { writeBytes(path, tmp, data); });
}

void saveLabels(const std::string& path, const std::vector<std::vector<int>>& columns) {
  if (columns.empty()) throw Error("cannot write '" + path + "': no label columns");
  const std::size_t n = columns.front().size();
  for (std::size_t c = 1; c < columns.size(); ++c)
    if (columns[c].size() != n)
      throw Error("cannot write '" + path + "': label column " + std::to_string(c) + " has " +
                  std::to_string(columns[c].size()) + " entries, column 0 has " +
                  std::to_string(n));
  std::string text;
  text.reserve(n * columns.size() * 4);
  for (std::size_t i = 0; i < n; ++i) {
    for (std::size_t c = 0; c < columns.size(); ++c) {
      if (c) text += ' ';
      text += std::to_string(columns[c][i]);
    }
    text += '\n';
  }
  writeTextAtomically(path, text);
}

std::vector<std::vector<int>> loadLabelColumns(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error("cannot open labels file '" + path + "'");
  std::vector<std::vector<int>> columns;
  std::string line;
  std::size_t number = 0, rows = 0, blank_run = 0;
  std::vector<int> row;
  while (std::getline(in, line)) {
    ++number;
    row.clear();
    const char* s = line.c_str();
    bool comment = false;
    while (*s) {
      while (*s == ' ' || *s == '\t' || *s == '\r' || *s == ',') ++s;
      if (!*s) break;
      if (*s == '#' && row.empty()) {
        comment = true;
        break;
      }
      char* end = nullptr;
      errno = 0;
      const long v = std::strtol(s, &end, 10);
      if (end == s || (*end && *end != ' ' && *end != '\t' && *end != '\r' && *end != ',') ||
          errno == ERANGE || v < INT32_MIN || v > INT32_MAX)
        throw Error("labels file '" + path + "' line " + std::to_string(number) +
                    ": not an integer: '" + line + "'");
      row.push_back(static_cast<int>(v));
      s = end;
    }
    if (comment) continue;
    if (row.empty()) {
      ++blank_run;  // allowed only at the end of the file (checked below)
      continue;
    }
    if (blank_run > 0)
      throw Error("labels file '" + path + "' line " + std::to_string(number - blank_run) +
                  " is empty: every point needs a line");
    if (rows == 0) columns.resize(row.size());
    if (row.size() != columns.size())
      throw Error("labels file '" + path + "' line " + std::to_string(number) + " has " +
                  std::to_string(row.size()) + " columns, the first line has " +
                  std::to_string(columns.size()));
    for (std::size_t c = 0; c < row.size(); ++c) columns[c].push_back(row[c]);
    ++rows;
  }
  if (in.bad()) throw Error("read error in labels file '" + path + "'");
  return columns;
}

std::vector<int> loadLabels(const std::string& path, int column) {
  auto columns = loadLabelColumns(path);
  if (columns.empty()) return {};
  if (column < 0 || static_cast<std::size_t>(column) >= columns.size())
    throw Error("labels file '" + path + "' has " + std::to_string(columns.size()) +
                " column(s); column " + std::to_string(column) + " was asked for");
  return std::move(columns[column]);
}

}  // namespace io
}  // namespace pcl_animseg
