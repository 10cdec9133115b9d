// The tree behind LightVisibilityTree (private to lib/exact/): its state and
// the declarations of its parts, each defined in a file of its own:
//
//   light_tree_build.cpp     Create: the light's exact geometry, the shaft, the
//                            occluders' selection; the tree's growth (Refine)
//   light_tree_query.cpp     a query: the store of answers, the classification
//                            of points before the tree, the descent, the
//                            integration over the visible polygons
//   light_tree_occluders.cpp exact tests of one occluder against the whole light
//   light_tree_subtract.cpp  the polygon machinery: edge planes, splitting,
//                            clipping, subtracting occluders from fragments
//   light_polygon.cpp        the light's checks and triangulation
//
// light_visibility.h explains the algorithm (Mora et al. 2013).
#pragma once

#include <atomic>
#include <cmath>
#include <cstdint>
#include <deque>
#include <limits>
#include <memory>
#include <new>
#include <optional>
#include <shared_mutex>
#include <span>
#include <type_traits>
#include <unordered_map>
#include <utility>
#include <vector>

#include <absl/container/flat_hash_map.h>
#include <absl/container/inlined_vector.h>
#include <glm/glm.hpp>

#include "common/check.h"
#include "exact/exact_geometry.h"
#include "exact/light_visibility.h"
#include "exact/line_box.h"
#include "exact/occluder_index.h"

namespace visq::exact::detail {

// Sides used by the BSP: child 0 takes lines with side > 0, child 1 lines with
// side <= 0 (a line touching an edge line is never "inside" that edge).
enum NodeKind : uint8_t { kInner, kVisible, kInvisible, kUndefined };

// 20 bytes. Visible and invisible leaves without occluders are two shared
// sentinel nodes (kSharedVisible, kSharedInvisible), so an occluder BSP costs
// only its 3 or 5 inner nodes until occluders are filtered into a leaf.
struct Node {
  uint32_t a = 0, b = 0;        // inner: edge line a -> b (point indices);
                                // undefined leaf: b = index into lists
  int32_t child[2] = {-1, -1};  // inner only
  uint8_t kind = kUndefined;
};
static_assert(sizeof(Node) == 20);
constexpr int32_t kSharedVisible = 1, kSharedInvisible = 2;

// A far occluder: a scene triangle oriented so that the light lies on its
// non-negative side; lines from the light through its interior then have all
// three edge sides > 0. When the light straddles its plane, lines may cross
// it either way and the BSP also needs the all-negative class (5 nodes).
struct FarOccluder {
  uint32_t v[3];
  bool two_sided = false;
};

// A near occluder, clipped per query; vertices as point indices and their
// exact sides against the light plane.
struct NearOccluder {
  uint32_t v[3];
  int8_t light_side[3];
  uint32_t scene_triangle;
};

// One edge of a light fragment lies on a light-triangle edge or on a plane.
struct FVert {
  const XPoint* point;
  int32_t light_edge;   // >= 0: edge (light_edge, light_edge + 1) of the light piece
  const XPlane* plane;  // otherwise: the plane holding the edge to the next vertex
};


struct Fragment {
  uint32_t piece = 0;  // the light piece it lies in (LightTree::light_pieces)
  absl::InlinedVector<FVert, 8> v;  // most fragments have few vertices: no allocation
  // The LineBox of the fragment, computed on first use: 0 not yet, 1 valid,
  // -1 none (a direction with d[k] not certainly of the light's sign).
  int8_t box_state = 0;
  LineBox box;
};

struct LightTriangle {
  uint32_t v[3];  // indices into light points
  const XPlane* plane;
};

// A convex part of the light that fragments start from: its vertices (into
// light points, in the light's winding) and its plane.
struct LightPiece {
  absl::InlinedVector<uint32_t, 8> v;
  const XPlane* plane;
};

// An answer as the store keeps it: the three figures, and the rest (the
// polygons, the errors of an answer that left occluders out) only where
// there is any (a PointVisibility carries an empty vector in every answer:
// 24 bytes of the 48). 32 bytes, so a 16 MB tree's store (half its budget)
// holds about 80,000 answers: a 320 x 180 frame on one tree, asked again, is
// answered from it whole.
struct StoredAnswer {
  struct Rest {
    std::vector<std::vector<glm::dvec3>> polygons;
    double visible_area_fraction_error = 0.0;
    double visible_solid_angle_fraction_error = 0.0;
    double irradiance_error = 0.0;
  };
  double visible_area_fraction = 0.0;
  double visible_solid_angle_fraction = 0.0;
  double irradiance = 0.0;
  std::unique_ptr<Rest> rest;

  static StoredAnswer From(const PointVisibility& v) {
    StoredAnswer a{v.visible_area_fraction, v.visible_solid_angle_fraction, v.irradiance, nullptr};
    if (!v.visible_polygons.empty() || v.visible_area_fraction_error > 0.0 ||
        v.visible_solid_angle_fraction_error > 0.0 || v.irradiance_error > 0.0) {
      a.rest = std::make_unique<Rest>(Rest{v.visible_polygons, v.visible_area_fraction_error,
                                           v.visible_solid_angle_fraction_error, v.irradiance_error});
    }
    return a;
  }
  PointVisibility Answer() const {
    PointVisibility v;
    v.visible_area_fraction = visible_area_fraction;
    v.visible_solid_angle_fraction = visible_solid_angle_fraction;
    v.irradiance = irradiance;
    if (rest) {
      v.visible_polygons = rest->polygons;
      v.visible_area_fraction_error = rest->visible_area_fraction_error;
      v.visible_solid_angle_fraction_error = rest->visible_solid_angle_fraction_error;
      v.irradiance_error = rest->irradiance_error;
    }
    return v;
  }
};
static_assert(sizeof(StoredAnswer) == 32);

// A query as the store of answers knows it: every input bit that the answer
// depends on.
struct AnswerKey {
  uint64_t position[3];
  uint64_t normal[3];
  uint32_t receiver_triangle;
  uint8_t has_normal, has_triangle, want_polygons;
  bool operator==(const AnswerKey&) const = default;
  template <typename H>
  friend H AbslHashValue(H h, const AnswerKey& k) {
    return H::combine(std::move(h), k.position[0], k.position[1], k.position[2], k.normal[0], k.normal[1],
                      k.normal[2], k.receiver_triangle, k.has_normal, k.has_triangle, k.want_polygons);
  }
};


struct PairHash {
  size_t operator()(const std::pair<const void*, const void*>& p) const {
    const auto a = reinterpret_cast<uintptr_t>(p.first), b = reinterpret_cast<uintptr_t>(p.second);
    return std::hash<uintptr_t>()(a * 0x9E3779B97F4A7C15ull ^ (b + 0x632BE59BD9B4E019ull));
  }
};

// Objects at stable addresses, constructed one at a time into blocks of
// 64 that outlive Clear(): a reused arena allocates nothing. Trim hands
// back the blocks past a count.
template <typename T>
class Arena {
 public:
  Arena() = default;
  Arena(const Arena&) = delete;
  Arena& operator=(const Arena&) = delete;
  ~Arena() { Clear(); }

  // Constructs make()'s result in its slot: no move of the few hundred
  // bytes a point or plane holds.
  template <typename Make>
  const T* Add(const Make& make) {
    const size_t block = size_ / kBlock, slot = size_ % kBlock;
    if (block == blocks_.size()) blocks_.push_back(std::make_unique<Storage[]>(kBlock));
    T* object = ::new (static_cast<void*>(&blocks_[block][slot])) T(make());
    ++size_;
    return object;
  }
  void Clear() {
    for (size_t i = 0; i < size_; ++i) std::destroy_at(reinterpret_cast<T*>(&blocks_[i / kBlock][i % kBlock]));
    size_ = 0;
  }
  size_t Bytes() const { return blocks_.size() * kBlock * sizeof(Storage); }
  // Empty arenas only.
  void Trim(size_t kept_blocks) {
    VISQ_DCHECK_EQ(size_, size_t{0});
    if (blocks_.size() > kept_blocks) blocks_.resize(kept_blocks);
  }

 private:
  static constexpr size_t kBlock = 64;
  struct Storage {
    alignas(T) unsigned char bytes[sizeof(T)];
  };
  std::vector<std::unique_ptr<Storage[]>> blocks_;
  size_t size_ = 0;
};

inline double Area3(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  return 0.5 * glm::length(glm::cross(b - a, c - a));
}

// Solid angle of triangle (a, b, c) seen from the origin (Van Oosterom and
// Strackee 1983).
inline double SolidAngle(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  const double la = glm::length(a), lb = glm::length(b), lc = glm::length(c);
  const double num = std::fabs(glm::dot(a, glm::cross(b, c)));
  const double den = la * lb * lc + glm::dot(a, b) * lc + glm::dot(a, c) * lb + glm::dot(b, c) * la;
  return 2.0 * std::atan2(num, den);
}

// The light moved to its centroid and triangulated, after every check
// (light_polygon.cpp).
struct PreparedLight {
  glm::dvec3 origin{0.0};
  std::vector<glm::dvec3> local;
  std::vector<std::array<uint32_t, 3>> triangles;
  glm::dvec3 unit_normal{0.0};  // towards the emitting side (Newell's, of the counter-clockwise winding)
  double diameter = 0.0;        // the largest distance between two vertices
};
[[nodiscard]] StatusOr<PreparedLight> PrepareLight(const AreaLight& light);

class PyramidCull;  // light_tree_query.cpp

// ---------------------------------------------------------------------------
struct LightTree {
  // Validates the light, selects the occluders and plants the tree
  // (light_tree_build.cpp).
  [[nodiscard]] static StatusOr<std::unique_ptr<LightTree>> Create(const AreaLight& light, const Scene& scene,
                                                                   const TreeOptions& options,
                                                                   const SceneTriangleIndex* index);

  // The frame: everything is stored relative to the light centroid, rounded
  // once; all exact predicates are exact for these local coordinates.
  glm::dvec3 origin{0.0};
  double radiance = 1.0;
  double light_area = 0.0;

  std::deque<XPoint> light_points;      // light vertices (local)
  std::vector<glm::dvec3> light_local;  // same, as doubles
  std::deque<XPlane> light_planes;      // one per light triangle
  std::vector<LightTriangle> light_triangles;
  // The whole light when it is one strictly convex polygon in the light
  // plane, else its triangles: a quadrilateral's diagonal would cut every
  // shadow across it in two (docs/exact-method-notes.md).
  std::vector<LightPiece> light_pieces;
  const XPlane* light_plane = nullptr;  // the largest triangle's: front side positive
  // orient3d through the same three points: moved to P, the side of a vertex
  // against the slab's top (TopSide) in double where it is clear.
  std::optional<Orient3dFan> light_fan;
  int light_axis = 2;  // the axis nearest the light's normal: k of the LineBoxes

  // The occluders' vertices (local frame, input doubles), one per position,
  // shared by the triangles that meet there; never grows after Create. The
  // tree keeps only these 24 bytes a vertex: a query makes the exact point of
  // a vertex (an XPoint, ten times larger) on first use (Vertex), so that a
  // dense room's tree of 100K occluders holds no 25 MB of exact points that
  // each query touches a few dozen of.
  std::vector<glm::dvec3> vertices;
  std::vector<FarOccluder> far;
  std::vector<NearOccluder> near;  // in increasing order of scene_triangle (NearOfTriangle)
  OccluderIndex index;  // ids: far occluders first, then near ones
  std::optional<std::pair<glm::dvec3, glm::dvec3>> receiver_box;  // local frame

  mutable std::shared_mutex mutex;
  std::vector<Node> nodes;
  std::vector<std::vector<uint32_t>> lists;  // occluder lists of undefined leaves
  std::vector<uint32_t> free_lists;
  size_t list_bytes = 0;

  std::atomic<uint64_t> queries{0}, hits{0}, refinements{0}, unrefined_leaf_visits{0}, wholly_visible{0}, wholly_hidden{0},
      subtracted_directly{0}, answers_reused{0}, hidden_by_remembered_blockers{0};
  // Counted where occluders are subtracted, which reads the tree only.
  mutable std::atomic<uint64_t> merged_occluders{0};
  mutable std::atomic<uint64_t> fragment_grids{0};

  // The store of answers (Query), under a lock of its own: a lookup must
  // not wait for a refinement.
  mutable std::shared_mutex answers_mutex;
  absl::flat_hash_map<AnswerKey, StoredAnswer> answers;
  size_t answer_bytes = 0;  // under answers_mutex
  std::atomic<size_t> answer_bytes_now{0};  // the same, for the tree's budget, which counts the store too
  size_t max_answer_bytes = 0;
  size_t max_bytes = 0;
  bool classify_points = true;
  size_t direct_candidates = 0;
  // TreeOptions' switches of the same names.
  bool cull_pyramid = true;
  bool quadrilaterals = true;
  bool line_boxes = true;
  bool fragment_grid = true;
  bool largest_first = true;
  double shadow_tolerance = 0.0;
  // The light's plane as doubles, for the bounds on left-out shadows: its
  // unit normal pointing away from the emitting side (from a point that
  // sees the light, towards the light) and the largest distance between two
  // of its vertices.
  glm::dvec3 light_unit_normal{0.0};
  double light_diameter = 0.0;
  // p's distance to the light's plane, at the nearest light vertex (they
  // stand up to 1e-6 of its diameter off it): positive where p sees the
  // light's front.
  double LightPlaneDistance(const glm::dvec3& p) const;

  size_t MemoryBytesLocked() const;

  // --- The end of Create, once the occluders are selected. ----------------
  // The occluders' boxes in their hierarchy (far ones first), then the tree
  // as one undefined leaf holding every far occluder. Node 0 is the root; 1
  // and 2 are the shared visible / invisible leaves.
  void IndexOccludersAndPlantTheTree();

  // The scene's triangles that can block a segment from the light to the
  // receivers, far ones and near ones (the rest of Create).
  [[nodiscard]] Status SelectOccluders(const Scene& scene, const TreeOptions& options, const SceneTriangleIndex* index,
                                       const LightTriangle& largest);

  // --- Tree growth (under the exclusive lock). -----------------------------

  // Which sides of edge line (a, b) the lines from the light to occluder o
  // reach: it suffices to test the vertex-to-light-vertex lines, because the
  // side of line(y, x) is bilinear in (y, x). The fans are orient3d(y, a, b, .)
  // for the light's vertices y, made once per edge line and shared by all
  // the occluders a refinement filters (a leaf of a dense room holds
  // thousands): orient3d(y, a, b, x) = -orient3d(x, a, b, y), the side of the
  // line x -> y.
  struct EdgeFans {
    uint32_t a = 0, b = 0;
    std::vector<Orient3dFan> fans;
  };
  EdgeFans MakeEdgeFans(uint32_t a, uint32_t b) const;
  void OccluderSides(const uint32_t v[3], const EdgeFans& edge, bool* pos, bool* nonpos) const;

  int32_t NewNode(uint8_t kind, uint32_t a = 0, uint32_t b = 0);

  uint32_t NewList();

  // Which occluder of a leaf to insert. The paper takes a random one; we
  // take one that the query's line from P to a point y of the fragment that
  // reached the leaf actually crosses (a double-precision guess: it only
  // steers the choice, never the answer). Its invisible class then swallows
  // the occluders behind it at once, instead of growing nodes for occluders
  // this region of line space never meets. Of the occluders the line
  // crosses, the one nearest P: seen from the receivers it is the largest,
  // so its class holds the most lines: smaller trees and faster queries than
  // the one nearest the light (docs/exact-method-notes.md).
  size_t ChooseOccluder(const std::vector<uint32_t>& list, const glm::dvec3& p,
                        const glm::dvec3& y) const;

  void Refine(int32_t id, const glm::dvec3& p, const glm::dvec3& y);

  // --- Queries. --------------------------------------------------------------
  // A query's own geometry: the points and planes it constructs, and the
  // edge planes by edge. One per thread, reused from query to query: a
  // query makes hundreds of objects, and allocating them one by one (a
  // std::deque of these 200-byte objects allocates every second one) cost
  // more than the warm queries' arithmetic.
  struct EdgeLine;
  struct Scratch {
    Arena<XPoint> points;
    Arena<XPlane> planes;
    absl::flat_hash_map<std::pair<const void*, const void*>, const XPlane*, PairHash> edge_planes;
    // The points where a fragment edge's support (a light piece's edge,
    // by the address of its first vertex's slot, or a plane) meets a
    // plane: neighbouring fragments cut by one plane share them.
    absl::flat_hash_map<std::pair<const void*, const void*>, const XPoint*, PairHash> meets;
    std::vector<int> signs;
    // Subtract's working lists, kept for their capacity (it runs once per
    // occluder that reaches the fragments).
    struct ChainPiece {
      Fragment f;
      uint32_t lines;  // the edge lines still to split it by (bit k: line k)
    };
    std::vector<EdgeLine> subtract_lines;
    std::vector<ChainPiece> subtract_stack;
    std::vector<int> subtract_signs;
    // SubtractOccluders' grid over its fragments' boxes, once they are many
    // (one subtraction at a time: they do not nest), and the fragments a
    // shadow's box meets.
    FragmentGrid fragment_grid;
    bool fragment_grid_in_use = false;
    std::vector<uint32_t> grid_meeting;
    const XPoint* p = nullptr;
    // The query's stop: looked at every kStopStride calls of StopNow.
    const StopToken* stop = nullptr;
    uint32_t stop_countdown = 0;
    Status stopped;
    // The sign of d[light_axis] for every direction from P to the light;
    // 0 when it is not one strict sign (then no LineBoxes this query).
    int line_box_sign = 0;
    // The exact points of the tree's vertices made by this query, by vertex
    // index: valid where the stamp is this query's. One object per vertex
    // and query, as when the tree kept them: a point made on an edge plane
    // is then recognised as lying on it by its definition (EdgePlane,
    // OnPlaneByDefinition). Their addresses now follow the order in which
    // the query meets them, which only orients the edge planes (EdgePlane
    // orders a line's ends by address): ThroughPoints(P, b, a) is exactly
    // -ThroughPoints(P, a, b), so no sign and no rounded value changes.
    struct VertexSlot {
      uint32_t stamp = 0;
      const XPoint* point = nullptr;
    };
    std::vector<VertexSlot> vertex_points;
    // Which occluders this query subtracts, by occluder id: still to come,
    // or taken (subtracted, passed over, or inside a quadrilateral), where
    // the stamp is this query's (SubtractOccluders with quads).
    static constexpr uint8_t kCandidate = 1, kTaken = 2;
    struct OccluderSlot {
      uint32_t stamp = 0;
      uint8_t state = 0;
    };
    std::vector<OccluderSlot> occluder_marks;
    uint32_t stamp = 0;
    // Sets of occluders that together hid a whole light from this thread,
    // each with the point they hid, most recent first, and their tree
    // (HiddenByRememberedBlockers); kept from query to query.
    struct BlockerSet {
      glm::dvec3 p;
      std::vector<uint32_t> ids;
    };
    const LightTree* blockers_tree = nullptr;
    std::vector<BlockerSet> blocker_sets;
    bool most_recent_failed = false;  // the first set failed a try since it came
    glm::dvec3 previous_p{0.0};       // the last point HiddenByRememberedBlockers saw
    // The tree whose last query on this thread was a penumbra point
    // (GatherCandidates then leaves near occluders' exact tests to
    // SubtractOccluders).
    const LightTree* penumbra_tree = nullptr;

    // A point or plane from its factory, made in the query's arena.
    template <typename Make>
    const std::invoke_result_t<Make>* Add(const Make& make) {
      if constexpr (std::is_same_v<std::invoke_result_t<Make>, XPoint>) {
        return points.Add(make);
      } else {
        return planes.Add(make);
      }
    }
    // What a thread keeps between queries is bounded: a query past these
    // (a foliage penumbra point makes tens of thousands of points) allocates
    // its excess again, and hands it back at the next query's start, rather
    // than holding its largest query's memory for the thread's life.
    static constexpr size_t kKeptArenaBlocks = 64;  // 4,096 objects of each kind (a grille point makes 800)
    static constexpr size_t kKeptSlotsOverNeed = 4;  // vertex and occluder slots past 4x this tree's

    void Reset() {
      points.Clear();
      planes.Clear();
      points.Trim(kKeptArenaBlocks);
      planes.Trim(kKeptArenaBlocks);
      // This absl's clear() frees a table past 127 slots, and a penumbra
      // point of a grille fills a few hundred: each query grew them again
      // through seven rehashes. One allocation of the last query's size.
      const size_t edge_plane_count = edge_planes.size(), meet_count = meets.size();
      edge_planes.clear();
      meets.clear();
      edge_planes.reserve(edge_plane_count);
      meets.reserve(meet_count);
      p = nullptr;
      line_box_sign = 0;
      stop = nullptr;
      stop_countdown = 0;
      stopped = absl::OkStatus();
      if (++stamp == 0) {  // wrapped: forget every slot
        for (VertexSlot& slot : vertex_points) slot.stamp = 0;
        for (OccluderSlot& slot : occluder_marks) slot.stamp = 0;
        stamp = 1;
      }
    }
    // Room for a tree of `count` vertices and `occluders` occluders, at a
    // query's start (the slots outlive the query; no slot is this query's
    // yet, so slots of a larger tree seen before can be handed back).
    void FitTree(size_t count, size_t occluders) {
      FitSlots(vertex_points, count);
      FitSlots(occluder_marks, occluders);
    }
    template <typename Slot>
    static void FitSlots(std::vector<Slot>& slots, size_t count) {
      if (slots.size() > kKeptSlotsOverNeed * count + 4096) {
        slots.assign(count, Slot{});
        slots.shrink_to_fit();
      }
      if (slots.size() < count) slots.resize(count);
    }
    // What the scratch holds: its arenas, tables and slots.
    size_t Bytes() const {
      size_t bytes = points.Bytes() + planes.Bytes() +
                     (edge_planes.capacity() + meets.capacity()) * (sizeof(std::pair<const void*, const void*>) +
                                                                    sizeof(void*) + 1) +
                     vertex_points.capacity() * sizeof(VertexSlot) + occluder_marks.capacity() * sizeof(OccluderSlot);
      for (const BlockerSet& set : blocker_sets) bytes += sizeof(BlockerSet) + set.ids.capacity() * sizeof(uint32_t);
      return bytes;
    }
    // Room for `count` occluders' marks within a query.
    void FitOccluders(size_t count) {
      if (occluder_marks.size() < count) occluder_marks.resize(count);
    }
  };

  // Vertex i as an exact input point, made on first use in this query (the
  // scratch must have been fitted to this tree's vertices).
  const XPoint& Vertex(Scratch& s, uint32_t i) const {
    VISQ_DCHECK_LT(size_t(i), vertices.size());
    VISQ_DCHECK_LE(vertices.size(), s.vertex_points.size());
    Scratch::VertexSlot& slot = s.vertex_points[i];
    if (slot.stamp != s.stamp) {
      slot.point = s.Add([&] { return XPoint::Input(vertices[i]); });
      slot.stamp = s.stamp;
    }
    return *slot.point;
  }

  // The near occluder of a scene triangle, or null.
  const NearOccluder* NearOfTriangle(uint32_t scene_triangle) const {
    const auto it = std::lower_bound(near.begin(), near.end(), scene_triangle,
                                     [](const NearOccluder& n, uint32_t t) { return n.scene_triangle < t; });
    return it != near.end() && it->scene_triangle == scene_triangle ? &*it : nullptr;
  }

  // A query's receiver triangle, and its plane when the triangle is a near
  // occluder of the tree with nonzero area. P is taken to lie on that
  // plane (its position may be rounded a hair off it to either side), so
  // every triangle whose three vertices lie exactly in it (the receiver,
  // a coincident twin of opposite winding, a coplanar neighbour) meets a
  // segment from P to the light at P alone, or along it where the segment
  // lies in the plane: never strictly inside, so it never blocks. Without
  // this, a twin that P lies a rounding behind blocks every segment.
  // "Exactly" is in the tree's frame, on the vertices the predicates see:
  // a twin shares the receiver's vertices, so it is always found; a
  // triangle coplanar in the scene's coordinates may not stay so once
  // moved to the light's centroid (then it is an occluder as any other).
  //
  // Far occluders are left as they are: one can be coplanar with a
  // receiver (a floor or a ramp running on past an axis plane towards the
  // light), but it is strictly separated from the receiver box, so it
  // cannot hold P, and the lines from P (on the plane or a rounding off it)
  // that meet it are those to the light's points within about that
  // rounding of the plane (scaled by the ratio of their distances): a
  // sliver along the plane where the light meets it, which the tree
  // (shared by every receiver) keeps. Near ones in the plane cut such
  // slivers too from a P a rounding off it; leaving them out moves 11 of
  // Sponza's 14,400 answers (160 x 90) by 2e-13 at most
  // (docs/exact-method-notes.md).
  struct Receiver {
    uint32_t triangle = UINT32_MAX;  // none: UINT32_MAX
    const NearOccluder* near = nullptr;  // the triangle's, if it is one
    std::optional<Orient3dFan> plane;    // through its vertices, then
  };
  Receiver ReceiverOf(const std::optional<uint32_t>& triangle) const {
    Receiver r;
    if (!triangle) return r;
    r.triangle = *triangle;
    r.near = NearOfTriangle(*triangle);
    if (r.near != nullptr) {
      const uint32_t* v = r.near->v;
      // Zero-area triangles are never occluders, so this one spans a plane.
      r.plane.emplace(vertices[v[0]], vertices[v[1]], vertices[v[2]]);
    }
    return r;
  }
  // Whether near occluder `id` (an occluder id) lies exactly in the
  // receiver's plane. Cheap for the rest: the first vertex off the plane
  // decides, mostly in the fan's filter.
  bool InReceiverPlane(uint32_t id, const Receiver& r) const {
    if (!r.plane || id < far.size()) return false;
    const uint32_t* t = near[id - far.size()].v;
    return r.plane->Side(vertices[t[0]]) == 0 && r.plane->Side(vertices[t[1]]) == 0 &&
           r.plane->Side(vertices[t[2]]) == 0;
  }
  // Whether occluder `id` is the receiver's own triangle (a near one).
  bool IsReceiverTriangle(uint32_t id, const Receiver& r) const {
    return id >= far.size() && near[id - far.size()].scene_triangle == r.triangle;
  }
  // Whether occluder `id` never blocks for this receiver: its own
  // triangle, or a near one in its plane.
  bool IsReceiver(uint32_t id, const Receiver& r) const {
    return IsReceiverTriangle(id, r) || InReceiverPlane(id, r);
  }

  // Whether the query must stop (its status then in s.stopped). The clock
  // is read every few calls: a call is one occluder subtracted or one step
  // of the descent, a few microseconds at most.
  static constexpr uint32_t kStopStride = 8;
  static bool StopNow(Scratch& s);

  // The plane through P and edge line (a, b), shared by both orientations
  // of the line (so that a vertex created on it is recognised as lying on it
  // later); `sign` orients it as the edge a -> b. Null when P is on the line.
  struct EdgePlaneRef {
    const XPlane* plane;
    int sign;
  };
  EdgePlaneRef EdgePlane(Scratch& s, const XPoint& a, const XPoint& b) const;

  // Whether x is on the plane by construction (then its sign is 0 without
  // any arithmetic; this is also what keeps repeated planes off the exact
  // fallback). Besides "x was made on this plane", one case matters a lot:
  // the shadow of an occluder vertex v is Π_t ∩ plane(P, v, a) ∩ plane(P, v, b),
  // a point of line(P, v), and so lies on every edge plane through P and v.
  static bool OnPlaneByDefinition(const XPoint& x, const XPlane* plane);

  // Whether x lies on `plane` (a plane through an input apex, P, and two
  // more input points) by the input points of the planes it is defined on:
  // one of those is `plane` itself, made from another edge on the same
  // line, or two of them, through P, meet along the line from P through a
  // vertex of one that lies on the other and on `plane` (boxes joined as a
  // modeller joins them share edge lines and corners on edges, not
  // vertices). Tested where the filter leaves a sign open, before the
  // exact evaluation, which finds the same zero at a hundred times the
  // cost of these orientation tests (a grille's window: 3.3 a query).
  static bool OnPlaneByInputs(const XPoint& x, const XPlane& plane);

  // An edge line (a, b) as one query sees it. The plane through P and the
  // line is made only when it is needed: to split, or to side a vertex that
  // is not an input point. An input vertex takes the orientation test on its
  // doubles (a static filter, about 20 flops), which is most of them: the
  // light's own vertices, on every fragment that nothing has split yet. Both
  // routes are exact, so they agree on every sign.
  struct EdgeLine {
    // Made in place (emplace_back): as an aggregate, each of a
    // subtraction's lines was a zeroed 288-byte temporary, then copied.
    EdgeLine(const XPoint* a_, const XPoint* b_) : a(a_), b(b_) {}
    const XPoint* a;
    const XPoint* b;
    bool has_plane = false;
    EdgePlaneRef plane{nullptr, 0};
    std::optional<Orient3dFan> fan;  // orient3d(P, a, b, .), for input vertices
    std::optional<PlaneFilter> fan_filter;  // its plane, for derived ones
  };
  EdgePlaneRef PlaneOf(Scratch& s, EdgeLine& e) const;

  // Side of x against the edge line, as the side of the line x -> P:
  // orient3d(x, P, a, b) = -orient3d(P, a, b, x). Zero when P is on the line.
  int LineSide(Scratch& s, EdgeLine& e, const XPoint& x) const;
  // The same from the line's exact plane (made on first use), past the
  // fan's tests.
  int PlaneLineSide(Scratch& s, EdgeLine& e, const XPoint& x) const;
  // The same, for the many vertices a fragment tests against one line: the
  // line's fan and filter made once (ReadyFan), and their tests inline.
  void ReadyFan(Scratch& s, EdgeLine& e) const {
    if (e.fan || e.a->kind != XPoint::Kind::kInput || e.b->kind != XPoint::Kind::kInput) return;
    e.fan.emplace(s.p->input, e.a->input, e.b->input);
    e.fan_filter = e.fan->Filter();
  }
  VISQ_EXACT_INLINE int QuickLineSide(Scratch& s, EdgeLine& e, const XPoint& x) const {
    if (e.fan_filter) {
      if (x.kind == XPoint::Kind::kInput) return -e.fan->Side(x.input);
      const int fast = FastSignOfDot(*e.fan_filter, x.fast);
      if (fast != kUncertain) return -fast * x.w_sign;
      return PlaneLineSide(s, e, x);
    }
    return LineSide(s, e, x);
  }

  // The side that every vertex of f has against the edge line, when f's
  // line box settles it (kUncertain otherwise): through P, the line's plane
  // is a line in the chart of the LineBoxes, and a box wholly on one side
  // of it, past the rounding of the fan's normal and of this evaluation,
  // holds the images of f's vertices on that side. One test where
  // EdgeStraddle takes one a vertex; exact as they are.
  int BoxLineSide(const Scratch& s, Fragment& f, EdgeLine& e) const {
    if (!e.fan || !HasLineBox(s, f)) return kUncertain;
    const int k = light_axis, u = (k + 1) % 3, v = (k + 2) % 3;
    const glm::dvec3& n = e.fan->Normal();
    const glm::dvec3& m = e.fan->Magnitude();
    const LineBox& b = f.box;
    // h(g) = n[u] g[0] + n[v] g[1] + n[k]: n . d = d[k] h for a direction d
    // whose image is g, and d[k] has the sign line_box_sign.
    const double h_max = n[u] * (n[u] > 0 ? b.hi[0] : b.lo[0]) + n[v] * (n[v] > 0 ? b.hi[1] : b.lo[1]) + n[k];
    const double h_min = n[u] * (n[u] > 0 ? b.lo[0] : b.hi[0]) + n[v] * (n[v] > 0 ? b.lo[1] : b.hi[1]) + n[k];
    const double g0 = std::max(std::fabs(b.lo[0]), std::fabs(b.hi[0]));
    const double g1 = std::max(std::fabs(b.lo[1]), std::fabs(b.hi[1]));
    // The normal's error (kFanNormalError of m a component) and three roundings of
    // the sum (of its absolute terms), with a factor of ten to spare.
    const double scale = (m[u] + std::fabs(n[u])) * g0 + (m[v] + std::fabs(n[v])) * g1 + m[k] + std::fabs(n[k]);
    if (!(scale > 1e-250) || !std::isfinite(scale)) return kUncertain;
    const double margin = 1e-14 * scale;
    // LineSide is -sign(n . d) = -line_box_sign * sign(h).
    if (h_min > margin) return -s.line_box_sign;
    if (h_max < -margin) return s.line_box_sign;
    return kUncertain;
  }

  // The sides of every fragment vertex. Returns false when every sign is zero
  // (P on the edge line, or a zero-area fragment).
  bool EdgeSides(Scratch& s, const Fragment& f, EdgeLine& e, std::vector<int>* signs) const;
  // Whether some vertex of f lies on each strict side of the edge line,
  // stopping at the first vertex that shows both.
  struct Straddle {
    bool any_positive = false, any_negative = false;
  };
  Straddle EdgeStraddle(Scratch& s, const Fragment& f, EdgeLine& e) const;

  // Exact tests of one occluder triangle against the whole light, on input
  // doubles only (orientation tests with a static filter, no constructed
  // points): a few hundred nanoseconds, against microseconds for clipping
  // and subtracting it.
  //
  // Whether no line from P through the light passes strictly inside the
  // triangle: some edge line has every light vertex on its <= 0 side (no
  // all-positive line), and some edge line has every light vertex > 0 (no
  // all-non-positive one). Sides are linear in the light point over each
  // light triangle, so vertices decide; lines through the closed light
  // polygon stand for the segments. P on an edge line: nothing is strictly
  // inside. A triangle whose shadow misses by this test blocks nothing, and
  // neither does any part of it (a clipped near occluder).
  bool ShadowMissesLight(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const;

  // The same decision from the sides of the lines from P to the light's
  // vertices against a convex polygon's edge lines: side_of(edge, vertex).
  template <typename SideOf>
  bool ShadowMissesLightBySides(size_t edge_count, const SideOf& side_of) const {
    bool miss_pos = false, miss_neg = false;
    for (size_t e = 0; e < edge_count; ++e) {
      bool all_nonpos = true, all_pos = true, all_zero = true;
      for (size_t i = 0; i < light_local.size(); ++i) {
        const int side = side_of(e, i);
        all_nonpos &= side <= 0;
        all_pos &= side > 0;
        all_zero &= side == 0;
      }
      // Every light vertex on one plane with P and the line: P is on the
      // line (P is strictly in front of the light), nothing strictly inside.
      if (all_zero) return true;
      miss_pos |= all_nonpos;
      miss_neg |= all_pos;
    }
    return miss_pos && miss_neg;
  }

  // Which segments from P to the light's vertices cross the triangle's
  // interior, P and the vertex strictly on opposite sides of its plane (bit
  // i: vertex i, for the first 64), and whether all of them do. When all do,
  // the triangle blocks every segment from P to the light: its plane
  // separates P from the light's convex hull, whose central projection from
  // P onto the plane is the convex hull of the vertices' crossings, inside
  // the triangle.
  struct Cover {
    uint64_t mask = 0;
    bool all = false;
  };
  Cover CoveredLightVertices(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const;

  // The vertices of an occluder: far ones first, then near ones.
  const uint32_t* OccluderVertices(uint32_t id) const {
    const uint32_t far_count = static_cast<uint32_t>(far.size());
    VISQ_DCHECK_LT(size_t(id), far.size() + near.size());
    return id < far_count ? far[id].v : near[id - far_count].v;
  }

  // ShadowMissesLight and, when the shadow does not miss, CoveredLightVertices
  // from one set of signs: both take the sides of the light's vertices
  // against the planes through P and the triangle's edges, and every query
  // tests dozens of candidates. Lights of many vertices take the two tests.
  static constexpr size_t kSharedSidesVertices = 16;
  struct OccluderTest {
    bool misses = true;
    Cover cover;
  };
  OccluderTest TestOccluder(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const;

  // The edges of a near occluder clipped to the slab between the light
  // plane and the plane through P parallel to it (`slab_top`): the part of
  // it that lies between, but for an edge on the slab's top (every light
  // point is on its inner side). False when no part of it can block
  // (nothing strictly between, or its clipped shadow misses the light).
  // `corners` gets the clipped polygon's vertices (for its LineBox).
  using Edges = std::vector<std::pair<const XPoint*, const XPoint*>>;
  using Corners = absl::InlinedVector<const XPoint*, 6>;
  bool NearOccluderEdges(Scratch& s, const NearOccluder& n, const XPlane& slab_top, Edges* edges,
                         Corners* corners) const;

  // EuclidSide of occluder vertex `vertex` against the slab's top (the
  // plane through P parallel to the light's): the light plane's normal, in
  // double, dotted with the vertex's offset from P where the static filter
  // settles it, else the exact test.
  int TopSide(Scratch& s, uint32_t vertex, const XPlane& slab_top) const {
    const int fast = light_fan->ParallelSide(s.p->input, vertices[vertex]);
    if (fast != kUncertain) return fast;
    return EuclidSide(Vertex(s, vertex), slab_top);
  }

  // The side of every line of a convex polygon's edges (`lines`, made from
  // `edges`, a -> b in order around it, an edge on the slab's top left
  // out) that the lines from the light through the polygon lie on: that of
  // any corner off the first edge's line (the polygon is on the light's
  // side of P). 0 when every corner is on it: P sees the polygon edge on.
  int InsideSign(Scratch& s, std::vector<EdgeLine>& lines, const Edges& edges) const;

  // An occluder's edges and corners as a query subtracts it: a far one
  // whole, a near one clipped to the slab under P (made on first use in
  // `*slab_top`). False when no part of it can block.
  bool OccluderEdges(Scratch& s, uint32_t id, const XPlane** slab_top, Edges* edges, Corners* corners) const;

  // Two occluders of one kind (far or near) next to each other in the
  // scene's triangle order (as meshes list a quadrilateral's triangles)
  // that share an edge and are seen from P as one strictly convex
  // quadrilateral, wholly inside the slab between P and the light, cast
  // that quadrilateral's shadow:
  // subtracted as one polygon, the fragments are not cut along their
  // diagonal. Longer runs of the order (strips) took no less time on
  // Sponza, veach-ajar and the bunny (docs/exact-method-notes.md).
  using OccluderPolygon = absl::InlinedVector<uint32_t, 4>;
  // The quadrilateral (or, where a shared vertex lies on the line of its
  // neighbours, the triangle) of occluder `id` and a neighbour still to be
  // subtracted in this query (Scratch::occluder_marks), which it marks
  // taken. False when there is none.
  bool QuadWithNeighbour(Scratch& s, const XPlane** slab_top, uint32_t id, OccluderPolygon* quad,
                         uint32_t* neighbour) const;

  // Whether subtracting the blockers that block the most light vertices (at
  // most kFewBlockers of them; near ones clipped to the slab, and with a
  // neighbour among them as one quadrilateral, as on the main route) leaves
  // nothing of the light.
  static constexpr size_t kFewBlockers = 16;
  struct Blocker {
    uint32_t id;   // occluder id: far ones first, then near ones
    int vertices;  // light vertices whose segments it blocks
  };
  bool HiddenByFewBlockers(Scratch& s, const std::vector<Fragment>& light, std::vector<Blocker>* blockers) const;

  // Neighbouring points in an umbra cast by several triangles together (a
  // gallery's vault, a mesh's faces) are mostly hidden by the same few:
  // those that hid a whole light from this thread at a point nearby (at
  // most kRememberedBlockers a set, remembered where a point was found
  // hidden by subtraction; kRememberedSets sets), subtracted from the
  // light before any gathering. The most recent set is tried (until it
  // fails, then not until a newer one comes), and the one found at the
  // point nearest P, within four steps of the thread's previous point (a
  // frame's row above). A set is subtracted (its neighbours as
  // quadrilaterals) only when each light vertex's
  // segment crosses one of its triangles; then, if nothing is left, the
  // point is hidden, exactly: any occluders of the tree but those in P's
  // receiver plane (IsReceiver) prove it, so a stale memory costs a try and
  // no wrong answer.
  // A set whose subtraction fails is forgotten.
  static constexpr size_t kRememberedBlockers = 64;
  static constexpr size_t kRememberedSets = 64;
  bool HiddenByRememberedBlockers(Scratch& s, const std::vector<Fragment>& light, const Receiver& receiver) const;
  // Remembers `ids` as blockers that hid the point P, if few.
  void RememberBlockers(Scratch& s, std::vector<uint32_t>* ids) const;

  // A triangle's size as seen from p: a number that grows with its area
  // projected across the direction from p (the area times the cosine of
  // its tilt) over its squared distance, a proxy of its solid angle (it
  // orders subtractions; any order gives the same answer). Without the
  // tilt a slat seen edge on came before the panes' bars that it hides
  // nothing of (a grille's window: 2 % slower).
  static double ApparentSize(const glm::dvec3& p, const glm::dvec3 (&v)[3]);

  // Orders occluder ids largest as seen from p first (they leave the fewest
  // fragments for the others to cut), ties by id, so the order (and the
  // float sums over the fragments) do not depend on the traversal.
  void SortLargestFirst(const glm::dvec3& p, std::vector<uint32_t>* ids) const;

  // With shadow_tolerance: takes out of `ids` the occluders whose shadows
  // on the light, seen from p, are smallest, while the bounds on their areas
  // (ShadowAreaBound) sum to at most shadow_tolerance of the light's area,
  // and returns that sum (0 when none is taken out).
  double LeaveOutSmallShadows(const glm::dvec3& p, std::vector<uint32_t>* ids) const;
  // An upper bound on the area of the part of the light's plane that the
  // triangle v hides from p: the area of its central projection from p, with
  // the rounding of its computation added; +infinity where a vertex lies
  // near or behind the plane through p parallel to the light (no bounded
  // projection). h_light: p's distance to the light's plane.
  double ShadowAreaBound(const glm::dvec3& p, double h_light, const glm::dvec3 (&v)[3]) const;

  // The point where a fragment edge support meets a plane.
  const XPoint* Meet(Scratch& s, const Fragment& f, const FVert& from, const XPlane& plane) const;

  // Splits f by `plane` given the vertex signs: *pos gets the part with
  // sign >= 0 (if some vertex is > 0), *neg the part <= 0 (if some is < 0).
  // New vertices are shared by both parts.
  void Split(Scratch& s, const Fragment& f, const std::vector<int>& sg, const XPlane& plane,
             Fragment* pos, Fragment* neg) const;

  // Keeps the part of f with plane side >= 0 (side sign flipped by `flip`).
  // Returns false when nothing of positive area remains.
  bool Clip(Scratch& s, Fragment* f, const XPlane& plane, int flip) const;

  // The LineBox of a convex set's vertices as seen from P; false when the
  // box does not hold (some direction not certainly on the light's side of
  // d[light_axis] = 0: its image would wrap through infinity).
  template <typename Points>
  bool LineBoxOf(const Scratch& s, const Points& xs, LineBox* box) const {
    if (s.line_box_sign == 0) return false;
    const int k = light_axis, u = (k + 1) % 3, v = (k + 2) % 3;
    const glm::dvec3& p = s.p->input;
    box->lo[0] = box->lo[1] = std::numeric_limits<double>::infinity();
    box->hi[0] = box->hi[1] = -std::numeric_limits<double>::infinity();
    for (const XPoint* x : xs) {
      if (x->kind == XPoint::Kind::kInput) {
        if (!ExtendByInputDirection(s, x->input, box)) return false;
        continue;
      }
      // A derived point belongs to the query (Scratch), and most are
      // corners of two fragments or more: its image is made once.
      if (x->chart_state == 0) {
        // d = X / W - P; the ratios d[u] / d[k] = (X[u] - P[u] W) / (X[k] - P[k] W).
        const IV4& h = x->approx;
        const Iv den = h[k] - Iv(p[k]) * h[3];
        const int den_sign = SignOf(den);
        x->chart_state = den_sign == kUncertain || den_sign * x->w_sign != s.line_box_sign ? -1 : 1;
        if (x->chart_state > 0) {
          QuotientBounds(h[u] - Iv(p[u]) * h[3], den, &x->chart[0], &x->chart[1]);
          QuotientBounds(h[v] - Iv(p[v]) * h[3], den, &x->chart[2], &x->chart[3]);
        }
      }
      if (x->chart_state < 0) return false;
      for (int i = 0; i < 2; ++i) {
        box->lo[i] = std::min(box->lo[i], x->chart[2 * i]);
        box->hi[i] = std::max(box->hi[i], x->chart[2 * i + 1]);
      }
    }
    return true;
  }

  // A box around the LineBox of occluder `id`'s shadow, from its input
  // vertices in double precision, widened past the rounding: the cheap
  // test a query applies to each of its dozens of candidates before making
  // the exact points of any (most are apart from the few fragments a
  // penumbra has left). A near occluder's clipped polygon lies inside its
  // triangle, so its shadow inside the triangle's, whose directions from P
  // span the hull of the vertices' when all lie on the light's side of P
  // (d[light_axis] of the query's sign). False otherwise.
  bool ShadowBoxBound(const Scratch& s, uint32_t id, LineBox* box) const {
    if (s.line_box_sign == 0) return false;
    const uint32_t* t = OccluderVertices(id);
    box->lo[0] = box->lo[1] = std::numeric_limits<double>::infinity();
    box->hi[0] = box->hi[1] = -std::numeric_limits<double>::infinity();
    for (int i = 0; i < 3; ++i) {
      if (!ExtendByInputDirection(s, vertices[t[i]], box)) return false;
    }
    return true;
  }

  // Extends a LineBox by the direction from P to an input point x, in
  // double precision widened past its rounding; false when x is not
  // certainly on the light's side of P (d[light_axis] of the query's sign).
  bool ExtendByInputDirection(const Scratch& s, const glm::dvec3& x, LineBox* box) const {
    const int k = light_axis, u = (k + 1) % 3, v = (k + 2) % 3;
    const glm::dvec3& p = s.p->input;
    // A rounded difference has the sign of the exact one.
    const double den = x[k] - p[k];
    if (!(den * s.line_box_sign > 0.0)) return false;
    const double g[2] = {(x[u] - p[u]) / den, (x[v] - p[v]) / den};
    for (int j = 0; j < 2; ++j) {
      if (!std::isfinite(g[j])) return false;
      // Three roundings of at most half an ulp each, and underflow.
      const double margin = std::fabs(g[j]) * 0x1p-50 + 0x1p-1022;
      box->lo[j] = std::min(box->lo[j], g[j] - margin);
      box->hi[j] = std::max(box->hi[j], g[j] + margin);
    }
    return true;
  }

  // Whether the fragment has a line box (computed on first use).
  bool HasLineBox(const Scratch& s, Fragment& f) const;

  // Whether no line from P through the fragment meets the set in `shadow`.
  bool ApartFrom(const Scratch& s, Fragment& f, const LineBox& shadow) const;

  // Removes from `fragments` the lines from the light to P that cross the
  // convex polygon with the given edge lines (each pair a -> b). With the
  // polygon's LineBox, fragments whose boxes are apart from it are kept
  // without a predicate: a dense mesh's many small occluders each meet few
  // of the many pieces it leaves.
  //
  // The lines inside the polygon's shadow have one sign against every edge
  // line, that of the polygon's corners against the first edge line. A
  // fragment is first judged whole: if some edge has none of its vertices
  // on that sign's side, it is outside and kept as it is. Only the others
  // are cut, and only by the edge lines they straddle: the rest have the
  // fragment, and so each of its pieces, on that sign's side. Cutting a
  // fragment that lies outside anyway would leave it in pieces, and every
  // piece costs each later occluder again.
  // Returns whether it cut (or removed) any fragment.
  // With `grid` (over every fragment's box), `fragments` keeps the ones
  // the grid holds dead in place, and only those whose boxes meet `shadow`
  // are visited; the ones cut or removed die there, and their pieces are
  // appended (not yet in the grid). The live ones are then, in order, what
  // the call without a grid leaves.
  bool Subtract(Scratch& s, std::vector<Fragment>* fragments,
                const std::vector<std::pair<const XPoint*, const XPoint*>>& edges,
                const LineBox* shadow = nullptr, FragmentGrid* grid = nullptr) const;

  // How a fragment lies against a convex polygon's edge lines (Subtract).
  enum class Against { kOutside, kInside, kStraddles };
  Against FragmentAgainst(Scratch& s, Fragment& f, std::vector<EdgeLine>& lines, int inside,
                          uint32_t* straddled) const;
  // Cuts the chained fragments of s.subtract_stack along their straddled
  // lines, appending the parts outside the polygon to `out`.
  void CutChains(Scratch& s, std::vector<Fragment>* out, int inside) const;

  // Moves SubtractOccluders to a FragmentGrid over `fragments` (every one
  // with a box); false (and the grid unused) when a box is not finite.
  bool StartFragmentGrid(Scratch& s, std::vector<Fragment>& fragments, const LineBox& all) const;
  // Lists the fragments appended after the grid's last; false (the grid
  // then to be dropped) when one has no finite box.
  bool GridTakesNewFragments(const Scratch& s, std::vector<Fragment>& fragments, FragmentGrid& grid) const;
  // Drops the grid's dead fragments from `fragments`, keeping the order.
  static void DropDeadFragments(const FragmentGrid& grid, std::vector<Fragment>* fragments);

  // The box around the fragments' line boxes; false when one has none.
  bool UnionLineBox(const Scratch& s, std::vector<Fragment>& fragments, LineBox* box) const;

  // Subtracts the occluders `ids` (occluder ids, in this order) from the
  // fragments, until nothing is left or `max_subtracted` of them have been
  // subtracted. An occluder whose line box is apart from the box around all
  // the fragments is passed over without visiting them: a dense mesh's
  // leaf lists thousands of triangles, most of which miss the few pieces
  // that reach it. So is one whose triangle's box (in double, before any
  // exact point of it is made) is apart from each fragment's. Returns the
  // number subtracted.
  // With `quads`, occluders that reach the fragments are subtracted
  // with a neighbour as one quadrilateral where they can be
  // (QuadWithNeighbour). With `cutting`, the ids of the occluders that cut
  // or removed a fragment are appended to it (both of a quadrilateral).
  // With `test_untested`, occluders whose shadows miss the light
  // (ShadowMissesLight) are passed over: the caller has not tested them.
  // With at least this many fragments, and four times as many candidates
  // still to test, SubtractOccluders keeps them in a FragmentGrid: below,
  // the list was as fast (the grille, whose points keep about a hundred
  // fragments and test 172 candidates, was 9 % slower at 32 and no bound
  // on the candidates).
  static constexpr size_t kGridFragments = 64;
  size_t SubtractOccluders(Scratch& s, std::vector<Fragment>* fragments, std::span<const uint32_t> ids,
                           const XPlane** slab_top, size_t max_subtracted = SIZE_MAX, bool quads = false,
                           std::vector<uint32_t>* cutting = nullptr, bool test_untested = false) const;

  // The answer from the store, or a new one, kept while the store has room.
  StatusOr<PointVisibility> Query(const QueryPoint& q, bool want_polygons, const StopToken& stop);
  // Whether Query would answer from the store.
  bool StoresAnswer(const QueryPoint& q, bool want_polygons) const;

  // This thread's scratch, shared by every tree's queries on it.
  static Scratch& ThreadScratch();
  // The answer to one query, from scratch.
  StatusOr<PointVisibility> Compute(const QueryPoint& q, bool want_polygons, const StopToken& stop);

  // The query point in the local frame, after the checks of its position
  // and normal (INVALID_ARGUMENT) and of the receiver box (OUT_OF_RANGE).
  StatusOr<glm::dvec3> LocalPosition(const QueryPoint& q) const;

  // Classify first, with exact tests on input points only. The occluders
  // whose triangles could block a segment from P to the light are
  // gathered; most points end here, before any fragment work: when none
  // can, the light is wholly visible (above the horizon); when one alone
  // blocks every segment, it is wholly hidden (a wall or a floor above).
  // Only the others (penumbrae, or umbrae cast by several triangles
  // together) descend the tree and subtract their near occluders. The
  // answers are those the tree would give: the tree never splits what it
  // does not have to, but splitting a wholly visible light into pieces
  // whose areas are summed gives 1 - 1e-16 where this gives 1.
  //
  // Umbrae cast by a few triangles together (the two halves of a quad, a
  // mesh's neighbouring faces) are common too. When every light vertex's
  // segment is blocked by some candidate, the few candidates that block
  // the most vertices are subtracted from the light directly; if nothing
  // is left, the point is hidden, exactly. Otherwise that work is dropped
  // and the tree decides.
  //
  // A point with few candidates in all (direct_candidates) subtracts them
  // all from the light itself: the candidates are every occluder whose
  // shadow can meet the light, so what is left is the exact answer, and
  // for a handful of triangles that costs no more than the descent while
  // the tree does not grow for it.
  //
  // After a penumbra point the next one is mostly a penumbra point too, and
  // then the classification is spent for nothing: of a Sponza penumbra
  // point's 86 candidates, 18 reach the fragments that the largest leave.
  // So after one, candidates are kept on the float cull alone, and
  // SubtractOccluders gives the exact whole-light test only to those whose
  // shadow's box reaches the fragments. The answer is the same: an
  // occluder whose shadow misses the light cuts nothing.
  //
  // Neighbouring points are mostly hidden by the same wall or floor: the
  // occluder that last hid a whole light from this thread, tried first,
  // spares the gathering. The test is exact for any occluder of the tree
  // but those in P's receiver plane (excluded, as below: P may lie a
  // rounding off that plane), so a stale entry costs one test and no wrong
  // answer.
  bool HiddenByLastCover(const glm::dvec3& p_local, const Receiver& receiver) const;

  // The occluders whose shadows can meet the light from P (far ids, and
  // near ones as indices into `near`), and the route the query takes.
  struct Candidates {
    std::vector<uint32_t> near, far;
    bool any_far = false;  // the tree must be descended (unless direct)
    bool direct = false;   // few enough to subtract them all from the light
    bool untested = false;  // kept without their exact test (after a penumbra point)
  };
  // Gathers them (GatherCandidates' caller has tried HiddenByLastCover);
  // true when the point is wholly hidden, and then nothing else is filled
  // in. Wholly visible: no candidate and any_far false.
  // Occluders in the receiver's plane are left out (IsReceiver).
  bool GatherCandidates(Scratch& s, const glm::dvec3& p_local, const Receiver& receiver, const PyramidCull& cull,
                        const std::vector<Fragment>& pending, Candidates* out);

  // Pushes the light fragments down the shared tree from its root: the
  // parts that reach visible leaves go to *visible; an undefined leaf is
  // refined under the exclusive lock (*refined), or, with the tree at its
  // budget, resolved against its occluders here. CANCELLED or
  // DEADLINE_EXCEEDED when the query's stop says so.
  Status DescendTree(Scratch& s, std::vector<Fragment>& pending, const PyramidCull& cull,
                     const glm::dvec3& p_local, std::vector<Fragment>* out, bool* refined_out);

  // The visible fraction of the light's area and solid angle, and the
  // irradiance for the normal, from the visible fragments (and their
  // polygons, when asked for).
  // left_out_area: LeaveOutSmallShadows' sum, turned into the answer's
  // errors.
  PointVisibility Integrate(const std::vector<Fragment>& visible, const glm::dvec3& p_local,
                            const std::optional<glm::dvec3>& normal, bool want_polygons,
                            double left_out_area = 0.0) const;
};

}  // namespace visq::exact::detail
