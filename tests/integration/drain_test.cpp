// SIGTERM during each kind of long call on a real scene: the real
// visq-server on loopback with llvmpipe, Sponza, and the client library.
// A pod's grace period holds only if every long job (a GL pass drawn in
// pieces, a bake's steps, the exact method's points) looks at the drain's
// stop flag, so each kind is stopped on its own here.
#include <chrono>
#include <cstdio>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "proto_builders.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq::testing {
namespace {

namespace fs = std::filesystem;
using client::Client;

// Short enough to keep the test to a few seconds per call, long enough that
// the server's "tell them to stop" moment (half the drain before its end,
// at most a second) comes well after the call is under way.
constexpr int kDrainSeconds = 2;

// The light and receiver of the 256^2 map: a 10 x 4 patch under
// Sponza's roof opening, the floor below it.
void SetSponzaPatches(v1::HiddenSampleMapRequest& request) {
  SetPatch(request.mutable_source(), {-5, 14, -2}, {10, 0, 0}, {0, 0, 4});
  SetPatch(request.mutable_receiver(), {-16, 0.2, -7}, {0, 0, 14}, {32, 0, 0});
}

v1::HiddenSampleMapRequest SponzaMap(uint32_t side) {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("sponza");
  SetSponzaPatches(request);
  request.mutable_samples()->set_count(256);
  request.set_width(side);
  request.set_height(side);
  request.set_method(v1::RASTER);
  request.set_lookup(v1::EXACT);
  return request;
}

v1::ComputeObscurancesRequest SponzaBake(uint32_t resolution, uint32_t directions) {
  v1::ComputeObscurancesRequest request;
  request.mutable_scene()->set_name("sponza");
  request.set_resolution(resolution);
  request.set_d_max(2.0);
  request.set_direction_count(directions);
  request.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);
  return request;
}

v1::VoxelizeRequest SponzaVoxels(uint32_t side, uint32_t slices) {
  v1::VoxelizeRequest request;
  request.mutable_scene()->set_name("sponza");
  request.set_width(side);
  request.set_height(side);
  request.set_slices(slices);
  request.set_conservative(true);
  return request;
}

v1::VolumetricShadowRequest SponzaVolumetric(uint32_t width, uint32_t height, uint32_t shadow_map) {
  v1::VolumetricShadowRequest request;
  request.mutable_scene()->set_name("sponza");
  Set(request.mutable_camera_position(), -10, 2, 0);
  Set(request.mutable_camera_forward(), 1, 0, 0);
  request.set_vertical_fov_deg(60);
  request.set_width(width);
  request.set_height(height);
  Set(request.mutable_light_direction(), 0.3, -1, 0.2);
  request.set_shadow_map_size(shadow_map);
  request.set_scattering(0.05);
  request.set_extinction(0.05);
  request.set_method(v1::VolumetricShadowRequest::RAY_MARCHING);
  return request;
}

// side x side points over Sponza's floor (half a unit above it, facing up),
// under the same 10 x 4 light facing down. `offset` shifts the grid so that
// the timed batch asks nothing the warm-up's trees already answered.
v1::LightVisibilityRequest SponzaLightBatch(int side, double offset) {
  v1::LightVisibilityRequest request;
  request.mutable_scene()->set_name("sponza");
  // Counter-clockwise from below: it shines down.
  Set(request.mutable_light()->add_vertices(), -5, 14, -2);
  Set(request.mutable_light()->add_vertices(), 5, 14, -2);
  Set(request.mutable_light()->add_vertices(), 5, 14, 2);
  Set(request.mutable_light()->add_vertices(), -5, 14, 2);
  for (int i = 0; i < side; ++i)
    for (int j = 0; j < side; ++j) {
      auto* p = request.add_points();
      Set(p->mutable_position(), -15 + 30 * (i + 0.5 + offset) / side, 0.5, -6 + 12 * (j + 0.5 + offset) / side);
      Set(p->mutable_normal(), 0, 1, 0);
    }
  return request;
}

struct LongCall {
  std::string name;
  std::string method;  // as the server's log names the call
  // The same kind of call, small: compiles its GL programs and builds the
  // scene's structures (seconds on llvmpipe) before the timed call.
  std::function<absl::Status(Client&)> warm_up;
  std::function<absl::Status(Client&)> run;  // far longer than the drain on llvmpipe
  // Also warm up with `run` itself, cut by a deadline: what only the timed
  // call's size allocates (a 4096^2 shadow map's targets, 2.4 s in one GL
  // job under ASan) is not counted against the drain. Not for calls that
  // cache their answers (the light's trees would answer the timed call).
  bool warm_up_at_size = false;
};

std::vector<LongCall> SponzaLongCalls() {
  return {
      {"HiddenSampleMap 256^2 RASTER", "HiddenSampleMap",
       [](Client& c) { return c.ComputeHiddenSampleMap(SponzaMap(8)).status(); },
       [](Client& c) { return c.ComputeHiddenSampleMap(SponzaMap(256)).status(); }},
      {"ComputeObscurances DEPTH_PEELING", "ComputeObscurances",
       [](Client& c) { return c.ComputeObscurances(SponzaBake(512, 1)).status(); },
       [](Client& c) { return c.ComputeObscurances(SponzaBake(1024, 256)).status(); }},
      {"Voxelize conservative", "Voxelize",
       [](Client& c) { return c.Voxelize(SponzaVoxels(32, 32)).status(); },
       [](Client& c) { return c.Voxelize(SponzaVoxels(2048, 1024)).status(); }},
      {"VolumetricShadow RAY_MARCHING", "VolumetricShadow",
       [](Client& c) { return c.VolumetricShadow(SponzaVolumetric(32, 32, 256)).status(); },
       [](Client& c) { return c.VolumetricShadow(SponzaVolumetric(1920, 1080, 4096)).status(); },
       /*warm_up_at_size=*/true},
      {"LightVisibility batch", "LightVisibility",
       [](Client& c) { return c.LightVisibility(SponzaLightBatch(4, 0.0)).status(); },
       [](Client& c) { return c.LightVisibility(SponzaLightBatch(200, 0.25)).status(); }},
      // The stream the CLI and the Python client send large batches over.
      {"LightVisibilityStream batch", "LightVisibilityStream",
       [](Client& c) { return c.LightVisibilityStream({SponzaLightBatch(4, 0.0)}).status(); },
       [](Client& c) { return c.LightVisibilityStream({SponzaLightBatch(200, 0.25)}).status(); }},
  };
}

// For each kind of long call: a server of its own (SIGTERM ends it), the
// call warmed up, then started again and SIGTERM sent a second into it. The
// process exits within --drain-seconds + 1 s and the call is answered
// UNAVAILABLE (retry on another replica) by the server itself. A device fast enough to finish a
// call within the drain answers it instead: then there is nothing to stop,
// and only the exit's time is checked.
TEST(Drain, SigtermDuringEachLongCallOnSponzaExitsWithinTheDrainAnsweringUnavailable) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  // Uploaded once into a repository that each server loads at start.
  ScratchDir repo;
  {
    auto server = ServerProcess::Start({repo.path(), {}});
    ASSERT_NE(server, nullptr);
    Client uploader({.address = server->address()});
    auto info = uploader.UploadScene(scenes / "sponza_dabrovic/sponza.gltf", "sponza");
    ASSERT_TRUE(info.ok()) << info.status();
  }
  for (const LongCall& call : SponzaLongCalls()) {
    SCOPED_TRACE(call.name);
    auto server = ServerProcess::Start({repo.path(), {"--drain-seconds", std::to_string(kDrainSeconds)}});
    ASSERT_NE(server, nullptr);
    Client client({.address = server->address(), .deadline = std::chrono::minutes(10),
                   .stream_deadline = std::chrono::milliseconds(0)});
    {
      const absl::Status warm = call.warm_up(client);
      ASSERT_TRUE(warm.ok()) << warm << "\n" << server->Log();
      if (call.warm_up_at_size) {
        Client cut({.address = server->address(), .deadline = std::chrono::seconds(3),
                    .stream_deadline = std::chrono::seconds(3)});
        (void)call.run(cut);
      }
    }
    absl::Status status;
    std::chrono::steady_clock::time_point answered;
    std::thread running([&] {
      status = call.run(client);
      answered = std::chrono::steady_clock::now();
    });
    std::this_thread::sleep_for(std::chrono::seconds(1));  // under way
    const auto term = std::chrono::steady_clock::now();
    const int exit_status = server->Stop();
    const double exit_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - term).count();
    running.join();
    const double answer_s = std::chrono::duration<double>(answered - term).count();
    EXPECT_EQ(exit_status, 0) << server->Log();
    EXPECT_LT(exit_s, kDrainSeconds + 1.0 + kSanitizedStopSlackSeconds) << server->Log();
    std::printf("%s: SIGTERM -> answer %.2f s (%s), exit %.2f s (drain %d s)\n", call.name.c_str(), answer_s,
                std::string(absl::StatusCodeToString(status.code())).c_str(), exit_s, kDrainSeconds);
    if (status.ok()) {
      RecordProperty(call.name, "finished within the drain: nothing to stop");
      continue;
    }
    EXPECT_EQ(status.code(), absl::StatusCode::kUnavailable) << status << "\n" << server->Log();
    EXPECT_LT(answer_s, kDrainSeconds + 1.0 + kSanitizedStopSlackSeconds) << server->Log();
    // The server's own answer, not gRPC's shutdown cutting the call at the
    // drain's end (which the client also sees as UNAVAILABLE): the call
    // was told to stop, and its work did.
    const std::string log = server->Log();
    EXPECT_NE(log.find("told to stop"), std::string::npos) << log;
    EXPECT_NE(log.find(" " + call.method + "] UNAVAILABLE in"), std::string::npos) << log;
  }
}

}  // namespace
}  // namespace visq::testing
