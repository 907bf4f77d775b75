#include <pcl/PCLPointCloud2.h>
#include <pcl/common/io.h>
#include <pcl/io/lzf.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/frame_readers.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <set>

namespace pcl_animseg {
namespace io {

namespace {

/** A whole number read as a double, for an error message: digits when it fits a long long,
 * otherwise as printf's %g (a cast of 9e34 to an integer is undefined; found by fuzz_ply). */
std::string integerText(double v) {
  if (std::isfinite(v) && std::abs(v) < 9.0e18) return std::to_string(static_cast<long long>(v));
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%g", v);
  return buf;
}

const float kNaN = std::numeric_limits<float>::quiet_NaN();

Error fileError(const std::string& path, const std::string& what) {
  return Error("'" + path + "': " + what);
}

Error lineError(const std::string& path, std::size_t line, const std::string& what) {
  return Error("'" + path + "' line " + std::to_string(line) + ": " + what);
}

std::string readWholeFile(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) throw fileError(path, "file does not exist");
  if (std::filesystem::is_directory(path, ec)) throw fileError(path, "is a directory, not a file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw fileError(path, std::string("cannot open: ") + std::strerror(errno));
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) throw fileError(path, "read error");
  return ss.str();
}

/** Splits into lines (LF or CRLF); keeps line numbers implicit (index + 1). */
std::vector<std::string> splitLines(const std::string& text) {
  std::vector<std::string> lines;
  std::size_t start = 0;
  while (start <= text.size()) {
    std::size_t end = text.find('\n', start);
    if (end == std::string::npos) end = text.size();
    std::string line = text.substr(start, end - start);
    if (!line.empty() && line.back() == '\r') line.pop_back();
    lines.push_back(std::move(line));
    if (end == text.size()) break;
    start = end + 1;
  }
  return lines;
}

/** Parses whitespace-separated numbers from `s`; returns false at the first token that is not a
 * number (strtod accepts nan/inf, which is what we want: those points are dropped later). */
bool parseNumbers(const char* s, std::vector<double>& out, std::size_t max_count = 64) {
  out.clear();
  while (*s && out.size() < max_count) {
    while (*s && std::isspace(static_cast<unsigned char>(*s))) ++s;
    if (!*s) break;
    char* end = nullptr;
    const double v = std::strtod(s, &end);
    if (end == s) return false;
    if (*end && !std::isspace(static_cast<unsigned char>(*end))) return false;
    out.push_back(v);
    s = end;
  }
  return true;
}

bool checkBinaryText(const std::string& text) {
  // Text formats must not contain NUL bytes; catches binary garbage early with a clear message.
  return text.find('\0') == std::string::npos;
}

void fanTriangulate(const pcl::Indices& poly, std::vector<pcl::Vertices>& faces) {
  for (std::size_t a = 1; a + 1 < poly.size(); ++a) {
    pcl::Vertices t;
    t.vertices = {poly[0], poly[a], poly[a + 1]};
    faces.push_back(std::move(t));
  }
}

double fieldValue(const std::uint8_t* p, std::uint8_t type) {
  switch (type) {
    case pcl::PCLPointField::INT8:
      return *reinterpret_cast<const std::int8_t*>(p);
    case pcl::PCLPointField::UINT8:
      return *p;
    case pcl::PCLPointField::INT16: {
      std::int16_t v;
      std::memcpy(&v, p, 2);
      return v;
    }
    case pcl::PCLPointField::UINT16: {
      std::uint16_t v;
      std::memcpy(&v, p, 2);
      return v;
    }
    case pcl::PCLPointField::INT32: {
      std::int32_t v;
      std::memcpy(&v, p, 4);
      return v;
    }
    case pcl::PCLPointField::UINT32: {
      std::uint32_t v;
      std::memcpy(&v, p, 4);
      return v;
    }
    case pcl::PCLPointField::FLOAT32: {
      float v;
      std::memcpy(&v, p, 4);
      return v;
    }
    case pcl::PCLPointField::FLOAT64: {
      double v;
      std::memcpy(&v, p, 8);
      return v;
    }
    default:
      return std::numeric_limits<double>::quiet_NaN();
  }
}

/** Copies x y z (and normals when all three fields exist) out of a PCLPointCloud2. */
void fromCloud2(const pcl::PCLPointCloud2& c, const std::string& path, RawFrame& raw) {
  auto field = [&](const char* name) -> const pcl::PCLPointField* {
    for (const auto& f : c.fields)
      if (f.name == name) return &f;
    return nullptr;
  };
  const pcl::PCLPointField* xyz[3] = {field("x"), field("y"), field("z")};
  if (!xyz[0] || !xyz[1] || !xyz[2]) throw fileError(path, "has no x y z fields");
  const pcl::PCLPointField* nrm[3] = {field("normal_x"), field("normal_y"), field("normal_z")};
  const bool has_normals = nrm[0] && nrm[1] && nrm[2];
  const std::size_t n = static_cast<std::size_t>(c.width) * c.height;
  if (c.point_step == 0 || c.data.size() < static_cast<std::size_t>(c.row_step) * c.height ||
      static_cast<std::size_t>(c.row_step) < static_cast<std::size_t>(c.width) * c.point_step)
    throw fileError(path, "the point data is shorter than the header says (truncated file?)");
  for (const auto* f : xyz)
    if (f->offset + 4 > c.point_step) throw fileError(path, "corrupt field layout");
  raw.points.resize(n);
  if (has_normals) raw.normals.resize(n);
  for (std::size_t r = 0, i = 0; r < c.height; ++r)
    for (std::size_t col = 0; col < c.width; ++col, ++i) {
      const std::uint8_t* p = c.data.data() + r * c.row_step + col * c.point_step;
      for (int a = 0; a < 3; ++a)
        raw.points[i][a] = static_cast<float>(fieldValue(p + xyz[a]->offset, xyz[a]->datatype));
      if (has_normals)
        for (int a = 0; a < 3; ++a)
          raw.normals[i][a] = static_cast<float>(fieldValue(p + nrm[a]->offset, nrm[a]->datatype));
    }
}

std::string lower(std::string s) {
  for (auto& ch : s) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
  return s;
}

}  // namespace

RawFrame readOBJ(const std::string& path) {
  const std::string text = readWholeFile(path);
  if (!checkBinaryText(text)) throw fileError(path, "is not a text OBJ file (binary content)");
  RawFrame raw;
  raw.format = "obj";
  std::vector<Eigen::Vector3f> vn;
  std::vector<std::pair<std::size_t, std::vector<long>>> polys;  // line, raw 0-based indices
  std::vector<double> vals;
  const auto lines = splitLines(text);
  for (std::size_t l = 0; l < lines.size(); ++l) {
    const char* s = lines[l].c_str();
    while (*s == ' ' || *s == '\t') ++s;
    if (s[0] == 'v' && (s[1] == ' ' || s[1] == '\t')) {
      if (!parseNumbers(s + 2, vals, 3) || vals.size() < 3)
        throw lineError(path, l + 1, "a vertex needs three numbers: '" + lines[l] + "'");
      raw.points.emplace_back(vals[0], vals[1], vals[2]);
    } else if (s[0] == 'v' && s[1] == 'n' && (s[2] == ' ' || s[2] == '\t')) {
      if (!parseNumbers(s + 3, vals, 3) || vals.size() < 3)
        throw lineError(path, l + 1, "a normal needs three numbers: '" + lines[l] + "'");
      vn.emplace_back(vals[0], vals[1], vals[2]);
    } else if (s[0] == 'f' && (s[1] == ' ' || s[1] == '\t')) {
      std::istringstream ss(s + 2);
      std::string tok;
      std::vector<long> poly;
      while (ss >> tok) {
        char* end = nullptr;
        const long v = std::strtol(tok.c_str(), &end, 10);
        if (end == tok.c_str() || (*end && *end != '/') || v == 0)
          throw lineError(path, l + 1, "bad face vertex '" + tok + "'");
        // Negative indices count back from the last vertex defined so far (OBJ spec).
        const long idx = v > 0 ? v - 1 : static_cast<long>(raw.points.size()) + v;
        if (idx < 0)
          throw lineError(path, l + 1, "face vertex " + tok + " refers before the first vertex");
        poly.push_back(idx);
      }
      if (poly.size() >= 3) polys.emplace_back(l + 1, std::move(poly));
    }
  }
  const long nv = static_cast<long>(raw.points.size());
  for (const auto& [line, poly] : polys) {
    pcl::Indices p;
    for (long i : poly) {
      if (i >= nv)
        throw lineError(path, line,
                        "face refers to vertex " + std::to_string(i + 1) + " but the file has " +
                            std::to_string(nv));
      p.push_back(static_cast<int>(i));
    }
    fanTriangulate(p, raw.faces);
  }
  if (raw.faces.empty() && !vn.empty() && vn.size() == raw.points.size()) raw.normals = vn;
  return raw;
}

RawFrame readOFF(const std::string& path) {
  const std::string text = readWholeFile(path);
  if (!checkBinaryText(text)) throw fileError(path, "is not a text OFF file (binary content)");
  RawFrame raw;
  raw.format = "off";
  // Non-empty lines with comments stripped, with their line numbers.
  std::vector<std::pair<std::size_t, std::string>> lines;
  {
    const auto all = splitLines(text);
    for (std::size_t l = 0; l < all.size(); ++l) {
      std::string s = all[l].substr(0, all[l].find('#'));
      if (s.find_first_not_of(" \t\r") == std::string::npos) continue;
      lines.emplace_back(l + 1, std::move(s));
    }
  }
  if (lines.empty()) throw fileError(path, "is empty");
  std::istringstream head(lines[0].second);
  std::string keyword;
  head >> keyword;
  if (keyword.size() < 3 || keyword.compare(keyword.size() - 3, 3, "OFF") != 0)
    throw fileError(path, "is not an OFF file (the first word is '" + keyword + "', not OFF)");
  const std::string prefix = keyword.substr(0, keyword.size() - 3);
  bool has_normals = false;
  for (std::size_t i = 0; i < prefix.size(); ++i) {
    const char c = prefix[i];
    if (c == 'N') {
      has_normals = true;
    } else if (c == 'C' || c == 'S' || c == 'T') {
      // Colours / texture coordinates follow the position (and normal); they are skipped.
    } else if (c == '4' || c == 'n') {
      throw fileError(path, "4D / nD OFF files are not supported");
    } else {
      throw fileError(path, "unknown OFF variant '" + keyword + "'");
    }
  }
  std::string rest;
  std::getline(head, rest);
  std::size_t next = 1;
  if (lower(rest).find("binary") != std::string::npos)
    throw fileError(path, "binary OFF is not supported (convert it to text OFF or PLY)");
  std::vector<double> vals;
  if (!parseNumbers(rest.c_str(), vals) || vals.empty()) {
    if (lines.size() < 2) throw fileError(path, "ends before the vertex/face counts");
    if (!parseNumbers(lines[1].second.c_str(), vals))
      throw lineError(path, lines[1].first, "expected the vertex, face and edge counts");
    next = 2;
  }
  if (vals.size() < 2 || vals[0] < 0 || vals[1] < 0 || vals[0] != std::floor(vals[0]) ||
      vals[1] != std::floor(vals[1]))
    throw fileError(path, "bad vertex/face counts");
  // Checked as doubles first: a count beyond size_t (found by fuzz_off) must not be cast.
  if (vals[0] + vals[1] > static_cast<double>(lines.size()))
    throw fileError(path, "truncated: the header announces " + std::to_string(vals[0]) +
                              " vertices and " + std::to_string(vals[1]) +
                              " faces but the file has only " +
                              std::to_string(lines.size()) + " lines");
  const std::size_t nv = static_cast<std::size_t>(vals[0]);
  const std::size_t nf = static_cast<std::size_t>(vals[1]);
  if (lines.size() - next < nv)
    throw fileError(path, "truncated: the header announces " + std::to_string(nv) +
                              " vertices but the file has only " +
                              std::to_string(lines.size() - next) + " more lines");
  const std::size_t need = has_normals ? 6 : 3;
  raw.points.reserve(nv);
  if (has_normals) raw.normals.reserve(nv);
  for (std::size_t i = 0; i < nv; ++i, ++next) {
    const auto& [ln, s] = lines[next];
    if (!parseNumbers(s.c_str(), vals, need) || vals.size() < need)
      throw lineError(
          path, ln, "vertex " + std::to_string(i) + " needs " + std::to_string(need) + " numbers");
    raw.points.emplace_back(vals[0], vals[1], vals[2]);
    if (has_normals) raw.normals.emplace_back(vals[3], vals[4], vals[5]);
  }
  if (lines.size() - next < nf)
    throw fileError(path, "truncated: the header announces " + std::to_string(nf) +
                              " faces but the file has only " +
                              std::to_string(lines.size() - next));
  for (std::size_t f = 0; f < nf; ++f, ++next) {
    const auto& [ln, s] = lines[next];
    std::istringstream ss(s);
    long count = -1;
    ss >> count;
    if (!ss || count < 0) throw lineError(path, ln, "bad face line");
    pcl::Indices poly;
    for (long a = 0; a < count; ++a) {
      long idx = -1;
      ss >> idx;
      if (!ss) throw lineError(path, ln, "face has fewer indices than its count");
      if (idx < 0 || static_cast<std::size_t>(idx) >= nv)
        throw lineError(path, ln,
                        "face refers to vertex " + std::to_string(idx) + " but the file has " +
                            std::to_string(nv));
      poly.push_back(static_cast<int>(idx));
    }
    fanTriangulate(poly, raw.faces);
  }
  return raw;
}

namespace {

// PLY is read by hand: PCL's PLY reader aborts the process (an assert) on some corrupt files, and
// a tool must be able to print one `error:` line instead.

enum class PlyType { kNone, kI8, kU8, kI16, kU16, kI32, kU32, kF32, kF64 };

PlyType plyType(const std::string& t) {
  if (t == "char" || t == "int8") return PlyType::kI8;
  if (t == "uchar" || t == "uint8") return PlyType::kU8;
  if (t == "short" || t == "int16") return PlyType::kI16;
  if (t == "ushort" || t == "uint16") return PlyType::kU16;
  if (t == "int" || t == "int32") return PlyType::kI32;
  if (t == "uint" || t == "uint32") return PlyType::kU32;
  if (t == "float" || t == "float32") return PlyType::kF32;
  if (t == "double" || t == "float64") return PlyType::kF64;
  return PlyType::kNone;
}

int plySize(PlyType t) {
  switch (t) {
    case PlyType::kI8:
    case PlyType::kU8:
      return 1;
    case PlyType::kI16:
    case PlyType::kU16:
      return 2;
    case PlyType::kI32:
    case PlyType::kU32:
    case PlyType::kF32:
      return 4;
    case PlyType::kF64:
      return 8;
    default:
      return 0;
  }
}

struct PlyProperty {
  std::string name;
  PlyType type = PlyType::kNone;        // item type for lists
  PlyType count_type = PlyType::kNone;  // kNone: not a list
};

struct PlyElement {
  std::string name;
  long count = 0;
  std::vector<PlyProperty> properties;
  long min_bytes = 0;  // lower bound per instance in binary (a list holds at least its count)
};

/** Reads PLY values from the body, ascii or binary of either endianness, with bounds checks. */
class PlyBody {
 public:
  PlyBody(const std::string& path, const std::string& text, std::size_t begin,
          const std::string& format)
      : path_(path),
        text_(text),
        pos_(begin),
        ascii_(format == "ascii"),
        swap_(format == "binary_big_endian") {}

  /** Throws a truncation error naming `where` when the data ends early. */
  double read(PlyType t, const std::string& where) {
    if (ascii_) {
      while (pos_ < text_.size() && std::isspace(static_cast<unsigned char>(text_[pos_]))) ++pos_;
      if (pos_ >= text_.size()) throw fileError(path_, "truncated: the data ends in " + where);
      const char* s = text_.c_str() + pos_;
      char* end = nullptr;
      const double v = std::strtod(s, &end);
      if (end == s || (*end && !std::isspace(static_cast<unsigned char>(*end))))
        throw fileError(path_, "bad number '" +
                                   std::string(s, std::min<std::size_t>(16, std::strlen(s))) +
                                   "' in " + where);
      pos_ += static_cast<std::size_t>(end - s);
      return v;
    }
    const int n = plySize(t);
    if (pos_ + n > text_.size()) throw fileError(path_, "truncated: the data ends in " + where);
    unsigned char b[8];
    std::memcpy(b, text_.data() + pos_, n);
    pos_ += n;
    if (swap_) std::reverse(b, b + n);
    switch (t) {
      case PlyType::kI8:
        return static_cast<std::int8_t>(b[0]);
      case PlyType::kU8:
        return b[0];
      case PlyType::kI16: {
        std::int16_t v;
        std::memcpy(&v, b, 2);
        return v;
      }
      case PlyType::kU16: {
        std::uint16_t v;
        std::memcpy(&v, b, 2);
        return v;
      }
      case PlyType::kI32: {
        std::int32_t v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::kU32: {
        std::uint32_t v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::kF32: {
        float v;
        std::memcpy(&v, b, 4);
        return v;
      }
      case PlyType::kF64: {
        double v;
        std::memcpy(&v, b, 8);
        return v;
      }
      default:
        return 0.0;
    }
  }

 private:
  const std::string& path_;
  const std::string& text_;
  std::size_t pos_;
  bool ascii_, swap_;
};

}  // namespace

RawFrame readPLY(const std::string& path) {
  const std::string text = readWholeFile(path);
  if (text.compare(0, 3, "ply") != 0 || (text.size() > 3 && text[3] != '\n' && text[3] != '\r'))
    throw fileError(path, "is not a PLY file (it does not start with 'ply')");
  const std::size_t end = text.find("end_header");
  if (end == std::string::npos)
    throw fileError(path, "has no 'end_header' (truncated or corrupt PLY header)");
  const std::size_t newline = text.find('\n', end);
  if (newline == std::string::npos) throw fileError(path, "truncated after 'end_header'");
  const std::size_t body = newline + 1;

  std::istringstream head(text.substr(0, end));
  std::string line, format;
  std::vector<PlyElement> elements;
  std::size_t number = 0;
  while (std::getline(head, line)) {
    ++number;
    std::istringstream ss(line);
    std::string key;
    if (!(ss >> key) || key == "ply" || key == "comment" || key == "obj_info") continue;
    if (key == "format") {
      ss >> format;
    } else if (key == "element") {
      PlyElement e;
      if (!(ss >> e.name >> e.count) || e.count < 0)
        throw lineError(path, number, "bad PLY element line '" + line + "'");
      elements.push_back(e);
    } else if (key == "property") {
      if (elements.empty()) throw lineError(path, number, "PLY property before any element");
      PlyProperty p;
      std::string type;
      ss >> type;
      if (type == "list") {
        std::string count_type, item_type;
        ss >> count_type >> item_type >> p.name;
        p.count_type = plyType(count_type);
        p.type = plyType(item_type);
        if (p.count_type == PlyType::kNone || p.type == PlyType::kNone ||
            p.count_type == PlyType::kF32 || p.count_type == PlyType::kF64)
          throw lineError(path, number, "bad PLY list property '" + line + "'");
        elements.back().min_bytes += plySize(p.count_type);
      } else {
        p.type = plyType(type);
        ss >> p.name;
        if (p.type == PlyType::kNone)
          throw lineError(path, number, "unknown PLY property type '" + type + "'");
        elements.back().min_bytes += plySize(p.type);
      }
      elements.back().properties.push_back(p);
    } else {
      throw lineError(path, number, "unexpected PLY header line '" + line + "'");
    }
  }
  if (format != "ascii" && format != "binary_little_endian" && format != "binary_big_endian")
    throw fileError(path, "unknown PLY format '" + format + "'");

  const PlyElement* vertex = nullptr;
  for (const auto& e : elements)
    if (e.name == "vertex") vertex = &e;
  if (!vertex) throw fileError(path, "PLY header has no vertex element");
  auto propIndex = [](const PlyElement& e, std::initializer_list<const char*> names) {
    for (const char* n : names)
      for (std::size_t i = 0; i < e.properties.size(); ++i)
        if (e.properties[i].name == n && e.properties[i].count_type == PlyType::kNone)
          return static_cast<int>(i);
    return -1;
  };
  const int ix = propIndex(*vertex, {"x"}), iy = propIndex(*vertex, {"y"}),
            iz = propIndex(*vertex, {"z"});
  if (ix < 0 || iy < 0 || iz < 0) throw fileError(path, "PLY vertices have no x y z properties");
  const int inx = propIndex(*vertex, {"nx", "normal_x"}),
            iny = propIndex(*vertex, {"ny", "normal_y"}),
            inz = propIndex(*vertex, {"nz", "normal_z"});
  const bool has_normals = inx >= 0 && iny >= 0 && inz >= 0;

  {
    // A lower bound, checked first so that a cut-off file says how much is missing (and a bogus
    // count is not allocated). In ascii every value takes at least a digit and a separator.
    const bool ascii = format == "ascii";
    double need = ascii ? -1 : 0;
    std::string what;
    for (const auto& e : elements) {
      const double per =
          ascii ? 2.0 * static_cast<double>(e.properties.size()) : static_cast<double>(e.min_bytes);
      need += static_cast<double>(e.count) * per;
      what += (what.empty() ? "" : ", ") + e.name + " x " + std::to_string(e.count);
    }
    const double have = static_cast<double>(text.size() - body);
    if (have < need)
      throw fileError(path, "truncated: the PLY header announces " + what + " (at least " +
                                integerText(need) +
                                " bytes) but the file has only " +
                                integerText(have) + " bytes of data");
  }

  RawFrame raw;
  raw.format = "ply";
  raw.points.resize(static_cast<std::size_t>(vertex->count));
  if (has_normals) raw.normals.resize(raw.points.size());
  PlyBody reader(path, text, body, format);
  std::vector<double> values;
  pcl::Indices poly;
  for (const auto& e : elements) {
    const bool is_vertex = &e == vertex;
    const bool is_face = e.name == "face";
    int face_list = -1;
    if (is_face) {
      for (std::size_t i = 0; i < e.properties.size() && face_list < 0; ++i)
        if (e.properties[i].count_type != PlyType::kNone &&
            (e.properties[i].name == "vertex_indices" || e.properties[i].name == "vertex_index"))
          face_list = static_cast<int>(i);
    }
    values.resize(e.properties.size());
    // An element without properties holds no data; looping over a huge count of it would hang
    // (found by fuzz_ply).
    if (e.properties.empty()) continue;
    for (long k = 0; k < e.count; ++k) {
      const std::string where = "element '" + e.name + "' " + std::to_string(k);
      for (std::size_t pi = 0; pi < e.properties.size(); ++pi) {
        const auto& p = e.properties[pi];
        if (p.count_type == PlyType::kNone) {
          values[pi] = reader.read(p.type, where);
          continue;
        }
        const double c = reader.read(p.count_type, where);
        if (c < 0 || c != std::floor(c) || c > 1e6)
          throw fileError(path, "bad list length " + std::to_string(c) + " in " + where);
        const long count = static_cast<long>(c);
        const bool keep = static_cast<int>(pi) == face_list;
        if (keep) poly.clear();
        for (long a = 0; a < count; ++a) {
          const double v = reader.read(p.type, where);
          if (!keep) continue;
          if (v < 0 || v >= static_cast<double>(vertex->count) || v != std::floor(v))
            throw fileError(path, "face " + std::to_string(k) + " refers to vertex " +
                                      integerText(v) +
                                      " but the file has " + std::to_string(vertex->count));
          poly.push_back(static_cast<int>(v));
        }
        if (keep) fanTriangulate(poly, raw.faces);
      }
      if (is_vertex) {
        raw.points[k] =
            Eigen::Vector3f(static_cast<float>(values[ix]), static_cast<float>(values[iy]),
                            static_cast<float>(values[iz]));
        if (has_normals)
          raw.normals[k] =
              Eigen::Vector3f(static_cast<float>(values[inx]), static_cast<float>(values[iny]),
                              static_cast<float>(values[inz]));
      }
    }
  }
  return raw;
}

namespace {

/** What checkPCDHeader learnt from a PCD header. */
struct PcdHeader {
  std::vector<std::string> fields;
  std::vector<long> sizes, counts;
  std::string types, data;
  long width = 0, height = 0;
  std::size_t data_offset = 0;  ///< bytes before the data (after the DATA line)
  std::vector<double> ascii_values;  ///< DATA ascii: every value, point after point
  std::uint32_t packed_bytes = 0;    ///< DATA binary_compressed: LZF bytes after the two sizes
};

/** The header checked before any data is read (PCL's PCD reader trusted it and crashed on
 * garbage): known keys, consistent counts, and that the file is long enough for the data; ASCII
 * data lines are checked and parsed here too. */
PcdHeader checkPCDHeader(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) throw fileError(path, "file does not exist");
  if (std::filesystem::is_directory(path, ec)) throw fileError(path, "is a directory, not a file");
  const std::uintmax_t file_size = std::filesystem::file_size(path, ec);
  std::ifstream in(path, std::ios::binary);
  if (!in) throw fileError(path, std::string("cannot open: ") + std::strerror(errno));
  std::vector<std::string> fields;
  std::vector<long> sizes, counts;
  std::string types, data;
  long width = -1, height = -1, points = -1;
  std::string line;
  std::size_t header_bytes = 0;
  const Error not_pcd = fileError(path, "is not a PCD file (bad or missing header)");
  std::set<std::string> seen;
  while (data.empty()) {
    if (!std::getline(in, line) || header_bytes > (1u << 16)) {
      if (fields.empty()) throw not_pcd;
      throw fileError(path, "PCD header has no DATA line (truncated or corrupt)");
    }
    header_bytes += line.size() + 1;
    if (line.find('\0') != std::string::npos) throw not_pcd;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream ss(line);
    std::string key;
    if (!(ss >> key) || key[0] == '#') continue;
    std::string tok;
    // WIDTH, HEIGHT and POINTS must be whole integers, given once: PCL's own reader crashes on a
    // header such as "WIDTH 4.7" followed by another WIDTH (found by fuzz_pcd).
    auto readCount = [&](long& out) {
      std::string v, rest;
      if (!(ss >> v) || (ss >> rest) || !seen.insert(key).second ||
          v.find_first_not_of("0123456789-") != std::string::npos)
        throw fileError(path, "PCD header: bad " + key + " line");
      try {
        out = std::stol(v);
      } catch (const std::exception&) {
        throw fileError(path, "PCD header: bad " + key + " line");
      }
    };
    if (key == "VERSION" || key == "VIEWPOINT") {
    } else if (key == "FIELDS") {
      while (ss >> tok) fields.push_back(tok);
    } else if (key == "SIZE" || key == "COUNT") {
      auto& v = key == "SIZE" ? sizes : counts;
      long x;
      while (ss >> x) v.push_back(x);
    } else if (key == "TYPE") {
      while (ss >> tok) types += tok.size() == 1 ? tok : std::string("?");
    } else if (key == "WIDTH") {
      readCount(width);
    } else if (key == "HEIGHT") {
      readCount(height);
    } else if (key == "POINTS") {
      readCount(points);
    } else if (key == "DATA") {
      ss >> data;
    } else {
      throw not_pcd;
    }
  }
  const std::size_t nf = fields.size();
  if (nf == 0 || sizes.size() != nf || types.size() != nf ||
      (!counts.empty() && counts.size() != nf))
    throw fileError(path, "PCD header: FIELDS, SIZE, TYPE and COUNT disagree");
  long point_size = 0;
  for (std::size_t i = 0; i < nf; ++i) {
    const long c = counts.empty() ? 1 : counts[i];
    // COUNT is bounded so that the sums below cannot overflow (found by fuzz_pcd).
    // A float is 4 or 8 bytes: PCL's reader segfaulted on a 1-byte F field (found by fuzz_pcd).
    if ((sizes[i] != 1 && sizes[i] != 2 && sizes[i] != 4 && sizes[i] != 8) || c < 1 ||
        c > (1L << 24) || std::string("IUF").find(types[i]) == std::string::npos ||
        (types[i] == 'F' && sizes[i] != 4 && sizes[i] != 8))
      throw fileError(path, "PCD header: bad SIZE/TYPE/COUNT for field '" + fields[i] + "'");
    point_size += sizes[i] * c;
  }
  if (width < 0 || height < 1) throw fileError(path, "PCD header: bad WIDTH/HEIGHT");
  PcdHeader h;
  // No file we read holds a petabyte; bounding the sizes first keeps the products below from
  // overflowing (found by fuzz_pcd). Such a header is a truncated (or corrupt) file.
  const double announced = static_cast<double>(width) * static_cast<double>(height);
  if (announced > 1e15 || announced * static_cast<double>(point_size) > 1e15) {
    char count[32];
    std::snprintf(count, sizeof(count), "%.0f", announced);
    throw fileError(path, std::string("truncated: the PCD header announces ") + count +
                              " points, more than any file holds");
  }
  if (points >= 0 && points != width * height)
    throw fileError(path, "PCD header: POINTS is not WIDTH x HEIGHT");
  const std::uintmax_t need = static_cast<std::uintmax_t>(width) * height * point_size;
  if (data == "binary") {
    if (file_size < header_bytes + need)
      throw fileError(
          path, "truncated: the PCD header announces " + std::to_string(width * height) +
                    " points (" + std::to_string(need) + " bytes) but the file has only " +
                    std::to_string(file_size - std::min<std::uintmax_t>(file_size, header_bytes)) +
                    " bytes of data");
  } else if (data == "binary_compressed") {
    std::uint32_t sz[2] = {0, 0};
    in.read(reinterpret_cast<char*>(sz), 8);
    // LZF expands at most 88-fold (264 bytes from a 3-byte back-reference): a header that
    // announces more is corrupt, and is rejected before anything of that size is allocated.
    if (!in || file_size < header_bytes + 8 + sz[0] || sz[1] != need ||
        static_cast<double>(sz[1]) > 100.0 * static_cast<double>(sz[0]) + 1024.0)
      throw fileError(path, "truncated or corrupt compressed PCD data");
    h.packed_bytes = sz[0];
  } else if (data == "ascii") {
    // Every value takes at least a digit and a separator: rejects a bogus count before anything
    // is allocated for it.
    long values = 0;
    for (std::size_t i = 0; i < nf; ++i) values += counts.empty() ? 1 : counts[i];
    const double need = 2.0 * static_cast<double>(width) * height * values - 1;
    if (static_cast<double>(file_size) - static_cast<double>(header_bytes) < need)
      throw fileError(path, "truncated: the PCD header announces " +
                                std::to_string(width * height) +
                                " points but the file is too short to hold them");
    // Every point a line of exactly `values` numbers, every value a number (PCL's ASCII reader
    // went out of bounds on a data line with other tokens, found by fuzz_pcd); the values are
    // kept for readAsciiPCD.
    const long expected = width * height;
    long lines = 0;
    h.ascii_values.reserve(static_cast<std::size_t>(expected) * static_cast<std::size_t>(values));
    while (std::getline(in, line)) {
      if (!line.empty() && line.back() == '\r') line.pop_back();
      std::istringstream ls(line);
      std::string tok;
      long n = 0;
      while (ls >> tok) {
        char* end = nullptr;
        const double v = std::strtod(tok.c_str(), &end);
        if (end == tok.c_str() || *end != '\0')
          throw fileError(path, "PCD data line " + std::to_string(lines + 1) + ": '" + tok +
                                    "' is not a number");
        h.ascii_values.push_back(v);
        ++n;
      }
      if (n == 0) continue;
      if (n != values || ++lines > expected)
        throw fileError(path, "PCD data line " + std::to_string(lines + 1) + " has " +
                                  std::to_string(n) + " values, expected " +
                                  std::to_string(values) + " per point and " +
                                  std::to_string(expected) + " points");
    }
    if (lines != expected)
      throw fileError(path, "truncated: the PCD header announces " + std::to_string(expected) +
                                " points but the data has " + std::to_string(lines));
  } else {
    throw fileError(path, "PCD header: unknown DATA encoding '" + data + "'");
  }
  h.fields = fields;
  h.sizes = sizes;
  h.counts = counts.empty() ? std::vector<long>(nf, 1) : counts;
  h.types = types;
  h.data = data;
  h.width = width;
  h.height = height;
  h.data_offset = header_bytes;
  return h;
}

/** An empty cloud laid out for the header's fields (declared types, packed records), its data
 * sized for every point. */
pcl::PCLPointCloud2 binaryLayout(const PcdHeader& h) {
  pcl::PCLPointCloud2 cloud;
  std::uint32_t offset = 0;
  for (std::size_t i = 0; i < h.fields.size(); ++i) {
    pcl::PCLPointField f;
    f.name = h.fields[i];
    f.offset = offset;
    f.count = static_cast<std::uint32_t>(h.counts[i]);
    const char t = h.types[i];
    const long sz = h.sizes[i];
    using PF = pcl::PCLPointField;
    if (t == 'F')
      f.datatype = sz == 8 ? PF::FLOAT64 : PF::FLOAT32;
    else if (t == 'I')
      f.datatype = sz == 1 ? PF::INT8 : sz == 2 ? PF::INT16 : sz == 4 ? PF::INT32 : PF::INT64;
    else
      f.datatype = sz == 1 ? PF::UINT8 : sz == 2 ? PF::UINT16 : sz == 4 ? PF::UINT32 : PF::UINT64;
    cloud.fields.push_back(f);
    offset += static_cast<std::uint32_t>(sz * h.counts[i]);
  }
  cloud.width = static_cast<std::uint32_t>(h.width);
  cloud.height = static_cast<std::uint32_t>(h.height);
  cloud.point_step = offset;
  cloud.row_step = offset * cloud.width;
  cloud.is_dense = false;
  cloud.data.resize(static_cast<std::size_t>(cloud.row_step) * cloud.height);
  return cloud;
}

/** Uncompressed binary PCD data, read by us: the header is already checked (sizes, counts, file
 * long enough), and the data is a plain array of `point_step`-byte records. PCL's reader crashed
 * (SIGSEGV inside pcl::PCDReader::read) on such a file whose header and length are valid and
 * whose data bytes are arbitrary (found by fuzz_pcd); there is nothing in these bytes that needs
 * PCL's parser. */
pcl::PCLPointCloud2 readBinaryPCD(const std::string& path, const PcdHeader& h) {
  pcl::PCLPointCloud2 cloud = binaryLayout(h);
  std::ifstream in(path, std::ios::binary);
  in.seekg(static_cast<std::streamoff>(h.data_offset));
  in.read(reinterpret_cast<char*>(cloud.data.data()),
          static_cast<std::streamsize>(cloud.data.size()));
  if (!in) throw fileError(path, "truncated: cannot read the PCD data");
  return cloud;
}

/** binary_compressed PCD data, read by us (the two sizes are already checked against the
 * header and the file): LZF (PCL's own lzfDecompress) into the announced size, which must come
 * out exactly, then each field's column (the format stores the
 * data field after field) copied into the point records. With this, no PCD data goes through
 * PCL's parser, which fuzz_pcd found crashing on six kinds of input. */
pcl::PCLPointCloud2 readCompressedPCD(const std::string& path, const PcdHeader& h) {
  pcl::PCLPointCloud2 cloud = binaryLayout(h);
  const Error corrupt = fileError(path, "truncated or corrupt compressed PCD data");
  std::ifstream in(path, std::ios::binary);
  in.seekg(static_cast<std::streamoff>(h.data_offset + 8));
  std::vector<char> packed(h.packed_bytes);
  in.read(packed.data(), static_cast<std::streamsize>(packed.size()));
  if (!in) throw corrupt;
  const auto unpacked = static_cast<unsigned int>(cloud.data.size());
  std::vector<std::uint8_t> columns(unpacked);
  if (unpacked > 0 && (h.packed_bytes == 0 ||
                       pcl::lzfDecompress(packed.data(), h.packed_bytes, columns.data(),
                                          unpacked) != unpacked))
    throw corrupt;
  const std::size_t n = static_cast<std::size_t>(cloud.width) * cloud.height;
  std::size_t column = 0;
  for (const auto& f : cloud.fields) {
    const std::size_t bytes = static_cast<std::size_t>(pcl::getFieldSize(f.datatype)) * f.count;
    for (std::size_t i = 0; i < n; ++i)
      std::memcpy(cloud.data.data() + i * cloud.point_step + f.offset,
                  columns.data() + column + i * bytes, bytes);
    column += n * bytes;
  }
  return cloud;
}

/** ASCII PCD data, read by us from the values that checkPCDHeader has already parsed (every
 * point one line of exactly the header's number of numbers), stored with the declared types
 * (integers rounded and clamped to their range, NaN as 0). PCL's parser crashed (SIGSEGV inside
 * pcl::PCDReader::read) on a file whose header had a blank-only line before the VERSION line
 * (found by fuzz_pcd), after the data-line check had already mended another of its crashes. */
pcl::PCLPointCloud2 readAsciiPCD(const PcdHeader& h) {
  pcl::PCLPointCloud2 cloud = binaryLayout(h);
  auto store = [](std::uint8_t* dst, char type, long size, double v) {
    if (type == 'F') {
      if (size == 8) {
        std::memcpy(dst, &v, 8);
      } else {
        const float f = static_cast<float>(v);
        std::memcpy(dst, &f, 4);
      }
      return;
    }
    auto fit = [&](double lo, double hi) {
      return std::isnan(v) ? 0.0 : std::clamp(std::nearbyint(v), lo, hi);
    };
    if (type == 'I') {
      const double lim = std::ldexp(1.0, static_cast<int>(8 * size - 1));
      // 2^63 itself does not fit: the top value is the largest double below it.
      const std::int64_t x = static_cast<std::int64_t>(fit(-lim, std::nextafter(lim, 0.0)));
      std::memcpy(dst, &x, static_cast<std::size_t>(size));  // little endian: the low bytes
    } else {
      const double lim = std::ldexp(1.0, static_cast<int>(8 * size));
      const std::uint64_t x = static_cast<std::uint64_t>(fit(0.0, std::nextafter(lim, 0.0)));
      std::memcpy(dst, &x, static_cast<std::size_t>(size));
    }
  };
  const std::size_t n = static_cast<std::size_t>(cloud.width) * cloud.height;
  std::size_t v = 0;
  for (std::size_t i = 0; i < n; ++i)
    for (std::size_t k = 0; k < h.fields.size(); ++k)
      for (long c = 0; c < h.counts[k]; ++c, ++v)
        store(cloud.data.data() + i * cloud.point_step + cloud.fields[k].offset + c * h.sizes[k],
              h.types[k], h.sizes[k], h.ascii_values[v]);
  return cloud;
}

}  // namespace

pcl::PCLPointCloud2 readPCDCloud(const std::string& path) {
  const PcdHeader header = checkPCDHeader(path);
  if (header.data == "binary") return readBinaryPCD(path, header);
  if (header.data == "ascii") return readAsciiPCD(header);
  return readCompressedPCD(path, header);
}

RawFrame readPCD(const std::string& path) {
  const pcl::PCLPointCloud2 cloud = readPCDCloud(path);
  RawFrame raw;
  raw.format = "pcd";
  fromCloud2(cloud, path, raw);
  return raw;
}

RawFrame readXYZ(const std::string& path) {
  std::string text = readWholeFile(path);
  if (!checkBinaryText(text)) throw fileError(path, "is not a text XYZ file (binary content)");
  std::replace(text.begin(), text.end(), ',', ' ');
  RawFrame raw;
  raw.format = "xyz";
  std::vector<Eigen::Vector3f> normals;
  bool any_normal = false;
  std::vector<double> vals;
  const auto lines = splitLines(text);
  for (std::size_t l = 0; l < lines.size(); ++l) {
    const char* s = lines[l].c_str();
    while (*s && std::isspace(static_cast<unsigned char>(*s))) ++s;
    if (!*s || *s == '#') continue;
    if (!parseNumbers(s, vals, 6) || vals.size() < 3)
      throw lineError(path, l + 1, "expected 'x y z [nx ny nz]', got '" + lines[l] + "'");
    raw.points.emplace_back(vals[0], vals[1], vals[2]);
    if (vals.size() >= 6) {
      normals.emplace_back(vals[3], vals[4], vals[5]);
      any_normal = true;
    } else {
      normals.emplace_back(kNaN, kNaN, kNaN);
    }
  }
  if (any_normal) raw.normals = std::move(normals);
  return raw;
}

RawFrame readRawFrame(const std::string& path) {
  const std::string ext = lower(std::filesystem::path(path).extension().string());
  if (ext == ".obj") return readOBJ(path);
  if (ext == ".off") return readOFF(path);
  if (ext == ".ply") return readPLY(path);
  if (ext == ".pcd") return readPCD(path);
  if (ext == ".xyz") return readXYZ(path);
  throw fileError(path, "unknown frame format '" + ext + "' (expected .obj .ply .off .pcd .xyz)");
}

}  // namespace io
}  // namespace pcl_animseg
