#include "visq/gpu/gpu_scene.h"
#include "scene/placement_checks.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include "common/check.h"
#include "gl_check.h"
#include "gpu_scene_resources.h"

namespace visq::gpu {
namespace {

// A box must be outside a plane by this much of the placement's magnitude
// (|w| + sum |n_k| reach_k) before its clusters are dropped: the shader's
// float rows and dot products err by under 1e-6 of it.
constexpr double kPlacedCullMargin = 1e-5;

// Which placements the GPU holds as instances, and the counts that follow.
// Upload and EstimateBytes both read the scene through this one function.
struct Layout {
  std::vector<uint8_t> instanced;      // per placement
  std::vector<int32_t> held_of_mesh;   // per scene mesh: its index among held meshes, or -1
  std::vector<uint32_t> held_meshes;   // scene mesh of each held mesh
  std::vector<uint32_t> held_from;     // the placement whose triangles' materials each held mesh takes
  uint32_t unplaced_triangles = 0;
  uint32_t held_triangles = 0;         // unplaced + each held mesh once
  size_t segments = 0;
};

Layout PlanLayout(const Scene& scene, const glm::dvec3& anchor) {
  Layout layout;
  layout.instanced.assign(scene.placements.size(), 0);
  layout.held_of_mesh.assign(scene.meshes.size(), -1);
  const uint64_t total = scene.TriangleCount();
  const std::vector<double> magnitude = MeshMagnitudes(scene);
  const glm::dvec3 extent = scene.bounds.Empty() ? glm::dvec3(0.0) : scene.bounds.Extent();
  const double largest_extent = std::max({extent.x, extent.y, extent.z});
  uint64_t cursor = 0, placed = 0, held = 0;
  const std::vector<uint8_t> in_range = PlacementsInRange(scene);
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    const MeshPlacement& p = scene.placements[k];
    if (p.mesh >= scene.meshes.size() || p.first_triangle < cursor) continue;
    const uint64_t count = scene.meshes[p.mesh].triangles.size();
    if (count < kFewestTrianglesToInstance || !in_range[k] ||
        !PlacementKeepsFloatPrecision(p.world, magnitude[p.mesh], anchor, largest_extent))
      continue;
    // The GPU keeps a held mesh's materials once, as the scene does
    // (SceneMesh::triangle_material).
    layout.instanced[k] = 1;
    if (p.first_triangle > cursor) ++layout.segments;
    ++layout.segments;
    cursor = p.first_triangle + count;
    placed += count;
    if (layout.held_of_mesh[p.mesh] < 0) {
      layout.held_of_mesh[p.mesh] = static_cast<int32_t>(layout.held_meshes.size());
      layout.held_meshes.push_back(p.mesh);
      layout.held_from.push_back(static_cast<uint32_t>(k));
      held += count;
    }
  }
  if (cursor < total) ++layout.segments;
  layout.unplaced_triangles = static_cast<uint32_t>(total - placed);
  layout.held_triangles = static_cast<uint32_t>(total - placed + held);
  return layout;
}

// GL refuses zero-sized storage: an empty scene gets one unused element.
uint64_t BufferBytes(size_t elements, size_t element_bytes) { return std::max<size_t>(elements, 1) * element_bytes; }

uint64_t LayoutBytes(const Layout& layout) {
  return BufferBytes(3 * size_t(layout.held_triangles), sizeof(glm::vec3)) +
         BufferBytes(layout.segments + 1, sizeof(PlacementRecord)) +
         BufferBytes(layout.held_triangles, sizeof(uint32_t)) +
         BufferBytes(3 * size_t(layout.held_triangles), sizeof(uint32_t)) +
         BufferBytes(4 * layout.segments, sizeof(uint32_t));
}

PlacementRecord Record(const glm::dmat4& place, int64_t triangle_offset) {
  VISQ_CHECK(triangle_offset >= INT32_MIN && triangle_offset <= INT32_MAX);
  PlacementRecord record{};
  for (int row = 0; row < 3; ++row)
    for (int column = 0; column < 4; ++column) record.rows[row][column] = static_cast<float>(place[column][row]);
  record.triangle_offset = static_cast<int32_t>(triangle_offset);
  return record;
}

template <typename T>
void Storage(const GlBuffer& buffer, const std::vector<T>& data) {
  const T none{};
  glNamedBufferStorage(buffer.id(), BufferBytes(data.size(), sizeof(T)), data.empty() ? &none : data.data(), 0);
}

glm::dvec3 DefaultAnchor(const Scene& scene) { return scene.bounds.Empty() ? glm::dvec3(0.0) : scene.bounds.Center(); }

}  // namespace

uint64_t GpuScene::EstimateBytes(const Scene& scene) {
  return LayoutBytes(PlanLayout(scene, DefaultAnchor(scene)));
}

StatusOr<std::shared_ptr<GpuScene>> GpuScene::Upload(GpuWorker& worker, const Scene& scene,
                                                     std::optional<glm::dvec3> anchor) {
  std::shared_ptr<GpuScene> out(new GpuScene());
  out->worker_ = &worker;
  out->anchor_ = anchor.value_or(DefaultAnchor(scene));
  out->bounds_ = scene.bounds;
  out->triangle_count_ = static_cast<uint32_t>(scene.TriangleCount());
  const Layout layout = PlanLayout(scene, out->anchor_);
  out->held_triangles_ = layout.held_triangles;
  glm::dmat4 from_world(1.0);
  from_world[3] = glm::dvec4(-out->anchor_, 1.0);

  // Where each held mesh's corners start in the buffer, after the unplaced.
  std::vector<uint32_t> held_first(layout.held_meshes.size());
  uint32_t next = layout.unplaced_triangles;
  for (size_t h = 0; h < layout.held_meshes.size(); ++h) {
    held_first[h] = next;
    next += static_cast<uint32_t>(scene.meshes[layout.held_meshes[h]].triangles.size());
  }

  // Segments in the scene's order, records, and the unplaced corners
  // relative to the anchor, converted on this thread so the GL thread only
  // copies.
  std::vector<glm::vec3> corners;
  corners.reserve(3 * size_t(layout.held_triangles));
  std::vector<PlacementRecord> records = {Record(glm::dmat4(1.0), 0)};
  // Materials in the buffer's order: a held mesh's once.
  std::vector<uint32_t> materials;
  materials.reserve(layout.held_triangles);
  auto material_of = [&scene](size_t t) { return scene.MaterialOf(t); };
  uint32_t unplaced_seen = 0;
  auto add_unplaced = [&](uint32_t first, uint32_t end) {
    if (first >= end) return;
    out->segments_.push_back({first, end - first, unplaced_seen, static_cast<uint32_t>(records.size()), -1});
    records.push_back(Record(glm::dmat4(1.0), int64_t(first) - int64_t(unplaced_seen)));
    for (uint32_t t = first; t < end; ++t) {
      for (int c = 0; c < 3; ++c) corners.emplace_back(scene.Vertex(t, c) - out->anchor_);
      materials.push_back(material_of(t));
    }
    unplaced_seen += end - first;
  };
  std::vector<std::pair<size_t, size_t>> placed_segments;  // (segment, placement)
  uint32_t cursor = 0;
  for (size_t k = 0; k < scene.placements.size(); ++k) {
    if (!layout.instanced[k]) continue;
    const MeshPlacement& p = scene.placements[k];
    add_unplaced(cursor, p.first_triangle);
    const int32_t held = layout.held_of_mesh[p.mesh];
    const uint32_t count = static_cast<uint32_t>(scene.meshes[p.mesh].triangles.size());
    placed_segments.emplace_back(out->segments_.size(), k);
    out->segments_.push_back(
        {p.first_triangle, count, held_first[size_t(held)], static_cast<uint32_t>(records.size()), held});
    records.push_back(Record(from_world * p.world, int64_t(p.first_triangle) - int64_t(held_first[size_t(held)])));
    cursor = p.first_triangle + count;
  }
  add_unplaced(cursor, out->triangle_count_);
  VISQ_CHECK_EQ(out->segments_.size(), layout.segments);
  VISQ_CHECK_EQ(unplaced_seen, layout.unplaced_triangles);
  for (size_t h = 0; h < layout.held_meshes.size(); ++h) {
    const SceneMesh& mesh = scene.meshes[layout.held_meshes[h]];
    const uint32_t first = scene.placements[layout.held_from[h]].first_triangle;
    for (size_t i = 0; i < mesh.triangles.size(); ++i) {
      for (int c = 0; c < 3; ++c) corners.emplace_back(mesh.positions[mesh.triangles[i][c]]);
      materials.push_back(material_of(first + i));
    }
  }

  // Each part's cluster hierarchy, over the very floats the GPU gets, and
  // its order as corner indices for the element buffer.
  std::vector<uint32_t> cluster_corners;
  cluster_corners.reserve(corners.size());
  std::vector<uint32_t> order;
  auto append_order = [&](uint32_t buffer_triangle) {
    for (const uint32_t t : order)
      for (uint32_t c = 0; c < 3; ++c) cluster_corners.push_back(3 * (buffer_triangle + t) + c);
  };
  out->clusters_ = TriangleClusters::Build(std::span(corners).first(3 * size_t(layout.unplaced_triangles)), order);
  append_order(0);
  for (size_t h = 0; h < layout.held_meshes.size(); ++h) {
    const size_t count = scene.meshes[layout.held_meshes[h]].triangles.size();
    HeldMesh held;
    held.clusters = TriangleClusters::Build(std::span(corners).subspan(3 * size_t(held_first[h]), 3 * count), order);
    held.element_triangle = static_cast<uint32_t>(cluster_corners.size() / 3);
    held.lo = glm::dvec3(held.clusters.lo());
    held.hi = glm::dvec3(held.clusters.hi());
    append_order(held_first[h]);
    out->meshes_.push_back(std::move(held));
  }
  std::vector<uint32_t>().swap(order);

  // Each placement's box and the magnitude its transform rounds at.
  for (const auto& [s, k] : placed_segments) {
    const Segment& segment = out->segments_[s];
    const HeldMesh& mesh = out->meshes_[size_t(segment.mesh)];
    Placed placed;
    placed.segment = static_cast<uint32_t>(s);
    placed.place = from_world * scene.placements[k].world;
    placed.lo = glm::dvec3(std::numeric_limits<double>::infinity());
    placed.hi = -placed.lo;
    for (int corner = 0; corner < 8; ++corner) {
      const glm::dvec3 x((corner & 1) ? mesh.hi.x : mesh.lo.x, (corner & 2) ? mesh.hi.y : mesh.lo.y,
                         (corner & 4) ? mesh.hi.z : mesh.lo.z);
      const glm::dvec3 p = PlacePoint(placed.place, x);
      placed.lo = glm::min(placed.lo, p);
      placed.hi = glm::max(placed.hi, p);
    }
    const glm::dvec3 extent = glm::max(glm::abs(mesh.lo), glm::abs(mesh.hi));
    for (int axis = 0; axis < 3; ++axis) {
      double reach = std::abs(placed.place[3][axis]);
      for (int j = 0; j < 3; ++j) reach += std::abs(placed.place[j][axis]) * extent[j];
      placed.reach[axis] = reach;
    }
    out->instances_.push_back(placed);
  }

  std::vector<uint32_t> whole;
  whole.reserve(4 * out->segments_.size());
  for (const Segment& s : out->segments_)
    for (const uint32_t v : {3 * s.count, 1u, 3 * s.buffer_triangle, s.record}) whole.push_back(v);

  Status status = worker.Run({}, [&]() -> Status {
    auto resources = std::make_shared<Resources>();
    Storage(resources->positions, corners);
    Storage(resources->placements, records);
    Storage(resources->triangle_materials, materials);
    Storage(resources->cluster_order, cluster_corners);
    Storage(resources->whole_draw, whole);
    resources->whole_draws = static_cast<GLsizei>(out->segments_.size());
    const GLuint vao = resources->vertex_array.id();
    glVertexArrayElementBuffer(vao, resources->cluster_order.id());
    glVertexArrayVertexBuffer(vao, 0, resources->positions.id(), 0, sizeof(glm::vec3));
    glEnableVertexArrayAttrib(vao, 0);
    glVertexArrayAttribFormat(vao, 0, 3, GL_FLOAT, GL_FALSE, 0);
    glVertexArrayAttribBinding(vao, 0, 0);
    glVertexArrayVertexBuffer(vao, 1, resources->placements.id(), 0, sizeof(PlacementRecord));
    glVertexArrayBindingDivisor(vao, 1, 1);
    for (GLuint row = 0; row < 3; ++row) {
      glEnableVertexArrayAttrib(vao, 1 + row);
      glVertexArrayAttribFormat(vao, 1 + row, 4, GL_FLOAT, GL_FALSE, static_cast<GLuint>(16 * row));
      glVertexArrayAttribBinding(vao, 1 + row, 1);
    }
    glEnableVertexArrayAttrib(vao, 4);
    glVertexArrayAttribIFormat(vao, 4, 1, GL_INT, offsetof(PlacementRecord, triangle_offset));
    glVertexArrayAttribBinding(vao, 4, 1);
    VISQ_RETURN_IF_ERROR(CollectGlErrors("scene upload"));
    out->resources_ = std::move(resources);
    out->generation_ = CurrentContextGeneration();
    return absl::OkStatus();
  });
  VISQ_RETURN_IF_ERROR(status);
  out->gpu_bytes_ = LayoutBytes(layout);
  return out;
}

ScenePartDraw GpuScene::Whole() const {
  ScenePartDraw part;
  part.everything = true;
  part.triangles = triangle_count_;
  return part;
}

ScenePartDraw GpuScene::WholeAsCommands() const {
  const std::pair<uint32_t, uint32_t> everything{0, triangle_count_};
  return TriangleRanges({&everything, 1});
}

ScenePartDraw GpuScene::ClustersInside(std::span<const glm::vec4> planes) const {
  ScenePartDraw part;
  part.indexed = true;
  auto add = [&part](uint32_t element_triangle, uint32_t count, uint32_t record) {
    for (const uint32_t v : {3 * count, 1u, 3 * element_triangle, 0u, record}) part.commands.push_back(v);
    part.triangles += count;
  };
  for (const TriangleClusters::Range& range : clusters_.Cull(planes)) add(range.first, range.count, 0);
  std::vector<glm::dvec4> local(planes.size());
  std::vector<double> slack(planes.size());
  for (const Placed& placed : instances_) {
    const Segment& segment = segments_[placed.segment];
    const HeldMesh& mesh = meshes_[size_t(segment.mesh)];
    bool outside = false, inside = true;
    for (size_t k = 0; k < planes.size() && !outside; ++k) {
      const glm::dvec3 n(planes[k]);
      const double w = planes[k].w;
      double most = w, least = w, magnitude = std::abs(w);
      for (int axis = 0; axis < 3; ++axis) {
        most += n[axis] * (n[axis] >= 0 ? placed.hi[axis] : placed.lo[axis]);
        least += n[axis] * (n[axis] >= 0 ? placed.lo[axis] : placed.hi[axis]);
        magnitude += std::abs(n[axis]) * placed.reach[axis];
      }
      slack[k] = kPlacedCullMargin * magnitude;
      outside = most < -slack[k];
      inside = inside && least >= 0.0;
      // n . (A x + t) + w = (A^T n) . x + (n . t + w).
      const glm::dmat3 a(placed.place);
      local[k] = glm::dvec4(glm::transpose(a) * n, glm::dot(n, glm::dvec3(placed.place[3])) + w);
    }
    if (outside) continue;
    if (inside) {
      add(mesh.element_triangle, segment.count, segment.record);
      continue;
    }
    for (const TriangleClusters::Range& range : mesh.clusters.Cull(local, slack))
      add(mesh.element_triangle + range.first, range.count, segment.record);
  }
  return part;
}

ScenePartDraw GpuScene::TriangleRanges(std::span<const std::pair<uint32_t, uint32_t>> ranges) const {
  ScenePartDraw part;
  for (const auto& [range_first, range_count] : ranges) {
    uint64_t first = range_first;
    const uint64_t end = std::min<uint64_t>(uint64_t(range_first) + range_count, triangle_count_);
    auto at = std::upper_bound(segments_.begin(), segments_.end(), first,
                               [](uint64_t t, const Segment& s) { return t < s.first_triangle; });
    if (at == segments_.begin()) continue;
    for (--at; first < end && at != segments_.end(); ++at) {
      const uint64_t take = std::min<uint64_t>(end, uint64_t(at->first_triangle) + at->count) - first;
      const uint64_t start = at->buffer_triangle + (first - at->first_triangle);
      for (const uint64_t v : {3 * take, uint64_t{1}, 3 * start, uint64_t(at->record)})
        part.commands.push_back(static_cast<uint32_t>(v));
      part.triangles += take;
      first += take;
    }
  }
  return part;
}

StatusOr<const GpuScene::Resources*> GpuScene::CurrentResources() const {
  if (generation_ != CurrentContextGeneration())
    return absl::InternalError("the GPU context holding this scene's buffers was lost; the next request re-uploads it");
  return resources_.get();
}

GpuScene::~GpuScene() {
  // GL objects die on the GL thread: the posted job holds the last reference.
  if (resources_ && worker_) worker_->Post([resources = std::move(resources_)]() mutable { resources.reset(); });
}

}  // namespace visq::gpu
