# visq_embed_files(TARGET NAMESPACE FILES...)
# Embeds text files (GLSL shaders) into TARGET as
#   std::string_view <NAMESPACE>::Find(std::string_view file_name)
# so shaders live as real files beside their algorithm and ship inside the binary.
function(visq_embed_files target namespace)
  set(out_dir ${CMAKE_CURRENT_BINARY_DIR}/embedded)
  set(out_cpp ${out_dir}/${target}_embedded.cpp)
  set(inputs)
  foreach(file ${ARGN})
    get_filename_component(abs ${file} ABSOLUTE)
    list(APPEND inputs ${abs})
  endforeach()
  # '|' separates the list on the command line: ';' would split the argument.
  string(REPLACE ";" "|" inputs_arg "${inputs}")
  add_custom_command(
    OUTPUT ${out_cpp}
    COMMAND ${CMAKE_COMMAND} -DOUT=${out_cpp} -DNAMESPACE=${namespace} "-DINPUTS=${inputs_arg}"
            -P ${PROJECT_SOURCE_DIR}/cmake/EmbedFilesScript.cmake
    DEPENDS ${inputs} ${PROJECT_SOURCE_DIR}/cmake/EmbedFilesScript.cmake
    COMMENT "Embedding ${target} resources"
    VERBATIM)
  target_sources(${target} PRIVATE ${out_cpp})
endfunction()
