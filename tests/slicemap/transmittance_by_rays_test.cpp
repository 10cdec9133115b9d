// Transmittance on each point's own ray (voxel_reference::TransmittanceByRays)
// against chords computed here in closed form: boxes are planar, so the
// path inside one is the line clipped to its slabs, exactly.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "scene/sample_scenes.h"
#include "voxel_reference/transmittance_by_rays.h"

namespace visq::voxel_reference {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

struct Box {
  glm::dvec3 lo, hi;
};

// Length of the line p + t u, t in [t_from, t_to], inside the box.
double LengthInside(const glm::dvec3& p, const glm::dvec3& u, double t_from, double t_to, const Box& box) {
  double t_in = t_from, t_out = t_to;
  for (int a = 0; a < 3; ++a) {
    if (u[a] == 0.0) {
      if (p[a] < box.lo[a] || p[a] > box.hi[a]) return 0.0;
      continue;
    }
    double t0 = (box.lo[a] - p[a]) / u[a], t1 = (box.hi[a] - p[a]) / u[a];
    if (t0 > t1) std::swap(t0, t1);
    t_in = std::max(t_in, t0);
    t_out = std::min(t_out, t1);
  }
  return std::max(0.0, t_out - t_in);
}

// The path from the light to p: the line p + t u with t in [t_light, 0].
void LightLine(const TransmittanceLight& light, const glm::dvec3& p, glm::dvec3& u, double& t_light) {
  if (light.kind == TransmittanceLightKind::kDirectional) {
    u = glm::normalize(light.direction);
    t_light = -kInf;
  } else {
    u = glm::normalize(p - light.position);
    t_light = -glm::length(p - light.position);
  }
}

// Every point not flagged holds its exact value in [od - error, od], with
// an error of rounding only; the transmittance is exp(-od).
void ExpectExact(const TransmittanceResult& result, const std::vector<double>& exact) {
  ASSERT_EQ(result.optical_depth.size(), exact.size());
  for (size_t i = 0; i < exact.size(); ++i) {
    const double od = result.optical_depth[i], error = result.optical_depth_error[i];
    EXPECT_EQ(result.ambiguous[i], 0) << "point " << i;
    EXPECT_LE(exact[i], od) << "point " << i;
    EXPECT_GE(exact[i], od - error) << "point " << i;
    EXPECT_LT(error, 1e-3) << "point " << i << ": rounding only";
    EXPECT_EQ(result.lateral_offset[i], 0.0f);
    EXPECT_NEAR(result.transmittance[i], std::exp(-od), 1e-6);
  }
}

TEST(TransmittanceByRays, ChordsThroughBoxesOfTwoCoefficientsAreTheirLengths) {
  Scene scene;
  // b overlaps a. No line below passes within rounding of two surfaces at
  // once: those count as one crossing, and flag the point (the open
  // absorber's test).
  const Box a{{0, 0, 0}, {2, 2, 2}}, b{{1.5, 0.4, 0.6}, {4, 1.6, 1.45}};
  AddBox(scene, "a", a.lo, a.hi, 0);
  AddBox(scene, "b", b.lo, b.hi, 0);
  AddQuad(scene, "floor", {-5, -2, -5}, {0, 0, 10}, {10, 0, 0}, 0);  // not an absorber
  UpdateBounds(scene);
  for (const bool directional : {true, false}) {
    TransmittanceParams params;
    if (directional) {
      params.light.kind = TransmittanceLightKind::kDirectional;
      params.light.direction = {0.3, -1.0, 0.2};
    } else {
      params.light.kind = TransmittanceLightKind::kPoint;
      params.light.position = {1.23, 1.07, 0.91};  // inside a: the path starts inside it
    }
    params.nodes = {{0, 0.5}, {1, 2.0}};
    params.points = {{0.7, -1.0, 1.1}, {1.0, 1.0, 1.0}, {2.5, 0.2, 1.0}, {3.0, -1.5, 1.0},
                     {8.0, -1.0, 8.0}, {1.7, 0.7, 0.7},  {-3.0, 5.0, 1.0}};
    std::vector<double> exact;
    for (const glm::dvec3& p : params.points) {
      glm::dvec3 u;
      double t_light;
      LightLine(params.light, p, u, t_light);
      // Two coefficients: each box's path counts with its own.
      exact.push_back(0.5 * LengthInside(p, u, t_light, 0.0, a) + 2.0 * LengthInside(p, u, t_light, 0.0, b));
    }
    auto result = TransmittanceByRays(scene, params);
    ASSERT_TRUE(result.ok()) << result.status();
    SCOPED_TRACE(directional ? "directional" : "point light inside a");
    ExpectExact(*result, exact);
    EXPECT_EQ(result->method, "transmittance-ray-stabbing");
    EXPECT_EQ(result->ambiguous_columns, 0u);
    EXPECT_GT(*std::max_element(exact.begin(), exact.end()), 1.0) << "some path crosses a box";
  }
}

// Two boxes of one coefficient that overlap, and a box nested in another:
// the path inside their union counts once (the slicemap's solid), which
// the crossings' facing resolves where a parity would not.
TEST(TransmittanceByRays, OverlappingAndNestedBoxesOfOneCoefficientCountTheirUnion) {
  Scene scene;
  AddBox(scene, "a", {0, 0, 0}, {2, 2, 2}, 0);
  AddBox(scene, "b", {1, 1, 0}, {3, 3, 2}, 0);
  AddBox(scene, "outer", {5, 0, 0}, {8, 3, 3}, 0);
  AddBox(scene, "inner", {6, 1, 1}, {7, 2, 2}, 0);
  UpdateBounds(scene);
  TransmittanceParams params;
  params.light.direction = {0, -1, 0};
  params.nodes = {{0, 1.0}, {1, 1.0}, {2, 1.0}, {3, 1.0}};
  // Under a only, inside both, under b only, under nothing, under the outer
  // box beside the inner one, under both nested ones, inside the inner one.
  params.points = {{0.5, -1, 1}, {1.5, 0.5, 1}, {2.5, -1, 1}, {4.0, -1, 1},
                   {5.5, -1, 1.5}, {6.5, -1, 1.5}, {6.5, 1.5, 1.5}};
  const std::vector<double> union_path = {2.0, 2.5, 2.0, 0.0, 3.0, 3.0, 1.5};
  auto result = TransmittanceByRays(scene, params);
  ASSERT_TRUE(result.ok()) << result.status();
  ExpectExact(*result, union_path);
}

// A BVH of the absorbers built once (a server keeps it) answers as one
// built for the call, bit for bit, under any coefficients and light; one
// built for other nodes is refused.
TEST(TransmittanceByRays, AbsorbersBuiltOnceAnswerAsBuiltForTheCall) {
  Scene scene;
  AddBox(scene, "a", {0, 0, 0}, {2, 2, 2}, 0);
  AddBox(scene, "b", {3, 0, 0}, {5, 2, 2}, 0);
  AddQuad(scene, "floor", {-5, -2, -5}, {0, 0, 10}, {10, 0, 0}, 0);
  UpdateBounds(scene);
  auto kept = BuildAbsorberRays(scene, {1, 0, 1}, {});
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_EQ((*kept)->nodes, (std::vector<uint32_t>{0, 1}));
  EXPECT_GT((*kept)->MemoryBytes(), 0u);
  for (const double sigma_b : {0.5, 3.0}) {
    TransmittanceParams params;
    params.light.kind = TransmittanceLightKind::kPoint;
    params.light.position = {2.5, 6.0, 1.0};
    params.nodes = {{0, 0.5}, {1, sigma_b}};
    params.points = {{1.0, -1.0, 1.0}, {4.0, -1.0, 1.0}, {2.5, -1.0, 1.0}, {1.0, 1.0, 1.0}};
    auto fresh = TransmittanceByRays(scene, params);
    auto reused = TransmittanceByRays(scene, params, kept->get());
    ASSERT_TRUE(fresh.ok() && reused.ok());
    EXPECT_EQ(fresh->optical_depth, reused->optical_depth);
    EXPECT_EQ(fresh->optical_depth_error, reused->optical_depth_error);
    EXPECT_GT(reused->optical_depth[1], 0.0f);
  }
  TransmittanceParams other;
  other.light.direction = {0, -1, 0};
  other.nodes = {{0, 1.0}};
  other.points = {{1.0, -1.0, 1.0}};
  auto refused = TransmittanceByRays(scene, other, kept->get());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  EXPECT_EQ(BuildAbsorberRays(scene, {7}, {}).status().code(), absl::StatusCode::kInvalidArgument);
}

// An open mesh (one quad) in the light's way: the line enters and never
// leaves. Two boxes that share a face: leaving one and entering the other
// happen at one place, within rounding, and count as one crossing. Either
// way the point is flagged and states the whole interval, which holds the
// true path.
TEST(TransmittanceByRays, AnOpenAbsorberAndTouchingOnesFlagThePointsWhoseLinesCrossThem) {
  Scene scene;
  AddBox(scene, "box", {0, 0, 0}, {1, 1, 1}, 0);
  AddQuad(scene, "sheet", {3, 1, 0}, {0, 0, 1}, {1, 0, 0}, 0);  // y = 1, x in [3, 4], facing up: entered, never left
  AddBox(scene, "lower", {6, 0, 0}, {7, 1, 1}, 0);
  AddBox(scene, "upper", {6, 1, 0}, {7, 2, 1}, 0);
  UpdateBounds(scene);
  TransmittanceParams params;
  params.light.direction = {0, -1, 0};
  params.nodes = {{0, 1.0}, {1, 1.0}, {2, 1.0}, {3, 1.0}};
  params.points = {{0.5, -1, 0.5}, {3.5, -1, 0.5}, {6.5, -1, 0.5}};
  auto result = TransmittanceByRays(scene, params);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->ambiguous, (std::vector<uint8_t>{0, 1, 1}));
  EXPECT_EQ(result->ambiguous_columns, 2u);
  EXPECT_NEAR(result->optical_depth[0], 1.0, 1e-4);
  const double truth[3] = {1.0, 0.0, 2.0};
  for (size_t i = 1; i < 3; ++i) {
    EXPECT_EQ(result->optical_depth_error[i], result->optical_depth[i]) << "the whole interval [0, od]";
    EXPECT_GE(result->optical_depth[i], truth[i]) << "point " << i;
  }
}

TEST(TransmittanceByRays, NoAbsorbingTrianglesAbsorbNothing) {
  Scene scene;
  AddBox(scene, "box", {0, 0, 0}, {1, 1, 1}, 0);
  scene.nodes.push_back(SceneNode{"empty", static_cast<int>(scene.nodes.size()), -1, glm::dmat4(1.0), 0, 0});
  UpdateBounds(scene);
  TransmittanceParams params;
  params.nodes = {{1, 3.0}};
  params.points = {{0.5, -1, 0.5}};
  auto result = TransmittanceByRays(scene, params);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->transmittance, std::vector<float>{1.0f});
}

// A node in two coefficients' unions would put two coincident surfaces on
// every line through it: refused, naming the node's entry; the same
// coefficient twice is one union.
TEST(TransmittanceByRays, ANodeWithTwoCoefficientsIsRefusedNamingIt) {
  Scene scene;
  AddBox(scene, "box", {0, 0, 0}, {1, 1, 1}, 0);
  UpdateBounds(scene);
  TransmittanceParams params;
  params.points = {{0.5, -1, 0.5}};
  params.nodes = {{0, 1.0}, {0, 1.0}};
  auto same = TransmittanceByRays(scene, params);
  ASSERT_TRUE(same.ok()) << same.status();
  EXPECT_NEAR(same->optical_depth[0], 1.0, 1e-4);
  params.nodes = {{0, 1.0}, {0, 2.0}};
  auto twice = TransmittanceByRays(scene, params);
  EXPECT_EQ(twice.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(twice.status().message()).find("params.nodes[1]"), std::string::npos) << twice.status();
  params.nodes = {{5, 1.0}};
  EXPECT_EQ(TransmittanceByRays(scene, params).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(TransmittanceByRays, ACancelledCallStops) {
  Scene scene;
  AddBox(scene, "box", {0, 0, 0}, {1, 1, 1}, 0);
  UpdateBounds(scene);
  TransmittanceParams params;
  params.nodes = {{0, 1.0}};
  params.points = {{0.5, -1, 0.5}};
  const std::atomic<bool> cancelled{true};
  params.job.stop.cancelled = &cancelled;
  EXPECT_EQ(TransmittanceByRays(scene, params).status().code(), absl::StatusCode::kCancelled);
}

}  // namespace
}  // namespace visq::voxel_reference
