#include "egl_context.h"

#include <cstdlib>
#include <map>
#include <mutex>
#include <string_view>
#include <vector>

#include <epoxy/gl.h>
#include <spdlog/spdlog.h>

namespace visq::gpu {
namespace {

// eglInitialize and eglTerminate act on a display for the whole process,
// and every context of one device shares its display: several workers (the
// tests' own, beside a shared one) use one display. Terminating it with one
// worker's context left the other workers without a current context, so
// the display is terminated with the last context made on it.
std::mutex display_mutex;
std::map<EGLDisplay, int> display_contexts;

void CountDisplayUser(EGLDisplay display) {
  std::lock_guard lock(display_mutex);
  ++display_contexts[display];
}

void ReleaseDisplayUser(EGLDisplay display) {
  std::lock_guard lock(display_mutex);
  auto it = display_contexts.find(display);
  if (it == display_contexts.end() || --it->second > 0) return;
  display_contexts.erase(it);
  eglTerminate(display);
}

std::string EglErrorName(EGLint error) {
  switch (error) {
    case EGL_SUCCESS: return "EGL_SUCCESS";
    case EGL_NOT_INITIALIZED: return "EGL_NOT_INITIALIZED";
    case EGL_BAD_ACCESS: return "EGL_BAD_ACCESS";
    case EGL_BAD_ALLOC: return "EGL_BAD_ALLOC";
    case EGL_BAD_ATTRIBUTE: return "EGL_BAD_ATTRIBUTE";
    case EGL_BAD_CONFIG: return "EGL_BAD_CONFIG";
    case EGL_BAD_CONTEXT: return "EGL_BAD_CONTEXT";
    case EGL_BAD_DISPLAY: return "EGL_BAD_DISPLAY";
    case EGL_BAD_MATCH: return "EGL_BAD_MATCH";
    case EGL_BAD_PARAMETER: return "EGL_BAD_PARAMETER";
    case EGL_CONTEXT_LOST: return "EGL_CONTEXT_LOST";
    default: return absl::StrCat("EGL error 0x", absl::Hex(error));
  }
}

Status EglFailure(std::string_view call) {
  return absl::UnavailableError(absl::StrCat(AbslView(call), " failed: ", EglErrorName(eglGetError())));
}

bool HasExtension(const char* list, std::string_view name) {
  if (list == nullptr) return false;
  std::string_view all(list);
  size_t pos = 0;
  while ((pos = all.find(name, pos)) != std::string_view::npos) {
    const size_t end = pos + name.size();
    if ((pos == 0 || all[pos - 1] == ' ') && (end == all.size() || all[end] == ' ')) return true;
    pos = end;
  }
  return false;
}

struct Candidate {
  EGLDisplay display;
  std::string platform;
  std::string description;
  bool software;
};

// EGL devices, in enumeration order, with whether each is a software renderer.
std::vector<Candidate> DeviceDisplays() {
  std::vector<Candidate> out;
  const char* client_ext = eglQueryString(EGL_NO_DISPLAY, EGL_EXTENSIONS);
  if (!HasExtension(client_ext, "EGL_EXT_device_enumeration") &&
      !HasExtension(client_ext, "EGL_EXT_device_base"))
    return out;
  EGLint count = 0;
  if (!eglQueryDevicesEXT(0, nullptr, &count) || count <= 0) return out;
  std::vector<EGLDeviceEXT> devices(count);
  eglQueryDevicesEXT(count, devices.data(), &count);
  for (EGLint i = 0; i < count; ++i) {
    const char* dev_ext = eglQueryDeviceStringEXT(devices[i], EGL_EXTENSIONS);
    const bool software = HasExtension(dev_ext, "EGL_MESA_device_software");
    std::string description = absl::StrCat("device ", i);
    if (HasExtension(dev_ext, "EGL_EXT_device_drm")) {
      if (const char* node = eglQueryDeviceStringEXT(devices[i], EGL_DRM_DEVICE_FILE_EXT))
        absl::StrAppend(&description, " (", node, ")");
    }
    if (software) absl::StrAppend(&description, " (software)");
    EGLDisplay display = eglGetPlatformDisplayEXT(EGL_PLATFORM_DEVICE_EXT, devices[i], nullptr);
    if (display != EGL_NO_DISPLAY) out.push_back({display, "device", description, software});
  }
  return out;
}

StatusOr<EGLContext> CreateCoreContext(EGLDisplay display, bool debug) {
  EGLint major = 0, minor = 0;
  if (!eglInitialize(display, &major, &minor)) return EglFailure("eglInitialize");
  if (!eglBindAPI(EGL_OPENGL_API)) return EglFailure("eglBindAPI(EGL_OPENGL_API)");
  const EGLint config_attribs[] = {EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT, EGL_NONE};
  EGLConfig config = nullptr;
  EGLint configs = 0;
  // Surfaceless contexts may have no config at all (EGL_KHR_no_config_context).
  if (!eglChooseConfig(display, config_attribs, &config, 1, &configs) || configs == 0) config = EGL_NO_CONFIG_KHR;
  // Ask for reset notification first, so that a GPU reset is reported by
  // glGetGraphicsResetStatus (the worker then makes a new context) instead
  // of leaving a context that silently does nothing; drivers that cannot
  // give it get a plain context.
  const EGLint robust_attribs[] = {EGL_CONTEXT_MAJOR_VERSION, 4,
                                   EGL_CONTEXT_MINOR_VERSION, 5,
                                   EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT,
                                   EGL_CONTEXT_OPENGL_DEBUG, debug ? EGL_TRUE : EGL_FALSE,
                                   EGL_CONTEXT_OPENGL_RESET_NOTIFICATION_STRATEGY, EGL_LOSE_CONTEXT_ON_RESET,
                                   EGL_NONE};
  const EGLint plain_attribs[] = {EGL_CONTEXT_MAJOR_VERSION, 4,
                                  EGL_CONTEXT_MINOR_VERSION, 5,
                                  EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT,
                                  EGL_CONTEXT_OPENGL_DEBUG, debug ? EGL_TRUE : EGL_FALSE,
                                  EGL_NONE};
  EGLContext context = EGL_NO_CONTEXT;
  if (major > 1 || (major == 1 && minor >= 5))
    context = eglCreateContext(display, config, EGL_NO_CONTEXT, robust_attribs);
  if (context == EGL_NO_CONTEXT) context = eglCreateContext(display, config, EGL_NO_CONTEXT, plain_attribs);
  if (context == EGL_NO_CONTEXT) return EglFailure("eglCreateContext(OpenGL 4.5 core)");
  if (!eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, context)) {
    Status status = EglFailure("eglMakeCurrent(surfaceless)");
    eglDestroyContext(display, context);
    return status;
  }
  return context;
}

}  // namespace

EglContext& EglContext::operator=(EglContext&& other) noexcept {
  std::swap(display_, other.display_);
  std::swap(context_, other.context_);
  std::swap(info_, other.info_);
  return *this;
}

EglContext::~EglContext() {
  if (context_ != EGL_NO_CONTEXT) {
    eglMakeCurrent(display_, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
    eglDestroyContext(display_, context_);
  }
  if (display_ != EGL_NO_DISPLAY) ReleaseDisplayUser(display_);
}

StatusOr<EglContext> EglContext::CreateCurrent(const GpuOptions& options) {
  std::string choice = options.device;
  if (choice.empty()) {
    const char* env = std::getenv("VISQ_EGL_DEVICE");
    choice = env != nullptr && *env != '\0' ? env : "auto";
  }

  // Candidates in order of preference for the requested choice.
  std::vector<Candidate> candidates;
  std::vector<Candidate> devices = DeviceDisplays();
  if (choice == "auto") {
    for (const auto& d : devices)
      if (!d.software) candidates.push_back(d);
  } else if (choice.rfind("device:", 0) == 0) {
    int index = -1;
    if (!absl::SimpleAtoi(choice.substr(7), &index) || index < 0 || index >= static_cast<int>(devices.size()))
      return absl::InvalidArgumentError(
          absl::StrCat("gpu device '", choice, "': ", devices.size(), " EGL device(s) present"));
    candidates.push_back(devices[index]);
  } else if (choice != "surfaceless") {
    return absl::InvalidArgumentError(
        absl::StrCat("gpu device '", choice, "': expected auto, surfaceless or device:N"));
  }
  if (choice == "auto" || choice == "surfaceless") {
    EGLDisplay display = eglGetPlatformDisplayEXT(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr);
    if (display != EGL_NO_DISPLAY) candidates.push_back({display, "surfaceless", "Mesa surfaceless", true});
  }
  if (candidates.empty()) return absl::UnavailableError(absl::StrCat("no EGL display for device '", choice, "'"));

  // First candidate that yields an OpenGL 4.5 core context wins.
  Status last_error = absl::UnavailableError("no EGL candidate tried");
  for (const auto& candidate : candidates) {
    StatusOr<EGLContext> context = CreateCoreContext(candidate.display, options.debug);
    if (!context.ok()) {
      spdlog::warn("EGL {} unusable: {}", candidate.description, context.status().message());
      last_error = context.status();
      continue;
    }
    EglContext out;
    out.display_ = candidate.display;
    CountDisplayUser(candidate.display);
    out.context_ = *context;
    out.info_.egl_platform = candidate.platform;
    out.info_.egl_device = candidate.description;
    out.info_.gl_vendor = reinterpret_cast<const char*>(glGetString(GL_VENDOR));
    out.info_.gl_renderer = reinterpret_cast<const char*>(glGetString(GL_RENDERER));
    out.info_.gl_version = reinterpret_cast<const char*>(glGetString(GL_VERSION));
    out.info_.software = candidate.software || out.info_.gl_renderer.find("llvmpipe") != std::string::npos;
    return out;
  }
  return absl::UnavailableError(
      absl::StrCat("could not create an OpenGL 4.5 core context: ", last_error.message()));
}

}  // namespace visq::gpu
