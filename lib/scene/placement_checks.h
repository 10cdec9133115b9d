// What every placement of a scene needs checked or bounded, at the cost of
// its mesh rather than of every placement: a level places one mesh
// thousands of times (300 copies of Sponza hold 10,200 placements of 34
// meshes), and checking each placement's corners, or placing each of its
// points for the bounds, made its upload cost seconds.
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include <glm/glm.hpp>

#include "scene/scene.h"

namespace visq {

// PlacementInRange of every placement, in order: each mesh's corners are
// checked once, however often it is placed.
std::vector<uint8_t> PlacementsInRange(const Scene& scene);

// The bounds of a mesh's positions, mesh space, for each of the scene's
// meshes.
std::vector<Bounds> MeshBounds(const Scene& scene);
Bounds BoundsOf(const std::vector<glm::dvec3>& points);

// The bounds of points with bounds `local` once placed by `world`
// (PlacePoint), when `world` only scales and translates them (its linear
// part is diagonal): each placed coordinate is then PlacePoint's rounding of
// a monotone function of one local coordinate, so the placed points' bounds
// are their extremes' placed, equal as numbers to placing every point
// (a zero's sign aside). nullopt for any other transform: the caller places
// every point.
std::optional<Bounds> PlacedBoundsWithoutRotation(const glm::dmat4& world, const Bounds& local);

}  // namespace visq
