// The GPU ray method against Embree: the same FloatSegments over the same
// frame, so every bit must agree except where a segment ties with a
// triangle's edge or plane in float arithmetic. The tests count those
// differences and hold them to a few in a million segments.
#include <algorithm>
#include <atomic>
#include <cstdio>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "gpu_test_support.h"
#include "raycast/embree_scene.h"
#include "raycast/flat_bvh.h"
#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "test_support.h"
#include "visq/gpu/ray_scene.h"

namespace visq {
namespace {

using raycast::Segment;

std::shared_ptr<gpu::RayScene> UploadOrFail(const Scene& scene) {
  auto bvh = raycast::BuildFlatBvh(scene);
  EXPECT_TRUE(bvh.ok()) << bvh.status();
  if (!bvh.ok()) return nullptr;
  EXPECT_LE(bvh->depth, raycast::kMaxFlatBvhDepth);
  EXPECT_EQ(bvh->triangle_count(), scene.TriangleCount());
  auto rays = gpu::RayScene::Upload(testing::SharedGpuWorker(), *bvh);
  EXPECT_TRUE(rays.ok()) << rays.status();
  return rays.ok() ? *rays : nullptr;
}

// Segments between random points of the scene's bounds (shrunk a little), so
// that about half are blocked in a closed room.
std::vector<Segment> RandomSegments(const Scene& scene, size_t count, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> unit(0.05, 0.95);
  const glm::dvec3 lo = scene.bounds.min, extent = scene.bounds.Extent();
  auto point = [&] { return lo + glm::dvec3(unit(rng), unit(rng), unit(rng)) * extent; };
  std::vector<Segment> segments(count);
  for (Segment& s : segments) {
    s.p = point();
    s.q = point();
  }
  return segments;
}

struct Comparison {
  size_t blocked = 0;
  size_t differ = 0;
};

Comparison Compare(const Scene& scene, const std::vector<Segment>& segments) {
  Comparison out;
  auto embree = raycast::EmbreeScene::Create(scene);
  EXPECT_TRUE(embree.ok()) << embree.status();
  const std::shared_ptr<gpu::RayScene> rays = UploadOrFail(scene);
  if (!embree.ok() || !rays) return out;
  EXPECT_EQ(rays->origin(), embree->origin());
  auto reference = embree->Occluded(segments);
  auto traced = rays->Occluded(segments.size(), [&](size_t i) { return segments[i]; });
  EXPECT_TRUE(reference.ok()) << reference.status();
  EXPECT_TRUE(traced.ok()) << traced.status();
  if (!reference.ok() || !traced.ok()) return out;
  EXPECT_EQ(traced->size(), segments.size());
  for (size_t i = 0; i < segments.size(); ++i) {
    out.blocked += (*reference)[i];
    out.differ += (*reference)[i] != (*traced)[i];
  }
  return out;
}

TEST(RayScene, CornellBoxSegmentsMatchEmbree) {
  const Scene scene = MakeCornellBox();
  const std::vector<Segment> segments = RandomSegments(scene, 200000, 7);
  const Comparison c = Compare(scene, segments);
  std::printf("Cornell box: %zu of %zu segments blocked, %zu differ from Embree\n", c.blocked, segments.size(),
              c.differ);
  EXPECT_GT(c.blocked, segments.size() / 20);
  EXPECT_LT(c.blocked, segments.size() * 19 / 20);
  EXPECT_LE(c.differ, 2u);
}

TEST(RayScene, SharedScenesMatchEmbree) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  for (const char* file : {"sponza_dabrovic/sponza.gltf", "interior_veach_ajar/veach_ajar.gltf"}) {
    const std::filesystem::path path = dir / file;
    if (!std::filesystem::exists(path)) {
      ADD_FAILURE() << path << " is missing from the shared scenes";
      continue;
    }
    auto scene = LoadGltfFile(path);
    ASSERT_TRUE(scene.ok()) << scene.status();
    const std::vector<Segment> segments = RandomSegments(*scene, 100000, 11);
    const Comparison c = Compare(*scene, segments);
    std::printf("%s: %zu of %zu segments blocked, %zu differ from Embree\n", file, c.blocked, segments.size(),
                c.differ);
    EXPECT_GT(c.blocked, 0u) << file;
    EXPECT_LE(c.differ, segments.size() / 20000) << file;
  }
}

// Closest hits: the same triangle as Embree's at the same t (float
// rounding of the same test), u and v as Embree's weights of corners 1
// and 2, and the same misses (rays of bounded length).
TEST(RayScene, ClosestHitsMatchEmbree) {
  VISQ_REQUIRE_SHARED_SCENES(dir);
  for (const char* file : {"cornell", "interior_veach_ajar/veach_ajar.gltf"}) {
    Scene scene;
    if (std::string(file) == "cornell") {
      scene = MakeCornellBox();
    } else {
      auto loaded = LoadGltfFile(dir / file);
      ASSERT_TRUE(loaded.ok()) << loaded.status();
      scene = std::move(*loaded);
    }
    std::vector<raycast::Ray> rays;
    const double d_max = 0.3 * glm::length(scene.bounds.Extent());
    for (const Segment& s : RandomSegments(scene, 100000, 13))
      rays.push_back({s.p, glm::normalize(s.q - s.p), d_max, raycast::kNoTriangle});
    auto embree = raycast::EmbreeScene::Create(scene);
    ASSERT_TRUE(embree.ok()) << embree.status();
    const std::shared_ptr<gpu::RayScene> gpu_rays = UploadOrFail(scene);
    ASSERT_NE(gpu_rays, nullptr);
    auto reference = embree->Intersect(rays);
    auto traced = gpu_rays->Intersect(rays);
    ASSERT_TRUE(reference.ok()) << reference.status();
    ASSERT_TRUE(traced.ok()) << traced.status();
    // A tie: another triangle at the same t (a ray through the edge two
    // triangles share, or a box's face standing on the floor).
    size_t hits = 0, ties = 0, other = 0, far_t = 0, far_uv = 0;
    for (size_t i = 0; i < rays.size(); ++i) {
      const raycast::Hit& a = (*reference)[i];
      const raycast::Hit& b = (*traced)[i];
      hits += a.hit;
      if (a.hit != b.hit) {
        ++other;
        continue;
      }
      if (!a.hit) continue;
      const bool same_t = std::abs(a.t - b.t) <= 1e-5 * (1.0 + a.t);
      if (a.triangle != b.triangle) {
        (same_t ? ties : other) += 1;
        continue;
      }
      far_t += !same_t;
      // Barycentrics from another formula (Embree's against the watertight
      // test's edge functions): a thin triangle's differ in the 4th digit.
      far_uv += std::abs(a.u - b.u) > 1e-4 || std::abs(a.v - b.v) > 1e-4;
    }
    std::printf("%s: %zu of %zu rays hit; %zu tie with another triangle at the same t, %zu differ otherwise, %zu in "
                "t, %zu in u or v beyond 1e-4\n",
                file, hits, rays.size(), ties, other, far_t, far_uv);
    EXPECT_GT(hits, rays.size() / 10) << file;
    EXPECT_LT(hits, rays.size()) << file;
    EXPECT_LE(ties, rays.size() / 1000) << file;
    EXPECT_LE(other, rays.size() / 20000) << file;
    EXPECT_EQ(far_t, 0u) << file;
    EXPECT_LE(far_uv, hits / 5000) << file;
  }
}

// A segment from a point on a triangle: blocked by that triangle only if
// it is not ignored; the same per-segment ignore as Embree's.
TEST(RayScene, ASegmentIgnoresItsOwnTriangleAsEmbreeDoes) {
  Scene scene;
  scene.materials.emplace_back();
  AddQuad(scene, "floor", {-1, 0, -1}, {2, 0, 0}, {0, 0, 2}, 0);
  AddQuad(scene, "wall", {-1, 0, 0.5}, {2, 0, 0}, {0, 2, 0}, 0);
  UpdateBounds(scene);
  // Through the wall's first triangle (2): blocked unless that one is
  // ignored; the floor (0) and the wall's other half (3) change nothing.
  std::vector<Segment> segments = {{{0.0, 0.5, 0.0}, {0.0, 0.5, 1.0}, raycast::kNoTriangle},
                                   {{0.0, 0.5, 0.0}, {0.0, 0.5, 1.0}, 0},
                                   {{0.0, 0.5, 0.0}, {0.0, 0.5, 1.0}, 2},
                                   {{0.0, 0.5, 0.0}, {0.0, 0.5, 1.0}, 3},
                                   {{0.0, 0.5, 0.0}, {0.0, 0.5, 0.2}, raycast::kNoTriangle},
                                   {{0.0, 0.5, 0.0}, {0.0, 0.5, 0.0}, raycast::kNoTriangle}};
  const std::shared_ptr<gpu::RayScene> rays = UploadOrFail(scene);
  ASSERT_NE(rays, nullptr);
  auto traced = rays->Occluded(segments.size(), [&](size_t i) { return segments[i]; });
  ASSERT_TRUE(traced.ok()) << traced.status();
  EXPECT_EQ(*traced, (std::vector<uint8_t>{1, 1, 0, 1, 0, 0}));
  auto embree = raycast::EmbreeScene::Create(scene);
  ASSERT_TRUE(embree.ok());
  EXPECT_EQ(*traced, *embree->Occluded(segments));
}

TEST(RayScene, AnEmptySceneBlocksNothing) {
  const std::shared_ptr<gpu::RayScene> rays = UploadOrFail(Scene{});
  ASSERT_NE(rays, nullptr);
  auto traced = rays->Occluded(3, [](size_t i) { return Segment{{0, 0, 0}, {1.0 + double(i), 0, 0}}; });
  ASSERT_TRUE(traced.ok()) << traced.status();
  EXPECT_EQ(*traced, (std::vector<uint8_t>{0, 0, 0}));
}

TEST(RayScene, AStoppedCallTracesNothing) {
  const Scene scene = MakeCornellBox();
  const std::shared_ptr<gpu::RayScene> rays = UploadOrFail(scene);
  ASSERT_NE(rays, nullptr);
  std::atomic<bool> cancelled{true};
  gpu::RayTraceOptions options;
  options.job.stop.cancelled = &cancelled;
  size_t made = 0;
  auto traced = rays->Occluded(
      1000000, [&](size_t) { ++made; return Segment{{0, 0.5, 0}, {0, 0.6, 0}}; }, options);
  EXPECT_EQ(traced.status().code(), absl::StatusCode::kCancelled) << traced.status();
  EXPECT_EQ(made, 0u);
}

}  // namespace
}  // namespace visq
