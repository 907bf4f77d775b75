// `--device` values (parseDeviceChoice) and the CUDA_VISIBLE_DEVICES value that leaves one GPU
// visible (visibleDevicesFor): what `animseg --device gpu:N` runs on.
#include <gtest/gtest.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/pipeline.h>

#include <string>

using pcl_animseg::DeviceChoice;
using pcl_animseg::parseDeviceChoice;
using pcl_animseg::visibleDevicesFor;

namespace {

std::string errorOf(const std::string& text) {
  try {
    parseDeviceChoice(text);
  } catch (const pcl_animseg::Error& e) {
    return e.what();
  }
  return std::string();
}

std::string visibleError(const char* current, int index) {
  try {
    visibleDevicesFor(current, index);
  } catch (const pcl_animseg::Error& e) {
    return e.what();
  }
  return std::string();
}

}  // namespace

TEST(DeviceChoice, NamesADeviceAndAGpusNumber) {
  for (const char* plain : {"auto", "cpu", "gpu"}) {
    const DeviceChoice c = parseDeviceChoice(plain);
    EXPECT_EQ(c.device, plain);
    EXPECT_EQ(c.gpu_index, -1) << plain;
  }
  const DeviceChoice one = parseDeviceChoice("gpu:1");
  EXPECT_EQ(one.device, "gpu");
  EXPECT_EQ(one.gpu_index, 1);
  EXPECT_EQ(parseDeviceChoice("gpu:0").gpu_index, 0);
  EXPECT_EQ(parseDeviceChoice("gpu:12").gpu_index, 12);
  EXPECT_EQ(parseDeviceChoice("gpu:007").gpu_index, 7);
}

TEST(DeviceChoice, AnythingElseIsAnErrorThatListsTheForms) {
  for (const char* bad : {"tpu", "", "GPU", "gpu:", "gpu:-1", "gpu:+1", "gpu:1x", "gpu: 1",
                          "gpu:1 ", "gpu:1.5", "gpu:99999", "cpu:0", "auto:1", "gpu1", ":1"}) {
    const std::string e = errorOf(bad);
    EXPECT_NE(e.find("device must be auto, cpu, gpu or gpu:N"), std::string::npos)
        << "'" << bad << "': " << e;
    EXPECT_NE(e.find(std::string("(got '") + bad + "')"), std::string::npos) << e;
  }
}

TEST(DeviceChoice, VisibleDevicesLeaveTheGpuAskedFor) {
  // Unset: the machine's number, as written.
  EXPECT_EQ(visibleDevicesFor(nullptr, 0), "0");
  EXPECT_EQ(visibleDevicesFor(nullptr, 3), "3");
  // Set: the list's N-th entry, an index or a UUID, without the spaces around it.
  EXPECT_EQ(visibleDevicesFor("2,3", 0), "2");
  EXPECT_EQ(visibleDevicesFor("2,3", 1), "3");
  EXPECT_EQ(visibleDevicesFor(" 5 , 4 ,1", 1), "4");
  EXPECT_EQ(visibleDevicesFor("GPU-8f2c1a2b-0c1d-4e5f-9a8b-7c6d5e4f3a2b,GPU-11111111", 1),
            "GPU-11111111");
  EXPECT_EQ(visibleDevicesFor("MIG-GPU-abc/1/0", 0), "MIG-GPU-abc/1/0");
}

TEST(DeviceChoice, AShorterListOrANegativeNumberIsAnError) {
  EXPECT_NE(visibleError("0,1", 2).find(
                "GPU 2 was asked for, but CUDA_VISIBLE_DEVICES='0,1' leaves 2 GPUs visible"),
            std::string::npos)
      << visibleError("0,1", 2);
  EXPECT_NE(visibleError("4", 1).find("leaves 1 GPU visible"), std::string::npos)
      << visibleError("4", 1);
  // An empty list hides every GPU.
  EXPECT_NE(visibleError("", 0).find("leaves 0 GPUs visible"), std::string::npos)
      << visibleError("", 0);
  EXPECT_NE(visibleError(",,", 0).find("leaves 0 GPUs visible"), std::string::npos);
  EXPECT_NE(visibleError(nullptr, -1).find(">= 0"), std::string::npos);
}
