// Obscurance bake: GPU depth peeling vs Embree casting cosine-distributed
// rays from every patch, with the same number of samples per patch and
// again with the ray count that gives the bake's error (a bundle's samples
// of one patch share one direction, so they are worth far fewer than as
// many rays), time and RMS error against a converged Embree reference; and
// the update latency for moving a ~1K-triangle object in Sponza. Prints a
// table; not a test.
//
//   visq_bench_obscurance [--quick] [--update-only] [--scene NAME] [--atlas N] [--directions N]
//                         [--bundle N] [--scenes DIR]
// --quick: Sponza only, 512^2, 16/64 directions, a 256-ray reference.
// --update-only: only the Sponza update latency.
// --scene sponza|veach_ajar, --atlas N, --directions N: only this scene,
// atlas resolution, direction count.
// --bundle N: pixels across each direction's bundle (default: 2 x atlas).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include <glm/gtc/matrix_transform.hpp>

#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "obscurance/obscurance_rays.h"
#include "obscurance/obscurance_update.h"
#include "scene/gltf_loader.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"
#include "visq/gpu/obscurance.h"

using namespace visq;
using namespace visq::obscurance;

namespace {

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

double Rms(const ObscuranceAtlas& atlas, const ObscuranceResult& x, const ObscuranceResult& y) {
  double s = 0;
  size_t n = 0;
  for (uint32_t t = 0; t < atlas.texel_count(); ++t) {
    if (!atlas.Covered(t) || !x.estimated[t] || !y.estimated[t]) continue;
    for (int c = 0; c < 3; ++c) {
      const double d = static_cast<double>(x.w[t][c]) - y.w[t][c];
      s += d * d;
      ++n;
    }
  }
  return n ? std::sqrt(s / n) : 0;
}

}  // namespace

int main(int argc, char** argv) {
  bool quick = false, update_only = false;
  uint32_t bundle = 0, only_directions = 0, only_atlas = 0;
  std::string only_scene;
  std::filesystem::path dir = "../shared/scenes";
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--quick")) quick = true;
    else if (!std::strcmp(argv[i], "--update-only")) update_only = true;
    else if (!std::strcmp(argv[i], "--scene") && i + 1 < argc) only_scene = argv[++i];
    else if (!std::strcmp(argv[i], "--atlas") && i + 1 < argc) only_atlas = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--directions") && i + 1 < argc)
      only_directions = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--bundle") && i + 1 < argc) bundle = static_cast<uint32_t>(std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--scenes") && i + 1 < argc) dir = argv[++i];
  }
  auto worker = gpu::GpuWorker::Start({});
  if (!worker.ok()) { std::fprintf(stderr, "%s\n", std::string(worker.status().message()).c_str()); return 1; }
  std::printf("device: %s\n", (*worker)->device().gl_renderer.c_str());
  struct SceneCase { std::string name; std::filesystem::path path; };
  std::vector<SceneCase> scenes = {{"sponza", dir / "sponza_dabrovic/sponza.gltf"}};
  if (!quick || !only_scene.empty()) scenes.push_back({"veach_ajar", dir / "interior_veach_ajar/veach_ajar.gltf"});
  if (!only_scene.empty()) std::erase_if(scenes, [&](const SceneCase& c) { return c.name != only_scene; });
  const std::vector<uint32_t> resolutions = only_atlas ? std::vector<uint32_t>{only_atlas}
                                            : quick    ? std::vector<uint32_t>{512}
                                                       : std::vector<uint32_t>{512, 1024};
  const std::vector<uint32_t> directions = only_directions ? std::vector<uint32_t>{only_directions}
                                          : quick           ? std::vector<uint32_t>{16, 64}
                                                            : std::vector<uint32_t>{64, 256, 1024};
  const uint32_t reference_rays = quick ? 256 : 2048;

  std::printf("%-10s %5s %5s | %9s %8s %8s | %9s %8s %8s | %9s %8s %8s | %s\n", "scene", "atlas", "dirs", "gpu s", "rms",
              "smp/pt", "embree s", "rms", "rays/pt", "eq-err s", "rms", "rays/pt", "reference");
  for (const SceneCase& sc : scenes) {
    auto scene = LoadGltfFile(sc.path);
    if (!scene.ok()) { std::printf("%s: %s\n", sc.name.c_str(), std::string(scene.status().message()).c_str()); continue; }
    auto gpu_scene = gpu::GpuScene::Upload(**worker, *scene);
    if (!gpu_scene.ok()) return 1;
    ObscuranceParams params;
    params.d_max = 0.1 * glm::length(scene->bounds.Extent());
    params.color_bleeding = true;
    params.bundle_resolution = bundle;
    for (uint32_t res : update_only ? std::vector<uint32_t>{} : resolutions) {
      auto t0 = std::chrono::steady_clock::now();
      auto atlas = BuildObscuranceAtlas(*scene, res);
      if (!atlas.ok()) { std::printf("%s %u: %s\n", sc.name.c_str(), res, std::string(atlas.status().message()).c_str()); continue; }
      const double atlas_s = Seconds(t0);
      RayEstimateOptions ref_options;
      ref_options.rays_per_patch = reference_rays;
      ref_options.seed = 999;
      t0 = std::chrono::steady_clock::now();
      auto reference = EstimateObscurancesByRays(*scene, *atlas, params, ref_options);
      if (!reference.ok()) return 1;
      const double ref_s = Seconds(t0);
      for (uint32_t d : directions) {
        params.direction_count = d;
        gpu::ObscuranceBakeStats stats;
        t0 = std::chrono::steady_clock::now();
        auto baked = gpu::BakeObscurances(**worker, **gpu_scene, *scene, *atlas, params, {}, &stats);
        if (!baked.ok()) { std::printf("bake: %s\n", std::string(baked.status().message()).c_str()); return 1; }
        const double gpu_s = Seconds(t0);
        RayEstimateOptions ro;
        ro.rays_per_patch = std::max<uint32_t>(1, static_cast<uint32_t>(std::lround(baked->mean_samples_per_patch)));
        t0 = std::chrono::steady_clock::now();
        auto rays = EstimateObscurancesByRays(*scene, *atlas, params, ro);
        if (!rays.ok()) return 1;
        const double ray_s = Seconds(t0);
        const double gpu_rms = Rms(*atlas, *baked, *reference), ray_rms = Rms(*atlas, *rays, *reference);
        // Equal error: the fewest rays per patch whose error is at most the
        // bake's, by bisection (the error falls with the ray count, but not
        // exactly like 1/sqrt(N): the rays are stratified), timed at the end.
        RayEstimateOptions eq = ro;
        if (ray_rms <= gpu_rms) {
          uint32_t too_few = 0, enough = ro.rays_per_patch;
          while (enough - too_few > 1) {
            RayEstimateOptions trial = ro;
            trial.rays_per_patch = too_few + (enough - too_few) / 2;
            auto estimate = EstimateObscurancesByRays(*scene, *atlas, params, trial);
            if (!estimate.ok()) return 1;
            (Rms(*atlas, *estimate, *reference) <= gpu_rms ? enough : too_few) = trial.rays_per_patch;
          }
          eq.rays_per_patch = enough;
        }
        t0 = std::chrono::steady_clock::now();
        auto rays_eq = EstimateObscurancesByRays(*scene, *atlas, params, eq);
        if (!rays_eq.ok()) return 1;
        const double eq_s = Seconds(t0);
        std::printf("%-10s %5u %5u | %9.2f %8.4f %8.0f | %9.2f %8.4f %8u | %9.2f %8.4f %8u | %u rays/pt %.0f s, atlas %.1f s, "
                    "%u charts, max layers %u\n",
                    sc.name.c_str(), res, d, gpu_s, gpu_rms, baked->mean_samples_per_patch, ray_s, ray_rms,
                    ro.rays_per_patch, eq_s, Rms(*atlas, *rays_eq, *reference), eq.rays_per_patch, reference_rays, ref_s,
                    atlas_s, atlas->chart_count, stats.max_layers);
        std::fflush(stdout);
      }
    }
    // Update latency: the node nearest 1K triangles.
    if (sc.name != "sponza") continue;
    uint32_t node = 0;
    for (uint32_t n = 0; n < scene->nodes.size(); ++n)
      if (std::abs(static_cast<int>(scene->nodes[n].triangle_count) - 1000) <
          std::abs(static_cast<int>(scene->nodes[node].triangle_count) - 1000))
        node = n;
    auto atlas = BuildObscuranceAtlas(*scene, 512);
    if (!atlas.ok()) return 1;
    params.direction_count = 16;
    auto baked = gpu::BakeObscurances(**worker, **gpu_scene, *scene, *atlas, params);
    if (!baked.ok()) return 1;
    // Each ray count twice: the plain path (every texel scanned, one ray at
    // a time) and the fast one (patch index, ray streams); the two must end
    // with the same W bit for bit.
    std::vector<glm::vec3> plain_w;
    for (uint32_t rays : {16u, 64u})
    for (int variant = 0; variant < 3; ++variant) {
      const bool exhaustive = variant == 0;
      UpdaterOptions uo;
      uo.rays_per_patch = rays;
      uo.exhaustive = exhaustive;
      uo.ray_streams = variant == 2;
      auto t0 = std::chrono::steady_clock::now();
      auto updater = ObscuranceUpdater::Create(*scene, *atlas, params, *baked, {node}, uo);
      if (!updater.ok()) { std::printf("updater: %s\n", std::string(updater.status().message()).c_str()); return 1; }
      const double create_s = Seconds(t0);
      std::vector<double> ms;
      ObscuranceUpdate last;
      for (int step = 1; step <= 5; ++step) {
        const glm::dmat4 world = glm::translate(glm::dmat4(1.0), glm::dvec3(0.02 * step * params.d_max * 10, 0, 0)) *
                                 scene->nodes[node].world;
        auto up = (*updater)->MoveNode(node, world);
        if (!up.ok()) { std::printf("update: %s\n", std::string(up.status().message()).c_str()); return 1; }
        ms.push_back(up->milliseconds);
        last = *up;
      }
      std::sort(ms.begin(), ms.end());
      std::printf("update sponza node '%s' (%u triangles), %u rays/patch, %s, d_max %.2f: median %.1f ms (min %.1f, max %.1f); "
                  "last move: %u pooled, %u within reach, %u candidates, %zu texels changed, %u recomputed, %llu rays "
                  "(move %.1f, candidates %.1f, trace %.1f ms); "
                  "create %.2f s\n",
                  scene->nodes[node].name.c_str(), scene->nodes[node].triangle_count, rays,
                  variant == 0 ? "plain (scan, 1 ray)" : variant == 1 ? "index, 1 ray" : "index, streams", params.d_max, ms[2], ms[0],
                  ms[4], last.pooled, last.within_reach, last.candidates, last.texels.size(), last.recomputed, static_cast<unsigned long long>(last.rays), last.move_ms, last.candidates_ms,
                  last.trace_ms, create_s);
      if (exhaustive) {
        plain_w = (*updater)->result().w;
      } else {
        size_t differ = 0;
        for (size_t t = 0; t < plain_w.size(); ++t)
          differ += std::memcmp(&plain_w[t], &(*updater)->result().w[t], sizeof(glm::vec3)) != 0;
        std::printf("  vs plain after 5 moves: %zu of %zu texels differ\n", differ, plain_w.size());
      }
    }
  }
  return 0;
}
