// Exact soft-shadow visibility (visq_exact, Mora et al. 2013) against Embree
// shadow rays (32 per point, stratified) on the same points: time, memory,
// and the sampled method's error against the exact answer.
//
//   visq_bench_exact [--occluders=N] [--size=S] [--boxes=N] [--grid=N]
//                    [--threads=N] [--rays=N] [--tiles=N] [--seed=N]
//
// Exact trees are built per receiver tile (tiles x tiles over the receiver
// bounds), the way the paper groups receivers per triangle: each tree then
// holds only the occluders in its tile's shaft.
//
// The scene is a BenchCase (scene, light, receiver points): MakeProcedural()
// builds one; MakeFromGltf() takes the points a pinhole camera sees in a
// glTF scene (one per pixel) and groups them as the server groups a batch:
// by cubes of 1/32 of the scene's size (exact::GroupReceivers), one tree
// each; --cells-per-side=0 groups them by image tile instead:
//
//   visq_bench_exact --gltf=../shared/scenes/sponza_dabrovic/sponza.gltf
//     --light='-1,10,-0.5;1,10,-0.5;1,10,0.5;-1,10,0.5' --eye=-10,2,0
//     --look-at=10,3,0 [--width=1280 --height=720]
//     [--cells-per-side=32 | --cells-per-side=0 --tile-pixels=32]
#include <algorithm>
#include <bit>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>
#include <thread>
#include <memory>
#include <filesystem>
#include <optional>

#include <sys/resource.h>
#include <time.h>

#include "exact/light_visibility.h"
#include "scene/gltf_loader.h"
#include "raycast/embree_scene.h"
#include "sampling/visibility_sampling.h"

namespace {

using visq::Bounds;
using visq::Scene;
using visq::exact::AreaLight;
using visq::exact::QueryPoint;

struct BenchCase {
  std::string name;
  Scene scene;
  AreaLight light;
  std::vector<QueryPoint> points;  // with normals and receiver triangles
  Bounds receivers;
  // Which tree each point belongs to (image tiles for a camera view); empty:
  // tiles x tiles over the receivers' x-y extent.
  std::vector<uint32_t> tile_of_point;
  uint32_t tile_count = 0;
  std::vector<Bounds> tile_boxes;  // receiver cells' boxes; empty: each tile's points' box
};

struct Params {
  int occluders = 300;
  double size = 0.08;  // occluder half-size
  int boxes = 6;
  int grid = 64;
  int threads = 0;
  int rays = 32;
  int tiles = 8;  // receiver tiles per side, one tree each (as the paper groups receivers)
  uint32_t seed = 1;
  // A glTF scene seen from a camera instead of the procedural case.
  std::string gltf;
  std::string light;          // "x,y,z;x,y,z;x,y,z;x,y,z", a parallelogram, front counter-clockwise
  glm::dvec3 eye{0.0}, look_at{1.0, 0.0, 0.0};
  int width = 1280, height = 720;
  int tile_pixels = 32;       // image tiles of this many pixels a side, one tree each
  // Receiver cells per side of the scene (exact::GroupReceivers), one tree
  // each, as the server groups a batch; 0: image tiles instead.
  int cells_per_side = 32;
  double tree_max_mb = 16;    // each tree's memory budget (TreeOptions::max_bytes), as the server's default
  // > 0: group the points as the server does without a grid
  // (exact::GroupReceiversByShaft with this many triangles per shaft),
  // instead of cells or tiles.
  size_t shaft_triangles = 0;
  double shaft_cap = visq::exact::ShaftGrouping{}.hard_cap;
  // The time-to-error table: Embree with k x k rays on an even grid per
  // point, k growing until its RMS error reaches the last target (or k = 64).
  bool error_table = true;
  // Where to write every point's exact answer, as the bits of its three
  // doubles (one line a point): two builds' files compare bit for bit.
  std::string answers_out;
};

// CPU seconds of the whole process (every thread).
double ProcessCpuSeconds() {
  timespec t{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + 1e-9 * static_cast<double>(t.tv_nsec);
}

double PeakRssMiB() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_maxrss) / 1024.0;
}

void AddTriangle(Scene& s, const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  const uint32_t base = static_cast<uint32_t>(s.positions.size());
  for (const auto& p : {a, b, c}) {
    s.positions.push_back(p);
    s.bounds.Extend(p);
  }
  s.triangles.push_back(glm::uvec3(base, base + 1, base + 2));
  s.triangle_material.push_back(0);
  s.triangle_node.push_back(0);
}

// An axis-aligned box as 12 outward-facing triangles.
void AddBox(Scene& s, const glm::dvec3& lo, const glm::dvec3& hi) {
  auto c = [&](int i) {
    return glm::dvec3(i & 1 ? hi.x : lo.x, i & 2 ? hi.y : lo.y, i & 4 ? hi.z : lo.z);
  };
  const int faces[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                           {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& f : faces) {
    AddTriangle(s, c(f[0]), c(f[1]), c(f[2]));
    AddTriangle(s, c(f[0]), c(f[2]), c(f[3]));
  }
}

// A 4 x 4 floor at z = 0 (the receiver), a 1 x 1 ceiling light at z = 2,
// a cloud of small random triangles in between and boxes standing on the
// floor (which touch the receiver: the per-query "near" path).
BenchCase MakeProcedural(const Params& p) {
  BenchCase bc;
  bc.name = "procedural";
  Scene& s = bc.scene;
  AddTriangle(s, {-2, -2, 0}, {2, -2, 0}, {2, 2, 0});
  AddTriangle(s, {-2, -2, 0}, {2, 2, 0}, {-2, 2, 0});
  std::mt19937 rng(p.seed);
  std::uniform_real_distribution<double> u(-1, 1), h(0.4, 1.8);
  for (int i = 0; i < p.occluders; ++i) {
    const glm::dvec3 c(1.8 * u(rng), 1.8 * u(rng), h(rng));
    AddTriangle(s, c + p.size * glm::dvec3(u(rng), u(rng), u(rng)),
                c + p.size * glm::dvec3(u(rng), u(rng), u(rng)),
                c + p.size * glm::dvec3(u(rng), u(rng), u(rng)));
  }
  for (int i = 0; i < p.boxes; ++i) {
    const glm::dvec3 c(1.5 * u(rng), 1.5 * u(rng), 0.0);
    AddBox(s, c - glm::dvec3(0.15, 0.15, 0.0), c + glm::dvec3(0.15, 0.15, 0.2 + 0.3 * (u(rng) + 1)));
  }
  bc.light.vertices = {{-0.5, -0.5, 2}, {-0.5, 0.5, 2}, {0.5, 0.5, 2}, {0.5, -0.5, 2}};
  bc.light.radiance = 10.0;
  for (int i = 0; i < p.grid; ++i) {
    for (int j = 0; j < p.grid; ++j) {
      const glm::dvec3 x(-1.95 + 3.9 * (i + 0.5) / p.grid, -1.95 + 3.9 * (j + 0.5) / p.grid, 0.0);
      bc.points.push_back({x, glm::dvec3(0, 0, 1), x.x - x.y > 0 ? 0u : 1u});
    }
  }
  bc.receivers.Extend({-2, -2, 0});
  bc.receivers.Extend({2, 2, 0});
  return bc;
}

// Points on the visible surfaces of a glTF scene, one per pixel of a
// pinhole camera (60 degree vertical field), found by Embree primary rays;
// each pixel's tree is its image tile's, as the paper groups receivers.
std::optional<BenchCase> MakeFromGltf(const Params& p) {
  auto scene = visq::LoadGltfFile(p.gltf);
  if (!scene.ok()) {
    std::fprintf(stderr, "%s: %s\n", p.gltf.c_str(), scene.status().ToString().c_str());
    return std::nullopt;
  }
  BenchCase bc;
  bc.name = std::filesystem::path(p.gltf).stem().string();
  bc.scene = std::move(*scene);
  for (size_t start = 0; start <= p.light.size();) {
    const size_t end = std::min(p.light.find(';', start), p.light.size());
    glm::dvec3 v;
    if (std::sscanf(p.light.substr(start, end - start).c_str(), "%lf,%lf,%lf", &v.x, &v.y, &v.z) != 3) {
      std::fprintf(stderr, "--light: '%s' is not x,y,z;x,y,z;...\n", p.light.c_str());
      return std::nullopt;
    }
    bc.light.vertices.push_back(v);
    start = end + 1;
  }
  if (bc.light.vertices.size() != 4) {
    std::fprintf(stderr, "--light: a parallelogram needs 4 vertices\n");
    return std::nullopt;
  }
  bc.light.radiance = 10.0;
  auto embree = visq::raycast::EmbreeScene::Create(bc.scene);
  if (!embree.ok()) return std::nullopt;
  const glm::dvec3 forward = glm::normalize(p.look_at - p.eye);
  const glm::dvec3 right = glm::normalize(glm::cross(forward, glm::dvec3(0, 1, 0)));
  const glm::dvec3 up = glm::cross(right, forward);
  const double half_height = std::tan(M_PI / 6.0), half_width = half_height * p.width / p.height;
  std::vector<visq::raycast::Ray> rays;
  for (int y = 0; y < p.height; ++y)
    for (int x = 0; x < p.width; ++x) {
      const double sx = (2.0 * (x + 0.5) / p.width - 1.0) * half_width;
      const double sy = (1.0 - 2.0 * (y + 0.5) / p.height) * half_height;
      rays.push_back({p.eye, glm::normalize(forward + sx * right + sy * up)});
    }
  auto hits = embree->Intersect(rays, {});
  if (!hits.ok()) return std::nullopt;
  const int tiles_x = (p.width + p.tile_pixels - 1) / p.tile_pixels;
  const int tiles_y = (p.height + p.tile_pixels - 1) / p.tile_pixels;
  bc.tile_count = static_cast<uint32_t>(tiles_x * tiles_y);
  for (size_t i = 0; i < rays.size(); ++i) {
    const visq::raycast::Hit& hit = (*hits)[i];
    if (!hit.hit) continue;
    const uint32_t t = hit.triangle;
    const glm::dvec3 a = bc.scene.Vertex(t, 0), b = bc.scene.Vertex(t, 1), c = bc.scene.Vertex(t, 2);
    glm::dvec3 normal = glm::cross(b - a, c - a);
    if (glm::length(normal) == 0.0) continue;
    normal = glm::normalize(normal);
    if (glm::dot(normal, rays[i].direction) > 0) normal = -normal;  // the side the camera sees
    // The hit point from the barycentrics, on the triangle in double.
    const glm::dvec3 x = a + hit.u * (b - a) + hit.v * (c - a);
    bc.points.push_back({x, normal, t});
    bc.receivers.Extend(x);
    const int px = static_cast<int>(i % p.width), py = static_cast<int>(i / p.width);
    bc.tile_of_point.push_back(static_cast<uint32_t>((py / p.tile_pixels) * tiles_x + px / p.tile_pixels));
  }
  if (p.cells_per_side > 0 || p.shaft_triangles > 0) {
    std::vector<visq::exact::ReceiverCell> cells;
    if (p.shaft_triangles > 0) {
      auto index = visq::exact::SceneTriangleIndex::Build(std::make_shared<const visq::Scene>(bc.scene));
      if (!index.ok()) return std::nullopt;
      cells = visq::exact::GroupReceiversByShaft(bc.points, bc.light, **index, {p.shaft_triangles, 64, visq::exact::ShaftGrouping{}.split_gain, p.shaft_cap});
    } else {
      cells = visq::exact::GroupReceivers(bc.points, bc.scene.bounds, p.cells_per_side);
    }
    for (uint32_t c = 0; c < cells.size(); ++c) {
      for (uint32_t i : cells[c].points) bc.tile_of_point[i] = c;
      bc.tile_boxes.push_back(cells[c].box);
    }
    bc.tile_count = static_cast<uint32_t>(cells.size());
  }
  return bc;
}

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Embree with k x k shadow rays per point at the centres of an even k x k
// grid over the light (no jitter), for growing k, against the exact
// answers: the smallest k whose RMS error in the visible fraction reaches
// each target, its CPU time (the BVH build included, as the exact side
// includes its index and trees), and the exact method's cold CPU time over
// it. Ratios below 1: the exact method is faster at that error.
void ErrorTable(const BenchCase& bc, const visq::raycast::EmbreeScene& embree,
                const std::vector<visq::exact::PointVisibility>& exact, double cpu_exact_cold, double cpu_embree_build,
                int threads) {
  const double targets[3] = {0.01, 0.005, 0.002};
  int reached_k[3] = {0, 0, 0};
  double reached_cpu[3] = {0, 0, 0}, reached_rms[3] = {0, 0, 0};
  const auto& lv = bc.light.vertices;
  const glm::dvec3 e1 = lv[1] - lv[0], e2 = lv[3] - lv[0];
  const glm::dvec3 light_normal = glm::normalize(glm::cross(e1, e2));
  const size_t n = bc.points.size();
  std::printf("\nEmbree, k x k even grid per point, against the exact answers (%zu points, %d threads):\n", n,
              threads);
  std::printf("%6s %8s %10s %10s %14s\n", "k", "rays", "RMS", "max err", "CPU s (+BVH)");
  visq::raycast::TraceOptions trace;
  trace.threads = threads;
  for (const int k : {2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 18, 20, 23, 26, 29, 32, 36, 40, 45, 51, 57, 64}) {
    const size_t rays = static_cast<size_t>(k) * k;
    const double cpu0 = ProcessCpuSeconds();
    double sq = 0.0, worst = 0.0;
    constexpr size_t kBlock = 4096;  // points per trace, so the flags stay small
    for (size_t begin = 0; begin < n; begin += kBlock) {
      const size_t end = std::min(n, begin + kBlock);
      auto occluded = embree.Occluded((end - begin) * rays, [&](size_t s) {
        const auto& q = bc.points[begin + s / rays];
        const size_t r = s % rays;
        const double u = (static_cast<double>(r % k) + 0.5) / k, v = (static_cast<double>(r / k) + 0.5) / k;
        return visq::raycast::Segment{q.position, lv[0] + u * e1 + v * e2,
                                      q.receiver_triangle.value_or(visq::raycast::kNoTriangle)};
      }, trace);
      if (!occluded.ok()) {
        std::fprintf(stderr, "occluded: %s\n", occluded.status().ToString().c_str());
        return;
      }
      for (size_t i = begin; i < end; ++i) {
        const auto& q = bc.points[i];
        size_t visible = 0;
        for (size_t r = 0; r < rays; ++r) {
          if ((*occluded)[(i - begin) * rays + r]) continue;
          const double u = (static_cast<double>(r % k) + 0.5) / k, v = (static_cast<double>(r / k) + 0.5) / k;
          const glm::dvec3 w = lv[0] + u * e1 + v * e2 - q.position;
          if ((q.normal && glm::dot(*q.normal, w) <= 0.0) || glm::dot(light_normal, w) >= 0.0) continue;
          ++visible;
        }
        const double err = static_cast<double>(visible) / static_cast<double>(rays) - exact[i].visible_area_fraction;
        sq += err * err;
        worst = std::max(worst, std::abs(err));
      }
    }
    const double cpu = ProcessCpuSeconds() - cpu0 + cpu_embree_build;
    const double rms = std::sqrt(sq / static_cast<double>(n));
    std::printf("%6d %8zu %10.5f %10.4f %14.3f\n", k, rays, rms, worst, cpu);
    for (int t = 0; t < 3; ++t) {
      if (reached_k[t] == 0 && rms <= targets[t]) {
        reached_k[t] = k;
        reached_cpu[t] = cpu;
        reached_rms[t] = rms;
      }
    }
    if (reached_k[2] != 0) break;
  }
  std::printf("\ntime to error (%s): exact cold CPU %.3f s (index, trees, queries)\n", bc.name.c_str(),
              cpu_exact_cold);
  std::printf("%10s %10s %12s %16s\n", "RMS", "Embree k^2", "Embree CPU s", "exact / Embree");
  for (int t = 0; t < 3; ++t) {
    if (reached_k[t] == 0) {
      std::printf("%10.3f %10s %12s %16s\n", targets[t], "> 4096", "-", "< (not reached)");
    } else {
      std::printf("%10.3f %10d %12.3f %16.2f\n", targets[t], reached_k[t] * reached_k[t], reached_cpu[t],
                  cpu_exact_cold / reached_cpu[t]);
    }
  }
  (void)reached_rms;
}

int Run(const BenchCase& bc, const Params& p) {
  const int threads = p.threads > 0 ? p.threads : static_cast<int>(std::thread::hardware_concurrency());
  std::printf("scene %s: %zu triangles, %zu points, %d threads, %d rays/point, %u receiver %s\n",
              bc.name.c_str(), bc.scene.TriangleCount(), bc.points.size(), threads, p.rays,
              bc.tile_of_point.empty() ? static_cast<unsigned>(p.tiles * p.tiles) : bc.tile_count,
              bc.tile_boxes.empty() ? "tiles" : "cells");
  if (p.shaft_triangles > 0) {
    std::printf("receiver groups: the points' box, halved while its shaft meets more than %zu triangles\n",
                p.shaft_triangles);
  } else if (!bc.tile_boxes.empty()) {
    const glm::dvec3 e = bc.scene.bounds.Extent();
    std::printf("receiver cells: cubes of %.3g (the scene's largest extent / %d)\n",
                std::max({e.x, e.y, e.z}) / p.cells_per_side, p.cells_per_side);
  }

  // Exact: per tile, build a tree and query its points (first pass, which
  // grows it), then query again (second pass, reusing it). Tiles run in
  // parallel, each single-threaded.
  const int tiles = std::max(1, p.tiles);
  std::vector<std::vector<size_t>> tile_points(bc.tile_of_point.empty() ? tiles * tiles : bc.tile_count);
  const glm::dvec3 ext = bc.receivers.Extent();
  for (size_t i = 0; i < bc.points.size(); ++i) {
    if (!bc.tile_of_point.empty()) {
      tile_points[bc.tile_of_point[i]].push_back(i);
      continue;
    }
    const glm::dvec3 r = (bc.points[i].position - bc.receivers.min) / glm::max(ext, glm::dvec3(1e-300));
    const int tx = std::clamp(static_cast<int>(r.x * tiles), 0, tiles - 1);
    const int ty = std::clamp(static_cast<int>(r.y * tiles), 0, tiles - 1);
    tile_points[ty * tiles + tx].push_back(i);
  }
  std::vector<std::unique_ptr<visq::exact::LightVisibilityTree>> trees(tile_points.size());
  std::vector<visq::exact::PointVisibility> exact(bc.points.size()), warm(bc.points.size());
  std::atomic<bool> failed{false};
  auto for_tiles = [&](const auto& body) {
    std::atomic<size_t> next{0};
    auto work = [&]() {
      for (size_t t = next.fetch_add(1); t < tile_points.size(); t = next.fetch_add(1)) body(t);
    };
    std::vector<std::thread> pool;
    for (int w = 1; w < threads; ++w) pool.emplace_back(work);
    work();
    for (auto& th : pool) th.join();
  };
  auto shared_scene = std::make_shared<const visq::Scene>(bc.scene);
  const double cpu_exact_start = ProcessCpuSeconds();
  auto t0 = std::chrono::steady_clock::now();
  // The scene's triangle index, once (a server keeps it with the scene).
  auto index = visq::exact::SceneTriangleIndex::Build(shared_scene);
  if (!index.ok()) {
    std::fprintf(stderr, "index: %s\n", index.status().ToString().c_str());
    return 1;
  }
  const double t_index = Seconds(t0);
  t0 = std::chrono::steady_clock::now();
  std::atomic<int64_t> create_ns{0};
  // Each query is timed by its answer: wholly hidden, wholly visible,
  // penumbra (the classes cost very differently). The warm pass is mostly
  // the store of answers, so the first pass is where they are told apart.
  const auto AnswerClass = [](const visq::exact::PointVisibility& v) {
    return v.visible_area_fraction == 0.0 ? 0 : v.visible_area_fraction == 1.0 ? 1 : 2;
  };
  std::atomic<int64_t> first_class_ns[3] = {0, 0, 0}, first_class_count[3] = {0, 0, 0};
  for_tiles([&](size_t t) {
    if (tile_points[t].empty()) return;
    const auto c0 = std::chrono::steady_clock::now();
    Bounds tb;
    for (size_t i : tile_points[t]) tb.Extend(bc.points[i].position);
    if (!bc.tile_boxes.empty()) tb = bc.tile_boxes[t];
    visq::exact::TreeOptions options;
    options.receiver_bounds = tb;
    options.max_bytes = static_cast<size_t>(p.tree_max_mb * (1 << 20));
    auto tree = visq::exact::LightVisibilityTree::Create(bc.light, bc.scene, options, index->get());
    create_ns += std::chrono::duration_cast<std::chrono::nanoseconds>(
                     std::chrono::steady_clock::now() - c0).count();
    if (!tree.ok()) {
      std::fprintf(stderr, "tree: %s\n", tree.status().ToString().c_str());
      failed = true;
      return;
    }
    trees[t] = std::move(*tree);
    for (size_t i : tile_points[t]) {
      const auto q0 = std::chrono::steady_clock::now();
      auto r = trees[t]->Query(bc.points[i]);
      if (!r.ok()) {
        std::fprintf(stderr, "query: %s\n", r.status().ToString().c_str());
        failed = true;
        return;
      }
      exact[i] = std::move(*r);
      const int c = AnswerClass(exact[i]);
      first_class_ns[c] += std::chrono::duration_cast<std::chrono::nanoseconds>(
                               std::chrono::steady_clock::now() - q0).count();
      first_class_count[c] += 1;
    }
  });
  const double t_cold_total = Seconds(t0);
  const double cpu_exact_cold = ProcessCpuSeconds() - cpu_exact_start;
  if (failed) return 1;
  const double t_create = t_index + 1e-9 * static_cast<double>(create_ns.load()) / threads;  // wall share
  const double t_cold = t_cold_total - t_create;
  visq::exact::TreeStats stats, stats_cold;
  for (const auto& tree : trees) {
    if (!tree) continue;
    const auto st = tree->Stats();
    stats_cold.hits += st.hits;
    stats_cold.queries += st.queries;
  }
  std::atomic<int64_t> class_ns[3] = {0, 0, 0}, class_count[3] = {0, 0, 0};
  t0 = std::chrono::steady_clock::now();
  for_tiles([&](size_t t) {
    for (size_t i : tile_points[t]) {
      const auto q0 = std::chrono::steady_clock::now();
      warm[i] = *trees[t]->Query(bc.points[i]);
      const int c = AnswerClass(warm[i]);
      class_ns[c] += std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - q0).count();
      class_count[c] += 1;
    }
  });
  const double t_warm = Seconds(t0);
  size_t max_tree_bytes = 0;
  visq::exact::TreeStats largest;
  for (const auto& tree : trees) {
    if (!tree) continue;
    const auto st = tree->Stats();
    stats += st;
    if (st.memory_bytes > max_tree_bytes) largest = st;
    max_tree_bytes = std::max(max_tree_bytes, st.memory_bytes);
  }

  // Embree: build, then p.rays stratified (jittered) shadow rays per point.
  const double cpu_embree_start = ProcessCpuSeconds();
  t0 = std::chrono::steady_clock::now();
  auto embree = visq::raycast::EmbreeScene::Create(bc.scene);
  if (!embree.ok()) {
    std::fprintf(stderr, "embree: %s\n", embree.status().ToString().c_str());
    return 1;
  }
  const double t_embree_build = Seconds(t0);
  const double cpu_embree_build = ProcessCpuSeconds() - cpu_embree_start;
  const auto& lv = bc.light.vertices;  // a parallelogram light: lv[0] + s e1 + t e2
  const glm::dvec3 e1 = lv[1] - lv[0], e2 = lv[3] - lv[0];
  const glm::dvec3 light_normal = glm::normalize(glm::cross(e1, e2));  // emitting side
  const double light_area = glm::length(glm::cross(e1, e2));
  // One jittered sample in each of p.rays equal-area cells of the light (the
  // pattern the sampled methods use), so the estimate is unbiased for every
  // ray count.
  const std::vector<glm::dvec2> pattern =
      visq::sampling::StratifiedSamplePattern(p.rays, visq::sampling::SamplePattern::kJittered, p.seed + 99);
  t0 = std::chrono::steady_clock::now();
  std::vector<visq::raycast::Segment> segments;
  segments.reserve(bc.points.size() * p.rays);
  for (const auto& q : bc.points) {
    for (int k = 0; k < p.rays; ++k) {
      const double s = pattern[k].x, t = pattern[k].y;
      segments.push_back({q.position, lv[0] + s * e1 + t * e2,
                          q.receiver_triangle.value_or(visq::raycast::kNoTriangle)});
    }
  }
  const double t_sample = Seconds(t0);
  t0 = std::chrono::steady_clock::now();
  visq::raycast::TraceOptions trace;
  trace.threads = threads;
  auto occluded = embree->Occluded(segments, trace);
  const double t_trace = Seconds(t0);
  if (!occluded.ok()) {
    std::fprintf(stderr, "occluded: %s\n", occluded.status().ToString().c_str());
    return 1;
  }

  // Errors of the sampled estimates against the exact answers.
  double sq_frac = 0.0, max_frac = 0.0, sq_irr = 0.0, sum_irr = 0.0;
  size_t penumbra = 0;
  for (size_t i = 0; i < bc.points.size(); ++i) {
    const auto& q = bc.points[i];
    int visible = 0;
    double irr = 0.0;
    for (int k = 0; k < p.rays; ++k) {
      const auto& seg = segments[i * p.rays + k];
      if ((*occluded)[i * p.rays + k]) continue;
      const glm::dvec3 d = seg.q - seg.p;
      const double r2 = glm::dot(d, d);
      const glm::dvec3 w = d / std::sqrt(r2);
      // Like the exact method: light below the receiver's horizon, or seen
      // from behind its emitting side, is not visible.
      if ((q.normal && glm::dot(*q.normal, w) <= 0.0) || glm::dot(light_normal, w) >= 0.0) continue;
      ++visible;
      irr += std::max(0.0, glm::dot(*q.normal, w)) * std::max(0.0, -glm::dot(light_normal, w)) / r2;
    }
    irr *= bc.light.radiance * light_area / p.rays;
    const double f_exact = exact[i].visible_area_fraction;
    const double e = static_cast<double>(visible) / p.rays - f_exact;
    sq_frac += e * e;
    max_frac = std::max(max_frac, std::abs(e));
    sq_irr += (irr - exact[i].irradiance) * (irr - exact[i].irradiance);
    sum_irr += exact[i].irradiance;
    penumbra += f_exact > 0.0 && f_exact < 1.0;
  }
  const double n = static_cast<double>(bc.points.size());
  bool same = true;
  for (size_t i = 0; same && i < bc.points.size(); ++i) {
    same = warm[i].visible_area_fraction == exact[i].visible_area_fraction;
  }

  const double t_exact = t_create + t_cold, t_rt = t_embree_build + t_sample + t_trace;
  std::printf("\n%-34s %12s %12s\n", "", "exact visq", "embree");
  std::printf("%-34s %12.4f %12.4f\n", "build (s)", t_create, t_embree_build);
  std::printf("%-34s %12.4f %12.4f\n", "first pass: queries / rays (s)", t_cold, t_sample + t_trace);
  std::printf("%-34s %12.4f %12s\n", "second pass, warm tree (s)", t_warm, "-");
  std::printf("%-34s %12.2f %12.2f\n", "us per point (first pass)", 1e6 * t_cold / n,
              1e6 * (t_sample + t_trace) / n);
  std::printf("%-34s %12.2f %12s\n", "us per point (warm)", 1e6 * t_warm / n, "-");
  std::printf("%-34s %12.1f %12.1f\n", "memory, all trees (KiB)", stats.memory_bytes / 1024.0,
              embree->memory_bytes() / 1024.0);
  std::printf("%-34s %12.1f %12s\n", "memory, largest tree (KiB)", max_tree_bytes / 1024.0, "-");
  // A frame computed tile by tile needs only the trees of the tiles in
  // flight, one per thread.
  std::printf("%-34s %12.1f %12s\n", "memory, tile by tile (KiB, <=)", threads * max_tree_bytes / 1024.0, "-");
  std::printf("%-34s %12.3f %12s\n", "time ratio exact / embree (total)", t_exact / t_rt, "");
  std::printf("%-34s %12.3f %12s\n", "time ratio warm exact / rays", t_warm / (t_sample + t_trace), "");
  std::printf("\nexact trees: %zu nodes, %zu far + %zu near occluders, %llu refinements, %llu leaves resolved "
              "per query at the %.0f MB budget, hits %llu / %llu queries (first pass %llu / %llu); second pass "
              "identical: %s\n",
              stats.nodes, stats.far_occluders, stats.near_occluders,
              static_cast<unsigned long long>(stats.refinements),
              static_cast<unsigned long long>(stats.unrefined_leaf_visits), p.tree_max_mb,
              static_cast<unsigned long long>(stats.hits), static_cast<unsigned long long>(stats.queries),
              static_cast<unsigned long long>(stats_cold.hits),
              static_cast<unsigned long long>(stats_cold.queries), same ? "yes" : "NO");
  std::printf("penumbra points (0 < exact < 1): %zu of %zu\n", penumbra, bc.points.size());
  std::printf("queries answered before the tree: %llu wholly visible, %llu wholly hidden (%llu by the blockers of "
              "a point nearby), %llu subtracted directly; "
              "%llu near occluders subtracted inside a neighbour's quadrilateral\n",
              static_cast<unsigned long long>(stats.wholly_visible),
              static_cast<unsigned long long>(stats.wholly_hidden),
              static_cast<unsigned long long>(stats.hidden_by_remembered_blockers),
              static_cast<unsigned long long>(stats.subtracted_directly),
              static_cast<unsigned long long>(stats.merged_occluders));
  const char* class_names[3] = {"hidden (0)", "visible (1)", "penumbra"};
  for (int c = 0; c < 3; ++c) {
    std::printf("first pass, %-12s %8lld points, %8.2f us per point (one thread's time, tree growth included)\n",
                class_names[c], static_cast<long long>(first_class_count[c].load()),
                1e-3 * static_cast<double>(first_class_ns[c].load()) /
                    std::max<int64_t>(1, first_class_count[c].load()));
  }
  for (int c = 0; c < 3; ++c) {
    std::printf("warm pass, %-12s %8lld points, %8.2f us per point (one thread's time)\n", class_names[c],
                static_cast<long long>(class_count[c].load()),
                1e-3 * static_cast<double>(class_ns[c].load()) / std::max<int64_t>(1, class_count[c].load()));
  }
  std::printf("%d-ray error vs exact: visible fraction RMS %.4f, max %.4f; irradiance RMS %.4f "
              "(%.2f%% of mean %.4f)\n",
              p.rays, std::sqrt(sq_frac / n), max_frac, std::sqrt(sq_irr / n),
              100.0 * std::sqrt(sq_irr / n) / (sum_irr / n), sum_irr / n);
  std::printf("memory: trees %.1f MiB in all (largest %.1f MiB: %zu far + %zu near occluders, %zu nodes, "
              "%zu answers), process peak RSS %.0f MiB\n",
              stats.memory_bytes / 1048576.0, max_tree_bytes / 1048576.0, largest.far_occluders,
              largest.near_occluders, largest.nodes, largest.answers_kept, PeakRssMiB());
  size_t occluders = 0;
  for (const auto& tree : trees) {
    if (!tree) continue;
    const auto st = tree->Stats();
    occluders += st.far_occluders + st.near_occluders;
  }
  // Bytes per occluder: the trees' memory (their occluders, their nodes)
  // without their stores of answers, over their occluders.
  std::printf("memory per occluder: %.1f bytes over all trees (%zu occluders; answers %.1f MiB more), %.1f in the "
              "largest tree; exact cold CPU %.3f s\n",
              static_cast<double>(stats.memory_bytes - stats.answer_bytes) / std::max<size_t>(1, occluders), occluders,
              stats.answer_bytes / 1048576.0,
              static_cast<double>(largest.memory_bytes - largest.answer_bytes) /
                  std::max<size_t>(1, largest.far_occluders + largest.near_occluders),
              cpu_exact_cold);
  if (!p.answers_out.empty()) {
    if (FILE* f = std::fopen(p.answers_out.c_str(), "w")) {
      for (const auto& a : exact) {
        std::fprintf(f, "%016llx %016llx %016llx\n",
                     static_cast<unsigned long long>(std::bit_cast<uint64_t>(a.visible_area_fraction)),
                     static_cast<unsigned long long>(std::bit_cast<uint64_t>(a.visible_solid_angle_fraction)),
                     static_cast<unsigned long long>(std::bit_cast<uint64_t>(a.irradiance)));
      }
      std::fclose(f);
    } else {
      std::fprintf(stderr, "--answers-out: cannot write %s\n", p.answers_out.c_str());
      return 1;
    }
  }
  if (p.error_table) ErrorTable(bc, *embree, exact, cpu_exact_cold, cpu_embree_build, threads);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Params p;
  for (int i = 1; i < argc; ++i) {
    const char* a = argv[i];
    auto value = [&](const char* flag) -> const char* {
      const size_t n = std::strlen(flag);
      return std::strncmp(a, flag, n) == 0 && a[n] == '=' ? a + n + 1 : nullptr;
    };
    if (const char* v = value("--occluders")) p.occluders = std::atoi(v);
    else if (const char* v = value("--boxes")) p.boxes = std::atoi(v);
    else if (const char* v = value("--grid")) p.grid = std::atoi(v);
    else if (const char* v = value("--threads")) p.threads = std::atoi(v);
    else if (const char* v = value("--rays")) p.rays = std::atoi(v);
    else if (const char* v = value("--tiles")) p.tiles = std::atoi(v);
    else if (const char* v = value("--size")) p.size = std::atof(v);
    else if (const char* v = value("--seed")) p.seed = static_cast<uint32_t>(std::atoi(v));
    else if (const char* v = value("--gltf")) p.gltf = v;
    else if (const char* v = value("--light")) p.light = v;
    else if (const char* v = value("--eye")) std::sscanf(v, "%lf,%lf,%lf", &p.eye.x, &p.eye.y, &p.eye.z);
    else if (const char* v = value("--look-at")) std::sscanf(v, "%lf,%lf,%lf", &p.look_at.x, &p.look_at.y, &p.look_at.z);
    else if (const char* v = value("--width")) p.width = std::atoi(v);
    else if (const char* v = value("--height")) p.height = std::atoi(v);
    else if (const char* v = value("--tile-pixels")) p.tile_pixels = std::max(1, std::atoi(v));
    else if (const char* v = value("--tree-max-mb")) p.tree_max_mb = std::atof(v);
    else if (const char* v = value("--cells-per-side")) p.cells_per_side = std::atoi(v);
    else if (const char* v = value("--shaft-triangles")) p.shaft_triangles = static_cast<size_t>(std::atoll(v));
    else if (const char* v = value("--shaft-cap")) p.shaft_cap = std::atof(v);
    else if (const char* v = value("--error-table")) p.error_table = std::atoi(v) != 0;
    else if (const char* v = value("--answers-out")) p.answers_out = v;
    else {
      std::fprintf(stderr, "usage: %s [--occluders=N] [--boxes=N] [--grid=N] [--threads=N] "
                   "[--rays=N] [--tiles=N] [--size=S] [--seed=N]\n"
                   "       %s --gltf=FILE --light='x,y,z;...' --eye=x,y,z --look-at=x,y,z [--width=1280] "
                   "[--height=720] [--cells-per-side=32 | --cells-per-side=0 --tile-pixels=32] [--tree-max-mb=16] [--threads=N] [--rays=N] [--error-table=0] [--answers-out=FILE]\n", argv[0], argv[0]);
      return 2;
    }
  }
  if (!p.gltf.empty()) {
    const std::optional<BenchCase> bc = MakeFromGltf(p);
    return bc ? Run(*bc, p) : 1;
  }
  return Run(MakeProcedural(p), p);
}
