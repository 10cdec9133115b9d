// Volumetric shadows: single scattering in a homogeneous medium with epipolar
// rectification and 1D min-max mipmaps (Chen, Baran, Durand, Jarosz 2011,
// "Real-Time Volumetric Shadows using 1D Min-Max Mipmaps"; slides in
// ../shared/papers/volumetric-shadows-minmax-mipmaps.txt). GL-free and
// protobuf-free: the algorithm and its shaders live in gpu/volumetric_shadows/.
//
// What one call computes, per camera pixel (ray from the eye through the
// pixel center, up to the first surface the camera rasterizes):
//
//   L_in = integral over the lit parts of the ray, inside the medium, of
//          sigma_s * phase(cos) * E_light(x) * exp(-sigma_t * l(x))
//                  * exp(-sigma_t * (s - s_in)) ds
//
// where s is the distance from the eye, s_in where the ray enters the medium,
// l(x) the light's path length inside the medium to x, and "lit" is decided by
// the shadow map. The medium is a world box, VolumetricParams::medium_bounds
// (the scene's bounds unless given): s runs over the part of the ray inside
// it, and inside the light's shadow-map volume:
//   directional light: light enters the medium at the plane, across the
//     light, through the box's corner it reaches first (the near face of the
//     box around the medium in the light's frame, VolumetricResult::
//     medium_box), so l(x) = depth of x below that plane and E_light =
//     intensity (irradiance) * light texture. The shadow map covers that
//     frame box, deepened towards the light over the scene, so occluders
//     outside the medium still shadow it;
//   spot light: also inside the square frustum of the cone (near = 1e-3 of
//     the diagonal, far = beyond the farthest corner of the scene and the
//     medium); l(x) = |x - position| and E_light = intensity (radiant
//     intensity) * cone * texture / l^2.
// Outside the medium there is vacuum (no scattering, no attenuation). Geometry
// far from the medium costs only the shadow map's depth range: a medium box
// given with the request keeps the map's texels on the medium.
//
// The shadow map (the light's depth) is resampled into an epipolar
// rectified map: row = one epipolar slice (a direction from the epipole, the
// eye's projection in the shadow map), column = distance from the epipole.
// Every view ray lies in one slice (the nearest row is used), and its shadow
// test becomes a height-field test along that row: the ray's shadow-map
// depth is affine in the column. Rectified map: shadow_map_size rows x
// shadow_map_size columns (columns span [r_min, r_max], the distances from
// the epipole to the map square; over a full circle when the epipole lies
// inside the map).
//
// Two methods share the code path and the per-texel integral:
//   kMinMaxTraversal: a binary min-max tree over each row; nodes fully below
//     the ray are skipped (shadowed), nodes fully above are integrated over
//     their whole span at once, mixed nodes are refined.
//   kRayMarching: every texel of the row between the ray's ends is tested and
//     integrated in turn.
// They give the same image up to float summation order.
//
// Integrand per lit span (VolumetricResult::integrand says which was used):
//   kAnalytic: directional light without texture: closed form exp(-a s).
//   kPrefixSum: no attenuation (zero extinction or medium.optically_thin)
//     and either a directional light (any phase) or
//     an isotropic phase: the ray-dependent factor is constant along the row's
//     parameter (directional: ds per column; spot: the angle subtended at the
//     light, since ds / l^2 = dphi / h), so a lit span is a difference of
//     per-row prefix sums of the light weight (texture x cone, times the
//     texel's angle for spots), as in the slides.
//   kSvd: the slides' "SVD approximation" (after Baran et al. 2010) for a
//     spot light with extinction or a Henyey-Greenstein phase, and, when
//     asked for, a textured directional light with extinction
//     (gpu/volumetric_shadows/svd_integrand.h has the derivations). The
//     ray-dependent factor f (spot: f(alpha, phi) = phase x attenuation
//     beyond d = |eye - light|, alpha the view ray's angle from the eye's
//     direction to the light, phi the light ray's angle from the light's
//     direction to the eye; directional: f(alpha, p) = exp(-sigma_t p
//     cot(alpha / 2)), p the light ray's offset from the eye's) is tabulated
//     in double and truncated to the smallest rank K <= 8 whose largest
//     residual is below svd_tolerance x max f (else K = 8), and each row
//     keeps K prefix sums (in double) of w V_k dphi (or dp): a lit span
//     costs O(K). Texels cut by the ray's ends or by a shadow edge keep the
//     exact per-texel integral, and so do rays with alpha within
//     kSvdAlphaMargin of 0 or pi (where f's domain pinches) or entering the
//     medium where f < e^-2 (the table's absolute error would be amplified).
//     VolumetricResult reports K and the table's relative error
//     (integrand_error): the largest residual anywhere in the table, a
//     conservative figure (for a spot it sits where the domain pinches;
//     images differ from kPerTexel's by far less, see the tests). kPerTexel
//     also serves when the prefix sums (rows x (columns + 1) x K doubles)
//     exceed the driver's largest storage block (`integrand` says which):
//     on llvmpipe (128 MiB blocks) that is every map above 1024.
//   kPerTexel: the reference, and the default for a textured directional
//     light with extinction (on llvmpipe its per-texel exp beats the SVD's
//     K double reads per span; integrand_choice kSvd takes the SVD there):
//     lit spans are summed texel by texel (shadowed spans are still skipped
//     by the tree), each texel exact in its ds / l^2 factor (atan) with the
//     attenuation and phase at the texel's midpoint.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "scene/scene.h"
#include "visq/gpu/camera.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

inline constexpr uint32_t kMaxVolumetricShadowMapSize = 4096;  // RESOURCE_EXHAUSTED beyond
inline constexpr uint32_t kMinVolumetricShadowMapSize = 16;
inline constexpr uint32_t kMaxVolumetricImageSize = 4096;      // width and height each
inline constexpr uint32_t kMaxVolumetricLightTextureSize = 1024;

// The camera (position, forward, up, vertical_fov_deg, width, height) is the
// pinhole camera every viewpoint image shares (visq/gpu/camera.h).
using VolumetricCamera = PinholeCamera;

enum class VolumetricLightKind { kDirectional, kSpot };

struct VolumetricLight {
  VolumetricLightKind kind = VolumetricLightKind::kDirectional;
  // Directional: the way light travels. Spot: the cone's axis.
  glm::dvec3 direction{0.0, -1.0, 0.0};
  glm::dvec3 position{0.0};      // spot only
  double cone_angle_deg = 30.0;  // spot: half-angle of the cone, in (0, 80]
  // Spot: the intensity falls smoothly to 0 over the last `cone_falloff_deg`
  // before the cone's edge (0: hard edge).
  double cone_falloff_deg = 0.0;
  glm::dvec3 color{1.0};  // multiplies every output channel
  // Directional: irradiance (W/m^2) on a plane facing the light. Spot:
  // radiant intensity (W/sr) along the axis.
  double intensity = 1.0;
  // Optional light texture: multipliers over the shadow map's square (for a
  // spot, the cone's square image), texture[y * texture_width + x], x along
  // the light's right axis, y along its up axis, (0, 0) at the (-right, -up)
  // corner; nearest sampling. Empty: 1 everywhere.
  uint32_t texture_width = 0, texture_height = 0;
  std::vector<float> texture;
  // The light's up axis (the shadow map's v); projected orthogonal to
  // `direction`. Zero: world +y, or +z when the direction is nearly vertical.
  glm::dvec3 up{0.0};
};

struct VolumetricMedium {
  double scattering = 0.05;  // sigma_s, per world unit, >= 0
  double extinction = 0.05;  // sigma_t, per world unit, >= sigma_s
  double hg_g = 0.0;         // Henyey-Greenstein asymmetry in (-1, 1); 0 = isotropic
  // The optically thin limit: no attenuation on either leg (sigma_t taken
  // as 0 in the integral, sigma_s kept). The slides' prefix sums are exact
  // only then (the integrand no longer depends on the ray beyond a factor).
  bool optically_thin = false;
};

enum class VolumetricMethod { kMinMaxTraversal, kRayMarching };
enum class VolumetricIntegrand { kAnalytic, kPrefixSum, kPerTexel, kSvd };
// Where kSvd or kPerTexel could serve: kAuto takes kSvd for spot lights and
// kPerTexel for textured directional lights (the faster on llvmpipe), kExact
// kPerTexel (the reference), kSvd kSvd.
enum class VolumetricIntegrandChoice { kAuto, kExact, kSvd };
// kSvd: rays within this angle (radians) of the table's alpha ends (spot:
// pointing at or away from the light; directional: along or against it)
// are integrated per texel.
inline constexpr double kSvdAlphaMargin = 0.2;

struct VolumetricParams {
  VolumetricCamera camera;
  VolumetricLight light;
  VolumetricMedium medium;
  uint32_t shadow_map_size = 1024;  // power of two in [16, 4096]
  VolumetricMethod method = VolumetricMethod::kMinMaxTraversal;
  // Also return `combined`: Lambert direct light on surfaces (material
  // reflectivity, shadow-mapped, attenuated both ways) plus in-scattering.
  bool combined_image = false;
  // Where the medium is: a world box (empty: the scene's bounds). Camera
  // rays scatter only inside it; see the file comment for where light
  // enters it.
  Bounds medium_bounds;
  VolumetricIntegrandChoice integrand_choice = VolumetricIntegrandChoice::kAuto;
  // kSvd: the largest residual of the rank-K table allowed, relative to its
  // largest value (the rank stops growing at 8).
  double svd_tolerance = 1e-3;
  // Each stage is a GL job, and the traversal one per band of image rows
  // of at most this many pixels (rounded to whole 8-row groups): other
  // queries get the GL thread between them. The image is that of one pass.
  uint32_t max_pixels_per_job = 1u << 18;
  // The scene's draws are cut into pieces of about this long, and the
  // traversal's bands sized to about four of them, the call asked between
  // them. 0: whole draws, bands of max_pixels_per_job.
  double piece_target_ms = 25.0;
  JobOptions job;
};

// Wall-clock per stage on the GL thread, each closed by glFinish and read
// with a steady clock (llvmpipe's GL_TIME_ELAPSED under-reports).
struct VolumetricTimings {
  double queue_ms = 0;
  double integrand_table_ms = 0; // kSvd: the SVD on the CPU (cached for the last few media and distances)
  double setup_ms = 0;           // programs (cached after the first call), buffers
  double shadow_map_ms = 0;      // the light's depth rasterization
  double camera_ms = 0;          // the camera's depth / normal rasterization
  double rectification_ms = 0;   // shadow map -> epipolar rows (+ light weights)
  double mipmap_ms = 0;          // min-max trees (+ prefix sums)
  double traversal_ms = 0;       // per-pixel integration (either method)
  double readback_ms = 0;
  double total_ms = 0;           // everything, queue included
};

// An oriented box: center + sum of axis[i] * [-half_extent[i], half_extent[i]].
struct VolumetricBox {
  glm::dvec3 center{0.0};
  glm::dvec3 axis[3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};  // right, up, light direction
  glm::dvec3 half_extent{0.0};
};

struct VolumetricResult {
  uint32_t width = 0, height = 0;
  // Float RGB per pixel, index (y * width + x) * 3, y = 0 the TOP row:
  // in-scattered radiance (light color included).
  std::vector<float> inscattering;
  std::vector<float> combined;  // same layout; empty unless asked for
  VolumetricMethod method = VolumetricMethod::kMinMaxTraversal;
  VolumetricIntegrand integrand = VolumetricIntegrand::kAnalytic;
  // kSvd: the rank K and the table's largest residual over the (alpha, phi)
  // that occur, relative to the table's largest value (0 for the others).
  uint32_t svd_rank = 0;
  double integrand_error = 0;
  uint32_t rectified_rows = 0, rectified_columns = 0;
  bool epipole_inside_map = false;
  VolumetricBox medium_box;  // directional light only (the medium's box)
  VolumetricTimings timings;
  // GL jobs the rendering took: one per stage and one per band of image
  // rows of the traversal. Other queries get the GL thread between them.
  uint32_t gl_jobs = 0;
};

// Rows of the image as each band of the traversal ends: pixels
// [first_pixel, first_pixel + inscattering.size() / 3), laid out as
// VolumetricResult's arrays.
struct VolumetricBand {
  size_t first_pixel = 0;
  std::vector<float> inscattering;
  std::vector<float> combined;  // empty unless asked for
};
// Receives each band in order, with the figures (everything but the
// timings is known before the first band). A status other than OK stops
// the rendering.
using VolumetricBandSink = std::function<Status(const VolumetricResult& figures, const VolumetricBand& band)>;

// Renders `params` over `gpu_scene` (the GPU copy of `scene`; `scene` gives
// the bounds and material colors). Without a sink the result holds the
// whole image; with one, each band goes to the sink and the result holds
// the figures only.
[[nodiscard]] StatusOr<VolumetricResult> RenderVolumetricShadows(GpuWorker& worker, const GpuScene& gpu_scene,
                                                                 const Scene& scene, const VolumetricParams& params,
                                                                 const VolumetricBandSink& sink = {});

// Checks params without touching the GPU: INVALID_ARGUMENT naming the field
// and value, RESOURCE_EXHAUSTED naming the cap.
[[nodiscard]] Status ValidateVolumetricParams(const VolumetricParams& params);

std::string_view VolumetricIntegrandName(VolumetricIntegrand integrand);

}  // namespace visq::gpu
