// GLSL programs built from shader files embedded at build time (see
// gpu/CMakeLists.txt). `#define`s are prepended at run time for variants.
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

// The text of an embedded shader file, with `#include "name"` lines replaced
// by the named embedded file; NOT_FOUND if it is not embedded.
[[nodiscard]] StatusOr<std::string> EmbeddedShaderText(const std::string& file_name);

// Compiles and links; a failure is INTERNAL naming the file and carrying the
// trimmed driver log.
[[nodiscard]] StatusOr<GlProgramObject> BuildProgram(const std::vector<ShaderSource>& sources,
                                                     const ShaderDefines& defines = {});

}  // namespace visq::gpu
