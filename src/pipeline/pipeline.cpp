#include <pcl_animseg/error.h>
#include <pcl_animseg/pipeline.h>
#include <pcl_animseg/progress.h>

#ifdef PCL_ANIMSEG_HAVE_CUDA
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/features.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>
#include <pcl_animseg/gpu/rigid_fits.h>
#endif

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <memory>
#include <utility>

namespace pcl_animseg {

void validate(const PipelineParams& p) {
  const auto& ms = p.mean_shift;
  if (!(ms.bandwidth > 0.0))
    throw Error("bandwidth must be > 0 (got " + std::to_string(ms.bandwidth) + ")");
  for (double w : {ms.w1, ms.w2, ms.w3, ms.w4})
    if (!(w >= 0.0)) throw Error("weights must be >= 0 (got " + std::to_string(w) + ")");
  if (p.device != "auto" && p.device != "cpu" && p.device != "gpu")
    throw Error("device must be auto, cpu or gpu (got '" + p.device + "')");
  if (p.levels < 0) throw Error("levels must be >= 0 (got " + std::to_string(p.levels) + ")");
  if (p.motion_levels < 0)
    throw Error("transform levels must be >= 0 (got " + std::to_string(p.motion_levels) + ")");
  // The refinement checks its parameters itself, but only after the mean shift: a typo should
  // not cost a run.
  if (p.refine) segmentation::validate(p.refinement);
}

DeviceChoice parseDeviceChoice(const std::string& text) {
  DeviceChoice c;
  if (text == "auto" || text == "cpu" || text == "gpu") {
    c.device = text;
    return c;
  }
  const std::string prefix = "gpu:";
  const std::string digits =
      text.size() > prefix.size() && text.compare(0, prefix.size(), prefix) == 0
          ? text.substr(prefix.size())
          : std::string();
  // A GPU's number: 1 to 4 decimal digits (no sign, no spaces: stoi would take "1x" or " 1").
  const bool number =
      !digits.empty() && digits.size() <= 4 &&
      std::all_of(digits.begin(), digits.end(), [](char ch) { return ch >= '0' && ch <= '9'; });
  if (!number)
    throw Error("device must be auto, cpu, gpu or gpu:N (N a GPU's number, from 0) (got '" + text +
                "')");
  c.device = "gpu";
  c.gpu_index = std::stoi(digits);
  return c;
}

std::string visibleDevicesFor(const char* current, int index) {
  if (index < 0) throw Error("a GPU's number must be >= 0 (got " + std::to_string(index) + ")");
  if (current == nullptr) return std::to_string(index);
  // CUDA's own reading: entries separated by commas; it stops at the first entry it cannot use,
  // which the driver then reports as no device (here: the entry is passed on as written).
  std::vector<std::string> entries;
  std::string entry;
  for (const char* ch = current;; ++ch) {
    if (*ch == ',' || *ch == '\0') {
      const auto b = entry.find_first_not_of(" \t");
      const auto e = entry.find_last_not_of(" \t");
      if (b != std::string::npos) entries.push_back(entry.substr(b, e - b + 1));
      entry.clear();
      if (*ch == '\0') break;
    } else {
      entry += *ch;
    }
  }
  if (static_cast<std::size_t>(index) >= entries.size())
    throw Error("GPU " + std::to_string(index) + " was asked for, but CUDA_VISIBLE_DEVICES='" +
                current + "' leaves " + std::to_string(entries.size()) +
                (entries.size() == 1 ? " GPU" : " GPUs") + " visible (numbered from 0)");
  return entries[index];
}

namespace {

// --device gpu without a GPU that works: a device's error (DeviceError), which a caller tells from
// the input's own by its type (animseg names the GPU that --device gpu:N asked for).
[[noreturn]] void noUsableGpu(const std::string& why) {
  throw DeviceError("--device gpu: no usable GPU: " + why);
}

// The number of distinct labels >= 0 (a flag per label: a std::set took 0.06-0.08 s for the
// levels of 800k points).
int countLabels(const std::vector<std::vector<int>>& labels) {
  // The labels that occur: each frame's, the frames side by side, then joined.
  const int frames = static_cast<int>(labels.size());
  std::vector<std::vector<char>> seen(labels.size());
#pragma omp parallel for schedule(static)
  for (int t = 0; t < frames; ++t)
    for (int l : labels[t]) {
      if (l < 0) continue;
      if (static_cast<std::size_t>(l) >= seen[t].size())
        seen[t].resize(static_cast<std::size_t>(l) + 1, 0);
      seen[t][l] = 1;
    }
  std::vector<char> any;
  for (const std::vector<char>& s : seen) {
    if (s.size() > any.size()) any.resize(s.size(), 0);
    for (std::size_t l = 0; l < s.size(); ++l) any[l] |= s[l];
  }
  return static_cast<int>(std::count(any.begin(), any.end(), 1));
}

std::string keypointDetail(const SequenceFeatures& f) {
  std::size_t n = 0;
  for (const auto& k : f.keypoints) n += k.size();
  return std::to_string(n) + " keypoints";
}

}  // namespace

DeviceWarmUp::DeviceWarmUp(const std::string& device) {
#ifdef PCL_ANIMSEG_HAVE_CUDA
  if (device == "cpu") return;
  // The context's hardware work queues: CUDA makes 8 unless CUDA_DEVICE_MAX_CONNECTIONS says
  // otherwise, and on the H100 machine each took about 7 ms of the context's start (8 queues:
  // 0.11-0.13 s, 2: 0.06-0.08 s, 32: 0.49-0.58 s). Streams share the queues (work of two streams
  // in one queue starts in order), and the pipeline has at most two streams busy at once (every
  // host thread has its own; the main thread's and a helper's beside it), so two: the 800k
  // humanoid's merges beside its labels took as long with two queues as with eight. Set on the
  // caller's thread before the check starts (setenv beside another thread's getenv is a data
  // race) and before this library starts a context (later it would do nothing); a value the
  // user set is kept.
  if (gpu::probeState() == gpu::ProbeState::NotStarted)
    ::setenv("CUDA_DEVICE_MAX_CONNECTIONS", "2", /*overwrite=*/0);
  thread_ = std::thread([] { gpu::gpuAvailable(); });
#else
  (void)device;
#endif
}

DeviceWarmUp::~DeviceWarmUp() {
  if (thread_.joinable()) thread_.join();
}

PipelineResult runPipeline(const PointCloudSequence& seq, const PipelineParams& params,
                           Progress& progress) {
  validate(params);
  if (seq.empty()) throw Error("the sequence has no frames");
  PipelineResult r;
  // The stages take shared pointers; the caller owns the sequence for the whole call.
  const PointCloudSequence::ConstPtr shared(&seq, [](const PointCloudSequence*) {});

  // 1. Multi-scale features (Sect. 3.1): scale space, DoG keypoints, signatures. They are the
  // paper method's joint space; the motion method (the default) clusters by rigid motion and
  // uses none of them, nor the joint-space densities and saddles they would feed (its hierarchy
  // follows its own merges), so neither is computed for it: same labels, levels and motions,
  // 27% less time on a 200k-point humanoid (15.7 s -> 11.5 s, 2 cores).
  const bool motion_method = params.mean_shift.method == segmentation::MeanShiftMethod::Motion;
  // Normals the loader had to estimate (plain point clouds): say so, with what it costs.
  for (std::size_t t = 0; t < seq.size(); ++t) r.normals_estimated += seq.estimatedNormals(t);
  if (r.normals_estimated > 0) {
    const std::string note =
        "normals estimated for " + std::to_string(r.normals_estimated) + " of " +
        std::to_string(seq.totalPoints()) +
        " points (the input has none for them): their directions blur the creases between "
        "parts, so parts that barely move against each other (a pelvis under a torso) merge more "
        "often than with the input's own normals";
    r.notes.push_back(note);
    progress.debug(note);
  }
  if (params.mean_shift.exact_borders &&
      (motion_method ||
       params.mean_shift.backend != segmentation::MeanShiftBackend::GaussianKdTree))
    r.notes.push_back(
        "--exact-borders not applied: it finishes the paper method's Gaussian kd-tree filter "
        "(--method paper --backend gkdtree)");
  SequenceFeatures features;
  if (params.features && motion_method) {
    r.notes.push_back(
        "features not computed: the motion method does not use them (--method paper does)");
  } else if (params.features) {
#ifdef PCL_ANIMSEG_HAVE_CUDA
    // The scale spaces and signatures on the GPU where there is one (gpu: or an error; auto: a
    // GPU that fails is a logged fall-back to the CPU, a missing one is noted with the mean
    // shift's below). A check still running (DeviceWarmUp) is not waited for: the device's first
    // call waits for the GPU's start while the cores check the frames and search their rows.
    std::unique_ptr<FeatureDevice> feature_device;
    if (params.device != "cpu") {
      std::string why;
      if (gpu::probeState() == gpu::ProbeState::Running || gpu::gpuAvailable(&why))
        feature_device = std::make_unique<gpu::FeatureDevice>();
      else if (params.device == "gpu")
        noUsableGpu(why);
    }
    // The stages a failed device attempt leaves open are abandoned before the CPU's run, which
    // is then recorded under its own names (a device that turned out missing, while its check
    // was still running when the features began, left "scale_space" open: summary.json's
    // scale_space was null).
    const std::size_t depth = progress.depth();
    try {
      features = computeSequenceFeatures(seq, params.multiscale, &progress, feature_device.get());
      if (feature_device) r.notes.push_back("scale space and signatures computed on the GPU");
    } catch (const DeviceError& e) {
      // The device's own errors (the input's are plain Errors, thrown as they are; without a
      // device there are none).
      std::string why;
      const bool missing = !gpu::gpuAvailable(&why);
      if (params.device == "gpu") {
        if (missing) noUsableGpu(why);
        throw;
      }
      if (!missing) {  // a missing GPU is noted with the mean shift's device below
        r.notes.push_back(std::string("the GPU failed in the features, the CPU was used: ") +
                          e.what());
        progress.info(std::string("warning: the GPU failed in the features, the CPU was used: ") +
                      e.what());
      }
      progress.abandon(depth);
      features = computeSequenceFeatures(seq, params.multiscale, &progress);
    }
#else
    features = computeSequenceFeatures(seq, params.multiscale, &progress);
#endif
    for (const auto& k : features.keypoints) {
      r.keypoints_per_frame.push_back(k.size());
      r.keypoints += k.size();
    }
    progress.debug(keypointDetail(features));
  } else if (!motion_method) {
    r.notes.push_back("features disabled: mean shift on position and normal only");
  }

  // 2. All frames clustered jointly (Sect. 3.2-3.3). The segmenter takes the signatures over
  // and is gone before the refinement, so they do not add to its peak memory.
  segmentation::MeanShiftParams msp = params.mean_shift;
  if (motion_method) msp.record_densities = false;
  segmentation::SegmentationResult clusters;
#ifdef PCL_ANIMSEG_HAVE_CUDA
  bool gpu_check_pending = false;  // the GPU's check ran on a DeviceWarmUp's thread
  // The ICP fits of the refinement and the rigid motions (see below), made here for the
  // refinement's frames prepared beside the motion method.
  std::unique_ptr<gpu::RigidFits> gpu_fits;
#endif
  // The refinement (3. below) is made now: what it needs of the frames alone (their trees and
  // spacings, every point's nearest points) is built beside the motion method's chains of
  // device calls (from its samples' poses on), which leave most cores idle, on half the threads
  // (the same results).
  segmentation::GMMBoundaryRefinement gmm;
  gmm.setInputSequence(&seq);
  bool prepared = false;
  {
    segmentation::RefinementParams rp = params.refinement;
    rp.seed = msp.seed;
    gmm.setParams(rp);
  }
  {
    segmentation::MeanShiftSegmentation ms;
    ms.setInputSequence(shared);
    ms.setParams(msp);
    if (params.device != "cpu") {
      // gpu: the GPU or an error; auto: the GPU when one works, else a logged fall-back to the CPU.
      std::string why;
#ifdef PCL_ANIMSEG_HAVE_CUDA
      // A check still running (DeviceWarmUp) is not waited for here: the backend waits where the
      // GPU is first needed, and a GPU found missing then is reported below as if found here.
      gpu_check_pending = gpu::probeState() == gpu::ProbeState::Running;
      if (gpu_check_pending || gpu::gpuAvailable(&why)) {
        gpu::resetPeakDeviceBytes();  // the run's peak, reported in summary.json
        ms.setDeviceBackend(gpu::makeMeanShiftBackend(/*check_now=*/false),
                            /*cpu_fallback=*/params.device == "auto");
        gpu_fits = std::make_unique<gpu::RigidFits>();
        why.clear();
      }
#else
      why = "this build has no CUDA module (nvcc was not found when it was configured)";
#endif
      if (!why.empty()) {
        if (params.device == "gpu") noUsableGpu(why);
        r.notes.push_back("device auto: the CPU was used: " + why);
        progress.debug("device auto: the CPU is used: " + why);
      }
    }
    if (!features.signatures.empty()) {
      ms.setSignatures(std::move(features.signatures));
      ms.setKeypoints(features.keypoints);
      features = SequenceFeatures();
    }
    if (params.refine && motion_method) {
      segmentation::RigidFitDevice* prep_device = nullptr;
#ifdef PCL_ANIMSEG_HAVE_CUDA
      prep_device = gpu_fits.get();
#endif
      ms.setBesideChains([&gmm, &prepared, prep_device, threads = omp_get_max_threads()] {
        if (prepared) return;  // once (a device failure reruns the method on the CPU)
        prepared = true;
        omp_set_num_threads(std::max(1, threads / 2));
        gmm.setRigidFitDevice(prep_device);
        gmm.prepareFrames();
      });
    }
    ms.setProgress(&progress);
    progress.begin("mean_shift");
#ifdef PCL_ANIMSEG_HAVE_CUDA
    try {
      ms.segment(clusters);
    } catch (const Error&) {
      std::string why;
      if (gpu_check_pending && !gpu::gpuAvailable(&why)) noUsableGpu(why);
      throw;
    }
#else
    ms.segment(clusters);
#endif
    progress.end(std::to_string(clusters.num_clusters) + " clusters" +
                 (clusters.sampling_factor > 0.0
                      ? " (filter N/M " + std::to_string(std::lround(clusters.sampling_factor)) +
                            ")"
                      : std::string()));
    r.device_used = ms.deviceUsed();
    r.sampling_factor = clusters.sampling_factor;
    // A GPU found missing by a check that ran beside the stage: said as if found before it.
    std::string no_gpu;
#ifdef PCL_ANIMSEG_HAVE_CUDA
    const bool found_late =
        gpu_check_pending && !ms.fallbackReason().empty() && !gpu::gpuAvailable(&no_gpu);
#else
    const bool found_late = false;
#endif
    if (found_late) {
      r.notes.push_back("device auto: the CPU was used: " + no_gpu);
      progress.debug("device auto: the CPU is used: " + no_gpu);
    } else if (!ms.fallbackReason().empty()) {
      r.notes.push_back("the GPU failed, the CPU was used: " + ms.fallbackReason());
      progress.info("warning: the GPU failed, the CPU was used: " + ms.fallbackReason());
    }
  }

  // The ICP fits of the refinement's motions and of the rigid motions run on the GPU when the
  // mean-shift stage ran there (the same results bit for bit). `onDevice(what, stage)` runs
  // stage(device); a GPU failure is an error with --device gpu, and with auto a logged fall-back:
  // the stage runs again on the CPU, as do the later ones.
  segmentation::RigidFitDevice* fit_device = nullptr;
#ifdef PCL_ANIMSEG_HAVE_CUDA
  if (r.device_used != "cpu" && gpu_fits) fit_device = gpu_fits.get();
#endif
  auto onDevice = [&](const std::string& what, const auto& stage) {
    if (fit_device) {
      try {
        stage(fit_device);
        return;
      } catch (const Error& e) {
        if (params.device == "gpu") throw;
        fit_device = nullptr;
        const std::string why = "the GPU failed in the " + what + ", the CPU was used: " + e.what();
        r.notes.push_back(why);
        progress.info("warning: " + why);
      }
    }
    stage(nullptr);
  };

  // The frames' mean spacings, measured once (in the first stage that needs them) for the
  // refinement and the rigid motions, which measured them twice each.
  std::vector<double> spacings;
  auto frameSpacings = [&]() {
    if (spacings.empty()) spacings = gmm.preparedSpacings();  // the same values
    if (spacings.empty()) spacings = meanSpacings(seq);
    return spacings;
  };

  // 3. Boundary refinement (Sect. 4), built over all frames jointly.
  segmentation::SegmentationResult refined;
  std::vector<segmentation::PartMotion> refinement_motions;
  if (params.refine && clusters.num_clusters > 1) {
    progress.begin("refine");
    gmm.setSpacings(frameSpacings());
    onDevice("refinement", [&](segmentation::RigidFitDevice* device) {
      gmm.setRigidFitDevice(device);
      gmm.refine(clusters, refined);
    });
    refinement_motions = gmm.getMotions();
    std::size_t changed = 0;
    for (std::size_t c : gmm.getStats().changed) changed += c;
    progress.end(std::to_string(changed) + " points relabelled by the GMMs, " +
                 std::to_string(gmm.getStats().snapped) + " snapped onto folds");
  } else {
    refined = clusters;
  }

  // 4. Hierarchy by region persistence (Sect. 5): nested levels, no re-clustering.
  progress.begin("hierarchy");
  segmentation::PersistenceHierarchy hierarchy;
  segmentation::HierarchyParams hp = params.hierarchy;
  hp.max_levels = params.levels;
  hierarchy.setParams(hp);
  segmentation::HierarchyResult levels;
  hierarchy.compute(refined, levels);
  r.levels = std::move(levels.labels);
  for (const auto& l : r.levels) r.parts_per_level.push_back(countLabels(l));
  progress.end(std::to_string(r.levels.size()) + " levels");

  // 5. Rigid motion of every part of every level (what skinning / bone estimation needs; the
  // same transforms.json as animseg_hierarchy writes). Parts that no merge touched keep the
  // motion of the level below, so only merged parts cost an ICP.
  if (params.motions) {
    progress.begin("rigid_motion");
    segmentation::RigidMotionEstimation rme;
    rme.setInputSequence(&seq);
    rme.setParams(params.rigid_motion);
    rme.setSpacings(frameSpacings());
    // Level 0's parts are the refinement's input parts with refined borders: their motions,
    // which the refinement fitted, start each frame's fit, and the frames run in parallel.
    rme.setInitialMotions(std::move(refinement_motions));
    const std::size_t max_levels = static_cast<std::size_t>(std::max(0, params.motion_levels));
    onDevice("rigid motions", [&](segmentation::RigidFitDevice* device) {
      rme.setDevice(device);
      r.motions = rme.computeLevels(r.levels, {}, max_levels);
    });
    progress.end();
  }
#ifdef PCL_ANIMSEG_HAVE_CUDA
  if (r.device_used != "cpu") {
    r.device_peak_bytes = gpu::peakDeviceBytes();
    r.device_start_s = gpu::startSeconds();
    try {
      r.device_pci_bus_id = gpu::deviceInfo().pci_bus_id;
    } catch (const Error&) {
      // The device ran every stage; a bus id it cannot give leaves the field empty (null).
    }
  }
#endif
  r.timings = progress.timings();
  return r;
}

}  // namespace pcl_animseg
