# Read by cpack after CPackConfig.cmake (CPACK_PROJECT_CONFIG_FILE,
# cmake/Package.cmake): VISQ_CPACK_COMPONENTS="server;client" in the
# environment makes only those packages.
if(DEFINED ENV{VISQ_CPACK_COMPONENTS})
  set(CPACK_COMPONENTS_ALL $ENV{VISQ_CPACK_COMPONENTS})
endif()
