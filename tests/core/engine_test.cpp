// The Engine on a real repository folder and a real GPU worker (llvmpipe
// here), without the server: scenes loaded from the repository, found by
// name and version, structures built lazily, unloaded and deleted.
#include "core/engine.h"

#include <atomic>
#include <chrono>
#include <mutex>
#include <map>
#include <fstream>
#include <thread>

#include <gtest/gtest.h>

#include "core/light_visibility_query.h"
#include "core/obscurance_query.h"
#include "core/scene_edit_query.h"
#include "core/scene_repository.h"
#include "core/visibility_sampling_query.h"

#include "large_scene.h"
#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "test_support.h"

namespace visq::core {
namespace {

std::unique_ptr<Engine> StartEngine(const std::filesystem::path& repo, size_t map_band_bytes = 0) {
  EXPECT_TRUE(WriteSampleScenes(repo).ok());
  EngineOptions options;
  if (map_band_bytes > 0) options.hidden_sample_map.band_readback_bytes = map_band_bytes;
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

  auto resident = engine->SceneForQuery("cornell_box_visq", 0);
  ASSERT_TRUE(resident.ok()) << resident.status();
  const uint64_t version = (*resident)->version;
  EXPECT_GT(version, 0u);
  EXPECT_EQ(engine->ListScenes().size(), 1u);
  EXPECT_TRUE(engine->SceneForQuery("cornell_box_visq", version).ok());
  EXPECT_EQ(engine->SceneForQuery("cornell_box_visq", version + 1).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(engine->SceneForQuery("no_such_scene", 0).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(engine->SceneForQuery("../etc", 0).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(Engine, BuildsEachStructureOnceAndCountsItsMemory) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  auto resident = engine->SceneForQuery("cornell_box_visq", 0);
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

// An update whose call stopped before its moves loses nothing: the next
// update reports every move since the last answer, from that answer's version.
TEST(Engine, AStoppedUpdateLeavesItsMovesToTheNextAnswer) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  ObscuranceQuery bake;
  bake.scene = "cornell_box_visq";
  bake.resolution = 32;
  bake.params.d_max = 0.5;
  bake.params.direction_count = 8;
  bake.method = ObscuranceMethod::kRaycast;
  bake.rays_per_patch = 16;
  auto baked = RunComputeObscurances(*engine, bake);
  ASSERT_TRUE(baked.ok()) << baked.status();
  ASSERT_TRUE(baked->update_ready);
  NodeTransformQuery move;
  move.scene = "cornell_box_visq";
  move.node_name = "short_box";
  uint64_t last = 0;
  for (int i = 1; i <= 2; ++i) {
    move.world_matrix = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0.1 * i, 0, 0, 1};
    auto moved = RunSetNodeTransform(*engine, move);
    ASSERT_TRUE(moved.ok()) << moved.status();
    last = moved->version;
  }
  ObscuranceUpdateQuery update;
  update.scene = "cornell_box_visq";
  std::atomic<bool> cancelled{true};
  update.call.stop.cancelled = &cancelled;
  EXPECT_EQ(RunUpdateObscurances(*engine, update).status().code(), absl::StatusCode::kCancelled);
  cancelled = false;
  auto answer = RunUpdateObscurances(*engine, update);
  ASSERT_TRUE(answer.ok()) << answer.status();
  EXPECT_EQ(answer->from_version, baked->scene_version);
  EXPECT_EQ(answer->scene_version, last);
  EXPECT_EQ(answer->moves_applied, 2u);
  EXPECT_FALSE(answer->update.texels.empty()) << "moving the short box changes texels";
}

// Another replica replaces a scene over and over while this engine loads
// it from the shared repository: every load holds one upload's files (no
// .gltf of one with the .bin of another) and reports the version that
// upload was committed with.
TEST(Engine, LoadsRacingAnotherReplicasReplacesReadOneUploadEach) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  // Two uploads that differ in both files: the box, and the box scaled.
  Scene scaled = MakeCornellBox();
  for (glm::dvec3& p : scaled.positions) p *= 1.5;
  for (SceneMesh& mesh : scaled.meshes)
    for (glm::dvec3& p : mesh.positions) p *= 1.5;
  std::vector<std::map<std::string, std::string>> uploads(2);
  for (int k = 0; k < 2; ++k) {
    const std::filesystem::path folder = dir.path() / ("upload" + std::to_string(k));
    std::filesystem::create_directories(folder);
    ASSERT_TRUE(WriteGltfFile(k == 0 ? MakeCornellBox() : scaled, folder / "scene.gltf").ok());
    for (const auto& entry : std::filesystem::directory_iterator(folder)) {
      std::ifstream in(entry.path(), std::ios::binary);
      uploads[k][entry.path().filename().string()] =
          std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    }
    ASSERT_GE(uploads[k].size(), 2u) << "a .gltf and its .bin";
  }
  auto replica = SceneRepository::Open(dir.path() / "repo");
  ASSERT_TRUE(replica.ok()) << replica.status();
  auto store = [&](int k) -> StatusOr<uint64_t> {
    VISQ_ASSIGN_OR_RETURN(std::unique_ptr<UploadStaging> staging,
                          (*replica)->BeginUpload("racing", "scene.gltf", 1 << 26));
    for (const auto& [file, bytes] : uploads[k]) VISQ_RETURN_IF_ERROR(staging->Append(file, bytes));
    VISQ_ASSIGN_OR_RETURN(const SceneRepository::Stored stored, (*replica)->Commit(*staging, /*replace=*/true));
    return stored.version;
  };
  // Each upload's content, loaded with nothing racing.
  std::map<uint64_t, int> variant_of_version;
  std::vector<std::string> hash(2);
  for (int k = 0; k < 2; ++k) {
    auto version = store(k);
    ASSERT_TRUE(version.ok()) << version.status();
    variant_of_version[*version] = k;
    ASSERT_TRUE(engine->LoadFromRepository("racing", true).ok());
    hash[k] = (*engine->SceneForQuery("racing", 0))->content_hash;
  }
  ASSERT_NE(hash[0], hash[1]);

  std::mutex mutex;
  std::atomic<bool> writing{true};
  std::thread writer([&] {
    for (int i = 0; i < 150; ++i) {
      auto version = store(i % 2);
      ASSERT_TRUE(version.ok()) << version.status();
      std::lock_guard lock(mutex);
      variant_of_version[*version] = i % 2;
    }
    writing = false;
  });
  std::vector<std::pair<uint64_t, std::string>> seen;
  int failed = 0;
  while (writing) {
    auto loaded = engine->LoadFromRepository("racing", true);
    if (!loaded.ok()) {
      ++failed;  // UNAVAILABLE after four commits in a row: never a wrong answer
      continue;
    }
    auto resident = engine->SceneForQuery("racing", 0);
    ASSERT_TRUE(resident.ok());
    seen.emplace_back((*resident)->version, (*resident)->content_hash);
  }
  writer.join();
  size_t mixtures = 0, wrong_versions = 0;
  for (const auto& [version, content] : seen) {
    if (content != hash[0] && content != hash[1]) {
      ++mixtures;
      continue;
    }
    auto it = variant_of_version.find(version);
    wrong_versions += it == variant_of_version.end() || hash[it->second] != content;
  }
  EXPECT_GE(seen.size(), 10u) << failed << " loads failed";
  EXPECT_EQ(mixtures, 0u) << "of " << seen.size() << " loads";
  EXPECT_EQ(wrong_versions, 0u) << "of " << seen.size() << " loads";
  RecordProperty("loads", static_cast<int>(seen.size()));
}

// Node moves make versions and join the scene's edit log, each starting
// from the version the one before made; a reload starts the log afresh, and
// per-scene state of a query kind goes with an unload.
TEST(Engine, NodeMovesFormTheScenesEditLog) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  auto resident = engine->SceneForQuery("cornell_box_visq", 0);
  ASSERT_TRUE(resident.ok()) << resident.status();
  const uint64_t loaded = (*resident)->version;
  NodeTransformQuery move;
  move.scene = "cornell_box_visq";
  move.node_index = 0;
  std::vector<uint64_t> versions = {loaded};
  for (int i = 1; i <= 3; ++i) {
    move.world_matrix = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0.01 * i, 0, 0, 1};
    auto moved = RunSetNodeTransform(*engine, move);
    ASSERT_TRUE(moved.ok()) << moved.status();
    versions.push_back(moved->version);
  }
  const std::vector<SceneEdit> all = engine->EditsBetween("cornell_box_visq", loaded, versions.back());
  ASSERT_EQ(all.size(), 3u);
  for (size_t i = 0; i < all.size(); ++i) {
    EXPECT_EQ(all[i].from_version, versions[i]);
    EXPECT_EQ(all[i].version, versions[i + 1]);
    EXPECT_EQ(all[i].node, 0u);
    EXPECT_DOUBLE_EQ(all[i].world[3][0], 0.01 * double(i + 1));
  }
  const std::vector<SceneEdit> middle = engine->EditsBetween("cornell_box_visq", versions[1], versions[2]);
  ASSERT_EQ(middle.size(), 1u);
  EXPECT_EQ(middle[0].version, versions[2]);

  // An edit names its field when its input is bad, and logs nothing.
  move.world_matrix = {1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  auto singular = RunSetNodeTransform(*engine, move);
  EXPECT_EQ(singular.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(singular.status().message().find("world_matrix"), std::string::npos) << singular.status();
  move.node_index = 100000;
  move.world_matrix = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  EXPECT_EQ(RunSetNodeTransform(*engine, move).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(engine->EditsBetween("cornell_box_visq", loaded, UINT64_MAX).size(), 3u);

  // A move whose call was cancelled, or whose deadline passed, moves
  // nothing: the resident version and the log stay as they were.
  move.node_index = 0;
  std::atomic<bool> cancelled{true};
  move.call.stop = StopToken{&cancelled};
  EXPECT_EQ(RunSetNodeTransform(*engine, move).status().code(), absl::StatusCode::kCancelled);
  move.call.stop = StopToken{nullptr, std::chrono::steady_clock::now() - std::chrono::milliseconds(1)};
  EXPECT_EQ(RunSetNodeTransform(*engine, move).status().code(), absl::StatusCode::kDeadlineExceeded);
  EXPECT_EQ((*engine->SceneForQuery("cornell_box_visq", 0))->version, versions.back());
  EXPECT_EQ(engine->EditsBetween("cornell_box_visq", loaded, UINT64_MAX).size(), 3u);
  move.call = {};

  struct Counter {
    int value = 0;
  };
  engine->SceneStateOf<Counter>("cornell_box_visq")->value = 7;
  EXPECT_EQ(engine->SceneStateOf<Counter>("cornell_box_visq")->value, 7) << "one state per scene and kind";

  auto reloaded = engine->LoadFromRepository("cornell_box_visq", /*replace=*/true);
  ASSERT_TRUE(reloaded.ok()) << reloaded.status();
  EXPECT_TRUE(engine->EditsBetween("cornell_box_visq", 0, UINT64_MAX).empty()) << "a reload starts a new log";
  ASSERT_TRUE(engine->UnloadScene("cornell_box_visq", false).ok());
  EXPECT_EQ(engine->SceneStateOf<Counter>("cornell_box_visq")->value, 0) << "an unload drops the scene's state";
}

TEST(Engine, UnloadKeepsTheStoredSceneUnlessAskedToDelete) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  ASSERT_TRUE(engine->SceneForQuery("cornell_box_visq", 0).ok());
  auto deleted = engine->UnloadScene("cornell_box_visq", false);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_FALSE(*deleted);
  EXPECT_TRUE(engine->ListScenes().empty());
  EXPECT_TRUE(engine->SceneForQuery("cornell_box_visq", 0).ok()) << "still stored: loads again";
  deleted = engine->UnloadScene("cornell_box_visq", true);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_TRUE(*deleted);
  EXPECT_EQ(engine->SceneForQuery("cornell_box_visq", 0).status().code(), absl::StatusCode::kNotFound);
}

// A first-use load of one scene holds that name only: an unload of
// another scene returns while it runs. One lock for every name made the
// unload (and the metadata thread it ran on) wait the load out.
TEST(Engine, AFirstUseLoadHoldsOnlyItsOwnName) {
  testing::ScratchDir dir;
  const std::filesystem::path repo = dir.path() / "repo";
  std::filesystem::create_directories(repo);
  ASSERT_TRUE(WriteGltfFile(testing::MakeRippledGrid(1000), repo / "big_grid.gltf").ok());
  auto engine = StartEngine(repo);
  ASSERT_TRUE(engine);
  ASSERT_TRUE(engine->SceneForQuery("cornell_box_visq", 0).ok());

  using Clock = std::chrono::steady_clock;
  Clock::time_point load_start, load_end;
  std::atomic<bool> started{false};
  std::thread loader([&] {
    load_start = Clock::now();
    started = true;
    EXPECT_TRUE(engine->SceneForQuery("big_grid", 0).ok());
    load_end = Clock::now();
  });
  while (!started) std::this_thread::yield();
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  auto unloaded = engine->UnloadScene("cornell_box_visq", false);
  const Clock::time_point unload_end = Clock::now();
  loader.join();
  ASSERT_TRUE(unloaded.ok()) << unloaded.status();
  const double load_ms = std::chrono::duration<double, std::milli>(load_end - load_start).count();
  if (load_ms < 200.0) GTEST_SKIP() << "the 2M-triangle load took " << load_ms << " ms: too quick to overlap";
  EXPECT_LT(unload_end, load_end) << "the unload waited for another scene's load (" << load_ms << " ms)";
}

// The light over the tall box onto the floor beside it: partly shadowed.
HiddenSampleMapQuery ShadowedFloorQuery(VisibilityMethod method, int samples, int size) {
  HiddenSampleMapQuery query;
  query.scene = "cornell_box_visq";
  query.method = method;
  sampling::HiddenSampleMapRequest& r = query.request;
  r.source.patch = {{-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5}};
  r.source.sample_count = samples;
  r.receiver.patch = {{-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998}};
  r.receiver.width = size;
  r.receiver.height = size;
  r.options.want_bitmasks = method != VisibilityMethod::kPluckerExact;
  return query;
}

// With a sink, a map arrives a band of rows at a time, each band before the
// next is made, and the bands are the map answered whole, bit for bit. A
// sink that fails (the client went away) stops the map at that band.
TEST(Engine, HiddenSampleMapStreamsItsBandsAsTheyAreMade) {
  testing::ScratchDir dir;
  // 32 x 32 texels, 64 samples: one uvec4 layer, 512 bytes of read-back a
  // row, so 2 KiB bands hold 4 rows.
  auto engine = StartEngine(dir.path() / "repo", /*map_band_bytes=*/2 << 10);
  ASSERT_TRUE(engine);
  for (VisibilityMethod method : {VisibilityMethod::kRaster, VisibilityMethod::kRaycast,
                                  VisibilityMethod::kPluckerExact}) {
    SCOPED_TRACE(VisibilityMethodName(method, sampling::LookupMode::kExact));
    const HiddenSampleMapQuery query =
        ShadowedFloorQuery(method, method == VisibilityMethod::kPluckerExact ? 0 : 64, 32);
    auto whole = RunHiddenSampleMap(*engine, query);
    ASSERT_TRUE(whole.ok()) << whole.status();

    std::vector<float> fractions;
    std::vector<uint32_t> bits;
    int bands = 0;
    auto streamed = RunHiddenSampleMap(
        *engine, query, [&](const sampling::HiddenSampleMapResult& map, const sampling::HiddenSampleMapBand& band) {
          EXPECT_EQ(map.width, 32);
          EXPECT_EQ(band.first, fractions.size()) << "bands in order, none missing";
          EXPECT_TRUE(map.visible_fraction.empty()) << "a streamed map is never held whole";
          fractions.insert(fractions.end(), band.visible_fraction.begin(), band.visible_fraction.end());
          bits.insert(bits.end(), band.blocked_bits.begin(), band.blocked_bits.end());
          ++bands;
          return absl::OkStatus();
        });
    ASSERT_TRUE(streamed.ok()) << streamed.status();
    EXPECT_EQ(fractions, whole->result.visible_fraction);
    EXPECT_EQ(bits, whole->result.blocked_bits);
    EXPECT_TRUE(streamed->result.visible_fraction.empty());
    EXPECT_EQ(streamed->result.error.total(), whole->result.error.total());
    if (method == VisibilityMethod::kPluckerExact) {
      EXPECT_EQ(bands, 1) << "the exact method answers its points together";
      continue;
    }
    // RASTER: 8 bands of 4 rows; RAYCAST: bands of 4M segments, one here.
    if (method == VisibilityMethod::kRaster) {
      EXPECT_EQ(bands, 8);
    }

    int calls = 0;
    auto stopped = RunHiddenSampleMap(*engine, query,
                                      [&](const sampling::HiddenSampleMapResult&, const sampling::HiddenSampleMapBand&) {
                                        ++calls;
                                        return absl::CancelledError("the client went away");
                                      });
    EXPECT_EQ(stopped.status().code(), absl::StatusCode::kCancelled);
    EXPECT_EQ(calls, 1) << "no band is made after the sink failed";

    // The time a band waits in the sink (a slow reader of the stream) is
    // the transport's, not the work's: the answer's compute time leaves it
    // out, RASTER's and RAYCAST's alike (a RAYCAST map once counted its band
    // writes).
    constexpr double kSinkMs = 300.0;
    const double whole_ms = WorkTimingOf(*whole).compute_ms;
    int slow_bands = 0;
    auto slow = RunHiddenSampleMap(*engine, query,
                                   [&](const sampling::HiddenSampleMapResult&, const sampling::HiddenSampleMapBand&) {
                                     ++slow_bands;
                                     std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(
                                         kSinkMs / (method == VisibilityMethod::kRaster ? 8 : 1)));
                                     return absl::OkStatus();
                                   });
    ASSERT_TRUE(slow.ok()) << slow.status();
    EXPECT_LT(WorkTimingOf(*slow).compute_ms, whole_ms + 0.5 * kSinkMs)
        << slow_bands << " bands, each held in the sink; the whole map computed in " << whole_ms << " ms";
  }
}

// Each texel's own bound (jittered samples, one per equal-area cell) holds
// against the exact method for at least the stated share of texels, and is
// far tighter than Hoeffding's worst case where the texel's samples agree.
TEST(Engine, PerTexelBoundsHoldAgainstTheExactMethod) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  const HiddenSampleMapQuery exact_query = ShadowedFloorQuery(VisibilityMethod::kPluckerExact, 0, 48);
  auto exact = RunHiddenSampleMap(*engine, exact_query);
  ASSERT_TRUE(exact.ok()) << exact.status();
  for (VisibilityMethod method : {VisibilityMethod::kRaster, VisibilityMethod::kRaycast}) {
    for (int samples : {64, 256}) {
      HiddenSampleMapQuery query = ShadowedFloorQuery(method, samples, 48);
      query.request.options.want_bitmasks = false;
      query.request.source.pattern = sampling::SamplePattern::kJittered;
      size_t outside = 0, penumbra = 0;
      double hoeffding = 0.0, widest = 0.0;
      std::vector<double> penumbra_bounds, penumbra_errors;
      for (uint64_t seed = 1; seed <= 4; ++seed) {
        query.request.source.seed = seed;
        auto map = RunHiddenSampleMap(*engine, query);
        ASSERT_TRUE(map.ok()) << map.status();
        const sampling::ErrorBound& error = map->result.error;
        ASSERT_TRUE(error.has_per_texel);
        ASSERT_EQ(error.per_texel.size(), exact->result.visible_fraction.size());
        hoeffding = error.sampling;
        widest = std::max(widest, error.per_texel_max);
        for (size_t j = 0; j < error.per_texel.size(); ++j) {
          const double truth = exact->result.visible_fraction[j];
          const double answer = map->result.visible_fraction[j];
          if (std::abs(answer - truth) > error.per_texel[j] + 1e-6) ++outside;
          if (truth > 0.02 && truth < 0.98) {
            ++penumbra;
            penumbra_bounds.push_back(error.per_texel[j]);
            penumbra_errors.push_back(std::abs(answer - truth));
          }
        }
      }
      const size_t texels = 4 * exact->result.visible_fraction.size();
      auto median = [](std::vector<double> v) {
        std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
        return v[v.size() / 2];
      };
      std::printf("%s, %d samples: %zu of %zu texels outside their bound; widest %.4f (Hoeffding %.4f); "
                  "penumbra (%zu texels): median bound %.4f, median error %.4f\n",
                  VisibilityMethodName(method, sampling::LookupMode::kExact).c_str(), samples, outside, texels,
                  widest, hoeffding, penumbra, median(penumbra_bounds), median(penumbra_errors));
      EXPECT_LE(double(outside), 0.05 * double(texels));
      EXPECT_LE(widest, hoeffding) << "never looser than the worst case";
      ASSERT_GT(penumbra, 20u) << "the placement must have a penumbra";
    }
  }
}

// Beyond one map's 4096 samples: several maps with independent jitter, their
// counts added. The answer states the total, its per-texel bounds hold
// against the exact method and are tighter than one map's; what cannot be
// spread over maps is refused by name.
TEST(Engine, MoreSamplesThanOneMapHoldsAreSeveralMaps) {
  testing::ScratchDir dir;
  auto engine = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(engine);
  auto exact = RunHiddenSampleMap(*engine, ShadowedFloorQuery(VisibilityMethod::kPluckerExact, 0, 24));
  ASSERT_TRUE(exact.ok()) << exact.status();
  for (VisibilityMethod method : {VisibilityMethod::kRaster, VisibilityMethod::kRaycast}) {
    HiddenSampleMapQuery one_map = ShadowedFloorQuery(method, 4096, 24);
    one_map.request.options.want_bitmasks = false;
    one_map.request.source.pattern = sampling::SamplePattern::kJittered;
    HiddenSampleMapQuery four_maps = one_map;
    four_maps.request.source.sample_count = 16384;
    auto one = RunHiddenSampleMap(*engine, one_map);
    auto four = RunHiddenSampleMap(*engine, four_maps);
    ASSERT_TRUE(one.ok()) << one.status();
    ASSERT_TRUE(four.ok()) << four.status();
    EXPECT_EQ(four->result.sample_count, 16384);
    EXPECT_EQ(four->result.samples.world.size(), 16384u);
    ASSERT_TRUE(four->result.error.has_per_texel);
    EXPECT_LT(four->result.error.per_texel_max, 0.6 * one->result.error.per_texel_max);
    size_t outside = 0;
    for (size_t j = 0; j < exact->result.visible_fraction.size(); ++j)
      if (std::abs(four->result.visible_fraction[j] - exact->result.visible_fraction[j]) >
          four->result.error.per_texel[j] + 1e-6)
        ++outside;
    EXPECT_LE(outside, exact->result.visible_fraction.size() / 20);
    std::printf("%s: 4096 samples widest bound %.4f, 16384 (4 maps) %.4f; %zu texels outside\n",
                VisibilityMethodName(method, sampling::LookupMode::kExact).c_str(), one->result.error.per_texel_max,
                four->result.error.per_texel_max, outside);
  }
  HiddenSampleMapQuery bitmasks = ShadowedFloorQuery(VisibilityMethod::kRaster, 8192, 8);
  bitmasks.request.source.pattern = sampling::SamplePattern::kJittered;
  auto refused = RunHiddenSampleMap(*engine, bitmasks);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted) << refused.status();
  EXPECT_NE(std::string(refused.status().message()).find("samples.count"), std::string::npos) << refused.status();
  HiddenSampleMapQuery too_many = ShadowedFloorQuery(VisibilityMethod::kRaster, kMaxPlannedSamples + 1, 8);
  too_many.request.options.want_bitmasks = false;
  EXPECT_EQ(RunHiddenSampleMap(*engine, too_many).status().code(), absl::StatusCode::kResourceExhausted);
}


// A target's sampled plans are predicted by the cost model: probed once per
// scene and method, updated by every run, and kept across a restart in the
// repository, so the restarted engine predicts what the first measured and
// probes no sampled method again. The exact plan is predicted from probes of
// each request's own points on its own trees (its cost per point follows the
// light and the penumbra, not the scene alone); its work is what its new
// trees' shafts hold and its points: none of the first once the probes built
// its trees.
TEST(Engine, CostModelLearnsFromEachRunAndOutlivesARestart) {
  testing::ScratchDir dir;
  HiddenSampleMapQuery query = ShadowedFloorQuery(VisibilityMethod::kRaster, 0, 32);
  query.request.options.want_bitmasks = false;
  query.target = AccuracyTarget{.max_error = 0.05, .confidence = 0.95};
  struct Predicted {
    std::string key;
    double work, extra, ms;
  };
  std::vector<Predicted> predicted;  // the first engine's predictions
  std::map<std::string, size_t> observations;
  {
    auto engine = StartEngine(dir.path() / "repo");
    ASSERT_TRUE(engine);
    auto first = RunHiddenSampleMap(*engine, query);
    ASSERT_TRUE(first.ok()) << first.status();
    ASSERT_TRUE(first->plan);
    EXPECT_GT(first->plan->probe_ms, 0.0);
    bool saw_exact = false;
    for (const Plan& plan : first->plan->plans) {
      if (plan.method != "plucker-exact") {
        EXPECT_GE(engine->cost_model().Observations(plan.cost_key), 1u) << plan.cost_key;
      }
      if (plan.method == "plucker-exact") {
        saw_exact = true;
        // The probes answered some of the map's own points on the map's own
        // trees: no tree is left to build, and those points are stored.
        EXPECT_EQ(plan.work, 0.0) << "the probes built the map's trees";
        EXPECT_GT(plan.extra_work, 0.0);
        EXPECT_LT(plan.extra_work, 32.0 * 32.0) << "the probes' points are answered from the trees' stores";
      }
    }
    EXPECT_TRUE(saw_exact);
    // The chosen plan's run is one more observation of its series.
    const Plan& chosen = first->plan->chosen_plan();
    const size_t before = engine->cost_model().Observations(chosen.cost_key);
    std::map<std::string, size_t> sampled_before;
    for (const Plan& plan : first->plan->plans)
      if (plan.method != "plucker-exact") sampled_before[plan.cost_key] = engine->cost_model().Observations(plan.cost_key);
    auto second = RunHiddenSampleMap(*engine, query);
    ASSERT_TRUE(second.ok()) << second.status();
    const std::string& second_key = second->plan->chosen_plan().cost_key;
    for (const auto& [key, count] : sampled_before)
      EXPECT_EQ(engine->cost_model().Observations(key), std::min<size_t>(count + (key == second_key ? 1 : 0), 16))
          << key << ": a sampled method is probed once per scene";
    if (second_key == chosen.cost_key) {
      EXPECT_EQ(engine->cost_model().Observations(chosen.cost_key), std::min<size_t>(before + 1, 16))
          << "a run updates its series";
    }
    for (const Plan& plan : second->plan->plans) {
      if (plan.method == "plucker-exact") {
        if (chosen.method == "plucker-exact") {
          EXPECT_EQ(plan.work, 0.0) << "the first call left the map's trees cached";
        }
        continue;
      }
      const std::optional<double> p = engine->cost_model().Predict(plan.cost_key, plan.work, plan.extra_work);
      ASSERT_TRUE(p);
      predicted.push_back({plan.cost_key, plan.work, plan.extra_work, *p});
      observations[plan.cost_key] = engine->cost_model().Observations(plan.cost_key);
    }
  }
  EXPECT_TRUE(std::filesystem::exists(dir.path() / "repo" / ".visq-cost-model.tsv"));

  auto restarted = StartEngine(dir.path() / "repo");
  ASSERT_TRUE(restarted);
  for (const auto& [key, count] : observations) EXPECT_EQ(restarted->cost_model().Observations(key), count) << key;
  // Before the restarted engine runs anything (a run records into its series).
  for (const Predicted& p : predicted)
    EXPECT_DOUBLE_EQ(*restarted->cost_model().Predict(p.key, p.work, p.extra), p.ms) << p.key;
  auto third = RunHiddenSampleMap(*restarted, query);
  ASSERT_TRUE(third.ok()) << third.status();
  const std::string& third_key = third->plan->chosen_plan().cost_key;
  for (const auto& [key, count] : observations)
    EXPECT_EQ(restarted->cost_model().Observations(key), std::min<size_t>(count + (key == third_key ? 1 : 0), 16))
        << key << ": the restarted engine probed a sampled method again";
}

}  // namespace
}  // namespace visq::core

// ---------------------------------------------------------------------------
// Structures built on first use: once, off every lock that metadata takes,
// each waiter stopping at its own deadline, a failure built again.

namespace visq::core {
namespace {

// A repository with the sample scenes and `name`: a grid of 2 cells^2
// triangles whose BVH takes a while to build.
std::unique_ptr<Engine> StartEngineWithGrid(const std::filesystem::path& repo, const std::string& name, int cells,
                                            uint64_t lose_context_at_job = 0) {
  EXPECT_TRUE(WriteSampleScenes(repo).ok());
  EXPECT_TRUE(WriteGltfFile(testing::MakeRippledGrid(cells), repo / (name + ".glb")).ok());
  EngineOptions options;
  options.scene_repo = repo;
  options.load_repository_at_start = false;
  options.gpu.lose_context_at_job = lose_context_at_job;
  auto engine = Engine::Create(options);
  EXPECT_TRUE(engine.ok()) << engine.status();
  return engine.ok() ? std::move(*engine) : nullptr;
}

BuildTimes::Figures BuildFigures(const Engine& engine, const std::string& kind) {
  const auto all = engine.build_times().Snapshot();
  auto it = all.find(kind);
  return it == all.end() ? BuildTimes::Figures{} : it->second;
}

// Waits (for a hang, not a time) until `kind` is being built.
void AwaitBuildInProgress(const Engine& engine, const std::string& kind) {
  const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (BuildFigures(engine, kind).in_progress == 0 && BuildFigures(engine, kind).count == 0 &&
         std::chrono::steady_clock::now() < give_up)
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
}

// Each test's engine, over a repository holding the grid, which is made
// resident.
class EngineStructures : public ::testing::Test {
 protected:
  void Start(int cells, uint64_t lose_context_at_job = 0) {
    engine_ = StartEngineWithGrid(dir_.path() / "repo", "grid", cells, lose_context_at_job);
    ASSERT_TRUE(engine_);
    auto resident = engine_->SceneForQuery("grid", 0);
    ASSERT_TRUE(resident.ok()) << resident.status();
    resident_ = *resident;
  }

  testing::ScratchDir dir_;
  std::unique_ptr<Engine> engine_;
  std::shared_ptr<const ResidentScene> resident_;
};

TEST_F(EngineStructures, ConcurrentFirstUsersShareOneBuild) {
  ASSERT_NO_FATAL_FAILURE(Start(500));
  constexpr int kCallers = 6;
  std::vector<std::shared_ptr<raycast::EmbreeScene>> bvhs(kCallers);
  std::vector<std::shared_ptr<const exact::SceneTriangleIndex>> indices(kCallers);
  std::vector<std::thread> callers;
  for (int i = 0; i < kCallers; ++i)
    callers.emplace_back([&, i] {
      auto bvh = engine_->EmbreeSceneOf(*resident_);
      auto index = engine_->TriangleIndexOf(*resident_);
      EXPECT_TRUE(bvh.ok()) << bvh.status();
      EXPECT_TRUE(index.ok()) << index.status();
      if (bvh.ok()) bvhs[i] = *bvh;
      if (index.ok()) indices[i] = *index;
    });
  for (std::thread& t : callers) t.join();
  for (int i = 1; i < kCallers; ++i) {
    EXPECT_EQ(bvhs[i], bvhs[0]) << "caller " << i;
    EXPECT_EQ(indices[i], indices[0]) << "caller " << i;
  }
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").count, 1u);
  EXPECT_EQ(BuildFigures(*engine_, "triangle_index").count, 1u);
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").in_progress, 0u);
}

TEST_F(EngineStructures, WaitersStopAtTheirDeadlineOrCancelWhileTheBuildGoesOn) {
  // 2M triangles: a BVH build of a good fraction of a second on 2 cores.
  ASSERT_NO_FATAL_FAILURE(Start(1000));

  // The first user gives up at once: the build it started goes on.
  std::atomic<bool> cancelled{true};
  CallOptions gave_up{StopToken{&cancelled}, std::make_shared<BuildClock>()};
  EXPECT_EQ(engine_->EmbreeSceneOf(*resident_, gave_up).status().code(), absl::StatusCode::kCancelled);
  AwaitBuildInProgress(*engine_, "embree_bvh");
  ASSERT_EQ(BuildFigures(*engine_, "embree_bvh").in_progress, 1u) << "the build should still be running";

  // Meanwhile: a waiter past its deadline and a cancelled one return, and
  // metadata answers, all before the build ends.
  CallOptions expired{StopToken{nullptr, std::chrono::steady_clock::now() + std::chrono::milliseconds(1)},
                      std::make_shared<BuildClock>()};
  EXPECT_EQ(engine_->EmbreeSceneOf(*resident_, expired).status().code(), absl::StatusCode::kDeadlineExceeded);
  EXPECT_EQ(engine_->EmbreeSceneOf(*resident_, gave_up).status().code(), absl::StatusCode::kCancelled);
  auto summary = engine_->GetScene("grid", false);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->cpu_bytes, resident_->scene->CpuBytes()) << "no BVH counted before it is built";
  EXPECT_EQ(engine_->ListScenes().size(), 1u);
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").in_progress, 1u)
      << "the waiters and metadata calls must have returned while the build ran";
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").count, 0u);

  // A patient caller gets the one BVH, and its wait is build time.
  CallOptions patient{StopToken{}, std::make_shared<BuildClock>()};
  auto bvh = engine_->EmbreeSceneOf(*resident_, patient);
  ASSERT_TRUE(bvh.ok()) << bvh.status();
  EXPECT_GT(patient.BuildMs(), 0.0);
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").count, 1u);
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").failures, 0u);
  summary = engine_->GetScene("grid", false);
  ASSERT_TRUE(summary.ok());
  EXPECT_EQ(summary->cpu_bytes, resident_->scene->CpuBytes() + (*bvh)->memory_bytes());

  // Built: no wait, no build time, no second build.
  CallOptions later{StopToken{}, std::make_shared<BuildClock>()};
  auto again = engine_->EmbreeSceneOf(*resident_, later);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->get(), bvh->get());
  EXPECT_EQ(later.BuildMs(), 0.0);
  EXPECT_EQ(BuildFigures(*engine_, "embree_bvh").count, 1u);
}

TEST_F(EngineStructures, AFailedBuildIsBuiltAgainByTheNextCall) {
  // GPU jobs: 1 the self-test, 2 the first upload, which loses the context.
  ASSERT_NO_FATAL_FAILURE(Start(8, /*lose_context_at_job=*/2));
  auto lost = engine_->GpuSceneOf(*resident_);
  EXPECT_EQ(lost.status().code(), absl::StatusCode::kInternal) << lost.status();
  EXPECT_EQ(BuildFigures(*engine_, "gpu_upload").failures, 1u);
  EXPECT_EQ(engine_->GetScene("grid", false)->gpu_bytes, 0u);
  auto uploaded = engine_->GpuSceneOf(*resident_);
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  EXPECT_TRUE((*uploaded)->IsCurrent());
  EXPECT_EQ(BuildFigures(*engine_, "gpu_upload").count, 1u);
  EXPECT_EQ(engine_->GetScene("grid", false)->gpu_bytes, (*uploaded)->gpu_bytes());
}

TEST_F(EngineStructures, LightVisibilityCountsItsIndexBuildApartFromCompute) {
  ASSERT_NO_FATAL_FAILURE(Start(300));
  LightVisibilityQuery query;
  query.scene = "grid";
  query.light.vertices = {{-0.1, 1, -0.1}, {0.1, 1, -0.1}, {0.1, 1, 0.1}, {-0.1, 1, 0.1}};
  query.points = {{glm::dvec3(0.3, 0.05, 0.3), glm::dvec3(0, 1, 0), std::nullopt}};
  query.call.build_clock = std::make_shared<BuildClock>();
  auto first = RunLightVisibility(*engine_, query);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_GT(query.call.BuildMs(), 0.0) << "the first call builds the triangle index";
  EXPECT_EQ(BuildFigures(*engine_, "triangle_index").count, 1u);
  query.call.build_clock = std::make_shared<BuildClock>();
  ASSERT_TRUE(RunLightVisibility(*engine_, query).ok());
  EXPECT_EQ(query.call.BuildMs(), 0.0);
  EXPECT_EQ(BuildFigures(*engine_, "triangle_index").count, 1u);
}

}  // namespace
}  // namespace visq::core
