#include "core/light_visibility_query.h"

#include <malloc.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <mutex>

#include <absl/cleanup/cleanup.h>

#include "common/job_timing.h"
#include "core/engine.h"
#include "common/coordinates.h"
#include "common/parallel.h"

namespace visq::core {
namespace {

// Finite and within visq's coordinate range (common/coordinates.h).

}  // namespace

Status ValidateLightVisibilityQuery(const LightVisibilityQuery& query, const Scene& scene) {
  if (query.points.empty()) return absl::InvalidArgumentError("points: empty");
  if (query.points.size() > kMaxLightVisibilityPoints)
    return absl::ResourceExhaustedError(absl::StrCat("points: ", query.points.size(), " exceeds the cap of ",
                                                     kMaxLightVisibilityPoints,
                                                     " per request (use LightVisibilityStream)"));
  if (query.light.vertices.size() > kMaxLightVertices)
    return absl::ResourceExhaustedError(absl::StrCat("light.vertices: ", query.light.vertices.size(),
                                                     " exceeds the cap of ", kMaxLightVertices));
  VISQ_RETURN_IF_ERROR(exact::ValidateAreaLight(query.light));  // after the vertex cap: it is quadratic
  if (query.shadow_tolerance && !(*query.shadow_tolerance >= 0.0 && *query.shadow_tolerance <= 1.0))
    return absl::InvalidArgumentError(
        absl::StrCat("shadow_tolerance: ", *query.shadow_tolerance, " is not a share of the light in [0, 1]"));
  if (!std::isfinite(query.light.radiance) || query.light.radiance < 0)
    return absl::InvalidArgumentError(absl::StrCat("radiance: ", query.light.radiance, " is not a finite value >= 0"));
  for (size_t i = 0; i < query.points.size(); ++i) {
    const auto& p = query.points[i];
    VISQ_RETURN_IF_ERROR(exact::ValidateQueryPoint(p, absl::StrCat("points[", i, "]")));
    if (p.receiver_triangle && *p.receiver_triangle >= scene.TriangleCount())
      return absl::InvalidArgumentError(absl::StrCat("points[", i, "].triangle: ", *p.receiver_triangle,
                                                     " out of range (", scene.TriangleCount(), " triangles)"));
  }
  for (size_t k = 0; k < query.answer_only.size(); ++k)
    if (query.answer_only[k] >= query.points.size() || (k > 0 && query.answer_only[k] <= query.answer_only[k - 1]))
      return absl::InvalidArgumentError(absl::StrCat("answer_only[", k, "]: ", query.answer_only[k],
                                                     " is out of range or out of order"));
  if (query.receiver_region) {
    const Bounds& r = *query.receiver_region;
    if (!InCoordinateRange(r.min) || !InCoordinateRange(r.max) || r.min.x > r.max.x || r.min.y > r.max.y || r.min.z > r.max.z)
      return absl::InvalidArgumentError("receiver_region: min must be finite and <= max");
    for (size_t i = 0; i < query.points.size(); ++i) {
      const glm::dvec3& q = query.points[i].position;
      if (glm::any(glm::lessThan(q, r.min)) || glm::any(glm::greaterThan(q, r.max)))
        return absl::InvalidArgumentError(absl::StrCat("points[", i, "]: outside receiver_region"));
    }
  }
  return absl::OkStatus();
}

namespace {

// The trees' options: the excluded nodes' triangles, the memory budget.
StatusOr<exact::TreeOptions> BaseTreeOptions(Engine& engine, const LightVisibilityQuery& query, const Scene& scene) {
  exact::TreeOptions base;
  // A batch uses one tree per receiver cell, so each may grow to 1/16 of
  // the cache; past that its queries resolve the undefined leaves they meet
  // themselves, exactly and, since line boxes skip the subtractions that
  // cannot meet a piece, about as fast; smaller trees were faster still
  // (docs/exact-method-notes.md).
  base.max_bytes = engine.light_cache_stats().capacity_bytes / 16;
  base.stop = query.call.stop;
  base.shadow_tolerance = query.shadow_tolerance.value_or(engine.light_shadow_tolerance());
  for (const std::string& node_name : query.exclude_nodes) {
    bool found = false;
    for (const SceneNode& node : scene.nodes) {
      if (node.name != node_name) continue;
      found = true;
      for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t)
        base.exclude_triangles.push_back(t);
    }
    if (!found) return absl::InvalidArgumentError(absl::StrCat("exclude_nodes: no node named '", node_name, "'"));
  }
  return base;
}

// One tree for the client's region, or one per group of receivers.
std::vector<exact::ReceiverCell> ReceiverGroups(Engine& engine, const LightVisibilityQuery& query, const Scene& scene,
                                                const exact::SceneTriangleIndex& index) {
  std::vector<exact::ReceiverCell> groups;
  if (query.receiver_region) {
    exact::ReceiverCell all{*query.receiver_region, {}};
    all.points.resize(query.points.size());
    for (uint32_t i = 0; i < all.points.size(); ++i) all.points[i] = i;
    groups.push_back(std::move(all));
  } else if (engine.light_receiver_cells() > 0) {
    groups = exact::GroupReceivers(query.points, scene.bounds, engine.light_receiver_cells(),
                                   engine.light_receiver_min_points());
  } else {
    groups = exact::GroupReceiversByShaft(query.points, query.light, index,
                                          {engine.light_shaft_triangles(), engine.light_receiver_min_points()});
  }
  return groups;
}

// The groups' points cut down to those the query answers (answer_only);
// groups left without a point are dropped: they need no tree.
void KeepAnsweredPoints(const LightVisibilityQuery& query, std::vector<exact::ReceiverCell>& groups) {
  if (query.answer_only.empty()) return;
  for (exact::ReceiverCell& group : groups)
    std::erase_if(group.points, [&](uint32_t i) {
      return !std::binary_search(query.answer_only.begin(), query.answer_only.end(), i);
    });
  std::erase_if(groups, [](const exact::ReceiverCell& group) { return group.points.empty(); });
}

// A stopped batch's status says how much of it was left.
Status WithPointsLeft(absl::StatusCode code, absl::string_view message, size_t left, size_t total) {
  return Status(code, absl::StrCat(message, " with ", left, " of ", total, " points left"));
}

// The cache key of a group's tree, as RunLightVisibility makes it.
exact::CacheKey GroupTreeKey(const ResidentScene& resident, const exact::AreaLight& light,
                             exact::TreeOptions options, const exact::ReceiverCell& group) {
  options.receiver_bounds = group.box;
  return exact::CacheKey{resident.name, resident.version, exact::HashLight(light, options)};
}

}  // namespace

StatusOr<LightVisibilityWork> EstimateLightVisibilityWork(Engine& engine, const LightVisibilityQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  const Scene& scene = *resident->scene;
  VISQ_RETURN_IF_ERROR(ValidateLightVisibilityQuery(query, scene));
  VISQ_ASSIGN_OR_RETURN(const exact::TreeOptions base, BaseTreeOptions(engine, query, scene));
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const exact::SceneTriangleIndex> index,
                        engine.TriangleIndexOf(*resident, query.call));
  Bounds light_box;
  for (const glm::dvec3& v : query.light.vertices) light_box.Extend(v);

  std::vector<exact::ReceiverCell> groups = ReceiverGroups(engine, query, scene, *index);
  KeepAnsweredPoints(query, groups);
  LightVisibilityWork work;
  for (const exact::ReceiverCell& group : groups) {
    ++work.groups;
    if (std::shared_ptr<exact::LightVisibilityTree> held =
            engine.light_cache().Peek(GroupTreeKey(*resident, query.light, base, group))) {
      ++work.cached_groups;
      for (uint32_t i : group.points) {
        const bool stored = held->StoresAnswer(query.points[i], query.want_polygons);
        (stored ? work.stored_points : work.points) += 1.0;
      }
      continue;
    }
    work.points += double(group.points.size());
    const glm::dvec3 lo = glm::min(light_box.min, group.box.min), hi = glm::max(light_box.max, group.box.max);
    work.new_shaft_triangles += double(index->CountInBox(lo, hi, SIZE_MAX));
  }
  return work;
}

uint64_t LightVisibilityWorkBytes(const LightVisibilityQuery& query) {
  // A point's answer (PointVisibility) and its message with its slot in
  // the response; a polygon vertex as a dvec3 and as a Vec3 message with
  // its slot; a point's polygon list as vectors and as messages.
  constexpr uint64_t kPointBytes = sizeof(exact::PointVisibility) + 80;
  constexpr uint64_t kVertexBytes = sizeof(glm::dvec3) + 56;
  constexpr uint64_t kPolygonListBytes = 2 * 32 + 64;
  const uint64_t points = query.answer_only.empty() ? query.points.size() : query.answer_only.size();
  uint64_t per_point = kPointBytes;
  if (query.want_polygons) per_point += kPolygonListBytes + (query.light.vertices.size() + 8) * kVertexBytes;
  return uint64_t(query.points.size()) * sizeof(exact::PointVisibility) + points * per_point;
}

StatusOr<LightVisibilityAnswer> RunLightVisibility(Engine& engine, const LightVisibilityQuery& query) {
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const ResidentScene> resident,
                        engine.SceneForQuery(query.scene, query.scene_version));
  const Scene& scene = *resident->scene;
  VISQ_RETURN_IF_ERROR(ValidateLightVisibilityQuery(query, scene));
  LightVisibilityAnswer answer;
  if (!query.work_reserved) {
    VISQ_ASSIGN_OR_RETURN(WorkMemoryBudget::Reservation memory,
                          engine.work_budget().Reserve(LightVisibilityWorkBytes(query),
                                                       query.want_polygons ? "points, want_polygons" : "points",
                                                       query.call.Job()));
    answer.memory = std::make_shared<WorkMemoryBudget::Reservation>(std::move(memory));
  }
  const auto start = std::chrono::steady_clock::now();

  VISQ_ASSIGN_OR_RETURN(const exact::TreeOptions base, BaseTreeOptions(engine, query, scene));
  answer.shadow_tolerance = base.shadow_tolerance;

  // The scene's triangle index, which new trees select their occluders
  // from and the grouping counts shafts in: fetched (or built, or waited
  // for) here, once, so that the wait is the call's build time, not its
  // compute, and is not paid in parallel by every group that builds a tree.
  const auto index_start = std::chrono::steady_clock::now();
  VISQ_ASSIGN_OR_RETURN(std::shared_ptr<const exact::SceneTriangleIndex> index,
                        engine.TriangleIndexOf(*resident, query.call));
  const double index_ms = MillisecondsSince(index_start);

  std::vector<exact::ReceiverCell> groups = ReceiverGroups(engine, query, scene, *index);
  KeepAnsweredPoints(query, groups);
  const StopToken& stop = query.call.stop;

  // Work in chunks of one group's points, in order, on every core: a single
  // cell's batch runs in parallel as well as many cells. The first chunk of
  // a group to run finds or builds its tree; the others wait for it; the
  // last to finish lets the tree go. Chunks are taken in order, so at most
  // one group more than there are workers holds a tree at any time: a
  // request's own trees take at most (workers + 1) x base.max_bytes beside
  // what the cache keeps, however many groups it has.
  struct GroupTree {
    std::once_flag once;
    Status status;
    std::shared_ptr<exact::LightVisibilityTree> tree;
    bool created = false;
    std::atomic<uint32_t> chunks_left{0};
  };
  // Trees this request built but the cache did not keep die with `trees`;
  // then glibc is asked to hand their memory back (declared first, so it
  // runs last).
  struct TrimAfterTrees {
    std::atomic<bool> built{false};
    ~TrimAfterTrees() {
      if (built.load()) malloc_trim(0);
    }
  } trim;
  std::vector<GroupTree> trees(groups.size());
  struct Chunk {
    uint32_t group, begin, end;
  };
  constexpr uint32_t kChunkPoints = 64;
  std::vector<Chunk> chunks;
  for (uint32_t g = 0; g < groups.size(); ++g) {
    const auto n = static_cast<uint32_t>(groups[g].points.size());
    for (uint32_t b = 0; b < n; b += kChunkPoints) {
      chunks.push_back({g, b, std::min(n, b + kChunkPoints)});
      trees[g].chunks_left.fetch_add(1, std::memory_order_relaxed);
    }
  }
  auto get_tree = [&](uint32_t g) {
    GroupTree& t = trees[g];
    exact::TreeOptions options = base;
    options.receiver_bounds = groups[g].box;
    const exact::CacheKey key = GroupTreeKey(*resident, query.light, base, groups[g]);
    StatusOr<std::shared_ptr<exact::LightVisibilityTree>> tree = engine.light_cache().GetOrCreate(
        key, [&]() -> StatusOr<std::unique_ptr<exact::LightVisibilityTree>> {
          t.created = true;
          trim.built = true;
          return exact::LightVisibilityTree::Create(query.light, scene, options, index.get());
        });
    if (tree.ok()) {
      t.tree = std::move(*tree);
    } else {
      t.status = tree.status();
    }
  };

  std::mutex held_mutex;  // the trees held now, and what the released ones did
  size_t held = 0;
  auto hold = [&] {
    std::lock_guard lock(held_mutex);
    answer.peak_trees_held = std::max(answer.peak_trees_held, ++held);
  };
  auto release = [&](GroupTree& t) {
    std::lock_guard lock(held_mutex);
    answer.tree += t.tree->Stats();
    t.tree.reset();
    --held;
  };

  answer.points.resize(query.points.size());
  const size_t to_answer = query.answer_only.empty() ? query.points.size() : query.answer_only.size();
  std::atomic<size_t> answered{0};
  std::atomic<bool> stopped{false};
  std::mutex error_mutex;
  Status error;
  auto fail = [&](Status status) {
    std::lock_guard lock(error_mutex);
    if (error.ok()) error = std::move(status);
    stopped = true;
  };
  // One chunk of a cell's points per parallel step, on the process's pool.
  ParallelFor(chunks.size(), 1, [&](size_t c, size_t) {
    if (stopped.load(std::memory_order_relaxed)) return;
    {
      const Chunk& chunk = chunks[c];
      GroupTree& t = trees[chunk.group];
      std::call_once(t.once, [&] {
        get_tree(chunk.group);
        if (t.status.ok()) hold();
      });
      if (!t.status.ok()) return fail(t.status);
      // Every return below has answered or failed this chunk.
      absl::Cleanup last_chunk = [&] {
        if (t.chunks_left.fetch_sub(1) == 1) release(t);
      };
      for (uint32_t k = chunk.begin; k < chunk.end; ++k) {
        const size_t left = to_answer - answered.load();
        if (Status stopped = stop.Check("light visibility"); !stopped.ok())
          return fail(WithPointsLeft(stopped.code(), stopped.message(), left, to_answer));
        const uint32_t i = groups[chunk.group].points[k];
        StatusOr<exact::PointVisibility> r = t.tree->Query(query.points[i], query.want_polygons, stop);
        if (!r.ok() && (absl::IsCancelled(r.status()) || absl::IsDeadlineExceeded(r.status())))
          return fail(WithPointsLeft(r.status().code(), r.status().message(), left, to_answer));
        if (!r.ok()) return fail(Status(r.status().code(), absl::StrCat("points[", i, "]: ", r.status().message())));
        answer.points[i] = std::move(*r);
        answered.fetch_add(1, std::memory_order_relaxed);
        if (query.answered != nullptr) query.answered->fetch_add(1, std::memory_order_relaxed);
      }
    }
  });
  if (!error.ok()) return error;

  answer.tree_reused = true;
  for (size_t g = 0; g < groups.size(); ++g) {
    answer.tree_reused &= !trees[g].created;
    answer.trees_created += trees[g].created ? 1 : 0;
    answer.receiver_region.Extend(groups[g].box.min);
    answer.receiver_region.Extend(groups[g].box.max);
  }
  answer.trees = groups.size();
  engine.RecordLightTreeUse(answer.trees_created > 0);
  answer.compute_ms = MillisecondsSince(start) - index_ms;
  return answer;
}

AccuracyStatement LightVisibilityStatement(const LightVisibilityAnswer& answer) {
  AccuracyStatement out = ExactStatement(
      "plucker-exact",
      "exact visibility: every side decision is an exact predicate; only the final areas and integrals are "
      "double-precision sums (relative error about 1e-12)");
  out.parameters["shadow_tolerance"] = answer.shadow_tolerance;
  if (answer.shadow_tolerance > 0.0) {
    size_t left_out = 0;
    for (const exact::PointVisibility& p : answer.points) {
      out.error_bound = std::max(out.error_bound, p.visible_area_fraction_error);
      left_out += p.visible_area_fraction_error > 0.0 ? 1 : 0;
    }
    absl::StrAppend(&out.note, "; at ", left_out, " of ", answer.points.size(),
                    " points occluders with small shadows were left out (shadow_tolerance ", answer.shadow_tolerance,
                    " of the light's area): error_bound is the largest visible_fraction_error, one-sided (the "
                    "true fraction is at most that much below the answer, never above)");
  }
  return out;
}

}  // namespace visq::core
