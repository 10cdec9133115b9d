# What `cmake --install build --prefix P` puts where: the two binaries, and
# the C++ client as a package of its own (find_package(visq CONFIG) with
# visq::client, or pkg-config visq-client), with the .proto files for other
# languages.
#   P/bin/visq-server, P/bin/visq
#   P/include/visq/       visq_client.h, the public floor (status.h,
#                         obscurance_partial.h), the generated visq/v1 and
#                         grpc/health/v1 headers
#   P/lib/                libvisq_client.a, libvisq_proto.a, cmake/visq/, pkgconfig/visq-client.pc
#   P/share/visq/proto/   visq/v1/visq.proto, grpc/health/v1/health.proto
include(CMakePackageConfigHelpers)
set(visq_cmake_dir ${CMAKE_INSTALL_LIBDIR}/cmake/visq)

# Each rule names its component, the Debian package it goes into
# (cmake/Package.cmake): server (visq-server), client (visq-client), dev
# (libvisq-client-dev), python (python3-visq). A plain cmake --install
# installs them all.
install(TARGETS visq-server RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR} COMPONENT server)
install(TARGETS visq RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR} COMPONENT client)

# The generated library's headers, under include/visq (proto/CMakeLists.txt
# gives the target its installed include folders).
set(gen ${VISQ_PROTO_GEN_DIR})
set(include_visq ${CMAKE_INSTALL_INCLUDEDIR}/visq)
install(FILES ${gen}/visq/v1/visq.pb.h ${gen}/visq/v1/visq.grpc.pb.h DESTINATION ${include_visq}/v1 COMPONENT dev)
install(FILES ${gen}/grpc/health/v1/health.pb.h ${gen}/grpc/health/v1/health.grpc.pb.h
        DESTINATION ${include_visq}/grpc/health/v1 COMPONENT dev)
set(proto_share ${CMAKE_INSTALL_DATADIR}/visq/proto)
install(FILES ${PROJECT_SOURCE_DIR}/proto/visq/v1/visq.proto DESTINATION ${proto_share}/visq/v1 COMPONENT dev)
install(FILES ${PROJECT_SOURCE_DIR}/proto/grpc/health/v1/health.proto DESTINATION ${proto_share}/grpc/health/v1 COMPONENT dev)

# The client, its headers and the public floor's.
install(TARGETS visq_client visq_proto visq_public EXPORT visqTargets ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR} COMPONENT dev)
# The client's public headers are the .h files directly in client/ (cli/ is
# the tool's); tests/layout checks that these include only installed files.
file(GLOB visq_client_headers CONFIGURE_DEPENDS ${PROJECT_SOURCE_DIR}/client/*.h)
install(FILES ${visq_client_headers} DESTINATION ${include_visq} COMPONENT dev)
install(DIRECTORY ${PROJECT_SOURCE_DIR}/include/visq DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}
        COMPONENT dev FILES_MATCHING PATTERN "*.h")

# The CMake package: visqConfig.cmake finds gRPC, protobuf and abseil, then
# defines visq::client (with visq::proto and visq::public under it).
install(EXPORT visqTargets NAMESPACE visq:: FILE visqTargets.cmake DESTINATION ${visq_cmake_dir} COMPONENT dev)
configure_package_config_file(${CMAKE_CURRENT_LIST_DIR}/visqConfig.cmake.in
                              ${PROJECT_BINARY_DIR}/visqConfig.cmake INSTALL_DESTINATION ${visq_cmake_dir})
# 0.x: a minor version may change the API.
write_basic_package_version_file(${PROJECT_BINARY_DIR}/visqConfigVersion.cmake COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/visqConfig.cmake ${PROJECT_BINARY_DIR}/visqConfigVersion.cmake
        DESTINATION ${visq_cmake_dir} COMPONENT dev)

# pkg-config: paths relative to the .pc file itself, so the tree stays right
# wherever --prefix puts it (the prefix is chosen at install time, not at
# configure time).
file(RELATIVE_PATH visq_pc_to_prefix /prefix/${CMAKE_INSTALL_LIBDIR}/pkgconfig /prefix)
string(REGEX REPLACE "/$" "" visq_pc_to_prefix "${visq_pc_to_prefix}")
configure_file(${CMAKE_CURRENT_LIST_DIR}/visq-client.pc.in ${PROJECT_BINARY_DIR}/visq-client.pc @ONLY)
install(FILES ${PROJECT_BINARY_DIR}/visq-client.pc DESTINATION ${CMAKE_INSTALL_LIBDIR}/pkgconfig COMPONENT dev)
