// libFuzzer target: readOBJ (and loadFrame) on arbitrary bytes as a .obj file.
#include "fuzz_frame.h"

PCL_ANIMSEG_FRAME_FUZZER("obj", pcl_animseg::io::readOBJ)
