// Occlusion rays: the GPU ray method (gpu::RayScene, GPU_RAYCAST) against
// Embree on every thread of this process (RAYCAST), over the same segments
// and the same float frame: Mrays/s side by side, their ratio, and how many
// answers differ (float ties). A table, not a test.
//
//   visq_bench_rays [--quick] [--scenes DIR]
//
// Two kinds of segments a scene:
// - coherent: a hidden-sample map's, a 256 x 256 receiver just above the
//   floor to 64 jittered points of a light patch under the ceiling (4M);
// - incoherent: pairs of random points inside the scene's bounds (1M).
// --quick: a quarter of each. Times are warm (the program compiled, the BVH
// built and uploaded once, outside the clock); the GPU's include making the
// segments on the CPU, copying them over and reading the bits back, as a
// call pays them. On llvmpipe the GPU side runs on the same CPU cores.
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "raycast/embree_scene.h"
#include "raycast/flat_bvh.h"
#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "visq/gpu/ray_scene.h"

using namespace visq;
using Clock = std::chrono::steady_clock;

namespace {

double Ms(Clock::time_point a) { return std::chrono::duration<double, std::milli>(Clock::now() - a).count(); }

std::vector<raycast::Segment> CoherentSegments(const Scene& scene, int side, int samples) {
  const glm::dvec3 lo = scene.bounds.min, e = scene.bounds.Extent(), m = scene.bounds.Center();
  const double light = 0.15 * std::min(e.x, e.z);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  std::vector<glm::dvec3> lights;
  const int cells = int(std::sqrt(double(samples)));
  for (int j = 0; j < cells; ++j)
    for (int i = 0; i < cells; ++i)
      lights.push_back({m.x - light / 2 + light * (i + unit(rng)) / cells, lo.y + 0.9 * e.y,
                        m.z - light / 2 + light * (j + unit(rng)) / cells});
  std::vector<raycast::Segment> segments;
  segments.reserve(size_t(side) * side * lights.size());
  for (int y = 0; y < side; ++y)
    for (int x = 0; x < side; ++x) {
      const glm::dvec3 p(lo.x + e.x * (0.1 + 0.8 * (x + 0.5) / side), lo.y + 0.01 * e.y,
                         lo.z + e.z * (0.1 + 0.8 * (y + 0.5) / side));
      for (const glm::dvec3& q : lights) segments.push_back({p, q});
    }
  return segments;
}

std::vector<raycast::Segment> IncoherentSegments(const Scene& scene, size_t count) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> unit(0.05, 0.95);
  const glm::dvec3 lo = scene.bounds.min, e = scene.bounds.Extent();
  std::vector<raycast::Segment> segments(count);
  for (raycast::Segment& s : segments) {
    s.p = lo + glm::dvec3(unit(rng), unit(rng), unit(rng)) * e;
    s.q = lo + glm::dvec3(unit(rng), unit(rng), unit(rng)) * e;
  }
  return segments;
}

}  // namespace

int main(int argc, char** argv) {
  bool quick = false;
  std::filesystem::path scenes = "../shared/scenes";
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--quick")) quick = true;
    else if (!std::strcmp(argv[i], "--scenes") && i + 1 < argc) scenes = argv[++i];
  }
  auto worker = gpu::GpuWorker::Start({});
  if (!worker.ok()) {
    std::fprintf(stderr, "%s\n", std::string(worker.status().message()).c_str());
    return 1;
  }
  std::printf("device: %s | %s\n", (*worker)->device().gl_renderer.c_str(), (*worker)->device().gl_version.c_str());
  struct Case {
    std::string name;
    Scene scene;
  };
  std::vector<Case> cases;
  cases.push_back({"cornell", MakeCornellBox()});
  for (const auto& [name, file] : {std::pair{"sponza", "sponza_dabrovic/sponza.gltf"},
                                   std::pair{"veach-ajar", "interior_veach_ajar/veach_ajar.gltf"},
                                   std::pair{"bunny", "bunny/bunny.gltf"}}) {
    auto scene = LoadGltfFile(scenes / file);
    if (!scene.ok()) {
      std::printf("skip %s: %s\n", name, std::string(scene.status().message()).c_str());
      continue;
    }
    cases.push_back({name, std::move(*scene)});
  }
  const int side = quick ? 128 : 256;
  const size_t incoherent = quick ? (size_t{1} << 18) : (size_t{1} << 20);
  std::printf("%-11s %9s %-10s %9s | %9s %9s | %9s %9s | %8s | %7s | %9s %9s\n", "scene", "tris", "segments", "count",
              "embree ms", "Mrays/s", "gpu ms", "Mrays/s", "gpu/emb", "differ", "bvh ms", "bvh MB");
  for (Case& c : cases) {
    auto embree = raycast::EmbreeScene::Create(c.scene);
    const auto build_start = Clock::now();
    auto bvh = raycast::BuildFlatBvh(c.scene);
    const double bvh_ms = Ms(build_start);
    if (!embree.ok() || !bvh.ok()) {
      std::printf("skip %s: a build failed\n", c.name.c_str());
      continue;
    }
    auto rays = gpu::RayScene::Upload(**worker, *bvh);
    if (!rays.ok()) {
      std::printf("skip %s: %s\n", c.name.c_str(), std::string(rays.status().message()).c_str());
      continue;
    }
    for (const bool coherent : {true, false}) {
      const std::vector<raycast::Segment> segments =
          coherent ? CoherentSegments(c.scene, side, 64) : IncoherentSegments(c.scene, incoherent);
      auto at = [&](size_t i) { return segments[i]; };
      // Warm both: the shader's compile, the sizer's first jobs, Embree's caches.
      (void)(*rays)->Occluded(std::min<size_t>(segments.size(), 65536), at);
      (void)embree->Occluded(std::span(segments).first(std::min<size_t>(segments.size(), 65536)));
      auto t = Clock::now();
      auto reference = embree->Occluded(segments);
      const double embree_ms = Ms(t);
      t = Clock::now();
      auto traced = (*rays)->Occluded(segments.size(), at);
      const double gpu_ms = Ms(t);
      if (!reference.ok() || !traced.ok()) {
        std::printf("%s: a trace failed\n", c.name.c_str());
        return 1;
      }
      size_t differ = 0;
      for (size_t i = 0; i < segments.size(); ++i) differ += (*reference)[i] != (*traced)[i];
      const double mrays = double(segments.size()) / 1000.0;
      std::printf("%-11s %9zu %-10s %9zu | %9.1f %9.2f | %9.1f %9.2f | %8.2f | %7zu | %9.1f %9.1f\n", c.name.c_str(),
                  c.scene.TriangleCount(), coherent ? "coherent" : "incoherent", segments.size(), embree_ms,
                  mrays / embree_ms, gpu_ms, mrays / gpu_ms, gpu_ms / embree_ms, differ, bvh_ms,
                  double(bvh->bytes()) / (1 << 20));
    }
  }
  return 0;
}
