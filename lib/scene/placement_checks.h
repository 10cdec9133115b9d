// What every placement of a scene needs checked or bounded, at the cost of
// its mesh rather than of every placement: a level places one mesh
// thousands of times (300 copies of Sponza hold 10,200 placements of 34
// meshes), and checking each placement's corners, or placing each of its
// points for the bounds, made its upload cost seconds.
#pragma once

#include <array>
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

// The bounds of one mesh's points placed by PlacePoint, equal as numbers to
// placing every point (a zero's sign aside), for each placement asked, at
// the cost of a few points a placement where placements share a linear
// part: a level's copies of a prefab differ by their translation, and its
// meshes are turned (Sponza's nodes swap y and z).
//
// Why a few points suffice: a placed coordinate is the exact affine value
// L(x) + t rounded by at most B (PlacePoint's four products and three sums,
// bounded from the mesh's largest magnitudes and |t|), and L(x) computed
// without t is within B_L of the exact one. A point whose computed L lies
// more than 2 B + 2 B_L below the largest computed L is placed strictly
// below that point, so only the points within that margin of the top (or
// bottom) are placed. For each linear part seen twice the points within the
// margin of a translation of kMaxOrderedTranslation are kept; other
// transforms, and larger translations, are placed point by point.
class PlacedMeshBounds {
 public:
  static constexpr double kMaxOrderedTranslation = 1e9;

  // `positions` are the mesh's, here and at every call.
  explicit PlacedMeshBounds(const std::vector<glm::dvec3>& positions);

  Bounds Of(const glm::dmat4& world, const std::vector<glm::dvec3>& positions);
  // Placements answered from the kept extremes (not point by point), for
  // tests and benches.
  uint64_t answered_by_extremes() const { return answered_by_extremes_; }

 private:
  // A point and its computed L in one row.
  struct Candidate {
    double value;
    uint32_t point;
  };
  struct Extremes {
    glm::dmat3 linear;
    // Per row: the points near the largest and the smallest computed L.
    std::array<std::vector<Candidate>, 3> top, bottom;
    glm::dvec3 largest{0.0}, smallest{0.0};
  };
  const Extremes* ExtremesFor(const glm::dmat3& linear, const glm::dvec3& linear_magnitude,
                              const std::vector<glm::dvec3>& positions);

  Bounds local_;
  glm::dvec3 largest_magnitude_{0.0};
  std::vector<glm::dmat3> seen_once_;
  std::vector<Extremes> extremes_;
  uint64_t answered_by_extremes_ = 0;
};

}  // namespace visq
