// Generated scenes of any size, for tests and benchmarks whose point is a
// large scene (an Embree BVH of millions of triangles, a level of repeated
// meshes): a rippled square grid and copies of a scene side by side,
// header-only so that suites which already link visq_scene use them without
// a library of their own.
#pragma once

#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include <glm/gtc/matrix_transform.hpp>

#include "scene/scene.h"

namespace visq::testing {

// `cells` x `cells` squares over [-1, 1] x [-1, 1] at y ~ 0 (2 cells^2
// triangles, front faces up), one node and one grey material.
inline Scene MakeRippledGrid(int cells) {
  Scene scene;
  scene.materials = {{"grey", glm::dvec3(0.5), glm::dvec3(0.0)}};
  const auto side = static_cast<uint32_t>(cells + 1);
  scene.positions.reserve(size_t(side) * side);
  for (uint32_t j = 0; j < side; ++j)
    for (uint32_t i = 0; i < side; ++i) {
      const double x = -1.0 + 2.0 * i / cells, z = -1.0 + 2.0 * j / cells;
      scene.positions.emplace_back(x, 0.01 * std::sin(37.0 * x) * std::cos(23.0 * z), z);
    }
  scene.triangles.reserve(2 * size_t(cells) * cells);
  for (uint32_t j = 0; j < uint32_t(cells); ++j)
    for (uint32_t i = 0; i < uint32_t(cells); ++i) {
      const uint32_t a = j * side + i, b = a + 1, c = a + side, d = c + 1;
      scene.triangles.emplace_back(a, c, b);
      scene.triangles.emplace_back(b, c, d);
    }
  scene.triangle_material.assign(scene.triangles.size(), 0);
  scene.triangle_node.assign(scene.triangles.size(), 0);
  SceneNode node;
  node.name = "grid";
  node.triangle_count = static_cast<uint32_t>(scene.triangles.size());
  scene.nodes.push_back(node);
  for (const glm::dvec3& p : scene.positions) scene.bounds.Extend(p);
  return scene;
}

// `mesh`'s triangles taken as one mesh in its own space and placed once by
// each of `worlds` (none of them mirroring), held once as placements of
// it as the loader holds a mesh that several nodes share.
// Materials and nodes are `mesh`'s, except that a placement is one node's
// (as the loader makes them): a mesh of several nodes is placed as one node
// covering the level. A scene that has placements of its own, or too few
// triangles to instance, is placed flattened only.
inline Scene PlaceMesh(const Scene& mesh, const std::vector<glm::dmat4>& worlds) {
  Scene out;
  out.materials = mesh.materials;
  out.nodes = mesh.nodes;
  const bool as_placements =
      worlds.size() >= 2 && mesh.placements.empty() && mesh.TriangleCount() >= kFewestTrianglesToInstance;
  if (as_placements) out.meshes.push_back(SceneMesh{mesh.positions, mesh.triangles});
  for (const glm::dmat4& world : worlds) {
    const auto base = static_cast<uint32_t>(out.positions.size());
    if (as_placements)
      out.placements.push_back(MeshPlacement{0, static_cast<uint32_t>(out.triangles.size()), base, world});
    for (const glm::dvec3& p : mesh.positions) {
      out.positions.push_back(PlacePoint(world, p));
      out.bounds.Extend(out.positions.back());
    }
    for (const glm::uvec3& t : mesh.triangles) out.triangles.push_back(t + glm::uvec3(base));
    out.triangle_material.insert(out.triangle_material.end(), mesh.triangle_material.begin(),
                                 mesh.triangle_material.end());
    out.triangle_node.insert(out.triangle_node.end(), mesh.triangle_node.begin(), mesh.triangle_node.end());
  }
  if (as_placements && out.nodes.size() > 1) {
    SceneNode level;
    level.name = "level";
    level.triangle_count = static_cast<uint32_t>(out.triangles.size());
    out.nodes = {level};
    out.triangle_node.assign(out.triangles.size(), 0);
  }
  HoldPlacementsOnce(out);
  return out;
}

// A prefab placed by each of `worlds`: every part (a scene of its own, in
// the prefab's space) a mesh that every world places, as the loader records
// a node tree that several parents share. Materials are the first part's;
// each part is one node.
inline Scene PlaceMeshes(const std::vector<Scene>& parts, const std::vector<glm::dmat4>& worlds) {
  Scene out;
  if (!parts.empty()) out.materials = parts.front().materials;
  for (const Scene& part : parts) {
    out.meshes.push_back(SceneMesh{part.positions, part.triangles});
    SceneNode node;
    node.name = "part" + std::to_string(out.nodes.size());
    out.nodes.push_back(node);
  }
  for (const glm::dmat4& world : worlds) {
    for (uint32_t m = 0; m < parts.size(); ++m) {
      const Scene& part = parts[m];
      const auto base = static_cast<uint32_t>(out.positions.size());
      out.placements.push_back(MeshPlacement{m, static_cast<uint32_t>(out.triangles.size()), base, world});
      for (const glm::dvec3& p : part.positions) {
        out.positions.push_back(PlacePoint(world, p));
        out.bounds.Extend(out.positions.back());
      }
      for (const glm::uvec3& t : part.triangles) out.triangles.push_back(t + glm::uvec3(base));
      out.triangle_material.insert(out.triangle_material.end(), part.triangles.size(), 0u);
      out.triangle_node.insert(out.triangle_node.end(), part.triangles.size(), m);
    }
  }
  HoldPlacementsOnce(out);
  return out;
}

// `scene`'s triangles split by node, each part over the positions it uses:
// the parts of a prefab for PlaceMeshes.
inline std::vector<Scene> SplitByNode(const Scene& placed) {
  const Scene& scene = placed.Flattened();
  std::vector<Scene> parts(scene.nodes.size());
  std::vector<uint32_t> vertex_of(scene.positions.size(), UINT32_MAX), vertex_part(scene.positions.size(), UINT32_MAX);
  for (uint32_t t = 0; t < scene.TriangleCount(); ++t) {
    const uint32_t n = scene.triangle_node[t];
    Scene& part = parts[n];
    glm::uvec3 corners;
    for (int c = 0; c < 3; ++c) {
      const uint32_t v = scene.triangles[t][c];
      if (vertex_part[v] != n) {
        vertex_part[v] = n;
        vertex_of[v] = static_cast<uint32_t>(part.positions.size());
        part.positions.push_back(scene.positions[v]);
      }
      corners[c] = vertex_of[v];
    }
    part.triangles.push_back(corners);
  }
  std::vector<Scene> kept;
  for (Scene& part : parts) {
    if (part.triangles.size() < kFewestTrianglesToInstance) continue;
    part.materials = scene.materials;
    kept.push_back(std::move(part));
  }
  return kept;
}

// Where `copies` copies of `scene` stand on a square grid in x and z, one
// tenth of the scene's extent apart, the first where `scene` is.
inline std::vector<glm::dmat4> CopyWorlds(const Scene& scene, int copies) {
  const int side = int(std::ceil(std::sqrt(double(copies))));
  const glm::dvec3 e = scene.bounds.Extent();
  std::vector<glm::dmat4> worlds;
  for (int c = 0; c < copies; ++c)
    worlds.push_back(glm::translate(glm::dmat4(1.0), glm::dvec3(1.1 * e.x * (c % side), 0.0, 1.1 * e.z * (c / side))));
  return worlds;
}

// Those copies as a level made of one repeated mesh (PlaceMesh).
inline Scene MakeCopies(const Scene& scene, int copies) {
  if (copies <= 1) return scene;
  return PlaceMesh(scene, CopyWorlds(scene, copies));
}

// The same scene with its placements forgotten: what every structure builds
// when it flattens everything.
inline Scene Flattened(const Scene& scene) { return Scene(scene.Flattened()); }

}  // namespace visq::testing
