// Hidden-sample map (RASTER, EXACT and HOUGH lookups) against Embree
// (RAYCAST) on the same segments: rays per second side by side. A table, not
// a test.
//
//   visq_bench_hidden_sample_map [--quick] [--scenes DIR] [--only NAME]
//   visq_bench_hidden_sample_map --copies 1,4,16,64,300 [--scenes DIR]
//
// --quick: receivers 128^2 only, N = 32, 256 and 1024 (the counts
// gpu-check.sh reports the raster method at), clouds of 1K and 10K.
// --only: one case (sponza, veach-ajar, window, furnished, cloud-1K, ...).
// "window" is a room lit through a window with sash bars and a blind
// (tests/support/window_room.h), the light upright outside it and the
// floor the receiver: source and receiver far from parallel, the raster
// method's worst case (issue 49 section 2); "furnished" a furnished room's
// floor with the window opening itself as the source.
// --copies: what a query costs as the level around it grows. Sponza copied
// side by side (tests/support/large_scene.h), the same query at the first
// copy; RASTER warm time drawing every triangle a pass against drawing only
// the triangle clusters the shaft keeps, with the triangles each pass draws,
// the upload and the cluster hierarchy's build time and bytes.
// Rays = receiver texels x source samples. RASTER time is the GL job (run_ms:
// draw + readback, glFinish'd) plus the CPU bit counting; the one-off Hough
// table build is reported apart (it is cached per pattern), and so are the
// fragments the exact map's passes shade a receiver texel (all passes; N
// over 1,024 takes more than one on llvmpipe's 8 targets). Embree time is
// EmbreeScene::Occluded over the same segments, BVH build excluded.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "raycast/embree_scene.h"
#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "large_scene.h"
#include "window_room.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/hidden_sample_map.h"

using namespace visq;
using Clock = std::chrono::steady_clock;

namespace {

double Ms(Clock::time_point a) { return std::chrono::duration<double, std::milli>(Clock::now() - a).count(); }

Scene Cloud(int triangles, uint32_t seed) {
  Scene scene;
  scene.materials.push_back({"white"});
  scene.nodes.push_back({"root"});
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  // Triangles of area ~ 1/triangles so the cloud's occlusion stays moderate.
  const double size = 1.5 / std::sqrt(double(triangles));
  for (int k = 0; k < triangles; ++k) {
    const glm::dvec3 c(u(rng) * 1.4 - 0.2, 0.05 + 0.9 * u(rng), u(rng) * 1.4 - 0.2);
    for (int v = 0; v < 3; ++v) {
      scene.positions.push_back(c + size * glm::dvec3(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5));
    }
    scene.triangles.emplace_back(3 * k, 3 * k + 1, 3 * k + 2);
    scene.triangle_material.push_back(0);
    scene.triangle_node.push_back(0);
  }
  UpdateBounds(scene);
  return scene;
}

struct Case {
  std::string name;
  Scene scene;
  sampling::Patch source, receiver;
};

// Sponza: a light patch high in the atrium, the atrium floor as receiver.
void SponzaPatches(Case& c) {
  const glm::dvec3 lo = c.scene.bounds.min, e = c.scene.bounds.Extent(), m = c.scene.bounds.Center();
  const double ls = 0.08 * e.x;
  c.source = {{m.x - ls / 2, lo.y + 0.75 * e.y, m.z - ls / 2}, {ls, 0, 0}, {0, 0, ls}};
  // The atrium floor is at y = 0.13, well above the bounds' minimum (the
  // foundations reach y = -0.91): a receiver at lo.y + 1 % of the height
  // was under the floor and saw nothing (accuracy_trade.cpp finds the floor
  // with an Embree ray; 0.135 is what it finds).
  c.receiver = {{lo.x + 0.15 * e.x, 0.135, m.z - 0.2 * e.z}, {0.7 * e.x, 0, 0}, {0, 0, 0.4 * e.z}};
}

template <typename F>
double BestMs(int repeat, F&& f) {
  double best = 1e300;
  for (int i = 0; i < repeat; ++i) {
    const auto t = Clock::now();
    f();
    best = std::min(best, Ms(t));
  }
  return best;
}

// The --copies table (see the header comment).
int CopiesTable(gpu::GpuWorker& worker, const std::filesystem::path& scenes, const std::vector<int>& copies) {
  auto loaded = LoadGltfFile(scenes / "sponza_dabrovic/sponza.gltf");
  if (!loaded.ok()) {
    std::printf("skip: %s\n", std::string(loaded.status().message()).c_str());
    return 0;
  }
  Case one{"sponza", std::move(*loaded), {}, {}};
  SponzaPatches(one);
  gpu::HiddenSampleMapperOptions draw_all;
  draw_all.cull_clusters = false;
  auto all_mapper = gpu::HiddenSampleMapper::Create(worker, draw_all);
  auto culled_mapper = gpu::HiddenSampleMapper::Create(worker);
  if (!all_mapper.ok() || !culled_mapper.ok()) { std::printf("mapper failed\n"); return 1; }
  sampling::HiddenSampleMapRequest r;
  r.source.patch = one.source;
  r.source.sample_count = 128;
  r.source.pattern = sampling::SamplePattern::kJittered;
  r.receiver.patch = one.receiver;
  r.receiver.width = r.receiver.height = 128;
  std::printf("Sponza x copies, query at the first copy: receiver 128^2, N = 128 jittered; warm ms, best of 3\n");
  std::printf("%6s %9s | %9s %9s %8s %8s %8s | %9s %9s %7s | %9s %9s %6s | %9s %9s %6s | %7s %7s | %5s\n", "copies",
              "triangles", "upload ms", "build ms", "clusters", "tree B/t", "elem B/t", "drawn all", "culled", "cull ms",
              "exact all", "culled", "ratio", "hough all", "culled", "ratio", "x1 all", "x1 cull", "bits");
  double first_exact[2] = {0, 0};
  for (const int n : copies) {
    const Scene scene = testing::MakeCopies(one.scene, n);
    const double tris = double(scene.TriangleCount());
    // The hierarchy alone, over the same corners the upload makes.
    std::vector<glm::vec3> corners;
    corners.reserve(scene.TriangleCount() * 3);
    const glm::dvec3 anchor = scene.bounds.Center();
    for (size_t t = 0; t < scene.TriangleCount(); ++t)
      for (int k = 0; k < 3; ++k) corners.emplace_back(scene.Vertex(t, k) - anchor);
    std::vector<uint32_t> order;
    gpu::TriangleClusters clusters;
    const double build_ms = BestMs(3, [&] { clusters = gpu::TriangleClusters::Build(corners, order); });
    std::vector<glm::vec3>().swap(corners);
    std::shared_ptr<gpu::GpuScene> gpu_scene;
    const double upload_ms = BestMs(1, [&] {
      auto uploaded = gpu::GpuScene::Upload(worker, scene);
      if (uploaded.ok()) gpu_scene = *uploaded;
    });
    if (!gpu_scene) { std::printf("upload failed\n"); return 1; }
    double ms[2][2] = {{0, 0}, {0, 0}};  // [lookup][all, culled]
    bool same = true;
    for (int mode = 0; mode < 2; ++mode) {
      r.options.lookup = mode == 0 ? sampling::LookupMode::kExact : sampling::LookupMode::kHough;
      r.options.want_bitmasks = true;
      sampling::HiddenSampleMapResult results[2];
      for (int culled = 0; culled < 2; ++culled) {
        gpu::HiddenSampleMapper& mapper = culled ? **culled_mapper : **all_mapper;
        auto warm = mapper.Compute(*gpu_scene, r);  // table, programs
        if (!warm.ok()) { std::printf("%s\n", std::string(warm.status().message()).c_str()); return 1; }
        results[culled] = std::move(*warm);
        ms[mode][culled] = BestMs(3, [&] { (void)mapper.Compute(*gpu_scene, r); });
      }
      same = same && results[0].blocked_bits == results[1].blocked_bits &&
             results[0].visible_fraction == results[1].visible_fraction;
    }
    const uint64_t drawn_all = *(*all_mapper)->TrianglesDrawnPerPass(*gpu_scene, r);
    uint64_t drawn_culled = 0;
    // The query's CPU planning: its frames and shaft, and the cull.
    const double cull_ms =
        BestMs(3, [&] { drawn_culled = *(*culled_mapper)->TrianglesDrawnPerPass(*gpu_scene, r); });
    if (first_exact[0] == 0) { first_exact[0] = ms[0][0]; first_exact[1] = ms[0][1]; }
    const uint64_t index_bytes = scene.TriangleCount() * 3 * sizeof(uint32_t);
    std::printf("%6d %9.0f | %9.1f %9.1f %8zu %8.2f %8.2f | %9llu %9llu %7.2f | %9.1f %9.1f %6.2f | %9.1f %9.1f %6.2f | "
                "%7.2f %7.2f | %5s\n",
                n, tris, upload_ms, build_ms, clusters.cluster_count(), clusters.memory_bytes() / tris,
                index_bytes / tris, (unsigned long long)drawn_all, (unsigned long long)drawn_culled, cull_ms, ms[0][0],
                ms[0][1], ms[0][0] / ms[0][1], ms[1][0], ms[1][1], ms[1][0] / ms[1][1], ms[0][0] / first_exact[0],
                ms[0][1] / first_exact[1], same ? "same" : "DIFF");
    std::fflush(stdout);
  }
  std::printf("build: the cluster hierarchy alone (part of the upload); tree B/t: its CPU bytes a triangle; elem B/t:\n"
              "the element buffer (cluster order) on the GPU; cull ms: the query's CPU planning with the cull;\n"
              "ratio: all / culled at that size; x1: exact time over the first row's (the same query, one copy)\n");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  bool quick = false;
  std::string only;
  std::filesystem::path scenes = "/work/shared/scenes";
  std::vector<int> copies;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--quick")) quick = true;
    else if (!std::strcmp(argv[i], "--scenes") && i + 1 < argc) scenes = argv[++i];
    else if (!std::strcmp(argv[i], "--only") && i + 1 < argc) only = argv[++i];
    else if (!std::strcmp(argv[i], "--copies") && i + 1 < argc)
      for (const char* p = argv[++i]; *p != 0;) {
        char* end = nullptr;
        copies.push_back(std::max(1, int(std::strtol(p, &end, 10))));
        p = (*end == ',') ? end + 1 : end;
        if (end == p && *p != 0) break;
      }
  }
  auto worker = gpu::GpuWorker::Start({});
  if (!worker.ok()) { std::fprintf(stderr, "%s\n", std::string(worker.status().message()).c_str()); return 1; }
  gpu::HiddenSampleMapperOptions counting;
  counting.count_fragments = true;
  auto mapper = gpu::HiddenSampleMapper::Create(**worker, counting);
  if (!mapper.ok()) { std::fprintf(stderr, "%s\n", std::string(mapper.status().message()).c_str()); return 1; }
  std::printf("device: %s | %s\n", (*worker)->device().gl_renderer.c_str(), (*worker)->device().gl_version.c_str());
  if (!copies.empty()) return CopiesTable(**worker, scenes, copies);

  std::vector<Case> cases;
  auto add_loaded = [&](const std::string& name, const std::filesystem::path& path, auto make_patches) {
    if (!only.empty() && name != only) return;
    auto scene = LoadGltfFile(path);
    if (!scene.ok()) { std::printf("skip %s: %s\n", name.c_str(), std::string(scene.status().message()).c_str()); return; }
    Case c{name, std::move(*scene), {}, {}};
    make_patches(c);
    cases.push_back(std::move(c));
  };
  // Sponza: a light patch high in the atrium, the atrium floor as receiver.
  add_loaded("sponza", scenes / "sponza_dabrovic/sponza.gltf", SponzaPatches);
  // Veach ajar: a patch under the ceiling, the floor of the room.
  add_loaded("veach-ajar", scenes / "interior_veach_ajar/veach_ajar.gltf", [](Case& c) {
    const glm::dvec3 lo = c.scene.bounds.min, e = c.scene.bounds.Extent(), m = c.scene.bounds.Center();
    const double ls = 0.1 * std::min(e.x, e.z);
    c.source = {{m.x - ls / 2, lo.y + 0.9 * e.y, m.z - ls / 2}, {ls, 0, 0}, {0, 0, ls}};
    c.receiver = {{lo.x + 0.1 * e.x, lo.y + 0.01 * e.y, lo.z + 0.1 * e.z}, {0.8 * e.x, 0, 0}, {0, 0, 0.8 * e.z}};
  });
  {
    // The light upright 1 m outside the window, the lit floor as receiver.
    const sampling::Patch light{{-1.0, 2.0, -0.8}, {0, 1.6, 0}, {0, 0, 1.6}};
    Case c{"window", testing::MakeGrilleScene(), light, {}};
    c.receiver = {{0.2, 0.01, -1.5}, {3.0, 0, 0}, {0, 0, 3.0}};
    cases.push_back(std::move(c));
    // A furnished room, the window itself the source (sky light through
    // it), the floor the receiver: most of the furniture stands above the
    // sill.
    const sampling::Patch window{{-0.1, 0.8, -1.05}, {0, 1.4, 0}, {0, 0, 2.1}};
    Case f{"furnished", testing::MakeFurnishedWindowRoom(7), window, {}};
    f.receiver = {{0.2, 0.01, -2.3}, {4.6, 0, 0}, {0, 0, 4.6}};
    cases.push_back(std::move(f));
  }
  for (int k : quick ? std::vector<int>{1000, 10000} : std::vector<int>{1000, 10000, 100000}) {
    Case c{"cloud-" + std::to_string(k / 1000) + "K", Cloud(k, 42), {}, {}};
    c.source = {{0.25, 1.0, 0.25}, {0.5, 0, 0}, {0, 0, 0.5}};
    c.receiver = {{0, 0, 0}, {1, 0, 0}, {0, 0, 1}};
    cases.push_back(std::move(c));
  }

  const std::vector<int> sizes = quick ? std::vector<int>{128} : std::vector<int>{128, 512};
  const std::vector<int> counts = quick ? std::vector<int>{32, 256, 1024} : std::vector<int>{32, 128, 256, 1024};
  std::printf("%-11s %5s %5s %9s | %9s %9s | %9s %9s | %9s | %7s %7s | %8s %9s\n", "scene", "recv", "N", "tris",
              "exact ms", "Mrays/s", "hough ms", "Mrays/s", "embree ms", "Mrays/s", "", "x exact", "x hough");
  for (Case& c : cases) {
    if (!only.empty() && c.name != only) continue;
    auto gpu_scene = gpu::GpuScene::Upload(**worker, c.scene);
    auto embree = raycast::EmbreeScene::Create(c.scene);
    if (!gpu_scene.ok() || !embree.ok()) { std::printf("skip %s: upload failed\n", c.name.c_str()); continue; }
    for (int size : sizes)
      for (int n : counts) {
        sampling::HiddenSampleMapRequest r;
        r.source.patch = c.source;
        r.source.sample_count = n;
        r.source.pattern = sampling::SamplePattern::kJittered;
        r.receiver.patch = c.receiver;
        r.receiver.width = r.receiver.height = size;
        double ms[2] = {0, 0}, table_ms = 0;
        uint64_t shaded = 0;  // fragments, every pass of the exact map
        sampling::HiddenSampleMapResult exact_result;
        for (int mode = 0; mode < 2; ++mode) {
          r.options.lookup = mode == 0 ? sampling::LookupMode::kExact : sampling::LookupMode::kHough;
          auto warm = (*mapper)->Compute(**gpu_scene, r);  // builds/caches the table, compiles
          if (!warm.ok()) { std::printf("%s: %s\n", c.name.c_str(), std::string(warm.status().message()).c_str()); return 1; }
          table_ms = std::max(table_ms, warm->table_ms);
          const uint64_t shaded_before = (*mapper)->fragments_shaded().value_or(0);
          const auto t = Clock::now();
          auto result = (*mapper)->Compute(**gpu_scene, r);
          ms[mode] = Ms(t);
          if (mode == 0) shaded = (*mapper)->fragments_shaded().value_or(0) - shaded_before;
          if (mode == 0) exact_result = std::move(*result);
        }
        // Embree on the same segments.
        std::vector<raycast::Segment> segments;
        segments.reserve(size_t(size) * size * n);
        for (int y = 0; y < size; ++y)
          for (int x = 0; x < size; ++x) {
            const glm::dvec3 p = sampling::ReceiverSamplePosition(r.receiver, x, y);
            for (const glm::dvec3& q : exact_result.samples.world) segments.push_back({p, q});
          }
        const auto t = Clock::now();
        auto occluded = embree->Occluded(segments);
        const double embree_ms = Ms(t);
        uint64_t visible = 0;
        if (occluded.ok()) for (uint8_t o : *occluded) visible += !o;
        const double rays = double(size) * size * n;
        std::printf("%-11s %5d %5d %9zu | %9.1f %9.1f | %9.1f %9.1f | %9.1f | %7.1f %7s | %8.2f %9.2f   (vis %.3f, table %.0f ms, %.1f fragments a texel)\n",
                    c.name.c_str(), size, n, c.scene.TriangleCount(), ms[0], rays / ms[0] / 1e3, ms[1],
                    rays / ms[1] / 1e3, embree_ms, rays / embree_ms / 1e3, "", embree_ms / ms[0],
                    embree_ms / ms[1], double(visible) / rays, table_ms, double(shaded) / (double(size) * size));
        std::fflush(stdout);
      }
  }
  return 0;
}
