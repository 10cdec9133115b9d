// The scene's triangles in a bounding-volume hierarchy, shared by every tree
// created on the scene. Its top level holds the triangles of no placement
// and one box per placement of a repeated mesh; each repeated mesh has a
// hierarchy of its own, in its own space, built once.
#include "exact/light_visibility.h"
#include "scene/placement_checks.h"

#include <algorithm>
#include <cmath>

#include "common/check.h"
#include "exact/occluder_index.h"

namespace visq::exact {
namespace {

using Box = std::pair<glm::dvec3, glm::dvec3>;

bool BoxMisses(const glm::dvec3& box_lo, const glm::dvec3& box_hi, const glm::dvec3& lo, const glm::dvec3& hi) {
  return glm::any(glm::lessThan(box_hi, lo)) || glm::any(glm::greaterThan(box_lo, hi));
}

// |world's linear part|, element by element: what a box's half-size
// becomes when the box is placed.
glm::dmat3 Spread(const glm::dmat4& world) {
  glm::dmat3 spread;
  for (int c = 0; c < 3; ++c) spread[c] = glm::abs(glm::dvec3(world[c]));
  return spread;
}

Box TriangleBox(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  return {glm::min(a, glm::min(b, c)), glm::max(a, glm::max(b, c))};
}

}  // namespace

struct SceneTriangleIndex::Impl {
  struct Mesh {
    detail::OccluderIndex boxes;  // of its triangles, in mesh space (nodes only)
    uint32_t scene_mesh = 0;      // into Scene::meshes
    double magnitude = 0.0;       // largest coordinate of its positions
  };
  struct Instance {
    uint32_t mesh;
    uint32_t first_triangle;
    glm::dmat4 world;
    // What placing a box may round by: a few ulps of the largest coordinate
    // the products and sums handle, covered by 1e-9 of it many times over.
    double pad;
    Box box;  // of its placed positions
  };
  std::shared_ptr<const Scene> scene;
  detail::OccluderIndex top;    // items [0, flat.size()): flat triangles; then the instances (nodes only)
  std::vector<uint32_t> flat;   // top item i's scene triangle; empty when the scene has no instances (item i is triangle i)
  std::vector<Instance> instances;
  std::vector<Mesh> meshes;
  size_t triangle_count = 0;

  size_t flat_count() const { return instances.empty() ? triangle_count : flat.size(); }
  uint32_t FlatTriangle(uint32_t item) const { return flat.empty() ? item : flat[item]; }
  Box SceneTriangleBox(uint32_t t) const {
    return TriangleBox(scene->Vertex(t, 0), scene->Vertex(t, 1), scene->Vertex(t, 2));
  }
  Box TopItemBox(uint32_t item) const {
    return item < flat_count() ? SceneTriangleBox(FlatTriangle(item)) : instances[item - flat_count()].box;
  }

  // Calls on_triangle(scene triangle) for each triangle of `instance` whose
  // world box meets [lo, hi], exactly as the flattened triangle's box would.
  // The mesh's hierarchy is searched with each node's box placed in the
  // world (the box around the placed box, padded for its rounding): that
  // holds the world box of every triangle under the node. Each candidate is
  // then placed and tested as the flattened one is.
  template <typename OnTriangle>
  void InInstance(const Instance& instance, const glm::dvec3& lo, const glm::dvec3& hi,
                  const OnTriangle& on_triangle) const {
    const Mesh& indexed = meshes[instance.mesh];
    const SceneMesh& mesh = scene->meshes[indexed.scene_mesh];
    const glm::dmat3 spread = Spread(instance.world);
    std::vector<uint32_t> candidates;
    indexed.boxes.Collect(
        [&](const glm::dvec3& box_lo, const glm::dvec3& box_hi) {
          const glm::dvec3 centre = PlacePoint(instance.world, 0.5 * (box_lo + box_hi));
          const glm::dvec3 half = spread * (0.5 * (box_hi - box_lo)) + glm::dvec3(instance.pad);
          return BoxMisses(centre - half, centre + half, lo, hi);
        },
        &candidates);
    for (uint32_t i : candidates) {
      const glm::uvec3 t = mesh.triangles[i];
      const auto [box_lo, box_hi] =
          TriangleBox(PlacePoint(instance.world, mesh.positions[t[0]]), PlacePoint(instance.world, mesh.positions[t[1]]),
                      PlacePoint(instance.world, mesh.positions[t[2]]));
      if (!BoxMisses(box_lo, box_hi, lo, hi)) on_triangle(instance.first_triangle + i);
    }
  }
};

namespace {

bool FiniteTransform(const glm::dmat4& world) {
  for (int c = 0; c < 4; ++c)
    for (int r = 0; r < 4; ++r)
      if (!std::isfinite(world[c][r])) return false;
  return true;
}

}  // namespace

StatusOr<std::unique_ptr<SceneTriangleIndex>> SceneTriangleIndex::Build(std::shared_ptr<const Scene> shared) {
  VISQ_CHECK(shared != nullptr);
  const Scene& scene = *shared;
  auto impl = std::make_unique<Impl>();
  impl->scene = std::move(shared);
  for (size_t ti = 0; ti < scene.triangles.size(); ++ti) {
    const glm::uvec3 tri = scene.triangles[ti];
    for (int c = 0; c < 3; ++c) {
      if (tri[c] >= scene.positions.size()) {
        return absl::InvalidArgumentError(absl::StrCat("scene.triangles[", ti, "][", c, "]: index ", tri[c],
                                                       " >= ", scene.positions.size(), " positions"));
      }
    }
  }
  impl->triangle_count = scene.TriangleCount();

  // The placements indexed as instances: those that stand for their
  // flattened triangles exactly (a placement that does not, or overlaps an
  // earlier one, is indexed flattened).
  std::vector<uint8_t> instanced(impl->triangle_count, 0);
  std::vector<uint32_t> mesh_slot(scene.meshes.size(), UINT32_MAX);
  std::vector<Box> top_boxes;
  impl->instances.reserve(scene.placements.size());
  const std::vector<uint8_t> in_range = PlacementsInRange(scene);
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    const MeshPlacement& placement = scene.placements[k];
    if (!FiniteTransform(placement.world) || !in_range[k]) continue;
    const SceneMesh& mesh = scene.meshes[placement.mesh];
    if (mesh.triangles.empty() || std::any_of(instanced.begin() + placement.first_triangle,
                    instanced.begin() + placement.first_triangle + mesh.triangles.size(), [](uint8_t b) { return b != 0; })) continue;
    uint32_t& slot = mesh_slot[placement.mesh];
    if (slot == UINT32_MAX) {
      slot = static_cast<uint32_t>(impl->meshes.size());
      Impl::Mesh& indexed = impl->meshes.emplace_back();
      indexed.scene_mesh = placement.mesh;
      for (const glm::dvec3& p : mesh.positions)
        indexed.magnitude = std::max({indexed.magnitude, std::abs(p.x), std::abs(p.y), std::abs(p.z)});
      indexed.boxes.Build(
          static_cast<uint32_t>(mesh.triangles.size()),
          [&](uint32_t i) {
            const glm::uvec3 t = mesh.triangles[i];
            return TriangleBox(mesh.positions[t[0]], mesh.positions[t[1]], mesh.positions[t[2]]);
          },
          /*full_leaves=*/true);
    }
    Impl::Instance& instance = impl->instances.emplace_back();
    instance.mesh = slot;
    instance.first_triangle = placement.first_triangle;
    instance.world = placement.world;
    const glm::dvec3 reach = glm::abs(glm::dvec3(placement.world[3])) + Spread(placement.world) * glm::dvec3(impl->meshes[slot].magnitude);
    instance.pad = 1e-9 * std::max({reach.x, reach.y, reach.z}) + 1e-300;
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    // The placed positions, the flattened scene's to the bit (PlacePoint).
    for (const glm::dvec3& p : mesh.positions) {
      const glm::dvec3 placed = PlacePoint(placement.world, p);
      lo = glm::min(lo, placed);
      hi = glm::max(hi, placed);
    }
    instance.box = {lo, hi};
    top_boxes.emplace_back(lo, hi);
    std::fill_n(instanced.begin() + placement.first_triangle, mesh.triangles.size(), uint8_t{1});
  }

  if (!impl->instances.empty()) {
    for (size_t ti = 0; ti < impl->triangle_count; ++ti) {
      if (!instanced[ti]) impl->flat.push_back(static_cast<uint32_t>(ti));
    }
  }
  impl->flat.shrink_to_fit();
  impl->instances.shrink_to_fit();
  const size_t flat_count = impl->flat_count();
  VISQ_CHECK_LT(flat_count + top_boxes.size(), size_t{UINT32_MAX});
  impl->top.Build(
      static_cast<uint32_t>(flat_count + top_boxes.size()),
      [&](uint32_t item) {
        return item < flat_count ? impl->SceneTriangleBox(impl->FlatTriangle(item)) : top_boxes[item - flat_count];
      },
      /*full_leaves=*/true);
  return std::unique_ptr<SceneTriangleIndex>(new SceneTriangleIndex(std::move(impl)));
}

SceneTriangleIndex::SceneTriangleIndex(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
SceneTriangleIndex::~SceneTriangleIndex() = default;

std::vector<uint32_t> SceneTriangleIndex::InBox(const glm::dvec3& lo, const glm::dvec3& hi) const {
  std::vector<uint32_t> items, out;
  impl_->top.Collect([&](const glm::dvec3& box_lo, const glm::dvec3& box_hi) { return BoxMisses(box_lo, box_hi, lo, hi); },
                     &items);
  const size_t flat_count = impl_->flat_count();
  for (uint32_t item : items) {
    if (item < flat_count) {
      out.push_back(impl_->FlatTriangle(item));
    } else {
      impl_->InInstance(impl_->instances[item - flat_count], lo, hi, [&](uint32_t t) { out.push_back(t); });
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

size_t SceneTriangleIndex::CountInBox(const glm::dvec3& lo, const glm::dvec3& hi, size_t limit) const {
  const auto misses = [&](const glm::dvec3& box_lo, const glm::dvec3& box_hi) { return BoxMisses(box_lo, box_hi, lo, hi); };
  if (impl_->instances.empty()) {
    return impl_->top.CountUpTo(
        misses,
        [&](uint32_t item) {
          const auto [box_lo, box_hi] = impl_->SceneTriangleBox(item);
          return misses(box_lo, box_hi);
        },
        limit);
  }
  std::vector<uint32_t> items;
  impl_->top.Collect(misses, &items);
  const size_t flat_count = impl_->flat_count();
  size_t count = 0;
  for (uint32_t item : items) {
    if (count >= limit) break;
    const auto [box_lo, box_hi] = impl_->TopItemBox(item);
    if (misses(box_lo, box_hi)) continue;
    if (item < flat_count) {
      ++count;
    } else {
      impl_->InInstance(impl_->instances[item - flat_count], lo, hi, [&](uint32_t) { ++count; });
    }
  }
  return std::min(count, limit);
}

size_t SceneTriangleIndex::triangle_count() const { return impl_->triangle_count; }
size_t SceneTriangleIndex::instance_count() const { return impl_->instances.size(); }

size_t SceneTriangleIndex::MemoryBytes() const {
  size_t bytes = sizeof(Impl) + impl_->top.MemoryBytes() + impl_->flat.capacity() * sizeof(uint32_t) +
                 impl_->instances.capacity() * sizeof(Impl::Instance);
  for (const Impl::Mesh& mesh : impl_->meshes) bytes += sizeof(Impl::Mesh) + mesh.boxes.MemoryBytes();
  return bytes;
}

}  // namespace visq::exact
