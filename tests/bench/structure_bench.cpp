// What a resident scene's lazily built structures cost: the Embree BVH at
// MEDIUM and HIGH build quality (build time, trace rate, bytes), the exact
// method's triangle index and the GPU buffers (time, bytes), per triangle.
// A table, not a test; the bytes per triangle are what
// server/core/structure_estimate.h admits scenes by.
//
//   visq_bench_structures [--scenes DIR] [--copies N] [--repeat R] [--only NAME]
//
// Each scene is measured as loaded and as N copies side by side (a level
// made of one repeated mesh), the copies twice: flattened ("flat", every
// structure holds every triangle) and kept as instances ("inst", the mesh
// once and N placements of it, as the loader keeps a mesh that several nodes
// share). Then the scene split into its nodes' meshes, each placed once per
// copy ("prefab", as a glTF of N parent nodes over one node tree loads): a
// copy's placements traced as one Embree instance ("grouped") and as one
// instance each ("each"). The inst column counts Embree instances.
// B/tri is per triangle of the level; B/unique per triangle held once (the
// instanced rows' per-instance cost is in it).
// Build and trace times are the least of R rounds, each round building and
// tracing MEDIUM then HIGH. Trace: 1M coherent occlusion
// segments (4096 receiver points x 256 samples of a light patch, as a
// RAYCAST hidden-sample map traces them) and 1M incoherent closest-hit rays
// from random points in random directions (as obscurance rays), on every
// core.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <random>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "exact/light_visibility.h"
#include "raycast/embree_scene.h"
#include "scene/gltf_loader.h"
#include "large_scene.h"
#include "visq/gpu/gpu_scene.h"

using namespace visq;
using Clock = std::chrono::steady_clock;

namespace {

double Ms(Clock::time_point a) { return std::chrono::duration<double, std::milli>(Clock::now() - a).count(); }

struct Trace {
  std::vector<raycast::Segment> segments;
  std::vector<raycast::Ray> rays;
};

// The first copy's workloads (the query at one copy of a level).
Trace MakeTrace(const Scene& one) {
  Trace t;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const glm::dvec3 lo = one.bounds.min, e = one.bounds.Extent();
  // A light patch high in the middle, receivers over the lower fifth.
  const glm::dvec3 light(lo.x + 0.45 * e.x, lo.y + 0.8 * e.y, lo.z + 0.45 * e.z);
  for (int r = 0; r < 4096; ++r) {
    const glm::dvec3 p(lo.x + u(rng) * e.x, lo.y + (0.02 + 0.2 * u(rng)) * e.y, lo.z + u(rng) * e.z);
    for (int s = 0; s < 256; ++s)
      t.segments.push_back({p, light + glm::dvec3(0.1 * e.x * (s % 16) / 16.0, 0.0, 0.1 * e.z * (s / 16) / 16.0)});
  }
  std::normal_distribution<double> n(0.0, 1.0);
  for (int r = 0; r < (1 << 20); ++r) {
    const glm::dvec3 o(lo.x + u(rng) * e.x, lo.y + u(rng) * e.y, lo.z + u(rng) * e.z);
    t.rays.push_back({o, glm::normalize(glm::dvec3(n(rng), n(rng), n(rng)))});
  }
  return t;
}

template <typename F>
double Best(int repeat, F&& f) {
  double best = 1e300;
  for (int i = 0; i < repeat; ++i) {
    const auto start = Clock::now();
    f();
    best = std::min(best, Ms(start));
  }
  return best;
}

}  // namespace

int main(int argc, char** argv) {
  std::filesystem::path scenes = "../shared/scenes";
  int copies = 16;
  int repeat = 3;
  std::string only;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--scenes") && i + 1 < argc) scenes = argv[++i];
    else if (!std::strcmp(argv[i], "--copies") && i + 1 < argc) copies = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--repeat") && i + 1 < argc) repeat = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--only") && i + 1 < argc) only = argv[++i];
  }
  auto worker = gpu::GpuWorker::Start({});
  if (!worker.ok()) {
    std::fprintf(stderr, "%s\n", std::string(worker.status().message()).c_str());
    return 1;
  }
  std::printf("device: %s; %u hardware threads\n", (*worker)->device().gl_renderer.c_str(),
              std::thread::hardware_concurrency());
  std::printf("%-28s %9s %5s %6s | %-6s %9s %8s %9s %9s %9s | %9s %8s %9s | %8s %8s | %8s\n", "scene", "triangles",
              "V/T", "inst", "BVH", "build ms", "B/tri", "B/unique", "occl Mr/s", "hit Mr/s", "index ms", "B/tri",
              "B/unique", "GPU ms", "B/tri", "scene B/t");
  for (const char* file : {"sponza_dabrovic/sponza.gltf", "interior_veach_ajar/veach_ajar.gltf", "bunny/bunny.gltf"}) {
    if (!only.empty() && std::string(file).find(only) == std::string::npos) continue;
    auto loaded = LoadGltfFile(scenes / file);
    if (!loaded.ok()) {
      std::printf("skip %s: %s\n", file, std::string(loaded.status().message()).c_str());
      continue;
    }
    const Trace trace = MakeTrace(*loaded);
    enum class Layout { kFlat, kInstanced, kPrefabGrouped, kPrefabEach };
    struct Level {
      int copies;
      Layout layout;
    };
    const std::vector<Scene> parts = testing::SplitByNode(*loaded);
    const std::vector<glm::dmat4> worlds = testing::CopyWorlds(*loaded, copies);
    for (const Level level : {Level{1, Layout::kFlat}, Level{copies, Layout::kFlat}, Level{copies, Layout::kInstanced},
                              Level{copies, Layout::kPrefabGrouped}, Level{copies, Layout::kPrefabEach}}) {
      const int n = level.copies;
      if (parts.size() < 2 && (level.layout == Layout::kPrefabGrouped || level.layout == Layout::kPrefabEach)) continue;
      const Scene scene = level.layout == Layout::kFlat        ? testing::Flattened(testing::MakeCopies(*loaded, n))
                          : level.layout == Layout::kInstanced ? testing::MakeCopies(*loaded, n)
                                                               : testing::PlaceMeshes(parts, worlds);
      const double tris = double(scene.TriangleCount());
      const char* layout_name[] = {" flat", " inst", " prefab grouped", " prefab each"};
      const std::string name = std::filesystem::path(file).stem().string() +
                               (n > 1 ? " x" + std::to_string(n) + layout_name[int(level.layout)] : "");
      // Triangles held once: those of no placement, and each mesh's once.
      double unique = tris;
      if (!scene.placements.empty()) {
        unique = 0;
        std::vector<uint8_t> placed(scene.TriangleCount(), 0);
        for (const MeshPlacement& p : scene.placements)
          std::fill_n(placed.begin() + p.first_triangle, scene.meshes[p.mesh].triangles.size(), uint8_t{1});
        unique = double(std::count(placed.begin(), placed.end(), 0));
        for (const SceneMesh& m : scene.meshes) unique += double(m.triangles.size());
      }
      // The exact method's index and the GPU buffers.
      size_t index_bytes = 0;
      const auto shared_scene = std::make_shared<const Scene>(scene);
      const double index_ms =
          Best(repeat, [&] { index_bytes = (*exact::SceneTriangleIndex::Build(shared_scene))->MemoryBytes(); });
      uint64_t gpu_bytes = 0;
      const double gpu_ms = Best(repeat, [&] { gpu_bytes = (*gpu::GpuScene::Upload(**worker, scene))->gpu_bytes(); });
      // Both qualities built and traced in turn, R rounds, the best of each:
      // load from elsewhere on the machine then weighs on both alike.
      const raycast::BuildQuality qualities[2] = {raycast::BuildQuality::kMedium, raycast::BuildQuality::kHigh};
      std::optional<raycast::EmbreeScene> bvh[2];
      double build_ms[2] = {1e300, 1e300}, occl_ms[2] = {1e300, 1e300}, hit_ms[2] = {1e300, 1e300};
      for (int round = 0; round < repeat; ++round)
        for (int q = 0; q < 2; ++q) {
          raycast::EmbreeSceneOptions options;
          options.quality = qualities[q];
          options.group_placements = level.layout != Layout::kPrefabEach;
          options.shared_scene = shared_scene;  // as the server builds it
          bvh[q].reset();
          build_ms[q] = std::min(build_ms[q], Best(1, [&] { bvh[q].emplace(*raycast::EmbreeScene::Create(*shared_scene, options)); }));
          occl_ms[q] = std::min(occl_ms[q], Best(1, [&] { (void)bvh[q]->Occluded(trace.segments); }));
          hit_ms[q] = std::min(hit_ms[q], Best(1, [&] { (void)bvh[q]->Intersect(trace.rays); }));
        }
      for (int q = 0; q < 2; ++q)
        std::printf("%-28s %9.0f %5.2f %6zu | %-6s %9.1f %8.1f %9.1f %9.2f %9.2f | %9.1f %8.1f %9.1f | %8.1f %8.1f | %8.1f\n",
                    name.c_str(), tris, scene.positions.size() / tris, bvh[q]->instance_group_count(),
                    q == 1 ? "HIGH" : "MEDIUM", build_ms[q], bvh[q]->memory_bytes() / tris,
                    bvh[q]->memory_bytes() / unique, trace.segments.size() / occl_ms[q] / 1e3,
                    trace.rays.size() / hit_ms[q] / 1e3, index_ms, index_bytes / tris, index_bytes / unique, gpu_ms,
                    gpu_bytes / tris, scene.CpuBytes() / tris);
    }
  }
  return 0;
}
