// The published trade: for each query kind, sweep the accuracy
// parameters and measure time and error against an exact (or converged)
// reference on the same inputs, on real scenes. Writes a Markdown report
// (tables, a summary of the cheapest setting reaching 1 % error on Sponza,
// the machine) and one log-log plot of error against time per query kind
// (gnuplot, png terminal). Not a test; --quick is (ctest accuracy_trade_quick).
//
//   visq_bench_accuracy_trade [--quick] [--scenes DIR] [--out DIR]
//                             [--md NAME] [--repeats N] [--command TEXT]
//                             [--only SCENE] [--kinds KEY,...]
//
// --out DIR: the report goes to DIR/NAME (default accuracy.md), the plots,
// their data and gnuplot script to DIR/accuracy/. --quick: the Cornell box
// only, tiny sizes (under a minute); it also reads its outputs back and fails
// when a file is missing or a number is not finite. --only: one scene
// (sponza, veach-ajar, tree, cornell), --kinds: some query kinds (file
// keys: hidden_sample_map, ...), for trying a change. Exit 77 (skipped) when
// the shared scenes are absent.
//
// References, per kind:
//   hidden-sample map, patch visibility: the exact visible fraction of the
//     source patch (as an area light facing the receiver) at the receiver
//     texel centres, by the Plücker-space BSP (lib/exact); plus Embree on
//     the very same segments (bit mismatch);
//   obscurances: a GPU bake with many more directions and another seed;
//   voxelization: the CPU reference voxelizer (exact triangle-box tests) at
//     the same grid;
//   volumetric shadows: ray marching on a 4096^2 shadow map.
// Timing: wall clock of the in-process call, after one warm-up call with the
// same parameters (programs compiled, Hough tables and BVHs built and cached,
// scene resident on the GPU); the median of up to --repeats runs, fewer when
// the runs already took more than about a second and a half.
#include <algorithm>
#include <bit>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <unistd.h>

#include "core/engine.h"
#include "core/visibility_sampling_query.h"
#include "exact/light_visibility.h"
#include "obscurance/obscurance_atlas.h"
#include "obscurance/obscurance_model.h"
#include "obscurance/obscurance_rays.h"
#include "raycast/embree_scene.h"
#include "scene/gltf_loader.h"
#include "scene/gltf_writer.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/gpu_worker.h"
#include "visq/gpu/hidden_sample_map.h"
#include "visq/gpu/obscurance.h"
#include "visq/gpu/slicemap.h"
#include "visq/gpu/volumetric_shadows.h"
#include "voxel_reference/voxel_reference.h"

namespace {

using namespace visq;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

constexpr int kSkipped = 77;
constexpr double kTarget = 0.01;  // the summary's 1 % error
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

double MsSince(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

std::string Fmt(const char* format, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, format, v);
  return buf;
}

// ---------------------------------------------------------------------------
// Results: one row per (scene, method, setting); four error figures per row,
// the first being the kind's headline error (plotted, and used by the
// summary).

std::string Num(double v, bool percent = false);

struct Row {
  std::string scene;
  std::string method;   // one plot series per method
  std::string setting;  // the swept parameter(s)
  double ms = kNaN;
  int runs = 0;
  double err[4] = {kNaN, kNaN, kNaN, kNaN};
  std::string note;
};

struct Kind {
  std::string key;    // file names
  std::string title;
  std::string error_labels[4];
  std::string definition;  // what the error is, against what
  std::vector<std::string> notes;  // per scene: the reference, its cost, the inputs
  std::vector<Row> rows;
};

// Keeps the row and prints it (progress, and the figures if the run is cut
// short).
void Record(Kind& kind, Row row) {
  std::printf("  %-18s %-11s %-18s %-14s %9.1f ms  err %.3g\n", kind.key.c_str(), row.scene.c_str(),
              row.method.c_str(), row.setting.c_str(), row.ms, row.err[0]);
  std::fflush(stdout);
  kind.rows.push_back(std::move(row));
}

struct Summary {
  double median = 0;
  int runs = 0;
};

// Median wall time of `body` over up to `repeats` runs (after the caller's
// warm-up); stops early once the runs took 1.5 s. `body` returns false on
// failure.
template <typename F>
bool Time(int repeats, F&& body, Summary& out) {
  std::vector<double> ms;
  double total = 0;
  for (int r = 0; r < repeats; ++r) {
    const auto t = Clock::now();
    if (!body()) return false;
    ms.push_back(MsSince(t));
    total += ms.back();
    if (total > 1500.0) break;
  }
  std::sort(ms.begin(), ms.end());
  out.median = ms[ms.size() / 2];
  out.runs = static_cast<int>(ms.size());
  return true;
}

struct Stats {
  double mean = 0, p95 = 0, max = 0;
};

Stats AbsErrorStats(std::vector<double> e) {
  Stats s;
  if (e.empty()) return {kNaN, kNaN, kNaN};
  for (double& x : e) x = std::abs(x);
  for (double x : e) s.mean += x;
  s.mean /= static_cast<double>(e.size());
  std::sort(e.begin(), e.end());
  s.p95 = e[std::min(e.size() - 1, static_cast<size_t>(std::ceil(0.95 * static_cast<double>(e.size()))) - 1)];
  s.max = e.back();
  return s;
}

void Fail(const std::string& what, const Status& status) {
  std::fprintf(stderr, "accuracy_trade: %s: %s\n", what.c_str(), std::string(status.message()).c_str());
  std::exit(1);
}

template <typename T>
T Must(StatusOr<T> value, const std::string& what) {
  if (!value.ok()) Fail(what, value.status());
  return std::move(*value);
}

// ---------------------------------------------------------------------------
// Scenes and their query inputs.

struct SceneCase {
  std::string name;
  fs::path path;
  Scene scene;
  sampling::Patch source, receiver;  // hidden-sample map, patch visibility
  gpu::VolumetricParams volumetric;
};

glm::dvec3 Lerp(const Bounds& b, double fx, double fy, double fz) { return b.min + glm::dvec3(fx, fy, fz) * b.Extent(); }

// Height of the first surface straight below `from` (or `fallback`).
double FloorBelow(const raycast::EmbreeScene& embree, const glm::dvec3& from, double fallback) {
  raycast::Ray ray{from, {0.0, -1.0, 0.0}};
  auto hits = embree.Intersect(std::span<const raycast::Ray>(&ray, 1));
  if (!hits.ok() || !(*hits)[0].hit) return fallback;
  return from.y - (*hits)[0].t;
}

// A horizontal source patch of side `side` centred at `center` and a
// horizontal receiver (extent ru x rv, centred at receiver_center) lifted a
// little above the floor under it.
void PlacePatches(SceneCase& c, const raycast::EmbreeScene& embree, const glm::dvec3& center, double side,
                  glm::dvec3 receiver_center, double ru, double rv, bool find_floor) {
  const double diag = glm::length(c.scene.bounds.Extent());
  c.source = {center - glm::dvec3(side / 2, 0, side / 2), {side, 0, 0}, {0, 0, side}};
  const double floor = find_floor ? FloorBelow(embree, center, c.scene.bounds.min.y) : c.scene.bounds.min.y;
  receiver_center.y = floor + 1e-3 * diag;
  c.receiver = {receiver_center - glm::dvec3(ru / 2, 0, rv / 2), {ru, 0, 0}, {0, 0, rv}};
}

gpu::VolumetricParams BaseVolumetric(const Scene& s, const glm::dvec3& eye, const glm::dvec3& at) {
  gpu::VolumetricParams p;
  p.camera.position = eye;
  p.camera.forward = at - eye;
  p.camera.vertical_fov_deg = 60;
  const double extent = glm::length(s.bounds.Extent());
  p.medium = {2.0 / extent, 3.0 / extent, 0.2, false};
  return p;
}

// Loads the scene and places the queries. Positions are fractions of the
// bounds (the floor found by a ray), so they follow the assets.
bool Prepare(SceneCase& c) {
  auto scene = LoadGltfFile(c.path);
  if (!scene.ok()) {
    std::printf("skip %s: %s\n", c.name.c_str(), std::string(scene.status().message()).c_str());
    return false;
  }
  c.scene = std::move(*scene);
  const Bounds& b = c.scene.bounds;
  const glm::dvec3 e = b.Extent(), m = b.Center();
  auto embree = Must(raycast::EmbreeScene::Create(c.scene), c.name + ": embree");
  if (c.name == "sponza") {
    // A light high in the open atrium; the atrium floor and the galleries'
    // floor strips under the arcades as receiver.
    const glm::dvec3 light = {m.x, b.min.y + 0.75 * e.y, m.z};
    PlacePatches(c, embree, light, 0.08 * e.x, m, 0.7 * e.x, 0.5 * e.z, true);
    c.volumetric = BaseVolumetric(c.scene, Lerp(b, 0.12, 0.25, 0.5), Lerp(b, 0.9, 0.35, 0.45));
    c.volumetric.light.direction = {0.25, -1.0, 0.45};
    c.volumetric.light.intensity = 4.0;
  } else if (c.name == "veach-ajar") {
    // A broad light under the ceiling over the table (a skylight's size,
    // so that the table and chairs cast wide penumbrae); the room's floor.
    const glm::dvec3 light = {m.x, b.min.y + 0.85 * e.y, m.z};
    PlacePatches(c, embree, light, 0.3 * std::min(e.x, e.z), m, 0.8 * e.x, 0.8 * e.z, true);
    // A spot in place of that light (the room is closed to a sun), the
    // camera across the room.
    c.volumetric = BaseVolumetric(c.scene, Lerp(b, 0.15, 0.5, 0.5), Lerp(b, 0.85, 0.3, 0.5));
    c.volumetric.light.kind = gpu::VolumetricLightKind::kSpot;
    c.volumetric.light.position = light;
    c.volumetric.light.direction = {0.15, -1.0, 0.1};
    c.volumetric.light.cone_angle_deg = 60;
    c.volumetric.light.intensity = 4.0 * e.y * e.y;
    c.volumetric.medium.hg_g = 0.0;
    c.volumetric.medium.optically_thin = true;
  } else if (c.name == "tree") {
    // A sun-sized patch above and to the side; the ground around the trunk.
    const glm::dvec3 light = {m.x + 0.3 * e.x, b.max.y + 0.5 * e.y, m.z};
    PlacePatches(c, embree, light, 0.3 * e.x, m - glm::dvec3(0.3 * e.x, 0, 0), 2.0 * e.x, 2.0 * e.z, false);
    c.volumetric = BaseVolumetric(c.scene, m + glm::dvec3(0.2 * e.x, -0.1 * e.y, -2.0 * std::max(e.x, e.z)), m);
    c.volumetric.light.direction = {-0.3, -1.0, 0.2};
    c.volumetric.light.intensity = 4.0;
    c.volumetric.medium_bounds.Extend(b.min - e);
    c.volumetric.medium_bounds.Extend(b.max + glm::dvec3(e.x, 0, e.z));
  } else {  // cornell
    // A patch just under the ceiling (below its emitter quad); the floor.
    const glm::dvec3 light = {m.x, b.max.y - 0.04 * e.y, m.z};
    PlacePatches(c, embree, light, 0.25 * e.x, m, 0.98 * e.x, 0.98 * e.z, true);
    c.volumetric = BaseVolumetric(c.scene, m + glm::dvec3(0, 0, 1.8 * e.z), m);
    c.volumetric.camera.vertical_fov_deg = 45;
    c.volumetric.light.kind = gpu::VolumetricLightKind::kSpot;
    c.volumetric.light.position = light;
    c.volumetric.light.direction = {0.0, -1.0, 0.0};
    c.volumetric.light.cone_angle_deg = 50;
    c.volumetric.light.intensity = 4.0 * e.y * e.y;
    c.volumetric.medium.hg_g = 0.0;
    c.volumetric.medium.optically_thin = true;
  }
  return true;
}

std::string PatchText(const sampling::Patch& p) {
  char buf[256];
  std::snprintf(buf, sizeof buf, "(%.3g, %.3g, %.3g); (%.3g, %.3g, %.3g); (%.3g, %.3g, %.3g)", p.origin.x, p.origin.y,
                p.origin.z, p.edge_u.x, p.edge_u.y, p.edge_u.z, p.edge_v.x, p.edge_v.y, p.edge_v.z);
  return buf;
}

// ---------------------------------------------------------------------------
// The run's sizes.

struct RunSizes {
  bool quick = false;
  int repeats = 3;
  int receiver = 64;  // receiver texels per side (both visibility kinds)
  std::vector<int> counts = {32, 64, 128, 256, 512, 1024, 2048, 4096};
  std::vector<int> hough = {64, 256, 1024};
  std::vector<int> source_grids = {4, 8, 16, 32, 64};
  uint32_t atlas = 256;
  std::vector<uint32_t> directions = {4, 8, 16, 32, 64, 128, 256};
  uint32_t reference_rays = 4096;
  std::vector<uint32_t> rays_per_patch = {4, 16, 64, 256};
  std::vector<uint32_t> voxel_sizes = {32, 64, 128, 256, 512};
  uint32_t image_w = 320, image_h = 240;
  std::vector<uint32_t> shadow_maps = {64, 128, 256, 512, 1024, 2048};
  uint32_t reference_map = 4096;
};

// Scenes other than Sponza get a lighter sweep where the GPU path is slow
// (every rasterization pass costs seconds on llvmpipe for veach-ajar).
bool Full(const RunSizes& plan, const SceneCase& c) { return plan.quick || c.name == "sponza"; }

// ---------------------------------------------------------------------------
// Exact reference: the visible fraction of the source patch, as a light
// facing the receiver, at every receiver texel centre. Receivers are grouped
// as the server groups a LightVisibility batch: cubes of 1/32 of the scene,
// one tree each, each growing to 16 MiB (the server's defaults).

struct ExactReference {
  std::vector<double> fraction;  // per texel, row-major
  double ms = 0;
  size_t penumbra = 0;  // texels with 0 < fraction < 1
  double mean = 0;
  size_t cells = 0;     // receiver cells (trees)
};

ExactReference ExactFractions(const SceneCase& c, int width, int height) {
  exact::AreaLight light;
  const sampling::Patch& s = c.source;
  light.vertices = {s.origin, s.origin + s.edge_u, s.origin + s.edge_u + s.edge_v, s.origin + s.edge_v};
  const glm::dvec3 normal = glm::cross(s.edge_u, s.edge_v);
  const glm::dvec3 toward = c.receiver.At(0.5, 0.5) - s.At(0.5, 0.5);
  if (glm::dot(normal, toward) < 0) std::reverse(light.vertices.begin(), light.vertices.end());
  sampling::ReceiverSpec receiver;
  receiver.patch = c.receiver;
  receiver.width = width;
  receiver.height = height;
  ExactReference ref;
  ref.fraction.resize(size_t(width) * height);
  std::vector<exact::QueryPoint> points;
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) points.push_back({sampling::ReceiverSamplePosition(receiver, x, y), {}, {}});
  auto shared_scene = std::make_shared<const Scene>(c.scene);
  const auto t0 = Clock::now();
  auto index = Must(exact::SceneTriangleIndex::Build(shared_scene), c.name + ": triangle index");
  const auto cells = exact::GroupReceivers(points, c.scene.bounds, 32);
  ref.cells = cells.size();
  for (const exact::ReceiverCell& cell : cells) {
    exact::TreeOptions options;
    options.receiver_bounds = cell.box;
    options.max_bytes = size_t{16} << 20;
    auto tree = Must(exact::LightVisibilityTree::Create(light, c.scene, options, index.get()), c.name + ": exact tree");
    std::vector<exact::QueryPoint> cell_points;
    for (const uint32_t i : cell.points) cell_points.push_back(points[i]);
    auto answers = Must(tree->QueryBatch(cell_points), c.name + ": exact queries");
    for (size_t k = 0; k < cell.points.size(); ++k) ref.fraction[cell.points[k]] = answers[k].visible_area_fraction;
  }
  ref.ms = MsSince(t0);
  for (double f : ref.fraction) {
    ref.penumbra += f > 1e-9 && f < 1 - 1e-9;
    ref.mean += f;
  }
  ref.mean /= static_cast<double>(ref.fraction.size());
  return ref;
}

// ---------------------------------------------------------------------------
// RAYCAST: Embree on exactly the segments the GPU path tests (the same
// source samples and receiver texel centres), as server/core does.

struct RaycastMap {
  std::vector<float> visible_fraction;
  std::vector<uint32_t> bits;
  int words = 0;
};

bool Raycast(const raycast::EmbreeScene& embree, const sampling::HiddenSampleMapRequest& request,
             const sampling::SourceSamples& samples, RaycastMap& out) {
  const int width = request.receiver.width, height = request.receiver.height;
  const int n = static_cast<int>(samples.world.size());
  out.words = (n + 31) / 32;
  out.bits.assign(size_t(width) * height * out.words, 0u);
  out.visible_fraction.assign(size_t(width) * height, 0.0f);
  std::vector<raycast::Segment> segments;
  segments.reserve(size_t(width) * height * n);
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      const glm::dvec3 p = sampling::ReceiverSamplePosition(request.receiver, x, y);
      for (int i = 0; i < n; ++i) segments.push_back({p, sampling::SourceSampleSeenFrom(request, samples, i, x, y)});
    }
  auto blocked = embree.Occluded(segments);
  if (!blocked.ok()) return false;
  size_t k = 0;
  for (size_t j = 0; j < out.visible_fraction.size(); ++j) {
    int hidden = 0;
    for (int i = 0; i < n; ++i, ++k)
      if ((*blocked)[k]) {
        out.bits[j * out.words + i / 32] |= 1u << (i % 32);
        ++hidden;
      }
    out.visible_fraction[j] = float(n - hidden) / float(n);
  }
  return true;
}

double BitMismatch(const std::vector<uint32_t>& a, const std::vector<uint32_t>& b, size_t texels, int n) {
  if (a.size() != b.size() || texels == 0) return kNaN;
  uint64_t diff = 0;
  for (size_t i = 0; i < a.size(); ++i) diff += std::popcount(a[i] ^ b[i]);
  return static_cast<double>(diff) / (static_cast<double>(texels) * n);
}

std::vector<double> Diff(const std::vector<float>& answer, const std::vector<double>& exact) {
  std::vector<double> d(answer.size());
  for (size_t i = 0; i < answer.size(); ++i) d[i] = double(answer[i]) - exact[i];
  return d;
}

// ---------------------------------------------------------------------------
// Hidden-sample map.

// How the per-texel bounds (sampling::BoundTexels) fare against the exact
// fractions: the share of texels whose error is within their bound (the
// bound's confidence is the share promised), and in the penumbra, where the
// answer is uncertain, the median bound against the median error.
std::string PerTexelBoundNote(const sampling::HiddenSampleMapResult& map, const ExactReference& ref) {
  if (!map.error.has_per_texel || map.error.per_texel.size() != ref.fraction.size()) return "no per-texel bound";
  size_t inside = 0, estimate_covers = 0;
  const bool estimated = map.error.per_texel_estimate.size() == ref.fraction.size();
  std::vector<double> bounds, errors, estimates;
  for (size_t j = 0; j < ref.fraction.size(); ++j) {
    const double error = std::abs(double(map.visible_fraction[j]) - ref.fraction[j]);
    inside += error <= double(map.error.per_texel[j]) + 1e-7;
    if (ref.fraction[j] > 1e-9 && ref.fraction[j] < 1 - 1e-9) {
      bounds.push_back(map.error.per_texel[j]);
      errors.push_back(error);
      if (estimated) {
        estimates.push_back(map.error.per_texel_estimate[j]);
        estimate_covers += error <= double(map.error.per_texel_estimate[j]) + 1e-7;
      }
    }
  }
  std::string note = "per-texel bound holds at " + Num(double(inside) / ref.fraction.size(), true) + " of texels (" +
                     Num(map.error.confidence, true) + " stated)";
  if (!bounds.empty()) {
    std::sort(bounds.begin(), bounds.end());
    std::sort(errors.begin(), errors.end());
    const double mb = bounds[bounds.size() / 2], me = errors[errors.size() / 2];
    note += "; penumbra median bound " + Fmt("%.3g", mb) + ", median error " + Fmt("%.3g", me);
    if (me > 0) note += " (" + Fmt("%.2g", mb / me) + "x)";
    if (!estimates.empty()) {
      // The estimate beside the bound (EstimateOfTexel): how tight, and how
      // often it covers the error where the answer is uncertain.
      std::sort(estimates.begin(), estimates.end());
      const double ms = estimates[estimates.size() / 2];
      note += "; penumbra median estimate " + Fmt("%.3g", ms);
      if (me > 0) note += " (" + Fmt("%.2g", ms / me) + "x)";
      note += ", covering " + Num(double(estimate_covers) / estimates.size(), true) + " of penumbra texels";
    }
  }
  return note;
}

void SweepHiddenSampleMap(const RunSizes& plan, SceneCase& c, gpu::HiddenSampleMapper& mapper,
                          const gpu::GpuScene& gpu_scene, const raycast::EmbreeScene& embree,
                          const ExactReference& ref, Kind& kind) {
  const bool full = Full(plan, c);
  // Embree takes every count on every scene (the error against N); the
  // raster paths fewer where a pass is slow.
  std::vector<int> raster_counts = plan.counts;
  std::vector<int> hough = plan.hough;
  if (!full) {
    raster_counts = {32, 256, 1024};  // one rasterization pass each
    hough = {256};
  }
  const size_t texels = size_t(plan.receiver) * plan.receiver;
  for (int n : plan.counts) {
    sampling::HiddenSampleMapRequest r;
    r.source.patch = c.source;
    r.source.sample_count = n;
    r.source.pattern = sampling::SamplePattern::kJittered;
    r.source.seed = 1;
    r.receiver.patch = c.receiver;
    r.receiver.width = r.receiver.height = plan.receiver;
    const std::string setting = "N=" + std::to_string(n);

    // RAYCAST first: its bits are what the raster paths are compared with.
    const sampling::SourceSamples samples = Must(sampling::ComputeSourceSamples(r.source), "source samples");
    RaycastMap rays;
    if (!Raycast(embree, r, samples, rays)) Fail("raycast", absl::InternalError("Occluded failed"));
    Summary t;
    RaycastMap scratch;
    if (!Time(plan.repeats, [&] { return Raycast(embree, r, samples, scratch); }, t)) continue;
    {
      const Stats s = AbsErrorStats(Diff(rays.visible_fraction, ref.fraction));
      Record(kind, {c.name, "RAYCAST (Embree)", setting, t.median, t.runs, {s.mean, s.p95, s.max, 0.0}, ""});
    }
    if (std::find(raster_counts.begin(), raster_counts.end(), n) == raster_counts.end()) continue;

    struct Variant {
      std::string method;
      sampling::LookupMode lookup;
      int hough;
    };
    std::vector<Variant> variants = {{"RASTER EXACT", sampling::LookupMode::kExact, 256}};
    for (int h : hough) variants.push_back({"RASTER HOUGH h" + std::to_string(h), sampling::LookupMode::kHough, h});
    for (const Variant& v : variants) {
      r.options.lookup = v.lookup;
      r.options.hough_theta_resolution = r.options.hough_r_resolution = v.hough;
      // Warm-up with bitmasks: builds and caches the Hough table, and gives
      // the bits to compare with Embree's.
      r.options.want_bitmasks = true;
      auto warm = mapper.Compute(gpu_scene, r);
      if (!warm.ok()) Fail(c.name + " " + v.method + " " + setting, warm.status());
      const double mismatch = BitMismatch(warm->blocked_bits, rays.bits, texels, n);
      r.options.want_bitmasks = false;
      sampling::HiddenSampleMapResult last;
      if (!Time(plan.repeats,
                [&] {
                  auto result = mapper.Compute(gpu_scene, r);
                  if (!result.ok()) return false;
                  last = std::move(*result);
                  return true;
                },
                t))
        Fail(c.name + " " + v.method, absl::InternalError("compute failed"));
      const Stats s = AbsErrorStats(Diff(last.visible_fraction, ref.fraction));
      std::string note;
      if (v.lookup == sampling::LookupMode::kHough) note = "stated bound " + Fmt("%.3g", last.error.lookup_max);
      if (v.lookup == sampling::LookupMode::kExact) note = PerTexelBoundNote(last, ref);
      Record(kind, {c.name, v.method, setting, t.median, t.runs, {s.mean, s.p95, s.max, mismatch}, note});
    }
  }
}

// ---------------------------------------------------------------------------
// Accuracy targets through the core (server/core, the server's own planner
// and cost model, without gRPC): the plan each target chose, what it was
// predicted to take and what it took; then each method's cheapest plan
// meeting the target, run as a plain request, so that the choice can be
// checked against what every candidate measures.

struct TargetRow {
  std::string scene;
  double max_error = 0;
  std::string call;  // which call of the target, or "direct"
  std::string plan;
  double predicted_ms = kNaN, measured_ms = kNaN;
  bool chosen = false;
};

struct TargetCheck {
  std::string scene;
  double max_error = 0;
  std::string chosen, cheapest;
  double chosen_ms = kNaN, cheapest_ms = kNaN;
};

double ComputeMsOf(const sampling::HiddenSampleMapResult& r) { return r.timing.run_ms + r.table_ms; }

void MeasureTargets(const RunSizes& plan, const SceneCase& c, core::Engine& engine, const std::string& name,
                    std::vector<TargetRow>& rows, std::vector<TargetCheck>& checks) {
  const std::vector<double> targets = plan.quick ? std::vector<double>{0.1} : std::vector<double>{0.05, 0.03};
  for (const double max_error : targets) {
    core::HiddenSampleMapQuery query;
    query.scene = name;
    query.request.source.patch = c.source;
    query.request.source.pattern = sampling::SamplePattern::kJittered;
    query.request.source.seed = 1;
    query.request.receiver.patch = c.receiver;
    query.request.receiver.width = query.request.receiver.height = plan.receiver;
    query.request.options.want_bitmasks = false;
    query.request.source.sample_count = 0;  // the target sets it
    query.target = core::AccuracyTarget{.max_error = max_error, .confidence = 0.95};
    const std::string what = c.name + " target " + Fmt("%.3g", max_error);
    auto first = Must(core::RunHiddenSampleMap(engine, query), what);
    const core::PlanReport& report = *first.plan;
    const ::visq::core::Plan& chosen = report.chosen_plan();
    rows.push_back({c.name, max_error, "1st call (probes " + Fmt("%.0f", report.probe_ms) + " ms)",
                    core::DescribePlan(chosen), chosen.predicted_ms, ComputeMsOf(first.result), true});
    std::printf("  target %.3g: chose %s, predicted %.1f ms, took %.1f ms, probes %.1f ms\n", max_error,
                core::DescribePlan(chosen).c_str(), chosen.predicted_ms, ComputeMsOf(first.result), report.probe_ms);
    TargetCheck check{c.name, max_error, core::DescribePlan(chosen), core::DescribePlan(chosen),
                      ComputeMsOf(first.result), ComputeMsOf(first.result)};

    // Every other method's cheapest plan meeting the target, run directly.
    std::map<std::string, const ::visq::core::Plan*> cheapest;
    for (const ::visq::core::Plan& p : report.plans)
      if (p.meets_target && (!cheapest.contains(p.method) || p.predicted_ms < cheapest[p.method]->predicted_ms))
        cheapest[p.method] = &p;
    for (const auto& [method, p] : cheapest) {
      if (method == chosen.method) continue;
      if (p->predicted_ms > 60000) {
        rows.push_back({c.name, max_error, "direct", core::DescribePlan(*p) + " (not run: predicted over 60 s)",
                        p->predicted_ms, kNaN, false});
        continue;
      }
      core::HiddenSampleMapQuery direct = query;
      direct.target.reset();
      direct.method = method == "plucker-exact" ? core::VisibilityMethod::kPluckerExact
                      : method == "raycast"    ? core::VisibilityMethod::kRaycast
                                               : core::VisibilityMethod::kRaster;
      direct.request.source.sample_count = p->parameters.contains("samples") ? int(p->parameters.at("samples")) : 0;
      auto answer = Must(core::RunHiddenSampleMap(engine, direct), what + " " + core::DescribePlan(*p));
      const double ms = ComputeMsOf(answer.result);
      rows.push_back({c.name, max_error, "direct", core::DescribePlan(*p), p->predicted_ms, ms, false});
      std::printf("    %s: predicted %.1f ms, took %.1f ms\n", core::DescribePlan(*p).c_str(), p->predicted_ms, ms);
      if (ms < check.cheapest_ms) {
        check.cheapest_ms = ms;
        check.cheapest = core::DescribePlan(*p);
      }
    }
    checks.push_back(check);

    // The same target again: predicted from what the first call measured.
    auto second = Must(core::RunHiddenSampleMap(engine, query), what + " again");
    const ::visq::core::Plan& again = second.plan->chosen_plan();
    rows.push_back({c.name, max_error, "2nd call", core::DescribePlan(again), again.predicted_ms,
                    ComputeMsOf(second.result), true});
  }
}

// ---------------------------------------------------------------------------
// Patch visibility: the mutual fraction against the mean of the exact
// per-receiver-sample fractions (the receiver grid is the texel grid of the
// hidden-sample map, so the exact reference is shared).

void SweepPatchVisibility(const RunSizes& plan, SceneCase& c, gpu::HiddenSampleMapper& mapper,
                          const gpu::GpuScene& gpu_scene, const raycast::EmbreeScene& embree,
                          const ExactReference& ref, Kind& kind) {
  std::vector<int> grids = plan.source_grids;
  if (!Full(plan, c)) grids = {4, 16, 32};  // up to 1024 samples: one pass
  double exact_mutual = 0;
  for (double f : ref.fraction) exact_mutual += f;
  exact_mutual /= static_cast<double>(ref.fraction.size());
  for (int g : grids) {
    sampling::PatchVisibilityRequest r;
    r.source = c.source;
    r.source_columns = r.source_rows = g;
    r.receiver = c.receiver;
    r.receiver_columns = r.receiver_rows = plan.receiver;
    const std::string setting = std::to_string(g) + "x" + std::to_string(g);
    auto record = [&](const std::string& method, const Summary& t, const sampling::PatchVisibilityResult& result) {
      const Stats s = AbsErrorStats(Diff(result.receiver_visible, ref.fraction));
      Record(kind, {c.name, method, setting, t.median, t.runs,
                           {std::abs(result.mutual_visible_fraction - exact_mutual), s.mean, s.p95, s.max}, ""});
    };
    // RAYCAST: the same map the GPU path computes, by Embree.
    const sampling::HiddenSampleMapRequest map = Must(sampling::PatchVisibilityAsHiddenSampleMap(r), "patch as map");
    const sampling::SourceSamples samples = Must(sampling::ComputeSourceSamples(map.source), "patch samples");
    sampling::PatchVisibilityResult last;
    auto raycast = [&] {
      RaycastMap rays;
      if (!Raycast(embree, map, samples, rays)) return false;
      sampling::HiddenSampleMapResult as_map;
      as_map.width = map.receiver.width;
      as_map.height = map.receiver.height;
      as_map.sample_count = static_cast<int>(samples.world.size());
      as_map.words_per_texel = rays.words;
      as_map.visible_fraction = std::move(rays.visible_fraction);
      as_map.blocked_bits = std::move(rays.bits);
      last = sampling::SummarizePatchVisibility(r, as_map);
      return true;
    };
    Summary t;
    if (!raycast() || !Time(plan.repeats, raycast, t)) Fail("patch raycast", absl::InternalError("failed"));
    record("RAYCAST (Embree)", t, last);
    for (auto lookup : {sampling::LookupMode::kExact, sampling::LookupMode::kHough}) {
      r.lookup = lookup;
      auto body = [&] {
        auto result = mapper.PatchVisibility(gpu_scene, r);
        if (!result.ok()) return false;
        last = std::move(*result);
        return true;
      };
      if (!body() || !Time(plan.repeats, body, t)) Fail("patch visibility", absl::InternalError("failed"));
      record(lookup == sampling::LookupMode::kExact ? "RASTER EXACT" : "RASTER HOUGH h256", t, last);
    }
  }
}

// ---------------------------------------------------------------------------
// Obscurances: W per atlas texel against a GPU bake with many more
// directions (another seed, so the sweep's sequences are not its prefixes).

// How the obscurance bounds hold against the reference: the answer's
// single bound over the texels, triangles and vertices it covers (and how
// many it leaves outside), and each element's own bound over all of them.
// Triangles (and vertices, all of whose triangles) whose reference rests on
// fewer than 1024 rays are left out: the reference's noise would be counted
// against the bake.
std::string BoundCoverageNote(const Scene& scene, const obscurance::ObscuranceAtlas& atlas,
                              const obscurance::ObscuranceResult& result, const obscurance::ObscuranceResult& reference,
                              double nominal) {
  using namespace visq::obscurance;
  constexpr double kConfidence = 0.95, kReferenceRays = 1024;
  const ObscuranceBounds bounds = ObscuranceBoundsOf(scene, result, kConfidence);
  const ObscuranceAnswerBound answer = ObscuranceAnswerBoundOf(result, bounds, nominal, kConfidence);
  const double single = answer.error_bound;
  struct Count {
    size_t covered = 0, covered_within = 0, all = 0, own_within = 0;
    void Add(double error, float own, double single) {
      ++all;
      own_within += error <= own;
      if (own <= single) {
        ++covered;
        covered_within += error <= single;
      }
    }
    std::string Share(size_t k, size_t n) const { return n ? Fmt("%.4g %%", 100.0 * double(k) / double(n)) : "–"; }
  };
  Count texels, triangles, vertices;
  // Where the rays' variance is known: the texels' median error and own
  // bound, and how often the estimate (ObscuranceTexelEstimates) holds.
  const std::vector<float> estimates = ObscuranceTexelEstimates(result, kConfidence);
  const bool rays = estimates.size() == result.w.size();
  std::vector<double> texel_errors, texel_bounds, texel_estimates;
  size_t estimate_within = 0;
  for (uint32_t t = 0; t < atlas.texel_count(); ++t)
    if (atlas.Covered(t) && result.estimated[t] && reference.estimated[t]) {
      const double error = std::abs(double(result.w[t].x) - reference.w[t].x);
      texels.Add(error, bounds.texel[t], single);
      texel_errors.push_back(error);
      texel_bounds.push_back(bounds.texel[t]);
      if (rays) {
        const double estimate = estimates[t];
        texel_estimates.push_back(estimate);
        estimate_within += error <= estimate;
      }
    }
  auto median = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 0.0 : v[v.size() / 2];
  };
  std::vector<uint8_t> vertex_ok(scene.positions.size(), 1);
  for (uint32_t t = 0; t < scene.TriangleCount(); ++t) {
    const bool ok = reference.triangle_effective_samples[t] >= kReferenceRays && result.triangle_effective_samples[t] > 0;
    if (!ok) {
      for (int k = 0; k < 3; ++k) vertex_ok[scene.triangles[t][k]] = 0;
      continue;
    }
    triangles.Add(std::abs(double(result.triangle_w[t].x) - reference.triangle_w[t].x), bounds.triangle[t], single);
  }
  std::vector<uint8_t> used(scene.positions.size(), 0);
  for (uint32_t t = 0; t < scene.TriangleCount(); ++t)
    for (int k = 0; k < 3; ++k) used[scene.triangles[t][k]] = 1;
  for (size_t v = 0; v < scene.positions.size(); ++v)
    if (used[v] && vertex_ok[v])
      vertices.Add(std::abs(double(result.vertex_w[v].x) - reference.vertex_w[v].x), bounds.vertex[v], single);
  return "single bound " + Fmt("%.3g", single) + " holds for texels " +
         texels.Share(texels.covered_within, texels.covered) + " (" +
         std::to_string(answer.texels.outside) + " outside), triangles " +
         triangles.Share(triangles.covered_within, triangles.covered) + " (" +
         std::to_string(answer.triangles.outside) + " outside), vertices " +
         vertices.Share(vertices.covered_within, vertices.covered) + " (" + std::to_string(answer.vertices.outside) +
         " outside); own bounds hold for texels " + texels.Share(texels.own_within, texels.all) + ", triangles " +
         triangles.Share(triangles.own_within, triangles.all) + " (" + std::to_string(triangles.all) + "), vertices " +
         vertices.Share(vertices.own_within, vertices.all) + " (" + std::to_string(vertices.all) + ")" +
         (rays ? "; texels' median error " + Fmt("%.3g", median(texel_errors)) + ", median own bound " +
                     Fmt("%.3g", median(texel_bounds)) + ", median estimate " +
                     Fmt("%.3g", median(texel_estimates)) + "; the estimate holds for texels " +
                     texels.Share(estimate_within, texels.all)
               : "");
}

void SweepObscurances(const RunSizes& plan, SceneCase& c, gpu::GpuWorker& worker, const gpu::GpuScene& gpu_scene,
                      Kind& kind) {
  using namespace visq::obscurance;
  const bool full = Full(plan, c);
  const auto t_atlas = Clock::now();
  const ObscuranceAtlas atlas = Must(BuildObscuranceAtlas(c.scene, plan.atlas), c.name + ": atlas");
  const double atlas_ms = MsSince(t_atlas);
  ObscuranceParams params;
  params.d_max = 0.1 * glm::length(c.scene.bounds.Extent());
  params.color_bleeding = false;
  auto bake = [&](uint32_t directions, uint64_t seed) {
    params.direction_count = directions;
    params.seed = seed;
    return Must(gpu::BakeObscurances(worker, gpu_scene, c.scene, atlas, params), c.name + ": obscurance bake");
  };
  (void)bake(1, 1);  // warm-up: programs and the scene's GPU buffers
  auto rays = [&](uint32_t n, uint64_t seed) {
    RayEstimateOptions options;
    options.rays_per_patch = n;
    options.seed = seed;
    return Must(EstimateObscurancesByRays(c.scene, atlas, params, options), c.name + ": obscurance rays");
  };

  // The sweep first, fewest directions first, stopping before a bake that
  // would take more than `max_bake_ms` at the cost per direction seen so far.
  struct Point {
    std::string method, setting;
    Summary t;
    ObscuranceResult result;
    double nominal = 0;  // directions or rays per patch: what the single bound rests on
  };
  std::vector<Point> points;
  const double max_bake_ms = plan.quick ? 5e3 : (full ? 40e3 : 15e3);
  double ms_per_direction = 0;
  for (uint32_t d : full ? plan.directions : std::vector<uint32_t>{4, 16, 64, 256}) {
    if (ms_per_direction * d > max_bake_ms) break;
    Point p{"GPU depth peeling", std::to_string(d) + " dirs", {}, {}, double(d)};
    Time(plan.repeats, [&] { p.result = bake(d, 1); return true; }, p.t);
    ms_per_direction = p.t.median / d;
    points.push_back(std::move(p));
  }
  for (uint32_t n : full ? plan.rays_per_patch : std::vector<uint32_t>{4, 16, 64}) {
    Point p{"Embree rays (CPU)", std::to_string(n) + " rays/patch", {}, {}, double(n)};
    Time(plan.repeats, [&] { p.result = rays(n, 1); return true; }, p.t);
    points.push_back(std::move(p));
  }

  // The reference. A GPU bake costs about half a second per direction on
  // llvmpipe (Sponza, 256^2 atlas), so a converged bake does not fit in the
  // run; the Embree estimator of the same patch averages (unbiased, see
  // obscurance_rays.h) with many rays per patch and another seed does.
  const auto t_ref = Clock::now();
  const ObscuranceResult reference = rays(plan.reference_rays, 7);
  const double ref_ms = MsSince(t_ref);
  std::printf("  obscurance reference %s: %u rays/patch, %.1f s\n", c.name.c_str(), plan.reference_rays,
              ref_ms / 1000);
  kind.notes.push_back(c.name + ": atlas " + std::to_string(atlas.width) + "x" + std::to_string(atlas.height) +
                       " (" + Fmt("%.0f", atlas_ms) + " ms to build), d_max = 0.1 x scene diagonal, no colour "
                       "bleeding. Reference: the Embree estimator with " + std::to_string(plan.reference_rays) +
                       " rays per patch and another seed (" + Fmt("%.1f", ref_ms / 1000) + " s). A GPU bake here "
                       "costs " + Fmt("%.0f", ms_per_direction) + " ms per direction, so a converged GPU bake "
                       "(thousands of directions) does not fit in the run. GPU bakes stop before one would take "
                       "more than " + Fmt("%.0f", max_bake_ms / 1000) + " s. The Embree times include building "
                       "its BVH, which every call does. Bounds (the note column) at 95 %: the answer's single bound "
                       "(ObscuranceAnswerBoundOf, what ComputeObscurances states) over the elements it covers, how "
                       "many it leaves outside, and each element's own bound (want_errors), against the reference "
                       "per texel, per triangle and per vertex; triangles and vertices only where the reference "
                       "rests on at least 1024 rays of their own (its own half-width 0.042).");
  for (const Point& p : points) {
    std::vector<double> d;
    for (uint32_t texel = 0; texel < atlas.texel_count(); ++texel)
      if (atlas.Covered(texel) && p.result.estimated[texel] && reference.estimated[texel])
        d.push_back(double(p.result.w[texel].x) - reference.w[texel].x);
    double sq = 0;
    for (double x : d) sq += x * x;
    const Stats s = AbsErrorStats(d);
    Record(kind, {c.name, p.method, p.setting, p.t.median, p.t.runs,
                  {s.mean, s.p95, s.max, d.empty() ? kNaN : std::sqrt(sq / double(d.size()))},
                  Fmt("%.0f samples/patch", p.result.mean_samples_per_patch) + "; " +
                      BoundCoverageNote(c.scene, atlas, p.result, reference, p.nominal)});
  }
}

// ---------------------------------------------------------------------------
// Voxelization: the GPU slicemap against the CPU reference voxelizer on the
// same grid (surface, uniform slices, depth along y).

void SweepVoxelization(const RunSizes& plan, SceneCase& c, gpu::GpuWorker& worker, const gpu::GpuScene& gpu_scene,
                       Kind& kind) {
  std::vector<uint32_t> sizes = plan.voxel_sizes;
  if (!Full(plan, c)) sizes = {64, 128, 256};
  for (uint32_t n : sizes) {
    gpu::VoxelizeParams params;
    params.box = gpu::AxisAlignedSlicemapBox(c.scene.bounds, 1, 1e-3 * glm::length(c.scene.bounds.Extent()));
    params.width = params.height = params.slices = n;
    params.max_bytes = uint64_t{4} << 30;
    const voxel_reference::GridBox box{params.box, n, n, n};
    voxel_reference::SurfaceStats stats;
    const auto reference = Must(voxel_reference::VoxelizeSurface(c.scene, box, {}, &stats), "voxel reference");
    const double occupied = static_cast<double>(reference.CountOccupied());
    // What a one-sample-per-texel rasterizer can see: the standard mode's own
    // definition, so its error against it is the implementation's alone.
    const auto centres = Must(voxel_reference::SampleColumnCenters(c.scene, box), "column-centre reference");
    const std::string setting = std::to_string(n) + "^3";
    for (auto raster : {gpu::Rasterization::kStandard, gpu::Rasterization::kConservative}) {
      params.rasterization = raster;
      gpu::VoxelizeResult last;
      auto body = [&] {
        auto r = gpu::Voxelize(worker, gpu_scene, params);
        if (!r.ok()) return false;
        last = std::move(*r);
        return true;
      };
      Summary t;
      if (!body() || !Time(plan.repeats, body, t)) Fail("voxelize", absl::InternalError("failed"));
      uint64_t missing = 0, extra = 0, off_centres = 0;
      for (size_t i = 0; i < last.grid.bits.size() && i < reference.bits.size(); ++i) {
        missing += std::popcount(reference.bits[i] & ~last.grid.bits[i]);
        extra += std::popcount(last.grid.bits[i] & ~reference.bits[i]);
        if (i < centres.bits.size()) off_centres += std::popcount(last.grid.bits[i] ^ centres.bits[i]);
      }
      const double o = std::max(occupied, 1.0);
      const bool standard = raster == gpu::Rasterization::kStandard;
      Record(kind, {c.name, standard ? "standard" : "conservative", setting, t.median, t.runs,
                           {double(missing + extra) / o, double(missing) / o, double(extra) / o,
                            standard ? double(off_centres) / std::max<double>(1.0, centres.CountOccupied()) : kNaN},
                           Fmt("%.0f", occupied) + " occupied; CPU reference " + Fmt("%.0f", stats.milliseconds) +
                               " ms"});
    }
  }
}

// ---------------------------------------------------------------------------
// Volumetric shadows: in-scattered radiance against ray marching on a large
// shadow map, same camera, light and medium.

void SweepVolumetric(const RunSizes& plan, SceneCase& c, gpu::GpuWorker& worker, const gpu::GpuScene& gpu_scene,
                     Kind& kind) {
  gpu::VolumetricParams params = c.volumetric;
  params.camera.width = plan.image_w;
  params.camera.height = plan.image_h;
  params.method = gpu::VolumetricMethod::kRayMarching;
  params.shadow_map_size = plan.reference_map;
  // The reference integrates per texel (no SVD table error); the sweep below
  // takes the default integrand, as the service does.
  params.integrand_choice = gpu::VolumetricIntegrandChoice::kExact;
  const auto t_ref = Clock::now();
  const gpu::VolumetricResult reference =
      Must(gpu::RenderVolumetricShadows(worker, gpu_scene, c.scene, params), c.name + ": volumetric reference");
  params.integrand_choice = gpu::VolumetricIntegrandChoice::kAuto;
  const double ref_ms = MsSince(t_ref);
  double mean_ref = 0, max_ref = 0;
  for (float v : reference.inscattering) {
    mean_ref += v;
    max_ref = std::max(max_ref, double(v));
  }
  mean_ref /= std::max<size_t>(1, reference.inscattering.size());
  kind.notes.push_back(c.name + ": " + std::to_string(plan.image_w) + "x" + std::to_string(plan.image_h) + ", " +
                       (c.volumetric.light.kind == gpu::VolumetricLightKind::kSpot ? "spot" : "directional") +
                       " light, reference integrand " + std::string(gpu::VolumetricIntegrandName(reference.integrand)) +
                       "; reference: ray marching on a " + std::to_string(plan.reference_map) + "^2 map (" +
                       Fmt("%.0f", ref_ms) + " ms, first call), mean in-scattering " + Fmt("%.3g", mean_ref) +
                       ", peak " + Fmt("%.3g", max_ref) + ".");
  std::vector<uint32_t> maps = plan.shadow_maps;
  if (!Full(plan, c)) maps = {64, 256, 1024};
  for (uint32_t map : maps)
    for (auto method : {gpu::VolumetricMethod::kMinMaxTraversal, gpu::VolumetricMethod::kRayMarching}) {
      params.shadow_map_size = map;
      params.method = method;
      gpu::VolumetricResult last;
      auto body = [&] {
        auto r = gpu::RenderVolumetricShadows(worker, gpu_scene, c.scene, params);
        if (!r.ok()) return false;
        last = std::move(*r);
        return true;
      };
      Summary t;
      if (!body() || !Time(plan.repeats, body, t)) Fail("volumetric", absl::InternalError("failed"));
      std::vector<double> d(last.inscattering.size());
      double sq = 0;
      for (size_t i = 0; i < d.size(); ++i) {
        d[i] = double(last.inscattering[i]) - reference.inscattering[i];
        sq += d[i] * d[i];
      }
      const Stats s = AbsErrorStats(d);
      const double mean = mean_ref > 0 ? mean_ref : 1.0, peak = max_ref > 0 ? max_ref : 1.0;
      Record(kind, {c.name, method == gpu::VolumetricMethod::kMinMaxTraversal ? "MIN_MAX" : "RAY_MARCHING",
                           "map " + std::to_string(map), t.median, t.runs,
                           {std::sqrt(sq / std::max<size_t>(1, d.size())) / mean, s.mean / mean, s.p95 / mean,
                            s.max / peak},
                           Fmt("traversal %.1f ms", last.timings.traversal_ms)});
    }
}

// ---------------------------------------------------------------------------
// Output: Markdown tables, gnuplot data and script, the plots.

std::string Num(double v, bool percent) {
  if (!std::isfinite(v)) return "–";
  if (percent) return Fmt(v == 0 ? "%.0f %%" : (v < 0.001 ? "%.2e %%" : "%.3g %%"), 100 * v);
  return Fmt(v == 0 ? "%.0f" : "%.3g", v);
}

std::string Escape(const std::string& s) {
  std::string out;
  for (char ch : s) {
    if (ch == '"' || ch == '\\') out += '\\';
    out += ch;
  }
  return out;
}

// A Markdown table cell: '|' would end the cell.
std::string Cell(const std::string& s) {
  std::string out;
  for (char ch : s) out += ch == '|' ? std::string("\\|") : std::string(1, ch);
  return out;
}

std::vector<std::string> Unique(const std::vector<Row>& rows, std::string Row::*field, const std::string& scene = "") {
  std::vector<std::string> out;
  for (const Row& r : rows)
    if ((scene.empty() || r.scene == scene) && std::find(out.begin(), out.end(), r.*field) == out.end())
      out.push_back(r.*field);
  return out;
}

// One PNG per kind: a panel per scene, a series per method, error against
// time on log-log axes. Returns false when gnuplot failed or is missing.
bool Plot(const Kind& kind, const fs::path& dir, bool have_gnuplot) {
  const fs::path dat = dir / (kind.key + ".dat"), gp = dir / (kind.key + ".gp"), png = dir / (kind.key + ".png");
  const std::vector<std::string> scenes = Unique(kind.rows, &Row::scene);
  std::ofstream d(dat);
  d << "# " << kind.title << ": time_ms headline_error (" << kind.error_labels[0]
    << "; zero drawn at 1e-6); one block per (scene, method)\n";
  std::ofstream g(gp);
  g << "# Generated by visq_bench_accuracy_trade; run `gnuplot " << gp.filename().string() << "` in this folder.\n"
    << "set terminal png size 1400," << (scenes.size() > 2 ? 1000 : 520) << " font \",10\"\n"
    << "set output '" << png.filename().string() << "'\n"
    << "set logscale xy\nset grid\nset key top right font \",9\"\n"
    << "set xlabel 'time per query (ms)'\nset ylabel '" << kind.error_labels[0] << "'\n"
    << "set multiplot layout " << (scenes.size() > 2 ? 2 : 1) << "," << std::min<size_t>(2, scenes.size())
    << " title \"" << Escape(kind.title) << ": error against time\"\n";
  int block = 0;
  for (const std::string& scene : scenes) {
    g << "set title '" << scene << "'\nplot";
    const std::vector<std::string> methods = Unique(kind.rows, &Row::method, scene);
    for (size_t m = 0; m < methods.size(); ++m) {
      d << "# " << scene << " / " << methods[m] << "\n";
      for (const Row& r : kind.rows)
        if (r.scene == scene && r.method == methods[m])
          d << r.ms << " " << std::max(r.err[0], 1e-6) << " \"" << r.setting << "\"\n";
      d << "\n\n";
      g << (m ? ", \\\n    " : " ") << "'" << dat.filename().string() << "' index " << block++
        << " using 1:2 with linespoints pt " << (m + 5) << " title \"" << Escape(methods[m]) << "\"";
    }
    g << "\n";
  }
  g << "unset multiplot\n";
  d.close();
  g.close();
  if (!have_gnuplot) return false;
  const std::string command = "cd '" + dir.string() + "' && gnuplot '" + gp.filename().string() + "'";
  return std::system(command.c_str()) == 0 && fs::exists(png);
}

std::string CpuModel() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("model name", 0) == 0) return line.substr(line.find(':') + 2);
  return "unknown";
}

struct Machine {
  std::string cpu, gl_renderer, gl_version, date, command;
  unsigned threads = 0;
};

void WriteReport(const fs::path& md, const std::string& plot_dir_name, const std::vector<Kind>& kinds,
                 const std::vector<TargetRow>& target_rows, const std::vector<TargetCheck>& target_checks,
                 const Machine& machine, const RunSizes& plan, bool plotted, double total_s) {
  std::ofstream o(md);
  o << "# The published trade: accuracy against time\n\n"
    << "Every number and plot on this page was measured by one run of `visq_bench_accuracy_trade` "
       "(tests/bench/accuracy_trade.cpp); nothing here is typed by hand. To regenerate this page and its plots, "
       "run `./visq.sh accuracy` from the checkout (as root on Debian 12). It installs what is missing (gnuplot "
       "included), builds the benchmark in Release and runs it. It writes `docs/accuracy.md` and "
       "`docs/accuracy/*.png`, and beside the plots their data (`.dat`) and gnuplot scripts (`.gp`). "
       "On a 2-core machine the full run takes about "
    << Fmt("%.0f", total_s / 60) << " minutes. `visq_bench_accuracy_trade --quick --out DIR` is the ctest "
       "smoke test (`accuracy_trade_quick`).\n\n"
    << "For each query kind, the accuracy parameters are swept and each setting's answer is compared with an exact "
       "or converged reference on the same inputs, in the same run:\n\n"
    << "- **hidden-sample map**: the exact visible fraction of the source patch at every receiver texel centre, "
       "from the Plücker-space BSP (`lib/exact`, the `LightVisibility` algorithm) with the patch as an area light "
       "facing the receiver. Also Embree on the very same segments (bits that differ).\n"
    << "- **patch visibility**: the same exact fractions, averaged (the exact mutual visible fraction).\n"
    << "- **obscurances**: the Embree estimator with many rays per patch, with another seed. On this machine a "
       "converged GPU bake does not fit in the run.\n"
    << "- **voxelization**: the CPU reference voxelizer (`lib/voxel_reference`, exact triangle-box tests) on the "
       "same grid.\n"
    << "- **volumetric shadows**: ray marching on a " << plan.reference_map << "² shadow map.\n\n";

  // Machine.
  o << "## Machine\n\n"
    << "| | |\n|---|---|\n"
    << "| CPU | " << machine.cpu << ", " << machine.threads << " hardware threads |\n"
    << "| GL renderer | " << machine.gl_renderer << " |\n"
    << "| GL version | " << machine.gl_version << " |\n"
    << "| date (UTC) | " << machine.date << " |\n"
    << "| command | `" << machine.command << "` |\n"
    << "| run time | " << Fmt("%.0f", total_s) << " s |\n\n"
    << "These figures come from a machine without a GPU: OpenGL is Mesa llvmpipe, a rasterizer that runs on the "
       "CPU. There, the GPU methods (RASTER, depth peeling, slicemap, volumetric) share the same cores as Embree, "
       "so the comparison favours the CPU methods far more than it would on a GPU. The errors do not depend on "
       "the machine, but the times do.\n\n"
    << "Time is the wall clock of the in-process call (the library entry that the server's RPC calls, without "
       "gRPC), after one warm-up call with the same parameters. The warm-up compiles the shader programs, builds "
       "and caches the Hough tables, and makes the scene resident on the GPU. The Embree BVH is built before any "
       "run. Each time is the median of up to "
    << plan.repeats << " runs, with fewer runs once they have taken 1.5 s (see the `runs` column). Sponza gets "
       "the full sweep. The other scenes get fewer settings, which keeps the run near 20 minutes; on llvmpipe a "
       "single rasterization pass over veach-ajar's 383K triangles takes seconds.\n\n";

  // Summary.
  o << "## Summary: the cheapest setting within 1 % on Sponza\n\n"
    << "Per query kind, the fastest measured setting on Sponza whose headline error (first error column of the "
       "kind's table) is at most "
    << Num(kTarget, true) << ".\n\n"
    << "| query kind | headline error | cheapest setting reaching 1 % | time (ms) | its error |\n"
    << "|---|---|---|---:|---:|\n";
  for (const Kind& kind : kinds) {
    const Row* best = nullptr;
    const Row* most_accurate = nullptr;
    for (const Row& r : kind.rows) {
      if (r.scene != "sponza") continue;
      if (std::isfinite(r.err[0]) && (!most_accurate || r.err[0] < most_accurate->err[0])) most_accurate = &r;
      if (r.err[0] <= kTarget && (!best || r.ms < best->ms)) best = &r;
    }
    o << "| " << kind.title << " | " << Cell(kind.error_labels[0]) << " | ";
    if (best)
      o << best->method << ", " << best->setting << " | " << Num(best->ms) << " | " << Num(best->err[0], true) << " |\n";
    else if (most_accurate)
      o << "none reached 1 % (best: " << most_accurate->method << ", " << most_accurate->setting << ") | "
        << Num(most_accurate->ms) << " | " << Num(most_accurate->err[0], true) << " |\n";
    else
      o << "Sponza not in this run | – | – |\n";
  }
  o << "\n";
  if (!plotted)
    o << "**No plots in this run**: gnuplot was not found (or failed), so only the tables were written. Install "
         "`gnuplot-nox` (`deploy/install-deps.sh` lists it) and run the command again.\n\n";

  // Accuracy targets.
  if (!target_rows.empty()) {
    o << "## Accuracy targets: predicted against measured\n\n"
      << "A hidden-sample map asked by error (`target.max_error` at 95 %) on each scene's placement below, "
         "through the server's core (its planner and cost model, without gRPC), starting with an empty cost "
         "model. The 1st call probes each method on this scene, then chooses; the 2nd call of the same target "
         "predicts from what the 1st measured. `direct` rows run every other method's cheapest plan meeting the "
         "target as a plain request, to check the choice. Times are compute (the GL job or the CPU work, Hough "
         "table included), as the cost model sees them; the 1st call of a plan also pays its cold caches "
         "(exact trees, Hough tables). A ratio is measured / predicted.\n\n"
      << "| scene | target | call | plan | predicted (ms) | measured (ms) | measured / predicted |\n"
      << "|---|---:|---|---|---:|---:|---:|\n";
    for (const TargetRow& r : target_rows)
      o << "| " << r.scene << " | ±" << Fmt("%.3g", r.max_error) << " | " << r.call << " | " << Cell(r.plan)
        << (r.chosen ? " (chosen)" : "") << " | " << Num(r.predicted_ms) << " | " << Num(r.measured_ms) << " | "
        << (std::isfinite(r.measured_ms) && r.predicted_ms > 0 ? Fmt("%.2f", r.measured_ms / r.predicted_ms) : "–")
        << " |\n";
    o << "\nThe choice against what the candidates then measured (the goal: the chosen plan within 2x of the "
         "cheapest measured):\n\n"
      << "| scene | target | chosen | its time (ms) | cheapest measured | its time (ms) | chosen / cheapest |\n"
      << "|---|---:|---|---:|---|---:|---:|\n";
    for (const TargetCheck& t : target_checks)
      o << "| " << t.scene << " | ±" << Fmt("%.3g", t.max_error) << " | " << Cell(t.chosen) << " | "
        << Num(t.chosen_ms) << " | " << Cell(t.cheapest) << " | " << Num(t.cheapest_ms) << " | "
        << Fmt("%.2f", t.chosen_ms / std::max(t.cheapest_ms, 1e-9)) << " |\n";
    o << "\n";
  }

  // Error against N: the hidden-sample map's sample counts, Embree casting
  // the segments (RASTER EXACT gives the same bits), per scene.
  for (const Kind& kind : kinds) {
    if (kind.key != "hidden_sample_map") continue;
    const std::vector<std::string> scenes = Unique(kind.rows, &Row::scene);
    std::vector<std::string> settings;
    for (const Row& r : kind.rows)
      if (r.method == "RAYCAST (Embree)" && std::find(settings.begin(), settings.end(), r.setting) == settings.end())
        settings.push_back(r.setting);
    if (settings.empty() || scenes.empty()) continue;
    o << "## Hidden-sample map: error against N\n\n"
      << "The mean |visible fraction − exact| over the receiver texels (and its 95th percentile) against the number "
         "of source samples N, with RAYCAST (Embree casting the segments; RASTER EXACT gives the same bits), per "
         "scene. Jittered samples, stratified for every N. The last row is the slope of log error against log N "
         "(least squares over the rows): −0.5 is the 1/√N of independent samples; stratification can fall "
         "faster.\n\n| N";
    for (const std::string& scene : scenes) o << " | " << scene << " mean | p95";
    o << " |\n|---";
    for (size_t i = 0; i < scenes.size(); ++i) o << "|---:|---:";
    o << "|\n";
    for (const std::string& setting : settings) {
      o << "| " << (setting.rfind("N=", 0) == 0 ? setting.substr(2) : setting);
      for (const std::string& scene : scenes) {
        const Row* found = nullptr;
        for (const Row& r : kind.rows)
          if (r.scene == scene && r.method == "RAYCAST (Embree)" && r.setting == setting) found = &r;
        if (found) o << " | " << Num(found->err[0], true) << " | " << Num(found->err[1], true);
        else o << " | – | –";
      }
      o << " |\n";
    }
    o << "| slope";
    for (const std::string& scene : scenes)
      for (int column = 0; column < 2; ++column) {
        double sx = 0, sy = 0, sxx = 0, sxy = 0;
        int n = 0;
        for (const Row& r : kind.rows) {
          if (r.scene != scene || r.method != "RAYCAST (Embree)" || !(r.err[column] > 0)) continue;
          const double x = std::log(std::atof(r.setting.c_str() + 2)), y = std::log(r.err[column]);
          sx += x;
          sy += y;
          sxx += x * x;
          sxy += x * y;
          ++n;
        }
        const double denominator = n * sxx - sx * sx;
        o << " | " << (n >= 2 && denominator > 0 ? Fmt("%.2f", (n * sxy - sx * sy) / denominator) : "–");
      }
    o << " |\n\n";
  }

  // Per kind.
  for (const Kind& kind : kinds) {
    o << "## " << kind.title << "\n\n" << kind.definition << "\n\n";
    for (const std::string& note : kind.notes) o << "- " << note << "\n";
    if (!kind.notes.empty()) o << "\n";
    if (plotted) o << "![" << kind.title << ": error against time](" << plot_dir_name << "/" << kind.key << ".png)\n\n";
    for (const std::string& scene : Unique(kind.rows, &Row::scene)) {
      o << "### " << scene << "\n\n| method | setting | time (ms) | runs";
      for (const std::string& label : kind.error_labels) o << " | " << Cell(label);
      o << " | note |\n|---|---|---:|---:|---:|---:|---:|---:|---|\n";
      for (const Row& r : kind.rows) {
        if (r.scene != scene) continue;
        o << "| " << r.method << " | " << r.setting << " | " << Num(r.ms) << " | " << r.runs;
        for (int i = 0; i < 4; ++i) {
          o << " | " << Num(r.err[i], true);
        }
        o << " | " << r.note << " |\n";
      }
      o << "\n";
    }
  }
}

// --quick's check: every output exists and is not empty, every figure of
// every row is finite where it should be.
bool CheckOutputs(const fs::path& md, const fs::path& plots, const std::vector<Kind>& kinds, bool plotted) {
  bool ok = true;
  auto need = [&](const fs::path& p) {
    if (!fs::exists(p) || fs::file_size(p) == 0) {
      std::fprintf(stderr, "check: %s missing or empty\n", p.c_str());
      ok = false;
    }
  };
  need(md);
  for (const Kind& kind : kinds) {
    need(plots / (kind.key + ".dat"));
    need(plots / (kind.key + ".gp"));
    if (plotted) need(plots / (kind.key + ".png"));
    if (kind.rows.empty()) {
      std::fprintf(stderr, "check: %s has no rows\n", kind.key.c_str());
      ok = false;
    }
    for (const Row& r : kind.rows)
      if (!std::isfinite(r.ms) || r.ms < 0 || !std::isfinite(r.err[0]) || !std::isfinite(r.err[1])) {
        std::fprintf(stderr, "check: %s %s %s %s: non-finite figure\n", kind.key.c_str(), r.scene.c_str(),
                     r.method.c_str(), r.setting.c_str());
        ok = false;
      }
  }
  std::ifstream in(md);
  std::stringstream text;
  text << in.rdbuf();
  // A printed non-finite number is the word "nan" or "inf" standing alone.
  const std::string& t = text.str();
  bool non_finite = false;
  for (const char* word : {"nan", "inf"})
    for (size_t at = t.find(word); at != std::string::npos && !non_finite; at = t.find(word, at + 1))
      non_finite = (at == 0 || !std::isalpha(static_cast<unsigned char>(t[at - 1]))) &&
                   (at + 3 >= t.size() || !std::isalpha(static_cast<unsigned char>(t[at + 3])));
  if (non_finite) {
    std::fprintf(stderr, "check: %s contains a non-finite number\n", md.c_str());
    ok = false;
  }
  return ok;
}

}  // namespace

int main(int argc, char** argv) {
  RunSizes plan;
  fs::path scenes_dir = "../shared/scenes", out_dir = "docs";
  std::string md_name = "accuracy.md", command, only, kinds_filter;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--quick") plan.quick = true;
    else if (a == "--scenes" && i + 1 < argc) scenes_dir = argv[++i];
    else if (a == "--out" && i + 1 < argc) out_dir = argv[++i];
    else if (a == "--md" && i + 1 < argc) md_name = argv[++i];
    else if (a == "--repeats" && i + 1 < argc) plan.repeats = std::max(1, std::atoi(argv[++i]));
    else if (a == "--command" && i + 1 < argc) command = argv[++i];
    else if (a == "--only" && i + 1 < argc) only = argv[++i];
    else if (a == "--kinds" && i + 1 < argc) kinds_filter = argv[++i];
    else {
      std::fprintf(stderr,
                   "usage: %s [--quick] [--scenes DIR] [--out DIR] [--md NAME] [--repeats N] [--command TEXT] "
                   "[--only SCENE] [--kinds KEY,...]\n",
                   argv[0]);
      return 2;
    }
  }
  if (command.empty()) {
    for (int i = 0; i < argc; ++i) command += (i ? " " : "") + std::string(argv[i]);
  }
  if (plan.quick) {
    plan.receiver = 16;
    plan.counts = {32, 256};
    plan.hough = {64};
    plan.source_grids = {4, 16};
    plan.atlas = 32;
    plan.directions = {4, 16};
    plan.reference_rays = 256;
    plan.rays_per_patch = {4, 16};
    plan.voxel_sizes = {16, 32};
    plan.image_w = 64;
    plan.image_h = 48;
    plan.shadow_maps = {64, 256};
    plan.reference_map = 1024;
    plan.repeats = std::min(plan.repeats, 2);
  }

  // The scenes; --quick: the Cornell box only.
  std::vector<SceneCase> cases;
  if (!plan.quick) {
    cases.push_back({"sponza", scenes_dir / "sponza_dabrovic/sponza.gltf", {}, {}, {}, {}});
    cases.push_back({"veach-ajar", scenes_dir / "interior_veach_ajar/veach_ajar.gltf", {}, {}, {}, {}});
    cases.push_back({"tree", scenes_dir / "tree_kenney/tree_detailed.glb", {}, {}, {}, {}});
  }
  cases.push_back({"cornell", scenes_dir / "cornell_box/cornell_box.gltf", {}, {}, {}, {}});
  if (!fs::is_directory(scenes_dir) || !fs::exists(cases.front().path)) {
    std::printf("SKIP: the shared scenes are absent (%s); nothing to measure\n", scenes_dir.c_str());
    return kSkipped;
  }

  const auto start = Clock::now();
  auto worker_or = gpu::GpuWorker::Start({});
  if (!worker_or.ok()) Fail("GL context", worker_or.status());
  gpu::GpuWorker& worker = **worker_or;
  auto mapper = Must(gpu::HiddenSampleMapper::Create(worker), "hidden-sample mapper");
  Machine machine;
  machine.cpu = CpuModel();
  machine.threads = std::max(1u, std::thread::hardware_concurrency());
  machine.gl_renderer = worker.device().gl_renderer;
  machine.gl_version = worker.device().gl_version;
  machine.command = command;
  {
    const std::time_t now = std::time(nullptr);
    char buf[64];
    std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M", std::gmtime(&now));
    machine.date = buf;
  }
  std::printf("device: %s | %s; CPU %s\n", machine.gl_renderer.c_str(), machine.gl_version.c_str(),
              machine.cpu.c_str());

  // The core for the accuracy targets: a scratch repository that the
  // scenes are written into, and a cost model that starts empty.
  const fs::path target_repo =
      fs::temp_directory_path() / ("visq-accuracy-targets-" + std::to_string(static_cast<long>(::getpid())));
  fs::create_directories(target_repo);
  core::EngineOptions engine_options;
  engine_options.scene_repo = target_repo;
  engine_options.cost_model_file = "-";
  engine_options.load_repository_at_start = false;
  auto engine = Must(core::Engine::Create(engine_options), "engine");
  std::vector<TargetRow> target_rows;
  std::vector<TargetCheck> target_checks;

  std::vector<Kind> kinds(5);
  Kind& hsm = kinds[0];
  Kind& patch = kinds[1];
  Kind& obsc = kinds[2];
  Kind& voxel = kinds[3];
  Kind& vol = kinds[4];
  hsm = {"hidden_sample_map",
         "Hidden-sample map",
         {"mean abs. error", "p95", "max", "bits ≠ Embree"},
         "Error: |visible fraction − exact| over the " + std::to_string(plan.receiver) + "² receiver texels "
         "(mean, 95th percentile, max), in units of the whole light. `bits ≠ Embree` is the fraction of "
         "(texel, sample) bits that differ from Embree casting the same segments. RASTER EXACT should be 0 up to "
         "float ties, and HOUGH is conservative. Jittered source samples, seed 1. N is the number of source samples. "
         "For HOUGH, hN is the Hough table's θ and r resolution.",
         {}, {}};
  patch = {"patch_visibility",
           "Patch visibility",
           {"mutual fraction abs. error", "per-sample mean", "per-sample p95", "per-sample max"},
           "Error: |mutual visible fraction − exact mutual fraction|, where the exact mutual fraction is the mean of "
           "the exact per-receiver-sample fractions. The receiver grid is the hidden-sample map's " +
               std::to_string(plan.receiver) + "² texels. The per-sample columns compare each receiver sample's "
               "fraction with its exact value. The source grid (regular, cell centres) is swept. HOUGH uses the "
               "default 256² Hough table.",
           {}, {}};
  obsc = {"obscurances",
          "Obscurances",
          {"mean |W − W_ref|", "p95", "max", "RMS"},
          "Error: |W − W_ref| over the atlas texels that both estimate (W in [0, 1], gray, no colour bleeding). "
          "The reference is itself a Monte Carlo estimate (see below), so the error of the largest settings includes some "
          "of the reference's own noise. The GPU bake (depth peeling, one orthographic bundle per direction) "
          "sweeps the number of directions. The Embree path (`obscurance/obscurance_rays`, the estimator that "
          "UpdateObscurances uses) sweeps the number of rays per patch.",
          {}, {}};
  voxel = {"voxelization",
           "Voxelization",
           {"differing voxels / reference", "missing / reference", "extra / reference", "standard: ≠ column-centre ref."},
           "Error: the number of voxels that differ from the CPU reference (exact triangle-box overlap) on the "
           "same grid, divided by the reference's occupied voxels. Surface mode, uniform slices, depth along y, "
           "over the scene's bounds. The grid is n × n × n. There is no finer-reference column: at a given grid, "
           "the CPU reference is the exact answer for that grid's voxels. A finer reference would measure the "
           "grid's own resolution, not the slicemap's error. A standard rasterization takes one sample per texel "
           "centre. It therefore misses every voxel that a triangle touches away from the column centres, and "
           "triangles seen edge-on. Its last column compares it with the CPU's column-centre sampling "
           "(`SampleColumnCenters`), which is the standard mode's own definition.",
           {}, {}};
  vol = {"volumetric_shadows",
         "Volumetric shadows",
         {"rel. RMS error", "rel. mean error", "rel. p95 error", "max error / peak"},
         "Error: in-scattered radiance against the reference image, pixel by pixel (RGB). The relative RMS, mean "
         "and p95 errors are divided by the reference's mean radiance; the max error is divided by its peak. The "
         "shadow-map size is swept for both methods. MIN_MAX is the 1D min-max mipmap traversal; RAY_MARCHING "
         "runs on the same rectified map.",
         {}, {}};

  for (SceneCase& c : cases) {
    const auto t_scene = Clock::now();
    if (!only.empty() && c.name != only) continue;
    if (!Prepare(c)) continue;
    std::printf("%s: %zu triangles\n", c.name.c_str(), c.scene.TriangleCount());
    std::fflush(stdout);
    auto gpu_scene = Must(gpu::GpuScene::Upload(worker, c.scene), c.name + ": upload");
    auto embree = Must(raycast::EmbreeScene::Create(c.scene), c.name + ": embree");

    // Visibility sampling, with the exact reference shared by both kinds.
    const ExactReference ref = ExactFractions(c, plan.receiver, plan.receiver);
    const std::string inputs = c.name + ": source " + PatchText(c.source) + ", receiver " + PatchText(c.receiver) +
                               " (origin; edge u; edge v). Exact reference: " + Fmt("%.0f", ref.ms) +
                               " ms for the " + std::to_string(ref.fraction.size()) +
                               " texels (Plücker BSP, " + std::to_string(ref.cells) +
                               " receiver cells of 1/32 of the scene, 16 MiB trees, tree building included). "
                               "Mean exact visible fraction " +
                               Fmt("%.3f", ref.mean) + ", " + std::to_string(ref.penumbra) +
                               " texels in penumbra (0 < fraction < 1).";
    std::printf("  exact reference: %.0f ms, mean %.3f, penumbra %zu / %zu\n", ref.ms, ref.mean, ref.penumbra,
                ref.fraction.size());
    std::fflush(stdout);
    hsm.notes.push_back(inputs);
    patch.notes.push_back(inputs);
    auto wanted = [&](const Kind& kind) {
      return kinds_filter.empty() || kinds_filter.find(kind.key) != std::string::npos;
    };
    if (wanted(hsm)) SweepHiddenSampleMap(plan, c, *mapper, *gpu_scene, embree, ref, hsm);
    if (wanted(patch)) SweepPatchVisibility(plan, c, *mapper, *gpu_scene, embree, ref, patch);
    if (wanted(obsc)) SweepObscurances(plan, c, worker, *gpu_scene, obsc);
    if (wanted(voxel)) SweepVoxelization(plan, c, worker, *gpu_scene, voxel);
    if (wanted(vol)) SweepVolumetric(plan, c, worker, *gpu_scene, vol);
    if (kinds_filter.empty() || kinds_filter.find("targets") != std::string::npos) {
      std::string stored = c.name;
      std::replace(stored.begin(), stored.end(), '-', '_');
      const Status written = WriteGltfFile(c.scene, target_repo / (stored + ".glb"));
      if (!written.ok()) Fail(c.name + ": writing the scene for the core", written);
      MeasureTargets(plan, c, *engine, stored, target_rows, target_checks);
    }
    std::printf("%s: %.0f s\n", c.name.c_str(), MsSince(t_scene) / 1000);
    std::fflush(stdout);
  }

  // Outputs.
  const fs::path plot_dir = out_dir / "accuracy";
  fs::create_directories(plot_dir);
  const bool have_gnuplot = std::system("command -v gnuplot > /dev/null 2>&1") == 0;
  if (!have_gnuplot)
    std::printf("WARNING: gnuplot not found: writing the tables and the plot scripts, but no PNG. Install "
                "gnuplot-nox (deploy/install-deps.sh) and rerun for the plots.\n");
  bool plotted = have_gnuplot;
  for (const Kind& kind : kinds) plotted = Plot(kind, plot_dir, have_gnuplot) && plotted;
  if (have_gnuplot && !plotted) std::printf("WARNING: gnuplot failed on some plot; see the messages above\n");
  const double total_s = MsSince(start) / 1000;
  const fs::path md = out_dir / md_name;
  WriteReport(md, "accuracy", kinds, target_rows, target_checks, machine, plan, plotted, total_s);
  engine.reset();
  std::error_code ec;
  fs::remove_all(target_repo, ec);
  std::printf("wrote %s and %s/*.png in %.0f s\n", md.c_str(), plot_dir.c_str(), total_s);
  if (plan.quick && !CheckOutputs(md, plot_dir, kinds, plotted)) return 1;
  return 0;
}
