#include "raycast/embree_scene.h"

#include <algorithm>
#include <array>
#include <memory>
#include <random>

#include <glm/gtc/matrix_transform.hpp>
#include <gtest/gtest.h>

#include "large_scene.h"
#include "raycast/embree_float_mode.h"
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

#if defined(__SSE__) || defined(__x86_64__)
// Whether the thread's MXCSR makes a denormal float input count as zero.
bool DenormalsReadAsZero() {
  volatile float denormal = 1e-39f;
  volatile float product = denormal * 1.0f;
  return product == 0.0f;
}

// Rays are traced with flush-to-zero and denormals-are-zero, as Embree
// expects, and the thread gets its own mode back: the exact method runs on
// the same threads and its error filters count on gradual underflow.
TEST(EmbreeSceneTest, RaysAreTracedInEmbreesFloatModeAndTheThreadsModeIsRestored) {
  ASSERT_FALSE(DenormalsReadAsZero()) << "the test process starts in the IEEE mode";
  {
    const EmbreeFloatMode float_mode;
    EXPECT_TRUE(DenormalsReadAsZero());
    EXPECT_EQ(_mm_getcsr() & _MM_FLUSH_ZERO_ON, unsigned{_MM_FLUSH_ZERO_ON});
  }
  EXPECT_FALSE(DenormalsReadAsZero());
  const unsigned before = _mm_getcsr();
  auto scene = EmbreeScene::Create(OneTriangle());
  ASSERT_TRUE(scene.ok()) << scene.status();
  // A segment whose direction has a denormal component still gets its answer.
  TraceOptions one_thread;
  one_thread.threads = 1;
  auto r = scene->Occluded(std::vector<Segment>{{{0.2, 0.2, -1}, {0.2 + 1e-39, 0.2, 1}}}, one_thread);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(*r, std::vector<uint8_t>{1});
  EXPECT_EQ(_mm_getcsr(), before);
  EXPECT_FALSE(DenormalsReadAsZero());
}
#endif

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


// A mesh placed by rotations, uniform scales and translations: traced as
// instances it answers as the flattened scene does. Random segments through
// the placements, segments leaving the meshes' own surfaces (the offset
// that skips a receiver's triangle) and ignored triangles inside instances.
TEST(EmbreeSceneTest, PlacedMeshesTraceAsInstancesWithTheFlattenedAnswers) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<std::array<glm::dvec3, 3>> cloud;
  for (int i = 0; i < 60; ++i) {
    const glm::dvec3 c(u(rng), u(rng), u(rng));
    std::array<glm::dvec3, 3> t;
    for (auto& p : t) {
      const double x = u(rng), y = u(rng), z = u(rng);
      p = c + 0.3 * glm::dvec3(x, y, z);
    }
    cloud.push_back(t);
  }
  const Scene mesh = SceneOfTriangles(cloud);
  std::vector<glm::dmat4> worlds;
  for (int i = 0; i < 12; ++i) {
    glm::dmat4 w = glm::translate(glm::dmat4(1.0), glm::dvec3(2.0 * (i % 4), 0.5 * (i % 3), 2.0 * (i / 4)));
    w = glm::rotate(w, 0.9 * i, glm::normalize(glm::dvec3(1.0, 2.0, 0.5 * i)));
    w = glm::scale(w, glm::dvec3(0.6 + 0.1 * (i % 5)));
    worlds.push_back(w);
  }
  const Scene placed = testing::PlaceMesh(mesh, worlds);
  ASSERT_TRUE(ValidatePlacements(placed).ok()) << ValidatePlacements(placed);
  auto instanced = EmbreeScene::Create(placed);
  EmbreeSceneOptions flatten;
  flatten.instance_meshes = false;
  auto flat = EmbreeScene::Create(placed, flatten);
  ASSERT_TRUE(instanced.ok() && flat.ok());
  EXPECT_EQ(instanced->instance_count(), worlds.size());
  EXPECT_EQ(instanced->instanced_triangle_count(), placed.TriangleCount());
  EXPECT_EQ(flat->instance_count(), 0u);
  // One mesh's BVH and twelve instances against twelve meshes' worth.
  EXPECT_LT(instanced->memory_bytes(), flat->memory_bytes() / 2);

  const Bounds& b = placed.bounds;
  std::uniform_real_distribution<double> in_x(b.min.x, b.max.x), in_y(b.min.y, b.max.y), in_z(b.min.z, b.max.z);
  std::uniform_int_distribution<uint32_t> any_triangle(0, static_cast<uint32_t>(placed.TriangleCount() - 1));
  std::vector<Segment> segments;
  std::vector<Ray> rays;
  for (int i = 0; i < 20000; ++i) {
    const double px = in_x(rng), py = in_y(rng), pz = in_z(rng), qx = in_x(rng), qy = in_y(rng), qz = in_z(rng);
    segments.push_back({{px, py, pz}, {qx, qy, qz}});
    rays.push_back({{px, py, pz}, glm::dvec3(qx, qy, qz) - glm::dvec3(px, py, pz)});
  }
  // A segment that leaves a surface nearly along it (under 0.6 degrees) is
  // a float tie at its origin: the float32 upload decides, and the
  // instance's upload rounds differently.
  std::vector<uint8_t> grazing(segments.size() + 5000, 0);
  for (int i = 0; i < 5000; ++i) {  // from a point on a triangle, that triangle ignored or not
    const uint32_t t = any_triangle(rng);
    const double a = 0.5 * (u(rng) + 1.0), c = 0.5 * (u(rng) + 1.0) * (1.0 - a);
    const glm::dvec3 on = placed.Vertex(t, 0) + a * (placed.Vertex(t, 1) - placed.Vertex(t, 0)) +
                          c * (placed.Vertex(t, 2) - placed.Vertex(t, 0));
    const glm::dvec3 to(in_x(rng), in_y(rng), in_z(rng));
    const glm::dvec3 normal = glm::normalize(glm::cross(placed.Vertex(t, 1) - placed.Vertex(t, 0),
                                                        placed.Vertex(t, 2) - placed.Vertex(t, 0)));
    grazing[segments.size()] = std::abs(glm::dot(normal, glm::normalize(to - on))) < 0.01;
    segments.push_back({on, to, i % 2 == 0 ? t : kNoTriangle});
    rays.push_back({on, to - on, 1.0, i % 2 == 0 ? t : kNoTriangle});
  }
  const std::vector<uint8_t> want = Occ(*flat, segments), got = Occ(*instanced, segments);
  ASSERT_EQ(got.size(), want.size());
  size_t blocked = 0, differing = 0;
  for (size_t i = 0; i < got.size(); ++i) {
    blocked += want[i];
    differing += got[i] != want[i];
    EXPECT_TRUE(got[i] == want[i] || grazing[i]) << "segment " << i;
  }
  EXPECT_LE(differing, 5u);
  EXPECT_GT(blocked, segments.size() / 10);
  EXPECT_LT(blocked, segments.size() * 9 / 10);

  // Closest hits: the same triangle and distance (to float rounding), away
  // from the ties.
  auto want_hits = flat->Intersect(rays), got_hits = instanced->Intersect(rays);
  ASSERT_TRUE(want_hits.ok() && got_hits.ok());
  size_t other_triangle = 0;
  for (size_t i = 0; i < rays.size(); ++i) {
    const Hit &w = (*want_hits)[i], &g = (*got_hits)[i];
    if (grazing[i]) continue;
    ASSERT_EQ(w.hit, g.hit) << "ray " << i;
    if (!w.hit) continue;
    other_triangle += w.triangle != g.triangle;
    EXPECT_NEAR(w.t, g.t, 1e-5) << "ray " << i;
    if (w.triangle == g.triangle) {
      EXPECT_NEAR(w.u, g.u, 1e-4);
      EXPECT_NEAR(w.v, g.v, 1e-4);
    }
  }
  EXPECT_LE(other_triangle, rays.size() / 1000);  // a ray through a shared edge may name either side

  // A batch-wide ignore list names instanced triangles too.
  std::vector<uint32_t> ignore(placed.TriangleCount());
  for (uint32_t t = 0; t < ignore.size(); ++t) ignore[t] = t;
  TraceOptions ignore_all;
  ignore_all.ignore_triangles = ignore;
  auto none = instanced->Occluded(segments, ignore_all);
  ASSERT_TRUE(none.ok());
  EXPECT_EQ(std::count(none->begin(), none->end(), 1), 0);
}

Scene RandomTriangles(std::mt19937& rng, int count, const glm::dvec3& centre) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<std::array<glm::dvec3, 3>> cloud;
  for (int i = 0; i < count; ++i) {
    const glm::dvec3 c = centre + 0.5 * glm::dvec3(u(rng), u(rng), u(rng));
    std::array<glm::dvec3, 3> t;
    for (auto& p : t) {
      const double x = u(rng), y = u(rng), z = u(rng);
      p = c + 0.3 * glm::dvec3(x, y, z);
    }
    cloud.push_back(t);
  }
  return SceneOfTriangles(cloud);
}

// Closest hits of random rays through the scene: the same triangle as the
// flattened scene's for all but ties on shared edges, at the same distance.
void ExpectFlattenedHits(const Scene& placed, const EmbreeScene& instanced, std::mt19937& rng) {
  EmbreeSceneOptions flatten;
  flatten.instance_meshes = false;
  auto flat = EmbreeScene::Create(placed, flatten);
  ASSERT_TRUE(flat.ok());
  const Bounds& b = placed.bounds;
  std::uniform_real_distribution<double> in_x(b.min.x, b.max.x), in_y(b.min.y, b.max.y), in_z(b.min.z, b.max.z);
  std::vector<Ray> rays;
  std::vector<Segment> segments;
  for (int i = 0; i < 20000; ++i) {
    const glm::dvec3 p(in_x(rng), in_y(rng), in_z(rng)), q(in_x(rng), in_y(rng), in_z(rng));
    rays.push_back({p, q - p});
    segments.push_back({p, q});
  }
  EXPECT_EQ(Occ(instanced, segments), Occ(*flat, segments));
  auto want = flat->Intersect(rays), got = instanced.Intersect(rays);
  ASSERT_TRUE(want.ok() && got.ok());
  size_t hits = 0, other_triangle = 0;
  for (size_t i = 0; i < rays.size(); ++i) {
    ASSERT_EQ((*got)[i].hit, (*want)[i].hit) << "ray " << i;
    if (!(*want)[i].hit) continue;
    ++hits;
    other_triangle += (*got)[i].triangle != (*want)[i].triangle;
    EXPECT_NEAR((*got)[i].t, (*want)[i].t, 1e-5) << "ray " << i;
  }
  EXPECT_GT(hits, rays.size() / 10);
  EXPECT_LE(other_triangle, rays.size() / 1000);
}

// A prefab of three meshes placed by six parents: one Embree instance per
// parent (its meshes' boxes overlap; as instances of their own they would
// sit side by side in the top level), every mesh held once, and the
// flattened scene's answers, each hit naming its own scene triangle.
TEST(EmbreeSceneTest, APrefabsMeshesPlacedTogetherAreOneInstance) {
  std::mt19937 rng(23);
  const std::vector<Scene> parts = {RandomTriangles(rng, 40, glm::dvec3(0.0)), RandomTriangles(rng, 30, glm::dvec3(0.3)),
                                    RandomTriangles(rng, 20, glm::dvec3(-0.2, 0.4, 0.0))};
  std::vector<glm::dmat4> worlds;
  for (int i = 0; i < 6; ++i)
    worlds.push_back(glm::rotate(glm::translate(glm::dmat4(1.0), glm::dvec3(2.5 * (i % 3), 0.0, 2.5 * (i / 3))), 0.7 * i,
                                 glm::dvec3(0.0, 1.0, 0.0)));
  const Scene placed = testing::PlaceMeshes(parts, worlds);
  ASSERT_TRUE(ValidatePlacements(placed).ok()) << ValidatePlacements(placed);
  auto instanced = EmbreeScene::Create(placed);
  ASSERT_TRUE(instanced.ok());
  EXPECT_EQ(instanced->instance_count(), parts.size() * worlds.size());
  EXPECT_EQ(instanced->instance_group_count(), worlds.size());
  EXPECT_EQ(instanced->instanced_triangle_count(), placed.TriangleCount());
  ExpectFlattenedHits(placed, *instanced, rng);
}

// A mesh in two prefabs (part 0 with part 1 at two parents, alone at two
// others) is still held once: every placement of it is an instance of its
// own. A mesh placed once is flattened.
TEST(EmbreeSceneTest, AMeshInTwoPrefabsIsStillHeldOnce) {
  std::mt19937 rng(29);
  const std::vector<Scene> parts = {RandomTriangles(rng, 40, glm::dvec3(0.0)), RandomTriangles(rng, 30, glm::dvec3(0.3))};
  const std::vector<glm::dmat4> worlds = {glm::translate(glm::dmat4(1.0), glm::dvec3(0, 0, 0)),
                                          glm::translate(glm::dmat4(1.0), glm::dvec3(3, 0, 0))};
  Scene placed = testing::PlaceMeshes(parts, worlds);
  // Part 0 alone at two more parents (placed in the flattened arrays, then
  // held once again).
  FlattenPlacements(placed);
  auto place = [&](uint32_t mesh, const glm::dmat4& world) {
    const auto base = static_cast<uint32_t>(placed.positions.size());
    placed.placements.push_back(MeshPlacement{mesh, static_cast<uint32_t>(placed.triangles.size()), base, world});
    for (const glm::dvec3& p : parts[mesh].positions) {
      placed.positions.push_back(PlacePoint(world, p));
      placed.bounds.Extend(placed.positions.back());
    }
    for (const glm::uvec3& t : parts[mesh].triangles) placed.triangles.push_back(t + glm::uvec3(base));
    placed.triangle_material.insert(placed.triangle_material.end(), parts[mesh].triangles.size(), 0u);
    placed.triangle_node.insert(placed.triangle_node.end(), parts[mesh].triangles.size(), mesh);
  };
  place(0, glm::translate(glm::dmat4(1.0), glm::dvec3(0, 0, 3)));
  place(0, glm::translate(glm::dmat4(1.0), glm::dvec3(3, 0, 3)));
  HoldPlacementsOnce(placed);
  ASSERT_TRUE(ValidatePlacements(placed).ok()) << ValidatePlacements(placed);
  auto instanced = EmbreeScene::Create(placed);
  ASSERT_TRUE(instanced.ok());
  EXPECT_EQ(instanced->instance_count(), 6u);
  EXPECT_EQ(instanced->instance_group_count(), 6u);
  ExpectFlattenedHits(placed, *instanced, rng);

  // Without the parents of part 0 alone: one instance per parent.
  auto two = EmbreeScene::Create(testing::PlaceMeshes(parts, worlds));
  ASSERT_TRUE(two.ok());
  EXPECT_EQ(two->instance_group_count(), 2u);

  auto once = EmbreeScene::Create(testing::PlaceMeshes({parts[0]}, {worlds[1]}));
  ASSERT_TRUE(once.ok());
  EXPECT_EQ(once->instance_count(), 0u);
}

// Shared with the scene, the BVH reads the scene's triangle indices in
// place: the same answers, 12 bytes a triangle less, and the scene kept
// alive by the BVH alone.
TEST(EmbreeSceneTest, ASharedSceneLendsItsTriangleIndices) {
  auto scene = std::make_shared<const Scene>(testing::MakeRippledGrid(64));
  EmbreeSceneOptions shared_options;
  shared_options.shared_scene = scene;
  auto shared = EmbreeScene::Create(*scene, shared_options);
  auto own = EmbreeScene::Create(*scene);
  ASSERT_TRUE(shared.ok() && own.ok());
  EXPECT_LE(shared->memory_bytes() + 12 * scene->TriangleCount(), own->memory_bytes());
  // Another scene's pointer is ignored.
  EmbreeSceneOptions other;
  other.shared_scene = std::make_shared<const Scene>(OneTriangle());
  auto unshared = EmbreeScene::Create(*scene, other);
  ASSERT_TRUE(unshared.ok());
  EXPECT_EQ(unshared->memory_bytes(), own->memory_bytes());

  std::vector<Segment> segments;
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-2.0, 2.0);  // the grid spans [-1, 1]: some miss it
  for (int i = 0; i < 5000; ++i) segments.push_back({{u(rng), 0.5, u(rng)}, {u(rng), -0.5, u(rng)}});
  const std::vector<uint8_t> want = Occ(*own, segments);
  std::weak_ptr<const Scene> watch = scene;
  scene.reset();
  shared_options.shared_scene.reset();
  EXPECT_FALSE(watch.expired());
  EXPECT_EQ(Occ(*shared, segments), want);
  const long blocked = std::count(want.begin(), want.end(), 1);
  EXPECT_GT(blocked, 500);
  EXPECT_LT(blocked, 4500);
  shared = absl::InternalError("released");
  EXPECT_TRUE(watch.expired());
}

// Placements that would lose the flattened upload's precision as instances
// (a strong anisotropic scale) are traced flattened.
TEST(EmbreeSceneTest, IllConditionedPlacementsAreTracedFlattened) {
  Scene grid = testing::MakeRippledGrid(4);
  const Scene placed = testing::PlaceMesh(
      grid, {glm::dmat4(1.0), glm::scale(glm::translate(glm::dmat4(1.0), glm::dvec3(3, 0, 0)), glm::dvec3(1, 1, 8)),
             glm::translate(glm::dmat4(1.0), glm::dvec3(0, 0, 3))});
  ASSERT_TRUE(ValidatePlacements(placed).ok());
  auto scene = EmbreeScene::Create(placed);
  ASSERT_TRUE(scene.ok());
  EXPECT_EQ(scene->instance_count(), 2u);
  EXPECT_EQ(scene->instanced_triangle_count(), 2 * grid.TriangleCount());
  const Segment down{{3.2, 1.0, 0.3}, {3.2, -1.0, 0.3}};  // through the stretched copy
  EXPECT_EQ(Occ(*scene, {down}), std::vector<uint8_t>{1});
}

}  // namespace
}  // namespace visq::raycast
