// libFuzzer target: readPLY (and loadFrame) on arbitrary bytes as a .ply file.
#include "fuzz_frame.h"

PCL_ANIMSEG_FRAME_FUZZER("ply", pcl_animseg::io::readPLY)
