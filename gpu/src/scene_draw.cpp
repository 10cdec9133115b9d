#include "scene_draw.h"

#include <algorithm>
#include <chrono>
#include <limits>

#include <epoxy/gl.h>

#include "common/check.h"
#include "common/job_timing.h"
#include "gl_check.h"

namespace visq::gpu {

Status DrawScenePart(const GpuScene::Resources& resources, const ScenePartDraw& part) {
  glBindVertexArray(resources.vertex_array.id());
  if (part.everything) {
    glBindBuffer(GL_DRAW_INDIRECT_BUFFER, resources.whole_draw.id());
    glMultiDrawArraysIndirect(GL_TRIANGLES, nullptr, resources.whole_draws, 0);
    glBindBuffer(GL_DRAW_INDIRECT_BUFFER, 0);
    VISQ_GL_CHECK("scene draw");
    return absl::OkStatus();
  }
  if (part.commands.empty()) return absl::OkStatus();
  VISQ_CHECK_EQ(part.commands.size() % (part.indexed ? 5 : 4), 0u);
  GlBuffer commands;
  glNamedBufferStorage(commands.id(), part.commands.size() * sizeof(uint32_t), part.commands.data(), 0);
  glBindBuffer(GL_DRAW_INDIRECT_BUFFER, commands.id());
  const GLsizei draws = static_cast<GLsizei>(part.draws());
  if (part.indexed)
    glMultiDrawElementsIndirect(GL_TRIANGLES, GL_UNSIGNED_INT, nullptr, draws, 0);
  else
    glMultiDrawArraysIndirect(GL_TRIANGLES, nullptr, draws, 0);
  glBindBuffer(GL_DRAW_INDIRECT_BUFFER, 0);
  VISQ_GL_CHECK("scene draw");
  return absl::OkStatus();
}

DrawCursor::DrawCursor(const ScenePartDraw& draw) : draw_(&draw) {}

bool DrawCursor::done() const {
  if (draw_->everything) return whole_taken_;
  return command_ * Stride() + Stride() > draw_->commands.size();
}

ScenePartDraw DrawCursor::Next(uint64_t triangles) {
  ScenePartDraw piece;
  piece.indexed = draw_->indexed;
  if (draw_->everything) {
    if (!whole_taken_) piece = *draw_;
    whole_taken_ = true;
    return piece;
  }
  triangles = std::max<uint64_t>(triangles, 1);
  const size_t stride = Stride();
  while (!done() && piece.triangles < triangles) {
    const uint32_t* command = draw_->commands.data() + command_ * stride;
    const uint32_t command_triangles = command[0] / 3, instances = std::max<uint32_t>(command[1], 1);
    const uint64_t room = triangles - piece.triangles;
    const uint64_t per_instance_room = std::max<uint64_t>(1, room / instances);
    const uint32_t run = uint32_t(std::min<uint64_t>(command_triangles - done_in_command_, per_instance_room));
    piece.commands.insert(piece.commands.end(), command, command + stride);
    uint32_t* copy = piece.commands.data() + piece.commands.size() - stride;
    copy[0] = 3 * run;
    copy[2] += 3 * done_in_command_;  // firstIndex (indexed) or first vertex (arrays)
    piece.triangles += uint64_t(run) * command[1];
    done_in_command_ += run;
    if (done_in_command_ >= command_triangles) {
      ++command_;
      done_in_command_ = 0;
    }
  }
  return piece;
}

Status DrawInTimedPieces(const GpuScene& scene, const ScenePartDraw& part, TimedSizer& pieces,
                         const JobOptions& job, std::string_view where) {
  DrawAcrossJobs draw(scene, part, pieces);
  return draw.DrawSome(std::numeric_limits<double>::infinity(), job, where);
}

// Each piece is cut at the sizer's size of the moment, so a draw that
// started small grows its pieces as it learns.
DrawAcrossJobs::DrawAcrossJobs(const GpuScene& scene, const ScenePartDraw& part, TimedSizer& pieces)
    : scene_(scene),
      pieces_(pieces),
      cut_(uint64_t(pieces.size()) < part.triangles),
      commands_(cut_ && part.everything ? scene.WholeAsCommands() : ScenePartDraw{}),
      cursor_(cut_ && part.everything ? commands_ : part) {}

Status DrawAcrossJobs::DrawSome(double job_ms, const JobOptions& job, std::string_view where) {
  VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* resources, scene_.CurrentResources());
  const auto job_start = std::chrono::steady_clock::now();
  for (bool first = true; !cursor_.done(); first = false) {
    if (!first) {
      VISQ_RETURN_IF_ERROR(job.stop.Check(where));
      if (MillisecondsSince(job_start) >= job_ms) return absl::OkStatus();
    }
    const ScenePartDraw piece = cut_ ? cursor_.Next(uint64_t(pieces_.size())) : cursor_.Next(UINT64_MAX);
    const auto start = std::chrono::steady_clock::now();
    VISQ_RETURN_IF_ERROR(DrawScenePart(*resources, piece));
    if (cut_ || !pieces_.settled()) {
      glFinish();  // the piece's time, and the stop's chance
      pieces_.Measured(int(std::min<uint64_t>(piece.triangles, INT32_MAX)), MillisecondsSince(start));
    }
  }
  return absl::OkStatus();
}

Status DrawWholeScene(const GpuScene::Resources& resources) {
  ScenePartDraw whole;
  whole.everything = true;
  return DrawScenePart(resources, whole);
}

}  // namespace visq::gpu
