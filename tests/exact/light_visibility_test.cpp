#include "exact/light_visibility.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>
#include <thread>

#include <glm/gtc/matrix_transform.hpp>
#include <gtest/gtest.h>

#include "exact/exact_geometry.h"
#include "large_scene.h"
#include "raycast/embree_scene.h"
#include "scene/gltf_loader.h"
#include "scene/sample_scenes.h"
#include "test_support.h"

namespace visq::exact {
namespace {

using Tri = std::array<glm::dvec3, 3>;

Scene MakeScene(const std::vector<Tri>& tris) { return SceneOfTriangles(tris); }

// A square light of half-size h centred at (0, 0, z), facing down (-z):
// counter-clockwise seen from below.
AreaLight SquareLight(double z, double h = 1.0, double radiance = 1.0) {
  return {{{-h, -h, z}, {-h, h, z}, {h, h, z}, {h, -h, z}}, radiance};
}

Bounds Box(const glm::dvec3& lo, const glm::dvec3& hi) {
  Bounds b;
  b.Extend(lo);
  b.Extend(hi);
  return b;
}

std::unique_ptr<LightVisibilityTree> MakeTree(const AreaLight& light, const Scene& scene,
                                              std::optional<Bounds> receivers,
                                              size_t direct_candidates = TreeOptions{}.direct_candidates) {
  TreeOptions options;
  options.receiver_bounds = receivers;
  options.direct_candidates = direct_candidates;
  auto tree = LightVisibilityTree::Create(light, scene, options);
  EXPECT_TRUE(tree.ok()) << tree.status();
  return tree.ok() ? std::move(*tree) : nullptr;
}

PointVisibility Q(LightVisibilityTree& tree, const glm::dvec3& p,
                  std::optional<glm::dvec3> n = glm::dvec3(0, 0, 1)) {
  auto r = tree.Query({p, n, std::nullopt});
  EXPECT_TRUE(r.ok()) << r.status();
  return r.ok() ? *r : PointVisibility{};
}

// Irradiance under the centre of a square of half-size h at height d, from
// the rectangle-to-parallel-differential-area form factor (4 quadrants).
double SquareIrradiance(double h, double d, double radiance) {
  const double a = h / d, b = h / d;
  const double f = (a / std::sqrt(1 + a * a) * std::atan(b / std::sqrt(1 + a * a)) +
                    b / std::sqrt(1 + b * b) * std::atan(a / std::sqrt(1 + b * b))) /
                   (2.0 * std::numbers::pi);
  return 4.0 * f * std::numbers::pi * radiance;
}

// ---------------------------------------------------------------------------
TEST(LightVisibilityTest, ValidationNamesTheField) {
  Scene empty;
  AreaLight light = SquareLight(1.0);
  light.vertices[2].y = std::nan("");
  auto r = LightVisibilityTree::Create(light, empty);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(r.status().message(), "light.vertices[2]: NaN coordinate");
  r = LightVisibilityTree::Create({{{0, 0, 0}, {1, 0, 0}, {2, 0, 0}}}, empty);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().message(), "light: zero area");
  r = LightVisibilityTree::Create({{{0, 0, 0}, {1, 0, 0}, {1, 1, 0.5}, {0, 1, 0}}}, empty);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("light: not planar"), std::string::npos);
  r = LightVisibilityTree::Create({{{0, 0, 0}, {1, 0, 0}}}, empty);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("light.vertices"), std::string::npos);
  r = LightVisibilityTree::Create({{{0, 0, 0}, {4, 0, 0}, {4, 2, 0}, {3, -1, 0}, {0, 2, 0}}}, empty);
  ASSERT_FALSE(r.ok());  // self-crossing, non-zero signed area
  EXPECT_NE(r.status().message().find("light: not a simple polygon"), std::string::npos);
  AreaLight negative = SquareLight(1.0, 1.0, -2.0);
  r = LightVisibilityTree::Create(negative, empty);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("light.radiance"), std::string::npos);

  auto tree = MakeTree(SquareLight(1.0), empty, Box({-1, -1, 0}, {1, 1, 0}));
  auto outside = tree->Query({{5, 5, 0}, glm::dvec3(0, 0, 1), std::nullopt});
  EXPECT_EQ(outside.status().code(), absl::StatusCode::kOutOfRange);
  auto nan = tree->Query({{std::nan(""), 0, 0}, std::nullopt, std::nullopt});
  EXPECT_EQ(nan.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(LightVisibilityTest, NothingInBetweenMatchesClosedFormIrradiance) {
  Scene empty;
  auto tree = MakeTree(SquareLight(2.0, 1.0, 3.0), empty, Box({-1, -1, 0}, {1, 1, 0}));
  const PointVisibility r = Q(*tree, {0, 0, 0});
  EXPECT_DOUBLE_EQ(r.visible_area_fraction, 1.0);
  EXPECT_NEAR(r.visible_solid_angle_fraction, 1.0, 1e-14);
  EXPECT_NEAR(r.irradiance, SquareIrradiance(1.0, 2.0, 3.0), 1e-12);
  // Light seen from behind: nothing.
  auto tree2 = MakeTree(SquareLight(-2.0), empty, std::nullopt);
  EXPECT_EQ(Q(*tree2, {0, 0, 0}).visible_area_fraction, 0.0);
}

// Creating a tree selects occluders from every triangle near the shaft
// (seconds on a large level): a call that was cancelled, or whose deadline
// passed, stops there.
TEST(LightVisibilityTest, CreationStopsForACancelledOrExpiredCall) {
  const Scene scene = MakeScene({{glm::dvec3(-1, -1, 1), glm::dvec3(1, -1, 1), glm::dvec3(0, 1, 1)}});
  std::atomic<bool> cancelled{true};
  TreeOptions options;
  options.stop.cancelled = &cancelled;
  auto tree = LightVisibilityTree::Create(SquareLight(2.0), scene, options);
  EXPECT_EQ(tree.status().code(), absl::StatusCode::kCancelled) << tree.status();
  options.stop.cancelled = nullptr;
  options.stop.deadline = std::chrono::steady_clock::now() - std::chrono::seconds(1);
  tree = LightVisibilityTree::Create(SquareLight(2.0), scene, options);
  EXPECT_EQ(tree.status().code(), absl::StatusCode::kDeadlineExceeded) << tree.status();
  options.stop.deadline = std::chrono::steady_clock::time_point::max();
  tree = LightVisibilityTree::Create(SquareLight(2.0), scene, options);
  EXPECT_TRUE(tree.ok()) << tree.status();
}

TEST(LightVisibilityTest, NonConvexLightIsTriangulated) {
  Scene empty;
  // An L-shaped light (area 3), facing down.
  AreaLight light{{{0, 0, 1}, {0, 2, 1}, {1, 2, 1}, {1, 1, 1}, {2, 1, 1}, {2, 0, 1}}, 1.0};
  auto tree = MakeTree(light, empty, std::nullopt);
  EXPECT_NEAR(tree->light_area(), 3.0, 1e-15);
  auto r = tree->Query({{0.5, 0.5, 0}, glm::dvec3(0, 0, 1), std::nullopt}, true);
  ASSERT_TRUE(r.ok());
  EXPECT_NEAR(r->visible_area_fraction, 1.0, 1e-15);
  EXPECT_EQ(r->visible_polygons.size(), 4u);
}

// Occluder triangle covering x < x0 at height z (big enough to cover the
// light's projection).
Tri HalfPlaneOccluder(double x0, double z, bool flip = false) {
  Tri t{glm::dvec3(x0, -50, z), glm::dvec3(x0, 50, z), glm::dvec3(x0 - 100, 0, z)};
  if (flip) std::swap(t[1], t[2]);
  return t;
}

TEST(LightVisibilityTest, TriangleCoveringHalfTheLight) {
  for (bool flip : {false, true}) {
    auto tree = MakeTree(SquareLight(2.0), MakeScene({HalfPlaneOccluder(0.0, 1.0, flip)}),
                         Box({-0.1, -0.1, 0}, {0.1, 0.1, 0}));
    const PointVisibility r = Q(*tree, {0, 0, 0});
    EXPECT_NEAR(r.visible_area_fraction, 0.5, 1e-14);
    EXPECT_NEAR(r.visible_solid_angle_fraction, 0.5, 1e-14);
    EXPECT_NEAR(r.irradiance, 0.5 * SquareIrradiance(1.0, 2.0, 1.0), 1e-13);
    EXPECT_EQ(tree->Stats().far_occluders, 1u);
  }
}

// Near occluders are culled in double precision when they miss the pyramid
// from the point to the light; the cull keeps a margin, so an occluder that
// enters the pyramid by a sliver still counts and one just outside changes
// nothing. Light [-1, 1]^2 at z = 2, point at the origin: at z = 1 the
// pyramid spans [-0.5, 0.5]^2, and an occluder over x >= 0.5 - d hides the
// strip x >= 1 - 2d of the light, a fraction d of it.
TEST(LightVisibilityTest, NearOccluderGrazingThePyramidCountsOnlyWhereItEnters) {
  for (const double d : {1e-9, 1e-12, 0.0, -1e-12, -1e-9}) {
    const double x0 = 0.5 - d;
    const Tri occluder{glm::dvec3(x0, -50, 1.0), glm::dvec3(x0 + 100, 0, 1.0), glm::dvec3(x0, 50, 1.0)};
    auto tree = MakeTree(SquareLight(2.0), MakeScene({occluder}), Box({-0.1, -0.1, 0}, {0.1, 0.1, 1.5}));
    ASSERT_NE(tree, nullptr);
    EXPECT_EQ(tree->Stats().near_occluders, 1u);
    const PointVisibility r = Q(*tree, {0, 0, 0});
    EXPECT_NEAR(r.visible_area_fraction, d > 0 ? 1.0 - d : 1.0, 1e-15) << "d = " << d;
  }
}

TEST(LightVisibilityTest, LightFullyCovered) {
  auto tree = MakeTree(SquareLight(2.0), MakeScene({HalfPlaneOccluder(60.0, 1.0)}),
                       Box({-0.1, -0.1, 0}, {0.1, 0.1, 0}));
  const PointVisibility r = Q(*tree, {0.05, -0.02, 0});
  EXPECT_EQ(r.visible_area_fraction, 0.0);
  EXPECT_EQ(r.irradiance, 0.0);
}

TEST(LightVisibilityTest, OverlappingOccludersGiveTheUnion) {
  // Shadow edges on the light plane z = 2 from P = 0: x = 0 and x = 0.25 * 2 / 1.5.
  const Scene scene = MakeScene({HalfPlaneOccluder(0.0, 1.0), HalfPlaneOccluder(0.25, 1.5)});
  for (auto receivers : {std::optional<Bounds>(Box({-0.1, -0.1, 0}, {0.1, 0.1, 0})),
                         std::optional<Bounds>()}) {
    auto tree = MakeTree(SquareLight(2.0), scene, receivers);
    const PointVisibility r = Q(*tree, {0, 0, 0});
    EXPECT_NEAR(r.visible_area_fraction, (1.0 - 1.0 / 3.0) / 2.0, 1e-14);
  }
  // Complementary occluders at different heights leave no crack.
  Tri right = HalfPlaneOccluder(0.0, 1.5);
  for (auto& p : right) p.x = -p.x;
  auto tree = MakeTree(SquareLight(2.0), MakeScene({HalfPlaneOccluder(0.0, 1.0), right}),
                       Box({-0.1, -0.1, 0}, {0.1, 0.1, 0}));
  EXPECT_EQ(Q(*tree, {0, 0, 0}).visible_area_fraction, 0.0);
  // From (0.05, 0, 0) the shadows end at x = -0.05 and x = -0.05 / 3.
  EXPECT_NEAR(Q(*tree, {0.05, 0, 0}).visible_area_fraction, 0.05 / 3.0, 1e-14);
}

TEST(LightVisibilityTest, OnlyOccludersBetweenCount) {
  // Occluders above the light and below the point never block.
  const Scene scene = MakeScene({HalfPlaneOccluder(60.0, 3.0), HalfPlaneOccluder(60.0, -1.0),
                                 HalfPlaneOccluder(60.0, 2.0)});  // and one in the light plane
  for (auto receivers : {std::optional<Bounds>(Box({-1, -1, 0}, {1, 1, 0})),
                         std::optional<Bounds>()}) {
    auto tree = MakeTree(SquareLight(2.0), scene, receivers);
    EXPECT_DOUBLE_EQ(Q(*tree, {0.3, 0.2, 0}).visible_area_fraction, 1.0);
  }
}

TEST(LightVisibilityTest, PointOnASurfaceIsNotShadowedByIt) {
  // A floor of two triangles at z = 0 with P on their shared edge and inside
  // one; a tilted light so the floor is not parallel to it.
  const Scene scene = MakeScene({{glm::dvec3(-5, -5, 0), glm::dvec3(5, -5, 0), glm::dvec3(5, 5, 0)},
                                 {glm::dvec3(-5, -5, 0), glm::dvec3(5, 5, 0), glm::dvec3(-5, 5, 0)},
                                 // A wall standing on the floor, far from the light's projection.
                                 {glm::dvec3(3, -5, 0), glm::dvec3(3, 5, 0), glm::dvec3(3, 0, 3)}});
  const AreaLight tilted{{{-1, -1, 2}, {-1, 1, 2.5}, {1, 1, 2.5}, {1, -1, 2}}, 1.0};
  for (auto receivers : {std::optional<Bounds>(Box({-5, -5, 0}, {5, 5, 0})),
                         std::optional<Bounds>()}) {
    auto tree = MakeTree(tilted, scene, receivers);
    EXPECT_NEAR(Q(*tree, {0, 0, 0}).visible_area_fraction, 1.0, 1e-14);
    EXPECT_NEAR(Q(*tree, {0.5, 0.5, 0}).visible_area_fraction, 1.0, 1e-14);
    EXPECT_NEAR(Q(*tree, {0.5, -0.5, 0}).visible_area_fraction, 1.0, 1e-14);
    auto by_id = tree->Query({{0.5, -0.5, 0}, std::nullopt, 0u});
    ASSERT_TRUE(by_id.ok());
    EXPECT_NEAR(by_id->visible_area_fraction, 1.0, 1e-14);
    EXPECT_GT(by_id->irradiance, 0.0);
    // A point at the wall's foot, on the light's side, still sees the light.
    EXPECT_GT(Q(*tree, {2.9, 0, 0}).visible_area_fraction, 0.5);
  }
}

// ---------------------------------------------------------------------------
// A random cloud of small triangles between a light at z = 2 and a floor.
std::vector<Tri> Cloud(int count, uint32_t seed, double size = 0.3) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1, 1), h(0.3, 1.7);
  std::vector<Tri> tris;
  for (int i = 0; i < count; ++i) {
    const glm::dvec3 c(1.5 * u(rng), 1.5 * u(rng), h(rng));
    Tri t;
    for (auto& p : t) p = c + size * glm::dvec3(u(rng), u(rng), u(rng));
    for (auto& p : t) p.z = std::clamp(p.z, 0.05, 1.95);
    tris.push_back(t);
  }
  return tris;
}

std::vector<glm::dvec3> FloorPoints(int count, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-1.5, 1.5);
  std::vector<glm::dvec3> pts;
  // Draws in sequence (an argument list's order is the compiler's): y, then x.
  for (int i = 0; i < count; ++i) {
    const double y = u(rng), x = u(rng);
    pts.emplace_back(x, y, 0.0);
  }
  return pts;
}

// Both trees' answers at a point of the floor (its receiver the floor's
// triangle under it), expected the same to 1e-12; the first tree's.
PointVisibility SameOnBoth(LightVisibilityTree& a, LightVisibilityTree& b, const glm::dvec3& p) {
  const uint32_t receiver = p.x - p.y > 0 ? 0u : 1u;
  auto x = a.Query({p, std::nullopt, receiver});
  auto y = b.Query({p, std::nullopt, receiver});
  EXPECT_TRUE(x.ok() && y.ok());
  if (!x.ok() || !y.ok()) return {};
  EXPECT_NEAR(x->visible_area_fraction, y->visible_area_fraction, 1e-12) << p.x << " " << p.y;
  EXPECT_NEAR(x->visible_solid_angle_fraction, y->visible_solid_angle_fraction, 1e-12) << p.x << " " << p.y;
  EXPECT_NEAR(x->irradiance, y->irradiance, 1e-12) << p.x << " " << p.y;
  return *x;
}

TEST(LightVisibilityTest, EmbreeSamplingConvergesToExact) {
  const Scene scene = MakeScene(Cloud(150, 11));
  const AreaLight light = SquareLight(2.0, 0.7);
  auto tree = MakeTree(light, scene, Box({-1.5, -1.5, 0}, {1.5, 1.5, 0}));
  auto embree = raycast::EmbreeScene::Create(scene);
  ASSERT_TRUE(embree.ok());
  const auto pts = FloorPoints(200, 5);
  std::vector<double> exact;
  for (const auto& p : pts) exact.push_back(Q(*tree, p).visible_area_fraction);

  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<double> rms;
  for (int n : {16, 256, 4096}) {
    std::vector<raycast::Segment> segs;
    for (const auto& p : pts) {
      for (int k = 0; k < n; ++k) {
        const glm::dvec3 y(0.7 * (2 * u(rng) - 1), 0.7 * (2 * u(rng) - 1), 2.0);
        segs.push_back({p, y});
      }
    }
    auto occ = embree->Occluded(segs);
    ASSERT_TRUE(occ.ok());
    double sq = 0.0;
    for (size_t i = 0; i < pts.size(); ++i) {
      int visible = 0;
      for (int k = 0; k < n; ++k) visible += (*occ)[i * n + k] == 0;
      const double est = static_cast<double>(visible) / n;
      const double err = est - exact[i];
      sq += err * err;
      // Binomial standard deviation is at most 0.5 / sqrt(n).
      EXPECT_LT(std::abs(err), 6.0 * 0.5 / std::sqrt(n) + 1e-3) << "point " << i << " n " << n;
    }
    rms.push_back(std::sqrt(sq / pts.size()));
  }
  // 1/sqrt(N): 16x the samples gives 4x less error (allow slack).
  EXPECT_LT(rms[1], rms[0] / 2.5);
  EXPECT_LT(rms[2], rms[1] / 2.5);
  EXPECT_LT(rms[2], 0.01);
  // Non-trivial shadows.
  double mean = 0.0;
  for (double e : exact) mean += e;
  mean /= exact.size();
  EXPECT_GT(mean, 0.1);
  EXPECT_LT(mean, 0.95);
}

// Boxes (12 triangles) standing on the floor: they touch the receivers, so
// they take the per-query "near" path.
void AddBox(std::vector<Tri>& tris, const glm::dvec3& lo, const glm::dvec3& hi) {
  auto c = [&](int i) {
    return glm::dvec3(i & 1 ? hi.x : lo.x, i & 2 ? hi.y : lo.y, i & 4 ? hi.z : lo.z);
  };
  const int faces[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                           {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& f : faces) {
    tris.push_back({c(f[0]), c(f[1]), c(f[2])});
    tris.push_back({c(f[0]), c(f[2]), c(f[3])});
  }
}

// Embree's rays from each floor point (the floor is triangles 0 and 1,
// split along x = y) to `samples` uniform points of the square light of
// half-side `half` at z = 2 agree with the exact fractions within six
// standard deviations of a fraction and the rays' float rounding.
void ExpectRaysAgree(const raycast::EmbreeScene& embree, const std::vector<glm::dvec3>& pts,
                     const std::vector<double>& exact, double half, int samples, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<raycast::Segment> segs;
  for (const glm::dvec3& p : pts) {
    const uint32_t receiver = p.x - p.y > 0 ? 0u : 1u;
    for (int k = 0; k < samples; ++k)
      segs.push_back({p, glm::dvec3(half * (2 * u(rng) - 1), half * (2 * u(rng) - 1), 2.0), receiver});
  }
  auto occ = embree.Occluded(segs);
  ASSERT_TRUE(occ.ok());
  for (size_t i = 0; i < pts.size(); ++i) {
    int visible = 0;
    for (int k = 0; k < samples; ++k) visible += (*occ)[i * samples + k] == 0;
    const double est = static_cast<double>(visible) / samples;
    EXPECT_LT(std::abs(est - exact[i]), 6.0 * 0.5 / std::sqrt(samples) + 2e-3)
        << "point " << i << " at " << pts[i].x << ", " << pts[i].y;
  }
}

TEST(LightVisibilityTest, NearOccludersMatchEmbreeAndTheAllNearPath) {
  // Floor (receiver, triangles 0 and 1), boxes on it, a cloud, and a wall
  // that passes through the light plane beside the light's centre.
  std::vector<Tri> tris = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                           {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)}};
  AddBox(tris, {-0.6, -0.3, 0}, {-0.3, 0.1, 0.5});
  AddBox(tris, {0.2, 0.2, 0}, {0.5, 0.6, 0.9});
  tris.push_back({glm::dvec3(1.0, -3, 0.5), glm::dvec3(1.0, 3, 0.5), glm::dvec3(0.2, 0, 3.0)});
  for (const Tri& t : Cloud(40, 61, 0.2)) tris.push_back(t);
  const Scene scene = MakeScene(tris);
  const AreaLight light = SquareLight(2.0, 0.7);
  // The BSP over the far occluders (every undecided point descends it),
  // the default route (every point subtracts its far and near candidates
  // itself), and all occluders near.
  auto with_bounds = MakeTree(light, scene, Box({-2, -2, 0}, {2, 2, 0}), 0);
  auto direct = MakeTree(light, scene, Box({-2, -2, 0}, {2, 2, 0}));
  auto all_near = MakeTree(light, scene, std::nullopt);
  EXPECT_GT(with_bounds->Stats().near_occluders, 20u);
  EXPECT_GT(with_bounds->Stats().far_occluders, 10u);
  EXPECT_EQ(all_near->Stats().far_occluders, 0u);
  auto embree = raycast::EmbreeScene::Create(scene);
  ASSERT_TRUE(embree.ok());

  const auto pts = FloorPoints(150, 17);
  std::vector<double> exact;
  for (const auto& p : pts) {
    exact.push_back(SameOnBoth(*with_bounds, *all_near, p).visible_area_fraction);
    SameOnBoth(*direct, *all_near, p);
  }
  ExpectRaysAgree(*embree, pts, exact, 0.7, 4096, 4);
  int shadowed = 0;
  for (double e : exact) shadowed += e < 0.99;
  EXPECT_GT(shadowed, 30);
}

// A bumpy grid of quadrilaterals with holes, each quadrilateral two
// triangles listed one after the other (as meshes list them), and some of
// them three: one triangle cut in two at the midpoint of an edge, so that
// the pair's union is a triangle whose middle vertex lies on its edge.
// Coordinates are dyadic, so the midpoints are exact.
std::vector<Tri> QuadGrid() {
  std::vector<Tri> tris;
  constexpr int kCells = 10;
  const auto at = [](int i, int j) {
    return glm::dvec3(-0.8 + 0.15625 * i, -0.8 + 0.15625 * j, 1.0 + 0.0625 * ((i * j) % 3));
  };
  for (int i = 0; i < kCells; ++i) {
    for (int j = 0; j < kCells; ++j) {
      if ((i * 7 + j * 3) % 5 == 0) continue;  // a hole
      const glm::dvec3 p00 = at(i, j), p10 = at(i + 1, j), p11 = at(i + 1, j + 1), p01 = at(i, j + 1);
      if ((i + j) % 2 == 0) {
        tris.push_back({p00, p10, p11});
        if ((i + j) % 4 == 0) {
          const glm::dvec3 m = 0.5 * (p01 + p00);
          tris.push_back({m, p11, p01});
          tris.push_back({m, p00, p11});
        } else {
          tris.push_back({p00, p11, p01});
        }
      } else {
        tris.push_back({p00, p10, p01});
        tris.push_back({p10, p11, p01});
      }
    }
  }
  return tris;
}

TEST(LightVisibilityTest, NeighbouringTrianglesSubtractedAsOneQuadrilateralGiveTheTrianglesAnswers) {
  const std::vector<Tri> floor = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                                  {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)}};
  const std::vector<Tri> grid = QuadGrid();
  // The same triangles with one below the floor after each: no two
  // candidates of a floor point are neighbours in the scene's order, so
  // every triangle is subtracted on its own.
  std::vector<Tri> listed = floor, apart = floor;
  for (const Tri& t : grid) {
    listed.push_back(t);
    apart.push_back(t);
    Tri below = t;
    for (glm::dvec3& v : below) v.z = -1.0 - v.z;
    apart.push_back(below);
  }
  const AreaLight light = SquareLight(2.0, 0.7);
  const Scene listed_scene = MakeScene(listed), apart_scene = MakeScene(apart);
  auto merging = MakeTree(light, listed_scene, std::nullopt);
  auto alone = MakeTree(light, apart_scene, std::nullopt);
  ASSERT_TRUE(merging && alone);
  int penumbra = 0;
  for (const glm::dvec3& p : FloorPoints(300, 23)) {
    const double visible = SameOnBoth(*merging, *alone, p).visible_area_fraction;
    penumbra += visible > 0.0 && visible < 1.0;
  }
  EXPECT_GT(penumbra, 100);
  // Most of the grid's quadrilaterals were subtracted whole, the cut
  // triangles' pairs among them; none of the separated triangles.
  EXPECT_GT(merging->Stats().merged_occluders, 2000u);
  EXPECT_EQ(alone->Stats().merged_occluders, 0u);
}

TEST(LightVisibilityTest, AStrictlyConvexLightSplitWholeGivesItsTrianglesAnswers) {
  // A strictly convex light in one plane is one piece: fragments start from
  // the whole polygon. The same polygon with a vertex in the middle of an
  // edge is not strictly convex, so its fragments start from its triangles
  // (the pieces of any light before). Both must give the same answers.
  std::vector<Tri> tris = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                           {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)}};
  for (const Tri& t : Cloud(150, 11)) tris.push_back(t);
  const Scene scene = MakeScene(tris);
  const double z = 2.0, h = 0.75;
  const std::vector<std::vector<glm::dvec3>> outlines = {
      {{-h, -h, z}, {-h, h, z}, {h, h, z}, {h, -h, z}},
      {{-h, 0, z}, {-0.5 * h, h, z}, {0.5 * h, h, z}, {h, 0, z}, {0.5 * h, -h, z}, {-0.5 * h, -h, z}}};
  for (const std::vector<glm::dvec3>& outline : outlines) {
    std::vector<glm::dvec3> straight = outline;
    straight.insert(straight.begin() + 1, 0.5 * (outline[0] + outline[1]));
    auto whole = MakeTree({outline, 1.0}, scene, std::nullopt);
    auto triangles = MakeTree({straight, 1.0}, scene, std::nullopt);
    ASSERT_TRUE(whole && triangles);
    int penumbra = 0;
    for (const glm::dvec3& p : FloorPoints(300, 23)) {
      const double visible = SameOnBoth(*whole, *triangles, p).visible_area_fraction;
      penumbra += visible > 0.0 && visible < 1.0;
    }
    EXPECT_GT(penumbra, 100) << outline.size() << " vertices";
  }
}

TEST(LightVisibilityTest, PointsHiddenByTheBlockersOfThePointBeforeAnswerAsOnAFreshThread) {
  // A ceiling of small quadrilaterals (two triangles each) with holes: from
  // the floor under it, no one triangle hides the light, a few dozen do
  // together. Points walk the floor row by row, as a frame's pixels come;
  // some in the middle lie on the ceiling itself, their own triangles among
  // the blockers the floor point before them remembered.
  std::vector<Tri> tris = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                           {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)}};
  // Dyadic corners: neighbouring cells share theirs exactly (with a step
  // of 0.2 they would leave cracks of 1e-16, which the method sees).
  constexpr int kCells = 13;
  constexpr double kCell = 0.25;
  std::vector<uint32_t> first_triangle_of_cell(kCells * kCells, 0);
  for (int i = 0; i < kCells; ++i) {
    for (int j = 0; j < kCells; ++j) {
      if ((i == 3 || i == 9) && j % 5 == 2) continue;  // holes
      first_triangle_of_cell[i * kCells + j] = static_cast<uint32_t>(tris.size());
      const glm::dvec3 a(-1.625 + kCell * i, -1.625 + kCell * j, 1.0);
      const glm::dvec3 b = a + glm::dvec3(kCell, 0, 0), c = a + glm::dvec3(kCell, kCell, 0),
                       d = a + glm::dvec3(0, kCell, 0);
      tris.push_back({a, b, c});
      tris.push_back({a, c, d});
    }
  }
  const Scene scene = MakeScene(tris);
  const AreaLight light = SquareLight(2.0, 0.7);
  auto walked = MakeTree(light, scene, std::nullopt);
  auto fresh = MakeTree(light, scene, std::nullopt);
  ASSERT_TRUE(walked && fresh);
  std::vector<QueryPoint> points;
  std::vector<QueryPoint> on_ceiling;
  for (int row = 0; row < 12; ++row) {
    for (int k = 0; k < 40; ++k) {
      const glm::dvec3 p(-1.4 + 2.8 * k / 39.0, -1.4 + 2.8 * row / 11.0, 0.0);
      points.push_back({p, glm::dvec3(0, 0, 1), p.x - p.y > 0 ? 0u : 1u});
      if (row == 6 && k == 20) {
        // (0.04, 0.13) is hidden by cells 5 to 7 of rows 5 to 7: the
        // centres of some of them, facing the light, each with its own
        // triangle as the receiver.
        for (int i = 5; i < 8; ++i) {
          const uint32_t triangle = first_triangle_of_cell[i * kCells + 6];
          const Tri& t = tris[triangle];
          points.push_back({(t[0] + t[1] + t[2]) / 3.0, glm::dvec3(0, 0, 1), triangle});
          on_ceiling.push_back(points.back());
        }
      }
    }
  }
  int hidden = 0, penumbra = 0;
  for (const QueryPoint& q : points) {
    auto in_walk = walked->Query(q);
    // A new thread's scratch remembers nothing.
    StatusOr<PointVisibility> alone = absl::UnknownError("not run");
    std::thread([&] { alone = fresh->Query(q); }).join();
    ASSERT_TRUE(in_walk.ok() && alone.ok());
    // Exact both ways; the fragments may be cut in another order (after a
    // penumbra point, the walk leaves near candidates' tests to the
    // subtraction), so the sums may round differently.
    EXPECT_NEAR(in_walk->visible_area_fraction, alone->visible_area_fraction, 1e-12)
        << q.position.x << " " << q.position.y;
    EXPECT_NEAR(in_walk->visible_solid_angle_fraction, alone->visible_solid_angle_fraction, 1e-12);
    EXPECT_NEAR(in_walk->irradiance, alone->irradiance, 1e-12);
    if (in_walk->visible_area_fraction == 0.0) {
      EXPECT_EQ(alone->visible_area_fraction, 0.0);
    }
    hidden += in_walk->visible_area_fraction == 0.0;
    penumbra += in_walk->visible_area_fraction > 0.0 && in_walk->visible_area_fraction < 1.0;
  }
  EXPECT_GT(hidden, 100);
  EXPECT_GT(penumbra, 50);
  // Most hidden points after the first of a run were settled by the
  // remembered blockers, none on the fresh threads.
  EXPECT_GT(walked->Stats().hidden_by_remembered_blockers, static_cast<uint64_t>(hidden / 2));
  EXPECT_EQ(fresh->Stats().hidden_by_remembered_blockers, 0u);
  // The ceiling points see the light whole.
  for (const QueryPoint& q : on_ceiling) {
    auto v = walked->Query(q);
    ASSERT_TRUE(v.ok());
    EXPECT_EQ(v->visible_area_fraction, 1.0);
  }
}

TEST(LightVisibilityTest, AlignedDegenerateGeometryAgreesAcrossPaths) {
  // Axis-aligned boxes: coplanar faces, shared and collinear edges, one box
  // whose top face lies in the light plane with edges along the light's
  // edges; receiver points on a grid, many exactly on shadow boundaries. The
  // tree path (BSP) and the all-near path (per-query subtraction) share no
  // occlusion logic, so they check each other; Embree checks both loosely.
  std::vector<Tri> tris;
  AddBox(tris, {-0.5, -0.5, 1.0}, {0.0, 0.5, 1.5});
  AddBox(tris, {0.0, 0.0, 0.5}, {0.5, 0.5, 1.0});
  AddBox(tris, {0.5, -1.0, 1.5}, {1.0, -0.5, 2.0});
  AddBox(tris, {-1.0, 0.5, 1.0}, {-0.5, 1.0, 1.0 + 1e-7});  // a sliver slab
  const Scene scene = MakeScene(tris);
  const AreaLight light = SquareLight(2.0);
  // The BSP (every undecided point descends it) and the default route
  // (every point subtracts its candidates, far ones whole and merged with
  // their neighbours) over the same far occluders.
  auto tree = MakeTree(light, scene, Box({-1, -1, 0}, {1, 1, 0}), 0);
  auto direct = MakeTree(light, scene, Box({-1, -1, 0}, {1, 1, 0}));
  auto all_near = MakeTree(light, scene, std::nullopt);
  auto embree = raycast::EmbreeScene::Create(scene);
  ASSERT_TRUE(embree.ok());
  std::mt19937 rng(8);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i <= 8; ++i) {
    for (int j = 0; j <= 8; ++j) {
      const glm::dvec3 p(-1.0 + 0.25 * i, -1.0 + 0.25 * j, 0.0);
      const PointVisibility a = Q(*tree, p), b = Q(*all_near, p), c = Q(*direct, p);
      EXPECT_NEAR(a.visible_area_fraction, b.visible_area_fraction, 1e-12) << p.x << " " << p.y;
      EXPECT_NEAR(a.irradiance, b.irradiance, 1e-12) << p.x << " " << p.y;
      EXPECT_NEAR(a.visible_area_fraction, c.visible_area_fraction, 1e-12) << p.x << " " << p.y;
      EXPECT_NEAR(a.irradiance, c.irradiance, 1e-12) << p.x << " " << p.y;
      std::vector<raycast::Segment> segs;
      for (int k = 0; k < 2048; ++k) segs.push_back({p, {u(rng), u(rng), 2.0}});
      auto occ = embree->Occluded(segs);
      ASSERT_TRUE(occ.ok());
      int visible = 0;
      for (uint8_t o : *occ) visible += o == 0;
      EXPECT_NEAR(visible / 2048.0, a.visible_area_fraction, 6.0 * 0.5 / std::sqrt(2048.0) + 2e-3)
          << p.x << " " << p.y;
    }
  }
}

// A bar cut in two boxes joined end to end casts the shadow of the whole
// bar: the halves' edges lie on the whole bar's edge lines (and the joint's
// corners on them), which the query recognises by their input points
// instead of evaluating exactly (OnPlaneByInputs). A crossbar meets the
// bar's side at a T: its corners lie on the bar's edges. The BSP and the
// default route (far occluders subtracted whole, merged with neighbours)
// must give the one bar's answers.
TEST(LightVisibilityTest, BoxesJoinedOnSharedEdgeLinesShadeAsOne) {
  std::vector<Tri> one, joined;
  AddBox(one, {-1.0, -0.05, 1.0}, {1.0, 0.05, 1.05});
  AddBox(joined, {-1.0, -0.05, 1.0}, {0.25, 0.05, 1.05});
  AddBox(joined, {0.25, -0.05, 1.0}, {1.0, 0.05, 1.05});
  for (std::vector<Tri>* tris : {&one, &joined}) {
    AddBox(*tris, {-0.03, 0.05, 1.0}, {0.03, 0.8, 1.05});
    AddBox(*tris, {-0.6, -0.7, 1.2}, {0.9, -0.1, 1.25});  // a slab above, for fragments to cut
  }
  const AreaLight light = SquareLight(2.0, 0.7);
  const Bounds receivers = Box({-1.5, -1.5, 0}, {1.5, 1.5, 0});
  auto reference = MakeTree(light, MakeScene(one), receivers, 0);
  auto joined_tree = MakeTree(light, MakeScene(joined), receivers, 0);
  auto joined_direct = MakeTree(light, MakeScene(joined), receivers);
  auto joined_near = MakeTree(light, MakeScene(joined), std::nullopt);
  ASSERT_TRUE(reference && joined_tree && joined_direct && joined_near);
  int penumbra = 0;
  for (const glm::dvec3& p : FloorPoints(200, 31)) {
    const PointVisibility r = Q(*reference, p);
    for (LightVisibilityTree* t : {joined_tree.get(), joined_direct.get(), joined_near.get()}) {
      const PointVisibility a = Q(*t, p);
      EXPECT_NEAR(a.visible_area_fraction, r.visible_area_fraction, 1e-12) << p.x << " " << p.y;
      EXPECT_NEAR(a.irradiance, r.irradiance, 1e-12) << p.x << " " << p.y;
    }
    penumbra += r.visible_area_fraction > 0.0 && r.visible_area_fraction < 1.0;
  }
  EXPECT_GT(penumbra, 50);
}

// The same world moved and scaled.
std::vector<Tri> Transform(const std::vector<Tri>& tris, double scale, const glm::dvec3& offset) {
  std::vector<Tri> out = tris;
  for (auto& t : out) {
    for (auto& p : t) p = offset + scale * p;
  }
  return out;
}

TEST(LightVisibilityTest, InvariantUnderScaleAndTranslation) {
  std::vector<Tri> tris = Cloud(80, 21);
  // Extremes: a sliver, an occluder touching the light, one touching the
  // floor, one with an edge collinear with a light edge (in the light plane
  // would be dropped, so just below along the same direction).
  tris.push_back({glm::dvec3(-1, 0.1, 1.0), glm::dvec3(1, 0.1 + 1e-9, 1.0), glm::dvec3(0, 0.1, 1.0 + 1e-9)});
  tris.push_back({glm::dvec3(0.2, 0.2, 2.0), glm::dvec3(0.5, 0.2, 2.0), glm::dvec3(0.3, 0.4, 1.5)});
  tris.push_back({glm::dvec3(-0.2, -0.8, 0.0), glm::dvec3(0.1, -0.8, 0.0), glm::dvec3(0.0, -0.6, 0.8)});
  tris.push_back({glm::dvec3(-0.7, -0.7, 1.2), glm::dvec3(0.7, -0.7, 1.2), glm::dvec3(0.0, -0.2, 1.2)});
  const AreaLight light = SquareLight(2.0, 0.7);
  const auto pts = FloorPoints(60, 8);
  std::vector<double> reference;
  struct Frame { double scale; glm::dvec3 offset; };
  for (const Frame& f : {Frame{1.0, glm::dvec3(0.0)}, Frame{1e-4, glm::dvec3(0.0)},
                         Frame{1e5, glm::dvec3(0.0)}, Frame{1.0, glm::dvec3(1e6, -1e6, 1e6)},
                         Frame{0.5, glm::dvec3(-1e6, 1e6, 0.0)}}) {
    const Scene scene = MakeScene(Transform(tris, f.scale, f.offset));
    AreaLight l = light;
    for (auto& v : l.vertices) v = f.offset + f.scale * v;
    auto tree = MakeTree(l, scene,
                         Box(f.offset + f.scale * glm::dvec3(-1.5, -1.5, 0),
                             f.offset + f.scale * glm::dvec3(1.5, 1.5, 0)));
    for (size_t i = 0; i < pts.size(); ++i) {
      const PointVisibility r = Q(*tree, f.offset + f.scale * pts[i]);
      if (reference.size() < pts.size()) {
        reference.push_back(r.visible_area_fraction);
      } else {
        EXPECT_NEAR(r.visible_area_fraction, reference[i], 1e-9 * std::max(1.0, reference[i]))
            << "scale " << f.scale << " point " << i;
      }
    }
  }
}

// Needles in the light's way: segments 0.3 long with their third vertex
// `width` off the long edge's middle, at random heights and directions,
// beside a few ordinary triangles; the whole scene turned by `turn`.
std::vector<Tri> Needles(int count, double width, uint32_t seed, const glm::dmat3& turn) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Tri> tris;
  for (int i = 0; i < count; ++i) {
    const glm::dvec3 c(-1.2 + 2.4 * u(rng), -1.2 + 2.4 * u(rng), 0.4 + 1.2 * u(rng));
    const double a = 2.0 * std::numbers::pi * u(rng);
    const glm::dvec3 d(0.15 * std::cos(a), 0.15 * std::sin(a), 0.05 * (u(rng) - 0.5));
    const glm::dvec3 side = glm::normalize(glm::cross(d, glm::dvec3(0, 0, 1)));
    tris.push_back({turn * (c - d), turn * (c + d), turn * (c + width * side)});
  }
  for (const Tri& t : Cloud(12, seed + 1)) tris.push_back({turn * t[0], turn * t[1], turn * t[2]});
  return tris;
}

// TreeOptions::shadow_tolerance: every answer that left occluders out lies
// at most its stated errors above the exact one (never below it), and the
// errors sum no more than the tolerance; an answer that left nothing out is
// the exact one, bit for bit. Tolerances from one that leaves out only the
// needles to one that leaves out ordinary triangles too; a light turned off
// the axes and one far from the origin.
TEST(LightVisibilityTest, AShadowToleranceLeavesOutSmallShadowsAndStatesThemAsTheError) {
  const glm::dmat3 straight(1.0);
  const glm::dmat3 turned(glm::rotate(glm::dmat4(1.0), 0.7, glm::normalize(glm::dvec3(1, 2, 0.5))));
  struct Case { glm::dmat3 turn; glm::dvec3 offset; double width, tolerance; };
  for (const Case& c : {Case{straight, glm::dvec3(0.0), 1e-7, 1e-5}, Case{turned, glm::dvec3(0.0), 1e-7, 1e-5},
                        Case{turned, glm::dvec3(3e5, -2e5, 1e5), 1e-7, 1e-5},
                        Case{straight, glm::dvec3(0.0), 2e-3, 0.05}, Case{turned, glm::dvec3(0.0), 2e-3, 0.05}}) {
    std::vector<Tri> tris = Needles(300, c.width, 5, c.turn);
    for (Tri& t : tris)
      for (glm::dvec3& v : t) v += c.offset;
    const Scene scene = MakeScene(tris);
    AreaLight light = SquareLight(2.0, 1.0, 3.0);
    for (glm::dvec3& v : light.vertices) v = c.turn * v + c.offset;
    Bounds receivers;
    for (const glm::dvec3& corner : {glm::dvec3(-1.5, -1.5, 0), glm::dvec3(1.5, 1.5, 0), glm::dvec3(-1.5, 1.5, 0),
                                     glm::dvec3(1.5, -1.5, 0)})
      receivers.Extend(c.turn * corner + c.offset);
    TreeOptions options;
    options.receiver_bounds = receivers;
    auto exact = LightVisibilityTree::Create(light, scene, options);
    options.shadow_tolerance = c.tolerance;
    auto tolerant = LightVisibilityTree::Create(light, scene, options);
    ASSERT_TRUE(exact.ok() && tolerant.ok());
    int left_out = 0;
    for (const glm::dvec3& floor : FloorPoints(150, 17)) {
      const QueryPoint q{c.turn * floor + c.offset, c.turn * glm::dvec3(0, 0, 1), std::nullopt};
      auto e = (*exact)->Query(q);
      auto t = (*tolerant)->Query(q);
      ASSERT_TRUE(e.ok() && t.ok());
      EXPECT_EQ(e->visible_area_fraction_error, 0.0);
      const double slack = 1e-10;
      EXPECT_LE(t->visible_area_fraction_error, c.tolerance * 1.0000001);
      EXPECT_GE(t->visible_area_fraction + slack, e->visible_area_fraction);
      EXPECT_LE(t->visible_area_fraction - t->visible_area_fraction_error, e->visible_area_fraction + slack);
      EXPECT_GE(t->visible_solid_angle_fraction + slack, e->visible_solid_angle_fraction);
      EXPECT_LE(t->visible_solid_angle_fraction - t->visible_solid_angle_fraction_error,
                e->visible_solid_angle_fraction + slack);
      EXPECT_GE(t->irradiance + 3.0 * slack, e->irradiance);
      EXPECT_LE(t->irradiance - t->irradiance_error, e->irradiance + 3.0 * slack);
      if (t->visible_area_fraction_error > 0.0) {
        ++left_out;
      } else {
        EXPECT_EQ(t->visible_area_fraction, e->visible_area_fraction);
        EXPECT_EQ(t->irradiance, e->irradiance);
      }
    }
    EXPECT_GT(left_out, 30) << "the tolerance left nothing out: the test tests nothing";
    // Asked again, the stored answer states the same errors.
    const QueryPoint q{c.turn * FloorPoints(150, 17)[0] + c.offset, c.turn * glm::dvec3(0, 0, 1), std::nullopt};
    auto first = (*tolerant)->Query(q);
    auto again = (*tolerant)->Query(q);
    ASSERT_TRUE(first.ok() && again.ok());
    EXPECT_EQ(first->visible_area_fraction_error, again->visible_area_fraction_error);
    EXPECT_EQ(first->irradiance_error, again->irradiance_error);
  }
  TreeOptions bad;
  bad.shadow_tolerance = -1e-3;
  EXPECT_FALSE(LightVisibilityTree::Create(SquareLight(2.0), MakeScene({}), bad).ok());
  bad.shadow_tolerance = std::nan("");
  EXPECT_FALSE(LightVisibilityTree::Create(SquareLight(2.0), MakeScene({}), bad).ok());
}

TEST(LightVisibilityTest, ShadowBoundaryAndCollinearEdges) {
  // P exactly on the shadow boundary plane of an occluder edge through a
  // light vertex; and occluder edges along light edge lines.
  const AreaLight light = SquareLight(2.0);
  const Scene scene = MakeScene({
      // Edge from (0.5, -1, 1) to (0.5, 1, 1): P = (0, 0, 0) sees it at x = 1
      // on the light: exactly the light's edge x = 1.
      {glm::dvec3(0.5, -1, 1), glm::dvec3(0.5, 1, 1), glm::dvec3(5, 0, 1)},
      // An occluder edge touching the light exactly along its edge y = 1.
      {glm::dvec3(-1, 1, 2), glm::dvec3(1, 1, 2), glm::dvec3(0, 0.5, 1.5)},
  });
  auto tree = MakeTree(light, scene, Box({-0.5, -0.5, 0}, {0.5, 0.5, 0}));
  const PointVisibility r = Q(*tree, {0, 0, 0});
  // The second occluder hides the wedge between y = 1 and the projection of
  // its lower vertex, (0, 0.5, 1.5) -> y = 0.5 * 2 / 1.5 on the light.
  const double y_tip = 0.5 * 2.0 / 1.5;
  const double hidden = 0.5 * 2.0 * (1.0 - y_tip);  // triangle area
  EXPECT_NEAR(r.visible_area_fraction, 1.0 - hidden / 4.0, 1e-14);
  // Nearby points: continuous answers, no crash.
  for (double dx : {-1e-12, 1e-12, 1e-6}) {
    const PointVisibility s = Q(*tree, {dx, 0, 0});
    EXPECT_NEAR(s.visible_area_fraction, r.visible_area_fraction, 1e-5);
  }
}

// A tree at its memory budget stops growing; queries that reach an
// undefined leaf then subtract its occluders themselves. The answers stay
// those of an unbounded tree (up to the float sums over other fragments).
TEST(LightVisibilityTest, TreeAtItsMemoryBudgetStopsGrowingAndStaysExact) {
  const Scene scene = MakeScene(Cloud(150, 31, 0.25));
  const AreaLight light = SquareLight(2.0);
  TreeOptions unbounded_options, bounded_options;
  unbounded_options.receiver_bounds = bounded_options.receiver_bounds = Box({-1.5, -1.5, 0}, {1.5, 1.5, 0});
  // Every undecided point descends the tree (by default it subtracts its
  // candidates directly, and the tree never grows).
  unbounded_options.direct_candidates = bounded_options.direct_candidates = 0;
  bounded_options.max_bytes = 1;  // below the empty tree: it never refines
  auto unbounded = LightVisibilityTree::Create(light, scene, unbounded_options);
  auto bounded = LightVisibilityTree::Create(light, scene, bounded_options);
  ASSERT_TRUE(unbounded.ok() && bounded.ok());
  const size_t empty_bytes = (*bounded)->MemoryBytes();
  int penumbra = 0;
  for (const glm::dvec3& p : FloorPoints(150, 5)) {
    const PointVisibility a = Q(**unbounded, p), b = Q(**bounded, p);
    EXPECT_NEAR(a.visible_area_fraction, b.visible_area_fraction, 1e-12) << p.x << "," << p.y;
    EXPECT_NEAR(a.irradiance, b.irradiance, 1e-12 * std::max(1.0, a.irradiance));
    penumbra += a.visible_area_fraction > 0 && a.visible_area_fraction < 1;
  }
  EXPECT_GT(penumbra, 20);
  const TreeStats grown = (*unbounded)->Stats(), capped = (*bounded)->Stats();
  EXPECT_GT(grown.refinements, 0u);
  EXPECT_EQ(capped.refinements, 0u);
  EXPECT_GT(capped.unrefined_leaf_visits, 0u);
  EXPECT_EQ((*bounded)->MemoryBytes(), empty_bytes);
  EXPECT_GT(grown.memory_bytes, empty_bytes);
}

TEST(LightVisibilityTest, ADenseMeshAtTheBudgetMatchesTheGrownTree) {
  // Foliage: hundreds of small triangles in a layer, so that a penumbra
  // point sees the light in many pieces. At the budget each leaf's
  // occluders are subtracted from every piece, and pieces whose line boxes
  // are apart from an occluder's skip the exact tests. The answers must be
  // those of the grown tree, in every frame, and under a tilted light whose
  // directions from some points straddle the box axis (no boxes there).
  std::vector<Tri> tris;
  std::mt19937 rng(41);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < 500; ++i) {
    const glm::dvec3 c(1.2 * u(rng), 1.2 * u(rng), 1.0 + 0.1 * u(rng));
    Tri t;
    for (auto& p : t) p = c + 0.05 * glm::dvec3(u(rng), u(rng), u(rng));
    tris.push_back(t);
  }
  const double c50 = std::cos(50.0 * std::numbers::pi / 180.0), s50 = std::sin(50.0 * std::numbers::pi / 180.0);
  AreaLight tilted = SquareLight(0.0, 0.5);
  for (auto& v : tilted.vertices) v = glm::dvec3(c50 * v.x, v.y, 2.0 + s50 * v.x);
  const auto pts = FloorPoints(40, 9);
  struct Frame { double scale; glm::dvec3 offset; };
  for (const AreaLight& light : {SquareLight(2.0, 0.5), tilted}) {
    std::vector<double> reference;
    int penumbra = 0;
    for (const Frame& f : {Frame{1.0, glm::dvec3(0.0)}, Frame{1e-4, glm::dvec3(0.0)},
                           Frame{1e5, glm::dvec3(1e6, -1e6, 1e6)}}) {
      const Scene scene = MakeScene(Transform(tris, f.scale, f.offset));
      AreaLight l = light;
      for (auto& v : l.vertices) v = f.offset + f.scale * v;
      TreeOptions grown_options, capped_options;
      grown_options.receiver_bounds = capped_options.receiver_bounds =
          Box(f.offset + f.scale * glm::dvec3(-1.5, -1.5, 0), f.offset + f.scale * glm::dvec3(1.5, 1.5, 0));
      capped_options.max_bytes = 1;
      // Every undecided point descends the tree; the default route (each
      // point subtracts its candidates itself) must agree with both.
      TreeOptions direct_options = grown_options;
      grown_options.direct_candidates = capped_options.direct_candidates = 0;
      auto grown = LightVisibilityTree::Create(l, scene, grown_options);
      auto capped = LightVisibilityTree::Create(l, scene, capped_options);
      auto direct = LightVisibilityTree::Create(l, scene, direct_options);
      ASSERT_TRUE(grown.ok() && capped.ok() && direct.ok());
      for (size_t i = 0; i < pts.size(); ++i) {
        const glm::dvec3 p = f.offset + f.scale * pts[i];
        const PointVisibility a = Q(**grown, p), b = Q(**capped, p), c = Q(**direct, p);
        EXPECT_NEAR(a.visible_area_fraction, b.visible_area_fraction, 1e-12) << "scale " << f.scale << " point " << i;
        EXPECT_NEAR(a.visible_area_fraction, c.visible_area_fraction, 1e-12) << "scale " << f.scale << " point " << i;
        if (reference.size() < pts.size()) {
          reference.push_back(a.visible_area_fraction);
          penumbra += a.visible_area_fraction > 0 && a.visible_area_fraction < 1;
        } else {
          EXPECT_NEAR(b.visible_area_fraction, reference[i], 1e-9) << "scale " << f.scale << " point " << i;
        }
      }
      EXPECT_GT((*capped)->Stats().unrefined_leaf_visits, 0u);
    }
    EXPECT_GT(penumbra, 20);
  }
}

// The foliage of issue 44 in small (docs/exact-method-notes.md, "Foliage:
// where the time goes"): four bunches of the shared scenes' flowers (petals and stems,
// about 3,500 triangles each) on a board between the floor and a square
// light, so that a floor point sees the light through hundreds of small
// triangles and its light is left in many pieces: the subtractions keep
// them in a grid over their line boxes (FragmentGrid). Answers against
// 1,024 rays a point, and against the route that clips every occluder as a
// near one (no receiver bounds).
// A floor (triangles 0 and 1, 4 x 4 m at z = 0) under `bunches` (at most
// four) bunches of the shared glass vase's flowers, 0.66 m tall, standing at
// z = 0.7 around the origin, each turned its own way.
std::vector<Tri> FloorUnderFlowerBunches(const Scene& flowers, int bunches = 4) {
  std::vector<Tri> tris = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                           {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)}};
  // The asset is Y-up; its first flower node ("Flowers1"), moved to the
  // origin, is one bunch (as the bench's MakeFoliageScene takes it).
  const glm::dvec3 base(0.0016, 0.038, 0.0022);
  int bunch = 0;
  for (const glm::dvec2 at : {glm::dvec2(-0.3, -0.3), glm::dvec2(0.3, -0.3), glm::dvec2(-0.3, 0.3),
                              glm::dvec2(0.3, 0.3)}) {
    if (bunch == bunches) break;
    const double a = 1.1 * bunch++, c = std::cos(a), sn = std::sin(a);
    for (size_t t = 0; t < flowers.TriangleCount(); ++t) {
      if (flowers.nodes[flowers.NodeOf(t)].name.rfind("Flowers1", 0) != 0) continue;
      Tri tri;
      for (int k = 0; k < 3; ++k) {
        const glm::dvec3 q = 4.0 * (flowers.Vertex(t, k) - base);
        tri[k] = glm::dvec3(at.x + c * q.x - sn * q.z, at.y + sn * q.x + c * q.z, 0.7 + q.y);
      }
      tris.push_back(tri);
    }
  }
  return tris;
}

TEST(LightVisibilityTest, FlowersFromTheSharedScenesMatchEmbreeRays) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  auto flowers = LoadGltfFile(scenes / "foliage_glass_vase_flowers/GlassVaseFlowers.gltf");
  ASSERT_TRUE(flowers.ok()) << flowers.status();
  const std::vector<Tri> tris = FloorUnderFlowerBunches(*flowers);
  ASSERT_GT(tris.size(), 4000u);
  const Scene scene = MakeScene(tris);
  const AreaLight light = SquareLight(2.0, 0.5);
  auto direct = MakeTree(light, scene, Box({-2, -2, 0}, {2, 2, 0}));
  auto all_near = MakeTree(light, scene, std::nullopt);
  ASSERT_TRUE(direct && all_near);
  auto embree = raycast::EmbreeScene::Create(scene);
  ASSERT_TRUE(embree.ok());

  std::vector<glm::dvec3> pts = FloorPoints(48, 71);
  for (glm::dvec3& p : pts) p *= 0.4;  // under the bunches
  std::vector<double> exact;
  for (const glm::dvec3& p : pts) exact.push_back(SameOnBoth(*direct, *all_near, p).visible_area_fraction);
  ExpectRaysAgree(*embree, pts, exact, 0.5, 1024, 12);
  int penumbra = 0;
  for (double e : exact) penumbra += e > 0.0 && e < 1.0;
  EXPECT_GT(penumbra, 24);
  // The points' light was left in many pieces: the grid was used.
  EXPECT_GT(direct->Stats().fragment_grids, 0u);
  EXPECT_GT(all_near->Stats().fragment_grids, 0u);

  // What this thread keeps for its next query after these points, and
  // after one point of a small tree: the flowers' working geometry and
  // slots are handed back.
  const size_t after_flowers = LightVisibilityTree::ThisThreadScratchBytes();
  auto small = MakeTree(SquareLight(2.0), MakeScene(Cloud(5, 3)), Box({-1.5, -1.5, 0}, {1.5, 1.5, 0}));
  ASSERT_TRUE(small);
  (void)Q(*small, {0.1, 0.2, 0.0});
  const size_t after_small = LightVisibilityTree::ThisThreadScratchBytes();
  std::printf("this thread's scratch: %zu bytes after the flowers, %zu after a small tree\n", after_flowers,
              after_small);
  EXPECT_LT(after_small, after_flowers);
  EXPECT_LT(after_small, size_t{16} << 20);
}

TEST(LightVisibilityTest, BatchStopsAtItsDeadline) {
  auto tree = MakeTree(SquareLight(2.0), MakeScene(Cloud(50, 3)), Box({-1.5, -1.5, 0}, {1.5, 1.5, 0}));
  std::vector<QueryPoint> points;
  for (const glm::dvec3& p : FloorPoints(100, 9)) points.push_back({p, glm::dvec3(0, 0, 1), std::nullopt});
  auto late = tree->QueryBatch(points, 2, false, StopToken{nullptr, std::chrono::steady_clock::now() - std::chrono::seconds(1)});
  EXPECT_EQ(late.status().code(), absl::StatusCode::kDeadlineExceeded);
  EXPECT_NE(std::string(late.status().message()).find("of 100 points left"), std::string::npos) << late.status();
  EXPECT_EQ(tree->Stats().queries, 0u);
  auto in_time = tree->QueryBatch(points, 2, false, StopToken{nullptr, std::chrono::steady_clock::now() + std::chrono::hours(1)});
  ASSERT_TRUE(in_time.ok()) << in_time.status();
  EXPECT_EQ(in_time->size(), 100u);
}

TEST(LightVisibilityTest, SecondPassRefinesNothingAndRepeats) {
  const Scene scene = MakeScene(Cloud(120, 31));
  TreeOptions options;
  options.receiver_bounds = Box({-1.5, -1.5, 0}, {1.5, 1.5, 0});
  options.direct_candidates = 0;  // every undecided point grows the tree
  options.keep_answers = false;   // the second pass descends the warm tree
  auto created = LightVisibilityTree::Create(SquareLight(2.0, 0.7), scene, options);
  ASSERT_TRUE(created.ok()) << created.status();
  auto& tree = *created;
  const auto pts = FloorPoints(100, 3);
  std::vector<PointVisibility> first;
  for (const auto& p : pts) first.push_back(Q(*tree, p));
  const TreeStats after_first = tree->Stats();
  EXPECT_GT(after_first.refinements, 0u);
  EXPECT_GT(after_first.nodes, 1u);
  for (size_t i = 0; i < pts.size(); ++i) {
    const PointVisibility r = Q(*tree, pts[i]);
    EXPECT_EQ(r.visible_area_fraction, first[i].visible_area_fraction);
    EXPECT_EQ(r.irradiance, first[i].irradiance);
  }
  const TreeStats after_second = tree->Stats();
  EXPECT_EQ(after_second.refinements, after_first.refinements);
  EXPECT_EQ(after_second.nodes, after_first.nodes);
  EXPECT_EQ(after_second.hits - after_first.hits, pts.size());
  EXPECT_GT(after_second.memory_bytes, 0u);
}

// A bumpy grid of triangles at height about z, sharing their vertices and
// edges, with a few cells left open so that the light shines through.
std::vector<Tri> Sheet(int cells, double z, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> bump(-0.05, 0.05), open(0, 1);
  std::vector<glm::dvec3> grid;
  for (int j = 0; j <= cells; ++j) {
    for (int i = 0; i <= cells; ++i) {
      const double b = bump(rng);
      grid.emplace_back(-1.5 + 3.0 * i / cells, -1.5 + 3.0 * j / cells, z + b);
    }
  }
  const auto at = [&](int i, int j) { return grid[static_cast<size_t>(j * (cells + 1) + i)]; };
  std::vector<Tri> tris;
  for (int j = 0; j < cells; ++j) {
    for (int i = 0; i < cells; ++i) {
      if (open(rng) < 0.3) continue;
      tris.push_back({at(i, j), at(i + 1, j), at(i + 1, j + 1)});
      tris.push_back({at(i, j), at(i + 1, j + 1), at(i, j + 1)});
    }
  }
  return tris;
}

// A query makes the exact points of the tree's vertices as it first meets
// them, so the order in which it meets them varies with the point and with
// the tree's growth. The answers may not: the same tree, asked again in the
// reverse order, answers every point bit for bit as before, with far
// occluders (the tree) and near ones (clipped per query) that share edges.
TEST(LightVisibilityTest, VerticesMadeInAnyOrderGiveTheSameAnswers) {
  std::vector<Tri> tris = Sheet(10, 1.0, 5);
  for (const Tri& t : Cloud(30, 17, 0.2)) tris.push_back(t);
  const Scene scene = MakeScene(tris);
  const std::vector<glm::dvec3> floor = FloorPoints(80, 9);
  // Receivers on the floor (the sheet far) and up to the sheet (all near).
  for (const double top : {0.0, 1.2}) {
    SCOPED_TRACE(top);
    TreeOptions options;
    options.receiver_bounds = Box({-1.5, -1.5, 0}, {1.5, 1.5, top});
    options.direct_candidates = 0;
    options.keep_answers = false;
    auto tree = LightVisibilityTree::Create(SquareLight(2.0, 0.7), scene, options);
    ASSERT_TRUE(tree.ok()) << tree.status();
    std::vector<QueryPoint> points;
    for (const glm::dvec3& p : floor) points.push_back({p, glm::dvec3(0, 0, 1), std::nullopt});
    for (size_t i = 0; top > 0.0 && i < 20; ++i) points.push_back({floor[i] + glm::dvec3(0, 0, 0.6), glm::dvec3(0, 0, 1), std::nullopt});
    std::vector<PointVisibility> first;
    size_t penumbra = 0;
    for (const QueryPoint& q : points) {
      auto r = (*tree)->Query(q);
      ASSERT_TRUE(r.ok()) << r.status();
      penumbra += r->visible_area_fraction > 0.0 && r->visible_area_fraction < 1.0;
      first.push_back(*r);
    }
    EXPECT_GT(penumbra, points.size() / 4);
    const TreeStats stats = (*tree)->Stats();
    EXPECT_GT(top > 0.0 ? stats.near_occluders : stats.far_occluders, 100u);
    for (size_t k = points.size(); k-- > 0;) {
      auto r = (*tree)->Query(points[k]);
      ASSERT_TRUE(r.ok()) << r.status();
      EXPECT_EQ(r->visible_area_fraction, first[k].visible_area_fraction) << k;
      EXPECT_EQ(r->visible_solid_angle_fraction, first[k].visible_solid_angle_fraction) << k;
      EXPECT_EQ(r->irradiance, first[k].irradiance) << k;
    }
  }
}

TEST(LightVisibilityTest, PointsAskedAgainAreAnsweredFromTheStore) {
  const Scene scene = MakeScene(Cloud(120, 31));
  TreeOptions options;
  options.receiver_bounds = Box({-1.5, -1.5, 0}, {1.5, 1.5, 0});
  auto created = LightVisibilityTree::Create(SquareLight(2.0, 0.7), scene, options);
  ASSERT_TRUE(created.ok()) << created.status();
  auto& tree = *created;
  std::vector<QueryPoint> points;
  for (const auto& p : FloorPoints(200, 4)) points.push_back({p, glm::dvec3(0, 0, 1), std::nullopt});
  auto first = tree->QueryBatch(points, 2);
  ASSERT_TRUE(first.ok()) << first.status();
  const TreeStats after_first = tree->Stats();
  EXPECT_EQ(after_first.answers_kept, points.size());
  EXPECT_EQ(after_first.answers_reused, 0u);
  auto second = tree->QueryBatch(points, 2);
  ASSERT_TRUE(second.ok()) << second.status();
  const TreeStats after_second = tree->Stats();
  EXPECT_EQ(after_second.answers_reused, points.size());
  EXPECT_EQ(after_second.refinements, after_first.refinements);
  EXPECT_EQ(after_second.nodes, after_first.nodes);
  EXPECT_EQ(after_second.unrefined_leaf_visits, after_first.unrefined_leaf_visits);
  for (size_t i = 0; i < points.size(); ++i) {
    EXPECT_EQ((*second)[i].visible_area_fraction, (*first)[i].visible_area_fraction);
    EXPECT_EQ((*second)[i].irradiance, (*first)[i].irradiance);
  }
  // Another normal, or polygons asked for, is another question.
  QueryPoint tilted = points[0];
  tilted.normal = glm::dvec3(0, 1, 1);
  ASSERT_TRUE(tree->Query(tilted).ok());
  ASSERT_TRUE(tree->Query(points[0], /*want_polygons=*/true).ok());
  EXPECT_EQ(tree->Stats().answers_reused, points.size());
  EXPECT_EQ(tree->Stats().answers_kept, points.size() + 2);

  // The store stays within half the tree's budget.
  TreeOptions small = options;
  small.max_bytes = 64 << 10;
  auto bounded = LightVisibilityTree::Create(SquareLight(2.0, 0.7), scene, small);
  ASSERT_TRUE(bounded.ok());
  std::vector<QueryPoint> many;
  for (const auto& p : FloorPoints(3000, 5)) many.push_back({p, glm::dvec3(0, 0, 1), std::nullopt});
  ASSERT_TRUE((*bounded)->QueryBatch(many, 2).ok());
  const TreeStats kept = (*bounded)->Stats();
  EXPECT_GT(kept.answers_kept, 0u);
  EXPECT_LT(kept.answers_kept, many.size());
  EXPECT_LE(kept.answer_bytes, small.max_bytes / 2);
  EXPECT_LE(kept.answers_kept * (sizeof(double) * 3), kept.answer_bytes);
}

// Foliage of many small triangles over the receivers, every one of them
// near (no receiver bounds): one penumbra point subtracts thousands.
TEST(LightVisibilityTest, AQueryStopsInsideItsSubtractions) {
  std::vector<Tri> tris;
  std::mt19937 rng(43);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < 20000; ++i) {
    const glm::dvec3 c(1.0 * u(rng), 1.0 * u(rng), 1.0 + 0.3 * u(rng));
    Tri t;
    for (auto& p : t) p = c + 0.02 * glm::dvec3(u(rng), u(rng), u(rng));
    tris.push_back(t);
  }
  const Scene scene = MakeScene(tris);
  auto tree = MakeTree(SquareLight(2.0, 0.5), scene, std::nullopt);
  ASSERT_NE(tree, nullptr);
  const QueryPoint point{{0.05, 0.03, 0.0}, glm::dvec3(0, 0, 1), std::nullopt};
  using Clock = std::chrono::steady_clock;
  const auto t0 = Clock::now();
  auto whole = tree->Query(point);
  const double whole_ms = std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
  ASSERT_TRUE(whole.ok()) << whole.status();
  ASSERT_GT(whole->visible_area_fraction, 0.0);
  ASSERT_LT(whole->visible_area_fraction, 1.0);

  // A cancelled call: CANCELLED before any work is kept.
  std::atomic<bool> cancelled{true};
  QueryPoint moved = point;
  moved.position.x += 0.01;
  auto stopped = tree->Query(moved, false, StopToken{&cancelled});
  EXPECT_EQ(stopped.status().code(), absl::StatusCode::kCancelled) << stopped.status();

  // A deadline a tenth of the way in: it stops in the middle of the point.
  const auto t1 = Clock::now();
  const auto deadline = t1 + std::chrono::duration_cast<Clock::duration>(
                                 std::chrono::duration<double, std::milli>(whole_ms / 10));
  auto late = tree->Query(moved, false, StopToken{nullptr, deadline});
  const double late_ms = std::chrono::duration<double, std::milli>(Clock::now() - deadline).count();
  EXPECT_EQ(late.status().code(), absl::StatusCode::kDeadlineExceeded) << late.status();
  EXPECT_LT(late_ms, 1000.0);
  std::printf("one penumbra point of %zu near occluders: %.1f ms whole; stopped %.2f ms after its deadline\n",
              scene.triangles.size(), whole_ms, late_ms);
  RecordProperty("stop_after_deadline_ms", std::to_string(late_ms));
  // The tree still answers, and the stopped query kept no answer.
  auto again = tree->Query(moved);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(tree->Stats().answers_reused, 0u);
}

TEST(LightVisibilityTest, ConcurrentQueriesMatchSingleThreaded) {
  const Scene scene = MakeScene(Cloud(120, 41));
  const AreaLight light = SquareLight(2.0, 0.7);
  const Bounds receivers = Box({-1.5, -1.5, 0}, {1.5, 1.5, 0});
  const auto pts = FloorPoints(300, 13);
  std::vector<QueryPoint> queries;
  for (const auto& p : pts) queries.push_back({p, glm::dvec3(0, 0, 1), std::nullopt});
  // Every undecided point descends the tree, so that the threads grow it
  // together.
  auto single = MakeTree(light, scene, receivers, 0);
  auto shared = MakeTree(light, scene, receivers, 0);
  auto a = single->QueryBatch(queries, 1);
  auto b = shared->QueryBatch(queries, 4);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_GT(shared->Stats().refinements, 10u);
  for (size_t i = 0; i < pts.size(); ++i) {
    EXPECT_NEAR((*a)[i].visible_area_fraction, (*b)[i].visible_area_fraction, 1e-12) << i;
    EXPECT_NEAR((*a)[i].irradiance, (*b)[i].irradiance, 1e-12) << i;
  }
}

// Two batches' answers at the same points, expected the same to 1e-12; how
// many of the first's are wholly lit, wholly hidden and partial.
struct AnswerKinds {
  int lit = 0, hidden = 0, partial = 0;
};
AnswerKinds SameAnswers(const std::vector<QueryPoint>& queries, const std::vector<PointVisibility>& a,
                        const std::vector<PointVisibility>& b) {
  AnswerKinds kinds;
  for (size_t i = 0; i < queries.size(); ++i) {
    const glm::dvec3& p = queries[i].position;
    EXPECT_NEAR(a[i].visible_area_fraction, b[i].visible_area_fraction, 1e-12) << p.x << " " << p.y;
    EXPECT_NEAR(a[i].visible_solid_angle_fraction, b[i].visible_solid_angle_fraction, 1e-12);
    EXPECT_NEAR(a[i].irradiance, b[i].irradiance, 1e-12);
    const double f = a[i].visible_area_fraction;
    kinds.lit += f == 1.0;
    kinds.hidden += f == 0.0;
    kinds.partial += f > 0.0 && f < 1.0;
  }
  return kinds;
}

TEST(LightVisibilityTest, PointsDecidedBeforeTheTreeAgreeWithTheTree) {
  // A large slab (two triangles sharing a diagonal) over part of the floor,
  // a box, a cloud and the floor itself: points in the open are wholly lit,
  // points under one of the slab's triangles wholly hidden by it, points
  // under its diagonal hidden by the two together (the tree decides those),
  // and the rest in penumbrae. Every point is answered with the
  // classification on and off, through the tree with receiver bounds and
  // without it (all occluders near).
  std::vector<Tri> tris = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                           {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)},
                           {glm::dvec3(-3, -3, 1.0), glm::dvec3(0.5, -3, 1.0), glm::dvec3(0.5, 0.5, 1.0)},
                           {glm::dvec3(-3, -3, 1.0), glm::dvec3(0.5, 0.5, 1.0), glm::dvec3(-3, 0.5, 1.0)}};
  AddBox(tris, {0.8, 0.8, 0}, {1.1, 1.2, 0.7});
  for (const Tri& t : Cloud(30, 71, 0.1)) {
    Tri moved = t;
    for (auto& p : moved) p.x = std::abs(p.x) + 0.6, p.y = std::abs(p.y) * 0.5 - 1.5;
    tris.push_back(moved);
  }
  const Scene scene = MakeScene(tris);
  const AreaLight light = SquareLight(2.0, 0.4);
  const Bounds receivers = Box({-2, -2, 0}, {2, 2, 0});
  std::vector<QueryPoint> queries;
  for (int i = 0; i <= 20; ++i) {
    for (int j = 0; j <= 20; ++j) {
      const glm::dvec3 p(-1.9 + 0.19 * i, -1.9 + 0.19 * j, 0.0);
      queries.push_back({p, std::nullopt, p.x - p.y > 0 ? 0u : 1u});
    }
  }
  // Classified points with few candidates subtract them directly
  // (direct_candidates); without that route, they descend the tree.
  for (const size_t direct : {size_t{32}, size_t{0}})
  for (const std::optional<Bounds>& bounds : {std::optional<Bounds>(receivers), std::optional<Bounds>()}) {
    TreeOptions on, off;
    on.receiver_bounds = off.receiver_bounds = bounds;
    on.direct_candidates = direct;
    off.classify_points = false;
    auto classified = LightVisibilityTree::Create(light, scene, on);
    auto tree_only = LightVisibilityTree::Create(light, scene, off);
    ASSERT_TRUE(classified.ok() && tree_only.ok());
    auto a = (*classified)->QueryBatch(queries, 1);
    auto b = (*tree_only)->QueryBatch(queries, 1);
    ASSERT_TRUE(a.ok() && b.ok());
    const auto [lit, hidden, partial] = SameAnswers(queries, *a, *b);
    const TreeStats on_stats = (*classified)->Stats(), off_stats = (*tree_only)->Stats();
    EXPECT_EQ(off_stats.wholly_visible + off_stats.wholly_hidden + off_stats.subtracted_directly, 0u);
    if (direct > 0) {
      EXPECT_GT(on_stats.subtracted_directly, 20u);
    } else {
      EXPECT_EQ(on_stats.subtracted_directly, 0u);
    }
    // Every wholly visible answer is exactly 1; hidden ones exactly 0 (some
    // of those, under the diagonal, came from the tree).
    EXPECT_GT(on_stats.wholly_visible, 20u);
    EXPECT_GT(on_stats.wholly_hidden, 20u);
    EXPECT_LE(on_stats.wholly_visible, static_cast<uint64_t>(lit));
    EXPECT_LE(on_stats.wholly_hidden, static_cast<uint64_t>(hidden));
    EXPECT_GT(partial, 20);
    // Decided points refine nothing: the classified tree grows less.
    EXPECT_LE(on_stats.refinements, off_stats.refinements);
  }
}

// visq's accelerations change no answer: every one on (the defaults) and
// the paper's algorithm alone (TreeOptions::PapersAlgorithmAlone: every
// point descends the tree its queries grow, occluders in index order, no
// culls, no classification, no store) agree to 1e-12 at floor points under
// slabs, a box and a cloud, and under the shared flowers, where the
// accelerated route starts fragment grids.
void ExpectPapersAlgorithmAgrees(const Scene& scene, const AreaLight& light, const std::vector<glm::dvec3>& points,
                                 bool expect_grids) {
  TreeOptions accelerated, paper = TreeOptions::PapersAlgorithmAlone();
  accelerated.receiver_bounds = paper.receiver_bounds = Box({-2, -2, 0}, {2, 2, 0});
  auto fast = LightVisibilityTree::Create(light, scene, accelerated);
  auto alone = LightVisibilityTree::Create(light, scene, paper);
  ASSERT_TRUE(fast.ok() && alone.ok());
  std::vector<QueryPoint> queries;
  for (const glm::dvec3& p : points) queries.push_back({p, std::nullopt, p.x - p.y > 0 ? 0u : 1u});
  auto a = (*fast)->QueryBatch(queries, 1);
  auto b = (*alone)->QueryBatch(queries, 1);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  const auto [lit, hidden, partial] = SameAnswers(queries, *a, *b);
  EXPECT_GT(partial, static_cast<int>(points.size()) / 4) << lit << " lit, " << hidden << " hidden";
  const TreeStats fast_stats = (*fast)->Stats(), alone_stats = (*alone)->Stats();
  // The paper's route: nothing decided before the tree, the tree grown.
  EXPECT_EQ(alone_stats.wholly_visible + alone_stats.wholly_hidden + alone_stats.subtracted_directly, 0u);
  EXPECT_EQ(alone_stats.fragment_grids, 0u);
  EXPECT_GT(alone_stats.refinements, 0u);
  EXPECT_GT(alone_stats.nodes, 3u);
  // The accelerated one: every undecided point subtracts directly.
  EXPECT_GT(fast_stats.subtracted_directly, 0u);
  if (expect_grids) {
    EXPECT_GT(fast_stats.fragment_grids, 0u);
  }
  std::printf("%zu points (%d lit, %d hidden, %d partial): accelerated %llu subtracted directly, %llu grids; "
              "the paper's %llu nodes, %llu refinements\n",
              points.size(), lit, hidden, partial, static_cast<unsigned long long>(fast_stats.subtracted_directly),
              static_cast<unsigned long long>(fast_stats.fragment_grids),
              static_cast<unsigned long long>(alone_stats.nodes),
              static_cast<unsigned long long>(alone_stats.refinements));
}

TEST(LightVisibilityTest, ThePapersAlgorithmAloneGivesTheAcceleratedAnswers) {
  std::vector<Tri> tris = {{glm::dvec3(-2, -2, 0), glm::dvec3(2, -2, 0), glm::dvec3(2, 2, 0)},
                           {glm::dvec3(-2, -2, 0), glm::dvec3(2, 2, 0), glm::dvec3(-2, 2, 0)},
                           {glm::dvec3(-3, -3, 1.0), glm::dvec3(0.5, -3, 1.0), glm::dvec3(0.5, 0.5, 1.0)},
                           {glm::dvec3(-3, -3, 1.0), glm::dvec3(0.5, 0.5, 1.0), glm::dvec3(-3, 0.5, 1.0)}};
  AddBox(tris, {0.8, 0.8, 0.2}, {1.1, 1.2, 0.7});
  for (const Tri& t : Cloud(60, 73, 0.15)) {
    Tri moved = t;
    for (auto& p : moved) p.z = 0.4 + 0.5 * p.z;
    tris.push_back(moved);
  }
  std::vector<glm::dvec3> points = FloorPoints(120, 29);
  ExpectPapersAlgorithmAgrees(MakeScene(tris), SquareLight(2.0, 0.6), points, /*expect_grids=*/false);

  VISQ_REQUIRE_SHARED_SCENES(scenes);  // the flowers
  auto flowers = LoadGltfFile(scenes / "foliage_glass_vase_flowers/GlassVaseFlowers.gltf");
  ASSERT_TRUE(flowers.ok()) << flowers.status();
  // One bunch: alone, the paper's tree grew to 649,431 nodes under four
  // (24 points, 190 s against the accelerated route's 1 s).
  points = FloorPoints(3, 71);
  for (glm::dvec3& p : points) p = glm::dvec3(-0.3, -0.3, 0.0) + 0.15 * p;  // under the bunch at (-0.3, -0.3)
  ExpectPapersAlgorithmAgrees(MakeScene(FloorUnderFlowerBunches(*flowers, 1)), SquareLight(2.0, 0.5), points,
                              /*expect_grids=*/true);
}

TEST(LightVisibilityTest, SceneIndexSelectsTheSameOccluders) {
  // Trees made with the scene's triangle index visit only the triangles near
  // their shafts, and must hold exactly the occluders, in the same order, as
  // trees made by scanning the scene: the same answers, bit for bit. The
  // world is far from the origin, so the index's padding is tested where
  // the local frame rounds.
  std::vector<Tri> tris = Transform(Cloud(200, 81, 0.2), 1.0, glm::dvec3(1e6, -2e6, 3e5));
  AddBox(tris, glm::dvec3(1e6 + 0.5, -2e6 + 0.5, 3e5), glm::dvec3(1e6 + 0.8, -2e6 + 0.9, 3e5 + 1.0));
  const Scene scene = MakeScene(tris);
  auto index = SceneTriangleIndex::Build(std::make_shared<const Scene>(scene));
  ASSERT_TRUE(index.ok()) << index.status();
  EXPECT_EQ((*index)->triangle_count(), scene.triangles.size());
  EXPECT_GT((*index)->MemoryBytes(), 0u);
  const glm::dvec3 offset(1e6, -2e6, 3e5);
  AreaLight light = SquareLight(2.0, 0.7);
  for (auto& v : light.vertices) v += offset;
  const auto pts = FloorPoints(60, 19);
  for (const glm::dvec3& corner : {glm::dvec3(-1.5, -1.5, 0), glm::dvec3(0.2, -0.4, 0)}) {
    TreeOptions options;
    options.receiver_bounds = Box(offset + corner, offset + corner + glm::dvec3(1.2, 1.0, 0.0));
    auto scanned = LightVisibilityTree::Create(light, scene, options);
    auto indexed = LightVisibilityTree::Create(light, scene, options, index->get());
    ASSERT_TRUE(scanned.ok() && indexed.ok());
    EXPECT_EQ((*scanned)->Stats().far_occluders, (*indexed)->Stats().far_occluders);
    EXPECT_EQ((*scanned)->Stats().near_occluders, (*indexed)->Stats().near_occluders);
    EXPECT_GT((*indexed)->Stats().far_occluders + (*indexed)->Stats().near_occluders, 10u);
    for (const glm::dvec3& p : pts) {
      const glm::dvec3 x = offset + corner + glm::dvec3((p.x + 1.5) / 3.0 * 1.2, (p.y + 1.5) / 3.0 * 1.0, 0.0);
      const PointVisibility a = Q(**scanned, x), b = Q(**indexed, x);
      EXPECT_EQ(a.visible_area_fraction, b.visible_area_fraction) << x.x << " " << x.y;
      EXPECT_EQ(a.irradiance, b.irradiance);
    }
  }
  // An index of another scene is refused.
  auto other = SceneTriangleIndex::Build(std::make_shared<const Scene>(MakeScene(Cloud(3, 1))));
  ASSERT_TRUE(other.ok());
  auto wrong = LightVisibilityTree::Create(light, scene, {}, other->get());
  EXPECT_EQ(wrong.status().code(), absl::StatusCode::kInvalidArgument);
  // A scene with a bad vertex index is refused when indexed.
  Scene broken = MakeScene(Cloud(2, 1));
  broken.triangles[1][2] = 99;
  EXPECT_EQ(SceneTriangleIndex::Build(std::make_shared<const Scene>(broken)).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(LightVisibilityTest, AnIndexOfSubnormalTrianglesHoldsThemAll) {
  // Centres spread over a subnormal extent: the hierarchy's Morton cells
  // are a ratio to that extent (scaling by its inverse overflowed to
  // infinity, and 0 x infinity is no cell; UBSan reports the cast).
  std::vector<Tri> tris;
  for (int i = 0; i < 40; ++i) {
    const double x = (i % 8) * 1e-310, y = (i / 8) * 1e-310;
    tris.push_back({glm::dvec3(x, y, 0), glm::dvec3(x + 1e-310, y, 0), glm::dvec3(x, y + 1e-310, 1e-310)});
  }
  const Scene scene = MakeScene(tris);
  auto index = SceneTriangleIndex::Build(std::make_shared<const Scene>(scene));
  ASSERT_TRUE(index.ok()) << index.status();
  const std::vector<uint32_t> all = (*index)->InBox(glm::dvec3(-1.0), glm::dvec3(1.0));
  EXPECT_EQ(all.size(), tris.size());
  EXPECT_EQ((*index)->CountInBox(glm::dvec3(-1.0), glm::dvec3(1.0), 1000), tris.size());
  // A thin box meets the first column only (their corners at x = 0); the
  // index lists its leaves' triangles, those among them.
  const glm::dvec3 thin_lo(-1.0), thin_hi(0.5e-310, 1.0, 1.0);
  EXPECT_EQ((*index)->CountInBox(thin_lo, thin_hi, 1000), 5u);
  const std::vector<uint32_t> near_thin = (*index)->InBox(thin_lo, thin_hi);
  for (uint32_t t = 0; t < tris.size(); t += 8) {
    EXPECT_TRUE(std::binary_search(near_thin.begin(), near_thin.end(), t)) << t;
  }
  EXPECT_LT(near_thin.size(), tris.size());
}

TEST(LightVisibilityTest, PlacedMeshesAreIndexedOnceAndSelectTheSameOccluders) {
  // A cloud placed nine times (rotated, one anisotropically scaled) far
  // from the origin: the index holds it once, answers every box as the
  // flattened scene's triangles would, and trees made with it hold the
  // scanned trees' occluders: the same answers, bit for bit.
  const glm::dvec3 offset(1e6, -2e6, 3e5);
  std::vector<glm::dmat4> worlds;
  for (int i = 0; i < 9; ++i) {
    glm::dmat4 w = glm::translate(glm::dmat4(1.0), offset + glm::dvec3(1.0 * (i % 3 - 1), 1.0 * (i / 3 - 1), 0.0));
    w = glm::rotate(w, 0.7 * i, glm::dvec3(0, 0, 1));
    w = glm::scale(w, i == 4 ? glm::dvec3(0.42, 0.28, 1.0) : glm::dvec3(0.35, 0.35, 1.0));
    worlds.push_back(w);
  }
  const Scene placed = testing::PlaceMesh(MakeScene(Cloud(24, 23)), worlds);
  ASSERT_TRUE(ValidatePlacements(placed).ok()) << ValidatePlacements(placed);
  auto index = SceneTriangleIndex::Build(std::make_shared<const Scene>(placed));
  auto flat_index = SceneTriangleIndex::Build(std::make_shared<const Scene>(testing::Flattened(placed)));
  ASSERT_TRUE(index.ok() && flat_index.ok());
  EXPECT_EQ((*index)->instance_count(), worlds.size());
  EXPECT_EQ((*flat_index)->instance_count(), 0u);
  EXPECT_EQ((*index)->triangle_count(), placed.TriangleCount());
  // The mesh's hierarchy once, plus nine placed boxes (about 200 bytes each,
  // which weigh on a mesh this small), against nine meshes' worth.
  EXPECT_LT((*index)->MemoryBytes(), (*flat_index)->MemoryBytes());

  // Every placement is an instance, so the index answers each box exactly:
  // the triangles whose boxes meet it.
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1.8, 1.8), h(0.0, 2.0), side(0.01, 0.8);
  for (int trial = 0; trial < 300; ++trial) {
    const double x = u(rng), y = u(rng), z = h(rng), sx = side(rng), sy = side(rng), sz = side(rng);
    const glm::dvec3 lo = offset + glm::dvec3(x, y, z), hi = lo + glm::dvec3(sx, sy, sz);
    std::vector<uint32_t> meeting;
    for (uint32_t t = 0; t < placed.TriangleCount(); ++t) {
      const glm::dvec3 a = placed.Vertex(t, 0), b = placed.Vertex(t, 1), c = placed.Vertex(t, 2);
      const glm::dvec3 t_lo = glm::min(a, glm::min(b, c)), t_hi = glm::max(a, glm::max(b, c));
      if (!glm::any(glm::lessThan(t_hi, lo)) && !glm::any(glm::greaterThan(t_lo, hi))) meeting.push_back(t);
    }
    EXPECT_EQ((*index)->InBox(lo, hi), meeting) << "box " << trial;
    EXPECT_EQ((*index)->CountInBox(lo, hi, SIZE_MAX), meeting.size());
    EXPECT_EQ((*flat_index)->CountInBox(lo, hi, SIZE_MAX), meeting.size());
    EXPECT_EQ((*index)->CountInBox(lo, hi, 3), std::min<size_t>(3, meeting.size()));
  }

  AreaLight light = SquareLight(2.0, 0.7);
  for (auto& v : light.vertices) v += offset;
  const auto pts = FloorPoints(24, 29);
  TreeOptions options;
  options.receiver_bounds = Box(offset + glm::dvec3(-1.5, -1.5, 0), offset + glm::dvec3(1.5, 1.5, 0));
  auto scanned = LightVisibilityTree::Create(light, placed, options);
  auto indexed = LightVisibilityTree::Create(light, placed, options, index->get());
  ASSERT_TRUE(scanned.ok() && indexed.ok());
  EXPECT_EQ((*scanned)->Stats().far_occluders, (*indexed)->Stats().far_occluders);
  EXPECT_EQ((*scanned)->Stats().near_occluders, (*indexed)->Stats().near_occluders);
  EXPECT_GT((*indexed)->Stats().far_occluders + (*indexed)->Stats().near_occluders, 60u);
  int partial = 0;
  for (const glm::dvec3& p : pts) {
    const PointVisibility a = Q(**scanned, offset + p), b = Q(**indexed, offset + p);
    EXPECT_EQ(a.visible_area_fraction, b.visible_area_fraction) << p.x << " " << p.y;
    EXPECT_EQ(a.irradiance, b.irradiance);
    partial += a.visible_area_fraction > 0.01 && a.visible_area_fraction < 0.99;
  }
  EXPECT_GT(partial, 5);
}

TEST(LightVisibilityTest, AnOccluderThatHidTheLastPointIsNotThisPointsOwnTriangle) {
  // A query first tries the occluder that hid the whole light from the
  // previous point. A point lying (a rounding below) on that very triangle,
  // named as its receiver, must not be hidden by it.
  const Scene scene = MakeScene({{glm::dvec3(-3, -3, 1), glm::dvec3(3, -3, 1), glm::dvec3(0, 4, 1)}});
  TreeOptions options;
  options.receiver_bounds = Box({-1, -1, 0}, {1, 1, 1});
  options.keep_answers = false;  // the second round takes the shortcut again
  auto tree = LightVisibilityTree::Create(SquareLight(2.0, 0.5), scene, options);
  ASSERT_TRUE(tree.ok()) << tree.status();
  for (int round = 0; round < 2; ++round) {
    auto under = (*tree)->Query({glm::dvec3(0.2, 0.1, 0.0), glm::dvec3(0, 0, 1), std::nullopt});
    ASSERT_TRUE(under.ok());
    EXPECT_EQ(under->visible_area_fraction, 0.0);
    auto on = (*tree)->Query({glm::dvec3(0.2, 0.1, 1.0 - 1e-12), glm::dvec3(0, 0, 1), 0u});
    ASSERT_TRUE(on.ok());
    EXPECT_EQ(on->visible_area_fraction, 1.0) << "round " << round;
  }
  EXPECT_EQ((*tree)->Stats().wholly_hidden, 2u);
}

// ---------------------------------------------------------------------------
// Surfaces modelled two-sided: each triangle and a coincident twin, the same
// three vertices in the other order. A point on the surface, its position
// rounded off the plane, lies a hair in front of one and a hair behind the
// other; by the segment semantics (only what lies strictly between P and the
// light blocks) neither can block, whichever of the two names it. So the
// answers must be those of the same scene without the twins.

// `tris` followed by each triangle of `twinned` (indices into tris) again in
// reverse winding; *twins gets the twins' scene ids, in that order.
std::vector<Tri> WithTwins(std::vector<Tri> tris, const std::vector<size_t>& twinned, std::vector<uint32_t>* twins) {
  for (const size_t i : twinned) {
    twins->push_back(static_cast<uint32_t>(tris.size()));
    tris.push_back({tris[i][0], tris[i][2], tris[i][1]});
  }
  return tris;
}

// Points on receiver triangles (interpolated, so rounded), each asked as
// lying on its triangle and on its twin, with the normal of the side that
// faces the light; a reference tree over the scene without the twins
// answers them as lying on the triangle. Returns how many were answered
// in a penumbra, and how many the twinned scene answered wrong by more than
// 1e-12 (every comparison is also an expectation).
struct TwinCheck {
  size_t penumbra = 0, lit = 0, wrong = 0;
};
TwinCheck CheckTwinsBlockNothing(const Scene& scene, const AreaLight& light, const std::vector<uint32_t>& twins,
                                 const std::vector<std::pair<uint32_t, uint32_t>>& receivers, int per_triangle,
                                 uint32_t seed, const std::optional<Bounds>& bounds, size_t direct) {
  TreeOptions twinned, reference;
  twinned.receiver_bounds = reference.receiver_bounds = bounds;
  twinned.direct_candidates = reference.direct_candidates = direct;
  reference.exclude_triangles = twins;
  auto tree = LightVisibilityTree::Create(light, scene, twinned);
  auto ref = LightVisibilityTree::Create(light, scene, reference);
  EXPECT_TRUE(tree.ok() && ref.ok());
  if (!tree.ok() || !ref.ok()) return {};
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.02, 1.0);
  TwinCheck check;
  for (const auto& [triangle, twin] : receivers) {
    const glm::uvec3 t = scene.triangles[triangle];
    const glm::dvec3 a = scene.positions[t[0]], b = scene.positions[t[1]], c = scene.positions[t[2]];
    const glm::dvec3 up = glm::cross(b - a, c - a);
    for (int k = 0; k < per_triangle; ++k) {
      const double w[3] = {u(rng), u(rng), u(rng)};
      const double sum = w[0] + w[1] + w[2];
      const glm::dvec3 p = (w[0] / sum) * a + (w[1] / sum) * b + (w[2] / sum) * c;
      auto expected = (*ref)->Query({p, up, triangle});
      EXPECT_TRUE(expected.ok());
      if (!expected.ok()) continue;
      check.penumbra += expected->visible_area_fraction > 0.0 && expected->visible_area_fraction < 1.0;
      check.lit += expected->visible_area_fraction > 0.0;
      // On the triangle, with and without its normal, and on the twin.
      const QueryPoint asked[3] = {{p, up, triangle}, {p, std::nullopt, triangle}, {p, up, twin}};
      bool wrong = false;
      for (const QueryPoint& q : asked) {
        auto r = (*tree)->Query(q);
        EXPECT_TRUE(r.ok());
        if (!r.ok()) continue;
        const auto differs = [](double x, double y) { return !(std::fabs(x - y) <= 1e-12); };
        wrong |= differs(r->visible_area_fraction, expected->visible_area_fraction) ||
                 differs(r->visible_solid_angle_fraction, expected->visible_solid_angle_fraction) ||
                 differs(r->irradiance, expected->irradiance);
        EXPECT_NEAR(r->visible_area_fraction, expected->visible_area_fraction, 1e-12)
            << "triangle " << triangle << " twin " << twin << " point " << k << " at " << p.x << " " << p.y << " "
            << p.z << (q.receiver_triangle == twin ? " (on the twin)" : "") << (q.normal ? "" : " (no normal)");
        EXPECT_NEAR(r->visible_solid_angle_fraction, expected->visible_solid_angle_fraction, 1e-12);
        EXPECT_NEAR(r->irradiance, expected->irradiance, 1e-12);
      }
      check.wrong += wrong;
    }
  }
  return check;
}

// Occluders for the twin tests: a cloud of small triangles between the
// surface (about z = 0) and the light.
std::vector<Tri> CloudAbove(int count, uint32_t seed) {
  std::vector<Tri> tris = Cloud(count, seed, 0.25);
  for (Tri& t : tris) {
    for (glm::dvec3& p : t) p.z += 0.4;
  }
  return tris;
}

TEST(LightVisibilityTest, ATwoSidedSheetsTwinsBlockNothingOfThePointsOnIt) {
  // A tilted sheet of 4 x 4 quads, each two triangles wound to face up, and
  // every triangle again facing down (appended, as exporters write a
  // double-sided mesh's back faces), under a cloud and a light.
  constexpr int kCells = 4;
  const auto corner = [](int i, int j) {
    const double x = -1.5 + 3.0 * i / kCells, y = -1.5 + 3.0 * j / kCells;
    return glm::dvec3(x, y, 0.07 * x + 0.03 * y + 0.01);
  };
  std::vector<Tri> sheet;
  for (int j = 0; j < kCells; ++j) {
    for (int i = 0; i < kCells; ++i) {
      sheet.push_back({corner(i, j), corner(i + 1, j), corner(i + 1, j + 1)});
      sheet.push_back({corner(i, j), corner(i + 1, j + 1), corner(i, j + 1)});
    }
  }
  std::vector<size_t> all(sheet.size());
  for (size_t i = 0; i < all.size(); ++i) all[i] = i;
  std::vector<Tri> tris = sheet;
  for (const Tri& t : CloudAbove(25, 31)) tris.push_back(t);
  std::vector<uint32_t> twins;
  tris = WithTwins(tris, all, &twins);
  const Scene scene = MakeScene(tris);
  std::vector<std::pair<uint32_t, uint32_t>> receivers;
  for (size_t i = 0; i < sheet.size(); ++i) receivers.emplace_back(static_cast<uint32_t>(i), twins[i]);
  const AreaLight light = SquareLight(2.5, 0.6);
  for (const size_t direct : {size_t{32}, size_t{0}}) {
    for (const std::optional<Bounds>& bounds :
         {std::optional<Bounds>(Box({-1.5, -1.5, -0.2}, {1.5, 1.5, 0.2})), std::optional<Bounds>()}) {
      SCOPED_TRACE(::testing::Message() << "direct " << direct << (bounds ? " bounds" : " no bounds"));
      const TwinCheck check = CheckTwinsBlockNothing(scene, light, twins, receivers, 12, 3, bounds, direct);
      EXPECT_EQ(check.wrong, 0u);
      EXPECT_GT(check.penumbra, 60u);
      EXPECT_GT(check.lit, 200u);
    }
  }
}

TEST(LightVisibilityTest, AScannedMeshsCoincidentPairsBlockNothingOfThePointsOnThem) {
  // A bumpy heightfield (no two neighbours coplanar) where a scan left a
  // third of the faces twice, the copies reversed; points on twinned faces
  // and on single ones.
  constexpr int kCells = 10;
  std::mt19937 rng(8);
  std::uniform_real_distribution<double> bump(-0.04, 0.04), pick(0, 1);
  std::vector<glm::dvec3> grid;
  for (int j = 0; j <= kCells; ++j) {
    for (int i = 0; i <= kCells; ++i) {
      grid.emplace_back(-1.5 + 3.0 * i / kCells + 0.3 * bump(rng), -1.5 + 3.0 * j / kCells + 0.3 * bump(rng),
                        bump(rng));
    }
  }
  const auto at = [&](int i, int j) { return grid[static_cast<size_t>(j * (kCells + 1) + i)]; };
  std::vector<Tri> mesh;
  for (int j = 0; j < kCells; ++j) {
    for (int i = 0; i < kCells; ++i) {
      mesh.push_back({at(i, j), at(i + 1, j), at(i + 1, j + 1)});
      mesh.push_back({at(i, j), at(i + 1, j + 1), at(i, j + 1)});
    }
  }
  std::vector<size_t> twinned;
  for (size_t i = 0; i < mesh.size(); ++i) {
    if (pick(rng) < 0.35) twinned.push_back(i);
  }
  std::vector<Tri> tris = mesh;
  for (const Tri& t : CloudAbove(30, 47)) tris.push_back(t);
  std::vector<uint32_t> twins;
  tris = WithTwins(tris, twinned, &twins);
  const Scene scene = MakeScene(tris);
  std::vector<std::pair<uint32_t, uint32_t>> receivers;
  for (size_t k = 0; k < twinned.size(); ++k) receivers.emplace_back(static_cast<uint32_t>(twinned[k]), twins[k]);
  // A face without a twin, asked as lying on itself twice.
  for (size_t i = 0; i < mesh.size(); i += 7) {
    if (!std::binary_search(twinned.begin(), twinned.end(), i)) {
      receivers.emplace_back(static_cast<uint32_t>(i), static_cast<uint32_t>(i));
    }
  }
  const AreaLight light = SquareLight(2.5, 0.6);
  for (const size_t direct : {size_t{32}, size_t{0}}) {
    for (const std::optional<Bounds>& bounds :
         {std::optional<Bounds>(Box({-1.6, -1.6, -0.1}, {1.6, 1.6, 0.1})), std::optional<Bounds>()}) {
      SCOPED_TRACE(::testing::Message() << "direct " << direct << (bounds ? " bounds" : " no bounds"));
      const TwinCheck check = CheckTwinsBlockNothing(scene, light, twins, receivers, 4, 5, bounds, direct);
      EXPECT_EQ(check.wrong, 0u);
      EXPECT_GT(check.penumbra, 60u);
      EXPECT_GT(check.lit, 200u);
    }
  }
}

TEST(LightVisibilityTest, OccludersThroughAPointWithoutAReceiverBlockNothingOfIt) {
  // Points placed exactly (in double) on a tilted two-sided sheet, on its
  // triangles' edges and vertices too, and on a wall standing across it,
  // asked without a receiver triangle: every triangle through P touches the
  // segments to the light at P only, so the answers are those without the
  // triangles through P. Dyadic coordinates keep the plane z = 0.25 + x / 8
  // exact.
  const auto on_sheet = [](double x, double y) { return glm::dvec3(x, y, 0.25 + 0.125 * x); };
  std::vector<Tri> tris;
  std::vector<uint32_t> sheet, wall;
  for (int j = -2; j < 2; ++j) {
    for (int i = -2; i < 2; ++i) {
      const double x0 = 0.75 * i, y0 = 0.75 * j, x1 = x0 + 0.75, y1 = y0 + 0.75;
      const Tri a{on_sheet(x0, y0), on_sheet(x1, y0), on_sheet(x1, y1)};
      const Tri b{on_sheet(x0, y0), on_sheet(x1, y1), on_sheet(x0, y1)};
      for (const Tri& t : {a, b}) {
        for (const Tri& side : {t, Tri{t[0], t[2], t[1]}}) {
          sheet.push_back(static_cast<uint32_t>(tris.size()));
          tris.push_back(side);
        }
      }
    }
  }
  // The wall x = 0.5, across the sheet and the light's shadow, up to z = 1.
  wall.push_back(static_cast<uint32_t>(tris.size()));
  tris.push_back({glm::dvec3(0.5, -1.5, 0.0), glm::dvec3(0.5, 1.5, 0.0), glm::dvec3(0.5, 0.0, 1.0)});
  for (const Tri& t : CloudAbove(25, 53)) tris.push_back(t);
  const Scene scene = MakeScene(tris);
  std::vector<QueryPoint> on_the_sheet, on_the_wall;
  for (int j = -48; j <= 48; j += 3) {
    for (int i = -48; i <= 48; i += 3) {
      on_the_sheet.push_back({on_sheet(i / 32.0, j / 32.0), glm::dvec3(-0.125, 0.0, 1.0), std::nullopt});
    }
  }
  // Above the sheet (z = 0.3125 at the wall) and below the wall's top.
  for (int j = -16; j <= 16; ++j) {
    const double y = j / 16.0, z = 0.3125 + 0.5 * (0.6875 - std::fabs(y) / 1.5);
    on_the_wall.push_back({glm::dvec3(0.5, y, z), glm::dvec3(1.0, 0.0, 1.0), std::nullopt});
  }
  // A tilted light: no sheet or wall plane is parallel to it.
  const AreaLight light{{{-0.6, -0.6, 2.4}, {-0.6, 0.6, 2.5}, {0.6, 0.6, 2.6}, {0.6, -0.6, 2.5}}, 1.0};
  for (const size_t direct : {size_t{32}, size_t{0}}) {
    for (const std::optional<Bounds>& bounds :
         {std::optional<Bounds>(Box({-1.5, -1.5, 0.0}, {1.5, 1.5, 1.0})), std::optional<Bounds>()}) {
      SCOPED_TRACE(::testing::Message() << "direct " << direct << (bounds ? " bounds" : " no bounds"));
      TreeOptions with;
      with.receiver_bounds = bounds;
      with.direct_candidates = direct;
      auto tree = LightVisibilityTree::Create(light, scene, with);
      ASSERT_TRUE(tree.ok());
      size_t penumbra = 0;
      for (const auto& [points, through] : {std::pair(&on_the_sheet, &sheet), std::pair(&on_the_wall, &wall)}) {
        TreeOptions without = with;
        without.exclude_triangles = *through;
        auto ref = LightVisibilityTree::Create(light, scene, without);
        ASSERT_TRUE(ref.ok());
        for (const QueryPoint& q : *points) {
          auto r = (*tree)->Query(q);
          auto e = (*ref)->Query(q);
          ASSERT_TRUE(r.ok() && e.ok());
          penumbra += e->visible_area_fraction > 0.0 && e->visible_area_fraction < 1.0;
          EXPECT_NEAR(r->visible_area_fraction, e->visible_area_fraction, 1e-12)
              << q.position.x << " " << q.position.y << " " << q.position.z;
          EXPECT_NEAR(r->visible_solid_angle_fraction, e->visible_solid_angle_fraction, 1e-12);
          EXPECT_NEAR(r->irradiance, e->irradiance, 1e-12);
        }
      }
      EXPECT_GT(penumbra, 100u);
    }
  }
}

// A light lying exactly in a surface's plane (the emitter's own quad, a
// wall it is set in) is blocked by none of it: every segment from a point
// ends on the light, where such a triangle lies (SelectTriangle drops the
// triangles with no vertex strictly in front of the light). The same
// emitter a hair (one ulp) in front of the light lies strictly between and
// hides it, but for slivers: the answer is that of the literal geometry.
// The light's height is not dyadic, so the local frame's rounding is
// exercised (the plane is an axis plane: it stays one).
TEST(LightVisibilityTest, TrianglesInTheLightsPlaneBlockNothingAHairInFrontHideIt) {
  const double z = 2.443769931793213, h = 0.5;
  const AreaLight light = SquareLight(z, h);
  const auto emitter = [&](double at) {
    const glm::dvec3 a(-h, -h, at), b(-h, h, at), c(h, h, at), d(h, -h, at);
    return std::vector<Tri>{{a, b, c}, {a, c, d}, {a, c, b}, {a, d, c}};  // both windings
  };
  std::vector<Tri> tris = {// A small occluder between, for a penumbra.
                           {glm::dvec3(-0.4, -0.4, 1.2), glm::dvec3(0.3, -0.2, 1.25), glm::dvec3(0.0, 0.4, 1.3)}};
  const uint32_t first_in_plane = static_cast<uint32_t>(tris.size());
  for (const Tri& t : emitter(z)) tris.push_back(t);
  // A wall panel beside the light, in its plane, sharing its edge x = h.
  tris.push_back({glm::dvec3(h, -2, z), glm::dvec3(2, -2, z), glm::dvec3(2, 2, z)});
  tris.push_back({glm::dvec3(h, -2, z), glm::dvec3(2, 2, z), glm::dvec3(h, 2, z)});
  std::vector<uint32_t> in_plane;
  for (uint32_t t = first_in_plane; t < tris.size(); ++t) in_plane.push_back(t);
  const Scene scene = MakeScene(tris);
  std::vector<Tri> ahead = {tris[0]};
  for (const Tri& t : emitter(std::nextafter(z, 0.0))) ahead.push_back(t);
  const Scene hair_ahead = MakeScene(ahead);

  const std::vector<glm::dvec3> pts = FloorPoints(64, 29);
  for (const size_t direct : {size_t{32}, size_t{0}}) {
    for (const std::optional<Bounds>& bounds :
         {std::optional<Bounds>(Box({-1.5, -1.5, 0.0}, {1.5, 1.5, 0.0})), std::optional<Bounds>()}) {
      SCOPED_TRACE(::testing::Message() << "direct " << direct << (bounds ? " bounds" : " no bounds"));
      TreeOptions with;
      with.receiver_bounds = bounds;
      with.direct_candidates = direct;
      TreeOptions without = with;
      without.exclude_triangles = in_plane;
      auto tree = LightVisibilityTree::Create(light, scene, with);
      auto ref = LightVisibilityTree::Create(light, scene, without);
      auto hidden = LightVisibilityTree::Create(light, hair_ahead, with);
      ASSERT_TRUE(tree.ok() && ref.ok() && hidden.ok());
      int penumbra = 0;
      for (const glm::dvec3& p : pts) {
        const QueryPoint q{p, glm::dvec3(0, 0, 1), std::nullopt};
        auto r = (*tree)->Query(q);
        auto e = (*ref)->Query(q);
        auto x = (*hidden)->Query(q);
        ASSERT_TRUE(r.ok() && e.ok() && x.ok());
        EXPECT_NEAR(r->visible_area_fraction, e->visible_area_fraction, 1e-12) << p.x << " " << p.y;
        EXPECT_NEAR(r->irradiance, e->irradiance, 1e-12) << p.x << " " << p.y;
        EXPECT_GT(e->visible_area_fraction, 0.0) << p.x << " " << p.y;
        EXPECT_LE(x->visible_area_fraction, 1e-12) << p.x << " " << p.y;
        penumbra += e->visible_area_fraction < 1.0;
      }
      EXPECT_GT(penumbra, 4);
    }
  }
}

// The shared veach-ajar scene's emitter quad (node trianglemesh_Light, at
// z = -4.44377 in float32: -4.443769931793213) as the source of the
// hidden-sample map asked for in the report (the floor at y = 0.01, 32 x 32
// texel centres). Given in the emitter's plane, the emitter blocks nothing
// and the exact answers agree with Embree's rays (384 of the 1,024 points
// see the whole light, the rest none). Given with z = -4.44377 in double,
// the source lies 6.8e-8 m behind the emitter, which then lies strictly
// between every point and the source and hides all of it but slivers along
// two edges (float32 rounded the emitter's corners inwards there): each
// point's answer is the sliver's share, 2e-8 to 4e-7, computed here in
// closed form. RAYCAST answers 0.375 there too, as it ignores geometry
// within 2^-17 of the coordinates' magnitude of a segment's end (proto).
TEST(LightVisibilityTest, VeachAjarsEmitterQuadAsTheSourceHidesItOnlyWhenTheSourceLiesBehind) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  auto scene = LoadGltfFile(scenes / "interior_veach_ajar/veach_ajar.gltf");
  ASSERT_TRUE(scene.ok()) << scene.status();
  const SceneNode* emitter = nullptr;
  for (const SceneNode& node : scene->nodes)
    if (node.name == "trianglemesh_Light") emitter = &node;
  ASSERT_NE(emitter, nullptr);
  ASSERT_EQ(emitter->triangle_count, 2u);
  glm::dvec3 lo(INFINITY), hi(-INFINITY);
  for (uint32_t t = emitter->first_triangle; t < emitter->first_triangle + 2; ++t) {
    for (int k = 0; k < 3; ++k) {
      lo = glm::min(lo, scene->Vertex(t, k));
      hi = glm::max(hi, scene->Vertex(t, k));
    }
  }
  ASSERT_EQ(lo.z, hi.z);
  ASSERT_EQ(lo.z, double(-4.44377f));
  // The source as the report gave it (origin + edges, as the server's
  // ExactLightQuery makes the corners), wound to face +z (the receivers).
  const auto source = [](double z) {
    const glm::dvec3 o(-5.16954, 0.185195, z), u(1.46089, 0, 0), v(0, 2.642725, 0);
    return AreaLight{{o, o + u, o + u + v, o + v}, 1.0};
  };
  std::vector<glm::dvec3> pts;
  for (int y = 0; y < 32; ++y)
    for (int x = 0; x < 32; ++x)
      pts.push_back(glm::dvec3(-9.0 + 16.0 * ((x + 0.5) / 32), 0.01, 0.5 - 4.5 * ((y + 0.5) / 32)));
  TreeOptions options;
  options.receiver_bounds = Box({-9, 0.01, -4}, {7, 0.01, 0.5});

  const AreaLight in_plane = source(lo.z);
  auto tree = LightVisibilityTree::Create(in_plane, *scene, options);
  ASSERT_TRUE(tree.ok()) << tree.status();
  std::vector<double> on;
  int whole = 0;
  for (const glm::dvec3& p : pts) {
    auto r = (*tree)->Query({p, std::nullopt, std::nullopt});
    ASSERT_TRUE(r.ok()) << r.status();
    on.push_back(r->visible_area_fraction);
    whole += r->visible_area_fraction == 1.0;
  }
  EXPECT_EQ(whole, 384);
  // Embree's rays to the source, every 17th point.
  auto embree = raycast::EmbreeScene::Create(*scene);
  ASSERT_TRUE(embree.ok());
  constexpr int kSamples = 256;
  std::mt19937 rng(14);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  const glm::dvec3 o = in_plane.vertices[0], eu = in_plane.vertices[1] - o, ev = in_plane.vertices[3] - o;
  std::vector<raycast::Segment> segs;
  std::vector<size_t> asked;
  for (size_t i = 0; i < pts.size(); i += 17) {
    asked.push_back(i);
    for (int k = 0; k < kSamples; ++k) segs.push_back({pts[i], o + u01(rng) * eu + u01(rng) * ev});
  }
  auto occ = embree->Occluded(segs);
  ASSERT_TRUE(occ.ok());
  for (size_t j = 0; j < asked.size(); ++j) {
    int visible = 0;
    for (int k = 0; k < kSamples; ++k) visible += (*occ)[j * kSamples + k] == 0;
    EXPECT_LT(std::abs(double(visible) / kSamples - on[asked[j]]), 6.0 * 0.5 / std::sqrt(kSamples))
        << "point " << asked[j];
  }

  // A hair behind: the emitter hides the source but for slivers.
  const AreaLight behind = source(-4.44377);
  ASSERT_LT(behind.vertices[0].z, lo.z);
  auto hidden = LightVisibilityTree::Create(behind, *scene, options);
  ASSERT_TRUE(hidden.ok()) << hidden.status();
  const glm::dvec3 s0 = behind.vertices[0], s1 = behind.vertices[2];
  const double area = (s1.x - s0.x) * (s1.y - s0.y);
  for (size_t i = 0; i < pts.size(); ++i) {
    const glm::dvec3& p = pts[i];
    auto r = (*hidden)->Query({p, std::nullopt, std::nullopt});
    ASSERT_TRUE(r.ok()) << r.status();
    if (on[i] != 1.0) {
      EXPECT_EQ(r->visible_area_fraction, 0.0) << "point " << i;
      continue;
    }
    // The emitter seen from P, on the source's plane: scaled about P.
    const double s = (p.z - s0.z) / (p.z - lo.z);
    const double x0 = std::max(s0.x, p.x + s * (lo.x - p.x)), x1 = std::min(s1.x, p.x + s * (hi.x - p.x));
    const double y0 = std::max(s0.y, p.y + s * (lo.y - p.y)), y1 = std::min(s1.y, p.y + s * (hi.y - p.y));
    const double sliver = ((s1.x - s0.x) * (s1.y - s0.y) - (x1 - x0) * (y1 - y0)) / area;
    EXPECT_GT(r->visible_area_fraction, 1e-8) << "point " << i;
    EXPECT_LT(r->visible_area_fraction, 1e-6) << "point " << i;
    EXPECT_NEAR(r->visible_area_fraction, sliver, 1e-12) << "point " << i;
  }
}

TEST(LightVisibilityTest, ReceiverCellsHoldTheirPointsAndGiveTheSameAnswers) {
  // Far from the origin, so that the cubes' faces round: every cell's box
  // must still hold its points (a tree refuses points outside its box).
  const glm::dvec3 offset(1e6, -2e6, 3e5);
  std::vector<Tri> tris = Transform(Cloud(120, 7, 0.2), 1.0, offset);
  const Scene scene = MakeScene(tris);
  std::vector<QueryPoint> points;
  for (const glm::dvec3& p : FloorPoints(40, 23)) points.push_back({offset + p, glm::dvec3(0, 0, 1), std::nullopt});
  // Points on the cubes' faces, and far outside the scene.
  const double cell = std::max({scene.bounds.Extent().x, scene.bounds.Extent().y, scene.bounds.Extent().z}) / 8;
  points.push_back({scene.bounds.min + glm::dvec3(cell, 2 * cell, 0.0), glm::dvec3(0, 0, 1), std::nullopt});
  points.push_back({offset + glm::dvec3(1e5, -3e4, 0.0), glm::dvec3(0, 0, 1), std::nullopt});
  const auto cells = GroupReceivers(points, scene.bounds, 8);
  ASSERT_GT(cells.size(), 4u);
  std::vector<int> seen(points.size(), 0);
  for (const ReceiverCell& c : cells) {
    ASSERT_FALSE(c.points.empty());
    EXPECT_TRUE(std::is_sorted(c.points.begin(), c.points.end()));
    for (uint32_t i : c.points) {
      ++seen[i];
      const glm::dvec3& x = points[i].position;
      EXPECT_TRUE(glm::all(glm::greaterThanEqual(x, c.box.min)) && glm::all(glm::lessThanEqual(x, c.box.max)))
          << "point " << i;
    }
    // A cube of the grid, unless it had to grow to hold a point.
    const glm::dvec3 e = c.box.Extent();
    EXPECT_GE(std::min({e.x, e.y, e.z}), cell * (1 - 1e-9));
  }
  for (size_t i = 0; i < points.size(); ++i) EXPECT_EQ(seen[i], 1) << "point " << i;
  // The same grouping for the same points: cached trees are found again.
  const auto again = GroupReceivers(points, scene.bounds, 8);
  ASSERT_EQ(again.size(), cells.size());
  for (size_t c = 0; c < cells.size(); ++c) {
    EXPECT_EQ(again[c].box.min, cells[c].box.min);
    EXPECT_EQ(again[c].box.max, cells[c].box.max);
  }
  // A scene near the doubles' range: every box stays finite.
  Bounds vast;
  vast.Extend(glm::dvec3(-1e308));
  vast.Extend(glm::dvec3(1e308));
  const std::vector<QueryPoint> extremes = {{glm::dvec3(1.7e308, 0, 0), std::nullopt, std::nullopt},
                                            {glm::dvec3(-1e308, 1e308, 3), std::nullopt, std::nullopt}};
  for (const ReceiverCell& c : GroupReceivers(extremes, vast, 32)) {
    for (int axis = 0; axis < 3; ++axis) {
      EXPECT_TRUE(std::isfinite(c.box.min[axis]) && std::isfinite(c.box.max[axis]));
    }
    for (uint32_t i : c.points) {
      EXPECT_TRUE(glm::all(glm::greaterThanEqual(extremes[i].position, c.box.min)) &&
                  glm::all(glm::lessThanEqual(extremes[i].position, c.box.max)));
    }
  }
  // One tree per cell answers as one tree over all the points does.
  AreaLight light = SquareLight(2.0, 0.7);
  for (auto& v : light.vertices) v += offset;
  TreeOptions whole;
  whole.receiver_bounds = Bounds();
  for (const QueryPoint& q : points) whole.receiver_bounds->Extend(q.position);
  auto one = LightVisibilityTree::Create(light, scene, whole);
  ASSERT_TRUE(one.ok()) << one.status();
  int penumbra = 0;
  for (const ReceiverCell& c : cells) {
    TreeOptions options;
    options.receiver_bounds = c.box;
    auto tree = LightVisibilityTree::Create(light, scene, options);
    ASSERT_TRUE(tree.ok()) << tree.status();
    for (uint32_t i : c.points) {
      auto a = (*tree)->Query(points[i]);
      auto b = (*one)->Query(points[i]);
      ASSERT_TRUE(a.ok() && b.ok()) << "point " << i;
      EXPECT_NEAR(a->visible_area_fraction, b->visible_area_fraction, 1e-12) << "point " << i;
      EXPECT_NEAR(a->irradiance, b->irradiance, 1e-12 * std::max(1.0, b->irradiance)) << "point " << i;
      penumbra += b->visible_area_fraction > 0 && b->visible_area_fraction < 1;
    }
  }
  EXPECT_GT(penumbra, 20) << "the comparison must include partly lit points";
}


// Sparse receivers share trees: cubes with fewer than min_points points give
// them to their parent cubes, while a dense cluster keeps its small cubes.
// Every point lands in exactly one group whose box holds it, and the same
// batch gives the same boxes (so its cached trees are found again).
TEST(LightVisibilityTest, SparseReceiversMergeIntoParentCubesDenseOnesStay) {
  std::vector<Tri> tris = Cloud(60, 3, 0.2);
  const Scene scene = MakeScene(tris);
  const glm::dvec3 lo = scene.bounds.min, e = scene.bounds.Extent();
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<QueryPoint> points;
  for (int i = 0; i < 100; ++i)  // scattered: about one per fine cube
    points.push_back({lo + glm::dvec3(u(rng), u(rng), u(rng)) * e, std::nullopt, std::nullopt});
  const glm::dvec3 corner = lo + 0.01 * e;
  for (int i = 0; i < 400; ++i)  // dense: one fine cube
    points.push_back({corner + glm::dvec3(u(rng), u(rng), u(rng)) * (0.02 * e), std::nullopt, std::nullopt});
  const auto fine = GroupReceivers(points, scene.bounds, 32);
  const auto merged = GroupReceivers(points, scene.bounds, 32, 64);
  EXPECT_GT(fine.size(), 60u);
  EXPECT_LT(merged.size(), 12u) << "sparse points share a few trees";
  std::vector<int> seen(points.size(), 0);
  bool dense_cube_kept = false;
  for (const ReceiverCell& c : merged) {
    ASSERT_FALSE(c.points.empty());
    EXPECT_TRUE(std::is_sorted(c.points.begin(), c.points.end()));
    for (uint32_t i : c.points) {
      ++seen[i];
      EXPECT_TRUE(glm::all(glm::greaterThanEqual(points[i].position, c.box.min)) &&
                  glm::all(glm::lessThanEqual(points[i].position, c.box.max)));
    }
    const double side = std::max({e.x, e.y, e.z}) / 32;
    if (c.points.size() >= 64 && c.box.Extent().x <= side * (1 + 1e-9)) dense_cube_kept = true;
  }
  for (size_t i = 0; i < points.size(); ++i) EXPECT_EQ(seen[i], 1) << "point " << i;
  EXPECT_TRUE(dense_cube_kept) << "the dense cluster keeps its small cube";
  for (size_t c = 1; c < merged.size(); ++c) EXPECT_LT(merged[c - 1].points[0], merged[c].points[0]);
  const auto again = GroupReceivers(points, scene.bounds, 32, 64);
  ASSERT_EQ(again.size(), merged.size());
  for (size_t c = 0; c < merged.size(); ++c) {
    EXPECT_EQ(again[c].box.min, merged[c].box.min);
    EXPECT_EQ(again[c].box.max, merged[c].box.max);
  }
}

TEST(LightVisibilityTest, ShaftGroupsSplitOnlyWhereTheOccludersAreMany) {
  // A dense cloud over the left half of the floor, nothing over the right.
  std::vector<Tri> tris;
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  // Draws in sequence (an argument list's order is the compiler's), so the
  // cloud is the same under every compiler: z, y, then x.
  auto draw = [&] {
    const double z = u(rng), y = u(rng), x = u(rng);
    return glm::dvec3(x, y, z);
  };
  for (int i = 0; i < 4000; ++i) {
    const glm::dvec3 r = draw();
    const glm::dvec3 c(-1.0 + 0.45 * r.x, 1.4 * r.y, 1.0 + 0.5 * r.z);
    Tri t;
    for (auto& p : t) p = c + 0.03 * draw();
    tris.push_back(t);
  }
  const Scene scene = MakeScene(tris);
  auto index = SceneTriangleIndex::Build(std::make_shared<const Scene>(scene));
  ASSERT_TRUE(index.ok());
  std::vector<QueryPoint> points;
  for (const auto& p : FloorPoints(1024, 12)) points.push_back({p, glm::dvec3(0, 0, 1), std::nullopt});

  // Few occluders in every shaft: one group over the points' own box.
  const AreaLight light = SquareLight(2.0, 0.2);
  const auto one = GroupReceiversByShaft(points, light, **index, {100000, 64});
  ASSERT_EQ(one.size(), 1u);
  EXPECT_EQ(one[0].points.size(), points.size());
  Bounds points_box;
  for (const auto& q : points) points_box.Extend(q.position);
  EXPECT_EQ(one[0].box.min, points_box.min);
  EXPECT_EQ(one[0].box.max, points_box.max);

  // A smaller budget: groups split, and never below min_points; every point
  // is in one group, inside its box; their trees answer as one tree does.
  const auto groups = GroupReceiversByShaft(points, light, **index, {1500, 64});
  EXPECT_GE(groups.size(), 2u);
  std::vector<int> seen(points.size(), 0);
  for (const ReceiverCell& g : groups) {
    EXPECT_GE(g.points.size(), 64u);
    for (uint32_t i : g.points) {
      ++seen[i];
      EXPECT_TRUE(glm::all(glm::greaterThanEqual(points[i].position, g.box.min)) &&
                  glm::all(glm::lessThanEqual(points[i].position, g.box.max)));
    }
    if (&g != &groups.front()) {
      EXPECT_LT((&g - 1)->points.front(), g.points.front()) << "in order of their first point";
    }
  }
  for (size_t i = 0; i < points.size(); ++i) EXPECT_EQ(seen[i], 1) << "point " << i;
  TreeOptions whole_options;
  whole_options.receiver_bounds = points_box;
  auto whole = LightVisibilityTree::Create(light, scene, whole_options, index->get());
  ASSERT_TRUE(whole.ok());
  size_t largest_tree = 0;
  int penumbra = 0;
  for (const ReceiverCell& g : groups) {
    TreeOptions options;
    options.receiver_bounds = g.box;
    auto tree = LightVisibilityTree::Create(light, scene, options, index->get());
    ASSERT_TRUE(tree.ok());
    for (uint32_t i : g.points) {
      auto a = (*tree)->Query(points[i]);
      auto b = (*whole)->Query(points[i]);
      ASSERT_TRUE(a.ok() && b.ok());
      EXPECT_NEAR(a->visible_area_fraction, b->visible_area_fraction, 1e-12) << "point " << i;
      penumbra += a->visible_area_fraction > 0 && a->visible_area_fraction < 1;
    }
    largest_tree = std::max(largest_tree, (*tree)->MemoryBytes());
  }
  EXPECT_GT(penumbra, 50);
  EXPECT_LT(largest_tree, TreeOptions{}.max_bytes);
}

TEST(LightVisibilityCacheTest, ReuseInvalidateAndEvict) {
  const Scene scene = MakeScene(Cloud(60, 51));
  const Bounds receivers = Box({-1.5, -1.5, 0}, {1.5, 1.5, 0});
  auto factory = [&](const AreaLight& light) {
    return [&scene, &receivers, light]() {
      TreeOptions options;
      options.receiver_bounds = receivers;
      return LightVisibilityTree::Create(light, scene, options);
    };
  };
  LightVisibilityCache big(1 << 30);
  const AreaLight l1 = SquareLight(2.0, 0.7);
  const CacheKey k1{"scene", 1, HashLight(l1)};
  auto t1 = big.GetOrCreate(k1, factory(l1));
  ASSERT_TRUE(t1.ok());
  auto again = big.GetOrCreate(k1, []() -> StatusOr<std::unique_ptr<LightVisibilityTree>> {
    ADD_FAILURE() << "factory called on a hit";
    return absl::InternalError("unreachable");
  });
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(t1->get(), again->get());
  EXPECT_EQ(big.size(), 1u);
  big.InvalidateScene("scene");
  EXPECT_EQ(big.size(), 0u);
  EXPECT_EQ(big.Find(k1), nullptr);

  // A bound that holds about two grown trees.
  const auto pts = FloorPoints(50, 2);
  size_t one_tree = 0;
  {
    auto t = factory(l1)();
    ASSERT_TRUE(t.ok());
    for (const auto& p : pts) Q(**t, p);
    one_tree = (*t)->MemoryBytes();
  }
  LightVisibilityCache small(one_tree * 5 / 2);
  for (int i = 0; i < 6; ++i) {
    const AreaLight l = SquareLight(2.0, 0.5 + 0.05 * i);
    auto t = small.GetOrCreate({"scene", 1, HashLight(l)}, factory(l));
    ASSERT_TRUE(t.ok());
    for (const auto& p : pts) Q(**t, p);
  }
  // Growth is measured on access: one more access enforces the bound.
  const AreaLight last = SquareLight(2.0, 0.5 + 0.05 * 5);
  EXPECT_NE(small.Find({"scene", 1, HashLight(last)}), nullptr);
  EXPECT_LE(small.bytes(), one_tree * 5 / 2);
  EXPECT_GT(small.evictions(), 0u);
  EXPECT_LT(small.size(), 6u);
  // The oldest went first.
  const AreaLight first = SquareLight(2.0, 0.5);
  EXPECT_EQ(small.Find({"scene", 1, HashLight(first)}), nullptr);
}

}  // namespace
}  // namespace visq::exact
