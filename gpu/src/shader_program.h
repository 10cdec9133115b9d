// The program layer: GLSL programs built from shader files embedded at build
// time (see visq_gpu_algorithm in cmake/EmbedFiles.cmake), with `#define`s
// prepended for variants, kept in one cache per GPU worker and context.
//
// Algorithms ask for a program with CachedProgram() on the GL thread: it is
// built once per (files, defines) and context, and dropped with the context
// (after a loss, or when the worker stops). A GlProgram looks its uniforms
// up once, at link time; a name that no shader of the program declares (a
// misspelling) fails the running job with INTERNAL when GPU debugging is on,
// instead of silently setting nothing.
#pragma once

#include <map>
#include <memory>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <epoxy/gl.h>
#include <glm/glm.hpp>

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

// A linked program with its uniform locations.
class GlProgram {
 public:
  GlProgram(GlProgramObject object, std::string name, std::map<std::string, GLint, std::less<>> active,
            std::set<std::string, std::less<>> declared);

  GLuint id() const { return object_.id(); }
  const std::string& name() const { return name_; }  // its files, "a.vert+a.frag"

  // The location of a uniform (of an array's first element); -1 for one the
  // linker dropped as unused, which the setters then skip. A name no shader
  // declares is recorded against the running job (see header comment).
  GLint Uniform(std::string_view name) const;

  void Set(std::string_view name, int value) const;
  void Set(std::string_view name, unsigned value) const;
  void Set(std::string_view name, float value) const;
  void Set(std::string_view name, bool value) const { Set(name, value ? 1 : 0); }
  void Set(std::string_view name, const glm::vec2& value) const;
  void Set(std::string_view name, const glm::vec3& value) const;
  void Set(std::string_view name, const glm::vec4& value) const;
  void Set(std::string_view name, const glm::ivec2& value) const;
  void Set(std::string_view name, const glm::ivec3& value) const;
  void Set(std::string_view name, const glm::mat4& value) const;
  // Doubles are rounded to float last, after the caller's double arithmetic.
  void Set(std::string_view name, const glm::dmat4& value) const { Set(name, glm::mat4(value)); }
  void SetArray(std::string_view name, const glm::vec3* values, size_t count) const;
  void SetArray(std::string_view name, const glm::vec4* values, size_t count) const;
  void SetArray(std::string_view name, const float* values, size_t count) const;

 private:
  GlProgramObject object_;
  std::string name_;
  std::map<std::string, GLint, std::less<>> active_;
  std::set<std::string, std::less<>> declared_;
};

// Compiles and links a program that the caller owns (one-off programs and
// tests); a failure is INTERNAL naming the file and carrying the trimmed
// driver log.
[[nodiscard]] StatusOr<std::unique_ptr<GlProgram>> BuildProgram(ShaderFiles files,
                                                                const std::vector<ShaderSource>& sources,
                                                                const ShaderDefines& defines = {});

// The worker's program for these files and defines, built on first use in
// the current context (GL thread only). The pointer stays valid while the
// context lives, which is at least until the job that asked ends.
[[nodiscard]] StatusOr<const GlProgram*> CachedProgram(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                                       const ShaderDefines& defines = {});

// The cache itself, owned by the GPU worker: one per context. Programs are
// deleted with it, on the GL thread, while their context is current.
class ProgramCache {
 public:
  ProgramCache() = default;
  ProgramCache(const ProgramCache&) = delete;
  ProgramCache& operator=(const ProgramCache&) = delete;
  ~ProgramCache();

  [[nodiscard]] StatusOr<const GlProgram*> Get(ShaderFiles files, const std::vector<ShaderSource>& sources,
                                               const ShaderDefines& defines);
  size_t size() const { return programs_.size(); }

 private:
  std::map<std::string, std::unique_ptr<GlProgram>> programs_;
};

// Set by the worker on its thread, for CachedProgram(); nullptr elsewhere.
void SetCurrentProgramCache(ProgramCache* cache);

// gpu/src's and gpu/self_test's own files.
std::string_view CoreShaderFiles(std::string_view name);

}  // namespace visq::gpu
