// Structures a scene builds on first use, end to end: metadata calls answer
// while a first query builds a large scene's BVH, concurrent first queries
// share one build, the build's time is the answer's build_ms, scenes warm at
// load when asked, and --max-scene-bytes admits by every structure.
// Ordering is shown by the server's own build counters (GetStats
// structure_builds), not by timing.
#include <bit>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cmath>
#include <fstream>
#include <map>
#include <thread>
#include <utility>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

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
  // 52 bytes a triangle held, 80 a draw run and 64 for the identity record
  // (gpu::GpuScene::EstimateBytes).
  EXPECT_EQ(admitted->estimated_memory().gpu_bytes(), 52u * admitted->triangle_count() + 80u + 64u);
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

// GPU_RAYCAST's BVH is built only when asked for (every placement
// flattened, 96 bytes a triangle at most): under a cap that admits the scene
// and its other structures but not it, the method is refused naming it and
// the cap, and a request naming no method runs without it.
TEST_F(StructureBuildTest, MaxSceneBytesLeavesOutTheGpuRaysWhereTheyDoNotFit) {
  Start();
  const fs::path grid = WriteGrid(100);
  auto admitted = client_->UploadScene(grid, "grid");
  ASSERT_TRUE(admitted.ok()) << admitted.status();
  const uint64_t estimate = admitted->estimated_memory().cpu_bytes() + admitted->estimated_memory().gpu_bytes();
  client_.reset();
  server_.reset();
  ScratchDir other_repo;
  server_ = ServerProcess::Start(
      {other_repo.path(), {"--max-scene-bytes", std::to_string(estimate + 48 * admitted->triangle_count())}});
  ASSERT_NE(server_, nullptr);
  client_ = std::make_unique<client::Client>(client::ClientOptions{.address = server_->address()});
  ASSERT_TRUE(client_->UploadScene(grid, "grid").ok());
  v1::HiddenSampleMapRequest request = RaycastOverGrid();
  request.set_method(v1::GPU_RAYCAST);
  auto refused = client_->ComputeHiddenSampleMap(request);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition) << refused.status();
  EXPECT_NE(std::string(refused.status().message()).find("method: GPU_RAYCAST"), std::string::npos) << refused.status();
  EXPECT_NE(std::string(refused.status().message()).find("--max-scene-bytes"), std::string::npos) << refused.status();
  request.set_method(v1::METHOD_UNSPECIFIED);
  auto chosen = client_->ComputeHiddenSampleMap(request);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  for (const v1::PlanEstimate& plan : chosen->figures.accuracy().plans()) EXPECT_NE(plan.method(), "gpu-raycast");
  auto stats = client_->GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();
  for (const auto& build : stats->structure_builds()) EXPECT_NE(build.structure(), "gpu_ray_bvh");
}


// A level of one repeated mesh: the grid placed sixteen times, tilted and
// stacked so that the copies shadow each other. Written twice over the same
// accessors: every node naming mesh 0 (placements, held once), and each
// node naming a mesh of its own (flattened). Both load to the same
// triangles; the placed one is held once by the CPU structures, admitted by
// that estimate, and answers RAYCAST and LightVisibility with the flattened
// scene's bits and numbers.
TEST_F(StructureBuildTest, PlacedMeshesAreHeldOnceAndAnswerAsTheFlattenedScene) {
  Start();
  const fs::path grid = files_.path() / "grid.gltf";
  ASSERT_TRUE(WriteGltfFile(testing::MakeRippledGrid(40), grid).ok());
  nlohmann::json doc = nlohmann::json::parse(std::ifstream(grid));
  ASSERT_EQ(doc["meshes"].size(), 1u);
  const nlohmann::json mesh = doc["meshes"][0];
  auto write_level = [&](const std::string& name, bool shared) {
    nlohmann::json level = doc;
    level["nodes"] = nlohmann::json::array();
    level["meshes"] = nlohmann::json::array();
    level["scenes"][0]["nodes"] = nlohmann::json::array();
    for (int k = 0; k < 16; ++k) {
      const double angle = 0.15 * (k % 5);  // about the x axis: (sin(a/2), 0, 0, cos(a/2))
      level["nodes"].push_back({{"mesh", shared ? 0 : k},
                                {"translation", {0.45 * (k % 4), 0.25 * k, 0.45 * (k / 4)}},
                                {"rotation", {std::sin(angle / 2), 0.0, 0.0, std::cos(angle / 2)}},
                                {"scale", {0.2, 0.2, 0.2}}});
      level["scenes"][0]["nodes"].push_back(k);
      if (!shared || k == 0) level["meshes"].push_back(mesh);
    }
    const fs::path path = files_.path() / (name + ".gltf");
    std::ofstream(path) << level.dump();
    return path;
  };
  auto placed = client_->UploadScene(write_level("placed", true), "placed");
  auto flat = client_->UploadScene(write_level("flat", false), "flat");
  ASSERT_TRUE(placed.ok() && flat.ok()) << placed.status() << flat.status();
  const uint64_t grid_triangles = 2 * 40 * 40;
  EXPECT_EQ(placed->triangle_count(), 16 * grid_triangles);
  EXPECT_EQ(flat->triangle_count(), 16 * grid_triangles);
  // The hash reads the scene as held (a mesh once and its placements), at
  // the cost of one copy: the same triangles held otherwise hash otherwise.
  EXPECT_NE(placed->content_hash(), flat->content_hash());
  EXPECT_EQ(placed->instance_count(), 16u);
  EXPECT_EQ(placed->unique_triangle_count(), grid_triangles);
  EXPECT_EQ(flat->instance_count(), 0u);
  EXPECT_EQ(flat->unique_triangle_count(), 16 * grid_triangles);
  // The BVH and the index of one grid and sixteen instances, against sixteen grids'.
  const uint64_t placed_structures = placed->estimated_memory().cpu_bytes() - placed->memory().cpu_bytes();
  const uint64_t flat_structures = flat->estimated_memory().cpu_bytes() - flat->memory().cpu_bytes();
  EXPECT_LT(placed_structures, flat_structures / 8) << placed_structures << " vs " << flat_structures;

  // A light above the stack, a receiver below it: the copies shadow part of it.
  v1::HiddenSampleMapRequest map;
  map.set_method(v1::RAYCAST);
  SetPatch(map.mutable_source(), {0.2, 6.0, 0.2}, {0.8, 0, 0}, {0, 0, 0.8});
  map.mutable_samples()->set_count(64);
  SetPatch(map.mutable_receiver(), {-0.6, -0.5, -0.6}, {2.4, 0, 0}, {0, 0, 2.4});
  map.set_width(24);
  map.set_height(24);
  map.set_want_bitmasks(true);
  // The same request of the placed and of the flattened level.
  auto on_both = [](auto request, auto call) {
    request.mutable_scene()->set_name("placed");
    auto placed_answer = call(request);
    request.mutable_scene()->set_name("flat");
    return std::make_pair(std::move(placed_answer), call(request));
  };
  auto [placed_map, flat_map] = on_both(map, [&](const auto& r) { return client_->ComputeHiddenSampleMap(r); });
  ASSERT_TRUE(placed_map.ok() && flat_map.ok()) << placed_map.status() << flat_map.status();
  EXPECT_EQ(placed_map->blocked_bits, flat_map->blocked_bits);
  size_t blocked = 0;
  for (uint32_t word : placed_map->blocked_bits) blocked += std::popcount(word);
  EXPECT_GT(blocked, placed_map->blocked_bits.size() * 2) << "some of the receiver is shadowed";
  EXPECT_LT(blocked, placed_map->blocked_bits.size() * 30) << "and some of it is lit";

  v1::LightVisibilityRequest light;
  for (const auto& v : {glm::dvec3(0.2, 6.0, 0.2), glm::dvec3(1.0, 6.0, 0.2), glm::dvec3(1.0, 6.0, 1.0),
                        glm::dvec3(0.2, 6.0, 1.0)})
    testing::Set(light.mutable_light()->add_vertices(), v.x, v.y, v.z);
  light.set_radiance(1.0);
  for (int i = 0; i < 25; ++i) {
    auto* point = light.add_points();
    testing::Set(point->mutable_position(), -0.5 + 0.1 * i, -0.5, -0.5 + 0.09 * i);
    testing::Set(point->mutable_normal(), 0, 1, 0);
  }
  auto [placed_light, flat_light] = on_both(light, [&](const auto& r) { return client_->LightVisibility(r); });
  ASSERT_TRUE(placed_light.ok() && flat_light.ok()) << placed_light.status() << flat_light.status();
  ASSERT_EQ(placed_light->points_size(), 25);
  int partial = 0;
  for (int i = 0; i < 25; ++i) {
    EXPECT_EQ(placed_light->points(i).visible_fraction(), flat_light->points(i).visible_fraction()) << "point " << i;
    const double f = placed_light->points(i).visible_fraction();
    partial += f > 0.01 && f < 0.99;
  }
  EXPECT_GT(partial, 0);

  // The GPU draws the grid once per placement: RASTER (its cluster cull
  // taken into each placement's space) gives the flattened scene's bits, and
  // so do the slicemap and the volumetric image. The placed corners are a float transform of
  // the mesh's floats, not the flattened doubles rounded: bits may differ
  // where a segment passes within float rounding of an edge.
  auto differing_bits = [](const std::vector<uint32_t>& a, const std::vector<uint32_t>& b) {
    size_t differ = a.size() == b.size() ? 0 : SIZE_MAX;
    for (size_t w = 0; w < a.size() && w < b.size(); ++w) differ += std::popcount(a[w] ^ b[w]);
    return differ;
  };
  map.set_method(v1::RASTER);
  auto [placed_raster, flat_raster] = on_both(map, [&](const auto& r) { return client_->ComputeHiddenSampleMap(r); });
  ASSERT_TRUE(placed_raster.ok() && flat_raster.ok()) << placed_raster.status() << flat_raster.status();
  const size_t raster_differ = differing_bits(placed_raster->blocked_bits, flat_raster->blocked_bits);
  std::printf("RASTER: %zu of %zu bits differ between placed and flattened; %zu between placed RASTER and RAYCAST\n",
              raster_differ, 32 * placed_raster->blocked_bits.size(),
              differing_bits(placed_raster->blocked_bits, placed_map->blocked_bits));
  EXPECT_LE(raster_differ, 2u);
  EXPECT_LE(differing_bits(placed_raster->blocked_bits, placed_map->blocked_bits), 2u);

  // RAYCAST, LightVisibility and RASTER built their structures over the
  // placements without flattening the placed level: its CPU memory (scene,
  // BVH and triangle index) is about one grid's and sixteen placements',
  // where the flattened level holds sixteen grids in each.
  auto placed_info = client_->GetScene("placed");
  auto flat_info = client_->GetScene("flat");
  ASSERT_TRUE(placed_info.ok() && flat_info.ok()) << placed_info.status() << flat_info.status();
  std::printf("CPU bytes after RAYCAST, LightVisibility and RASTER: placed %llu, flattened %llu\n",
              static_cast<unsigned long long>(placed_info->memory().cpu_bytes()),
              static_cast<unsigned long long>(flat_info->memory().cpu_bytes()));
  EXPECT_LT(placed_info->memory().cpu_bytes(), flat_info->memory().cpu_bytes() / 6);
  EXPECT_LE(placed_info->memory().cpu_bytes(), placed->estimated_memory().cpu_bytes());

  v1::VoxelizeRequest voxels;
  voxels.set_width(48);
  voxels.set_height(48);
  voxels.set_slices(64);
  voxels.set_depth_axis(1);
  voxels.set_conservative(true);
  auto [placed_voxels, flat_voxels] = on_both(voxels, [&](const auto& r) { return client_->Voxelize(r); });
  ASSERT_TRUE(placed_voxels.ok() && flat_voxels.ok()) << placed_voxels.status() << flat_voxels.status();
  const size_t voxels_differ = differing_bits(placed_voxels->bits, flat_voxels->bits);
  size_t occupied = 0;
  for (uint32_t word : placed_voxels->bits) occupied += std::popcount(word);
  std::printf("slicemap: %zu of %zu occupied voxels differ between placed and flattened\n", voxels_differ, occupied);
  EXPECT_GT(occupied, 1000u);
  EXPECT_LE(voxels_differ, occupied / 1000);

  v1::VolumetricShadowRequest shafts;
  testing::Set(shafts.mutable_camera_position(), 0.7, 1.5, 4.5);
  testing::Set(shafts.mutable_camera_forward(), 0.0, -0.3, -1.0);
  shafts.set_vertical_fov_deg(60);
  shafts.set_width(48);
  shafts.set_height(36);
  testing::Set(shafts.mutable_light_direction(), 0.2, -1.0, 0.3);
  shafts.set_shadow_map_size(256);
  shafts.set_scattering(0.3);
  shafts.set_extinction(0.3);
  shafts.set_combined_image(true);  // the surfaces too: face normals and materials
  auto [placed_shafts, flat_shafts] = on_both(shafts, [&](const auto& r) { return client_->VolumetricShadow(r); });
  ASSERT_TRUE(placed_shafts.ok() && flat_shafts.ok()) << placed_shafts.status() << flat_shafts.status();
  ASSERT_EQ(placed_shafts->combined.size(), flat_shafts->combined.size());
  size_t pixels_differ = 0;
  for (size_t i = 0; i < placed_shafts->combined.size(); ++i)
    pixels_differ += std::abs(placed_shafts->combined[i] - flat_shafts->combined[i]) > 1e-5f;
  std::printf("volumetric: %zu of %zu channels differ between placed and flattened\n", pixels_differ,
              placed_shafts->combined.size());
  EXPECT_LE(pixels_differ, placed_shafts->combined.size() / 200);

  // The bake reads each scene triangle's atlas corners through its
  // placement's triangle offset (named: the server's choice may probe the
  // ray estimators, whose structures are not the GPU buffers compared below).
  v1::ComputeObscurancesRequest bake;
  bake.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
  bake.set_resolution(128);
  bake.set_d_max(0.5);
  bake.set_direction_count(16);
  bake.set_want_averages(true);
  auto [placed_bake, flat_bake] = on_both(bake, [&](const auto& r) { return client_->ComputeObscurances(r); });
  ASSERT_TRUE(placed_bake.ok() && flat_bake.ok()) << placed_bake.status() << flat_bake.status();
  ASSERT_EQ(placed_bake->triangle_w.size(), flat_bake->triangle_w.size());
  size_t triangles_differ = 0;
  double w_sum = 0.0, largest = 0.0;
  for (size_t i = 0; i < placed_bake->triangle_w.size(); ++i) {
    const double difference = std::abs(placed_bake->triangle_w[i] - flat_bake->triangle_w[i]);
    triangles_differ += difference > 1e-4;
    largest = std::max(largest, difference);
    w_sum += placed_bake->triangle_w[i];
  }
  std::printf("obscurance: %zu of %zu triangle W channels differ between placed and flattened, by %.3g at most "
              "(mean W %.3f)\n",
              triangles_differ, placed_bake->triangle_w.size(), largest, w_sum / placed_bake->triangle_w.size());
  // Where copies touch, a depth tie may fall the other way: far inside the
  // bake's own bound.
  EXPECT_LE(triangles_differ, placed_bake->triangle_w.size() / 200);
  EXPECT_LT(largest, placed_bake->figures.accuracy().error_bound());
  EXPECT_LT(w_sum / placed_bake->triangle_w.size(), 0.99) << "the copies occlude each other";

  // Once queried, the placed level holds less than the flattened one, on
  // the CPU (the bake flattened it for its atlas, and the scene keeps and
  // counts that copy) and on the GPU, where it holds what its estimate said.
  auto placed_now = client_->GetScene("placed");
  auto flat_now = client_->GetScene("flat");
  ASSERT_TRUE(placed_now.ok() && flat_now.ok());
  EXPECT_LT(placed_now->memory().cpu_bytes(), flat_now->memory().cpu_bytes() / 2)
      << placed_now->memory().cpu_bytes() << " vs " << flat_now->memory().cpu_bytes();
  std::printf("GPU bytes: placed %llu, flattened %llu\n",
              static_cast<unsigned long long>(placed_now->memory().gpu_bytes()),
              static_cast<unsigned long long>(flat_now->memory().gpu_bytes()));
  EXPECT_EQ(placed_now->memory().gpu_bytes(), placed->estimated_memory().gpu_bytes());
  EXPECT_EQ(flat_now->memory().gpu_bytes(), flat->estimated_memory().gpu_bytes());
  EXPECT_LT(placed_now->memory().gpu_bytes(), flat_now->memory().gpu_bytes() / 12);
}

}  // namespace
}  // namespace visq
