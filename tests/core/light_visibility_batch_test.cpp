// A LightVisibility batch spread over many receiver cells, through the
// Engine on the generated Cornell box: each cell's tree is let go as soon
// as its points are answered, so the request holds a few trees at a time
// however many cells it has, and the answers equal those of one tree over
// the whole region.
#include <gtest/gtest.h>

#include "common/parallel.h"
#include "core/engine.h"
#include "core/light_visibility_query.h"
#include "scene/sample_scenes.h"
#include "test_support.h"

namespace visq {
namespace {

TEST(LightVisibilityBatch, ManyCellsHoldFewTreesAtATime) {
  testing::ScratchDir dir;
  ASSERT_TRUE(WriteSampleScenes(dir.path() / "repo").ok());
  EngineOptions options;
  options.scene_repo = dir.path() / "repo";
  options.load_repository_at_start = false;
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

}  // namespace
}  // namespace visq
