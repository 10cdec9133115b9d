#include "core/engine.h"

#include <algorithm>
#include <chrono>
#include <mutex>

#include <absl/strings/str_join.h>
#include <spdlog/spdlog.h>
#include <xxhash.h>

#include "common/job_timing.h"
#include "common/parallel.h"
#include "resource_limits/resource_limits.h"
#include "scene/scene_edit.h"
#include "scene/gltf_loader.h"

namespace visq::core {

std::string SceneContentHash(const Scene& scene) {
  XXH3_state_t* state = XXH3_createState();
  XXH3_128bits_reset(state);
  auto add_bytes = [&](const void* data, size_t bytes) { XXH3_128bits_update(state, data, bytes); };
  auto add = [&](const auto& values) {
    const uint64_t count = values.size();
    add_bytes(&count, sizeof(count));
    add_bytes(values.data(), values.size() * sizeof(values[0]));
  };
  // The scene as held: its unplaced triangles, each placed mesh once and
  // where it is placed, so that a level of many copies hashes at the cost
  // of one copy and its placements. (A level written flattened holds the
  // same triangles otherwise, and hashes otherwise.)
  add(scene.positions);
  add(scene.triangles);
  add(scene.triangle_material);
  for (const SceneMesh& mesh : scene.meshes) {
    add(mesh.positions);
    add(mesh.triangles);
    add(mesh.triangle_material);
  }
  for (const MeshPlacement& p : scene.placements) {
    add_bytes(&p.mesh, sizeof(p.mesh));
    add_bytes(&p.first_triangle, sizeof(p.first_triangle));
    add_bytes(&p.world, sizeof(p.world));
  }
  for (const auto& m : scene.materials) {
    add_bytes(&m.reflectivity, sizeof(m.reflectivity));
    add_bytes(&m.emission, sizeof(m.emission));
  }
  const XXH128_hash_t hash = XXH3_128bits_digest(state);
  XXH3_freeState(state);
  return absl::StrCat(absl::Hex(hash.high64, absl::kZeroPad16), absl::Hex(hash.low64, absl::kZeroPad16));
}

std::shared_ptr<ResidentScene> NewResidentScene(std::string name, Scene scene) {
  auto resident = std::make_shared<ResidentScene>();
  resident->name = std::move(name);
  resident->content_hash = SceneContentHash(scene);
  // Counted once here: metadata calls must not walk millions of triangles.
  auto emissive = [&](uint32_t m) { return glm::dot(scene.materials[m].emission, glm::dvec3(1.0)) > 0.0; };
  for (uint32_t m : scene.triangle_material)
    if (emissive(m)) ++resident->emissive_triangles;
  std::vector<int64_t> emissive_of_mesh(scene.meshes.size(), -1);
  for (const MeshPlacement& p : scene.placements) {
    int64_t& count = emissive_of_mesh[p.mesh];
    if (count < 0) {
      const std::vector<uint32_t>& materials = scene.meshes[p.mesh].triangle_material;
      count = std::count_if(materials.begin(), materials.end(), emissive);
    }
    resident->emissive_triangles += count;
  }
  resident->estimate = EstimateStructures(scene);
  resident->scene = std::make_shared<const Scene>(std::move(scene));
  return resident;
}

StatusOr<std::unique_ptr<Engine>> Engine::Create(const EngineOptions& options) {
  std::unique_ptr<Engine> engine(new Engine());
  engine->options_ = options;
  VISQ_ASSIGN_OR_RETURN(engine->repository_,
                        SceneRepository::Open({options.scene_repo, options.catalog, options.replica_id}));
  VISQ_ASSIGN_OR_RETURN(engine->gpu_, gpu::GpuWorker::Start(options.gpu));
  engine->light_cache_ = std::make_unique<exact::LightVisibilityCache>(options.light_cache_bytes);
  engine->work_budget_ = std::make_unique<WorkMemoryBudget>(options.max_work_bytes);
  if (options.cost_model_file != "-")
    engine->cost_model_.PersistTo(options.cost_model_file.empty() ? options.scene_repo / ".visq-cost-model.tsv"
                                                                  : options.cost_model_file);
  spdlog::info("budget for work in flight (--max-work-bytes): {} bytes, {}", engine->work_budget_->capacity(),
               engine->work_budget_->capacity_source());
  spdlog::info("compute workers: {}, from the {}", ParallelWorkers(), resource_limits::ProcessCpuLimit().source);
  const auto& device = engine->gpu_->device();
  spdlog::info("GPU: {} / {} / OpenGL {} via EGL {} ({}){}", device.gl_vendor, device.gl_renderer,
               device.gl_version, device.egl_platform, device.egl_device, device.software ? ", software" : "");
  VISQ_RETURN_IF_ERROR(gpu::RunSelfTest(*engine->gpu_));
  if (options.explore_when_idle)
    engine->idle_explorer_ = std::make_unique<IdleExplorer>(engine->cost_model_, options.idle_exploration);
  return engine;
}

Engine::~Engine() = default;

StatusOr<std::shared_ptr<const ResidentScene>> StillHeld(const std::weak_ptr<const ResidentScene>& scene) {
  std::shared_ptr<const ResidentScene> held = scene.lock();
  if (!held) return absl::FailedPreconditionError("the scene this probe measures was unloaded or replaced");
  return held;
}

void Engine::LoadRepositoryScenes() {
  if (!options_.load_repository_at_start) {
    spdlog::info("{} scene(s) in the repository load on first use", repository_->List().size());
    return;
  }
  for (const std::string& name : repository_->List()) {
    StatusOr<SceneSummary> loaded = LoadFromRepository(name, /*replace=*/true);
    if (!loaded.ok()) spdlog::error("scene '{}' from the repository not loaded: {}", name, loaded.status().message());
  }
}

Status Engine::AdmitSceneSize(const ResidentScene& resident) const {
  const StructureEstimate& e = resident.estimate;
  if (e.total_bytes() > options_.max_scene_bytes)
    return absl::ResourceExhaustedError(absl::StrCat(
        "scene '", resident.name, "' needs about ", e.total_bytes(), " bytes once its structures are built (geometry ",
        e.scene_bytes, ", Embree BVH ", e.embree_bvh_bytes, ", triangle index ", e.triangle_index_bytes,
        ", GPU buffers ", e.gpu_bytes, "), above the cap of ", options_.max_scene_bytes, " (--max-scene-bytes)"));
  return absl::OkStatus();
}

bool Engine::WeighsGpuRays() const {
  if (options_.gpu_rays_in_choice == "always") return true;
  if (options_.gpu_rays_in_choice == "never") return false;
  return !gpu_->device().software;
}

Status Engine::AdmitRayScene(const ResidentScene& resident) const {
  const uint64_t bytes = kGpuRayBytesPerTriangle * resident.scene->TriangleCount();
  if (resident.estimate.total_bytes() + bytes > options_.max_scene_bytes)
    return absl::FailedPreconditionError(absl::StrCat(
        "method: GPU_RAYCAST would hold about ", bytes, " bytes for scene '", resident.name, "' (",
        resident.scene->TriangleCount(), " triangles, every placement flattened); with its other structures (",
        resident.estimate.total_bytes(), ") that is above the cap of ", options_.max_scene_bytes,
        " (--max-scene-bytes); use RAYCAST, which keeps placements as instances"));
  return absl::OkStatus();
}

GltfLoadLimits Engine::LoadLimits(const std::filesystem::path& file_root) const {
  GltfLoadLimits limits;
  limits.file_root = file_root;
  limits.max_scene_bytes = options_.max_scene_bytes;
  return limits;
}

StatusOr<SceneSummary> Engine::MakeResident(const StoredSceneView& stored, bool replace) {
  const auto start = std::chrono::steady_clock::now();
  GltfLoadReport report;
  VISQ_ASSIGN_OR_RETURN(Scene scene, LoadGltfFile(stored.main_file(), &report, LoadLimits(stored.dir())));
  std::shared_ptr<ResidentScene> resident = NewResidentScene(stored.name(), std::move(scene));
  VISQ_RETURN_IF_ERROR(AdmitSceneSize(*resident));
  resident->dropped = std::move(report.dropped);
  resident->persisted = true;
  resident->load_ms = MillisecondsSince(start);
  build_times_.Record("scene_load", resident->load_ms);
  {
    std::unique_lock lock(scenes_mutex_);
    if (!replace && scenes_.count(resident->name))
      return absl::AlreadyExistsError(absl::StrCat("scene '", resident->name, "' is already resident (set replace)"));
    resident->version = stored.version();
    scenes_[resident->name] = resident;
  }
  ForgetScene(resident->name);
  if (!resident->dropped.empty())
    spdlog::info("scene '{}': dropped {}", resident->name, absl::StrJoin(resident->dropped, ", "));
  spdlog::info("scene '{}' v{} resident: {} triangles, {:.1f} ms", resident->name, resident->version,
               resident->scene->TriangleCount(), resident->load_ms);
  if (options_.warm_at_load) StartWarming(*resident, kEveryStructure);
  return Summarize(*resident, false);
}

StatusOr<SceneSummary> Engine::LoadFromRepository(absl::string_view name, bool replace) {
  // One version's files, linked from their blobs: whatever other replicas
  // commit meanwhile, the load reads one upload and reports its version.
  VISQ_ASSIGN_OR_RETURN(const std::unique_ptr<StoredSceneView> stored, repository_->Checkout(name));
  return MakeResident(*stored, replace);
}

StatusOr<std::unique_ptr<SceneUpload>> Engine::BeginUpload(absl::string_view name, absl::string_view main_file,
                                                           bool replace, uint64_t expected_bytes) {
  VISQ_RETURN_IF_ERROR(SceneRepository::ValidateName(name));
  if (expected_bytes > options_.max_upload_bytes)
    return absl::ResourceExhaustedError(absl::StrCat("upload of ", expected_bytes,
                                                     " bytes exceeds the server's upload limit of ",
                                                     options_.max_upload_bytes, " bytes (--max-upload-bytes)"));
  if (!replace) {
    std::shared_lock lock(scenes_mutex_);
    if (scenes_.count(name))
      return absl::AlreadyExistsError(absl::StrCat("scene '", name, "' is already resident (set replace)"));
  }
  auto upload = std::make_unique<SceneUpload>();
  VISQ_ASSIGN_OR_RETURN(upload->staging_, repository_->BeginUpload(name, main_file, options_.max_upload_bytes));
  upload->replace_ = replace;
  upload->expected_bytes_ = expected_bytes;
  return upload;
}

StatusOr<SceneSummary> Engine::FinishUpload(std::unique_ptr<SceneUpload> upload, const StopToken& stop) {
  const auto start = std::chrono::steady_clock::now();
  UploadStaging& staging = *upload->staging_;
  if (upload->expected_bytes_ != 0 && staging.bytes() != upload->expected_bytes_)
    return absl::InvalidArgumentError(absl::StrCat("header.expected_bytes: ", upload->expected_bytes_,
                                                   " bytes announced, ", staging.bytes(),
                                                   " received; nothing stored"));
  // A main file no chunk carried is the client's mistake, not a file the
  // server lost.
  std::error_code absent;
  if (std::filesystem::symlink_status(staging.main_file(), absent).type() == std::filesystem::file_type::not_found)
    return absl::InvalidArgumentError(absl::StrCat("header.upload_main_file '", staging.main_file().filename().string(),
                                                   "': never sent (no chunk carries that file); nothing stored"));
  // Parse from the staging folder first: a malformed upload never reaches
  // the repository, and the staging folder goes with `upload`.
  GltfLoadReport report;
  VISQ_ASSIGN_OR_RETURN(Scene scene, LoadGltfFile(staging.main_file(), &report, LoadLimits(staging.dir())));
  std::shared_ptr<ResidentScene> resident = NewResidentScene(staging.name(), std::move(scene));
  VISQ_RETURN_IF_ERROR(AdmitSceneSize(*resident));
  // Only what the scene model keeps is stored: textures and other files the
  // geometry never read are not.
  VISQ_ASSIGN_OR_RETURN(const size_t unused_files, staging.KeepOnly(report.files_read));
  if (unused_files > 0) report.dropped.push_back(absl::StrCat(unused_files, " uploaded file(s) the geometry does not use"));

  const std::shared_ptr<std::mutex> name_lock = NameLock(staging.name());
  std::lock_guard commit_lock(*name_lock);
  {
    std::shared_lock lock(scenes_mutex_);
    if (!upload->replace_ && (scenes_.count(staging.name()) || repository_->Contains(staging.name())))
      return absl::AlreadyExistsError(absl::StrCat("scene '", staging.name(), "' already exists (set replace)"));
  }
  VISQ_RETURN_IF_ERROR(stop.Check("LoadScene, before the scene was stored (nothing stored)"));
  VISQ_ASSIGN_OR_RETURN(const SceneRepository::Stored stored, repository_->Commit(staging, upload->replace_));

  resident->dropped = std::move(report.dropped);
  resident->persisted = true;
  resident->load_ms = MillisecondsSince(start);
  build_times_.Record("scene_load", resident->load_ms);
  resident->version = stored.version;
  {
    std::unique_lock lock(scenes_mutex_);
    scenes_[resident->name] = resident;
  }
  ForgetScene(resident->name);
  spdlog::info("scene '{}' v{} uploaded ({} bytes): {} triangles, {:.1f} ms", resident->name, resident->version,
               staging.bytes(), resident->scene->TriangleCount(), resident->load_ms);
  if (!resident->dropped.empty())
    spdlog::info("scene '{}': dropped {}", resident->name, absl::StrJoin(resident->dropped, ", "));
  if (options_.warm_at_load) StartWarming(*resident, kEveryStructure);
  return Summarize(*resident, false);
}

std::vector<SceneSummary> Engine::ListScenes() const {
  std::vector<SceneSummary> out;
  std::shared_lock lock(scenes_mutex_);
  for (const auto& [name, resident] : scenes_) out.push_back(Summarize(*resident, false));
  return out;
}

StatusOr<SceneSummary> Engine::GetScene(absl::string_view name, bool with_nodes, bool load_if_stored) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident, SceneForQuery(name, 0, load_if_stored));
  return Summarize(*resident, with_nodes);
}

StatusOr<bool> Engine::UnloadScene(absl::string_view name, bool delete_from_repository) {
  VISQ_RETURN_IF_ERROR(SceneRepository::ValidateName(name));
  const std::shared_ptr<std::mutex> name_lock = NameLock(name);
  std::lock_guard commit_lock(*name_lock);
  bool was_resident = false;
  {
    std::unique_lock lock(scenes_mutex_);
    auto it = scenes_.find(name);
    if (it != scenes_.end()) {
      scenes_.erase(it);
      was_resident = true;
    }
  }
  ForgetScene(name);
  {
    std::lock_guard lock(scene_states_mutex_);
    std::erase_if(scene_states_, [&](const auto& entry) { return entry.first.first == name; });
  }
  if (delete_from_repository) {
    Status removed = repository_->Remove(name);
    if (removed.ok()) return true;
    if (!absl::IsNotFound(removed) || !was_resident) return removed;
    return false;
  }
  if (!was_resident) return absl::NotFoundError(absl::StrCat("scene '", name, "' is not resident"));
  return false;
}

std::shared_ptr<std::mutex> Engine::NameLock(absl::string_view name) {
  std::lock_guard lock(name_locks_mutex_);
  // Locks nobody holds any more go first: the map stays as large as the
  // names in use, whatever names clients try.
  std::erase_if(name_locks_, [](const auto& entry) { return entry.second.expired(); });
  auto [it, added] = name_locks_.try_emplace(std::string(name));
  std::shared_ptr<std::mutex> held = it->second.lock();
  if (!held) {
    held = std::make_shared<std::mutex>();
    it->second = held;
  }
  return held;
}

StatusOr<std::shared_ptr<const ResidentScene>> Engine::SceneForQuery(absl::string_view name, uint64_t version,
                                                                 bool load_if_stored) {
  VISQ_RETURN_IF_ERROR(SceneRepository::ValidateName(name));
  bool resident = false;
  {
    std::shared_lock lock(scenes_mutex_);
    resident = scenes_.count(name) > 0;
  }
  if (!resident && load_if_stored && repository_->Contains(name)) {
    const std::shared_ptr<std::mutex> name_lock = NameLock(name);
    std::lock_guard commit_lock(*name_lock);  // one loader per name at a time
    std::shared_lock lock(scenes_mutex_);
    resident = scenes_.count(name) > 0;
    lock.unlock();
    if (!resident) {
      spdlog::info("scene '{}' is stored but not resident: loading it for this request", name);
      VISQ_RETURN_IF_ERROR(LoadFromRepository(name, /*replace=*/false).status());
    }
  }
  std::shared_lock lock(scenes_mutex_);
  auto it = scenes_.find(name);
  if (it == scenes_.end()) return absl::NotFoundError(absl::StrCat("scene '", name, "' is not resident"));
  if (version != 0 && it->second->version != version)
    return absl::FailedPreconditionError(absl::StrCat("scene '", name, "' is at version ", it->second->version,
                                                      ", the request names version ", version));
  return it->second;
}

StatusOr<SceneSummary> Engine::ReplaceWithEdited(const ResidentScene& current, Scene scene) {
  // Not warmed: a node being dragged makes a version per move, and most are
  // never queried.
  std::shared_ptr<ResidentScene> resident = NewResidentScene(current.name, std::move(scene));
  resident->dropped = current.dropped;
  resident->load_ms = current.load_ms;
  resident->persisted = false;  // the repository still holds the stored scene
  VISQ_ASSIGN_OR_RETURN(const uint64_t version, repository_->NextVersion());
  {
    std::unique_lock lock(scenes_mutex_);
    auto it = scenes_.find(current.name);
    if (it == scenes_.end() || it->second.get() != &current)
      return absl::FailedPreconditionError(
          absl::StrCat("scene '", current.name, "' changed (reloaded, unloaded or edited) during the edit"));
    resident->version = version;
    it->second = resident;
  }
  light_cache_->InvalidateScene(resident->name);
  return Summarize(*resident, false);
}

// What a new resident version (or none) of `name` makes stale: its cached
// light trees, the edits that led to the version it replaces, and the
// per-scene state of each query kind (an obscurance solution of an edited
// version). A reload from the repository brings back the stored version's
// number, lower than its edits': state compared by number would take the
// edits' solution for the newer one.
void Engine::ForgetScene(absl::string_view name) {
  light_cache_->InvalidateScene(std::string(name));
  {
    std::lock_guard lock(scene_states_mutex_);
    std::erase_if(scene_states_, [&](const auto& entry) { return entry.first.first == name; });
  }
  std::lock_guard lock(edits_mutex_);
  if (auto it = edit_logs_.find(name); it != edit_logs_.end()) edit_logs_.erase(it);
}

StatusOr<SceneSummary> Engine::MoveNode(absl::string_view name, uint64_t version,
                                        const std::function<StatusOr<uint32_t>(const Scene&)>& pick_node,
                                        const glm::dmat4& world, const StopToken& stop) {
  // Held across the edit, so that the version the move starts from is the
  // one the last logged move made. Queries never take it.
  std::lock_guard edit(one_edit_at_a_time_);
  VISQ_RETURN_IF_ERROR(stop.Check("SetNodeTransform: waiting for the scene's previous edit"));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> current, SceneForQuery(name, version));
  VISQ_ASSIGN_OR_RETURN(const uint32_t node, pick_node(*current->scene));
  // The resident Scene is shared and immutable: edit a copy.
  Scene moved = *current->scene;
  VISQ_RETURN_IF_ERROR(MoveNodeSubtree(moved, node, world));
  // The last point where the call can stop: past it the move is made.
  VISQ_RETURN_IF_ERROR(stop.Check("SetNodeTransform: before the moved scene is made resident"));
  VISQ_ASSIGN_OR_RETURN(SceneSummary summary, ReplaceWithEdited(*current, std::move(moved)));
  {
    std::lock_guard lock(edits_mutex_);
    std::vector<SceneEdit>& log = edit_logs_[std::string(name)];
    if (log.size() >= kMaxSceneEdits) log.erase(log.begin(), log.begin() + static_cast<ptrdiff_t>(log.size() / 2));
    log.push_back(SceneEdit{current->version, summary.version, node, world});
  }
  spdlog::info("scene '{}' v{}: node {} ('{}') moved", summary.name, summary.version, node,
               current->scene->nodes[node].name);
  return summary;
}

std::vector<SceneEdit> Engine::EditsBetween(absl::string_view scene, uint64_t after_version,
                                            uint64_t up_to_version) const {
  std::lock_guard lock(edits_mutex_);
  std::vector<SceneEdit> out;
  auto it = edit_logs_.find(scene);
  if (it == edit_logs_.end()) return out;
  for (const SceneEdit& e : it->second)
    if (e.version > after_version && e.version <= up_to_version) out.push_back(e);
  return out;
}

namespace {

// A lazy structure's build of `resident`'s scene by `make`: counted in
// `times` under `kind` while it runs and when it ends, and logged with its
// size. The build holds the scene, not the ResidentScene.
template <typename T>
typename LazyStructure<T>::Build TimedBuild(BuildTimes& times, const char* kind, const ResidentScene& resident,
                                            std::function<StatusOr<std::shared_ptr<T>>(const Scene&)> make,
                                            std::function<uint64_t(const T&)> bytes) {
  typename LazyStructure<T>::Build build;
  build.bytes = bytes;
  build.make = [&times, kind, make = std::move(make), bytes, scene = resident.scene, name = resident.name,
                version = resident.version]() -> StatusOr<std::shared_ptr<T>> {
    const auto start = std::chrono::steady_clock::now();
    times.Started(kind);
    StatusOr<std::shared_ptr<T>> built = make(*scene);
    times.Finished(kind, MillisecondsSince(start), built.ok());
    if (built.ok())
      spdlog::info("scene '{}' v{}: {} of {} bytes built in {:.1f} ms", name, version, kind, bytes(**built),
                   MillisecondsSince(start));
    return built;
  };
  return build;
}

}  // namespace

LazyStructure<gpu::GpuScene>::Build Engine::GpuBuild(const ResidentScene& resident) {
  auto build = TimedBuild<gpu::GpuScene>(
      build_times_, "gpu_upload", resident, [this](const Scene& scene) { return gpu::GpuScene::Upload(*gpu_, scene); },
      [](const gpu::GpuScene& g) -> uint64_t { return g.gpu_bytes(); });
  // Buffers uploaded into a context that was lost since are uploaded again.
  build.usable = [](const gpu::GpuScene& g) { return g.IsCurrent(); };
  return build;
}

LazyStructure<raycast::EmbreeScene>::Build Engine::EmbreeBuild(const ResidentScene& resident) {
  return TimedBuild<raycast::EmbreeScene>(
      build_times_, "embree_bvh", resident,
      [this, shared = resident.scene](const Scene& scene) -> StatusOr<std::shared_ptr<raycast::EmbreeScene>> {
        raycast::EmbreeSceneOptions options;
        options.shared_scene = shared;
        // The resident BVH only casts shadow segments: MEDIUM builds it
        // 2.2-5x faster than HIGH, and traces them about as fast (7 % slower
        // on Sponza, as fast or faster elsewhere; raycast::BuildQuality).
        options.quality = raycast::BuildQuality::kMedium;
        options.stop = builds_.stop();
        VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene embree, raycast::EmbreeScene::Create(scene, options));
        return std::make_shared<raycast::EmbreeScene>(std::move(embree));
      },
      [](const raycast::EmbreeScene& e) -> uint64_t { return e.memory_bytes(); });
}

// The BVH is built on the build's thread and only copied on the GL thread.
LazyStructure<gpu::RayScene>::Build Engine::RayBuild(const ResidentScene& resident) {
  auto build = TimedBuild<gpu::RayScene>(
      build_times_, "gpu_ray_bvh", resident,
      [this](const Scene& scene) -> StatusOr<std::shared_ptr<gpu::RayScene>> {
        raycast::FlatBvhOptions options;
        options.stop = builds_.stop();
        VISQ_ASSIGN_OR_RETURN(const raycast::FlatBvh bvh, raycast::BuildFlatBvh(scene, options));
        return gpu::RayScene::Upload(*gpu_, bvh);
      },
      [](const gpu::RayScene& r) -> uint64_t { return r.gpu_bytes(); });
  build.usable = [](const gpu::RayScene& r) { return r.IsCurrent(); };
  return build;
}

LazyStructure<const exact::SceneTriangleIndex>::Build Engine::TriangleIndexBuild(const ResidentScene& resident) {
  return TimedBuild<const exact::SceneTriangleIndex>(
      build_times_, "triangle_index", resident,
      [scene = resident.scene](const Scene&) -> StatusOr<std::shared_ptr<const exact::SceneTriangleIndex>> {
        VISQ_ASSIGN_OR_RETURN(std::unique_ptr<exact::SceneTriangleIndex> index, exact::SceneTriangleIndex::Build(scene));
        return std::shared_ptr<const exact::SceneTriangleIndex>(std::move(index));
      },
      [](const exact::SceneTriangleIndex& i) -> uint64_t { return i.MemoryBytes(); });
}

StatusOr<std::shared_ptr<gpu::GpuScene>> Engine::GpuSceneOf(const ResidentScene& resident, const CallOptions& call) {
  return resident.gpu_scene.Get(builds_, call, GpuBuild(resident), "GPU upload");
}

StatusOr<std::shared_ptr<raycast::EmbreeScene>> Engine::EmbreeSceneOf(const ResidentScene& resident,
                                                                      const CallOptions& call) {
  return resident.embree_scene.Get(builds_, call, EmbreeBuild(resident), "Embree BVH");
}

StatusOr<std::shared_ptr<gpu::RayScene>> Engine::RaySceneOf(const ResidentScene& resident, const CallOptions& call) {
  if (!resident.ray_scene.bytes()) VISQ_RETURN_IF_ERROR(AdmitRayScene(resident));
  return resident.ray_scene.Get(builds_, call, RayBuild(resident), "GPU ray BVH");
}

StatusOr<std::shared_ptr<const exact::SceneTriangleIndex>> Engine::TriangleIndexOf(const ResidentScene& resident,
                                                                                   const CallOptions& call) {
  return resident.triangle_index.Get(builds_, call, TriangleIndexBuild(resident), "triangle index");
}

void Engine::StartWarming(const ResidentScene& resident, std::span<const StructureKind> kinds) {
  for (StructureKind kind : kinds) {
    switch (kind) {
      case StructureKind::kGpuBuffers: resident.gpu_scene.Start(builds_, GpuBuild(resident)); break;
      case StructureKind::kEmbreeBvh: resident.embree_scene.Start(builds_, EmbreeBuild(resident)); break;
      case StructureKind::kTriangleIndex: resident.triangle_index.Start(builds_, TriangleIndexBuild(resident)); break;
    }
  }
}

Status Engine::Warm(absl::string_view name, uint64_t version, std::span<const StructureKind> kinds) {
  std::shared_ptr<const ResidentScene> resident;
  {
    std::shared_lock lock(scenes_mutex_);
    auto it = scenes_.find(name);
    if (it != scenes_.end() && it->second->version == version) resident = it->second;
  }
  if (!resident)
    return absl::NotFoundError(absl::StrCat("scene '", name, "' v", version, " is no longer resident"));
  StartWarming(*resident, kinds);
  return absl::OkStatus();
}

StatusOr<std::shared_ptr<LocalFrame>> Engine::LocalFrameFor(const ResidentScene& resident,
                                                            const sampling::HiddenSampleMapRequest& request,
                                                            sampling::SegmentTracer tracer, const CallOptions& call) {
  const Scene& scene = *resident.scene;
  // The scene's own copies (GPU and Embree alike) are anchored at its centre.
  // They serve where their tolerances are negligible beside the sample
  // spacing. Merely resolving the query (tolerances up to 1/4 of it) is not
  // enough: a copy of the scene 1e3 to 1e5 away moved the centre so far that
  // RASTER ignored occluders 0.38 from the receiver and changed 3,440 bits
  // of a map that a local frame answers like the scene alone.
  const sampling::FloatFrame own{scene.bounds.Empty() ? glm::dvec3(0.0) : scene.bounds.Center(), scene.bounds};
  const StatusOr<sampling::EndpointTolerances> own_tolerances =
      sampling::ResolvableEndpointTolerances(request, own, tracer);
  if (own_tolerances.ok() && sampling::TolerancesAreNegligible(request, *own_tolerances))
    return std::shared_ptr<LocalFrame>();
  // A region that could not resolve the query even if geometry filled it
  // (a query as large as the world, a light far out) is not copied: the
  // copy would cost up to the whole scene and help nothing. Nor is one that
  // would not resolve it at least twice as finely as the scene's own frame.
  const Bounds hull = sampling::HullOf(request).Box();
  const Bounds region = LocalFrames::RegionAround(hull);
  const StatusOr<sampling::EndpointTolerances> region_tolerances =
      sampling::ResolvableEndpointTolerances(request, sampling::FloatFrame{region.Center(), region}, tracer);
  if (own_tolerances.ok() &&
      (!region_tolerances.ok() ||
       2.0 * std::max(region_tolerances->source, region_tolerances->receiver) >
           std::max(own_tolerances->source, own_tolerances->receiver)))
    return std::shared_ptr<LocalFrame>();
  VISQ_RETURN_IF_ERROR(region_tolerances.status());
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const exact::SceneTriangleIndex> index, TriangleIndexOf(resident, call));
  const auto start = std::chrono::steady_clock::now();
  const size_t frames_before = resident.local_frames.size();
  std::shared_ptr<LocalFrame> frame = resident.local_frames.For(scene, *index, hull);
  // A copy made (or, with every slot taken, perhaps made) is a build.
  const bool copied = resident.local_frames.size() != frames_before || frames_before == LocalFrames::kMaxFrames;
  if (copied && call.build_clock) call.build_clock->Add(MillisecondsSince(start));
  VISQ_RETURN_IF_ERROR(sampling::ResolvableEndpointTolerances(request, frame->float_frame(), tracer).status());
  if (copied)
    spdlog::debug("scene '{}' v{}: local frame of side {} at ({}, {}, {}), {} triangles, in {:.1f} ms",
                  resident.name, resident.version, frame->side, frame->lo.x, frame->lo.y, frame->lo.z,
                  frame->scene->TriangleCount(), MillisecondsSince(start));
  return frame;
}

// A local frame's copies are small (the triangles near one query) and built
// under the frame's own lock, which no metadata call takes; the time still
// goes to the call's build clock.
StatusOr<std::shared_ptr<gpu::GpuScene>> Engine::GpuSceneFor(const ResidentScene& resident,
                                                             const sampling::HiddenSampleMapRequest& request,
                                                             const CallOptions& call) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<LocalFrame> frame,
                        LocalFrameFor(resident, request, sampling::SegmentTracer::kRaster, call));
  if (!frame) return GpuSceneOf(resident, call);
  const auto start = std::chrono::steady_clock::now();
  std::lock_guard lock(frame->mutex);
  if (!frame->gpu_scene || !frame->gpu_scene->IsCurrent()) {
    VISQ_ASSIGN_OR_RETURN(frame->gpu_scene, gpu::GpuScene::Upload(*gpu_, *frame->scene, frame->origin()));
    build_times_.Record("gpu_upload_local", MillisecondsSince(start));
    if (call.build_clock) call.build_clock->Add(MillisecondsSince(start));
  }
  return frame->gpu_scene;
}

StatusOr<std::shared_ptr<raycast::EmbreeScene>> Engine::EmbreeSceneFor(
    const ResidentScene& resident, const sampling::HiddenSampleMapRequest& request, const CallOptions& call) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<LocalFrame> frame,
                        LocalFrameFor(resident, request, sampling::SegmentTracer::kRaycast, call));
  if (!frame) return EmbreeSceneOf(resident, call);
  const auto start = std::chrono::steady_clock::now();
  std::lock_guard lock(frame->mutex);
  if (!frame->embree_scene) {
    raycast::EmbreeSceneOptions options;
    options.origin = frame->origin();
    options.quality = raycast::BuildQuality::kMedium;  // shadow segments only, as the scene's own BVH
    VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene embree, raycast::EmbreeScene::Create(*frame->scene, options));
    frame->embree_scene = std::make_shared<raycast::EmbreeScene>(std::move(embree));
    build_times_.Record("embree_bvh_local", MillisecondsSince(start));
    if (call.build_clock) call.build_clock->Add(MillisecondsSince(start));
  }
  return frame->embree_scene;
}

StatusOr<std::shared_ptr<gpu::RayScene>> Engine::RaySceneFor(const ResidentScene& resident,
                                                             const sampling::HiddenSampleMapRequest& request,
                                                             const CallOptions& call) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<LocalFrame> frame,
                        LocalFrameFor(resident, request, sampling::SegmentTracer::kRaycast, call));
  if (!frame) return RaySceneOf(resident, call);
  const auto start = std::chrono::steady_clock::now();
  std::lock_guard lock(frame->mutex);
  if (!frame->ray_scene || !frame->ray_scene->IsCurrent()) {
    raycast::FlatBvhOptions options;
    options.origin = frame->origin();
    options.stop = call.stop;
    VISQ_ASSIGN_OR_RETURN(const raycast::FlatBvh bvh, raycast::BuildFlatBvh(*frame->scene, options));
    VISQ_ASSIGN_OR_RETURN(frame->ray_scene, gpu::RayScene::Upload(*gpu_, bvh, call.Job()));
    build_times_.Record("gpu_ray_bvh_local", MillisecondsSince(start));
    if (call.build_clock) call.build_clock->Add(MillisecondsSince(start));
  }
  return frame->ray_scene;
}

Status Engine::ValidateSampledPrecision(const ResidentScene& resident, const sampling::HiddenSampleMapRequest& request,
                                     sampling::SegmentTracer tracer, const CallOptions& call) {
  return LocalFrameFor(resident, request, tracer, call).status();
}

void BuildTimes::Record(const std::string& kind, double ms) {
  Started(kind);
  Finished(kind, ms, /*ok=*/true);
}

void BuildTimes::Started(const std::string& kind) {
  std::lock_guard lock(mutex_);
  ++kinds_[kind].in_progress;
}

void BuildTimes::Finished(const std::string& kind, double ms, bool ok) {
  std::lock_guard lock(mutex_);
  Figures& f = kinds_[kind];
  --f.in_progress;
  if (!ok) {
    ++f.failures;
    return;
  }
  ++f.count;
  f.total_ms += ms;
  f.max_ms = std::max(f.max_ms, ms);
}

std::map<std::string, BuildTimes::Figures> BuildTimes::Snapshot() const {
  std::lock_guard lock(mutex_);
  return kinds_;
}

StatusOr<gpu::HiddenSampleMapper*> Engine::hidden_sample_mapper() {
  std::lock_guard lock(mapper_mutex_);
  if (!hidden_sample_mapper_) {
    VISQ_ASSIGN_OR_RETURN(hidden_sample_mapper_, gpu::HiddenSampleMapper::Create(*gpu_, options_.hidden_sample_map));
  }
  return hidden_sample_mapper_.get();
}

SceneSummary Engine::Summarize(const ResidentScene& resident, bool with_nodes) const {
  const Scene& scene = *resident.scene;
  SceneSummary s;
  s.name = resident.name;
  s.version = resident.version;
  s.triangles = scene.TriangleCount();
  s.vertices = scene.PositionCount();
  s.bounds = scene.bounds;
  s.content_hash = resident.content_hash;
  // What is built so far, read without waiting for a build in progress:
  // nothing is uploaded until a GPU query needs it.
  s.cpu_bytes = scene.CpuBytes() + resident.embree_scene.bytes() + resident.triangle_index.bytes() +
                resident.absorber_rays.MemoryBytes();
  s.gpu_bytes = resident.gpu_scene.bytes() + resident.ray_scene.bytes();
  s.estimate = resident.estimate;
  s.materials = static_cast<uint32_t>(scene.materials.size());
  s.emissive_triangles = resident.emissive_triangles;
  s.has_lightmap_uvs = !scene.lightmap_uvs.empty();
  s.dropped = resident.dropped;
  s.load_ms = resident.load_ms;
  s.persisted = resident.persisted;
  if (with_nodes) s.nodes = scene.nodes;
  return s;
}

}  // namespace visq::core
