# The programs' allocator. PCL_ANIMSEG_WITH_JEMALLOC (AUTO|ON|OFF, default AUTO): the tools and
# the benchmarks allocate through jemalloc with transparent huge pages (tools/jemalloc_conf.c),
# where libjemalloc-dev is installed. Measured on the GPU machine (docs/gpu.md, stop 45): the
# default pipeline at 800k points takes 0.08 s less (10 interleaved pairs; 130k -> 36k page
# faults); jemalloc without huge pages gains nothing, and glibc's malloc with them only through
# GLIBC_TUNABLES, which a program cannot set for itself. The libraries allocate through whatever
# allocator the program that loads them uses: a PCL pipeline of its own keeps its allocator. Off
# under the sanitizers, which bring their own.
set(PCL_ANIMSEG_WITH_JEMALLOC AUTO CACHE STRING "Link the programs with jemalloc (AUTO|ON|OFF)")
set_property(CACHE PCL_ANIMSEG_WITH_JEMALLOC PROPERTY STRINGS AUTO ON OFF)
add_library(pcl_animseg_allocator INTERFACE)
set(PCL_ANIMSEG_HAVE_JEMALLOC OFF)
if(PCL_ANIMSEG_SANITIZE OR PCL_ANIMSEG_BUILD_FUZZERS)
  if(PCL_ANIMSEG_WITH_JEMALLOC STREQUAL "ON")
    message(FATAL_ERROR "PCL_ANIMSEG_WITH_JEMALLOC=ON cannot be combined with the sanitizers")
  endif()
elseif(NOT PCL_ANIMSEG_WITH_JEMALLOC STREQUAL "OFF")
  find_library(PCL_ANIMSEG_JEMALLOC_LIBRARY NAMES jemalloc)
  if(PCL_ANIMSEG_JEMALLOC_LIBRARY)
    set(PCL_ANIMSEG_HAVE_JEMALLOC ON)
    target_sources(pcl_animseg_allocator INTERFACE ${PROJECT_SOURCE_DIR}/tools/jemalloc_conf.c)
    # Kept where a linker drops libraries none of whose symbols the program names.
    target_link_libraries(pcl_animseg_allocator INTERFACE "-Wl,--push-state,--no-as-needed"
                          ${PCL_ANIMSEG_JEMALLOC_LIBRARY} "-Wl,--pop-state")
    message(STATUS "pcl_animseg: programs allocate through jemalloc (${PCL_ANIMSEG_JEMALLOC_LIBRARY})")
  elseif(PCL_ANIMSEG_WITH_JEMALLOC STREQUAL "ON")
    message(FATAL_ERROR "PCL_ANIMSEG_WITH_JEMALLOC=ON but jemalloc was not found (libjemalloc-dev)")
  else()
    message(STATUS "pcl_animseg: jemalloc not found, the programs use the C library's allocator")
  endif()
endif()
