// The algorithm RPCs end to end through the real server and client, on the
// generated Cornell box: the GPU answer against the ray-cast reference of
// the same segments, the exact light visibility's cache, and bad input.
#include <bit>
#include <cmath>
#include <chrono>
#include <cstdio>
#include <string>
#include <thread>

#include <glm/glm.hpp>
#include <gtest/gtest.h>

#include "server_process.h"
#include "shared_server_suite.h"
#include "proto_builders.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

using client::Client;

using testing::Set;
using testing::SetPatch;

class AlgorithmRpcTest : public testing::SharedServerSuite<AlgorithmRpcTest> {
 protected:

  // The ceiling light (just under it) onto the floor (just above it).
  v1::HiddenSampleMapRequest LightOntoFloor(uint32_t samples, uint32_t size) {
    v1::HiddenSampleMapRequest request;
    request.mutable_scene()->set_name("cornell_box_visq");
    SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    request.mutable_samples()->set_count(samples);
    request.mutable_samples()->set_seed(7);
    SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
    request.set_width(size);
    request.set_height(size);
    request.set_want_bitmasks(true);
    return request;
  }
};

TEST_F(AlgorithmRpcTest, HiddenSampleMapRasterMatchesRaycastBitForBit) {
  v1::HiddenSampleMapRequest request = LightOntoFloor(64, 32);
  request.set_method(v1::RASTER);
  auto raster = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(raster.ok()) << raster.status();
  request.set_method(v1::RAYCAST);
  auto raycast = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(raycast.ok()) << raycast.status();

  ASSERT_EQ(raster->figures.width(), 32u);
  ASSERT_EQ(raster->visible_fraction.size(), 32u * 32u);
  ASSERT_EQ(raster->blocked_bits.size(), raycast->blocked_bits.size());
  size_t differing = 0, blocked = 0;
  for (size_t w = 0; w < raster->blocked_bits.size(); ++w) {
    differing += std::popcount(raster->blocked_bits[w] ^ raycast->blocked_bits[w]);
    blocked += std::popcount(raycast->blocked_bits[w]);
  }
  const size_t total = 32 * 32 * 64;
  EXPECT_GT(blocked, total / 20) << "the boxes should hide part of the light from the floor";
  EXPECT_LT(blocked, total) << "and not all of it";
  EXPECT_LE(differing, total / 10000) << "EXACT lookup must give the ray-cast bits (float ties aside)";
  EXPECT_EQ(raster->figures.accuracy().method(), "raster-exact-lookup");
  EXPECT_EQ(raycast->figures.accuracy().method(), "raycast");
  EXPECT_GT(raster->figures.accuracy().error_bound(), 0.0) << "64 samples have a sampling error";
  EXPECT_GT(raster->figures.timing().total_ms(), 0.0);
  EXPECT_EQ(raster->figures.source_samples_size(), 64);
}

// GPU_RAYCAST traces RAYCAST's float segments in a compute shader: the same
// bits but for float ties on triangle edges, far from the origin too (the
// query's local frame, as RAYCAST's).
TEST_F(AlgorithmRpcTest, HiddenSampleMapGpuRaysMatchRaycastBitForBit) {
  v1::HiddenSampleMapRequest request = LightOntoFloor(128, 32);
  request.set_method(v1::RAYCAST);
  auto raycast = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(raycast.ok()) << raycast.status();
  request.set_method(v1::GPU_RAYCAST);
  auto gpu_rays = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(gpu_rays.ok()) << gpu_rays.status();
  EXPECT_EQ(gpu_rays->figures.accuracy().method(), "gpu-raycast");
  ASSERT_EQ(gpu_rays->blocked_bits.size(), raycast->blocked_bits.size());
  size_t differing = 0, blocked = 0;
  for (size_t w = 0; w < raycast->blocked_bits.size(); ++w) {
    differing += std::popcount(gpu_rays->blocked_bits[w] ^ raycast->blocked_bits[w]);
    blocked += std::popcount(raycast->blocked_bits[w]);
  }
  const size_t total = 32 * 32 * 128;
  std::printf("GPU rays: %zu of %zu bits differ from RAYCAST (%zu blocked)\n", differing, total, blocked);
  EXPECT_GT(blocked, total / 20);
  EXPECT_LE(differing, total / 100000) << "the ray-cast bits, float ties aside";
  EXPECT_DOUBLE_EQ(gpu_rays->figures.accuracy().error_bound(), raycast->figures.accuracy().error_bound());

  v1::PatchVisibilityRequest patches;
  patches.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(patches.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(patches.mutable_receiver(), {-0.999, 0.001, -0.997}, {1.998, 0, 0}, {0, 0, 1.998});
  patches.set_source_columns(8);
  patches.set_source_rows(8);
  patches.set_receiver_columns(16);
  patches.set_receiver_rows(16);
  patches.set_method(v1::RAYCAST);
  auto raycast_patches = client_->PatchVisibility(patches);
  ASSERT_TRUE(raycast_patches.ok()) << raycast_patches.status();
  patches.set_method(v1::GPU_RAYCAST);
  auto gpu_patches = client_->PatchVisibility(patches);
  ASSERT_TRUE(gpu_patches.ok()) << gpu_patches.status();
  EXPECT_EQ(gpu_patches->accuracy().method(), "gpu-raycast");
  EXPECT_NEAR(gpu_patches->mutual_visible_fraction(), raycast_patches->mutual_visible_fraction(), 1e-4);
}

// With no method, a map runs the fastest here of RASTER, RAYCAST and
// GPU_RAYCAST, which give the same bits: the answer says which, lists what was weighed, and
// has the ray caster's bits; the HOUGH lookup is RASTER's alone.
TEST_F(AlgorithmRpcTest, AMapNamingNoMethodRunsTheFasterOfTwoWithTheSameBits) {
  v1::HiddenSampleMapRequest request = LightOntoFloor(64, 32);
  auto chosen = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  request.set_method(v1::RAYCAST);
  auto raycast = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(raycast.ok()) << raycast.status();
  const v1::Accuracy& accuracy = chosen->figures.accuracy();
  EXPECT_TRUE(accuracy.method() == "raster-exact-lookup" || accuracy.method() == "raycast" ||
              accuracy.method() == "gpu-raycast")
      << accuracy.method();
  EXPECT_NE(accuracy.note().find("no method named"), std::string::npos) << accuracy.note();
  ASSERT_GE(accuracy.plans_size(), 1);
  bool chosen_listed = false;
  for (const v1::PlanEstimate& plan : accuracy.plans()) {
    EXPECT_TRUE(plan.method() == "raster-exact-lookup" || plan.method() == "raycast" || plan.method() == "gpu-raycast")
        << plan.method();
    EXPECT_EQ(plan.parameters().at("samples"), 64.0);
    chosen_listed |= plan.method() == accuracy.method();
  }
  EXPECT_TRUE(chosen_listed);
  ASSERT_EQ(chosen->blocked_bits.size(), raycast->blocked_bits.size());
  size_t differing = 0;
  for (size_t w = 0; w < chosen->blocked_bits.size(); ++w)
    differing += std::popcount(chosen->blocked_bits[w] ^ raycast->blocked_bits[w]);
  EXPECT_LE(differing, 32u * 32u * 64u / 10000u) << "the ray-cast bits, float ties aside";
  EXPECT_DOUBLE_EQ(accuracy.error_bound(), raycast->figures.accuracy().error_bound());

  request.set_method(v1::METHOD_UNSPECIFIED);
  request.set_lookup(v1::HOUGH);
  request.set_want_bitmasks(false);
  auto hough = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(hough.ok()) << hough.status();
  EXPECT_EQ(hough->figures.accuracy().method(), "raster-hough-lookup");
}

// A map too small to pay for probing RASTER (a quarter of the ray caster's
// few ms) leaves that probe to the server's idle time: the first call
// weighs the ray caster alone and says what waits; once the server has had
// a quiet spell, the same request weighs both, from what idle time
// measured, and gives the same bits. A server told not to explore when
// idle leaves the method unweighed.
TEST(IdleExplorationRpc, AProbeNoRequestCouldPayForRunsWhileTheServerIsIdle) {
  for (const bool explore : {true, false}) {
    SCOPED_TRACE(explore ? "exploring when idle" : "not exploring");
    testing::ScratchDir repo;
    auto server = testing::ServerProcess::Start(
        {repo.path(),
         {"--seed-samples", "--idle-quiet-ms", "20", explore ? "--explore-when-idle=true" : "--explore-when-idle=false"}});
    ASSERT_NE(server, nullptr);
    Client client({.address = server->address()});
    v1::HiddenSampleMapRequest map;
    map.mutable_scene()->set_name("cornell_box_visq");
    SetPatch(map.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    SetPatch(map.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
    map.mutable_samples()->set_count(32);
    map.mutable_samples()->set_seed(7);
    map.set_width(8);
    map.set_height(8);
    map.set_want_bitmasks(true);
    auto weighs = [](const v1::Accuracy& accuracy, const std::string& method) {
      for (const v1::PlanEstimate& plan : accuracy.plans())
        if (plan.method() == method) return true;
      return false;
    };

    auto first = client.ComputeHiddenSampleMap(map);
    ASSERT_TRUE(first.ok()) << first.status();
    const v1::Accuracy& before = first->figures.accuracy();
    EXPECT_EQ(before.method(), "raycast");
    EXPECT_FALSE(weighs(before, "raster-exact-lookup")) << before.note();
    if (explore) {
      EXPECT_NE(before.note().find("runs while the server is idle): raster-exact-lookup"), std::string::npos)
          << before.note();
      // GetStats is metadata: polling it does not stop the probe.
      bool probed = false;
      for (int i = 0; i < 300 && !probed; ++i) {
        auto stats = client.GetStats();
        ASSERT_TRUE(stats.ok()) << stats.status();
        ASSERT_TRUE(stats->has_idle_exploration());
        probed = stats->idle_exploration().probes_run() >= 1 && stats->idle_exploration().pending() == 0;
        if (!probed) std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
      ASSERT_TRUE(probed) << "no idle-time probe finished within 30 s";
    } else {
      std::this_thread::sleep_for(std::chrono::milliseconds(500));
      auto stats = client.GetStats();
      ASSERT_TRUE(stats.ok()) << stats.status();
      EXPECT_FALSE(stats->has_idle_exploration());
    }

    auto second = client.ComputeHiddenSampleMap(map);
    ASSERT_TRUE(second.ok()) << second.status();
    const v1::Accuracy& after = second->figures.accuracy();
    EXPECT_EQ(weighs(after, "raster-exact-lookup"), explore) << after.note();
    EXPECT_TRUE(weighs(after, "raycast")) << after.note();
    ASSERT_EQ(second->blocked_bits.size(), first->blocked_bits.size());
    size_t differing = 0;
    for (size_t w = 0; w < first->blocked_bits.size(); ++w)
      differing += std::popcount(first->blocked_bits[w] ^ second->blocked_bits[w]);
    EXPECT_LE(differing, 8u * 8u * 32u / 1000u) << "the same bits whichever ran, float ties aside";
  }
}

// Where the server weighs GPU_RAYCAST (on a GPU; here forced with
// --gpu-rays-in-choice always on llvmpipe), every choice lists it beside the
// others and answers with the ray-cast bits whichever runs: a map naming no
// method, a map with a target, and a bake naming no method.
TEST(GpuRaysInTheChoice, EveryChoiceWeighsThemAndAnswersWithTheRaycastBits) {
  testing::ScratchDir repo;
  auto server = testing::ServerProcess::Start({repo.path(), {"--seed-samples", "--gpu-rays-in-choice", "always"}});
  ASSERT_NE(server, nullptr);
  Client client({.address = server->address()});
  // Weighed: among the plans, or named among the methods whose probe this
  // request could not pay for (on llvmpipe the GPU's rays cost several
  // times Embree's, so a small request sets its share aside).
  auto weighed = [](const v1::Accuracy& accuracy, const std::string& method) {
    for (const v1::PlanEstimate& plan : accuracy.plans())
      if (plan.method() == method) return true;
    const size_t not_weighed = accuracy.note().find("not weighed");
    return not_weighed != std::string::npos && accuracy.note().find(method, not_weighed) != std::string::npos;
  };

  v1::HiddenSampleMapRequest map;
  map.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(map.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(map.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  map.mutable_samples()->set_count(64);
  map.mutable_samples()->set_seed(7);
  map.set_width(32);
  map.set_height(32);
  map.set_want_bitmasks(true);
  auto chosen = client.ComputeHiddenSampleMap(map);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  EXPECT_TRUE(weighed(chosen->figures.accuracy(), "gpu-raycast")) << chosen->figures.accuracy().DebugString();
  map.set_method(v1::RAYCAST);
  auto raycast = client.ComputeHiddenSampleMap(map);
  ASSERT_TRUE(raycast.ok()) << raycast.status();
  ASSERT_EQ(chosen->blocked_bits.size(), raycast->blocked_bits.size());
  size_t differing = 0;
  for (size_t w = 0; w < raycast->blocked_bits.size(); ++w)
    differing += std::popcount(chosen->blocked_bits[w] ^ raycast->blocked_bits[w]);
  EXPECT_LE(differing, 32u * 32u * 64u / 10000u);

  v1::HiddenSampleMapRequest targeted = map;
  targeted.clear_samples();
  targeted.set_method(v1::METHOD_UNSPECIFIED);
  targeted.set_want_bitmasks(false);
  targeted.mutable_target()->set_max_error(0.1);
  auto planned = client.ComputeHiddenSampleMap(targeted);
  ASSERT_TRUE(planned.ok()) << planned.status();
  EXPECT_TRUE(weighed(planned->figures.accuracy(), "gpu-raycast")) << planned->figures.accuracy().DebugString();
  EXPECT_LE(planned->figures.accuracy().error_bound(), 0.1);

  v1::ComputeObscurancesRequest bake;
  bake.mutable_scene()->set_name("cornell_box_visq");
  bake.set_resolution(32);
  bake.set_d_max(0.5);
  bake.set_direction_count(16);
  auto baked = client.ComputeObscurances(bake, nullptr);
  ASSERT_TRUE(baked.ok()) << baked.status();
  EXPECT_TRUE(weighed(baked->figures.accuracy(), "obscurance-gpu-raycast")) << baked->figures.accuracy().DebugString();
  EXPECT_TRUE(weighed(baked->figures.accuracy(), "obscurance-raycast")) << baked->figures.accuracy().DebugString();

  // A target probes every method it plans with (the GPU's rays too).
  bake.set_direction_count(0);
  bake.mutable_target()->set_max_error(0.3);
  auto targeted_bake = client.ComputeObscurances(bake, nullptr);
  ASSERT_TRUE(targeted_bake.ok()) << targeted_bake.status();
  bool gpu_planned = false;
  for (const v1::PlanEstimate& plan : targeted_bake->figures.accuracy().plans())
    gpu_planned |= plan.method() == "obscurance-gpu-raycast" && plan.predicted_ms() > 0.0;
  EXPECT_TRUE(gpu_planned) << targeted_bake->figures.accuracy().DebugString();
  EXPECT_LE(targeted_bake->figures.accuracy().error_bound(), 0.3);
}

TEST_F(AlgorithmRpcTest, PatchVisibilityNamingNoMethodRunsOneOfTheTwo) {
  v1::PatchVisibilityRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.997}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_source_columns(8);
  request.set_source_rows(8);
  request.set_receiver_columns(12);
  request.set_receiver_rows(12);
  auto chosen = client_->PatchVisibility(request);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  request.set_method(v1::RAYCAST);
  auto raycast = client_->PatchVisibility(request);
  ASSERT_TRUE(raycast.ok()) << raycast.status();
  EXPECT_TRUE(chosen->accuracy().method() == "raster-exact-lookup" || chosen->accuracy().method() == "raycast" ||
              chosen->accuracy().method() == "gpu-raycast");
  EXPECT_GE(chosen->accuracy().plans_size(), 1);
  EXPECT_NEAR(chosen->mutual_visible_fraction(), raycast->mutual_visible_fraction(), 1e-3);
}

TEST_F(AlgorithmRpcTest, PatchVisibilityRasterMatchesRaycast) {
  v1::PatchVisibilityRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.997}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_source_columns(8);
  request.set_source_rows(8);
  request.set_receiver_columns(16);
  request.set_receiver_rows(16);
  request.set_unblocked_limit(10);
  auto raster = client_->PatchVisibility(request);
  ASSERT_TRUE(raster.ok()) << raster.status();
  request.set_method(v1::RAYCAST);
  auto raycast = client_->PatchVisibility(request);
  ASSERT_TRUE(raycast.ok()) << raycast.status();
  EXPECT_GT(raycast->mutual_visible_fraction(), 0.3);
  EXPECT_LT(raycast->mutual_visible_fraction(), 1.0);
  EXPECT_NEAR(raster->mutual_visible_fraction(), raycast->mutual_visible_fraction(), 1e-3);
  EXPECT_EQ(raster->source_visible_size(), 64);
  EXPECT_EQ(raster->receiver_visible_size(), 256);
  EXPECT_EQ(raster->unblocked_size(), 10);
  EXPECT_GT(raster->unblocked_total(), 10u);
}

TEST_F(AlgorithmRpcTest, HiddenSampleMapBadInput) {
  v1::HiddenSampleMapRequest nan = LightOntoFloor(32, 8);
  nan.mutable_source()->mutable_edge_u()->set_x(std::nan(""));
  EXPECT_EQ(client_->ComputeHiddenSampleMap(nan).status().code(), absl::StatusCode::kInvalidArgument);
  v1::HiddenSampleMapRequest zero = LightOntoFloor(0, 8);
  auto status = client_->ComputeHiddenSampleMap(zero).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find("samples.count"), std::string::npos) << status;
  v1::HiddenSampleMapRequest huge = LightOntoFloor(4096, 4096);
  EXPECT_EQ(client_->ComputeHiddenSampleMap(huge).status().code(), absl::StatusCode::kResourceExhausted);
  v1::HiddenSampleMapRequest unknown = LightOntoFloor(32, 8);
  unknown.mutable_scene()->set_name("nope");
  EXPECT_EQ(client_->ComputeHiddenSampleMap(unknown).status().code(), absl::StatusCode::kNotFound);
  v1::HiddenSampleMapRequest stale = LightOntoFloor(32, 8);
  stale.mutable_scene()->set_version(999);
  EXPECT_EQ(client_->ComputeHiddenSampleMap(stale).status().code(), absl::StatusCode::kFailedPrecondition);
}

v1::LightVisibilityRequest CeilingLight() {
  v1::LightVisibilityRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  // The light's quad, counter-clockwise seen from below (facing down).
  for (const auto& v : {glm::dvec3(-0.25, 1.99, -0.25), glm::dvec3(0.25, 1.99, -0.25), glm::dvec3(0.25, 1.99, 0.25),
                        glm::dvec3(-0.25, 1.99, 0.25)})
    Set(request.mutable_light()->add_vertices(), v.x, v.y, v.z);
  request.set_radiance(10.0);
  return request;
}

void AddPoint(v1::LightVisibilityRequest& request, double x, double y, double z) {
  auto* p = request.add_points();
  Set(p->mutable_position(), x, y, z);
  Set(p->mutable_normal(), 0, 1, 0);
}

TEST_F(AlgorithmRpcTest, LightVisibilityIsExactAndReusesTheTree) {
  v1::LightVisibilityRequest request = CeilingLight();
  AddPoint(request, 0.0, 1.5, 0.0);    // in the open, under the light: all visible
  AddPoint(request, 0.4, 0.61, 0.35);  // on top of the short box
  AddPoint(request, 0.4, 0.001, 0.35); // under the short box: nothing visible
  AddPoint(request, -0.9, 0.001, 0.9); // on the floor, in the open
  request.set_want_polygons(true);
  auto first = client_->LightVisibility(request);
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_EQ(first->points_size(), 4);
  EXPECT_NEAR(first->points(0).visible_fraction(), 1.0, 1e-9);
  EXPECT_NEAR(first->points(2).visible_fraction(), 0.0, 1e-9);
  EXPECT_GT(first->points(3).visible_fraction(), 0.0);
  EXPECT_GT(first->points(0).irradiance(), first->points(3).irradiance());
  EXPECT_EQ(first->points(0).visible_polygons_size() > 0, true);
  EXPECT_EQ(first->accuracy().method(), "plucker-exact");

  // Four points in four cubes of the receiver grid, each far below
  // --light-receiver-min-points: they share one tree (the cubes merge).
  EXPECT_EQ(first->tree().trees(), 1u);
  EXPECT_EQ(first->tree().trees_created(), 1u);

  auto second = client_->LightVisibility(request);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_TRUE(second->tree().reused());
  EXPECT_EQ(second->tree().trees(), 1u);
  EXPECT_EQ(second->tree().trees_created(), 0u);
  EXPECT_EQ(second->tree().refinements(), first->tree().refinements()) << "a second pass refines nothing";
  // The point in the open is answered before the tree on the first pass
  // (the second is answered from the tree's store of answers); the point
  // under the box is hidden by the box's bottom faces (two triangles
  // together, or one), before the tree too: by one of them, or by
  // subtracting the few triangles whose shadows can meet the light.
  const auto& t = second->tree();
  EXPECT_GE(t.wholly_visible(), 1u);
  EXPECT_GE(t.wholly_hidden() + t.subtracted_directly(), 1u);
  EXPECT_LE(t.wholly_visible() + t.wholly_hidden() + t.subtracted_directly(), t.queries());
  for (int i = 0; i < 4; ++i) {
    EXPECT_EQ(second->points(i).visible_fraction(), first->points(i).visible_fraction());
    EXPECT_EQ(second->points(i).irradiance(), first->points(i).irradiance());
  }
  EXPECT_GE(second->cache().hits(), 1u);
  EXPECT_GT(second->cache().bytes(), 0u);
}

TEST_F(AlgorithmRpcTest, LightVisibilityCellsAnswerAsOneRegion) {
  // A batch spread over the floor is grouped by the server (the points'
  // box, halved where its shaft meets many triangles: on the Cornell box,
  // one group), one tree each; one tree for a region the client names must
  // give the same answers. The splitting itself is tested in tests/exact.
  v1::LightVisibilityRequest cells = CeilingLight();
  for (int i = 0; i < 15; ++i)
    for (int j = 0; j < 15; ++j) AddPoint(cells, -0.95 + 0.135 * i, 0.001, -0.95 + 0.135 * j);
  v1::LightVisibilityRequest region = cells;
  Set(region.mutable_receiver_region()->mutable_min(), -1, 0, -1);
  Set(region.mutable_receiver_region()->mutable_max(), 1, 0.01, 1);
  auto split = client_->LightVisibility(cells);
  ASSERT_TRUE(split.ok()) << split.status();
  auto whole = client_->LightVisibility(region);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_GE(split->tree().trees(), 1u);
  EXPECT_EQ(whole->tree().trees(), 1u);
  ASSERT_EQ(split->points_size(), whole->points_size());
  int penumbra = 0;
  for (int i = 0; i < split->points_size(); ++i) {
    EXPECT_NEAR(split->points(i).visible_fraction(), whole->points(i).visible_fraction(), 1e-12) << i;
    EXPECT_NEAR(split->points(i).irradiance(), whole->points(i).irradiance(), 1e-9) << i;
    const double f = whole->points(i).visible_fraction();
    penumbra += f > 0 && f < 1;
  }
  EXPECT_GT(penumbra, 5) << "the comparison must include partly lit points";
  // The cells' trees may be the earlier tests' (same light, same cubes):
  // their counts include those queries.
  EXPECT_GE(split->tree().queries(), 225u);
}

TEST_F(AlgorithmRpcTest, LightVisibilityBatchOverManyCellsStopsAtTheDeadline) {
  // 160,000 floor points over 1,024 receiver cells, each a tree to build
  // (a light no other test uses): about a second here, far more than the
  // deadline. The server stops between points and answers the next request.
  v1::LightVisibilityRequest big = CeilingLight();
  for (auto& v : *big.mutable_light()->mutable_vertices()) v.set_y(1.98);
  for (int i = 0; i < 400; ++i)
    for (int j = 0; j < 400; ++j) AddPoint(big, -0.99 + 0.00495 * i, 0.001, -0.99 + 0.00495 * j);
  client::Client impatient(client::ClientOptions{.address = server_->address(), .deadline = std::chrono::milliseconds(150)});
  const auto start = std::chrono::steady_clock::now();
  const Status status = impatient.LightVisibility(big).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
  v1::LightVisibilityRequest small = CeilingLight();
  AddPoint(small, 0.0, 1.5, 0.0);
  auto next = client_->LightVisibility(small);
  ASSERT_TRUE(next.ok()) << next.status();
  EXPECT_NEAR(next->points(0).visible_fraction(), 1.0, 1e-9);
  EXPECT_LT(std::chrono::steady_clock::now() - start, std::chrono::seconds(20));
}

TEST_F(AlgorithmRpcTest, LightVisibilityStreamMatchesUnary) {
  std::vector<v1::LightVisibilityRequest> batches;
  v1::LightVisibilityRequest unary = CeilingLight();
  for (int b = 0; b < 3; ++b) {
    v1::LightVisibilityRequest batch = b == 0 ? CeilingLight() : v1::LightVisibilityRequest();
    for (int i = 0; i < 5; ++i) {
      const double x = -0.9 + 0.12 * (b * 5 + i);
      AddPoint(batch, x, 0.001, 0.8);
      AddPoint(unary, x, 0.001, 0.8);
    }
    batches.push_back(batch);
  }
  auto streamed = client_->LightVisibilityStream(batches);
  ASSERT_TRUE(streamed.ok()) << streamed.status();
  auto whole = client_->LightVisibility(unary);
  ASSERT_TRUE(whole.ok()) << whole.status();
  int k = 0;
  for (const auto& answer : *streamed)
    for (const auto& p : answer.points()) EXPECT_NEAR(p.visible_fraction(), whole->points(k++).visible_fraction(), 1e-12);
  EXPECT_EQ(k, 15);
  EXPECT_GT(whole->points(0).visible_fraction(), 0.0) << "the comparison must not be between zeros";
}

TEST_F(AlgorithmRpcTest, LightVisibilityBadInput) {
  v1::LightVisibilityRequest nan = CeilingLight();
  AddPoint(nan, std::nan(""), 0, 0);
  auto status = client_->LightVisibility(nan).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(status.message()).find("points[0]"), std::string::npos) << status;

  v1::LightVisibilityRequest degenerate = CeilingLight();
  degenerate.mutable_light()->clear_vertices();
  for (int i = 0; i < 3; ++i) Set(degenerate.mutable_light()->add_vertices(), i, i, i);  // collinear: zero area
  AddPoint(degenerate, 0, 0.5, 0);
  EXPECT_EQ(client_->LightVisibility(degenerate).status().code(), absl::StatusCode::kInvalidArgument);

  v1::LightVisibilityRequest no_points = CeilingLight();
  EXPECT_EQ(client_->LightVisibility(no_points).status().code(), absl::StatusCode::kInvalidArgument);

  v1::LightVisibilityRequest bad_node = CeilingLight();
  AddPoint(bad_node, 0, 0.5, 0);
  bad_node.add_exclude_nodes("no such node");
  EXPECT_EQ(client_->LightVisibility(bad_node).status().code(), absl::StatusCode::kInvalidArgument);

  for (const double tolerance : {-1e-6, 1.5, std::nan("")}) {
    v1::LightVisibilityRequest bad_tolerance = CeilingLight();
    AddPoint(bad_tolerance, 0, 0.5, 0);
    bad_tolerance.set_shadow_tolerance(tolerance);
    const Status refused = client_->LightVisibility(bad_tolerance).status();
    EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << tolerance;
    EXPECT_NE(std::string(refused.message()).find("shadow_tolerance"), std::string::npos) << refused;
  }
}

}  // namespace
}  // namespace visq

namespace visq {
namespace {

TEST_F(AlgorithmRpcTest, VoxelizeFloorFillsTheFirstSliceAndConservativeContainsStandard) {
  v1::VoxelizeRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_width(32);
  request.set_height(32);
  request.set_slices(32);
  request.set_depth_axis(1);  // slices along y: the floor (y = 0) is slice 0
  auto standard = client_->Voxelize(request);
  ASSERT_TRUE(standard.ok()) << standard.status();
  const auto& f = standard->figures;
  ASSERT_EQ(standard->bits.size(), size_t(32) * 32 * f.words_per_column());
  for (uint32_t y = 0; y < 32; ++y)
    for (uint32_t x = 0; x < 32; ++x) ASSERT_TRUE(standard->Occupied(x, y, 0)) << x << "," << y;
  EXPECT_EQ(f.rasterization(), "standard");
  EXPECT_LT(f.accuracy().error_bound(), 0.0) << "standard rasterization can miss thin triangles: no numeric bound";

  request.set_conservative(true);
  auto conservative = client_->Voxelize(request);
  ASSERT_TRUE(conservative.ok()) << conservative.status();
  EXPECT_EQ(conservative->figures.rasterization(), "conservative");
  EXPECT_GT(conservative->figures.accuracy().error_bound(), 0.0);
  size_t missing = 0;
  for (size_t w = 0; w < standard->bits.size(); ++w) missing += std::popcount(standard->bits[w] & ~conservative->bits[w]);
  EXPECT_EQ(missing, 0u) << "the conservative grid must contain the standard one";
  EXPECT_GE(conservative->figures.occupied_voxels(), f.occupied_voxels());

  v1::VoxelizeRequest bad = request;
  bad.set_slices(5000);
  EXPECT_FALSE(client_->Voxelize(bad).ok());
  bad = request;
  bad.add_nodes("no such node");
  EXPECT_EQ(client_->Voxelize(bad).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(AlgorithmRpcTest, TransmittanceThroughTheShortBox) {
  v1::TransmittanceRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  request.set_light_kind(v1::TransmittanceRequest::DIRECTIONAL);
  Set(request.mutable_light_direction(), 0, -1, 0);
  auto* absorber = request.add_absorbers();
  absorber->set_node("short_box");
  absorber->set_absorption(2.0);
  Set(request.add_points(), 0.4, 0.001, 0.35);   // under the short box: 0.6 units of it above
  Set(request.add_points(), -0.9, 0.001, 0.9);  // in the open
  request.set_method(v1::TransmittanceRequest::SLICEMAP);
  auto response = client_->Transmittance(request);
  ASSERT_TRUE(response.ok()) << response.status();
  ASSERT_EQ(response->transmittance_size(), 2);
  // exp(-2 * 0.6), within the stated error.
  EXPECT_NEAR(response->optical_depth(0), 1.2, response->optical_depth_error(0) + 0.05);
  EXPECT_FLOAT_EQ(response->transmittance(1), 1.0f);
  EXPECT_EQ(response->accuracy().method(), "transmittance-slicemap");

  // The points' own rays, to rounding: the box spans y in [0, 0.6] and the
  // point is inside it at y = 0.001, so its path is 0.599.
  request.set_method(v1::TransmittanceRequest::RAY_STABBING);
  auto own = client_->Transmittance(request);
  ASSERT_TRUE(own.ok()) << own.status();
  ASSERT_EQ(own->optical_depth_size(), 2);
  EXPECT_EQ(own->accuracy().method(), "transmittance-ray-stabbing");
  const double exact = 2.0 * 0.599;
  EXPECT_LE(exact, own->optical_depth(0) + 1e-6);
  EXPECT_GE(exact, own->optical_depth(0) - own->optical_depth_error(0) - 1e-6);
  EXPECT_LT(own->optical_depth_error(0), 1e-3);
  EXPECT_EQ(own->lateral_offset(0), 0.0f);
  EXPECT_FALSE(own->ambiguous(0));
  EXPECT_FLOAT_EQ(own->transmittance(1), 1.0f);
  request.set_method(static_cast<v1::TransmittanceRequest::Method>(7));
  auto unknown = client_->Transmittance(request);
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(unknown.status().message()).find("method"), std::string::npos) << unknown.status();
  request.set_method(v1::TransmittanceRequest::SLICEMAP);

  // Named no method, the server runs one of the two after weighing them
  // (both are listed, or the one whose probe was cut is named in the
  // note), and its answer is that method's by name.
  request.clear_method();
  auto chosen = client_->Transmittance(request);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  const std::string ran = chosen->accuracy().method();
  ASSERT_TRUE(ran == "transmittance-slicemap" || ran == "transmittance-ray-stabbing") << ran;
  EXPECT_GE(chosen->accuracy().plans_size(), 1) << chosen->accuracy().DebugString();
  EXPECT_NE(chosen->accuracy().note().find("no method named"), std::string::npos) << chosen->accuracy().note();
  EXPECT_EQ(chosen->accuracy().plans(0).method().rfind("transmittance-", 0), 0u) << chosen->accuracy().DebugString();
  const auto& by_name = ran == "transmittance-slicemap" ? *response : *own;
  for (int i = 0; i < 2; ++i) {
    EXPECT_FLOAT_EQ(chosen->optical_depth(i), by_name.optical_depth(i)) << i;
    EXPECT_FLOAT_EQ(chosen->optical_depth_error(i), by_name.optical_depth_error(i)) << i;
  }
  request.set_method(v1::TransmittanceRequest::SLICEMAP);

  absorber->set_node("nope");
  EXPECT_EQ(client_->Transmittance(request).status().code(), absl::StatusCode::kInvalidArgument);
}

// The error estimate of a volumetric image (Richardson's, from the same
// image with a half and a quarter of the shadow map) against the error
// itself, measured against fine ray marching of a 4096^2 map, on
// Sponza's atrium; and a target that makes the server choose the map.
TEST_F(AlgorithmRpcTest, VolumetricErrorEstimateTracksTheErrorAndATargetChoosesTheMap) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  auto info = client_->UploadScene(scenes / "sponza_dabrovic/sponza.gltf", "sponza_volumetric", /*replace=*/true);
  ASSERT_TRUE(info.ok()) << info.status();
  const glm::dvec3 lo(info->bounds_min().x(), info->bounds_min().y(), info->bounds_min().z());
  const glm::dvec3 hi(info->bounds_max().x(), info->bounds_max().y(), info->bounds_max().z());
  auto at = [&](double x, double y, double z) { return lo + glm::dvec3(x, y, z) * (hi - lo); };
  v1::VolumetricShadowRequest request;
  request.mutable_scene()->set_name("sponza_volumetric");
  const glm::dvec3 eye = at(0.12, 0.25, 0.5), target_point = at(0.9, 0.35, 0.45);
  Set(request.mutable_camera_position(), eye.x, eye.y, eye.z);
  Set(request.mutable_camera_forward(), target_point.x - eye.x, target_point.y - eye.y, target_point.z - eye.z);
  request.set_vertical_fov_deg(60);
  request.set_width(96);
  request.set_height(72);
  Set(request.mutable_light_direction(), 0.25, -1.0, 0.45);
  request.set_light_intensity(4.0);
  const double extent = glm::length(hi - lo);
  request.set_scattering(2.0 / extent);
  request.set_extinction(3.0 / extent);

  v1::VolumetricShadowRequest reference_request = request;
  reference_request.set_shadow_map_size(4096);
  reference_request.set_method(v1::VolumetricShadowRequest::RAY_MARCHING);  // fine ray marching, every texel
  auto reference = client_->VolumetricShadow(reference_request);
  ASSERT_TRUE(reference.ok()) << reference.status();
  EXPECT_LT(reference->figures.accuracy().error_bound(), 0.0) << "no estimate unless asked for";

  request.set_shadow_map_size(256);
  request.set_estimate_error(true);
  auto estimated = client_->VolumetricShadow(request);
  ASSERT_TRUE(estimated.ok()) << estimated.status();
  const v1::Accuracy& accuracy = estimated->figures.accuracy();
  ASSERT_EQ(estimated->inscattering.size(), reference->inscattering.size());
  double true_max = 0, abs_sum = 0, sum = 0;
  for (size_t i = 0; i < reference->inscattering.size(); ++i) {
    const double error = std::abs(double(estimated->inscattering[i]) - reference->inscattering[i]);
    true_max = std::max(true_max, error);
    abs_sum += error;
    sum += reference->inscattering[i];
  }
  ASSERT_GT(true_max, 0.0);
  const double true_l1 = abs_sum / sum;
  const double estimate = accuracy.error_bound(), estimate_l1 = accuracy.parameters().at("relative_l1_error");
  EXPECT_EQ(accuracy.confidence(), 0.0) << "an estimate, not a bound";
  EXPECT_NE(accuracy.note().find("an estimate"), std::string::npos) << accuracy.note();
  EXPECT_EQ(accuracy.parameters().at("coarse_shadow_map_size"), 128);
  EXPECT_EQ(accuracy.parameters().at("coarser_shadow_map_size"), 64) << "three maps measure the convergence";
  EXPECT_NE(accuracy.note().find("Richardson"), std::string::npos) << accuracy.note();
  const double ratio = accuracy.parameters().at("convergence_ratio");
  EXPECT_GE(ratio, 0.5);
  EXPECT_LE(ratio, 0.75);
  EXPECT_NEAR(estimate, accuracy.parameters().at("max_difference") * ratio / (1 - ratio), 1e-12 + 1e-9 * estimate);
  // An estimate of the right size: not under the error it estimates (the
  // reference's own error, a 4096^2 map's, allows a quarter less), and not
  // more than 3x over it.
  EXPECT_GT(estimate, true_max / 1.25) << "true " << true_max;
  EXPECT_LT(estimate, true_max * 3) << "true " << true_max;
  EXPECT_GT(estimate_l1, true_l1 / 3) << "true " << true_l1;
  EXPECT_LT(estimate_l1, true_l1 * 3) << "true " << true_l1;
  RecordProperty("estimate_256", absl::StrCat(estimate, " (true ", true_max, "), L1 ", estimate_l1, " (true ", true_l1, ")"));

  // A target half the 256 map's estimate: a larger map, whose estimate meets it.
  v1::VolumetricShadowRequest targeted = request;
  targeted.clear_shadow_map_size();
  targeted.set_estimate_error(false);
  targeted.mutable_target()->set_max_error(estimate / 2);
  auto chosen = client_->VolumetricShadow(targeted);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  const v1::Accuracy& chosen_accuracy = chosen->figures.accuracy();
  EXPECT_GT(chosen_accuracy.parameters().at("shadow_map_size"), 256);
  EXPECT_TRUE(chosen_accuracy.error_bound() <= estimate / 2 ||
              chosen_accuracy.parameters().at("shadow_map_size") == 4096)
      << chosen_accuracy.error_bound();
  ASSERT_EQ(chosen->inscattering.size(), reference->inscattering.size());
  RecordProperty("target_map", absl::StrCat(chosen_accuracy.parameters().at("shadow_map_size")));

  // A worst-case target is refused by its field; so is a map size beside a target.
  targeted.mutable_target()->set_confidence(1.0);
  Status worst_case = client_->VolumetricShadow(targeted).status();
  EXPECT_EQ(worst_case.code(), absl::StatusCode::kInvalidArgument) << worst_case;
  EXPECT_NE(std::string(worst_case.message()).find("target.confidence"), std::string::npos) << worst_case;
  targeted.mutable_target()->set_confidence(0.0);
  targeted.set_shadow_map_size(512);
  Status both = client_->VolumetricShadow(targeted).status();
  EXPECT_EQ(both.code(), absl::StatusCode::kInvalidArgument) << both;
}

TEST_F(AlgorithmRpcTest, VolumetricMinMaxEqualsRayMarching) {
  v1::VolumetricShadowRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  Set(request.mutable_camera_position(), 0, 1, 3.5);
  Set(request.mutable_camera_forward(), 0, 0, -1);
  Set(request.mutable_light_direction(), 0.3, -0.6, -1.0);  // through the open front
  request.set_width(64);
  request.set_height(48);
  request.set_shadow_map_size(256);
  request.set_scattering(0.2);
  request.set_extinction(0.2);
  auto min_max = client_->VolumetricShadow(request);
  ASSERT_TRUE(min_max.ok()) << min_max.status();
  request.set_method(v1::VolumetricShadowRequest::RAY_MARCHING);
  auto marching = client_->VolumetricShadow(request);
  ASSERT_TRUE(marching.ok()) << marching.status();
  ASSERT_EQ(min_max->inscattering.size(), size_t(64) * 48 * 3);
  ASSERT_EQ(marching->inscattering.size(), min_max->inscattering.size());
  float peak = 0, worst = 0;
  for (size_t i = 0; i < marching->inscattering.size(); ++i) {
    peak = std::max(peak, marching->inscattering[i]);
    worst = std::max(worst, std::abs(marching->inscattering[i] - min_max->inscattering[i]));
  }
  EXPECT_GT(peak, 0.0f) << "the image must not be black";
  EXPECT_LE(worst, 1e-4f * peak + 1e-7f);
  EXPECT_EQ(min_max->figures.method(), "min-max-mipmap");

  // The medium where the request puts it: a box that holds none of the
  // camera's rays scatters nothing, and a box without volume is refused by
  // its field.
  v1::VolumetricShadowRequest boxed = request;
  Set(boxed.mutable_medium_box()->mutable_min(), 5, 5, 5);
  Set(boxed.mutable_medium_box()->mutable_max(), 6, 6, 6);
  auto empty = client_->VolumetricShadow(boxed);
  ASSERT_TRUE(empty.ok()) << empty.status();
  EXPECT_EQ(*std::max_element(empty->inscattering.begin(), empty->inscattering.end()), 0.0f);
  Set(boxed.mutable_medium_box()->mutable_max(), 6, 5, 6);
  const Status flat = client_->VolumetricShadow(boxed).status();
  EXPECT_EQ(flat.code(), absl::StatusCode::kInvalidArgument) << flat;
  EXPECT_NE(std::string(flat.message()).find("medium_box"), std::string::npos) << flat;

  // A spot light with extinction takes the SVD integrand and states its rank
  // and table error among the accuracy parameters.
  request.set_method(v1::VolumetricShadowRequest::MIN_MAX);
  request.set_light_kind(v1::VolumetricShadowRequest::SPOT);
  Set(request.mutable_light_position(), 0, 1.9, 0);
  Set(request.mutable_light_direction(), 0.1, -1, 0.1);
  request.set_cone_angle_deg(40);
  auto spot = client_->VolumetricShadow(request);
  ASSERT_TRUE(spot.ok()) << spot.status();
  EXPECT_EQ(spot->figures.integrand(), "svd");
  const auto& parameters = spot->figures.accuracy().parameters();
  ASSERT_TRUE(parameters.contains("svd_rank") && parameters.contains("integrand_error"));
  EXPECT_GE(parameters.at("svd_rank"), 1.0);
  EXPECT_LE(parameters.at("svd_rank"), 8.0);
  EXPECT_GE(parameters.at("integrand_error"), 0.0);
  EXPECT_NE(spot->figures.accuracy().note().find("SVD"), std::string::npos) << spot->figures.accuracy().note();
  request.set_vertical_fov_deg(200);
  EXPECT_EQ(client_->VolumetricShadow(request).status().code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace visq
