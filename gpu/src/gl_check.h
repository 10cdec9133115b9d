// GL error checks: free in release builds unless the worker runs with
// debug on (tests turn it on). Each job's errors are also collected by the
// worker after it runs, so an error never leaks into the next job.
#pragma once

#include <string>

#include <epoxy/gl.h>

#include "common/status.h"

namespace visq::gpu {

std::string GlErrorName(GLenum error);

// Drains glGetError; INTERNAL naming every error and `where` if there was
// any.
[[nodiscard]] Status CollectGlErrors(std::string_view where);

// Whether VISQ_GL_CHECK does anything on this GL thread (set by its worker
// from GpuOptions::debug).
bool GlChecksEnabled();
void SetGlChecksEnabled(bool enabled);

}  // namespace visq::gpu

// Returns INTERNAL from the enclosing function if GL reported an error.
#define VISQ_GL_CHECK(where)                                                   \
  do {                                                                         \
    if (::visq::gpu::GlChecksEnabled())                                        \
      VISQ_RETURN_IF_ERROR(::visq::gpu::CollectGlErrors(where));               \
  } while (false)
