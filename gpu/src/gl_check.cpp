#include "gl_check.h"

#include <string>

namespace visq::gpu {
namespace {
// Per GL thread: each worker runs with its own debug option.
thread_local bool checks_enabled = false;
constexpr int kMaxErrorsDrained = 16;  // glGetError can loop on a lost context
}  // namespace

bool GlChecksEnabled() { return checks_enabled; }
void SetGlChecksEnabled(bool enabled) { checks_enabled = enabled; }

std::string GlErrorName(GLenum error) {
  switch (error) {
    case GL_INVALID_ENUM: return "GL_INVALID_ENUM";
    case GL_INVALID_VALUE: return "GL_INVALID_VALUE";
    case GL_INVALID_OPERATION: return "GL_INVALID_OPERATION";
    case GL_INVALID_FRAMEBUFFER_OPERATION: return "GL_INVALID_FRAMEBUFFER_OPERATION";
    case GL_OUT_OF_MEMORY: return "GL_OUT_OF_MEMORY";
    case GL_STACK_OVERFLOW: return "GL_STACK_OVERFLOW";
    case GL_STACK_UNDERFLOW: return "GL_STACK_UNDERFLOW";
    case GL_CONTEXT_LOST: return "GL_CONTEXT_LOST";
    default: return absl::StrCat("GL error 0x", absl::Hex(error));
  }
}

Status CollectGlErrors(std::string_view where) {
  std::string errors;
  for (int i = 0; i < kMaxErrorsDrained; ++i) {
    const GLenum error = glGetError();
    if (error == GL_NO_ERROR) break;
    absl::StrAppend(&errors, errors.empty() ? "" : ", ", GlErrorName(error));
  }
  if (errors.empty()) return absl::OkStatus();
  return absl::InternalError(absl::StrCat("GL error in ", AbslView(where), ": ", errors));
}

}  // namespace visq::gpu
