// A LightVisibility batch spread over many receiver cells, through the
// Engine on the generated Cornell box: each cell's tree is let go as soon
// as its points are answered, so the request holds a few trees at a time
// however many cells it has, and the answers equal those of one tree over
// the whole region.
#include <atomic>
#include <chrono>
#include <cstdio>
#include <optional>
#include <random>
#include <thread>

#include <gtest/gtest.h>

#include "common/parallel.h"
#include "core/engine.h"
#include "core/light_visibility_query.h"
#include "core/visibility_sampling_query.h"
#include "large_scene.h"
#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "test_support.h"

namespace visq::core {
namespace {

TEST(LightVisibilityBatch, ManyCellsHoldFewTreesAtATime) {
  testing::ScratchDir dir;
  ASSERT_TRUE(WriteSampleScenes(dir.path() / "repo").ok());
  EngineOptions options;
  options.scene_repo = dir.path() / "repo";
  options.load_repository_at_start = false;
  options.light_receiver_cells = 32;      // the grid's cubes, 2 m / 32
  options.light_receiver_min_points = 1;  // every occupied cell keeps its own tree
  auto engine = Engine::Create(options);
  ASSERT_TRUE(engine.ok()) << engine.status();

  // The box's ceiling light, facing down; points over the floor, a grid
  // coarser than the cells (2 m / 32), so each point is a cell of its own.
  LightVisibilityQuery query;
  query.scene = "cornell_box_visq";
  query.light.vertices = {{-0.25, 1.98, -0.25}, {-0.25, 1.98, 0.25}, {0.25, 1.98, 0.25}, {0.25, 1.98, -0.25}};
  constexpr int kSide = 12;
  for (int i = 0; i < kSide; ++i)
    for (int j = 0; j < kSide; ++j)
      query.points.push_back(
          {glm::dvec3(-0.9 + 1.8 * i / (kSide - 1), 0.01, -0.9 + 1.8 * j / (kSide - 1)), glm::dvec3(0, 1, 0), {}});
  StatusOr<LightVisibilityAnswer> cells = RunLightVisibility(**engine, query);
  ASSERT_TRUE(cells.ok()) << cells.status();
  EXPECT_EQ(cells->trees, query.points.size());
  EXPECT_GE(cells->peak_trees_held, 1u);
  EXPECT_LE(cells->peak_trees_held, ParallelWorkers() + 1) << "of " << cells->trees << " trees";
  RecordProperty("peak_trees_held", std::to_string(cells->peak_trees_held));

  query.receiver_region = Bounds{glm::dvec3(-1, 0, -1), glm::dvec3(1, 0.02, 1)};
  StatusOr<LightVisibilityAnswer> one = RunLightVisibility(**engine, query);
  ASSERT_TRUE(one.ok()) << one.status();
  EXPECT_EQ(one->trees, 1u);
  for (size_t i = 0; i < query.points.size(); ++i)
    EXPECT_NEAR(cells->points[i].visible_area_fraction, one->points[i].visible_area_fraction, 1e-12) << "point " << i;
}

// A rippled floor under a layer of foliage (`leaves` small triangles at
// y ~ 1) and a square light at y = 2 facing down, as "foliage" in a fresh
// repository; and `points` points on the floor under the light. With a
// needle_width, the leaves are needles instead: 0.4 long, their third
// vertex that far off the middle of their long edge.
struct Foliage {
  testing::ScratchDir dir;
  std::unique_ptr<Engine> engine;
  LightVisibilityQuery query;
};
std::unique_ptr<Foliage> MakeFoliage(int leaves, int points, std::optional<double> needle_width = std::nullopt) {
  auto f = std::make_unique<Foliage>();
  Scene scene = testing::MakeRippledGrid(32);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < leaves; ++i) {
    const glm::dvec3 c(0.8 * u(rng), 1.0 + 0.2 * u(rng), 0.8 * u(rng));
    const auto base = static_cast<uint32_t>(scene.positions.size());
    if (needle_width) {
      const double a = 3.14159 * u(rng);
      const glm::dvec3 half(0.2 * std::cos(a), 0.0, 0.2 * std::sin(a));
      const glm::dvec3 side(-std::sin(a), 0.0, std::cos(a));
      for (const glm::dvec3& v : {c - half, c + half, c + *needle_width * side}) {
        scene.positions.push_back(v);
        scene.bounds.Extend(v);
      }
    }
    for (int k = 0; k < 3 && !needle_width; ++k) {
      scene.positions.push_back(c + 0.03 * glm::dvec3(u(rng), u(rng), u(rng)));
      scene.bounds.Extend(scene.positions.back());
    }
    scene.triangles.emplace_back(base, base + 1, base + 2);
    scene.triangle_material.push_back(0);
    scene.triangle_node.push_back(0);
  }
  scene.nodes[0].triangle_count = static_cast<uint32_t>(scene.triangles.size());
  std::filesystem::create_directories(f->dir.path() / "repo");
  EXPECT_TRUE(WriteGltfFile(scene, f->dir.path() / "repo" / "foliage.glb").ok());
  EngineOptions options;
  options.scene_repo = f->dir.path() / "repo";
  options.load_repository_at_start = false;
  auto engine = Engine::Create(options);
  EXPECT_TRUE(engine.ok()) << engine.status();
  if (!engine.ok()) return nullptr;
  f->engine = std::move(*engine);
  f->query.scene = "foliage";
  f->query.light.vertices = {{-0.3, 2, -0.3}, {0.3, 2, -0.3}, {0.3, 2, 0.3}, {-0.3, 2, 0.3}};  // facing down
  std::uniform_real_distribution<double> floor(-0.6, 0.6);
  for (int i = 0; i < points; ++i) {
    const double x = floor(rng), z = floor(rng);
    f->query.points.push_back({glm::dvec3(x, 0.05, z), glm::dvec3(0, 1, 0), {}});
  }
  return f;
}

TEST(LightVisibilityBatch, AnIdenticalSecondBatchRefinesNothing) {
  auto f = MakeFoliage(1000, 256);
  ASSERT_NE(f, nullptr);
  StatusOr<LightVisibilityAnswer> first = RunLightVisibility(*f->engine, f->query);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_GT(first->trees_created, 0u);
  // The first call did the work: its penumbra points subtracted their
  // occluders (TreeOptions::direct_candidates; the trees grow only for
  // points that descend them).
  EXPECT_GT(first->tree.refinements + first->tree.subtracted_directly, 0u);
  StatusOr<LightVisibilityAnswer> second = RunLightVisibility(*f->engine, f->query);
  ASSERT_TRUE(second.ok()) << second.status();
  // The statistics are the trees' own, summed: unchanged counts mean the
  // second call grew nothing.
  EXPECT_TRUE(second->tree_reused);
  EXPECT_EQ(second->trees_created, 0u);
  EXPECT_EQ(second->tree.refinements, first->tree.refinements);
  EXPECT_EQ(second->tree.nodes, first->tree.nodes);
  EXPECT_EQ(second->tree.unrefined_leaf_visits, first->tree.unrefined_leaf_visits);
  EXPECT_EQ(second->tree.answers_reused - first->tree.answers_reused, f->query.points.size());
  int penumbra = 0;
  for (size_t i = 0; i < f->query.points.size(); ++i) {
    EXPECT_EQ(second->points[i].visible_area_fraction, first->points[i].visible_area_fraction) << "point " << i;
    penumbra += first->points[i].visible_area_fraction > 0 && first->points[i].visible_area_fraction < 1;
  }
  EXPECT_GT(penumbra, 50);
  std::printf("first call %.1f ms, identical second call %.1f ms (%zu trees)\n", first->compute_ms,
              second->compute_ms, second->trees);
}

// Needles across the light: under the engine's shadow tolerance (a
// millionth of the light unless the query names one) they are left out and
// stated as each point's error, which holds against the exact answers of a
// query naming 0; and the batch's statement gives the largest.
TEST(LightVisibilityBatch, NeedlesAreLeftOutUnderTheShadowToleranceAndStatedAsTheError) {
  auto f = MakeFoliage(600, 128, 1e-9);
  ASSERT_NE(f, nullptr);
  ASSERT_EQ(f->engine->light_shadow_tolerance(), 1e-6);
  StatusOr<LightVisibilityAnswer> tolerant = RunLightVisibility(*f->engine, f->query);
  ASSERT_TRUE(tolerant.ok()) << tolerant.status();
  LightVisibilityQuery strict = f->query;
  strict.shadow_tolerance = 0.0;
  StatusOr<LightVisibilityAnswer> exact = RunLightVisibility(*f->engine, strict);
  ASSERT_TRUE(exact.ok()) << exact.status();
  EXPECT_EQ(tolerant->shadow_tolerance, 1e-6);
  EXPECT_EQ(exact->shadow_tolerance, 0.0);
  int left_out = 0;
  double largest = 0.0;
  for (size_t i = 0; i < f->query.points.size(); ++i) {
    const exact::PointVisibility& t = tolerant->points[i];
    const exact::PointVisibility& e = exact->points[i];
    EXPECT_EQ(e.visible_area_fraction_error, 0.0);
    EXPECT_LE(t.visible_area_fraction_error, 1e-6);
    EXPECT_GE(t.visible_area_fraction + 1e-10, e.visible_area_fraction) << i;
    EXPECT_LE(t.visible_area_fraction - t.visible_area_fraction_error, e.visible_area_fraction + 1e-10) << i;
    EXPECT_LE(t.irradiance - t.irradiance_error, e.irradiance + 1e-9) << i;
    left_out += t.visible_area_fraction_error > 0.0;
    largest = std::max(largest, t.visible_area_fraction_error);
  }
  EXPECT_GT(left_out, 64) << "most floor points see needles across the light";
  const AccuracyStatement statement = LightVisibilityStatement(*tolerant);
  EXPECT_EQ(statement.error_bound, largest);
  EXPECT_EQ(LightVisibilityStatement(*exact).error_bound, 0.0);

  // The exact patch visibility (and so the exact map) leaves the same
  // needles out and states what they could hide.
  PatchVisibilityQuery patches;
  patches.scene = "foliage";
  patches.method = VisibilityMethod::kPluckerExact;
  patches.request.source = sampling::Patch{{-0.3, 2.0, -0.3}, {0.6, 0.0, 0.0}, {0.0, 0.0, 0.6}};
  patches.request.receiver = sampling::Patch{{-0.6, 0.05, -0.6}, {1.2, 0.0, 0.0}, {0.0, 0.0, 1.2}};
  patches.request.receiver_columns = patches.request.receiver_rows = 12;
  StatusOr<PatchVisibilityAnswer> pv = RunPatchVisibility(*f->engine, patches);
  ASSERT_TRUE(pv.ok()) << pv.status();
  EXPECT_GT(pv->accuracy.error_bound, 0.0) << pv->accuracy.note;
  EXPECT_LE(pv->accuracy.error_bound, 1e-6);
  EXPECT_EQ(pv->accuracy.method, "plucker-exact");
  EXPECT_TRUE(pv->accuracy.note.find("one-sided") != std::string::npos) << pv->accuracy.note;

  LightVisibilityQuery bad = f->query;
  bad.shadow_tolerance = 1.5;
  const Status refused = RunLightVisibility(*f->engine, bad).status();
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(refused.message()).find("shadow_tolerance"), std::string::npos) << refused;
}

// The planner's probe (answer_only): some of a batch's points answered on
// the trees the whole batch would use. Those trees are then held and those
// answers stored, so the batch itself builds nothing, answers the probed
// points from the stores, and gives them the probe's bits; the work
// estimate says so before either runs.
TEST(LightVisibilityBatch, AProbeOfSomePointsBuildsTheBatchsOwnTrees) {
  auto f = MakeFoliage(1000, 256);
  ASSERT_NE(f, nullptr);
  StatusOr<LightVisibilityWork> cold = EstimateLightVisibilityWork(*f->engine, f->query);
  ASSERT_TRUE(cold.ok()) << cold.status();
  EXPECT_GT(cold->new_shaft_triangles, 0.0);
  EXPECT_EQ(cold->cached_groups, 0u);
  EXPECT_EQ(cold->points, 256.0);

  LightVisibilityQuery probe = f->query;
  for (uint32_t i = 3; i < 256; i += 8) probe.answer_only.push_back(i);  // 32 points
  StatusOr<LightVisibilityWork> probe_work = EstimateLightVisibilityWork(*f->engine, probe);
  ASSERT_TRUE(probe_work.ok()) << probe_work.status();
  EXPECT_EQ(probe_work->points, 32.0);
  StatusOr<LightVisibilityAnswer> probed = RunLightVisibility(*f->engine, probe);
  ASSERT_TRUE(probed.ok()) << probed.status();
  EXPECT_GT(probed->trees_created, 0u);
  EXPECT_EQ(probed->tree.queries, 32u);

  StatusOr<LightVisibilityWork> warm = EstimateLightVisibilityWork(*f->engine, f->query);
  ASSERT_TRUE(warm.ok()) << warm.status();
  EXPECT_EQ(warm->new_shaft_triangles, 0.0) << "the probe built the batch's trees";
  EXPECT_EQ(warm->cached_groups, warm->groups);
  EXPECT_EQ(warm->stored_points, 32.0);
  EXPECT_EQ(warm->points, 256.0 - 32.0);

  StatusOr<LightVisibilityAnswer> batch = RunLightVisibility(*f->engine, f->query);
  ASSERT_TRUE(batch.ok()) << batch.status();
  EXPECT_EQ(batch->trees_created, 0u);
  EXPECT_GE(batch->tree.answers_reused, 32u);
  for (uint32_t i : probe.answer_only)
    EXPECT_EQ(batch->points[i].visible_area_fraction, probed->points[i].visible_area_fraction) << "point " << i;

  probe.answer_only = {5, 5};
  EXPECT_EQ(RunLightVisibility(*f->engine, probe).status().code(), absl::StatusCode::kInvalidArgument);
  probe.answer_only = {256};
  EXPECT_EQ(RunLightVisibility(*f->engine, probe).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(LightVisibilityBatch, ACancelledBatchStopsWhileItRuns) {
  auto f = MakeFoliage(20000, 4096);
  ASSERT_NE(f, nullptr);
  // The scene's index first, so that the call's work is the batch's.
  auto resident = f->engine->SceneForQuery("foliage", 0);
  ASSERT_TRUE(resident.ok()) << resident.status();
  ASSERT_TRUE(f->engine->TriangleIndexOf(**resident).ok());
  std::atomic<bool> cancelled{false};
  f->query.call.stop.cancelled = &cancelled;
  using Clock = std::chrono::steady_clock;
  Clock::time_point cancelled_at;
  std::thread canceller([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    cancelled_at = Clock::now();
    cancelled = true;
  });
  StatusOr<LightVisibilityAnswer> answer = RunLightVisibility(*f->engine, f->query);
  const auto returned_at = Clock::now();
  canceller.join();
  ASSERT_EQ(answer.status().code(), absl::StatusCode::kCancelled) << "the batch ran to its end in under 300 ms";
  EXPECT_NE(std::string(answer.status().message()).find("points left"), std::string::npos) << answer.status();
  const double after_ms = std::chrono::duration<double, std::milli>(returned_at - cancelled_at).count();
  EXPECT_LT(after_ms, 1000.0);
  std::printf("returned %.1f ms after the cancel: %s\n", after_ms, answer.status().ToString().c_str());
  RecordProperty("stop_after_cancel_ms", std::to_string(after_ms));

  // A deadline passes mid-batch the same way.
  f->query.call.stop.cancelled = nullptr;
  f->query.call.stop.deadline = Clock::now() + std::chrono::milliseconds(300);
  StatusOr<LightVisibilityAnswer> late = RunLightVisibility(*f->engine, f->query);
  const double late_ms = std::chrono::duration<double, std::milli>(Clock::now() - f->query.call.stop.deadline).count();
  EXPECT_EQ(late.status().code(), absl::StatusCode::kDeadlineExceeded) << late.status();
  EXPECT_LT(late_ms, 1000.0);
  std::printf("returned %.1f ms after the deadline: %s\n", late_ms, late.status().ToString().c_str());
}

}  // namespace
}  // namespace visq::core
