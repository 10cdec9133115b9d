#include "scene_draw.h"

#include <epoxy/gl.h>

#include "common/check.h"
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

Status DrawWholeScene(const GpuScene::Resources& resources) {
  ScenePartDraw whole;
  whole.everything = true;
  return DrawScenePart(resources, whole);
}

}  // namespace visq::gpu
