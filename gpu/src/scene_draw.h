// Draws a planned part of a GpuScene (GpuScene::ScenePartDraw) with the
// scene's vertex array: every algorithm's draws of scene triangles go
// through here, so that each reads its corners and placements one way
// (scene_vertex.glsl). GL thread only; the caller's program and targets
// are bound.
#pragma once

#include <cstdint>
#include <string_view>
#include <vector>

#include "common/status.h"
#include "gpu_scene_resources.h"
#include "timed_sizer.h"
#include "visq/gpu/gpu_worker.h"

namespace visq::gpu {

[[nodiscard]] Status DrawScenePart(const GpuScene::Resources& resources, const ScenePartDraw& part);
// Walks a draw's commands in order and hands out pieces of it: drawing
// every piece, one after the other, draws what `draw` does, in the same
// order. A command longer than a piece is cut into runs of its triangles
// (indexed: firstIndex moves 3 a triangle; arrays: first does). A draw of
// the whole scene (no commands on the CPU) is one piece. `draw` must
// outlive the cursor. No GL calls.
class DrawCursor {
 public:
  explicit DrawCursor(const ScenePartDraw& draw);
  bool done() const;
  // The next piece, of about `triangles` triangles (placements counted).
  ScenePartDraw Next(uint64_t triangles);

 private:
  size_t Stride() const { return draw_->indexed ? 5 : 4; }
  const ScenePartDraw* draw_;
  size_t command_ = 0;            // the next command
  uint32_t done_in_command_ = 0;  // its triangles already handed out
  bool whole_taken_ = false;
};

// Draws `part` of `scene` in pieces sized by `pieces`, each finished and
// timed while the sizer still learns, and asks `job` between pieces
// (its stop token, naming `where`): a stop reaches a draw that takes seconds on
// a CPU rasterizer within about one piece. For draws whose pieces combine
// as one draw would (OR logic ops, depth-tested targets).
[[nodiscard]] Status DrawInTimedPieces(const GpuScene& scene, const ScenePartDraw& part, TimedSizer& pieces,
                                       const JobOptions& job, std::string_view where);

// The same draw spread over GL jobs: each DrawSome, in a job of its own with
// the caller's program and targets bound again, draws pieces until the draw
// is done or it has drawn for `job_ms`, and the next goes on where it
// stopped. Other calls' jobs get the GL thread between, so a draw that takes
// seconds on a CPU rasterizer holds it for about `job_ms` at a time. Built
// on the calling thread (no GL calls); `part` and `pieces` must outlive it.
class DrawAcrossJobs {
 public:
  DrawAcrossJobs(const GpuScene& scene, const ScenePartDraw& part, TimedSizer& pieces);
  DrawAcrossJobs(const DrawAcrossJobs&) = delete;  // the cursor points into it
  DrawAcrossJobs& operator=(const DrawAcrossJobs&) = delete;
  bool done() const { return cursor_.done(); }
  // GL thread. Asks `job` between pieces, not before the first: the worker
  // asked before the job started.
  [[nodiscard]] Status DrawSome(double job_ms, const JobOptions& job, std::string_view where);

 private:
  const GpuScene& scene_;
  TimedSizer& pieces_;
  bool cut_;
  ScenePartDraw commands_;  // the whole scene as commands, when it is cut
  DrawCursor cursor_;
};
// Every triangle once, in the scene's order (GpuScene::Whole()).
[[nodiscard]] Status DrawWholeScene(const GpuScene::Resources& resources);

}  // namespace visq::gpu
