// The public face of the tree (light_visibility.h): creation, queries one by
// one and in batches, statistics. The tree itself is detail::LightTree
// (light_visibility_impl.h).
#include "exact/light_visibility.h"

#include <atomic>
#include <mutex>

#include "common/coordinates.h"
#include "common/parallel.h"
#include "exact/light_visibility_impl.h"

namespace visq::exact {

LightVisibilityTree::LightVisibilityTree(std::unique_ptr<detail::LightTree> impl) : impl_(std::move(impl)) {}
LightVisibilityTree::~LightVisibilityTree() = default;

StatusOr<std::unique_ptr<LightVisibilityTree>> LightVisibilityTree::Create(const AreaLight& light, const Scene& scene,
                                                                           const TreeOptions& options,
                                                                           const SceneTriangleIndex* index) {
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<detail::LightTree> tree,
                        detail::LightTree::Create(light, scene, options, index));
  return std::unique_ptr<LightVisibilityTree>(new LightVisibilityTree(std::move(tree)));
}

Status ValidateQueryPoint(const QueryPoint& point, std::string_view field) {
  if (!InCoordinateRange(point.position))
    return absl::InvalidArgumentError(
        fmt::format("{}.position: ({}, {}, {}) is NaN, Inf or beyond ±{:g}", field, point.position.x,
                    point.position.y, point.position.z, kMaxCoordinate));
  if (point.normal && !IsDirection(*point.normal))
    return absl::InvalidArgumentError(
        fmt::format("{}.normal: ({}, {}, {}) is zero, NaN, Inf or too long to normalize", field, point.normal->x,
                    point.normal->y, point.normal->z));
  return absl::OkStatus();
}

StatusOr<PointVisibility> LightVisibilityTree::Query(const QueryPoint& point, bool want_polygons,
                                                     const StopToken& stop) {
  return impl_->Query(point, want_polygons, stop);
}

bool LightVisibilityTree::StoresAnswer(const QueryPoint& point, bool want_polygons) const {
  return impl_->StoresAnswer(point, want_polygons);
}

StatusOr<std::vector<PointVisibility>> LightVisibilityTree::QueryBatch(
    std::span<const QueryPoint> points, int threads, bool want_polygons, const StopToken& stop_token) {
  std::vector<PointVisibility> out(points.size());
  std::atomic<bool> stop{false};
  std::mutex error_mutex;
  Status error;
  // One point per chunk: query costs vary a lot (refinement, penumbrae).
  ParallelFor(
      points.size(), 1,
      [&](size_t i, size_t) {
        if (stop.load(std::memory_order_relaxed)) return;
        // The message is made only once the call has stopped: a point takes
        // microseconds where its tree is refined.
        if (stop_token.Stopped()) {
          const Status stopped = stop_token.Check(
              absl::StrCat("light visibility, with ", points.size() - i, " of ", points.size(), " points left"));
          std::lock_guard lock(error_mutex);
          if (error.ok()) error = stopped;
          stop = true;
          return;
        }
        auto r = impl_->Query(points[i], want_polygons, stop_token);
        if (!r.ok()) {
          std::lock_guard lock(error_mutex);
          if (error.ok()) error = Status(r.status().code(), absl::StrCat("points[", i, "]: ", r.status().message()));
          return;
        }
        out[i] = std::move(*r);
      },
      threads > 0 ? static_cast<size_t>(threads) : 0);
  if (!error.ok()) return error;
  return out;
}

TreeStats LightVisibilityTree::Stats() const {
  TreeStats s;
  std::shared_lock lock(impl_->mutex);
  s.nodes = impl_->nodes.size();
  s.memory_bytes = impl_->MemoryBytesLocked();
  s.queries = impl_->queries.load();
  s.hits = impl_->hits.load();
  s.refinements = impl_->refinements.load();
  s.unrefined_leaf_visits = impl_->unrefined_leaf_visits.load();
  s.wholly_visible = impl_->wholly_visible.load();
  s.wholly_hidden = impl_->wholly_hidden.load();
  s.subtracted_directly = impl_->subtracted_directly.load();
  s.merged_occluders = impl_->merged_occluders.load();
  s.fragment_grids = impl_->fragment_grids.load();
  s.hidden_by_remembered_blockers = impl_->hidden_by_remembered_blockers.load();
  s.answers_reused = impl_->answers_reused.load();
  {
    std::shared_lock answers_lock(impl_->answers_mutex);
    s.answers_kept = impl_->answers.size();
    s.answer_bytes = impl_->answer_bytes;
    s.memory_bytes += impl_->answer_bytes;
  }
  s.far_occluders = impl_->far.size();
  s.near_occluders = impl_->near.size();
  return s;
}

TreeStats& TreeStats::operator+=(const TreeStats& o) {
  nodes += o.nodes;
  memory_bytes += o.memory_bytes;
  queries += o.queries;
  hits += o.hits;
  refinements += o.refinements;
  unrefined_leaf_visits += o.unrefined_leaf_visits;
  wholly_visible += o.wholly_visible;
  wholly_hidden += o.wholly_hidden;
  subtracted_directly += o.subtracted_directly;
  merged_occluders += o.merged_occluders;
  fragment_grids += o.fragment_grids;
  hidden_by_remembered_blockers += o.hidden_by_remembered_blockers;
  answers_reused += o.answers_reused;
  answers_kept += o.answers_kept;
  answer_bytes += o.answer_bytes;
  far_occluders += o.far_occluders;
  near_occluders += o.near_occluders;
  return *this;
}

size_t LightVisibilityTree::MemoryBytes() const {
  size_t bytes;
  {
    std::shared_lock lock(impl_->mutex);
    bytes = impl_->MemoryBytesLocked();
  }
  std::shared_lock lock(impl_->answers_mutex);
  return bytes + impl_->answer_bytes;
}

double LightVisibilityTree::light_area() const { return impl_->light_area; }

size_t LightVisibilityTree::ThisThreadScratchBytes() { return detail::LightTree::ThreadScratch().Bytes(); }

}  // namespace visq::exact
