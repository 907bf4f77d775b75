// libFuzzer target: readXYZ (and loadFrame) on arbitrary bytes as a .xyz file.
#include "fuzz_frame.h"

PCL_ANIMSEG_FRAME_FUZZER("xyz", pcl_animseg::io::readXYZ)
