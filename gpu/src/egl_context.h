// Headless EGL: choose a device, create an OpenGL 4.5 core context without a
// surface, make it current on the calling thread.
#pragma once

#include <epoxy/egl.h>

#include "common/status.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

class EglContext {
 public:
  [[nodiscard]] static StatusOr<EglContext> CreateCurrent(const GpuOptions& options);
  EglContext() = default;
  EglContext(EglContext&& other) noexcept { *this = std::move(other); }
  EglContext& operator=(EglContext&& other) noexcept;
  ~EglContext();

  const DeviceInfo& info() const { return info_; }

 private:
  EGLDisplay display_ = EGL_NO_DISPLAY;
  EGLContext context_ = EGL_NO_CONTEXT;
  DeviceInfo info_;
};

}  // namespace visq::gpu
