// Hidden-sample maps on the GPU (Eisemann & Décoret 2007): plans the passes,
// keeps the Hough tables and programs, runs the draw on the GL thread and
// turns the read-back bitmasks into visible fractions (section 8's bit
// counting is std::popcount on the CPU: the bitmasks are read back anyway).
#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <map>
#include <mutex>

#include <epoxy/gl.h>

#include "gl_check.h"
#include "gl_object.h"
#include "gpu_scene_resources.h"
#include "hough_table.h"
#include "shader_program.h"
#include "visq/gpu/hidden_sample_map.h"
#include "visq_gpu_hidden_sample_map_embedded.h"

namespace visq::gpu {

// The model this file answers in.
using namespace ::visq::sampling;

struct HiddenSampleMapper::State {
  struct Table {
    hsm::HoughTableLayout layout;
    std::vector<uint32_t> cpu;       // until uploaded
    std::vector<glm::vec2> centred;  // sample positions the shader tests
    GlTexture2DArray texture{NoCreate};
    GlBuffer samples{NoCreate};
    uint64_t generation = 0;  // the context generation `texture` lives in
    uint64_t last_use = 0;
  };
  std::mutex mutex;  // guards `tables` (the map, not the GL objects)
  std::map<std::string, std::shared_ptr<Table>> tables;
  uint64_t clock = 0;
  // GL thread only:
  std::map<std::pair<int, bool>, GlProgramObject> programs;
  uint64_t programs_generation = 0;
  GLint max_draw_buffers = 0;
};

namespace {

constexpr size_t kMaxCachedTables = 6;

using Clock = std::chrono::steady_clock;
constexpr size_t kMaxShaftPlanes = 16;  // hsm_draw.geom's u_shaft_planes

double MsSince(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

// Affine map as a mat4 whose rows are (a_k . X + b_k), k < 3.
glm::dmat4 RowsToMatrix(const glm::dvec3 a[3], const double b[3]) {
  glm::dmat4 m(0.0);
  for (int r = 0; r < 3; ++r) {
    m[0][r] = a[r].x; m[1][r] = a[r].y; m[2][r] = a[r].z; m[3][r] = b[r];
  }
  m[3][3] = 1.0;
  return m;
}

// Dual basis of a patch: s = dual_u . (X - origin), t = dual_v . (X - origin).
void Duals(const Patch& p, glm::dvec3& du, glm::dvec3& dv) {
  const glm::dvec3 n = glm::cross(p.edge_u, p.edge_v);
  const glm::dvec3 cu = glm::cross(p.edge_v, n), cv = glm::cross(n, p.edge_u);
  du = cu / glm::dot(p.edge_u, cu);
  dv = cv / glm::dot(p.edge_v, cv);
}

std::string TableKey(const std::vector<glm::vec2>& centred, int theta_res, int r_res) {
  std::string key(reinterpret_cast<const char*>(centred.data()), centred.size() * sizeof(glm::vec2));
  key += absl::StrCat("|", theta_res, "x", r_res);
  return key;
}

void SetMat4(GLuint program, const char* name, const glm::dmat4& m) {
  const glm::mat4 f(m);
  glProgramUniformMatrix4fv(program, glGetUniformLocation(program, name), 1, GL_FALSE, &f[0][0]);
}

// The planes of the convex hull of `points`, as (n, w) with n . x + w >= 0
// inside, each loosened by `slack`. Every segment between a source sample
// and a receiver point lies in that hull (the shaft), so a triangle wholly
// outside one plane blocks nothing: the geometry shader drops it before its
// influence region (which can cover the whole receiver when the source and
// receiver planes are not parallel) costs a fragment. Brute force over point
// triples: a dozen points. Coplanar points give the plane both ways round,
// which is right: every segment then lies in it.
std::vector<glm::vec4> ShaftPlanes(const std::vector<glm::dvec3>& points, double slack) {
  double diameter = 0;
  for (const glm::dvec3& a : points)
    for (const glm::dvec3& b : points) diameter = std::max(diameter, glm::length(a - b));
  const double flat = 1e-9 * diameter;
  std::vector<glm::dvec4> planes;
  for (size_t i = 0; i < points.size(); ++i)
    for (size_t j = i + 1; j < points.size(); ++j)
      for (size_t k = j + 1; k < points.size(); ++k) {
        glm::dvec3 n = glm::cross(points[j] - points[i], points[k] - points[i]);
        const double length = glm::length(n);
        if (!(length > flat * diameter)) continue;
        n /= length;
        for (const double orientation : {1.0, -1.0}) {
          const glm::dvec3 inward = orientation * n;
          const double w = -glm::dot(inward, points[i]);
          bool supporting = true;
          for (const glm::dvec3& q : points) supporting = supporting && glm::dot(inward, q) + w >= -flat;
          if (!supporting) continue;
          bool known = false;
          for (const glm::dvec4& plane : planes)
            known = known || (glm::length(glm::dvec3(plane) - inward) < 1e-9 && std::abs(plane.w - w) <= flat);
          if (!known) planes.emplace_back(inward, w);
        }
      }
  std::vector<glm::vec4> out;
  for (const glm::dvec4& plane : planes)
    if (out.size() < kMaxShaftPlanes) out.emplace_back(glm::vec3(plane), static_cast<float>(plane.w + slack));
  return out;
}

}  // namespace

HiddenSampleMapper::HiddenSampleMapper(GpuWorker& worker) : worker_(&worker), state_(std::make_shared<State>()) {}

HiddenSampleMapper::~HiddenSampleMapper() {
  if (state_) worker_->Post([state = std::move(state_)]() mutable { state.reset(); });
}

StatusOr<std::unique_ptr<HiddenSampleMapper>> HiddenSampleMapper::Create(GpuWorker& worker) {
  std::unique_ptr<HiddenSampleMapper> mapper(new HiddenSampleMapper(worker));
  State* state = mapper->state_.get();
  VISQ_RETURN_IF_ERROR(worker.Run({}, [state]() -> Status {
    glGetIntegerv(GL_MAX_DRAW_BUFFERS, &state->max_draw_buffers);
    GLint attachments = 0;
    glGetIntegerv(GL_MAX_COLOR_ATTACHMENTS, &attachments);
    state->max_draw_buffers = std::min({state->max_draw_buffers, attachments, 8});
    if (state->max_draw_buffers < 2)
      return absl::FailedPreconditionError(
          absl::StrCat("hidden-sample map needs 2 draw buffers, the device has ", state->max_draw_buffers));
    return CollectGlErrors("hidden-sample map start");
  }));
  return mapper;
}

StatusOr<HiddenSampleMapResult> HiddenSampleMapper::Compute(const GpuScene& scene,
                                                            const HiddenSampleMapRequest& request,
                                                            const JobOptions& job) {
  VISQ_RETURN_IF_ERROR(ValidateHiddenSampleMapRequest(request));
  const SourceSpec& source = request.source;
  const ReceiverSpec& receiver = request.receiver;
  const HiddenSampleMapOptions& options = request.options;
  HiddenSampleMapResult result;
  VISQ_ASSIGN_OR_RETURN(result.samples, ComputeSourceSamples(source));
  const int n = static_cast<int>(result.samples.uv.size());
  const int width = receiver.width, height = receiver.height;
  const bool exact = options.lookup == LookupMode::kExact;
  result.width = width;
  result.height = height;
  result.sample_count = n;
  result.words_per_texel = (n + 31) / 32;

  // The Hough table for this pattern: cached, else built here (not on the GL
  // thread, which other queries share).
  std::vector<glm::vec2> centred;
  for (const glm::dvec2& uv : result.samples.uv)
    centred.emplace_back(static_cast<float>(uv.x - 0.5), static_cast<float>(uv.y - 0.5));
  const std::string key = TableKey(centred, options.hough_theta_resolution, options.hough_r_resolution);
  std::shared_ptr<State::Table> table;
  {
    std::lock_guard lock(state_->mutex);
    auto it = state_->tables.find(key);
    if (it != state_->tables.end()) { table = it->second; table->last_use = ++state_->clock; }
  }
  if (!table) {
    const auto start = Clock::now();
    auto built = std::make_shared<State::Table>();
    built->layout.theta_res = options.hough_theta_resolution;
    built->layout.r_res = options.hough_r_resolution;
    built->cpu = hsm::BuildHoughTable(centred, built->layout);
    built->centred = centred;
    result.table_ms = MsSince(start);
    std::lock_guard lock(state_->mutex);
    auto [it, inserted] = state_->tables.emplace(key, built);
    table = it->second;
    table->last_use = ++state_->clock;
    // Evict the least recently used; the GL objects die on the GL thread.
    while (state_->tables.size() > kMaxCachedTables) {
      auto oldest = std::min_element(state_->tables.begin(), state_->tables.end(), [](auto& a, auto& b) {
        return a.second->last_use < b.second->last_use;
      });
      worker_->Post([doomed = std::move(oldest->second)]() mutable { doomed.reset(); });
      state_->tables.erase(oldest);
    }
  }
  const hsm::HoughTableLayout layout = table->layout;
  const int groups = layout.groups();

  // Frames, in double relative to the scene anchor, rounded to float last.
  const glm::dvec3 anchor = scene.anchor();
  const Patch& sp = source.patch;
  const Patch& rp = receiver.patch;
  const glm::dvec3 rn = glm::normalize(glm::cross(rp.edge_u, rp.edge_v));
  const glm::dvec3 sn = glm::normalize(glm::cross(sp.edge_u, sp.edge_v));
  const double s_sign = glm::dot(sn, rp.At(0.5, 0.5) - sp.origin) > 0 ? 1.0 : -1.0;
  const double r_sign = glm::dot(rn, sp.At(0.5, 0.5) - rp.origin) > 0 ? 1.0 : -1.0;
  glm::dmat4 world_to_source, world_to_receiver;
  {
    glm::dvec3 du, dv;
    Duals(sp, du, dv);
    const glm::dvec3 rows[3] = {du, dv, s_sign * sn};
    const glm::dvec3 rel = anchor - sp.origin;
    const double b[3] = {glm::dot(du, rel) - 0.5, glm::dot(dv, rel) - 0.5, glm::dot(s_sign * sn, rel)};
    world_to_source = RowsToMatrix(rows, b);
  }
  {
    glm::dvec3 du, dv;
    Duals(rp, du, dv);
    const glm::dvec3 rows[3] = {du, dv, r_sign * rn};
    const glm::dvec3 rel = anchor - rp.origin;
    const double b[3] = {glm::dot(du, rel), glm::dot(dv, rel), glm::dot(r_sign * rn, rel)};
    world_to_receiver = RowsToMatrix(rows, b);
  }
  glm::dmat4 receiver_to_world(1.0);
  receiver_to_world[0] = glm::dvec4(rp.edge_u, 0.0);
  receiver_to_world[1] = glm::dvec4(rp.edge_v, 0.0);
  receiver_to_world[2] = glm::dvec4(rn, 0.0);
  receiver_to_world[3] = glm::dvec4(rp.origin - anchor, 1.0);
  const glm::dmat4 receiver_to_source = world_to_source * receiver_to_world;
  // d (distance from the source plane) as a linear function of (a, b, e).
  const glm::dvec3 d_gradient(s_sign * glm::dot(sn, rp.edge_u), s_sign * glm::dot(sn, rp.edge_v),
                              s_sign * r_sign * glm::dot(sn, rn));

  // Endpoint tolerance, as in EmbreeScene::Occluded.
  VISQ_ASSIGN_OR_RETURN(const double delta, ResolvableEndpointTolerance(sp, rp, anchor));
  double e_min = 0.0;
  for (float h : receiver.heightfield) e_min = std::min(e_min, r_sign * h);
  const bool bumpy = !receiver.heightfield.empty();
  const float clip_e = static_cast<float>(bumpy ? e_min : delta);
  const float decorrelation_amplitude = 1.0f / std::ceil(std::sqrt(float(source.sample_count)));

  // The shaft: source samples (moved by up to half the decorrelation
  // amplitude) and receiver points (raised by the heightfield), anchor
  // relative. The slack covers the float rounding of anchor-relative
  // positions and the endpoint tolerance.
  std::vector<glm::vec4> shaft_planes;
  {
    const double spread = options.decorrelate ? 0.5 * decorrelation_amplitude : 0.0;
    double height_lo = 0.0, height_hi = 0.0;
    for (float h : receiver.heightfield) {
      height_lo = std::min(height_lo, double(h));
      height_hi = std::max(height_hi, double(h));
    }
    std::vector<glm::dvec3> hull;
    double magnitude = 0;
    for (int k = 0; k < 4; ++k) {
      const double u = (k & 1) ? 1.0 + spread : -spread, v = (k & 2) ? 1.0 + spread : -spread;
      hull.push_back(sp.At(u, v) - anchor);
      for (const double h : {height_lo, height_hi}) hull.push_back(rp.At(k & 1, k >> 1) + h * rn - anchor);
    }
    for (const glm::dvec3& q : hull) magnitude = std::max({magnitude, std::abs(q.x), std::abs(q.y), std::abs(q.z)});
    shaft_planes = ShaftPlanes(hull, 1e-5 * magnitude + 4.0 * delta);
  }

  // Passes: EXACT writes `groups` uvec4 targets, HOUGH twice as many (maybe
  // and surely blocked), at most max_draw_buffers per pass.
  const int targets_per_pass = state_->max_draw_buffers;
  const int groups_per_pass = exact ? targets_per_pass : targets_per_pass / 2;
  const int passes = (groups + groups_per_pass - 1) / groups_per_pass;
  const int target_layers = exact ? groups : 2 * groups;
  result.passes = passes;

  std::vector<uint32_t> readback(size_t(target_layers) * width * height * 4);
  State* state = state_.get();
  const GLsizei vertex_count = static_cast<GLsizei>(scene.triangle_count()) * 3;

  Status run = worker_->Run(job, [&]() -> Status {
    // After a context loss the table's texture and the programs are gone:
    // rebuild them here (the table from its sample positions) rather than
    // fail every request that follows.
    const uint64_t generation = CurrentContextGeneration();
    if (state->programs_generation != generation) {
      state->programs.clear();
      state->programs_generation = generation;
    }
    if (table->texture && table->generation != generation) {
      hsm::HoughTableLayout same_layout = table->layout;  // other threads read table->layout
      table->cpu = hsm::BuildHoughTable(table->centred, same_layout);
    }
    if (!table->texture || table->generation != generation) {
      GlTexture2DArray texture;
      glTextureStorage3D(texture.id(), 1, GL_RGBA32UI, layout.r_res, layout.theta_res, 2 * groups);
      glTextureSubImage3D(texture.id(), 0, 0, 0, 0, layout.r_res, layout.theta_res, 2 * groups, GL_RGBA_INTEGER,
                          GL_UNSIGNED_INT, table->cpu.data());
      glTextureParameteri(texture.id(), GL_TEXTURE_MIN_FILTER, GL_NEAREST);
      glTextureParameteri(texture.id(), GL_TEXTURE_MAG_FILTER, GL_NEAREST);
      GlBuffer samples;
      glNamedBufferStorage(samples.id(), table->centred.size() * sizeof(glm::vec2), table->centred.data(), 0);
      VISQ_GL_CHECK("hidden-sample map table upload");
      table->texture = std::move(texture);
      table->samples = std::move(samples);
      table->generation = generation;
      std::vector<uint32_t>().swap(table->cpu);
    }

    GlTexture2DArray targets;
    glTextureStorage3D(targets.id(), 1, GL_RGBA32UI, width, height, target_layers);
    GlTexture2D heights(NoCreate);
    if (bumpy) {
      heights = GlTexture2D();
      glTextureStorage2D(heights.id(), 1, GL_R32F, width, height);
      glTextureSubImage2D(heights.id(), 0, 0, 0, width, height, GL_RED, GL_FLOAT, receiver.heightfield.data());
      glTextureParameteri(heights.id(), GL_TEXTURE_MIN_FILTER, GL_NEAREST);
      glTextureParameteri(heights.id(), GL_TEXTURE_MAG_FILTER, GL_NEAREST);
    }
    GlFramebuffer framebuffer;
    glBindFramebuffer(GL_FRAMEBUFFER, framebuffer.id());
    glViewport(0, 0, width, height);
    glDisable(GL_DEPTH_TEST);
    glDisable(GL_CULL_FACE);
    glDisable(GL_BLEND);
    glEnable(GL_COLOR_LOGIC_OP);
    glLogicOp(GL_OR);
    VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* resources, scene.CurrentResources());
    glBindVertexArray(resources->vertex_array.id());
    glBindTextureUnit(0, table->texture.id());
    glBindTextureUnit(1, bumpy ? heights.id() : 0);
    glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, table->samples.id());

    for (int pass = 0; pass < passes; ++pass) {
      VISQ_RETURN_IF_ERROR(StillWanted(job, "hidden-sample map: between passes"));
      const int first = pass * groups_per_pass;
      const int count = std::min(groups_per_pass, groups - first);
      // (Not operator[]: a default GlProgramObject creates a GL program.)
      auto found = state->programs.find({count, exact});
      if (found == state->programs.end()) {
        VISQ_ASSIGN_OR_RETURN(GlProgramObject built, BuildProgram(hidden_sample_map_shaders::Find,
                                                    {{GL_VERTEX_SHADER, "hsm_draw.vert"},
                                                     {GL_GEOMETRY_SHADER, "hsm_draw.geom"},
                                                     {GL_FRAGMENT_SHADER, "hsm_draw.frag"}},
                                                    {{"GROUPS", std::to_string(count)},
                                                     {"EXACT_LOOKUP", exact ? "1" : "0"}}));
        found = state->programs.emplace(std::make_pair(count, exact), std::move(built)).first;
      }
      const GLuint p = found->second.id();
      auto loc = [p](const char* name) { return glGetUniformLocation(p, name); };
      SetMat4(p, "u_world_to_source", world_to_source);
      SetMat4(p, "u_world_to_receiver", world_to_receiver);
      SetMat4(p, "u_receiver_to_source", receiver_to_source);
      glm::vec3 source_corners[4];
      for (int k = 0; k < 4; ++k) source_corners[k] = glm::vec3(sp.At(k & 1, k >> 1) - anchor);
      glProgramUniform3fv(p, loc("u_source_corners"), 4, &source_corners[0].x);
      glProgramUniform3f(p, loc("u_d_gradient"), float(d_gradient.x), float(d_gradient.y), float(d_gradient.z));
      glProgramUniform1f(p, loc("u_e_per_height"), float(r_sign));
      glProgramUniform1f(p, loc("u_delta"), static_cast<float>(delta));
      glProgramUniform1f(p, loc("u_clip_e"), clip_e);
      glProgramUniform1f(p, loc("u_far_e"), static_cast<float>(e_min));
      glProgramUniform1i(p, loc("u_heightfield"), bumpy ? 1 : 0);
      glProgramUniform1i(p, loc("u_watertight"), options.watertight ? 1 : 0);
      glProgramUniform1i(p, loc("u_shaft_plane_count"), static_cast<GLint>(shaft_planes.size()));
      if (!shaft_planes.empty())
        glProgramUniform4fv(p, loc("u_shaft_planes"), static_cast<GLsizei>(shaft_planes.size()), &shaft_planes[0].x);
      glProgramUniform1i(p, loc("u_table"), 0);
      glProgramUniform1i(p, loc("u_heights"), 1);
      glProgramUniform1i(p, loc("u_theta_res"), layout.theta_res);
      glProgramUniform1i(p, loc("u_r_res"), layout.r_res);
      glProgramUniform1f(p, loc("u_r_max"), layout.r_max);
      glProgramUniform1i(p, loc("u_layer_base"), first);
      glProgramUniform1i(p, loc("u_ambiguous_layer_offset"), groups);
      glProgramUniform1i(p, loc("u_sample_count"), n);
      glProgramUniform2f(p, loc("u_receiver_size"), float(width), float(height));
      glProgramUniform1i(p, loc("u_decorrelate"), options.decorrelate ? 1 : 0);
      glProgramUniform1ui(p, loc("u_decorrelation_seed"), options.decorrelation_seed);
      glProgramUniform1f(p, loc("u_decorrelation_amplitude"), decorrelation_amplitude);

      // Attach this pass's layers: maybe (or exact) masks, then for HOUGH the
      // surely-blocked masks.
      std::vector<GLenum> buffers;
      const int attached = exact ? count : 2 * count;
      for (int k = 0; k < attached; ++k) {
        const int layer = k < count ? first + k : groups + first + (k - count);
        glNamedFramebufferTextureLayer(framebuffer.id(), GL_COLOR_ATTACHMENT0 + k, targets.id(), 0, layer);
        buffers.push_back(GL_COLOR_ATTACHMENT0 + k);
      }
      for (int k = attached; k < targets_per_pass; ++k)
        glNamedFramebufferTextureLayer(framebuffer.id(), GL_COLOR_ATTACHMENT0 + k, 0, 0, 0);
      glNamedFramebufferDrawBuffers(framebuffer.id(), static_cast<GLsizei>(buffers.size()), buffers.data());
      if (glCheckNamedFramebufferStatus(framebuffer.id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
        return absl::InternalError("hidden-sample map: framebuffer incomplete");
      const GLuint zero[4] = {0, 0, 0, 0};
      for (int k = 0; k < attached; ++k) glClearBufferuiv(GL_COLOR, k, zero);
      glUseProgram(p);
      glDrawArrays(GL_TRIANGLES, 0, vertex_count);
      VISQ_GL_CHECK("hidden-sample map pass");
    }
    glDisable(GL_COLOR_LOGIC_OP);
    glBindFramebuffer(GL_FRAMEBUFFER, 0);
    glUseProgram(0);
    glGetTextureImage(targets.id(), 0, GL_RGBA_INTEGER, GL_UNSIGNED_INT,
                      static_cast<GLsizei>(readback.size() * sizeof(uint32_t)), readback.data());
    return CollectGlErrors("hidden-sample map");
  }, &result.timing);
  VISQ_RETURN_IF_ERROR(run);

  // Bit counting per texel (section 8); words beyond N are masked off.
  const int wpt = result.words_per_texel;
  const size_t texels = size_t(width) * height;
  const uint32_t last_mask = (n % 32 == 0) ? ~0u : ((1u << (n % 32)) - 1u);
  auto word_at = [&](int plane_layer_base, size_t texel, int w) {
    const int layer = plane_layer_base + w / 4;
    return readback[(size_t(layer) * texels + texel) * 4 + (w & 3)] & (w == wpt - 1 ? last_mask : ~0u);
  };
  result.visible_fraction.resize(texels);
  if (options.want_bitmasks) result.blocked_bits.resize(texels * wpt);
  if (!exact) result.error.lookup_per_texel.resize(texels);
  glm::dvec3 all_colors(0.0);
  for (const glm::vec3& c : result.samples.color) all_colors += glm::dvec3(c);
  if (!result.samples.color.empty()) result.visible_rgb.resize(texels);
  for (size_t j = 0; j < texels; ++j) {
    int blocked = 0, sure = 0;
    glm::dvec3 blocked_color(0.0);
    for (int w = 0; w < wpt; ++w) {
      const uint32_t word = word_at(0, j, w);
      blocked += std::popcount(word);
      if (options.want_bitmasks) result.blocked_bits[j * wpt + w] = word;
      if (!exact) sure += std::popcount(word_at(groups, j, w));
      if (!result.samples.color.empty())
        for (uint32_t bits = word; bits != 0; bits &= bits - 1)
          blocked_color += glm::dvec3(result.samples.color[w * 32 + std::countr_zero(bits)]);
    }
    result.visible_fraction[j] = float(n - blocked) / float(n);
    if (!result.samples.color.empty()) result.visible_rgb[j] = glm::vec3((all_colors - blocked_color) / double(n));
    if (!exact) {
      result.error.lookup_per_texel[j] = float(blocked - sure) / float(n);
      result.error.lookup_max = std::max(result.error.lookup_max, double(blocked - sure) / n);
    }
  }
  result.error.confidence = options.confidence;
  result.error.sampling = SamplingErrorBound(n, options.confidence);
  return result;
}

StatusOr<PatchVisibilityResult> HiddenSampleMapper::PatchVisibility(const GpuScene& scene,
                                                                    const PatchVisibilityRequest& request,
                                                                    const JobOptions& job) {
  VISQ_ASSIGN_OR_RETURN(HiddenSampleMapRequest map, PatchVisibilityAsHiddenSampleMap(request));
  VISQ_ASSIGN_OR_RETURN(HiddenSampleMapResult hsm, Compute(scene, map, job));
  return SummarizePatchVisibility(request, hsm);
}

}  // namespace visq::gpu
