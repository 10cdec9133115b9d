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
// builds one; MakeView() takes the points a pinhole camera sees (one per
// pixel) in a glTF scene or in one generated here (--scene=grille: a room
// lit through a window with sash bars and a Venetian blind, MakeGrilleScene;
// --scene=foliage: the same room, its window open, lit through flowers on
// shelves and trees on the floor, MakeFoliageScene, from the shared scenes)
// and groups them as the server groups a batch: by cubes of 1/32 of the
// scene's size (exact::GroupReceivers), one tree each; --cells-per-side=0
// groups them by image tile instead:
//
//   visq_bench_exact --gltf=../shared/scenes/sponza_dabrovic/sponza.gltf
//     --light='-1,10,-0.5;1,10,-0.5;1,10,0.5;-1,10,0.5' --eye=-10,2,0
//     --look-at=10,3,0 [--width=1280 --height=720]
//     [--cells-per-side=32 | --cells-per-side=0 --tile-pixels=32]
//   visq_bench_exact --scene=grille --width=160 --height=90 --shaft-triangles=20000
//   visq_bench_exact --scene=foliage [--scenes=../shared/scenes] --width=160 --height=90 --shaft-triangles=20000
//
// The time-to-error table at the end sets the exact method's CPU time
// against Embree's with k x k rays per point, jittered (the baseline) and on
// the even grid, at the k reaching each RMS error.
#include <algorithm>
#include <bit>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
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
#include "scene/sample_scenes.h"
#include "raycast/embree_scene.h"
#include "sampling/visibility_sampling.h"
#include "window_room.h"

namespace {

using visq::Bounds;
using visq::Scene;
using visq::testing::MakeGrilleScene;
using visq::testing::MakeWindowRoom;
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
  // A glTF scene seen from a camera instead of the procedural case, or a
  // scene generated here ("grille": MakeGrilleScene).
  std::string gltf;
  std::string scene;
  // The shared scenes, where --scene=foliage takes its assets from.
  std::filesystem::path scenes = VISQ_SHARED_SCENES_DIR;
  std::string light;          // "x,y,z;x,y,z;x,y,z;x,y,z", a parallelogram, front counter-clockwise
  glm::dvec3 eye{0.0}, look_at{1.0, 0.0, 0.0};
  int width = 1280, height = 720;
  int tile_pixels = 32;       // image tiles of this many pixels a side, one tree each
  // Receiver cells per side of the scene (exact::GroupReceivers), one tree
  // each, as the server groups a batch; 0: image tiles instead.
  int cells_per_side = 32;
  double tree_max_mb = 16;    // each tree's memory budget (TreeOptions::max_bytes), as the server's default
  long direct_candidates = -1;  // >= 0: TreeOptions::direct_candidates (else its default)
  bool keep_answers = true;     // TreeOptions::keep_answers (0: the warm pass descends the grown tree)
  bool accelerations = true;    // 0: TreeOptions::PapersAlgorithmAlone (--direct-candidates still applies)
  double shadow_tolerance = 0.0;  // TreeOptions::shadow_tolerance (0: every answer exact)
  // > 0: group the points as the server does without a grid
  // (exact::GroupReceiversByShaft with this many triangles per shaft),
  // instead of cells or tiles.
  size_t shaft_triangles = 0;
  double shaft_cap = visq::exact::ShaftGrouping{}.hard_cap;
  // The time-to-error table: Embree with k x k rays per point, jittered and
  // on the even grid, k growing until its RMS error reaches the last target
  // (or k = 64).
  bool error_table = true;
  // Where to write every point's exact answer, as the bits of its three
  // doubles (one line a point): two builds' files compare bit for bit.
  std::string answers_out;
  // --scene=slivers: how many, and how far the third vertex is off the long edge.
  int slivers = 3000;
  double sliver_width = 1e-9;
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

// The --light flag's parallelogram, "x,y,z;x,y,z;x,y,z;x,y,z".
bool ParseLight(const std::string& text, AreaLight& light) {
  light.vertices.clear();
  for (size_t start = 0; start <= text.size();) {
    const size_t end = std::min(text.find(';', start), text.size());
    glm::dvec3 v;
    if (std::sscanf(text.substr(start, end - start).c_str(), "%lf,%lf,%lf", &v.x, &v.y, &v.z) != 3) {
      std::fprintf(stderr, "--light: '%s' is not x,y,z;x,y,z;...\n", text.c_str());
      return false;
    }
    light.vertices.push_back(v);
    start = end + 1;
  }
  if (light.vertices.size() != 4) {
    std::fprintf(stderr, "--light: a parallelogram needs 4 vertices\n");
    return false;
  }
  light.radiance = 10.0;
  return true;
}

// Slivers (issue 44, section 3: "3,000 sliver triangles that hide nothing
// cost 3.4 s a point"): the room with its window open, and `count` needles
// in the light's way just inside it (x in [0.2, 1], y in [0.9, 2.1], z in
// [-1, 1]), each 0.2 m long, at random directions, its third vertex
// `width` off the middle of its long edge: at 1e-9 m, next to nothing of the
// light hides behind them, as with a mesh's leftover slivers; at 1e-3 they
// are wires.
Scene MakeSliverScene(int count, double width, uint32_t seed) {
  Scene s = MakeWindowRoom();
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  auto unit = [&] {
    const double z = 2.0 * u(rng) - 1.0, a = 2.0 * M_PI * u(rng), r = std::sqrt(1.0 - z * z);
    return glm::dvec3(r * std::cos(a), r * std::sin(a), z);
  };
  const uint32_t node = static_cast<uint32_t>(s.nodes.size());
  const uint32_t first = static_cast<uint32_t>(s.triangles.size());
  for (int i = 0; i < count; ++i) {
    const glm::dvec3 centre(0.2 + 0.8 * u(rng), 0.9 + 1.2 * u(rng), -1.0 + 2.0 * u(rng));
    const glm::dvec3 along = unit();
    const glm::dvec3 off = glm::normalize(glm::cross(along, unit()));
    const uint32_t base = static_cast<uint32_t>(s.positions.size());
    s.positions.push_back(centre - 0.1 * along);
    s.positions.push_back(centre + 0.1 * along);
    s.positions.push_back(centre + width * off);
    s.triangles.push_back(glm::uvec3(base, base + 1, base + 2));
    s.triangle_material.push_back(0);
    s.triangle_node.push_back(node);
  }
  s.nodes.push_back(visq::SceneNode{"slivers", static_cast<int>(node), -1, glm::dmat4(1.0), first,
                                    static_cast<uint32_t>(s.triangles.size()) - first});
  visq::UpdateBounds(s);
  return s;
}

// Appends the triangles of `asset`'s nodes whose names start with `prefix`
// (all: ""), moved by `world`, as one new node `name`: a copy placed by hand,
// flattened like every triangle of a loaded scene.
void AddCopy(Scene& s, const std::string& name, const Scene& asset, const std::string& prefix,
             const glm::dmat4& world) {
  const uint32_t node = static_cast<uint32_t>(s.nodes.size());
  const uint32_t first = static_cast<uint32_t>(s.triangles.size());
  for (size_t t = 0; t < asset.TriangleCount(); ++t) {
    if (asset.nodes[asset.NodeOf(t)].name.rfind(prefix, 0) != 0) continue;
    const uint32_t base = static_cast<uint32_t>(s.positions.size());
    for (int c = 0; c < 3; ++c) s.positions.push_back(visq::PlacePoint(world, asset.Vertex(t, c)));
    s.triangles.push_back(glm::uvec3(base, base + 1, base + 2));
    s.triangle_material.push_back(0);
    s.triangle_node.push_back(node);
  }
  s.nodes.push_back(visq::SceneNode{name, static_cast<int>(node), -1, world, first,
                                    static_cast<uint32_t>(s.triangles.size()) - first});
}

// Translation, rotation about +y and uniform scale.
glm::dmat4 Place(const glm::dvec3& at, double degrees_about_y, double scale) {
  const double a = degrees_about_y * M_PI / 180.0, c = std::cos(a), sn = std::sin(a);
  glm::dmat4 m(1.0);
  m[0] = glm::dvec4(scale * c, 0, -scale * sn, 0);
  m[1] = glm::dvec4(0, scale, 0, 0);
  m[2] = glm::dvec4(scale * sn, 0, scale * c, 0);
  m[3] = glm::dvec4(at, 1.0);
  return m;
}

// The foliage (issue 44, section 3): the grille's closed 5 x 2.8 x 5 room
// (Y up, floor at y = 0, x in [0, 5], z in [-2.5, 2.5]) with the same
// 2.1 x 1.4 window in its x = 0 wall, but open, and lit by the same
// 1.6 x 1.6 light 1 m outside. The light reaches the floor through
// foliage, as in a plant-filled room: the glass vase's flowers
// (GlassVaseFlowers, the flowers alone, twice their size: 0.33 m tall)
// stand in rows on the window sill and on a shelf across the opening at
// 1.45 m, and Kenney's two trees (tree_detailed, tree_palmDetailedTall,
// 0.7-1.1x) stand on the floor in a 3 x 4 grid where the window lights it.
// Every lit floor point sees the light through dozens of petals, leaves and
// fronds: thin, many, at every distance, with no regular pattern for a
// ray caster's strata to alias against. Copies are flattened (the bench's
// exact side works on the flattened triangles, as the server's does). The
// assets come from the shared scenes; nullopt (and a message) without them.
std::optional<Scene> MakeFoliageScene(const std::filesystem::path& scenes) {
  const std::filesystem::path files[3] = {scenes / "foliage_glass_vase_flowers/GlassVaseFlowers.gltf",
                                          scenes / "tree_kenney/tree_detailed.glb",
                                          scenes / "tree_kenney/tree_palmDetailedTall.glb"};
  std::vector<Scene> assets;
  for (const auto& file : files) {
    auto asset = visq::LoadGltfFile(file);
    if (!asset.ok()) {
      std::fprintf(stderr, "foliage: %s: %s\n", file.c_str(), asset.status().ToString().c_str());
      return std::nullopt;
    }
    assets.push_back(std::move(*asset));
  }
  const Scene &flowers = assets[0], &tree = assets[1], &palm = assets[2];
  Scene s = MakeWindowRoom();
  // The sill (inside the wall's 0.25 m) and a shelf board across the opening.
  visq::AddBox(s, "sill", {0.0, 0.78, -1.05}, {0.25, 0.8, 1.05}, 0);
  visq::AddBox(s, "shelf", {0.0, 1.43, -1.05}, {0.25, 1.45, 1.05}, 0);
  // Flowers: 9 on the sill and 9 on the shelf, each turned its own way.
  // The asset's flower nodes stand at x 0.0016 and 0.1216: the first alone,
  // moved to the origin, is one bunch.
  int n = 0;
  for (const double y : {0.8, 1.45})
    for (int i = 0; i < 9; ++i, ++n) {
      const double z = -0.92 + 1.84 * i / 8.0;
      glm::dmat4 to_origin(1.0);
      to_origin[3] = glm::dvec4(-0.0016, -0.038, 0.0022, 1.0);
      AddCopy(s, "flowers", flowers, "Flowers1", Place({0.13, y, z}, 37.0 * n, 2.0) * to_origin);
    }
  // Trees on the floor where the window lights it, alternating the kinds.
  n = 0;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 4; ++j, ++n) {
      const glm::dvec3 at(0.9 + 0.75 * i, 0.05, -1.35 + 0.9 * j + (i % 2 ? 0.3 : 0.0));
      AddCopy(s, n % 2 ? "palm" : "tree", n % 2 ? palm : tree, "", Place(at, 53.0 * n, 0.7 + 0.4 * ((n * 7) % 5) / 4.0));
    }
  visq::UpdateBounds(s);
  return s;
}

// A scene to look at: a glTF file, or --scene=grille or foliage built here.
std::optional<BenchCase> LoadCase(const Params& p) {
  BenchCase bc;
  if (p.scene == "grille") {
    bc.name = "grille";
    bc.scene = MakeGrilleScene();
  } else if (p.scene == "slivers") {
    bc.name = "slivers";
    bc.scene = MakeSliverScene(p.slivers, p.sliver_width, p.seed);
  } else if (p.scene == "foliage") {
    bc.name = "foliage";
    std::optional<Scene> scene = MakeFoliageScene(p.scenes);
    if (!scene) return std::nullopt;
    bc.scene = std::move(*scene);
    std::printf("foliage: %zu triangles\n", bc.scene.TriangleCount());
  } else {
    auto scene = visq::LoadGltfFile(p.gltf);
    if (!scene.ok()) {
      std::fprintf(stderr, "%s: %s\n", p.gltf.c_str(), scene.status().ToString().c_str());
      return std::nullopt;
    }
    bc.name = std::filesystem::path(p.gltf).stem().string();
    bc.scene = std::move(*scene);
  }
  if (!ParseLight(p.light, bc.light)) return std::nullopt;
  return bc;
}

// Points on the visible surfaces of the case's scene, one per pixel of a
// pinhole camera (60 degree vertical field), found by Embree primary rays;
// each pixel's tree is its image tile's, as the paper groups receivers.
std::optional<BenchCase> MakeView(BenchCase bc, const Params& p) {
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

// SplitMix64's finalizer: a well-mixed 64-bit hash, so that a sample's
// jitter is a pure function of (seed, point, k, ray) and the tracing threads
// can make it again in any order.
uint64_t Mix64(uint64_t z) {
  z += 0x9e3779b97f4a7c15ULL;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

// Where ray r of k x k falls on the light, in (s, t) over its edges: the
// centre of cell (r % k, r / k) for the even grid; for the jittered pattern
// one uniform sample in that cell, from a hash seeded per point (so a run
// repeats, and points do not share one pattern whose errors would line up).
glm::dvec2 LightSample(bool jittered, uint64_t seed, size_t point, int k, size_t r) {
  double ju = 0.5, jv = 0.5;
  if (jittered) {
    const uint64_t h = Mix64(Mix64(seed ^ Mix64(point)) ^ (static_cast<uint64_t>(k) << 32 | r));
    ju = static_cast<double>(h >> 40) * 0x1.0p-24;               // top 24 bits
    jv = static_cast<double>((h >> 8) & 0xffffff) * 0x1.0p-24;  // the next 24
  }
  return {(static_cast<double>(r % k) + ju) / k, (static_cast<double>(r / k) + jv) / k};
}

// The smallest k x k whose RMS error reached each target, and at what CPU time.
struct ErrorSweep {
  static constexpr double kTargets[3] = {0.01, 0.005, 0.002};
  int reached_k[3] = {0, 0, 0};
  double reached_cpu[3] = {0, 0, 0};
};

// Embree with k x k shadow rays per point (jittered or on the even grid's
// cell centres), for growing k, against the exact answers: the smallest k
// whose RMS error in the visible fraction reaches each target, and its CPU
// time (the BVH build included, as the exact side includes its index and
// trees). Both patterns run on the same `threads` as the exact method.
ErrorSweep SweepErrors(const BenchCase& bc, const visq::raycast::EmbreeScene& embree,
                       const std::vector<visq::exact::PointVisibility>& exact, double cpu_embree_build, int threads,
                       bool jittered, uint64_t seed) {
  ErrorSweep sweep;
  const auto& lv = bc.light.vertices;
  const glm::dvec3 e1 = lv[1] - lv[0], e2 = lv[3] - lv[0];
  const glm::dvec3 light_normal = glm::normalize(glm::cross(e1, e2));
  const size_t n = bc.points.size();
  std::printf("\nEmbree, k x k %s per point, against the exact answers (%zu points, %d threads):\n",
              jittered ? "jittered (one uniform sample per cell, seeded per point)" : "even grid (cell centres)", n,
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
        const size_t i = begin + s / rays;
        const auto& q = bc.points[i];
        const glm::dvec2 uv = LightSample(jittered, seed, i, k, s % rays);
        return visq::raycast::Segment{q.position, lv[0] + uv.x * e1 + uv.y * e2,
                                      q.receiver_triangle.value_or(visq::raycast::kNoTriangle)};
      }, trace);
      if (!occluded.ok()) {
        std::fprintf(stderr, "occluded: %s\n", occluded.status().ToString().c_str());
        return sweep;
      }
      for (size_t i = begin; i < end; ++i) {
        const auto& q = bc.points[i];
        size_t visible = 0;
        for (size_t r = 0; r < rays; ++r) {
          if ((*occluded)[(i - begin) * rays + r]) continue;
          const glm::dvec2 uv = LightSample(jittered, seed, i, k, r);
          const glm::dvec3 w = lv[0] + uv.x * e1 + uv.y * e2 - q.position;
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
      if (sweep.reached_k[t] == 0 && rms <= ErrorSweep::kTargets[t]) {
        sweep.reached_k[t] = k;
        sweep.reached_cpu[t] = cpu;
      }
    }
    if (sweep.reached_k[2] != 0) break;
  }
  return sweep;
}

// The time-to-error table: for each target RMS error, the exact method's
// cold CPU time over Embree's at the smallest k x k reaching it, jittered
// first (the honest baseline: what a ray caster would use), the even grid
// beside it (what this table compared against before stop 44). Ratios below
// 1: the exact method is faster at that error.
void ErrorTable(const BenchCase& bc, const visq::raycast::EmbreeScene& embree,
                const std::vector<visq::exact::PointVisibility>& exact, double cpu_exact_cold, double cpu_embree_build,
                int threads, uint64_t seed) {
  const ErrorSweep jittered = SweepErrors(bc, embree, exact, cpu_embree_build, threads, true, seed);
  const ErrorSweep even = SweepErrors(bc, embree, exact, cpu_embree_build, threads, false, seed);
  std::printf("\ntime to error (%s): exact cold CPU %.3f s (index, trees, queries)\n", bc.name.c_str(),
              cpu_exact_cold);
  std::printf("%8s | %-40s | %-40s\n", "", "Embree jittered", "Embree even grid");
  std::printf("%8s | %10s %12s %16s | %10s %12s %16s\n", "RMS", "k^2", "CPU s", "exact / Embree", "k^2", "CPU s",
              "exact / Embree");
  for (int t = 0; t < 3; ++t) {
    std::printf("%8.3f", ErrorSweep::kTargets[t]);
    for (const ErrorSweep* s : {&jittered, &even}) {
      if (s->reached_k[t] == 0) {
        std::printf(" | %10s %12s %16s", "> 4096", "-", "< (not reached)");
      } else {
        std::printf(" | %10d %12.3f %16.2f", s->reached_k[t] * s->reached_k[t], s->reached_cpu[t],
                    cpu_exact_cold / s->reached_cpu[t]);
      }
    }
    std::printf("\n");
  }
}

// What a penumbra point's light looks like from the point, measured from
// outside the exact method (which keeps no per-query counts): how many
// scene triangles are the first thing seen along k x k even rays towards
// the light (k = 16, and 64 on fewer points) (the blockers whose outlines cut the visible part, so what its
// fragments and splits grow with), from how many scene nodes (slats, bars),
// and how many triangles the scene index finds in the box of the point and
// the light (what the candidate gather starts from, before its culls).
// Printed per scene, so a scene that is hard for the exact method shows
// where: many blockers per point, not many triangles.
void BlockersSeen(const BenchCase& bc, const visq::raycast::EmbreeScene& embree,
                  const visq::exact::SceneTriangleIndex& index, const std::vector<size_t>& penumbra, int side,
                  size_t max_points, int threads) {
  const size_t stride = std::max<size_t>(1, penumbra.size() / max_points);
  const auto& lv = bc.light.vertices;
  const glm::dvec3 e1 = lv[1] - lv[0], e2 = lv[3] - lv[0];
  Bounds light_box;
  for (const auto& v : lv) light_box.Extend(v);
  std::vector<visq::raycast::Ray> rays;
  std::vector<size_t> chosen;
  for (size_t j = 0; j < penumbra.size(); j += stride) {
    const auto& q = bc.points[penumbra[j]];
    chosen.push_back(penumbra[j]);
    for (int r = 0; r < side * side; ++r) {
      const glm::dvec3 y = lv[0] + ((r % side + 0.5) / side) * e1 + ((r / side + 0.5) / side) * e2;
      // Up to the light and no further (tmax in units of the direction).
      rays.push_back({q.position, y - q.position, 1.0 - 1e-9,
                      q.receiver_triangle.value_or(visq::raycast::kNoTriangle)});
    }
  }
  visq::raycast::TraceOptions trace;
  trace.threads = threads;
  auto hits = embree.Intersect(rays, trace);
  if (!hits.ok()) return;
  double sum_tris = 0, sum_nodes = 0, sum_box = 0;
  size_t max_tris = 0, max_box = 0;
  for (size_t c = 0; c < chosen.size(); ++c) {
    std::vector<uint32_t> tris, nodes;
    for (int r = 0; r < side * side; ++r) {
      const auto& h = (*hits)[c * side * side + r];
      if (!h.hit) continue;
      tris.push_back(h.triangle);
      nodes.push_back(bc.scene.NodeOf(h.triangle));
    }
    for (auto* v : {&tris, &nodes}) {
      std::sort(v->begin(), v->end());
      v->erase(std::unique(v->begin(), v->end()), v->end());
    }
    Bounds box = light_box;
    box.Extend(bc.points[chosen[c]].position);
    const size_t in_box = index.CountInBox(box.min, box.max, std::numeric_limits<size_t>::max());
    sum_tris += static_cast<double>(tris.size());
    sum_nodes += static_cast<double>(nodes.size());
    sum_box += static_cast<double>(in_box);
    max_tris = std::max(max_tris, tris.size());
    max_box = std::max(max_box, in_box);
  }
  const double m = static_cast<double>(chosen.size());
  std::printf("penumbra geometry (%zu of %zu penumbra points, %d x %d rays each): blockers seen %.1f triangles "
              "(max %zu) from %.1f nodes; triangles in the box of the point and the light %.0f (max %zu)\n",
              chosen.size(), penumbra.size(), side, side, sum_tris / m, max_tris, sum_nodes / m, sum_box / m,
              max_box);
}

void PenumbraGeometry(const BenchCase& bc, const visq::raycast::EmbreeScene& embree,
                      const visq::exact::SceneTriangleIndex& index,
                      const std::vector<visq::exact::PointVisibility>& exact, int threads) {
  std::vector<size_t> penumbra;
  for (size_t i = 0; i < bc.points.size(); ++i) {
    if (exact[i].visible_area_fraction > 0.0 && exact[i].visible_area_fraction < 1.0) penumbra.push_back(i);
  }
  if (penumbra.empty()) return;
  // 16 x 16 rays at most 2,000 of them, evenly spread, so this costs well
  // under a second; then 64 x 64 at at most 100 (first hits undercount what
  // a point sees of a dense, deep layer: each ray reports only one).
  for (const int side : {16, 64}) {
    BlockersSeen(bc, embree, index, penumbra, side, side == 16 ? 2000 : 100, threads);
  }
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
    if (!p.accelerations) options = visq::exact::TreeOptions::PapersAlgorithmAlone();
    options.receiver_bounds = tb;
    options.max_bytes = static_cast<size_t>(p.tree_max_mb * (1 << 20));
    if (p.direct_candidates >= 0) options.direct_candidates = static_cast<size_t>(p.direct_candidates);
    if (p.accelerations) options.keep_answers = p.keep_answers;
    options.shadow_tolerance = p.shadow_tolerance;
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
  {
    size_t left_out = 0;
    double largest = 0.0;
    for (const auto& e : exact) {
      left_out += e.visible_area_fraction_error > 0.0 ? 1 : 0;
      largest = std::max(largest, e.visible_area_fraction_error);
    }
    std::printf("shadow tolerance %g: %zu points left occluders out, largest stated error %.3g\n",
                p.shadow_tolerance, left_out, largest);
  }
  std::printf("queries answered before the tree: %llu wholly visible, %llu wholly hidden (%llu by the blockers of "
              "a point nearby), %llu subtracted directly; "
              "%llu occluders subtracted inside a neighbour's quadrilateral; "
              "%llu subtractions kept their fragments in a grid\n",
              static_cast<unsigned long long>(stats.wholly_visible),
              static_cast<unsigned long long>(stats.wholly_hidden),
              static_cast<unsigned long long>(stats.hidden_by_remembered_blockers),
              static_cast<unsigned long long>(stats.subtracted_directly),
              static_cast<unsigned long long>(stats.merged_occluders),
              static_cast<unsigned long long>(stats.fragment_grids));
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
  PenumbraGeometry(bc, *embree, **index, exact, threads);
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
  if (p.error_table) ErrorTable(bc, *embree, exact, cpu_exact_cold, cpu_embree_build, threads, p.seed);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Params p;
  bool eye_given = false, look_at_given = false;
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
    else if (const char* v = value("--scene")) p.scene = v;
    else if (const char* v = value("--scenes")) p.scenes = v;
    else if (const char* v = value("--light")) p.light = v;
    else if (const char* v = value("--eye")) eye_given = std::sscanf(v, "%lf,%lf,%lf", &p.eye.x, &p.eye.y, &p.eye.z) == 3;
    else if (const char* v = value("--look-at")) {
      look_at_given = std::sscanf(v, "%lf,%lf,%lf", &p.look_at.x, &p.look_at.y, &p.look_at.z) == 3;
    }
    else if (const char* v = value("--width")) p.width = std::atoi(v);
    else if (const char* v = value("--height")) p.height = std::atoi(v);
    else if (const char* v = value("--tile-pixels")) p.tile_pixels = std::max(1, std::atoi(v));
    else if (const char* v = value("--tree-max-mb")) p.tree_max_mb = std::atof(v);
    else if (const char* v = value("--direct-candidates")) p.direct_candidates = std::atol(v);
    else if (const char* v = value("--keep-answers")) p.keep_answers = std::atoi(v) != 0;
    else if (const char* v = value("--accelerations")) p.accelerations = std::atoi(v) != 0;
    else if (const char* v = value("--shadow-tolerance")) p.shadow_tolerance = std::atof(v);
    else if (const char* v = value("--cells-per-side")) p.cells_per_side = std::atoi(v);
    else if (const char* v = value("--shaft-triangles")) p.shaft_triangles = static_cast<size_t>(std::atoll(v));
    else if (const char* v = value("--shaft-cap")) p.shaft_cap = std::atof(v);
    else if (const char* v = value("--error-table")) p.error_table = std::atoi(v) != 0;
    else if (const char* v = value("--answers-out")) p.answers_out = v;
    else if (const char* v = value("--slivers")) p.slivers = std::atoi(v);
    else if (const char* v = value("--sliver-width")) p.sliver_width = std::atof(v);
    else {
      std::fprintf(stderr, "usage: %s [--occluders=N] [--boxes=N] [--grid=N] [--threads=N] "
                   "[--rays=N] [--tiles=N] [--size=S] [--seed=N]\n"
                   "       %s --gltf=FILE --light='x,y,z;...' --eye=x,y,z --look-at=x,y,z [--width=1280] "
                   "[--height=720] [--cells-per-side=32 | --cells-per-side=0 --tile-pixels=32] [--tree-max-mb=16] [--direct-candidates=N] [--keep-answers=0] [--accelerations=0] [--shadow-tolerance=X] [--threads=N] [--rays=N] [--error-table=0] [--answers-out=FILE]\n"
                   "       %s --scene=grille|foliage|slivers [--scenes=DIR] [--slivers=3000 --sliver-width=1e-9] [the camera and grouping flags; --light, --eye, --look-at default to the room's]\n",
                   argv[0], argv[0], argv[0]);
      return 2;
    }
  }
  if (!p.scene.empty() && p.scene != "grille" && p.scene != "foliage" && p.scene != "slivers") {
    std::fprintf(stderr, "--scene: '%s' is not a generated scene (grille, foliage, slivers)\n", p.scene.c_str());
    return 2;
  }
  if (p.scene == "foliage" && !std::filesystem::exists(p.scenes / "tree_kenney")) {
    std::printf("--scene=foliage: the shared scenes are not at %s (--scenes=DIR): nothing measured\n",
                p.scenes.c_str());
    return 77;
  }
  // The foliage stands in the grille's room, under the same window and light.
  if (p.scene == "grille" || p.scene == "foliage" || p.scene == "slivers") {
    // The light just outside the window, facing into the room; the camera
    // 2.2 m over the floor, looking almost straight down at the part the
    // window lights (x in [0.35, 2.9]), so every point is on the floor and
    // the window's parts are far occluders (outside the points' box). With
    // --eye=4.6,2,0 --look-at=1.4,0,0 it stands by the back wall and sees
    // the window and the blind too: they become near occluders.
    if (p.light.empty()) p.light = "-1,2,-0.8;-1,3.6,-0.8;-1,3.6,0.8;-1,2,0.8";
    if (!eye_given) p.eye = {1.9, 2.2, 0.0};
    if (!look_at_given) p.look_at = {1.7, 0.0, 0.0};
  }
  if (!p.gltf.empty() || !p.scene.empty()) {
    std::optional<BenchCase> bc = LoadCase(p);
    if (bc) bc = MakeView(std::move(*bc), p);
    return bc ? Run(*bc, p) : 1;
  }
  return Run(MakeProcedural(p), p);
}
