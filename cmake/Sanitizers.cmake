# PCL_ANIMSEG_SANITIZE=ON: AddressSanitizer + UndefinedBehaviorSanitizer for everything this
# project compiles (PCL, Boost and the system libraries stay uninstrumented, which is fine: ASan
# still catches our out-of-bounds accesses into their buffers). Included before the modules are
# declared, so the flags reach every target. Use a separate build directory (scripts/asan.sh).
option(PCL_ANIMSEG_SANITIZE "Build with AddressSanitizer and UndefinedBehaviorSanitizer" OFF)
if(PCL_ANIMSEG_SANITIZE)
  if(NOT CMAKE_CXX_COMPILER_ID MATCHES "GNU|Clang")
    message(FATAL_ERROR "PCL_ANIMSEG_SANITIZE needs GCC or Clang")
  endif()
  # -fno-sanitize-recover: a UBSan report fails the test instead of scrolling by.
  set(_pcl_animseg_san -fsanitize=address,undefined -fno-sanitize-recover=undefined
                       -fno-omit-frame-pointer)
  add_compile_options("$<$<COMPILE_LANGUAGE:CXX>:${_pcl_animseg_san}>")
  add_link_options(-fsanitize=address,undefined)
  message(STATUS "pcl_animseg: building with ASan + UBSan")
endif()
