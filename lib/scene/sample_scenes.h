// Scenes the project generates itself, so a fresh server has something
// resident and tests have inputs without the shared scene folder.
#pragma once

#include <array>
#include <filesystem>
#include <span>

#include "common/status.h"
#include "scene/scene.h"

namespace visq {

// A Cornell box, 2 units wide, Y up, floor at y = 0, open towards +z: red
// left wall, green right wall, white floor, ceiling and back wall, a short
// and a tall box, and an emissive patch just under the ceiling.
Scene MakeCornellBox();

// Appends an axis-aligned box (12 triangles, outward-facing) as a new node.
void AddBox(Scene& scene, const std::string& node_name, const glm::dvec3& lo, const glm::dvec3& hi,
            uint32_t material);
// Appends a quad (2 triangles) origin, origin + u, origin + u + v, origin + v
// as a new node; its front faces u x v.
void AddQuad(Scene& scene, const std::string& node_name, const glm::dvec3& origin, const glm::dvec3& u,
             const glm::dvec3& v, uint32_t material);
// Appends one triangle a, b, c as a new node; its front faces (b - a) x (c - a).
void AddTriangle(Scene& scene, const std::string& node_name, const glm::dvec3& a, const glm::dvec3& b,
                 const glm::dvec3& c, uint32_t material);
// A scene of loose triangles, all in one node "triangles" with one grey
// material, bounds set: the input of most algorithm tests.
Scene SceneOfTriangles(std::span<const std::array<glm::dvec3, 3>> triangles);
// Recomputes bounds after edits.
void UpdateBounds(Scene& scene);

// Writes every generated sample scene into `repository` as <name>/<name>.gltf
// unless a scene of that name is already there.
[[nodiscard]] Status WriteSampleScenes(const std::filesystem::path& repository);

}  // namespace visq
