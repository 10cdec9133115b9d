// Slicemap voxelization (gpu/slicemap) against the CPU reference
// (lib/voxel_reference): exact triangle-box overlap for surfaces, Embree
// ray parity for solids, the analytic chord for transmittance.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <map>
#include <thread>

#include <gtest/gtest.h>

#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "gpu_test_support.h"
#include "test_support.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/slicemap.h"
#include "voxel_reference/voxel_reference.h"

namespace visq {
namespace {

using gpu::Rasterization;
using gpu::SlicePrecision;
using gpu::VoxelizeMode;
using gpu::VoxelizeParams;

// A closed, outward-facing icosphere; coordinates snapped to multiples of
// 2^-20 so that translating by 1e6 is exact in double.
Scene MakeSphere(const glm::dvec3& center, double radius, int subdivisions) {
  std::vector<glm::dvec3> v;
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  for (auto p : {glm::dvec3(-1, t, 0), glm::dvec3(1, t, 0), glm::dvec3(-1, -t, 0), glm::dvec3(1, -t, 0),
                 glm::dvec3(0, -1, t), glm::dvec3(0, 1, t), glm::dvec3(0, -1, -t), glm::dvec3(0, 1, -t),
                 glm::dvec3(t, 0, -1), glm::dvec3(t, 0, 1), glm::dvec3(-t, 0, -1), glm::dvec3(-t, 0, 1)})
    v.push_back(glm::normalize(p));
  std::vector<glm::uvec3> f = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
                               {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
                               {3, 8, 9},  {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
  for (int s = 0; s < subdivisions; ++s) {
    std::map<std::pair<uint32_t, uint32_t>, uint32_t> mid;
    auto midpoint = [&](uint32_t a, uint32_t b) {
      auto key = std::minmax(a, b);
      auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      v.push_back(glm::normalize(v[a] + v[b]));
      return mid[key] = static_cast<uint32_t>(v.size() - 1);
    };
    std::vector<glm::uvec3> next;
    for (const auto& tri : f) {
      const uint32_t a = midpoint(tri[0], tri[1]), b = midpoint(tri[1], tri[2]), c = midpoint(tri[2], tri[0]);
      next.insert(next.end(), {{tri[0], a, c}, {tri[1], b, a}, {tri[2], c, b}, {a, b, c}});
    }
    f = std::move(next);
  }
  Scene scene;
  const double q = std::ldexp(1.0, 20);
  for (const auto& p : v) scene.positions.push_back(glm::round((center + radius * p) * q) / q);
  scene.triangles = f;
  scene.nodes.push_back(SceneNode{"sphere", 0, -1, glm::dmat4(1.0), 0, static_cast<uint32_t>(f.size())});
  scene.triangle_node.assign(f.size(), 0);
  scene.triangle_material.assign(f.size(), 0);
  scene.materials.push_back(Material{"white", glm::dvec3(1.0), glm::dvec3(0.0)});
  UpdateBounds(scene);
  return scene;
}

voxel_reference::GridBox ToReference(const voxel_reference::OrientedBox& box, uint32_t w, uint32_t h, uint32_t s) {
  return {box, w, h, s};
}

// |a & ~b| over two packed grids of the same shape.
uint64_t CountOnlyIn(const std::vector<uint32_t>& a, const std::vector<uint32_t>& b) {
  uint64_t n = 0;
  for (size_t i = 0; i < a.size(); ++i) n += std::popcount(a[i] & ~b[i]);
  return n;
}
uint64_t CountAll(const std::vector<uint32_t>& a) { return CountOnlyIn(a, std::vector<uint32_t>(a.size(), 0u)); }
uint64_t CountOnlyInOutside(const std::vector<uint32_t>& a, const std::vector<uint32_t>& b,
                            const std::vector<uint32_t>& mask) {
  uint64_t n = 0;
  for (size_t i = 0; i < a.size(); ++i) n += std::popcount(a[i] & ~b[i] & ~mask[i]);
  return n;
}

struct Uploaded {
  Scene scene;
  std::shared_ptr<gpu::GpuScene> gpu;
};
Uploaded Upload(Scene scene) {
  auto uploaded = gpu::GpuScene::Upload(testing::SharedGpuWorker(), scene);
  EXPECT_TRUE(uploaded.ok()) << uploaded.status();
  return {std::move(scene), uploaded.ok() ? *uploaded : nullptr};
}

gpu::VoxelizeResult MustVoxelize(const Uploaded& s, const VoxelizeParams& params) {
  auto result = gpu::Voxelize(testing::SharedGpuWorker(), *s.gpu, params);
  EXPECT_TRUE(result.ok()) << result.status();
  return result.ok() ? std::move(*result) : gpu::VoxelizeResult{};
}

VoxelizeParams Params(const Scene& scene, int axis, uint32_t w, uint32_t h, uint32_t s) {
  VoxelizeParams p;
  p.box = gpu::AxisAlignedSlicemapBox(scene.bounds, axis, 1e-3 * glm::length(scene.bounds.Extent()));
  p.width = w;
  p.height = h;
  p.slices = s;
  return p;
}

// Standard rasterization against the exact grid: the GPU sees (almost) only
// voxels the reference has, and what it misses is what center sampling
// cannot see (voxels touched only by triangles that miss the column center
// at that depth: edge-on and thin triangles).
//
// Centers within kRoundingMargin of an edge, and depths within it of a
// slice boundary, may fall either side: GPUs snap vertices to 1/256 of a
// pixel (an H200 missed 24 voxels of the 64^3 sphere that exact center
// sampling has, all at such places), so the reference counts only what every
// rasterizer must see.
constexpr double kRoundingMargin = 1.0 / 32.0;
void CheckStandardSurface(const Uploaded& s, const VoxelizeParams& params, const char* label) {
  const gpu::VoxelizeResult gpu_result = MustVoxelize(s, params);
  ASSERT_EQ(gpu_result.rasterization, Rasterization::kStandard);
  const auto box = ToReference(params.box, params.width, params.height, params.slices);
  voxel_reference::SurfaceOptions options;
  options.column_near = gpu_result.column_near;
  options.column_far = gpu_result.column_far;
  auto exact = voxel_reference::VoxelizeSurface(s.scene, box, options);
  ASSERT_TRUE(exact.ok()) << exact.status();
  auto sampled = voxel_reference::SampleColumnCenters(s.scene, box, options, kRoundingMargin);
  ASSERT_TRUE(sampled.ok()) << sampled.status();
  const auto& g = gpu_result.grid.bits;
  const uint64_t occupied = CountAll(g), reference = exact->CountOccupied();
  const uint64_t extra = CountOnlyIn(g, exact->bits);
  const uint64_t missed = CountOnlyIn(exact->bits, g);
  // Missed voxels that center sampling should have seen: only rounding at
  // edges and slice boundaries may produce these.
  std::vector<uint32_t> missed_bits(g.size());
  for (size_t i = 0; i < g.size(); ++i) missed_bits[i] = exact->bits[i] & ~g[i];
  const uint64_t unexplained = CountOnlyIn(missed_bits, std::vector<uint32_t>(g.size(), 0u)) -
                               CountOnlyIn(missed_bits, sampled->bits);
  std::printf("[%s] gpu %llu, reference %llu, gpu-only %llu, missed %llu (of which seen by center sampling %llu)\n",
              label, (unsigned long long)occupied, (unsigned long long)reference, (unsigned long long)extra,
              (unsigned long long)missed, (unsigned long long)unexplained);
  EXPECT_GT(occupied, 0u);
  EXPECT_EQ(gpu_result.occupied_voxels, occupied);
  EXPECT_LE(extra, occupied / 1000 + 2) << label;
  EXPECT_LE(unexplained, reference / 10000 + 2) << label;
}

// Conservative mode must contain the exact grid.
void CheckConservativeSurface(const Uploaded& s, VoxelizeParams params, const char* label) {
  params.rasterization = Rasterization::kConservative;
  const gpu::VoxelizeResult gpu_result = MustVoxelize(s, params);
  ASSERT_EQ(gpu_result.rasterization, Rasterization::kConservative);
  const auto box = ToReference(params.box, params.width, params.height, params.slices);
  voxel_reference::SurfaceOptions options;
  options.column_near = gpu_result.column_near;
  options.column_far = gpu_result.column_far;
  voxel_reference::SurfaceStats stats;
  auto exact = voxel_reference::VoxelizeSurface(s.scene, box, options, &stats);
  ASSERT_TRUE(exact.ok()) << exact.status();
  const auto& g = gpu_result.grid.bits;
  const uint64_t missing = CountOnlyIn(exact->bits, g), extra = CountOnlyIn(g, exact->bits);
  std::printf("[%s] conservative gpu %llu voxels, reference %llu, missing %llu, extra %llu (%.3f%%)\n", label,
              (unsigned long long)CountAll(g), (unsigned long long)exact->CountOccupied(),
              (unsigned long long)missing, (unsigned long long)extra,
              100.0 * static_cast<double>(extra) / std::max<double>(1, exact->CountOccupied()));
  EXPECT_GT(exact->CountOccupied(), 0u);
  EXPECT_EQ(missing, 0u) << label;
  if (missing != 0 && std::getenv("VISQ_DEBUG_MISSING") != nullptr) {  // lists them
    for (uint32_t y = 0; y < params.height; ++y)
      for (uint32_t x = 0; x < params.width; ++x)
        for (uint32_t k = 0; k < params.slices; ++k)
          if (exact->Get(x, y, k) && !gpu_result.grid.Get(x, y, k)) std::printf("  missing %u %u %u\n", x, y, k);
  }
  EXPECT_EQ(stats.touches_in_empty_columns, 0u) << label;
  // Extras come from the 1e-3 voxel slack only: a small fraction.
  EXPECT_LE(extra, exact->CountOccupied() / 20 + 2) << label;
}

const glm::dvec3 kSphereCenter(0.1234567, -0.2345678, 0.3456789);

TEST(SlicemapSurface, SphereStandardAgreesExceptWhereCenterSamplingIsBlind) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 3));
  for (int axis = 0; axis < 3; ++axis) CheckStandardSurface(s, Params(s.scene, axis, 64, 64, 64), "sphere 64^3");
  VoxelizeParams local = Params(s.scene, 2, 64, 64, 64);
  local.precision = SlicePrecision::kLocal;
  CheckStandardSurface(s, local, "sphere 64^3 local");
}

TEST(SlicemapSurface, SphereConservativeContainsReference) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 3));
  for (int axis = 0; axis < 3; ++axis) CheckConservativeSurface(s, Params(s.scene, axis, 64, 64, 64), "sphere");
  VoxelizeParams local = Params(s.scene, 1, 64, 48, 100);
  local.precision = SlicePrecision::kLocal;
  CheckConservativeSurface(s, local, "sphere local");
}

// Axis-aligned walls lying exactly on voxel boundaries and seen edge-on: the
// case the slides call "not watertight".
TEST(SlicemapSurface, EdgeOnWallsAreMissedByStandardAndKeptByConservative) {
  Scene scene;
  AddQuad(scene, "wall_x", glm::dvec3(0.25, 0, 0), glm::dvec3(0, 1, 0), glm::dvec3(0, 0, 1), 0);
  AddQuad(scene, "wall_y", glm::dvec3(0, 0.625, 0), glm::dvec3(0, 0, 1), glm::dvec3(1, 0, 0), 0);
  AddQuad(scene, "floor", glm::dvec3(0, 0, 0.5), glm::dvec3(1, 0, 0), glm::dvec3(0, 1, 0), 0);
  scene.materials.push_back(Material{"white", glm::dvec3(1.0), glm::dvec3(0.0)});
  UpdateBounds(scene);
  const Uploaded s = Upload(std::move(scene));
  VoxelizeParams params = Params(s.scene, 2, 32, 32, 32);
  params.box.center = glm::dvec3(0.5);
  params.box.half_extent = glm::dvec3(0.5);
  const auto standard = MustVoxelize(s, params);
  const auto box = ToReference(params.box, 32, 32, 32);
  auto exact = voxel_reference::VoxelizeSurface(s.scene, box);
  ASSERT_TRUE(exact.ok());
  // The two walls are seen edge-on along z: standard rasterization loses them.
  EXPECT_GT(CountOnlyIn(exact->bits, standard.grid.bits), 0u);
  CheckConservativeSurface(s, params, "edge-on walls");
}

TEST(SlicemapSurface, OrientedBoxConservativeContainsReference) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 2));
  VoxelizeParams params;
  const glm::dvec3 u = glm::normalize(glm::dvec3(1, 1, 0)), v = glm::normalize(glm::dvec3(-1, 1, 1));
  params.box.center = kSphereCenter + glm::dvec3(0.05, 0.0, -0.03);
  params.box.axis_u = u;
  params.box.axis_v = v;
  params.box.axis_w = glm::cross(u, v);
  params.box.half_extent = glm::dvec3(1.1, 0.9, 1.05);
  params.width = 40;
  params.height = 56;
  params.slices = 70;
  CheckConservativeSurface(s, params, "oriented box");
  CheckStandardSurface(s, params, "oriented box");
}

TEST(SlicemapSurface, MoreThan1024SlicesUseSeveralPasses) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 2));
  VoxelizeParams params = Params(s.scene, 2, 24, 24, 1100);
  params.rasterization = Rasterization::kConservative;
  const auto result = MustVoxelize(s, params);
  EXPECT_EQ(result.passes, 2u);
  CheckConservativeSurface(s, params, "1100 slices");
}

// A band's draw spread over GL jobs, a piece a job (as a pass over a large
// scene is on llvmpipe, so that other queries get the GL thread between its
// pieces), gives the bits of one draw: the sphere's 20,480 triangles are
// over the first piece of a 40 x 18 band (2^22 / 720 = 5,825 triangles).
TEST(SlicemapBands, ADrawSpreadOverGlJobsGivesTheBitsOfOneDraw) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 5));
  ASSERT_EQ(s.scene.TriangleCount(), 20480u);
  struct Case {
    VoxelizeMode mode;
    SlicePrecision precision;
    Rasterization rasterization;
  };
  for (const Case& c : {Case{VoxelizeMode::kSurface, SlicePrecision::kUniform, Rasterization::kConservative},
                        Case{VoxelizeMode::kSolid, SlicePrecision::kLocal, Rasterization::kStandard}}) {
    VoxelizeParams params = Params(s.scene, 2, 40, 36, 64);
    params.mode = c.mode;
    params.precision = c.precision;
    params.rasterization = c.rasterization;
    params.piece_target_ms = 0.0;  // one draw, one job
    const gpu::VoxelizeResult whole = MustVoxelize(s, params);
    params.max_columns_per_job = 40 * 18;
    params.piece_target_ms = 1e-6;
    params.draw_ms_per_job = 0.0;
    const gpu::VoxelizeResult over_jobs = MustVoxelize(s, params);
    SCOPED_TRACE(::testing::Message() << "mode " << int(c.mode) << ", precision " << int(c.precision));
    EXPECT_GT(whole.occupied_voxels, 0u);
    EXPECT_EQ(over_jobs.grid.bits, whole.grid.bits);
    EXPECT_EQ(over_jobs.column_near, whole.column_near);
    EXPECT_EQ(over_jobs.column_far, whole.column_far);
    EXPECT_EQ(over_jobs.passes, whole.passes);
    // 2 bands, each a draw of at least 4 pieces: 8 jobs at least beside
    // the targets' (and the depth-range pass's).
    EXPECT_GE(over_jobs.gl_jobs, whole.gl_jobs + 7) << "draws spread over jobs";
  }
}

// A standard fragment's depth is the triangle's plane at the image's texel
// centre, computed from the same corners in every band, so a band's viewport
// offset cannot move a depth across a slice boundary: the bits do not depend
// on how the server cut the grid into bands (which it does by its load).
// Before, 19 of 262,144 columns of this sphere differed by a slice between
// one band of 512 rows and bands of 64.
TEST(SlicemapBands, StandardDepthsDoNotDependOnTheBandsOnAFineSphere) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 5));
  for (const SlicePrecision precision : {SlicePrecision::kUniform, SlicePrecision::kLocal}) {
    for (const VoxelizeMode mode : {VoxelizeMode::kSurface, VoxelizeMode::kSolid}) {
      VoxelizeParams params = Params(s.scene, 2, 512, 512, 1024);
      params.precision = precision;
      params.mode = mode;
      params.piece_target_ms = 0.0;
      params.max_columns_per_job = 512 * 512;
      const gpu::VoxelizeResult whole = MustVoxelize(s, params);
      params.max_columns_per_job = 512 * 64;
      const gpu::VoxelizeResult banded = MustVoxelize(s, params);
      SCOPED_TRACE(::testing::Message() << "precision " << int(precision) << ", mode " << int(mode));
      ASSERT_EQ(banded.grid.bits.size(), whole.grid.bits.size());
      const uint32_t words = whole.grid.words_per_column;
      size_t columns_differing = 0;
      for (size_t c = 0; c < size_t{512} * 512; ++c)
        columns_differing += !std::equal(whole.grid.bits.begin() + c * words, whole.grid.bits.begin() + (c + 1) * words,
                                         banded.grid.bits.begin() + c * words);
      EXPECT_GT(whole.occupied_voxels, 0u);
      EXPECT_EQ(columns_differing, 0u) << "of 262,144 columns";
      EXPECT_EQ(banded.column_near, whole.column_near);
      EXPECT_EQ(banded.column_far, whole.column_far);
    }
  }
}

// While other calls' jobs wait for the GL thread and a band's pieces take
// over four times their target (here every piece), the next bands take half
// the rows, down to 4 (a small query then waits for a piece of a narrower
// band); bands of every size give the bits of one job.
TEST(SlicemapBands, BandsHalvedWhileOthersWaitGiveTheBitsOfOneJob) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 3));
  VoxelizeParams params = Params(s.scene, 2, 40, 144, 64);
  params.rasterization = Rasterization::kConservative;
  params.piece_target_ms = 0.0;  // one draw, one job
  const gpu::VoxelizeResult whole = MustVoxelize(s, params);
  ASSERT_GT(whole.occupied_voxels, 0u);
  params.max_columns_per_job = 40 * 36;
  params.piece_target_ms = 1e-6;
  gpu::GpuWorker& worker = testing::SharedGpuWorker();
  std::atomic<bool> voxelizing{true};
  std::thread other_call([&] {  // keeps a job of another caller queued
    while (voxelizing.load()) {
      if (worker.queue_depth() == 0) worker.Post([] {});
      std::this_thread::yield();
    }
  });
  std::vector<uint32_t> bits, band_rows;
  auto sink = [&](const gpu::VoxelizeResult&, const gpu::VoxelizeBand& band) -> Status {
    band_rows.push_back(static_cast<uint32_t>(band.bits.size() / (40 * whole.grid.words_per_column)));
    bits.insert(bits.end(), band.bits.begin(), band.bits.end());
    return absl::OkStatus();
  };
  const auto banded = gpu::Voxelize(worker, *s.gpu, params, sink);
  voxelizing = false;
  other_call.join();
  ASSERT_TRUE(banded.ok()) << banded.status();
  EXPECT_EQ(bits, whole.grid.bits);
  ASSERT_FALSE(band_rows.empty());
  EXPECT_EQ(band_rows.front(), 36u);
  EXPECT_LT(*std::min_element(band_rows.begin(), band_rows.end()), 36u) << "halved while others waited";
  EXPECT_GE(*std::min_element(band_rows.begin(), band_rows.end() - 1), 4u);
}

// Bands of image rows, each a GL job of its own (other queries run between
// them), give the bits of one job, in every mode: surface, solid with a
// conservative surface pass, local precision, and several slice passes.
TEST(SlicemapBands, BandsOfRowsGiveTheBitsOfOneJob) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 3));
  struct Case {
    VoxelizeMode mode;
    SlicePrecision precision;
    Rasterization rasterization;
    uint32_t slices;
  };
  for (const Case& c : {Case{VoxelizeMode::kSurface, SlicePrecision::kUniform, Rasterization::kStandard, 64},
                        Case{VoxelizeMode::kSolid, SlicePrecision::kUniform, Rasterization::kConservative, 600},
                        Case{VoxelizeMode::kSolid, SlicePrecision::kLocal, Rasterization::kStandard, 64},
                        Case{VoxelizeMode::kSurface, SlicePrecision::kUniform, Rasterization::kConservative, 1100}}) {
    VoxelizeParams params = Params(s.scene, 2, 40, 36, c.slices);
    params.mode = c.mode;
    params.precision = c.precision;
    params.rasterization = c.rasterization;
    // A draw a job, however long it takes on a loaded machine: this test
    // counts the bands' jobs (ADrawSpreadOverGlJobs... the draws').
    params.draw_ms_per_job = std::numeric_limits<double>::infinity();
    const gpu::VoxelizeResult whole = MustVoxelize(s, params);
    params.max_columns_per_job = 40 * 5;  // bands of 5 rows, the last of 1
    const gpu::VoxelizeResult banded = MustVoxelize(s, params);
    SCOPED_TRACE(::testing::Message() << "slices " << c.slices << ", mode " << int(c.mode));
    EXPECT_GT(whole.occupied_voxels, 0u);
    EXPECT_EQ(banded.grid.bits, whole.grid.bits);
    EXPECT_EQ(banded.column_near, whole.column_near);
    EXPECT_EQ(banded.passes, whole.passes) << "rasterizations of the scene, not bands";
    const uint32_t per_band = (c.mode == VoxelizeMode::kSolid && c.rasterization == Rasterization::kConservative) ? 2 : 1;
    const uint32_t slice_passes = (c.slices + (c.mode == VoxelizeMode::kSolid ? 511 : 1023)) /
                                  (c.mode == VoxelizeMode::kSolid ? 512 : 1024);
    // The targets, with local precision the depth-range pass, then the
    // passes: each draw here fits one job.
    const uint32_t setup_jobs = c.precision == SlicePrecision::kLocal ? 2 : 1;
    EXPECT_EQ(whole.gl_jobs, setup_jobs + slice_passes * per_band);
    EXPECT_EQ(banded.gl_jobs, setup_jobs + slice_passes * per_band * 8) << "36 rows in bands of 5";

    // Streamed: each band, whole in depth, goes to the sink as it is made,
    // and the bands are the grid; the result keeps the figures only.
    std::vector<uint32_t> bits;
    std::vector<float> near;
    int bands = 0;
    auto streamed = gpu::Voxelize(testing::SharedGpuWorker(), *s.gpu, params,
                                  [&](const gpu::VoxelizeResult& figures, const gpu::VoxelizeBand& band) {
                                    EXPECT_EQ(band.first * figures.grid.words_per_column, bits.size());
                                    bits.insert(bits.end(), band.bits.begin(), band.bits.end());
                                    near.insert(near.end(), band.column_near.begin(), band.column_near.end());
                                    ++bands;
                                    return absl::OkStatus();
                                  });
    ASSERT_TRUE(streamed.ok()) << streamed.status();
    EXPECT_EQ(bands, 8);
    EXPECT_EQ(bits, whole.grid.bits);
    EXPECT_EQ(near, whole.column_near);
    EXPECT_TRUE(streamed->grid.bits.empty());
    EXPECT_EQ(streamed->occupied_voxels, whole.occupied_voxels);
    EXPECT_EQ(streamed->ambiguous_columns, whole.ambiguous_columns);
    int calls = 0;
    auto stopped = gpu::Voxelize(testing::SharedGpuWorker(), *s.gpu, params,
                                 [&](const gpu::VoxelizeResult&, const gpu::VoxelizeBand&) {
                                   ++calls;
                                   return absl::CancelledError("the client went away");
                                 });
    EXPECT_EQ(stopped.status().code(), absl::StatusCode::kCancelled);
    EXPECT_EQ(calls, 1);
  }
}

TEST(SlicemapSurface, TranslatedBy1e6GivesTheSameGrid) {
  const Uploaded near_origin = Upload(MakeSphere(kSphereCenter, 1.0, 3));
  const Uploaded far = Upload(MakeSphere(kSphereCenter + glm::dvec3(1e6, -1e6, 1e6), 1.0, 3));
  for (Rasterization r : {Rasterization::kStandard, Rasterization::kConservative}) {
    for (VoxelizeMode m : {VoxelizeMode::kSurface, VoxelizeMode::kSolid}) {
      VoxelizeParams a = Params(near_origin.scene, 2, 64, 64, 64);
      VoxelizeParams b = Params(far.scene, 2, 64, 64, 64);
      a.rasterization = b.rasterization = r;
      a.mode = b.mode = m;
      const auto ra = MustVoxelize(near_origin, a), rb = MustVoxelize(far, b);
      EXPECT_GT(ra.occupied_voxels, 0u);
      EXPECT_EQ(ra.occupied_voxels, rb.occupied_voxels);
      EXPECT_TRUE(ra.grid.bits == rb.grid.bits) << "rasterization " << static_cast<int>(r) << " mode "
                                                << static_cast<int>(m);
    }
  }
}

// Solid voxelization of a closed mesh agrees with Embree parity everywhere
// except on the surface shell.
void CheckSolid(const Uploaded& s, VoxelizeParams params, const char* label, bool expect_closed) {
  params.mode = VoxelizeMode::kSolid;
  const auto result = MustVoxelize(s, params);
  const auto box = ToReference(params.box, params.width, params.height, params.slices);
  auto reference = voxel_reference::VoxelizeSolid(s.scene, box);
  ASSERT_TRUE(reference.ok()) << reference.status();
  // The shell: every voxel a surface touches (reference), plus the GPU's.
  std::vector<uint32_t> shell = reference->surface.bits;
  VoxelizeParams surface_params = params;
  surface_params.mode = VoxelizeMode::kSurface;
  const auto surface = MustVoxelize(s, surface_params);
  for (size_t i = 0; i < shell.size(); ++i) shell[i] |= surface.grid.bits[i];
  // Columns either side calls inconsistent are left out of the comparison.
  const uint32_t wpc = result.grid.words_per_column;
  uint64_t inconsistent = 0;
  for (size_t c = 0; c < reference->column_consistent.size(); ++c) {
    if (reference->column_consistent[c]) continue;
    ++inconsistent;
    for (uint32_t w = 0; w < wpc; ++w) shell[c * wpc + w] = ~0u;
  }
  for (uint32_t c : result.ambiguous_column_list)
    for (uint32_t w = 0; w < wpc; ++w) shell[size_t{c} * wpc + w] = ~0u;
  const uint64_t gpu_only = CountOnlyInOutside(result.grid.bits, reference->solid.bits, shell);
  const uint64_t ref_only = CountOnlyInOutside(reference->solid.bits, result.grid.bits, shell);
  std::printf("[%s] solid gpu %llu voxels, reference %llu; ambiguous columns gpu %llu (resolved %llu), reference "
              "inconsistent %llu; outside the shell: gpu-only %llu, reference-only %llu\n",
              label, (unsigned long long)result.occupied_voxels,
              (unsigned long long)reference->solid.CountOccupied(), (unsigned long long)result.ambiguous_columns,
              (unsigned long long)result.resolved_columns, (unsigned long long)inconsistent,
              (unsigned long long)gpu_only, (unsigned long long)ref_only);
  EXPECT_GT(reference->solid.CountOccupied(), reference->surface.CountOccupied()) << label;
  EXPECT_EQ(gpu_only, 0u) << label;
  EXPECT_EQ(ref_only, 0u) << label;
  if (expect_closed) {
    EXPECT_EQ(result.ambiguous_columns, 0u) << label;
    EXPECT_EQ(inconsistent, 0u) << label;
  }
}

TEST(SlicemapSolid, SphereAgreesWithEmbreeParityOutsideTheShell) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 3));
  for (int axis = 0; axis < 3; ++axis) CheckSolid(s, Params(s.scene, axis, 64, 64, 64), "sphere", true);
  VoxelizeParams conservative = Params(s.scene, 0, 48, 64, 80);
  conservative.rasterization = Rasterization::kConservative;
  CheckSolid(s, conservative, "sphere conservative", true);
  CheckSolid(s, Params(s.scene, 2, 32, 32, 600), "sphere 600 slices (2 passes)", true);
}

TEST(SlicemapSolid, TwoSeparateSpheresAndABox) {
  Scene scene = MakeSphere(kSphereCenter, 1.0, 3);
  const Scene second = MakeSphere(kSphereCenter + glm::dvec3(0.3, 0.2, 2.6), 0.7, 3);
  const uint32_t offset = static_cast<uint32_t>(scene.positions.size());
  scene.positions.insert(scene.positions.end(), second.positions.begin(), second.positions.end());
  for (auto t : second.triangles) scene.triangles.push_back(t + glm::uvec3(offset));
  scene.triangle_node.resize(scene.triangles.size(), 0);
  scene.triangle_material.resize(scene.triangles.size(), 0);
  AddBox(scene, "box", kSphereCenter + glm::dvec3(-0.9, -0.8, 4.0), kSphereCenter + glm::dvec3(0.7, 0.6, 4.4), 0);
  UpdateBounds(scene);
  const Uploaded s = Upload(std::move(scene));
  CheckSolid(s, Params(s.scene, 2, 64, 64, 96), "two spheres and a box, along z", true);
  CheckSolid(s, Params(s.scene, 1, 64, 96, 64), "two spheres and a box, along y", true);
}

TEST(SlicemapSolid, LocalPrecisionSphereMatchesTheAnalyticBall) {
  const double radius = 1.0;
  const Uploaded s = Upload(MakeSphere(kSphereCenter, radius, 4));
  VoxelizeParams params = Params(s.scene, 2, 48, 48, 64);
  params.mode = VoxelizeMode::kSolid;
  params.precision = SlicePrecision::kLocal;
  const auto result = MustVoxelize(s, params);
  ASSERT_EQ(result.column_near.size(), size_t{48} * 48);
  EXPECT_EQ(result.ambiguous_columns, 0u);
  // Voxel centers (in each column's own slices) clearly inside the ball are
  // set, clearly outside are clear; "clearly" = half a voxel diagonal plus
  // the tessellation's deviation from the sphere.
  const voxel_reference::OrientedBox& box = params.box;
  const double depth = 2.0 * box.half_extent.z;
  const double texel = 2.0 * box.half_extent.x / params.width;
  const double tessellation = radius * (1.0 - std::cos(0.04));
  uint64_t checked_in = 0, checked_out = 0, wrong = 0, empty_columns = 0;
  for (uint32_t y = 0; y < params.height; ++y) {
    for (uint32_t x = 0; x < params.width; ++x) {
      const size_t c = size_t{y} * params.width + x;
      const double near = result.column_near[c], far = result.column_far[c];
      const glm::dvec3 base = box.center - box.half_extent.z * box.axis_w +
                              ((x + 0.5) * texel - box.half_extent.x) * box.axis_u +
                              ((y + 0.5) * texel - box.half_extent.y) * box.axis_v;
      const glm::dvec3 d = base - kSphereCenter;
      const double ray_distance = glm::length(d - glm::dot(d, box.axis_w) * box.axis_w);
      if (near > far) {
        ++empty_columns;
        EXPECT_GT(ray_distance, radius - tessellation) << "empty column " << x << "," << y;
        continue;
      }
      EXPECT_LT(ray_distance, radius + texel) << "column " << x << "," << y;
      const double slice = (far - near) * depth / params.slices;
      const double margin = 0.5 * std::sqrt(2.0 * texel * texel + slice * slice) + tessellation;
      for (uint32_t k = 0; k < params.slices; ++k) {
        const glm::dvec3 p = base + (near + (k + 0.5) / params.slices * (far - near)) * depth * box.axis_w;
        const double signed_distance = glm::length(p - kSphereCenter) - radius;
        const bool set = result.grid.Get(x, y, k);
        if (signed_distance < -margin) {
          ++checked_in;
          if (!set) ++wrong;
        } else if (signed_distance > margin) {
          ++checked_out;
          if (set) ++wrong;
        }
      }
    }
  }
  std::printf("local solid: %llu voxels checked inside, %llu outside, %llu wrong, %llu empty columns\n",
              (unsigned long long)checked_in, (unsigned long long)checked_out, (unsigned long long)wrong,
              (unsigned long long)empty_columns);
  EXPECT_GT(checked_in, 10000u);
  EXPECT_EQ(wrong, 0u);
}

// An open quad has entering faces and no leaving ones: every column it
// covers is ambiguous, reported, and keeps only its surface voxels.
TEST(SlicemapSolid, OpenMeshColumnsAreReportedAmbiguous) {
  Scene scene;
  AddQuad(scene, "sheet", glm::dvec3(0.1, 0.1, 0.3), glm::dvec3(0.6, 0, 0.1), glm::dvec3(0, 0.5, 0.05), 0);
  scene.materials.push_back(Material{"white", glm::dvec3(1.0), glm::dvec3(0.0)});
  UpdateBounds(scene);
  const Uploaded s = Upload(std::move(scene));
  VoxelizeParams params = Params(s.scene, 2, 32, 32, 32);
  params.box.center = glm::dvec3(0.5);
  params.box.half_extent = glm::dvec3(0.5);
  params.mode = VoxelizeMode::kSolid;
  const auto solid = MustVoxelize(s, params);
  params.mode = VoxelizeMode::kSurface;
  const auto surface = MustVoxelize(s, params);
  // Columns whose center the quad covers: those with a surface bit.
  std::vector<uint32_t> covered;
  const uint32_t wpc = surface.grid.words_per_column;
  for (uint32_t c = 0; c < 32 * 32; ++c) {
    bool any = false;
    for (uint32_t w = 0; w < wpc; ++w) any |= surface.grid.bits[size_t{c} * wpc + w] != 0;
    if (any) covered.push_back(c);
  }
  EXPECT_GT(covered.size(), 100u);
  EXPECT_EQ(solid.ambiguous_columns, covered.size());
  EXPECT_EQ(solid.ambiguous_column_list, covered);
  EXPECT_TRUE(solid.grid.bits == surface.grid.bits);
}

TEST(SlicemapRealScenes, BunnySurfaceAndSolid) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  auto loaded = LoadGltfFile(dir / "bunny" / "bunny.gltf");
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  const Uploaded s = Upload(std::move(*loaded));
  std::printf("bunny: %zu triangles\n", s.scene.TriangleCount());
  CheckStandardSurface(s, Params(s.scene, 2, 96, 96, 96), "bunny 96^3");
  CheckConservativeSurface(s, Params(s.scene, 2, 96, 96, 96), "bunny 96^3");
  VoxelizeParams local = Params(s.scene, 1, 96, 96, 64);
  local.precision = SlicePrecision::kLocal;
  CheckConservativeSurface(s, local, "bunny local");
  // The bunny is not closed (holes in its base): columns through the holes
  // are left out on both sides; everywhere else the solids agree.
  CheckSolid(s, Params(s.scene, 2, 96, 96, 96), "bunny", false);
}

TEST(SlicemapRealScenes, SponzaSurface) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  auto loaded = LoadGltfFile(dir / "sponza_dabrovic" / "sponza.gltf");
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  const Uploaded s = Upload(std::move(*loaded));
  std::printf("sponza: %zu triangles\n", s.scene.TriangleCount());
  CheckStandardSurface(s, Params(s.scene, 1, 128, 128, 128), "sponza 128^3");
  CheckConservativeSurface(s, Params(s.scene, 1, 128, 128, 128), "sponza 128^3");
  CheckConservativeSurface(s, Params(s.scene, 0, 64, 128, 96), "sponza along x");
}

// Transmittance through a voxelized ball against the analytic chord
// 2 sqrt(R^2 - b^2), within the stated error.
void CheckTransmittance(const gpu::TransmittanceLight& light, const char* label) {
  const double radius = 1.0, sigma = 0.8;
  Scene scene = MakeSphere(kSphereCenter, radius, 4);
  AddQuad(scene, "receiver", kSphereCenter + glm::dvec3(-3, -3, -3), glm::dvec3(6, 0, 0), glm::dvec3(0, 0, 6), 0);
  UpdateBounds(scene);
  const Uploaded s = Upload(std::move(scene));
  gpu::TransmittanceParams params;
  params.light = light;
  params.nodes = {{0, sigma}};
  params.resolution = 128;
  params.slices = 128;
  // Points beyond the ball along rays at several impact parameters b, and
  // points inside it and before it.
  const glm::dvec3 dir0 = light.kind == gpu::LightKind::kDirectional
                              ? glm::normalize(light.direction)
                              : glm::normalize(kSphereCenter - light.position);
  glm::dvec3 side = glm::normalize(glm::cross(dir0, glm::dvec3(0.3, 0.9, 0.1)));
  struct Query { double b; double along; };  // along: signed distance past the center
  std::vector<Query> queries;
  for (double b : {0.0, 0.21, 0.43, 0.6, 0.72, 0.8}) queries.push_back({b, 2.5});
  queries.push_back({0.3, 0.0});   // inside, half way
  queries.push_back({0.1, -2.0});  // before the ball
  queries.push_back({1.3, 2.5});   // beside it
  std::vector<double> exact;
  for (const Query& q : queries) {
    glm::dvec3 p;
    glm::dvec3 dir = dir0;
    if (light.kind == gpu::LightKind::kDirectional) {
      p = kSphereCenter + q.b * side + q.along * dir0;
    } else {
      // The ray from the light passing at distance b from the center.
      const double d = glm::length(kSphereCenter - light.position);
      dir = glm::normalize(d * dir0 + q.b * side);
      const double t_closest = glm::dot(kSphereCenter - light.position, dir);
      p = light.position + (t_closest + q.along) * dir;
    }
    params.points.push_back(p);
    // Chord of the ray inside the ball up to p.
    const glm::dvec3 origin = light.kind == gpu::LightKind::kDirectional ? p - 10.0 * dir : light.position;
    const double t_center = glm::dot(kSphereCenter - origin, dir);
    const double b2 = glm::dot(kSphereCenter - origin, kSphereCenter - origin) - t_center * t_center;
    double length = 0;
    if (b2 < radius * radius) {
      const double half = std::sqrt(radius * radius - b2);
      const double t_p = glm::dot(p - origin, dir);
      length = std::clamp(t_p, t_center - half, t_center + half) - (t_center - half);
    }
    exact.push_back(sigma * length);
  }
  auto result = gpu::Transmittance(testing::SharedGpuWorker(), s.scene, *s.gpu, params);
  ASSERT_TRUE(result.ok()) << result.status();
  std::printf("[%s] %s\n", label, result->error_statement.c_str());
  const double tessellation = radius * (1.0 - std::cos(0.04));
  for (size_t i = 0; i < queries.size(); ++i) {
    const double tau = result->optical_depth[i], err = result->optical_depth_error[i];
    // The column's ray is up to lateral_offset from the point's ray: the chord
    // changes by at most |d chord / d b| * offset = 2 b / sqrt(R^2 - b^2) * offset
    // (b <= 0.8 R here), plus the tessellation's deviation from the sphere.
    const double b = queries[i].b;
    const double slope = b < radius ? 2.0 * (b + result->lateral_offset[i]) /
                                          std::sqrt(std::max(1e-3, radius * radius - std::pow(b + result->lateral_offset[i], 2)))
                                    : 0.0;
    const double lateral = sigma * (slope * result->lateral_offset[i] + 2.0 * tessellation);
    std::printf("  b %.2f along %+.1f: optical depth %.4f (error <= %.4f, lateral <= %.4f), exact %.4f, T %.4f\n", b,
                queries[i].along, tau, err, lateral, exact[i], result->transmittance[i]);
    EXPECT_LE(exact[i], tau + lateral + 1e-4) << label << " query " << i;
    EXPECT_GE(exact[i], tau - err - lateral - 1e-4) << label << " query " << i;
    EXPECT_NEAR(result->transmittance[i], std::exp(-tau), 1e-5);
  }
  EXPECT_GT(result->optical_depth[0], 1.0);  // through the center: 2 R sigma = 1.6
  EXPECT_EQ(result->optical_depth[queries.size() - 1], 0.0f);
  EXPECT_EQ(result->ambiguous_columns, 0u);
}

TEST(SlicemapTransmittance, DirectionalLightThroughABall) {
  gpu::TransmittanceLight light;
  light.kind = gpu::LightKind::kDirectional;
  light.direction = glm::dvec3(0.2, -1.0, 0.1);
  CheckTransmittance(light, "directional");
}

TEST(SlicemapTransmittance, PointLightThroughABall) {
  gpu::TransmittanceLight light;
  light.kind = gpu::LightKind::kPoint;
  light.position = kSphereCenter + glm::dvec3(0.5, 4.0, -0.7);
  CheckTransmittance(light, "point");
}

TEST(SlicemapTransmittance, ReceiverPatchAndNoAbsorbers) {
  Scene scene = MakeSphere(kSphereCenter, 1.0, 2);
  const Uploaded s = Upload(std::move(scene));
  gpu::TransmittanceParams params;
  params.light.direction = glm::dvec3(0, -1, 0);
  params.nodes = {{0, 2.0}};
  params.resolution = 64;
  params.slices = 64;
  params.patch.origin = kSphereCenter + glm::dvec3(-2, -3, -2);
  params.patch.u = glm::dvec3(4, 0, 0);
  params.patch.v = glm::dvec3(0, 0, 4);
  params.patch.nu = 16;
  params.patch.nv = 16;
  auto result = gpu::Transmittance(testing::SharedGpuWorker(), s.scene, *s.gpu, params);
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_EQ(result->transmittance.size(), 256u);
  // The shadow is darkest in the middle and absent at the corners.
  EXPECT_LT(result->transmittance[8 * 16 + 8], 0.05f);
  EXPECT_EQ(result->transmittance[0], 1.0f);
  EXPECT_EQ(result->transmittance[255], 1.0f);
}

// Two absorbing boxes of one coefficient that overlap in depth: columns
// through both enter twice before they leave, which does not resolve. The
// points behind those columns are flagged and state the whole interval, [0,
// sigma x the column's length up to them], which holds the union's path;
// the other points keep their tight interval and no flag.
TEST(SlicemapTransmittance, AmbiguousColumnsFlagTheirPointsAndWidenTheirBounds) {
  Scene scene;
  AddBox(scene, "a", {0, 0, 0}, {2, 2, 2}, 0);
  AddBox(scene, "b", {1, 1, 0}, {3, 3, 2}, 0);
  UpdateBounds(scene);
  const Uploaded s = Upload(std::move(scene));
  gpu::TransmittanceParams params;
  params.light.kind = gpu::LightKind::kDirectional;
  params.light.direction = glm::dvec3(0, -1, 0);
  params.nodes = {{0, 1.0}, {1, 1.0}};
  params.resolution = 64;
  params.slices = 128;
  // Under a only, under both (in a, below b), under b only, under nothing.
  params.points = {{0.5, -1, 1}, {1.5, 0.5, 1}, {2.5, -1, 1}, {4.0, -1, 1}};
  const double union_path[4] = {2.0, 2.5, 2.0, 0.0};
  auto result = gpu::Transmittance(testing::SharedGpuWorker(), s.scene, *s.gpu, params);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_GT(result->ambiguous_columns, 0u);
  const std::vector<uint8_t> expected_flags = {0, 1, 0, 0};
  EXPECT_EQ(result->ambiguous, expected_flags);
  for (size_t i = 0; i < 4; ++i) {
    const double od = result->optical_depth[i], error = result->optical_depth_error[i];
    EXPECT_LE(od - error, union_path[i] + 1e-3) << "point " << i;
    EXPECT_GE(od, union_path[i] - 1e-3) << "point " << i;
    if (!result->ambiguous[i]) {
      EXPECT_LE(error, 0.1) << "point " << i << ": a resolved column stays tight";
    }
  }
  EXPECT_EQ(result->transmittance[3], 1.0f) << "no absorber on the way";
  EXPECT_NEAR(result->optical_depth_error[1], result->optical_depth[1], 1e-6) << "the whole interval [0, od]";
}

TEST(SlicemapValidation, BadParamsNameTheField) {
  const Uploaded s = Upload(MakeSphere(kSphereCenter, 1.0, 1));
  auto expect = [&](VoxelizeParams p, absl::StatusCode code, const std::string& needle) {
    auto result = gpu::Voxelize(testing::SharedGpuWorker(), *s.gpu, p);
    ASSERT_FALSE(result.ok()) << needle;
    EXPECT_EQ(result.status().code(), code) << result.status();
    EXPECT_NE(std::string(result.status().message()).find(needle), std::string::npos) << result.status();
  };
  const VoxelizeParams good = Params(s.scene, 2, 16, 16, 16);
  ASSERT_TRUE(gpu::Voxelize(testing::SharedGpuWorker(), *s.gpu, good).ok());
  VoxelizeParams p = good;
  p.box.center.y = std::nan("");
  expect(p, absl::StatusCode::kInvalidArgument, "params.box.center");
  p = good;
  p.box.half_extent.z = 0.0;
  expect(p, absl::StatusCode::kInvalidArgument, "params.box.half_extent[2]: 0");
  p = good;
  p.box.half_extent.x = -1.0;
  expect(p, absl::StatusCode::kInvalidArgument, "params.box.half_extent[0]: -1");
  p = good;
  p.box.axis_u = glm::dvec3(2, 0, 0);
  expect(p, absl::StatusCode::kInvalidArgument, "params.box.axis_u");
  p = good;
  p.box.axis_v = glm::dvec3(1, 0, 0);
  expect(p, absl::StatusCode::kInvalidArgument, "not orthogonal");
  p = good;
  p.width = 0;
  expect(p, absl::StatusCode::kInvalidArgument, "params.width: 0");
  p = good;
  p.slices = 0;
  expect(p, absl::StatusCode::kInvalidArgument, "params.slices: 0");
  p = good;
  p.height = 4097;
  expect(p, absl::StatusCode::kResourceExhausted, "params.height: 4097");
  p = good;
  p.slices = 5000;
  expect(p, absl::StatusCode::kResourceExhausted, "params.slices: 5000");
  p = good;
  p.width = p.height = 4096;
  p.slices = 4096;
  expect(p, absl::StatusCode::kResourceExhausted, "4096 x 4096 x 4096");
  p = good;
  p.max_bytes = 100;
  expect(p, absl::StatusCode::kResourceExhausted, "over the cap of 100 bytes");
  p = good;
  p.triangles = {{0, 1000000}};
  expect(p, absl::StatusCode::kInvalidArgument, "params.triangles[0]");
  p = good;
  p.mode = static_cast<VoxelizeMode>(7);
  expect(p, absl::StatusCode::kInvalidArgument, "params.mode: unknown value 7");

  auto expect_t = [&](gpu::TransmittanceParams t, absl::StatusCode code, const std::string& needle) {
    auto result = gpu::Transmittance(testing::SharedGpuWorker(), s.scene, *s.gpu, t);
    ASSERT_FALSE(result.ok()) << needle;
    EXPECT_EQ(result.status().code(), code) << result.status();
    EXPECT_NE(std::string(result.status().message()).find(needle), std::string::npos) << result.status();
  };
  gpu::TransmittanceParams t;
  t.nodes = {{0, 1.0}};
  t.points = {glm::dvec3(0.0)};
  ASSERT_TRUE(gpu::Transmittance(testing::SharedGpuWorker(), s.scene, *s.gpu, t).ok());
  gpu::TransmittanceParams bad = t;
  bad.nodes.clear();
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.nodes: empty");
  bad = t;
  bad.nodes = {{5, 1.0}};
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.nodes[0].node: 5");
  bad = t;
  bad.nodes = {{0, -1.0}};
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.nodes[0].absorption: -1");
  bad = t;
  bad.points.push_back(glm::dvec3(0, std::numeric_limits<double>::infinity(), 0));
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.points[1]");
  bad = t;
  bad.light.direction = glm::dvec3(0.0);
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.light.direction");
  bad = t;
  bad.light.kind = gpu::LightKind::kPoint;
  bad.light.position = kSphereCenter;
  expect_t(bad, absl::StatusCode::kFailedPrecondition, "inside the absorbers' bounding sphere");
  bad = t;
  bad.resolution = 0;
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.resolution = 0");
  bad = t;
  bad.slices = 9999;
  expect_t(bad, absl::StatusCode::kResourceExhausted, "params.slices: 9999");
  bad = t;
  bad.patch.nu = 3;
  expect_t(bad, absl::StatusCode::kInvalidArgument, "params.patch");
}

}  // namespace
}  // namespace visq
