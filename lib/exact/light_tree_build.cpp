// Creating a tree (its light, its shaft and its occluders) and growing it
// lazily: an undefined leaf replaced by its occluder's BSP (Refine).
#include "exact/light_visibility_impl.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <mutex>

#include <absl/hash/hash.h>

#include "common/check.h"

namespace visq::exact::detail {

namespace {

// The light's exact geometry: input points, triangle planes, and the light
// plane through the largest triangle (oriented: front side positive).
// Returns the largest triangle.
const LightTriangle& PlantLight(LightTree& tree, const std::vector<std::array<uint32_t, 3>>& triangles) {
  const auto& ll = tree.light_local;
  for (const auto& p : ll) tree.light_points.push_back(XPoint::Input(p));
  double best = -1.0;
  const LightTriangle* largest = nullptr;
  for (const auto& t : triangles) {
    const double a = Area3(ll[t[0]], ll[t[1]], ll[t[2]]);
    tree.light_area += a;
    tree.light_planes.push_back(
        XPlane::ThroughPoints(tree.light_points[t[0]], tree.light_points[t[1]], tree.light_points[t[2]]));
    tree.light_planes.back().PrecomputeExact();
    tree.light_triangles.push_back({{t[0], t[1], t[2]}, &tree.light_planes.back()});
    if (a > best) {
      best = a;
      tree.light_plane = &tree.light_planes.back();
    }
  }
  for (const auto& t : tree.light_triangles) {
    if (t.plane == tree.light_plane) largest = &t;
  }
  VISQ_CHECK(largest != nullptr);
  tree.light_fan.emplace(ll[largest->v[0]], ll[largest->v[1]], ll[largest->v[2]]);
  const glm::dvec3 n =
      glm::abs(glm::cross(ll[largest->v[1]] - ll[largest->v[0]], ll[largest->v[2]] - ll[largest->v[0]]));
  tree.light_axis = n.x >= n.y && n.x >= n.z ? 0 : n.y >= n.z ? 1 : 2;

  // One piece when every vertex lies on the light plane and every other
  // vertex is strictly on one side of each edge (exact tests).
  bool convex = ll.size() > 3;
  for (size_t i = 0; convex && i < ll.size(); ++i) convex = EuclidSide(tree.light_points[i], *tree.light_plane) == 0;
  const int i2 = (tree.light_axis + 1) % 3, j2 = (tree.light_axis + 2) % 3;
  int turn = 0;
  for (size_t e = 0; convex && e < ll.size(); ++e) {
    const size_t f = (e + 1) % ll.size();
    for (size_t m = 0; convex && m < ll.size(); ++m) {
      if (m == e || m == f) continue;
      const int side = Orient2d(ll[e], ll[f], ll[m], i2, j2);
      convex = side != 0 && (turn == 0 || side == turn);
      turn = side;
    }
  }
  if (convex) {
    LightPiece whole{{}, tree.light_plane};
    for (uint32_t i = 0; i < ll.size(); ++i) whole.v.push_back(i);
    tree.light_pieces.push_back(std::move(whole));
  } else {
    for (const LightTriangle& t : tree.light_triangles) tree.light_pieces.push_back({{t.v[0], t.v[1], t.v[2]}, t.plane});
  }
  return *largest;
}

// What a tree with receiver bounds knows of its shaft (the convex hull of
// the light and the receiver box): its box, its supporting planes, and the
// planes parallel to the light through the box's corners. Without receiver
// bounds, the light's box alone and no planes. Built in place: the corner
// planes point at the corner points.
struct Shaft {
  struct Plane {
    Orient3dFan fan;
    int outside;  // the fan's side of points outside the shaft
    std::array<size_t, 3> triple;  // the hull points it was made of
  };
  glm::dvec3 lo, hi;
  std::vector<Plane> planes;
  bool light_below_receivers = false;  // the light strictly below every corner plane
  std::deque<XPoint> corner_points;
  std::deque<XPlane> corner_planes;

  explicit Shaft(const LightTree& tree);
  Shaft(const Shaft&) = delete;
  Shaft& operator=(const Shaft&) = delete;

  // Whether the triangle lies wholly outside the shaft's box or beyond one
  // of its planes.
  bool Outside(const glm::dvec3 (&v)[3], bool has_box) const {
    bool outside = false;
    for (int i = 0; i < 3 && !outside && has_box; ++i) {
      outside = (v[0][i] < lo[i] && v[1][i] < lo[i] && v[2][i] < lo[i]) ||
                (v[0][i] > hi[i] && v[1][i] > hi[i] && v[2][i] > hi[i]);
    }
    for (size_t k = 0; k < planes.size() && !outside; ++k) {
      outside = true;
      for (int c = 0; c < 3 && outside; ++c) outside = planes[k].fan.Side(v[c]) == planes[k].outside;
    }
    return outside;
  }
};

Shaft::Shaft(const LightTree& tree) {
  const auto& ll = tree.light_local;
  lo = glm::dvec3(std::numeric_limits<double>::infinity());
  hi = -lo;
  for (const auto& p : ll) {
    lo = glm::min(lo, p);
    hi = glm::max(hi, p);
  }
  if (!tree.receiver_box) return;
  const auto& [box_lo, box_hi] = *tree.receiver_box;
  lo = glm::min(lo, box_lo);
  hi = glm::max(hi, box_hi);
  glm::dvec3 corners[8];
  for (int c = 0; c < 8; ++c) {
    corners[c] = glm::dvec3((c & 1) ? box_hi.x : box_lo.x, (c & 2) ? box_hi.y : box_lo.y,
                            (c & 4) ? box_hi.z : box_lo.z);
    corner_points.push_back(XPoint::Input(corners[c]));
    corner_planes.push_back(XPlane::ParallelThrough(*tree.light_plane, corner_points.back()));
  }
  // The shaft: supporting planes of the convex hull of the light and the
  // box (brute force over point triples; a dozen points). Every segment
  // from the light to a receiver lies inside it.
  std::vector<glm::dvec3> hull_points(ll.begin(), ll.end());
  for (const auto& c : corners) {
    if (std::find(hull_points.begin(), hull_points.end(), c) == hull_points.end()) {
      hull_points.push_back(c);
    }
  }
  const size_t m = hull_points.size();
  // Any subset of the supporting planes bounds a superset of the hull, so
  // culling with fewer planes stays correct, only looser. Brute force costs
  // O(m^4) and keeps every triple of (coplanar) light vertices as a plane:
  // a 1024-vertex light never finished. For lights of more than a dozen
  // vertices only the triples that can bound the sides of the shaft are
  // tried: at least one box corner, and light vertices only as one vertex
  // or an edge of the polygon (its hull edges when it is convex). The light
  // plane itself culls nothing more than the "behind the light" test below.
  const size_t light_count = ll.size();
  const bool all_triples = m <= 16;
  auto is_light = [&](size_t index) { return index < light_count; };
  auto light_edge = [&](size_t a, size_t b) { return b == a + 1 || (a == 0 && b == light_count - 1); };
  for (size_t i = 0; i < m; ++i) {
    for (size_t j = i + 1; j < m; ++j) {
      if (!all_triples && is_light(i) && is_light(j) && !light_edge(i, j)) continue;
      for (size_t k = j + 1; k < m; ++k) {
        if (!all_triples && is_light(k)) continue;  // i < j < k: three light vertices
        bool pos = false, neg = false;
        for (size_t x = 0; x < m && !(pos && neg); ++x) {
          const int o = Orient3d(hull_points[i], hull_points[j], hull_points[k], hull_points[x]);
          pos |= o > 0;
          neg |= o < 0;
        }
        if (pos == neg) continue;  // not supporting (or all coplanar)
        // A face with four or more corners (a box's side, the light with a
        // box edge) is found once per triple of them: keep it once. Its
        // points lie on a plane already kept exactly when the triple does.
        const auto on_plane = [&](const Plane& plane, size_t x) {
          const auto& [a, b, c] = plane.triple;
          return Orient3d(hull_points[a], hull_points[b], hull_points[c], hull_points[x]) == 0;
        };
        const bool known = std::any_of(planes.begin(), planes.end(), [&](const Plane& plane) {
          return on_plane(plane, i) && on_plane(plane, j) && on_plane(plane, k);
        });
        if (known) continue;
        planes.push_back({Orient3dFan(hull_points[i], hull_points[j], hull_points[k]), pos ? -1 : 1, {i, j, k}});
      }
    }
  }
  // Separation along the light normal needs the light strictly below the box.
  light_below_receivers = true;
  for (const auto& plane : corner_planes) {
    for (const auto& y : tree.light_points) light_below_receivers &= EuclidSide(y, plane) < 0;
  }
}

// A triangle kept as an occluder, before its vertices are merged.
struct Selected {
  int8_t light_side[3];  // exact sides of its vertices against the light plane
  bool far = false;
};

// Whether the triangle (local frame) is an occluder of the tree, and whether
// it is far: not outside the shaft, not degenerate, not behind or in the
// light plane; far when it is in the light's closed front and strictly
// separated from the receiver box by an axis plane or a plane parallel to
// the light, with the light on the occluder's side.
std::optional<Selected> SelectTriangle(const LightTree& tree, const Shaft& shaft, const Orient3dFan& light_fan,
                                       const glm::dvec3 (&v)[3]) {
  // Shaft box (only with receiver bounds: otherwise receivers are anywhere).
  if (shaft.Outside(v, tree.receiver_box.has_value())) return std::nullopt;
  // Degenerate (zero-area) triangles block nothing. Test the projection
  // along the dominant normal axis first: it is the one whose sign the
  // filter settles.
  const glm::dvec3 g = glm::abs(glm::cross(v[1] - v[0], v[2] - v[0]));
  const int k = g.x >= g.y && g.x >= g.z ? 0 : (g.y >= g.z ? 1 : 2);
  if (Orient2d(v[0], v[1], v[2], (k + 1) % 3, (k + 2) % 3) == 0 && Orient2d(v[0], v[1], v[2], k, (k + 1) % 3) == 0 &&
      Orient2d(v[0], v[1], v[2], (k + 2) % 3, k) == 0) {
    return std::nullopt;
  }
  // Behind or in the light plane: blocks no segment from the light.
  Selected selected{};
  bool any_front = false, any_back = false;
  for (int c = 0; c < 3; ++c) {
    selected.light_side[c] = static_cast<int8_t>(light_fan.Side(v[c]));
    any_front |= selected.light_side[c] > 0;
    any_back |= selected.light_side[c] < 0;
  }
  if (!any_front) return std::nullopt;
  if (!tree.receiver_box || any_back) return selected;
  const auto& [lo, hi] = *tree.receiver_box;
  for (int axis = 0; axis < 3 && !selected.far; ++axis) {
    bool above = true, below = true;
    for (int c = 0; c < 3; ++c) {
      above &= v[c][axis] > hi[axis];
      below &= v[c][axis] < lo[axis];
    }
    for (const auto& y : tree.light_local) {
      above &= y[axis] > hi[axis];
      below &= y[axis] < lo[axis];
    }
    selected.far = above || below;
  }
  if (!selected.far && shaft.light_below_receivers) {
    bool separated = true;
    for (int c = 0; c < 3 && separated; ++c) {
      const XPoint x = XPoint::Input(v[c]);
      for (const auto& plane : shaft.corner_planes) separated &= EuclidSide(x, plane) < 0;
    }
    selected.far = separated;
  }
  return selected;
}

}  // namespace

StatusOr<std::unique_ptr<LightTree>> LightTree::Create(const AreaLight& light, const Scene& scene,
                                                       const TreeOptions& options, const SceneTriangleIndex* index) {
  if (index != nullptr && index->triangle_count() != scene.TriangleCount()) {
    return absl::InvalidArgumentError(absl::StrCat("the triangle index has ", index->triangle_count(),
                                                   " triangles, the scene ", scene.TriangleCount()));
  }
  if (!(options.shadow_tolerance >= 0.0 && options.shadow_tolerance <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("shadow_tolerance: must be a share of the light in [0, 1], got ", options.shadow_tolerance));
  }
  auto tree = std::make_unique<LightTree>();
  VISQ_ASSIGN_OR_RETURN(PreparedLight prepared, PrepareLight(light));
  tree->origin = prepared.origin;
  tree->radiance = light.radiance;
  tree->max_bytes = options.max_bytes;
  // Half the budget: a frame's answers (a 320 x 180 view on one tree) fit,
  // and an identical second call refines nothing and subtracts nothing.
  tree->max_answer_bytes = options.keep_answers ? options.max_bytes / 2 : 0;
  tree->classify_points = options.classify_points;
  tree->direct_candidates = options.classify_points ? options.direct_candidates : 0;
  tree->cull_pyramid = options.cull_pyramid;
  tree->quadrilaterals = options.quadrilaterals;
  tree->line_boxes = options.line_boxes;
  tree->fragment_grid = options.fragment_grid && options.line_boxes;
  tree->largest_first = options.largest_first;
  tree->shadow_tolerance = options.shadow_tolerance;
  tree->light_local = std::move(prepared.local);
  // The normal kept points away from the emitting side: from a point that
  // sees the light, towards it.
  tree->light_unit_normal = -prepared.unit_normal;
  tree->light_diameter = prepared.diameter;
  const LightTriangle& largest = PlantLight(*tree, prepared.triangles);

  // The receiver box in the local frame. No outward rounding is needed:
  // rounding is monotone, so a world point inside the world box lands inside
  // the converted box (and widening would make flat boxes thick by an ulp,
  // which costs near-degenerate hull faces).
  if (options.receiver_bounds && !options.receiver_bounds->Empty()) {
    const glm::dvec3 lo = options.receiver_bounds->min - tree->origin;
    const glm::dvec3 hi = options.receiver_bounds->max - tree->origin;
    tree->receiver_box = std::make_pair(lo, hi);
  }
  VISQ_RETURN_IF_ERROR(tree->SelectOccluders(scene, options, index, largest));
  tree->IndexOccludersAndPlantTheTree();
  return tree;
}

Status LightTree::SelectOccluders(const Scene& scene, const TreeOptions& options, const SceneTriangleIndex* index,
                                  const LightTriangle& largest) {
  const auto& ll = light_local;
  const Orient3dFan light_fan(ll[largest.v[0]], ll[largest.v[1]], ll[largest.v[2]]);
  const Shaft shaft(*this);
  std::vector<uint8_t> excluded;
  if (!options.exclude_triangles.empty()) {
    excluded.assign(scene.TriangleCount(), 0);
    for (uint32_t t : options.exclude_triangles) {
      if (t < excluded.size()) excluded[t] = 1;
    }
  }

  // Occluder vertices are merged by position, not by index: meshes often
  // repeat positions (flat shading, per-face vertices), and one point object
  // per position lets a split vertex be recognised as lying on an edge plane
  // by construction instead of by an exact evaluation (see EdgePlane).
  // By scene vertex index, for the triangles visited only: a vector over
  // all the scene's positions would be filled per tree, however few
  // triangles the shaft meets.
  // A placed position's key is its placement's (plus one) in the high
  // half, its mesh vertex in the low one.
  absl::flat_hash_map<uint64_t, uint32_t> remap;
  struct PositionHash {
    size_t operator()(const glm::dvec3& p) const {
      // The coordinates' bits, mixed (the map mixes the result again);
      // + 0.0 makes -0 hash as +0, which it equals.
      return absl::HashOf(std::bit_cast<uint64_t>(p.x + 0.0), std::bit_cast<uint64_t>(p.y + 0.0),
                          std::bit_cast<uint64_t>(p.z + 0.0));
    }
  };
  absl::flat_hash_map<glm::dvec3, uint32_t, PositionHash> by_position;
  std::vector<glm::dvec3> occ_local;
  struct Pending { uint32_t v[3]; int8_t side[3]; uint32_t tri; bool far; bool two_sided; };
  std::vector<Pending> pending;
  // With an index, only the triangles whose boxes meet the shaft's box (in
  // world coordinates, padded far beyond the rounding of the local frame:
  // a superset; the exact tests below decide) and in increasing order, as
  // without it, so the occluder lists are the same.
  std::vector<uint32_t> near_shaft;
  const bool indexed = index != nullptr && receiver_box.has_value();
  if (indexed) {
    const auto largest = [](const glm::dvec3& x) { return std::max({std::fabs(x.x), std::fabs(x.y), std::fabs(x.z)}); };
    const double magnitude = std::max(largest(shaft.lo), largest(shaft.hi)) + largest(origin);
    const glm::dvec3 pad(1e-9 * magnitude + 1e-300);
    near_shaft = index->InBox(shaft.lo + origin - pad, shaft.hi + origin + pad);
  }
  const size_t visit_count = indexed ? near_shaft.size() : scene.TriangleCount();
  // Most triangles the shaft meets are kept, with about half a new vertex
  // each: growing the maps by doubling cost a tenth of a large room's tree.
  remap.reserve(visit_count / 2);
  by_position.reserve(visit_count / 2);
  for (size_t visit = 0; visit < visit_count; ++visit) {
    if (visit % 4096 == 0) {
      VISQ_RETURN_IF_ERROR(
          options.stop.Check(absl::StrCat("light tree, after ", visit, " of ", visit_count, " triangles")));
    }
    const size_t ti = indexed ? near_shaft[visit] : visit;
    // The triangle's corners where the scene holds it: the record's, or
    // placed (PlacePoint: the flattened scene's doubles to the bit).
    const Scene::Held held = scene.Locate(ti);
    uint64_t tri[3];
    glm::dvec3 v[3];
    if (held.placement < 0) {
      const glm::uvec3 corners = scene.triangles[held.index];
      for (int c = 0; c < 3; ++c) {
        if (corners[c] >= scene.positions.size()) {
          return absl::InvalidArgumentError(absl::StrCat("scene.triangles[", held.index, "][", c, "]: index ",
                                                         corners[c], " >= ", scene.positions.size(), " positions"));
        }
      }
      if (!excluded.empty() && excluded[ti]) continue;
      for (int c = 0; c < 3; ++c) {
        tri[c] = corners[c];
        v[c] = scene.positions[corners[c]] - origin;
      }
    } else {
      if (!excluded.empty() && excluded[ti]) continue;
      const MeshPlacement& placement = scene.placements[size_t(held.placement)];
      const SceneMesh& mesh = scene.meshes[placement.mesh];
      const glm::uvec3 corners = mesh.triangles[held.index];
      for (int c = 0; c < 3; ++c) {
        tri[c] = (uint64_t(held.placement) + 1) << 32 | corners[c];
        v[c] = PlacePoint(placement.world, mesh.positions[corners[c]]) - origin;
      }
    }
    const std::optional<Selected> selected = SelectTriangle(*this, shaft, light_fan, v);
    if (!selected) continue;
    Pending p{};
    for (int c = 0; c < 3; ++c) p.side[c] = selected->light_side[c];
    p.far = selected->far;
    for (int c = 0; c < 3; ++c) {
      auto [known, first] = remap.try_emplace(tri[c], 0u);
      if (first) {
        auto [it, inserted] =
            by_position.try_emplace(v[c], static_cast<uint32_t>(occ_local.size()));
        if (inserted) occ_local.push_back(v[c]);
        known->second = it->second;
      }
      p.v[c] = known->second;
    }
    p.tri = static_cast<uint32_t>(ti);
    if (p.far) {
      // Orient so that the light is on the non-negative side.
      bool pos = false, neg = false;
      for (const auto& y : ll) {
        const int s = Orient3d(y, v[0], v[1], v[2]);
        pos |= s > 0;
        neg |= s < 0;
      }
      if (neg && !pos) std::swap(p.v[1], p.v[2]);
      p.two_sided = pos && neg;
    }
    pending.push_back(p);
  }
  vertices = std::move(occ_local);
  vertices.shrink_to_fit();
  for (const auto& p : pending) {
    if (p.far) {
      far.push_back({{p.v[0], p.v[1], p.v[2]}, p.two_sided});
    } else {
      // The triangles are visited in increasing order (NearOfTriangle).
      if (!near.empty()) VISQ_CHECK_LT(near.back().scene_triangle, p.tri);
      near.push_back({{p.v[0], p.v[1], p.v[2]}, {p.side[0], p.side[1], p.side[2]}, p.tri});
    }
  }
  return absl::OkStatus();
}

size_t LightTree::MemoryBytesLocked() const {
  return sizeof(LightTree) + nodes.capacity() * sizeof(Node) + list_bytes +
         lists.capacity() * sizeof(std::vector<uint32_t>) + free_lists.capacity() * 4 +
         vertices.capacity() * sizeof(glm::dvec3) + far.capacity() * sizeof(FarOccluder) +
         near.capacity() * sizeof(NearOccluder) + index.MemoryBytes() +
         light_points.size() * sizeof(XPoint) +
         light_planes.size() * sizeof(XPlane);
}

void LightTree::IndexOccludersAndPlantTheTree() {
  far.shrink_to_fit();
  near.shrink_to_fit();
  VISQ_CHECK_LT(far.size() + near.size(), size_t{UINT32_MAX});
  for (const FarOccluder& o : far) {
    for (const uint32_t v : o.v) VISQ_CHECK_LT(v, vertices.size());
  }
  for (const NearOccluder& n : near) {
    for (const uint32_t v : n.v) VISQ_CHECK_LT(v, vertices.size());
  }
  // Ids: far occluders first, then near ones.
  index.Build(static_cast<uint32_t>(far.size() + near.size()), [&](uint32_t id) {
    const uint32_t* v = OccluderVertices(id);
    const glm::dvec3 a = vertices[v[0]], b = vertices[v[1]], c = vertices[v[2]];
    return std::make_pair(glm::min(a, glm::min(b, c)), glm::max(a, glm::max(b, c)));
  });

  if (far.empty()) {
    NewNode(kVisible);
  } else {
    const uint32_t list = NewList();
    for (uint32_t i = 0; i < far.size(); ++i) lists[list].push_back(i);
    list_bytes = lists[list].capacity() * sizeof(uint32_t);
    NewNode(kUndefined, 0, list);
  }
  NewNode(kVisible);
  NewNode(kInvisible);
  VISQ_CHECK_EQ(nodes.size(), size_t{3});
  VISQ_CHECK_EQ(int{nodes[kSharedVisible].kind}, int{kVisible});
  VISQ_CHECK_EQ(int{nodes[kSharedInvisible].kind}, int{kInvisible});
}

LightTree::EdgeFans LightTree::MakeEdgeFans(uint32_t a, uint32_t b) const {
  EdgeFans e{a, b, {}};
  e.fans.reserve(light_local.size());
  for (const glm::dvec3& y : light_local) e.fans.emplace_back(y, vertices[a], vertices[b]);
  return e;
}

void LightTree::OccluderSides(const uint32_t v[3], const EdgeFans& edge, bool* pos, bool* nonpos) const {
  *pos = *nonpos = false;
  for (int i = 0; i < 3 && !(*pos && *nonpos); ++i) {
    const glm::dvec3& x = vertices[v[i]];
    for (const Orient3dFan& fan : edge.fans) {
      if (fan.Side(x) > 0) *pos = true; else *nonpos = true;
      if (*pos && *nonpos) break;
    }
  }
}

int32_t LightTree::NewNode(uint8_t kind, uint32_t a, uint32_t b) {
  // Inner nodes name two occluder vertices; undefined leaves a list.
  if (kind == kInner) {
    VISQ_DCHECK_LT(a, vertices.size());
    VISQ_DCHECK_LT(b, vertices.size());
  } else if (kind == kUndefined) {
    VISQ_DCHECK_LT(b, lists.size());
  }
  VISQ_CHECK_LT(nodes.size(), size_t{INT32_MAX});
  Node n;
  n.kind = kind;
  n.a = a;
  n.b = b;
  nodes.push_back(n);
  return static_cast<int32_t>(nodes.size() - 1);
}

uint32_t LightTree::NewList() {
  if (!free_lists.empty()) {
    const uint32_t i = free_lists.back();
    free_lists.pop_back();
    return i;
  }
  lists.emplace_back();
  return static_cast<uint32_t>(lists.size() - 1);
}

size_t LightTree::ChooseOccluder(const std::vector<uint32_t>& list, const glm::dvec3& p,
                                 const glm::dvec3& y) const {
  const glm::dvec3 d = p - y;
  size_t best = 0;
  double best_t = 0.0;  // crossings strictly between the light (t = 0) and P
  for (size_t k = 0; k < list.size(); ++k) {
    const FarOccluder& o = far[list[k]];
    const glm::dvec3 a = vertices[o.v[0]], b = vertices[o.v[1]], c = vertices[o.v[2]];
    // Möller-Trumbore: the crossing nearest P (t = 1) wins.
    const glm::dvec3 e1 = b - a, e2 = c - a, h = glm::cross(d, e2);
    const double det = glm::dot(e1, h);
    if (det == 0.0) continue;
    const glm::dvec3 s = y - a;
    const double u = glm::dot(s, h) / det;
    if (u < 0.0 || u > 1.0) continue;
    const glm::dvec3 qv = glm::cross(s, e1);
    const double v = glm::dot(d, qv) / det;
    if (v < 0.0 || u + v > 1.0) continue;
    const double t = glm::dot(e2, qv) / det;
    if (t > best_t && t < 1.0) {
      best_t = t;
      best = k;
    }
  }
  return best;
}

void LightTree::Refine(int32_t id, const glm::dvec3& p, const glm::dvec3& y) {
  VISQ_DCHECK_LT(size_t(id), nodes.size());
  if (nodes[id].kind != kUndefined) return;  // another query did it
  VISQ_DCHECK_LT(size_t(nodes[id].b), lists.size());
  std::vector<uint32_t> list = std::move(lists[nodes[id].b]);
  VISQ_DCHECK(!list.empty());
  lists[nodes[id].b] = {};
  free_lists.push_back(nodes[id].b);
  list_bytes -= list.capacity() * sizeof(uint32_t);
  refinements.fetch_add(1, std::memory_order_relaxed);
  std::swap(list[0], list[ChooseOccluder(list, p, y)]);

  // Replace the leaf by the BSP of the chosen occluder: inside its three
  // edge lines (all > 0, or all <= 0 for two-sided ones) is invisible.
  const FarOccluder o = far[list[0]];
  const uint32_t e[3][2] = {{o.v[0], o.v[1]}, {o.v[1], o.v[2]}, {o.v[2], o.v[0]}};
  const int32_t n2 = NewNode(kInner, e[1][0], e[1][1]);
  const int32_t n3 = NewNode(kInner, e[2][0], e[2][1]);
  nodes[n2].child[0] = n3;
  nodes[n2].child[1] = kSharedVisible;
  nodes[n3].child[0] = kSharedInvisible;
  nodes[n3].child[1] = kSharedVisible;
  int32_t negative = kSharedVisible;
  if (o.two_sided) {
    const int32_t n4 = NewNode(kInner, e[1][0], e[1][1]);
    const int32_t n5 = NewNode(kInner, e[2][0], e[2][1]);
    nodes[n4].child[0] = kSharedVisible;
    nodes[n4].child[1] = n5;
    nodes[n5].child[0] = kSharedVisible;
    nodes[n5].child[1] = kSharedInvisible;
    negative = n4;
  }
  Node& root = nodes[id];
  root.kind = kInner;
  root.a = e[0][0];
  root.b = e[0][1];
  root.child[0] = n2;
  root.child[1] = negative;

  // Filter the other occluders into the new leaves: invisible leaves drop
  // them, visible leaves that receive some become undefined.
  // The new inner nodes use the occluder's three edge lines.
  const EdgeFans edge_fans[3] = {MakeEdgeFans(e[0][0], e[0][1]), MakeEdgeFans(e[1][0], e[1][1]),
                                 MakeEdgeFans(e[2][0], e[2][1])};
  const auto fans_of = [&](const Node& node) -> const EdgeFans& {
    for (const EdgeFans& f : edge_fans) {
      if (f.a == node.a && f.b == node.b) return f;
    }
    VISQ_CHECK(false);
    return edge_fans[0];
  };
  struct Step { int32_t node, parent; int slot; };
  std::vector<Step> stack;
  for (size_t k = 1; k < list.size(); ++k) {
    const FarOccluder& other = far[list[k]];
    stack.assign(1, {id, -1, 0});
    while (!stack.empty()) {
      const Step step = stack.back();
      stack.pop_back();
      VISQ_DCHECK_LT(size_t(step.node), nodes.size());
      const uint8_t kind = nodes[step.node].kind;
      if (kind == kInner) {
        bool pos, nonpos;
        const Node& node = nodes[step.node];
        OccluderSides(other.v, fans_of(node), &pos, &nonpos);
        if (pos) stack.push_back({node.child[0], step.node, 0});
        if (nonpos) stack.push_back({node.child[1], step.node, 1});
      } else if (kind == kVisible) {
        // A visible class that receives an occluder becomes undefined.
        VISQ_DCHECK(step.node == kSharedVisible);
        const int32_t leaf = NewNode(kUndefined, 0, NewList());
        nodes[step.parent].child[step.slot] = leaf;
        stack.push_back({leaf, step.parent, step.slot});
      } else if (kind == kUndefined) {
        auto& l = lists[nodes[step.node].b];
        const size_t before = l.capacity();
        l.push_back(list[k]);
        list_bytes += (l.capacity() - before) * sizeof(uint32_t);
      }
      // kInvisible: the occluder is hidden there; dropped.
    }
  }
}

}  // namespace visq::exact::detail
