// Volumetric shadows with epipolar rectification and 1D min-max mipmaps
// (Chen, Baran, Durand, Jarosz 2011). See visq/gpu/volumetric_shadows.h for
// the model and the API. Shaders: vol_shadow.vert/.frag (shadow map),
// vol_shadow.vert + vol_camera.frag (camera distances and normals),
// vol_rectify.comp, vol_minmax.comp, vol_prefix.comp, vol_integrate.comp.
//
// Pipeline of one call, each stage a GL job of its own, closed by glFinish
// and timed (the traversal a job per band of image rows):
//   1. shadow map: the scene's depth from the light (DEPTH32F, N x N);
//   2. camera: distance to the first surface, face normal, material color;
//   3. rectification: N rows (epipolar slices) x N columns (distance from the
//      epipole) resampled from the shadow map (nearest), plus the light's
//      per-texel weights when the integrand needs them (and, for the SVD
//      integrand, each texel's angle at the light from the light-to-eye
//      direction);
//   4. mipmap: per row, log2(N) min-max levels (the traversal's; ray
//      marching reads none) and prefix sums (one per row
//      for kPrefixSum, K interleaved in double for kSvd, with each texel's K
//      terms in float);
//   5. traversal: one invocation per pixel, min-max traversal or ray
//      marching (the same shader, RAY_MARCH defined or not).
// All geometry is set up here in double relative to the scene's anchor and
// handed to GL as float, so a scene translated far from the origin renders
// the same image.
#include "visq/gpu/volumetric_shadows.h"

#include <algorithm>
#include <array>
#include <bit>
#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <mutex>
#include <numbers>

#include <epoxy/gl.h>
#include <fmt/format.h>
#include <glm/gtc/matrix_transform.hpp>
#include <glm/gtc/type_ptr.hpp>

#include "common/check.h"
#include "common/coordinates.h"
#include "common/job_timing.h"
#include "gl_check.h"
#include "gl_state_across_jobs.h"
#include "gl_object.h"
#include "gpu_scene_resources.h"
#include "scene_draw.h"
#include "shader_program.h"
#include "svd_integrand.h"
#include "visq_gpu_volumetric_shadows_embedded.h"

namespace visq::gpu {
namespace {

using Clock = std::chrono::steady_clock;

// Bias of the medium's shadow test, in shadow-map texels of depth: a ray
// grazing a lit receiver runs within a texel's depth variation of it for a
// long way, and the nearest-resampled depth of the neighbouring texel would
// shadow that stretch. Two texels cover receivers up to ~63 degrees from
// facing the light. Spot lights: the same at the geometric middle of the
// frustum's depth range (window depth is not linear there).
constexpr double kMediumBiasTexels = 2.0;
// Farthest epipole accepted, in shadow-map widths from the map's center:
// beyond it float column coordinates lose sub-texel precision.
constexpr double kMaxEpipoleDistance = 256.0;

bool Finite(double v) { return std::isfinite(v); }
bool Finite(const glm::dvec3& v) { return Finite(v.x) && Finite(v.y) && Finite(v.z); }
std::string Vec(const glm::dvec3& v) { return fmt::format("({}, {}, {})", v.x, v.y, v.z); }

Status Invalid(std::string message) { return absl::InvalidArgumentError(message); }

// Everything the GL passes need, computed in double on the calling thread.
struct Setup {
  uint32_t map_size = 0, rows = 0, cols = 0, levels = 0;
  uint32_t width = 0, height = 0;
  bool spot = false;
  VolumetricIntegrand integrand = VolumetricIntegrand::kAnalytic;
  bool weighted = false;
  glm::dmat4 light_clip{1.0};    // light clip space from anchor-relative positions
  glm::dmat4 camera_clip{1.0};   // camera clip space from anchor-relative positions
  glm::dvec3 eye{0.0};           // anchor-relative
  glm::dvec3 cam_forward{0.0}, cam_right{0.0}, cam_up{0.0};
  glm::dvec4 c0{0.0};            // light clip of the eye
  glm::dvec2 epipole{0.0};       // shadow-map texels
  bool epipole_inside = false;
  double theta_ref = 0, theta_min_rel = 0, dtheta = 0, r0 = 0, dr = 0;
  double half_depth = 0;         // directional: the shadow map box's half depth
  double medium_start = 0;       // directional: the medium's entry plane below that box's near face
  Bounds medium;                 // anchor-relative: the camera rays' part that scatters
  double tan_half = 0, cos_outer = 0, cos_inner = 0;
  double normal_offset = 0;
  double bias = 0;               // window depth
  glm::dvec3 light_dir{0.0}, light_pos{0.0};
  double light_reach = 0;        // spot: the farthest point of the frustum from the light
  glm::dvec3 eye_in_light{0.0};  // spot: direction light -> eye in the light's (u, v, w) frame
  SvdIntegrandTable svd;         // kSvd only
  double svd_ms = 0;
  glm::dvec2 texel_world{0.0};   // directional: a shadow-map texel's world size
  double eye_light_distance = 0;
  VolumetricBox box;
  std::vector<glm::vec4> albedo;
};

// The SVD tables of the last few calls: a still camera and light reuse theirs.
struct SvdKey {
  bool spot;
  double sigma_t_d, g, max_depth, tolerance;  // directional: sigma_t, 0, p_max, tolerance
  bool operator==(const SvdKey&) const = default;
};

SvdIntegrandTable CachedSvdTable(const SvdKey& key) {
  static std::mutex mutex;
  static std::vector<std::pair<SvdKey, SvdIntegrandTable>> recent;  // most recent last
  constexpr size_t kKept = 4;
  {
    std::lock_guard lock(mutex);
    for (size_t i = 0; i < recent.size(); ++i) {
      if (recent[i].first == key) {
        std::rotate(recent.begin() + i, recent.begin() + i + 1, recent.end());
        return recent.back().second;
      }
    }
  }
  SvdIntegrandTable table =
      key.spot ? BuildSpotSvdTable(key.sigma_t_d, key.g, key.max_depth, kSvdAlphaMargin,
                                   std::numbers::pi - kSvdAlphaMargin, key.tolerance)
               : BuildDirectionalSvdTable(key.sigma_t_d, key.max_depth, kSvdAlphaMargin,
                                          std::numbers::pi - kSvdAlphaMargin, key.tolerance);
  std::lock_guard lock(mutex);
  if (recent.size() == kKept) recent.erase(recent.begin());
  recent.emplace_back(key, table);
  return table;
}

// Rows of a clip matrix: clip_r = dot(row_r.xyz, p) + row_r.w.
glm::dmat4 FromRows(const std::array<glm::dvec4, 4>& rows) {
  glm::dmat4 m(0.0);
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) m[c][r] = rows[r][c];
  return m;
}

// The eight corners of `b`, relative to the scene's anchor.
std::array<glm::dvec3, 8> CornersOf(const Bounds& b, const glm::dvec3& anchor) {
  std::array<glm::dvec3, 8> corners;
  for (int i = 0; i < 8; ++i)
    corners[i] = glm::dvec3(i & 1 ? b.max.x : b.min.x, i & 2 ? b.max.y : b.min.y, i & 4 ? b.max.z : b.min.z) - anchor;
  return corners;
}

// The light's frame: w along the light, v its up, u = w x v its right.
struct LightFrame {
  glm::dvec3 u, v, w;
};

// A directional light's shadow map: an orthographic box in the light's frame.
void FrameDirectionalLight(const Scene& scene, const Bounds& medium, const LightFrame& frame, const glm::dvec3& anchor,
                           double diagonal, Setup& setup) {
  const glm::dvec3 &u = frame.u, &v = frame.v, &w = frame.w;
  // The medium's box in the light's frame around its corners; the shadow
  // map's box is the same, deepened towards the light over the scene's
  // corners there: occluders above the medium shadow it.
  auto light_frame_box = [&](const std::array<glm::dvec3, 8>& points, glm::dvec3& center, glm::dvec3& half) {
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    for (const auto& p : points) {
      const glm::dvec3 q(glm::dot(p, u), glm::dot(p, v), glm::dot(p, w));
      lo = glm::min(lo, q);
      hi = glm::max(hi, q);
    }
    center = 0.5 * (lo + hi);
    half = glm::max(0.5 * (hi - lo) * 1.01, glm::dvec3(1e-3 * diagonal));
  };
  glm::dvec3 center, half;
  light_frame_box(CornersOf(medium, anchor), center, half);
  setup.box.center = anchor + center.x * u + center.y * v + center.z * w;
  setup.box.axis[0] = u;
  setup.box.axis[1] = v;
  setup.box.axis[2] = w;
  setup.box.half_extent = half;
  const double medium_near = center.z - half.z;
  double scene_near = medium_near;
  if (!scene.bounds.Empty())
    for (const auto& p : CornersOf(scene.bounds, anchor)) scene_near = std::min(scene_near, glm::dot(p, w));
  if (scene_near < medium_near) {
    const double far = center.z + half.z;
    const double near = scene_near - 0.005 * (far - scene_near);
    center.z = 0.5 * (near + far);
    half.z = 0.5 * (far - near);
  }
  setup.medium_start = medium_near - (center.z - half.z);
  setup.light_clip = FromRows({glm::dvec4(u / half.x, -center.x / half.x), glm::dvec4(v / half.y, -center.y / half.y),
                               glm::dvec4(w / half.z, -center.z / half.z), glm::dvec4(0, 0, 0, 1)});
  setup.half_depth = half.z;
  setup.normal_offset = 1.5 * 2.0 * std::max(half.x, half.y) / setup.map_size;
  // World depth -> window depth is 1 / (2 half.z).
  setup.bias = kMediumBiasTexels * 2.0 * std::max(half.x, half.y) / setup.map_size / (2.0 * half.z);
}

// A spot light's shadow map: a square frustum along its axis.
Status FrameSpotLight(const VolumetricLight& light, const std::array<glm::dvec3, 8>& corners, const LightFrame& frame,
                      const glm::dvec3& anchor, double diagonal, Setup& setup) {
  const glm::dvec3 &u = frame.u, &v = frame.v, &w = frame.w;
  // The cone's square frustum from a near plane close to the light to
  // beyond the farthest corner.
  const glm::dvec3 l = light.position - anchor;
  double far_depth = 0;
  for (const auto& p : corners) far_depth = std::max(far_depth, glm::dot(p - l, w));
  const double near_depth = 5e-3 * diagonal;
  far_depth *= 1.01;
  if (far_depth <= near_depth)
    return absl::FailedPreconditionError(
        fmt::format("light.direction: the scene lies behind the spot light at {}", Vec(light.position)));
  const double tan_half = std::tan(light.cone_angle_deg * std::numbers::pi / 180.0);
  const double a = (far_depth + near_depth) / (far_depth - near_depth);
  const double b = -2.0 * far_depth * near_depth / (far_depth - near_depth);
  setup.light_clip = FromRows({glm::dvec4(u / tan_half, -glm::dot(u, l) / tan_half),
                               glm::dvec4(v / tan_half, -glm::dot(v, l) / tan_half),
                               glm::dvec4(a * w, -a * glm::dot(w, l) + b), glm::dvec4(w, -glm::dot(w, l))});
  setup.light_pos = l;
  setup.tan_half = tan_half;
  setup.light_reach = far_depth * std::sqrt(1.0 + 2.0 * tan_half * tan_half);
  setup.cos_outer = std::cos(light.cone_angle_deg * std::numbers::pi / 180.0);
  setup.cos_inner =
      std::cos(std::max(0.0, light.cone_angle_deg - light.cone_falloff_deg) * std::numbers::pi / 180.0);
  setup.normal_offset = 1.5 * 2.0 * tan_half / setup.map_size;
  // Window depth = (a + b / z) / 2 + 1/2: d/dz = -b / (2 z^2).
  const double z_mid = std::sqrt(near_depth * far_depth);
  setup.bias = kMediumBiasTexels * (2.0 * tan_half * z_mid / setup.map_size) * std::abs(b) / (2.0 * z_mid * z_mid);
  return absl::OkStatus();
}

// The shadow map's rows as slices around the epipole (setup.epipole set).
void RectifyAroundTheEpipole(Setup& setup) {
  const double n = setup.map_size;
  // Rectification: slices over the full circle when the epipole lies inside
  // the map, else over the angles the map subtends from it.
  const std::array<glm::dvec2, 4> square = {glm::dvec2(0, 0), glm::dvec2(n, 0), glm::dvec2(0, n), glm::dvec2(n, n)};
  double r_max = 0;
  for (const auto& c : square) r_max = std::max(r_max, glm::length(c - setup.epipole));
  setup.epipole_inside = setup.epipole.x > 0 && setup.epipole.x < n && setup.epipole.y > 0 && setup.epipole.y < n;
  if (setup.epipole_inside) {
    setup.theta_ref = 0;
    setup.theta_min_rel = -std::numbers::pi;
    setup.dtheta = 2 * std::numbers::pi / setup.rows;
    setup.r0 = 0;
  } else {
    const glm::dvec2 to_center = glm::dvec2(0.5 * n) - setup.epipole;
    setup.theta_ref = std::atan2(to_center.y, to_center.x);
    double lo = std::numbers::pi, hi = -std::numbers::pi;
    for (const auto& c : square) {
      double rel = std::atan2(c.y - setup.epipole.y, c.x - setup.epipole.x) - setup.theta_ref;
      rel -= 2 * std::numbers::pi * std::floor((rel + std::numbers::pi) / (2 * std::numbers::pi));
      lo = std::min(lo, rel);
      hi = std::max(hi, rel);
    }
    setup.theta_min_rel = lo;
    setup.dtheta = (hi - lo) / setup.rows;
    const glm::dvec2 nearest = glm::clamp(setup.epipole, glm::dvec2(0.0), glm::dvec2(n));
    setup.r0 = glm::length(nearest - setup.epipole);
  }
  setup.dr = (r_max - setup.r0) / setup.cols;
}

// Which integrand the traversal evaluates, and its SVD table if any.
void ChooseIntegrand(const VolumetricParams& params, const LightFrame& frame, double diagonal, Setup& setup) {
  const glm::dvec3 &u = frame.u, &v = frame.v, &w = frame.w;
  const VolumetricLight& light = params.light;
  const double n = setup.map_size;
  const std::array<glm::dvec2, 4> square = {glm::dvec2(0, 0), glm::dvec2(n, 0), glm::dvec2(0, n), glm::dvec2(n, n)};
  const bool textured = !light.texture.empty();
  const bool zero_extinction = params.medium.extinction == 0.0 || params.medium.optically_thin;
  if (!setup.spot && !textured) {
    setup.integrand = VolumetricIntegrand::kAnalytic;
  } else if (zero_extinction && (!setup.spot || params.medium.hg_g == 0.0)) {
    setup.integrand = VolumetricIntegrand::kPrefixSum;
  } else {
    setup.integrand = VolumetricIntegrand::kPerTexel;
  }
  const glm::dvec3 to_eye = setup.eye - setup.light_pos;
  setup.eye_light_distance = glm::length(to_eye);
  if (setup.spot && setup.integrand == VolumetricIntegrand::kPerTexel &&
      params.integrand_choice != VolumetricIntegrandChoice::kExact && setup.eye_light_distance > 1e-6 * diagonal) {
    // The SVD of f(alpha, phi) for this sigma_t d and phase (svd_integrand.h).
    const double sigma_t = zero_extinction ? 0.0 : params.medium.extinction;
    const auto svd_start = Clock::now();
    setup.svd = CachedSvdTable({true, sigma_t * setup.eye_light_distance, params.medium.hg_g,
                                2.0 * sigma_t * setup.light_reach, params.svd_tolerance});
    setup.svd_ms = MillisecondsSince(svd_start);
    setup.integrand = VolumetricIntegrand::kSvd;
    setup.eye_in_light = glm::normalize(glm::dvec3(glm::dot(to_eye, u), glm::dot(to_eye, v), glm::dot(to_eye, w)));
  } else if (!setup.spot && setup.integrand == VolumetricIntegrand::kPerTexel &&
             params.integrand_choice == VolumetricIntegrandChoice::kSvd) {
    // The SVD of f(alpha, p) over the offsets p the map holds from the eye's light ray.
    setup.texel_world = 2.0 * glm::dvec2(setup.box.half_extent) / n;
    double p_max = 0;
    for (const auto& c : square) p_max = std::max(p_max, glm::length((c - setup.epipole) * setup.texel_world));
    const auto svd_start = Clock::now();
    setup.svd = CachedSvdTable({false, params.medium.extinction, 0.0, p_max, params.svd_tolerance});
    setup.svd_ms = MillisecondsSince(svd_start);
    setup.integrand = VolumetricIntegrand::kSvd;
  }
  setup.weighted = setup.integrand != VolumetricIntegrand::kAnalytic;
}

StatusOr<Setup> BuildSetup(const GpuScene& gpu_scene, const Scene& scene, const VolumetricParams& params) {
  Setup setup;
  const glm::dvec3 anchor = gpu_scene.anchor();
  const VolumetricCamera& camera = params.camera;
  const VolumetricLight& light = params.light;
  setup.map_size = params.shadow_map_size;
  setup.rows = setup.cols = params.shadow_map_size;
  setup.levels = static_cast<uint32_t>(std::countr_zero(setup.cols));
  setup.width = camera.width;
  setup.height = camera.height;
  setup.spot = light.kind == VolumetricLightKind::kSpot;

  // The medium: its box (the scene's bounds unless the request gives one).
  // The camera sees the scene and the medium; the shadow map covers the
  // medium and whatever lies between it and the light.
  const Bounds medium = params.medium_bounds.Empty() ? scene.bounds : params.medium_bounds;
  if (medium.Empty()) return absl::FailedPreconditionError("volumetric shadows: the scene has no geometry and no medium box");
  Bounds bounds = medium;
  if (!scene.bounds.Empty()) {
    bounds.Extend(scene.bounds.min);
    bounds.Extend(scene.bounds.max);
  }
  setup.medium.Extend(medium.min - anchor);
  setup.medium.Extend(medium.max - anchor);
  const double diagonal = std::max(glm::length(bounds.Extent()), 1e-9);
  const std::array<glm::dvec3, 8> corners = CornersOf(bounds, anchor);

  // The light's frame (LightFrame).
  const glm::dvec3 w = glm::normalize(light.direction);
  glm::dvec3 up = light.up;
  if (glm::length(up) == 0.0) up = std::abs(w.y) > 0.99 ? glm::dvec3(0, 0, 1) : glm::dvec3(0, 1, 0);
  glm::dvec3 v = up - glm::dot(up, w) * w;
  if (glm::length(v) < 1e-9) return Invalid(fmt::format("light.up: {} is parallel to light.direction", Vec(light.up)));
  v = glm::normalize(v);
  const glm::dvec3 u = glm::cross(w, v);
  setup.light_dir = w;

  const LightFrame frame{u, v, w};
  if (setup.spot) {
    VISQ_RETURN_IF_ERROR(FrameSpotLight(light, corners, frame, anchor, diagonal, setup));
  } else {
    FrameDirectionalLight(scene, medium, frame, anchor, diagonal, setup);
  }

  // The camera: rays through pixel centers, and the matching raster transform.
  setup.eye = camera.position - anchor;
  const glm::dvec3 f = glm::normalize(camera.forward);
  const glm::dvec3 r = glm::normalize(glm::cross(f, camera.up));
  const glm::dvec3 cu = glm::cross(r, f);
  const double aspect = double(camera.width) / camera.height;
  const double tan_y = std::tan(0.5 * camera.vertical_fov_deg * std::numbers::pi / 180.0);
  setup.cam_forward = f;
  setup.cam_right = r * tan_y * aspect;
  setup.cam_up = cu * tan_y;
  // The raster transform every pinhole image shares (camera.h), over the
  // medium's bounds as well as the scene's.
  setup.camera_clip = PinholeClipFromAnchor(camera, anchor, bounds);

  // The epipole: the eye in the shadow map.
  setup.c0 = setup.light_clip * glm::dvec4(setup.eye, 1.0);
  const double n = setup.map_size;
  if (std::abs(setup.c0.w) < 1e-12 * diagonal)
    return absl::FailedPreconditionError(fmt::format(
        "camera.position: {} lies in the spot light's plane (the epipole is at infinity); move it off that plane",
        Vec(camera.position)));
  setup.epipole = (glm::dvec2(setup.c0) / setup.c0.w * 0.5 + 0.5) * n;
  if (glm::length(setup.epipole - glm::dvec2(0.5 * n)) > kMaxEpipoleDistance * n)
    return absl::FailedPreconditionError(fmt::format(
        "camera.position: {} projects {} shadow-map widths from the map (more than {}): too close to the spot "
        "light's plane for float rectification",
        Vec(camera.position), glm::length(setup.epipole - glm::dvec2(0.5 * n)) / n, kMaxEpipoleDistance));

  RectifyAroundTheEpipole(setup);
  ChooseIntegrand(params, frame, diagonal, setup);

  for (const auto& m : scene.materials) setup.albedo.emplace_back(glm::vec3(m.reflectivity), 1.0f);
  if (setup.albedo.empty()) setup.albedo.emplace_back(1.0f);
  return setup;
}

// The algorithm's programs and their uniforms. vol_light.glsl's and the
// rectification's are shared by two programs each.
struct LightUniforms {
  explicit LightUniforms(UniformLocator& at)
      : texture_size(at.Find<glm::ivec2>("u_texture_size")),
        tan_half(at.Find<float>("u_tan_half")),
        cos_outer(at.Find<float>("u_cos_outer")),
        cos_inner(at.Find<float>("u_cos_inner")) {}
  Uniform<glm::ivec2> texture_size;  // (0, 0): no texture
  Uniform<float> tan_half, cos_outer, cos_inner;
};

struct RectUniforms {
  explicit RectUniforms(UniformLocator& at)
      : epipole(at.Find<glm::vec2>("u_epipole")),
        theta_ref(at.Find<float>("u_theta_ref")),
        theta_min_rel(at.Find<float>("u_theta_min_rel")),
        dtheta(at.Find<float>("u_dtheta")),
        r0(at.Find<float>("u_r0")),
        dr(at.Find<float>("u_dr")),
        rows(at.Find<int>("u_rows")),
        cols(at.Find<int>("u_cols")) {}
  Uniform<glm::vec2> epipole;
  Uniform<float> theta_ref, theta_min_rel, dtheta, r0, dr;
  Uniform<int> rows, cols;
};

struct SceneDrawUniforms {  // vol_shadow.vert, with vol_shadow.frag or vol_camera.frag
  explicit SceneDrawUniforms(UniformLocator& at)
      : clip_from_anchor(at.Find<glm::mat4>("u_clip_from_anchor")), eye(at.FindInVariant<glm::vec3>("u_eye")) {}
  Uniform<glm::mat4> clip_from_anchor;
  Uniform<glm::vec3> eye;  // vol_camera.frag's
};

struct RectifyUniforms {
  explicit RectifyUniforms(UniformLocator& at)
      : rect(at),
        light(at),
        map_size(at.Find<int>("u_map_size")),
        eye_in_light(at.Find<glm::vec3>("u_eye_in_light")),
        texel_world(at.Find<glm::vec2>("u_texel_world")) {}
  RectUniforms rect;
  LightUniforms light;
  Uniform<int> map_size;
  Uniform<glm::vec3> eye_in_light;
  Uniform<glm::vec2> texel_world;
};

struct MinMaxUniforms {
  explicit MinMaxUniforms(UniformLocator& at)
      : level(at.Find<int>("u_level")), cols(at.Find<int>("u_cols")), rows(at.Find<int>("u_rows")) {}
  Uniform<int> level, cols, rows;
};

struct PrefixUniforms {
  explicit PrefixUniforms(UniformLocator& at)
      : cols(at.Find<int>("u_cols")), rows(at.Find<int>("u_rows")), svd_x_step(at.Find<float>("u_svd_x_step")) {}
  Uniform<int> cols, rows;
  Uniform<float> svd_x_step;
};

struct IntegrateUniforms {
  explicit IntegrateUniforms(UniformLocator& at)
      : rect(at),
        light(at),
        light_clip(at.Find<glm::mat4>("u_light_clip")),
        c0(at.Find<glm::vec4>("u_c0")),
        image_size(at.Find<glm::ivec2>("u_image_size")),
        first_row(at.Find<int>("u_first_row")),
        eye(at.Find<glm::vec3>("u_eye")),
        cam_forward(at.Find<glm::vec3>("u_cam_forward")),
        cam_right(at.Find<glm::vec3>("u_cam_right")),
        cam_up(at.Find<glm::vec3>("u_cam_up")),
        light_dir(at.Find<glm::vec3>("u_light_dir")),
        light_pos(at.Find<glm::vec3>("u_light_pos")),
        map_size(at.Find<float>("u_map_size")),
        levels(at.Find<int>("u_levels")),
        bias(at.Find<float>("u_bias")),
        sigma_s(at.Find<float>("u_sigma_s")),
        sigma_t(at.Find<float>("u_sigma_t")),
        g(at.Find<float>("u_g")),
        intensity(at.Find<float>("u_intensity")),
        half_depth(at.Find<float>("u_half_depth")),
        medium_start(at.Find<float>("u_medium_start")),
        medium_min(at.Find<glm::vec3>("u_medium_min")),
        medium_max(at.Find<glm::vec3>("u_medium_max")),
        direct(at.Find<int>("u_direct")),
        normal_offset(at.Find<float>("u_normal_offset")),
        svd_alpha0(at.Find<float>("u_svd_alpha0")),
        svd_alpha_step(at.Find<float>("u_svd_alpha_step")),
        eye_light_distance(at.Find<float>("u_eye_light_distance")) {}
  RectUniforms rect;
  LightUniforms light;
  Uniform<glm::mat4> light_clip;
  Uniform<glm::vec4> c0;
  Uniform<glm::ivec2> image_size;
  Uniform<int> first_row;
  Uniform<glm::vec3> eye, cam_forward, cam_right, cam_up, light_dir, light_pos;
  Uniform<float> map_size;
  Uniform<int> levels;
  Uniform<float> bias, sigma_s, sigma_t, g, intensity, half_depth, medium_start;
  Uniform<glm::vec3> medium_min, medium_max;
  Uniform<int> direct;
  Uniform<float> normal_offset, svd_alpha0, svd_alpha_step, eye_light_distance;
};

template <typename Uniforms>
StatusOr<const TypedProgram<Uniforms>*> Program(const std::vector<ShaderSource>& sources,
                                                const ShaderDefines& defines) {
  return CachedProgram<Uniforms>(volumetric_shadows_shaders::Find, sources, defines);
}

GlBuffer MakeBuffer(size_t bytes, const void* data = nullptr) {
  GlBuffer buffer;
  glNamedBufferStorage(buffer.id(), static_cast<GLsizeiptr>(std::max<size_t>(bytes, 16)), data, 0);
  return buffer;
}

GLuint Groups(uint32_t n, uint32_t size) { return (n + size - 1) / size; }

void SetLightUniforms(const LightUniforms& u, const Setup& setup, const VolumetricLight& light) {
  const bool textured = !light.texture.empty();
  u.texture_size.Set(textured ? glm::ivec2(GLint(light.texture_width), GLint(light.texture_height)) : glm::ivec2(0));
  u.tan_half.Set(float(setup.tan_half));
  u.cos_outer.Set(float(setup.cos_outer));
  u.cos_inner.Set(float(setup.cos_inner));
}

void SetRectUniforms(const RectUniforms& u, const Setup& setup) {
  u.epipole.Set(glm::vec2(setup.epipole));
  u.theta_ref.Set(float(setup.theta_ref));
  u.theta_min_rel.Set(float(setup.theta_min_rel));
  u.dtheta.Set(float(setup.dtheta));
  u.r0.Set(float(setup.r0));
  u.dr.Set(float(setup.dr));
  u.rows.Set(GLint(setup.rows));
  u.cols.Set(GLint(setup.cols));
}

// One rendering's programs and GL objects, made by its first GL job and
// used by the next: every stage is a GL job of its own, and the traversal
// is split into bands of image rows, so other queries get the GL thread
// between them. Each job binds what it uses and sets its programs' uniforms
// (the jobs in between may use the same cached programs).
struct VolumetricTargets {
  const TypedProgram<SceneDrawUniforms>* shadow = nullptr;  // the worker's program cache owns the programs
  const TypedProgram<SceneDrawUniforms>* camera = nullptr;
  const TypedProgram<RectifyUniforms>* rectify = nullptr;
  const TypedProgram<MinMaxUniforms>* minmax = nullptr;
  const TypedProgram<PrefixUniforms>* prefix = nullptr;
  const TypedProgram<IntegrateUniforms>* integrate = nullptr;
  GlTexture2D shadow_map{NoCreate}, geometry{NoCreate}, albedo{NoCreate};
  GlRenderbuffer camera_depth{NoCreate};
  GlFramebuffer shadow_fb{NoCreate}, camera_fb{NoCreate};
  GlBuffer rect_depth{NoCreate}, tree_min{NoCreate}, tree_max{NoCreate}, rect_weight{NoCreate}, rect_unit{NoCreate},
      prefix_sums{NoCreate}, rect_phi{NoCreate}, svd_terms{NoCreate}, svd_table{NoCreate}, light_texture{NoCreate},
      albedo_buffer{NoCreate}, output{NoCreate};
  GlVertexArray empty_vao{NoCreate};
};

// Rows per traversal job: whole 8-row groups of the shader, at least one.
uint32_t TraversalBandRows(uint32_t width, uint32_t max_pixels) {
  return std::max<uint32_t>(8, max_pixels / std::max<uint32_t>(width, 1) / 8 * 8);
}

// GL thread: the programs for `setup` (which may fall back from kSvd when
// its prefix sums exceed a storage block), the targets and the buffers.
StatusOr<std::shared_ptr<VolumetricTargets>> CreateTargets(Setup& setup, const VolumetricLight& light,
                                                           VolumetricMethod method, const JobOptions& job) {
  // kSvd's prefix sums (K doubles per row and column) must fit one storage
  // block; beyond it the per-texel sum serves.
  if (setup.integrand == VolumetricIntegrand::kSvd) {
    GLint64 max_block = 0;
    glGetInteger64v(GL_MAX_SHADER_STORAGE_BLOCK_SIZE, &max_block);
    const double bytes = double(setup.rows) * (setup.cols + 1) * setup.svd.rank * sizeof(double);  // > the terms'
    if (bytes > double(max_block)) setup.integrand = VolumetricIntegrand::kPerTexel;
  }
  const bool svd = setup.integrand == VolumetricIntegrand::kSvd;
  ShaderDefines common;
  if (setup.spot) common.emplace_back("SPOT", "1");
  if (setup.weighted) common.emplace_back("WEIGHTED", "1");
  ShaderDefines rect_defines = common;
  if (setup.weighted) rect_defines.emplace_back("WEIGHTS", "1");
  ShaderDefines svd_defines;
  if (svd) {
    svd_defines = {{"INTEGRAND_SVD", "1"}, {"SVD_RANK", std::to_string(setup.svd.rank)},
                   {"SVD_GRID", std::to_string(kSvdGrid)}};
    rect_defines.emplace_back("INTEGRAND_SVD", "1");
  }
  ShaderDefines integrate_defines = common;
  if (svd) {
    integrate_defines.insert(integrate_defines.end(), svd_defines.begin(), svd_defines.end());
  } else {
    integrate_defines.emplace_back(setup.integrand == VolumetricIntegrand::kAnalytic    ? "INTEGRAND_ANALYTIC"
                                   : setup.integrand == VolumetricIntegrand::kPrefixSum ? "INTEGRAND_PREFIX"
                                                                                       : "INTEGRAND_PER_TEXEL",
                                   "1");
  }
  if (method == VolumetricMethod::kRayMarching) integrate_defines.emplace_back("RAY_MARCH", "1");

  auto t = std::make_shared<VolumetricTargets>();
  VISQ_ASSIGN_OR_RETURN(t->shadow, Program<SceneDrawUniforms>(
                                       {{GL_VERTEX_SHADER, "vol_shadow.vert"}, {GL_FRAGMENT_SHADER, "vol_shadow.frag"}}, {}));
  VISQ_ASSIGN_OR_RETURN(t->camera, Program<SceneDrawUniforms>(
                                       {{GL_VERTEX_SHADER, "vol_shadow.vert"}, {GL_FRAGMENT_SHADER, "vol_camera.frag"}},
                                       {{"CAMERA", "1"}}));
  VISQ_ASSIGN_OR_RETURN(t->rectify, Program<RectifyUniforms>({{GL_COMPUTE_SHADER, "vol_rectify.comp"}}, rect_defines));
  VISQ_ASSIGN_OR_RETURN(t->minmax, Program<MinMaxUniforms>({{GL_COMPUTE_SHADER, "vol_minmax.comp"}}, {}));
  VISQ_ASSIGN_OR_RETURN(t->prefix, Program<PrefixUniforms>({{GL_COMPUTE_SHADER, "vol_prefix.comp"}}, svd_defines));
  VISQ_ASSIGN_OR_RETURN(t->integrate,
                        Program<IntegrateUniforms>({{GL_COMPUTE_SHADER, "vol_integrate.comp"}}, integrate_defines));

  // The driver fills every store it allocates (llvmpipe: a memset of up to
  // 67 MB each, 1.2 s for a 4096 map and a 1920 x 1080 image on this
  // machine, several times that under ASan): the call is asked between them.
  const std::string_view where = "volumetric shadows: setup";
  const uint32_t n = setup.map_size;
  const size_t cells = size_t{setup.rows} * setup.cols;
  VISQ_RETURN_IF_ERROR(job.stop.Check(where));
  t->shadow_map = GlTexture2D();
  glTextureStorage2D(t->shadow_map.id(), 1, GL_DEPTH_COMPONENT32F, GLsizei(n), GLsizei(n));
  glTextureParameteri(t->shadow_map.id(), GL_TEXTURE_MIN_FILTER, GL_NEAREST);
  glTextureParameteri(t->shadow_map.id(), GL_TEXTURE_MAG_FILTER, GL_NEAREST);
  t->shadow_fb = GlFramebuffer();
  glNamedFramebufferTexture(t->shadow_fb.id(), GL_DEPTH_ATTACHMENT, t->shadow_map.id(), 0);
  glNamedFramebufferDrawBuffer(t->shadow_fb.id(), GL_NONE);
  if (glCheckNamedFramebufferStatus(t->shadow_fb.id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
    return absl::InternalError("volumetric shadows: shadow-map framebuffer incomplete");

  t->geometry = GlTexture2D();
  t->albedo = GlTexture2D();
  glTextureStorage2D(t->geometry.id(), 1, GL_RGBA32F, GLsizei(setup.width), GLsizei(setup.height));
  glTextureStorage2D(t->albedo.id(), 1, GL_RGBA8, GLsizei(setup.width), GLsizei(setup.height));
  t->camera_depth = GlRenderbuffer();
  glNamedRenderbufferStorage(t->camera_depth.id(), GL_DEPTH_COMPONENT32F, GLsizei(setup.width), GLsizei(setup.height));
  t->camera_fb = GlFramebuffer();
  glNamedFramebufferTexture(t->camera_fb.id(), GL_COLOR_ATTACHMENT0, t->geometry.id(), 0);
  glNamedFramebufferTexture(t->camera_fb.id(), GL_COLOR_ATTACHMENT1, t->albedo.id(), 0);
  glNamedFramebufferRenderbuffer(t->camera_fb.id(), GL_DEPTH_ATTACHMENT, GL_RENDERBUFFER, t->camera_depth.id());
  const GLenum draw_buffers[2] = {GL_COLOR_ATTACHMENT0, GL_COLOR_ATTACHMENT1};
  glNamedFramebufferDrawBuffers(t->camera_fb.id(), 2, draw_buffers);
  if (glCheckNamedFramebufferStatus(t->camera_fb.id(), GL_FRAMEBUFFER) != GL_FRAMEBUFFER_COMPLETE)
    return absl::InternalError("volumetric shadows: camera framebuffer incomplete");

  VISQ_RETURN_IF_ERROR(job.stop.Check(where));
  t->rect_depth = MakeBuffer(cells * sizeof(float));
  // Ray marching tests every texel and reads no tree.
  const bool tree = method == VolumetricMethod::kMinMaxTraversal;
  VISQ_RETURN_IF_ERROR(job.stop.Check(where));
  t->tree_min = MakeBuffer(tree ? cells * sizeof(float) : 0);
  VISQ_RETURN_IF_ERROR(job.stop.Check(where));
  t->tree_max = MakeBuffer(tree ? cells * sizeof(float) : 0);
  VISQ_RETURN_IF_ERROR(job.stop.Check(where));
  const bool prefix = setup.integrand == VolumetricIntegrand::kPrefixSum;
  t->rect_weight = MakeBuffer(setup.weighted ? cells * sizeof(float) : 0);
  t->rect_unit = MakeBuffer(setup.weighted ? cells * sizeof(float) : 0);
  const size_t prefix_bytes = prefix ? sizeof(float) : svd ? setup.svd.rank * sizeof(double) : 0;
  t->prefix_sums = MakeBuffer(size_t{setup.rows} * (setup.cols + 1) * prefix_bytes);
  t->rect_phi = MakeBuffer(svd ? cells * sizeof(float) : 0);
  t->svd_terms = MakeBuffer(svd ? cells * setup.svd.rank * sizeof(float) : 0);
  std::vector<float> svd_table = setup.svd.u;
  svd_table.insert(svd_table.end(), setup.svd.v.begin(), setup.svd.v.end());
  t->svd_table = MakeBuffer(svd ? svd_table.size() * sizeof(float) : 0, svd ? svd_table.data() : nullptr);
  t->light_texture =
      MakeBuffer(light.texture.size() * sizeof(float), light.texture.empty() ? nullptr : light.texture.data());
  t->albedo_buffer = MakeBuffer(setup.albedo.size() * sizeof(glm::vec4), setup.albedo.data());
  t->output = MakeBuffer(size_t{setup.width} * setup.height * sizeof(glm::vec4));
  t->empty_vao = GlVertexArray();
  VISQ_GL_CHECK("volumetric shadows: setup");
  glFinish();
  return t;
}

// The rectified rows, trees, sums and output as the compute stages see
// them, bound afresh by each of their jobs.
void BindComputeStorage(const VolumetricTargets& t) {
  glBindVertexArray(t.empty_vao.id());
  glBindTextureUnit(0, t.shadow_map.id());
  glBindTextureUnit(1, t.geometry.id());
  glBindTextureUnit(2, t.albedo.id());
  const GLuint buffers[11] = {t.rect_depth.id(),    t.tree_min.id(),  t.tree_max.id(),    t.rect_weight.id(),
                              t.rect_unit.id(),     t.prefix_sums.id(), t.light_texture.id(), t.output.id(),
                              t.rect_phi.id(),      t.svd_table.id(), t.svd_terms.id()};
  for (GLuint binding = 0; binding < 11; ++binding)
    glBindBufferBase(GL_SHADER_STORAGE_BUFFER, binding, buffers[binding]);
}

// What every job leaves as it found it: no program, buffers or textures.
void UnbindAll() {
  for (GLuint unit = 0; unit < 3; ++unit) glBindTextureUnit(unit, 0);
  for (GLuint binding = 0; binding < 11; ++binding) glBindBufferBase(GL_SHADER_STORAGE_BUFFER, binding, 0);
  glBindFramebuffer(GL_FRAMEBUFFER, 0);
  glBindVertexArray(0);
  glUseProgram(0);
}

// 1. Shadow map.
Status DrawShadowMap(const GpuScene& scene, const VolumetricTargets& t, const Setup& setup, TimedSizer& pieces,
                     const JobOptions& job) {
  const glm::mat4 clip(setup.light_clip);
  const GLsizei n = GLsizei(setup.map_size);
  glBindFramebuffer(GL_FRAMEBUFFER, t.shadow_fb.id());
  glViewport(0, 0, n, n);
  glEnable(GL_DEPTH_TEST);
  glDepthFunc(GL_LESS);
  glDepthMask(GL_TRUE);
  glDisable(GL_CULL_FACE);
  const float one = 1.0f;
  glClearBufferfv(GL_DEPTH, 0, &one);
  glUseProgram(t.shadow->id());
  t.shadow->uniforms.clip_from_anchor.Set(clip);
  const Status drawn = DrawInTimedPieces(scene, scene.Whole(), pieces, job, "volumetric shadows: shadow map");
  glDisable(GL_DEPTH_TEST);
  UnbindAll();
  VISQ_RETURN_IF_ERROR(drawn);
  VISQ_GL_CHECK("volumetric shadows: shadow map");
  glFinish();
  return absl::OkStatus();
}

// 2. Camera distances, normals, colors.
Status DrawCameraPass(const GpuScene& scene, const GpuScene::Resources& res, const VolumetricTargets& t,
                      const Setup& setup, TimedSizer& pieces, const JobOptions& job) {
  const glm::mat4 clip(setup.camera_clip);
  glBindFramebuffer(GL_FRAMEBUFFER, t.camera_fb.id());
  glViewport(0, 0, GLsizei(setup.width), GLsizei(setup.height));
  glEnable(GL_DEPTH_TEST);
  glDepthFunc(GL_LESS);
  glDepthMask(GL_TRUE);
  glDisable(GL_CULL_FACE);
  const float no_surface[4] = {0, 0, 0, -1};
  const float black[4] = {0, 0, 0, 0};
  const float one = 1.0f;
  glClearBufferfv(GL_COLOR, 0, no_surface);
  glClearBufferfv(GL_COLOR, 1, black);
  glClearBufferfv(GL_DEPTH, 0, &one);
  glUseProgram(t.camera->id());
  t.camera->uniforms.clip_from_anchor.Set(clip);
  t.camera->uniforms.eye.Set(glm::vec3(setup.eye));
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 0, res.positions.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 1, res.triangle_materials.id());
  glBindBufferBase(GL_SHADER_STORAGE_BUFFER, 2, t.albedo_buffer.id());
  const Status drawn = DrawInTimedPieces(scene, scene.Whole(), pieces, job, "volumetric shadows: camera pass");
  glDisable(GL_DEPTH_TEST);
  UnbindAll();
  VISQ_RETURN_IF_ERROR(drawn);
  VISQ_GL_CHECK("volumetric shadows: camera pass");
  glFinish();
  return absl::OkStatus();
}

// 3. Rectification.
Status Rectify(const VolumetricTargets& t, const Setup& setup, const VolumetricLight& light) {
  BindComputeStorage(t);
  const RectifyUniforms& u = t.rectify->uniforms;
  glUseProgram(t.rectify->id());
  SetRectUniforms(u.rect, setup);
  SetLightUniforms(u.light, setup, light);
  u.map_size.Set(GLint(setup.map_size));
  u.eye_in_light.Set(glm::vec3(setup.eye_in_light));
  u.texel_world.Set(glm::vec2(setup.texel_world));
  glDispatchCompute(Groups(setup.cols, 8), Groups(setup.rows, 8), 1);
  glMemoryBarrier(GL_SHADER_STORAGE_BARRIER_BIT);
  UnbindAll();
  VISQ_GL_CHECK("volumetric shadows: rectification");
  glFinish();
  return absl::OkStatus();
}

// 4. Min-max levels, then prefix sums.
Status BuildMinMax(const VolumetricTargets& t, const Setup& setup, VolumetricMethod method) {
  BindComputeStorage(t);
  if (method == VolumetricMethod::kMinMaxTraversal) {
    const MinMaxUniforms& u = t.minmax->uniforms;
    glUseProgram(t.minmax->id());
    u.cols.Set(GLint(setup.cols));
    u.rows.Set(GLint(setup.rows));
    for (uint32_t level = 1; level <= setup.levels; ++level) {
      u.level.Set(GLint(level));
      glDispatchCompute(Groups(setup.cols >> level, 64), setup.rows, 1);
      glMemoryBarrier(GL_SHADER_STORAGE_BARRIER_BIT);
    }
  }
  if (setup.integrand == VolumetricIntegrand::kPrefixSum || setup.integrand == VolumetricIntegrand::kSvd) {
    const PrefixUniforms& u = t.prefix->uniforms;
    glUseProgram(t.prefix->id());
    u.cols.Set(GLint(setup.cols));
    u.rows.Set(GLint(setup.rows));
    u.svd_x_step.Set(float(setup.svd.x_step));
    glDispatchCompute(Groups(setup.rows, 64), 1, 1);
    glMemoryBarrier(GL_SHADER_STORAGE_BARRIER_BIT);
  }
  UnbindAll();
  VISQ_GL_CHECK("volumetric shadows: mipmap");
  glFinish();
  return absl::OkStatus();
}

// 5. Per-pixel integration of image rows [first_row, first_row + rows).
Status IntegrateRows(const VolumetricTargets& t, const Setup& setup, const VolumetricParams& params,
                     uint32_t first_row, uint32_t rows) {
  BindComputeStorage(t);
  const IntegrateUniforms& u = t.integrate->uniforms;
  const VolumetricLight& light = params.light;
  glUseProgram(t.integrate->id());
  SetRectUniforms(u.rect, setup);
  SetLightUniforms(u.light, setup, light);
  u.light_clip.Set(glm::mat4(setup.light_clip));
  u.c0.Set(glm::vec4(setup.c0));
  u.image_size.Set(glm::ivec2(GLint(setup.width), GLint(setup.height)));
  u.first_row.Set(GLint(first_row));
  u.eye.Set(glm::vec3(setup.eye));
  u.cam_forward.Set(glm::vec3(setup.cam_forward));
  u.cam_right.Set(glm::vec3(setup.cam_right));
  u.cam_up.Set(glm::vec3(setup.cam_up));
  u.light_dir.Set(glm::vec3(setup.light_dir));
  u.light_pos.Set(glm::vec3(setup.light_pos));
  u.map_size.Set(float(setup.map_size));
  u.levels.Set(GLint(setup.levels));
  u.bias.Set(float(setup.bias));
  u.sigma_s.Set(float(params.medium.scattering));
  u.sigma_t.Set(params.medium.optically_thin ? 0.0f : float(params.medium.extinction));
  u.g.Set(float(params.medium.hg_g));
  u.intensity.Set(float(light.intensity));
  u.half_depth.Set(float(setup.half_depth));
  u.medium_start.Set(float(setup.medium_start));
  u.medium_min.Set(glm::vec3(setup.medium.min));
  u.medium_max.Set(glm::vec3(setup.medium.max));
  u.direct.Set(params.combined_image ? 1 : 0);
  u.normal_offset.Set(float(setup.normal_offset));
  u.svd_alpha0.Set(float(setup.svd.alpha0));
  u.svd_alpha_step.Set(float(setup.svd.alpha_step));
  u.eye_light_distance.Set(float(setup.eye_light_distance));
  glDispatchCompute(Groups(setup.width, 8), Groups(rows, 8), 1);
  glMemoryBarrier(GL_BUFFER_UPDATE_BARRIER_BIT);
  UnbindAll();
  VISQ_GL_CHECK("volumetric shadows: traversal");
  glFinish();
  return absl::OkStatus();
}

// Rows [first_row, first_row + rows) of the image.
Status ReadRows(const VolumetricTargets& t, const Setup& setup, uint32_t first_row, uint32_t rows,
                std::vector<glm::vec4>& pixels) {
  // The output buffer holds width x height pixels: a band past it is the
  // band planner's bug, not a GL error for the caller to see.
  VISQ_CHECK_LE(size_t{first_row} + rows, size_t{setup.height});
  pixels.resize(size_t{setup.width} * rows);
  glGetNamedBufferSubData(t.output.id(), GLintptr(size_t{first_row} * setup.width * sizeof(glm::vec4)),
                          GLsizeiptr(pixels.size() * sizeof(glm::vec4)), pixels.data());
  return CollectGlErrors("volumetric shadows: readback");
}

}  // namespace

Status ValidateVolumetricParams(const VolumetricParams& params) {
  const VolumetricCamera& camera = params.camera;
  const VolumetricLight& light = params.light;
  const VolumetricMedium& medium = params.medium;
  VISQ_RETURN_IF_ERROR(ValidatePinholeCamera(camera, kMaxVolumetricImageSize));
  // Light.
  if (!IsDirection(light.direction))
    return Invalid(fmt::format("light.direction: {} is not a direction (zero, not finite or too long to normalize)",
                               Vec(light.direction)));
  if (!Finite(light.up)) return Invalid(fmt::format("light.up: non-finite {}", Vec(light.up)));
  if (!Finite(light.color) || light.color.x < 0 || light.color.y < 0 || light.color.z < 0)
    return Invalid(fmt::format("light.color: {} must be finite and non-negative", Vec(light.color)));
  if (!Finite(light.intensity) || light.intensity < 0)
    return Invalid(fmt::format("light.intensity: {} must be finite and non-negative", light.intensity));
  if (light.kind == VolumetricLightKind::kSpot) {
    if (!InCoordinateRange(light.position))
      return Invalid(fmt::format("light.position: {} is not finite or beyond ±{:g}", Vec(light.position),
                                 kMaxCoordinate));
    if (!(light.cone_angle_deg > 0.0 && light.cone_angle_deg <= 80.0))
      return Invalid(fmt::format("light.cone_angle_deg: {} is not in (0, 80]", light.cone_angle_deg));
    if (!(light.cone_falloff_deg >= 0.0 && light.cone_falloff_deg <= light.cone_angle_deg))
      return Invalid(fmt::format("light.cone_falloff_deg: {} is not in [0, cone_angle_deg = {}]",
                                 light.cone_falloff_deg, light.cone_angle_deg));
  }
  if (!light.texture.empty() || light.texture_width != 0 || light.texture_height != 0) {
    if (light.texture_width == 0 || light.texture_height == 0)
      return Invalid(fmt::format("light.texture: {} x {} has a zero side", light.texture_width, light.texture_height));
    if (light.texture_width > kMaxVolumetricLightTextureSize || light.texture_height > kMaxVolumetricLightTextureSize)
      return absl::ResourceExhaustedError(fmt::format("light.texture: {} x {} exceeds the cap of {} per side",
                                                      light.texture_width, light.texture_height,
                                                      kMaxVolumetricLightTextureSize));
    if (light.texture.size() != size_t{light.texture_width} * light.texture_height)
      return Invalid(fmt::format("light.texture: {} values for {} x {}", light.texture.size(), light.texture_width,
                                 light.texture_height));
    for (size_t i = 0; i < light.texture.size(); ++i)
      if (!std::isfinite(light.texture[i]) || light.texture[i] < 0)
        return Invalid(fmt::format("light.texture[{}]: {} must be finite and non-negative", i, light.texture[i]));
  }
  // Medium.
  if (!Finite(medium.scattering) || medium.scattering < 0)
    return Invalid(fmt::format("medium.scattering: {} must be finite and non-negative", medium.scattering));
  if (!Finite(medium.extinction) || medium.extinction < 0)
    return Invalid(fmt::format("medium.extinction: {} must be finite and non-negative", medium.extinction));
  if (medium.extinction < medium.scattering)
    return Invalid(fmt::format("medium.extinction: {} is below medium.scattering = {}", medium.extinction,
                               medium.scattering));
  if (!(medium.hg_g > -1.0 && medium.hg_g < 1.0))
    return Invalid(fmt::format("medium.hg_g: {} is not in (-1, 1)", medium.hg_g));
  if (!(params.svd_tolerance > 0.0 && params.svd_tolerance < 1.0))
    return Invalid(fmt::format("svd_tolerance: {} is not in (0, 1)", params.svd_tolerance));
  if (!params.medium_bounds.Empty()) {
    const Bounds& m = params.medium_bounds;
    if (!InCoordinateRange(m.min) || !InCoordinateRange(m.max) || m.min.x >= m.max.x || m.min.y >= m.max.y ||
        m.min.z >= m.max.z)
      return Invalid(fmt::format("medium_box: min {} and max {} must be within ±{:g} with min < max on every axis",
                                 Vec(m.min), Vec(m.max), kMaxCoordinate));
  }
  // Shadow map.
  if (params.shadow_map_size > kMaxVolumetricShadowMapSize)
    return absl::ResourceExhaustedError(fmt::format("shadow_map_size: {} exceeds the cap of {}",
                                                    params.shadow_map_size, kMaxVolumetricShadowMapSize));
  if (params.shadow_map_size < kMinVolumetricShadowMapSize || !std::has_single_bit(params.shadow_map_size))
    return Invalid(fmt::format("shadow_map_size: {} is not a power of two in [{}, {}]", params.shadow_map_size,
                               kMinVolumetricShadowMapSize, kMaxVolumetricShadowMapSize));
  return absl::OkStatus();
}

StatusOr<VolumetricResult> RenderVolumetricShadows(GpuWorker& worker, const GpuScene& gpu_scene, const Scene& scene,
                                                   const VolumetricParams& params, const VolumetricBandSink& sink) {
  const auto start = Clock::now();
  VISQ_RETURN_IF_ERROR(ValidateVolumetricParams(params));
  VISQ_ASSIGN_OR_RETURN(Setup setup, BuildSetup(gpu_scene, scene, params));

  VolumetricResult result;
  // Each stage, and each band of the traversal, is a GL job of its own; a
  // cancelled or expired call stops at the next.
  GlStateAcrossJobs<VolumetricTargets> targets(worker);
  VolumetricTimings& ms = result.timings;
  auto job = [&](double& stage_ms, const std::function<Status()>& body) -> Status {
    JobTiming timing;
    const Status status = worker.Run(params.job, body, &timing);
    ms.queue_ms += timing.queue_ms;
    stage_ms += timing.run_ms;
    ++result.gl_jobs;
    return status;
  };
  using Stage = std::function<Status(const GpuScene::Resources&, const VolumetricTargets&)>;
  auto stage = [&](double& stage_ms, const Stage& body) -> Status {
    return job(stage_ms, [&]() -> Status {
      VISQ_ASSIGN_OR_RETURN(const VolumetricTargets* t, targets.Get("volumetric shadows"));
      VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* resources, gpu_scene.CurrentResources());
      return body(*resources, *t);
    });
  };
  VISQ_RETURN_IF_ERROR(job(ms.setup_ms, [&]() -> Status {
    VISQ_ASSIGN_OR_RETURN(std::shared_ptr<VolumetricTargets> made, CreateTargets(setup, params.light, params.method, params.job));
    targets.Set(std::move(made));
    return absl::OkStatus();
  }));
  // The two draws of the scene in pieces of about piece_target_ms (each
  // pass learns its own: the shadow map and the camera image differ).
  const int scene_triangles = int(std::clamp<uint64_t>(gpu_scene.triangle_count(), 1, INT32_MAX));
  const bool cut = params.piece_target_ms > 0.0;
  TimedSizer shadow_pieces(params.piece_target_ms, scene_triangles,
                           cut ? FirstPieceTriangles(uint64_t{setup.map_size} * setup.map_size, scene_triangles)
                               : scene_triangles);
  TimedSizer camera_pieces(params.piece_target_ms, scene_triangles,
                           cut ? FirstPieceTriangles(uint64_t{setup.width} * setup.height, scene_triangles)
                               : scene_triangles);
  VISQ_RETURN_IF_ERROR(stage(ms.shadow_map_ms, [&](const GpuScene::Resources&, const VolumetricTargets& t) {
    return DrawShadowMap(gpu_scene, t, setup, shadow_pieces, params.job);
  }));
  VISQ_RETURN_IF_ERROR(stage(ms.camera_ms, [&](const GpuScene::Resources& res, const VolumetricTargets& t) {
    return DrawCameraPass(gpu_scene, res, t, setup, camera_pieces, params.job);
  }));
  VISQ_RETURN_IF_ERROR(stage(ms.rectification_ms, [&](const GpuScene::Resources&, const VolumetricTargets& t) {
    return Rectify(t, setup, params.light);
  }));
  VISQ_RETURN_IF_ERROR(stage(ms.mipmap_ms, [&](const GpuScene::Resources&, const VolumetricTargets& t) {
    return BuildMinMax(t, setup, params.method);
  }));
  // The figures are known now (the first job may have fallen back from
  // kSvd), before any band.
  result.timings.integrand_table_ms = setup.svd_ms;
  result.width = setup.width;
  result.height = setup.height;
  result.method = params.method;
  result.integrand = setup.integrand;
  if (setup.integrand == VolumetricIntegrand::kSvd) {
    result.svd_rank = static_cast<uint32_t>(setup.svd.rank);
    result.integrand_error = setup.svd.relative_error;
  }
  result.rectified_rows = setup.rows;
  result.rectified_columns = setup.cols;
  result.epipole_inside_map = setup.epipole_inside;
  if (!setup.spot) result.medium_box = setup.box;
  const size_t pixel_count = size_t{setup.width} * setup.height;
  if (!sink) {
    result.inscattering.reserve(pixel_count * 3);
    if (params.combined_image) result.combined.reserve(pixel_count * 3);
  }

  // The traversal a band of rows per job, each band read back in its job
  // and handed on (the light colour applied here: the shader works in one
  // channel for the medium).
  const glm::vec3 color(params.light.color);
  std::vector<glm::vec4> pixels;
  VolumetricBand band;
  // Bands of 8-row groups: at most max_pixels_per_job (memory), sized by
  // their measured time to about 4 x piece_target_ms (ray marching a large
  // image takes seconds on llvmpipe), from one group.
  const uint32_t most_groups = TraversalBandRows(setup.width, params.max_pixels_per_job) / 8;
  TimedSizer band_groups(4.0 * params.piece_target_ms, int(most_groups),
                         params.piece_target_ms > 0.0 ? 1 : int(most_groups));
  for (uint32_t first_row = 0, rows = 0; first_row < setup.height; first_row += rows) {
    rows = std::min(8 * uint32_t(band_groups.size()), setup.height - first_row);
    double readback_ms = 0.0, integrate_ms = 0.0;
    VISQ_RETURN_IF_ERROR(stage(ms.traversal_ms, [&](const GpuScene::Resources&, const VolumetricTargets& t) {
      const auto integrate_start = Clock::now();
      VISQ_RETURN_IF_ERROR(IntegrateRows(t, setup, params, first_row, rows));
      integrate_ms = MillisecondsSince(integrate_start);
      const auto readback_start = Clock::now();
      const Status read = ReadRows(t, setup, first_row, rows, pixels);
      readback_ms = MillisecondsSince(readback_start);
      return read;
    }));
    band_groups.Measured(int((rows + 7) / 8), integrate_ms);
    ms.traversal_ms -= readback_ms;  // the job held both
    ms.readback_ms += readback_ms;
    band.first = size_t{first_row} * setup.width;
    band.inscattering.resize(pixels.size() * 3);
    band.combined.resize(params.combined_image ? pixels.size() * 3 : 0);
    for (size_t i = 0; i < pixels.size(); ++i) {
      for (int k = 0; k < 3; ++k) {
        band.inscattering[i * 3 + k] = color[k] * pixels[i].x;
        if (params.combined_image) band.combined[i * 3 + k] = color[k] * (pixels[i].x + pixels[i][k + 1]);
      }
    }
    if (sink) {
      VISQ_RETURN_IF_ERROR(sink(result, band));
    } else {
      result.inscattering.insert(result.inscattering.end(), band.inscattering.begin(), band.inscattering.end());
      result.combined.insert(result.combined.end(), band.combined.begin(), band.combined.end());
    }
  }
  result.timings.total_ms = MillisecondsSince(start);
  return result;
}

}  // namespace visq::gpu
