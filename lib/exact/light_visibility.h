// Exact point-to-area-light visibility (Mora, Aveneau, Apostu, Ghazanfarpour,
// "Lazy Visibility Evaluation for Exact Soft Shadows", Eurographics 2013;
// slides in shared/papers/lazy-visibility-exact-soft-shadows.txt).
//
// The idea. A line through p and q has Plücker coordinates (q - p, p x q);
// the side of one line against another (their permuted inner product) equals
// the orientation determinant of the four points spanning them, and a line
// stabs a triangle exactly when its sides against the three edge lines share
// one sign. A BSP tree over line space, whose inner nodes are occluder edge
// lines, partitions the lines through the light into classes that hit the
// same occluders; leaves are visible, invisible or undefined. The tree starts
// as one undefined leaf holding every occluder and grows lazily: only when a
// query reaches an undefined leaf is one of its occluders replaced by its 3
// (or 5) node BSP, the other occluders being filtered down by the sides of
// their vertex-to-light-vertex lines. A query from a point P pushes the light
// polygon (the beam of lines from P to the light) down the tree, splitting
// it by the plane through P and a node's edge line where the node separates
// it; fragments reaching visible leaves are the visible parts of the light.
// From those polygons we integrate irradiance analytically.
//
// What is exact. Every sign the algorithm takes is computed by an exact,
// filtered predicate (see exact_geometry.h for the representation of split
// points), so the partition of the light is topologically consistent: no
// cracks, no lost area, no loops, whatever the scale or translation. Only the
// final areas, solid angles and irradiance are floating point.
//
// Segments, not lines. Occluders must lie between the light and the point.
// The tree is built for a receiver region R (a box): occluders strictly
// separated from R, on the light's side, by an axis plane or by a plane
// parallel to the light are "far" and live in the shared tree, where a line
// hit is a segment hit for every P in R. All other occluders (near the
// receivers, crossing the light plane, the receiver's own surface) are
// "near": each query clips them exactly to the slab between the light plane
// and the plane through P parallel to it, and subtracts their shadow from the
// tree's visible fragments with the same split machinery. So a point lying on
// a surface works: its own triangle (and its neighbours) become boundary
// touchers, which never block; so does one on a surface modelled two-sided,
// whose twin its rounded position may lie a hair behind (triangles in the
// receiver triangle's plane are left out, see QueryPoint). Near occluders
// cost O(count) per query (each is clipped, and tested against the light
// before any fragment work), so the tree only pays off for receivers
// grouped tightly: without receiver bounds every occluder is near (correct,
// but nothing is cached). The paper groups receivers per triangle; the
// server groups a batch by its shafts by default (GroupReceiversByShaft:
// the points' box, halved while its shaft meets too many triangles), and
// by cubes of a grid over the scene with --light-receiver-cells
// (GroupReceivers: the same cells, so the same cached trees, for the next
// batch over the same surfaces). The shaft (convex hull of light and
// receiver box, exact) then also culls everything that cannot matter.
//
// Cost. The tree is exact for every line through the light, so its size
// grows with the arrangement of the occluders' shadow edges on the light:
// near-linear for a few large occluders, close to quadratic for clouds of
// small ones (see tests/bench/exact_vs_embree.cpp). Most points of a real
// frame are wholly lit or wholly in umbra; a query first gathers the
// occluders near its pyramid (one hierarchy over far and near ones) and
// decides those points with exact tests on input points alone: none can
// block (visible), one blocks every segment to the light (hidden), or a
// few that block the light's vertices leave nothing when subtracted
// (hidden). Only the rest pay for fragments. By default they subtract their
// candidates, far and near, from the light themselves
// (TreeOptions::direct_candidates): the descent cuts a fragment along every
// node line on its way down, however little of it the occluder below
// hides, where the subtraction cuts it only along the shadow edges it
// straddles, and on every scene the bench measured, cold or with a grown
// tree, the descent cost more (a grille's window 2.4x; docs/
// exact-method-notes.md, stop 50). The tree then keeps its root; a finite
// direct_candidates grows and descends it as the paper does.
//
// Threads. Queries on one tree may run concurrently. A std::shared_mutex
// guards the tree: queries descend under a shared lock; a query that reaches
// an undefined leaf drops it, takes the exclusive lock, refines that one leaf
// (if nobody did meanwhile) and resumes under a shared lock. Refinement is
// rare once the tree is warm (it is bounded by the tree size, queries are
// not), so readers almost never wait; per-node locks would cost more in the
// common, read-only case. All per-query geometry is query-local.
//
// Where the parts are: light_visibility_impl.h (the tree's state, and a map
// of the files that define it: its build and growth, a query, the occluder
// tests, the polygon subtraction, the light's triangulation),
// occluder_index.h, scene_triangle_index.cpp, receiver_grouping.cpp,
// light_visibility_cache.cpp; exact_geometry.h for the predicates.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <list>
#include <memory>
#include <mutex>
#include <optional>
#include <shared_mutex>
#include <span>
#include <string>
#include <unordered_map>
#include <vector>

#include <glm/glm.hpp>

#include "common/status.h"
#include "common/stop_token.h"
#include "scene/scene.h"

namespace visq::exact {

namespace detail {
struct LightTree;  // light_visibility_impl.h
}  // namespace detail

// A planar polygon (convex or not, simple), emitting on its front side: the
// side its counter-clockwise winding faces. Uniform Lambertian radiance.
// "Planar" allows vertices 1e-6 of the light's diameter off the best plane
// (float-authored quads); the polygon is triangulated (exact ear clipping)
// and each triangle is exactly planar, so the tolerance never reaches a
// predicate. Points on or behind the plane of its largest triangle see
// nothing.
struct AreaLight {
  std::vector<glm::dvec3> vertices;  // world space
  double radiance = 1.0;             // W / (m^2 sr)
};

struct TreeOptions {
  // Where query points lie; enables the far (cached) occluder set and the
  // shaft culling. Queries outside it fail with OUT_OF_RANGE.
  std::optional<Bounds> receiver_bounds;
  // Scene triangles that are never occluders (e.g. the emitter's own mesh).
  std::vector<uint32_t> exclude_triangles;
  // The tree (with its store of answers) stops growing at this size. A query that then reaches an
  // undefined leaf subtracts the leaf's occluders from its fragment itself,
  // as it does the near ones: the answer stays exact, only slower, and the
  // memory stays bounded (the tree of a dense scene otherwise grows close to
  // quadratically with its occluders; docs/exact-method-notes.md).
  size_t max_bytes = size_t{512} << 20;
  // Decide wholly visible and wholly hidden points before the tree, with
  // exact tests of the occluders near each point's pyramid (see Query). The
  // answers are the same either way; off only to compare the two routes.
  bool classify_points = true;
  // With classify_points: a point whose candidate occluders (those whose
  // shadows can meet the light, far and near) are at most this many
  // subtracts them all from the light itself, without the tree. The answers
  // are the same, to rounding in the area sums.
  // By default every such point does: the subtraction cuts a fragment only
  // along the edges of the shadows that it straddles, where the tree cuts it
  // along every node line on its way down, however little of it the
  // occluder below hides; measured on every scene of the exact bench, cold
  // and with a fully grown tree, the direct route was faster (a grille's
  // window 2.4x, Sponza in 16-pixel tiles 2.9x; docs/exact-method-notes.md,
  // stop 50), and the tree then stays at its few nodes.
  // 0: every point that is not decided before the tree descends it.
  size_t direct_candidates = SIZE_MAX;
  // Keep answers for points asked again (LightVisibilityTree::Query). The
  // answers are the same either way; off only to time the tree itself.
  bool keep_answers = true;
  // visq's accelerations of the subtraction, each on by default. Like the
  // three above, none changes an answer beyond rounding in the area sums;
  // they are switches so that each can be measured, and so that the
  // paper's algorithm alone can be run (PapersAlgorithmAlone).
  // Occluders and tree nodes wholly outside the pyramid from the point to
  // the light are passed over on float tests with a margin, before any
  // exact one.
  bool cull_pyramid = true;
  // A subtracted triangle takes with it a neighbour across an edge, where
  // the two make a convex quadrilateral as seen from the point: one shadow
  // of four edges instead of two of three.
  bool quadrilaterals = true;
  // Where every direction from the point to the light has one sign along
  // an axis, fragments and shadows carry boxes in the chart of lines
  // through the point, and boxes that are apart settle a test without the
  // exact predicates.
  bool line_boxes = true;
  // A subtraction holding many fragments (with many more candidates left)
  // lists them in a grid over their boxes, so that a shadow meets only the
  // fragments near it (needs line_boxes).
  bool fragment_grid = true;
  // A point's occluders are subtracted largest first as seen from it (in
  // index order a penumbra under a dense mesh was cut into thousands of
  // pieces).
  bool largest_first = true;
  // Per point, occluders whose shadows on the light are small may be left
  // out of the subtraction, the smallest first, while the areas of their
  // shadows (each bounded by the triangle's central projection from the
  // point onto the light's plane) sum to at most this share of the light's
  // area; the answer then states that sum as its error
  // (PointVisibility::visible_area_fraction_error). 0: none is left out, and
  // every answer is exact up to rounding in the area sums. The route for
  // needles and wires that hide almost nothing: n of them across the light
  // cut it into about n^2 pieces, whatever their width
  // (docs/exact-method-notes.md, "Slivers"). Part of the tree's identity.
  double shadow_tolerance = 0.0;

  // Mora et al. 2013 as the paper gives it: every query descends the
  // shared tree, which its queries grow; its leaves' occluders and the near
  // ones are subtracted in index order; every acceleration above is off.
  // The answers are those of the default options (a test holds them to
  // 1e-12).
  static TreeOptions PapersAlgorithmAlone() {
    TreeOptions paper;
    paper.classify_points = false;
    paper.direct_candidates = 0;
    paper.keep_answers = false;
    paper.cull_pyramid = paper.quadrilaterals = paper.line_boxes = paper.fragment_grid = paper.largest_first = false;
    return paper;
  }
  // Asked by Create only, every few thousand triangles while it selects the
  // occluders: a call that was cancelled or whose deadline passed stops
  // there (CANCELLED / DEADLINE_EXCEEDED). Not part of the tree's identity.
  StopToken stop;
};

struct QueryPoint {
  glm::dvec3 position{0.0};
  // Receiver normal: light below the tangent plane is invisible and the
  // irradiance uses this cosine. Optional.
  std::optional<glm::dvec3> normal;
  // The receiver's own triangle: never an occluder for this point, nor is
  // any triangle lying exactly in its plane (a two-sided surface's
  // coincident twin, a coplanar neighbour): P is taken to lie on that
  // plane, which its rounded position misses by a hair to either side.
  // Its geometric normal is used when `normal` is absent (so a point named
  // on a twin facing away from the light, without a normal, sees nothing).
  std::optional<uint32_t> receiver_triangle;
};

struct PointVisibility {
  double visible_area_fraction = 0.0;         // of the light's area
  double visible_solid_angle_fraction = 0.0;  // of the light's solid angle from P
  double irradiance = 0.0;  // W/m^2 at P for its normal; 0 without a normal
  // The visible parts of the light, world space, when asked for.
  std::vector<std::vector<glm::dvec3>> visible_polygons;
  // Occluders left out under TreeOptions::shadow_tolerance: the true figures
  // lie at most these below the three above (never above them: an occluder
  // left out can only hide more). 0 where none was left out. The polygons
  // are those of the light without them.
  double visible_area_fraction_error = 0.0;
  double visible_solid_angle_fraction_error = 0.0;
  double irradiance_error = 0.0;
};

struct TreeStats {
  size_t nodes = 0;
  size_t memory_bytes = 0;
  uint64_t queries = 0;
  uint64_t hits = 0;         // queries that refined nothing
  uint64_t refinements = 0;  // leaves turned into occluder BSPs
  uint64_t unrefined_leaf_visits = 0;  // undefined leaves resolved per query (tree at max_bytes)
  uint64_t wholly_visible = 0;  // queries answered before the tree: no occluder can block
  uint64_t wholly_hidden = 0;   // ... one occluder blocks the whole light
  uint64_t subtracted_directly = 0;  // ... few candidates, subtracted without the tree
  // Occluders subtracted inside a neighbour's polygon (two triangles
  // seen as one convex quadrilateral), not on their own.
  uint64_t merged_occluders = 0;
  // Subtractions whose fragments grew many enough to be kept in a grid over
  // their line boxes (SubtractOccluders): a penumbra seen through foliage.
  uint64_t fragment_grids = 0;
  // Queries found wholly hidden by occluders that together hid a point
  // nearby on the same thread (the most recent such set, or the one found
  // nearest; no gathering); counted in wholly_hidden too.
  uint64_t hidden_by_remembered_blockers = 0;
  // Answers given again from the tree's store of answers (an identical
  // point, normal and receiver triangle was asked before): no descent, no
  // subtraction. `answers_kept` is the store's size.
  uint64_t answers_reused = 0;
  size_t answers_kept = 0;
  size_t answer_bytes = 0;  // the store's part of memory_bytes
  size_t far_occluders = 0;  // in the shared tree
  size_t near_occluders = 0;  // clipped per query

  // Sums every field (the statistics of several trees).
  TreeStats& operator+=(const TreeStats& o);
};

// The scene's triangles in a bounding-volume hierarchy over their boxes, so
// that creating a tree visits the triangles near its shaft instead of the
// whole scene (docs/exact-method-notes.md). It does
// not depend on the light: build it once per scene, lazily, and pass it to
// every Create on that scene.
//
// A mesh the scene places more than once (Scene::placements) is indexed once,
// in its own space, and each placement is one box of the scene's level; what
// the index answers is the same as if the scene were flattened.
//
// The index shares the scene (it reads triangle boxes off its positions
// rather than holding copies: 48 bytes a triangle less).
class SceneTriangleIndex {
 public:
  // Validates the triangles' vertex indices (INVALID_ARGUMENT).
  [[nodiscard]] static StatusOr<std::unique_ptr<SceneTriangleIndex>> Build(std::shared_ptr<const Scene> scene);
  ~SceneTriangleIndex();
  SceneTriangleIndex(const SceneTriangleIndex&) = delete;
  SceneTriangleIndex& operator=(const SceneTriangleIndex&) = delete;

  // Every triangle whose box meets the box [lo, hi], and perhaps others near
  // it (those that share an index leaf with one), in increasing order.
  std::vector<uint32_t> InBox(const glm::dvec3& lo, const glm::dvec3& hi) const;
  // How many triangles' boxes meet [lo, hi], counting no further than `limit`.
  size_t CountInBox(const glm::dvec3& lo, const glm::dvec3& hi, size_t limit) const;
  size_t triangle_count() const;
  size_t instance_count() const;
  size_t MemoryBytes() const;

 private:
  struct Impl;
  explicit SceneTriangleIndex(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The checks LightVisibilityTree::Create makes of a light, alone: INVALID_ARGUMENT
// naming the vertex or property at fault.
[[nodiscard]] Status ValidateAreaLight(const AreaLight& light);
// INVALID_ARGUMENT naming `field` ("points[3]") for a position that is not
// finite or beyond the coordinate range, or a normal that is not a
// direction; the receiver triangle is the caller's to check against its
// scene. The one check of a point, at the server's door and at the tree's.
[[nodiscard]] Status ValidateQueryPoint(const QueryPoint& point, std::string_view field);

class LightVisibilityTree {
 public:
  // Validates the light ("light.vertices[2]: NaN coordinate", "light: zero
  // area", "light: not planar", ...) and selects the occluders. With an
  // index of the scene (built from this scene) and receiver bounds, only the
  // triangles near the shaft are visited; the tree is the same either way.
  [[nodiscard]] static StatusOr<std::unique_ptr<LightVisibilityTree>> Create(
      const AreaLight& light, const Scene& scene, const TreeOptions& options = {},
      const SceneTriangleIndex* index = nullptr);
  ~LightVisibilityTree();
  LightVisibilityTree(const LightVisibilityTree&) = delete;
  LightVisibilityTree& operator=(const LightVisibilityTree&) = delete;

  // Thread-safe; grows the tree as needed. CANCELLED or DEADLINE_EXCEEDED
  // when `stop` says so, within one occluder's subtraction or one leaf's
  // refinement; the tree stays whole.
  //
  // Answers are kept, up to half the tree's max_bytes (which counts them
  // with the tree; about 100 bytes an answer without polygons): a
  // point asked again with the same position, normal and receiver triangle
  // (bit for bit) is answered from that store. A frame asked twice (a
  // re-render, a client's retry) then costs a hash lookup per point.
  [[nodiscard]] StatusOr<PointVisibility> Query(const QueryPoint& point, bool want_polygons = false,
                                                const StopToken& stop = {});
  // Whether Query would answer `point` from the store (no counts change).
  bool StoresAnswer(const QueryPoint& point, bool want_polygons = false) const;
  // Queries in parallel on `threads` workers (0: hardware concurrency).
  // Once `stop` says stop (asked between points and inside them), its
  // status, so a batch whose caller gave up stops.
  [[nodiscard]] StatusOr<std::vector<PointVisibility>> QueryBatch(std::span<const QueryPoint> points, int threads = 0,
                                                                  bool want_polygons = false,
                                                                  const StopToken& stop = {});

  TreeStats Stats() const;
  // The tree and its store of answers.
  size_t MemoryBytes() const;
  double light_area() const;
  // What the calling thread keeps between queries for its next one (the
  // query's working geometry and slots, of any tree): bounded whatever the
  // largest query the thread answered.
  static size_t ThisThreadScratchBytes();

 private:
  explicit LightVisibilityTree(std::unique_ptr<detail::LightTree> impl);
  std::unique_ptr<detail::LightTree> impl_;
};

// Receivers grouped for their trees: the cubes of a grid over the scene
// (the largest extent / cells_per_side a side, anchored at the scene's lower
// corner) that a batch's points fall in. A tree's cost follows its receiver
// box: occluders strictly separated from the box are cached in the tree,
// the rest are clipped by every query. One box around a whole frame holds
// every occluder in its shaft as "near", and one image tile of a deep room
// spans the room's depth; small cubes keep most occluders far whatever the
// view. A later batch over the same surfaces finds the same cells, so their
// cached trees are reused.
struct ReceiverCell {
  Bounds box;                     // the grid cube (widened only to hold its points)
  std::vector<uint32_t> points;   // indices into the batch, increasing
};
// Cells in order of their first point. Points must be finite.
// A cube with fewer than `min_points` points gives them to its octree parent
// (up to a cube as large as the scene): a sparse batch shares a few trees, a
// dense one keeps small cubes. 1: the grid's cubes as they are.
std::vector<ReceiverCell> GroupReceivers(std::span<const QueryPoint> points, const Bounds& scene_bounds,
                                         int cells_per_side, size_t min_points = 1);

// Receivers grouped by the batch and the occluders, without a grid: one
// group of every point, its box the points' box, split in two at the median
// of its longest axis while the box around its shaft (the light and the
// group's box) meets more than max_shaft_triangles scene triangles, as long
// as both halves keep min_points and their shafts meet markedly fewer (or
// the whole is past a hard cap). A compact batch under a light in open
// space stays one tree over its own box (the best single region); a frame
// over a dense room is cut until each tree's occluders are few enough to
// bound its memory. The points' boxes are tight, so the trees' shafts are
// too; a different batch over the same surfaces gets different boxes, and
// so new trees (GroupReceivers' grid cells are found again instead).
struct ShaftGrouping {
  size_t max_shaft_triangles = 20000;
  size_t min_points = 64;
  // ... and as long as the halves' shafts meet at most this fraction of
  // twice the whole's triangles (0.5: no more than the whole, together):
  // halves that share their occluders would build the same tree twice, and
  // each half's tree would hold as far occluders what the whole's clips as
  // near ones (on the bunny, two halves cost 2.3x one tree).
  double split_gain = 0.5;
  // Past hard_cap x max_shaft_triangles a group is halved whatever the
  // gain. A tree keeps some 55-70 bytes per occluder (docs/exact-method-notes.md),
  // so the default cap's trees start with at most about 64 MB of occluders,
  // a quarter of the server's default cache. Below it, halves that share
  // their occluders are not worth it even when the whole's occluders exceed
  // its tree's growth budget: on veach-ajar (the whole room in the light's
  // shaft) one tree of 26.8 MiB that cannot grow answered a frame in 1.2 s of
  // CPU, where a cap of 12 cut it into 42 trees of 122 MiB in all, 3.8 s.
  double hard_cap = 48.0;
};
// Cells in order of their first point. Points must be finite.
std::vector<ReceiverCell> GroupReceiversByShaft(std::span<const QueryPoint> points, const AreaLight& light,
                                                const SceneTriangleIndex& index, const ShaftGrouping& options = {});

// A 64-bit hash of the light (and of the tree options, which change the
// tree), for cache keys.
uint64_t HashLight(const AreaLight& light, const TreeOptions& options = {});

struct CacheKey {
  std::string scene_id;
  uint64_t scene_version = 0;
  uint64_t light_hash = 0;
  bool operator==(const CacheKey&) const = default;
};

// Trees by (scene id, scene version, light), bounded in bytes (trees grow
// after insertion, so the bound is enforced on every access), least recently
// used first out. Evicted trees live on while callers hold them.
class LightVisibilityCache {
 public:
  using Factory = std::function<StatusOr<std::unique_ptr<LightVisibilityTree>>()>;
  explicit LightVisibilityCache(size_t max_bytes);

  // The cached tree, or a new one from `make` (not called on a hit).
  [[nodiscard]] StatusOr<std::shared_ptr<LightVisibilityTree>> GetOrCreate(const CacheKey& key,
                                                                           const Factory& make);
  std::shared_ptr<LightVisibilityTree> Find(const CacheKey& key);
  // The key's tree if it is held, without counting as a use (a planner
  // asking what a batch would build and which answers it holds).
  std::shared_ptr<LightVisibilityTree> Peek(const CacheKey& key) const;
  // Drops every tree of the scene (all versions).
  void InvalidateScene(const std::string& scene_id);

  size_t bytes() const;
  size_t size() const;
  uint64_t evictions() const;

 private:
  struct KeyHash {
    size_t operator()(const CacheKey& k) const;
  };
  using Entry = std::pair<CacheKey, std::shared_ptr<LightVisibilityTree>>;
  void EvictLocked(const CacheKey* keep);

  mutable std::mutex mutex_;
  size_t max_bytes_;
  uint64_t evictions_ = 0;
  std::list<Entry> lru_;  // front: most recent
  std::unordered_map<CacheKey, std::list<Entry>::iterator, KeyHash> index_;
};

}  // namespace visq::exact
