# Installation (`cmake --install build --prefix PREFIX`) and the CMake package of the client
# library, `find_package(crowdmap)` with target crowdmap::client (see examples/consumer/):
#   bin/                      mapd, mapctl, mapsim
#   lib/                      the client library and the static libraries it is made of
#   include/crowdmap/         their headers (client/api, core, server/{grpc_status,wire_convert,...}.h)
#                             and the generated mapservice/v1/*.pb.h
#   share/crowdmap/proto/     the wire contract, mapservice/v1/*.proto
#   lib/cmake/crowdmap/       crowdmap-config.cmake, its version and the exported targets
include(GNUInstallDirs)
include(CMakePackageConfigHelpers)

set(CROWDMAP_INSTALL_INCLUDEDIR ${CMAKE_INSTALL_INCLUDEDIR}/crowdmap)
set(CROWDMAP_INSTALL_CMAKEDIR ${CMAKE_INSTALL_LIBDIR}/cmake/crowdmap)

install(TARGETS mapd mapctl mapsim RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})

install(DIRECTORY ${PROJECT_SOURCE_DIR}/proto/mapservice DESTINATION ${CMAKE_INSTALL_DATADIR}/crowdmap/proto
  FILES_MATCHING PATTERN "*.proto")

# The client library and what it links (static libraries, exported as crowdmap::<name without
# the crowdmap_ prefix>). Their include directories point into the source and build trees; for
# the export they are wrapped so that an installed consumer sees include/crowdmap instead.
set(crowdmap_exported crowdmap_client crowdmap_wire crowdmap_proto crowdmap_map crowdmap_sparse_threads crowdmap_model crowdmap_geo
  crowdmap_localization crowdmap_estimation)
foreach(target IN LISTS crowdmap_exported)
  get_target_property(dirs ${target} INTERFACE_INCLUDE_DIRECTORIES)
  set(wrapped "$<INSTALL_INTERFACE:${CROWDMAP_INSTALL_INCLUDEDIR}>")
  if(dirs)
    foreach(dir IN LISTS dirs)
      if(dir MATCHES "^(${PROJECT_SOURCE_DIR}|${PROJECT_BINARY_DIR})")
        list(APPEND wrapped "$<BUILD_INTERFACE:${dir}>")
      else()
        list(APPEND wrapped "${dir}")
      endif()
    endforeach()
  endif()
  set_target_properties(${target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${wrapped}")
  string(REGEX REPLACE "^crowdmap_" "" export_name ${target})
  set_target_properties(${target} PROPERTIES EXPORT_NAME ${export_name})
endforeach()
install(TARGETS ${crowdmap_exported} EXPORT crowdmapTargets
  ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR}
  LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR})
install(EXPORT crowdmapTargets NAMESPACE crowdmap:: DESTINATION ${CROWDMAP_INSTALL_CMAKEDIR})

install(DIRECTORY ${PROJECT_SOURCE_DIR}/core DESTINATION ${CROWDMAP_INSTALL_INCLUDEDIR} FILES_MATCHING PATTERN "*.h")
install(DIRECTORY ${PROJECT_SOURCE_DIR}/client/api DESTINATION ${CROWDMAP_INSTALL_INCLUDEDIR}/client
  FILES_MATCHING PATTERN "*.h")
install(FILES ${PROJECT_SOURCE_DIR}/server/grpc_status.h ${PROJECT_SOURCE_DIR}/server/wire_convert.h
  ${PROJECT_SOURCE_DIR}/server/geojson.h DESTINATION ${CROWDMAP_INSTALL_INCLUDEDIR}/server)
install(FILES ${PROJECT_SOURCE_DIR}/server/storage/map_store.h DESTINATION ${CROWDMAP_INSTALL_INCLUDEDIR}/server/storage)
install(DIRECTORY ${PROJECT_BINARY_DIR}/proto/mapservice DESTINATION ${CROWDMAP_INSTALL_INCLUDEDIR}
  FILES_MATCHING PATTERN "*.pb.h")

configure_package_config_file(${PROJECT_SOURCE_DIR}/cmake/crowdmap-config.cmake.in
  ${PROJECT_BINARY_DIR}/crowdmap-config.cmake INSTALL_DESTINATION ${CROWDMAP_INSTALL_CMAKEDIR})
write_basic_package_version_file(${PROJECT_BINARY_DIR}/crowdmap-config-version.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/crowdmap-config.cmake ${PROJECT_BINARY_DIR}/crowdmap-config-version.cmake
  DESTINATION ${CROWDMAP_INSTALL_CMAKEDIR})

# Install into a temporary prefix, build examples/consumer against it, and run it and
# examples/python/map_info.py against the installed mapd.
if(CROWDMAP_BUILD_TESTS)
  add_test(NAME packaging_install_consumer
    COMMAND /usr/bin/python3 ${PROJECT_SOURCE_DIR}/tests/packaging/packaging_test.py
            --build ${PROJECT_BINARY_DIR} --source ${PROJECT_SOURCE_DIR})
  set_tests_properties(packaging_install_consumer PROPERTIES TIMEOUT 600)
endif()
