// Hidden-sample maps on the GPU (Eisemann & Décoret 2007): plans the passes,
// keeps the Hough tables and programs, culls the scene's triangle clusters
// against the shaft (so that a pass draws what lies near the query, not the
// whole scene), runs the draw on the GL thread and
// turns the read-back bitmasks into visible fractions (section 8's bit
// counting is std::popcount on the CPU: the bitmasks are read back anyway).
#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <map>
#include <mutex>

#include <epoxy/gl.h>

#include "common/check.h"
#include "gl_check.h"
#include "gl_object.h"
#include "gpu_scene_resources.h"
#include "hough_table.h"
#include "scene_draw.h"
#include "sampling/count_intervals.h"
#include "shader_program.h"
#include "timed_sizer.h"
#include "visq/gpu/hidden_sample_map.h"
#include "common/job_timing.h"
#include "visq_gpu_hidden_sample_map_embedded.h"

namespace visq::gpu {

// The model this file answers in.
using namespace ::visq::sampling;

struct HiddenSampleMapper::State {
  struct Table {
    hsm::HoughTableLayout layout;
    std::vector<uint32_t> cpu;       // until uploaded
    std::vector<glm::vec2> centred;  // sample positions the shader tests
    glm::vec4 sample_box{0.0f};      // their bounding box: (lo.x, lo.y, hi.x, hi.y)
    GlTexture2DArray texture{NoCreate};
    GlBuffer samples{NoCreate};
    uint64_t generation = 0;  // the context generation `texture` lives in
    uint64_t last_use = 0;
  };
  std::mutex mutex;  // guards `tables` (the map, not the GL objects)
  std::map<std::string, std::shared_ptr<Table>> tables;
  uint64_t clock = 0;
  GLint max_draw_buffers = 0;  // set once at creation
  bool count_fragments = false;  // asked for, and the driver counts them
  std::atomic<uint64_t> fragments_shaded{0};
};

namespace {

constexpr size_t kMaxCachedTables = 6;

using Clock = std::chrono::steady_clock;
constexpr size_t kMaxShaftPlanes = 16;  // hsm_draw.geom's u_shaft_planes

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

// Texel-passes (rows x width x passes) a band of the scene's last map held
// when it met the target, so the next map starts there. Keyed by the scene
// object (a heuristic: a new scene at a freed address starts from another's
// size and corrects it within a band or two).
struct HiddenSampleMapper::BandSizes {
  std::mutex mutex;
  std::map<const GpuScene*, double> texel_passes;
  std::map<const GpuScene*, int> piece_triangles;  // a draw piece's, at a quarter of band_target_ms
};

HiddenSampleMapper::HiddenSampleMapper(GpuWorker& worker, HiddenSampleMapperOptions options)
    : worker_(&worker), options_(options), state_(std::make_shared<State>()),
      band_sizes_(std::make_shared<BandSizes>()) {}

HiddenSampleMapper::~HiddenSampleMapper() {
  if (state_) worker_->Post([state = std::move(state_)]() mutable { state.reset(); });
}

StatusOr<std::unique_ptr<HiddenSampleMapper>> HiddenSampleMapper::Create(GpuWorker& worker,
                                                                        HiddenSampleMapperOptions options) {
  std::unique_ptr<HiddenSampleMapper> mapper(new HiddenSampleMapper(worker, options));
  State* state = mapper->state_.get();
  VISQ_RETURN_IF_ERROR(worker.Run({}, [state, options]() -> Status {
    glGetIntegerv(GL_MAX_DRAW_BUFFERS, &state->max_draw_buffers);
    GLint attachments = 0;
    glGetIntegerv(GL_MAX_COLOR_ATTACHMENTS, &attachments);
    state->max_draw_buffers = std::min({state->max_draw_buffers, attachments, 8});
    state->count_fragments = options.count_fragments && (epoxy_gl_version() >= 46 ||
                                                         epoxy_has_gl_extension("GL_ARB_pipeline_statistics_query"));
    if (state->max_draw_buffers < 2)
      return absl::FailedPreconditionError(
          absl::StrCat("hidden-sample map needs 2 draw buffers, the device has ", state->max_draw_buffers));
    return CollectGlErrors("hidden-sample map start");
  }));
  return mapper;
}

std::optional<uint64_t> HiddenSampleMapper::fragments_shaded() const {
  if (!state_->count_fragments) return std::nullopt;
  return state_->fragments_shaded.load();
}

namespace {

using Table = HiddenSampleMapper::State::Table;

// The table for this sample pattern: cached, else built here (not on the GL
// thread, which other queries share) until the call stops wanting it.
// `build_ms` gets the time spent building.

StatusOr<std::shared_ptr<Table>> CachedTable(HiddenSampleMapper::State& state, GpuWorker& worker,
                                             const std::vector<glm::vec2>& centred,
                                             const HiddenSampleMapOptions& options, const JobOptions& job,
                                             double& build_ms) {
  const std::string key = TableKey(centred, options.hough_theta_resolution, options.hough_r_resolution);
  {
    std::lock_guard lock(state.mutex);
    auto it = state.tables.find(key);
    if (it != state.tables.end()) {
      it->second->last_use = ++state.clock;
      return it->second;
    }
  }
  const auto start = Clock::now();
  auto built = std::make_shared<Table>();
  built->layout.theta_res = options.hough_theta_resolution;
  built->layout.r_res = options.hough_r_resolution;
  built->cpu = hsm::BuildHoughTable(centred, built->layout, job.stop);
  if (built->cpu.empty()) return job.stop.Check("hidden-sample map: building the sample table");
  built->centred = centred;
  built->sample_box = glm::vec4(centred.front(), centred.front());
  for (const glm::vec2& c : centred)
    built->sample_box = glm::vec4(glm::min(glm::vec2(built->sample_box), c),
                                  glm::max(glm::vec2(built->sample_box.z, built->sample_box.w), c));
  build_ms = MillisecondsSince(start);
  std::lock_guard lock(state.mutex);
  auto [it, inserted] = state.tables.emplace(key, built);
  std::shared_ptr<Table> table = it->second;
  table->last_use = ++state.clock;
  // Evict the least recently used; the GL objects die on the GL thread.
  while (state.tables.size() > kMaxCachedTables) {
    auto oldest = std::min_element(state.tables.begin(), state.tables.end(),
                                   [](auto& a, auto& b) { return a.second->last_use < b.second->last_use; });
    worker.Post([doomed = std::move(oldest->second)]() mutable { doomed.reset(); });
    state.tables.erase(oldest);
  }
  return table;
}

// The table's texture and sample buffer in the current context (GL thread).
// After a context loss they are gone: rebuilt here from the sample
// positions rather than failing every request that follows.
Status EnsureTableOnGpu(Table& table, int groups, const JobOptions& job) {
  const uint64_t generation = CurrentContextGeneration();
  if (table.texture && table.generation == generation) return absl::OkStatus();
  const hsm::HoughTableLayout layout = table.layout;  // other threads read table.layout
  if (table.cpu.empty()) {
    hsm::HoughTableLayout same_layout = layout;
    table.cpu = hsm::BuildHoughTable(table.centred, same_layout, job.stop);
    if (table.cpu.empty()) return job.stop.Check("hidden-sample map: rebuilding the sample table");
  }
  GlTexture2DArray texture;
  glTextureStorage3D(texture.id(), 1, GL_RGBA32UI, layout.r_res, layout.theta_res, 2 * groups);
  glTextureSubImage3D(texture.id(), 0, 0, 0, 0, layout.r_res, layout.theta_res, 2 * groups, GL_RGBA_INTEGER,
                      GL_UNSIGNED_INT, table.cpu.data());
  glTextureParameteri(texture.id(), GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTextureParameteri(texture.id(), GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  GlBuffer samples;
  glNamedBufferStorage(samples.id(), table.centred.size() * sizeof(glm::vec2), table.centred.data(), 0);
  VISQ_GL_CHECK("hidden-sample map table upload");
  table.texture = std::move(texture);
  table.samples = std::move(samples);
  table.generation = generation;
  std::vector<uint32_t>().swap(table.cpu);
  return absl::OkStatus();
}

// Where source and receiver sit, in the frames the shaders work in: double
// relative to the scene anchor, rounded to float last.
struct MapFrames {
  glm::dmat4 world_to_source{1.0};
  glm::dmat4 world_to_receiver{1.0};
  glm::dmat4 receiver_to_source{1.0};
  glm::dvec3 d_gradient{0.0};  // d (distance from the source plane) as a linear function of (a, b, e)
  glm::vec3 source_corners[4];
  double r_sign = 1.0;
  double delta = 0.0;  // endpoint tolerance, as in EmbreeScene::Occluded
  double e_min = 0.0;  // lowest point of the heightfield, receiver side
  bool bumpy = false;
  float clip_e = 0.0f;
  float decorrelation_amplitude = 0.0f;
  std::vector<glm::vec4> shaft_planes;
};

StatusOr<MapFrames> PlanFrames(const HiddenSampleMapRequest& request, const GpuScene& scene) {
  const glm::dvec3& anchor = scene.anchor();
  const Patch& sp = request.source.patch;
  const Patch& rp = request.receiver.patch;
  MapFrames f;
  const glm::dvec3 rn = glm::normalize(glm::cross(rp.edge_u, rp.edge_v));
  const glm::dvec3 sn = glm::normalize(glm::cross(sp.edge_u, sp.edge_v));
  const double s_sign = glm::dot(sn, rp.At(0.5, 0.5) - sp.origin) > 0 ? 1.0 : -1.0;
  f.r_sign = glm::dot(rn, sp.At(0.5, 0.5) - rp.origin) > 0 ? 1.0 : -1.0;
  {
    glm::dvec3 du, dv;
    Duals(sp, du, dv);
    const glm::dvec3 rows[3] = {du, dv, s_sign * sn};
    const glm::dvec3 rel = anchor - sp.origin;
    const double b[3] = {glm::dot(du, rel) - 0.5, glm::dot(dv, rel) - 0.5, glm::dot(s_sign * sn, rel)};
    f.world_to_source = RowsToMatrix(rows, b);
  }
  {
    glm::dvec3 du, dv;
    Duals(rp, du, dv);
    const glm::dvec3 rows[3] = {du, dv, f.r_sign * rn};
    const glm::dvec3 rel = anchor - rp.origin;
    const double b[3] = {glm::dot(du, rel), glm::dot(dv, rel), glm::dot(f.r_sign * rn, rel)};
    f.world_to_receiver = RowsToMatrix(rows, b);
  }
  glm::dmat4 receiver_to_world(1.0);
  receiver_to_world[0] = glm::dvec4(rp.edge_u, 0.0);
  receiver_to_world[1] = glm::dvec4(rp.edge_v, 0.0);
  receiver_to_world[2] = glm::dvec4(rn, 0.0);
  receiver_to_world[3] = glm::dvec4(rp.origin - anchor, 1.0);
  f.receiver_to_source = f.world_to_source * receiver_to_world;
  f.d_gradient = glm::dvec3(s_sign * glm::dot(sn, rp.edge_u), s_sign * glm::dot(sn, rp.edge_v),
                            s_sign * f.r_sign * glm::dot(sn, rn));

  VISQ_ASSIGN_OR_RETURN(const EndpointTolerances tolerances,
                        ResolvableEndpointTolerances(request, FloatFrame{anchor, scene.bounds()}, SegmentTracer::kRaster));
  f.delta = tolerances.source;  // RASTER's are the same at both ends
  for (float h : request.receiver.heightfield) f.e_min = std::min(f.e_min, f.r_sign * h);
  f.bumpy = !request.receiver.heightfield.empty();
  f.clip_e = static_cast<float>(f.bumpy ? f.e_min : f.delta);
  f.decorrelation_amplitude = 1.0f / std::ceil(std::sqrt(float(request.source.sample_count)));

  // The shaft: source samples (moved by up to half the decorrelation
  // amplitude) and receiver points (raised by the heightfield), anchor
  // relative. The slack covers the float rounding of anchor-relative
  // positions and the endpoint tolerance.
  const double spread = request.options.decorrelate ? 0.5 * f.decorrelation_amplitude : 0.0;
  // The corners that the influence regions and the watertight culling
  // project from bound every sample as seen from any texel, so they take the
  // decorrelation's spread too: a sample moved off the patch is still
  // blocked by a triangle whose region the patch alone would not reach.
  for (int k = 0; k < 4; ++k) {
    const double u = (k & 1) ? 1.0 + spread : -spread, v = (k & 2) ? 1.0 + spread : -spread;
    f.source_corners[k] = glm::vec3(sp.At(u, v) - anchor);
  }
  double height_lo = 0.0, height_hi = 0.0;
  for (float h : request.receiver.heightfield) {
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
  f.shaft_planes = ShaftPlanes(hull, 1e-5 * magnitude + 4.0 * f.delta);
  return f;
}

// What each pass draws: the whole scene, or the clusters the shaft keeps
// (which hold every triangle the geometry shader's shaft test keeps, so the
// bits are the same).
ScenePartDraw PlanDraw(const GpuScene& scene, const MapFrames& frames, bool cull_clusters) {
  return cull_clusters ? scene.ClustersInside(frames.shaft_planes) : scene.Whole();
}

// How the bitmask targets are split: EXACT writes `groups` uvec4 targets,
// HOUGH twice as many (maybe and surely blocked), at most max_draw_buffers
// per pass; and the receiver into bands of rows.
struct PassPlan {
  bool exact = false;
  int groups = 0;
  int groups_per_pass = 0;
  int passes = 0;
  int target_layers = 0;
  int band_rows = 0;
};

PassPlan PlanPasses(int groups, bool exact, int max_draw_buffers, int width, int height, size_t band_bytes) {
  PassPlan plan;
  plan.exact = exact;
  plan.groups = groups;
  plan.groups_per_pass = exact ? max_draw_buffers : max_draw_buffers / 2;
  plan.passes = (groups + plan.groups_per_pass - 1) / plan.groups_per_pass;
  plan.target_layers = exact ? groups : 2 * groups;
  const size_t row_bytes = size_t(plan.target_layers) * size_t(width) * 4 * sizeof(uint32_t);
  plan.band_rows = static_cast<int>(std::clamp<size_t>(band_bytes / row_bytes, 1, size_t(height)));
  return plan;
}

// hsm_draw's uniforms: the geometry stage's influence regions, the fragment
// stage's lookup and counting.
struct HsmDrawUniforms {
  explicit HsmDrawUniforms(UniformLocator& at)
      : world_to_source(at.Find<glm::mat4>("u_world_to_source")),
        world_to_receiver(at.Find<glm::mat4>("u_world_to_receiver")),
        receiver_to_source(at.Find<glm::mat4>("u_receiver_to_source")),
        source_corners(at.Find<glm::vec3>("u_source_corners")),
        d_gradient(at.Find<glm::vec3>("u_d_gradient")),
        e_per_height(at.Find<float>("u_e_per_height")),
        delta(at.Find<float>("u_delta")),
        clip_e(at.Find<float>("u_clip_e")),
        far_e(at.Find<float>("u_far_e")),
        heightfield(at.Find<bool>("u_heightfield")),
        watertight(at.Find<bool>("u_watertight")),
        shaft_plane_count(at.Find<int>("u_shaft_plane_count")),
        shaft_planes(at.Find<glm::vec4>("u_shaft_planes")),
        table(at.Find<int>("u_table")),
        heights(at.Find<int>("u_heights")),
        theta_res(at.Find<int>("u_theta_res")),
        r_res(at.Find<int>("u_r_res")),
        r_max(at.Find<float>("u_r_max")),
        layer_base(at.Find<int>("u_layer_base")),
        ambiguous_layer_offset(at.Find<int>("u_ambiguous_layer_offset")),
        sample_count(at.Find<int>("u_sample_count")),
        receiver_size(at.Find<glm::vec2>("u_receiver_size")),
        first_row(at.Find<int>("u_first_row")),
        decorrelate(at.Find<bool>("u_decorrelate")),
        decorrelation_seed(at.Find<unsigned>("u_decorrelation_seed")),
        decorrelation_amplitude(at.Find<float>("u_decorrelation_amplitude")),
        sample_box(at.Find<glm::vec4>("u_sample_box")) {}
  Uniform<glm::mat4> world_to_source, world_to_receiver, receiver_to_source;
  Uniform<glm::vec3> source_corners;  // [4]
  Uniform<glm::vec3> d_gradient;
  Uniform<float> e_per_height, delta, clip_e, far_e;
  Uniform<bool> heightfield, watertight;
  Uniform<int> shaft_plane_count;
  Uniform<glm::vec4> shaft_planes;  // [16]
  Uniform<int> table, heights;      // texture units
  Uniform<int> theta_res, r_res;
  Uniform<float> r_max;
  Uniform<int> layer_base, ambiguous_layer_offset, sample_count;
  Uniform<glm::vec2> receiver_size;
  Uniform<int> first_row;
  Uniform<bool> decorrelate;
  Uniform<unsigned> decorrelation_seed;
  Uniform<float> decorrelation_amplitude;
  Uniform<glm::vec4> sample_box;
};

void SetPassUniforms(const HsmDrawUniforms& u, const MapFrames& f, const HiddenSampleMapRequest& request,
                     const Table& samples, int first_group, int groups, int first_row) {
  const hsm::HoughTableLayout& layout = samples.layout;
  const HiddenSampleMapOptions& options = request.options;
  u.world_to_source.Set(glm::mat4(f.world_to_source));
  u.world_to_receiver.Set(glm::mat4(f.world_to_receiver));
  u.receiver_to_source.Set(glm::mat4(f.receiver_to_source));
  u.source_corners.SetArray(f.source_corners, 4);
  u.d_gradient.Set(glm::vec3(f.d_gradient));
  u.e_per_height.Set(float(f.r_sign));
  u.delta.Set(static_cast<float>(f.delta));
  u.clip_e.Set(f.clip_e);
  u.far_e.Set(static_cast<float>(f.e_min));
  u.heightfield.Set(f.bumpy);
  u.watertight.Set(options.watertight);
  u.shaft_plane_count.Set(static_cast<int>(f.shaft_planes.size()));
  u.shaft_planes.SetArray(f.shaft_planes.data(), f.shaft_planes.size());
  u.table.Set(0);
  u.heights.Set(1);
  u.theta_res.Set(layout.theta_res);
  u.r_res.Set(layout.r_res);
  u.r_max.Set(layout.r_max);
  u.layer_base.Set(first_group);
  u.ambiguous_layer_offset.Set(groups);
  u.sample_count.Set(static_cast<int>(request.source.sample_count));
  u.receiver_size.Set(glm::vec2(float(request.receiver.width), float(request.receiver.height)));
  u.first_row.Set(first_row);
  u.decorrelate.Set(options.decorrelate);
  u.decorrelation_seed.Set(options.decorrelation_seed);
  u.decorrelation_amplitude.Set(f.decorrelation_amplitude);
  u.sample_box.Set(samples.sample_box);
}

// One band of receiver rows [first_row, first_row + rows), every pass, read
// back into `readback` (target layers x band texels x uvec4). GL thread.
// A pass is drawn in pieces sized by `pieces` (a quarter of a band's target,
// finished and timed), so that a stop reaches a band between pieces even
// where one pass over the scene takes seconds (a CPU rasterizer).
Status DrawBand(const GpuScene& scene, Table& table, const MapFrames& frames, const HiddenSampleMapRequest& request,
                const ScenePartDraw& draw, const PassPlan& plan, int max_draw_buffers, int first_row, int rows,
                const JobOptions& job, TimedSizer& pieces, std::vector<uint32_t>& readback,
                std::atomic<uint64_t>* fragments_shaded) {
  const int width = request.receiver.width, height = request.receiver.height;
  VISQ_RETURN_IF_ERROR(EnsureTableOnGpu(table, plan.groups, job));
  GlTexture2DArray targets;
  glTextureStorage3D(targets.id(), 1, GL_RGBA32UI, width, rows, plan.target_layers);
  GlTexture2D heights(NoCreate);
  if (frames.bumpy) {
    heights = GlTexture2D();
    glTextureStorage2D(heights.id(), 1, GL_R32F, width, rows);
    glTextureSubImage2D(heights.id(), 0, 0, 0, width, rows, GL_RED, GL_FLOAT,
                        request.receiver.heightfield.data() + size_t(first_row) * width);
    glTextureParameteri(heights.id(), GL_TEXTURE_MIN_FILTER, GL_NEAREST);
    glTextureParameteri(heights.id(), GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  }
  GlFramebuffer framebuffer;
  glBindFramebuffer(GL_FRAMEBUFFER, framebuffer.id());
  // The whole receiver's viewport, shifted so that the band's rows land in
  // the band's targets: texel centres, and so the bits, are those of a
  // single full-size draw.
  glViewport(0, -first_row, width, height);
  glDisable(GL_DEPTH_TEST);
  glDisable(GL_CULL_FACE);
  glDisable(GL_BLEND);
  glEnable(GL_COLOR_LOGIC_OP);
  glLogicOp(GL_OR);
  VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* resources, scene.CurrentResources());
  glBindVertexArray(resources->vertex_array.id());
  glBindTextureUnit(0, table.texture.id());
  glBindTextureUnit(1, frames.bumpy ? heights.id() : 0);
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, table.samples.id());

  for (int pass = 0; pass < plan.passes; ++pass) {
    VISQ_RETURN_IF_ERROR(job.stop.Check("hidden-sample map: between passes"));
    const int first = pass * plan.groups_per_pass;
    const int count = std::min(plan.groups_per_pass, plan.groups - first);
    VISQ_ASSIGN_OR_RETURN(
        const TypedProgram<HsmDrawUniforms>* program,
        CachedProgram<HsmDrawUniforms>(hidden_sample_map_shaders::Find,
                                       {{GL_VERTEX_SHADER, "hsm_draw.vert"},
                                        {GL_GEOMETRY_SHADER, "hsm_draw.geom"},
                                        {GL_FRAGMENT_SHADER, "hsm_draw.frag"}},
                                       {{"GROUPS", std::to_string(count)}, {"EXACT_LOOKUP", plan.exact ? "1" : "0"}}));
    SetPassUniforms(program->uniforms, frames, request, table, first, plan.groups, first_row);

    // Attach this pass's layers: maybe (or exact) masks, then for HOUGH the
    // surely-blocked masks.
    std::vector<GLenum> buffers;
    const int attached = plan.exact ? count : 2 * count;
    for (int k = 0; k < attached; ++k) {
      const int layer = k < count ? first + k : plan.groups + first + (k - count);
      glNamedFramebufferTextureLayer(framebuffer.id(), GL_COLOR_ATTACHMENT0 + k, targets.id(), 0, layer);
      buffers.push_back(GL_COLOR_ATTACHMENT0 + k);
    }
    for (int k = attached; k < max_draw_buffers; ++k)
      glNamedFramebufferTextureLayer(framebuffer.id(), GL_COLOR_ATTACHMENT0 + k, 0, 0, 0);
    glNamedFramebufferDrawBuffers(framebuffer.id(), static_cast<GLsizei>(buffers.size()), buffers.data());
    if (glCheckNamedFramebufferStatus(framebuffer.id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
      return absl::InternalError("hidden-sample map: framebuffer incomplete");
    const GLuint zero[4] = {0, 0, 0, 0};
    for (int k = 0; k < attached; ++k) glClearBufferuiv(GL_COLOR, k, zero);
    glUseProgram(program->id());
    GlQueryFragmentsShaded fragments(NoCreate);
    if (fragments_shaded != nullptr) {
      fragments = GlQueryFragmentsShaded();
      glBeginQuery(GL_FRAGMENT_SHADER_INVOCATIONS, fragments.id());
    }
    VISQ_RETURN_IF_ERROR(DrawInTimedPieces(scene, draw, pieces, job, "hidden-sample map: between draws"));
    if (fragments_shaded != nullptr) {
      glEndQuery(GL_FRAGMENT_SHADER_INVOCATIONS);
      GLuint64 shaded = 0;
      glGetQueryObjectui64v(fragments.id(), GL_QUERY_RESULT, &shaded);
      *fragments_shaded += shaded;
    }
    VISQ_GL_CHECK("hidden-sample map pass");
  }
  glDisable(GL_COLOR_LOGIC_OP);
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glUseProgram(0);
  readback.resize(size_t(plan.target_layers) * width * rows * 4);
  glGetTextureImage(targets.id(), 0, GL_RGBA_INTEGER, GL_UNSIGNED_INT,
                    static_cast<GLsizei>(readback.size() * sizeof(uint32_t)), readback.data());
  return CollectGlErrors("hidden-sample map");
}

// Bit counting (section 8) for one band's read-back into `band` (its
// texels from 0); words beyond N are masked off. The Hough lookup's worst
// texel goes into the map's bound.
void CountBand(const std::vector<uint32_t>& readback, const PassPlan& plan, size_t band_texels,
               const HiddenSampleMapOptions& options, const glm::dvec3& all_colors, HiddenSampleMapResult& map,
               HiddenSampleMapBand& band) {
  const int n = map.sample_count;
  const int wpt = map.words_per_texel;
  VISQ_DCHECK_EQ(readback.size(), size_t(plan.target_layers) * band_texels * 4);
  VISQ_DCHECK_LE(size_t(wpt), size_t(4 * plan.groups));
  const uint32_t last_mask = (n % 32 == 0) ? ~0u : ((1u << (n % 32)) - 1u);
  auto word_at = [&](int plane_layer_base, size_t texel, int w) {
    const int layer = plane_layer_base + w / 4;
    return readback[(size_t(layer) * band_texels + texel) * 4 + (w & 3)] & (w == wpt - 1 ? last_mask : ~0u);
  };
  const bool colored = !map.samples.color.empty();
  band.visible_fraction.resize(band_texels);
  band.visible_rgb.resize(colored ? band_texels : 0);
  band.blocked_bits.resize(options.want_bitmasks ? band_texels * size_t(wpt) : 0);
  band.lookup_error.resize(plan.exact ? 0 : band_texels);
  band.split_pairs.resize(band_texels);
  std::vector<uint32_t> answer_words(size_t(wpt), 0u), sure_words(plan.exact ? 0 : size_t(wpt), 0u);
  for (size_t t = 0; t < band_texels; ++t) {
    int blocked = 0, sure = 0;
    glm::dvec3 blocked_color(0.0);
    for (int w = 0; w < wpt; ++w) {
      const uint32_t word = word_at(0, t, w);
      answer_words[size_t(w)] = word;
      blocked += std::popcount(word);
      if (options.want_bitmasks) band.blocked_bits[t * wpt + w] = word;
      if (!plan.exact) {
        sure_words[size_t(w)] = word_at(plan.groups, t, w);
        sure += std::popcount(sure_words[size_t(w)]);
      }
      if (colored)
        for (uint32_t bits = word; bits != 0; bits &= bits - 1)
          blocked_color += glm::dvec3(map.samples.color[w * 32 + std::countr_zero(bits)]);
    }
    band.visible_fraction[t] = float(n - blocked) / float(n);
    band.split_pairs[t] = plan.exact ? sampling::SplitPairs(answer_words, n)
                                     : sampling::SplitPairsAtMost(answer_words, sure_words, n);
    if (colored) band.visible_rgb[t] = glm::vec3((all_colors - blocked_color) / double(n));
    if (!plan.exact) {
      band.lookup_error[t] = float(blocked - sure) / float(n);
      map.error.lookup_max = std::max(map.error.lookup_max, double(blocked - sure) / n);
    }
  }
}

}  // namespace

StatusOr<HiddenSampleMapResult> HiddenSampleMapper::Compute(const GpuScene& scene,
                                                            const HiddenSampleMapRequest& request,
                                                            const JobOptions& job,
                                                            const HiddenSampleMapBandSink& sink) {
  VISQ_RETURN_IF_ERROR(ValidateHiddenSampleMapRequest(request));
  const HiddenSampleMapOptions& options = request.options;
  HiddenSampleMapResult result;
  VISQ_ASSIGN_OR_RETURN(result.samples, ComputeSourceSamples(request.source));
  const int n = static_cast<int>(result.samples.uv.size());
  const int width = request.receiver.width, height = request.receiver.height;
  result.width = width;
  result.height = height;
  result.sample_count = n;
  result.words_per_texel = (n + 31) / 32;

  std::vector<glm::vec2> centred;
  for (const glm::dvec2& uv : result.samples.uv)
    centred.emplace_back(static_cast<float>(uv.x - 0.5), static_cast<float>(uv.y - 0.5));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<Table> table,
                        CachedTable(*state_, *worker_, centred, options, job, result.table_ms));
  VISQ_ASSIGN_OR_RETURN(const MapFrames frames, PlanFrames(request, scene));
  const ScenePartDraw draw = PlanDraw(scene, frames, options_.cull_clusters);
  const PassPlan plan = PlanPasses(table->layout.groups(), options.lookup == LookupMode::kExact,
                                   state_->max_draw_buffers, width, height, options_.band_readback_bytes);
  result.passes = plan.passes;

  glm::dvec3 all_colors(0.0);
  for (const glm::vec3& c : result.samples.color) all_colors += glm::dvec3(c);

  // One GL job per band: a large map yields the GL thread between bands,
  // and no band runs much past band_target_ms.
  const double texel_passes_per_row = double(width) * plan.passes;
  int start_rows = plan.band_rows;
  if (options_.band_target_ms > 0.0) {
    std::lock_guard lock(band_sizes_->mutex);
    auto known = band_sizes_->texel_passes.find(&scene);
    // A scene not yet measured starts small (64K texel-passes: a few ms on a
    // GPU, tens on llvmpipe) and doubles from there.
    constexpr double kFirstBandTexelPasses = 65536.0;
    const double texel_passes = known != band_sizes_->texel_passes.end() ? known->second : kFirstBandTexelPasses;
    start_rows = int(texel_passes / texel_passes_per_row);
  }
  TimedSizer sizer(options_.band_target_ms, plan.band_rows, start_rows);
  // Pieces of a pass: a quarter of a band's target each, from the scene's
  // last size; when none, about 2^20 triangle-texels (a triangle's
  // influence region can cover the band: on a CPU rasterizer a big
  // receiver's pass over a real scene takes minutes).
  const double first_band_texels = double(std::clamp(start_rows, 1, plan.band_rows)) * width;
  int start_piece = int(std::clamp(double(1 << 20) / first_band_texels, 16.0, 8192.0));
  {
    std::lock_guard lock(band_sizes_->mutex);
    auto known = band_sizes_->piece_triangles.find(&scene);
    if (known != band_sizes_->piece_triangles.end()) start_piece = known->second;
  }
  const int draw_triangles = int(std::clamp<uint64_t>(draw.triangles, 1, INT32_MAX));
  TimedSizer pieces(options_.band_target_ms > 0.0 ? options_.band_target_ms / 4.0 : 0.0, draw_triangles,
                   options_.band_target_ms > 0.0 ? start_piece : draw_triangles);
  std::vector<uint32_t> readback;
  HiddenSampleMapBand band;
  const int max_draw_buffers = state_->max_draw_buffers;
  for (int first_row = 0, rows = 0; first_row < height; first_row += rows) {
    rows = std::min(sizer.size(), height - first_row);
    JobTiming band_timing;
    VISQ_RETURN_IF_ERROR(worker_->Run(job, [&]() -> Status {
      return DrawBand(scene, *table, frames, request, draw, plan, max_draw_buffers, first_row, rows, job, pieces,
                      readback, state_->count_fragments ? &state_->fragments_shaded : nullptr);
    }, &band_timing));
    sizer.Measured(rows, band_timing.run_ms);
    result.timing.queue_ms += band_timing.queue_ms;
    result.timing.run_ms += band_timing.run_ms;
    band.first = size_t(first_row) * width;
    CountBand(readback, plan, size_t(rows) * width, options, all_colors, result, band);
    BoundTexels(request, result, band);
    VISQ_RETURN_IF_ERROR(DeliverBand(result, band, sink));
  }
  if (options_.band_target_ms > 0.0) {
    std::lock_guard lock(band_sizes_->mutex);
    if (band_sizes_->texel_passes.size() >= 64) {
      band_sizes_->texel_passes.clear();
      band_sizes_->piece_triangles.clear();
    }
    band_sizes_->texel_passes[&scene] = sizer.size() * texel_passes_per_row;
    band_sizes_->piece_triangles[&scene] = pieces.size();
  }
  result.error.confidence = options.confidence;
  result.error.sampling = SamplingErrorBound(n, options.confidence);
  result.error.rigorous = SamplesAreIndependentStrata(request);
  return result;
}

StatusOr<uint64_t> HiddenSampleMapper::TrianglesDrawnPerPass(const GpuScene& scene,
                                                            const HiddenSampleMapRequest& request) const {
  VISQ_RETURN_IF_ERROR(ValidateHiddenSampleMapRequest(request));
  VISQ_ASSIGN_OR_RETURN(const MapFrames frames, PlanFrames(request, scene));
  return PlanDraw(scene, frames, options_.cull_clusters).triangles;
}

StatusOr<PatchVisibilityResult> HiddenSampleMapper::PatchVisibility(const GpuScene& scene,
                                                                    const PatchVisibilityRequest& request,
                                                                    const JobOptions& job) {
  VISQ_ASSIGN_OR_RETURN(HiddenSampleMapRequest map, PatchVisibilityAsHiddenSampleMap(request));
  VISQ_ASSIGN_OR_RETURN(HiddenSampleMapResult hsm, Compute(scene, map, job));
  return SummarizePatchVisibility(request, hsm);
}

}  // namespace visq::gpu
