// One RAII owner per GL object kind (magnum's GL::Buffer pattern): move-only,
// deleted in the destructor on the GL thread that created it, with an
// explicit empty state. Only the GL thread may create or destroy them.
//
// Each owner remembers the context generation it was created in: after a
// context loss the worker makes a new context, in which the old names mean
// nothing or, worse, name new objects. An owner from an earlier generation
// therefore deletes nothing.
#pragma once

#include <cstdint>
#include <utility>

#include <epoxy/gl.h>

namespace visq::gpu {

// The generation of the context current on this thread (0 off the GL
// thread); defined by the worker, which bumps it on every new context.
uint64_t CurrentContextGeneration();

struct NoCreateT { explicit constexpr NoCreateT() = default; };
inline constexpr NoCreateT NoCreate{};

template <typename Traits>
class GlObject {
 public:
  // Creates a new object (needs a current context).
  GlObject() : id_(Traits::Create()), generation_(CurrentContextGeneration()) {}
  // The empty state: owns nothing, needs no context.
  explicit GlObject(NoCreateT) noexcept {}
  // Takes ownership of an existing name.
  static GlObject Wrap(GLuint id) noexcept {
    GlObject o(NoCreate);
    o.id_ = id;
    o.generation_ = CurrentContextGeneration();
    return o;
  }

  GlObject(const GlObject&) = delete;
  GlObject& operator=(const GlObject&) = delete;
  GlObject(GlObject&& other) noexcept : id_(std::exchange(other.id_, 0)), generation_(other.generation_) {}
  GlObject& operator=(GlObject&& other) noexcept {
    std::swap(id_, other.id_);
    std::swap(generation_, other.generation_);
    return *this;
  }
  ~GlObject() {
    if (id_ != 0 && generation_ == CurrentContextGeneration()) Traits::Delete(id_);
  }

  GLuint id() const noexcept { return id_; }
  explicit operator bool() const noexcept { return id_ != 0; }
  // Gives up ownership without deleting.
  GLuint Release() noexcept { return std::exchange(id_, 0); }

 private:
  GLuint id_ = 0;
  uint64_t generation_ = 0;
};

namespace traits {
struct Buffer {
  static GLuint Create() { GLuint id = 0; glCreateBuffers(1, &id); return id; }
  static void Delete(GLuint id) { glDeleteBuffers(1, &id); }
};
template <GLenum kTarget>
struct Texture {
  static GLuint Create() { GLuint id = 0; glCreateTextures(kTarget, 1, &id); return id; }
  static void Delete(GLuint id) { glDeleteTextures(1, &id); }
};
struct Framebuffer {
  static GLuint Create() { GLuint id = 0; glCreateFramebuffers(1, &id); return id; }
  static void Delete(GLuint id) { glDeleteFramebuffers(1, &id); }
};
struct VertexArray {
  static GLuint Create() { GLuint id = 0; glCreateVertexArrays(1, &id); return id; }
  static void Delete(GLuint id) { glDeleteVertexArrays(1, &id); }
};
struct Program {
  static GLuint Create() { return glCreateProgram(); }
  static void Delete(GLuint id) { glDeleteProgram(id); }
};
struct Renderbuffer {
  static GLuint Create() { GLuint id = 0; glCreateRenderbuffers(1, &id); return id; }
  static void Delete(GLuint id) { glDeleteRenderbuffers(1, &id); }
};
template <GLenum kTarget>
struct Query {
  static GLuint Create() { GLuint id = 0; glCreateQueries(kTarget, 1, &id); return id; }
  static void Delete(GLuint id) { glDeleteQueries(1, &id); }
};
// Named by glGenQueries and made by its first glBeginQuery: Mesa 22's
// glCreateQueries refuses the pipeline-statistics targets (GL_INVALID_ENUM)
// on a 4.5 context that has GL_ARB_pipeline_statistics_query.
struct GeneratedQuery {
  static GLuint Create() { GLuint id = 0; glGenQueries(1, &id); return id; }
  static void Delete(GLuint id) { glDeleteQueries(1, &id); }
};
}  // namespace traits

using GlBuffer = GlObject<traits::Buffer>;
using GlTexture2D = GlObject<traits::Texture<GL_TEXTURE_2D>>;
using GlTexture2DArray = GlObject<traits::Texture<GL_TEXTURE_2D_ARRAY>>;
using GlTexture1D = GlObject<traits::Texture<GL_TEXTURE_1D>>;
using GlFramebuffer = GlObject<traits::Framebuffer>;
using GlVertexArray = GlObject<traits::VertexArray>;
using GlProgramObject = GlObject<traits::Program>;
using GlRenderbuffer = GlObject<traits::Renderbuffer>;
using GlQueryAnySamplesPassed = GlObject<traits::Query<GL_ANY_SAMPLES_PASSED>>;
using GlQueryFragmentsShaded = GlObject<traits::GeneratedQuery>;  // for GL_FRAGMENT_SHADER_INVOCATIONS

}  // namespace visq::gpu
