# The floors of the house, checked on every include of the source tree
# (cmake -P, run by ctest as LayerRules). Each rule names what may not be
# included from where, and why; a violation prints the file, the include and
# the rule, and fails.
#   lib/      the ground floor: the scene model and the CPU algorithms that
#             gpu/, server/ and client/ stand on. No GL, no gRPC, nothing above.
#   gpu/      every GL call. Stands on lib/; never on server/ or client/.
#   client/   the C++ client. Stands on lib/ and the generated proto; never
#             on server/ or gpu/.
#   server/   core/ (the query API, no protobuf, no GL) and service/ (the
#             gRPC transport) over everything below.
cmake_minimum_required(VERSION 3.25)
if(NOT SOURCE_DIR)
  message(FATAL_ERROR "usage: cmake -DSOURCE_DIR=<checkout> -P check_layers.cmake")
endif()

set(violations 0)
# A quoted include resolves against lib/, server/ or gpu/include: which
# floor it lands on is what counts.
function(floor_of include out)
  if(EXISTS "${SOURCE_DIR}/server/${include}")
    set(${out} server PARENT_SCOPE)
  elseif(EXISTS "${SOURCE_DIR}/gpu/include/${include}")
    set(${out} gpu PARENT_SCOPE)
  elseif(EXISTS "${SOURCE_DIR}/lib/${include}")
    set(${out} lib PARENT_SCOPE)
  else()
    set(${out} "" PARENT_SCOPE)
  endif()
endfunction()

function(check_tree folder allowed_floors forbidden_system_regex why)
  file(GLOB_RECURSE files RELATIVE "${SOURCE_DIR}" "${SOURCE_DIR}/${folder}/*.h" "${SOURCE_DIR}/${folder}/*.cpp")
  foreach(file IN LISTS files)
    file(STRINGS "${SOURCE_DIR}/${file}" lines REGEX "^[ \t]*#[ \t]*include")
    foreach(line IN LISTS lines)
      if(line MATCHES "#[ \t]*include[ \t]*\"([^\"]+)\"")
        set(include "${CMAKE_MATCH_1}")
        floor_of("${include}" floor)
        if(floor AND NOT floor IN_LIST allowed_floors)
          message("${file}: #include \"${include}\" reaches ${floor}/ (${why})")
          math(EXPR violations "${violations} + 1")
        endif()
      endif()
      if(forbidden_system_regex AND line MATCHES "#[ \t]*include[ \t]*[<\"](${forbidden_system_regex})")
        message("${file}: ${line} (${why})")
        math(EXPR violations "${violations} + 1")
      endif()
    endforeach()
  endforeach()
  set(violations ${violations} PARENT_SCOPE)
endfunction()

set(gl_headers "epoxy/|EGL/|GL/|GLES")
set(rpc_headers "grpc|google/protobuf|visq/v1/|.*\\.pb\\.h")
check_tree(lib "lib" "${gl_headers}|${rpc_headers}"
           "lib/ is the ground floor: no GL, no gRPC, nothing from gpu/ or server/")
check_tree(gpu "lib;gpu" "${rpc_headers}" "gpu/ stands on lib/ only and knows no gRPC")
check_tree(client "lib" "${gl_headers}" "client/ stands on lib/ and the proto, never on server/ or gpu/")
check_tree(server/core "lib;gpu;server" "${gl_headers}|${rpc_headers}"
           "core/ is the query API: no protobuf, no GL (GPU work goes through gpu/)")

if(violations GREATER 0)
  message(FATAL_ERROR "${violations} include(s) break the floors of the house")
endif()
message("the floors hold: lib/ < gpu/ < server/, lib/ < client/, no GL outside gpu/, no gRPC below the service")
