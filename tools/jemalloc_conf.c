/* jemalloc's options for the pcl_animseg programs (cmake/Allocator.cmake), read by jemalloc at
 * its start; MALLOC_CONF in the environment still overrides them. Transparent huge pages for the
 * heap and jemalloc's own metadata: the pipeline touches about 0.5 GB at 800k points, and in 4 KiB
 * pages its first touches (130k page faults) and TLB misses cost 0.08-0.11 s of a 1.2 s run on
 * the GPU machine's 16 threads (docs/gpu.md, stop 45). Where the kernel's THP mode is "never",
 * jemalloc leaves them off. */
const char* malloc_conf = "thp:always,metadata_thp:always";
