// The core API of visq: resident scenes and the queries on them. The gRPC
// service is a thin layer over this class; nothing here knows protobuf.
#pragma once

#include <any>
#include <atomic>
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <memory>
#include <shared_mutex>
#include <span>
#include <string>
#include <typeindex>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "core/absorber_rays_cache.h"
#include "core/accuracy_planner.h"
#include "core/call_options.h"
#include "core/idle_exploration.h"
#include "core/lazy_structure.h"
#include "core/local_frames.h"
#include "core/scene_repository.h"
#include "core/structure_estimate.h"
#include "core/work_budget.h"
#include "exact/light_visibility.h"
#include "raycast/embree_scene.h"
#include "scene/gltf_loader.h"
#include "scene/scene.h"
#include "visq/gpu/gpu_scene.h"
#include "visq/gpu/hidden_sample_map.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::core {

// One node move of a resident scene: what its edit log holds, and what a
// query that keeps a solution across versions (the obscurance updater)
// replays.
struct SceneEdit {
  uint64_t from_version = 0;  // the scene version the move was made on
  uint64_t version = 0;       // the scene version this move made
  uint32_t node = 0;
  glm::dmat4 world{1.0};      // the node's new world matrix (its subtree follows)
};

// A scene's log keeps this many edits; a solution older than the oldest can
// no longer be replayed forward (and says so).
inline constexpr size_t kMaxSceneEdits = 1 << 16;

// The structures a scene builds on first use, which a load may ask to build
// at once (warm) instead.
enum class StructureKind { kGpuBuffers, kEmbreeBvh, kTriangleIndex };
inline constexpr StructureKind kEveryStructure[] = {StructureKind::kGpuBuffers, StructureKind::kEmbreeBvh,
                                                     StructureKind::kTriangleIndex};

struct EngineOptions {
  std::filesystem::path scene_repo = "/var/lib/visq/scenes";
  // Where the repository's catalog is and this replica's name in it
  // (RepositoryOptions::catalog, ::replica_id).
  std::string catalog;
  std::string replica_id;
  gpu::GpuOptions gpu;
  uint64_t max_upload_bytes = 4ull << 30;
  // A scene whose geometry and every structure its queries may build
  // (core/structure_estimate.h) would exceed this is refused
  // (RESOURCE_EXHAUSTED), before it displaces anything.
  uint64_t max_scene_bytes = 8ull << 30;
  // Whether the server's choice and the accuracy planner weigh GPU_RAYCAST:
  // "auto" on a GPU only (Engine::WeighsGpuRays), "always", or "never".
  std::string gpu_rays_in_choice = "auto";
  // Build every structure (GPU buffers, Embree BVH, triangle index) of each
  // scene loaded or uploaded, in the background right after the load, so
  // that its first query does not wait for them.
  bool warm_at_load = false;
  // Bound on the exact light-visibility trees kept (LRU beyond it).
  size_t light_cache_bytes = 256ull << 20;
  // LightVisibility batches without a receiver_region: 0 groups them by the
  // batch and its occluders (exact::GroupReceiversByShaft: the points' box,
  // halved while its shaft meets more than light_shaft_triangles triangles);
  // N > 0 into cubes of the scene's largest extent / N, one tree each
  // (exact::GroupReceivers), which later batches over the same surfaces
  // find again.
  int light_receiver_cells = 0;
  size_t light_shaft_triangles = 20000;
  // ... and no group has fewer points than this unless the batch has (a cube
  // with fewer gives them to its parent cube): a sparse batch shares a few trees.
  uint32_t light_receiver_min_points = 64;
  // LightVisibility requests without a shadow_tolerance of their own
  // (exact::TreeOptions::shadow_tolerance): a millionth of the light, far
  // below what any lightmap stores, is enough for needles and wires.
  double light_shadow_tolerance = 1e-6;
  // Load every scene of the repository at start (resident from the first
  // request on). Either way, a request naming a scene that is stored but not
  // resident loads it first (replicas sharing one repository rely on this).
  bool load_repository_at_start = true;
  // Memory that answers in progress may hold together (WorkMemoryBudget);
  // 0: half of the machine's physical memory.
  uint64_t max_work_bytes = 0;
  // How large a band of a hidden-sample map may be (its GPU read-back):
  // smaller bands reach the client sooner and give other queries the GL
  // thread sooner.
  gpu::HiddenSampleMapperOptions hidden_sample_map;
  // Where the accuracy planner's cost model keeps its observations across
  // restarts (CostModel::PersistTo); empty: <scene_repo>/.visq-cost-model.tsv,
  // which the repository's scene listing skips. "-": nowhere.
  std::filesystem::path cost_model_file;
  // Probes of the server's choice that no request could pay for run while
  // no call is in flight (core/idle_exploration.h); off, a request probes a
  // new method only with the share it can pay or that earlier requests set
  // aside.
  bool explore_when_idle = true;
  IdleExplorationOptions idle_exploration;
};

// A scene as the server holds it: immutable geometry plus the lazily built
// structures queries add. A new version is a new ResidentScene.
struct ResidentScene {
  std::string name;
  uint64_t version = 0;
  std::shared_ptr<const Scene> scene;
  std::string content_hash;
  std::vector<std::string> dropped;
  double load_ms = 0;
  bool persisted = false;

  uint32_t emissive_triangles = 0;
  StructureEstimate estimate;  // what --max-scene-bytes admitted it by

  // Structures built on first use by the queries that need them (or at
  // load, when warmed), and only then: a scene that is never queried on the
  // GPU never costs GPU memory. Each is built once, outside any lock that
  // metadata calls take (core/lazy_structure.h).
  mutable LazyStructure<gpu::GpuScene> gpu_scene;
  mutable LazyStructure<raycast::EmbreeScene> embree_scene;
  mutable LazyStructure<gpu::RayScene> ray_scene;  // GPU_RAYCAST's BVH
  mutable LazyStructure<const exact::SceneTriangleIndex> triangle_index;  // for exact light trees and local frames
  mutable LocalFrames local_frames;  // for sampled queries far from the scene's centre
  mutable AbsorberRaysCache absorber_rays;  // Transmittance's RAY_STABBING
};

// The scene a probe left to idle time runs on, which it holds weakly so
// that a scene unloaded or replaced meanwhile is not kept in memory for it:
// FAILED_PRECONDITION (the probe cannot answer) once nothing else holds it.
[[nodiscard]] StatusOr<std::shared_ptr<const ResidentScene>> StillHeld(const std::weak_ptr<const ResidentScene>& scene);

// A ResidentScene of `scene` under `name`, with what is derived from the
// geometry once (hash, emissive count, estimate); no version yet.
std::shared_ptr<ResidentScene> NewResidentScene(std::string name, Scene scene);

struct SceneSummary {
  std::string name;
  uint64_t version = 0;
  uint64_t triangles = 0;
  uint64_t vertices = 0;
  Bounds bounds;
  std::string content_hash;
  uint64_t cpu_bytes = 0;
  uint64_t gpu_bytes = 0;
  StructureEstimate estimate;  // every structure built
  uint32_t materials = 0;
  uint32_t emissive_triangles = 0;
  bool has_lightmap_uvs = false;
  std::vector<std::string> dropped;
  double load_ms = 0;
  bool persisted = false;
  std::vector<SceneNode> nodes;  // filled on request
};

// An upload in progress: chunks are written to the repository's staging
// area; Finish() parses, stores atomically and makes the scene resident.
class SceneUpload {
 public:
  [[nodiscard]] Status Append(absl::string_view file, absl::string_view data) { return staging_->Append(file, data); }
  uint64_t bytes() const { return staging_->bytes(); }

 private:
  friend class Engine;
  std::unique_ptr<UploadStaging> staging_;
  bool replace_ = false;
  uint64_t expected_bytes_ = 0;  // 0: not announced
};

// How long the structures built on first use took, per kind ("scene_load",
// "gpu_upload", "embree_bvh", "triangle_index"), and how many are being
// built: for GetStats and /metrics.
class BuildTimes {
 public:
  struct Figures {
    uint64_t count = 0;  // finished builds
    uint64_t failures = 0;
    uint32_t in_progress = 0;
    double total_ms = 0;  // of the finished builds
    double max_ms = 0;
  };
  // A build that was not counted as started.
  void Record(const std::string& kind, double ms);
  void Started(const std::string& kind);
  void Finished(const std::string& kind, double ms, bool ok);
  std::map<std::string, Figures> Snapshot() const;

 private:
  mutable std::mutex mutex_;
  std::map<std::string, Figures> kinds_;
};

class Engine {
 public:
  // Opens the repository and starts the GL thread; does not load scenes yet
  // (LoadRepositoryScenes), so the server can report NOT_SERVING meanwhile.
  [[nodiscard]] static StatusOr<std::unique_ptr<Engine>> Create(const EngineOptions& options);
  ~Engine();

  // Loads every scene in the repository; a scene that fails to load is
  // logged and skipped, never fatal.
  void LoadRepositoryScenes();

  [[nodiscard]] StatusOr<SceneSummary> LoadFromRepository(absl::string_view name, bool replace);
  [[nodiscard]] StatusOr<std::unique_ptr<SceneUpload>> BeginUpload(absl::string_view name,
                                                                   absl::string_view main_file, bool replace,
                                                                   uint64_t expected_bytes);
  // Commits a complete upload: every announced byte arrived, and the call
  // still wants it (asked again just before the commit: a client whose
  // deadline passed was told the upload failed). Anything else leaves the
  // repository as it was.
  [[nodiscard]] StatusOr<SceneSummary> FinishUpload(std::unique_ptr<SceneUpload> upload, const StopToken& stop = {});

  std::vector<SceneSummary> ListScenes() const;
  [[nodiscard]] StatusOr<SceneSummary> GetScene(absl::string_view name, bool with_nodes, bool load_if_stored = false);
  // Returns whether the scene was also deleted from the repository.
  [[nodiscard]] StatusOr<bool> UnloadScene(absl::string_view name, bool delete_from_repository);

  // The resident scene for a query, loaded first from the repository when
  // it is stored but not resident and `load_if_stored` (queries pass it;
  // replicas sharing a repository rely on it): NOT_FOUND if unknown,
  // FAILED_PRECONDITION if `version` is non-zero and not the resident one.
  [[nodiscard]] StatusOr<std::shared_ptr<const ResidentScene>> SceneForQuery(absl::string_view name, uint64_t version,
                                                                         bool load_if_stored = true);
  // Moves node `pick_node(scene)` (and its subtree) to `world` in a copy of
  // the resident scene `name` and makes the copy resident as the next
  // version, in memory only, appending the move to the scene's edit log.
  // Edits of the engine's scenes are one at a time, so each logged edit
  // starts from the version the one before it made. A `stop` that stopped
  // before the copy is made resident leaves the scene as it was.
  [[nodiscard]] StatusOr<SceneSummary> MoveNode(absl::string_view name, uint64_t version,
                                                const std::function<StatusOr<uint32_t>(const Scene&)>& pick_node,
                                                const glm::dmat4& world, const StopToken& stop = {});
  // The edits of `scene` that made versions after `after_version`, up to
  // and including `up_to_version`, in order. A load, reload or unload of the
  // scene clears its log.
  std::vector<SceneEdit> EditsBetween(absl::string_view scene, uint64_t after_version, uint64_t up_to_version) const;

  // State that a query kind keeps per scene name (the obscurance updater's
  // solution), created on first use and dropped with the scene when it is
  // unloaded. The engine holds it without knowing its type.
  template <typename State>
  std::shared_ptr<State> SceneStateOf(absl::string_view scene) {
    std::lock_guard lock(scene_states_mutex_);
    std::any& slot = scene_states_[{std::string(scene), std::type_index(typeid(State))}];
    if (!slot.has_value()) slot = std::make_shared<State>();
    return std::any_cast<std::shared_ptr<State>>(slot);
  }

  // The scene's GPU buffers, Embree BVH and triangle index: built once, by
  // the first call that needs them (on a thread of the build's own), the
  // calls meanwhile waiting for that build until their deadline or
  // cancellation (`call`, whose build clock gets the time waited).
  [[nodiscard]] StatusOr<std::shared_ptr<gpu::GpuScene>> GpuSceneOf(const ResidentScene& resident,
                                                                    const CallOptions& call = {});
  [[nodiscard]] StatusOr<std::shared_ptr<raycast::EmbreeScene>> EmbreeSceneOf(const ResidentScene& resident,
                                                                              const CallOptions& call = {});
  [[nodiscard]] StatusOr<std::shared_ptr<gpu::RayScene>> RaySceneOf(const ResidentScene& resident,
                                                                     const CallOptions& call = {});
  [[nodiscard]] StatusOr<std::shared_ptr<const exact::SceneTriangleIndex>> TriangleIndexOf(
      const ResidentScene& resident, const CallOptions& call = {});
  // Starts building `kinds` of the resident scene `name` at `version` in the
  // background, unless built or being built already; returns at once.
  // NOT_FOUND when that version is no longer resident.
  [[nodiscard]] Status Warm(absl::string_view name, uint64_t version, std::span<const StructureKind> kinds);
  // The float32 copy of the scene that resolves `request` as RASTER
  // (GpuSceneFor) or RAYCAST (EmbreeSceneFor) trace it: the scene's own when
  // it does, else the local frame of the query's region (core/local_frames.h).
  // FAILED_PRECONDITION, naming the end, when neither does.
  [[nodiscard]] StatusOr<std::shared_ptr<gpu::GpuScene>> GpuSceneFor(const ResidentScene& resident,
                                                                     const sampling::HiddenSampleMapRequest& request,
                                                                     const CallOptions& call = {});
  [[nodiscard]] StatusOr<std::shared_ptr<raycast::EmbreeScene>> EmbreeSceneFor(
      const ResidentScene& resident, const sampling::HiddenSampleMapRequest& request, const CallOptions& call = {});
  // Whether the server's choice weighs GPU_RAYCAST: only on a GPU. On a
  // CPU rasterizer its shader runs on the cores Embree would use, at 9-26x
  // Embree's time (visq_bench_rays --quick, llvmpipe on 2 cores), so probing
  // it would cost a flattened BVH and a probe per scene for nothing; named,
  // it runs there too.
  bool WeighsGpuRays() const;
  // Whether GPU_RAYCAST's BVH (built on first use, every placement
  // flattened) fits beside the scene's other structures under
  // --max-scene-bytes: FAILED_PRECONDITION naming the method when not, so
  // that the server's choice leaves the method out.
  [[nodiscard]] Status AdmitRayScene(const ResidentScene& resident) const;
  // GPU_RAYCAST's, which traces RAYCAST's segments in the same frame.
  [[nodiscard]] StatusOr<std::shared_ptr<gpu::RayScene>> RaySceneFor(const ResidentScene& resident,
                                                                     const sampling::HiddenSampleMapRequest& request,
                                                                     const CallOptions& call = {});
  // The same decision without building either copy: for the planner.
  [[nodiscard]] Status ValidateSampledPrecision(const ResidentScene& resident,
                                             const sampling::HiddenSampleMapRequest& request,
                                             sampling::SegmentTracer tracer, const CallOptions& call = {});
  // The hidden-sample map's programs, compiled on first use.
  [[nodiscard]] StatusOr<gpu::HiddenSampleMapper*> hidden_sample_mapper();

  exact::LightVisibilityCache& light_cache() { return *light_cache_; }
  WorkMemoryBudget& work_budget() { return *work_budget_; }
  // A LightVisibility request's use of the cache: a hit when every tree it
  // used was cached, a miss when it built any.
  void RecordLightTreeUse(bool built_any) { (built_any ? light_tree_misses_ : light_tree_hits_).fetch_add(1); }
  struct LightCacheStats {
    size_t entries = 0;
    size_t bytes = 0;
    size_t capacity_bytes = 0;
    uint64_t hits = 0, misses = 0, evictions = 0;
  };
  LightCacheStats light_cache_stats() const {
    return {light_cache_->size(),      light_cache_->bytes(),      options_.light_cache_bytes,
            light_tree_hits_.load(),   light_tree_misses_.load(), light_cache_->evictions()};
  }
  int light_receiver_cells() const { return options_.light_receiver_cells; }
  size_t light_shaft_triangles() const { return options_.light_shaft_triangles; }
  uint32_t light_receiver_min_points() const { return options_.light_receiver_min_points; }
  double light_shadow_tolerance() const { return options_.light_shadow_tolerance; }

  const GpuDeviceInfo& device() const { return gpu_->device(); }
  gpu::GpuWorker& gpu() { return *gpu_; }
  SceneRepository& repository() { return *repository_; }
  // Measured costs of the query methods, for AccuracyTarget requests.
  CostModel& cost_model() { return cost_model_; }
  // Null when the server does not explore in its idle time.
  IdleExplorer* idle_explorer() { return idle_explorer_.get(); }
  const IdleExplorer* idle_explorer() const { return idle_explorer_.get(); }
  const BuildTimes& build_times() const { return build_times_; }

 private:
  Engine() = default;
  // The stored version `stored` (checked out of the repository) made resident.
  StatusOr<SceneSummary> MakeResident(const StoredSceneView& stored, bool replace);
  SceneSummary Summarize(const ResidentScene& resident, bool with_nodes) const;
  // The local frame that resolves `request` (null: the scene's own frame does).
  StatusOr<std::shared_ptr<LocalFrame>> LocalFrameFor(const ResidentScene& resident,
                                                      const sampling::HiddenSampleMapRequest& request,
                                                      sampling::SegmentTracer tracer, const CallOptions& call);
  Status AdmitSceneSize(const ResidentScene& resident) const;
  // What each lazy structure's build does (and records in build_times_).
  LazyStructure<gpu::GpuScene>::Build GpuBuild(const ResidentScene& resident);
  LazyStructure<raycast::EmbreeScene>::Build EmbreeBuild(const ResidentScene& resident);
  LazyStructure<gpu::RayScene>::Build RayBuild(const ResidentScene& resident);
  LazyStructure<const exact::SceneTriangleIndex>::Build TriangleIndexBuild(const ResidentScene& resident);
  void StartWarming(const ResidentScene& resident, std::span<const StructureKind> kinds);
  GltfLoadLimits LoadLimits(const std::filesystem::path& file_root) const;

  EngineOptions options_;
  std::unique_ptr<SceneRepository> repository_;
  std::unique_ptr<gpu::GpuWorker> gpu_;
  std::unique_ptr<WorkMemoryBudget> work_budget_;
  std::unique_ptr<exact::LightVisibilityCache> light_cache_;
  std::mutex mapper_mutex_;
  std::unique_ptr<gpu::HiddenSampleMapper> hidden_sample_mapper_;
  mutable std::shared_mutex scenes_mutex_;
  std::map<std::string, std::shared_ptr<const ResidentScene>, std::less<>> scenes_;
  // Serializes check-then-commit of one name's uploads, unloads and
  // first-use loads (parsing an upload happens outside it); other names'
  // go on. One lock for every name made an unload of one scene wait out a
  // first-use load of another (9.4 s), holding a metadata thread, so that
  // ListScenes and GetStats queued behind it.
  std::shared_ptr<std::mutex> NameLock(absl::string_view name);
  std::mutex name_locks_mutex_;
  std::map<std::string, std::weak_ptr<std::mutex>, std::less<>> name_locks_;
  std::mutex scene_states_mutex_;
  std::map<std::pair<std::string, std::type_index>, std::any> scene_states_;
  std::mutex one_edit_at_a_time_;
  mutable std::mutex edits_mutex_;  // guards edit_logs_
  std::map<std::string, std::vector<SceneEdit>, std::less<>> edit_logs_;
  void ForgetScene(absl::string_view name);
  // Makes `scene`, an edited copy of `current`'s, resident as the next
  // version: in memory only, not written to the repository.
  // FAILED_PRECONDITION if `current` is no longer the resident version.
  StatusOr<SceneSummary> ReplaceWithEdited(const ResidentScene& current, Scene scene);
  CostModel cost_model_;
  BuildTimes build_times_;
  std::atomic<uint64_t> light_tree_hits_{0};
  std::atomic<uint64_t> light_tree_misses_{0};
  // Destroyed after the explorer only, so builds still running stop and are joined
  // while the GPU worker and everything else they use still exist.
  StructureBuilds builds_;
  // After the builds: destroyed before them. Its probes run queries on the
  // GPU worker, the scenes and their builds (a probe waiting for a build
  // stops with it), so it is stopped and joined before anything they use.
  std::unique_ptr<IdleExplorer> idle_explorer_;
};

// XXH3-128 of the geometry as held (the unplaced triangles, each placed
// mesh once and its placements) and the materials, as 32 hex digits.
std::string SceneContentHash(const Scene& scene);

}  // namespace visq::core
