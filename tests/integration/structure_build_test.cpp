// Structures a scene builds on first use, end to end: metadata calls answer
// while a first query builds a large scene's BVH, concurrent first queries
// share one build, the build's time is the answer's build_ms, scenes warm at
// load when asked, and --max-scene-bytes admits by every structure.
// Ordering is shown by the server's own build counters (GetStats
// structure_builds), not by timing.
#include <chrono>
#include <map>
#include <thread>

#include <gtest/gtest.h>

#include "large_scene.h"
#include "proto_builders.h"
#include "scene/gltf_writer.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using testing::ScratchDir;
using testing::ServerProcess;
using testing::SetPatch;

// A small RAYCAST map over the grid: what it costs is the BVH.
v1::HiddenSampleMapRequest RaycastOverGrid() {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("grid");
  request.set_method(v1::RAYCAST);
  SetPatch(request.mutable_source(), {-0.25, 1.0, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  request.mutable_samples()->set_count(16);
  SetPatch(request.mutable_receiver(), {-0.5, 0.1, -0.5}, {1, 0, 0}, {0, 0, 1});
  request.set_width(8);
  request.set_height(8);
  return request;
}

std::map<std::string, v1::StructureBuildStats> Builds(client::Client& client) {
  std::map<std::string, v1::StructureBuildStats> out;
  auto stats = client.GetStats();
  EXPECT_TRUE(stats.ok()) << stats.status();
  if (stats.ok())
    for (const auto& b : stats->structure_builds()) out[b.structure()] = b;
  return out;
}

// Polls GetStats until `done` holds of the builds (a hang guard, not a
// timing: two minutes).
template <typename Done>
bool AwaitBuilds(client::Client& client, Done done) {
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::minutes(2);
  while (std::chrono::steady_clock::now() < give_up) {
    if (done(Builds(client))) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return false;
}

class StructureBuildTest : public ::testing::Test {
 protected:
  // The grid of 2 cells^2 triangles, as a user's file.
  fs::path WriteGrid(int cells) {
    const fs::path path = files_.path() / "grid.glb";
    EXPECT_TRUE(WriteGltfFile(testing::MakeRippledGrid(cells), path).ok());
    return path;
  }
  void Start(std::vector<std::string> args = {}) {
    server_ = ServerProcess::Start({repo_.path(), std::move(args)});
    ASSERT_NE(server_, nullptr);
    client_ = std::make_unique<client::Client>(client::ClientOptions{.address = server_->address()});
  }

  ScratchDir repo_;
  ScratchDir files_;
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<client::Client> client_;
};

TEST_F(StructureBuildTest, MetadataAnswersWhileFirstQueriesShareOneBuild) {
  Start();
  // 2M triangles: the BVH takes about 2 s on 2 cores.
  auto uploaded = client_->UploadScene(WriteGrid(1000), "grid");
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();

  // Two first queries at once; each on its own client.
  std::vector<StatusOr<client::HiddenSampleMap>> maps(2, absl::UnknownError("not run"));
  std::vector<std::thread> queries;
  for (size_t i = 0; i < maps.size(); ++i)
    queries.emplace_back([&, i] {
      client::Client own(client::ClientOptions{.address = server_->address()});
      maps[i] = own.ComputeHiddenSampleMap(RaycastOverGrid());
    });
  const bool started = AwaitBuilds(*client_, [](const auto& b) {
    return b.count("embree_bvh") && (b.at("embree_bvh").in_progress() > 0 || b.at("embree_bvh").builds() > 0);
  });
  ASSERT_TRUE(started) << "no BVH build started";
  ASSERT_EQ(Builds(*client_)["embree_bvh"].in_progress(), 1u) << "the build ended before it was observed";

  // Every metadata call answers now, and the build is still running after.
  auto info = client_->GetScene("grid");
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->triangle_count(), 2'000'000u);
  auto list = client_->ListScenes();
  ASSERT_TRUE(list.ok()) << list.status();
  EXPECT_EQ(list->scenes_size(), 1);
  auto during = Builds(*client_);
  EXPECT_EQ(during["embree_bvh"].in_progress(), 1u)
      << "GetScene, ListScenes and GetStats must answer while the BVH builds";
  EXPECT_EQ(during["embree_bvh"].builds(), 0u);
  EXPECT_EQ(info->memory().cpu_bytes(), uploaded->memory().cpu_bytes()) << "no BVH counted before it exists";

  for (std::thread& t : queries) t.join();
  for (const auto& map : maps) {
    ASSERT_TRUE(map.ok()) << map.status();
    EXPECT_GT(map->figures.timing().build_ms(), 0.0) << "both waited for the BVH";
  }
  auto after = Builds(*client_);
  EXPECT_EQ(after["embree_bvh"].builds(), 1u) << "one build for both first queries";
  EXPECT_EQ(after["embree_bvh"].in_progress(), 0u);
  EXPECT_GT(client_->GetScene("grid")->memory().cpu_bytes(), uploaded->memory().cpu_bytes());

  // Built: the next query waits for nothing.
  auto warm = client_->ComputeHiddenSampleMap(RaycastOverGrid());
  ASSERT_TRUE(warm.ok()) << warm.status();
  EXPECT_EQ(warm->figures.timing().build_ms(), 0.0);
  EXPECT_EQ(Builds(*client_)["embree_bvh"].builds(), 1u);
}

TEST_F(StructureBuildTest, WarmScenesFlagBuildsEveryStructureAtLoad) {
  Start({"--warm-scenes"});
  auto uploaded = client_->UploadScene(WriteGrid(300), "grid");
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  const bool built = AwaitBuilds(*client_, [](const auto& b) {
    for (const char* kind : {"gpu_upload", "embree_bvh", "triangle_index"})
      if (!b.count(kind) || b.at(kind).builds() < 1) return false;
    return true;
  });
  ASSERT_TRUE(built) << "the warm builds never finished";
  auto map = client_->ComputeHiddenSampleMap(RaycastOverGrid());
  ASSERT_TRUE(map.ok()) << map.status();
  EXPECT_EQ(map->figures.timing().build_ms(), 0.0) << "warmed: the first query builds nothing";
  auto raster = RaycastOverGrid();
  raster.set_method(v1::RASTER);
  auto drawn = client_->ComputeHiddenSampleMap(raster);
  ASSERT_TRUE(drawn.ok()) << drawn.status();
  EXPECT_EQ(drawn->figures.timing().build_ms(), 0.0);
  auto builds = Builds(*client_);
  for (const char* kind : {"gpu_upload", "embree_bvh", "triangle_index"})
    EXPECT_EQ(builds[kind].builds(), 1u) << kind;
  auto info = client_->GetScene("grid");
  ASSERT_TRUE(info.ok());
  EXPECT_GT(info->memory().gpu_bytes(), 0u);
}

TEST_F(StructureBuildTest, LoadSceneWarmsWhatItNamesAndRefusesUnknownKinds) {
  Start();
  ASSERT_TRUE(client_->UploadScene(WriteGrid(100), "grid").ok());
  auto load = [&](std::vector<int> warm) {
    auto context = client_->NewContext();
    v1::SceneInfo info;
    auto writer = client_->stub().LoadScene(context.get(), &info);
    v1::LoadSceneRequest request;
    request.mutable_header()->set_name("grid");
    request.mutable_header()->set_from_repository(true);
    request.mutable_header()->set_replace(true);
    for (int kind : warm) request.mutable_header()->add_warm(static_cast<v1::StructureKind>(kind));
    writer->Write(request);
    writer->WritesDone();
    return writer->Finish();
  };
  const grpc::Status bad = load({v1::EMBREE_BVH, 7});
  EXPECT_EQ(bad.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(bad.error_message().find("header.warm[1]"), std::string::npos) << bad.error_message();
  EXPECT_EQ(load({v1::STRUCTURE_UNSPECIFIED}).error_code(), grpc::StatusCode::INVALID_ARGUMENT);

  const grpc::Status ok = load({v1::EMBREE_BVH});
  ASSERT_TRUE(ok.ok()) << ok.error_message();
  ASSERT_TRUE(AwaitBuilds(*client_, [](const auto& b) {
    return b.count("embree_bvh") && b.at("embree_bvh").builds() >= 1;
  }));
  auto builds = Builds(*client_);
  EXPECT_EQ(builds["embree_bvh"].builds(), 1u);
  EXPECT_EQ(builds.count("gpu_upload"), 0u) << "only what was named";
  EXPECT_EQ(builds.count("triangle_index"), 0u);
  auto map = client_->ComputeHiddenSampleMap(RaycastOverGrid());
  ASSERT_TRUE(map.ok()) << map.status();
  EXPECT_EQ(map->figures.timing().build_ms(), 0.0);
}

TEST_F(StructureBuildTest, MaxSceneBytesAdmitsByEveryStructure) {
  Start();
  const fs::path grid = WriteGrid(100);
  auto admitted = client_->UploadScene(grid, "grid");
  ASSERT_TRUE(admitted.ok()) << admitted.status();
  const uint64_t geometry = admitted->memory().cpu_bytes();
  const uint64_t estimate = admitted->estimated_memory().cpu_bytes() + admitted->estimated_memory().gpu_bytes();
  EXPECT_GT(admitted->estimated_memory().cpu_bytes(), geometry) << "the estimate adds the BVH and the index";
  EXPECT_EQ(admitted->estimated_memory().gpu_bytes(), 52u * admitted->triangle_count());
  ASSERT_GT(estimate, geometry);

  // A cap the geometry fits under but not its structures.
  client_.reset();
  server_.reset();
  ScratchDir other_repo;
  server_ = ServerProcess::Start(
      {other_repo.path(), {"--max-scene-bytes", std::to_string(geometry + (estimate - geometry) / 2)}});
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<client::Client>(client::ClientOptions{.address = server_->address()});
  auto refused = client_->UploadScene(grid, "grid");
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted) << refused.status();
  EXPECT_NE(std::string(refused.status().message()).find("--max-scene-bytes"), std::string::npos)
      << refused.status();
  EXPECT_NE(std::string(refused.status().message()).find("Embree BVH"), std::string::npos) << refused.status();
  EXPECT_FALSE(client_->GetScene("grid").ok()) << "nothing resident";
}

}  // namespace
}  // namespace visq
