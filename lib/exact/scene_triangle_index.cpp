// The scene's triangles in a bounding-volume hierarchy, shared by every tree
// created on the scene.
#include "exact/light_visibility.h"

#include <algorithm>

#include "exact/occluder_index.h"

namespace visq::exact {

struct SceneTriangleIndex::Impl {
  detail::OccluderIndex boxes;
  size_t triangle_count = 0;
};

StatusOr<std::unique_ptr<SceneTriangleIndex>> SceneTriangleIndex::Build(const Scene& scene) {
  auto impl = std::make_unique<Impl>();
  std::vector<std::pair<glm::dvec3, glm::dvec3>> boxes;
  boxes.reserve(scene.triangles.size());
  for (size_t ti = 0; ti < scene.triangles.size(); ++ti) {
    const glm::uvec3 tri = scene.triangles[ti];
    for (int c = 0; c < 3; ++c) {
      if (tri[c] >= scene.positions.size()) {
        return absl::InvalidArgumentError(absl::StrCat("scene.triangles[", ti, "][", c, "]: index ", tri[c],
                                                       " >= ", scene.positions.size(), " positions"));
      }
    }
    const glm::dvec3 &a = scene.positions[tri[0]], &b = scene.positions[tri[1]], &c = scene.positions[tri[2]];
    boxes.emplace_back(glm::min(a, glm::min(b, c)), glm::max(a, glm::max(b, c)));
  }
  impl->triangle_count = scene.triangles.size();
  impl->boxes.Build(std::move(boxes));
  return std::unique_ptr<SceneTriangleIndex>(new SceneTriangleIndex(std::move(impl)));
}

SceneTriangleIndex::SceneTriangleIndex(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
SceneTriangleIndex::~SceneTriangleIndex() = default;

std::vector<uint32_t> SceneTriangleIndex::InBox(const glm::dvec3& lo, const glm::dvec3& hi) const {
  std::vector<uint32_t> out;
  impl_->boxes.Collect(
      [&](const glm::dvec3& box_lo, const glm::dvec3& box_hi) {
        return glm::any(glm::lessThan(box_hi, lo)) || glm::any(glm::greaterThan(box_lo, hi));
      },
      &out);
  std::sort(out.begin(), out.end());
  return out;
}

size_t SceneTriangleIndex::CountInBox(const glm::dvec3& lo, const glm::dvec3& hi, size_t limit) const {
  return impl_->boxes.CountUpTo(
      [&](const glm::dvec3& box_lo, const glm::dvec3& box_hi) {
        return glm::any(glm::lessThan(box_hi, lo)) || glm::any(glm::greaterThan(box_lo, hi));
      },
      limit);
}

size_t SceneTriangleIndex::triangle_count() const { return impl_->triangle_count; }
size_t SceneTriangleIndex::MemoryBytes() const { return sizeof(Impl) + impl_->boxes.MemoryBytes(); }

}  // namespace visq::exact
