# pcl_animseg_add_module(NAME [DEPS...]): library pcl_animseg_NAME from src/NAME/*.cpp.
set(PCL_ANIMSEG_MODULE_TARGETS "")
function(pcl_animseg_add_module name)
  file(GLOB _srcs CONFIGURE_DEPENDS ${PROJECT_SOURCE_DIR}/src/${name}/*.cpp)
  set(_target pcl_animseg_${name})
  set(_deps "")
  foreach(_d ${ARGN})
    list(APPEND _deps pcl_animseg_${_d})
  endforeach()
  if(_srcs)
    add_library(${_target} SHARED ${_srcs})
    target_include_directories(${_target} PUBLIC
      $<BUILD_INTERFACE:${PROJECT_SOURCE_DIR}/include>
      $<INSTALL_INTERFACE:${CMAKE_INSTALL_INCLUDEDIR}>)
    target_include_directories(${_target} SYSTEM PUBLIC ${PCL_INCLUDE_DIRS})
    target_compile_definitions(${_target} PUBLIC ${PCL_DEFINITIONS})
    target_link_libraries(${_target} PUBLIC ${_deps} ${PCL_ANIMSEG_PCL_LIBS} Eigen3::Eigen
                          OpenMP::OpenMP_CXX Boost::program_options PRIVATE FLANN::FLANN)
    set_target_properties(${_target} PROPERTIES
      LIBRARY_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/lib
      VERSION ${PROJECT_VERSION} SOVERSION ${PROJECT_VERSION_MAJOR}.${PROJECT_VERSION_MINOR}
      EXPORT_NAME ${name})
  else()
    add_library(${_target} INTERFACE)
    target_include_directories(${_target} INTERFACE
      $<BUILD_INTERFACE:${PROJECT_SOURCE_DIR}/include>
      $<INSTALL_INTERFACE:${CMAKE_INSTALL_INCLUDEDIR}>)
    target_link_libraries(${_target} INTERFACE ${_deps})
    set_target_properties(${_target} PROPERTIES EXPORT_NAME ${name})
  endif()
  add_library(pcl_animseg::${name} ALIAS ${_target})
  set(PCL_ANIMSEG_MODULE_TARGETS ${PCL_ANIMSEG_MODULE_TARGETS} ${_target} PARENT_SCOPE)
endfunction()
