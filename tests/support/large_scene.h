// A generated scene of any size, for tests whose point is a long structure
// build (an Embree BVH of millions of triangles): a rippled square grid,
// header-only so that suites which already link visq_scene use it without a
// library of their own.
#pragma once

#include <cmath>
#include <string>

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

}  // namespace visq::testing
