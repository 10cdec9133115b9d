#include "scene_draw.h"

#include <algorithm>
#include <chrono>

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

std::vector<ScenePartDraw> DrawPieces(const ScenePartDraw& draw, uint64_t triangles) {
  const size_t stride = draw.indexed ? 5 : 4;
  if (draw.everything || draw.triangles <= triangles) return {draw};
  triangles = std::max<uint64_t>(triangles, 1);
  std::vector<ScenePartDraw> pieces(1);
  pieces.back().indexed = draw.indexed;
  for (size_t c = 0; c + stride <= draw.commands.size(); c += stride) {
    const uint32_t* command = draw.commands.data() + c;
    const uint32_t command_triangles = command[0] / 3, instances = command[1];
    for (uint32_t done = 0; done < command_triangles;) {
      ScenePartDraw& piece = pieces.back();
      const uint64_t room = triangles > piece.triangles ? triangles - piece.triangles : 0;
      const uint64_t per_instance_room = std::max<uint64_t>(1, room / std::max<uint32_t>(instances, 1));
      const uint32_t run = uint32_t(std::min<uint64_t>(command_triangles - done, per_instance_room));
      piece.commands.insert(piece.commands.end(), command, command + stride);
      uint32_t* copy = piece.commands.data() + piece.commands.size() - stride;
      copy[0] = 3 * run;
      copy[2] += 3 * done;  // firstIndex (indexed) or first vertex (arrays)
      piece.triangles += uint64_t(run) * instances;
      done += run;
      if (piece.triangles >= triangles) {
        pieces.emplace_back();
        pieces.back().indexed = draw.indexed;
      }
    }
  }
  if (pieces.back().commands.empty()) pieces.pop_back();
  return pieces;
}

Status DrawInTimedPieces(const GpuScene& scene, const ScenePartDraw& part, TimedSizer& pieces,
                         const JobOptions& job, std::string_view where) {
  VISQ_ASSIGN_OR_RETURN(const GpuScene::Resources* resources, scene.CurrentResources());
  const bool cut = uint64_t(pieces.size()) < part.triangles;
  const std::vector<ScenePartDraw> parts =
      cut ? DrawPieces(part.everything ? scene.WholeAsCommands() : part, uint64_t(pieces.size()))
          : std::vector<ScenePartDraw>{part};
  for (size_t k = 0; k < parts.size(); ++k) {
    if (k > 0) VISQ_RETURN_IF_ERROR(StillWanted(job, where));
    const auto start = std::chrono::steady_clock::now();
    VISQ_RETURN_IF_ERROR(DrawScenePart(*resources, parts[k]));
    if (parts.size() > 1 || !pieces.settled()) {
      glFinish();  // the piece's time, and the stop's chance
      pieces.Measured(int(std::min<uint64_t>(parts[k].triangles, INT32_MAX)), MillisecondsSince(start));
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
