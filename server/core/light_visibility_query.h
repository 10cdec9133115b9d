// Exact light visibility as a core query: validation, the per-light tree
// cache keyed by (scene, version, light, receiver region), and the batch.
#pragma once

#include <atomic>
#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/accuracy_statement.h"
#include "core/call_options.h"
#include "core/work_budget.h"
#include "common/status.h"
#include "exact/light_visibility.h"
#include "core/work_timing.h"

namespace visq::core {

class Engine;

struct LightVisibilityQuery {
  std::string scene;
  uint64_t scene_version = 0;
  exact::AreaLight light;
  std::vector<exact::QueryPoint> points;
  bool want_polygons = false;
  std::optional<Bounds> receiver_region;
  std::vector<std::string> exclude_nodes;
  // exact::TreeOptions::shadow_tolerance; unset: the engine's
  // light_shadow_tolerance.
  std::optional<double> shadow_tolerance;
  // Not on the wire. When not empty, only these points (indices, sorted and
  // distinct) are answered, on the trees the whole batch would use (the
  // groups are made of every point); the others' answers are left empty.
  // The planner's probe of a batch (core/visibility_sampling_query.cpp):
  // the trees it builds and the answers it stores are the batch's own.
  std::vector<uint32_t> answer_only;
  // Not on the wire. Where set, counts the points answered as they are,
  // so that a probe stopped at its budget still says how far it got.
  std::atomic<size_t>* answered = nullptr;
  // Checked between points and while a tree selects its occluders.
  CallOptions call;
  // Not on the wire. The caller's reservation of the work budget covers
  // this batch (a hidden-sample map's): RunLightVisibility takes none of
  // its own, which would wait while the caller's is held.
  bool work_reserved = false;
};

struct LightVisibilityAnswer {
  std::vector<exact::PointVisibility> points;
  exact::TreeStats tree;  // summed over the trees the batch used
  bool tree_reused = false;  // every one of them existed before
  size_t trees = 0;
  size_t trees_created = 0;
  // The most of the batch's trees held at once: each is let go when its
  // group's points are answered, so at most ParallelWorkers() + 1.
  size_t peak_trees_held = 0;
  Bounds receiver_region;  // the union of their receiver boxes
  double shadow_tolerance = 0.0;  // what the trees left out at most (TreeOptions)
  double compute_ms = 0;
  // The answers' share of the work budget (LightVisibilityWorkBytes), held
  // until the answer is sent; empty when the query's caller reserved.
  std::shared_ptr<WorkMemoryBudget::Reservation> memory;
};
inline WorkTiming WorkTimingOf(const LightVisibilityAnswer& a) { return {0.0, a.compute_ms}; }

inline constexpr size_t kMaxLightVisibilityPoints = 1'000'000;  // per request message
inline constexpr size_t kMaxLightVertices = 1024;

// Every check of the query against its scene that needs no tree: what is
// refused before any work starts.
[[nodiscard]] Status ValidateLightVisibilityQuery(const LightVisibilityQuery& query, const Scene& scene);

// What a batch's answers hold until they are sent, reserved before it
// runs: per point its answer and its message, and with polygons, as many
// as the light's vertices and 8 more a point (a visible part is the light
// cut by a few occluder edges), as vectors and as messages. 200,000
// points of a quad light with polygons: about 0.1 GB.
uint64_t LightVisibilityWorkBytes(const LightVisibilityQuery& query);

[[nodiscard]] StatusOr<LightVisibilityAnswer> RunLightVisibility(Engine& engine, const LightVisibilityQuery& query);

// What a batch would cost the exact method, found before it runs, in the
// cost model's two units (core/accuracy_planner.h): the groups
// RunLightVisibility would make of its points, which of their trees the
// cache already holds, and, for each tree it would build, the scene
// triangles whose boxes meet the box of its shaft (the light and the
// group's box), which is what a new tree selects and refines; and the
// points to answer that no held tree has in its store. A batch whose trees
// are all held costs its new points' descents alone; a repeated frame,
// hash lookups.
struct LightVisibilityWork {
  size_t groups = 0;
  size_t cached_groups = 0;
  double new_shaft_triangles = 0.0;
  double points = 0.0;         // not answered from a store
  double stored_points = 0.0;  // answered from a held tree's store
};
[[nodiscard]] StatusOr<LightVisibilityWork> EstimateLightVisibilityWork(Engine& engine,
                                                                       const LightVisibilityQuery& query);

// Every LightVisibility answer's: exact, with no samples to bound.
// The statement of a batch's answers: exact, or, where occluders were left
// out under its shadow tolerance, bounded by the largest point's error.
AccuracyStatement LightVisibilityStatement(const LightVisibilityAnswer& answer);

}  // namespace visq::core
