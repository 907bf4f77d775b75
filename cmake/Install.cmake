include(CMakePackageConfigHelpers)
set(_targets pcl_animseg ${PCL_ANIMSEG_MODULE_TARGETS})
if(TARGET pcl_animseg_gpu)
  list(APPEND _targets pcl_animseg_gpu)
endif()
install(TARGETS ${_targets} EXPORT pcl_animsegTargets
        LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR}
        ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR}
        RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})
install(DIRECTORY include/pcl_animseg DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})
if(EXISTS ${PROJECT_SOURCE_DIR}/gpu/include/pcl_animseg)
  install(DIRECTORY gpu/include/pcl_animseg DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})
endif()
set(_cfgdir ${CMAKE_INSTALL_LIBDIR}/cmake/pcl_animseg)
install(EXPORT pcl_animsegTargets NAMESPACE pcl_animseg:: DESTINATION ${_cfgdir})
configure_package_config_file(cmake/pcl_animsegConfig.cmake.in
  ${PROJECT_BINARY_DIR}/pcl_animsegConfig.cmake INSTALL_DESTINATION ${_cfgdir})
write_basic_package_version_file(${PROJECT_BINARY_DIR}/pcl_animsegConfigVersion.cmake
  COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/pcl_animsegConfig.cmake
              ${PROJECT_BINARY_DIR}/pcl_animsegConfigVersion.cmake DESTINATION ${_cfgdir})
install(FILES README.md DESTINATION ${CMAKE_INSTALL_DOCDIR} OPTIONAL)
