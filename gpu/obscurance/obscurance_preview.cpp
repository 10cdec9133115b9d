// The obscurance preview (visq/gpu/obscurance.h): one GL job that uploads
// the per-texel values and corner coordinates, rasterizes the scene from the
// camera into an RGBA32F target (alpha = coverage) with a depth test, and
// reads the image back. Shaders: obscurance_preview.vert / .frag.
#include <chrono>
#include <cmath>
#include <string>
#include <vector>

#include <epoxy/gl.h>
#include <fmt/format.h>
#include <glm/gtc/type_ptr.hpp>

#include "common/job_timing.h"
#include "gl_check.h"
#include "gl_object.h"
#include "gpu_scene_resources.h"
#include "scene_draw.h"
#include "shader_program.h"
#include "visq/gpu/obscurance.h"
#include "visq_gpu_obscurance_embedded.h"

namespace visq::gpu {
namespace {

using Clock = std::chrono::steady_clock;

Status ValidatePreviewRequest(const GpuScene& gpu_scene, const ObscurancePreviewRequest& request) {
  VISQ_RETURN_IF_ERROR(ValidatePinholeCamera(request.camera, kMaxObscurancePreviewSize));
  if (request.atlas_width == 0 || request.atlas_height == 0)
    return absl::InvalidArgumentError(
        fmt::format("atlas: {} x {} has a zero side", request.atlas_width, request.atlas_height));
  if (request.texel_values.size() != size_t{request.atlas_width} * request.atlas_height)
    return absl::InvalidArgumentError(fmt::format("texel_values: {} values for a {} x {} atlas",
                                                  request.texel_values.size(), request.atlas_width,
                                                  request.atlas_height));
  if (request.corner_uv.size() != size_t{gpu_scene.triangle_count()} * 3)
    return absl::InvalidArgumentError(fmt::format("corner_uv: {} corners for a scene of {} triangles",
                                                  request.corner_uv.size(), gpu_scene.triangle_count()));
  if (gpu_scene.triangle_count() == 0 || request.scene_bounds.Empty())
    return absl::FailedPreconditionError("obscurance preview: the scene has no geometry");
  return absl::OkStatus();
}

struct PreviewUniforms {
  explicit PreviewUniforms(UniformLocator& at)
      : clip_from_anchor(at.Find<glm::mat4>("u_clip_from_anchor")),
        inv_atlas_size(at.Find<glm::vec2>("u_inv_atlas_size")) {}
  Uniform<glm::mat4> clip_from_anchor;
  Uniform<glm::vec2> inv_atlas_size;
};

// Everything GL of one call, created and destroyed inside the job.
struct PreviewObjects {
  const TypedProgram<PreviewUniforms>* program = nullptr;  // the worker's program cache owns it
  GlBuffer corner_uv{NoCreate};
  GlTexture2D values{NoCreate};
  GlTexture2D color{NoCreate};
  GlRenderbuffer depth{NoCreate};
  GlFramebuffer framebuffer{NoCreate};
};

Status DrawPreview(const GpuScene& gpu_scene, const ObscurancePreviewRequest& request, const glm::mat4& clip,
                   std::vector<glm::vec4>& pixels) {
  VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* scene_resources, gpu_scene.CurrentResources());
  const GpuScene::Resources& res = *scene_resources;
  const uint32_t width = request.camera.width, height = request.camera.height;
  PreviewObjects o;
  VISQ_ASSIGN_OR_RETURN(o.program, CachedProgram<PreviewUniforms>(obscurance_shaders::Find,
                                                                 {{GL_VERTEX_SHADER, "obscurance_preview.vert"},
                                                                  {GL_FRAGMENT_SHADER, "obscurance_preview.frag"}}));

  // The atlas: corner coordinates (texels) and the values, filtered
  // bilinearly and clamped at the atlas's edge.
  o.corner_uv = GlBuffer();
  glNamedBufferStorage(o.corner_uv.id(), static_cast<GLsizeiptr>(request.corner_uv.size() * sizeof(glm::vec2)),
                       request.corner_uv.data(), 0);
  o.values = GlTexture2D();
  glTextureStorage2D(o.values.id(), 1, GL_RGB32F, GLsizei(request.atlas_width), GLsizei(request.atlas_height));
  glPixelStorei(GL_UNPACK_ALIGNMENT, 4);
  glTextureSubImage2D(o.values.id(), 0, 0, 0, GLsizei(request.atlas_width), GLsizei(request.atlas_height), GL_RGB,
                      GL_FLOAT, request.texel_values.data());
  glTextureParameteri(o.values.id(), GL_TEXTURE_MIN_FILTER, GL_LINEAR);
  glTextureParameteri(o.values.id(), GL_TEXTURE_MAG_FILTER, GL_LINEAR);
  glTextureParameteri(o.values.id(), GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
  glTextureParameteri(o.values.id(), GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);

  // The target: RGBA32F (alpha = covered) and a float depth buffer.
  o.color = GlTexture2D();
  glTextureStorage2D(o.color.id(), 1, GL_RGBA32F, GLsizei(width), GLsizei(height));
  o.depth = GlRenderbuffer();
  glNamedRenderbufferStorage(o.depth.id(), GL_DEPTH_COMPONENT32F, GLsizei(width), GLsizei(height));
  o.framebuffer = GlFramebuffer();
  glNamedFramebufferTexture(o.framebuffer.id(), GL_COLOR_ATTACHMENT0, o.color.id(), 0);
  glNamedFramebufferRenderbuffer(o.framebuffer.id(), GL_DEPTH_ATTACHMENT, GL_RENDERBUFFER, o.depth.id());
  if (glCheckNamedFramebufferStatus(o.framebuffer.id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
    return absl::InternalError("obscurance preview: framebuffer incomplete");

  // Draw: both faces, nearest surface wins.
  const GLuint program = o.program->id();
  glBindFramebuffer(GL_FRAMEBUFFER, o.framebuffer.id());
  glViewport(0, 0, GLsizei(width), GLsizei(height));
  glDisable(GL_CULL_FACE);
  glDisable(GL_BLEND);
  glEnable(GL_DEPTH_TEST);
  glDepthFunc(GL_LESS);
  glDepthMask(GL_TRUE);
  const float background[4] = {0, 0, 0, 0};
  const float far_depth = 1.0f;
  glClearNamedFramebufferfv(o.framebuffer.id(), GL_COLOR, 0, background);
  glClearNamedFramebufferfv(o.framebuffer.id(), GL_DEPTH, 0, &far_depth);
  glUseProgram(program);
  o.program->uniforms.clip_from_anchor.Set(clip);
  o.program->uniforms.inv_atlas_size.Set(
      glm::vec2(1.0f / float(request.atlas_width), 1.0f / float(request.atlas_height)));
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, o.corner_uv.id());
  glBindTextureUnit(0, o.values.id());
  VISQ_RETURN_IF_ERROR(DrawWholeScene(res));

  // Read back (GL rows run bottom-up) and leave no state behind.
  pixels.resize(size_t{width} * height);
  glMemoryBarrier(GL_TEXTURE_UPDATE_BARRIER_BIT | GL_FRAMEBUFFER_BARRIER_BIT);
  glPixelStorei(GL_PACK_ALIGNMENT, 4);
  glGetTextureImage(o.color.id(), 0, GL_RGBA, GL_FLOAT, static_cast<GLsizei>(pixels.size() * sizeof(glm::vec4)),
                    pixels.data());
  glBindVertexArray(0);
  glBindTextureUnit(0, 0);
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, 0);
  glUseProgram(0);
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glDisable(GL_DEPTH_TEST);
  VISQ_GL_CHECK("obscurance preview");
  return absl::OkStatus();
}

}  // namespace

StatusOr<ObscurancePreviewImage> RenderObscurancePreview(GpuWorker& worker, const GpuScene& gpu_scene,
                                                         const ObscurancePreviewRequest& request) {
  const auto start = Clock::now();
  VISQ_RETURN_IF_ERROR(ValidatePreviewRequest(gpu_scene, request));
  const glm::mat4 clip(PinholeClipFromAnchor(request.camera, gpu_scene.anchor(), request.scene_bounds));

  std::vector<glm::vec4> pixels;
  JobTiming timing;
  VISQ_RETURN_IF_ERROR(
      worker.Run(request.job, [&]() -> Status { return DrawPreview(gpu_scene, request, clip, pixels); }, &timing));

  // Top row first; alpha is the coverage.
  ObscurancePreviewImage image;
  image.width = request.camera.width;
  image.height = request.camera.height;
  image.rgb.resize(pixels.size() * 3);
  image.covered.resize(pixels.size());
  for (uint32_t y = 0; y < image.height; ++y) {
    for (uint32_t x = 0; x < image.width; ++x) {
      const glm::vec4& p = pixels[size_t{image.height - 1 - y} * image.width + x];
      const size_t i = size_t{y} * image.width + x;
      const bool covered = p.a > 0.5f;
      image.covered[i] = covered ? 1 : 0;
      for (int k = 0; k < 3; ++k) image.rgb[i * 3 + k] = covered ? p[k] : 0.0f;
    }
  }
  image.queue_ms = timing.queue_ms;
  image.render_ms = timing.run_ms;
  image.total_ms = MillisecondsSince(start);
  return image;
}

}  // namespace visq::gpu
