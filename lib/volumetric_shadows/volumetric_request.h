// Volumetric shadows' requests and answers (Chen, Baran, Durand, Jarosz
// 2011, "Real-Time Volumetric Shadows using 1D Min-Max Mipmaps"): the
// camera, light and medium a rendering asks for, the image it returns band
// by band, and its timings. The GPU algorithm (gpu/volumetric_shadows,
// visq/gpu/volumetric_shadows.h, whose file comment says what one call
// computes and how each integrand is chosen) answers in these types; the
// core and the transport name them without naming gpu/. Header only: no GL,
// no gRPC, nothing to link.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <string_view>
#include <vector>

#include <glm/glm.hpp>

#include "common/band.h"
#include "common/job_options.h"
#include "common/status.h"
#include "scene/pinhole_camera.h"
#include "scene/scene.h"

namespace visq::volumetric_shadows {

inline constexpr uint32_t kMaxVolumetricShadowMapSize = 4096;  // RESOURCE_EXHAUSTED beyond
inline constexpr uint32_t kMinVolumetricShadowMapSize = 16;
inline constexpr uint32_t kMaxVolumetricImageSize = 4096;      // width and height each
inline constexpr uint32_t kMaxVolumetricLightTextureSize = 1024;

// The camera (position, forward, up, vertical_fov_deg, width, height) is the
// pinhole camera every viewpoint image shares (scene/pinhole_camera.h).
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
// [first, first + inscattering.size() / 3), laid out as VolumetricResult's
// arrays.
struct VolumetricBand : BandPlace {
  std::vector<float> inscattering;
  std::vector<float> combined;  // empty unless asked for
};
// With the figures (everything but the timings is known before the first
// band).
using VolumetricBandSink = BandSink<VolumetricResult, VolumetricBand>;

// The integrand's name in logs and answers ("analytic", "prefix_sum",
// "per_texel", "svd").
constexpr std::string_view VolumetricIntegrandName(VolumetricIntegrand integrand) {
  switch (integrand) {
    case VolumetricIntegrand::kAnalytic: return "analytic";
    case VolumetricIntegrand::kPrefixSum: return "prefix_sum";
    case VolumetricIntegrand::kPerTexel: return "per_texel";
    case VolumetricIntegrand::kSvd: return "svd";
  }
  return "unknown";
}

}  // namespace visq::volumetric_shadows
