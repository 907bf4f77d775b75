// DeviceWarmUp (pipeline.h): the GPU's check started on a thread of its own before runPipeline,
// which then waits for it only where the GPU is first needed. Each test is a process of its own
// (gtest_discover_tests), so the check is still running when runPipeline starts on a machine with
// a GPU (it takes 0.2-0.35 s there); without one it ends at once, and the pipeline decides as it
// did before. Either way the labels are the CPU's, and a missing GPU is said in the same words.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/pipeline.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/synth/articulated.h>

#include <algorithm>
#include <cstdlib>
#include <string>

namespace gpu = pcl_animseg::gpu;
namespace synth = pcl_animseg::synth;

namespace {

pcl_animseg::PointCloudSequence humanoid() {
  synth::SynthParams sp;
  sp.plan = synth::BodyPlan::Humanoid;
  sp.frames = 8;
  sp.points = 1500;
  sp.seed = 5;
  return synth::toSequence(synth::generate(sp));
}

pcl_animseg::PipelineParams params(const std::string& device) {
  pcl_animseg::PipelineParams p;
  p.device = device;
  p.levels = 1;
  return p;
}

bool hasNote(const pcl_animseg::PipelineResult& r, const std::string& text) {
  return std::any_of(r.notes.begin(), r.notes.end(),
                     [&](const std::string& n) { return n.find(text) != std::string::npos; });
}

}  // namespace

TEST(DeviceWarmUp, AutoGivesTheCpuLabelsAndSaysWhichDeviceRan) {
  const auto seq = humanoid();
  pcl_animseg::Progress quiet(true, false);
  pcl_animseg::PipelineResult dev;
  {
    const pcl_animseg::DeviceWarmUp warm_up("auto");
    dev = pcl_animseg::runPipeline(seq, params("auto"), quiet);
  }
  const pcl_animseg::PipelineResult cpu = pcl_animseg::runPipeline(seq, params("cpu"), quiet);
  ASSERT_FALSE(cpu.levels.empty());
  EXPECT_TRUE(cpu.device_pci_bus_id.empty()) << cpu.device_pci_bus_id;
  EXPECT_LT(cpu.device_start_s, 0.0);
  EXPECT_EQ(dev.levels, cpu.levels);
  EXPECT_EQ(dev.parts_per_level, cpu.parts_per_level);
  std::string why;
  if (gpu::gpuAvailable(&why)) {
    EXPECT_NE(dev.device_used, "cpu");
    EXPECT_FALSE(hasNote(dev, "the CPU was used"));
    EXPECT_GT(dev.device_peak_bytes, 0u);
    // Which GPU: its PCI bus id, "DDDD:BB:DD.F" as nvidia-smi lists it.
    EXPECT_EQ(dev.device_pci_bus_id, gpu::deviceInfo().pci_bus_id);
    EXPECT_EQ(dev.device_pci_bus_id.size(), 12u) << dev.device_pci_bus_id;
    EXPECT_EQ(dev.device_pci_bus_id.find(':'), 4u) << dev.device_pci_bus_id;
    // The GPU's start, timed by its probe: the same number the library reports.
    EXPECT_GT(dev.device_start_s, 0.0);
    EXPECT_LT(dev.device_start_s, 60.0);
    EXPECT_EQ(dev.device_start_s, gpu::startSeconds());
  } else {
    EXPECT_EQ(dev.device_used, "cpu");
    EXPECT_TRUE(dev.device_pci_bus_id.empty());
    EXPECT_TRUE(hasNote(dev, "device auto: the CPU was used: " + why));
    EXPECT_FALSE(hasNote(dev, "the GPU failed"));
  }
}

TEST(DeviceWarmUp, GpuWithoutAGpuIsOneClearError) {
  const auto seq = humanoid();
  pcl_animseg::Progress quiet(true, false);
  std::string message;
  bool ran = false;
  {
    const pcl_animseg::DeviceWarmUp warm_up("gpu");
    try {
      const auto r = pcl_animseg::runPipeline(seq, params("gpu"), quiet);
      ran = true;
      EXPECT_NE(r.device_used, "cpu");
    } catch (const pcl_animseg::Error& e) {
      message = e.what();
    }
  }
  std::string why;
  if (gpu::gpuAvailable(&why)) {
    EXPECT_TRUE(ran) << message;
  } else {
    EXPECT_FALSE(ran);
    EXPECT_EQ(message, "--device gpu: no usable GPU: " + why);
  }
}

// The warm-up of a CPU run starts nothing: the check has not run when the pipeline is done.
TEST(DeviceWarmUp, CpuStartsNoCheck) {
  if (gpu::probeState() != gpu::ProbeState::NotStarted)
    GTEST_SKIP() << "an earlier test of this process checked the GPU (ctest runs each alone)";
  const auto seq = humanoid();
  pcl_animseg::Progress quiet(true, false);
  {
    const pcl_animseg::DeviceWarmUp warm_up("cpu");
    const auto r = pcl_animseg::runPipeline(seq, params("cpu"), quiet);
    EXPECT_EQ(r.device_used, "cpu");
  }
  EXPECT_EQ(gpu::probeState(), gpu::ProbeState::NotStarted);
}

namespace {

// CUDA_DEVICE_MAX_CONNECTIONS now, or "" where unset.
std::string queues() {
  const char* v = std::getenv("CUDA_DEVICE_MAX_CONNECTIONS");
  return v ? v : "";
}

}  // namespace

// A GPU run's warm-up asks for two hardware queues (the context starts sooner) unless the
// environment names a number; a CPU run's leaves the environment alone.
TEST(DeviceWarmUp, AsksForTwoHardwareQueues) {
  if (gpu::probeState() != gpu::ProbeState::NotStarted)
    GTEST_SKIP() << "an earlier test of this process checked the GPU (ctest runs each alone)";
  ::unsetenv("CUDA_DEVICE_MAX_CONNECTIONS");
  { const pcl_animseg::DeviceWarmUp warm_up("cpu"); }
  EXPECT_EQ(queues(), "");
  { const pcl_animseg::DeviceWarmUp warm_up("auto"); }
  EXPECT_EQ(queues(), "2");
}

TEST(DeviceWarmUp, KeepsTheHardwareQueuesTheUserSet) {
  if (gpu::probeState() != gpu::ProbeState::NotStarted)
    GTEST_SKIP() << "an earlier test of this process checked the GPU (ctest runs each alone)";
  ::setenv("CUDA_DEVICE_MAX_CONNECTIONS", "5", 1);
  { const pcl_animseg::DeviceWarmUp warm_up("gpu"); }
  EXPECT_EQ(queues(), "5");
}
