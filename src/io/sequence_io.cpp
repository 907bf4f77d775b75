#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/frame_readers.h>
#include <pcl_animseg/io/normals.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

namespace pcl_animseg {
namespace io {

namespace fs = std::filesystem;

namespace {

std::string lowerExt(const std::string& path) {
  std::string e = fs::path(path).extension().string();
  for (auto& c : e) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return e;
}

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r\n");
  if (b == std::string::npos) return "";
  const auto e = s.find_last_not_of(" \t\r\n");
  return s.substr(b, e - b + 1);
}

bool finite3(const Eigen::Vector3f& v) {
  return std::isfinite(v.x()) && std::isfinite(v.y()) && std::isfinite(v.z());
}

const char* kFrameExtensions = ".obj .ply .off .pcd .xyz";

}  // namespace

bool naturalLess(const std::string& a, const std::string& b) {
  std::size_t i = 0, j = 0;
  while (i < a.size() && j < b.size()) {
    const bool da = std::isdigit(static_cast<unsigned char>(a[i]));
    const bool db = std::isdigit(static_cast<unsigned char>(b[j]));
    if (da && db) {
      // Compare digit runs as numbers of any length: skip leading zeros, then longer is larger.
      std::size_t ie = i, je = j;
      while (ie < a.size() && std::isdigit(static_cast<unsigned char>(a[ie]))) ++ie;
      while (je < b.size() && std::isdigit(static_cast<unsigned char>(b[je]))) ++je;
      std::size_t is = i, js = j;
      while (is + 1 < ie && a[is] == '0') ++is;
      while (js + 1 < je && b[js] == '0') ++js;
      if (ie - is != je - js) return ie - is < je - js;
      const int c = a.compare(is, ie - is, b, js, je - js);
      if (c != 0) return c < 0;
      i = ie;
      j = je;
    } else {
      const int ca = std::tolower(static_cast<unsigned char>(a[i]));
      const int cb = std::tolower(static_cast<unsigned char>(b[j]));
      if (ca != cb) return ca < cb;
      ++i;
      ++j;
    }
  }
  if ((i < a.size()) != (j < b.size())) return i >= a.size();
  // Equal up to case and leading zeros ("f01" vs "f1"): fall back to plain order so that the
  // order is strict and total.
  return a < b;
}

bool isFrameFile(const std::string& path) {
  const std::string e = lowerExt(path);
  return e == ".obj" || e == ".ply" || e == ".off" || e == ".pcd" || e == ".xyz";
}

std::string stem(const std::string& path) { return fs::path(path).stem().string(); }

std::vector<std::string> listSequence(const std::string& path) {
  std::error_code ec;
  if (path.empty()) throw Error("no input given (expected a directory of frames or a list file)");
  if (!fs::exists(path, ec)) throw Error("input '" + path + "' does not exist");
  std::vector<std::string> frames;
  if (fs::is_directory(path, ec)) {
    std::vector<std::string> names;
    for (const auto& entry : fs::directory_iterator(path, ec)) {
      const std::string name = entry.path().filename().string();
      // Hidden files include our own temporary files (atomic_file.h) and editor droppings.
      if (name.empty() || name[0] == '.') continue;
      if (!entry.is_regular_file(ec) || !isFrameFile(name)) continue;
      names.push_back(name);
    }
    if (ec) throw Error("cannot list directory '" + path + "': " + ec.message());
    if (names.empty())
      throw Error("directory '" + path + "' contains no frame files (" + kFrameExtensions + ")");
    std::sort(names.begin(), names.end(), naturalLess);
    for (const auto& n : names) frames.push_back((fs::path(path) / n).string());
    return frames;
  }
  // A single frame file is a one-frame sequence; anything else is read as a list file.
  if (isFrameFile(path)) return {path};
  std::ifstream in(path);
  if (!in) throw Error("cannot open list file '" + path + "'");
  const fs::path base = fs::path(path).parent_path();
  std::string line;
  std::size_t number = 0;
  while (std::getline(in, line)) {
    ++number;
    const std::string entry = trim(line);
    if (entry.empty() || entry[0] == '#') continue;
    if (entry.find('\0') != std::string::npos)
      throw Error("'" + path + "' is neither a directory nor a text list of frame files");
    fs::path p(entry);
    if (p.is_relative()) p = base / p;
    const std::string ps = p.lexically_normal().string();
    if (!fs::exists(p, ec))
      throw Error("list file '" + path + "' line " + std::to_string(number) + " names '" + entry +
                  "', which does not exist (looked for '" + ps + "')");
    if (!isFrameFile(ps))
      throw Error("list file '" + path + "' line " + std::to_string(number) + " names '" + entry +
                  "', which is not a frame file (" + kFrameExtensions + ")");
    frames.push_back(ps);
  }
  if (frames.empty()) throw Error("list file '" + path + "' names no frames");
  return frames;
}

void loadFrame(const std::string& path, PointCloudSequence& sequence, const LoadOptions& options) {
  RawFrame raw = readRawFrame(path);
  const std::size_t n_in = raw.points.size();
  const bool have_file_normals = !raw.normals.empty();
  if (have_file_normals && raw.normals.size() != n_in)
    throw Error("'" + path + "': normal count does not match point count");

  // Drop points with NaN/Inf coordinates, remembering where each kept point came from.
  std::vector<int> index;
  std::vector<int> remap(n_in, -1);
  index.reserve(n_in);
  for (std::size_t i = 0; i < n_in; ++i)
    if (finite3(raw.points[i])) {
      remap[i] = static_cast<int>(index.size());
      index.push_back(static_cast<int>(i));
    }
  const std::size_t n = index.size();
  if (n == 0)
    throw Error("'" + path + "': no valid points (" + std::to_string(n_in) +
                (n_in ? " points, all with NaN/Inf coordinates)" : " points)"));
  if (n < options.min_points)
    throw Error("'" + path + "': only " + std::to_string(n) +
                (n == 1 ? " valid point" : " valid points") + ", at least " +
                std::to_string(options.min_points) + " are needed");

  PointCloudSequence::Cloud::Ptr cloud(new PointCloudSequence::Cloud);
  cloud->resize(n);
  for (std::size_t j = 0; j < n; ++j) {
    auto& p = (*cloud)[j];
    p.getVector3fMap() = raw.points[index[j]];
    p.normal_x = p.normal_y = p.normal_z = std::numeric_limits<float>::quiet_NaN();
    p.curvature = 0.0f;
  }
  cloud->width = static_cast<std::uint32_t>(n);
  cloud->height = 1;
  cloud->is_dense = true;
  if (boundingBoxDiagonal(*cloud) <= 0.0)
    throw Error("'" + path + "': all " + std::to_string(n) +
                " points coincide (a frame needs an extent)");

  std::vector<pcl::Vertices> faces;
  faces.reserve(raw.faces.size());
  for (const auto& f : raw.faces) {
    pcl::Vertices g;
    bool ok = true;
    for (auto i : f.vertices) {
      if (i < 0 || static_cast<std::size_t>(i) >= n_in || remap[i] < 0) {
        ok = false;  // a face touching a dropped point is dropped with it
        break;
      }
      g.vertices.push_back(remap[i]);
    }
    if (ok) faces.push_back(std::move(g));
  }

  std::vector<char> known(n, 0);
  if (!faces.empty()) known = computeMeshNormals(*cloud, faces);
  bool all_known = true;
  for (std::size_t j = 0; j < n; ++j) {
    if (known[j]) continue;
    if (have_file_normals) {
      const Eigen::Vector3f nn = raw.normals[index[j]];
      const float len = nn.norm();
      if (finite3(nn) && len > 1e-12f) {
        (*cloud)[j].getNormalVector3fMap() = nn / len;
        known[j] = 1;
        continue;
      }
    }
    all_known = false;
  }
  std::size_t estimated = 0;
  if (!all_known) {
    estimateNormals(*cloud, options.normal_k, known);
    for (char k : known) estimated += !k;
  }

  sequence.addFrame(cloud, stem(path), path, std::move(index), n_in, std::move(faces));
  sequence.setEstimatedNormals(sequence.size() - 1, estimated);
}

PointCloudSequence loadSequence(const std::string& path, const LoadOptions& options,
                                Progress* progress) {
  const std::vector<std::string> files = listSequence(path);
  const int nf = static_cast<int>(files.size());
  // Frames load independently into their own one-frame sequences; formats may be mixed freely.
  std::vector<PointCloudSequence> parts(files.size());
  std::vector<std::string> errors(files.size());
  std::atomic<std::size_t> done{0};
  if (progress) progress->begin("load", files.size());
    // With fewer frames than threads, frames load one after another so that the normal estimation
    // inside each (OpenMP itself) gets the threads instead of running nested and serial.
#pragma omp parallel for schedule(dynamic, 1) if (nf >= omp_get_max_threads())
  for (int t = 0; t < nf; ++t) {
    try {
      loadFrame(files[t], parts[t], options);
    } catch (const std::exception& e) {
      errors[t] = e.what();
    }
    const std::size_t d = ++done;
    if (progress && omp_get_thread_num() == 0) progress->update(d);
  }
  // The first failing frame in sequence order decides the message, whatever the thread timing.
  for (int t = 0; t < nf; ++t)
    if (!errors[t].empty())
      throw Error("cannot load frame " + std::to_string(t) + " of '" + path + "': " + errors[t]);

  PointCloudSequence seq;
  for (int t = 0; t < nf; ++t) {
    const PointCloudSequence& p = parts[t];
    seq.addFrame(p.frame(0), p.name(0), p.source(0), p.inputIndex(0), p.inputSize(0), p.faces(0));
    seq.setEstimatedNormals(seq.size() - 1, p.estimatedNormals(0));
  }

  if (options.max_scale_ratio > 0.0 && nf > 1) {
    std::size_t tmin = 0, tmax = 0;
    std::vector<double> diag(files.size());
    for (int t = 0; t < nf; ++t) {
      diag[t] = boundingBoxDiagonal(*seq.frame(t));
      if (diag[t] < diag[tmin]) tmin = t;
      if (diag[t] > diag[tmax]) tmax = t;
    }
    if (diag[tmin] <= 0.0)
      throw Error("frame '" + seq.source(tmin) + "': all points coincide (zero extent)");
    const double ratio = diag[tmax] / diag[tmin];
    if (ratio > options.max_scale_ratio) {
      std::ostringstream msg;
      msg << "mixed units: frame '" << seq.source(tmax) << "' is " << ratio
          << " times larger (bounding-box diagonal " << diag[tmax] << ") than frame '"
          << seq.source(tmin) << "' (" << diag[tmin] << "), more than the allowed factor "
          << options.max_scale_ratio << "; convert all frames to the same unit";
      throw Error(msg.str());
    }
  }
  if (progress) {
    std::ostringstream detail;
    detail << nf << " frames, " << seq.totalPoints() << " points";
    progress->end(detail.str());
  }
  return seq;
}

}  // namespace io
}  // namespace pcl_animseg
