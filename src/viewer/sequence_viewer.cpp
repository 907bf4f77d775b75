#include <pcl/common/centroid.h>
#include <pcl/visualization/pcl_visualizer.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/visualization/contact_sheet.h>
#include <pcl_animseg/visualization/sequence_viewer.h>

#include <chrono>
#include <cstdlib>
#include <map>
#include <sstream>

namespace pcl_animseg {
namespace visualization {

bool displayAvailable() {
  const char* display = std::getenv("DISPLAY");
  return display != nullptr && *display != '\0';
}

namespace {

/** What the window shows, and the small state machine the keys drive. */
class ViewerState {
 public:
  ViewerState(const LabelledSequence& seq, const ViewerOptions& opt)
      : seq_(seq), opt_(opt), level_(opt.level), show_keypoints_(opt.keypoints) {}

  void onKey(const pcl::visualization::KeyboardEvent& e) {
    if (!e.keyDown()) return;
    const std::string key = e.getKeySym();
    const int T = static_cast<int>(seq_.size()), L = seq_.levels();
    if (key == "n" || key == "Right")
      frame_ = (frame_ + 1) % T;
    else if (key == "p" || key == "Left")
      frame_ = (frame_ + T - 1) % T;
    else if (key == "space")
      playing_ = !playing_;
    else if (key == "k")
      show_keypoints_ = !show_keypoints_;
    else if (key == "plus" || key == "KP_Add" || key == "equal")
      level_ = std::min(level_ + 1, L - 1);
    else if (key == "minus" || key == "KP_Subtract")
      level_ = std::max(level_ - 1, 0);
    else if (key.size() == 1 && key[0] >= '0' && key[0] <= '9' && key[0] - '0' < L)
      level_ = key[0] - '0';
    else
      return;
    dirty_ = true;
  }

  void run() {
    pcl::visualization::PCLVisualizer viewer("animseg_view");
    viewer.setBackgroundColor(0.12, 0.12, 0.14);
    viewer.registerKeyboardCallback(
        [this](const pcl::visualization::KeyboardEvent& e) { onKey(e); });
    draw(viewer);
    placeCamera(viewer);
    auto last = std::chrono::steady_clock::now();
    while (!viewer.wasStopped()) {
      viewer.spinOnce(20);
      const auto now = std::chrono::steady_clock::now();
      if (playing_ && std::chrono::duration<double>(now - last).count() >= 1.0 / opt_.fps) {
        frame_ = (frame_ + 1) % static_cast<int>(seq_.size());
        dirty_ = true;
        last = now;
      }
      if (dirty_) draw(viewer);
    }
    viewer.close();
  }

 private:
  void placeCamera(pcl::visualization::PCLVisualizer& viewer) {
    // The contact sheet's 3/4 view, so both show the object the same way.
    const auto& cloud = *seq_.frames[0].cloud;
    Eigen::Vector4f c;
    pcl::compute3DCentroid(cloud, c);
    const float diag = static_cast<float>(boundingBoxDiagonal(cloud));
    Eigen::Vector3f dir, up;
    defaultView(cloud, dir, up);
    const Eigen::Vector3f eye = c.head<3>() - 2.2f * diag * dir.normalized();
    viewer.setCameraPosition(eye.x(), eye.y(), eye.z(), c.x(), c.y(), c.z(), up.x(), up.y(),
                             up.z());
  }

  void draw(pcl::visualization::PCLVisualizer& viewer) {
    dirty_ = false;
    const LabelledFrame& f = seq_.frames[static_cast<std::size_t>(frame_)];
    const std::vector<int>& labels = f.levels[static_cast<std::size_t>(level_)];
    pcl::PointCloud<pcl::PointXYZRGB>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZRGB>);
    cloud->resize(f.cloud->size());
    std::map<int, std::size_t> counts;
    for (std::size_t j = 0; j < f.cloud->size(); ++j) {
      auto& q = (*cloud)[j];
      q.x = (*f.cloud)[j].x, q.y = (*f.cloud)[j].y, q.z = (*f.cloud)[j].z;
      io::labelColor(labels[j], q.r, q.g, q.b);
      ++counts[labels[j]];
    }
    pcl::visualization::PointCloudColorHandlerRGBField<pcl::PointXYZRGB> colours(cloud);
    if (!viewer.updatePointCloud(cloud, colours, "cloud")) {
      viewer.addPointCloud(cloud, colours, "cloud");
    }
    viewer.setPointCloudRenderingProperties(pcl::visualization::PCL_VISUALIZER_POINT_SIZE,
                                            opt_.point_size, "cloud");

    // Status line and the keys.
    std::ostringstream status;
    status << "frame " << frame_ + 1 << "/" << seq_.size() << "  " << f.name << "   level "
           << level_ << " (0-" << seq_.levels() - 1 << ")   " << counts.size() - counts.count(-1)
           << " parts" << (playing_ ? "   [playing]" : "");
    setText(viewer, "status", status.str(), 10, 30, 16, 1, 1, 1);
    setText(viewer, "keys",
            "n/p frame  space play  0-9 +/- level  k keypoints  r reset view  q quit", 10, 10, 12,
            0.7, 0.7, 0.7);

    // Legend: part ids in their colours with this frame's point counts.
    for (int i = 0; i < legend_shown_; ++i) viewer.removeShape("legend" + std::to_string(i));
    legend_shown_ = 0;
    int y = 60;
    for (const auto& [label, n] : counts) {
      if (static_cast<std::size_t>(legend_shown_) >= opt_.max_legend_entries) break;
      unsigned char r, g, b;
      io::labelColor(label, r, g, b);
      const std::string text =
          (label < 0 ? std::string("unlabelled") : "part " + std::to_string(label)) + ": " +
          std::to_string(n) + " pts";
      viewer.addText(text, 10, y, 13, r / 255.0, g / 255.0, b / 255.0,
                     "legend" + std::to_string(legend_shown_++));
      y += 16;
    }

    // Keypoints as wire spheres of their scale ("overlaid with their scale").
    for (int i = 0; i < keypoints_shown_; ++i) viewer.removeShape("kp" + std::to_string(i));
    keypoints_shown_ = 0;
    if (show_keypoints_) {
      const float fallback = static_cast<float>(boundingBoxDiagonal(*f.cloud)) / 200.f;
      for (const auto& kp : f.keypoints) {
        if (keypoints_shown_ >= 500) break;  // beyond that VTK slows to a crawl
        const std::string id = "kp" + std::to_string(keypoints_shown_++);
        pcl::PointXYZ centre(kp.position.x(), kp.position.y(), kp.position.z());
        viewer.addSphere(centre, kp.scale > 0 ? kp.scale : fallback, 1.0, 1.0, 1.0, id);
        viewer.setShapeRenderingProperties(
            pcl::visualization::PCL_VISUALIZER_REPRESENTATION,
            pcl::visualization::PCL_VISUALIZER_REPRESENTATION_WIREFRAME, id);
      }
    }
  }

  static void setText(pcl::visualization::PCLVisualizer& viewer, const std::string& id,
                      const std::string& text, int x, int y, int size, double r, double g,
                      double b) {
    if (!viewer.updateText(text, x, y, size, r, g, b, id))
      viewer.addText(text, x, y, size, r, g, b, id);
  }

  const LabelledSequence& seq_;
  ViewerOptions opt_;
  int frame_ = 0;
  int level_ = 0;
  bool playing_ = false;
  bool show_keypoints_ = true;
  bool dirty_ = true;
  int legend_shown_ = 0;
  int keypoints_shown_ = 0;
};

}  // namespace

void runSequenceViewer(const LabelledSequence& sequence, const ViewerOptions& options) {
  if (sequence.size() == 0) throw Error("nothing to show: the sequence has no frames");
  if (options.level < 0 || options.level >= sequence.levels())
    throw Error("level " + std::to_string(options.level) + " does not exist (levels 0.." +
                std::to_string(sequence.levels() - 1) + ")");
  if (!(options.fps > 0)) throw Error("--fps must be > 0");
  if (!displayAvailable())
    throw Error(
        "no display (DISPLAY is not set): use --png FILE to render a contact sheet "
        "headless, or run under an X server");
  ViewerState(sequence, options).run();
}

}  // namespace visualization
}  // namespace pcl_animseg
