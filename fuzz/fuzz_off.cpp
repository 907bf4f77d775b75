// libFuzzer target: readOFF (and loadFrame) on arbitrary bytes as a .off file.
#include "fuzz_frame.h"

PCL_ANIMSEG_FRAME_FUZZER("off", pcl_animseg::io::readOFF)
