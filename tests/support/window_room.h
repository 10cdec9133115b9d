// Rooms lit through a window, built here rather than loaded: the exact
// method's and the hidden-sample map's worst cases (issue 44 section 3,
// issue 49 section 2), shared by the benches and the tests that measure and
// check them.
#pragma once

#include <cstdint>
#include <string>

#include <glm/glm.hpp>

#include "scene/scene.h"

namespace visq::testing {

// An n_u x n_v grid of quads over origin + [0, 1] u + [0, 1] v as one node,
// corners shared (as a modelled floor would be); fronts face u x v.
void AddGrid(Scene& s, const std::string& name, const glm::dvec3& origin, const glm::dvec3& u, const glm::dvec3& v,
             int n_u, int n_v);

// A box centred at c with half-extents h along the orthonormal axes a, b
// and a x b (12 triangles, outward-facing): a tilted blind slat.
void AddOrientedBox(Scene& s, const std::string& name, const glm::dvec3& c, const glm::dvec3& a, const glm::dvec3& b,
                    const glm::dvec3& h);

// A closed 5 x 2.8 x 5 room (Y up, floor at y = 0, x in [0, 5], z in
// [-2.5, 2.5]), its surfaces facing its inside, with a 2.1 x 1.4 opening in
// its x = 0 wall (y in [0.8, 2.2], z in [-1.05, 1.05]). The floor is a
// 32 x 32 grid, as a mesh would be modelled.
Scene MakeWindowRoom();

// The window room with a frame, sash bars making 3 x 4 panes (no glass)
// and, inside, a Venetian blind of 20 slats tilted 50 degrees, partly open:
// 2,496 triangles, 432 of them the window frame, bars and blind. Lit by an
// area light outside the window, every lit floor point sees it through
// dozens of thin occluders at once.
Scene MakeGrilleScene();

// The window room with the grille's frame and sash bars (no blind), lit
// through its window, and furnished: six tables, two bookshelves along the
// side walls full of books, and four leafy plants, about 13,000 triangles,
// most of them above the window's sill and far from it. Their shadows on
// the floor are small and near them, though a segment from the window
// can pass over most of them nearly level.
Scene MakeFurnishedWindowRoom(uint32_t seed);

}  // namespace visq::testing
