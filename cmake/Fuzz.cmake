# PCL_ANIMSEG_BUILD_FUZZERS=ON (Clang only): libFuzzer targets fuzz/fuzz_<name>.cpp, one per reader,
# in a build directory of their own (scripts/fuzz.sh). The common and io sources are compiled
# again into a static library with coverage instrumentation and ASan + UBSan; PCL, Boost and the
# system libraries (built by GCC) are linked as they are.
option(PCL_ANIMSEG_BUILD_FUZZERS "Build the libFuzzer targets (Clang only)" OFF)
if(PCL_ANIMSEG_BUILD_FUZZERS)
  if(NOT CMAKE_CXX_COMPILER_ID STREQUAL "Clang")
    message(FATAL_ERROR "PCL_ANIMSEG_BUILD_FUZZERS needs Clang (configure with CXX=clang++)")
  endif()
  set(_san address,undefined)
  file(GLOB _fuzz_lib_srcs CONFIGURE_DEPENDS ${PROJECT_SOURCE_DIR}/src/common/*.cpp
       ${PROJECT_SOURCE_DIR}/src/io/*.cpp)
  # fuzz_config includes tool_common.cpp itself (to reach its internal parser).
  list(FILTER _fuzz_lib_srcs EXCLUDE REGEX "/tool_common\\.cpp$")
  add_library(pcl_animseg_fuzz_io STATIC ${_fuzz_lib_srcs})
  target_include_directories(pcl_animseg_fuzz_io PUBLIC ${PROJECT_SOURCE_DIR}/include)
  target_include_directories(pcl_animseg_fuzz_io SYSTEM PUBLIC ${PCL_INCLUDE_DIRS})
  target_compile_definitions(pcl_animseg_fuzz_io PUBLIC ${PCL_DEFINITIONS})
  target_compile_options(pcl_animseg_fuzz_io PUBLIC -g -fno-omit-frame-pointer
                         -fsanitize=fuzzer-no-link,${_san} -fno-sanitize-recover=undefined)
  target_link_libraries(pcl_animseg_fuzz_io PUBLIC ${PCL_ANIMSEG_PCL_LIBS} Eigen3::Eigen
                        OpenMP::OpenMP_CXX Boost::program_options FLANN::FLANN)
  file(GLOB _fuzzers CONFIGURE_DEPENDS ${PROJECT_SOURCE_DIR}/fuzz/fuzz_*.cpp)
  set(PCL_ANIMSEG_FUZZ_TARGETS "")
  foreach(_src ${_fuzzers})
    get_filename_component(_name ${_src} NAME_WE)
    add_executable(${_name} ${_src})
    target_compile_options(${_name} PRIVATE -fsanitize=fuzzer,${_san})
    target_link_options(${_name} PRIVATE -fsanitize=fuzzer,${_san})
    target_link_libraries(${_name} PRIVATE pcl_animseg_fuzz_io)
    set_target_properties(${_name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/fuzz)
    list(APPEND PCL_ANIMSEG_FUZZ_TARGETS ${_name})
  endforeach()
  add_custom_target(fuzzers DEPENDS ${PCL_ANIMSEG_FUZZ_TARGETS})
  message(STATUS "pcl_animseg: fuzzers ${PCL_ANIMSEG_FUZZ_TARGETS}")
endif()
