// The GPU device the server draws on, as the GL thread found it at start-up:
// a plain record, so that the core and the transport report it (GetStats,
// /metrics) without naming gpu/.
#pragma once

#include <string>

namespace visq {

struct GpuDeviceInfo {
  std::string egl_platform;  // "device" or "surfaceless"
  std::string egl_device;    // DRM node or extension summary
  std::string gl_vendor;
  std::string gl_renderer;
  std::string gl_version;
  bool software = false;     // llvmpipe or another CPU rasterizer
};

}  // namespace visq
