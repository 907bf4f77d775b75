// libFuzzer target: listSequence on arbitrary bytes as a list file. The list lives next to a few
// real (empty) frame files, so inputs can name existing and missing, relative and odd paths.
#include <pcl_animseg/io/sequence_io.h>

#include "fuzz_common.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const bool frames = [] {
    for (const char* name : {"a.xyz", "b.ply", "c.OBJ", "d.txt"}) std::ofstream(fuzz::workDir() / name);
    std::filesystem::create_directories(fuzz::workDir() / "sub");
    std::ofstream(fuzz::workDir() / "sub" / "e.pcd");
    return true;
  }();
  (void)frames;
  const std::string path = fuzz::writeInput(data, size, "frames.txt");
  fuzz::expectOnlyErrors([&] {
    const auto list = pcl_animseg::io::listSequence(path);
    if (list.empty()) std::abort();  // documented: a list naming no frames is an Error
  });
  return 0;
}
