// GLSL programs built from shader files embedded at build time (see
// visq_gpu_algorithm in cmake/EmbedFiles.cmake): each algorithm library
// passes its own file lookup, e.g. visq::gpu::slicemap_shaders::Find.
// `#define`s are prepended at run time for variants.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include <epoxy/gl.h>

#include "common/status.h"
#include "gl_object.h"

namespace visq::gpu {

struct ShaderSource {
  GLenum stage;           // GL_VERTEX_SHADER, GL_GEOMETRY_SHADER, ...
  std::string file_name;  // an embedded file, e.g. "hidden_sample_map.geom"
};

using ShaderDefines = std::vector<std::pair<std::string, std::string>>;

// An embedded-file lookup: the text of a file by name, empty if absent.
using ShaderFiles = std::string_view (*)(std::string_view);

// The text of an embedded shader file, with `#include "name"` lines replaced
// by the named file (looked up in `files`, then in gpu/src's shared files);
// NOT_FOUND if a file is not embedded.
[[nodiscard]] StatusOr<std::string> EmbeddedShaderText(ShaderFiles files, const std::string& file_name);

// Compiles and links; a failure is INTERNAL naming the file and carrying the
// trimmed driver log.
[[nodiscard]] StatusOr<GlProgramObject> BuildProgram(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                                     const ShaderDefines& defines = {});

// gpu/src's and gpu/self_test's own files.
std::string_view CoreShaderFiles(std::string_view name);

}  // namespace visq::gpu
