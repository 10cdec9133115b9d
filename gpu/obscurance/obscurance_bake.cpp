#include "visq/gpu/obscurance.h"

#include <algorithm>
#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <vector>

#include <epoxy/gl.h>

#include "gl_check.h"
#include "gl_object.h"
#include "gpu_scene_resources.h"
#include "scene_draw.h"
#include "shader_program.h"
#include "timed_sizer.h"
#include "common/job_timing.h"
#include "visq_gpu_obscurance_embedded.h"

namespace visq::gpu {
namespace {

using obscurance::ObscuranceAtlas;
using obscurance::ObscuranceParams;
using obscurance::ObscurancePartial;

struct PeelUniforms {
  explicit PeelUniforms(UniformLocator& at)
      : clip_from_scene(at.Find<glm::mat4>("u_clip_from_scene")),
        atlas_size(at.Find<glm::uvec2>("u_atlas_size")),
        first(at.Find<int>("u_first")) {}
  Uniform<glm::mat4> clip_from_scene;
  Uniform<glm::uvec2> atlas_size;
  Uniform<int> first;  // the direction's first layer: nothing in front to peel
};

struct TransferUniforms {
  explicit TransferUniforms(UniformLocator& at)
      : size(at.Find<unsigned>("u_size")),
        texel_count(at.Find<unsigned>("u_texel_count")),
        depth_to_distance(at.Find<float>("u_depth_to_distance")),
        d_max(at.Find<float>("u_d_max")),
        unoccluded(at.Find<glm::vec3>("u_unoccluded")),
        has_a(at.Find<int>("u_has_a")),
        has_b(at.Find<int>("u_has_b")),
        first_row(at.Find<unsigned>("u_first_row")) {}
  Uniform<unsigned> size;
  Uniform<unsigned> texel_count;
  Uniform<float> depth_to_distance;
  Uniform<float> d_max;
  Uniform<glm::vec3> unoccluded;
  Uniform<int> has_a, has_b;
  Uniform<unsigned> first_row;
};

struct CountSquaresUniforms {
  explicit CountSquaresUniforms(UniformLocator& at)
      : first_element(at.Find<unsigned>("u_first_element")), end_element(at.Find<unsigned>("u_end_element")) {}
  Uniform<unsigned> first_element, end_element;
};

// GL state of one bake, created and destroyed on the GL thread.
struct BakeState {
  const TypedProgram<PeelUniforms>* peel = nullptr;  // the worker's program cache owns the programs
  const TypedProgram<TransferUniforms>* transfer = nullptr;
  const TypedProgram<CountSquaresUniforms>* count_squares = nullptr;
  GlBuffer corner_uv{NoCreate};
  GlBuffer triangle_material{NoCreate};
  GlBuffer reflectivity{NoCreate};
  GlBuffer sums{NoCreate};
  GlBuffer triangle_sums{NoCreate};
  GlBuffer direction_counts{NoCreate};  // texels, then triangles
  GlBuffer count_squares_sums{NoCreate};
  GlTexture2D layer[2] = {GlTexture2D(NoCreate), GlTexture2D(NoCreate)};
  GlTexture2D depth[2] = {GlTexture2D(NoCreate), GlTexture2D(NoCreate)};
  GlFramebuffer framebuffer[2] = {GlFramebuffer(NoCreate), GlFramebuffer(NoCreate)};
  GlQueryAnySamplesPassed any_samples{NoCreate};
};

void NearestNoMips(GLuint texture) {
  glTextureParameteri(texture, GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTextureParameteri(texture, GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  glTextureParameteri(texture, GL_TEXTURE_WRAP_S, GL_CLAMP_TO_EDGE);
  glTextureParameteri(texture, GL_TEXTURE_WRAP_T, GL_CLAMP_TO_EDGE);
}

Status CreateState(BakeState& s, const Scene& placed_scene, const ObscuranceAtlas& atlas, uint32_t channels,
                   uint32_t bundle) {
  const Scene& scene = placed_scene.Flattened();
  const std::string channel_text = std::to_string(channels);
  VISQ_ASSIGN_OR_RETURN(s.peel, CachedProgram<PeelUniforms>(obscurance_shaders::Find,
                                                            {{GL_VERTEX_SHADER, "obscurance_peel.vert"},
                                                             {GL_FRAGMENT_SHADER, "obscurance_peel.frag"}}));
  VISQ_ASSIGN_OR_RETURN(
      s.transfer,
      CachedProgram<TransferUniforms>(obscurance_shaders::Find, {{GL_COMPUTE_SHADER, "obscurance_transfer.comp"}},
                                      {{"CHANNELS", channel_text + "u"},
                                       {"FIXED_POINT_SCALE", std::to_string(obscurance::kObscuranceFixedPointScale)}}));
  VISQ_ASSIGN_OR_RETURN(s.count_squares, CachedProgram<CountSquaresUniforms>(
                                             obscurance_shaders::Find,
                                             {{GL_COMPUTE_SHADER, "obscurance_count_squares.comp"}}));
  // Per-corner atlas coordinates, per-triangle material, per-material color.
  s.corner_uv = GlBuffer();
  glNamedBufferStorage(s.corner_uv.id(), atlas.corner_uv.size() * sizeof(glm::vec2), atlas.corner_uv.data(), 0);
  s.triangle_material = GlBuffer();
  glNamedBufferStorage(s.triangle_material.id(), scene.triangle_material.size() * sizeof(uint32_t),
                       scene.triangle_material.data(), 0);
  std::vector<glm::vec4> colors;
  for (const Material& m : scene.materials) colors.emplace_back(glm::vec3(m.reflectivity), 1.0f);
  if (colors.empty()) colors.emplace_back(1.0f);
  s.reflectivity = GlBuffer();
  glNamedBufferStorage(s.reflectivity.id(), colors.size() * sizeof(glm::vec4), colors.data(), 0);
  // Sums: per texel `channels` (lo, hi) pairs, then the count's pair.
  const size_t words = static_cast<size_t>(atlas.texel_count()) * 2 * (channels + 1);
  s.sums = GlBuffer();
  glNamedBufferStorage(s.sums.id(), words * sizeof(uint32_t), nullptr, GL_DYNAMIC_STORAGE_BIT);
  const GLuint zero = 0;
  glClearNamedBufferData(s.sums.id(), GL_R32UI, GL_RED_INTEGER, GL_UNSIGNED_INT, &zero);
  // The same per triangle, and the per-direction counts and their squares.
  const size_t triangles = scene.TriangleCount();
  s.triangle_sums = GlBuffer();
  glNamedBufferStorage(s.triangle_sums.id(), triangles * 2 * (channels + 1) * sizeof(uint32_t), nullptr,
                       GL_DYNAMIC_STORAGE_BIT);
  glClearNamedBufferData(s.triangle_sums.id(), GL_R32UI, GL_RED_INTEGER, GL_UNSIGNED_INT, &zero);
  const size_t elements = atlas.texel_count() + triangles;
  s.direction_counts = GlBuffer();
  glNamedBufferStorage(s.direction_counts.id(), elements * sizeof(uint32_t), nullptr, GL_DYNAMIC_STORAGE_BIT);
  glClearNamedBufferData(s.direction_counts.id(), GL_R32UI, GL_RED_INTEGER, GL_UNSIGNED_INT, &zero);
  s.count_squares_sums = GlBuffer();
  glNamedBufferStorage(s.count_squares_sums.id(), elements * sizeof(double), nullptr, GL_DYNAMIC_STORAGE_BIT);
  glClearNamedBufferData(s.count_squares_sums.id(), GL_R32UI, GL_RED_INTEGER, GL_UNSIGNED_INT, &zero);
  // Two layers in flight: (patch + 1, triangle * 2 + front) and depth.
  for (int i = 0; i < 2; ++i) {
    s.layer[i] = GlTexture2D();
    glTextureStorage2D(s.layer[i].id(), 1, GL_RG32UI, bundle, bundle);
    NearestNoMips(s.layer[i].id());
    s.depth[i] = GlTexture2D();
    glTextureStorage2D(s.depth[i].id(), 1, GL_DEPTH_COMPONENT32F, bundle, bundle);
    NearestNoMips(s.depth[i].id());
    glTextureParameteri(s.depth[i].id(), GL_TEXTURE_COMPARE_MODE, GL_NONE);
    s.framebuffer[i] = GlFramebuffer();
    glNamedFramebufferTexture(s.framebuffer[i].id(), GL_COLOR_ATTACHMENT0, s.layer[i].id(), 0);
    glNamedFramebufferTexture(s.framebuffer[i].id(), GL_DEPTH_ATTACHMENT, s.depth[i].id(), 0);
    if (glCheckNamedFramebufferStatus(s.framebuffer[i].id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
      return absl::InternalError("obscurance bake: layer framebuffer incomplete");
  }
  s.any_samples = GlQueryAnySamplesPassed();
  return CollectGlErrors("obscurance bake setup");
}

struct DirectionFrame {
  glm::mat4 clip_from_scene{1.0f};
  float depth_to_distance = 0;
};

// The orthographic view of one bundle: the scene's bounding sphere (center c
// relative to the anchor, radius r) fills the image, shifted by the
// direction's sub-pixel offset; clip z runs along the view over [-r, r].
DirectionFrame FrameOf(const obscurance::BundleDirection& d, const glm::dvec3& c, double r, uint32_t bundle) {
  // One pixel of margin so that the shift never pushes geometry out.
  const double R = r * (1.0 + 2.0 / bundle) + 1e-12;
  glm::dmat4 m(0.0);
  for (int i = 0; i < 3; ++i) {
    m[i][0] = d.right[i] / R;
    m[i][1] = d.up[i] / R;
    m[i][2] = d.view[i] / R;
  }
  m[3][0] = -glm::dot(c, d.right) / R + 2.0 * d.pixel_offset.x / bundle;
  m[3][1] = -glm::dot(c, d.up) / R + 2.0 * d.pixel_offset.y / bundle;
  m[3][2] = -glm::dot(c, d.view) / R;
  m[3][3] = 1.0;
  return DirectionFrame{glm::mat4(m), static_cast<float>(2.0 * R)};
}

// Where a direction's peeling stands between GL jobs: the layer being drawn
// and how much of its draw is done, or how far the transfer after it (or
// the count squares at the direction's end) has run. A direction is peeled
// in GL jobs of about a step's target, each drawing whole layers or pieces
// of one and dispatching bands of rows, so that a call's stop, and other
// calls' jobs, get the GL thread between them even where one layer over a
// large scene, or one transfer over a large bundle, takes a second (a CPU
// rasterizer). The sums are integers added atomically: the bands leave the
// bits as one dispatch would.
struct DirectionPeel {
  enum class Stage { kDraw, kTransfer, kLastTransfer, kCountSquares, kDone };
  Stage stage = Stage::kDraw;
  uint32_t layer = 0;
  std::optional<DrawCursor> layer_draw;  // what is left of the layer's draw
  bool any_sample = false;  // a fragment of the layer passed
  uint32_t next_band = 0;   // the transfer's next row of groups, or the count squares' next group
  bool done() const { return stage == Stage::kDone; }
};

// Sizes of the units a step is made of, by their measured time: triangles
// of a draw piece, rows of groups of a transfer band, groups of a count
// squares band. One set for a whole bake: every direction draws the same
// scene into the same bundle.
struct PeelSizers {
  TimedSizer draw;
  TimedSizer transfer_rows;
  TimedSizer square_groups;
};

Status PeelSome(BakeState& s, const GpuScene& gpu_scene, const ScenePartDraw& whole_draw,
                const ScenePartDraw& whole_commands,
                const DirectionFrame& frame, uint32_t bundle, const ObscuranceAtlas& atlas,
                const ObscuranceParams& params, const glm::vec3& unoccluded, uint32_t max_layers,
                const JobOptions& job, double step_ms, PeelSizers& sizers, DirectionPeel& peel) {
  const auto job_start = std::chrono::steady_clock::now();
  VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* scene_resources, gpu_scene.CurrentResources());
  const GpuScene::Resources& res = *scene_resources;
  // Other calls' jobs ran since the last step: every binding and uniform
  // is set again (the programs are the worker's, shared with other bakes).
  glViewport(0, 0, static_cast<GLsizei>(bundle), static_cast<GLsizei>(bundle));
  glDisable(GL_CULL_FACE);
  glDisable(GL_BLEND);
  glDisable(GL_COLOR_LOGIC_OP);
  glEnable(GL_DEPTH_TEST);
  glDepthFunc(GL_LESS);
  glDepthMask(GL_TRUE);
  glFrontFace(GL_CCW);
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, s.corner_uv.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 1, s.triangle_material.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 2, s.reflectivity.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 3, s.sums.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 4, s.triangle_sums.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 5, s.direction_counts.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 6, s.count_squares_sums.id());

  const GLuint peel_program = s.peel->id(), transfer = s.transfer->id();
  const PeelUniforms& peel_uniforms = s.peel->uniforms;
  const TransferUniforms& transfer_uniforms = s.transfer->uniforms;
  peel_uniforms.clip_from_scene.Set(frame.clip_from_scene);
  peel_uniforms.atlas_size.Set(glm::uvec2(atlas.width, atlas.height));
  transfer_uniforms.size.Set(bundle);
  transfer_uniforms.texel_count.Set(atlas.texel_count());
  transfer_uniforms.depth_to_distance.Set(frame.depth_to_distance);
  transfer_uniforms.d_max.Set(static_cast<float>(params.d_max));
  transfer_uniforms.unoccluded.Set(unoccluded);
  const GLuint groups = (bundle + 7) / 8;
  auto step_spent = [&] { return MillisecondsSince(job_start) >= step_ms; };

  const GLuint clear_layer[4] = {0, 0, 0, 0};
  const GLfloat clear_depth = 1.0f;
  const GLuint square_program = s.count_squares->id();
  const uint32_t elements = atlas.texel_count() + gpu_scene.triangle_count();
  const uint32_t element_groups = (elements + 63) / 64;
  constexpr uint32_t kRowGroups = 32768;  // groups of 64 per row of the count squares' dispatch

  // Dispatches `program` in bands from peel.next_band until `total` units
  // are done (true) or the step is spent (false, to resume in the next
  // job); `dispatch(first, count)` runs one band, which glFinish times.
  auto in_bands = [&](TimedSizer& sizer, uint32_t total,
                      const std::function<void(uint32_t, uint32_t)>& dispatch) -> StatusOr<bool> {
    while (peel.next_band < total) {
      const uint32_t count = std::min<uint32_t>(uint32_t(sizer.size()), total - peel.next_band);
      const auto band_start = std::chrono::steady_clock::now();
      dispatch(peel.next_band, count);
      glFinish();
      sizer.Measured(int(count), MillisecondsSince(band_start));
      peel.next_band += count;
      if (peel.next_band < total) {
        VISQ_RETURN_IF_ERROR(job.stop.Check("obscurance bake: between bands of a dispatch"));
        if (step_spent()) return false;
      }
    }
    peel.next_band = 0;
    return true;
  };
  // Transfers between the layers in `prev` (A, when has_a) and `cur` (B,
  // when has_b), in bands of rows of 8 x 8 groups.
  auto transfer_bands = [&](int a, int b, bool has_a, bool has_b) -> StatusOr<bool> {
    glBindFramebuffer(GL_FRAMEBUFFER, 0);
    glUseProgram(transfer);
    transfer_uniforms.has_a.Set(has_a ? 1 : 0);
    transfer_uniforms.has_b.Set(has_b ? 1 : 0);
    glBindTextureUnit(0, s.layer[a].id());
    glBindTextureUnit(1, s.depth[a].id());
    glBindTextureUnit(2, s.layer[b].id());
    glBindTextureUnit(3, s.depth[b].id());
    return in_bands(sizers.transfer_rows, groups, [&](uint32_t first, uint32_t count) {
      transfer_uniforms.first_row.Set(first * 8);
      glDispatchCompute(groups, count, 1);
      glMemoryBarrier(GL_SHADER_STORAGE_BARRIER_BIT | GL_TEXTURE_FETCH_BARRIER_BIT | GL_FRAMEBUFFER_BARRIER_BIT);
    });
  };

  while (!peel.done()) {
    const uint32_t k = peel.layer;
    const int cur = static_cast<int>(k % 2), prev = 1 - cur;
    if (peel.stage == DirectionPeel::Stage::kDraw) {
      // Layer k: fragments strictly behind layer k - 1, drawn piece by
      // piece into the same targets (the depth test orders them as one
      // draw would).
      if (!peel.layer_draw) {
        // The whole scene at once when the sizer holds it all, else pieces
        // cut at the sizer's size of the moment.
        const bool cut = uint64_t(sizers.draw.size()) < whole_commands.triangles;
        peel.layer_draw.emplace(cut ? whole_commands : whole_draw);
        peel.any_sample = false;
        glClearNamedFramebufferuiv(s.framebuffer[cur].id(), GL_COLOR, 0, clear_layer);
        glClearNamedFramebufferfv(s.framebuffer[cur].id(), GL_DEPTH, 0, &clear_depth);
      }
      glBindFramebuffer(GL_FRAMEBUFFER, s.framebuffer[cur].id());
      glUseProgram(peel_program);
      peel_uniforms.first.Set(k == 0 ? 1 : 0);
      glBindTextureUnit(0, s.depth[prev].id());
      while (!peel.layer_draw->done()) {
        const ScenePartDraw piece = peel.layer_draw->Next(uint64_t(sizers.draw.size()));
        const auto piece_start = std::chrono::steady_clock::now();
        glBeginQuery(GL_ANY_SAMPLES_PASSED, s.any_samples.id());
        const Status drawn = DrawScenePart(res, piece);
        glEndQuery(GL_ANY_SAMPLES_PASSED);
        VISQ_RETURN_IF_ERROR(drawn);
        GLuint any = 0;
        glGetQueryObjectuiv(s.any_samples.id(), GL_QUERY_RESULT, &any);  // waits: the piece's time
        peel.any_sample = peel.any_sample || any != 0;
        if (!piece.everything || !sizers.draw.settled())
          sizers.draw.Measured(int(std::min<uint64_t>(piece.triangles, INT32_MAX)), MillisecondsSince(piece_start));
        if (!peel.layer_draw->done()) {
          VISQ_RETURN_IF_ERROR(job.stop.Check("obscurance bake: between draws of a layer"));
          if (step_spent()) return absl::OkStatus();
        }
      }
      peel.layer_draw.reset();
      glMemoryBarrier(GL_TEXTURE_FETCH_BARRIER_BIT | GL_FRAMEBUFFER_BARRIER_BIT);
      // Nothing to transfer from a first layer that is empty.
      peel.stage = k > 0 || peel.any_sample ? DirectionPeel::Stage::kTransfer : DirectionPeel::Stage::kCountSquares;
      if (step_spent()) break;
    }
    if (peel.stage == DirectionPeel::Stage::kTransfer) {
      // Between layer k - 1 (A) and layer k (B, none if empty).
      VISQ_ASSIGN_OR_RETURN(const bool transferred, transfer_bands(prev, cur, k > 0, peel.any_sample));
      if (!transferred) break;
      if (!peel.any_sample) {
        peel.stage = DirectionPeel::Stage::kCountSquares;
      } else if (k + 1 >= max_layers) {
        peel.stage = DirectionPeel::Stage::kLastTransfer;
      } else {
        peel.layer = k + 1;
        peel.stage = DirectionPeel::Stage::kDraw;
        VISQ_RETURN_IF_ERROR(job.stop.Check("obscurance bake: between layers"));
        if (step_spent()) break;
        continue;
      }
    }
    if (peel.stage == DirectionPeel::Stage::kLastTransfer) {
      // The back faces of the last kept layer see nothing: transfer to "none".
      VISQ_ASSIGN_OR_RETURN(const bool transferred, transfer_bands(cur, prev, true, false));
      if (!transferred) break;
      peel.layer = k + 1;
      peel.stage = DirectionPeel::Stage::kCountSquares;
    }
    if (peel.stage == DirectionPeel::Stage::kCountSquares) {
      // The direction's counts: squared into their sums, then cleared.
      glUseProgram(square_program);
      VISQ_ASSIGN_OR_RETURN(const bool squared,
                            in_bands(sizers.square_groups, element_groups, [&](uint32_t first, uint32_t count) {
                              s.count_squares->uniforms.first_element.Set(first * 64);
                              s.count_squares->uniforms.end_element.Set(std::min(elements, (first + count) * 64));
                              glDispatchCompute(std::min(count, kRowGroups), (count + kRowGroups - 1) / kRowGroups, 1);
                              glMemoryBarrier(GL_SHADER_STORAGE_BARRIER_BIT);
                            }));
      if (!squared) break;
      peel.stage = DirectionPeel::Stage::kDone;
    }
  }
  for (int unit = 0; unit < 4; ++unit) glBindTextureUnit(unit, 0);
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glBindVertexArray(0);
  glUseProgram(0);
  VISQ_GL_CHECK("obscurance bake direction");
  return absl::OkStatus();
}

}  // namespace

StatusOr<ObscurancePartial> BakeObscurancePartial(GpuWorker& worker, const GpuScene& gpu_scene, const Scene& placed_scene,
                                                  const ObscuranceAtlas& atlas, const ObscuranceParams& params,
                                                  const ObscuranceBakeOptions& options, ObscuranceBakeStats* stats) {
  const Scene& scene = placed_scene.Flattened();
  const auto start = std::chrono::steady_clock::now();
  VISQ_RETURN_IF_ERROR(obscurance::ValidateParams(params));
  if (gpu_scene.triangle_count() != scene.TriangleCount())
    return absl::InvalidArgumentError(absl::StrCat("gpu_scene: ", gpu_scene.triangle_count(),
                                                   " triangles, scene has ", scene.TriangleCount()));
  if (atlas.corner_uv.size() != scene.TriangleCount() * 3)
    return absl::InvalidArgumentError("atlas: built for another scene (corner count differs)");
  const uint32_t bundle = obscurance::EffectiveBundleResolution(params, atlas);
  const uint32_t channels = params.color_bleeding ? 3 : 1;
  const obscurance::AmbientModel ambient = obscurance::ComputeAmbient(scene, params.color_bleeding);
  const glm::vec3 unoccluded(obscurance::UnoccludedValue(ambient, params.color_bleeding));
  const glm::dvec3 center = scene.bounds.Center() - gpu_scene.anchor();
  const double radius = 0.5 * glm::length(scene.bounds.Extent());

  auto state = std::make_shared<BakeState>();
  // GL objects die on the GL thread whatever happens below.
  struct Release {
    GpuWorker& worker;
    std::shared_ptr<BakeState>& state;
    ~Release() { worker.Post([s = std::move(state)]() mutable { s.reset(); }); }
  } release{worker, state};

  const JobOptions& job = options.job;
  VISQ_RETURN_IF_ERROR(worker.Run(job, [&]() { return CreateState(*state, scene, atlas, channels, bundle); }));

  // Steps of about step_target_ms, in draw pieces of a quarter of it, sized
  // by their measured time (one sizer for the whole bake: every direction
  // draws the same scene into the same bundle).
  const double step_ms = options.step_target_ms > 0.0 ? options.step_target_ms : 1e300;
  const ScenePartDraw whole_draw = gpu_scene.Whole(), whole_commands = gpu_scene.WholeAsCommands();
  const int all_triangles = int(std::clamp<uint64_t>(whole_commands.triangles, 1, INT32_MAX));
  const double unit_ms = options.step_target_ms / 4.0;
  const bool stepped = options.step_target_ms > 0.0;
  const int transfer_rows = int((bundle + 7) / 8);
  const int square_groups = int((atlas.texel_count() + gpu_scene.triangle_count() + 63) / 64);
  // Unmeasured, a transfer band starts at 8 rows of groups (64 x bundle
  // pixels) and a count squares band at 4096 groups; both double from there.
  PeelSizers sizers{
      TimedSizer(unit_ms, all_triangles,
                 stepped ? FirstPieceTriangles(uint64_t{bundle} * bundle, all_triangles) : all_triangles),
      TimedSizer(unit_ms, transfer_rows, stepped ? 8 : transfer_rows),
      TimedSizer(unit_ms, square_groups, stepped ? 4096 : square_groups)};

  ObscuranceBakeStats local;
  local.bundle_resolution = bundle;
  const double kStart = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  for (uint32_t i = 0; i < params.direction_count; ++i) {
    VISQ_RETURN_IF_ERROR(job.stop.Check(
        absl::StrCat("obscurance bake, after ", i, " of ", params.direction_count, " directions")));
    const uint32_t index = params.first_direction + i;
    const DirectionFrame frame = FrameOf(obscurance::DirectionOfSequence(params.seed, index), center, radius, bundle);
    DirectionPeel peel;
    while (!peel.done()) {
      VISQ_RETURN_IF_ERROR(worker.Run(job, [&]() {
        return PeelSome(*state, gpu_scene, whole_draw, whole_commands, frame, bundle, atlas, params, unoccluded,
                        options.max_layers, job, step_ms, sizers, peel);
      }));
    }
    const uint32_t layers = peel.layer;
    local.layers += layers;
    local.max_layers = std::max(local.max_layers, layers);
    if (layers >= options.max_layers) ++local.truncated_directions;
    if (options.progress) {
      const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      const double per = (elapsed - kStart) / (i + 1);
      options.progress(ObscuranceProgress{i + 1, params.direction_count, elapsed,
                                          per * (params.direction_count - i - 1), layers});
    }
  }

  // Read back the sums: (lo, hi) pairs to 64-bit.
  ObscurancePartial partial;
  partial.fingerprint = obscurance::BakeFingerprint(scene, atlas, params);
  partial.width = atlas.width;
  partial.height = atlas.height;
  partial.channels = channels;
  partial.ranges = {obscurance::DirectionRange{params.first_direction, params.direction_count}};
  const size_t texels = atlas.texel_count();
  const size_t triangles = scene.TriangleCount();
  std::vector<uint32_t> words(texels * 2 * (channels + 1)), triangle_words(triangles * 2 * (channels + 1));
  partial.count_squares.resize(texels + triangles);
  VISQ_RETURN_IF_ERROR(worker.Run({options.job.priority}, [&]() -> Status {
    glMemoryBarrier(GL_BUFFER_UPDATE_BARRIER_BIT);
    glGetNamedBufferSubData(state->sums.id(), 0, static_cast<GLsizeiptr>(words.size() * sizeof(uint32_t)),
                            words.data());
    glGetNamedBufferSubData(state->triangle_sums.id(), 0,
                            static_cast<GLsizeiptr>(triangle_words.size() * sizeof(uint32_t)), triangle_words.data());
    glGetNamedBufferSubData(state->count_squares_sums.id(), 0,
                            static_cast<GLsizeiptr>(partial.count_squares.size() * sizeof(double)),
                            partial.count_squares.data());
    return CollectGlErrors("obscurance bake readback");
  }));
  // (lo, hi) words of `count` elements to 64-bit sums and counts.
  auto unpack = [channels](const std::vector<uint32_t>& from, size_t count, std::vector<uint64_t>& sums,
                           std::vector<uint64_t>& counts) {
    sums.resize(count * channels);
    counts.resize(count);
    for (size_t t = 0; t < count; ++t) {
      const uint32_t* w = &from[t * 2 * (channels + 1)];
      for (uint32_t c = 0; c < channels; ++c)
        sums[t * channels + c] = (static_cast<uint64_t>(w[2 * c + 1]) << 32) | w[2 * c];
      counts[t] = (static_cast<uint64_t>(w[2 * channels + 1]) << 32) | w[2 * channels];
    }
  };
  unpack(words, texels, partial.sums, partial.counts);
  unpack(triangle_words, triangles, partial.triangle_sums, partial.triangle_counts);
  local.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (stats != nullptr) *stats = local;
  return partial;
}

StatusOr<obscurance::ObscuranceResult> BakeObscurances(GpuWorker& worker, const GpuScene& gpu_scene,
                                                       const Scene& placed_scene, const ObscuranceAtlas& atlas,
                                                       const ObscuranceParams& params,
                                                       const ObscuranceBakeOptions& options,
                                                       ObscuranceBakeStats* stats) {
  const Scene& scene = placed_scene.Flattened();
  VISQ_ASSIGN_OR_RETURN(ObscurancePartial partial,
                        BakeObscurancePartial(worker, gpu_scene, scene, atlas, params, options, stats));
  return obscurance::FinalizeObscurances(scene, atlas, params, partial);
}

}  // namespace visq::gpu
