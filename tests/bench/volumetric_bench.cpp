// Volumetric shadows (Chen et al. 2011): 1D min-max mipmap traversal against
// brute-force ray marching on the same rectified shadow map, Sponza with the
// sun through the columns. Prints one row per (shadow map, image) with both
// traversal times (glFinish + steady clock), their ratio and the largest
// absolute difference between the two images.
//
// Then a spot light with extinction and a textured sun with extinction (1K
// map, 640x480), where the integrand of a lit span is either the SVD (kSvd,
// O(K) per span) or the per-texel reference (kExact): min-max with
// each, and ray marching with each, as times and ratios against the SVD
// min-max, with K, the SVD table's error and the largest image difference
// between the two integrands.
//
//   visq_bench_volumetric [--quick] [--svd-only] [--scene PATH] [--repeats N]
// --quick: 1K and 4K maps at 320x240 and 640x480 (minutes on llvmpipe); the
// full run is 640x480 and 1280x960. --svd-only: the SVD rows
// alone.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include "scene/gltf_loader.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"
#include "visq/gpu/volumetric_shadows.h"

using namespace visq;
using namespace visq::gpu;

namespace {

glm::dvec3 Lerp(const Bounds& b, double fx, double fy, double fz) { return b.min + glm::dvec3(fx, fy, fz) * b.Extent(); }

// The light-shafts view of the tests: low in the nave, the sun slanting
// through the gallery columns.
VolumetricParams SponzaParams(const Scene& sponza, uint32_t width, uint32_t height, uint32_t map) {
  VolumetricParams params;
  const Bounds& b = sponza.bounds;
  params.camera.position = Lerp(b, 0.12, 0.25, 0.5);
  params.camera.forward = Lerp(b, 0.9, 0.35, 0.45) - params.camera.position;
  params.camera.vertical_fov_deg = 60;
  params.camera.width = width;
  params.camera.height = height;
  params.light.direction = glm::dvec3(0.25, -1.0, 0.45);
  params.light.intensity = 4.0;
  const double extent = glm::length(b.Extent());
  params.medium = {2.0 / extent, 3.0 / extent, 0.2};
  params.shadow_map_size = map;
  return params;
}

// A spot high in the nave, aimed down across it, with the sun's medium.
VolumetricParams SponzaSpotParams(const Scene& sponza, uint32_t width, uint32_t height, uint32_t map) {
  VolumetricParams params = SponzaParams(sponza, width, height, map);
  const Bounds& b = sponza.bounds;
  params.light.kind = VolumetricLightKind::kSpot;
  params.light.position = Lerp(b, 0.55, 0.85, 0.5);
  params.light.direction = Lerp(b, 0.35, 0.0, 0.4) - params.light.position;
  params.light.cone_angle_deg = 45;
  params.light.cone_falloff_deg = 5;
  params.light.intensity = 4.0 * glm::dot(b.Extent(), b.Extent()) / 16.0;
  return params;
}

}  // namespace

int main(int argc, char** argv) {
  bool quick = false, svd_only = false;
  int repeats = 1;
  std::filesystem::path scene_path = std::filesystem::path(VISQ_SHARED_SCENES_DIR) / "sponza_dabrovic" / "sponza.gltf";
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--quick")) quick = true;
    else if (!std::strcmp(argv[i], "--svd-only")) svd_only = true;
    else if (!std::strcmp(argv[i], "--scene") && i + 1 < argc) scene_path = argv[++i];
    else if (!std::strcmp(argv[i], "--repeats") && i + 1 < argc) repeats = std::max(1, std::atoi(argv[++i]));
    else {
      std::fprintf(stderr, "usage: %s [--quick] [--svd-only] [--scene PATH] [--repeats N]\n", argv[0]);
      return 2;
    }
  }
  auto scene = LoadGltfFile(scene_path);
  if (!scene.ok()) {
    std::fprintf(stderr, "loading %s: %s\n", scene_path.c_str(), std::string(scene.status().message()).c_str());
    return 1;
  }
  auto worker = GpuWorker::Start({});
  if (!worker.ok()) {
    std::fprintf(stderr, "GPU: %s\n", std::string(worker.status().message()).c_str());
    return 1;
  }
  auto gpu_scene = GpuScene::Upload(**worker, *scene);
  if (!gpu_scene.ok()) {
    std::fprintf(stderr, "upload: %s\n", std::string(gpu_scene.status().message()).c_str());
    return 1;
  }
  std::printf("device: %s | scene %s, %zu triangles | repeats %d (best of)\n", (*worker)->device().gl_renderer.c_str(),
              scene_path.filename().c_str(), scene->TriangleCount(), repeats);

  struct Size { uint32_t w, h; };
  const std::vector<Size> images = quick ? std::vector<Size>{{320, 240}, {640, 480}} : std::vector<Size>{{640, 480}, {1280, 960}};
  const std::vector<uint32_t> maps = {1024, 4096};

  // Warm-up: llvmpipe compiles each shader variant at its first dispatch.
  for (auto method : {VolumetricMethod::kMinMaxTraversal, VolumetricMethod::kRayMarching}) {
    for (int light = 0; light < 5; ++light) {
      VolumetricParams warm = light < 3 ? SponzaParams(*scene, 64, 48, 256) : SponzaSpotParams(*scene, 64, 48, 256);
      if (light == 1 || light == 2) {
        warm.light.texture_width = warm.light.texture_height = 2;
        warm.light.texture = {1.0f, 0.25f, 0.25f, 1.0f};
      }
      warm.integrand_choice = light == 2 || light == 4 ? VolumetricIntegrandChoice::kExact : VolumetricIntegrandChoice::kSvd;
      warm.method = method;
      auto r = RenderVolumetricShadows(**worker, **gpu_scene, *scene, warm);
      if (!r.ok()) {
        std::fprintf(stderr, "warm-up: %s\n", std::string(r.status().message()).c_str());
        return 1;
      }
    }
  }

  if (!svd_only) {
    std::printf("\n%-6s %-10s | %12s %12s %8s | %12s | %9s %9s %9s | %s\n", "map", "image", "minmax ms", "march ms",
                "ratio", "max |diff|", "shadow ms", "rect ms", "mipmap ms", "peak");
    for (uint32_t map : maps) {
      for (const Size& size : images) {
        VolumetricParams params = SponzaParams(*scene, size.w, size.h, map);
        double best[2] = {1e300, 1e300};
        VolumetricResult results[2];
        for (int m = 0; m < 2; ++m) {
          params.method = m == 0 ? VolumetricMethod::kMinMaxTraversal : VolumetricMethod::kRayMarching;
          for (int r = 0; r < repeats; ++r) {
            auto result = RenderVolumetricShadows(**worker, **gpu_scene, *scene, params);
            if (!result.ok()) {
              std::fprintf(stderr, "render: %s\n", std::string(result.status().message()).c_str());
              return 1;
            }
            best[m] = std::min(best[m], result->timings.traversal_ms);
            results[m] = std::move(*result);
          }
        }
        double diff = 0, peak = 0;
        for (size_t i = 0; i < results[0].inscattering.size(); ++i) {
          diff = std::max(diff, double(std::abs(results[0].inscattering[i] - results[1].inscattering[i])));
          peak = std::max(peak, double(results[1].inscattering[i]));
        }
        const VolumetricTimings& t = results[0].timings;
        std::printf("%-6u %4ux%-5u | %12.1f %12.1f %7.2fx | %12.3g | %9.1f %9.1f %9.1f | %.3g\n", map, size.w, size.h,
                    best[0], best[1], best[1] / best[0], diff, t.shadow_map_ms, t.rectification_ms, t.mipmap_ms, peak);
        std::fflush(stdout);
      }
    }
  }

  // SVD against per-texel integrands: the spot with extinction, then the
  // sun through a checkerboard gobo.
  VolumetricParams gobo = SponzaParams(*scene, 640, 480, 1024);
  gobo.light.texture_width = gobo.light.texture_height = 8;
  for (int i = 0; i < 64; ++i) gobo.light.texture.push_back(((i / 8 + i % 8) % 2) ? 1.0f : 0.25f);
  const std::pair<const char*, VolumetricParams> cases[2] = {
      {"spot light with extinction", SponzaSpotParams(*scene, 640, 480, 1024)},
      {"textured sun with extinction", gobo}};
  for (auto [label, params] : cases) {
    struct Variant { const char* name; VolumetricMethod method; bool exact; };
    const Variant variants[4] = {{"svd min-max", VolumetricMethod::kMinMaxTraversal, false},
                                 {"per-texel min-max", VolumetricMethod::kMinMaxTraversal, true},
                                 {"svd marching", VolumetricMethod::kRayMarching, false},
                                 {"per-texel marching", VolumetricMethod::kRayMarching, true}};
    double best[4] = {1e300, 1e300, 1e300, 1e300};
    double table_ms = 0;  // the first call's (later ones find it cached)
    VolumetricResult results[4];
    for (int v = 0; v < 4; ++v) {
      params.method = variants[v].method;
      params.integrand_choice = variants[v].exact ? VolumetricIntegrandChoice::kExact : VolumetricIntegrandChoice::kSvd;
      for (int r = 0; r < repeats; ++r) {
        auto result = RenderVolumetricShadows(**worker, **gpu_scene, *scene, params);
        if (!result.ok()) {
          std::fprintf(stderr, "render: %s\n", std::string(result.status().message()).c_str());
          return 1;
        }
        best[v] = std::min(best[v], result->timings.traversal_ms);
        if (v == 0 && r == 0) table_ms = result->timings.integrand_table_ms;
        results[v] = std::move(*result);
      }
    }
    double peak = 0, integrand_diff = 0, method_diff = 0;
    for (size_t i = 0; i < results[0].inscattering.size(); ++i) {
      peak = std::max(peak, double(results[1].inscattering[i]));
      integrand_diff = std::max(integrand_diff, double(std::abs(results[0].inscattering[i] - results[1].inscattering[i])));
      method_diff = std::max(method_diff, double(std::abs(results[0].inscattering[i] - results[2].inscattering[i])));
    }
    std::printf("\n%s (g %.1f), %ux%u, %u map, integrand %s, K %u, table error %.3g (table %.1f ms)\n", label,
                params.medium.hg_g, params.camera.width, params.camera.height, params.shadow_map_size,
                std::string(VolumetricIntegrandName(results[0].integrand)).c_str(), results[0].svd_rank,
                results[0].integrand_error, table_ms);
    for (int v = 0; v < 4; ++v)
      std::printf("  %-20s %10.1f ms  %6.2fx the svd min-max time\n", variants[v].name, best[v], best[v] / best[0]);
    std::printf("  max |svd - per texel| (min-max) = %.3g of the peak %.3g; max |svd min-max - svd marching| = %.3g "
                "of the peak; mipmap (with prefix sums) %.1f ms svd, %.1f ms per texel\n",
                integrand_diff / peak, peak, method_diff / peak, results[0].timings.mipmap_ms,
                results[1].timings.mipmap_ms);
    std::fflush(stdout);
  }
  return 0;
}
