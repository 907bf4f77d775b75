#pragma once
/** \file pipeline.h The whole method of Fig. 1 as one call: what `animseg` runs. */
#include <pcl_animseg/features/multiscale.h>
#include <pcl_animseg/segmentation/gmm_refinement.h>
#include <pcl_animseg/segmentation/hierarchy.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/segmentation/rigid_motion.h>
#include <pcl_animseg/sequence.h>

#include <map>
#include <string>
#include <thread>
#include <vector>

namespace pcl_animseg {
class Progress;

/** \brief Every knob of the one-shot pipeline, one struct per stage; `animseg` options and
 * `--config` keys map onto it. The mean shift's bandwidth, weights, method and seed live in
 * `mean_shift`. */
struct PipelineParams {
  std::string device = "auto";  ///< auto | cpu | gpu (mean shift backend)
  int levels = 4;               ///< hierarchy levels above level 0, at most
  /** Compute scale space, keypoints and signatures for the paper method's joint space. The
   * motion method (the default) uses none of them, and they are skipped for it. */
  bool features = true;
  bool refine = true;           ///< run the GMM boundary refinement
  bool motions = true;          ///< estimate the rigid motion of every part of every level
  /** Levels whose parts get rigid motions, finest first; 0: all. The coarse levels' merged
   * parts are large and not rigid, so their ICPs cost most on few cores (200k points, 2
   * threads: 0.8 s for level 0, 3.8 s for all five levels). */
  int motion_levels = 0;
  MultiscaleParams multiscale;
  segmentation::MeanShiftParams mean_shift;
  segmentation::RefinementParams refinement;
  segmentation::HierarchyParams hierarchy;
  segmentation::RigidMotionParams rigid_motion;
};

/** \brief What a run produced. Labels are in kept-point order (PointCloudSequence); expand with
 * PointCloudSequence::toInputOrder for files. */
struct PipelineResult {
  /** levels[l][t][j]: part of point j of frame t at hierarchy level l (0 = finest). */
  std::vector<std::vector<std::vector<int>>> levels;
  std::vector<int> parts_per_level;
  /** Stage name -> seconds, for the stages this run went through (a skipped stage is absent). */
  std::vector<std::pair<std::string, double>> timings;
  std::string device_used = "cpu";
  /** Peak GPU memory of the run: the mean-shift stage, the refinement's and the rigid motions'
   * fits (bytes; 0 on the CPU). */
  std::size_t device_peak_bytes = 0;
  /** The GPU's PCI bus id ("0000:1A:00.0", as nvidia-smi lists it; empty on the CPU): which of
   * a machine's GPUs ran. */
  std::string device_pci_bus_id;
  /** How long the GPU took to start (the driver's start and the context's, seconds; negative on
   * the CPU). Part of it runs beside the loading and the first CPU work (DeviceWarmUp); a GPU idle
   * for a second or more before the run starts slower (H200: 0.27 s instead of 0.16-0.18 s). */
  double device_start_s = -1.0;
  std::size_t keypoints = 0;
  std::vector<std::size_t> keypoints_per_frame;
  /** Points of the input whose normals the loader estimated (0 when every point came with one). */
  std::size_t normals_estimated = 0;
  std::vector<segmentation::LevelMotion> motions;  ///< every level's parts (empty when not asked for)
  std::vector<std::string> notes;   ///< fall-backs and warnings worth keeping in summary.json
  /** The paper method's Gaussian kd-tree: points per filter cell (N/M); 0 when no filter ran. */
  double sampling_factor = 0.0;
};

/** \brief Runs scale space, keypoints, signatures (paper method only), mean shift, refinement,
 * hierarchy and rigid motion on a loaded sequence (Fig. 1). Throws Error on bad parameters.
 * Stage times are recorded in `progress` under the names of DESIGN.md's summary.json. */
PipelineResult runPipeline(const PointCloudSequence& sequence, const PipelineParams& params,
                           Progress& progress);

/** \brief Starts the GPU's check (the CUDA driver's and context's start: 0.2-0.35 s on the H100
 * machine) on a thread of its own, so that it runs while the caller loads the sequence and while
 * runPipeline does its first CPU work, instead of before them. runPipeline then waits for it only
 * where the GPU is first needed, and the results are the same. Does nothing for device "cpu" or in
 * a build without the CUDA module. Keep it alive until runPipeline returns: its destructor waits
 * for the check to finish.
 *
 * Construct it before the process starts other threads or a CUDA context: unless the environment
 * sets CUDA_DEVICE_MAX_CONNECTIONS, it sets it to 2 (the context's hardware work queues, 8 by
 * default: the context starts about 0.05 s sooner with 2, and the pipeline keeps at most two
 * streams busy). A program with CUDA work of its own can set the variable first.
 *
 * \code
 * pcl_animseg::DeviceWarmUp warm_up(params.device);
 * const auto seq = pcl_animseg::io::loadSequence(dir);
 * const auto result = pcl_animseg::runPipeline(seq, params, progress);
 * \endcode */
class DeviceWarmUp {
 public:
  explicit DeviceWarmUp(const std::string& device);
  ~DeviceWarmUp();
  DeviceWarmUp(const DeviceWarmUp&) = delete;
  DeviceWarmUp& operator=(const DeviceWarmUp&) = delete;

 private:
  std::thread thread_;
};

/** \brief Checks parameters (bandwidth > 0, weights >= 0, known device, levels >= 0). */
void validate(const PipelineParams& params);

/** \brief A `--device` value: "auto", "cpu", "gpu", or "gpu:N" for the machine's GPU N. */
struct DeviceChoice {
  std::string device = "auto";  ///< auto | cpu | gpu: PipelineParams::device
  int gpu_index = -1;           ///< N of "gpu:N"; -1 when no GPU was named
};

/** \brief Parses a `--device` value; throws Error naming the accepted forms on anything else
 * ("gpu:", "gpu:-1", "gpu:1x", "tpu"). */
DeviceChoice parseDeviceChoice(const std::string& text);

/** \brief The CUDA_VISIBLE_DEVICES value that leaves GPU `index` alone visible, given the
 * variable's value now (`current`; null when it is unset): "N" when unset, else the list's N-th
 * entry (an index or a GPU's UUID, as the user wrote it). Throws Error when the list is shorter.
 *
 * The library runs on the current CUDA device of the threads it starts, device 0 of those
 * visible, so a program picks one of a machine's GPUs for the whole process by setting the
 * variable to this value before its first CUDA call (before DeviceWarmUp): `animseg --device
 * gpu:N` does, with CUDA_DEVICE_ORDER=PCI_BUS_ID where neither variable is set, so that N is
 * nvidia-smi's number. */
std::string visibleDevicesFor(const char* current, int index);

}  // namespace pcl_animseg
