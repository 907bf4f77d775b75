// The contact sheet renders headless (no display, no X server) from an OUT directory written
// here: five shapes moving as five parts, two hierarchy levels, one frame with a dropped point.
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/visualization/contact_sheet.h>

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <set>
#include <unistd.h>

namespace fs = std::filesystem;
using namespace pcl_animseg;
using namespace pcl_animseg::visualization;

namespace {

constexpr int kParts = 5;
constexpr int kFrames = 6;

struct Frame {
  PointCloudSequence::Cloud::Ptr cloud{new PointCloudSequence::Cloud};
  std::vector<int> part;
};

void addPoint(Frame& f, const Eigen::Vector3f& p, const Eigen::Vector3f& n, int label) {
  pcl::PointNormal q;
  q.x = p.x(), q.y = p.y(), q.z = p.z();
  q.normal_x = n.x(), q.normal_y = n.y(), q.normal_z = n.z();
  f.cloud->push_back(q);
  f.part.push_back(label);
}

// Part 0 is a sphere (the body), parts 1-4 boxes (limbs) that swing about the body over time.
Frame makeFrame(int t, std::mt19937& rng) {
  Frame f;
  std::uniform_real_distribution<float> u(-1.f, 1.f);
  std::normal_distribution<float> g(0.f, 1.f);
  const float phase = 0.5f * static_cast<float>(t);
  const Eigen::Vector3f drift(0.15f * t, 0.f, 0.f);
  for (int i = 0; i < 900; ++i) {
    Eigen::Vector3f n(g(rng), g(rng), g(rng));
    n.normalize();
    addPoint(f, drift + 0.5f * n, n, 0);
  }
  const Eigen::Vector3f anchors[4] = {{0.9f, 0.6f, 0.f}, {-0.9f, 0.6f, 0.f}, {0.9f, -0.6f, 0.f},
                                      {-0.9f, -0.6f, 0.f}};
  for (int k = 0; k < 4; ++k) {
    const float angle = std::sin(phase + k) * 0.6f;
    const Eigen::Matrix3f R = Eigen::AngleAxisf(angle, Eigen::Vector3f::UnitZ()).toRotationMatrix();
    const Eigen::Vector3f half(0.45f, 0.15f, 0.2f);
    for (int i = 0; i < 500; ++i) {
      // A point on a random face of the box, area-weighted enough for a picture.
      const int axis = i % 3;
      const float side = (i / 3) % 2 ? 1.f : -1.f;
      Eigen::Vector3f p(u(rng) * half.x(), u(rng) * half.y(), u(rng) * half.z());
      p(axis) = side * half(axis);
      Eigen::Vector3f n = Eigen::Vector3f::Zero();
      n(axis) = side;
      addPoint(f, drift + anchors[k] + R * p, R * n, 1 + k);
    }
  }
  return f;
}

class ContactSheetTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = (fs::temp_directory_path() / ("pcl_animseg_view_" + std::to_string(::getpid()))).string();
    fs::remove_all(dir_);
    io::ensureDirectory(dir_ + "/out");
    std::mt19937 rng(7);
    for (int t = 0; t < kFrames; ++t) {
      Frame f = makeFrame(t, rng);
      const std::string name = "f" + std::to_string(t);
      // Level 0: the five parts; level 1: body alone, the four limbs merged.
      std::vector<std::vector<int>> columns(2);
      for (int p : f.part) {
        columns[0].push_back(p);
        columns[1].push_back(p == 0 ? 0 : 1);
      }
      std::vector<std::vector<int>> rows = columns;
      if (t == 1) {
        // An input point dropped on load (NaN): a -1 row in .labels, absent from the .pcd.
        for (auto& c : rows) c.insert(c.begin() + 1000, -1);
      }
      io::saveLabels(dir_ + "/out/" + name + ".labels", rows);
      // The input sequence it came from, with the dropped point as NaN.
      PointCloudSequence::Cloud input = *f.cloud;
      if (t == 1) {
        pcl::PointNormal nan;
        nan.x = nan.y = nan.z = std::numeric_limits<float>::quiet_NaN();
        input.insert(input.begin() + 1000, nan);
      }
      io::ensureDirectory(dir_ + "/in");
      io::savePLY(dir_ + "/in/" + name + ".ply", input);
      io::saveLabelledPCD(dir_ + "/out/" + name + ".pcd", *f.cloud, columns[0]);
      frames_.push_back(std::move(f));
    }
  }
  static void TearDownTestSuite() {
    if (!std::getenv("PCL_ANIMSEG_KEEP_TEST_OUTPUT")) fs::remove_all(dir_);
  }
  static std::string dir_;
  static std::vector<Frame> frames_;
};
std::string ContactSheetTest::dir_;
std::vector<Frame> ContactSheetTest::frames_;

// Hue in [0, 1) of an RGB colour.
double hue(double r, double g, double b) {
  const double mx = std::max({r, g, b}), mn = std::min({r, g, b}), d = mx - mn;
  if (d <= 0) return 0;
  double h;
  if (mx == r) h = std::fmod((g - b) / d, 6.0);
  else if (mx == g) h = (b - r) / d + 2;
  else h = (r - g) / d + 4;
  h /= 6.0;
  return h < 0 ? h + 1 : h;
}

// Pixels in `rect` per part, classifying saturated pixels by the nearest labelColor hue (shading
// scales a colour, which keeps its hue).
std::vector<int> partPixels(const RGBImage& img, const ContactSheetLayout::Rect& rect, int parts) {
  std::vector<double> hues;
  for (int l = 0; l < parts; ++l) {
    unsigned char r, g, b;
    io::labelColor(l, r, g, b);
    hues.push_back(hue(r, g, b));
  }
  std::vector<int> count(parts, 0);
  for (int y = rect.y0; y < rect.y1; ++y)
    for (int x = rect.x0; x < rect.x1; ++x) {
      const std::uint8_t* p = img.at(x, y);
      const double mx = std::max({p[0], p[1], p[2]}), mn = std::min({p[0], p[1], p[2]});
      if (mx < 40 || (mx - mn) / mx < 0.3) continue;  // background, text, outlines
      const double h = hue(p[0], p[1], p[2]);
      int best = 0;
      double bd = 2;
      for (int l = 0; l < parts; ++l) {
        double d = std::abs(h - hues[l]);
        d = std::min(d, 1 - d);
        if (d < bd) bd = d, best = l;
      }
      if (bd < 0.04) ++count[best];
    }
  return count;
}

}  // namespace

TEST_F(ContactSheetTest, LoadsOutDirectoryAlignedWithLabelRows) {
  const LabelledSequence seq = loadLabelledSequence(dir_ + "/out");
  ASSERT_EQ(seq.size(), static_cast<std::size_t>(kFrames));
  EXPECT_EQ(seq.levels(), 2);
  EXPECT_EQ(seq.frames[0].name, "f0");
  for (int t = 0; t < kFrames; ++t) {
    const auto& f = seq.frames[t];
    ASSERT_EQ(f.cloud->size(), frames_[t].cloud->size());
    EXPECT_EQ(f.levels[0], frames_[t].part) << "frame " << t;  // frame 1 skips the -1 row
    for (std::size_t j = 0; j < f.cloud->size(); ++j)
      ASSERT_EQ(f.levels[1][j], frames_[t].part[j] == 0 ? 0 : 1);
  }
  const auto counts = seq.partCounts(0);
  ASSERT_EQ(counts.size(), static_cast<std::size_t>(kParts));
  EXPECT_EQ(counts[0].second, static_cast<std::size_t>(900 * kFrames));
  EXPECT_EQ(counts[3].second, static_cast<std::size_t>(500 * kFrames));
}

TEST_F(ContactSheetTest, TakesGeometryFromTheInputSequence) {
  const LabelledSequence seq = loadLabelledSequence(dir_ + "/out", dir_ + "/in");
  ASSERT_EQ(seq.size(), static_cast<std::size_t>(kFrames));
  for (int t = 0; t < kFrames; ++t) {
    ASSERT_EQ(seq.frames[t].cloud->size(), frames_[t].cloud->size()) << "frame " << t;
    EXPECT_EQ(seq.frames[t].levels[0], frames_[t].part) << "frame " << t;
    EXPECT_NEAR((*seq.frames[t].cloud)[1500].x, (*frames_[t].cloud)[1500].x, 1e-5f);
  }
  // Another OUT directory works as a geometry source too.
  EXPECT_EQ(loadLabelledSequence(dir_ + "/out", dir_ + "/out").frames[1].levels[0], frames_[1].part);
}

TEST_F(ContactSheetTest, RendersHeadlessPNGWithEveryPartColour) {
  // Nothing may need a display: take it away for good measure.
  ::unsetenv("DISPLAY");
  ::unsetenv("WAYLAND_DISPLAY");
  const std::string png = dir_ + "/sheet.png";
  ContactSheetOptions opt;
  opt.width = 1200;
  renderContactSheet(dir_ + "/out", png, opt);
  ASSERT_TRUE(fs::exists(png));
  const RGBImage img = readPNG(png);
  ContactSheetLayout layout;
  const RGBImage again = renderContactSheet(loadLabelledSequence(dir_ + "/out"), opt, &layout);
  EXPECT_EQ(img.pixels, again.pixels) << "rendering must be deterministic";
  EXPECT_EQ(img.width, 1200);
  ASSERT_EQ(layout.cells.size(), static_cast<std::size_t>(kFrames));  // 6 frames <= 8: all
  EXPECT_EQ(layout.frames.front(), 0u);
  EXPECT_EQ(layout.frames.back(), static_cast<std::size_t>(kFrames - 1));
  EXPECT_EQ(layout.parts, kParts);

  for (std::size_t c = 0; c < layout.cells.size(); ++c) {
    const auto& r = layout.cells[c];
    std::size_t drawn = 0, total = 0;
    for (int y = r.y0; y < r.y1; ++y)
      for (int x = r.x0; x < r.x1; ++x, ++total) {
        const std::uint8_t* p = img.at(x, y);
        if (p[0] < 250 || p[1] < 250 || p[2] < 250) ++drawn;
      }
    // Non-blank: the object covers a real share of each cell (not a dot, not everything).
    EXPECT_GT(drawn, total / 10) << "cell " << c;
    EXPECT_LT(drawn, total * 9 / 10) << "cell " << c;
    // Every part is visible in every frame, with its own colour (stable across frames).
    const auto per_part = partPixels(img, r, kParts);
    for (int l = 0; l < kParts; ++l) EXPECT_GT(per_part[l], 200) << "cell " << c << " part " << l;
  }
  // Distinct part colours over the whole picture area of the grid.
  ContactSheetLayout::Rect grid{layout.cells.front().x0, layout.cells.front().y0,
                                layout.cells.back().x1, layout.cells.back().y1};
  const auto all = partPixels(img, grid, kParts);
  int distinct = 0;
  for (int n : all) distinct += n > 1000;
  EXPECT_GE(distinct, kParts);
}

TEST_F(ContactSheetTest, CoarserLevelShowsMergedParts) {
  ContactSheetOptions opt;
  opt.level = 1;
  opt.frames = 4;
  opt.columns = 2;
  opt.width = 800;
  ContactSheetLayout layout;
  const RGBImage img = renderContactSheet(loadLabelledSequence(dir_ + "/out"), opt, &layout);
  ASSERT_EQ(layout.cells.size(), 4u);
  EXPECT_EQ(layout.parts, 2);
  const std::vector<std::size_t> expected_frames{0, 2, 3, 5};
  EXPECT_EQ(layout.frames, expected_frames);
  EXPECT_GT(layout.cells[2].y0, layout.cells[0].y1);  // two rows
  const auto per_part = partPixels(img, layout.cells[0], kParts);
  EXPECT_GT(per_part[0], 200);
  EXPECT_GT(per_part[1], 200);
  EXPECT_EQ(per_part[2] + per_part[3] + per_part[4], 0);  // labels 2-4 do not exist at level 1
}

TEST_F(ContactSheetTest, RejectsWhatItCannotDraw) {
  const LabelledSequence seq = loadLabelledSequence(dir_ + "/out");
  ContactSheetOptions opt;
  opt.level = 2;
  EXPECT_THROW(renderContactSheet(seq, opt), Error);
  opt.level = 0;
  opt.width = 10;
  EXPECT_THROW(renderContactSheet(seq, opt), Error);
  EXPECT_THROW(loadLabelledSequence(dir_ + "/nowhere"), Error);
  EXPECT_THROW(loadLabelledSequence(dir_), Error);  // a directory without .labels
  EXPECT_THROW(readPNG(dir_ + "/out/f0.pcd"), Error);
}

TEST(ContactSheet, SpreadFramesEvenly) {
  EXPECT_EQ(spreadFrames(12, 8).size(), 8u);
  EXPECT_EQ(spreadFrames(12, 8).front(), 0u);
  EXPECT_EQ(spreadFrames(12, 8).back(), 11u);
  const auto s = spreadFrames(100, 6);
  for (std::size_t i = 1; i < s.size(); ++i) EXPECT_GT(s[i], s[i - 1]);
  EXPECT_EQ(spreadFrames(3, 8), (std::vector<std::size_t>{0, 1, 2}));
  EXPECT_EQ(spreadFrames(5, 1), (std::vector<std::size_t>{0}));
  EXPECT_TRUE(spreadFrames(0, 4).empty());
}

TEST(ContactSheet, PNGRoundTripAndText) {
  RGBImage img(64, 20, 255, 255, 255);
  const int end = drawText(img, 2, 2, "f01 A", 2, 10, 20, 30);
  EXPECT_EQ(end, 2 + 5 * 12);
  EXPECT_EQ(textWidth("f01 A", 2), 5 * 12 - 2);
  int ink = 0;
  for (std::size_t i = 0; i < img.pixels.size(); i += 3) ink += img.pixels[i] == 10;
  EXPECT_GT(ink, 40);
  const std::string path =
      (fs::temp_directory_path() / ("pcl_animseg_png_" + std::to_string(::getpid()) + ".png")).string();
  writePNG(path, img);
  const RGBImage back = readPNG(path);
  fs::remove(path);
  EXPECT_EQ(back.width, 64);
  EXPECT_EQ(back.height, 20);
  EXPECT_EQ(back.pixels, img.pixels);
  EXPECT_THROW(writePNG(path, RGBImage()), Error);
}
