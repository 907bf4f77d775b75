// animseg_view: look at a decomposition — a window with frame stepping, or a headless PNG sheet.
#include <pcl_animseg/error.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/tool_common.h>
#include <pcl_animseg/visualization/contact_sheet.h>
#include <pcl_animseg/visualization/sequence_viewer.h>

#include <string>

namespace po = boost::program_options;
using namespace pcl_animseg;

namespace {

Eigen::Vector3f parseUp(const std::string& text) {
  if (text == "auto") return Eigen::Vector3f::Zero();
  const bool minus = !text.empty() && text[0] == '-';
  const std::string axis = minus ? text.substr(1) : text;
  Eigen::Vector3f up;
  if (axis == "x") up = Eigen::Vector3f::UnitX();
  else if (axis == "y") up = Eigen::Vector3f::UnitY();
  else if (axis == "z") up = Eigen::Vector3f::UnitZ();
  else throw Error("--up must be auto, x, y, z, -x, -y or -z (got '" + text + "')");
  return minus ? Eigen::Vector3f(-up) : up;
}

}  // namespace

int main(int argc, char** argv) {
  po::options_description od("Options");
  od.add_options()
    ("input,i", po::value<std::string>()->required(),
     "the OUT directory of animseg (NAME.labels + NAME.pcd per frame)")
    ("frames", po::value<std::string>()->default_value(""),
     "geometry from here instead of OUT/NAME.pcd: the input sequence (directory or list file) "
     "or another OUT directory")
    ("level", po::value<int>()->default_value(0), "hierarchy level to colour by (0 = finest)")
    ("png", po::value<std::string>()->default_value(""),
     "render a contact sheet to this PNG file, headless (no display needed), and exit")
    ("columns", po::value<int>()->default_value(0), "contact sheet columns (0 = automatic)")
    ("count", po::value<int>()->default_value(0),
     "contact sheet frames, evenly spread over the sequence (0 = all up to 8)")
    ("width", po::value<int>()->default_value(1600), "contact sheet width in pixels")
    ("up", po::value<std::string>()->default_value("auto"),
     "up direction of the contact sheet: auto (from the principal axes) | x | y | z | -x | -y | -z")
    ("fps", po::value<double>()->default_value(4.0), "viewer autoplay speed (frames per second)")
    ("point-size", po::value<double>()->default_value(3.0), "viewer point size in pixels");
  return tools::runTool(
      argc, argv, "animseg_view",
      "animseg_view --input OUT [--frames SEQ_OR_OUT] [--level L] [--png FILE] [--columns C]\n"
      "                    [--count N] [--width W]\n"
      "  viewer keys: n/p frame, space autoplay, 0-9 or +/- level, k keypoints, q quit",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        const std::string png = ctx.vm["png"].as<std::string>();
        // Fail before the (possibly long) load when there is nowhere to show anything.
        if (png.empty() && !visualization::displayAvailable())
          throw Error("no display (DISPLAY is not set): use --png FILE to render a contact sheet "
                      "headless");
        const Eigen::Vector3f up = parseUp(ctx.vm["up"].as<std::string>());
        progress.begin("load");
        const visualization::LabelledSequence seq = visualization::loadLabelledSequence(
            ctx.vm["input"].as<std::string>(), ctx.vm["frames"].as<std::string>());
        progress.end(std::to_string(seq.size()) + " frames, " + std::to_string(seq.levels()) +
                     " levels");
        const int level = ctx.vm["level"].as<int>();
        if (!png.empty()) {
          visualization::ContactSheetOptions opt;
          opt.level = level;
          opt.columns = ctx.vm["columns"].as<int>();
          opt.frames = ctx.vm["count"].as<int>();
          opt.width = ctx.vm["width"].as<int>();
          opt.up = up;
          progress.begin("render");
          visualization::writePNG(png, visualization::renderContactSheet(seq, opt));
          progress.end("-> " + png);
          return 0;
        }
        visualization::ViewerOptions opt;
        opt.level = level;
        opt.fps = ctx.vm["fps"].as<double>();
        opt.point_size = ctx.vm["point-size"].as<double>();
        visualization::runSequenceViewer(seq, opt);
        return 0;
      });
}
