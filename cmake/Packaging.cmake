# `cpack -G DEB` (run in the build directory after building): a Debian package "pcl-animseg"
# with the libraries, headers, CMake package config and tools, installed under /usr.
set(CPACK_PACKAGE_NAME pcl-animseg)
set(CPACK_PACKAGE_VENDOR "pcl_animseg")
set(CPACK_PACKAGE_VERSION ${PROJECT_VERSION})
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY
    "Decomposition of animated point-cloud/mesh sequences into near-rigid parts (PCL)")
set(CPACK_PACKAGE_CONTACT "pcl_animseg maintainers <pcl-animseg@users.noreply.github.com>")
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_GENERATOR DEB)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)
set(CPACK_DEBIAN_PACKAGE_SECTION science)
# The headers and the CMake config need PCL's development files (which bring Eigen, Boost, VTK and
# libpng); the libraries need OpenMP's runtime.
set(CPACK_DEBIAN_PACKAGE_DEPENDS
    "libpcl-dev (>= 1.13), libeigen3-dev, libboost-program-options-dev, libgomp1")
if(PCL_ANIMSEG_HAVE_JEMALLOC)
  string(APPEND CPACK_DEBIAN_PACKAGE_DEPENDS ", libjemalloc2")  # the programs' allocator
endif()
if(PCL_ANIMSEG_HAVE_CUDA)
  set(CPACK_DEBIAN_PACKAGE_RECOMMENDS "nvidia-cuda-toolkit")
endif()
# Build trees are not sources: keep cpack's source generator from packing them.
set(CPACK_SOURCE_IGNORE_FILES "/build[^/]*/" "/\\\\.git/" "/out/")
include(CPack)
