// One query on a tree: the store of answers, the exact classification of
// points before the tree, the descent, and the integration over the light's
// visible polygons.
#include "exact/light_visibility_impl.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <mutex>

#include "common/check.h"
#include "common/coordinates.h"

namespace visq::exact::detail {

namespace {

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
  size_t bytes = sizeof(AnswerKey) + sizeof(StoredAnswer) + 16;
  if (!v.visible_polygons.empty() || v.visible_area_fraction_error > 0.0) bytes += sizeof(StoredAnswer::Rest);
  for (const auto& polygon : v.visible_polygons) bytes += sizeof(polygon) + polygon.size() * sizeof(glm::dvec3);
  return bytes;
}

}  // namespace

// A floating-point cull of the near occluders that cannot touch the pyramid
// from P to the light: before any exact predicate, an occluder whose box
// misses the pyramid's box, or that lies wholly outside one side plane of
// the pyramid, blocks no segment from P to the light. It only ever skips an
// occluder when the double-precision test clears a margin far above its
// rounding error, so it never changes an answer; anything closer is left to
// the exact code.
//
// The side planes are those of the light's outline (through P and each
// edge of the light polygon) when every one of them has the whole light on
// its inner side: a convex light, four planes for a quad. Otherwise (a
// concave outline, or a vertex too close to call) they are the three of
// each light triangle, and an occluder must be outside one of every
// triangle's. The outline's planes cull at least what the triangles' do
// on a convex light, in fewer tests.
class PyramidCull {
 public:
  // MissesBox and Misses are asked only about boxes and triangles inside
  // `bounds` (the occluders').
  // Without `enabled`, it misses nothing.
  PyramidCull(const glm::dvec3& p, const std::vector<glm::dvec3>& light, const std::vector<LightTriangle>& triangles,
              const std::pair<glm::dvec3, glm::dvec3>& bounds, bool enabled)
      : enabled_(enabled), p_(p), lo_(p), hi_(p) {
    if (!enabled_) return;
    for (const glm::dvec3& v : light) {
      lo_ = glm::min(lo_, v);
      hi_ = glm::max(hi_, v);
    }
    if (!OutlinePlanes(light)) TrianglePlanes(light, triangles);
    // The margin is taken at the farthest point of `bounds` from P, at
    // least that of every point tested: one margin a plane, and the box
    // corner furthest inside picked once a plane (MissesBox runs at every
    // node a query visits, Misses at every occluder it lists).
    const double reach = Norm1(glm::max(glm::abs(bounds.first - p), glm::abs(bounds.second - p)));
    for (Sides& sides : triangle_sides_) {
      for (Plane& plane : sides.planes) {
        plane.margin = -kRelativeMargin * plane.scale * reach;
        for (int axis = 0; axis < 3; ++axis) plane.pick[axis] = plane.normal[axis] > 0 ? 1 : 0;
      }
    }
  }

  // Whether every point of the box [lo, hi] (inside the constructor's
  // bounds) passes the test Misses applies to vertices (so no triangle
  // inside the box can touch the pyramid). Per plane, the corner furthest
  // inside decides.
  bool MissesBox(const glm::dvec3& lo, const glm::dvec3& hi) const {
    if (!enabled_) return false;
    for (int axis = 0; axis < 3; ++axis)
      if (hi[axis] < lo_[axis] || lo[axis] > hi_[axis]) return true;
    const glm::dvec3* corners[2] = {&lo, &hi};
    const auto outside = [&](const Plane& plane) {
      const glm::dvec3 furthest_inside((*corners[plane.pick[0]]).x, (*corners[plane.pick[1]]).y,
                                       (*corners[plane.pick[2]]).z);
      return glm::dot(plane.normal, furthest_inside - p_) < plane.margin;
    };
    return OutsideEverySet(outside);
  }

  bool Misses(const glm::dvec3 (&v)[3]) const {
    if (!enabled_) return false;
    for (int axis = 0; axis < 3; ++axis) {
      if (v[0][axis] < lo_[axis] && v[1][axis] < lo_[axis] && v[2][axis] < lo_[axis]) return true;
      if (v[0][axis] > hi_[axis] && v[1][axis] > hi_[axis] && v[2][axis] > hi_[axis]) return true;
    }
    const glm::dvec3 x[3] = {v[0] - p_, v[1] - p_, v[2] - p_};
    const auto outside = [&](const Plane& plane) {
      for (int i = 0; i < 3; ++i) {
        if (!(glm::dot(plane.normal, x[i]) < plane.margin)) return false;
      }
      return true;
    };
    return OutsideEverySet(outside);
  }

 private:
  // The side value is a 3x3 determinant of differences of doubles; its
  // rounding error is a few ulps of the product of the vectors' lengths.
  // This margin is about 450 ulps of that product; the 1-norms it is taken
  // of are at least the lengths.
  static constexpr double kRelativeMargin = 1e-13;
  struct Plane {
    glm::dvec3 normal;  // inwards
    double scale;       // at least |normal|
    double margin = 0.0;            // a side below it is outside (MissesBox, Misses)
    std::array<uint8_t, 3> pick{};  // per axis, the box corner furthest inside: 0 lo, 1 hi
  };
  struct Sides {
    bool usable = true;
    absl::InlinedVector<Plane, 4> planes;
  };

  static double Norm1(const glm::dvec3& x) { return std::fabs(x.x) + std::fabs(x.y) + std::fabs(x.z); }

  // Each light triangle's three planes.
  void TrianglePlanes(const std::vector<glm::dvec3>& light, const std::vector<LightTriangle>& triangles) {
    for (const LightTriangle& t : triangles) {
      Sides sides;
      for (int e = 0; e < 3; ++e) {
        const glm::dvec3 a = light[t.v[e]] - p_, b = light[t.v[(e + 1) % 3]] - p_, c = light[t.v[(e + 2) % 3]] - p_;
        glm::dvec3 normal = glm::cross(a, b);
        const double scale = Norm1(a) * Norm1(b);
        // Orient inwards by the opposite vertex; too close to call: no cull.
        const double inside = glm::dot(normal, c);
        if (!(std::fabs(inside) > kRelativeMargin * scale * Norm1(c))) {
          sides.usable = false;
          break;
        }
        if (inside < 0) normal = -normal;
        sides.planes.push_back({normal, scale});
      }
      triangle_sides_.push_back(std::move(sides));
    }
  }

  // The outline's planes, when each has every light vertex but its edge's
  // clearly inside. False (and none kept) otherwise.
  bool OutlinePlanes(const std::vector<glm::dvec3>& light) {
    const size_t n = light.size();
    if (n > kMaxOutlineVertices) return false;
    Sides outline;
    for (size_t e = 0; e < n; ++e) {
      const size_t f = (e + 1) % n;
      const glm::dvec3 a = light[e] - p_, b = light[f] - p_;
      glm::dvec3 normal = glm::cross(a, b);
      const double scale = Norm1(a) * Norm1(b);
      int sign = 0;
      for (size_t c = 0; c < n; ++c) {
        if (c == e || c == f) continue;
        const glm::dvec3 y = light[c] - p_;
        const double inside = glm::dot(normal, y);
        if (!(std::fabs(inside) > kRelativeMargin * scale * Norm1(y))) return false;
        const int side = inside > 0 ? 1 : -1;
        if (sign != 0 && side != sign) return false;  // not supporting: concave here
        sign = side;
      }
      if (sign < 0) normal = -normal;
      outline.planes.push_back({normal, scale});
    }
    triangle_sides_.push_back(std::move(outline));
    return true;
  }

  // Whether, in every set of planes, some plane has the tested thing
  // outside (and there is a set at all).
  template <typename Outside>
  bool OutsideEverySet(const Outside& outside) const {
    for (const Sides& sides : triangle_sides_) {
      if (!sides.usable) return false;
      if (!std::any_of(sides.planes.begin(), sides.planes.end(), outside)) return false;
    }
    return !triangle_sides_.empty();
  }

  static constexpr size_t kMaxOutlineVertices = 16;
  bool enabled_;
  glm::dvec3 p_, lo_, hi_;
  std::vector<Sides> triangle_sides_;  // the outline's planes alone, or each light triangle's
};

bool LightTree::StoresAnswer(const QueryPoint& q, bool want_polygons) const {
  const AnswerKey key = KeyOf(q, want_polygons);
  std::shared_lock lock(answers_mutex);
  return answers.contains(key);
}

StatusOr<PointVisibility> LightTree::Query(const QueryPoint& q, bool want_polygons, const StopToken& stop) {
  const AnswerKey key = KeyOf(q, want_polygons);
  {
    std::shared_lock lock(answers_mutex);
    if (auto it = answers.find(key); it != answers.end()) {
      queries.fetch_add(1, std::memory_order_relaxed);
      hits.fetch_add(1, std::memory_order_relaxed);
      answers_reused.fetch_add(1, std::memory_order_relaxed);
      return it->second.Answer();
    }
  }
  StatusOr<PointVisibility> answer = Compute(q, want_polygons, stop);
  if (answer.ok()) {
    const size_t bytes = AnswerBytes(*answer);
    std::unique_lock lock(answers_mutex);
    if (answer_bytes + bytes <= max_answer_bytes && answers.try_emplace(key, StoredAnswer::From(*answer)).second) {
      answer_bytes += bytes;
      answer_bytes_now.store(answer_bytes, std::memory_order_relaxed);
    }
  }
  return answer;
}

namespace {

// The occluder that last hid a whole light from this thread, and its tree
// (see HiddenByLastCover).
thread_local struct {
  const LightTree* tree = nullptr;
  uint32_t id = 0;
} t_last_cover;

}  // namespace

StatusOr<glm::dvec3> LightTree::LocalPosition(const QueryPoint& q) const {
  VISQ_RETURN_IF_ERROR(ValidateQueryPoint(q, "point"));
  const glm::dvec3 p_local = q.position - origin;
  if (receiver_box) {
    const auto& [lo, hi] = *receiver_box;
    for (int i = 0; i < 3; ++i) {
      if (p_local[i] < lo[i] || p_local[i] > hi[i]) {
        return absl::OutOfRangeError("point.position: outside the tree's receiver_bounds");
      }
    }
  }
  return p_local;
}

bool LightTree::HiddenByLastCover(const glm::dvec3& p_local, const Receiver& receiver) const {
  if (t_last_cover.tree != this || t_last_cover.id >= far.size() + near.size() ||
      IsReceiver(t_last_cover.id, receiver)) {
    return false;
  }
  const uint32_t* t = OccluderVertices(t_last_cover.id);
  const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
  return TestOccluder(p_local, v).cover.all;
}

bool LightTree::GatherCandidates(Scratch& s, const glm::dvec3& p_local, const Receiver& receiver,
                                 const PyramidCull& cull, const std::vector<Fragment>& pending, Candidates* out) {
  std::vector<Blocker> blockers;
  uint64_t blocked_vertices = 0;
  const uint32_t far_count = static_cast<uint32_t>(far.size());
  {
    std::vector<uint32_t> ids;
    index.Collect([&](const glm::dvec3& lo, const glm::dvec3& hi) { return cull.MissesBox(lo, hi); }, &ids);
    for (const uint32_t id : ids) {
      const bool is_far = id < far_count;
      if (is_far && !classify_points) continue;  // the tree decides
      if (IsReceiverTriangle(id, receiver)) continue;
      const uint32_t* t = OccluderVertices(id);
      const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
      if (cull.Misses(v)) continue;
      // The receiver's plane is tested on the few that pass the culls (an
      // occluder that misses the light is dropped either way).
      if (s.penumbra_tree == this) {
        if (is_far) {
          // Far ones are used only by the direct route (the tree's descent
          // meets them in its leaves), which tests them as near ones.
          out->any_far = true;
          out->far.push_back(id);
        } else {
          if (InReceiverPlane(id, receiver)) continue;
          out->near.push_back(id - far_count);
        }
        out->untested = true;
        continue;
      }
      if (!classify_points) {
        if (ShadowMissesLight(p_local, v) || InReceiverPlane(id, receiver)) continue;
      } else {
        const OccluderTest test = TestOccluder(p_local, v);
        if (test.misses || InReceiverPlane(id, receiver)) continue;
        const Cover& cover = test.cover;
        if (cover.all) {
          t_last_cover.tree = this;
          t_last_cover.id = id;
          return true;
        }
        if (cover.mask != 0) {
          blockers.push_back({id, std::popcount(cover.mask)});
          blocked_vertices |= cover.mask;
        }
      }
      if (is_far) {
        out->any_far = true;
        out->far.push_back(id);
      } else {
        out->near.push_back(id - far_count);
      }
    }
  }
  if (!classify_points) {
    out->any_far = !far.empty();
  } else if (!out->any_far && out->near.empty()) {
    wholly_visible.fetch_add(1, std::memory_order_relaxed);
  } else if (out->far.size() + out->near.size() <= direct_candidates) {
    out->direct = true;
    subtracted_directly.fetch_add(1, std::memory_order_relaxed);
  } else if (light_local.size() <= 64 && blocked_vertices == (~uint64_t{0} >> (64 - light_local.size()))) {
    if (HiddenByFewBlockers(s, pending, &blockers)) return true;
  }

  return false;
}

LightTree::Scratch& LightTree::ThreadScratch() {
  thread_local Scratch scratch;
  return scratch;
}

StatusOr<PointVisibility> LightTree::Compute(const QueryPoint& q, bool want_polygons, const StopToken& stop) {
  VISQ_ASSIGN_OR_RETURN(const glm::dvec3 p_local, LocalPosition(q));
  std::optional<glm::dvec3> normal = q.normal;
  queries.fetch_add(1, std::memory_order_relaxed);
  PointVisibility result;

  Scratch& s = ThreadScratch();
  s.Reset();
  s.FitTree(vertices.size(), far.size() + near.size());
  s.stop = &stop;
  s.p = s.Add([&] { return XPoint::Input(p_local); });
  // A light seen from behind (or edge-on) gives nothing.
  if (EuclidSide(*s.p, *light_plane) <= 0) {
    hits.fetch_add(1, std::memory_order_relaxed);
    return result;
  }
  const Receiver receiver = ReceiverOf(q.receiver_triangle);
  if (!normal && q.receiver_triangle) {
    // A triangle containing P is always near (never culled, never
    // separated from the receivers), so its vertices are at hand.
    if (const NearOccluder* n = receiver.near) {
      const glm::dvec3 a = vertices[n->v[0]], b = vertices[n->v[1]], c = vertices[n->v[2]];
      const glm::dvec3 g = glm::cross(b - a, c - a);
      if (g != glm::dvec3(0.0)) normal = g;
    }
  }

  // Start from the light's pieces, clipped to the receiver's hemisphere.
  std::vector<Fragment> pending;
  const XPlane* horizon = normal ? s.Add([&] { return XPlane::PointNormal(*s.p, *normal); }) : nullptr;
  for (uint32_t t = 0; t < light_pieces.size(); ++t) {
    Fragment f;
    f.piece = t;
    const LightPiece& piece = light_pieces[t];
    for (size_t i = 0; i < piece.v.size(); ++i) {
      f.v.push_back({&light_points[piece.v[i]], static_cast<int32_t>(i), nullptr});
    }
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
  if (!line_boxes) s.line_box_sign = 0;

  // Classify first (GatherCandidates): most points end there.
  if (classify_points && HiddenByLastCover(p_local, receiver)) {
    hits.fetch_add(1, std::memory_order_relaxed);
    wholly_hidden.fetch_add(1, std::memory_order_relaxed);
    return result;
  }
  if (classify_points && HiddenByRememberedBlockers(s, pending, receiver)) {
    hits.fetch_add(1, std::memory_order_relaxed);
    wholly_hidden.fetch_add(1, std::memory_order_relaxed);
    hidden_by_remembered_blockers.fetch_add(1, std::memory_order_relaxed);
    return result;
  }
  const PyramidCull cull(p_local, light_local, light_triangles, index.Bounds(), cull_pyramid);
  Candidates candidates;
  if (GatherCandidates(s, p_local, receiver, cull, pending, &candidates)) {
    hits.fetch_add(1, std::memory_order_relaxed);
    wholly_hidden.fetch_add(1, std::memory_order_relaxed);
    return result;
  }

  // Push the fragments down the shared tree.
  std::vector<Fragment> visible;
  bool refined = false;
  if (!candidates.any_far || candidates.direct) {
    visible = std::move(pending);
  } else {
    VISQ_RETURN_IF_ERROR(DescendTree(s, pending, cull, p_local, &visible, &refined));
  }
  if (!refined) hits.fetch_add(1, std::memory_order_relaxed);

  // Subtract the near occluders, clipped to the slab between the light
  // plane and the plane through P parallel to it (and, on the direct
  // route, the far candidates whole).
  std::vector<uint32_t> subtract;  // occluder ids: far ones first, then near ones
  if (candidates.direct) subtract = std::move(candidates.far);
  const uint32_t far_count = static_cast<uint32_t>(far.size());
  for (const uint32_t candidate : candidates.near) subtract.push_back(far_count + candidate);
  double left_out_area = 0.0;
  if (!subtract.empty() && !visible.empty()) {
    if (shadow_tolerance > 0.0) left_out_area = LeaveOutSmallShadows(p_local, &subtract);
    const XPlane* slab_top = nullptr;
    // Largest first: in index order a penumbra under a dense mesh was cut
    // into thousands of pieces, and nearest first was little better
    // (docs/exact-method-notes.md).
    SortLargestFirst(p_local, &subtract);
    std::vector<uint32_t> cutting;
    SubtractOccluders(s, &visible, subtract, &slab_top, SIZE_MAX, quadrilaterals, &cutting,
                      candidates.untested);
    if (!s.stopped.ok()) return s.stopped;
    // Only the light itself was cut on these routes, so the cutting
    // occluders alone hide it when nothing is left.
    if (visible.empty() && classify_points && (!candidates.any_far || candidates.direct)) {
      RememberBlockers(s, &cutting);
    }
  }

  // Integrate over the visible polygons.
  PointVisibility answer = Integrate(visible, p_local, normal, want_polygons, left_out_area);
  s.penumbra_tree =
      answer.visible_area_fraction > 0.0 && answer.visible_area_fraction < 1.0 ? this : nullptr;
  return answer;
}

Status LightTree::DescendTree(Scratch& s, std::vector<Fragment>& pending, const PyramidCull& cull,
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
    VISQ_DCHECK_LT(size_t(id), nodes.size());
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
        const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
        if (cull.Misses(v)) continue;
        if (fragment_box) {
          const XPoint* corners[3] = {&Vertex(s, t[0]), &Vertex(s, t[1]), &Vertex(s, t[2])};
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
      EdgeLine line{&Vertex(s, node.a), &Vertex(s, node.b)};
      const int32_t c0 = node.child[0], c1 = node.child[1];
      VISQ_DCHECK_LT(size_t(c0), nodes.size());
      VISQ_DCHECK_LT(size_t(c1), nodes.size());
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

double LightTree::ShadowAreaBound(const glm::dvec3& p, double h_light, const glm::dvec3 (&v)[3]) const {
  glm::dvec3 u[3];  // the vertices' projections, from p
  double reach = 0.0;
  for (int i = 0; i < 3; ++i) {
    const glm::dvec3 d = v[i] - p;
    const double h = glm::dot(light_unit_normal, d);
    // At a thousandth of p's distance to the light the rounding of h cannot
    // flip its sign, and every point of the triangle lies on the light's
    // side of p, where the projection maps it to a triangle.
    if (!(h >= 1e-3 * h_light)) return std::numeric_limits<double>::infinity();
    u[i] = d * (h_light / h);
    reach = std::max(reach, std::max({std::fabs(u[i].x), std::fabs(u[i].y), std::fabs(u[i].z)}));
  }
  const double area = 0.5 * glm::length(glm::cross(u[1] - u[0], u[2] - u[0]));
  // The cross product's rounding is a few ulps of reach^2 times the
  // relative error of the projections (a few ulps, times reach / h_light
  // where a vertex is seen at a grazing angle): 1e-12 is some hundred times
  // that. The 1.01 covers a light whose vertices stand up to 1e-6 of its
  // diameter off its plane (PrepareLight's limit) at h_light of at least a
  // thousandth of the diameter.
  return 1.01 * area + 1e-12 * reach * reach * (1.0 + reach / h_light);
}

double LightTree::LightPlaneDistance(const glm::dvec3& p) const {
  double h = std::numeric_limits<double>::infinity();
  for (const glm::dvec3& l : light_local) h = std::min(h, glm::dot(light_unit_normal, l - p));
  return h;
}

double LightTree::LeaveOutSmallShadows(const glm::dvec3& p, std::vector<uint32_t>* ids) const {
  const double h_light = LightPlaneDistance(p);
  if (!(h_light > 1e-3 * light_diameter)) return 0.0;
  const double budget = shadow_tolerance * light_area;
  std::vector<std::pair<double, uint32_t>> small;  // (area bound, occluder id)
  for (const uint32_t id : *ids) {
    const uint32_t* t = OccluderVertices(id);
    const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
    const double area = ShadowAreaBound(p, h_light, v);
    if (area <= budget) small.emplace_back(area, id);
  }
  std::sort(small.begin(), small.end());
  double sum = 0.0;
  size_t left_out = 0;
  while (left_out < small.size() && sum + small[left_out].first <= budget) sum += small[left_out++].first;
  if (left_out == 0) return 0.0;
  std::vector<uint32_t> out(left_out);
  for (size_t i = 0; i < left_out; ++i) out[i] = small[i].second;
  std::sort(out.begin(), out.end());
  std::erase_if(*ids, [&](uint32_t id) { return std::binary_search(out.begin(), out.end(), id); });
  // The sum's own rounding: at most left_out ulps of it.
  return sum * (1.0 + 1e-15 * static_cast<double>(left_out + 1));
}

PointVisibility LightTree::Integrate(const std::vector<Fragment>& visible, const glm::dvec3& p_local,
                                     const std::optional<glm::dvec3>& normal, bool want_polygons,
                                     double left_out_area) const {
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
  if (left_out_area > 0.0) {
    // Seen from P, a light-plane area A spans a solid angle of at most
    // A / h^2 (the density cos / r^2 = h / r^3 is largest at r = h), and
    // its irradiance at most the radiance times that.
    const double h_light = LightPlaneDistance(p_local);
    const double left_out_solid_angle = 1.01 * left_out_area / (h_light * h_light);
    result.visible_area_fraction_error = std::min(result.visible_area_fraction, left_out_area / light_area);
    result.visible_solid_angle_fraction_error =
        total_solid_angle > 0.0
            ? std::min(result.visible_solid_angle_fraction, left_out_solid_angle / total_solid_angle)
            : 0.0;
    result.irradiance_error = std::min(result.irradiance, radiance * left_out_solid_angle);
  }
  return result;
}

}  // namespace visq::exact::detail
