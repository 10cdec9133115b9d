// The program layer: GLSL programs built from shader files embedded at build
// time (see visq_gpu_algorithm in cmake/EmbedFiles.cmake), with `#define`s
// prepended for variants, kept in one cache per GPU worker and context.
//
// Algorithms ask for a program with CachedProgram<Uniforms>() on the GL
// thread: it is built once per (files, defines) and context, and dropped
// with the context (after a loss, or when the worker stops). Each program
// has its uniforms as the typed members of a struct of its own (a
// `Uniforms`, constructed from a UniformLocator), located once when the
// program is first asked for: setting one is one GL call, with no name
// looked up, and a name that no shader of the program declares (a
// misspelling) fails that first request with INTERNAL, naming it.
#pragma once

#include <map>
#include <optional>
#include <memory>
#include <set>
#include <string>
#include <string_view>
#include <typeindex>
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

// One uniform's value into a program (glProgramUniform*), by type. Callers
// round their doubles to float last, after their double arithmetic.
void SetUniform(GLuint program, GLint location, int value);
void SetUniform(GLuint program, GLint location, unsigned value);
void SetUniform(GLuint program, GLint location, float value);
void SetUniform(GLuint program, GLint location, bool value);
void SetUniform(GLuint program, GLint location, const glm::vec2& value);
void SetUniform(GLuint program, GLint location, const glm::vec3& value);
void SetUniform(GLuint program, GLint location, const glm::vec4& value);
void SetUniform(GLuint program, GLint location, const glm::ivec2& value);
void SetUniform(GLuint program, GLint location, const glm::ivec3& value);
void SetUniform(GLuint program, GLint location, const glm::uvec2& value);
void SetUniform(GLuint program, GLint location, const glm::mat4& value);
void SetUniformArray(GLuint program, GLint location, const glm::vec3* values, size_t count);
void SetUniformArray(GLuint program, GLint location, const glm::vec4* values, size_t count);
void SetUniformArray(GLuint program, GLint location, const float* values, size_t count);

// A uniform of one program, located once: Set is one GL call. Location -1
// (declared, but dropped by the linker as unused in this variant) sets
// nothing, as GL does.
template <typename T>
class Uniform {
 public:
  Uniform() = default;
  Uniform(GLuint program, GLint location) : program_(program), location_(location) {}
  void Set(const T& value) const { SetUniform(program_, location_, value); }
  // An array uniform's first `count` elements.
  void SetArray(const T* values, size_t count) const { SetUniformArray(program_, location_, values, count); }
  GLint location() const { return location_; }

 private:
  GLuint program_ = 0;
  GLint location_ = -1;
};

class GlProgram;

// Finds a program's uniforms by name for its Uniforms struct; the names no
// shader of the program declares make status() INTERNAL.
class UniformLocator {
 public:
  explicit UniformLocator(const GlProgram& program) : program_(program) {}
  template <typename T>
  Uniform<T> Find(std::string_view name);
  // A uniform of a file that only some variants link (a stage of their
  // own): where none declares it, a uniform that sets nothing.
  template <typename T>
  Uniform<T> FindInVariant(std::string_view name);
  [[nodiscard]] Status status() const;

 private:
  GLint Locate(std::string_view name);
  const GlProgram& program_;
  std::vector<std::string> undeclared_;
};

// A program and its uniforms: `uniforms` is a `Uniforms`, made by
// `Uniforms(UniformLocator&)` when the program was first asked for.
template <typename Uniforms>
struct TypedProgram {
  const GlProgram& program;
  Uniforms uniforms;
  GLuint id() const;
};

// A linked program with its uniform locations.
class GlProgram {
 public:
  GlProgram(GlProgramObject object, std::string name, std::map<std::string, GLint, std::less<>> active,
            std::set<std::string, std::less<>> declared);

  GLuint id() const { return object_.id(); }
  const std::string& name() const { return name_; }  // its files, "a.vert+a.frag"

  // The location of a uniform (of an array's first element): -1 for one the
  // linker dropped as unused, none for a name no shader declares.
  std::optional<GLint> Location(std::string_view name) const;

  // This program with its uniforms as `Uniforms`, located on the first
  // request and kept with the program. GL thread only.
  template <typename Uniforms>
  [[nodiscard]] StatusOr<const TypedProgram<Uniforms>*> Typed() const {
    const std::type_index key(typeid(Uniforms));
    if (auto it = typed_.find(key); it != typed_.end())
      return static_cast<const TypedProgram<Uniforms>*>(it->second.get());
    UniformLocator locator(*this);
    auto typed = std::make_shared<const TypedProgram<Uniforms>>(TypedProgram<Uniforms>{*this, Uniforms(locator)});
    VISQ_RETURN_IF_ERROR(locator.status());
    const TypedProgram<Uniforms>* out = typed.get();
    typed_.emplace(key, std::move(typed));
    return out;
  }

 private:
  GlProgramObject object_;
  std::string name_;
  std::map<std::string, GLint, std::less<>> active_;
  std::set<std::string, std::less<>> declared_;
  mutable std::map<std::type_index, std::shared_ptr<const void>> typed_;
};

template <typename Uniforms>
GLuint TypedProgram<Uniforms>::id() const {
  return program.id();
}

template <typename T>
Uniform<T> UniformLocator::Find(std::string_view name) {
  return Uniform<T>(program_.id(), Locate(name));
}
template <typename T>
Uniform<T> UniformLocator::FindInVariant(std::string_view name) {
  return Uniform<T>(program_.id(), program_.Location(name).value_or(-1));
}

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
// The same, with its uniforms as `Uniforms` (see the header comment).
template <typename Uniforms>
[[nodiscard]] StatusOr<const TypedProgram<Uniforms>*> CachedProgram(ShaderFiles files,
                                                                    const std::vector<ShaderSource>& sources,
                                                                    const ShaderDefines& defines = {}) {
  VISQ_ASSIGN_OR_RETURN(const GlProgram* program, CachedProgram(files, sources, defines));
  return program->Typed<Uniforms>();
}

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
