// Hidden-sample maps against independent references: Embree casting the very
// same segments (the sample positions the API reports), and closed forms.
//
// Tolerance for EXACT mode: kTieFraction of the bits may differ from Embree.
// Both sides decide in float32 (Embree's watertight test in its frame, the
// shader's edge test on the back-projection), so samples within ~1e-6 of a
// triangle edge's shadow can fall either way; nothing else may differ.
#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <random>

#include <gtest/gtest.h>

#include "exact/exact_geometry.h"
#include "raycast/embree_scene.h"
#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "gpu_test_support.h"
#include "large_scene.h"
#include "test_support.h"
#include "window_room.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/hidden_sample_map.h"
#include "visq/gpu/triangle_clusters.h"

namespace visq::gpu {

using namespace ::visq::sampling;
namespace {

constexpr double kTieFraction = 1e-4;

HiddenSampleMapper& Mapper() {
  static std::unique_ptr<HiddenSampleMapper> mapper = [] {
    auto created = HiddenSampleMapper::Create(testing::SharedGpuWorker());
    if (!created.ok()) { ADD_FAILURE() << created.status(); std::abort(); }
    return std::move(*created);
  }();
  return *mapper;
}

std::shared_ptr<GpuScene> Upload(const Scene& scene) {
  auto uploaded = GpuScene::Upload(testing::SharedGpuWorker(), scene);
  EXPECT_TRUE(uploaded.ok()) << uploaded.status();
  return uploaded.ok() ? *uploaded : nullptr;
}

void AddTriangle(Scene& scene, const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  const uint32_t base = static_cast<uint32_t>(scene.positions.size());
  scene.positions.insert(scene.positions.end(), {a, b, c});
  scene.triangles.emplace_back(base, base + 1, base + 2);
  scene.triangle_material.push_back(0);
  scene.triangle_node.push_back(0);
}

Scene EmptyFrame() {
  Scene scene;
  scene.materials.push_back({"white"});
  scene.nodes.push_back({"root"});
  return scene;
}

Scene RandomCloud(int triangles, uint32_t seed, const glm::dvec3& lo, const glm::dvec3& hi, double size) {
  Scene scene = EmptyFrame();
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u01(0.0, 1.0), side(-size, size);
  for (int k = 0; k < triangles; ++k) {
    const glm::dvec3 c = lo + glm::dvec3(u01(rng), u01(rng), u01(rng)) * (hi - lo);
    AddTriangle(scene, c + glm::dvec3(side(rng), side(rng), side(rng)), c + glm::dvec3(side(rng), side(rng), side(rng)),
                c + glm::dvec3(side(rng), side(rng), side(rng)));
  }
  UpdateBounds(scene);
  return scene;
}

// The unit-square light at y = 1 facing down and the unit-square receiver at y = 0.
// The culled draw (`culled`) against drawing every triangle (`all`): the
// same bits, fractions and lookup bounds, on a map that is neither all
// hidden nor all visible.
void ExpectCulledGivesTheBitsOfDrawingAll(HiddenSampleMapper& culled_mapper, HiddenSampleMapper& all_mapper,
                                          const GpuScene& gpu_scene, const HiddenSampleMapRequest& r) {
  auto culled = culled_mapper.Compute(gpu_scene, r);
  auto all = all_mapper.Compute(gpu_scene, r);
  ASSERT_TRUE(culled.ok()) << culled.status();
  ASSERT_TRUE(all.ok()) << all.status();
  EXPECT_EQ(culled->blocked_bits, all->blocked_bits);
  EXPECT_EQ(culled->visible_fraction, all->visible_fraction);
  EXPECT_EQ(culled->error.lookup_per_texel, all->error.lookup_per_texel);
  EXPECT_EQ(culled->error.lookup_max, all->error.lookup_max);
  const auto [lo, hi] = std::minmax_element(all->visible_fraction.begin(), all->visible_fraction.end());
  EXPECT_LT(*lo, 1.0f);
  EXPECT_GT(*hi, 0.0f);
}

HiddenSampleMapRequest UnitRequest(int n, int size) {
  HiddenSampleMapRequest r;
  r.source.patch = {{0, 1, 0}, {1, 0, 0}, {0, 0, 1}};
  r.source.sample_count = n;
  r.receiver.patch = {{0, 0, 0}, {1, 0, 0}, {0, 0, 1}};
  r.receiver.width = r.receiver.height = size;
  r.options.want_bitmasks = true;
  return r;
}

struct Agreement {
  uint64_t bits = 0, differ = 0, blocked = 0;
  double differ_fraction() const { return bits ? double(differ) / bits : 0.0; }
  double blocked_fraction() const { return bits ? double(blocked) / bits : 0.0; }
};

// Embree on exactly the segments the map tested: receiver sample -> source sample.
std::vector<uint8_t> EmbreeBits(const Scene& scene, const HiddenSampleMapRequest& request,
                                const HiddenSampleMapResult& result) {
  auto embree = raycast::EmbreeScene::Create(scene);
  EXPECT_TRUE(embree.ok()) << embree.status();
  if (!embree.ok()) return {};
  std::vector<raycast::Segment> segments;
  segments.reserve(size_t(result.width) * result.height * result.sample_count);
  for (int y = 0; y < result.height; ++y)
    for (int x = 0; x < result.width; ++x) {
      const glm::dvec3 p = ReceiverSamplePosition(request.receiver, x, y);
      for (int i = 0; i < result.sample_count; ++i)
        segments.push_back({p, SourceSampleSeenFrom(request, result.samples, i, x, y)});
    }
  auto occluded = embree->Occluded(segments);
  EXPECT_TRUE(occluded.ok()) << occluded.status();
  return occluded.ok() ? *occluded : std::vector<uint8_t>{};
}

bool Bit(const HiddenSampleMapResult& r, size_t texel, int i) {
  return (r.blocked_bits[texel * r.words_per_texel + i / 32] >> (i % 32)) & 1u;
}

Agreement Compare(const HiddenSampleMapResult& result, const std::vector<uint8_t>& reference) {
  Agreement a;
  const size_t texels = size_t(result.width) * result.height;
  if (reference.size() != texels * result.sample_count) { ADD_FAILURE() << "reference size"; return a; }
  for (size_t j = 0; j < texels; ++j)
    for (int i = 0; i < result.sample_count; ++i) {
      const bool ref = reference[j * result.sample_count + i] != 0;
      a.bits++;
      a.blocked += ref;
      if (ref != Bit(result, j, i) && a.differ < 12 && std::getenv("HSM_DEBUG"))
        std::printf("mismatch texel %zu (%zu,%zu) sample %d embree %d\n", j, j % result.width, j / result.width, i, ref);
      a.differ += ref != Bit(result, j, i);
    }
  return a;
}

// Runs EXACT against Embree and asserts agreement; returns the agreement.
Agreement ExpectMatchesEmbree(const Scene& scene, const HiddenSampleMapRequest& request) {
  auto gpu_scene = Upload(scene);
  if (!gpu_scene) return {};
  auto result = Mapper().Compute(*gpu_scene, request);
  EXPECT_TRUE(result.ok()) << result.status();
  if (!result.ok()) return {};
  const Agreement a = Compare(*result, EmbreeBits(scene, request, *result));
  EXPECT_LE(a.differ_fraction(), kTieFraction) << a.differ << " of " << a.bits << " bits differ from Embree";
  // Consistency of the fractions with the bits.
  for (size_t j = 0; j < result->visible_fraction.size(); ++j) {
    int blocked = 0;
    for (int i = 0; i < result->sample_count; ++i) blocked += Bit(*result, j, i);
    EXPECT_FLOAT_EQ(result->visible_fraction[j], float(result->sample_count - blocked) / result->sample_count);
  }
  EXPECT_EQ(result->error.lookup_max, 0.0);
  return a;
}

// ---------------------------------------------------------------- validation

TEST(HiddenSampleMapValidation, RejectsBadParametersNamingTheField) {
  struct Case { const char* field; std::function<void(HiddenSampleMapRequest&)> edit; };
  const std::vector<Case> cases = {
      {"source.origin", [](auto& r) { r.source.patch.origin.x = std::nan(""); }},
      {"source", [](auto& r) { r.source.patch.edge_v = r.source.patch.edge_u * 2.0; }},
      {"receiver", [](auto& r) { r.receiver.patch.edge_u = glm::dvec3(0.0); }},
      {"samples.count", [](auto& r) { r.source.sample_count = 0; }},
      {"samples.count", [](auto& r) { r.source.sample_count = 4097; }},
      {"width", [](auto& r) { r.receiver.width = 0; }},
      {"height", [](auto& r) { r.receiver.height = 5000; }},
      {"heightfield", [](auto& r) { r.receiver.heightfield.assign(7, 0.0f); }},
      {"heightfield[3]", [](auto& r) {
         r.receiver.heightfield.assign(size_t(r.receiver.width) * r.receiver.height, 0.0f);
         r.receiver.heightfield[3] = INFINITY;
       }},
      {"samples.custom_uv", [](auto& r) { r.source.pattern = SamplePattern::kCustom; }},
      {"hough_resolution", [](auto& r) { r.options.hough_theta_resolution = 8; }},
      {"confidence", [](auto& r) { r.options.confidence = 1.0; }},
      {"receiver", [](auto& r) { r.receiver.patch.edge_v = {0, 2, 1}; }},  // across the source plane
      {"samples.polygon_uv", [](auto& r) { r.source.polygon_uv = {{2, 2}, {3, 2}, {3, 3}}; }},
  };
  auto scene = Upload(RandomCloud(4, 1, {0, 0.2, 0}, {1, 0.8, 1}, 0.1));
  ASSERT_TRUE(scene);
  for (const Case& c : cases) {
    HiddenSampleMapRequest request = UnitRequest(32, 8);
    c.edit(request);
    auto result = Mapper().Compute(*scene, request);
    ASSERT_FALSE(result.ok()) << c.field << " was accepted";
    // Malformed values are INVALID_ARGUMENT; values beyond a cap (4096
    // samples, texels a side) RESOURCE_EXHAUSTED, as in every RPC.
    const bool beyond_cap = request.source.sample_count > 4096 || request.receiver.height > 4096;
    EXPECT_EQ(result.status().code(),
              beyond_cap ? absl::StatusCode::kResourceExhausted : absl::StatusCode::kInvalidArgument)
        << result.status();
    EXPECT_NE(std::string(result.status().message()).find(c.field), std::string::npos) << result.status();
  }
}

// -------------------------------------------------------------- closed forms

TEST(HiddenSampleMapClosedForm, EmptySceneSeesEverything) {
  Scene scene = EmptyFrame();
  UpdateBounds(scene);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  auto result = Mapper().Compute(*gpu_scene, UnitRequest(64, 16));
  ASSERT_TRUE(result.ok()) << result.status();
  for (float v : result->visible_fraction) ASSERT_EQ(v, 1.0f);
}

// A horizontal half-plane at y = 0.5 covering x < 0.5: from receiver x = rx
// the segment to source sample sx crosses y = 0.5 at (rx + sx) / 2, so the
// hidden samples are exactly those with sx < 1 - rx.
Scene HalfPlaneAt(double y, double x_edge) {
  Scene scene = EmptyFrame();
  AddTriangle(scene, {x_edge, y, -50}, {x_edge, y, 50}, {-50, y, 0});
  UpdateBounds(scene);
  return scene;
}

TEST(HiddenSampleMapClosedForm, TriangleHidingExactlyHalfTheSource) {
  auto gpu_scene = Upload(HalfPlaneAt(0.5, 0.5));
  ASSERT_TRUE(gpu_scene);
  for (LookupMode mode : {LookupMode::kExact, LookupMode::kHough}) {
    // One receiver sample under the centre: exactly half of an 8 x 8 grid.
    HiddenSampleMapRequest centre = UnitRequest(64, 1);
    centre.options.lookup = mode;
    auto one = Mapper().Compute(*gpu_scene, centre);
    ASSERT_TRUE(one.ok()) << one.status();
    if (mode == LookupMode::kExact) {
      EXPECT_EQ(one->visible_fraction[0], 0.5f);
    }
    EXPECT_LE(std::abs(one->visible_fraction[0] - 0.5), one->error.lookup_max + 1e-6);

    // A 16 x 16 receiver under the middle half: the closed form per texel.
    HiddenSampleMapRequest strip = UnitRequest(64, 16);
    strip.receiver.patch = {{0.25, 0, 0}, {0.5, 0, 0}, {0, 0, 1}};
    strip.options.lookup = mode;
    auto result = Mapper().Compute(*gpu_scene, strip);
    ASSERT_TRUE(result.ok()) << result.status();
    for (int x = 0; x < 16; ++x) {
      const double rx = 0.25 + 0.5 * (x + 0.5) / 16;
      int hidden = 0;
      for (const glm::dvec2& uv : result->samples.uv) hidden += uv.x < 1.0 - rx;
      for (int y = 0; y < 16; ++y) {
        const size_t j = size_t(y) * 16 + x;
        const double expected = 1.0 - double(hidden) / 64;
        if (mode == LookupMode::kExact) {
          EXPECT_FLOAT_EQ(result->visible_fraction[j], expected) << "texel " << x << "," << y;
        } else {
          // HOUGH errs towards blocked, within its reported bound.
          EXPECT_LE(result->visible_fraction[j], expected + 1e-6);
          EXPECT_GE(result->visible_fraction[j] + result->error.lookup_per_texel[j], expected - 1e-6);
        }
      }
    }
  }
}

TEST(HiddenSampleMapClosedForm, OccludersBehindReceiverOrBeyondSourceBlockNothing) {
  for (double y : {-0.5, -0.01, 1.01, 1.5}) {
    auto gpu_scene = Upload(HalfPlaneAt(y, 0.5));
    ASSERT_TRUE(gpu_scene);
    auto result = Mapper().Compute(*gpu_scene, UnitRequest(64, 16));
    ASSERT_TRUE(result.ok()) << result.status();
    for (float v : result->visible_fraction) ASSERT_EQ(v, 1.0f) << "occluder at y = " << y;
  }
}

// A wall in the plane x = 0.5 spanning y in [y0, y1] (crossing one of the
// planes): segment (rx, 0) -> (sx, 1) meets x = 0.5 at height
// t = (0.5 - rx) / (sx - rx), blocked iff the sides differ and t is in the
// part of the wall strictly between the planes.
void ExpectWall(double y0, double y1) {
  Scene scene = EmptyFrame();
  AddQuad(scene, "wall", {0.5, y0, -50}, {0, y1 - y0, 0}, {0, 0, 100}, 0);
  UpdateBounds(scene);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  auto result = Mapper().Compute(*gpu_scene, UnitRequest(64, 16));
  ASSERT_TRUE(result.ok()) << result.status();
  int blocked_total = 0;
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) {
      const double rx = (x + 0.5) / 16;
      for (int i = 0; i < 64; ++i) {
        const double sx = result->samples.uv[i].x;
        const bool crosses = (rx - 0.5) * (sx - 0.5) < 0;
        const double t = crosses ? (0.5 - rx) / (sx - rx) : -1;
        const bool expected = crosses && t > std::max(y0, 0.0) && t < std::min(y1, 1.0);
        blocked_total += expected;
        ASSERT_EQ(Bit(*result, size_t(y) * 16 + x, i), expected) << "texel " << x << "," << y << " sample " << i;
      }
    }
  EXPECT_GT(blocked_total, 0);
}

TEST(HiddenSampleMapClosedForm, OccluderCrossingTheReceiverPlane) { ExpectWall(-0.7, 0.43); }
TEST(HiddenSampleMapClosedForm, OccluderCrossingTheSourcePlane) { ExpectWall(0.57, 1.9); }

// ------------------------------------------------------------ against Embree

TEST(HiddenSampleMapEmbree, RandomCloudN32) {
  Scene scene = RandomCloud(300, 7, {-0.2, 0.05, -0.2}, {1.2, 0.95, 1.2}, 0.08);
  HiddenSampleMapRequest r = UnitRequest(32, 64);
  r.source.pattern = SamplePattern::kJittered;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.05);
  EXPECT_LT(a.blocked_fraction(), 0.95);
}

TEST(HiddenSampleMapEmbree, RandomCloudN1024) {
  Scene scene = RandomCloud(1000, 11, {-0.2, 0.05, -0.2}, {1.2, 0.95, 1.2}, 0.05);
  HiddenSampleMapRequest r = UnitRequest(1024, 32);
  r.source.pattern = SamplePattern::kJittered;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.05);
  EXPECT_LT(a.blocked_fraction(), 0.95);
}

TEST(HiddenSampleMapEmbree, RandomCloudN4096SeveralPasses) {
  Scene scene = RandomCloud(200, 13, {-0.2, 0.05, -0.2}, {1.2, 0.95, 1.2}, 0.1);
  HiddenSampleMapRequest r = UnitRequest(4096, 24);
  r.source.pattern = SamplePattern::kJittered;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.05);
}

TEST(HiddenSampleMapEmbree, DecorrelatedSamples) {
  Scene scene = RandomCloud(300, 17, {-0.2, 0.05, -0.2}, {1.2, 0.95, 1.2}, 0.08);
  HiddenSampleMapRequest r = UnitRequest(128, 48);
  r.options.decorrelate = true;
  r.options.decorrelation_seed = 5;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.05);
}

TEST(HiddenSampleMapEmbree, TiltedPatchesAndBumpyReceiver) {
  Scene scene = RandomCloud(300, 19, {-0.2, 0.2, -0.2}, {1.2, 0.95, 1.2}, 0.08);
  HiddenSampleMapRequest r = UnitRequest(256, 40);
  r.source.patch = {{0.1, 1.0, 0.0}, {0.8, 0.15, 0.0}, {0.0, -0.1, 0.9}};  // not parallel to the receiver
  r.receiver.heightfield.resize(40 * 40);
  for (int y = 0; y < 40; ++y)
    for (int x = 0; x < 40; ++x) r.receiver.heightfield[y * 40 + x] = 0.15f * std::sin(x * 0.4f) * std::cos(y * 0.3f);
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.05);
}

// A source standing upright beside a floor receiver: triangles around the
// shaft (above the source, behind the receiver, off to the sides) are dropped
// by the shaft planes before their influence regions, which for planes this
// far from parallel would cover the whole receiver; those inside still
// block exactly Embree's bits.
TEST(HiddenSampleMapEmbree, UprightSourceWithGeometryAllAroundTheShaft) {
  Scene scene = RandomCloud(800, 23, {-1.0, -0.5, -1.5}, {2.0, 2.0, 2.0}, 0.08);
  HiddenSampleMapRequest r = UnitRequest(256, 32);
  r.source.patch = {{0.0, 0.3, -0.2}, {1.0, 0.0, 0.0}, {0.0, 0.5, 0.0}};
  r.source.pattern = SamplePattern::kJittered;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.01);
  EXPECT_LT(a.blocked_fraction(), 0.95);
}

// A large map is drawn a band of receiver rows at a time (each band its own
// GL job): the bits, fractions and lookup bounds must be those of one draw,
// with a heightfield and decorrelated samples (both indexed by texel), for
// the exact and the Hough lookups, and for bands of one row and of several.
TEST(HiddenSampleMap, BandsOfRowsGiveTheBitsOfOneDraw) {
  Scene scene = RandomCloud(300, 29, {-0.2, 0.2, -0.2}, {1.2, 0.95, 1.2}, 0.08);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  HiddenSampleMapRequest r = UnitRequest(300, 24);
  r.receiver.height = 17;
  r.receiver.heightfield.resize(24 * 17);
  for (int y = 0; y < 17; ++y)
    for (int x = 0; x < 24; ++x) r.receiver.heightfield[y * 24 + x] = 0.1f * std::sin(x * 0.5f) * std::cos(y * 0.7f);
  r.options.decorrelate = true;
  for (const size_t band_bytes : {size_t{1}, size_t{40000}}) {
    HiddenSampleMapperOptions options;
    options.band_readback_bytes = band_bytes;
    auto banded_mapper = HiddenSampleMapper::Create(testing::SharedGpuWorker(), options);
    ASSERT_TRUE(banded_mapper.ok()) << banded_mapper.status();
    for (const LookupMode lookup : {LookupMode::kExact, LookupMode::kHough}) {
      r.options.lookup = lookup;
      auto whole = Mapper().Compute(*gpu_scene, r);
      auto banded = (*banded_mapper)->Compute(*gpu_scene, r);
      ASSERT_TRUE(whole.ok()) << whole.status();
      ASSERT_TRUE(banded.ok()) << banded.status();
      EXPECT_EQ(banded->blocked_bits, whole->blocked_bits) << "band bytes " << band_bytes;
      EXPECT_EQ(banded->visible_fraction, whole->visible_fraction);
      EXPECT_EQ(banded->error.lookup_per_texel, whole->error.lookup_per_texel);
      EXPECT_EQ(banded->error.lookup_max, whole->error.lookup_max);
      // Not a trivial map: some samples blocked, not all.
      const auto [lo, hi] = std::minmax_element(whole->visible_fraction.begin(), whole->visible_fraction.end());
      EXPECT_LT(*lo, 1.0f);
      EXPECT_GT(*hi, 0.0f);
    }
  }
}

TEST(HiddenSampleMapEmbree, WatertightCullingKeepsTheBits) {
  Scene scene = EmptyFrame();
  AddBox(scene, "a", {0.1, 0.3, 0.2}, {0.4, 0.5, 0.6}, 0);
  AddBox(scene, "b", {0.5, 0.6, 0.1}, {0.9, 0.7, 0.4}, 0);
  UpdateBounds(scene);
  HiddenSampleMapRequest r = UnitRequest(256, 48);
  r.source.patch = {{0.25, 1.0, 0.25}, {0.5, 0, 0}, {0, 0, 0.5}};
  // Jittered: a regular grid over axis-aligned boxes at round coordinates
  // puts segments exactly through box edges, ties either side may call.
  r.source.pattern = SamplePattern::kJittered;
  r.options.watertight = true;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.02);
}

TEST(HiddenSampleMapEmbree, CornellBoxLightOntoFloor) {
  const Scene scene = MakeCornellBox();
  HiddenSampleMapRequest r;
  // The emissive quad itself (coplanar geometry must not block) onto the floor.
  r.source.patch = {{-0.25, 2.0 - 0.005, -0.25}, {0.5, 0, 0}, {0, 0, 0.5}};
  r.source.sample_count = 256;
  r.source.pattern = SamplePattern::kJittered;
  r.receiver.patch = {{-1, 0, -1}, {2, 0, 0}, {0, 0, 2}};
  r.receiver.width = r.receiver.height = 64;
  r.options.want_bitmasks = true;
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.05);
  EXPECT_LT(a.blocked_fraction(), 0.9);

  // The back wall as a receiver: not parallel to the light.
  r.receiver.patch = {{-1, 0, -1}, {2, 0, 0}, {0, 1.9, 0}};
  ExpectMatchesEmbree(scene, r);
}

TEST(HiddenSampleMapEmbree, HoughModeStaysWithinItsBound) {
  Scene scene = RandomCloud(1000, 23, {-0.2, 0.05, -0.2}, {1.2, 0.95, 1.2}, 0.05);
  HiddenSampleMapRequest r = UnitRequest(256, 48);
  r.options.lookup = LookupMode::kHough;
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  auto result = Mapper().Compute(*gpu_scene, r);
  ASSERT_TRUE(result.ok()) << result.status();
  const std::vector<uint8_t> reference = EmbreeBits(scene, r, *result);
  const Agreement a = Compare(*result, reference);
  uint64_t missed = 0;
  double worst_excess = 0;
  for (size_t j = 0; j < size_t(48 * 48); ++j) {
    int ref_blocked = 0;
    for (int i = 0; i < 256; ++i) {
      ref_blocked += reference[j * 256 + i];
      missed += reference[j * 256 + i] && !Bit(*result, j, i);
    }
    const double err = std::abs(result->visible_fraction[j] - (1.0 - ref_blocked / 256.0));
    worst_excess = std::max(worst_excess, err - result->error.lookup_per_texel[j]);
  }
  EXPECT_LE(worst_excess, 1e-6);
  EXPECT_LE(double(missed) / a.bits, kTieFraction) << "HOUGH must only err towards blocked";
  EXPECT_GT(result->error.lookup_max, 0.0);
  std::printf("HOUGH 256x256: %.4f%% of bits differ from Embree, lookup_max %.4f\n", 100.0 * a.differ_fraction(),
              result->error.lookup_max);
}

TEST(HiddenSampleMap, TranslatedSceneGivesTheSameAnswer) {
  Scene scene = MakeCornellBox();
  HiddenSampleMapRequest r;
  r.source.patch = {{-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5}};
  r.source.sample_count = 128;
  r.receiver.patch = {{-1, 0, -1}, {2, 0, 0}, {0, 0, 2}};
  r.receiver.width = r.receiver.height = 48;
  r.options.want_bitmasks = true;
  auto near = Upload(scene);
  ASSERT_TRUE(near);
  auto a = Mapper().Compute(*near, r);
  ASSERT_TRUE(a.ok()) << a.status();

  const glm::dvec3 shift(1e6, -1e6, 1e6);
  for (auto& p : scene.positions) p += shift;
  UpdateBounds(scene);
  r.source.patch.origin += shift;
  r.receiver.patch.origin += shift;
  auto far = Upload(scene);
  ASSERT_TRUE(far);
  auto b = Mapper().Compute(*far, r);
  ASSERT_TRUE(b.ok()) << b.status();
  size_t differ = 0;
  for (size_t k = 0; k < a->blocked_bits.size(); ++k) differ += std::popcount(a->blocked_bits[k] ^ b->blocked_bits[k]);
  EXPECT_LE(double(differ) / (48.0 * 48 * 128), kTieFraction);
  EXPECT_NE(std::count(a->visible_fraction.begin(), a->visible_fraction.end(), 1.0f), 48 * 48);
}

TEST(HiddenSampleMap, ColoredPolygonLight) {
  Scene scene = HalfPlaneAt(0.5, 0.5);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  HiddenSampleMapRequest r = UnitRequest(256, 16);
  // A triangle-shaped light, red on the left half (s < 0.5) and blue on the right.
  r.source.polygon_uv = {{0.0, 0.0}, {1.0, 0.0}, {0.5, 1.0}};
  r.source.color_texture_width = 2;
  r.source.color_texture_height = 1;
  r.source.color_texture = {{1, 0, 0}, {0, 0, 1}};
  auto result = Mapper().Compute(*gpu_scene, r);
  ASSERT_TRUE(result.ok()) << result.status();
  ASSERT_GT(result->sample_count, 64);
  ASSERT_LT(result->sample_count, 256);
  for (const glm::dvec2& uv : result->samples.uv) {
    ASSERT_LE(uv.y, 2.0 * std::min(uv.x, 1.0 - uv.x) + 1e-12);
  }
  for (size_t j = 0; j < result->visible_rgb.size(); ++j) {
    glm::dvec3 expected(0.0);
    for (int i = 0; i < result->sample_count; ++i)
      if (!Bit(*result, j, i)) expected += glm::dvec3(result->samples.color[i]);
    expected /= result->sample_count;
    EXPECT_NEAR(result->visible_rgb[j].r, expected.r, 1e-5);
    EXPECT_NEAR(result->visible_rgb[j].b, expected.b, 1e-5);
  }
  // Texels on the left (rx < 0.5) see the red half hidden (sx < 1 - rx).
  EXPECT_LT(result->visible_rgb[8].r, result->visible_rgb[8].b);
}

TEST(PatchVisibility, MatchesEmbreeOnTheCornellBox) {
  const Scene scene = MakeCornellBox();
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  PatchVisibilityRequest r;
  r.source = {{-0.95, 0.1, -0.9}, {0, 0, 1.8}, {0, 1.6, 0}};  // the left wall, just inside
  r.receiver = {{0.95, 0.1, -0.9}, {0, 0, 1.8}, {0, 1.6, 0}};  // the right wall
  // Off the round grid: unshifted, whole rows of segments pass exactly through
  // the short box's top edge (e.g. (0.95, 0.475, z) -> (-0.95, 1.425, z') meets
  // x = 0.7 at y = 0.6), ties that either side may call.
  r.receiver.origin += glm::dvec3(0, 0.00123, 0.00321);
  r.unblocked_limit = 100;
  auto result = Mapper().PatchVisibility(*gpu_scene, r);
  ASSERT_TRUE(result.ok()) << result.status();

  auto embree = raycast::EmbreeScene::Create(scene);
  ASSERT_TRUE(embree.ok());
  std::vector<raycast::Segment> segments;
  for (int rj = 0; rj < 32 * 32; ++rj)
    for (int si = 0; si < 32 * 32; ++si) {
      const glm::dvec3 p = r.receiver.At((rj % 32 + 0.5) / 32, (rj / 32 + 0.5) / 32);
      const glm::dvec3 q = r.source.At((si % 32 + 0.5) / 32, (si / 32 + 0.5) / 32);
      segments.push_back({p, q});
    }
  auto occluded = embree->Occluded(segments);
  ASSERT_TRUE(occluded.ok());
  uint64_t unblocked = 0;
  for (uint8_t o : *occluded) unblocked += !o;
  const double expected = double(unblocked) / segments.size();
  EXPECT_NEAR(result->mutual_visible_fraction, expected, kTieFraction);
  EXPECT_GT(expected, 0.05);
  EXPECT_LT(expected, 0.95);
  EXPECT_EQ(result->unblocked.size(), std::min<uint64_t>(100, result->unblocked_total));
  for (const UnblockedPair& pair : result->unblocked)
    EXPECT_FALSE((*occluded)[size_t(pair.receiver_sample) * 1024 + pair.source_sample]);
  double mean_source = 0;
  for (float f : result->source_visible) mean_source += f;
  EXPECT_NEAR(mean_source / 1024, result->mutual_visible_fraction, 1e-5);
}

// --------------------------------------------------------------- real scenes

Scene LoadOrFail(const std::filesystem::path& path) {
  auto scene = LoadGltfFile(path);
  EXPECT_TRUE(scene.ok()) << scene.status();
  return scene.ok() ? std::move(*scene) : Scene{};
}

// A light patch high in the scene's bounds, the receiver just above its floor.
HiddenSampleMapRequest SceneRequest(const Scene& scene, double light_height, double light_size, int n, int size) {
  const glm::dvec3 lo = scene.bounds.min, ext = scene.bounds.Extent(), c = scene.bounds.Center();
  HiddenSampleMapRequest r;
  const double ls = light_size * std::max(ext.x, ext.z);
  r.source.patch = {{c.x - ls / 2, lo.y + light_height * ext.y, c.z - ls / 2}, {ls, 0, 0}, {0, 0, ls}};
  r.source.sample_count = n;
  r.source.pattern = SamplePattern::kJittered;
  r.receiver.patch = {{lo.x + 0.2 * ext.x, lo.y + 0.02 * ext.y, lo.z + 0.2 * ext.z}, {0.6 * ext.x, 0, 0},
                      {0, 0, 0.6 * ext.z}};
  r.receiver.width = r.receiver.height = size;
  r.options.want_bitmasks = true;
  return r;
}

TEST(HiddenSampleMapRealScenes, Sponza) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  const Scene scene = LoadOrFail(dir / "sponza_dabrovic/sponza.gltf");
  ASSERT_GT(scene.TriangleCount(), 0u);
  const Agreement a = ExpectMatchesEmbree(scene, SceneRequest(scene, 0.7, 0.1, 128, 48));
  EXPECT_GT(a.blocked_fraction(), 0.02);
}

TEST(HiddenSampleMapRealScenes, Tree) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  const Scene scene = LoadOrFail(dir / "tree_kenney/tree_detailed.glb");
  ASSERT_GT(scene.TriangleCount(), 0u);
  HiddenSampleMapRequest r = SceneRequest(scene, 1.2, 0.5, 128, 48);
  // The ground under the whole crown.
  const glm::dvec3 lo = scene.bounds.min, ext = scene.bounds.Extent();
  r.receiver.patch = {{lo.x - 0.2 * ext.x, lo.y - 0.01 * ext.y, lo.z - 0.2 * ext.z}, {1.4 * ext.x, 0, 0},
                      {0, 0, 1.4 * ext.z}};
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.02);
}

TEST(HiddenSampleMapRealScenes, FlowerVase) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  const Scene scene = LoadOrFail(dir / "foliage_glass_vase_flowers/GlassVaseFlowers.gltf");
  ASSERT_GT(scene.TriangleCount(), 0u);
  HiddenSampleMapRequest r = SceneRequest(scene, 1.3, 0.4, 128, 40);
  const glm::dvec3 lo = scene.bounds.min, ext = scene.bounds.Extent();
  r.receiver.patch = {{lo.x - 0.3 * ext.x, lo.y - 0.01 * ext.y, lo.z - 0.3 * ext.z}, {1.6 * ext.x, 0, 0},
                      {0, 0, 1.6 * ext.z}};
  const Agreement a = ExpectMatchesEmbree(scene, r);
  EXPECT_GT(a.blocked_fraction(), 0.01);
}



// ------------------------------------------------------ source inside a trim

// Whether the open segment pq meets triangle abc, decided by exact
// orientation predicates: a ray caster that shares nothing with Embree or
// the shaders. A touch (a zero orientation) counts as a hit; the caller's
// scene has none.
bool SegmentMeetsTriangleExactly(const glm::dvec3& p, const glm::dvec3& q, const glm::dvec3& a, const glm::dvec3& b,
                                 const glm::dvec3& c) {
  using exact::detail::Orient3d;
  const int sp = Orient3d(a, b, c, p), sq = Orient3d(a, b, c, q);
  if (sp == 0 || sq == 0 || sp == sq) return false;
  const int s1 = Orient3d(p, q, a, b), s2 = Orient3d(p, q, b, c), s3 = Orient3d(p, q, c, a);
  return (s1 >= 0 && s2 >= 0 && s3 >= 0) || (s1 <= 0 && s2 <= 0 && s3 <= 0);
}

// A window in the wall z = 0: the unit-square source at height 1.5 sits in
// the thickness of a trim (four bars 8 cm wide, 3 cm in front of the source
// plane and 10 cm behind it) whose reveal faces cross that plane 2-4 cm
// outside the rectangle; the receiver is the floor 2.5-3.5 m out.
// Decorrelated jittered samples move by up to half a cell (3.1 cm), some past
// the reveals into the bars: the bars must block those exactly as the ray
// casters find, though seen from the rectangle alone their front faces reach
// only about a metre across the floor.
TEST(HiddenSampleMapEmbree, SourceInsideAWindowTrimGivesTheRayCastBits) {
  Scene scene = EmptyFrame();
  const double left = 0.02, right = 0.03, bottom = 0.02, top = 0.025, front = 0.03, back = 0.1, bar = 0.08;
  const double x0 = -left, x1 = 1.0 + right, y0 = 1.5 - bottom, y1 = 2.5 + top;
  AddBox(scene, "left", {x0 - bar, y0 - bar, -back}, {x0, y1 + bar, front}, 0);
  AddBox(scene, "right", {x1, y0 - bar, -back}, {x1 + bar, y1 + bar, front}, 0);
  AddBox(scene, "sill", {x0, y0 - bar, -back}, {x1, y0, front}, 0);
  AddBox(scene, "head", {x0, y1, -back}, {x1, y1 + bar, front}, 0);
  UpdateBounds(scene);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);

  HiddenSampleMapRequest r;
  r.source.patch = {{0, 1.5, 0}, {1, 0, 0}, {0, 1, 0}};
  r.source.sample_count = 256;
  r.source.pattern = SamplePattern::kJittered;
  r.receiver.patch = {{-1.5, 0, 2.5}, {4, 0, 0}, {0, 0, 1}};
  r.receiver.width = r.receiver.height = 24;
  r.options.want_bitmasks = true;
  for (const bool decorrelate : {false, true}) {
    SCOPED_TRACE(decorrelate ? "decorrelated" : "one pattern");
    r.options.decorrelate = decorrelate;
    r.options.decorrelation_seed = 3;
    auto result = Mapper().Compute(*gpu_scene, r);
    ASSERT_TRUE(result.ok()) << result.status();
    const std::vector<uint8_t> embree = EmbreeBits(scene, r, *result);
    ASSERT_EQ(embree.size(), size_t(24 * 24 * 256));

    // The independent caster, on the very same segments.
    std::vector<uint8_t> exact(embree.size(), 0);
    for (int y = 0; y < 24; ++y)
      for (int x = 0; x < 24; ++x) {
        const glm::dvec3 p = ReceiverSamplePosition(r.receiver, x, y);
        for (int i = 0; i < 256; ++i) {
          const glm::dvec3 q = SourceSampleSeenFrom(r, result->samples, i, x, y);
          uint8_t& hit = exact[(size_t(y) * 24 + x) * 256 + i];
          for (const glm::uvec3& t : scene.triangles) {
            if (SegmentMeetsTriangleExactly(p, q, scene.positions[t.x], scene.positions[t.y], scene.positions[t.z])) {
              hit = 1;
              break;
            }
          }
        }
      }
    EXPECT_EQ(exact, embree) << "the two ray casters disagree: the case has float ties";
    const Agreement a = Compare(*result, embree);
    EXPECT_EQ(a.differ, 0u) << a.differ << " of " << a.bits << " bits differ from the ray casters";
    // Seen from the rectangle alone the trim blocks nothing here; the
    // decorrelated samples inside the bars are blocked from every texel.
    if (decorrelate) {
      EXPECT_GT(a.blocked_fraction(), 0.003);
    }
  }
}


// A room lit through its window, the window the source (upright) and the
// floor the receiver: segments from the window pass the furniture above the
// sill nearly level, so the influence regions of those triangles reach the
// floor's edge along the ways such segments leave them, and only there
// (hsm_draw.geom, step 3). The bits stay the ray caster's, with one pattern
// and decorrelated; and under the grille's blind, lit from above the window.
TEST(HiddenSampleMapEmbree, AWindowLightingAFurnishedFloorGivesTheRayCastBits) {
  const Scene furnished = testing::MakeFurnishedWindowRoom(7);
  HiddenSampleMapRequest r;
  r.source.patch = {{-0.1, 0.8, -1.05}, {0, 1.4, 0}, {0, 0, 2.1}};
  r.source.sample_count = 64;
  r.source.pattern = SamplePattern::kJittered;
  r.receiver.patch = {{0.2, 0.01, -2.3}, {4.6, 0, 0}, {0, 0, 4.6}};
  r.receiver.width = r.receiver.height = 40;
  r.options.want_bitmasks = true;
  for (const bool decorrelate : {false, true}) {
    SCOPED_TRACE(decorrelate ? "decorrelated" : "one pattern");
    r.options.decorrelate = decorrelate;
    r.options.decorrelation_seed = 11;
    const Agreement a = ExpectMatchesEmbree(furnished, r);
    EXPECT_GT(a.blocked_fraction(), 0.1);
    EXPECT_LT(a.blocked_fraction(), 0.9);
  }
  HiddenSampleMapRequest above = r;
  above.source.patch = {{-1.0, 2.0, -0.8}, {0, 1.6, 0}, {0, 0, 1.6}};
  above.receiver.patch = {{0.2, 0.01, -1.5}, {3.0, 0, 0}, {0, 0, 3.0}};
  const Agreement a = ExpectMatchesEmbree(testing::MakeGrilleScene(), above);
  EXPECT_GT(a.blocked_fraction(), 0.5);
}

// Source and receiver tilted apart at random (the source up to 45 degrees
// off the receiver's plane, the receiver up to 15), with a cloud that
// reaches above the source's lower edge: every way an influence region can
// open (an axis, a wedge, the box) meets Embree's bits on the same
// segments, with one pattern and decorrelated.
TEST(HiddenSampleMapEmbree, TiltedSourcesOverTiltedReceiversGiveTheRayCastBits) {
  std::mt19937 rng(61);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  auto turned = [](const glm::dvec3& v, const glm::dvec3& axis, double angle) {
    return v * std::cos(angle) + glm::cross(axis, v) * std::sin(angle) + axis * glm::dot(axis, v) * (1.0 - std::cos(angle));
  };
  for (int round = 0; round < 6; ++round) {
    SCOPED_TRACE(round);
    const double azimuth = 2.0 * M_PI * u01(rng);
    const glm::dvec3 axis(std::cos(azimuth), 0.0, std::sin(azimuth));
    const double tilt = (M_PI / 4.0) * u01(rng);
    const glm::dvec3 su = turned({0.6, 0, 0}, axis, tilt), sv = turned({0, 0, 0.6}, axis, tilt);
    const glm::dvec3 centre(0.5, 1.2, 0.5);
    const glm::dvec3 receiver_axis(1.0, 0.0, 0.0);
    const double receiver_tilt = (M_PI / 12.0) * (2.0 * u01(rng) - 1.0);
    HiddenSampleMapRequest r;
    r.source.patch = {centre - 0.5 * su - 0.5 * sv, su, sv};
    r.source.sample_count = 64;
    r.source.pattern = SamplePattern::kJittered;
    r.receiver.patch = {{0, 0, 0}, turned({1, 0, 0}, receiver_axis, receiver_tilt), turned({0, 0, 1}, receiver_axis, receiver_tilt)};
    r.receiver.width = r.receiver.height = 24;
    r.options.want_bitmasks = true;
    r.options.decorrelate = round % 2 == 1;
    r.options.decorrelation_seed = 7;
    const Scene scene = RandomCloud(400, 100 + round, {-0.2, 0.2, -0.2}, {1.2, 1.15, 1.2}, 0.08);
    const Agreement a = ExpectMatchesEmbree(scene, r);
    EXPECT_GT(a.blocked_fraction(), 0.01);
  }
}

// One leaf 1 m up and 2 m into a room, lit through a window 0.1 m outside
// its wall (sill 0.8 m, head 2.2 m) onto the floor: a segment from the
// window through the leaf comes down 3.51 m in at the earliest (from the
// head through the leaf's lowest corner, 1.95 m in and 0.95 m up:
// -0.1 + 2.05 x 2.2 / 1.25), so the leaf shades the floor's far part only,
// 15 of its 50 columns, where its influence region used to be the whole
// floor (a vertex above a source corner made it unbounded). Its bits are
// the ray caster's, and it shades well under what a triangle covering the
// floor does.
TEST(HiddenSampleMap, ATriangleAboveTheSillShadesOnlyTheFloorBeyondIt) {
  HiddenSampleMapperOptions counting;
  counting.count_fragments = true;
  auto mapper = HiddenSampleMapper::Create(testing::SharedGpuWorker(), counting);
  ASSERT_TRUE(mapper.ok()) << mapper.status();
  Scene scene = EmptyFrame();
  AddTriangle(scene, {1.95, 0.95, -0.05}, {2.05, 1.0, 0.05}, {2.0, 1.05, 0.0});
  UpdateBounds(scene);
  auto gpu_scene = Upload(scene);
  ASSERT_TRUE(gpu_scene);
  HiddenSampleMapRequest r;
  r.source.patch = {{-0.1, 0.8, -1.05}, {0, 1.4, 0}, {0, 0, 2.1}};
  r.source.sample_count = 32;
  r.receiver.patch = {{0.0, 0.0, -2.5}, {5.0, 0, 0}, {0, 0, 5.0}};
  r.receiver.width = r.receiver.height = 50;
  r.options.want_bitmasks = true;
  auto result = (*mapper)->Compute(*gpu_scene, r);
  ASSERT_TRUE(result.ok()) << result.status();
  const Agreement a = Compare(*result, EmbreeBits(scene, r, *result));
  EXPECT_EQ(a.differ, 0u);
  EXPECT_GT(a.blocked, 0u);
  if (!(*mapper)->fragments_shaded()) GTEST_SKIP() << "the driver does not count fragments";
  const uint64_t leaf = *(*mapper)->fragments_shaded();
  // What a quad over the whole floor costs on this driver (it counts the
  // lanes of the blocks a quad's edges cut): a sheet just above the floor,
  // wider than it.
  Scene sheet = EmptyFrame();
  AddTriangle(sheet, {-1.0, 0.05, -4.0}, {8.0, 0.05, 0.0}, {-1.0, 0.05, 4.0});
  UpdateBounds(sheet);
  auto sheet_scene = Upload(sheet);
  ASSERT_TRUE(sheet_scene);
  ASSERT_TRUE((*mapper)->Compute(*sheet_scene, r).ok());
  const uint64_t whole_floor = *(*mapper)->fragments_shaded() - leaf;
  EXPECT_GT(leaf, 0u);
  EXPECT_LT(double(leaf), 0.5 * double(whole_floor)) << leaf << " fragments, the whole floor " << whole_floor;
}

// ------------------------------------------------------- cluster culling

// The cluster hierarchy alone (no context): every triangle once in its
// order, and a cull drops only triangles that the geometry shader's own
// float test (every corner below one plane) would drop, also for planes
// through the very corners of the clusters' boxes.
TEST(TriangleClusters, CullDropsOnlyWhatTheShaderDrops) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-10.0f, 10.0f), small(-0.3f, 0.3f);
  std::vector<glm::vec3> corners;
  for (int t = 0; t < 5000; ++t) {
    const glm::vec3 c(u(rng), u(rng), u(rng));
    for (int k = 0; k < 3; ++k) corners.push_back(c + glm::vec3(small(rng), small(rng), small(rng)));
  }
  // One triangle with a corner that is not finite: never dropped. Two with
  // corners near the float range's ends, whose extent overflows a float.
  corners[3 * 77] = glm::vec3(std::numeric_limits<float>::quiet_NaN());
  corners[3 * 78] = glm::vec3(3e38f, -3e38f, 3e38f);
  corners[3 * 79 + 1] = glm::vec3(-3e38f, 3e38f, -3e38f);
  std::vector<uint32_t> order;
  const TriangleClusters clusters = TriangleClusters::Build(corners, order);
  ASSERT_EQ(clusters.triangle_count(), 5000u);
  std::vector<uint32_t> sorted = order;
  std::sort(sorted.begin(), sorted.end());
  for (uint32_t t = 0; t < 5000; ++t) ASSERT_EQ(sorted[t], t);
  EXPECT_GE(clusters.cluster_count(), 5000u / TriangleClusters::kMaxClusterTriangles);
  EXPECT_EQ(clusters.node_count(), 2 * clusters.cluster_count() - 1);
  EXPECT_EQ(clusters.Cull({}), (std::vector<TriangleClusters::Range>{{0, 5000}}));

  auto shader_drops = [&](uint32_t t, const std::vector<glm::vec4>& planes) {
    for (const glm::vec4& p : planes) {
      bool below = true;
      for (int k = 0; k < 3; ++k) below = below && glm::dot(glm::vec3(p), corners[3 * t + k]) + p.w < 0.0f;
      if (below) return true;
    }
    return false;
  };
  std::normal_distribution<float> normal(0.0f, 1.0f);
  size_t dropped_total = 0;
  for (int round = 0; round < 60; ++round) {
    // Random slabs, and axis planes through a corner (where a box's face
    // lies on the plane, and its triangles must stay).
    std::vector<glm::vec4> planes;
    for (int k = 0; k < 4; ++k) {
      const glm::vec3 n = glm::normalize(glm::vec3(normal(rng), normal(rng), normal(rng)));
      planes.emplace_back(n, 4.0f - glm::dot(n, glm::vec3(u(rng), u(rng), u(rng))));
    }
    const glm::vec3& corner = corners[3 * (rng() % 5000) + rng() % 3];
    const int axis = round % 3;
    glm::vec4 through(0.0f);
    through[axis] = (round & 1) ? 1.0f : -1.0f;
    through.w = -through[axis] * corner[axis];
    planes.push_back(through);
    std::vector<uint8_t> kept(5000, 0);
    std::optional<uint32_t> previous_end;
    for (const TriangleClusters::Range& range : clusters.Cull(planes)) {
      if (previous_end) {
        EXPECT_GT(range.first, *previous_end) << "ranges ascend and are merged";
      }
      previous_end = range.first + range.count;
      for (uint32_t i = range.first; i < range.first + range.count; ++i) kept[order[i]] = 1;
    }
    for (uint32_t t = 0; t < 5000; ++t) {
      if (kept[t]) continue;
      ++dropped_total;
      EXPECT_TRUE(shader_drops(t, planes)) << "triangle " << t << " dropped, round " << round;
    }
    EXPECT_TRUE(kept[77]);
  }
  EXPECT_GT(dropped_total, 60u * 1000u) << "the culling should drop most triangles";
}

// A query at one copy of a level of copies: drawing only the clusters in
// the shaft gives the bits of drawing everything, for the exact and the
// Hough lookups, with a bumpy receiver and decorrelated samples (both widen
// the shaft), and draws a small part of the level.
TEST(HiddenSampleMap, CulledClustersGiveTheBitsOfDrawingEverything) {
  const Scene level = testing::MakeCopies(RandomCloud(300, 31, {-0.2, 0.2, -0.2}, {1.2, 0.95, 1.2}, 0.08), 16);
  auto gpu_scene = Upload(level);
  ASSERT_TRUE(gpu_scene);
  HiddenSampleMapperOptions draw_all;
  draw_all.cull_clusters = false;
  auto all_mapper = HiddenSampleMapper::Create(testing::SharedGpuWorker(), draw_all);
  ASSERT_TRUE(all_mapper.ok()) << all_mapper.status();
  HiddenSampleMapRequest r = UnitRequest(200, 20);
  for (const bool bumpy : {false, true}) {
    SCOPED_TRACE(bumpy ? "bumpy, decorrelated" : "flat");
    r.receiver.heightfield.clear();
    if (bumpy)
      for (int k = 0; k < 20 * 20; ++k) r.receiver.heightfield.push_back(0.15f * std::sin(0.9f * k));
    r.options.decorrelate = bumpy;
    for (const LookupMode lookup : {LookupMode::kExact, LookupMode::kHough}) {
      r.options.lookup = lookup;
      ExpectCulledGivesTheBitsOfDrawingAll(Mapper(), **all_mapper, *gpu_scene, r);
    }
    auto drawn = Mapper().TrianglesDrawnPerPass(*gpu_scene, r);
    auto drawn_all = (*all_mapper)->TrianglesDrawnPerPass(*gpu_scene, r);
    ASSERT_TRUE(drawn.ok() && drawn_all.ok());
    EXPECT_EQ(*drawn_all, level.TriangleCount());
    EXPECT_LT(*drawn, level.TriangleCount() / 4) << "one copy of 16 and its neighbours' edges";
    EXPECT_GT(*drawn, 0u);
  }
}

// The GPU holds a repeated mesh once and draws it at each placement: the
// level of copies gives the flattened level's bits, drawn whole or culled
// (planes taken into each placement's own space), at a twelfth of the bytes.
TEST(HiddenSampleMap, PlacedCopiesGiveTheFlattenedLevelsBits) {
  const Scene level = testing::MakeCopies(RandomCloud(300, 37, {-0.2, 0.2, -0.2}, {1.2, 0.95, 1.2}, 0.08), 16);
  ASSERT_EQ(level.placements.size(), 16u);
  auto placed = Upload(level);
  auto flat = Upload(testing::Flattened(level));
  ASSERT_TRUE(placed && flat);
  EXPECT_EQ(placed->instance_count(), 16u);
  EXPECT_EQ(placed->held_triangle_count(), level.TriangleCount() / 16);
  EXPECT_EQ(flat->instance_count(), 0u);
  EXPECT_EQ(placed->gpu_bytes(), GpuScene::EstimateBytes(level));
  EXPECT_LT(placed->gpu_bytes(), flat->gpu_bytes() / 12) << placed->gpu_bytes() << " vs " << flat->gpu_bytes();
  HiddenSampleMapperOptions draw_all;
  draw_all.cull_clusters = false;
  auto all_mapper = HiddenSampleMapper::Create(testing::SharedGpuWorker(), draw_all);
  ASSERT_TRUE(all_mapper.ok()) << all_mapper.status();
  HiddenSampleMapRequest r = UnitRequest(128, 20);
  // A source above the copies' middle, the receiver under four of them.
  r.source.patch = {{1.0, 2.0, 1.0}, {0.6, 0, 0}, {0, 0, 0.6}};
  r.receiver.patch = {{0.2, 0.0, 0.2}, {2.4, 0, 0}, {0, 0, 2.4}};
  for (const LookupMode lookup : {LookupMode::kExact, LookupMode::kHough}) {
    r.options.lookup = lookup;
    auto flat_map = Mapper().Compute(*flat, r);
    auto placed_culled = Mapper().Compute(*placed, r);
    auto placed_all = (*all_mapper)->Compute(*placed, r);
    ASSERT_TRUE(flat_map.ok() && placed_culled.ok() && placed_all.ok());
    EXPECT_EQ(placed_culled->blocked_bits, flat_map->blocked_bits);
    EXPECT_EQ(placed_all->blocked_bits, flat_map->blocked_bits);
    const auto [lo, hi] = std::minmax_element(flat_map->visible_fraction.begin(), flat_map->visible_fraction.end());
    EXPECT_LT(*lo, 0.9f);
    EXPECT_GT(*hi, 0.1f);
  }
  auto drawn = Mapper().TrianglesDrawnPerPass(*placed, r);
  auto drawn_flat = Mapper().TrianglesDrawnPerPass(*flat, r);
  ASSERT_TRUE(drawn.ok() && drawn_flat.ok());
  EXPECT_LT(*drawn, level.TriangleCount() / 2) << "the shaft holds a few copies";
  EXPECT_GT(*drawn, 0u);
  std::printf("triangles drawn: placed %llu, flattened %llu of %zu\n", static_cast<unsigned long long>(*drawn),
              static_cast<unsigned long long>(*drawn_flat), level.TriangleCount());
}

// A placement whose float transform would lose the flattened upload's
// precision (here a scale of 8 along one axis: condition number 8) is drawn
// from flattened corners; the others stay instances, and the bits are the
// flattened level's.
TEST(HiddenSampleMap, PlacementsThatWouldLosePrecisionAreDrawnFlattened) {
  const Scene cloud = RandomCloud(200, 41, {-0.2, 0.2, -0.2}, {1.2, 0.95, 1.2}, 0.08);
  std::vector<glm::dmat4> worlds = testing::CopyWorlds(cloud, 4);
  glm::dmat4 stretch(1.0);
  stretch[0][0] = 8.0;
  worlds[1] = worlds[1] * stretch;
  const Scene level = testing::PlaceMesh(cloud, worlds);
  ASSERT_EQ(level.placements.size(), 4u);
  auto placed = Upload(level);
  auto flat = Upload(testing::Flattened(level));
  ASSERT_TRUE(placed && flat);
  EXPECT_EQ(placed->instance_count(), 3u);
  EXPECT_EQ(placed->held_triangle_count(), 2 * cloud.TriangleCount());
  EXPECT_EQ(placed->gpu_bytes(), GpuScene::EstimateBytes(level));
  HiddenSampleMapRequest r = UnitRequest(64, 16);
  r.source.patch = {{0.5, 3.0, 0.5}, {1.0, 0, 0}, {0, 0, 1.0}};
  r.receiver.patch = {{0.0, 0.0, 0.0}, {3.0, 0, 0}, {0, 0, 3.0}};
  auto flat_map = Mapper().Compute(*flat, r);
  auto placed_map = Mapper().Compute(*placed, r);
  ASSERT_TRUE(flat_map.ok() && placed_map.ok());
  EXPECT_EQ(placed_map->blocked_bits, flat_map->blocked_bits);
}

// The same on a real level: four copies of Sponza, the query in the first.
TEST(HiddenSampleMapRealScenes, SponzaCopiesCulledGiveTheBitsOfDrawingEverything) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  const Scene sponza = LoadOrFail(dir / "sponza_dabrovic/sponza.gltf");
  ASSERT_GT(sponza.TriangleCount(), 0u);
  const Scene level = testing::MakeCopies(sponza, 4);
  auto gpu_scene = Upload(level);
  ASSERT_TRUE(gpu_scene);
  HiddenSampleMapperOptions draw_all;
  draw_all.cull_clusters = false;
  auto all_mapper = HiddenSampleMapper::Create(testing::SharedGpuWorker(), draw_all);
  ASSERT_TRUE(all_mapper.ok()) << all_mapper.status();
  // A light patch high in the atrium, the atrium floor (at y = 0.135, far
  // above the foundations' bounds) as receiver, as the benchmark queries.
  const glm::dvec3 lo = sponza.bounds.min, e = sponza.bounds.Extent(), m = sponza.bounds.Center();
  const double ls = 0.08 * e.x;
  HiddenSampleMapRequest r = SceneRequest(sponza, 0.75, 0.1, 128, 24);
  r.source.patch = {{m.x - ls / 2, lo.y + 0.75 * e.y, m.z - ls / 2}, {ls, 0, 0}, {0, 0, ls}};
  r.receiver.patch = {{lo.x + 0.15 * e.x, 0.135, m.z - 0.2 * e.z}, {0.7 * e.x, 0, 0}, {0, 0, 0.4 * e.z}};
  r.options.decorrelate = true;
  for (const LookupMode lookup : {LookupMode::kExact, LookupMode::kHough}) {
    r.options.lookup = lookup;
    ExpectCulledGivesTheBitsOfDrawingAll(Mapper(), **all_mapper, *gpu_scene, r);
  }
  auto drawn = Mapper().TrianglesDrawnPerPass(*gpu_scene, r);
  ASSERT_TRUE(drawn.ok()) << drawn.status();
  EXPECT_LT(*drawn, sponza.TriangleCount()) << "at most the first copy's share";
}

}  // namespace
}  // namespace visq::gpu
