// Draws a planned part of a GpuScene (GpuScene::ScenePartDraw) with the
// scene's vertex array: every algorithm's draws of scene triangles go
// through here, so that each reads its corners and placements one way
// (scene_vertex.glsl). GL thread only; the caller's program and targets
// are bound.
#pragma once

#include "common/status.h"
#include "gpu_scene_resources.h"

namespace visq::gpu {

[[nodiscard]] Status DrawScenePart(const GpuScene::Resources& resources, const ScenePartDraw& part);
// Every triangle once, in the scene's order (GpuScene::Whole()).
[[nodiscard]] Status DrawWholeScene(const GpuScene::Resources& resources);

}  // namespace visq::gpu
