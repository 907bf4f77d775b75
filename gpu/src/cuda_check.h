#pragma once
// Internal: PCL-style cudaSafeCall that throws pcl_animseg::Error with CUDA's message.
#include <cuda_runtime.h>

#include <pcl_animseg/error.h>

#include <string>

namespace pcl_animseg {
namespace gpu {
namespace detail {

[[noreturn]] inline void throwCuda(cudaError_t err, const char* what, const char* file, int line) {
  std::string msg = "GPU: " + std::string(what) + " failed: " + cudaGetErrorString(err) + " (" +
                    cudaGetErrorName(err) + ")";
  if (err == cudaErrorMemoryAllocation)
    msg += "; the GPU is out of memory: use fewer points or --device cpu";
  else if (err == cudaErrorNoDevice || err == cudaErrorInsufficientDriver)
    msg += "; no usable GPU: use --device cpu";
  (void)file;
  (void)line;
  throw DeviceError(msg);
}

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg

#define cudaSafeCall(expr)                                                            \
  do {                                                                                \
    const cudaError_t _err = (expr);                                                  \
    if (_err != cudaSuccess) {                                                        \
      cudaGetLastError(); /* clear a non-sticky error so the next call starts clean */ \
      ::pcl_animseg::gpu::detail::throwCuda(_err, #expr, __FILE__, __LINE__);         \
    }                                                                                 \
  } while (0)

// After a kernel launch: catches bad launch configurations at once (kernel faults show up at the
// next synchronising call, which is checked too).
#define cudaCheckLaunch() cudaSafeCall(cudaGetLastError())
