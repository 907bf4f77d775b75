// Device buffers, device queries and allocation accounting.
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/device_array.h>

#include "cuda_check.h"
#include "gkdtree_device.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <mutex>

namespace pcl_animseg {
namespace gpu {

namespace {
std::atomic<std::size_t> g_allocated{0};
std::atomic<std::size_t> g_peak{0};

void noteAlloc(std::size_t bytes) {
  const std::size_t now = g_allocated.fetch_add(bytes) + bytes;
  std::size_t peak = g_peak.load();
  while (now > peak && !g_peak.compare_exchange_weak(peak, now)) {
  }
}

std::string mib(std::size_t bytes) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.1f MiB", bytes / (1024.0 * 1024.0));
  return buf;
}

__global__ void probeKernel(int* flag) { *flag = 42; }
}  // namespace

DeviceMemory::DeviceMemory(DeviceMemory&& other) noexcept : ptr_(other.ptr_), bytes_(other.bytes_) {
  other.ptr_ = nullptr;
  other.bytes_ = 0;
}

DeviceMemory& DeviceMemory::operator=(DeviceMemory&& other) noexcept {
  if (this != &other) {
    release();
    ptr_ = other.ptr_;
    bytes_ = other.bytes_;
    other.ptr_ = nullptr;
    other.bytes_ = 0;
  }
  return *this;
}

void DeviceMemory::create(std::size_t bytes) {
  if (bytes == bytes_ && ptr_) return;
  release();
  if (bytes == 0) return;
  void* p = nullptr;
  const cudaError_t err = cudaMalloc(&p, bytes);
  if (err != cudaSuccess) {
    cudaGetLastError();
    if (err == cudaErrorMemoryAllocation) {
      std::size_t free_b = 0, total_b = 0;
      cudaMemGetInfo(&free_b, &total_b);
      cudaGetLastError();
      throw DeviceError("GPU out of memory: cannot allocate " + mib(bytes) + " (" + mib(free_b) +
                        " free of " + mib(total_b) + "); use fewer points or --device cpu");
    }
    detail::throwCuda(err, "cudaMalloc", __FILE__, __LINE__);
  }
  ptr_ = p;
  bytes_ = bytes;
  noteAlloc(bytes);
}

void DeviceMemory::release() noexcept {
  if (ptr_) {
    cudaFree(ptr_);  // errors here are sticky kernel faults already reported elsewhere
    g_allocated.fetch_sub(bytes_);
  }
  ptr_ = nullptr;
  bytes_ = 0;
}

void DeviceMemory::uploadBytes(const void* host, std::size_t bytes) {
  if (bytes > bytes_) throw DeviceError("GPU: upload of more bytes than the buffer holds");
  if (bytes) cudaSafeCall(cudaMemcpy(ptr_, host, bytes, cudaMemcpyHostToDevice));
}

void DeviceMemory::downloadBytes(void* host, std::size_t bytes) const {
  if (bytes > bytes_) throw DeviceError("GPU: download of more bytes than the buffer holds");
  if (bytes) cudaSafeCall(cudaMemcpy(host, ptr_, bytes, cudaMemcpyDeviceToHost));
}

void DeviceMemory::setZero() {
  if (bytes_) cudaSafeCall(cudaMemset(ptr_, 0, bytes_));
}

void DeviceMemory::copyTo(DeviceMemory& other) const {
  other.create(bytes_);
  if (bytes_) cudaSafeCall(cudaMemcpy(other.ptr_, ptr_, bytes_, cudaMemcpyDeviceToDevice));
}

namespace {
// gpuAvailable()'s probe: 0 not started, 1 running, 2 done (probeState() reads it, never waits).
std::atomic<int>& probeStage() {
  static std::atomic<int> stage{0};
  return stage;
}
// gpuAvailable()'s probe's duration (seconds; negative until it has ended).
std::atomic<double>& probeSeconds() {
  static std::atomic<double> seconds{-1.0};
  return seconds;
}
}  // namespace

bool gpuAvailable(std::string* why) {
  // Probed once: the answer does not change during a run, and the probe costs a context start
  // (0.2-0.35 s on the H100 machine: the driver's start and the context's, about half each).
  static std::once_flag once;
  static bool ok = false;
  static std::string reason;
  std::call_once(once, [] {
    probeStage().store(1);
    // Under ANIMSEG_MS_TIMING: how long the start took, and when it ended on the steady clock
    // (the first device call's line says when it came: whether it waited for the start).
    struct Done {
      std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now();
      ~Done() {
        const auto t1 = std::chrono::steady_clock::now();
        probeSeconds().store(std::chrono::duration<double>(t1 - t0).count());
        probeStage().store(2);
        if (std::getenv("ANIMSEG_MS_TIMING")) {
          std::fprintf(stderr, "[gpu] started in %.3f s (ended at %.3f s)\n",
                       std::chrono::duration<double>(t1 - t0).count(),
                       std::chrono::duration<double>(t1.time_since_epoch()).count());
        }
      }
    } done;
    int count = 0;
    cudaError_t err = cudaGetDeviceCount(&count);
    if (err != cudaSuccess || count == 0) {
      cudaGetLastError();
      reason = err != cudaSuccess ? std::string("no usable CUDA device (") + cudaGetErrorString(err) + ")"
                                  : std::string("no CUDA device found");
      return;
    }
    int* flag = nullptr;
    err = cudaMalloc(&flag, sizeof(int));
    if (err == cudaSuccess) {
      probeKernel<<<1, 1>>>(flag);
      err = cudaGetLastError();
      int host = 0;
      if (err == cudaSuccess) err = cudaMemcpy(&host, flag, sizeof(int), cudaMemcpyDeviceToHost);
      if (err == cudaSuccess && host != 42) err = cudaErrorUnknown;
      cudaFree(flag);
    }
    if (err != cudaSuccess) {
      cudaGetLastError();
      reason = std::string("the CUDA device cannot run this build's kernels (") +
               cudaGetErrorString(err) +
               "); rebuild with CMAKE_CUDA_ARCHITECTURES set for this GPU, or use --device cpu";
      return;
    }
    ok = true;
  });
  if (why) *why = reason;
  return ok;
}

ProbeState probeState() {
  switch (probeStage().load()) {
    case 0:
      return ProbeState::NotStarted;
    case 1:
      return ProbeState::Running;
    default:
      return ProbeState::Done;
  }
}

double startSeconds() { return probeSeconds().load(); }

void requireGpu() {
  std::string why;
  if (!gpuAvailable(&why)) throw DeviceError("no usable GPU: " + why);
}

DeviceInfo deviceInfo() {
  DeviceInfo info;
  cudaSafeCall(cudaGetDevice(&info.id));
  cudaDeviceProp prop;
  cudaSafeCall(cudaGetDeviceProperties(&prop, info.id));
  info.name = prop.name;
  info.compute_major = prop.major;
  info.compute_minor = prop.minor;
  info.multiprocessors = prop.multiProcessorCount;
  char bus[32] = {0};
  cudaSafeCall(cudaDeviceGetPCIBusId(bus, static_cast<int>(sizeof(bus)), info.id));
  info.pci_bus_id = bus;
  cudaSafeCall(cudaMemGetInfo(&info.free_bytes, &info.total_bytes));
  return info;
}

std::string deviceLabel() {
  try {
    return "gpu (" + deviceInfo().name + ")";
  } catch (const Error&) {
    return "gpu";
  }
}

void setDevice(int id) { cudaSafeCall(cudaSetDevice(id)); }

void synchronize() { cudaSafeCall(cudaDeviceSynchronize()); }

namespace detail {
void copyDeviceBytes(void* dst, const void* src, std::size_t bytes) {
  if (bytes) cudaSafeCall(cudaMemcpy(dst, src, bytes, cudaMemcpyDeviceToDevice));
}
}  // namespace detail

std::size_t allocatedDeviceBytes() { return g_allocated.load(); }
std::size_t peakDeviceBytes() { return g_peak.load(); }
void resetPeakDeviceBytes() { g_peak.store(g_allocated.load()); }

}  // namespace gpu
}  // namespace pcl_animseg
