// Volumetric shadows (Chen et al. 2011) on llvmpipe: closed forms for an
// unoccluded medium and a single occluding plane, min-max traversal against
// ray marching on real scenes, translation invariance, bad inputs.
#include "visq/gpu/volumetric_shadows.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <numbers>

#include <gmock/gmock.h>
#include <fmt/format.h>
#include <gtest/gtest.h>

#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "gpu_test_support.h"
#include "large_scene.h"
#include "test_support.h"

namespace visq::gpu {
namespace {

using ::testing::HasSubstr;

constexpr double kPi = std::numbers::pi;

// The documented camera model: a ray through each pixel center, y = 0 the top row.
glm::dvec3 PixelRay(const VolumetricCamera& c, uint32_t x, uint32_t y) {
  const glm::dvec3 f = glm::normalize(c.forward);
  const glm::dvec3 r = glm::normalize(glm::cross(f, c.up));
  const glm::dvec3 u = glm::cross(r, f);
  const double tan_y = std::tan(0.5 * c.vertical_fov_deg * kPi / 180.0);
  const double aspect = double(c.width) / c.height;
  const double nx = (x + 0.5) / c.width * 2.0 - 1.0;
  const double ny = 1.0 - (y + 0.5) / c.height * 2.0;
  return glm::normalize(f + nx * tan_y * aspect * r + ny * tan_y * u);
}

double HenyeyGreenstein(double g, double cos_theta) {
  const double denom = 1.0 + g * g - 2.0 * g * cos_theta;
  return (1.0 - g * g) / (4.0 * kPi * denom * std::sqrt(denom));
}

// [lo, hi] of the ray inside the oriented box; false if it misses.
bool ClipToBox(const VolumetricBox& box, const glm::dvec3& eye, const glm::dvec3& d, double& lo, double& hi) {
  for (int k = 0; k < 3; ++k) {
    const double o = glm::dot(eye - box.center, box.axis[k]);
    const double v = glm::dot(d, box.axis[k]);
    const double h = box.half_extent[k];
    if (std::abs(v) < 1e-300) {
      if (std::abs(o) > h) return false;
      continue;
    }
    double a = (-h - o) / v, b = (h - o) / v;
    if (a > b) std::swap(a, b);
    lo = std::max(lo, a);
    hi = std::min(hi, b);
  }
  return hi > lo;
}

// The medium's world box as an oriented box, for ClipToBox.
VolumetricBox AxisBox(const Bounds& b) {
  VolumetricBox box;
  box.center = b.Center();
  box.axis[0] = {1, 0, 0};
  box.axis[1] = {0, 1, 0};
  box.axis[2] = {0, 0, 1};
  box.half_extent = 0.5 * b.Extent();
  return box;
}

// Closed form of the directional single-scattering integral over [a, b] of a
// ray entering the medium at s_in (the header's model, in double).
struct DirectionalIntegral {
  const VolumetricBox& box;
  const VolumetricParams& params;
  glm::dvec3 eye, d;
  double s_in;
  double operator()(double a, double b) const {
    if (!(b > a)) return 0.0;
    const VolumetricMedium& m = params.medium;
    const glm::dvec3 w = box.axis[2];
    const double k = m.scattering * HenyeyGreenstein(m.hg_g, glm::dot(glm::normalize(params.light.direction), -d)) *
                     params.light.intensity;
    // l(s) = depth below the box face the light enters by.
    const double l_a = glm::dot(eye + a * d - box.center, w) + box.half_extent.z;
    const double rate = m.extinction * (1.0 + glm::dot(d, w));
    const double front = k * std::exp(-m.extinction * (l_a + a - s_in));
    if (rate * (b - a) < 1e-12) return front * (b - a);
    return front * -std::expm1(-rate * (b - a)) / rate;
  }
};

double MaxOf(const std::vector<float>& v) {
  double m = 0;
  for (float x : v) m = std::max(m, double(x));
  return m;
}

double MaxAbsDiff(const std::vector<float>& a, const std::vector<float>& b) {
  double m = 0;
  for (size_t i = 0; i < a.size(); ++i) m = std::max(m, std::abs(double(a[i]) - double(b[i])));
  return m;
}

std::shared_ptr<GpuScene> Upload(const Scene& scene) {
  auto uploaded = GpuScene::Upload(testing::SharedGpuWorker(), scene);
  EXPECT_TRUE(uploaded.ok()) << uploaded.status();
  return uploaded.ok() ? *uploaded : nullptr;
}

// With VISQ_VOLUMETRIC_DUMP=folder, images are written there as PPM (each
// scaled by its own 99.5th percentile) for a look; the tests never read them.
void MaybeDump(const std::vector<float>& rgb, uint32_t width, uint32_t height, const std::string& name) {
  const char* folder = std::getenv("VISQ_VOLUMETRIC_DUMP");
  if (folder == nullptr || rgb.empty()) return;
  std::vector<float> sorted = rgb;
  std::sort(sorted.begin(), sorted.end());
  const double peak = std::max(1e-30, double(sorted[sorted.size() * 995 / 1000]));
  FILE* f = std::fopen((std::string(folder) + "/" + name + ".ppm").c_str(), "wb");
  if (f == nullptr) return;
  std::fprintf(f, "P6\n%u %u\n255\n", width, height);
  for (float v : rgb) std::fputc(int(std::clamp(std::sqrt(v / peak), 0.0, 1.0) * 255.0 + 0.5), f);
  std::fclose(f);
}

VolumetricResult Render(const GpuScene& gpu_scene, const Scene& scene, const VolumetricParams& params) {
  auto result = RenderVolumetricShadows(testing::SharedGpuWorker(), gpu_scene, scene, params);
  EXPECT_TRUE(result.ok()) << result.status();
  if (!result.ok()) return VolumetricResult{};
  static int counter = 0;
  const std::string name = fmt::format("{}_{}_{}", ::testing::UnitTest::GetInstance()->current_test_info()->name(),
                                       counter++, params.method == VolumetricMethod::kRayMarching ? "march" : "minmax");
  MaybeDump(result->inscattering, result->width, result->height, name);
  MaybeDump(result->combined, result->width, result->height, name + "_combined");
  return std::move(*result);
}

// ---------------------------------------------------------------------------
// No occluder: a floor under a box of medium, a sun from above at a slant.
// Every ray is lit from the medium's entry to the floor or the box's exit.
TEST(VolumetricShadowsTest, NoOccluderMatchesClosedForm) {
  Scene scene;
  scene.materials.push_back({"floor", glm::dvec3(0.8), glm::dvec3(0.0)});
  AddQuad(scene, "floor", {-5, 0, 5}, {10, 0, 0}, {0, 0, -10}, 0);
  UpdateBounds(scene);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);

  VolumetricParams params;
  params.camera.position = {0.3, 2.0, 4.0};
  params.camera.forward = {0.1, -0.35, -1.0};
  params.camera.vertical_fov_deg = 50;
  params.camera.width = 96;
  params.camera.height = 72;
  params.light.direction = {0.3, -1.0, 0.2};
  params.light.intensity = 3.0;
  params.medium = {0.08, 0.15, 0.3};
  params.shadow_map_size = 256;
  params.medium_bounds.Extend({-5, 0, -5});
  params.medium_bounds.Extend({5, 4, 5});
  const VolumetricResult result = Render(*gpu_scene, scene, params);
  ASSERT_EQ(result.inscattering.size(), 96u * 72 * 3);
  EXPECT_EQ(result.integrand, VolumetricIntegrand::kAnalytic);

  // The medium box must hold the medium bounds (it is the model's definition).
  const VolumetricBox& box = result.medium_box;
  for (int i = 0; i < 8; ++i) {
    const glm::dvec3 corner(i & 1 ? 5 : -5, i & 2 ? 4 : 0, i & 4 ? 5 : -5);
    for (int k = 0; k < 3; ++k)
      ASSERT_LE(std::abs(glm::dot(corner - box.center, box.axis[k])), box.half_extent[k] * (1 + 1e-9));
  }

  double max_err = 0, max_ref = 0;
  int floor_pixels = 0, sky_pixels = 0;
  for (uint32_t y = 0; y < 72; ++y) {
    for (uint32_t x = 0; x < 96; ++x) {
      const glm::dvec3 d = PixelRay(params.camera, x, y);
      double lo = 0, hi = 1e30;
      ASSERT_TRUE(ClipToBox(box, params.camera.position, d, lo, hi));
      // Rays scatter only inside the medium's world box.
      ASSERT_TRUE(ClipToBox(AxisBox(params.medium_bounds), params.camera.position, d, lo, hi));
      // The floor: y = 0 inside the quad.
      const double t_floor = -params.camera.position.y / d.y;
      const glm::dvec3 hit = params.camera.position + t_floor * d;
      const bool on_floor = d.y < 0 && std::abs(hit.x) <= 5 && std::abs(hit.z) <= 5;
      if (on_floor) hi = std::min(hi, t_floor);
      (on_floor ? floor_pixels : sky_pixels)++;
      const DirectionalIntegral integral{box, params, params.camera.position, d, lo};
      const double ref = integral(lo, hi);
      const double got = result.inscattering[(y * 96 + x) * 3];
      max_ref = std::max(max_ref, ref);
      max_err = std::max(max_err, std::abs(got - ref));
      EXPECT_NEAR(got, ref, 2e-3 * ref + 1e-6) << "pixel " << x << "," << y;
    }
  }
  EXPECT_GT(floor_pixels, 500);
  EXPECT_GT(sky_pixels, 500);
  EXPECT_GT(max_ref, 0.05);
  std::printf("no occluder: max |gpu - closed form| = %.3g (max value %.3g)\n", max_err, max_ref);
}

// The camera, sun and medium (box x in [-4, 4], y in [0, 4], z in [-8, 5])
// of the occluding-plane scenes.
VolumetricParams OccludingPlaneParams() {
  VolumetricParams params;
  params.camera.position = {0.0, 1.5, 5.0};
  params.camera.forward = {0.0, 0.0, -1.0};
  params.camera.vertical_fov_deg = 40;
  params.camera.width = 96;
  params.camera.height = 72;
  params.light.direction = {0.0, -1.0, -0.5};
  params.medium = {0.1, 0.12, 0.0};
  params.medium_bounds.Extend({-4, 0, -8});
  params.medium_bounds.Extend({4, 4, 5});
  return params;
}

// ---------------------------------------------------------------------------
// One occluding plane y = 3 over x in [-4, 4], z in [-8, 0]; the sun travels
// along (0, -1, -0.5). A point below the plane is shadowed when its light
// ray back towards the sun meets the plane inside the quad. Along a view
// ray each condition is linear in s, so the shadowed part is one interval.
TEST(VolumetricShadowsTest, OccludingPlaneMatchesClosedForm) {
  Scene scene;
  scene.materials.push_back({"occluder", glm::dvec3(0.5), glm::dvec3(0.0)});
  AddQuad(scene, "occluder", {-4, 3, 0}, {8, 0, 0}, {0, 0, -8}, 0);
  UpdateBounds(scene);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);

  VolumetricParams params = OccludingPlaneParams();
  params.shadow_map_size = 1024;
  const VolumetricResult result = Render(*gpu_scene, scene, params);
  ASSERT_EQ(result.inscattering.size(), 96u * 72 * 3);
  const VolumetricBox& box = result.medium_box;

  // Where the rectified map can put the shadow's edge: the shadow map's
  // texel, the rectified column (up to sqrt 2 texels) and the row's angle
  // quantization (a row is 2 pi / N wide: up to pi * sqrt 2 texels across at
  // the map's far corner), plus nearest resampling.
  const double texel_world = 2.0 * std::max(box.half_extent.x, box.half_extent.y) / params.shadow_map_size;
  const double edge_slack = (2.0 + std::sqrt(2.0) + kPi * std::sqrt(2.0)) * texel_world;
  const glm::dvec3 to_sun = -glm::normalize(params.light.direction);

  int partial = 0;
  for (uint32_t y = 0; y < 72; ++y) {
    for (uint32_t x = 0; x < 96; ++x) {
      const glm::dvec3 eye = params.camera.position;
      const glm::dvec3 d = PixelRay(params.camera, x, y);
      double lo = 0, hi = 1e30;
      ASSERT_TRUE(ClipToBox(box, eye, d, lo, hi));
      ASSERT_TRUE(ClipToBox(AxisBox(params.medium_bounds), eye, d, lo, hi));
      // Rays that rise into the occluder end on it.
      if (d.y > 0) {
        const double t_plane = (3.0 - eye.y) / d.y;
        const glm::dvec3 hit = eye + t_plane * d;
        if (std::abs(hit.x) <= 4 && hit.z >= -8 && hit.z <= 0) hi = std::min(hi, t_plane);
      }
      const DirectionalIntegral integral{box, params, eye, d, lo};
      // Shadowed iff g_k(s) >= 0 for all k, each g linear in s; `slack`
      // widens (+1) or narrows (-1) the shadow by edge_slack, measured
      // perpendicular to the light (the shadow map's plane).
      auto shadow_interval = [&](double slack, double& a, double& b) {
        a = lo;
        b = hi;
        auto constrain = [&](glm::dvec3 gradient, double offset) {
          // g(p) = dot(gradient, p) + offset, with the gradient's part along
          // the light removed: constant along light rays.
          gradient -= glm::dot(gradient, to_sun) * to_sun;
          const double norm = glm::length(gradient);
          const double g0 = glm::dot(gradient, eye) + offset + slack * edge_slack * norm;
          const double g1 = glm::dot(gradient, d);
          if (std::abs(g1) < 1e-15) {
            if (g0 < 0) b = a;
            return;
          }
          if (g1 > 0) a = std::max(a, -g0 / g1); else b = std::min(b, -g0 / g1);
        };
        // The sun ray through p meets y = 3 at (x, 3, z + 0.5 (3 - y)) along (0, 1, 0.5)... which the quad holds iff
        // -4 <= x <= 4 and -8 <= z' <= 0, z' = z - 0.5 y + 1.5.
        constrain({1, 0, 0}, 4);             // x + 4 >= 0
        constrain({-1, 0, 0}, 4);            // 4 - x >= 0
        constrain({0, 0.5, -1}, -1.5);       // -z' >= 0
        constrain({0, -0.5, 1}, 1.5 + 8);    // z' + 8 >= 0
        // Below the plane: y <= 3 (along the ray, not an edge of the map).
        if (std::abs(d.y) > 1e-15) {
          const double s3 = (3.0 - eye.y) / d.y;
          if (d.y > 0) b = std::min(b, s3); else a = std::max(a, s3);
        } else if (eye.y > 3.0) {
          b = a;
        }
        // A shadow that would begin beyond the ray's end is empty.
        a = std::min(a, hi);
        b = std::min(std::max(a, b), hi);
      };
      auto lit_integral = [&](double a, double b) { return integral(lo, a) + integral(b, hi); };
      double a_narrow, b_narrow, a_wide, b_wide, a, b;
      shadow_interval(-1, a_narrow, b_narrow);
      shadow_interval(+1, a_wide, b_wide);
      shadow_interval(0, a, b);
      if (b > a && (a > lo || b < hi)) ++partial;
      const double most = lit_integral(a_narrow, b_narrow);   // least shadow
      const double least = lit_integral(a_wide, b_wide);      // most shadow
      const double got = result.inscattering[(y * 96 + x) * 3];
      const double tol = 2e-3 * most + 1e-7;
      EXPECT_GE(got, least - tol) << "pixel " << x << "," << y << " exact " << lit_integral(a, b);
      EXPECT_LE(got, most + tol) << "pixel " << x << "," << y << " exact " << lit_integral(a, b);
    }
  }
  // Most rays are lit up to a distance and shadowed from there on.
  EXPECT_GT(partial, 96 * 72 / 3);
  std::printf("occluding plane: %d of %d rays partly shadowed; edge slack %.4f world units\n", partial, 96 * 72,
              edge_slack);
}

// ---------------------------------------------------------------------------
// Min-max traversal against ray marching on the same rectified map.

// Tolerance: float summation order. Each pixel is a sum of at most a few
// thousand positive terms (one per lit span or texel) in float; the two
// methods group them differently: |a - b| <= 1e-4 * max(|a|, |b|) + 1e-6 *
// (the image's largest value), the second term for texels whose depth ties
// the ray's within a rounding of the node test.
void ExpectSameImage(const VolumetricResult& traversal, const VolumetricResult& marching, const char* what) {
  ASSERT_EQ(traversal.inscattering.size(), marching.inscattering.size());
  const double peak = std::max(MaxOf(traversal.inscattering), MaxOf(marching.inscattering));
  ASSERT_GT(peak, 0.0) << what << ": an all-black image tests nothing";
  size_t bad = 0;
  for (size_t i = 0; i < traversal.inscattering.size(); ++i) {
    const double a = traversal.inscattering[i], b = marching.inscattering[i];
    if (std::abs(a - b) > 1e-4 * std::max(std::abs(a), std::abs(b)) + 1e-6 * peak) {
      if (++bad < 5) ADD_FAILURE() << what << ": value " << i << " traversal " << a << " marching " << b;
    }
  }
  EXPECT_EQ(bad, 0u) << what;
  std::printf("%s: max |traversal - marching| = %.3g (peak %.3g), traversal %.1f ms, marching %.1f ms, integrand %s\n",
              what, MaxAbsDiff(traversal.inscattering, marching.inscattering), peak, traversal.timings.traversal_ms,
              marching.timings.traversal_ms, std::string(VolumetricIntegrandName(traversal.integrand)).c_str());
}

// Renders both methods and checks they agree and that the image has both
// shadowed and lit structure (a sanity check that the scene is meaningful).
void CompareMethods(const Scene& scene, VolumetricParams params, const char* what) {
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  params.method = VolumetricMethod::kMinMaxTraversal;
  const VolumetricResult traversal = Render(*gpu_scene, scene, params);
  params.method = VolumetricMethod::kRayMarching;
  const VolumetricResult marching = Render(*gpu_scene, scene, params);
  ExpectSameImage(traversal, marching, what);
}

glm::dvec3 Lerp(const Bounds& b, double fx, double fy, double fz) {
  return b.min + glm::dvec3(fx, fy, fz) * b.Extent();
}

// Sponza: the long axis is x; the sun from above and across the columns.
VolumetricParams SponzaParams(const Scene& sponza) {
  VolumetricParams params;
  const Bounds& b = sponza.bounds;
  params.camera.position = Lerp(b, 0.12, 0.25, 0.5);
  params.camera.forward = Lerp(b, 0.9, 0.35, 0.45) - params.camera.position;
  params.camera.vertical_fov_deg = 60;
  params.camera.width = 128;
  params.camera.height = 96;
  params.light.direction = glm::dvec3(0.25, -1.0, 0.45);
  params.light.intensity = 4.0;
  const double extent = glm::length(b.Extent());
  params.medium = {2.0 / extent, 3.0 / extent, 0.2};
  params.shadow_map_size = 512;
  return params;
}

void CompareSvdWithPerTexel(const Scene& scene, VolumetricParams params, const char* what);

TEST(VolumetricShadowsTest, SponzaTraversalMatchesRayMarching) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  auto sponza = LoadGltfFile(dir / "sponza_dabrovic" / "sponza.gltf");
  ASSERT_TRUE(sponza.ok()) << sponza.status();
  CompareMethods(*sponza, SponzaParams(*sponza), "sponza sun, analytic");

  // A textured sun (a checkerboard gobo): per-texel sums or the SVD with
  // extinction, prefix sums in the optically thin limit.
  VolumetricParams textured = SponzaParams(*sponza);
  textured.light.texture_width = 8;
  textured.light.texture_height = 8;
  for (int i = 0; i < 64; ++i) textured.light.texture.push_back(((i / 8 + i % 8) % 2) ? 1.0f : 0.25f);
  CompareMethods(*sponza, textured, "sponza textured sun, per texel");
  CompareSvdWithPerTexel(*sponza, textured, "sponza textured sun, svd");
  textured.medium.optically_thin = true;
  CompareMethods(*sponza, textured, "sponza textured sun, optically thin, prefix sums");
}

// Four copies of Sponza as one placed mesh: the GPU holds it once (a
// quarter of the bytes), and the image (surfaces' face normals and
// materials included) is the flattened level's, looking into the first copy
// with the others beside it.
TEST(VolumetricShadowsTest, PlacedCopiesGiveTheFlattenedImage) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  auto sponza = LoadGltfFile(dir / "sponza_dabrovic" / "sponza.gltf");
  ASSERT_TRUE(sponza.ok()) << sponza.status();
  const Scene level = testing::MakeCopies(*sponza, 4);
  ASSERT_EQ(level.placements.size(), 4u);
  auto placed = Upload(level);
  auto flat = Upload(testing::Flattened(level));
  ASSERT_TRUE(placed && flat);
  EXPECT_EQ(placed->instance_count(), 4u);
  EXPECT_LT(placed->gpu_bytes(), flat->gpu_bytes() / 3);
  VolumetricParams params = SponzaParams(*sponza);
  params.combined_image = true;
  const VolumetricResult a = Render(*placed, level, params);
  const VolumetricResult b = Render(*flat, testing::Flattened(level), params);
  ASSERT_EQ(a.combined.size(), b.combined.size());
  const double peak = MaxOf(b.combined);
  ASSERT_GT(peak, 0.0);
  // The placed corners are a float transform of the mesh's floats, not the
  // flattened doubles rounded: a depth tie (coplanar surfaces, a silhouette
  // through a pixel centre) may fall the other way at a pixel or two.
  EXPECT_LE(MaxAbsDiff(a.inscattering, b.inscattering), 1e-3 * MaxOf(b.inscattering));
  size_t differ = 0;
  for (size_t i = 0; i < a.combined.size(); ++i) differ += std::abs(a.combined[i] - b.combined[i]) > 1e-3 * peak;
  EXPECT_LE(differ, a.combined.size() / 1000);
  std::printf("placed vs flattened: max diff %.3g (peak %.3g), %zu of %zu channels; GPU bytes %llu vs %llu\n",
              MaxAbsDiff(a.combined, b.combined), peak, differ, a.combined.size(), static_cast<unsigned long long>(placed->gpu_bytes()),
              static_cast<unsigned long long>(flat->gpu_bytes()));
}

TEST(VolumetricShadowsTest, VeachAjarTraversalMatchesRayMarching) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  auto veach = LoadGltfFile(dir / "interior_veach_ajar" / "veach_ajar.gltf");
  ASSERT_TRUE(veach.ok()) << veach.status();
  const Bounds& b = veach->bounds;
  std::printf("veach-ajar bounds (%g %g %g) - (%g %g %g)\n", b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z);
  const double extent = glm::length(b.Extent());
  VolumetricParams params;
  params.camera.position = Lerp(b, 0.5, 0.45, 0.85);
  params.camera.forward = Lerp(b, 0.5, 0.4, 0.1) - params.camera.position;
  params.camera.vertical_fov_deg = 55;
  params.camera.width = 128;
  params.camera.height = 96;
  params.shadow_map_size = 512;
  params.medium = {1.5 / extent, 2.5 / extent, 0.0};
  params.light.direction = glm::dvec3(-0.4, -0.6, 0.7);
  params.light.intensity = 4.0;
  CompareMethods(*veach, params, "veach-ajar sun, analytic");

  // A spot light inside the room (per-texel integrand: extinction > 0).
  VolumetricParams spot = params;
  spot.light.kind = VolumetricLightKind::kSpot;
  spot.light.position = Lerp(b, 0.3, 0.9, 0.3);
  spot.light.direction = Lerp(b, 0.6, 0.0, 0.6) - spot.light.position;
  spot.light.cone_angle_deg = 40;
  spot.light.cone_falloff_deg = 10;
  spot.light.intensity = 20.0;
  spot.integrand_choice = VolumetricIntegrandChoice::kExact;
  CompareMethods(*veach, spot, "veach-ajar spot, per texel");
  CompareSvdWithPerTexel(*veach, spot, "veach-ajar spot, svd");

  // The same spot, optically thin and isotropic: the prefix-sum path.
  spot.integrand_choice = VolumetricIntegrandChoice::kAuto;
  spot.medium.optically_thin = true;
  spot.medium.hg_g = 0.0;
  CompareMethods(*veach, spot, "veach-ajar spot, optically thin, prefix sums");
}

// ---------------------------------------------------------------------------
// The SVD integrand (kSvd) against the per-texel reference (kExact) on the
// same rectified map: they differ by the rank-K table's error
// (integrand_error, relative to the table's largest value) and by where each
// takes the integrand inside a texel (the per-texel path at the ray's
// midpoint of the texel, the SVD at the light ray through the texel's
// center in the row's middle), a fraction of a texel: `slack`, relative to
// the image's peak. Min-max and ray marching with kSvd agree to float
// summation order like the others.
void CompareSvdWithPerTexel(const Scene& scene, VolumetricParams params, const char* what) {
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  params.method = VolumetricMethod::kMinMaxTraversal;
  params.integrand_choice = VolumetricIntegrandChoice::kExact;
  const VolumetricResult exact = Render(*gpu_scene, scene, params);
  params.integrand_choice = VolumetricIntegrandChoice::kSvd;
  const VolumetricResult svd = Render(*gpu_scene, scene, params);
  params.method = VolumetricMethod::kRayMarching;
  const VolumetricResult svd_marching = Render(*gpu_scene, scene, params);
  ASSERT_EQ(exact.integrand, VolumetricIntegrand::kPerTexel);
  ASSERT_EQ(svd.integrand, VolumetricIntegrand::kSvd);
  EXPECT_EQ(exact.svd_rank, 0u);
  EXPECT_EQ(exact.integrand_error, 0.0);
  EXPECT_GE(svd.svd_rank, 1u);
  EXPECT_LE(svd.svd_rank, 8u);
  EXPECT_GE(svd.integrand_error, 0.0);
  EXPECT_TRUE(svd.svd_rank == 8 || svd.integrand_error <= params.svd_tolerance) << svd.integrand_error;
  ExpectSameImage(svd, svd_marching, what);

  const double peak = MaxOf(exact.inscattering);
  ASSERT_GT(peak, 0.0);
  const double diff = MaxAbsDiff(svd.inscattering, exact.inscattering);
  constexpr double kSlack = 2e-3;
  EXPECT_LE(diff, (svd.integrand_error + kSlack) * peak) << what;
  std::printf("%s: K %u, table error %.3g; max |svd - per texel| = %.3g of the peak %.3g; traversal %.1f ms svd, "
              "%.1f ms per texel, %.1f ms svd marching\n",
              what, svd.svd_rank, svd.integrand_error, diff / peak, peak, svd.timings.traversal_ms,
              exact.timings.traversal_ms, svd_marching.timings.traversal_ms);
}

// A spot in the Cornell box, aimed down past the tall block.
VolumetricParams CornellSpotParams() {
  VolumetricParams params;
  params.camera.position = {1.0, 1.0, 3.5};
  params.camera.forward = {0.0, -0.1, -1.0};
  params.camera.vertical_fov_deg = 45;
  params.camera.width = 96;
  params.camera.height = 72;
  params.light.kind = VolumetricLightKind::kSpot;
  params.light.position = {1.0, 1.9, 1.0};
  params.light.direction = {0.2, -1.0, 0.1};
  params.light.cone_angle_deg = 45;
  params.light.cone_falloff_deg = 5;
  params.light.intensity = 2.0;
  params.medium = {0.3, 0.5, 0.0};
  params.shadow_map_size = 512;
  return params;
}

TEST(VolumetricShadowsTest, SvdIntegrandMatchesPerTexel) {
  const Scene scene = MakeCornellBox();
  VolumetricParams params = CornellSpotParams();
  CompareSvdWithPerTexel(scene, params, "cornell spot, extinction, isotropic");
  params.medium.hg_g = 0.5;
  CompareSvdWithPerTexel(scene, params, "cornell spot, extinction, hg 0.5");
  params.medium.optically_thin = true;
  CompareSvdWithPerTexel(scene, params, "cornell spot, optically thin, hg 0.5");
}

TEST(VolumetricShadowsTest, SvdIntegrandChoice) {
  const Scene scene = MakeCornellBox();
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  VolumetricParams params = CornellSpotParams();
  params.camera.width = 32;
  params.camera.height = 24;
  params.shadow_map_size = 64;
  // A looser tolerance takes a rank no higher than a tighter one.
  params.svd_tolerance = 0.05;
  const VolumetricResult loose = Render(*gpu_scene, scene, params);
  params.svd_tolerance = 1e-4;
  const VolumetricResult tight = Render(*gpu_scene, scene, params);
  ASSERT_EQ(loose.integrand, VolumetricIntegrand::kSvd);
  EXPECT_LE(loose.svd_rank, tight.svd_rank);
  EXPECT_TRUE(loose.svd_rank == 8 || loose.integrand_error <= 0.05) << loose.integrand_error;
  EXPECT_GE(loose.integrand_error, tight.integrand_error);
  // The optically thin isotropic spot keeps the exact prefix sums.
  params.medium.optically_thin = true;
  EXPECT_EQ(Render(*gpu_scene, scene, params).integrand, VolumetricIntegrand::kPrefixSum);
  // A textured sun with extinction: per texel unless the SVD is asked for.
  VolumetricParams sun = params;
  sun.light.kind = VolumetricLightKind::kDirectional;
  sun.medium.optically_thin = false;
  sun.light.texture_width = sun.light.texture_height = 2;
  sun.light.texture = {1.0f, 0.5f, 0.5f, 1.0f};
  sun.svd_tolerance = 1e-3;
  EXPECT_EQ(Render(*gpu_scene, scene, sun).integrand, VolumetricIntegrand::kPerTexel);
  sun.integrand_choice = VolumetricIntegrandChoice::kSvd;
  EXPECT_EQ(Render(*gpu_scene, scene, sun).integrand, VolumetricIntegrand::kSvd);
  sun.integrand_choice = VolumetricIntegrandChoice::kExact;
  EXPECT_EQ(Render(*gpu_scene, scene, sun).integrand, VolumetricIntegrand::kPerTexel);
  // The spot takes the SVD by default, the reference when told.
  params.medium.optically_thin = false;
  params.integrand_choice = VolumetricIntegrandChoice::kExact;
  EXPECT_EQ(Render(*gpu_scene, scene, params).integrand, VolumetricIntegrand::kPerTexel);
  params.integrand_choice = VolumetricIntegrandChoice::kAuto;
  EXPECT_EQ(Render(*gpu_scene, scene, params).integrand, VolumetricIntegrand::kSvd);
  params.svd_tolerance = 0.0;
  const Status status = ValidateVolumetricParams(params);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()), HasSubstr("svd_tolerance"));
}

// ---------------------------------------------------------------------------
// A world translated by 1e6 renders the same image (positions are
// anchor-relative before they become float).
Scene OccluderScene(const glm::dvec3& offset) {
  Scene scene = MakeCornellBox();
  for (auto& p : scene.positions) p += offset;
  UpdateBounds(scene);
  return scene;
}

TEST(VolumetricShadowsTest, TranslatedWorldGivesSameImage) {
  // The Cornell spot, smaller, with a hard cone edge, an HG phase and the
  // direct light too.
  VolumetricParams params = CornellSpotParams();
  params.camera.width = 80;
  params.camera.height = 60;
  params.light.cone_falloff_deg = 0;
  params.medium = {0.3, 0.5, 0.2};
  params.shadow_map_size = 256;
  params.combined_image = true;

  const Scene near = OccluderScene(glm::dvec3(0.0));
  const glm::dvec3 offset(1e6, -1e6, 1e6);
  const Scene far = OccluderScene(offset);
  auto near_gpu = Upload(near);
  auto far_gpu = Upload(far);
  ASSERT_TRUE(near_gpu && far_gpu);
  const VolumetricResult a = Render(*near_gpu, near, params);
  VolumetricParams moved = params;
  moved.camera.position += offset;
  moved.light.position += offset;
  const VolumetricResult b = Render(*far_gpu, far, moved);
  ASSERT_EQ(a.inscattering.size(), b.inscattering.size());
  const double peak = MaxOf(a.inscattering);
  ASSERT_GT(peak, 0.0);
  const double diff = MaxAbsDiff(a.inscattering, b.inscattering);
  EXPECT_LE(diff, 1e-4 * peak) << "in-scattering";
  // Direct light adds to the surfaces the spot reaches (and only adds).
  size_t brighter = 0;
  for (size_t i = 0; i < a.combined.size(); ++i) {
    ASSERT_GE(a.combined[i], a.inscattering[i]);
    if (a.combined[i] > 1.01 * a.inscattering[i] + 1e-6) ++brighter;
  }
  EXPECT_GT(brighter, a.combined.size() / 20);
  const double combined_peak = MaxOf(a.combined);
  EXPECT_LE(MaxAbsDiff(a.combined, b.combined), 1e-4 * combined_peak) << "combined";
  std::printf("translated by 1e6: max diff %.3g (peak %.3g)\n", diff, peak);
}

// The medium is where the request puts it: a far object beside the medium
// (a second building 2 km away) changes nothing in the medium's image when
// the medium box is given, while with the scene's bounds as the medium the
// shadow map spreads over the whole world and the occluder's shadow blurs.
TEST(VolumetricShadowsTest, AMediumBoxKeepsFarGeometryOutOfTheImage) {
  auto occluder_scene = [](bool far_object) {
    Scene scene;
    scene.materials.push_back({"occluder", glm::dvec3(0.5), glm::dvec3(0.0)});
    AddQuad(scene, "occluder", {-4, 3, 0}, {8, 0, 0}, {0, 0, -8}, 0);
    if (far_object) AddBox(scene, "far", glm::dvec3(2000, 0, -10), glm::dvec3(2010, 10, 0), 0);
    UpdateBounds(scene);
    return scene;
  };
  const Scene alone = occluder_scene(false), with_far = occluder_scene(true);
  auto alone_gpu = Upload(alone), far_gpu = Upload(with_far);
  ASSERT_TRUE(alone_gpu && far_gpu);
  VolumetricParams params = OccludingPlaneParams();
  params.shadow_map_size = 512;
  const VolumetricResult reference = Render(*alone_gpu, alone, params);
  const VolumetricResult boxed = Render(*far_gpu, with_far, params);
  VolumetricParams scene_bounds = params;
  scene_bounds.medium_bounds = Bounds{};
  const VolumetricResult unboxed = Render(*far_gpu, with_far, scene_bounds);
  ASSERT_EQ(boxed.inscattering.size(), reference.inscattering.size());
  ASSERT_EQ(unboxed.inscattering.size(), reference.inscattering.size());
  const double peak = MaxOf(reference.inscattering);
  ASSERT_GT(peak, 0.0);
  size_t boxed_off = 0, unboxed_off = 0;
  for (size_t i = 0; i < reference.inscattering.size(); ++i) {
    boxed_off += std::abs(boxed.inscattering[i] - reference.inscattering[i]) > 0.01 * peak;
    unboxed_off += std::abs(unboxed.inscattering[i] - reference.inscattering[i]) > 0.01 * peak;
  }
  const size_t pixels = reference.inscattering.size();
  EXPECT_LE(boxed_off, pixels / 200) << "with the medium box, the far building moves only the anchor";
  EXPECT_GT(unboxed_off, pixels / 20) << "with the scene's bounds, the far building takes the shadow map's texels";
  std::printf("far geometry: pixels off by > 1%% of the peak: %zu of %zu with the medium box, %zu with the scene's bounds\n",
              boxed_off, pixels, unboxed_off);
}

// Every stage is its own GL job and the traversal one per band of rows
// (other queries run between them): bands give the image of one pass, for
// the min-max traversal and for ray marching, with the direct light too.
TEST(VolumetricShadowsTest, BandsOfRowsGiveTheImageOfOnePass) {
  VolumetricParams params = CornellSpotParams();
  params.camera.width = 80;
  params.camera.height = 60;
  params.medium = {0.3, 0.5, 0.2};
  params.shadow_map_size = 256;
  params.combined_image = true;
  const Scene scene = OccluderScene(glm::dvec3(0.0));
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  for (VolumetricMethod method : {VolumetricMethod::kMinMaxTraversal, VolumetricMethod::kRayMarching}) {
    params.method = method;
    // Bands sized by their measured time (the default): whatever sizes they
    // take, the image is that of one pass.
    params.piece_target_ms = 0.001;
    params.max_pixels_per_job = 80 * 64;
    const VolumetricResult timed = Render(*gpu_scene, scene, params);
    EXPECT_GT(timed.gl_jobs, 5u + 1u) << "bands of a microsecond's target stay one group of 8 rows";
    // Bands of max_pixels_per_job only, to count them.
    params.piece_target_ms = 0.0;
    params.max_pixels_per_job = 80 * 64;  // whole 8-row groups: one band of 64 rows
    const VolumetricResult whole = Render(*gpu_scene, scene, params);
    EXPECT_EQ(timed.inscattering, whole.inscattering);
    EXPECT_EQ(timed.combined, whole.combined);
    params.max_pixels_per_job = 80 * 16;  // bands of 16 rows: 16, 16, 16, 12
    const VolumetricResult banded = Render(*gpu_scene, scene, params);
    ASSERT_GT(MaxOf(whole.inscattering), 0.0);
    EXPECT_EQ(banded.inscattering, whole.inscattering);
    EXPECT_EQ(banded.combined, whole.combined);
    // Set-up, shadow map, camera, rectification, min-max, then a job per
    // band (its traversal and its read-back).
    EXPECT_EQ(whole.gl_jobs, 5u + 1u);
    EXPECT_EQ(banded.gl_jobs, 5u + 4u);
    // Streamed: the bands are the image; the result keeps the figures.
    std::vector<float> streamed_image;
    int bands = 0;
    auto streamed = RenderVolumetricShadows(testing::SharedGpuWorker(), *gpu_scene, scene, params,
                                            [&](const VolumetricResult& figures, const gpu::VolumetricBand& band) {
                                              EXPECT_EQ(figures.width, 80u);
                                              EXPECT_EQ(band.first * 3, streamed_image.size());
                                              streamed_image.insert(streamed_image.end(), band.inscattering.begin(),
                                                                    band.inscattering.end());
                                              ++bands;
                                              return absl::OkStatus();
                                            });
    ASSERT_TRUE(streamed.ok()) << streamed.status();
    EXPECT_EQ(bands, 4);
    EXPECT_EQ(streamed_image, whole.inscattering);
    EXPECT_TRUE(streamed->inscattering.empty());
  }
}

// ---------------------------------------------------------------------------
// Bad inputs name the field and the value.
TEST(VolumetricShadowsTest, BadInputsAreRejected) {
  auto check = [](void (*edit)(VolumetricParams&), absl::StatusCode code, const char* field, const char* value) {
    VolumetricParams params;
    ASSERT_TRUE(ValidateVolumetricParams(params).ok());
    edit(params);
    const Status status = ValidateVolumetricParams(params);
    EXPECT_EQ(status.code(), code) << status;
    EXPECT_THAT(std::string(status.message()), HasSubstr(field));
    EXPECT_THAT(std::string(status.message()), HasSubstr(value));
  };
  using C = absl::StatusCode;
  check([](VolumetricParams& p) { p.camera.position.x = std::nan(""); }, C::kInvalidArgument, "camera.position", "nan");
  // Positions are held to the coordinate range as every other request's
  // points are, directions to a length that normalizes (a camera 1e300 away
  // had passed, and a forward of -1e300 was blamed on camera.up).
  check([](VolumetricParams& p) { p.camera.position.z = 1e300; }, C::kInvalidArgument, "camera.position", "1e+15");
  check([](VolumetricParams& p) { p.camera.forward = glm::dvec3(0, 0, -1e300); }, C::kInvalidArgument,
        "camera.forward", "-1e+300");
  check([](VolumetricParams& p) { p.camera.up = glm::dvec3(0, 1e300, 0); }, C::kInvalidArgument, "camera.up", "1e+300");
  check([](VolumetricParams& p) { p.light.direction = glm::dvec3(1e300, -1e300, 0); }, C::kInvalidArgument,
        "light.direction", "1e+300");
  check([](VolumetricParams& p) { p.light.kind = VolumetricLightKind::kSpot; p.light.position = glm::dvec3(0, 2e15, 0); },
        C::kInvalidArgument, "light.position", "2000000000000000");
  check([](VolumetricParams& p) { p.camera.vertical_fov_deg = 0; }, C::kInvalidArgument, "vertical_fov_deg", "0");
  check([](VolumetricParams& p) { p.camera.vertical_fov_deg = 180; }, C::kInvalidArgument, "vertical_fov_deg", "180");
  check([](VolumetricParams& p) { p.camera.vertical_fov_deg = std::nan(""); }, C::kInvalidArgument, "vertical_fov_deg", "nan");
  check([](VolumetricParams& p) { p.camera.width = 0; }, C::kInvalidArgument, "resolution", "0 x 120");
  check([](VolumetricParams& p) { p.camera.height = 5000; }, C::kResourceExhausted, "resolution", "4096");
  check([](VolumetricParams& p) { p.camera.up = p.camera.forward; }, C::kInvalidArgument, "camera.up", "parallel");
  check([](VolumetricParams& p) { p.shadow_map_size = 8192; }, C::kResourceExhausted, "shadow_map_size", "4096");
  check([](VolumetricParams& p) { p.medium_bounds = Bounds{glm::dvec3(0.0), glm::dvec3(1.0, 1.0, std::nan(""))}; },
        C::kInvalidArgument, "medium_box", "nan");
  check([](VolumetricParams& p) { p.medium_bounds = Bounds{glm::dvec3(0.0), glm::dvec3(1.0, 0.0, 1.0)}; },
        C::kInvalidArgument, "medium_box", "min < max");
  check([](VolumetricParams& p) { p.shadow_map_size = 1000; }, C::kInvalidArgument, "shadow_map_size", "1000");
  check([](VolumetricParams& p) { p.medium.scattering = -0.5; }, C::kInvalidArgument, "medium.scattering", "-0.5");
  check([](VolumetricParams& p) { p.medium.extinction = -1; }, C::kInvalidArgument, "medium.extinction", "-1");
  check([](VolumetricParams& p) { p.medium.extinction = 0.01; }, C::kInvalidArgument, "medium.extinction", "0.01");
  check([](VolumetricParams& p) { p.medium.hg_g = 1.0; }, C::kInvalidArgument, "medium.hg_g", "1");
  check([](VolumetricParams& p) { p.light.direction = glm::dvec3(0.0); }, C::kInvalidArgument, "light.direction", "(0, 0, 0)");
  check([](VolumetricParams& p) { p.light.intensity = -2; }, C::kInvalidArgument, "light.intensity", "-2");
  check([](VolumetricParams& p) { p.light.kind = VolumetricLightKind::kSpot; p.light.cone_angle_deg = 95; },
        C::kInvalidArgument, "light.cone_angle_deg", "95");
  check([](VolumetricParams& p) { p.light.texture_width = 2; p.light.texture_height = 2; p.light.texture = {1, 1, 1}; },
        C::kInvalidArgument, "light.texture", "3 values");
  check([](VolumetricParams& p) { p.light.texture_width = 2000; p.light.texture_height = 1; p.light.texture.assign(2000, 1.f); },
        C::kResourceExhausted, "light.texture", "1024");

  // The render entry point validates too, before touching the GPU.
  Scene scene = MakeCornellBox();
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  VolumetricParams params;
  params.shadow_map_size = 16384;
  auto result = RenderVolumetricShadows(testing::SharedGpuWorker(), *gpu_scene, scene, params);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(std::string(result.status().message()), HasSubstr("4096"));
}

}  // namespace
}  // namespace visq::gpu
