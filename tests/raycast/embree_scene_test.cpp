#include "raycast/embree_scene.h"

#include <array>
#include <random>

#include <gtest/gtest.h>

#include "scene/sample_scenes.h"

namespace visq::raycast {
namespace {

Scene OneTriangle(const glm::dvec3& offset = glm::dvec3(0.0), double scale = 1.0) {
  const std::array<glm::dvec3, 3> t = {offset, offset + scale * glm::dvec3(1, 0, 0), offset + scale * glm::dvec3(0, 1, 0)};
  return SceneOfTriangles({&t, 1});
}

std::vector<uint8_t> Occ(const EmbreeScene& e, std::vector<Segment> segs) {
  auto r = e.Occluded(segs);
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? *r : std::vector<uint8_t>{};
}

TEST(EmbreeSceneTest, SingleTriangleBlocksCrossingSegments) {
  auto scene = EmbreeScene::Create(OneTriangle());
  ASSERT_TRUE(scene.ok()) << scene.status();
  auto r = Occ(*scene, {{{0.2, 0.2, -1}, {0.2, 0.2, 1}},     // through the interior
                        {{0.8, 0.8, -1}, {0.8, 0.8, 1}},     // misses (outside hypotenuse)
                        {{0.2, 0.2, 0.5}, {0.2, 0.2, 1}},    // entirely above
                        {{0.2, 0.2, 1}, {0.2, 0.2, -1}}});   // reversed direction
  EXPECT_EQ(r, (std::vector<uint8_t>{1, 0, 0, 1}));
}

TEST(EmbreeSceneTest, EndpointOnTriangleDoesNotBlock) {
  auto scene = EmbreeScene::Create(OneTriangle());
  ASSERT_TRUE(scene.ok());
  auto r = Occ(*scene, {{{0.2, 0.2, 0}, {0.3, 0.1, 1}},     // starts on the triangle
                        {{0.3, 0.1, 1}, {0.2, 0.2, 0}},     // ends on it
                        {{0.2, 0.2, 0}, {0.2, 0.2, 0}},     // degenerate
                        {{0.2, 0.2, 0}, {0.25, 0.2, -1}}}); // leaves through the back
  EXPECT_EQ(r, (std::vector<uint8_t>{0, 0, 0, 0}));
}

TEST(EmbreeSceneTest, IgnoredTrianglesNeverBlock) {
  auto scene = EmbreeScene::Create(OneTriangle());
  ASSERT_TRUE(scene.ok());
  std::vector<Segment> segs = {{{0.2, 0.2, -1}, {0.2, 0.2, 1}, 0}, {{0.2, 0.2, -1}, {0.2, 0.2, 1}}};
  auto r = scene->Occluded(segs);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(*r, (std::vector<uint8_t>{0, 1}));
  const uint32_t ignore[] = {0};
  TraceOptions opts;
  opts.ignore_triangles = ignore;
  r = scene->Occluded(segs, opts);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(*r, (std::vector<uint8_t>{0, 0}));
  auto h = scene->Intersect(std::vector<Ray>{{{0.2, 0.2, -1}, {0, 0, 1}, 10.0, 0}});
  ASSERT_TRUE(h.ok());
  EXPECT_FALSE((*h)[0].hit);
}

TEST(EmbreeSceneTest, TranslationByOneMillionKeepsAnswers) {
  const glm::dvec3 off(1e6, -1e6, 1e6);
  auto near = EmbreeScene::Create(OneTriangle());
  auto far = EmbreeScene::Create(OneTriangle(off, 1e-3));
  ASSERT_TRUE(near.ok() && far.ok());
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.5, 1.5);
  std::vector<Segment> a, b;
  for (int i = 0; i < 2000; ++i) {
    glm::dvec3 p(u(rng), u(rng), -1.0), q(u(rng), u(rng), 1.0);
    // Keep away from the edges so that float rounding cannot flip answers.
    auto cross = 0.5 * (p + q);
    const double margin = std::min({cross.x, cross.y, 1.0 - cross.x - cross.y});
    if (std::abs(margin) < 1e-3) continue;
    a.push_back({p, q});
    b.push_back({off + 1e-3 * p, off + 1e-3 * q});
  }
  EXPECT_EQ(Occ(*near, a), Occ(*far, b));
}

TEST(EmbreeSceneTest, IntersectDistancesMatchClosedForm) {
  auto scene = EmbreeScene::Create(OneTriangle());
  ASSERT_TRUE(scene.ok());
  std::vector<Ray> rays;
  // Rays from (x, y, h) towards the plane z = 0 along a tilted direction.
  for (int i = 0; i < 50; ++i) {
    const double h = 0.5 + 0.1 * i;
    rays.push_back({{0.1 + 0.002 * i, 0.2, h}, glm::normalize(glm::dvec3(0.05, 0.02, -1.0)), 100.0});
  }
  rays.push_back({{0.2, 0.2, 1.0}, {0, 0, 1}, 100.0});   // pointing away
  rays.push_back({{0.2, 0.2, 1.0}, {0, 0, -1}, 0.5});    // tmax too short
  auto hits = scene->Intersect(rays);
  ASSERT_TRUE(hits.ok());
  for (int i = 0; i < 50; ++i) {
    const Ray& r = rays[i];
    const double t = -r.origin.z / r.direction.z;
    const glm::dvec3 x = r.origin + t * r.direction;
    ASSERT_TRUE((*hits)[i].hit) << i;
    EXPECT_NEAR((*hits)[i].t, t, 1e-5 * t);
    EXPECT_EQ((*hits)[i].triangle, 0u);
    EXPECT_NEAR((*hits)[i].u, x.x, 1e-5);
    EXPECT_NEAR((*hits)[i].v, x.y, 1e-5);
  }
  EXPECT_FALSE((*hits)[50].hit);
  EXPECT_FALSE((*hits)[51].hit);
}

TEST(EmbreeSceneTest, BatchedAndSingleRayPathsAgree) {
  // A random triangle cloud and many random segments.
  Scene s;
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int t = 0; t < 500; ++t) {
    glm::dvec3 c(u(rng), u(rng), u(rng));
    for (int k = 0; k < 3; ++k) s.positions.push_back(c + 0.2 * glm::dvec3(u(rng), u(rng), u(rng)));
    s.triangles.push_back(glm::uvec3(3 * t, 3 * t + 1, 3 * t + 2));
  }
  for (const auto& p : s.positions) s.bounds.Extend(p);
  auto scene = EmbreeScene::Create(s);
  ASSERT_TRUE(scene.ok());
  std::vector<Segment> segs;
  std::vector<Ray> rays;
  for (int i = 0; i < 20000; ++i) {
    glm::dvec3 p(u(rng), u(rng), u(rng)), q(u(rng), u(rng), u(rng));
    segs.push_back({p, q});
    rays.push_back({p, q - p, 1.0});
  }
  TraceOptions many;
  many.threads = 4;
  auto batched = scene->Occluded(segs, many);
  auto hits = scene->Intersect(rays, many);
  ASSERT_TRUE(batched.ok() && hits.ok());
  int blocked = 0;
  for (size_t i = 0; i < segs.size(); i += 37) {
    TraceOptions one;
    one.threads = 1;
    auto single = scene->Occluded(std::span<const Segment>(&segs[i], 1), one);
    ASSERT_TRUE(single.ok());
    EXPECT_EQ((*single)[0], (*batched)[i]) << i;
  }
  for (size_t i = 0; i < segs.size(); ++i) {
    blocked += (*batched)[i];
    // A closest hit inside the segment exists exactly when it is occluded
    // (up to the shared end offsets).
    EXPECT_EQ((*batched)[i] != 0, (*hits)[i].hit && (*hits)[i].t < 1.0 - 1e-4) << i;
  }
  EXPECT_GT(blocked, 1000);
  EXPECT_LT(blocked, 19000);
}

TEST(EmbreeSceneTest, MoveOnlyAndInvalidIndices) {
  static_assert(!std::is_copy_constructible_v<EmbreeScene>);
  static_assert(std::is_nothrow_move_constructible_v<EmbreeScene>);
  Scene s = OneTriangle();
  s.triangles[0][2] = 7;
  auto bad = EmbreeScene::Create(s);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find("scene.triangles[0][2]"), std::string::npos);
  auto a = EmbreeScene::Create(OneTriangle());
  ASSERT_TRUE(a.ok());
  EmbreeScene b = std::move(*a);
  EXPECT_EQ(b.triangle_count(), 1u);
}

}  // namespace
}  // namespace visq::raycast
