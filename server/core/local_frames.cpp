#include "core/local_frames.h"

#include <algorithm>
#include <cmath>

namespace visq::core {
namespace {

// The region's side and corner for a query box: side 2c, corner on the grid
// of step c, c = 2^ceil(log2(extent)). The box's extent is at most c, so it
// fits from its grid cell's corner.
void RegionOf(const Bounds& box, glm::dvec3& lo, double& side) {
  const glm::dvec3 extent = box.Extent();
  const double largest = std::max({extent.x, extent.y, extent.z, 0x1p-40});
  const double step = std::ldexp(1.0, std::ilogb(largest) + 1);  // > largest, a power of two
  lo = glm::floor(box.min / step) * step;
  side = 2.0 * step;
}

// The triangles among `candidates` whose boxes meet [lo, hi] (the index
// answers by its leaves, which may hold others).
Scene CopyOfTriangles(const Scene& scene, const std::vector<uint32_t>& candidates, const glm::dvec3& lo,
                      const glm::dvec3& hi) {
  Scene out;
  out.materials = scene.materials;
  for (uint32_t t : candidates) {
    Bounds box;
    for (int c = 0; c < 3; ++c) box.Extend(scene.Vertex(t, c));
    if (glm::any(glm::lessThan(box.max, lo)) || glm::any(glm::greaterThan(box.min, hi))) continue;
    const uint32_t base = static_cast<uint32_t>(out.positions.size());
    for (int c = 0; c < 3; ++c) {
      out.positions.push_back(scene.Vertex(t, c));
      out.bounds.Extend(out.positions.back());
    }
    out.triangles.emplace_back(base, base + 1, base + 2);
    out.triangle_material.push_back(scene.MaterialOf(t));
  }
  return out;
}

}  // namespace

std::shared_ptr<LocalFrame> LocalFrames::For(const Scene& scene, const exact::SceneTriangleIndex& index,
                                             const Bounds& hull) {
  glm::dvec3 lo;
  double side = 0.0;
  RegionOf(hull, lo, side);
  std::lock_guard lock(mutex_);
  for (auto it = frames_.begin(); it != frames_.end(); ++it)
    if ((*it)->side == side && (*it)->lo == lo) {
      frames_.splice(frames_.begin(), frames_, it);
      return frames_.front();
    }
  auto frame = std::make_shared<LocalFrame>();
  frame->lo = lo;
  frame->side = side;
  // Triangles whose boxes meet the region, a hair wider so that one lying
  // in its boundary is kept.
  const glm::dvec3 margin(side * 0x1p-20);
  const glm::dvec3 box_lo = lo - margin, box_hi = lo + glm::dvec3(side) + margin;
  frame->scene = std::make_shared<const Scene>(CopyOfTriangles(scene, index.InBox(box_lo, box_hi), box_lo, box_hi));
  frames_.push_front(frame);
  if (frames_.size() > kMaxFrames) frames_.pop_back();
  return frame;
}

Bounds LocalFrames::RegionAround(const Bounds& hull) {
  glm::dvec3 lo;
  double side = 0.0;
  RegionOf(hull, lo, side);
  Bounds region;
  region.Extend(lo);
  region.Extend(lo + glm::dvec3(side));
  return region;
}

size_t LocalFrames::size() const {
  std::lock_guard lock(mutex_);
  return frames_.size();
}

}  // namespace visq::core
