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
#   include/  the public floor under all of them (Status, the obscurance
#             partial sums): standard C++ and abseil only.
# The installed client (client/*.h, include/, the generated proto) is
# checked as a whole: a program built against it has no source tree, so its
# headers include only each other and gRPC, protobuf, abseil and the
# standard library.
cmake_minimum_required(VERSION 3.25)
if(NOT SOURCE_DIR)
  message(FATAL_ERROR "usage: cmake -DSOURCE_DIR=<checkout> -P check_layers.cmake")
endif()

set(violations 0)
# Prints one broken rule and counts it (a macro: it counts in the caller's scope).
macro(violation text)
  message("${text}")
  math(EXPR violations "${violations} + 1")
endmacro()
# A quoted include resolves against lib/, server/ or gpu/include: which
# floor it lands on is what counts.
function(floor_of include out)
  if(EXISTS "${SOURCE_DIR}/server/${include}")
    set(${out} server PARENT_SCOPE)
  elseif(EXISTS "${SOURCE_DIR}/gpu/include/${include}")
    set(${out} gpu PARENT_SCOPE)
  elseif(EXISTS "${SOURCE_DIR}/lib/${include}")
    set(${out} lib PARENT_SCOPE)
  elseif(EXISTS "${SOURCE_DIR}/include/${include}")
    set(${out} public PARENT_SCOPE)
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
          violation("${file}: #include \"${include}\" reaches ${floor}/ (${why})")
        endif()
      endif()
      if(forbidden_system_regex AND line MATCHES "#[ \t]*include[ \t]*[<\"](${forbidden_system_regex})")
        violation("${file}: ${line} (${why})")
      endif()
    endforeach()
  endforeach()
  set(violations ${violations} PARENT_SCOPE)
endfunction()

set(gl_headers "epoxy/|EGL/|GL/|GLES")
set(rpc_headers "grpc|google/protobuf|visq/v1/|.*\\.pb\\.h")
check_tree(include "public" "${gl_headers}|${rpc_headers}"
           "include/ is the public floor: nothing from lib/, gpu/ or server/")
check_tree(lib "lib;public" "${gl_headers}|${rpc_headers}"
           "lib/ is the ground floor: no GL, no gRPC, nothing from gpu/ or server/")
check_tree(gpu "lib;gpu;public" "${rpc_headers}" "gpu/ stands on lib/ only and knows no gRPC")
check_tree(client "lib;public" "${gl_headers}" "client/ stands on lib/ and the proto, never on server/ or gpu/")
check_tree(server/core "lib;gpu;server;public" "${gl_headers}|${rpc_headers}"
           "core/ is the query API: no protobuf, no GL (GPU work goes through gpu/)")

# The transport names no GPU type: what it converts (requests, results,
# bands, timings, deadlines, the device record) is lib/'s vocabulary, and the
# GPU work itself goes through the core (issue 48 §1). A text check: a
# `gpu::` anywhere in server/service/, comments included, is a violation.
function(check_no_name folder name why)
  file(GLOB_RECURSE files RELATIVE "${SOURCE_DIR}" "${SOURCE_DIR}/${folder}/*.h" "${SOURCE_DIR}/${folder}/*.cpp")
  foreach(file IN LISTS files)
    file(STRINGS "${SOURCE_DIR}/${file}" lines REGEX "${name}")
    foreach(line IN LISTS lines)
      string(STRIP "${line}" line)
      violation("${file}: ${line} (${why})")
    endforeach()
  endforeach()
  set(violations ${violations} PARENT_SCOPE)
endfunction()
check_no_name(server/service "(^|[^A-Za-z0-9_])gpu::"
              "server/service/ names no gpu:: type: requests and answers are lib/'s, GPU work goes through the core")

# The installed headers (cmake/Install.cmake installs client/*.h and
# include/visq/): every quoted include is another installed header or a
# generated proto header, every <include> a standard header or one of
# `system_regex`'s packages; nothing reaches lib/, gpu/ or server/.
function(check_installed files system_regex why)
  foreach(file IN LISTS files)
    file(STRINGS "${SOURCE_DIR}/${file}" lines REGEX "^[ \t]*#[ \t]*include")
    foreach(line IN LISTS lines)
      set(bad "")
      if(line MATCHES "#[ \t]*include[ \t]*\"([^\"]+)\"")
        set(include "${CMAKE_MATCH_1}")
        floor_of("${include}" floor)
        if(floor AND NOT floor STREQUAL "public")
          set(bad "reaches ${floor}/")
        elseif(NOT EXISTS "${SOURCE_DIR}/include/${include}" AND NOT include MATCHES "\\.pb\\.h$" AND
               NOT (include MATCHES "^[^/]+$" AND EXISTS "${SOURCE_DIR}/client/${include}"))
          set(bad "is not installed")
        endif()
      elseif(line MATCHES "#[ \t]*include[ \t]*<([^>]+)>")
        set(include "${CMAKE_MATCH_1}")
        floor_of("${include}" floor)
        if(floor)
          set(bad "reaches ${floor}/")
        elseif(NOT include MATCHES "^(${system_regex}|[a-z_]+)$")
          set(bad "needs a package the installed config does not find")
        endif()
      endif()
      if(bad)
        violation("${file}: ${line} ${bad} (${why})")
      endif()
    endforeach()
  endforeach()
  set(violations ${violations} PARENT_SCOPE)
endfunction()
file(GLOB_RECURSE public_headers RELATIVE "${SOURCE_DIR}" "${SOURCE_DIR}/include/*.h")
file(GLOB client_headers RELATIVE "${SOURCE_DIR}" "${SOURCE_DIR}/client/*.h")
check_installed("${public_headers}" "absl/.+" "the public floor is standard C++ and abseil only")
check_installed("${client_headers}" "(absl|grpc|grpcpp|google/protobuf)/.+"
                "the installed client needs only the installed tree, gRPC, protobuf and abseil")

# Each folder's code lives in its own namespace, so a name says its floor
# at the call site (core::Engine in the transport, exact::TreeOptions in the
# core). lib/common and lib/scene are the shared vocabulary, in visq itself.
function(check_namespace folder expected)
  file(GLOB files RELATIVE "${SOURCE_DIR}" "${SOURCE_DIR}/${folder}/*.h" "${SOURCE_DIR}/${folder}/*.cpp")
  foreach(file IN LISTS files)
    file(STRINGS "${SOURCE_DIR}/${file}" lines REGEX "^namespace visq[a-z_:]* {")
    foreach(line IN LISTS lines)
      if(NOT line MATCHES "^namespace ${expected}(::[a-z_:]+)? {")
        violation("${file}: ${line} (code in ${folder}/ lives in ${expected})")
      endif()
    endforeach()
  endforeach()
  set(violations ${violations} PARENT_SCOPE)
endfunction()
foreach(rule IN ITEMS "lib/exact=visq::exact" "lib/obscurance=visq::obscurance" "lib/raycast=visq::raycast"
                      "lib/sampling=visq::sampling" "lib/voxel_reference=visq::voxel_reference"
                      "lib/volumetric_shadows=visq::volumetric_shadows" "gpu/src=visq::gpu"
                      "gpu/include/visq/gpu=visq::gpu" "gpu/hidden_sample_map=visq::gpu" "gpu/slicemap=visq::gpu"
                      "gpu/obscurance=visq::gpu" "gpu/volumetric_shadows=visq::gpu" "server/core=visq::core"
                      "server/service=visq::service" "client=visq::client" "client/cli=visq::cli")
  string(REPLACE "=" ";" pair "${rule}")
  list(GET pair 0 folder)
  list(GET pair 1 expected)
  check_namespace("${folder}" "${expected}")
endforeach()

if(violations GREATER 0)
  message(FATAL_ERROR "${violations} violation(s) break the floors of the house")
endif()
message("the floors hold: include/ < lib/ < gpu/ < server/, lib/ < client/, no GL outside gpu/, no gRPC below the service, "
        "the installed client headers self-contained, each folder in its namespace, no gpu:: in the transport")
