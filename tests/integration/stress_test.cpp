// Load: 16 concurrent clients mixing every kind of query on two scenes for
// a bounded time, while a long obscurance bake runs and an editor changes a
// third scene (moves and obscurance updates) and uploads and unloads a
// fourth. No request may fail,
// every answer must equal the single-client answer to the same request,
// the server's memory must stay bounded, and small queries must keep
// completing while the bake holds the GPU queue (they have priority).
#include <atomic>
#include <fstream>
#include <thread>

#include <gtest/gtest.h>

#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "proto_builders.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

using client::Client;
using testing::ScratchDir;
using testing::ServerProcess;

constexpr int kClients = 16;
constexpr auto kDuration = std::chrono::seconds(12);

using testing::Set;
using testing::SetPatch;

// The server's peak resident memory, from /proc.
long PeakRssKiB(int pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(status, line))
    if (line.rfind("VmHWM:", 0) == 0) return std::stol(line.substr(6));
  return -1;
}

// The queries every client repeats, on one scene: their answers are
// deterministic, so each must equal the first answer.
struct Queries {
  v1::HiddenSampleMapRequest map;
  v1::LightVisibilityRequest light;
  v1::VoxelizeRequest voxels;
  v1::PatchVisibilityRequest patches;
  v1::TransmittanceRequest transmittance;
  v1::VolumetricShadowRequest volumetric;
  v1::HiddenSampleMapRequest bad_map;  // NaN receiver: INVALID_ARGUMENT, always

  explicit Queries(const std::string& scene) {
    map.mutable_scene()->set_name(scene);
    SetPatch(map.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    map.mutable_samples()->set_count(32);
    SetPatch(map.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
    map.set_width(16);
    map.set_height(16);
    map.set_want_bitmasks(true);

    light.mutable_scene()->set_name(scene);
    for (const auto& v : {glm::dvec3(-0.25, 1.99, -0.25), glm::dvec3(0.25, 1.99, -0.25), glm::dvec3(0.25, 1.99, 0.25),
                          glm::dvec3(-0.25, 1.99, 0.25)})
      Set(light.mutable_light()->add_vertices(), v.x, v.y, v.z);
    for (double x : {-0.9, -0.3, 0.3, 0.9}) {
      auto* p = light.add_points();
      Set(p->mutable_position(), x, 0.001, 0.7);
      Set(p->mutable_normal(), 0, 1, 0);
    }

    voxels.mutable_scene()->set_name(scene);
    voxels.set_width(32);
    voxels.set_height(32);
    voxels.set_slices(32);

    patches.mutable_scene()->set_name(scene);
    SetPatch(patches.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
    SetPatch(patches.mutable_receiver(), {-0.999, 0.001, -0.997}, {1.998, 0, 0}, {0, 0, 1.998});
    for (auto* n : {&patches}) {
      n->set_source_columns(8);
      n->set_source_rows(8);
      n->set_receiver_columns(8);
      n->set_receiver_rows(8);
    }

    transmittance.mutable_scene()->set_name(scene);
    transmittance.set_light_kind(v1::TransmittanceRequest::DIRECTIONAL);
    Set(transmittance.mutable_light_direction(), 0, -1, 0);
    auto* absorber = transmittance.add_absorbers();
    absorber->set_node("short_box");
    absorber->set_absorption(2.0);
    Set(transmittance.add_points(), 0.4, 0.001, 0.35);
    Set(transmittance.add_points(), -0.9, 0.001, 0.9);
    transmittance.set_resolution(64);
    transmittance.set_method(v1::TransmittanceRequest::SLICEMAP);  // one method: every answer the same bits
    transmittance.set_slices(64);

    volumetric.mutable_scene()->set_name(scene);
    Set(volumetric.mutable_camera_position(), 0, 1, 3.5);
    Set(volumetric.mutable_camera_forward(), 0, 0, -1);
    Set(volumetric.mutable_light_direction(), 0.3, -0.6, -1.0);
    volumetric.set_width(32);
    volumetric.set_height(24);
    volumetric.set_shadow_map_size(128);
    volumetric.set_scattering(0.2);
    volumetric.set_extinction(0.2);

    bad_map = map;
    bad_map.mutable_receiver()->mutable_origin()->set_y(std::nan(""));
  }
};

// What the 16 clients mix: every RPC but the scene-changing ones (upload,
// unload, SetNodeTransform, UpdateObscurances), which would change the other
// clients' answers; the editor thread runs those on scenes of its own.
constexpr int kQueryKinds = 9;

struct Answers {
  std::vector<uint32_t> map_bits;
  std::vector<double> light_fractions;
  std::vector<uint32_t> voxel_bits;
  double mutual = 0;
  std::vector<float> values;  // transmittance, in-scattering
  uint64_t triangles = 0;     // catalog reads
  absl::StatusCode expected_error = absl::StatusCode::kOk;
};

StatusOr<Answers> Ask(Client& client, const Queries& q, int which) {
  Answers a;
  switch (which % kQueryKinds) {
    case 0: {
      VISQ_ASSIGN_OR_RETURN(client::HiddenSampleMap map, client.ComputeHiddenSampleMap(q.map));
      a.map_bits = std::move(map.blocked_bits);
      break;
    }
    case 1: {
      VISQ_ASSIGN_OR_RETURN(v1::LightVisibilityResponse light, client.LightVisibility(q.light));
      for (const auto& p : light.points()) a.light_fractions.push_back(p.visible_fraction());
      break;
    }
    case 2: {
      VISQ_ASSIGN_OR_RETURN(client::VoxelGrid grid, client.Voxelize(q.voxels));
      a.voxel_bits = std::move(grid.bits);
      break;
    }
    case 3: {
      VISQ_ASSIGN_OR_RETURN(v1::PatchVisibilityResponse pv, client.PatchVisibility(q.patches));
      a.mutual = pv.mutual_visible_fraction();
      break;
    }
    case 4: {
      VISQ_ASSIGN_OR_RETURN(v1::TransmittanceResponse t, client.Transmittance(q.transmittance));
      a.values.assign(t.transmittance().begin(), t.transmittance().end());
      break;
    }
    case 5: {
      VISQ_ASSIGN_OR_RETURN(client::VolumetricImage image, client.VolumetricShadow(q.volumetric));
      a.values = std::move(image.inscattering);
      break;
    }
    case 6: {
      VISQ_ASSIGN_OR_RETURN(std::vector<v1::LightVisibilityResponse> stream,
                            client.LightVisibilityStream({q.light, q.light}));
      for (const auto& response : stream)
        for (const auto& p : response.points()) a.light_fractions.push_back(p.visible_fraction());
      break;
    }
    case 7: {
      VISQ_ASSIGN_OR_RETURN(v1::ListScenesResponse list, client.ListScenes());
      VISQ_ASSIGN_OR_RETURN(v1::SceneInfo info, client.GetScene(q.map.scene().name()));
      VISQ_ASSIGN_OR_RETURN(v1::ServerStats stats, client.GetStats());
      if (list.scenes_size() < 2 || stats.scenes_resident() < 2)
        return absl::InternalError("the catalog lost a scene");
      a.triangles = info.triangle_count();
      break;
    }
    case 8: {
      // A bad request under load: refused with its field named, never
      // queued, never anything else.
      auto refused = client.ComputeHiddenSampleMap(q.bad_map);
      if (refused.ok() || refused.status().code() != absl::StatusCode::kInvalidArgument)
        return absl::InternalError(absl::StrCat("bad request answered ", refused.status().ToString()));
      a.expected_error = refused.status().code();
      break;
    }
  }
  return a;
}

bool Same(const Answers& a, const Answers& b) {
  return a.map_bits == b.map_bits && a.light_fractions == b.light_fractions && a.voxel_bits == b.voxel_bits &&
         a.mutual == b.mutual && a.values == b.values && a.triangles == b.triangles &&
         a.expected_error == b.expected_error;
}

TEST(Stress, SixteenClientsMixingQueriesOnTwoScenesDuringABake) {
  ScratchDir repo, files;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--worker-threads", "8"}});
  ASSERT_NE(server, nullptr);
  Client setup({.address = server->address()});
  // The second scene: the same box, shifted far from the origin.
  Scene shifted = MakeCornellBox();
  for (auto& p : shifted.positions) p += glm::dvec3(1e5, 0, 0);
  UpdateBounds(shifted);
  ASSERT_TRUE(WriteGltfFile(shifted, files.path() / "far.glb").ok());
  ASSERT_TRUE(setup.UploadScene(files.path() / "far.glb", "far_box").ok());

  const Queries near_queries("cornell_box_visq");
  Queries far_queries("far_box");
  // Shift the far scene's queries with it.
  auto shift = [](v1::Vec3* v) { v->set_x(v->x() + 1e5); };
  for (auto* patch : {far_queries.map.mutable_source(), far_queries.map.mutable_receiver(),
                      far_queries.patches.mutable_source(), far_queries.patches.mutable_receiver()})
    shift(patch->mutable_origin());
  for (auto& v : *far_queries.light.mutable_light()->mutable_vertices()) shift(&v);
  for (auto& p : *far_queries.light.mutable_points()) shift(p.mutable_position());
  for (auto& p : *far_queries.transmittance.mutable_points()) shift(&p);
  shift(far_queries.volumetric.mutable_camera_position());

  // Reference answers, one client, one at a time.
  std::vector<Answers> reference[2];
  for (int s = 0; s < 2; ++s)
    for (int k = 0; k < kQueryKinds; ++k) {
      auto answer = Ask(setup, s == 0 ? near_queries : far_queries, k);
      ASSERT_TRUE(answer.ok()) << "scene " << s << " query " << k << ": " << answer.status();
      reference[s].push_back(std::move(*answer));
    }

  // A long bake at batch priority, running through the whole test.
  std::atomic<bool> bake_done{false};
  std::atomic<uint32_t> bake_directions{0};
  std::atomic<int> small_done_during_bake{0};
  std::thread baker([&] {
    Client client({.address = server->address(), .deadline = kDuration + std::chrono::seconds(3)});
    v1::ComputeObscurancesRequest bake;
    bake.mutable_scene()->set_name("cornell_box_visq");
    bake.set_resolution(64);
    bake.set_d_max(1.0);
    bake.set_direction_count(4000);
    bake.set_total_directions(4000);
    bake.set_method(v1::ComputeObscurancesRequest::DEPTH_PEELING);  // the GPU's batch work
    // Ends by its deadline or by finishing; either way it held the queue.
    (void)client.ComputeObscurances(
        bake, [&](const v1::ObscuranceProgress& progress) { bake_directions = progress.directions_done(); });
    bake_done = true;
  });

  // The editor: the RPCs that change scenes, on scenes nobody else reads.
  ASSERT_TRUE(WriteGltfFile(MakeCornellBox(), files.path() / "moving.glb").ok());
  ASSERT_TRUE(setup.UploadScene(files.path() / "moving.glb", "moving_box").ok());
  // Its bake runs before the load: under load, batch work only gets the GPU
  // between interactive jobs.
  v1::ComputeObscurancesRequest editor_bake;
  editor_bake.mutable_scene()->set_name("moving_box");
  editor_bake.set_resolution(32);
  editor_bake.set_d_max(0.5);
  editor_bake.set_direction_count(8);
  ASSERT_TRUE(setup.ComputeObscurances(editor_bake, nullptr).ok());
  std::atomic<int> edits{0}, edit_failures{0};
  const auto edits_end = std::chrono::steady_clock::now() + kDuration;
  std::thread editor([&] {
    Client client({.address = server->address(), .deadline = std::chrono::seconds(60)});
    auto fail = [&](const std::string& what, const Status& status) {
      ++edit_failures;
      ADD_FAILURE() << "editor, " << what << ": " << status;
    };
    for (int i = 0; std::chrono::steady_clock::now() < edits_end; ++i) {
      v1::SetNodeTransformRequest move;
      move.mutable_scene()->set_name("moving_box");
      move.set_node_name("short_box");
      for (double v : testing::Translation(i % 2 == 0 ? -0.05 : 0.05, 0, 0)) move.add_world_matrix(v);
      auto moved = client.SetNodeTransform(move);
      if (!moved.ok()) return fail("move", moved.status());
      v1::UpdateObscurancesRequest update;
      update.mutable_scene()->set_name("moving_box");
      auto updated = client.UpdateObscurances(update);
      if (!updated.ok()) return fail("update", updated.status());
      if (updated->scene_version() != moved->version()) {
        ++edit_failures;
        ADD_FAILURE() << "update answered for version " << updated->scene_version() << ", not " << moved->version();
      }
      auto uploaded = client.UploadScene(files.path() / "moving.glb", "churn_box");
      if (!uploaded.ok()) return fail("upload", uploaded.status());
      auto unloaded = client.UnloadScene("churn_box", /*delete_from_repository=*/true);
      if (!unloaded.ok()) return fail("unload", unloaded.status());
      edits += 4;
    }
  });

  std::atomic<int> requests{0}, failures{0}, mismatches{0};
  std::vector<std::thread> clients;
  const auto end = std::chrono::steady_clock::now() + kDuration;
  for (int c = 0; c < kClients; ++c) {
    clients.emplace_back([&, c] {
      Client client({.address = server->address(), .deadline = std::chrono::seconds(30)});
      for (int i = 0; std::chrono::steady_clock::now() < end; ++i) {
        const int scene = (c + i) % 2, which = (c * 7 + i) % kQueryKinds;
        auto answer = Ask(client, scene == 0 ? near_queries : far_queries, which);
        ++requests;
        if (!answer.ok()) {
          ++failures;
          ADD_FAILURE() << "client " << c << ": " << answer.status();
          continue;
        }
        if (!Same(*answer, reference[scene][which])) {
          ++mismatches;
          const Answers& expected = reference[scene][which];
          std::string where;
          for (size_t k = 0; k < std::min(answer->values.size(), expected.values.size()); ++k)
            if (answer->values[k] != expected.values[k]) {
              where = absl::StrCat(", first at value ", k, ": ", answer->values[k], " against ", expected.values[k]);
              break;
            }
          ADD_FAILURE() << "scene " << scene << ", query kind " << which % kQueryKinds
                        << " (see Ask) differs from its single-client answer" << where;
        }
        if (!bake_done) ++small_done_during_bake;
      }
    });
  }
  for (auto& t : clients) t.join();
  editor.join();
  const long peak_kib = PeakRssKiB(server->pid());
  baker.join();

  std::printf("stress: %d requests from %d clients in %lld s, %d failures, %d mismatches, "
              "%d completed while the bake ran, which did %u directions; editor: %d scene changes, %d failures; "
              "server peak RSS %ld MiB\n",
              requests.load(), kClients, static_cast<long long>(kDuration.count()), failures.load(),
              mismatches.load(), small_done_during_bake.load(), bake_directions.load(), edits.load(),
              edit_failures.load(), peak_kib / 1024);
  ::testing::Test::RecordProperty("requests", requests.load());
  ::testing::Test::RecordProperty("peak_rss_kib", static_cast<int>(peak_kib));
  EXPECT_EQ(failures.load(), 0);
  EXPECT_EQ(edit_failures.load(), 0);
  EXPECT_GT(edits.load(), 0) << "the editor must have changed scenes during the load";
  EXPECT_EQ(mismatches.load(), 0) << "concurrent answers must equal the single-client answers";
  EXPECT_GT(requests.load(), kClients * 2);
  EXPECT_GT(small_done_during_bake.load(), kClients) << "small queries must not wait for the bake";
  EXPECT_GT(bake_directions.load(), 0u) << "nor may they starve it";
  EXPECT_GT(peak_kib, 0);
  EXPECT_LT(peak_kib, 4L << 20) << "server memory must stay bounded (4 GiB)";
}

}  // namespace
}  // namespace visq
