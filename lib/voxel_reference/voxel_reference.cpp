#include "voxel_reference/voxel_reference.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstddef>

#include <fmt/format.h>

#include "common/job_timing.h"
#include "common/parallel.h"
#include "raycast/embree_scene.h"

namespace visq::voxel_reference {
namespace {

using Clock = std::chrono::steady_clock;

ReferenceGrid EmptyGrid(const GridBox& box) {
  ReferenceGrid grid;
  grid.width = box.width;
  grid.height = box.height;
  grid.slices = box.slices;
  grid.words_per_column = (box.slices + 31) / 32;
  grid.bits.assign(size_t{grid.width} * grid.height * grid.words_per_column, 0u);
  return grid;
}

Status ValidateBox(const GridBox& box) {
  if (box.width == 0 || box.height == 0 || box.slices == 0)
    return absl::InvalidArgumentError(
        fmt::format("grid {} x {} x {}: every size must be at least 1", box.width, box.height, box.slices));
  for (int i = 0; i < 3; ++i)
    if (!(box.half_extent[i] > 0.0) || !std::isfinite(box.half_extent[i]))
      return absl::InvalidArgumentError(fmt::format("box.half_extent[{}]: {}", i, box.half_extent[i]));
  return absl::OkStatus();
}

// World point to grid coordinates: x, y in texels from the box corner, z as
// a fraction of the box depth (0 = front face).
glm::dvec3 ToGrid(const GridBox& box, const glm::dvec3& p) {
  const glm::dvec3 d = p - box.center;
  return {(glm::dot(d, box.axis_u) / box.half_extent.x * 0.5 + 0.5) * box.width,
          (glm::dot(d, box.axis_v) / box.half_extent.y * 0.5 + 0.5) * box.height,
          glm::dot(d, box.axis_w) / box.half_extent.z * 0.5 + 0.5};
}

// The depth range of a triangle inside the column [x0, x1] x [y0, y1]
// (Sutherland-Hodgman); false when it misses the column. Only used to pick
// candidate voxels, which the separating-axis test then decides.
bool ColumnDepthRange(const glm::dvec3 tri[3], double x0, double x1, double y0, double y1, double& zmin,
                      double& zmax) {
  glm::dvec3 poly[8], next[8];
  int n = 3;
  for (int i = 0; i < 3; ++i) poly[i] = tri[i];
  const double bounds[4] = {x0, x1, y0, y1};
  for (int side = 0; side < 4; ++side) {
    const int axis = side / 2;
    const double sgn = side % 2 == 0 ? 1.0 : -1.0;
    int m = 0;
    for (int i = 0; i < n; ++i) {
      const glm::dvec3 a = poly[i], b = poly[(i + 1) % n];
      const double da = sgn * (a[axis] - bounds[side]), db = sgn * (b[axis] - bounds[side]);
      if (da >= 0.0) next[m++] = a;
      if ((da >= 0.0) != (db >= 0.0)) next[m++] = a + (b - a) * (da / (da - db));
    }
    n = m;
    if (n == 0) return false;
    std::copy(next, next + n, poly);
  }
  zmin = zmax = poly[0].z;
  for (int i = 1; i < n; ++i) {
    zmin = std::min(zmin, poly[i].z);
    zmax = std::max(zmax, poly[i].z);
  }
  return true;
}

int ThreadCount(int requested) {
  return requested > 0 ? requested : static_cast<int>(ParallelWorkers());
}

}  // namespace

uint64_t ReferenceGrid::CountOccupied() const {
  uint64_t n = 0;
  for (uint32_t w : bits) n += static_cast<uint64_t>(std::popcount(w));
  return n;
}

bool TriangleBoxOverlap(const glm::dvec3& center, const glm::dvec3& half, const glm::dvec3& a, const glm::dvec3& b,
                        const glm::dvec3& c) {
  // Separating axes (Akenine-Möller 2001): the box's three face normals, the
  // triangle's normal, and the nine cross products of box and triangle edges.
  const glm::dvec3 v[3] = {a - center, b - center, c - center};
  auto separated = [&](const glm::dvec3& axis) {
    const double p0 = glm::dot(axis, v[0]), p1 = glm::dot(axis, v[1]), p2 = glm::dot(axis, v[2]);
    const double r = half.x * std::abs(axis.x) + half.y * std::abs(axis.y) + half.z * std::abs(axis.z);
    return std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r;
  };
  for (int i = 0; i < 3; ++i) {
    glm::dvec3 axis(0.0);
    axis[i] = 1.0;
    if (separated(axis)) return false;
  }
  const glm::dvec3 edges[3] = {v[1] - v[0], v[2] - v[1], v[0] - v[2]};
  for (const glm::dvec3& e : edges) {
    for (int i = 0; i < 3; ++i) {
      glm::dvec3 unit(0.0);
      unit[i] = 1.0;
      if (separated(glm::cross(unit, e))) return false;
    }
  }
  const glm::dvec3 normal = glm::cross(edges[0], edges[1]);
  const double distance = glm::dot(normal, v[0]);
  const double r = half.x * std::abs(normal.x) + half.y * std::abs(normal.y) + half.z * std::abs(normal.z);
  return std::abs(distance) <= r;
}

StatusOr<ReferenceGrid> VoxelizeSurface(const Scene& scene, const GridBox& box, const SurfaceOptions& options,
                                        SurfaceStats* stats) {
  const auto start = Clock::now();
  if (Status s = ValidateBox(box); !s.ok()) return s;
  const bool local = !options.column_near.empty();
  const size_t columns = size_t{box.width} * box.height;
  if (local && (options.column_near.size() != columns || options.column_far.size() != columns))
    return absl::InvalidArgumentError(fmt::format("column_near/far: {} / {} entries for {} columns",
                                                  options.column_near.size(), options.column_far.size(), columns));
  std::vector<std::pair<uint32_t, uint32_t>> ranges = options.triangles;
  if (ranges.empty()) ranges.emplace_back(0u, static_cast<uint32_t>(scene.TriangleCount()));
  for (const auto& [first, count] : ranges)
    if (uint64_t{first} + count > scene.TriangleCount())
      return absl::InvalidArgumentError(fmt::format("triangles [{}, {}) beyond {}", first, first + count,
                                                    scene.TriangleCount()));

  ReferenceGrid grid = EmptyGrid(box);
  const uint32_t wpc = grid.words_per_column;
  const int threads = std::min<int>(ThreadCount(options.threads), static_cast<int>(box.height));
  std::vector<uint64_t> empty_touches(threads, 0);

  // Each band of rows is one chunk, so no two threads write one word.
  auto work = [&](int t) {
    const uint32_t row_begin = static_cast<uint32_t>(uint64_t{box.height} * t / threads);
    const uint32_t row_end = static_cast<uint32_t>(uint64_t{box.height} * (t + 1) / threads);
    const glm::dvec3 half(0.5);
    for (const auto& [first, count] : ranges) {
      for (uint32_t tri = first; tri < first + count; ++tri) {
        glm::dvec3 g[3];
        for (int c = 0; c < 3; ++c) g[c] = ToGrid(box, scene.Vertex(tri, c));
        const glm::dvec3 lo = glm::min(glm::min(g[0], g[1]), g[2]), hi = glm::max(glm::max(g[0], g[1]), g[2]);
        if (hi.z < 0.0 || lo.z > 1.0) continue;
        // Columns whose closed square the triangle's bounds touch.
        const int64_t x0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(lo.x)) - 1);
        const int64_t x1 = std::min<int64_t>(box.width - 1, static_cast<int64_t>(std::floor(hi.x)));
        const int64_t y0 = std::max<int64_t>(row_begin, static_cast<int64_t>(std::floor(lo.y)) - 1);
        const int64_t y1 = std::min<int64_t>(int64_t{row_end} - 1, static_cast<int64_t>(std::floor(hi.y)));
        for (int64_t y = y0; y <= y1; ++y) {
          for (int64_t x = x0; x <= x1; ++x) {
            // Candidate slices from the triangle's depth range in the column
            // (grown by a little and one slice each way); SAT decides.
            const double slack = 1e-6;
            double zmin, zmax;
            if (!ColumnDepthRange(g, x - slack, x + 1 + slack, y - slack, y + 1 + slack, zmin, zmax)) continue;
            const size_t column = static_cast<size_t>(y) * box.width + static_cast<size_t>(x);
            double near = 0.0, far = 1.0;
            if (local) {
              near = options.column_near[column];
              far = options.column_far[column];
              if (near > far) {
                if (zmax >= 0.0 && zmin <= 1.0) ++empty_touches[t];
                continue;
              }
            }
            const double scale = box.slices / (far - near);
            const int64_t k0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor((zmin - near) * scale)) - 1);
            const int64_t k1 =
                std::min<int64_t>(box.slices - 1, static_cast<int64_t>(std::floor((zmax - near) * scale)) + 1);
            if (k0 > k1) continue;
            // The triangle in this column's slice units (the mapping is affine in z).
            glm::dvec3 s[3];
            for (int c = 0; c < 3; ++c) s[c] = glm::dvec3(g[c].x, g[c].y, (g[c].z - near) * scale);
            uint32_t* words = &grid.bits[column * wpc];
            for (int64_t k = k0; k <= k1; ++k) {
              if (TriangleBoxOverlap(glm::dvec3(x + 0.5, y + 0.5, k + 0.5), half, s[0], s[1], s[2]))
                words[k / 32] |= 1u << (k % 32);
            }
          }
        }
      }
    }
  };
  ParallelFor(static_cast<size_t>(threads), 1, [&](size_t t, size_t) { work(static_cast<int>(t)); },
              static_cast<size_t>(threads));
  if (stats != nullptr) {
    stats->touches_in_empty_columns = 0;
    for (uint64_t n : empty_touches) stats->touches_in_empty_columns += n;
    stats->milliseconds = MillisecondsSince(start);
  }
  return grid;
}

StatusOr<ReferenceGrid> SampleColumnCenters(const Scene& scene, const GridBox& box, const SurfaceOptions& options,
                                            double margin) {
  if (Status s = ValidateBox(box); !s.ok()) return s;
  if (!(margin >= 0.0 && margin < 0.5)) return absl::InvalidArgumentError("margin must lie in [0, 0.5)");
  const bool local = !options.column_near.empty();
  std::vector<std::pair<uint32_t, uint32_t>> ranges = options.triangles;
  if (ranges.empty()) ranges.emplace_back(0u, static_cast<uint32_t>(scene.TriangleCount()));
  ReferenceGrid grid = EmptyGrid(box);
  const uint32_t wpc = grid.words_per_column;
  for (const auto& [first, count] : ranges) {
    for (uint32_t tri = first; tri < first + count && tri < scene.TriangleCount(); ++tri) {
      glm::dvec3 g[3];
      for (int c = 0; c < 3; ++c) g[c] = ToGrid(box, scene.Vertex(tri, c));
      const double area = (g[1].x - g[0].x) * (g[2].y - g[0].y) - (g[2].x - g[0].x) * (g[1].y - g[0].y);
      if (area == 0.0) continue;  // edge-on: covers no column center
      // A barycentric coordinate is the distance to the opposite edge over
      // the corner's height above it: margin columns is margin / height.
      double min_weight[3] = {0, 0, 0};
      for (int c = 0; c < 3 && margin > 0.0; ++c) {
        const glm::dvec2 edge = glm::dvec2(g[(c + 2) % 3]) - glm::dvec2(g[(c + 1) % 3]);
        min_weight[c] = margin * glm::length(edge) / std::abs(area);
      }
      const glm::dvec3 lo = glm::min(glm::min(g[0], g[1]), g[2]), hi = glm::max(glm::max(g[0], g[1]), g[2]);
      const int64_t x0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(lo.x - 0.5)));
      const int64_t x1 = std::min<int64_t>(box.width - 1, static_cast<int64_t>(std::ceil(hi.x - 0.5)));
      const int64_t y0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(lo.y - 0.5)));
      const int64_t y1 = std::min<int64_t>(box.height - 1, static_cast<int64_t>(std::ceil(hi.y - 0.5)));
      for (int64_t y = y0; y <= y1; ++y) {
        for (int64_t x = x0; x <= x1; ++x) {
          const double px = x + 0.5, py = y + 0.5;
          // Barycentrics of the column center.
          const double w0 = ((g[1].x - px) * (g[2].y - py) - (g[2].x - px) * (g[1].y - py)) / area;
          const double w1 = ((g[2].x - px) * (g[0].y - py) - (g[0].x - px) * (g[2].y - py)) / area;
          const double w2 = 1.0 - w0 - w1;
          if (w0 < min_weight[0] || w1 < min_weight[1] || w2 < min_weight[2]) continue;
          const double depth = w0 * g[0].z + w1 * g[1].z + w2 * g[2].z;
          if (depth < 0.0 || depth > 1.0) continue;
          const size_t column = static_cast<size_t>(y) * box.width + static_cast<size_t>(x);
          double near = 0.0, far = 1.0;
          if (local) {
            near = options.column_near[column];
            far = options.column_far[column];
            if (near > far) continue;
          }
          const double slice = (depth - near) / (far - near) * box.slices;
          if (margin > 0.0 && std::abs(slice - std::round(slice)) < margin) continue;
          const int64_t k = std::clamp<int64_t>(static_cast<int64_t>(std::floor(slice)), 0, box.slices - 1);
          grid.bits[column * wpc + k / 32] |= 1u << (k % 32);
        }
      }
    }
  }
  return grid;
}

StatusOr<SolidReference> VoxelizeSolid(const Scene& scene, const GridBox& box, int threads) {
  const auto start = Clock::now();
  if (Status s = ValidateBox(box); !s.ok()) return s;
  SolidReference out;
  SurfaceOptions surface_options;
  surface_options.threads = threads;
  VISQ_ASSIGN_OR_RETURN(out.surface, VoxelizeSurface(scene, box, surface_options));
  out.solid = out.surface;
  const size_t columns = size_t{box.width} * box.height;
  out.column_consistent.assign(columns, 1);

  // One ray per column through its center, front face to back face; after
  // each hit the ray restarts at the hit point (EmbreeScene skips hits
  // within its small offset of the origin, so a crossing through a shared
  // edge is counted once).
  raycast::EmbreeSceneOptions embree_options;
  embree_options.origin = box.center;
  VISQ_ASSIGN_OR_RETURN(raycast::EmbreeScene embree, raycast::EmbreeScene::Create(scene, embree_options));
  const glm::dvec3 direction = box.axis_w * (2.0 * box.half_extent.z);
  const glm::dvec3 front = box.center - box.axis_w * box.half_extent.z;
  std::vector<raycast::Ray> rays(columns);
  std::vector<double> travelled(columns, 0.0);  // fraction of the box depth
  std::vector<std::vector<std::pair<double, bool>>> crossings(columns);  // (depth fraction, entering)
  for (uint32_t y = 0; y < box.height; ++y) {
    for (uint32_t x = 0; x < box.width; ++x) {
      const double u = ((x + 0.5) / box.width * 2.0 - 1.0) * box.half_extent.x;
      const double v = ((y + 0.5) / box.height * 2.0 - 1.0) * box.half_extent.y;
      raycast::Ray& ray = rays[size_t{y} * box.width + x];
      ray.origin = front + box.axis_u * u + box.axis_v * v;
      ray.direction = direction;
      ray.tmax = 1.0;
    }
  }
  std::vector<size_t> active(columns);
  for (size_t c = 0; c < columns; ++c) active[c] = c;
  raycast::TraceOptions trace;
  trace.threads = threads;
  for (int round = 0; !active.empty() && round < 4096; ++round) {
    std::vector<raycast::Ray> batch;
    batch.reserve(active.size());
    for (size_t c : active) batch.push_back(rays[c]);
    VISQ_ASSIGN_OR_RETURN(std::vector<raycast::Hit> hits, embree.Intersect(batch, trace));
    std::vector<size_t> next;
    for (size_t i = 0; i < active.size(); ++i) {
      const size_t c = active[i];
      if (!hits[i].hit) continue;
      raycast::Ray& ray = rays[c];
      travelled[c] += hits[i].t;
      const uint32_t tri = hits[i].triangle;
      const glm::dvec3 normal = glm::cross(scene.Vertex(tri, 1) - scene.Vertex(tri, 0),
                                           scene.Vertex(tri, 2) - scene.Vertex(tri, 0));
      crossings[c].emplace_back(travelled[c], glm::dot(normal, box.axis_w) < 0.0);
      ray.origin = front + (ray.origin - front) + direction * hits[i].t;
      ray.tmax = 1.0 - travelled[c];
      if (ray.tmax > 0.0) next.push_back(c);
    }
    active = std::move(next);
  }

  // Parity at each voxel center; consistency of the facing sequence.
  const uint32_t wpc = out.solid.words_per_column;
  for (size_t c = 0; c < columns; ++c) {
    const auto& list = crossings[c];
    bool inside = false;
    for (const auto& [depth, entering] : list) {
      if (entering == inside) out.column_consistent[c] = 0;
      inside = !inside;
    }
    if (inside) out.column_consistent[c] = 0;
    size_t next = 0;
    inside = false;
    for (uint32_t k = 0; k < box.slices; ++k) {
      const double center = (k + 0.5) / box.slices;
      while (next < list.size() && list[next].first < center) {
        inside = !inside;
        ++next;
      }
      if (inside) out.solid.bits[c * wpc + k / 32] |= 1u << (k % 32);
    }
  }
  out.milliseconds = MillisecondsSince(start);
  return out;
}

}  // namespace visq::voxel_reference
