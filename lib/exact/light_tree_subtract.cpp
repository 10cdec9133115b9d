// The polygon machinery of a query: light fragments split by planes through
// the query point and occluder edges, near occluders clipped to the slab under
// the point, and occluders subtracted from the fragments.
#include "exact/light_visibility_impl.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <limits>
#include <mutex>

#include "common/check.h"

namespace visq::exact::detail {

bool LightTree::StopNow(Scratch& s) {
  if (!s.stopped.ok()) return true;
  if (s.stop == nullptr || s.stop_countdown-- > 0) return false;
  s.stop_countdown = kStopStride;
  s.stopped = s.stop->Check("light visibility query");
  return !s.stopped.ok();
}

LightTree::EdgePlaneRef LightTree::EdgePlane(Scratch& s, const XPoint& a, const XPoint& b) const {
  const XPoint* lo = std::less<const XPoint*>()(&a, &b) ? &a : &b;
  const XPoint* hi = lo == &a ? &b : &a;
  auto [it, inserted] = s.edge_planes.try_emplace({lo, hi}, nullptr);
  if (inserted) {
    const XPlane* plane = s.Add([&] { return XPlane::ThroughPoints(*s.p, *lo, *hi); });
    it->second = plane->Degenerate() ? nullptr : plane;
  }
  return {it->second, lo == &a ? 1 : -1};
}

bool LightTree::OnPlaneByDefinition(const XPoint& x, const XPlane* plane) {
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

bool LightTree::OnPlaneByInputs(const XPoint& x, const XPlane& plane) {
  using PK = XPlane::Kind;
  using XK = XPoint::Kind;
  if (plane.kind != PK::kThroughPoints) return false;
  const XPoint* apex = plane.points[0];
  const XPoint* c = plane.points[1];
  const XPoint* d = plane.points[2];
  if (apex->kind != XK::kInput || c->kind != XK::kInput || d->kind != XK::kInput) return false;
  const glm::dvec3& p = apex->input;
  // The planes x lies on by definition that pass through the apex and two
  // more input points (edge planes through P).
  const XPlane* own[3];
  int count = 0;
  const int defining = x.kind == XK::kLinePlane ? 1 : x.kind == XK::kThreePlanes ? 3 : 0;
  for (int i = 0; i < defining; ++i) {
    const XPlane* q = x.planes[i];
    if (q->kind == PK::kThroughPoints && q->points[0] == apex && q->points[1]->kind == XK::kInput &&
        q->points[2]->kind == XK::kInput) {
      own[count++] = q;
    }
  }
  // Whether x lies on the plane through P and the line (a, b): on the line
  // itself first (exact 2D tests, which settle the shared coordinates of
  // axis-aligned edges at once), then the exact test through P, which
  // settles a zero only in GMP.
  const auto on_plane = [&](const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& y) {
    if (Orient2d(a, b, y, 0, 1) == 0 && Orient2d(a, b, y, 1, 2) == 0 && Orient2d(a, b, y, 2, 0) == 0) return true;
    return Orient3d(p, a, b, y) == 0;
  };
  // One of them is `plane` itself, through another edge on its line.
  for (int i = 0; i < count; ++i) {
    const glm::dvec3 &a = own[i]->points[1]->input, &b = own[i]->points[2]->input;
    if (on_plane(a, b, c->input) && on_plane(a, b, d->input)) return true;
  }
  // Two of them meet along the line from P through a vertex v of one that
  // lies on the other (an edge ending on another's line, as where a bar
  // meets an upright): x is on that line, and on `plane` when v is.
  if (count == 2) {
    for (int i = 0; i < 2; ++i) {
      const XPlane* q = own[i];
      const XPlane* r = own[1 - i];
      for (int k = 1; k < 3; ++k) {
        const glm::dvec3& v = q->points[k]->input;
        if (v == p) continue;
        if (!on_plane(r->points[1]->input, r->points[2]->input, v)) continue;
        if (on_plane(c->input, d->input, v)) return true;
      }
    }
  }
  return false;
}

LightTree::EdgePlaneRef LightTree::PlaneOf(Scratch& s, EdgeLine& e) const {
  if (!e.has_plane) {
    e.plane = EdgePlane(s, *e.a, *e.b);
    e.has_plane = true;
  }
  return e.plane;
}

int LightTree::LineSide(Scratch& s, EdgeLine& e, const XPoint& x) const {
  using K = XPoint::Kind;
  if (e.a->kind == K::kInput && e.b->kind == K::kInput) {
    if (!e.fan) e.fan.emplace(s.p->input, e.a->input, e.b->input);
    if (x.kind == K::kInput) return -e.fan->Side(x.input);
    // Most lines only test the fragments (a third ever cut one): their
    // exact planes are made when the fan's filter cannot settle a side.
    if (!e.fan_filter) e.fan_filter = e.fan->Filter();
    const int fast = FastSignOfDot(*e.fan_filter, x.fast);
    if (fast != kUncertain) return -fast * x.w_sign;
  }
  return PlaneLineSide(s, e, x);
}

int LightTree::PlaneLineSide(Scratch& s, EdgeLine& e, const XPoint& x) const {
  const EdgePlaneRef ref = PlaneOf(s, e);
  if (ref.plane == nullptr) return 0;
  // The filter first: it settles nearly every vertex, and it never settles
  // one that lies on the plane by its definition (an exact zero).
  const int fast = FastSignOfDot(ref.plane->fast, x.fast);
  if (fast != kUncertain) return -ref.sign * fast * x.w_sign * ref.plane->o_sign;
  if (OnPlaneByDefinition(x, ref.plane)) return 0;
  if (OnPlaneByInputs(x, *ref.plane)) return 0;
  return -ref.sign * EuclidSideSlow(x, *ref.plane);
}

LightTree::Straddle LightTree::EdgeStraddle(Scratch& s, const Fragment& f, EdgeLine& e) const {
  Straddle straddle;
  ReadyFan(s, e);
  for (const FVert& v : f.v) {
    const int side = QuickLineSide(s, e, *v.point);
    straddle.any_positive |= side > 0;
    straddle.any_negative |= side < 0;
    if (straddle.any_positive && straddle.any_negative) break;  // the rest cannot change the verdict
  }
  return straddle;
}

bool LightTree::EdgeSides(Scratch& s, const Fragment& f, EdgeLine& e, std::vector<int>* signs) const {
  signs->assign(f.v.size(), 0);
  bool any = false;
  ReadyFan(s, e);
  for (size_t i = 0; i < f.v.size(); ++i) {
    (*signs)[i] = QuickLineSide(s, e, *f.v[i].point);
    any |= (*signs)[i] != 0;
  }
  return any;
}

bool LightTree::NearOccluderEdges(Scratch& s, const NearOccluder& n, const XPlane& slab_top, Edges* edges,
                                  Corners* corners) const {
  const XPoint* v[3] = {&Vertex(s, n.v[0]), &Vertex(s, n.v[1]), &Vertex(s, n.v[2])};
  int top_side[3];
  bool any_below_top = false;
  for (int i = 0; i < 3; ++i) {
    top_side[i] = TopSide(s, n.v[i], slab_top);
    any_below_top |= top_side[i] < 0;
  }
  if (!any_below_top) return false;  // nothing strictly between
  // The edge from a vertex to the next: a part of the triangle's edge
  // orig_edge, or on the cut by the light plane or by the slab's top.
  constexpr int kLightCut = -1, kTopCut = -2;
  struct CV { const XPoint* point; int orig_edge; };
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
      } else if (!cut) {
        sides[i] = -top_side[poly[i].orig_edge];  // still the triangle, in its order
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
      const int cut_edge = pass == 0 ? kLightCut : kTopCut;
      if (sc == 0) clipped.push_back({poly[i].point, sn < 0 ? cut_edge : poly[i].orig_edge});
      if ((sc > 0 && sn < 0) || (sc < 0 && sn > 0)) {
        // Crossing edges of the second pass are parts of triangle
        // edges too: the first cut lies in the light plane, strictly
        // on the kept side of the second.
        const int e = poly[i].orig_edge;
        VISQ_CHECK(e >= 0);
        const XPoint* x = s.Add([&] { return XPoint::LinePlane(*v[e], *v[(e + 1) % 3], plane); });
        clipped.push_back({x, sc > 0 ? cut_edge : e});
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
    } else if (e == kLightCut) {
      edges->emplace_back(poly[i].point, poly[(i + 1) % poly.size()].point);
    }
    // An edge on the slab's top has no line: the top passes through P, so
    // the plane through P and the edge is the top itself, and every point
    // of the light lies on its inner side. The shadow on the light's plane
    // is the wedge of the other edges.
  }
  if (!cut) return true;  // the whole triangle: ShadowMissesLight has passed it
  // Skip clipped occluders whose shadow misses the whole light: some edge
  // line has no light vertex on its inner side. Sides are linear over
  // each light triangle, so vertices decide.
  std::vector<EdgeLine> lines;
  lines.reserve(edges->size());
  for (const auto& [a, b] : *edges) lines.emplace_back(a, b);
  const int inside = InsideSign(s, lines, *edges);
  if (inside == 0) return false;  // seen edge on
  for (EdgeLine& line : lines) {
    bool any_inside = false;
    for (size_t i = 0; i < light_points.size() && !any_inside; ++i) {
      any_inside = LineSide(s, line, light_points[i]) == inside;
    }
    if (!any_inside) return false;
  }
  return true;
}

int LightTree::InsideSign(Scratch& s, std::vector<EdgeLine>& lines, const Edges& edges) const {
  int inside = 0;
  for (size_t j = 1; j < edges.size() && inside == 0; ++j) {
    inside = LineSide(s, lines[0], *edges[j].first);
    if (inside == 0) inside = LineSide(s, lines[0], *edges[j].second);
  }
  return inside;
}

bool LightTree::OccluderEdges(Scratch& s, uint32_t id, const XPlane** slab_top, Edges* edges, Corners* corners) const {
  const uint32_t far_count = static_cast<uint32_t>(far.size());
  if (id < far_count) {
    const uint32_t* t = far[id].v;
    *corners = {&Vertex(s, t[0]), &Vertex(s, t[1]), &Vertex(s, t[2])};
    *edges = {{(*corners)[0], (*corners)[1]}, {(*corners)[1], (*corners)[2]}, {(*corners)[2], (*corners)[0]}};
    return true;
  }
  if (*slab_top == nullptr) *slab_top = s.Add([&] { return XPlane::ParallelThrough(*light_plane, *s.p); });
  return NearOccluderEdges(s, near[id - far_count], **slab_top, edges, corners);
}

bool LightTree::QuadWithNeighbour(Scratch& s, const XPlane** slab_top, uint32_t id, OccluderPolygon* quad,
                                  uint32_t* neighbour) const {
  const uint32_t far_count = static_cast<uint32_t>(far.size());
  const uint32_t occluder_count = far_count + static_cast<uint32_t>(near.size());
  // Far occluders pair with far ones, near with near: a far one is
  // subtracted whole, a near one only when nothing of it is clipped.
  const bool is_far = id < far_count;
  const auto is_candidate = [&](uint32_t other) {
    return other < occluder_count && (other < far_count) == is_far && s.occluder_marks[other].stamp == s.stamp &&
           s.occluder_marks[other].state == Scratch::kCandidate;
  };
  if (!(is_candidate(id + 1) || is_candidate(id - 1))) return false;
  // Strictly inside the slab: in the light's open front (a near one: a
  // far one is subtracted whole, and never lies behind the light) and
  // strictly below the plane through P parallel to the light (nothing to
  // clip; and the four corners, on one side of a plane through P, are seen
  // from P in one chart, where the turns below decide convexity).
  const auto inside_slab = [&](uint32_t occluder) {
    if (occluder >= far_count) {
      const NearOccluder& n = near[occluder - far_count];
      if (n.light_side[0] <= 0 || n.light_side[1] <= 0 || n.light_side[2] <= 0) return false;
    }
    if (*slab_top == nullptr) *slab_top = s.Add([&] { return XPlane::ParallelThrough(*light_plane, *s.p); });
    for (int i = 0; i < 3; ++i) {
      if (TopSide(s, OccluderVertices(occluder)[i], **slab_top) >= 0) return false;
    }
    return true;
  };
  const uint32_t* first = OccluderVertices(id);
  if (!inside_slab(id)) return false;
  const glm::dvec3& p = s.p->input;
  const auto orient = [&](uint32_t a, uint32_t b, uint32_t c) {
    return Orient3d(p, vertices[a], vertices[b], vertices[c]);
  };
  const int o = orient(first[0], first[1], first[2]);
  if (o == 0) return false;
  for (const uint32_t other : {id + 1, id - 1}) {
    if (!is_candidate(other)) continue;
    const uint32_t* n = OccluderVertices(other);
    // The edge (u, v) of the first triangle that n lies across, and n's
    // third vertex w. The union is the quadrilateral (u, w, v, t) when it
    // turns with sign o at every corner. A zero turn at u puts P's view of
    // u on the segment from t to w (the turns at the other corners are
    // strict), so u is dropped and the union is the triangle (t, w, v); v
    // likewise.
    for (int k = 0; k < 3; ++k) {
      const uint32_t u = first[k], v = first[(k + 1) % 3], t = first[(k + 2) % 3];
      int on_edge = 0;
      uint32_t w = 0;
      for (int i = 0; i < 3; ++i) {
        const uint32_t x = n[i];
        if (x == u || x == v) {
          ++on_edge;
        } else {
          w = x;
        }
      }
      if (on_edge != 2 || w == t) continue;
      if (!inside_slab(other) || orient(u, w, v) != o) break;
      const int turn_u = orient(t, u, w), turn_v = orient(w, v, t);
      if ((turn_u != o && turn_u != 0) || (turn_v != o && turn_v != 0)) break;
      quad->clear();
      if (turn_u != 0) quad->push_back(u);
      quad->push_back(w);
      if (turn_v != 0) quad->push_back(v);
      quad->push_back(t);
      s.occluder_marks[other].state = Scratch::kTaken;
      *neighbour = other;
      return true;
    }
  }
  return false;
}

bool LightTree::HiddenByFewBlockers(Scratch& s, const std::vector<Fragment>& light,
                                    std::vector<Blocker>* blockers) const {
  std::stable_sort(blockers->begin(), blockers->end(),
                   [](const Blocker& x, const Blocker& y) { return x.vertices > y.vertices; });
  const XPlane* slab_top = nullptr;
  std::vector<Fragment> left = light;
  std::vector<uint32_t> ids;
  for (const Blocker& blocker : *blockers) ids.push_back(blocker.id);
  std::vector<uint32_t> cutting;
  SubtractOccluders(s, &left, ids, &slab_top, kFewBlockers, quadrilaterals, &cutting);
  if (!left.empty() || !s.stopped.ok()) return false;
  RememberBlockers(s, &cutting);
  return true;
}

void LightTree::RememberBlockers(Scratch& s, std::vector<uint32_t>* ids) const {
  if (ids->empty() || ids->size() > kRememberedBlockers) return;
  if (s.blockers_tree != this) s.blocker_sets.clear();
  s.blockers_tree = this;
  if (s.blocker_sets.size() == kRememberedSets) s.blocker_sets.pop_back();
  s.blocker_sets.insert(s.blocker_sets.begin(), {s.p->input, {}});
  s.blocker_sets.front().ids.swap(*ids);
  s.most_recent_failed = false;
}

bool LightTree::HiddenByRememberedBlockers(Scratch& s, const std::vector<Fragment>& light,
                                           const Receiver& receiver) const {
  const glm::dvec3& p = s.p->input;
  // The step from the thread's previous point sizes "nearby": a frame's
  // neighbouring pixel, in the row or the row above.
  const glm::dvec3 step = p - s.previous_p;
  const double reach = 16.0 * glm::dot(step, step);  // four steps, squared
  s.previous_p = p;
  if (s.blockers_tree != this || s.blocker_sets.empty()) return false;
  size_t nearest = 0;
  double nearest_distance = reach;
  for (size_t i = 1; i < s.blocker_sets.size(); ++i) {
    const glm::dvec3 d = s.blocker_sets[i].p - p;
    const double distance = glm::dot(d, d);
    if (distance <= nearest_distance) {
      nearest = i;
      nearest_distance = distance;
    }
  }
  const size_t occluders = far.size() + near.size();
  const uint64_t all_vertices = light_local.size() >= 64 ? ~uint64_t{0} : (uint64_t{1} << light_local.size()) - 1;
  const size_t tries[2] = {0, nearest};
  for (size_t k = 0; k < (nearest != 0 ? 2u : 1u); ++k) {
    const size_t set = tries[k];
    // The most recent set, once it has failed, waits for a newer one (the
    // points after a hidden run are mostly not hidden).
    if (set == 0 && s.most_recent_failed) continue;
    std::vector<uint32_t>& ids = s.blocker_sets[set].ids;
    if (std::any_of(ids.begin(), ids.end(),
                    [&](uint32_t id) { return id >= occluders || IsReceiver(id, receiver); })) {
      if (set == 0) s.most_recent_failed = true;
      continue;
    }
    // A light vertex whose segment from P crosses none of the set's
    // triangles leaves some of the light to see: a penumbra point after a
    // hidden run ends here, before any subtraction.
    uint64_t covered = 0;
    for (size_t i = 0; i < ids.size() && covered != all_vertices; ++i) {
      const uint32_t* t = OccluderVertices(ids[i]);
      const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
      covered |= CoveredLightVertices(p, v).mask;
    }
    if (covered != all_vertices) {
      if (set == 0) s.most_recent_failed = true;
      continue;
    }
    std::vector<Fragment> left = light;
    const XPlane* slab_top = nullptr;
    SubtractOccluders(s, &left, ids, &slab_top, SIZE_MAX, quadrilaterals);
    if (!s.stopped.ok()) return false;
    if (left.empty()) {
      if (set != 0) {
        std::rotate(s.blocker_sets.begin(), s.blocker_sets.begin() + static_cast<ptrdiff_t>(set),
                    s.blocker_sets.begin() + static_cast<ptrdiff_t>(set) + 1);
        s.most_recent_failed = false;
      }
      return true;
    }
    s.blocker_sets.erase(s.blocker_sets.begin() + static_cast<ptrdiff_t>(set));
    if (set == 0) s.most_recent_failed = false;  // the next one is tried afresh
    return false;
  }
  return false;
}

const XPoint* LightTree::Meet(Scratch& s, const Fragment& f, const FVert& from, const XPlane& plane) const {
  VISQ_DCHECK_LT(size_t(f.piece), light_pieces.size());
  const LightPiece& piece = light_pieces[f.piece];
  const void* support = from.light_edge >= 0 ? static_cast<const void*>(&piece.v[from.light_edge]) : from.plane;
  auto [it, inserted] = s.meets.try_emplace({support, &plane}, nullptr);
  if (!inserted) return it->second;
  if (from.light_edge >= 0) {
    const XPoint& a = light_points[piece.v[from.light_edge]];
    const XPoint& b = light_points[piece.v[(from.light_edge + 1) % piece.v.size()]];
    it->second = s.Add([&] { return XPoint::LinePlane(a, b, plane); });
  } else {
    it->second = s.Add([&] { return XPoint::ThreePlanes(*piece.plane, *from.plane, plane); });
  }
  return it->second;
}

void LightTree::Split(Scratch& s, const Fragment& f, const std::vector<int>& sg, const XPlane& plane,
                      Fragment* pos, Fragment* neg) const {
  VISQ_DCHECK_EQ(sg.size(), f.v.size());
  pos->v.clear();
  neg->v.clear();
  pos->box_state = neg->box_state = 0;
  pos->piece = neg->piece = f.piece;
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

bool LightTree::Clip(Scratch& s, Fragment* f, const XPlane& plane, int flip) const {
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

bool LightTree::HasLineBox(const Scratch& s, Fragment& f) const {
  if (f.box_state == 0) {
    absl::InlinedVector<const XPoint*, 8> xs;
    for (const FVert& fv : f.v) xs.push_back(fv.point);
    f.box_state = LineBoxOf(s, xs, &f.box) ? 1 : -1;
  }
  return f.box_state == 1;
}

bool LightTree::ApartFrom(const Scratch& s, Fragment& f, const LineBox& shadow) const {
  return HasLineBox(s, f) && f.box.Apart(shadow);
}

// Inline: it runs once per fragment a shadow meets, in Subtract's two loops
// (out of line, Sponza's queries took 0.4 % more instructions).
VISQ_EXACT_INLINE LightTree::Against LightTree::FragmentAgainst(Scratch& s, Fragment& f, std::vector<EdgeLine>& lines, int inside,
                                               uint32_t* straddled) const {
  // Outside when some edge line has none of its vertices on the inside
  // (touching it at most): kept whole.
  *straddled = 0;
  for (size_t k = 0; k < lines.size(); ++k) {
    ReadyFan(s, lines[k]);
    const int box_side = BoxLineSide(s, f, lines[k]);
    Straddle straddle;
    if (box_side != kUncertain) {
      straddle.any_positive = box_side > 0;
      straddle.any_negative = box_side < 0;
    } else {
      straddle = EdgeStraddle(s, f, lines[k]);
    }
    const bool any_inside = inside > 0 ? straddle.any_positive : straddle.any_negative;
    const bool any_outside = inside > 0 ? straddle.any_negative : straddle.any_positive;
    if (!any_inside) return Against::kOutside;
    if (any_outside) *straddled |= uint32_t{1} << k;
  }
  // Every line it does not straddle has it, and so each of its pieces,
  // on the inside: only the straddled lines can cut it, and with none it
  // lies inside the shadow.
  return *straddled == 0 ? Against::kInside : Against::kStraddles;
}

void LightTree::CutChains(Scratch& s, std::vector<Fragment>* out, int inside) const {
  std::vector<Scratch::ChainPiece>& stack = s.subtract_stack;
  std::vector<EdgeLine>& lines = s.subtract_lines;
  std::vector<int>& sg = s.subtract_signs;
  while (!stack.empty()) {
    Scratch::ChainPiece item = std::move(stack.back());
    stack.pop_back();
    const int k = std::countr_zero(item.lines);
    const uint32_t later_lines = item.lines & (item.lines - 1);
    EdgeLine& line = lines[k];
    if (!EdgeSides(s, item.f, line, &sg)) {  // touches the edge line only: not inside
      out->push_back(std::move(item.f));
      continue;
    }
    const bool any_pos = std::any_of(sg.begin(), sg.end(), [](int x) { return x > 0; });
    const bool any_neg = std::any_of(sg.begin(), sg.end(), [](int x) { return x < 0; });
    Fragment pos, neg;
    if (any_pos && any_neg) {
      Split(s, item.f, sg, *PlaneOf(s, line).plane, &pos, &neg);
    } else {  // a piece on one side of this line: not cut by it
      (any_pos ? pos : neg) = std::move(item.f);
    }
    const bool last = later_lines == 0;
    // Continue the chain with the part on the inner side; the rest is
    // outside the occluder's shadow.
    Fragment* parts[2] = {&pos, &neg};
    for (int side = 0; side < 2; ++side) {
      Fragment& part = *parts[side];
      if (part.v.empty()) continue;
      const int sign = side == 0 ? 1 : -1;
      if (sign != inside) {
        out->push_back(std::move(part));
      } else if (!last) {
        stack.push_back({std::move(part), later_lines});
      }
      // else: inside all edges, shadowed.
    }
  }
}

bool LightTree::Subtract(Scratch& s, std::vector<Fragment>* fragments,
                         const std::vector<std::pair<const XPoint*, const XPoint*>>& edges,
                         const LineBox* shadow, FragmentGrid* grid) const {
  // A polygon has a handful of edges (a triangle clipped twice, five).
  VISQ_CHECK_LE(edges.size(), size_t{32});
  std::vector<EdgeLine>& lines = s.subtract_lines;
  lines.clear();
  for (const auto& [a, b] : edges) lines.emplace_back(a, b);
  // With no inner side, P sees the polygon edge on, and it hides no set
  // of lines of positive measure.
  const int inside = InsideSign(s, lines, edges);
  if (inside == 0) return false;
  std::vector<Fragment>& out = *fragments;
  std::vector<Scratch::ChainPiece>& stack = s.subtract_stack;
  stack.clear();
  bool cut = false;
  if (grid != nullptr) {
    // Only the fragments whose boxes meet the shadow's can be cut; the
    // others stay in place, as below, and the cut ones die in place.
    VISQ_CHECK_EQ(grid->Size(), out.size());
    std::vector<uint32_t>& meeting = s.grid_meeting;
    if (shadow != nullptr) {
      grid->Meeting(*shadow, &meeting);
    } else {
      meeting.clear();
      for (uint32_t i = 0; i < out.size(); ++i) {
        if (grid->Alive(i)) meeting.push_back(i);
      }
    }
    for (const uint32_t i : meeting) {
      uint32_t straddled = 0;
      const Against against = FragmentAgainst(s, out[i], lines, inside, &straddled);
      if (against == Against::kOutside) continue;
      grid->Remove(i);
      cut = true;
      if (against == Against::kStraddles) stack.push_back({std::move(out[i]), straddled});
    }
    CutChains(s, &out, inside);
    return cut;
  }
  // Fragments that stay whole stay in place (a fragment is a few hundred
  // bytes, and a dense mesh's penumbra has hundreds for every occluder);
  // the pieces of the cut ones are appended.
  size_t kept = 0;
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
    uint32_t straddled = 0;
    const Against against = FragmentAgainst(s, f, lines, inside, &straddled);
    if (against == Against::kOutside) {
      keep(i);
    } else if (against == Against::kStraddles) {
      stack.push_back({std::move(f), straddled});
    }
  }
  cut = kept < out.size();
  out.resize(kept);
  CutChains(s, &out, inside);
  return cut;
}

bool LightTree::UnionLineBox(const Scratch& s, std::vector<Fragment>& fragments, LineBox* box) const {
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

bool LightTree::StartFragmentGrid(Scratch& s, std::vector<Fragment>& fragments, const LineBox& all) const {
  FragmentGrid& grid = s.fragment_grid;
  if (!grid.Reset(all)) return false;
  for (uint32_t i = 0; i < fragments.size(); ++i) {
    VISQ_DCHECK_EQ(int(fragments[i].box_state), 1);
    if (!grid.Add(i, fragments[i].box)) return false;
  }
  return true;
}

bool LightTree::GridTakesNewFragments(const Scratch& s, std::vector<Fragment>& fragments, FragmentGrid& grid) const {
  for (size_t i = grid.Size(); i < fragments.size(); ++i) {
    if (!HasLineBox(s, fragments[i]) || !grid.Add(static_cast<uint32_t>(i), fragments[i].box)) return false;
  }
  return true;
}

void LightTree::DropDeadFragments(const FragmentGrid& grid, std::vector<Fragment>* fragments) {
  size_t kept = 0;
  for (size_t i = 0; i < fragments->size(); ++i) {
    // Pieces past the grid's last were never listed: alive.
    if (i < grid.Size() && !grid.Alive(static_cast<uint32_t>(i))) continue;
    if (kept != i) (*fragments)[kept] = std::move((*fragments)[i]);
    ++kept;
  }
  fragments->resize(kept);
}

size_t LightTree::SubtractOccluders(Scratch& s, std::vector<Fragment>* fragments, std::span<const uint32_t> ids,
                                    const XPlane** slab_top, size_t max_subtracted, bool quads,
                                    std::vector<uint32_t>* cutting, bool test_untested) const {
  if (quads) {
    s.FitOccluders(far.size() + near.size());
    for (const uint32_t id : ids) s.occluder_marks[id] = {s.stamp, Scratch::kCandidate};
  }
  Edges edges;
  Corners corners;
  LineBox all;
  bool all_valid = UnionLineBox(s, *fragments, &all);
  // Past kGridFragments fragments (and with every box), the fragments move
  // to the grid: the occluders are then tested against the few fragments
  // near their shadows. Every verdict is the one the whole list gives.
  VISQ_CHECK(!s.fragment_grid_in_use);  // subtractions do not nest
  FragmentGrid* grid = nullptr;
  bool grid_possible = fragment_grid;
  const auto stop_grid = [&] {
    DropDeadFragments(*grid, fragments);
    grid = nullptr;
    s.fragment_grid_in_use = false;
  };
  size_t subtracted = 0;
  OccluderPolygon quad;
  uint32_t neighbour = 0;
  for (size_t position = 0; position < ids.size(); ++position) {
    const uint32_t id = ids[position];
    // With a grid, its live fragments and the pieces it has not listed yet
    // (none between subtractions).
    VISQ_DCHECK(grid == nullptr || grid->Size() == fragments->size());
    const size_t live = grid != nullptr ? grid->Live() : fragments->size();
    if (live == 0 || subtracted == max_subtracted || StopNow(s)) break;
    // The grid pays where many candidates are left for many fragments.
    if (grid == nullptr && live >= kGridFragments && grid_possible && all_valid &&
        ids.size() - position >= 4 * live) {
      // A box the grid cannot place (not finite) keeps the list for good,
      // rather than a try per candidate.
      grid_possible = StartFragmentGrid(s, *fragments, all);
      if (grid_possible) {
        grid = &s.fragment_grid;
        s.fragment_grid_in_use = true;
        fragment_grids.fetch_add(1, std::memory_order_relaxed);
      }
    }
    if (quads) {
      if (s.occluder_marks[id].state == Scratch::kTaken) continue;  // inside an earlier quadrilateral
      s.occluder_marks[id].state = Scratch::kTaken;
    }
    LineBox shadow;
    const bool triangle_box = ShadowBoxBound(s, id, &shadow);
    // all_valid: every fragment has its box. The box around them all
    // first: one test where each fragment's is one a fragment (the grid:
    // the fragments near the shadow).
    if (all_valid && triangle_box) {
      const bool apart = grid != nullptr ? !grid->AnyMeets(shadow)
                                         : all.Apart(shadow) || std::all_of(fragments->begin(), fragments->end(),
                                                                            [&](const Fragment& f) {
                                                                              return f.box.Apart(shadow);
                                                                            });
      if (apart) continue;
    }
    if (test_untested) {
      const uint32_t* t = OccluderVertices(id);
      const glm::dvec3 v[3] = {vertices[t[0]], vertices[t[1]], vertices[t[2]]};
      if (ShadowMissesLight(s.p->input, v)) continue;
    }
    if (!OccluderEdges(s, id, slab_top, &edges, &corners)) continue;
    // An unclipped triangle's corners are its vertices, whose box is made.
    const bool whole = corners.size() == 3 && std::all_of(corners.begin(), corners.end(), [](const XPoint* x) {
                         return x->kind == XPoint::Kind::kInput;
                       });
    bool has_shadow = whole ? triangle_box : LineBoxOf(s, corners, &shadow);
    if (has_shadow && all_valid && grid != nullptr) all = grid->Union();
    if (has_shadow && all_valid && all.Apart(shadow)) continue;
    // Only an occluder that reaches the fragments looks for its neighbour:
    // most candidates of a penumbra point are passed over above.
    const bool merged = quads && QuadWithNeighbour(s, slab_top, id, &quad, &neighbour);
    if (merged) {
      merged_occluders.fetch_add(1, std::memory_order_relaxed);
      corners.clear();
      for (const uint32_t v : quad) corners.push_back(&Vertex(s, v));
      edges.clear();
      for (size_t k = 0; k < corners.size(); ++k) edges.emplace_back(corners[k], corners[(k + 1) % corners.size()]);
      has_shadow = LineBoxOf(s, corners, &shadow);
    }
    ++subtracted;
    if (!Subtract(s, fragments, edges, has_shadow ? &shadow : nullptr, grid)) continue;
    if (cutting != nullptr) {
      cutting->push_back(id);
      if (merged) cutting->push_back(neighbour);
    }
    if (grid == nullptr || !GridTakesNewFragments(s, *fragments, *grid)) {
      if (grid != nullptr) stop_grid();  // a piece without a box: as without a grid
      all_valid = UnionLineBox(s, *fragments, &all);
    }
  }
  if (grid != nullptr) stop_grid();
  return subtracted;
}

}  // namespace visq::exact::detail
