// Start-up check that the device rasterizes into integer targets and that
// the OR logic op combines draws bitwise (the hidden-sample map and the
// slicemap depend on both).
#include <vector>

#include <epoxy/gl.h>

#include "gl_check.h"
#include "gl_object.h"
#include "shader_program.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {
namespace {

struct SelfTestUniforms {
  explicit SelfTestUniforms(UniformLocator& at) : pattern(at.Find<unsigned>("u_pattern")) {}
  Uniform<unsigned> pattern;
};

}  // namespace

Status RunSelfTest(GpuWorker& worker) {
  return worker.Run({}, []() -> Status {
    constexpr int kSize = 8;
    VISQ_ASSIGN_OR_RETURN(const TypedProgram<SelfTestUniforms>* program,
                          CachedProgram<SelfTestUniforms>(CoreShaderFiles, {{GL_VERTEX_SHADER, "self_test.vert"},
                                                                            {GL_FRAGMENT_SHADER, "self_test.frag"}}));
    GlTexture2D target;
    glTextureStorage2D(target.id(), 1, GL_RGBA32UI, kSize, kSize);
    GlFramebuffer framebuffer;
    glNamedFramebufferTexture(framebuffer.id(), GL_COLOR_ATTACHMENT0, target.id(), 0);
    if (glCheckNamedFramebufferStatus(framebuffer.id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
      return absl::InternalError("self-test: RGBA32UI framebuffer incomplete");
    GlVertexArray vao;

    // Two draws OR-ed together over the left half; the right half stays clear.
    glBindFramebuffer(GL_FRAMEBUFFER, framebuffer.id());
    glViewport(0, 0, kSize, kSize);
    const GLuint zero[4] = {0, 0, 0, 0};
    glClearBufferuiv(GL_COLOR, 0, zero);
    glUseProgram(program->id());
    glBindVertexArray(vao.id());
    glEnable(GL_COLOR_LOGIC_OP);
    glLogicOp(GL_OR);
    for (unsigned pattern : {0x5u, 0x8u}) {
      program->uniforms.pattern.Set(pattern);
      glDrawArrays(GL_TRIANGLE_STRIP, 0, 4);
    }
    glDisable(GL_COLOR_LOGIC_OP);

    std::vector<GLuint> texels(kSize * kSize * 4);
    glGetTextureImage(target.id(), 0, GL_RGBA_INTEGER, GL_UNSIGNED_INT,
                      static_cast<GLsizei>(texels.size() * sizeof(GLuint)), texels.data());
    glBindFramebuffer(GL_FRAMEBUFFER, 0);
    VISQ_RETURN_IF_ERROR(CollectGlErrors("self-test"));
    for (int y = 0; y < kSize; ++y) {
      for (int x = 0; x < kSize; ++x) {
        const GLuint* t = &texels[(y * kSize + x) * 4];
        const bool left = x < kSize / 2;
        const GLuint want_r = left ? 0xDu : 0u, want_g = left ? 0x1Au : 0u, want_b = left ? 1u : 0u;
        if (t[0] != want_r || t[1] != want_g || t[2] != want_b)
          return absl::InternalError(absl::StrCat("self-test: texel (", x, ",", y, ") is (", t[0], ",", t[1], ",",
                                                  t[2], "), expected (", want_r, ",", want_g, ",", want_b, ")"));
      }
    }
    return absl::OkStatus();
  });
}

}  // namespace visq::gpu
