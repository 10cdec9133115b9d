// A GPU reset while the server runs: the request whose GPU job was running
// fails with INTERNAL and says why, and the next requests work, on a new
// context, with the same answers as before the loss. The reset is injected
// (--fault-lose-gpu-context-at-job); what follows it is the real recovery:
// the worker destroys the context and makes a new one, and every GPU-resident
// structure (scene buffers, programs, Hough tables) is rebuilt on next use.
#include <gtest/gtest.h>

#include "proto_builders.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

using testing::Set;
using testing::SetPatch;

v1::HiddenSampleMapRequest CeilingLightOntoFloor() {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  request.mutable_samples()->set_count(64);
  request.mutable_samples()->set_seed(7);
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_width(32);
  request.set_height(32);
  request.set_want_bitmasks(true);
  request.set_method(v1::RASTER);  // a GPU job per map
  return request;
}

TEST(GpuFault, ContextLossFailsOneRequestAndTheNextOnesWork) {
  testing::ScratchDir repo;
  // GPU jobs: 1 self-test, 2 scene upload, 3 mapper set-up, 4 the first map;
  // the fifth (the second map) loses the context.
  auto server = testing::ServerProcess::Start(
      {repo.path(), {"--seed-samples", "--fault-lose-gpu-context-at-job", "5"}});
  ASSERT_NE(server, nullptr);
  client::Client client(client::ClientOptions{.address = server->address()});

  std::vector<std::vector<uint32_t>> answers;
  std::vector<Status> failures;
  for (int attempt = 0; attempt < 4; ++attempt) {
    auto map = client.ComputeHiddenSampleMap(CeilingLightOntoFloor());
    if (map.ok()) answers.push_back(map->blocked_bits);
    else failures.push_back(map.status());
  }
  ASSERT_EQ(failures.size(), 1u) << "exactly the request running at the loss fails";
  EXPECT_EQ(failures[0].code(), absl::StatusCode::kInternal) << failures[0];
  EXPECT_NE(std::string(failures[0].message()).find("GPU context lost"), std::string::npos) << failures[0];
  ASSERT_EQ(answers.size(), 3u);
  EXPECT_EQ(answers[1], answers[0]) << "the map after the loss (re-uploaded scene, rebuilt table) must not change";
  EXPECT_EQ(answers[2], answers[0]);

  // Programs cached per context in other algorithms are rebuilt too.
  v1::VoxelizeRequest voxelize;
  voxelize.mutable_scene()->set_name("cornell_box_visq");
  voxelize.set_width(16);
  voxelize.set_height(16);
  voxelize.set_slices(16);
  voxelize.set_depth_axis(1);
  auto grid = client.Voxelize(voxelize);
  ASSERT_TRUE(grid.ok()) << grid.status();
  EXPECT_GT(grid->figures.occupied_voxels(), 0u);

  auto stats = client.GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->gpu_contexts_lost(), 1u);
  EXPECT_NE(server->Log().find("GPU context lost"), std::string::npos);
}

}  // namespace
}  // namespace visq
