# visq_embed_files(TARGET NAMESPACE FILES...)
# Embeds text files (GLSL shaders) into TARGET as
#   std::string_view <NAMESPACE>::Find(std::string_view file_name)
# declared in the generated header "<TARGET>_embedded.h" (on TARGET's include
# path), so shaders live as real files beside their algorithm and ship
# inside the binary.
function(visq_embed_files target namespace)
  set(out_dir ${CMAKE_CURRENT_BINARY_DIR}/embedded)
  set(out_cpp ${out_dir}/${target}_embedded.cpp)
  set(out_h ${out_dir}/${target}_embedded.h)
  set(inputs)
  foreach(file ${ARGN})
    get_filename_component(abs ${file} ABSOLUTE)
    list(APPEND inputs ${abs})
  endforeach()
  # '|' separates the list on the command line: ';' would split the argument.
  string(REPLACE ";" "|" inputs_arg "${inputs}")
  add_custom_command(
    OUTPUT ${out_cpp} ${out_h}
    COMMAND ${CMAKE_COMMAND} -DOUT=${out_cpp} -DOUT_HEADER=${out_h} -DNAMESPACE=${namespace}
            "-DINPUTS=${inputs_arg}" -P ${PROJECT_SOURCE_DIR}/cmake/EmbedFilesScript.cmake
    DEPENDS ${inputs} ${PROJECT_SOURCE_DIR}/cmake/EmbedFilesScript.cmake
    COMMENT "Embedding ${target} resources"
    VERBATIM)
  target_sources(${target} PRIVATE ${out_cpp} ${out_h})
  target_include_directories(${target} PRIVATE ${out_dir})
endfunction()

# visq_gpu_algorithm(NAME): the library visq_gpu_NAME from the .cpp files and
# shaders (*.vert *.geom *.frag *.comp *.glsl) of the calling folder, with the
# shaders embedded as visq::gpu::NAME_shaders::Find (header
# "visq_gpu_NAME_embedded.h"). Linked into the visq_gpu umbrella.
function(visq_gpu_algorithm name)
  file(GLOB sources CONFIGURE_DEPENDS ${CMAKE_CURRENT_SOURCE_DIR}/*.cpp)
  file(GLOB shaders CONFIGURE_DEPENDS
    ${CMAKE_CURRENT_SOURCE_DIR}/*.vert ${CMAKE_CURRENT_SOURCE_DIR}/*.geom ${CMAKE_CURRENT_SOURCE_DIR}/*.frag
    ${CMAKE_CURRENT_SOURCE_DIR}/*.comp ${CMAKE_CURRENT_SOURCE_DIR}/*.glsl)
  if(NOT sources)
    message(STATUS "gpu/${name}: no sources yet, not built")
    return()
  endif()
  add_library(visq_gpu_${name} STATIC ${sources})
  target_include_directories(visq_gpu_${name} PRIVATE ${PROJECT_SOURCE_DIR}/gpu/src ${CMAKE_CURRENT_SOURCE_DIR})
  target_link_libraries(visq_gpu_${name} PUBLIC visq_gpu_core PRIVATE visq_warnings PkgConfig::EPOXY)
  if(shaders)
    visq_embed_files(visq_gpu_${name} visq::gpu::${name}_shaders ${shaders})
  endif()
  target_link_libraries(visq_gpu INTERFACE visq_gpu_${name})
endfunction()
