// Receivers grouped for their trees: by the cubes of a grid over the scene
// (GroupReceivers) or by the batch and the occluders (GroupReceiversByShaft).
#include "exact/light_visibility.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include <absl/container/flat_hash_map.h>

namespace visq::exact {

std::vector<ReceiverCell> GroupReceivers(std::span<const QueryPoint> points, const Bounds& scene_bounds,
                                         int cells_per_side, size_t min_points) {
  const glm::dvec3 extent = scene_bounds.Empty() ? glm::dvec3(1.0) : scene_bounds.Extent();
  const glm::dvec3 origin = scene_bounds.Empty() ? glm::dvec3(0.0) : scene_bounds.min;
  const double largest = std::max({extent.x, extent.y, extent.z, 1e-300});
  const double cell = largest / std::max(cells_per_side, 1);
  // Cell coordinates are clamped so that points far outside the scene stay
  // integers; such a cell's box is widened to its points below.
  constexpr double kLimit = double(int64_t{1} << 40);
  auto coordinate = [&](double x, int axis) {
    const double q = std::floor((x - origin[axis]) / cell);  // NaN only past the doubles' range
    return std::isnan(q) ? int64_t{0} : static_cast<int64_t>(std::clamp(q, -kLimit, kLimit));
  };
  using Key = std::array<int64_t, 3>;
  struct Group {
    Key key;
    int level = 0;  // the cube's side is cell * 2^level
    std::vector<uint32_t> points;
  };
  std::vector<Group> open;
  {
    absl::flat_hash_map<Key, uint32_t> by_key;
    for (uint32_t i = 0; i < points.size(); ++i) {
      const glm::dvec3& x = points[i].position;
      const Key key = {coordinate(x.x, 0), coordinate(x.y, 1), coordinate(x.z, 2)};
      auto [it, inserted] = by_key.try_emplace(key, static_cast<uint32_t>(open.size()));
      if (inserted) open.push_back({key, 0, {}});
      open[it->second].points.push_back(i);
    }
  }
  // Octree merging, bottom up: a cube with fewer than `min_points` points
  // gives them to its parent cube, so that sparse receivers share a tree
  // (a tree per point reuses nothing) while dense ones keep small cubes
  // (whose occluders are mostly far, and cached). A parent may then overlap
  // a dense child kept as it is: each point is in one group, and each group
  // has a tree of its own. Merging stops at a cube as large as the scene.
  std::vector<Group> done;
  for (int level = 0; !open.empty(); ++level) {
    const bool last = min_points <= 1 || std::ldexp(cell, level) >= largest || level >= 48;
    if (last) {
      for (Group& g : open) done.push_back(std::move(g));
      break;
    }
    absl::flat_hash_map<Key, std::vector<uint32_t>> children;  // parent key -> indices into open
    std::vector<Key> parents;  // in order of first appearance
    for (uint32_t g = 0; g < open.size(); ++g) {
      const Key parent = {open[g].key[0] >> 1, open[g].key[1] >> 1, open[g].key[2] >> 1};
      auto [it, inserted] = children.try_emplace(parent);
      if (inserted) parents.push_back(parent);
      it->second.push_back(g);
    }
    std::vector<Group> next;
    for (const Key& parent : parents) {
      Group merged{parent, level + 1, {}};
      for (uint32_t g : children[parent]) {
        if (open[g].points.size() >= min_points) {
          done.push_back(std::move(open[g]));
        } else {
          merged.points.insert(merged.points.end(), open[g].points.begin(), open[g].points.end());
        }
      }
      if (merged.points.empty()) continue;
      std::sort(merged.points.begin(), merged.points.end());
      next.push_back(std::move(merged));
    }
    open = std::move(next);
  }
  std::sort(done.begin(), done.end(), [](const Group& a, const Group& b) { return a.points[0] < b.points[0]; });

  std::vector<ReceiverCell> cells;
  cells.reserve(done.size());
  for (Group& g : done) {
    ReceiverCell c;
    const double side = std::ldexp(cell, g.level);
    for (int axis = 0; axis < 3; ++axis) {
      c.box.min[axis] = origin[axis] + static_cast<double>(g.key[axis]) * side;
      c.box.max[axis] = origin[axis] + static_cast<double>(g.key[axis] + 1) * side;
    }
    // A cube beyond the doubles' range (a scene near 1e308 wide): the box of
    // its points alone.
    const auto finite = [](const glm::dvec3& x) { return std::isfinite(x.x + x.y + x.z); };
    if (!finite(c.box.min) || !finite(c.box.max)) c.box = Bounds();
    // Rounding may put a point on the far side of its cube's computed face.
    for (uint32_t i : g.points) c.box.Extend(points[i].position);
    c.points = std::move(g.points);
    cells.push_back(std::move(c));
  }
  return cells;
}

std::vector<ReceiverCell> GroupReceiversByShaft(std::span<const QueryPoint> points, const AreaLight& light,
                                                const SceneTriangleIndex& index, const ShaftGrouping& options) {
  // Groups to judge: each is split at the median of its box's longest axis
  // while its shaft's box holds too many triangles and both halves keep
  // min_points; what cannot be split, or need not be, is a cell.
  const size_t min_points = std::max<size_t>(1, options.min_points);
  glm::dvec3 light_lo(std::numeric_limits<double>::infinity()), light_hi(-std::numeric_limits<double>::infinity());
  for (const glm::dvec3& v : light.vertices) {
    light_lo = glm::min(light_lo, v);
    light_hi = glm::max(light_hi, v);
  }
  std::vector<ReceiverCell> done;
  std::vector<std::vector<uint32_t>> open(1);
  open[0].resize(points.size());
  for (uint32_t i = 0; i < points.size(); ++i) open[0][i] = i;
  if (points.empty()) return done;
  while (!open.empty()) {
    std::vector<uint32_t> group = std::move(open.back());
    open.pop_back();
    Bounds box;
    for (const uint32_t i : group) box.Extend(points[i].position);
    const glm::dvec3 shaft_lo = glm::min(light_lo, box.min), shaft_hi = glm::max(light_hi, box.max);
    const glm::dvec3 extent = box.Extent();
    const int axis = extent.x >= extent.y && extent.x >= extent.z ? 0 : extent.y >= extent.z ? 1 : 2;
    const bool splittable = group.size() >= 2 * min_points && extent[axis] > 0.0;
    const size_t count = splittable ? index.CountInBox(shaft_lo, shaft_hi, SIZE_MAX) : 0;
    auto keep_whole = [&] {
      std::sort(group.begin(), group.end());
      done.push_back({box, std::move(group)});
    };
    if (count <= options.max_shaft_triangles) {
      keep_whole();
      continue;
    }
    const size_t middle = group.size() / 2;
    std::nth_element(group.begin(), group.begin() + static_cast<std::ptrdiff_t>(middle), group.end(),
                     [&](uint32_t a, uint32_t b) {
                       const double pa = points[a].position[axis], pb = points[b].position[axis];
                       return pa < pb || (pa == pb && a < b);
                     });
    std::vector<uint32_t> upper(group.begin() + static_cast<std::ptrdiff_t>(middle), group.end());
    std::vector<uint32_t> lower(group.begin(), group.begin() + static_cast<std::ptrdiff_t>(middle));
    // Halves whose shafts together still meet nearly twice the whole's
    // triangles (compact receivers under a dense mesh: the shaft is the
    // light's) would only build the same tree twice: one tree it stays,
    // unless it would hold more than the hard cap (its memory).
    if (static_cast<double>(count) <= options.hard_cap * static_cast<double>(options.max_shaft_triangles)) {
      size_t halves = 0;
      for (const auto* half : {&lower, &upper}) {
        Bounds half_box;
        for (const uint32_t i : *half) half_box.Extend(points[i].position);
        halves += index.CountInBox(glm::min(light_lo, half_box.min), glm::max(light_hi, half_box.max), SIZE_MAX);
      }
      if (static_cast<double>(halves) > 2.0 * options.split_gain * static_cast<double>(count)) {
        keep_whole();
        continue;
      }
    }
    open.push_back(std::move(upper));
    open.push_back(std::move(lower));
  }
  std::sort(done.begin(), done.end(),
            [](const ReceiverCell& a, const ReceiverCell& b) { return a.points.front() < b.points.front(); });
  return done;
}

}  // namespace visq::exact
