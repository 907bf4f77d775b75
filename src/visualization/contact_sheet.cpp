// Contact sheet: a tiny orthographic point-splat renderer (see contact_sheet.h for why not VTK).
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/visualization/contact_sheet.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>

namespace pcl_animseg {
namespace visualization {

namespace {

using Rect = ContactSheetLayout::Rect;

const std::uint8_t kText[3] = {40, 40, 40};
const std::uint8_t kFrame[3] = {215, 215, 215};

struct Camera {
  Eigen::Vector3f right, up, dir;  // orthonormal; dir points into the picture
  Eigen::Vector3f light;           // unit, towards the light
};

Camera makeCamera(Eigen::Vector3f d, Eigen::Vector3f up) {
  if (d.norm() < 1e-12f) throw Error("contact sheet: the view direction is zero");
  d.normalize();
  if (up.norm() < 1e-12f || std::abs(d.dot(up.normalized())) > 0.99f) {
    // Any axis not along the view will do; prefer world Y, then Z.
    up = std::abs(d.y()) < 0.9f ? Eigen::Vector3f::UnitY() : Eigen::Vector3f::UnitZ();
  }
  Camera c;
  c.dir = d;
  c.right = d.cross(up).normalized();
  c.up = c.right.cross(d).normalized();
  // A key light from the upper left, slightly in front: shapes read better than head-on light.
  c.light = (-c.dir + 0.6f * c.up - 0.4f * c.right).normalized();
  return c;
}

std::string withThousands(std::size_t n) {
  std::string s = std::to_string(n);
  for (int i = static_cast<int>(s.size()) - 3; i > 0; i -= 3) s.insert(static_cast<std::size_t>(i), ",");
  return s;
}

}  // namespace

std::vector<std::size_t> spreadFrames(std::size_t T, std::size_t n) {
  std::vector<std::size_t> out;
  if (T == 0 || n == 0) return out;
  n = std::min(n, T);
  if (n == 1) return {0};
  for (std::size_t i = 0; i < n; ++i)
    out.push_back(static_cast<std::size_t>(std::llround(static_cast<double>(i) * (T - 1) / (n - 1))));
  return out;
}

void defaultView(const PointCloudSequence::Cloud& cloud, Eigen::Vector3f& view_direction,
                 Eigen::Vector3f& up) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  std::size_t n = 0;
  for (const auto& p : cloud)
    if (std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z)) {
      mean += Eigen::Vector3d(p.x, p.y, p.z);
      ++n;
    }
  if (n < 3) {
    view_direction = Eigen::Vector3f(-1, -1, -1).normalized();
    up = Eigen::Vector3f::UnitY();
    return;
  }
  mean /= static_cast<double>(n);
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& p : cloud)
    if (std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z)) {
      const Eigen::Vector3d q = Eigen::Vector3d(p.x, p.y, p.z) - mean;
      cov += q * q.transpose();
    }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(cov);
  Eigen::Vector3d e[3];  // e[0] largest variance ... e[2] smallest
  for (int i = 0; i < 3; ++i) {
    e[i] = es.eigenvectors().col(2 - i);
    Eigen::Index k;
    e[i].cwiseAbs().maxCoeff(&k);
    if (e[i](k) < 0) e[i] = -e[i];  // a stable sign, so the view does not flip between runs
  }
  // Up: a principal axis cannot tell up from along, so ask the world axes first: of the two broad
  // axes, the one within 30 degrees of world Z (our synthetic data and most scans are Z-up), else
  // of world Y (the OBJ/PLY habit), signed to match; otherwise e2, which suits long low shapes.
  int u = 1;
  Eigen::Vector3d upv = e[1];
  for (int axis : {2, 1}) {
    const double c0 = std::abs(e[0](axis)), c1 = std::abs(e[1](axis));
    if (std::max(c0, c1) > std::cos(M_PI / 6)) {
      u = c0 > c1 ? 0 : 1;
      upv = e[u](axis) < 0 ? -e[u] : e[u];
      break;
    }
  }
  const Eigen::Vector3d side = e[1 - u];
  // Camera placed off the thin axis, turned ~35 degrees and raised ~20: a 3/4 view.
  const Eigen::Vector3d eye = (e[2] + 0.7 * side + 0.45 * upv).normalized();
  view_direction = (-eye).cast<float>();
  up = upv.cast<float>();
}

RGBImage renderContactSheet(const LabelledSequence& seq, const ContactSheetOptions& opt,
                            ContactSheetLayout* layout_out) {
  if (seq.size() == 0) throw Error("contact sheet: the sequence has no frames");
  if (opt.level < 0 || opt.level >= seq.levels())
    throw Error("contact sheet: level " + std::to_string(opt.level) + " does not exist (levels 0.." +
                std::to_string(seq.levels() - 1) + ")");
  if (opt.width < 200 || opt.width > 16384)
    throw Error("contact sheet: width " + std::to_string(opt.width) + " is outside [200, 16384]");
  if (opt.frames < 0 || opt.columns < 0 || opt.splat_radius < 0)
    throw Error("contact sheet: frames, columns and splat radius must not be negative");

  ContactSheetLayout layout;
  const std::size_t n = opt.frames > 0 ? static_cast<std::size_t>(opt.frames) : 8;
  layout.frames = spreadFrames(seq.size(), n);
  const int count = static_cast<int>(layout.frames.size());
  const int cols = opt.columns > 0 ? std::min(opt.columns, count)
                                   : (count <= 4 ? count : (count + 1) / 2);
  const int rows = (count + cols - 1) / cols;

  // Camera: one for all frames, so that motion between cells is motion of the object.
  Eigen::Vector3f d = opt.view_direction, up = opt.up;
  if (d.norm() < 1e-12f) {
    Eigen::Vector3f auto_up;
    defaultView(*seq.frames[layout.frames[0]].cloud, d, auto_up);
    if (up.norm() < 1e-12f) {
      up = auto_up;
    } else {
      // A given up: keep the automatic view's heading, raised ~25 degrees above that up's horizon.
      const Eigen::Vector3f un = up.normalized();
      Eigen::Vector3f h = d - d.dot(un) * un;
      if (h.norm() < 1e-3f) h = un.unitOrthogonal();
      d = h.normalized() - 0.45f * un;
    }
  }
  const Camera cam = makeCamera(d, up);

  // Common extent of all shown frames on the picture plane.
  float umin = std::numeric_limits<float>::max(), umax = -umin, vmin = umin, vmax = -umin;
  std::size_t shown_points = 0;
  for (std::size_t t : layout.frames)
    for (const auto& p : *seq.frames[t].cloud) {
      if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) continue;
      const Eigen::Vector3f q(p.x, p.y, p.z);
      const float u = q.dot(cam.right), v = q.dot(cam.up);
      umin = std::min(umin, u), umax = std::max(umax, u);
      vmin = std::min(vmin, v), vmax = std::max(vmax, v);
      ++shown_points;
    }
  if (shown_points == 0) throw Error("contact sheet: the frames shown have no finite points");
  const float ext_u = std::max(umax - umin, 1e-6f), ext_v = std::max(vmax - vmin, 1e-6f);

  // Layout (pixels). Text scale grows with the picture so that names stay readable.
  const int ts = std::max(1, (opt.width + 400) / 800);
  const int margin = 6 * ts;
  const int header_h = textHeight(ts) + 2 * margin;
  const int name_h = textHeight(ts) + 2 * ts;
  const int cell_w = (opt.width - margin * (cols + 1)) / cols;
  if (cell_w < 32) throw Error("contact sheet: width too small for " + std::to_string(cols) + " columns");
  const int cell_h = static_cast<int>(
      std::clamp(static_cast<float>(cell_w) * ext_v / ext_u, 0.45f * cell_w, 1.3f * cell_w));
  const int grid_top = header_h;
  const int grid_h = rows * (name_h + cell_h + margin);

  // Legend entries: swatch + "id: points", flowed into lines.
  const auto parts = seq.partCounts(opt.level);
  layout.parts = static_cast<int>(parts.size());
  const std::size_t max_entries = 96;
  std::vector<std::string> entry_text;
  for (std::size_t i = 0; i < parts.size() && i < max_entries; ++i)
    entry_text.push_back(std::to_string(parts[i].first) + ": " + withThousands(parts[i].second));
  const int swatch = textHeight(ts);
  int entry_w = 0;
  for (const auto& s : entry_text) entry_w = std::max(entry_w, swatch + 2 * ts + textWidth(s, ts));
  entry_w += 4 * margin;
  const int per_line = std::max(1, (opt.width - 2 * margin) / std::max(entry_w, 1));
  int legend_lines = 0;
  if (opt.legend) {
    legend_lines = 1 + static_cast<int>((entry_text.size() + per_line - 1) / per_line);
    if (parts.size() > max_entries) ++legend_lines;
  }
  const int line_h = textHeight(ts) + 2 * ts + ts;
  const int legend_h = opt.legend ? legend_lines * line_h + margin : 0;
  const int height = grid_top + grid_h + legend_h + margin;

  RGBImage img(opt.width, height, 255, 255, 255);

  // Header.
  std::string title = opt.title;
  if (title.empty()) {
    std::ostringstream os;
    os << "level " << opt.level << " (levels 0-" << (seq.levels() - 1) << "): " << parts.size()
       << " parts, " << count << " of " << seq.size() << " frames shown";
    title = os.str();
  }
  drawText(img, margin, margin, title, ts, kText[0], kText[1], kText[2]);

  // Splat radius from frame 0's spacing at the common scale.
  const float scale = std::min((cell_w - 2.f * margin) / ext_u, (cell_h - 2.f * margin) / ext_v);
  float radius = opt.splat_radius;
  if (radius <= 0.f) {
    const auto& c0 = *seq.frames[layout.frames[0]].cloud;
    const double spacing = c0.size() >= 2 ? meanSpacing(c0) : 0.0;
    // The nearest-neighbour spacing underestimates the gaps of a random sampling: 1.5x closes
    // most holes without blurring parts into each other.
    radius = std::clamp(static_cast<float>(1.5 * spacing) * scale, 1.0f, 8.0f);
  }

  layout.cells.resize(static_cast<std::size_t>(count));
  for (int i = 0; i < count; ++i) {
    const int r = i / cols, c = i % cols;
    Rect& cell = layout.cells[static_cast<std::size_t>(i)];
    cell.x0 = margin + c * (cell_w + margin);
    cell.y0 = grid_top + r * (name_h + cell_h + margin) + name_h;
    cell.x1 = cell.x0 + cell_w;
    cell.y1 = cell.y0 + cell_h;
  }

  // Cells are independent regions of the picture: one thread each, deterministic.
#pragma omp parallel for schedule(dynamic, 1)
  for (int i = 0; i < count; ++i) {
    const Rect& cell = layout.cells[static_cast<std::size_t>(i)];
    const LabelledFrame& f = seq.frames[layout.frames[static_cast<std::size_t>(i)]];
    const std::vector<int>& labels = f.levels[static_cast<std::size_t>(opt.level)];
    std::vector<float> zbuf(static_cast<std::size_t>(cell_w) * cell_h,
                            std::numeric_limits<float>::infinity());
    const float ox = cell.x0 + 0.5f * (cell_w - scale * ext_u);
    const float oy = cell.y0 + 0.5f * (cell_h - scale * ext_v);
    const int ir = static_cast<int>(std::ceil(radius));
    for (std::size_t j = 0; j < f.cloud->size(); ++j) {
      const auto& p = (*f.cloud)[j];
      if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) continue;
      const Eigen::Vector3f q(p.x, p.y, p.z);
      const float sx = ox + (q.dot(cam.right) - umin) * scale;
      const float sy = oy + (vmax - q.dot(cam.up)) * scale;  // picture rows grow downwards
      const float depth = q.dot(cam.dir) * scale;             // in pixels, like the splat
      Eigen::Vector3f nrm(p.normal_x, p.normal_y, p.normal_z);
      float shade = 0.85f;
      if (std::isfinite(nrm.squaredNorm()) && nrm.squaredNorm() > 1e-12f) {
        nrm.normalize();
        // Two-sided Lambert: estimated normals may point either way; light the visible side.
        if (nrm.dot(cam.dir) > 0) nrm = -nrm;
        shade = 0.32f + 0.68f * std::max(0.f, nrm.dot(cam.light));
      }
      unsigned char br, bg, bb;
      io::labelColor(labels[j], br, bg, bb);
      const std::uint8_t cr = static_cast<std::uint8_t>(std::lround(br * shade));
      const std::uint8_t cg = static_cast<std::uint8_t>(std::lround(bg * shade));
      const std::uint8_t cb = static_cast<std::uint8_t>(std::lround(bb * shade));
      const int cx = static_cast<int>(std::floor(sx)), cy = static_cast<int>(std::floor(sy));
      for (int y = cy - ir; y <= cy + ir; ++y) {
        if (y < cell.y0 || y >= cell.y1) continue;
        for (int x = cx - ir; x <= cx + ir; ++x) {
          if (x < cell.x0 || x >= cell.x1) continue;
          const float dx = x + 0.5f - sx, dy = y + 0.5f - sy;
          const float d2 = dx * dx + dy * dy;
          if (d2 > radius * radius) continue;
          // A splat is a small sphere facing the camera: its centre is nearest, so overlapping
          // splats of one surface interleave smoothly instead of in stripes.
          const float z = depth - std::sqrt(radius * radius - d2);
          float& zb = zbuf[static_cast<std::size_t>(y - cell.y0) * cell_w + (x - cell.x0)];
          if (z < zb) {
            zb = z;
            std::uint8_t* px = img.at(x, y);
            px[0] = cr, px[1] = cg, px[2] = cb;
          }
        }
      }
    }
    // Silhouette: darken covered pixels that touch the background, so parts read as shapes.
    const float inf = std::numeric_limits<float>::infinity();
    auto covered = [&](int x, int y) {
      if (x < cell.x0 || x >= cell.x1 || y < cell.y0 || y >= cell.y1) return false;
      return zbuf[static_cast<std::size_t>(y - cell.y0) * cell_w + (x - cell.x0)] < inf;
    };
    std::vector<std::pair<int, int>> edge;
    for (int y = cell.y0; y < cell.y1; ++y)
      for (int x = cell.x0; x < cell.x1; ++x)
        if (covered(x, y) && (!covered(x - 1, y) || !covered(x + 1, y) || !covered(x, y - 1) ||
                              !covered(x, y + 1)))
          edge.emplace_back(x, y);
    for (const auto& e : edge) {
      std::uint8_t* px = img.at(e.first, e.second);
      for (int k = 0; k < 3; ++k) px[k] = static_cast<std::uint8_t>(px[k] * 0.55f);
    }
    // Cell frame.
    img.fillRect(cell.x0 - 1, cell.y0 - 1, cell.x1 + 1, cell.y0, kFrame[0], kFrame[1], kFrame[2]);
    img.fillRect(cell.x0 - 1, cell.y1, cell.x1 + 1, cell.y1 + 1, kFrame[0], kFrame[1], kFrame[2]);
    img.fillRect(cell.x0 - 1, cell.y0, cell.x0, cell.y1, kFrame[0], kFrame[1], kFrame[2]);
    img.fillRect(cell.x1, cell.y0, cell.x1 + 1, cell.y1, kFrame[0], kFrame[1], kFrame[2]);
  }

  // Frame names (serially: a long name may run into the next cell's band, so it is cut to fit).
  const int max_chars = std::max(1, (cell_w + ts) / (6 * ts));
  for (int i = 0; i < count; ++i) {
    const Rect& cell = layout.cells[static_cast<std::size_t>(i)];
    const LabelledFrame& f = seq.frames[layout.frames[static_cast<std::size_t>(i)]];
    std::string name = f.name + "  (" + withThousands(f.cloud->size()) + " pts)";
    if (static_cast<int>(name.size()) > max_chars) name = f.name;
    if (static_cast<int>(name.size()) > max_chars) name = name.substr(0, max_chars);
    drawText(img, cell.x0, cell.y0 - name_h, name, ts, kText[0], kText[1], kText[2]);
  }

  // Legend.
  if (opt.legend) {
    Rect& lg = layout.legend;
    lg.x0 = margin;
    lg.y0 = grid_top + grid_h;
    lg.x1 = opt.width - margin;
    lg.y1 = lg.y0 + legend_h;
    drawText(img, lg.x0, lg.y0, "parts at level " + std::to_string(opt.level) +
                                    " (id: points over all " + std::to_string(seq.size()) + " frames)",
             ts, kText[0], kText[1], kText[2]);
    for (std::size_t i = 0; i < entry_text.size(); ++i) {
      const int x = lg.x0 + static_cast<int>(i % per_line) * entry_w;
      const int y = lg.y0 + (1 + static_cast<int>(i / per_line)) * line_h;
      unsigned char r, g, b;
      io::labelColor(parts[i].first, r, g, b);
      img.fillRect(x, y, x + swatch, y + swatch, kText[0], kText[1], kText[2]);
      img.fillRect(x + 1, y + 1, x + swatch - 1, y + swatch - 1, r, g, b);
      drawText(img, x + swatch + 2 * ts, y, entry_text[i], ts, kText[0], kText[1], kText[2]);
    }
    if (parts.size() > max_entries)
      drawText(img, lg.x0,
               lg.y0 + (1 + static_cast<int>((entry_text.size() + per_line - 1) / per_line)) * line_h,
               "... and " + std::to_string(parts.size() - max_entries) + " more parts", ts, kText[0],
               kText[1], kText[2]);
  }
  if (layout_out) *layout_out = layout;
  return img;
}

void renderContactSheet(const std::string& out_dir, const std::string& png_path,
                        const ContactSheetOptions& options) {
  const LabelledSequence seq = loadLabelledSequence(out_dir);
  writePNG(png_path, renderContactSheet(seq, options));
}

}  // namespace visualization
}  // namespace pcl_animseg
