# cpack -G DEB, then the package is unpacked with dpkg-deb -x into a temporary root and a tool is
# run from there (LD_LIBRARY_PATH pointing into the root, as nothing is installed system-wide).
file(REMOVE_RECURSE ${WORK_DIR})
file(MAKE_DIRECTORY ${WORK_DIR})

# cpack first builds the tree's "preinstall" target: a no-op here, as tests run on a built tree.
execute_process(COMMAND ${CPACK} -G DEB --config ${BINARY_DIR}/CPackConfig.cmake -B ${WORK_DIR}/pkg
                WORKING_DIRECTORY ${BINARY_DIR}
                RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "cpack failed (${rc}):\n${out}\n${err}")
endif()
file(GLOB debs ${WORK_DIR}/pkg/*.deb)
list(LENGTH debs n)
if(NOT n EQUAL 1)
  message(FATAL_ERROR "expected one .deb in ${WORK_DIR}/pkg, found ${n}: ${debs}")
endif()

execute_process(COMMAND ${DPKG_DEB} --field ${debs} Package Depends RESULT_VARIABLE rc
                OUTPUT_VARIABLE fields)
if(NOT rc EQUAL 0 OR NOT fields MATCHES "Package: pcl-animseg" OR NOT fields MATCHES "libpcl-dev")
  message(FATAL_ERROR "unexpected control fields (${rc}):\n${fields}")
endif()

execute_process(COMMAND ${DPKG_DEB} -x ${debs} ${WORK_DIR}/root RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "dpkg-deb -x failed: ${rc}")
endif()
set(root ${WORK_DIR}/root/usr)
foreach(f include/pcl_animseg/sequence.h include/pcl_animseg/visualization/contact_sheet.h
          ${LIBDIR}/cmake/pcl_animseg/pcl_animsegConfig.cmake
          ${LIBDIR}/cmake/pcl_animseg/pcl_animsegTargets.cmake bin/animseg)
  if(NOT EXISTS ${root}/${f})
    message(FATAL_ERROR "the package lacks /usr/${f}")
  endif()
endforeach()
file(GLOB libs ${root}/${LIBDIR}/libpcl_animseg_common.so*)
if(NOT libs)
  message(FATAL_ERROR "the package lacks /usr/${LIBDIR}/libpcl_animseg_common.so")
endif()

set(ENV{LD_LIBRARY_PATH} ${root}/${LIBDIR})
foreach(tool animseg animseg_view)
  if(NOT EXISTS ${root}/bin/${tool})
    continue()
  endif()
  execute_process(COMMAND ${root}/bin/${tool} --help RESULT_VARIABLE rc OUTPUT_VARIABLE out
                  ERROR_VARIABLE err)
  if(NOT rc EQUAL 0 OR NOT out MATCHES "--input")
    message(FATAL_ERROR "${tool} --help from the unpacked package failed (${rc}):\n${out}\n${err}")
  endif()
  # The libraries it runs with must be the package's, not the build tree's.
  execute_process(COMMAND ldd ${root}/bin/${tool} OUTPUT_VARIABLE deps RESULT_VARIABLE rc)
  if(rc EQUAL 0 AND NOT deps MATCHES "${root}/${LIBDIR}/libpcl_animseg_common")
    message(FATAL_ERROR "${tool} does not load libpcl_animseg_common from the package:\n${deps}")
  endif()
  # A program linked with jemalloc (cmake/Allocator.cmake) needs the package to depend on it.
  if(rc EQUAL 0 AND deps MATCHES "libjemalloc" AND NOT fields MATCHES "libjemalloc2")
    message(FATAL_ERROR "${tool} loads jemalloc, which the package does not depend on:\n${fields}")
  endif()
  message(STATUS "${tool} --help runs from the unpacked package")
endforeach()
