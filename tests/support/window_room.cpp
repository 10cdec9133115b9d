#include "window_room.h"

#include <cmath>
#include <random>

#include "scene/sample_scenes.h"

namespace visq::testing {

// An n_u x n_v grid of quads over origin + [0, 1] u + [0, 1] v as one node,
// corners shared (as a modelled floor would be); fronts face u x v.
void AddGrid(Scene& s, const std::string& name, const glm::dvec3& origin, const glm::dvec3& u, const glm::dvec3& v,
             int n_u, int n_v) {
  const uint32_t base = static_cast<uint32_t>(s.positions.size());
  for (int j = 0; j <= n_v; ++j)
    for (int i = 0; i <= n_u; ++i)
      s.positions.push_back(origin + (static_cast<double>(i) / n_u) * u + (static_cast<double>(j) / n_v) * v);
  const uint32_t node = static_cast<uint32_t>(s.nodes.size());
  s.nodes.push_back(SceneNode{name, static_cast<int>(node), -1, glm::dmat4(1.0),
                              static_cast<uint32_t>(s.triangles.size()), static_cast<uint32_t>(2 * n_u * n_v)});
  const auto at = [&](int i, int j) { return base + static_cast<uint32_t>(j * (n_u + 1) + i); };
  for (int j = 0; j < n_v; ++j)
    for (int i = 0; i < n_u; ++i)
      for (const glm::uvec3& t : {glm::uvec3(at(i, j), at(i + 1, j), at(i + 1, j + 1)),
                                  glm::uvec3(at(i, j), at(i + 1, j + 1), at(i, j + 1))}) {
        s.triangles.push_back(t);
        s.triangle_material.push_back(0);
        s.triangle_node.push_back(node);
      }
}

// A box centred at c with half-extents h along the orthonormal axes a, b
// and a x b (12 triangles, outward-facing): a tilted blind slat.
void AddOrientedBox(Scene& s, const std::string& name, const glm::dvec3& c, const glm::dvec3& a, const glm::dvec3& b,
                    const glm::dvec3& h) {
  const glm::dvec3 axes[3] = {a, b, glm::cross(a, b)};
  const uint32_t base = static_cast<uint32_t>(s.positions.size());
  for (int i = 0; i < 8; ++i) {
    s.positions.push_back(c + (i & 1 ? h.x : -h.x) * axes[0] + (i & 2 ? h.y : -h.y) * axes[1] +
                          (i & 4 ? h.z : -h.z) * axes[2]);
  }
  // Corner i has bit 0 = a, bit 1 = b, bit 2 = a x b: a right-handed frame,
  // so the faces of AddBox's table are wound outward here too.
  static constexpr glm::uvec3 kFaces[12] = {{0, 2, 3}, {0, 3, 1}, {4, 5, 7}, {4, 7, 6}, {0, 4, 6}, {0, 6, 2},
                                            {1, 3, 7}, {1, 7, 5}, {0, 1, 5}, {0, 5, 4}, {2, 6, 7}, {2, 7, 3}};
  const uint32_t node = static_cast<uint32_t>(s.nodes.size());
  s.nodes.push_back(SceneNode{name, static_cast<int>(node), -1, glm::dmat4(1.0),
                              static_cast<uint32_t>(s.triangles.size()), 12});
  for (const auto& f : kFaces) {
    s.triangles.push_back(f + base);
    s.triangle_material.push_back(0);
    s.triangle_node.push_back(node);
  }
}

// The grille's, the foliage's and the slivers' room: 5 x 2.8 x 5 (Y up,
// floor at y = 0, x in [0, 5], z in [-2.5, 2.5]), its surfaces facing its
// inside, with a 2.1 x 1.4 opening in its x = 0 wall (y in [0.8, 2.2], z in
// [-1.05, 1.05]). The floor is a 32 x 32 grid, as a mesh would be modelled.
Scene MakeWindowRoom() {
  Scene s;
  s.materials = {{"white", glm::dvec3(0.7), glm::dvec3(0.0)}};
  AddGrid(s, "floor", {0, 0, -2.5}, {0, 0, 5}, {5, 0, 0}, 32, 32);
  AddQuad(s, "ceiling", {0, 2.8, -2.5}, {5, 0, 0}, {0, 0, 5}, 0);
  AddQuad(s, "back_wall", {5, 0, -2.5}, {0, 0, 5}, {0, 2.8, 0}, 0);
  AddQuad(s, "side_wall_near", {0, 0, -2.5}, {5, 0, 0}, {0, 2.8, 0}, 0);
  AddQuad(s, "side_wall_far", {0, 0, 2.5}, {0, 2.8, 0}, {5, 0, 0}, 0);
  AddQuad(s, "wall_below", {0, 0, -2.5}, {0, 0.8, 0}, {0, 0, 5}, 0);
  AddQuad(s, "wall_above", {0, 2.2, -2.5}, {0, 0.6, 0}, {0, 0, 5}, 0);
  AddQuad(s, "wall_left", {0, 0.8, -2.5}, {0, 1.4, 0}, {0, 0, 1.45}, 0);
  AddQuad(s, "wall_right", {0, 0.8, 1.05}, {0, 1.4, 0}, {0, 0, 1.45}, 0);
  return s;
}

// The grille (issue 44, section 3): a closed 5 x 2.8 x 5 room (Y up, floor
// at y = 0, x in [0, 5], z in [-2.5, 2.5]) lit through a 2.1 x 1.4 window in
// its x = 0 wall by a 1.6 x 1.6 area light 1 m outside. The window has a
// frame, sash bars making 3 x 4 panes (no glass) and, inside, a Venetian
// blind of 20 slats tilted 50 degrees, partly open. From the lit floor the
// light is seen through dozens of thin occluders at once: every point there
// is in the penumbra of many of them, the exact method's worst case (many
// fragments per point), where a ray caster's error falls as fast as ever.
// The floor is a 32 x 32 grid (as a mesh would be modelled): 2,496
// triangles in all, 432 of them the window frame, bars and blind.
Scene MakeGrilleScene() {
  Scene s = MakeWindowRoom();
  // The frame, 5 cm inside the opening: the panes span y in [0.85, 2.15], z in [-1, 1].
  AddBox(s, "frame_bottom", {-0.05, 0.8, -1.05}, {0.05, 0.85, 1.05}, 0);
  AddBox(s, "frame_top", {-0.05, 2.15, -1.05}, {0.05, 2.2, 1.05}, 0);
  AddBox(s, "frame_left", {-0.05, 0.85, -1.05}, {0.05, 2.15, -1.0}, 0);
  AddBox(s, "frame_right", {-0.05, 0.85, 1.0}, {0.05, 2.15, 1.05}, 0);
  // Sash bars 3 cm wide: two upright, and three across cut between them
  // (boxes that do not pass through each other, as a modeller would join them).
  const double bar = 0.015, z_bars[2] = {-1.0 + 2.0 / 3.0, -1.0 + 4.0 / 3.0};
  for (const double z : z_bars) AddBox(s, "sash_upright", {-0.02, 0.85, z - bar}, {0.02, 2.15, z + bar}, 0);
  for (int row = 1; row < 4; ++row) {
    const double y = 0.85 + 1.3 * row / 4.0;
    const double z_cuts[4] = {-1.0, z_bars[0], z_bars[1], 1.0};
    for (int c = 0; c < 3; ++c) {
      AddBox(s, "sash_bar", {-0.02, y - bar, z_cuts[c] + (c > 0 ? bar : 0.0)},
                   {0.02, y + bar, z_cuts[c + 1] - (c < 2 ? bar : 0.0)}, 0);
    }
  }
  // The blind: a head rail and 20 slats 5 cm deep, 3 mm thick, 1.96 m long,
  // on a 6.5 cm pitch and tilted 50 degrees, so each hides 3.8 cm of its
  // pitch straight on: the light comes through the gaps between them.
  AddBox(s, "blind_rail", {0.055, 2.15, -1.0}, {0.11, 2.2, 1.0}, 0);
  const double tilt = 50.0 * M_PI / 180.0;
  const glm::dvec3 across(std::cos(tilt), std::sin(tilt), 0.0), thick(-std::sin(tilt), std::cos(tilt), 0.0);
  for (int i = 0; i < 20; ++i) {
    const double y = 0.85 + 1.3 * (i + 0.5) / 20.0;
    AddOrientedBox(s, "slat", {0.08, y, 0.0}, across, thick, {0.025, 0.0015, 0.98});
  }
  UpdateBounds(s);
  return s;
}

Scene MakeFurnishedWindowRoom(uint32_t seed) {
  Scene s = MakeWindowRoom();
  AddBox(s, "frame_bottom", {-0.05, 0.8, -1.05}, {0.05, 0.85, 1.05}, 0);
  AddBox(s, "frame_top", {-0.05, 2.15, -1.05}, {0.05, 2.2, 1.05}, 0);
  for (const double z : {-1.0 / 3.0, 1.0 / 3.0}) AddBox(s, "sash_upright", {-0.02, 0.85, z - 0.015}, {0.02, 2.15, z + 0.015}, 0);
  AddBox(s, "sash_bar", {-0.02, 1.485, -1.0}, {0.02, 1.515, 1.0}, 0);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  // Tables: a top at 0.75 m on four legs.
  for (int i = 0; i < 6; ++i) {
    const glm::dvec3 at(1.0 + 3.2 * u(rng), 0.0, -1.8 + 3.6 * u(rng));
    AddBox(s, "table_top", at + glm::dvec3(-0.6, 0.72, -0.4), at + glm::dvec3(0.6, 0.76, 0.4), 0);
    for (const double dx : {-0.55, 0.51})
      for (const double dz : {-0.35, 0.31})
        AddBox(s, "table_leg", at + glm::dvec3(dx, 0.0, dz), at + glm::dvec3(dx + 0.04, 0.72, dz + 0.04), 0);
  }
  // Bookshelves along both side walls, x in [1.5, 4.5], five shelves of books.
  for (const double wall : {-2.5, 2.5}) {
    const double inward = wall < 0 ? 1.0 : -1.0;
    for (int shelf = 0; shelf < 5; ++shelf) {
      const double y = 0.1 + 0.4 * shelf;
      AddBox(s, "shelf", {1.5, y - 0.02, std::min(wall, wall + 0.3 * inward)}, {4.5, y, std::max(wall, wall + 0.3 * inward)}, 0);
      for (double x = 1.52; x < 4.45;) {
        const double width = 0.025 + 0.035 * u(rng), height = 0.18 + 0.15 * u(rng), depth = 0.18 + 0.08 * u(rng);
        const double z0 = wall + 0.02 * inward, z1 = wall + (0.02 + depth) * inward;
        AddBox(s, "book", {x, y, std::min(z0, z1)}, {x + width, y + height, std::max(z0, z1)}, 0);
        x += width + 0.004;
      }
    }
  }
  // Plants: 600 leaves each, between 0.8 and 1.8 m, around a stem.
  const uint32_t node = static_cast<uint32_t>(s.nodes.size());
  const uint32_t first = static_cast<uint32_t>(s.triangles.size());
  for (int p = 0; p < 4; ++p) {
    const glm::dvec3 stem(1.2 + 3.0 * u(rng), 0.0, -1.6 + 3.2 * u(rng));
    for (int leaf = 0; leaf < 600; ++leaf) {
      const double a = 2.0 * M_PI * u(rng), r = 0.35 * std::sqrt(u(rng));
      const glm::dvec3 c = stem + glm::dvec3(r * std::cos(a), 0.8 + u(rng), r * std::sin(a));
      const uint32_t base = static_cast<uint32_t>(s.positions.size());
      for (int k = 0; k < 3; ++k) s.positions.push_back(c + 0.05 * glm::dvec3(u(rng) - 0.5, u(rng) - 0.5, u(rng) - 0.5));
      s.triangles.push_back(glm::uvec3(base, base + 1, base + 2));
      s.triangle_material.push_back(0);
      s.triangle_node.push_back(node);
    }
  }
  s.nodes.push_back(SceneNode{"plants", static_cast<int>(node), -1, glm::dmat4(1.0), first,
                              static_cast<uint32_t>(s.triangles.size()) - first});
  UpdateBounds(s);
  return s;
}

}  // namespace visq::testing
