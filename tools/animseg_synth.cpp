// animseg_synth: articulated test sequences with known parts (frames + ground-truth labels).
#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/synth/articulated.h>
#include <pcl_animseg/tool_common.h>

#include <unistd.h>

#include <filesystem>
#include <regex>
#include <set>
#include <sstream>

namespace po = boost::program_options;
namespace fs = std::filesystem;
using namespace pcl_animseg;

namespace {

std::string infoJson(const tools::ToolContext& ctx, const synth::SynthParams& p,
                     const std::vector<synth::SynthFrame>& frames) {
  std::ostringstream os;
  os << "{\n  \"generator\": \"animseg_synth\",\n  \"parameters\": " << ctx.optionsJson() << ",\n";
  os << "  \"plan\": \"" << synth::toString(p.plan) << "\",\n  \"mode\": \""
     << (p.mesh ? "mesh" : "points") << "\",\n  \"frames\": " << frames.size()
     << ",\n  \"points_per_frame\": [";
  for (std::size_t t = 0; t < frames.size(); ++t) os << (t ? ", " : "") << frames[t].cloud->size();
  os << "],\n  \"parts\": " << tools::jsonStringArray(synth::partNames(p.plan)) << "\n}\n";
  return os.str();
}

bool isEmptyDir(const fs::path& p) {
  std::error_code ec;
  return fs::is_directory(p, ec) && fs::directory_iterator(p, ec) == fs::directory_iterator();
}

}  // namespace

int main(int argc, char** argv) {
  po::options_description od("Options");
  od.add_options()
    ("output,o", po::value<std::string>()->required(),
     "output directory: gets f000.ply + f000.gt, f001.ply + f001.gt, ... and synth.json")
    ("plan", po::value<std::string>()->default_value("quadruped"),
     "body plan: quadruped|humanoid|spider|snake|hand")
    ("frames", po::value<int>()->default_value(20), "number of frames T")
    ("points", po::value<int>()->default_value(4000), "mean points per frame (point mode)")
    ("variation", po::value<double>()->default_value(0.2),
     "each frame gets points * (1 +- variation) points, uniformly drawn")
    ("noise", po::value<double>()->default_value(0.0),
     "Gaussian position noise sigma, as a fraction of the frame's bounding-box diagonal")
    ("motion", po::value<double>()->default_value(1.0),
     "joint-angle amplitude multiplier (1: large, gallop-like; 0: rigid body)")
    ("scale", po::value<double>()->default_value(1.0), "uniform scale of the body")
    ("mesh", po::bool_switch(), "mesh mode: triangulated parts, same vertices in every frame")
    ("resolution", po::value<int>()->default_value(24), "tessellation per part in mesh mode")
    ("seed", po::value<unsigned>()->default_value(1), "random seed (output is deterministic)")
    ("force", po::bool_switch(), "write into a non-empty output directory (replaces its frames)");
  return tools::runTool(
      argc, argv, "animseg_synth",
      "animseg_synth --output DIR [--plan quadruped|humanoid|spider|snake|hand] [--frames T]\n"
      "              [--points N] [--variation 0.2] [--noise 0] [--motion 1] [--scale 1]\n"
      "              [--mesh] [--resolution R] [--seed S] [--force] [--quiet]",
      od, [&](const tools::ToolContext& ctx) {
        Progress progress(ctx.quiet, ctx.verbose);
        synth::SynthParams p;
        p.plan = synth::bodyPlanFromString(ctx.vm["plan"].as<std::string>());
        p.frames = ctx.vm["frames"].as<int>();
        p.points = ctx.vm["points"].as<int>();
        p.point_variation = ctx.vm["variation"].as<double>();
        p.noise = ctx.vm["noise"].as<double>();
        p.motion = ctx.vm["motion"].as<double>();
        p.scale = ctx.vm["scale"].as<double>();
        p.mesh = ctx.vm["mesh"].as<bool>();
        p.mesh_resolution = ctx.vm["resolution"].as<int>();
        p.seed = ctx.vm["seed"].as<unsigned>();
        const bool force = ctx.vm["force"].as<bool>();
        const fs::path out(ctx.vm["output"].as<std::string>());
        synth::validate(p);  // before any output, so a bad value gives just its error line

        std::error_code ec;
        const bool exists = fs::exists(out, ec);
        if (exists && !fs::is_directory(out, ec))
          throw Error("'" + out.string() + "' exists and is not a directory");
        const bool fresh = !exists || isEmptyDir(out);
        if (!fresh && !force)
          throw Error("output directory '" + out.string() +
                      "' is not empty; choose another or pass --force to replace its frames");

        progress.begin("generate");
        const auto frames = synth::generate(p);
        std::size_t total = 0;
        for (const auto& f : frames) total += f.cloud->size();
        progress.end(std::to_string(frames.size()) + " frames, " + std::to_string(total) +
                     (p.mesh ? " vertices" : " points"));

        progress.begin("write", frames.size());
        if (fresh) {
          // The whole directory appears at once: written under a hidden sibling, then renamed.
          const fs::path parent = out.has_parent_path() ? out.parent_path() : fs::path(".");
          io::ensureDirectory(parent.string());
          const fs::path tmp =
              parent / ("." + out.filename().string() + ".tmp." + std::to_string(::getpid()));
          try {
            fs::remove_all(tmp, ec);
            synth::writeSequence(tmp.string(), frames, &progress);
            io::writeTextAtomically((tmp / "synth.json").string(), infoJson(ctx, p, frames));
            if (exists) fs::remove(out);  // empty: rename() cannot replace it otherwise
            fs::rename(tmp, out);
          } catch (const fs::filesystem_error& e) {
            fs::remove_all(tmp, ec);
            throw Error("cannot write '" + out.string() + "': " + e.what());
          } catch (...) {
            fs::remove_all(tmp, ec);
            throw;
          }
        } else {
          // --force: frames of an earlier, longer run would join the sequence; remove those only
          // (other files are the user's), then replace each file atomically.
          std::set<std::string> keep;
          for (std::size_t t = 0; t < frames.size(); ++t) {
            keep.insert(synth::frameName(t, frames.size()) + ".ply");
            keep.insert(synth::frameName(t, frames.size()) + ".gt");
          }
          const std::regex frame_file("f[0-9]+\\.(ply|gt)");
          for (const auto& entry : fs::directory_iterator(out)) {
            const std::string name = entry.path().filename().string();
            if (std::regex_match(name, frame_file) && !keep.count(name)) fs::remove(entry.path());
          }
          synth::writeSequence(out.string(), frames, &progress);
          io::writeTextAtomically((out / "synth.json").string(), infoJson(ctx, p, frames));
        }
        progress.end();
        progress.info("animseg_synth: " + synth::toString(p.plan) + ", " +
                      std::to_string(frames.size()) + " frames, " +
                      std::to_string(synth::partCount(p.plan)) + " parts -> " + out.string());
        return 0;
      });
}
