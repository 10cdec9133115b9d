#include "exact/light_visibility.h"

#include "common/coordinates.h"

#include <algorithm>
#include <array>
#include <bit>
#include <atomic>
#include <cmath>
#include <cstring>
#include <deque>
#include <limits>
#include <memory>
#include <numbers>
#include <mutex>

#include <absl/container/flat_hash_map.h>
#include <absl/container/inlined_vector.h>

#include "common/check.h"
#include "common/parallel.h"
#include "exact/exact_geometry.h"

namespace visq::exact {

using detail::Iv;
using detail::IV4;
using detail::kUncertain;
using detail::SignOf;
using detail::EuclidSide;
using detail::Orient2d;
using detail::Orient3d;
using detail::Orient3dFan;
using detail::XPlane;
using detail::XPoint;

namespace {

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
  int32_t light_edge;   // >= 0: edge (light_edge, light_edge + 1) of the triangle
  const XPlane* plane;  // otherwise: the plane holding the edge to the next vertex
};

// An enclosure of the lines through the query point P that pass through a
// convex set, as a box in gnomonic coordinates: the direction d = x - P maps
// to (d[u] / d[k], d[v] / d[k]), the same point for d and -d, so every line
// through P is one point and the lines through a convex set whose directions
// all have d[k] of one strict sign are the convex hull of its vertices'
// images. Bounds are outward-rounded (interval arithmetic): two boxes that
// are apart certify that no line through P meets both sets.
struct LineBox {
  double lo[2], hi[2];
  bool Apart(const LineBox& o) const {
    return hi[0] < o.lo[0] || o.hi[0] < lo[0] || hi[1] < o.lo[1] || o.hi[1] < lo[1];
  }
};

struct Fragment {
  uint32_t triangle = 0;  // light triangle
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

AnswerKey KeyOf(const QueryPoint& q, bool want_polygons) {
  AnswerKey k{};
  const glm::dvec3 n = q.normal.value_or(glm::dvec3(0.0));
  for (int i = 0; i < 3; ++i) {
    k.position[i] = std::bit_cast<uint64_t>(q.position[i]);
    k.normal[i] = std::bit_cast<uint64_t>(n[i]);
  }
  k.receiver_triangle = q.receiver_triangle.value_or(0);
  k.has_normal = q.normal.has_value();
  k.has_triangle = q.receiver_triangle.has_value();
  k.want_polygons = want_polygons;
  return k;
}

size_t AnswerBytes(const PointVisibility& v) {
  // The entry, the map's slot overhead, and the polygons.
  size_t bytes = sizeof(AnswerKey) + sizeof(PointVisibility) + 16;
  for (const auto& polygon : v.visible_polygons) bytes += sizeof(polygon) + polygon.size() * sizeof(glm::dvec3);
  return bytes;
}

struct PairHash {
  size_t operator()(const std::pair<const void*, const void*>& p) const {
    const auto a = reinterpret_cast<uintptr_t>(p.first), b = reinterpret_cast<uintptr_t>(p.second);
    return std::hash<uintptr_t>()(a * 0x9E3779B97F4A7C15ull ^ (b + 0x632BE59BD9B4E019ull));
  }
};

// Objects at stable addresses, constructed one at a time into blocks of
// 64 that outlive Clear(): a reused arena allocates nothing.
template <typename T>
class Arena {
 public:
  Arena() = default;
  Arena(const Arena&) = delete;
  Arena& operator=(const Arena&) = delete;
  ~Arena() { Clear(); }

  const T* Add(T value) {
    const size_t block = size_ / kBlock, slot = size_ % kBlock;
    if (block == blocks_.size()) blocks_.push_back(std::make_unique<Storage[]>(kBlock));
    T* object = std::construct_at(reinterpret_cast<T*>(&blocks_[block][slot]), std::move(value));
    ++size_;
    return object;
  }
  void Clear() {
    for (size_t i = 0; i < size_; ++i) std::destroy_at(reinterpret_cast<T*>(&blocks_[i / kBlock][i % kBlock]));
    size_ = 0;
  }

 private:
  static constexpr size_t kBlock = 64;
  struct Storage {
    alignas(T) unsigned char bytes[sizeof(T)];
  };
  std::vector<std::unique_ptr<Storage[]>> blocks_;
  size_t size_ = 0;
};

double Area3(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  return 0.5 * glm::length(glm::cross(b - a, c - a));
}

// Solid angle of triangle (a, b, c) seen from the origin (Van Oosterom and
// Strackee 1983).
double SolidAngle(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c) {
  const double la = glm::length(a), lb = glm::length(b), lc = glm::length(c);
  const double num = std::fabs(glm::dot(a, glm::cross(b, c)));
  const double den = la * lb * lc + glm::dot(a, b) * lc + glm::dot(a, c) * lb + glm::dot(b, c) * la;
  return 2.0 * std::atan2(num, den);
}

}  // namespace

// A floating-point cull of the near occluders that cannot touch the pyramid
// from P to the light: before any exact predicate, an occluder whose box
// misses the pyramid's box, or that lies wholly outside one side plane of
// the pyramid over every light triangle, blocks no segment from P to the
// light. It only ever skips an occluder when the double-precision test
// clears a margin far above its rounding error, so it never changes an
// answer; anything closer is left to the exact code.
class PyramidCull {
 public:
  PyramidCull(const glm::dvec3& p, const std::vector<glm::dvec3>& light, const std::vector<LightTriangle>& triangles)
      : p_(p), lo_(p), hi_(p) {
    for (const glm::dvec3& v : light) {
      lo_ = glm::min(lo_, v);
      hi_ = glm::max(hi_, v);
    }
    for (const LightTriangle& t : triangles) {
      Sides sides;
      for (int e = 0; e < 3; ++e) {
        const glm::dvec3 a = light[t.v[e]] - p, b = light[t.v[(e + 1) % 3]] - p, c = light[t.v[(e + 2) % 3]] - p;
        glm::dvec3 normal = glm::cross(a, b);
        const double scale = glm::length(a) * glm::length(b);
        // Orient inwards by the opposite vertex; too close to call: no cull.
        const double inside = glm::dot(normal, c);
        if (!(std::fabs(inside) > kRelativeMargin * scale * glm::length(c))) {
          sides.usable = false;
          break;
        }
        if (inside < 0) normal = -normal;
        sides.normal[e] = normal;
        sides.scale[e] = scale;
      }
      triangle_sides_.push_back(sides);
    }
  }

  // Whether every point of the box [lo, hi] passes the test Misses applies to
  // vertices (so no triangle inside the box can touch the pyramid). Per
  // plane, the corner furthest inside decides; the margin is taken at the
  // box's farthest corner from P, which is at least each point's own.
  bool MissesBox(const glm::dvec3& lo, const glm::dvec3& hi) const {
    for (int axis = 0; axis < 3; ++axis)
      if (hi[axis] < lo_[axis] || lo[axis] > hi_[axis]) return true;
    // The farthest corner from P takes, per axis, the farther face.
    const glm::dvec3 far_offset = glm::max(glm::abs(lo - p_), glm::abs(hi - p_));
    const double reach = glm::length(far_offset);
    for (const Sides& sides : triangle_sides_) {
      if (!sides.usable) return false;
      bool outside = false;
      for (int e = 0; e < 3 && !outside; ++e) {
        const glm::dvec3& n = sides.normal[e];
        const glm::dvec3 furthest_inside(n.x > 0 ? hi.x : lo.x, n.y > 0 ? hi.y : lo.y, n.z > 0 ? hi.z : lo.z);
        outside = glm::dot(n, furthest_inside - p_) < -kRelativeMargin * sides.scale[e] * reach;
      }
      if (!outside) return false;
    }
    return !triangle_sides_.empty();
  }

  bool Misses(const glm::dvec3 (&v)[3]) const {
    for (int axis = 0; axis < 3; ++axis) {
      if (v[0][axis] < lo_[axis] && v[1][axis] < lo_[axis] && v[2][axis] < lo_[axis]) return true;
      if (v[0][axis] > hi_[axis] && v[1][axis] > hi_[axis] && v[2][axis] > hi_[axis]) return true;
    }
    const glm::dvec3 x[3] = {v[0] - p_, v[1] - p_, v[2] - p_};
    const double length[3] = {glm::length(x[0]), glm::length(x[1]), glm::length(x[2])};
    for (const Sides& sides : triangle_sides_) {
      if (!sides.usable) return false;
      bool outside = false;
      for (int e = 0; e < 3 && !outside; ++e) {
        outside = true;
        for (int i = 0; i < 3 && outside; ++i) {
          outside = glm::dot(sides.normal[e], x[i]) < -kRelativeMargin * sides.scale[e] * length[i];
        }
      }
      if (!outside) return false;
    }
    return !triangle_sides_.empty();
  }

 private:
  // The side value is a 3x3 determinant of differences of doubles; its
  // rounding error is a few ulps of the product of the vectors' lengths.
  // This margin is about 450 ulps of that product.
  static constexpr double kRelativeMargin = 1e-13;
  struct Sides {
    bool usable = true;
    glm::dvec3 normal[3];
    double scale[3] = {};
  };
  glm::dvec3 p_, lo_, hi_;
  std::vector<Sides> triangle_sides_;
};

// A bounding-volume hierarchy over the occluders' boxes (far and near), so
// that a query visits the occluders near its pyramid instead of all of them
// (a receiver tile's tree holds hundreds, a point's pyramid meets a few
// dozen; docs/exact-method-notes.md). Built once per tree; read-only afterwards.
class OccluderIndex {
 public:
  void Build(std::vector<std::pair<glm::dvec3, glm::dvec3>> boxes) {
    boxes_ = std::move(boxes);
    order_.resize(boxes_.size());
    for (uint32_t i = 0; i < order_.size(); ++i) order_[i] = i;
    nodes_.clear();
    if (boxes_.empty()) return;
    nodes_.emplace_back();
    BuildNode(0, 0, static_cast<uint32_t>(order_.size()));
  }

  // Appends the occluders whose boxes `box_misses` does not rule out.
  template <typename BoxMisses>
  void Collect(const BoxMisses& box_misses, std::vector<uint32_t>* out) const {
    if (nodes_.empty()) return;
    uint32_t stack[64];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
      const Node& node = nodes_[stack[--top]];
      if (box_misses(node.lo, node.hi)) continue;
      if (node.left == kLeaf) {
        for (uint32_t i = node.begin; i < node.end; ++i) out->push_back(order_[i]);
      } else {
        stack[top++] = node.left;
        stack[top++] = node.left + 1;
      }
    }
  }

  // How many occluders' boxes `box_misses` does not rule out, counting no
  // further than `limit`.
  template <typename BoxMisses>
  size_t CountUpTo(const BoxMisses& box_misses, size_t limit) const {
    if (nodes_.empty()) return 0;
    uint32_t stack[64];
    int top = 0;
    stack[top++] = 0;
    size_t count = 0;
    while (top > 0 && count < limit) {
      const Node& node = nodes_[stack[--top]];
      if (box_misses(node.lo, node.hi)) continue;
      if (node.left == kLeaf) {
        for (uint32_t i = node.begin; i < node.end; ++i) {
          const auto& [lo, hi] = boxes_[order_[i]];
          count += box_misses(lo, hi) ? 0 : 1;
        }
      } else {
        stack[top++] = node.left;
        stack[top++] = node.left + 1;
      }
    }
    return std::min(count, limit);
  }

  size_t MemoryBytes() const {
    return boxes_.capacity() * sizeof(boxes_[0]) + order_.capacity() * 4 + nodes_.capacity() * sizeof(Node);
  }

 private:
  static constexpr uint32_t kLeaf = UINT32_MAX;
  static constexpr uint32_t kLeafSize = 8;
  struct Node {
    glm::dvec3 lo, hi;
    uint32_t begin, end;
    uint32_t left;  // children at left and left + 1, or kLeaf
  };

  // Fills node `id` with the occluders order_[begin, end); its children go
  // to two new consecutive slots. Depth stays under 64: each split halves.
  void BuildNode(uint32_t id, uint32_t begin, uint32_t end) {
    glm::dvec3 lo(std::numeric_limits<double>::infinity()), hi(-std::numeric_limits<double>::infinity());
    glm::dvec3 centre_lo = lo, centre_hi = hi;
    for (uint32_t i = begin; i < end; ++i) {
      const auto& [box_lo, box_hi] = boxes_[order_[i]];
      lo = glm::min(lo, box_lo);
      hi = glm::max(hi, box_hi);
      centre_lo = glm::min(centre_lo, box_lo + box_hi);
      centre_hi = glm::max(centre_hi, box_lo + box_hi);
    }
    nodes_[id] = Node{lo, hi, begin, end, kLeaf};
    if (end - begin <= kLeafSize) return;
    const glm::dvec3 spread = centre_hi - centre_lo;
    const int axis = spread.x >= spread.y && spread.x >= spread.z ? 0 : spread.y >= spread.z ? 1 : 2;
    const uint32_t middle = begin + (end - begin) / 2;
    std::nth_element(order_.begin() + begin, order_.begin() + middle, order_.begin() + end, [&](uint32_t x, uint32_t y) {
      return boxes_[x].first[axis] + boxes_[x].second[axis] < boxes_[y].first[axis] + boxes_[y].second[axis];
    });
    const uint32_t left = static_cast<uint32_t>(nodes_.size());
    nodes_.emplace_back();
    nodes_.emplace_back();
    nodes_[id].left = left;
    BuildNode(left, begin, middle);
    BuildNode(left + 1, middle, end);
  }

  std::vector<std::pair<glm::dvec3, glm::dvec3>> boxes_;
  std::vector<uint32_t> order_;
  std::vector<Node> nodes_;
};

// ---------------------------------------------------------------------------
struct LightVisibilityTree::Impl {
  // The frame: everything is stored relative to the light centroid, rounded
  // once; all exact predicates are exact for these local coordinates.
  glm::dvec3 origin{0.0};
  double radiance = 1.0;
  double light_area = 0.0;

  std::deque<XPoint> light_points;      // light vertices (local)
  std::vector<glm::dvec3> light_local;  // same, as doubles
  std::deque<XPlane> light_planes;      // one per light triangle
  std::vector<LightTriangle> light_triangles;
  const XPlane* light_plane = nullptr;  // the largest triangle's: front side positive
  int light_axis = 2;  // the axis nearest the light's normal: k of the LineBoxes

  std::vector<XPoint> points;  // occluder vertices (local, inputs); never grows after Create
  std::vector<FarOccluder> far;
  std::vector<NearOccluder> near;
  OccluderIndex index;  // ids: far occluders first, then near ones
  std::unordered_map<uint32_t, uint32_t> near_by_triangle;  // scene triangle -> index in near
  std::optional<std::pair<glm::dvec3, glm::dvec3>> receiver_box;  // local frame

  mutable std::shared_mutex mutex;
  std::vector<Node> nodes;
  std::vector<std::vector<uint32_t>> lists;  // occluder lists of undefined leaves
  std::vector<uint32_t> free_lists;
  size_t list_bytes = 0;

  std::atomic<uint64_t> queries{0}, hits{0}, refinements{0}, unrefined_leaf_visits{0}, wholly_visible{0}, wholly_hidden{0},
      subtracted_directly{0}, answers_reused{0};

  // The store of answers (Query), under a lock of its own: a lookup must
  // not wait for a refinement.
  mutable std::shared_mutex answers_mutex;
  absl::flat_hash_map<AnswerKey, PointVisibility> answers;
  size_t answer_bytes = 0;  // under answers_mutex
  std::atomic<size_t> answer_bytes_now{0};  // the same, for the tree's budget, which counts the store too
  size_t max_answer_bytes = 0;
  size_t max_bytes = 0;
  bool classify_points = true;
  size_t direct_candidates = 0;

  size_t MemoryBytesLocked() const {
    return sizeof(Impl) + nodes.capacity() * sizeof(Node) + list_bytes +
           lists.capacity() * sizeof(std::vector<uint32_t>) + free_lists.capacity() * 4 +
           points.size() * sizeof(XPoint) + far.capacity() * sizeof(FarOccluder) +
           near.capacity() * sizeof(NearOccluder) + index.MemoryBytes() + near_by_triangle.size() * 24 +
           light_points.size() * sizeof(XPoint) +
           light_planes.size() * sizeof(XPlane);
  }

  // --- The end of Create, once the occluders are selected. ----------------
  // The occluders' boxes in their hierarchy (far ones first), then the tree
  // as one undefined leaf holding every far occluder. Node 0 is the root; 1
  // and 2 are the shared visible / invisible leaves.
  void IndexOccludersAndPlantTheTree() {
    far.shrink_to_fit();
    near.shrink_to_fit();
    std::vector<std::pair<glm::dvec3, glm::dvec3>> boxes;
    boxes.reserve(far.size() + near.size());
    auto add_box = [&](const uint32_t (&v)[3]) {
      const glm::dvec3 a = points[v[0]].input, b = points[v[1]].input, c = points[v[2]].input;
      boxes.emplace_back(glm::min(a, glm::min(b, c)), glm::max(a, glm::max(b, c)));
    };
    for (const FarOccluder& o : far) add_box(o.v);
    for (const NearOccluder& n : near) add_box(n.v);
    index.Build(std::move(boxes));

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
  }

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
  EdgeFans MakeEdgeFans(uint32_t a, uint32_t b) const {
    EdgeFans e{a, b, {}};
    e.fans.reserve(light_local.size());
    for (const glm::dvec3& y : light_local) e.fans.emplace_back(y, points[a].input, points[b].input);
    return e;
  }
  void OccluderSides(const uint32_t v[3], const EdgeFans& edge, bool* pos, bool* nonpos) const {
    *pos = *nonpos = false;
    for (int i = 0; i < 3 && !(*pos && *nonpos); ++i) {
      const glm::dvec3& x = points[v[i]].input;
      for (const Orient3dFan& fan : edge.fans) {
        if (fan.Side(x) > 0) *pos = true; else *nonpos = true;
        if (*pos && *nonpos) break;
      }
    }
  }

  int32_t NewNode(uint8_t kind, uint32_t a = 0, uint32_t b = 0) {
    Node n;
    n.kind = kind;
    n.a = a;
    n.b = b;
    nodes.push_back(n);
    return static_cast<int32_t>(nodes.size() - 1);
  }

  uint32_t NewList() {
    if (!free_lists.empty()) {
      const uint32_t i = free_lists.back();
      free_lists.pop_back();
      return i;
    }
    lists.emplace_back();
    return static_cast<uint32_t>(lists.size() - 1);
  }

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
                        const glm::dvec3& y) const {
    const glm::dvec3 d = p - y;
    size_t best = 0;
    double best_t = 0.0;  // crossings strictly between the light (t = 0) and P
    for (size_t k = 0; k < list.size(); ++k) {
      const FarOccluder& o = far[list[k]];
      const glm::dvec3 a = points[o.v[0]].input, b = points[o.v[1]].input, c = points[o.v[2]].input;
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

  void Refine(int32_t id, const glm::dvec3& p, const glm::dvec3& y) {
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

  // --- Queries. --------------------------------------------------------------
  // A query's own geometry: the points and planes it constructs, and the
  // edge planes by edge. One per thread, reused from query to query: a
  // query makes hundreds of objects, and allocating them one by one (a
  // std::deque of these 200-byte objects allocates every second one) cost
  // more than the warm queries' arithmetic.
  struct Scratch {
    Arena<XPoint> points;
    Arena<XPlane> planes;
    absl::flat_hash_map<std::pair<const void*, const void*>, const XPlane*, PairHash> edge_planes;
    std::vector<int> signs;
    const XPoint* p = nullptr;
    // The query's stop: looked at every kStopStride calls of StopNow.
    const StopToken* stop = nullptr;
    uint32_t stop_countdown = 0;
    Status stopped;
    // The sign of d[light_axis] for every direction from P to the light;
    // 0 when it is not one strict sign (then no LineBoxes this query).
    int line_box_sign = 0;

    const XPoint* Add(XPoint x) { return points.Add(std::move(x)); }
    const XPlane* Add(XPlane x) { return planes.Add(std::move(x)); }
    void Reset() {
      points.Clear();
      planes.Clear();
      edge_planes.clear();
      p = nullptr;
      line_box_sign = 0;
      stop = nullptr;
      stop_countdown = 0;
      stopped = absl::OkStatus();
    }
  };

  // Whether the query must stop (its status then in s.stopped). The clock
  // is read every few calls: a call is one occluder subtracted or one step
  // of the descent, a few microseconds at most.
  static constexpr uint32_t kStopStride = 8;
  static bool StopNow(Scratch& s) {
    if (!s.stopped.ok()) return true;
    if (s.stop == nullptr || s.stop_countdown-- > 0) return false;
    s.stop_countdown = kStopStride;
    s.stopped = s.stop->Check();
    return !s.stopped.ok();
  }

  // The plane through P and edge line (a, b), shared by both orientations
  // of the line (so that a vertex created on it is recognised as lying on it
  // later); `sign` orients it as the edge a -> b. Null when P is on the line.
  struct EdgePlaneRef {
    const XPlane* plane;
    int sign;
  };
  EdgePlaneRef EdgePlane(Scratch& s, const XPoint& a, const XPoint& b) const {
    const XPoint* lo = std::less<const XPoint*>()(&a, &b) ? &a : &b;
    const XPoint* hi = lo == &a ? &b : &a;
    auto [it, inserted] = s.edge_planes.try_emplace({lo, hi}, nullptr);
    if (inserted) {
      const XPlane* plane = s.Add(XPlane::ThroughPoints(*s.p, *lo, *hi));
      it->second = plane->Degenerate() ? nullptr : plane;
    }
    return {it->second, lo == &a ? 1 : -1};
  }

  // Whether x is on the plane by construction (then its sign is 0 without
  // any arithmetic; this is also what keeps repeated planes off the exact
  // fallback). Besides "x was made on this plane", one case matters a lot:
  // the shadow of an occluder vertex v is Π_t ∩ plane(P, v, a) ∩ plane(P, v, b),
  // a point of line(P, v), and so lies on every edge plane through P and v.
  static bool OnPlaneByDefinition(const XPoint& x, const XPlane* plane) {
    if (x.kind == XPoint::Kind::kLinePlane) return x.planes[0] == plane;
    if (x.kind != XPoint::Kind::kThreePlanes) return false;
    if (x.planes[0] == plane || x.planes[1] == plane || x.planes[2] == plane) return true;
    const XPlane* p1 = x.planes[1];
    const XPlane* p2 = x.planes[2];
    using K = XPlane::Kind;
    if (plane->kind != K::kThroughPoints || p1->kind != K::kThroughPoints ||
        p2->kind != K::kThroughPoints || p1->points[0] != plane->points[0] ||
        p2->points[0] != plane->points[0]) {
      return false;
    }
    for (int i = 1; i < 3; ++i) {
      const XPoint* v = p1->points[i];
      if ((v == p2->points[1] || v == p2->points[2]) &&
          (v == plane->points[1] || v == plane->points[2])) {
        return true;
      }
    }
    return false;
  }

  // An edge line (a, b) as one query sees it. The plane through P and the
  // line is made only when it is needed: to split, or to side a vertex that
  // is not an input point. An input vertex takes the orientation test on its
  // doubles (a static filter, about 20 flops), which is most of them: the
  // light's own vertices, on every fragment that nothing has split yet. Both
  // routes are exact, so they agree on every sign.
  struct EdgeLine {
    const XPoint* a;
    const XPoint* b;
    bool has_plane = false;
    EdgePlaneRef plane{nullptr, 0};
    std::optional<Orient3dFan> fan;  // orient3d(P, a, b, .), for input vertices
  };
  EdgePlaneRef PlaneOf(Scratch& s, EdgeLine& e) const {
    if (!e.has_plane) {
      e.plane = EdgePlane(s, *e.a, *e.b);
      e.has_plane = true;
    }
    return e.plane;
  }

  // Side of x against the edge line, as the side of the line x -> P:
  // orient3d(x, P, a, b) = -orient3d(P, a, b, x). Zero when P is on the line.
  int LineSide(Scratch& s, EdgeLine& e, const XPoint& x) const {
    using K = XPoint::Kind;
    if (x.kind == K::kInput && e.a->kind == K::kInput && e.b->kind == K::kInput) {
      if (!e.fan) e.fan.emplace(s.p->input, e.a->input, e.b->input);
      return -e.fan->Side(x.input);
    }
    const EdgePlaneRef ref = PlaneOf(s, e);
    if (ref.plane == nullptr || OnPlaneByDefinition(x, ref.plane)) return 0;
    return -ref.sign * EuclidSide(x, *ref.plane);
  }

  // The sides of every fragment vertex. Returns false when every sign is zero
  // (P on the edge line, or a zero-area fragment).
  bool EdgeSides(Scratch& s, const Fragment& f, EdgeLine& e, std::vector<int>* signs) const {
    signs->assign(f.v.size(), 0);
    bool any = false;
    for (size_t i = 0; i < f.v.size(); ++i) {
      (*signs)[i] = LineSide(s, e, *f.v[i].point);
      any |= (*signs)[i] != 0;
    }
    return any;
  }

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
  bool ShadowMissesLight(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const {
    const Orient3dFan fans[3] = {{p, v[0], v[1]}, {p, v[1], v[2]}, {p, v[2], v[0]}};
    // orient3d(y, p, a, b) = -orient3d(p, a, b, y)
    return ShadowMissesLightBySides(3, [&](size_t e, size_t i) { return -fans[e].Side(light_local[i]); });
  }

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
  Cover CoveredLightVertices(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const {
    Cover cover;
    const Orient3dFan plane(v[0], v[1], v[2]);
    const int p_side = plane.Side(p);
    if (p_side == 0) return cover;
    // A segment crosses the interior when its line has one strict side
    // against the three edge lines.
    const Orient3dFan edges[3] = {{p, v[0], v[1]}, {p, v[1], v[2]}, {p, v[2], v[0]}};
    cover.all = true;
    for (size_t i = 0; i < light_local.size(); ++i) {
      const glm::dvec3& y = light_local[i];
      bool crosses = plane.Side(y) == -p_side;
      if (crosses) {
        const int s0 = edges[0].Side(y);
        crosses = s0 != 0 && edges[1].Side(y) == s0 && edges[2].Side(y) == s0;
      }
      cover.all &= crosses;
      if (crosses && i < 64) cover.mask |= uint64_t{1} << i;
      if (!cover.all && i >= 64) break;
    }
    return cover;
  }

  // The vertices of an occluder: far ones first, then near ones.
  const uint32_t* OccluderVertices(uint32_t id) const {
    const uint32_t far_count = static_cast<uint32_t>(far.size());
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
  OccluderTest TestOccluder(const glm::dvec3& p, const glm::dvec3 (&v)[3]) const {
    OccluderTest test;
    const size_t n = light_local.size();
    if (n > kSharedSidesVertices) {
      test.misses = ShadowMissesLight(p, v);
      if (!test.misses) test.cover = CoveredLightVertices(p, v);
      return test;
    }
    const Orient3dFan edges[3] = {{p, v[0], v[1]}, {p, v[1], v[2]}, {p, v[2], v[0]}};
    int8_t side[3][kSharedSidesVertices];  // orient3d(p, v_e, v_e+1, y_i)
    for (int e = 0; e < 3; ++e) {
      for (size_t i = 0; i < n; ++i) side[e][i] = static_cast<int8_t>(edges[e].Side(light_local[i]));
    }
    test.misses = ShadowMissesLightBySides(3, [&](size_t e, size_t i) { return -side[e][i]; });
    if (test.misses) return test;
    const Orient3dFan plane(v[0], v[1], v[2]);
    const int p_side = plane.Side(p);
    if (p_side == 0) return test;
    test.cover.all = true;
    for (size_t i = 0; i < n; ++i) {
      const bool crosses = side[0][i] != 0 && side[1][i] == side[0][i] && side[2][i] == side[0][i] &&
                           plane.Side(light_local[i]) == -p_side;
      test.cover.all &= crosses;
      if (crosses) test.cover.mask |= uint64_t{1} << i;
    }
    return test;
  }

  // The edges of a near occluder clipped to the slab between the light
  // plane and the plane through P parallel to it (`slab_top`): the part of
  // it that lies between. False when no part of it can block (nothing
  // strictly between, or its clipped shadow misses the light).
  // `corners` gets the clipped polygon's vertices (for its LineBox).
  using Edges = std::vector<std::pair<const XPoint*, const XPoint*>>;
  using Corners = absl::InlinedVector<const XPoint*, 6>;
  bool NearOccluderEdges(Scratch& s, const NearOccluder& n, const XPlane& slab_top, Edges* edges,
                         Corners* corners) const {
    const XPoint* v[3] = {&points[n.v[0]], &points[n.v[1]], &points[n.v[2]]};
    bool any_below_top = false;
    for (int i = 0; i < 3; ++i) any_below_top |= EuclidSide(*v[i], slab_top) < 0;
    if (!any_below_top) return false;  // nothing strictly between
    struct CV { const XPoint* point; int orig_edge; };  // orig_edge -1: on a cut
    absl::InlinedVector<CV, 6> poly = {{v[0], 0}, {v[1], 1}, {v[2], 2}}, clipped;
    absl::InlinedVector<int, 6> sides;
    bool cut = false;
    // Clip to the light's front (keep >= 0), then below P (keep >= 0).
    for (int pass = 0; pass < 2 && !poly.empty(); ++pass) {
      const XPlane& plane = pass == 0 ? *light_plane : slab_top;
      sides.resize(poly.size());
      bool any_neg = false, any_pos = false;
      for (size_t i = 0; i < poly.size(); ++i) {
        if (pass == 0) {
          sides[i] = n.light_side[poly[i].orig_edge];  // poly is still the triangle
        } else {
          sides[i] = -EuclidSide(*poly[i].point, plane);
        }
        any_neg |= sides[i] < 0;
        any_pos |= sides[i] > 0;
      }
      if (!any_pos) return false;
      if (!any_neg) continue;
      cut = true;
      clipped.clear();
      for (size_t i = 0; i < poly.size(); ++i) {
        const size_t j = (i + 1) % poly.size();
        const int sc = sides[i], sn = sides[j];
        if (sc > 0) clipped.push_back(poly[i]);
        if (sc == 0) clipped.push_back({poly[i].point, sn < 0 ? -1 : poly[i].orig_edge});
        if ((sc > 0 && sn < 0) || (sc < 0 && sn > 0)) {
          // Crossing edges of the second pass are parts of triangle
          // edges too: the first cut lies in the light plane, strictly
          // on the kept side of the second.
          const int e = poly[i].orig_edge;
          VISQ_CHECK(e >= 0);
          const XPoint* x = s.Add(XPoint::LinePlane(*v[e], *v[(e + 1) % 3], plane));
          clipped.push_back({x, sc > 0 ? -1 : e});
        }
      }
      poly.swap(clipped);
    }
    if (poly.size() < 3) return false;
    edges->clear();
    corners->clear();
    for (size_t i = 0; i < poly.size(); ++i) {
      corners->push_back(poly[i].point);
      const int e = poly[i].orig_edge;
      if (e >= 0) {
        edges->emplace_back(v[e], v[(e + 1) % 3]);
      } else {
        edges->emplace_back(poly[i].point, poly[(i + 1) % poly.size()].point);
      }
    }
    if (!cut) return true;  // the whole triangle: ShadowMissesLight has passed it
    // Skip clipped occluders whose shadow misses the whole light: some edge
    // has every light vertex on its <= 0 side (no all-positive line) and
    // some edge has every light vertex > 0 (no all-non-positive line). Sides
    // are linear over each light triangle, so vertices decide.
    std::vector<EdgeLine> lines;
    lines.reserve(edges->size());
    for (const auto& [a, b] : *edges) lines.push_back({a, b});
    return !ShadowMissesLightBySides(lines.size(),
                                     [&](size_t e, size_t i) { return LineSide(s, lines[e], light_points[i]); });
  }

  // An occluder's edges and corners as a query subtracts it: a far one
  // whole, a near one clipped to the slab under P (made on first use in
  // `*slab_top`). False when no part of it can block.
  bool OccluderEdges(Scratch& s, uint32_t id, const XPlane** slab_top, Edges* edges, Corners* corners) const {
    const uint32_t far_count = static_cast<uint32_t>(far.size());
    if (id < far_count) {
      const uint32_t* t = far[id].v;
      *corners = {&points[t[0]], &points[t[1]], &points[t[2]]};
      *edges = {{(*corners)[0], (*corners)[1]}, {(*corners)[1], (*corners)[2]}, {(*corners)[2], (*corners)[0]}};
      return true;
    }
    if (*slab_top == nullptr) *slab_top = s.Add(XPlane::ParallelThrough(*light_plane, *s.p));
    return NearOccluderEdges(s, near[id - far_count], **slab_top, edges, corners);
  }

  // Whether subtracting the blockers that block the most light vertices (at
  // most kFewBlockers of them; near ones clipped to the slab) leaves nothing
  // of the light.
  static constexpr size_t kFewBlockers = 16;
  struct Blocker {
    uint32_t id;   // occluder id: far ones first, then near ones
    int vertices;  // light vertices whose segments it blocks
  };
  bool HiddenByFewBlockers(Scratch& s, const std::vector<Fragment>& light, std::vector<Blocker>* blockers) const {
    std::stable_sort(blockers->begin(), blockers->end(),
                     [](const Blocker& x, const Blocker& y) { return x.vertices > y.vertices; });
    const XPlane* slab_top = nullptr;
    std::vector<Fragment> left = light;
    std::vector<uint32_t> ids;
    for (const Blocker& blocker : *blockers) ids.push_back(blocker.id);
    SubtractOccluders(s, &left, ids, &slab_top, kFewBlockers);
    return left.empty() && s.stopped.ok();
  }

  // A triangle's size as seen from p: its area over its squared distance,
  // a proxy of its solid angle (it orders subtractions; any order gives the
  // same answer).
  static double ApparentSize(const glm::dvec3& p, const glm::dvec3 (&v)[3]) {
    const glm::dvec3 offset = (v[0] + v[1] + v[2]) / 3.0 - p;
    const double area = glm::length(glm::cross(v[1] - v[0], v[2] - v[0]));
    return area / std::max(glm::dot(offset, offset), 1e-300);
  }

  // Orders occluder ids largest as seen from p first (they leave the fewest
  // fragments for the others to cut), ties by id, so the order (and the
  // float sums over the fragments) do not depend on the traversal.
  void SortLargestFirst(const glm::dvec3& p, std::vector<uint32_t>* ids) const {
    std::vector<std::pair<double, uint32_t>> by_size;
    by_size.reserve(ids->size());
    for (const uint32_t id : *ids) {
      const uint32_t* t = OccluderVertices(id);
      const glm::dvec3 v[3] = {points[t[0]].input, points[t[1]].input, points[t[2]].input};
      by_size.emplace_back(-ApparentSize(p, v), id);
    }
    std::sort(by_size.begin(), by_size.end());
    for (size_t i = 0; i < by_size.size(); ++i) (*ids)[i] = by_size[i].second;
  }

  // The point where a fragment edge support meets a plane.
  const XPoint* Meet(Scratch& s, const Fragment& f, const FVert& from, const XPlane& plane) const {
    const LightTriangle& t = light_triangles[f.triangle];
    if (from.light_edge >= 0) {
      return s.Add(XPoint::LinePlane(light_points[t.v[from.light_edge]],
                                     light_points[t.v[(from.light_edge + 1) % 3]], plane));
    }
    return s.Add(XPoint::ThreePlanes(*t.plane, *from.plane, plane));
  }

  // Splits f by `plane` given the vertex signs: *pos gets the part with
  // sign >= 0 (if some vertex is > 0), *neg the part <= 0 (if some is < 0).
  // New vertices are shared by both parts.
  void Split(Scratch& s, const Fragment& f, const std::vector<int>& sg, const XPlane& plane,
             Fragment* pos, Fragment* neg) const {
    pos->v.clear();
    neg->v.clear();
    pos->box_state = neg->box_state = 0;
    pos->triangle = neg->triangle = f.triangle;
    const size_t n = f.v.size();
    const bool has_pos = std::any_of(sg.begin(), sg.end(), [](int x) { return x > 0; });
    const bool has_neg = std::any_of(sg.begin(), sg.end(), [](int x) { return x < 0; });
    for (size_t i = 0; i < n; ++i) {
      const FVert& cur = f.v[i];
      const int sc = sg[i], sn = sg[(i + 1) % n];
      const FVert on_plane{cur.point, -1, &plane};
      if (sc > 0) pos->v.push_back(cur);
      if (sc < 0) neg->v.push_back(cur);
      if (sc == 0) {
        pos->v.push_back(sn < 0 ? on_plane : cur);
        neg->v.push_back(sn > 0 ? on_plane : cur);
      }
      if ((sc > 0 && sn < 0) || (sc < 0 && sn > 0)) {
        const XPoint* x = Meet(s, f, cur, plane);
        const FVert along{x, cur.light_edge, cur.plane};
        const FVert across{x, -1, &plane};
        if (sc > 0) {
          pos->v.push_back(across);
          neg->v.push_back(along);
        } else {
          neg->v.push_back(across);
          pos->v.push_back(along);
        }
      }
    }
    if (!has_pos) pos->v.clear();
    if (!has_neg) neg->v.clear();
  }

  // Keeps the part of f with plane side >= 0 (side sign flipped by `flip`).
  // Returns false when nothing of positive area remains.
  bool Clip(Scratch& s, Fragment* f, const XPlane& plane, int flip) const {
    s.signs.resize(f->v.size());
    bool any_neg = false, any_pos = false;
    for (size_t i = 0; i < f->v.size(); ++i) {
      s.signs[i] = OnPlaneByDefinition(*f->v[i].point, &plane)
                       ? 0
                       : flip * EuclidSide(*f->v[i].point, plane);
      any_neg |= s.signs[i] < 0;
      any_pos |= s.signs[i] > 0;
    }
    if (!any_pos) return false;
    if (!any_neg) return true;
    Fragment pos, neg;
    Split(s, *f, s.signs, plane, &pos, &neg);
    *f = std::move(pos);
    return true;
  }

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
      // d = X / W - P; the ratios d[u] / d[k] = (X[u] - P[u] W) / (X[k] - P[k] W).
      const IV4& h = x->approx;
      const Iv den = h[k] - Iv(p[k]) * h[3];
      const int den_sign = SignOf(den);
      if (den_sign == kUncertain || den_sign * x->w_sign != s.line_box_sign) return false;
      const Iv g[2] = {(h[u] - Iv(p[u]) * h[3]) / den, (h[v] - Iv(p[v]) * h[3]) / den};
      for (int i = 0; i < 2; ++i) {
        box->lo[i] = std::min(box->lo[i], g[i].lo);
        box->hi[i] = std::max(box->hi[i], g[i].hi);
      }
    }
    return true;
  }

  // Whether the fragment has a line box (computed on first use).
  bool HasLineBox(const Scratch& s, Fragment& f) const {
    if (f.box_state == 0) {
      absl::InlinedVector<const XPoint*, 8> xs;
      for (const FVert& fv : f.v) xs.push_back(fv.point);
      f.box_state = LineBoxOf(s, xs, &f.box) ? 1 : -1;
    }
    return f.box_state == 1;
  }

  // Whether no line from P through the fragment meets the set in `shadow`.
  bool ApartFrom(const Scratch& s, Fragment& f, const LineBox& shadow) const {
    return HasLineBox(s, f) && f.box.Apart(shadow);
  }

  // Removes from `fragments` the lines from the light to P that cross the
  // convex polygon with the given edge lines (each pair a -> b). With the
  // polygon's LineBox, fragments whose boxes are apart from it are kept
  // without a predicate: a dense mesh's many small occluders each meet few
  // of the many pieces it leaves.
  //
  // The lines inside the polygon's shadow have one sign against every edge
  // line. A fragment is first judged whole: if for each sign some edge has
  // none of its vertices on that sign's side, it is outside and kept as it
  // is. Only the others are cut, edge by edge, following the one sign that
  // can still hold. Cutting a fragment that lies outside anyway would leave
  // it in pieces, and every piece costs each later occluder again.
  // Returns whether it cut (or removed) any fragment.
  bool Subtract(Scratch& s, std::vector<Fragment>* fragments,
                const std::vector<std::pair<const XPoint*, const XPoint*>>& edges,
                const LineBox* shadow = nullptr) const {
    std::vector<EdgeLine> lines;
    lines.reserve(edges.size());
    for (const auto& [a, b] : edges) lines.push_back({a, b});
    // Fragments that stay whole stay in place (a fragment is a few hundred
    // bytes, and a dense mesh's penumbra has hundreds for every occluder);
    // the pieces of the cut ones are appended.
    std::vector<Fragment>& out = *fragments;
    size_t kept = 0;
    struct Item { Fragment f; size_t k; int chain; };
    std::vector<Item> stack;
    std::vector<int> sg;
    const auto keep = [&](size_t i) {
      if (kept != i) out[kept] = std::move(out[i]);
      ++kept;
    };
    for (size_t i = 0; i < out.size(); ++i) {
      Fragment& f = out[i];
      if (shadow != nullptr && ApartFrom(s, f, *shadow)) {
        keep(i);
        continue;
      }
      bool outside_positive = false, outside_negative = false, touches_only = false;
      for (EdgeLine& line : lines) {
        if (!EdgeSides(s, f, line, &sg)) {  // touches the edge line only: not inside
          touches_only = true;
          break;
        }
        outside_positive |= std::none_of(sg.begin(), sg.end(), [](int x) { return x > 0; });
        outside_negative |= std::none_of(sg.begin(), sg.end(), [](int x) { return x < 0; });
      }
      if (touches_only || (outside_positive && outside_negative)) {
        keep(i);
        continue;
      }
      stack.push_back({std::move(f), 0, outside_positive ? -1 : outside_negative ? 1 : 0});
    }
    const bool cut = kept < out.size();
    out.resize(kept);
    while (!stack.empty()) {
      Item item = std::move(stack.back());
      stack.pop_back();
      EdgeLine& line = lines[item.k];
      if (!EdgeSides(s, item.f, line, &sg)) {  // touches the edge line only: not inside
        out.push_back(std::move(item.f));
        continue;
      }
      Fragment pos, neg;
      Split(s, item.f, sg, *PlaneOf(s, line).plane, &pos, &neg);
      const bool last = item.k + 1 == edges.size();
      // Continue the chain with the part that keeps the chain's sign; the
      // rest is outside the occluder's shadow.
      Fragment* keep[2] = {&pos, &neg};
      for (int side = 0; side < 2; ++side) {
        Fragment& part = *keep[side];
        if (part.v.empty()) continue;
        const int sign = side == 0 ? 1 : -1;
        if (item.chain != 0 && sign != item.chain) {
          out.push_back(std::move(part));
        } else if (!last) {
          stack.push_back({std::move(part), item.k + 1, sign});
        }
        // else: inside all edges, shadowed.
      }
    }
    return cut;
  }

  // The box around the fragments' line boxes; false when one has none.
  bool UnionLineBox(const Scratch& s, std::vector<Fragment>& fragments, LineBox* box) const {
    box->lo[0] = box->lo[1] = std::numeric_limits<double>::infinity();
    box->hi[0] = box->hi[1] = -std::numeric_limits<double>::infinity();
    for (Fragment& f : fragments) {
      if (!HasLineBox(s, f)) return false;
      for (int i = 0; i < 2; ++i) {
        box->lo[i] = std::min(box->lo[i], f.box.lo[i]);
        box->hi[i] = std::max(box->hi[i], f.box.hi[i]);
      }
    }
    return true;
  }

  // Subtracts the occluders `ids` (occluder ids, in this order) from the
  // fragments, until nothing is left or `max_subtracted` of them have been
  // subtracted. An occluder whose line box is apart from the box around all
  // the fragments is passed over without visiting them: a dense mesh's
  // leaf lists thousands of triangles, most of which miss the few pieces
  // that reach it. Returns the number subtracted.
  size_t SubtractOccluders(Scratch& s, std::vector<Fragment>* fragments, std::span<const uint32_t> ids,
                           const XPlane** slab_top, size_t max_subtracted = SIZE_MAX) const {
    Edges edges;
    Corners corners;
    LineBox all;
    bool all_valid = UnionLineBox(s, *fragments, &all);
    size_t subtracted = 0;
    for (const uint32_t id : ids) {
      if (fragments->empty() || subtracted == max_subtracted || StopNow(s)) break;
      if (!OccluderEdges(s, id, slab_top, &edges, &corners)) continue;
      LineBox shadow;
      const bool has_shadow = LineBoxOf(s, corners, &shadow);
      if (has_shadow && all_valid && all.Apart(shadow)) continue;
      ++subtracted;
      if (Subtract(s, fragments, edges, has_shadow ? &shadow : nullptr)) {
        all_valid = UnionLineBox(s, *fragments, &all);
      }
    }
    return subtracted;
  }

  // The answer from the store, or a new one, kept while the store has room.
  StatusOr<PointVisibility> Query(const QueryPoint& q, bool want_polygons, const StopToken& stop) {
    const AnswerKey key = KeyOf(q, want_polygons);
    {
      std::shared_lock lock(answers_mutex);
      if (auto it = answers.find(key); it != answers.end()) {
        queries.fetch_add(1, std::memory_order_relaxed);
        hits.fetch_add(1, std::memory_order_relaxed);
        answers_reused.fetch_add(1, std::memory_order_relaxed);
        return it->second;
      }
    }
    StatusOr<PointVisibility> answer = Compute(q, want_polygons, stop);
    if (answer.ok()) {
      const size_t bytes = AnswerBytes(*answer);
      std::unique_lock lock(answers_mutex);
      if (answer_bytes + bytes <= max_answer_bytes && answers.emplace(key, *answer).second) {
        answer_bytes += bytes;
        answer_bytes_now.store(answer_bytes, std::memory_order_relaxed);
      }
    }
    return answer;
  }

  StatusOr<PointVisibility> Compute(const QueryPoint& q, bool want_polygons, const StopToken& stop) {
    // Validate and move the point into the local frame.
    for (int i = 0; i < 3; ++i) {
      if (!InCoordinateRange(q.position[i])) {
        return absl::InvalidArgumentError(absl::StrCat("point.position[", i, "]: not finite or beyond ±", kMaxCoordinate));
      }
    }
    std::optional<glm::dvec3> normal = q.normal;
    if (normal) {
      for (int i = 0; i < 3; ++i) {
        if (!std::isfinite((*normal)[i])) {
          return absl::InvalidArgumentError(absl::StrCat("point.normal[", i, "]: not finite"));
        }
      }
      if (*normal == glm::dvec3(0.0)) return absl::InvalidArgumentError("point.normal: zero");
    }
    const glm::dvec3 p_local = q.position - origin;
    if (receiver_box) {
      const auto& [lo, hi] = *receiver_box;
      for (int i = 0; i < 3; ++i) {
        if (p_local[i] < lo[i] || p_local[i] > hi[i]) {
          return absl::OutOfRangeError("point.position: outside the tree's receiver_bounds");
        }
      }
    }
    queries.fetch_add(1, std::memory_order_relaxed);
    PointVisibility result;

    thread_local Scratch scratch;
    Scratch& s = scratch;
    s.Reset();
    s.stop = &stop;
    s.p = s.Add(XPoint::Input(p_local));
    // A light seen from behind (or edge-on) gives nothing.
    if (EuclidSide(*s.p, *light_plane) <= 0) {
      hits.fetch_add(1, std::memory_order_relaxed);
      return result;
    }
    const uint32_t receiver = q.receiver_triangle.value_or(UINT32_MAX);
    if (!normal && q.receiver_triangle) {
      // A triangle containing P is always near (never culled, never
      // separated from the receivers), so its vertices are at hand.
      if (auto it = near_by_triangle.find(receiver); it != near_by_triangle.end()) {
        const NearOccluder& n = near[it->second];
        const glm::dvec3 a = points[n.v[0]].input, b = points[n.v[1]].input, c = points[n.v[2]].input;
        const glm::dvec3 g = glm::cross(b - a, c - a);
        if (g != glm::dvec3(0.0)) normal = g;
      }
    }

    // Start from the light triangles, clipped to the receiver's hemisphere.
    std::vector<Fragment> pending;
    const XPlane* horizon = normal ? s.Add(XPlane::PointNormal(*s.p, *normal)) : nullptr;
    for (uint32_t t = 0; t < light_triangles.size(); ++t) {
      Fragment f;
      f.triangle = t;
      for (int i = 0; i < 3; ++i) f.v.push_back({&light_points[light_triangles[t].v[i]], i, nullptr});
      if (horizon != nullptr && !Clip(s, &f, *horizon, 1)) continue;
      pending.push_back(std::move(f));
    }

    if (pending.empty()) {
      hits.fetch_add(1, std::memory_order_relaxed);
      return result;
    }
    // LineBoxes hold when every direction from P to the light has d[k] of
    // one strict sign; the light is convex per triangle, so its vertices
    // decide (the sign of a difference of doubles is exact).
    for (size_t i = 0; i < light_local.size(); ++i) {
      const double d = light_local[i][light_axis] - p_local[light_axis];
      const int sign = d > 0.0 ? 1 : d < 0.0 ? -1 : 0;
      if (i == 0) s.line_box_sign = sign;
      if (sign != s.line_box_sign) s.line_box_sign = 0;
    }

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
    // Neighbouring points are mostly hidden by the same wall or floor: the
    // occluder that last hid a whole light from this thread, tried first,
    // spares the gathering. The test is exact for any occluder of the tree
    // but P's own triangle (excluded, as below: P may lie a rounding off its
    // plane), so a stale entry costs one test and no wrong answer.
    thread_local struct {
      const Impl* tree = nullptr;
      uint32_t id = 0;
    } last_cover;
    const auto is_receiver = [&](uint32_t id) {
      return id >= far.size() && near[id - far.size()].scene_triangle == receiver;
    };
    if (classify_points && last_cover.tree == this && last_cover.id < far.size() + near.size() &&
        !is_receiver(last_cover.id)) {
      const uint32_t* t = OccluderVertices(last_cover.id);
      const glm::dvec3 v[3] = {points[t[0]].input, points[t[1]].input, points[t[2]].input};
      if (TestOccluder(p_local, v).cover.all) {
        hits.fetch_add(1, std::memory_order_relaxed);
        wholly_hidden.fetch_add(1, std::memory_order_relaxed);
        return result;
      }
    }
    const PyramidCull cull(p_local, light_local, light_triangles);
    std::vector<uint32_t> near_candidates, far_candidates;
    bool any_far = false;
    std::vector<Blocker> blockers;
    uint64_t blocked_vertices = 0;
    const uint32_t far_count = static_cast<uint32_t>(far.size());
    {
      std::vector<uint32_t> ids;
      index.Collect([&](const glm::dvec3& lo, const glm::dvec3& hi) { return cull.MissesBox(lo, hi); }, &ids);
      for (const uint32_t id : ids) {
        const bool is_far = id < far_count;
        if (is_far && !classify_points) continue;  // the tree decides
        if (is_receiver(id)) continue;
        const uint32_t* t = OccluderVertices(id);
        const glm::dvec3 v[3] = {points[t[0]].input, points[t[1]].input, points[t[2]].input};
        if (cull.Misses(v)) continue;
        if (!classify_points) {
          if (ShadowMissesLight(p_local, v)) continue;
        } else {
          const OccluderTest test = TestOccluder(p_local, v);
          if (test.misses) continue;
          const Cover& cover = test.cover;
          if (cover.all) {
            last_cover.tree = this;
            last_cover.id = id;
            hits.fetch_add(1, std::memory_order_relaxed);
            wholly_hidden.fetch_add(1, std::memory_order_relaxed);
            return result;
          }
          if (cover.mask != 0) {
            blockers.push_back({id, std::popcount(cover.mask)});
            blocked_vertices |= cover.mask;
          }
        }
        if (is_far) {
          any_far = true;
          far_candidates.push_back(id);
        } else {
          near_candidates.push_back(id - far_count);
        }
      }
    }
    bool direct = false;
    if (!classify_points) {
      any_far = !far.empty();
    } else if (!any_far && near_candidates.empty()) {
      wholly_visible.fetch_add(1, std::memory_order_relaxed);
    } else if (far_candidates.size() + near_candidates.size() <= direct_candidates) {
      direct = true;
      subtracted_directly.fetch_add(1, std::memory_order_relaxed);
    } else if (light_local.size() <= 64 && blocked_vertices == (~uint64_t{0} >> (64 - light_local.size()))) {
      if (HiddenByFewBlockers(s, pending, &blockers)) {
        hits.fetch_add(1, std::memory_order_relaxed);
        wholly_hidden.fetch_add(1, std::memory_order_relaxed);
        return result;
      }
    }

    // Push the fragments down the shared tree.
    std::vector<Fragment> visible;
    bool refined = false;
    if (!any_far || direct) {
      visible = std::move(pending);
    } else {
      VISQ_RETURN_IF_ERROR(DescendTree(s, pending, cull, p_local, &visible, &refined));
    }
    if (!refined) hits.fetch_add(1, std::memory_order_relaxed);

    // Subtract the near occluders, clipped to the slab between the light
    // plane and the plane through P parallel to it (and, on the direct
    // route, the far candidates whole).
    std::vector<uint32_t> subtract;  // occluder ids: far ones first, then near ones
    if (direct) subtract = std::move(far_candidates);
    for (const uint32_t candidate : near_candidates) subtract.push_back(far_count + candidate);
    if (!subtract.empty() && !visible.empty()) {
      const XPlane* slab_top = nullptr;
      // Largest first: in index order a penumbra under a dense mesh was cut
      // into thousands of pieces, and nearest first was little better
      // (docs/exact-method-notes.md).
      SortLargestFirst(p_local, &subtract);
      SubtractOccluders(s, &visible, subtract, &slab_top);
      if (!s.stopped.ok()) return s.stopped;
    }

    // Integrate over the visible polygons.
    return Integrate(visible, p_local, normal, want_polygons);
  }

  // Pushes the light fragments down the shared tree from its root: the
  // parts that reach visible leaves go to *visible; an undefined leaf is
  // refined under the exclusive lock (*refined), or, with the tree at its
  // budget, resolved against its occluders here. CANCELLED or
  // DEADLINE_EXCEEDED when the query's stop says so.
  Status DescendTree(Scratch& s, std::vector<Fragment>& pending, const PyramidCull& cull,
                     const glm::dvec3& p_local, std::vector<Fragment>* out, bool* refined_out) {
    std::vector<Fragment>& visible = *out;
    bool& refined = *refined_out;
    std::vector<std::pair<int32_t, Fragment>> stack;
    for (auto& f : pending) stack.emplace_back(0, std::move(f));
    std::vector<int> sg;
    std::shared_lock lock(mutex);
    while (!stack.empty()) {
      if (StopNow(s)) return s.stopped;
      auto [id, f] = std::move(stack.back());
      stack.pop_back();
      const Node& node = nodes[id];
      if (node.kind == kVisible) {
        visible.push_back(std::move(f));
      } else if (node.kind == kUndefined &&
                 MemoryBytesLocked() + answer_bytes_now.load(std::memory_order_relaxed) >= max_bytes) {
        // The tree is at its budget: resolve this fragment against the
        // leaf's occluders here, without growing the tree.
        // Only the occluders whose shadows can meet the light, largest
        // first, as the near ones: a leaf of a dense room lists
        // thousands, and in index order a penumbra point was cut into
        // thousands of pieces (docs/exact-method-notes.md).
        unrefined_leaf_visits.fetch_add(1, std::memory_order_relaxed);
        std::vector<Fragment> pieces;
        pieces.push_back(std::move(f));
        // The fragment is usually a small part of the light: occluders
        // whose line boxes are apart from its box go first.
        const bool fragment_box = HasLineBox(s, pieces[0]);
        std::vector<uint32_t> ids;
        VISQ_DCHECK_LT(size_t(node.b), lists.size());
        for (const uint32_t index : lists[node.b]) {
          const uint32_t* t = far[index].v;
          const glm::dvec3 v[3] = {points[t[0]].input, points[t[1]].input, points[t[2]].input};
          if (cull.Misses(v)) continue;
          if (fragment_box) {
            const XPoint* corners[3] = {&points[t[0]], &points[t[1]], &points[t[2]]};
            LineBox box;
            if (LineBoxOf(s, corners, &box) && pieces[0].box.Apart(box)) continue;
          }
          if (ShadowMissesLight(p_local, v)) continue;
          ids.push_back(index);
        }
        SortLargestFirst(p_local, &ids);
        const XPlane* no_slab = nullptr;  // far occluders are whole
        SubtractOccluders(s, &pieces, ids, &no_slab);
        if (!s.stopped.ok()) return s.stopped;
        for (Fragment& piece : pieces) visible.push_back(std::move(piece));
      } else if (node.kind == kUndefined) {
        // Refine this leaf under the exclusive lock, then resume here.
        lock.unlock();
        {
          std::unique_lock exclusive(mutex);
          glm::dvec3 y(0.0);  // the fragment's vertex average, inside it
          for (const FVert& fv : f.v) y += fv.point->Euclid();
          Refine(id, p_local, y / static_cast<double>(f.v.size()));
        }
        lock.lock();
        refined = true;
        stack.emplace_back(id, std::move(f));
      } else if (node.kind == kInner) {
        EdgeLine line{&points[node.a], &points[node.b]};
        const int32_t c0 = node.child[0], c1 = node.child[1];
        if (!EdgeSides(s, f, line, &sg)) {
          stack.emplace_back(c1, std::move(f));
          continue;
        }
        const bool any_pos = std::any_of(sg.begin(), sg.end(), [](int x) { return x > 0; });
        const bool any_neg = std::any_of(sg.begin(), sg.end(), [](int x) { return x < 0; });
        if (!any_neg) {
          stack.emplace_back(c0, std::move(f));
        } else if (!any_pos) {
          stack.emplace_back(c1, std::move(f));
        } else {
          Fragment pos, neg;
          Split(s, f, sg, *PlaneOf(s, line).plane, &pos, &neg);
          stack.emplace_back(c0, std::move(pos));
          stack.emplace_back(c1, std::move(neg));
        }
      }
      // kInvisible: dropped.
    }
    return absl::OkStatus();
  }

  // The visible fraction of the light's area and solid angle, and the
  // irradiance for the normal, from the visible fragments (and their
  // polygons, when asked for).
  PointVisibility Integrate(const std::vector<Fragment>& visible, const glm::dvec3& p_local,
                            const std::optional<glm::dvec3>& normal, bool want_polygons) const {
    PointVisibility result;
    double area = 0.0, solid_angle = 0.0, irradiance = 0.0;
    for (const Fragment& f : visible) {
      std::vector<glm::dvec3> v(f.v.size());
      for (size_t i = 0; i < v.size(); ++i) v[i] = f.v[i].point->Euclid();
      glm::dvec3 phi(0.0);  // vector irradiance of the polygon (Lambert)
      for (size_t i = 0; i < v.size(); ++i) {
        if (i >= 1 && i + 1 < v.size()) {
          area += Area3(v[0], v[i], v[i + 1]);
          solid_angle += SolidAngle(v[0] - p_local, v[i] - p_local, v[i + 1] - p_local);
        }
        const glm::dvec3 r0 = v[i] - p_local, r1 = v[(i + 1) % v.size()] - p_local;
        const glm::dvec3 c = glm::cross(r0, r1);
        const double lc = glm::length(c);
        if (lc > 0.0) phi += std::atan2(lc, glm::dot(r0, r1)) * (c / lc);
      }
      if (normal) irradiance += 0.5 * glm::dot(glm::normalize(*normal), phi);
      if (want_polygons) {
        std::vector<glm::dvec3> world(v.size());
        for (size_t i = 0; i < v.size(); ++i) world[i] = v[i] + origin;
        result.visible_polygons.push_back(std::move(world));
      }
    }
    double total_solid_angle = 0.0;
    for (const LightTriangle& t : light_triangles) {
      total_solid_angle += SolidAngle(light_local[t.v[0]] - p_local, light_local[t.v[1]] - p_local,
                                      light_local[t.v[2]] - p_local);
    }
    result.visible_area_fraction = std::min(1.0, area / light_area);
    result.visible_solid_angle_fraction =
        total_solid_angle > 0.0 ? std::min(1.0, solid_angle / total_solid_angle) : 0.0;
    // All visible fragments wind the same way as seen from P.
    result.irradiance = radiance * std::fabs(irradiance);
    return result;
  }
};

// ---------------------------------------------------------------------------
namespace {

// Ear clipping in the projection that drops the dominant normal axis; exact
// 2D orientation tests. Returns triangles as vertex index triples in the
// polygon's winding, or an error for non-simple polygons.
StatusOr<std::vector<std::array<uint32_t, 3>>> Triangulate(const std::vector<glm::dvec3>& v,
                                                           const glm::dvec3& newell) {
  int k = 0;
  for (int i = 1; i < 3; ++i) {
    if (std::fabs(newell[i]) > std::fabs(newell[k])) k = i;
  }
  int i2 = (k + 1) % 3, j2 = (k + 2) % 3;
  if (newell[k] < 0) std::swap(i2, j2);  // make the polygon counter-clockwise
  // Simple: no two non-adjacent edges meet (exact segment tests).
  const size_t n = v.size();
  auto meet = [&](const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, const glm::dvec3& d) {
    const int o1 = Orient2d(a, b, c, i2, j2), o2 = Orient2d(a, b, d, i2, j2);
    const int o3 = Orient2d(c, d, a, i2, j2), o4 = Orient2d(c, d, b, i2, j2);
    if (o1 * o2 < 0 && o3 * o4 < 0) return true;
    auto on = [&](const glm::dvec3& p, const glm::dvec3& q, const glm::dvec3& x, int o) {
      return o == 0 && std::min(p[i2], q[i2]) <= x[i2] && x[i2] <= std::max(p[i2], q[i2]) &&
             std::min(p[j2], q[j2]) <= x[j2] && x[j2] <= std::max(p[j2], q[j2]);
    };
    return on(a, b, c, o1) || on(a, b, d, o2) || on(c, d, a, o3) || on(c, d, b, o4);
  };
  for (size_t e = 0; e < n; ++e) {
    for (size_t f = e + 2; f < n; ++f) {
      if (e == 0 && f == n - 1) continue;  // adjacent through vertex 0
      if (meet(v[e], v[(e + 1) % n], v[f], v[(f + 1) % n])) {
        return absl::InvalidArgumentError(absl::StrCat(
            "light: not a simple polygon (edges ", e, " and ", f, " meet)"));
      }
    }
  }
  std::vector<uint32_t> ring(v.size());
  for (uint32_t i = 0; i < ring.size(); ++i) ring[i] = i;
  std::vector<std::array<uint32_t, 3>> out;
  // Drop exactly collinear (straight) vertices first; they would give
  // zero-area ears.
  auto drop_straight = [&]() {
    bool changed = true;
    while (changed && ring.size() > 3) {
      changed = false;
      for (size_t i = 0; i < ring.size(); ++i) {
        const size_t a = (i + ring.size() - 1) % ring.size(), c = (i + 1) % ring.size();
        if (Orient2d(v[ring[a]], v[ring[i]], v[ring[c]], i2, j2) == 0) {
          ring.erase(ring.begin() + static_cast<long>(i));
          changed = true;
          break;
        }
      }
    }
  };
  drop_straight();
  while (ring.size() > 3) {
    bool found = false;
    for (size_t i = 0; i < ring.size() && !found; ++i) {
      const size_t a = (i + ring.size() - 1) % ring.size(), c = (i + 1) % ring.size();
      const glm::dvec3 &pa = v[ring[a]], &pb = v[ring[i]], &pc = v[ring[c]];
      if (Orient2d(pa, pb, pc, i2, j2) <= 0) continue;  // reflex
      bool empty = true;
      for (size_t m = 0; m < ring.size() && empty; ++m) {
        if (m == a || m == i || m == c) continue;
        const glm::dvec3& x = v[ring[m]];
        if (Orient2d(pa, pb, x, i2, j2) >= 0 && Orient2d(pb, pc, x, i2, j2) >= 0 &&
            Orient2d(pc, pa, x, i2, j2) >= 0) {
          empty = false;
        }
      }
      if (!empty) continue;
      out.push_back({ring[a], ring[i], ring[c]});
      ring.erase(ring.begin() + static_cast<long>(i));
      drop_straight();
      found = true;
    }
    if (!found) return absl::InvalidArgumentError("light: not a simple polygon");
  }
  if (ring.size() == 3) {
    if (Orient2d(v[ring[0]], v[ring[1]], v[ring[2]], i2, j2) <= 0) {
      return absl::InvalidArgumentError("light: not a simple polygon");
    }
    out.push_back({ring[0], ring[1], ring[2]});
  }
  return out;
}

}  // namespace

namespace {

// The light moved to its centroid and triangulated, after every check.
struct PreparedLight {
  glm::dvec3 origin{0.0};
  std::vector<glm::dvec3> local;
  std::vector<std::array<uint32_t, 3>> triangles;
};

StatusOr<PreparedLight> PrepareLight(const AreaLight& light) {
  const auto& lv = light.vertices;
  if (lv.size() < 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("light.vertices: need at least 3, got ", lv.size()));
  }
  for (size_t i = 0; i < lv.size(); ++i) {
    for (int c = 0; c < 3; ++c) {
      if (std::isnan(lv[i][c])) {
        return absl::InvalidArgumentError(absl::StrCat("light.vertices[", i, "]: NaN coordinate"));
      }
      if (!InCoordinateRange(lv[i][c])) {
        return absl::InvalidArgumentError(
            absl::StrCat("light.vertices[", i, "]: infinite coordinate or beyond ±", kMaxCoordinate));
      }
    }
    if (lv[i] == lv[(i + 1) % lv.size()]) {
      return absl::InvalidArgumentError(absl::StrCat("light.vertices[", (i + 1) % lv.size(),
                                                     "]: repeats light.vertices[", i, "]"));
    }
  }
  if (!std::isfinite(light.radiance) || light.radiance < 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("light.radiance: must be finite and >= 0, got ", light.radiance));
  }
  glm::dvec3 centroid(0.0);
  for (const auto& p : lv) centroid += p;
  centroid /= static_cast<double>(lv.size());
  PreparedLight out;
  out.origin = centroid;
  for (const auto& p : lv) out.local.push_back(p - centroid);
  const auto& ll = out.local;
  glm::dvec3 newell(0.0);
  double diameter = 0.0;
  for (size_t i = 0; i < ll.size(); ++i) {
    newell += glm::cross(ll[i], ll[(i + 1) % ll.size()]);
    for (size_t j = 0; j < i; ++j) diameter = std::max(diameter, glm::length(ll[i] - ll[j]));
  }
  const double newell_len = glm::length(newell);
  if (!(newell_len > 1e-12 * diameter * diameter)) {
    return absl::InvalidArgumentError("light: zero area");
  }
  const glm::dvec3 unit_normal = newell / newell_len;
  for (size_t i = 0; i < ll.size(); ++i) {
    const double off = std::fabs(glm::dot(unit_normal, ll[i]));
    if (off > 1e-6 * diameter) {
      return absl::InvalidArgumentError(absl::StrCat(
          "light: not planar (light.vertices[", i, "] is ", off, " off the plane)"));
    }
  }
  VISQ_ASSIGN_OR_RETURN(out.triangles, Triangulate(ll, newell));
  return out;
}

}  // namespace

Status ValidateAreaLight(const AreaLight& light) { return PrepareLight(light).status(); }

struct SceneTriangleIndex::Impl {
  OccluderIndex boxes;
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

StatusOr<std::unique_ptr<LightVisibilityTree>> LightVisibilityTree::Create(
    const AreaLight& light, const Scene& scene, const TreeOptions& options, const SceneTriangleIndex* index) {
  if (index != nullptr && index->triangle_count() != scene.triangles.size()) {
    return absl::InvalidArgumentError(absl::StrCat("the triangle index has ", index->triangle_count(),
                                                   " triangles, the scene ", scene.triangles.size()));
  }
  auto impl = std::make_unique<Impl>();

  VISQ_ASSIGN_OR_RETURN(PreparedLight prepared, PrepareLight(light));
  impl->origin = prepared.origin;
  impl->radiance = light.radiance;
  impl->max_bytes = options.max_bytes;
  impl->max_answer_bytes = options.keep_answers ? options.max_bytes / 4 : 0;
  impl->classify_points = options.classify_points;
  impl->direct_candidates = options.classify_points ? options.direct_candidates : 0;
  impl->light_local = std::move(prepared.local);
  const auto& ll = impl->light_local;
  const auto& triangles = prepared.triangles;

  // The light's exact geometry: input points, triangle planes, and the light
  // plane through the largest triangle (oriented: front side positive).
  for (const auto& p : ll) impl->light_points.push_back(XPoint::Input(p));
  double best = -1.0;
  for (const auto& t : triangles) {
    const double a = Area3(ll[t[0]], ll[t[1]], ll[t[2]]);
    impl->light_area += a;
    impl->light_planes.push_back(XPlane::ThroughPoints(
        impl->light_points[t[0]], impl->light_points[t[1]], impl->light_points[t[2]]));
    impl->light_planes.back().PrecomputeExact();
    impl->light_triangles.push_back({{t[0], t[1], t[2]}, &impl->light_planes.back()});
    if (a > best) {
      best = a;
      impl->light_plane = &impl->light_planes.back();
    }
  }
  const LightTriangle* main_tri = nullptr;
  for (const auto& t : impl->light_triangles) {
    if (t.plane == impl->light_plane) main_tri = &t;
  }
  {
    const glm::dvec3 n = glm::abs(glm::cross(ll[main_tri->v[1]] - ll[main_tri->v[0]],
                                             ll[main_tri->v[2]] - ll[main_tri->v[0]]));
    impl->light_axis = n.x >= n.y && n.x >= n.z ? 0 : n.y >= n.z ? 1 : 2;
  }
  const Orient3dFan light_fan(ll[main_tri->v[0]], ll[main_tri->v[1]], ll[main_tri->v[2]]);

  // The receiver box in the local frame. No outward rounding is needed:
  // rounding is monotone, so a world point inside the world box lands inside
  // the converted box (and widening would make flat boxes thick by an ulp,
  // which costs near-degenerate hull faces).
  if (options.receiver_bounds && !options.receiver_bounds->Empty()) {
    const glm::dvec3 lo = options.receiver_bounds->min - impl->origin;
    const glm::dvec3 hi = options.receiver_bounds->max - impl->origin;
    impl->receiver_box = std::make_pair(lo, hi);
  }

  // Select the occluders: drop what lies behind the light plane or outside
  // the shaft's box; keep far ones (strictly separated from the receivers)
  // in the tree, the rest near.
  std::vector<uint8_t> excluded;
  if (!options.exclude_triangles.empty()) {
    excluded.assign(scene.triangles.size(), 0);
    for (uint32_t t : options.exclude_triangles) {
      if (t < excluded.size()) excluded[t] = 1;
    }
  }
  glm::dvec3 shaft_lo(std::numeric_limits<double>::infinity()), shaft_hi(-shaft_lo);
  for (const auto& p : ll) {
    shaft_lo = glm::min(shaft_lo, p);
    shaft_hi = glm::max(shaft_hi, p);
  }
  glm::dvec3 corners[8];
  struct ShaftPlane { Orient3dFan fan; int outside; };
  std::vector<ShaftPlane> shaft_planes;
  bool light_below_receivers = false;
  std::deque<XPoint> corner_points;
  std::deque<XPlane> corner_planes;
  if (impl->receiver_box) {
    const auto& [lo, hi] = *impl->receiver_box;
    shaft_lo = glm::min(shaft_lo, lo);
    shaft_hi = glm::max(shaft_hi, hi);
    for (int c = 0; c < 8; ++c) {
      corners[c] = glm::dvec3((c & 1) ? hi.x : lo.x, (c & 2) ? hi.y : lo.y, (c & 4) ? hi.z : lo.z);
      corner_points.push_back(XPoint::Input(corners[c]));
      corner_planes.push_back(XPlane::ParallelThrough(*impl->light_plane, corner_points.back()));
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
          shaft_planes.push_back({Orient3dFan(hull_points[i], hull_points[j], hull_points[k]), pos ? -1 : 1});
        }
      }
    }
    // Separation along the light normal needs the light strictly below the box.
    light_below_receivers = true;
    for (const auto& plane : corner_planes) {
      for (const auto& y : impl->light_points) light_below_receivers &= EuclidSide(y, plane) < 0;
    }
  }

  // Occluder vertices are merged by position, not by index: meshes often
  // repeat positions (flat shading, per-face vertices), and one point object
  // per position lets a split vertex be recognised as lying on an edge plane
  // by construction instead of by an exact evaluation (see EdgePlane).
  // By scene vertex index, for the triangles visited only: a vector over
  // all the scene's positions would be filled per tree, however few
  // triangles the shaft meets.
  absl::flat_hash_map<uint32_t, uint32_t> remap;
  struct PositionHash {
    size_t operator()(const glm::dvec3& p) const {
      size_t h = 0;
      for (int i = 0; i < 3; ++i) {
        h = h * 0x9E3779B97F4A7C15ull + std::hash<double>()(p[i] + 0.0);  // -0 == +0
      }
      return h;
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
  const bool indexed = index != nullptr && impl->receiver_box.has_value();
  if (indexed) {
    const auto largest = [](const glm::dvec3& x) { return std::max({std::fabs(x.x), std::fabs(x.y), std::fabs(x.z)}); };
    const double magnitude = std::max(largest(shaft_lo), largest(shaft_hi)) + largest(impl->origin);
    const glm::dvec3 pad(1e-9 * magnitude + 1e-300);
    near_shaft = index->InBox(shaft_lo + impl->origin - pad, shaft_hi + impl->origin + pad);
  }
  const size_t visit_count = indexed ? near_shaft.size() : scene.triangles.size();
  for (size_t visit = 0; visit < visit_count; ++visit) {
    if (visit % 4096 == 0) {
      if (options.cancelled != nullptr && options.cancelled->load())
        return absl::CancelledError(absl::StrCat("light tree: cancelled after ", visit, " of ", visit_count,
                                                 " triangles"));
      if (std::chrono::steady_clock::now() > options.deadline)
        return absl::DeadlineExceededError(absl::StrCat("light tree: the deadline passed after ", visit, " of ",
                                                        visit_count, " triangles"));
    }
    const size_t ti = indexed ? near_shaft[visit] : visit;
    const glm::uvec3 tri = scene.triangles[ti];
    for (int c = 0; c < 3; ++c) {
      if (tri[c] >= scene.positions.size()) {
        return absl::InvalidArgumentError(absl::StrCat("scene.triangles[", ti, "][", c, "]: index ",
                                                       tri[c], " >= ", scene.positions.size(),
                                                       " positions"));
      }
    }
    if (!excluded.empty() && excluded[ti]) continue;
    glm::dvec3 v[3];
    for (int c = 0; c < 3; ++c) v[c] = scene.positions[tri[c]] - impl->origin;
    // Shaft box (only with receiver bounds: otherwise receivers are anywhere).
    bool outside = false;
    for (int i = 0; i < 3 && !outside && impl->receiver_box; ++i) {
      outside = (v[0][i] < shaft_lo[i] && v[1][i] < shaft_lo[i] && v[2][i] < shaft_lo[i]) ||
                (v[0][i] > shaft_hi[i] && v[1][i] > shaft_hi[i] && v[2][i] > shaft_hi[i]);
    }
    for (size_t k = 0; k < shaft_planes.size() && !outside; ++k) {
      const ShaftPlane& sp = shaft_planes[k];
      outside = true;
      for (int c = 0; c < 3 && outside; ++c) outside = sp.fan.Side(v[c]) == sp.outside;
    }
    if (outside) continue;
    // Degenerate (zero-area) triangles block nothing.
    {
      // Test the projection along the dominant normal axis first: it is the
      // one whose sign the filter settles.
      const glm::dvec3 g = glm::abs(glm::cross(v[1] - v[0], v[2] - v[0]));
      const int k = g.x >= g.y && g.x >= g.z ? 0 : (g.y >= g.z ? 1 : 2);
      if (Orient2d(v[0], v[1], v[2], (k + 1) % 3, (k + 2) % 3) == 0 &&
          Orient2d(v[0], v[1], v[2], k, (k + 1) % 3) == 0 &&
          Orient2d(v[0], v[1], v[2], (k + 2) % 3, k) == 0) {
        continue;
      }
    }
    // Behind or in the light plane: blocks no segment from the light.
    Pending p{};
    bool any_front = false, any_back = false;
    for (int c = 0; c < 3; ++c) {
      p.side[c] = static_cast<int8_t>(light_fan.Side(v[c]));
      any_front |= p.side[c] > 0;
      any_back |= p.side[c] < 0;
    }
    if (!any_front) continue;
    // Far: in the light's closed front and strictly separated from the
    // receiver box by an axis plane or a plane parallel to the light, with
    // the light on the occluder's side.
    if (impl->receiver_box && !any_back) {
      const auto& [lo, hi] = *impl->receiver_box;
      for (int axis = 0; axis < 3 && !p.far; ++axis) {
        bool above = true, below = true;
        for (int c = 0; c < 3; ++c) {
          above &= v[c][axis] > hi[axis];
          below &= v[c][axis] < lo[axis];
        }
        for (const auto& y : ll) {
          above &= y[axis] > hi[axis];
          below &= y[axis] < lo[axis];
        }
        p.far = above || below;
      }
      if (!p.far && light_below_receivers) {
        bool separated = true;
        for (int c = 0; c < 3 && separated; ++c) {
          const XPoint x = XPoint::Input(v[c]);
          for (const auto& plane : corner_planes) separated &= EuclidSide(x, plane) < 0;
        }
        p.far = separated;
      }
    }
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
  impl->points.reserve(occ_local.size());  // filled once: the pointers into it stay valid
  for (const auto& x : occ_local) impl->points.push_back(XPoint::Input(x));
  for (const auto& p : pending) {
    if (p.far) {
      impl->far.push_back({{p.v[0], p.v[1], p.v[2]}, p.two_sided});
    } else {
      impl->near_by_triangle[p.tri] = static_cast<uint32_t>(impl->near.size());
      impl->near.push_back({{p.v[0], p.v[1], p.v[2]}, {p.side[0], p.side[1], p.side[2]}, p.tri});
    }
  }
  impl->IndexOccludersAndPlantTheTree();
  return std::unique_ptr<LightVisibilityTree>(new LightVisibilityTree(std::move(impl)));
}

LightVisibilityTree::LightVisibilityTree(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
LightVisibilityTree::~LightVisibilityTree() = default;

Status StopToken::Check() const {
  if (cancelled != nullptr && cancelled->load(std::memory_order_relaxed)) return absl::CancelledError("cancelled");
  if (deadline != std::chrono::steady_clock::time_point::max() && std::chrono::steady_clock::now() > deadline)
    return absl::DeadlineExceededError("deadline passed");
  return absl::OkStatus();
}

StatusOr<PointVisibility> LightVisibilityTree::Query(const QueryPoint& point, bool want_polygons,
                                                     const StopToken& stop) {
  return impl_->Query(point, want_polygons, stop);
}

StatusOr<std::vector<PointVisibility>> LightVisibilityTree::QueryBatch(
    std::span<const QueryPoint> points, int threads, bool want_polygons,
    std::chrono::steady_clock::time_point deadline) {
  std::vector<PointVisibility> out(points.size());
  std::atomic<bool> stop{false};
  std::mutex error_mutex;
  Status error;
  // One point per chunk: query costs vary a lot (refinement, penumbrae).
  ParallelFor(
      points.size(), 1,
      [&](size_t i, size_t) {
        if (stop.load(std::memory_order_relaxed)) return;
        if (std::chrono::steady_clock::now() > deadline) {
          std::lock_guard lock(error_mutex);
          if (error.ok())
            error = absl::DeadlineExceededError(
                absl::StrCat("deadline passed with ", points.size() - i, " of ", points.size(), " points left"));
          stop = true;
          return;
        }
        auto r = impl_->Query(points[i], want_polygons, StopToken{nullptr, deadline});
        if (!r.ok()) {
          std::lock_guard lock(error_mutex);
          if (error.ok()) error = Status(r.status().code(), absl::StrCat("points[", i, "]: ", r.status().message()));
          return;
        }
        out[i] = std::move(*r);
      },
      threads > 0 ? static_cast<size_t>(threads) : 0);
  if (!error.ok()) return error;
  return out;
}

TreeStats LightVisibilityTree::Stats() const {
  TreeStats s;
  std::shared_lock lock(impl_->mutex);
  s.nodes = impl_->nodes.size();
  s.memory_bytes = impl_->MemoryBytesLocked();
  s.queries = impl_->queries.load();
  s.hits = impl_->hits.load();
  s.refinements = impl_->refinements.load();
  s.unrefined_leaf_visits = impl_->unrefined_leaf_visits.load();
  s.wholly_visible = impl_->wholly_visible.load();
  s.wholly_hidden = impl_->wholly_hidden.load();
  s.subtracted_directly = impl_->subtracted_directly.load();
  s.answers_reused = impl_->answers_reused.load();
  {
    std::shared_lock answers_lock(impl_->answers_mutex);
    s.answers_kept = impl_->answers.size();
    s.memory_bytes += impl_->answer_bytes;
  }
  s.far_occluders = impl_->far.size();
  s.near_occluders = impl_->near.size();
  return s;
}

TreeStats& TreeStats::operator+=(const TreeStats& o) {
  nodes += o.nodes;
  memory_bytes += o.memory_bytes;
  queries += o.queries;
  hits += o.hits;
  refinements += o.refinements;
  unrefined_leaf_visits += o.unrefined_leaf_visits;
  wholly_visible += o.wholly_visible;
  wholly_hidden += o.wholly_hidden;
  subtracted_directly += o.subtracted_directly;
  answers_reused += o.answers_reused;
  answers_kept += o.answers_kept;
  far_occluders += o.far_occluders;
  near_occluders += o.near_occluders;
  return *this;
}

size_t LightVisibilityTree::MemoryBytes() const {
  size_t bytes;
  {
    std::shared_lock lock(impl_->mutex);
    bytes = impl_->MemoryBytesLocked();
  }
  std::shared_lock lock(impl_->answers_mutex);
  return bytes + impl_->answer_bytes;
}

double LightVisibilityTree::light_area() const { return impl_->light_area; }

// ---------------------------------------------------------------------------
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
    if (count <= 4 * options.max_shaft_triangles) {
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

uint64_t HashLight(const AreaLight& light, const TreeOptions& options) {
  uint64_t h = 1469598103934665603ull;  // FNV-1a over the bit patterns
  auto mix = [&](const void* data, size_t n) {
    const auto* b = static_cast<const unsigned char*>(data);
    for (size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 1099511628211ull;
  };
  for (const auto& v : light.vertices) mix(&v, sizeof(v));
  mix(&light.radiance, sizeof(light.radiance));
  if (options.receiver_bounds) {
    mix(&options.receiver_bounds->min, sizeof(glm::dvec3));
    mix(&options.receiver_bounds->max, sizeof(glm::dvec3));
  }
  for (uint32_t t : options.exclude_triangles) mix(&t, sizeof(t));
  return h;
}

size_t LightVisibilityCache::KeyHash::operator()(const CacheKey& k) const {
  return std::hash<std::string>()(k.scene_id) ^ (k.scene_version * 0x9E3779B97F4A7C15ull) ^
         (k.light_hash * 0xC2B2AE3D27D4EB4Full);
}

LightVisibilityCache::LightVisibilityCache(size_t max_bytes) : max_bytes_(max_bytes) {}

std::shared_ptr<LightVisibilityTree> LightVisibilityCache::Find(const CacheKey& key) {
  std::lock_guard lock(mutex_);
  auto it = index_.find(key);
  if (it == index_.end()) return nullptr;
  lru_.splice(lru_.begin(), lru_, it->second);
  EvictLocked(&key);
  return it->second->second;
}

StatusOr<std::shared_ptr<LightVisibilityTree>> LightVisibilityCache::GetOrCreate(
    const CacheKey& key, const Factory& make) {
  if (auto hit = Find(key)) return hit;
  // Build outside the lock: creation scans the whole scene.
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<LightVisibilityTree> made, make());
  std::shared_ptr<LightVisibilityTree> tree(std::move(made));
  std::lock_guard lock(mutex_);
  auto it = index_.find(key);
  if (it != index_.end()) {  // somebody else built it meanwhile; keep theirs
    lru_.splice(lru_.begin(), lru_, it->second);
    return it->second->second;
  }
  lru_.emplace_front(key, tree);
  index_[key] = lru_.begin();
  EvictLocked(&key);
  return tree;
}

void LightVisibilityCache::EvictLocked(const CacheKey* keep) {
  // Trees grow after insertion, so the total is measured afresh.
  size_t total = 0;
  for (const auto& [k, tree] : lru_) total += tree->MemoryBytes();
  while (total > max_bytes_ && !lru_.empty()) {
    auto victim = std::prev(lru_.end());
    if (keep != nullptr && victim->first == *keep) break;  // never the one being returned
    total -= victim->second->MemoryBytes();
    index_.erase(victim->first);
    lru_.erase(victim);
    ++evictions_;
  }
}

void LightVisibilityCache::InvalidateScene(const std::string& scene_id) {
  std::lock_guard lock(mutex_);
  for (auto it = lru_.begin(); it != lru_.end();) {
    if (it->first.scene_id == scene_id) {
      index_.erase(it->first);
      it = lru_.erase(it);
    } else {
      ++it;
    }
  }
}

size_t LightVisibilityCache::bytes() const {
  std::lock_guard lock(mutex_);
  size_t total = 0;
  for (const auto& [k, tree] : lru_) total += tree->MemoryBytes();
  return total;
}

size_t LightVisibilityCache::size() const {
  std::lock_guard lock(mutex_);
  return lru_.size();
}

uint64_t LightVisibilityCache::evictions() const {
  std::lock_guard lock(mutex_);
  return evictions_;
}

}  // namespace visq::exact
