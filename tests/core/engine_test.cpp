// The Engine on a real repository folder and a real GPU worker (llvmpipe
// here), without the server: scenes loaded from the repository, found by
// name and version, structures built lazily, unloaded and deleted.
#include "core/engine.h"

#include <gtest/gtest.h>

#include "scene/sample_scenes.h"
#include "test_support.h"

namespace visq {
namespace {

std::unique_ptr<Engine> StartEngine(const std::filesystem::path& repo) {
  EXPECT_TRUE(WriteSampleScenes(repo).ok());
  EngineOptions options;
  options.scene_repo = repo;
  options.gpu.debug = true;
  options.load_repository_at_start = false;
  auto engine = Engine::Create(options);
  EXPECT_TRUE(engine.ok()) << engine.status();
  return engine.ok() ? std::move(*engine) : nullptr;
}

TEST(Engine, FindsStoredScenesByNameAndVersion) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  EXPECT_TRUE(engine->ListScenes().empty()) << "nothing resident before the first use";

  auto resident = engine->FindScene("cornell_box_visq", 0);
  ASSERT_TRUE(resident.ok()) << resident.status();
  const uint64_t version = (*resident)->version;
  EXPECT_GT(version, 0u);
  EXPECT_EQ(engine->ListScenes().size(), 1u);
  EXPECT_TRUE(engine->FindScene("cornell_box_visq", version).ok());
  EXPECT_EQ(engine->FindScene("cornell_box_visq", version + 1).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(engine->FindScene("no_such_scene", 0).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(engine->FindScene("../etc", 0).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(Engine, BuildsEachStructureOnceAndCountsItsMemory) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  auto resident = engine->FindScene("cornell_box_visq", 0);
  ASSERT_TRUE(resident.ok()) << resident.status();
  auto gpu_scene = engine->GpuSceneOf(**resident);
  ASSERT_TRUE(gpu_scene.ok()) << gpu_scene.status();
  auto again = engine->GpuSceneOf(**resident);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(gpu_scene->get(), again->get()) << "uploaded once";
  auto embree = engine->EmbreeSceneOf(**resident);
  ASSERT_TRUE(embree.ok()) << embree.status();
  EXPECT_EQ(embree->get(), engine->EmbreeSceneOf(**resident)->get()) << "built once";
  auto summary = engine->GetScene("cornell_box_visq", false);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_GT(summary->gpu_bytes, 0u);
  EXPECT_GT(summary->cpu_bytes, 0u);
  EXPECT_EQ(summary->triangles, (*resident)->scene->triangles.size());
}

TEST(Engine, UnloadKeepsTheStoredSceneUnlessAskedToDelete) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  ASSERT_TRUE(engine->FindScene("cornell_box_visq", 0).ok());
  auto deleted = engine->UnloadScene("cornell_box_visq", false);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_FALSE(*deleted);
  EXPECT_TRUE(engine->ListScenes().empty());
  EXPECT_TRUE(engine->FindScene("cornell_box_visq", 0).ok()) << "still stored: loads again";
  deleted = engine->UnloadScene("cornell_box_visq", true);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_TRUE(*deleted);
  EXPECT_EQ(engine->FindScene("cornell_box_visq", 0).status().code(), absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace visq
