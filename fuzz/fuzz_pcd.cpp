// libFuzzer target: readPCD (and loadFrame) on arbitrary bytes as a .pcd file.
#include "fuzz_frame.h"

PCL_ANIMSEG_FRAME_FUZZER("pcd", pcl_animseg::io::readPCD)
