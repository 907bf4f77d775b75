#pragma once
/** \file device.h Which GPU we run on, whether there is one, and how much memory we used. */
#include <cstddef>
#include <string>

namespace pcl_animseg {
namespace gpu {

/** \brief True when a CUDA device is present and runs this library's kernels (the check
 * launches an empty kernel once, so a driver too old or a GPU of another architecture than the
 * one compiled for is reported too). On false, `why` (if given) says what is missing, in words a
 * user can act on; `--device auto` logs it and falls back to the CPU. Never throws. */
bool gpuAvailable(std::string* why = nullptr);

/** \brief Where gpuAvailable()'s one probe stands. A call made while another thread probes waits
 * for that probe; probeState() never waits. */
enum class ProbeState { NotStarted, Running, Done };
ProbeState probeState();

/** \brief How long gpuAvailable()'s probe took, in seconds: the driver's start (cuInit) and the
 * primary context's, with one small kernel; negative until a probe has ended. A GPU that has been
 * idle for a second or more starts slower (H200: the driver's start 0.19 s instead of 0.10 s). */
double startSeconds();

/** \brief Throws Error("no usable GPU: <why>") unless gpuAvailable() (waits for a probe under
 * way on another thread). */
void requireGpu();

/** \brief The current device. */
struct DeviceInfo {
  int id = -1;
  std::string name;
  int compute_major = 0;
  int compute_minor = 0;
  int multiprocessors = 0;
  std::string pci_bus_id;  ///< "0000:1A:00.0" (domain:bus:device.function), as nvidia-smi lists it
  std::size_t total_bytes = 0;
  std::size_t free_bytes = 0;
};

/** \brief Describes the current device; throws Error when there is none. */
DeviceInfo deviceInfo();

/** \brief "gpu (NAME)" for the current device, "gpu" when it cannot be named: what the device
 * backends call themselves in logs and summary.json. Never throws. */
std::string deviceLabel();

/** \brief Makes `id` the current device; throws Error when it does not exist. */
void setDevice(int id);

/** \brief Waits for all queued GPU work; throws Error when a kernel failed. */
void synchronize();

/** \brief Device bytes held now by DeviceMemory buffers of this library. */
std::size_t allocatedDeviceBytes();
/** \brief The most device bytes held at once by this library since the last reset (CUDA's own
 * context and library overhead, a few hundred MiB, are not included). */
std::size_t peakDeviceBytes();
/** \brief Restarts peak tracking from what is held now. */
void resetPeakDeviceBytes();

}  // namespace gpu
}  // namespace pcl_animseg
