#pragma once
// One fuzzer per frame format: the raw reader, then (when it accepts the file) loadFrame, which is
// what animseg runs on every frame (NaN removal, mesh normals, kNN normal estimation).
#include <pcl_animseg/io/frame_readers.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/sequence.h>

#include "fuzz_common.h"

namespace fuzz {

template <typename Reader>
int fuzzFrame(const std::uint8_t* data, std::size_t size, const char* ext, Reader read) {
  const std::string path = writeInput(data, size, std::string("frame.") + ext);
  expectOnlyErrors([&] {
    const pcl_animseg::io::RawFrame raw = read(path);
    // Mesh/normal bookkeeping must be consistent whatever the input.
    for (const auto& f : raw.faces)
      for (auto v : f.vertices)
        if (v < 0 || static_cast<std::size_t>(v) >= raw.points.size()) std::abort();
    if (!raw.normals.empty() && raw.normals.size() != raw.points.size())
      std::abort();
    pcl_animseg::PointCloudSequence seq;
    pcl_animseg::io::LoadOptions options;
    options.min_points = 1;
    options.normal_k = 4;
    pcl_animseg::io::loadFrame(path, seq, options);
  });
  return 0;
}

}  // namespace fuzz

#define PCL_ANIMSEG_FRAME_FUZZER(EXT, READER)                                     \
  extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) { \
    return fuzz::fuzzFrame(data, size, EXT, [](const std::string& p) { return READER(p); }); \
  }
