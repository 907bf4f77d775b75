// animseg: the one-shot pipeline of Fig. 1 — a sequence in, temporally coherent near-rigid parts
// out.
//
// This program only starts the GPU's driver, then loads the pipeline: its body (options, stages,
// output) is tools/cli/animseg_main.cpp, in the library libpcl_animseg_cli.so. Before `main` a
// program linked to the pipeline loads and relocates about 80 shared libraries (PCL's I/O and
// the VTK libraries it needs: 0.02-0.03 s on the GPU machine), and on an idle GPU the driver's
// and the context's start (0.25-0.3 s there) is what the first device call waits for. Here the
// driver starts first, on a thread of its own, and the libraries load beside it.
//
// Written by us: no kept library starts a CUDA driver before a program's libraries load.
#include <dlfcn.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>

#include "cli/launch_args.h"

namespace {

using Clock = std::chrono::steady_clock;

double secondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// The CUDA driver's start and the device's primary context (the one the CUDA runtime of the
// pipeline then uses), through the driver library loaded here: a machine without it, or
// without a GPU, only skips this. The context is kept for the process's life.
void startDriver(bool report) {
  const auto t0 = Clock::now();
  void* cuda = dlopen("libcuda.so.1", RTLD_NOW | RTLD_LOCAL);
  if (!cuda) return;
  using Init = int (*)(unsigned);
  using DeviceGet = int (*)(int*, int);
  using Retain = int (*)(void**, int);
  const auto init = reinterpret_cast<Init>(dlsym(cuda, "cuInit"));
  const auto get = reinterpret_cast<DeviceGet>(dlsym(cuda, "cuDeviceGet"));
  const auto retain = reinterpret_cast<Retain>(dlsym(cuda, "cuDevicePrimaryCtxRetain"));
  if (!init || !get || !retain || init(0) != 0) return;
  const double t_init = secondsSince(t0);
  int device = 0;
  void* context = nullptr;
  if (get(&device, 0) != 0 || retain(&context, device) != 0) return;
  if (report)
    std::fprintf(stderr, "[launcher] the GPU's driver started in %.3f s (its context %.3f s)\n",
                 secondsSince(t0), secondsSince(t0) - t_init);
}

}  // namespace

int main(int argc, char** argv) {
  const bool report = std::getenv("ANIMSEG_MS_TIMING") != nullptr;
  std::thread driver;
#ifdef PCL_ANIMSEG_HAVE_CUDA
  if (pcl_animseg::tools::startsGpu(argc, argv)) {
    // As the program sets it before its own start of the GPU (DeviceWarmUp): two hardware work
    // queues; the user's value is kept. Read when the context is made, so set before.
    ::setenv("CUDA_DEVICE_MAX_CONNECTIONS", "2", /*overwrite=*/0);
    driver = std::thread(startDriver, report);
  }
#endif
  // The library is found through this program's run path ($ORIGIN/../lib, or the build tree's),
  // then LD_LIBRARY_PATH and the system's.
  const auto t0 = Clock::now();
  void* cli = dlopen("libpcl_animseg_cli.so", RTLD_NOW | RTLD_LOCAL);
  using Main = int (*)(int, char**);
  Main body = cli ? reinterpret_cast<Main>(dlsym(cli, "animseg_main")) : nullptr;
  int code = 1;
  if (!body) {
    const char* why = dlerror();
    std::fprintf(stderr, "error: cannot load the pipeline (libpcl_animseg_cli.so): %s\n",
                 why ? why : "no animseg_main in it");
  } else {
    if (report)
      std::fprintf(stderr, "[launcher] the pipeline's libraries loaded in %.3f s\n",
                   secondsSince(t0));
    code = body(argc, argv);
  }
  // Joined, not left running into the exit handlers (a quick error exit waits for the driver).
  if (driver.joinable()) driver.join();
  return code;
}
