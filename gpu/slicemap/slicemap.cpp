// Slicemap voxelization (Eisemann & Décoret 2006). See visq/gpu/slicemap.h
// for the API and the packed layout; the shaders are slicemap.vert,
// slicemap_corners.geom (orthographic views) and slicemap.frag. Transmittance shadow maps,
// which count the voxels of solid slicemaps, are in transmittance.cpp.
//
// Pipeline of one voxelization:
//   1. (local precision) one rasterization writes each column's depth range:
//      RG32F (near, -far) with MIN blending, so one pass gives both ends.
//   2. per pass of up to 1024 slices (512 for solids), the scene is drawn
//      once into up to 8 RGBA32UI targets with the OR logic op; each fragment
//      writes the bit (or, conservative, the bit range) of its depth.
//   3. the targets are read back into the column-major packed layout.
//   4. (solid) each column's in/out state is resolved from its front and back
//      bits on the CPU (ResolveSolidColumn below), on all cores.
#include "visq/gpu/slicemap.h"
#include "common/check.h"
#include "common/job_timing.h"
#include "common/coordinates.h"
#include "common/parallel.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <set>
#include <mutex>
#include <optional>
#include <vector>

#include <epoxy/gl.h>
#include <fmt/format.h>

#include "gl_check.h"
#include "scene_draw.h"
#include "gl_state_across_jobs.h"
#include "gl_object.h"
#include "gpu_scene_resources.h"
#include "shader_program.h"
#include "slicemap_passes.h"
#include "visq_gpu_slicemap_embedded.h"

namespace visq::gpu {

using namespace slicemap_internal;

namespace {

using Clock = std::chrono::steady_clock;


// What the GL thread hands back, a band of rows at a time; solids are
// resolved afterwards.
struct RawSlicemap {
  SlicemapGrid surface;       // the band: every voxel a surface touches
  SlicemapGrid front, back;   // the band, solid: entering / leaving faces (standard sampling)
  std::vector<float> near_far;  // local: (near, -far) per column, as rendered
  uint32_t passes = 0;
  uint32_t gl_jobs = 0;
  SlicemapTimings timings;
};

// A grid's sizes with no bits: the whole answer's, whose bits arrive band
// by band (zeroing them first cost a 2048² x 1024 grid a second of memset
// before its first GL job, with no stop checked).
SlicemapGrid GridShape(uint32_t width, uint32_t height, uint32_t slices) {
  SlicemapGrid grid;
  grid.width = width;
  grid.height = height;
  grid.slices = slices;
  grid.words_per_column = (slices + 31) / 32;
  return grid;
}

SlicemapGrid EmptyGrid(uint32_t width, uint32_t height, uint32_t slices) {
  SlicemapGrid grid = GridShape(width, height, slices);
  grid.bits.assign(size_t{width} * height * grid.words_per_column, 0u);
  return grid;
}


// ---------------------------------------------------------------------------
// The voxelization program and its variants (the worker's program cache).
// Orthographic views send each triangle's corners to the fragment stage
// (conservative columns, or the plane's depth at the texel): the bits do
// not depend on the bands.
bool SendsCorners(const ViewSetup& view) { return !view.perspective; }

struct SlicemapUniforms {
  explicit SlicemapUniforms(UniformLocator& at)
      : clip_from_anchor(at.Find<glm::mat4>("u_clip_from_anchor")),
        depth_plane(at.Find<glm::vec4>("u_depth_plane")),
        light(at.Find<glm::vec3>("u_light")),
        radial(at.Find<glm::vec2>("u_radial")),
        band_origin(at.Find<glm::vec2>("u_band_origin")),
        image_size(at.FindInVariant<glm::vec2>("u_image_size")),
        slices(at.Find<float>("u_slices")),
        near_far(at.Find<int>("u_near_far")),
        pass_first_slice(at.Find<int>("u_pass_first_slice")),
        pass_slices(at.Find<int>("u_pass_slices")) {}
  Uniform<glm::mat4> clip_from_anchor;
  Uniform<glm::vec4> depth_plane;
  Uniform<glm::vec3> light;
  Uniform<glm::vec2> radial;
  Uniform<glm::vec2> band_origin;
  Uniform<glm::vec2> image_size;  // the geometry stage's: corners in image texels
  Uniform<float> slices;
  Uniform<int> near_far;  // the texture unit of the columns' local ranges
  Uniform<int> pass_first_slice, pass_slices;
};
using SlicemapProgram = TypedProgram<SlicemapUniforms>;

StatusOr<const SlicemapProgram*> Program(const ViewSetup& view, const ShaderDefines& defines) {
  std::vector<ShaderSource> sources = {{GL_VERTEX_SHADER, "slicemap.vert"}, {GL_FRAGMENT_SHADER, "slicemap.frag"}};
  if (SendsCorners(view)) sources.push_back({GL_GEOMETRY_SHADER, "slicemap_corners.geom"});
  return CachedProgram<SlicemapUniforms>(slicemap_shaders::Find, sources, defines);
}

void SetViewUniforms(const SlicemapProgram& program, const ViewSetup& view, const PassConfig& config,
                     uint32_t first_row) {
  const SlicemapUniforms& u = program.uniforms;
  u.clip_from_anchor.Set(view.clip_from_anchor);
  u.band_origin.Set(glm::vec2(0.0f, static_cast<float>(first_row)));
  u.depth_plane.Set(view.depth_plane);
  u.light.Set(view.light);
  u.radial.Set(view.radial);
  u.image_size.Set(glm::vec2(static_cast<float>(config.width), static_cast<float>(config.height)));
  u.slices.Set(static_cast<float>(config.slices));
  u.near_far.Set(0);
}

ShaderDefines BaseDefines(const ViewSetup& view, const PassConfig& config, bool conservative) {
  ShaderDefines defines;
  if (conservative) defines.emplace_back("CONSERVATIVE", "1");
  else if (SendsCorners(view)) defines.emplace_back("PLANE_DEPTH", "1");
  if (view.perspective) defines.emplace_back("PERSPECTIVE", "1");
  if (config.precision == SlicePrecision::kLocal) defines.emplace_back("LOCAL", "1");
  return defines;
}

// Copies one RGBA32UI target (128 slices of the pass), read back for the
// columns from `first_column` on, into the packed grid.
void ScatterTarget(const std::vector<GLuint>& texels, size_t first_column, size_t columns, SlicemapGrid& grid,
                   uint32_t first_word) {
  const uint32_t wpc = grid.words_per_column;
  // A target past the column's last word would make `wpc - first_word` wrap
  // and write beyond the column.
  VISQ_CHECK_LT(first_word, wpc);
  VISQ_CHECK_LE((first_column + columns) * wpc, grid.bits.size());
  VISQ_CHECK_LE(columns * 4, texels.size());
  const uint32_t words = std::min<uint32_t>(4, wpc - first_word);
  for (size_t c = 0; c < columns; ++c) {
    uint32_t* column = &grid.bits[(first_column + c) * wpc + first_word];
    const GLuint* texel = &texels[c * 4];
    for (uint32_t i = 0; i < words; ++i) column[i] |= texel[i];
  }
}

// The GL part: depth-range pass, slicemap passes, readback.
// The targets of one voxelization, made by its first GL job and used by
// the next: the depth-range pass and every slicemap pass over every band of
// image rows are GL jobs of their own, so other queries get the GL thread
// between them. The slicemap targets hold one band of rows (the viewport
// shifts each band onto them), so their memory and the first job's cost
// follow the band, not the image: 8 targets of a 2048² image were 512 MiB,
// zeroed by llvmpipe in one uncut job of 1.5 s.
struct SlicemapTargets {
  GlTexture2D near_far{NoCreate};
  GlFramebuffer near_far_framebuffer{NoCreate};
  std::vector<GlTexture2D> targets;
  GlFramebuffer framebuffer{NoCreate};
};

// The fixed state of every slicemap job, restored by RestoreState. The view
// looks along +w with x = u, y = v: a face whose normal points back at the
// viewer winds clockwise in window coordinates. Image rows
// [first_row, first_row + rows) land on the target's rows [0, rows): the
// viewport starts first_row below the target, and the shaders add
// u_band_origin to gl_FragCoord to get the image's texel.
void SetPassState(const PassConfig& config, uint32_t first_row, uint32_t rows) {
  glViewport(0, -static_cast<GLint>(first_row), static_cast<GLsizei>(config.width),
             static_cast<GLsizei>(config.height));
  glDisable(GL_DEPTH_TEST);
  glDisable(GL_CULL_FACE);
  glDisable(GL_BLEND);
  glDisable(GL_MULTISAMPLE);
  glEnable(GL_SCISSOR_TEST);
  glScissor(0, 0, static_cast<GLsizei>(config.width), static_cast<GLsizei>(rows));
  glFrontFace(GL_CW);
}

void RestoreState() {
  glDisable(GL_SCISSOR_TEST);
  glFrontFace(GL_CCW);
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glBindTextureUnit(0, 0);
  glUseProgram(0);
  glBindVertexArray(0);
}

// GL thread: the device's limits and the targets (with local precision,
// the depth-range target too).
StatusOr<std::shared_ptr<SlicemapTargets>> CreateTargets(const PassConfig& config, uint32_t target_count,
                                                         uint32_t band_rows, RawSlicemap& raw) {
  const auto setup_start = Clock::now();
  // The device's limits: the image must fit a texture and a viewport, and a
  // pass needs 8 color attachments.
  GLint max_texture = 0, max_draw_buffers = 0, max_attachments = 0;
  GLint max_viewport[2] = {0, 0};
  glGetIntegerv(GL_MAX_TEXTURE_SIZE, &max_texture);
  glGetIntegerv(GL_MAX_VIEWPORT_DIMS, max_viewport);
  glGetIntegerv(GL_MAX_DRAW_BUFFERS, &max_draw_buffers);
  glGetIntegerv(GL_MAX_COLOR_ATTACHMENTS, &max_attachments);
  const GLint max_image = std::min({max_texture, max_viewport[0], max_viewport[1]});
  if (config.width > static_cast<uint32_t>(max_image) || config.height > static_cast<uint32_t>(max_image))
    return absl::ResourceExhaustedError(fmt::format("image {} x {} exceeds this device's limit {} (GL_MAX_TEXTURE_SIZE / "
                                                    "GL_MAX_VIEWPORT_DIMS)",
                                                    config.width, config.height, max_image));
  if (max_draw_buffers < 8 || max_attachments < 8)
    return absl::FailedPreconditionError(fmt::format("the device offers {} draw buffers and {} color attachments; the "
                                                     "slicemap needs 8",
                                                     max_draw_buffers, max_attachments));
  auto t = std::make_shared<SlicemapTargets>();
  for (uint32_t i = 0; i < target_count; ++i) {
    t->targets.emplace_back();
    glTextureStorage2D(t->targets.back().id(), 1, GL_RGBA32UI, static_cast<GLsizei>(config.width),
                       static_cast<GLsizei>(band_rows));
  }
  t->framebuffer = GlFramebuffer();
  for (uint32_t i = 0; i < t->targets.size(); ++i)
    glNamedFramebufferTexture(t->framebuffer.id(), GL_COLOR_ATTACHMENT0 + i, t->targets[i].id(), 0);
  if (config.precision == SlicePrecision::kLocal) {
    t->near_far = GlTexture2D();
    glTextureStorage2D(t->near_far.id(), 1, GL_RG32F, static_cast<GLsizei>(config.width),
                       static_cast<GLsizei>(config.height));
    glTextureParameteri(t->near_far.id(), GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTextureParameteri(t->near_far.id(), GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    t->near_far_framebuffer = GlFramebuffer();
    glNamedFramebufferTexture(t->near_far_framebuffer.id(), GL_COLOR_ATTACHMENT0, t->near_far.id(), 0);
  }
  raw.timings.setup_ms += MillisecondsSince(setup_start);
  return t;
}

using JobRunner = std::function<Status(const std::function<Status()>& body)>;

// Bands are not halved below this many rows: each band draws the whole
// selection again.
constexpr uint32_t kMinRowsPerBand = 4;

// One draw of a pass, over as many GL jobs as it takes (a conservative pass
// over a large scene takes seconds on llvmpipe: a small query behind it
// waits about config.draw_ms_per_job, not the whole pass): `bind` sets the
// pass's state in each job (`first`: clear the targets too), the draw goes
// on where the last job stopped, and `finish` runs after its last piece, in
// that job (the readback).
Status DrawPassOverJobs(const JobRunner& job, const GpuScene& scene, const ScenePartDraw& part, bool draw_nothing,
                        TimedSizer& pieces, const PassConfig& config,
                        const std::function<StatusOr<GLuint>(bool first)>& bind,
                        const std::function<Status()>& finish, double& draw_ms) {
  std::optional<DrawAcrossJobs> draw;
  if (!draw_nothing) draw.emplace(scene, part, pieces);
  bool first = true, finished = false;
  while (!finished) {
    VISQ_RETURN_IF_ERROR(job([&]() -> Status {
      StatusOr<GLuint> program = bind(first);
      if (!program.ok()) {
        RestoreState();
        return program.status();
      }
      first = false;
      const auto start = Clock::now();
      glUseProgram(*program);
      const Status drawn =
          draw ? draw->DrawSome(config.draw_ms_per_job, config.job, "voxelization: between draws") : absl::OkStatus();
      glDisable(GL_COLOR_LOGIC_OP);
      glDisable(GL_BLEND);
      glBlendEquation(GL_FUNC_ADD);
      RestoreState();
      VISQ_RETURN_IF_ERROR(drawn);
      if (draw && !draw->done()) {
        draw_ms += MillisecondsSince(start);
        return absl::OkStatus();  // the next job draws on
      }
      glFinish();
      draw_ms += MillisecondsSince(start);
      finished = true;
      return finish();
    }));
  }
  return absl::OkStatus();
}

// Runs the passes, each band of rows of each pass GL jobs of its own, and
// hands each band on as soon as all its passes are done: `raw`'s grids then
// hold that band's rows (a solid's surface merged with its front and back
// maps). With local precision a depth-range pass over the whole image comes
// first.
using RawBand = std::function<Status(uint32_t first_row, RawSlicemap& raw)>;

// One voxelization's passes: the triangle selection, the render targets
// (made in the first job, kept across the others), the draw pieces and the
// GL jobs, shared by the depth-range pass, the slice passes and the bands.
class SlicemapPasses {
 public:
  SlicemapPasses(GpuWorker& worker, const GpuScene& scene, const ViewSetup& view, const PassConfig& config,
                 RawSlicemap& raw)
      : worker_(worker),
        scene_(scene),
        view_(view),
        config_(config),
        raw_(raw),
        solid_(config.mode == VoxelizeMode::kSolid),
        conservative_(config.rasterization == Rasterization::kConservative),
        local_(config.precision == SlicePrecision::kLocal),
        part_(SelectedPart(scene, config)),
        draw_nothing_(!part_.everything && part_.commands.empty()),
        per_pass_(solid_ ? kSolidSlicesPerPass : kSlicesPerPass),
        max_targets_per_map_((std::min(config.slices, per_pass_) + 127) / 128),
        // Each band draws the selection again, under a scissor, and reads
        // back only its rows.
        band_rows_(static_cast<uint32_t>(
            std::clamp<size_t>(config.max_columns_per_job / std::max<uint32_t>(config.width, 1), 1, config.height))),
        // Draw pieces of about piece_target_ms.
        pieces_(config.piece_target_ms, PartTriangles(part_),
                config.piece_target_ms > 0.0
                    ? FirstPieceTriangles(uint64_t{config.width} * band_rows_, PartTriangles(part_))
                    : PartTriangles(part_)),
        targets_(worker) {}

  Status Run(const RawBand& on_band) {
    VISQ_RETURN_IF_ERROR(Job([&]() -> Status {
      const uint32_t maps = solid_ ? 2 : 1;
      VISQ_ASSIGN_OR_RETURN(std::shared_ptr<SlicemapTargets> made,
                            CreateTargets(config_, maps * max_targets_per_map_, band_rows_, raw_));
      targets_.Set(std::move(made));
      return absl::OkStatus();
    }));
    if (local_) VISQ_RETURN_IF_ERROR(DepthRangePass());
    return Bands(on_band);
  }

 private:
  // The triangle selection (all when the list is empty).
  static ScenePartDraw SelectedPart(const GpuScene& scene, const PassConfig& config) {
    if (config.triangles.empty()) return scene.Whole();
    std::vector<std::pair<uint32_t, uint32_t>> selected;
    for (const TriangleRange& range : config.triangles)
      if (range.count > 0) selected.emplace_back(range.first, range.count);
    return scene.TriangleRanges(selected);
  }
  static int PartTriangles(const ScenePartDraw& part) { return int(std::clamp<uint64_t>(part.triangles, 1, INT32_MAX)); }

  // One GL job of this call, counting the jobs at whose end another call's
  // job was queued.
  Status Job(const std::function<Status()>& body) {
    JobTiming timing;
    const Status status = worker_.Run(
        config_.job,
        [&]() -> Status {
          const Status done = body();
          if (worker_.queue_depth() > 0) ++jobs_others_waited_for_;
          return done;
        },
        &timing);
    raw_.timings.queue_ms += timing.queue_ms;
    ++raw_.gl_jobs;
    return status;
  }
  Status DrawPass(const std::function<StatusOr<GLuint>(bool first)>& bind, const std::function<Status()>& finish,
                  double& draw_ms) {
    const JobRunner job = [this](const std::function<Status()>& body) { return Job(body); };
    return DrawPassOverJobs(job, scene_, part_, draw_nothing_, pieces_, config_, bind, finish, draw_ms);
  }

  // Local precision: each column's depth range, in one pass over the image.
  Status DepthRangePass() {
    auto bind = [&](bool first) -> StatusOr<GLuint> {
      VISQ_ASSIGN_OR_RETURN(const SlicemapTargets* made, targets_.Get("slicemap"));
      SetPassState(config_, 0, config_.height);
      ShaderDefines defines = BaseDefines(view_, config_, conservative_);
      defines.emplace_back("DEPTH_RANGE_PASS", "1");
      VISQ_ASSIGN_OR_RETURN(const SlicemapProgram* program, Program(view_, defines));
      SetViewUniforms(*program, view_, config_, 0);
      const GLuint framebuffer = made->near_far_framebuffer.id();
      if (glCheckNamedFramebufferStatus(framebuffer, GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
        return absl::InternalError("slicemap: RG32F depth-range framebuffer incomplete");
      glBindFramebuffer(GL_FRAMEBUFFER, framebuffer);
      if (first) {
        const GLfloat empty[4] = {2.0f, 2.0f, 0.0f, 0.0f};  // near 2 > far -2: no geometry
        glClearNamedFramebufferfv(framebuffer, GL_COLOR, 0, empty);
      }
      glEnable(GL_BLEND);
      glBlendEquation(GL_MIN);
      return program->id();
    };
    auto finish = [&]() -> Status {
      VISQ_ASSIGN_OR_RETURN(const SlicemapTargets* made, targets_.Get("slicemap"));
      VISQ_GL_CHECK("slicemap depth-range pass");
      raw_.near_far.resize(size_t{config_.width} * config_.height * 2);
      glGetTextureImage(made->near_far.id(), 0, GL_RG, GL_FLOAT,
                        static_cast<GLsizei>(raw_.near_far.size() * sizeof(float)), raw_.near_far.data());
      raw_.passes += 1;
      return absl::OkStatus();
    };
    return DrawPass(bind, finish, raw_.timings.depth_ms);
  }

  // One slicemap pass over rows [first_row, first_row + rows): `pass_solid`
  // splits front and back faces, else every fragment goes to the surface map.
  Status SlicePass(bool pass_solid, bool pass_conservative, uint32_t first_slice, uint32_t pass_slices,
                   uint32_t first_row, uint32_t rows) {
    const uint32_t targets_per_map = (pass_slices + 127) / 128;
    const uint32_t pass_maps = pass_solid ? 2 : 1;
    auto bind = [&](bool first) -> StatusOr<GLuint> {
      VISQ_ASSIGN_OR_RETURN(const SlicemapTargets* made, targets_.Get("slicemap"));
      const GLuint framebuffer = made->framebuffer.id();
      const auto start = Clock::now();
      SetPassState(config_, first_row, rows);
      if (local_) glBindTextureUnit(0, made->near_far.id());
      ShaderDefines defines = BaseDefines(view_, config_, pass_conservative);
      defines.emplace_back("TARGETS", std::to_string(targets_per_map));
      if (pass_solid) defines.emplace_back("SOLID", "1");
      VISQ_ASSIGN_OR_RETURN(const SlicemapProgram* program, Program(view_, defines));
      SetViewUniforms(*program, view_, config_, first_row);
      program->uniforms.pass_first_slice.Set(static_cast<int>(first_slice));
      program->uniforms.pass_slices.Set(static_cast<int>(pass_slices));
      // Attachment i of the pass: map i / targets_per_map, target i % targets_per_map.
      std::vector<GLenum> buffers;
      for (uint32_t m = 0; m < pass_maps; ++m)
        for (uint32_t t = 0; t < targets_per_map; ++t)
          buffers.push_back(GL_COLOR_ATTACHMENT0 + m * max_targets_per_map_ + t);
      glNamedFramebufferDrawBuffers(framebuffer, static_cast<GLsizei>(buffers.size()), buffers.data());
      if (glCheckNamedFramebufferStatus(framebuffer, GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
        return absl::InternalError("slicemap: RGBA32UI framebuffer incomplete");
      glBindFramebuffer(GL_FRAMEBUFFER, framebuffer);
      if (first) {
        // Clears honour the scissor: only the band's rows.
        const GLuint zero[4] = {0, 0, 0, 0};
        for (GLint i = 0; i < static_cast<GLint>(buffers.size()); ++i)
          glClearNamedFramebufferuiv(framebuffer, GL_COLOR, i, zero);
      }
      glEnable(GL_COLOR_LOGIC_OP);
      glLogicOp(GL_OR);
      raw_.timings.setup_ms += MillisecondsSince(start);
      return program->id();
    };
    auto finish = [&]() -> Status {
      VISQ_ASSIGN_OR_RETURN(const SlicemapTargets* made, targets_.Get("slicemap"));
      VISQ_GL_CHECK("slicemap pass");
      if (first_row == 0) raw_.passes += 1;
      const auto start = Clock::now();
      VISQ_CHECK_LE(size_t{first_row} + rows, size_t{config_.height});
      const size_t band_columns = size_t{config_.width} * rows;
      texels_.resize(band_columns * 4);
      for (uint32_t m = 0; m < pass_maps; ++m) {
        SlicemapGrid& grid = !pass_solid ? raw_.surface : (m == 0 ? raw_.front : raw_.back);
        for (uint32_t t = 0; t < targets_per_map; ++t) {
          glGetTextureSubImage(made->targets[m * max_targets_per_map_ + t].id(), 0, 0, 0, 0,
                               static_cast<GLsizei>(config_.width), static_cast<GLsizei>(rows), 1, GL_RGBA_INTEGER,
                               GL_UNSIGNED_INT, static_cast<GLsizei>(texels_.size() * sizeof(GLuint)), texels_.data());
          ScatterTarget(texels_, 0, band_columns, grid, first_slice / 32 + t * 4);
        }
      }
      VISQ_GL_CHECK("slicemap readback");
      raw_.timings.readback_ms += MillisecondsSince(start);
      return absl::OkStatus();
    };
    return DrawPass(bind, finish, raw_.timings.voxelize_ms);
  }

  // Solid: front/back maps sampled at texel centers (the in/out events);
  // their union is the surface unless a conservative surface pass follows.
  // Band by band, every slice pass of the band, so each band's columns are
  // whole when it is handed on.
  Status Bands(const RawBand& on_band) {
    uint32_t rows_per_band = band_rows_;
    for (uint32_t first_row = 0, rows = 0; first_row < config_.height; first_row += rows) {
      rows = std::min(rows_per_band, config_.height - first_row);
      pieces_.TakeLongestMs();
      const uint64_t jobs_others_waited_for_before_band = jobs_others_waited_for_;
      raw_.surface = EmptyGrid(config_.width, rows, config_.slices);
      if (solid_) {
        raw_.front = EmptyGrid(config_.width, rows, config_.slices);
        raw_.back = EmptyGrid(config_.width, rows, config_.slices);
      }
      for (uint32_t first = 0; first < config_.slices; first += per_pass_) {
        const uint32_t n = std::min(per_pass_, config_.slices - first);
        if (solid_) {
          VISQ_RETURN_IF_ERROR(SlicePass(true, false, first, n, first_row, rows));
          if (conservative_) VISQ_RETURN_IF_ERROR(SlicePass(false, true, first, n, first_row, rows));
        } else {
          VISQ_RETURN_IF_ERROR(SlicePass(false, conservative_, first, n, first_row, rows));
        }
      }
      if (solid_) {
        const auto start = Clock::now();
        for (size_t i = 0; i < raw_.surface.bits.size(); ++i)
          raw_.surface.bits[i] |= raw_.front.bits[i] | raw_.back.bits[i];
        raw_.timings.readback_ms += MillisecondsSince(start);
      }
      VISQ_RETURN_IF_ERROR(on_band(first_row, raw_));
      // A piece's cost follows the texels its triangles cover in the band,
      // not their count: a few triangles across a wide band (a floor, a
      // wall, the Cornell box's sides under conservative boxes) cost
      // hundreds of ms on a CPU rasterizer however the pieces are cut, and
      // another call's job waits for the piece. While other calls' jobs
      // waited for this call's and a piece took over four times the target,
      // the next bands take half the rows; alone, they grow back, as each
      // band draws the whole selection again.
      const double longest_ms = pieces_.TakeLongestMs();
      const bool others_waiting = jobs_others_waited_for_ > jobs_others_waited_for_before_band;
      if (others_waiting && config_.piece_target_ms > 0.0 && longest_ms > 4.0 * config_.piece_target_ms)
        rows_per_band = std::max<uint32_t>(kMinRowsPerBand, rows_per_band / 2);
      else if (!others_waiting)
        rows_per_band = std::min(band_rows_, rows_per_band * 2);
    }
    return absl::OkStatus();
  }

  GpuWorker& worker_;
  const GpuScene& scene_;
  const ViewSetup& view_;
  const PassConfig& config_;
  RawSlicemap& raw_;
  const bool solid_, conservative_, local_;
  const ScenePartDraw part_;
  const bool draw_nothing_;
  const uint32_t per_pass_;
  const uint32_t max_targets_per_map_;
  const uint32_t band_rows_;
  TimedSizer pieces_;
  GlStateAcrossJobs<SlicemapTargets> targets_;
  uint64_t jobs_others_waited_for_ = 0;
  std::vector<GLuint> texels_;  // a pass's readback
};

Status RunPasses(GpuWorker& worker, const GpuScene& scene, const ViewSetup& view, const PassConfig& config,
                 RawSlicemap& raw, const RawBand& on_band) {
  SlicemapPasses passes(worker, scene, view, config, raw);
  return passes.Run(on_band);
}

// Sets (or flips) bits [a, b) of one column.
void SetRange(uint32_t* column, uint32_t a, uint32_t b) {
  for (uint32_t k = a; k < b;) {
    const uint32_t word = k / 32, lo = k % 32;
    const uint32_t hi = std::min<uint32_t>(32, lo + (b - k));
    const uint32_t mask = (hi == 32 ? ~0u : ((1u << hi) - 1u)) & (~0u << lo);
    column[word] |= mask;
    k += hi - lo;
  }
}
void FlipRange(uint32_t* column, uint32_t a, uint32_t b) {
  for (uint32_t k = a; k < b;) {
    const uint32_t word = k / 32, lo = k % 32;
    const uint32_t hi = std::min<uint32_t>(32, lo + (b - k));
    const uint32_t mask = (hi == 32 ? ~0u : ((1u << hi) - 1u)) & (~0u << lo);
    column[word] ^= mask;
    k += hi - lo;
  }
}

enum class ColumnState { kConsistent, kResolved, kAmbiguous };

// In/out along one column from its front (entering) and back (leaving) bits;
// `out` holds the column's surface bits on entry and gets the interior added.
//
// The column starts and ends outside. A voxel with only front bits is where
// the column enters (it must have been outside before), one with only back
// bits where it leaves. A voxel with both is the slides' ambiguity: the OR
// lost how many faces it holds. It is first taken as an even number (a thin
// feature entered and left inside the voxel: the state does not change), and
// when the next single-facing voxel (or the column's end) contradicts that,
// exactly one both-facing voxel since the last single-facing one held an odd
// number, and the gap after it takes the other state ("resolved"). With more
// than one candidate, or none (an open mesh, nested or overlapping shells),
// the column is ambiguous and keeps only its surface voxels.
ColumnState ResolveSolidColumn(const uint32_t* front, const uint32_t* back, uint32_t* out, uint32_t words) {
  bool inside = false;
  bool resolved = false;
  uint32_t gap_start = 0;
  int both_since_single = 0;
  uint32_t last_both = 0;
  for (uint32_t w = 0; w < words; ++w) {
    uint32_t events = front[w] | back[w];
    while (events != 0) {
      const uint32_t bit = static_cast<uint32_t>(std::countr_zero(events));
      events &= events - 1;
      const uint32_t k = w * 32 + bit;
      if (inside) SetRange(out, gap_start, k);
      const bool f = (front[w] >> bit) & 1u, b = (back[w] >> bit) & 1u;
      if (f && b) {
        ++both_since_single;
        last_both = k;
      } else {
        const bool must_be_inside = b;  // leaving needs inside, entering outside
        if (inside != must_be_inside) {
          if (both_since_single != 1) return ColumnState::kAmbiguous;
          FlipRange(out, last_both + 1, k);
          resolved = true;
        }
        inside = f;
        both_since_single = 0;
      }
      gap_start = k + 1;
    }
  }
  if (inside) {
    // The column must end outside: the last both-facing voxel held an odd
    // number of faces and the tail after it (never filled) is outside.
    if (both_since_single != 1) return ColumnState::kAmbiguous;
    resolved = true;
  }
  return resolved ? ColumnState::kResolved : ColumnState::kConsistent;
}

struct SolidSummary {
  uint64_t resolved = 0;
  std::vector<uint32_t> ambiguous;
};

// Resolves every column on all cores; returns the solid grid in `surface`'s
// place (ambiguous columns keep their surface bits).
SolidSummary ResolveSolid(const SlicemapGrid& front, const SlicemapGrid& back, SlicemapGrid& grid) {
  const size_t columns = size_t{grid.width} * grid.height;
  const uint32_t wpc = grid.words_per_column;
  // Chunks of columns, each with its own summary (merged below in order).
  constexpr size_t kColumnsPerChunk = 4096;
  std::vector<SolidSummary> partial((columns + kColumnsPerChunk - 1) / kColumnsPerChunk);
  ParallelFor(columns, kColumnsPerChunk, [&](size_t begin, size_t end) {
    SolidSummary& mine = partial[begin / kColumnsPerChunk];
    std::vector<uint32_t> saved(wpc);
    for (size_t c = begin; c < end; ++c) {
      uint32_t* out = &grid.bits[c * wpc];
      std::copy(out, out + wpc, saved.begin());
      switch (ResolveSolidColumn(&front.bits[c * wpc], &back.bits[c * wpc], out, wpc)) {
        case ColumnState::kConsistent: break;
        case ColumnState::kResolved: ++mine.resolved; break;
        case ColumnState::kAmbiguous:
          std::copy(saved.begin(), saved.end(), out);
          mine.ambiguous.push_back(static_cast<uint32_t>(c));
          break;
      }
    }
  });
  SolidSummary summary;
  for (auto& p : partial) {
    summary.resolved += p.resolved;
    summary.ambiguous.insert(summary.ambiguous.end(), p.ambiguous.begin(), p.ambiguous.end());
  }
  return summary;
}

}  // namespace

namespace slicemap_internal {

Status ValidateGridSize(std::string_view prefix, uint32_t width, uint32_t height, uint32_t slices, bool solid,
                        uint64_t max_bytes) {
  auto field = [&](std::string_view name) { return fmt::format("{}{}", prefix, name); };
  if (width == 0) return absl::InvalidArgumentError(fmt::format("{}: 0 (must be at least 1)", field("width")));
  if (height == 0) return absl::InvalidArgumentError(fmt::format("{}: 0 (must be at least 1)", field("height")));
  if (slices == 0) return absl::InvalidArgumentError(fmt::format("{}: 0 (must be at least 1)", field("slices")));
  if (width > kMaxSlicemapImageSize)
    return absl::ResourceExhaustedError(
        fmt::format("{}: {} exceeds the image cap {}", field("width"), width, kMaxSlicemapImageSize));
  if (height > kMaxSlicemapImageSize)
    return absl::ResourceExhaustedError(
        fmt::format("{}: {} exceeds the image cap {}", field("height"), height, kMaxSlicemapImageSize));
  if (slices > kMaxSlicemapSlices)
    return absl::ResourceExhaustedError(
        fmt::format("{}: {} exceeds the slice cap {}", field("slices"), slices, kMaxSlicemapSlices));
  // The packed result (three grids for a solid: front, back, result) and one
  // pass's targets must fit the byte cap.
  const uint64_t columns = uint64_t{width} * height;
  const uint64_t result_bytes = columns * ((slices + 31) / 32) * 4 * (solid ? 3 : 1);
  const uint64_t per_pass = solid ? kSolidSlicesPerPass : kSlicesPerPass;
  const uint64_t target_bytes = columns * 16 * ((std::min<uint64_t>(slices, per_pass) + 127) / 128) * (solid ? 2 : 1);
  if (result_bytes > max_bytes || target_bytes > max_bytes)
    return absl::ResourceExhaustedError(
        fmt::format("{}width x height x slices = {} x {} x {} needs {} bytes (GPU targets {} bytes), over the cap of {} "
                    "bytes",
                    prefix, width, height, slices, result_bytes, target_bytes, max_bytes));
  return absl::OkStatus();
}

ViewSetup OrthographicView(const OrientedBox& box, const glm::dvec3& anchor) {
  // ndc = (p - center) . axis / half, p = p_rel + anchor.
  const glm::dvec3 offset = anchor - box.center;
  glm::dmat4 m(0.0);
  const glm::dvec3 axes[3] = {box.axis_u, box.axis_v, box.axis_w};
  for (int row = 0; row < 3; ++row) {
    const double half = box.half_extent[row];
    for (int col = 0; col < 3; ++col) m[col][row] = axes[row][col] / half;
    m[3][row] = glm::dot(offset, axes[row]) / half;
  }
  m[3][3] = 1.0;
  ViewSetup view;
  view.clip_from_anchor = glm::mat4(m);
  const double depth = 2.0 * box.half_extent.z;
  view.depth_plane = glm::vec4(glm::vec3(box.axis_w / depth), static_cast<float>(glm::dot(offset, box.axis_w) / depth + 0.5));
  view.box = box;
  return view;
}

}  // namespace slicemap_internal

OrientedBox AxisAlignedSlicemapBox(const Bounds& bounds, int depth_axis, double margin) {
  OrientedBox box;
  const int w = std::clamp(depth_axis, 0, 2), u = (w + 1) % 3, v = (w + 2) % 3;
  box.axis_u = glm::dvec3(0.0);
  box.axis_v = glm::dvec3(0.0);
  box.axis_w = glm::dvec3(0.0);
  box.axis_u[u] = 1.0;
  box.axis_v[v] = 1.0;
  box.axis_w[w] = 1.0;
  box.center = bounds.Center();
  const glm::dvec3 half = 0.5 * bounds.Extent() + glm::dvec3(margin);
  box.half_extent = glm::dvec3(half[u], half[v], half[w]);
  return box;
}

Status ValidateVoxelizeParams(const VoxelizeParams& params, uint32_t triangle_count) {
  const OrientedBox& box = params.box;
  if (!InCoordinateRange(box.center))
    return absl::InvalidArgumentError(fmt::format("params.box.center: non-finite or beyond ±1e15 {}", Vec(box.center)));
  const std::pair<const char*, const glm::dvec3*> axes[3] = {
      {"axis_u", &box.axis_u}, {"axis_v", &box.axis_v}, {"axis_w", &box.axis_w}};
  for (const auto& [name, axis] : axes) {
    if (!InCoordinateRange(*axis)) return absl::InvalidArgumentError(fmt::format("params.box.{}: non-finite or beyond ±1e15 {}", name, Vec(*axis)));
    if (std::abs(glm::length(*axis) - 1.0) > 1e-6)
      return absl::InvalidArgumentError(
          fmt::format("params.box.{}: {} is not unit length (|a| = {})", name, Vec(*axis), glm::length(*axis)));
  }
  if (std::abs(glm::dot(box.axis_u, box.axis_v)) > 1e-6 || std::abs(glm::dot(box.axis_u, box.axis_w)) > 1e-6 ||
      std::abs(glm::dot(box.axis_v, box.axis_w)) > 1e-6)
    return absl::InvalidArgumentError(fmt::format("params.box axes {} {} {} are not orthogonal", Vec(box.axis_u),
                                                  Vec(box.axis_v), Vec(box.axis_w)));
  for (int i = 0; i < 3; ++i) {
    const double h = box.half_extent[i];
    if (!std::isfinite(h) || !(h > 0.0))
      return absl::InvalidArgumentError(
          fmt::format("params.box.half_extent[{}]: {} (must be finite and > 0)", i, h));
    if (h < 1e-9 * std::max(1.0, glm::length(box.center)))
      return absl::InvalidArgumentError(fmt::format(
          "params.box.half_extent[{}]: {} is too small to resolve at center {}", i, h, Vec(box.center)));
  }
  if (params.mode != VoxelizeMode::kSurface && params.mode != VoxelizeMode::kSolid)
    return absl::InvalidArgumentError(fmt::format("params.mode: unknown value {}", static_cast<int>(params.mode)));
  if (params.precision != SlicePrecision::kUniform && params.precision != SlicePrecision::kLocal)
    return absl::InvalidArgumentError(
        fmt::format("params.precision: unknown value {}", static_cast<int>(params.precision)));
  if (params.rasterization != Rasterization::kStandard && params.rasterization != Rasterization::kConservative)
    return absl::InvalidArgumentError(
        fmt::format("params.rasterization: unknown value {}", static_cast<int>(params.rasterization)));
  for (size_t i = 0; i < params.triangles.size(); ++i) {
    const TriangleRange& r = params.triangles[i];
    if (uint64_t{r.first} + r.count > triangle_count)
      return absl::InvalidArgumentError(fmt::format("params.triangles[{}]: [{}, {}) beyond the scene's {} triangles", i,
                                                    r.first, uint64_t{r.first} + r.count, triangle_count));
  }
  return ValidateGridSize("params.", params.width, params.height, params.slices,
                          params.mode == VoxelizeMode::kSolid, params.max_bytes);
}

namespace slicemap_internal {

StatusOr<VoxelizeResult> VoxelizeView(GpuWorker& worker, const GpuScene& scene, const ViewSetup& view,
                                      const PassConfig& config, const VoxelizeBandSink& sink,
                                      SlicemapGrid* surface_out) {
  const auto start = Clock::now();
  VoxelizeResult result;
  result.mode = config.mode;
  result.precision = config.precision;
  result.rasterization = config.rasterization;
  result.grid = GridShape(config.width, config.height, config.slices);
  result.box = view.box;
  if (!sink) result.grid.bits.reserve(size_t{config.width} * config.height * result.grid.words_per_column);
  if (surface_out != nullptr) {
    *surface_out = result.grid;
    surface_out->bits.reserve(size_t{config.width} * config.height * result.grid.words_per_column);
  }
  const bool local = config.precision == SlicePrecision::kLocal;
  RawSlicemap raw;
  VoxelizeBand band;
  auto on_band = [&](uint32_t first_row, RawSlicemap& made) -> Status {
    const size_t first_column = size_t{first_row} * config.width;
    const size_t columns = size_t{config.width} * made.surface.height;
    band.first = first_column;
    // Local precision: the range the shader really used.
    band.column_near.clear();
    band.column_far.clear();
    if (local) {
      band.column_near.resize(columns);
      band.column_far.resize(columns);
      for (size_t c = 0; c < columns; ++c) {
        const float near = made.near_far[2 * (first_column + c)], far = -made.near_far[2 * (first_column + c) + 1];
        band.column_near[c] = near > far ? 1.0f : near;
        band.column_far[c] = near > far ? 0.0f : std::max(far, near + kMinLocalRange);
      }
    }
    if (surface_out != nullptr)
      surface_out->bits.insert(surface_out->bits.end(), made.surface.bits.begin(), made.surface.bits.end());
    if (config.mode == VoxelizeMode::kSolid) {
      const auto resolve_start = Clock::now();
      SolidSummary summary = ResolveSolid(made.front, made.back, made.surface);
      result.resolved_columns += summary.resolved;
      result.ambiguous_columns += summary.ambiguous.size();
      for (uint32_t c : summary.ambiguous) result.ambiguous_column_list.push_back(static_cast<uint32_t>(first_column + c));
      made.timings.resolve_ms += MillisecondsSince(resolve_start);
    }
    result.occupied_voxels += made.surface.CountOccupied();
    band.bits = std::move(made.surface.bits);
    if (sink) {
      result.passes = made.passes;
      return sink(result, band);
    }
    result.grid.bits.insert(result.grid.bits.end(), band.bits.begin(), band.bits.end());
    result.column_near.insert(result.column_near.end(), band.column_near.begin(), band.column_near.end());
    result.column_far.insert(result.column_far.end(), band.column_far.begin(), band.column_far.end());
    return absl::OkStatus();
  };
  VISQ_RETURN_IF_ERROR(RunPasses(worker, scene, view, config, raw, on_band));
  std::sort(result.ambiguous_column_list.begin(), result.ambiguous_column_list.end());
  result.passes = raw.passes;
  result.gl_jobs = raw.gl_jobs;
  result.timings = raw.timings;
  result.timings.total_ms = MillisecondsSince(start);
  return result;
}

}  // namespace slicemap_internal

StatusOr<VoxelizeResult> Voxelize(GpuWorker& worker, const GpuScene& gpu_scene, const VoxelizeParams& params,
                                  const VoxelizeBandSink& sink) {
  VISQ_RETURN_IF_ERROR(ValidateVoxelizeParams(params, gpu_scene.triangle_count()));
  PassConfig config;
  static_cast<SlicemapSettings&>(config) = params;
  return VoxelizeView(worker, gpu_scene, OrthographicView(params.box, gpu_scene.anchor()), config, sink, nullptr);
}

}  // namespace visq::gpu
