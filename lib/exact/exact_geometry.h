// Exact geometric predicates for the Plücker-space visibility BSP (private to
// lib/exact/).
//
// Why this design. Every decision the algorithm makes is the sign of a
// polynomial in input coordinates: the side of a line against an occluder
// edge line (an orientation determinant of four points), and the side of a
// light-fragment vertex against a plane through the query point and an edge.
// Fragment vertices are created by splitting, so they are not input doubles.
// Storing them as rounded doubles would make later signs inconsistent (the
// classic source of cracks, lost area and infinite loops), and storing them
// as explicit rationals makes bit sizes grow with every split. Instead every
// derived point keeps its *definition* in terms of fixed input geometry:
//
//   - an input point (light vertex, occluder vertex, query point);
//   - LinePlane(p, q, plane): the line through two points cut by a plane;
//   - ThreePlanes(a, b, c): the meeting point of three planes;
//
// and every plane is one of ThroughPoints(p, q, r), ParallelThrough(plane,
// point) or PointNormal(point, input normal). A light fragment is a convex
// polygon inside one light triangle whose edges lie on light edges or on
// split planes through the query point and an occluder edge; a new vertex is
// always LinePlane(light edge, split plane) or ThreePlanes(light triangle
// plane, split plane, split plane), and both split planes are built from
// input points (or from slab-clipped occluder vertices, one level deeper).
// So the degree of every predicate is bounded, however often a fragment is
// split, and signs stay consistent because each sign is a property of the
// definitions, not of a rounded value.
//
// Points and planes use homogeneous coordinates (x, y, z, w) so that no
// predicate divides. Each carries an interval enclosure of its coordinates
// (outward-rounded double arithmetic, see Iv) and, lazily, the exact value in
// GMP integers (ZV4). A sign is read from the interval when the interval excludes
// zero (the filter); otherwise it is recomputed exactly. Input-only
// orientation tests use Shewchuk's static error bound for orient3d instead of
// intervals, again with an exact fallback.
#pragma once

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>

#include <gmpxx.h>
#include <glm/glm.hpp>

#include "exact/rounding.h"

namespace visq::exact::detail {

// Counts of exact (GMP) fallbacks, for statistics and tests.
inline std::atomic<uint64_t> g_exact_fallbacks{0};

// ---------------------------------------------------------------------------
// Interval arithmetic in midpoint-radius form: an Iv holds the reals within
// rad of mid. Each operation rounds its midpoint to nearest and bounds, in
// its radius, the operands' radii and that rounding (u |result|, u = 2^-53);
// the radius, a sum of positive terms rounded to nearest, is scaled up by
// Up past its own roundings (at most a few ulps) and underflow. A product
// costs 3 products for its radius where endpoint intervals took 4 and their
// minimum and maximum, and a plane's or point's fast filter (PlaneFilter,
// PointFilter) reads the form as it is.
//
// Point intervals (rad 0) stay points while the arithmetic is exact
// (error-free TwoSum for sums, whose error is then the exact radius; a
// significant-bit count for products). Why: degenerate configurations with
// "nice" coordinates (axis-aligned boxes, a receiver on the floor, a light
// at z = 2) produce exact zeros, and an exact zero is then certified as
// [0, 0] here instead of falling back to GMP on every query.
#define VISQ_EXACT_INLINE [[gnu::always_inline]] inline
VISQ_EXACT_INLINE double RoundDown(double r) { return r - (std::fabs(r) * 0x1p-52 + 0x1p-1074); }
VISQ_EXACT_INLINE double RoundUp(double r) { return r + (std::fabs(r) * 0x1p-52 + 0x1p-1074); }
// A bound on the exact value of a sum of at most 8 positive terms (products
// or sums of doubles) computed with rounding to nearest: each rounding loses
// at most u of the running value, or 2^-1075 in underflow.
VISQ_EXACT_INLINE double Up(double r) { return r * (1.0 + 0x1p-49) + 0x1p-1068; }
inline constexpr double kUnitRoundoff = 0x1p-53;

struct Iv {
  double mid = 0.0, rad = 0.0;
  Iv() = default;
  explicit Iv(double x) : mid(x) {}
  Iv(double m, double r) : mid(m), rad(r) {}
  // Outward bounds of the interval's ends.
  double Lo() const { return rad == 0.0 ? mid : RoundDown(mid - rad); }
  double Hi() const { return rad == 0.0 ? mid : RoundUp(mid + rad); }
};

// Bits between the leading and the last set bit of a normal double's
// significand (1..53); 64 for zero, subnormals, inf and NaN.
VISQ_EXACT_INLINE int SignificantBits(double x) {
  const uint64_t u = std::bit_cast<uint64_t>(x);
  const uint64_t exponent = (u >> 52) & 0x7FF;
  if (exponent == 0 || exponent == 0x7FF) return 64;
  const uint64_t m = (u & ((uint64_t{1} << 52) - 1)) | (uint64_t{1} << 52);
  return 53 - std::countr_zero(m);
}

VISQ_EXACT_INLINE Iv operator+(const Iv& a, const Iv& b) {
  const double s = a.mid + b.mid;
  if (a.rad == 0.0 && b.rad == 0.0) {
    const double bb = s - a.mid;  // TwoSum: err is the exact rounding error
    const double err = (a.mid - (s - bb)) + (b.mid - bb);
    if (std::isfinite(s)) return {s, std::fabs(err)};
    return {s, std::numeric_limits<double>::infinity()};
  }
  return {s, Up(a.rad + b.rad + kUnitRoundoff * std::fabs(s))};
}
VISQ_EXACT_INLINE Iv operator-(const Iv& a) { return {-a.mid, a.rad}; }
VISQ_EXACT_INLINE Iv operator-(const Iv& a, const Iv& b) { return a + (-b); }
VISQ_EXACT_INLINE Iv operator*(const Iv& a, const Iv& b) {
  const double p = a.mid * b.mid;
  if (a.rad == 0.0 && b.rad == 0.0) {
    if (a.mid == 0.0 || b.mid == 0.0) return Iv(0.0);
    if (SignificantBits(a.mid) + SignificantBits(b.mid) <= 53 && std::isnormal(p)) return Iv(p);
    return {p, Up(kUnitRoundoff * std::fabs(p))};
  }
  const double am = std::fabs(a.mid), bm = std::fabs(b.mid);
  return {p, Up(am * b.rad + a.rad * (bm + b.rad) + kUnitRoundoff * std::fabs(p))};
}

// Outward bounds of a / b for an interval b that excludes zero (the caller
// checks SignOf(b)): the quotient is monotone in each operand there, so the
// corners bound it.
VISQ_EXACT_INLINE void QuotientBounds(const Iv& a, const Iv& b, double* lo, double* hi) {
  const double al = a.Lo(), ah = a.Hi(), bl = b.Lo(), bh = b.Hi();
  const double q1 = al / bl, q2 = al / bh, q3 = ah / bl, q4 = ah / bh;
  *lo = RoundDown(std::min(std::min(q1, q2), std::min(q3, q4)));
  *hi = RoundUp(std::max(std::max(q1, q2), std::max(q3, q4)));
}
inline constexpr int kUncertain = 2;
// Sign of an interval, or kUncertain when it contains zero (or is NaN).
inline int SignOf(const Iv& a) {
  if (a.mid > a.rad) return 1;
  if (-a.mid > a.rad) return -1;
  if (a.mid == 0.0 && a.rad == 0.0) return 0;
  return kUncertain;
}

// ---------------------------------------------------------------------------
// Homogeneous 4-vectors and the two operations everything is built from.
template <typename T>
struct V4 {
  std::array<T, 4> v;
  const T& operator[](int i) const { return v[i]; }
  T& operator[](int i) { return v[i]; }
};
using IV4 = V4<Iv>;
// Exact homogeneous coordinates: integers. Inputs are scaled by powers of
// two (InputExact), and every construction is a polynomial that is linear
// in each of its objects, so a positive scale of any of them only scales
// the result: no rationals, none of their gcds.
using ZV4 = V4<mpz_class>;

template <typename T>
VISQ_EXACT_INLINE T Dot4(const V4<T>& a, const V4<T>& b) {
  T r = a[0] * b[0];
  r = r + a[1] * b[1];
  r = r + a[2] * b[2];
  r = r + a[3] * b[3];
  return r;
}

template <typename T>
VISQ_EXACT_INLINE T Det3(const T& a0, const T& a1, const T& a2, const T& b0, const T& b1, const T& b2, const T& c0,
       const T& c1, const T& c2) {
  T m0 = b1 * c2 - b2 * c1;
  T m1 = b0 * c2 - b2 * c0;
  T m2 = b0 * c1 - b1 * c0;
  T r = a0 * m0 - a1 * m1;
  r = r + a2 * m2;
  return r;
}

// Returns r with Dot4(r, x) == det4(rows a, b, c, x). Used both for the plane
// through three points and for the point common to three planes.
template <typename T>
V4<T> Cross4(const V4<T>& a, const V4<T>& b, const V4<T>& c) {
  V4<T> r;
  r[0] = -Det3(a[1], a[2], a[3], b[1], b[2], b[3], c[1], c[2], c[3]);
  r[1] = Det3(a[0], a[2], a[3], b[0], b[2], b[3], c[0], c[2], c[3]);
  r[2] = -Det3(a[0], a[1], a[3], b[0], b[1], b[3], c[0], c[1], c[3]);
  r[3] = Det3(a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2]);
  return r;
}

// X = (plane . q) p - (plane . p) q lies on the plane and on line(p, q).
template <typename T>
V4<T> LinePlanePoint(const V4<T>& p, const V4<T>& q, const V4<T>& plane) {
  const T pq = Dot4(plane, q), pp = Dot4(plane, p);
  V4<T> r;
  for (int i = 0; i < 4; ++i) r[i] = pq * p[i] - pp * q[i];
  return r;
}

// A lazily computed exact value that shared (tree-owned) objects may fill
// from several query threads: the first finished computation wins a
// compare-and-swap, losers free theirs. Exact values are needed only when a
// filter fails, so most objects never pay for one.
class ExactCache {
 public:
  ExactCache() = default;
  ExactCache(ExactCache&& other) noexcept : value_(other.value_.exchange(nullptr)) {}
  ExactCache& operator=(ExactCache&& other) noexcept {
    delete value_.exchange(other.value_.exchange(nullptr));
    return *this;
  }
  ~ExactCache() { delete value_.load(); }
  template <typename Make>
  const ZV4& Get(const Make& make) const {
    if (const ZV4* v = value_.load(std::memory_order_acquire)) return *v;
    auto* fresh = new ZV4(make());
    ZV4* expected = nullptr;
    if (value_.compare_exchange_strong(expected, fresh, std::memory_order_acq_rel)) return *fresh;
    delete fresh;
    return *expected;
  }

 private:
  mutable std::atomic<ZV4*> value_{nullptr};
};

// The fast sign filter of Dot4(a, x) for a plane a and a point x, from
// Higham's dot-product bound: |sum a_i x_i - fl(sum am_i xm_i)| <=
// sum(|am_i| xr_i + ar_i |xm_i| + ar_i xr_i) + gamma_4 sum |am_i xm_i|,
// which is at most sum((|am_i| + ar_i)(xr_i + gamma_4 |xm_i|) + ar_i |xm_i|).
// The plane keeps |am_i| + ar_i and the point xr_i + gamma_4 |xm_i|, made
// once, so each test pays two products a term for its bound.
//
// Each side also keeps two sums of its terms, for a first bound of one
// product a side (at most four times the termwise one): sum_i wide_i xr_i
// <= (sum_i wide_i) max_i xr_i, and sum_i ar_i |xm_i| <= (max_i ar_i)
// sum_i |xm_i|. Most tests settle on it.
inline constexpr double kGamma4 = Gamma(4);
struct PlaneFilter {
  std::array<double, 4> mid{}, rad{}, wide{};  // wide: |mid| + rad
  double wide_sum = 0.0, rad_max = 0.0;
  static PlaneFilter From(const IV4& v) {
    PlaneFilter f;
    for (int i = 0; i < 4; ++i) {
      f.mid[i] = v[i].mid;
      f.rad[i] = v[i].rad;
      f.wide[i] = std::fabs(v[i].mid) + v[i].rad;
    }
    f.Summarize();
    return f;
  }
  // Fills the sums from mid, rad and wide.
  void Summarize() {
    wide_sum = rad_max = 0.0;
    for (int i = 0; i < 4; ++i) {
      wide_sum += wide[i];
      rad_max = std::max(rad_max, rad[i]);
    }
  }
};
struct PointFilter {
  std::array<double, 4> mid{}, rad{};  // rad: the radius plus gamma_4 |mid|
  double rad_max = 0.0, mid_sum = 0.0;  // max_i rad_i, sum_i |mid_i|
  static PointFilter From(const IV4& v) {
    PointFilter f;
    for (int i = 0; i < 4; ++i) {
      f.mid[i] = v[i].mid;
      f.rad[i] = v[i].rad + kGamma4 * std::fabs(v[i].mid);
      f.rad_max = std::max(f.rad_max, f.rad[i]);
      f.mid_sum += std::fabs(v[i].mid);
    }
    return f;
  }
};

// Sign of the dot product of an enclosed plane and point, or kUncertain.
VISQ_EXACT_INLINE int FastSignOfDot(const PlaneFilter& a, const PointFilter& x) {
  double s = 0.0;
  for (int i = 0; i < 4; ++i) s += a.mid[i] * x.mid[i];
  // Each bound's own rounding (its terms are all positive: a relative
  // error of about 12 ulps, the sums and precomputed terms included) is
  // covered by the factor, underflow by the absolute floor.
  const double first = (a.wide_sum * x.rad_max + a.rad_max * x.mid_sum) * kDotFilterRounding + 1e-300;
  if (s > first) return 1;
  if (s < -first) return -1;
  double bound = 0.0;
  for (int i = 0; i < 4; ++i) bound += a.wide[i] * x.rad[i] + a.rad[i] * std::fabs(x.mid[i]);
  bound = bound * kDotFilterRounding + 1e-300;
  if (s > bound) return 1;
  if (s < -bound) return -1;
  return kUncertain;
}

// ---------------------------------------------------------------------------
// Points and planes defined from input geometry.
struct XPlane;

struct XPoint {
  enum class Kind : uint8_t { kInput, kLinePlane, kThreePlanes };
  Kind kind = Kind::kInput;
  int8_t w_sign = 1;                    // exact sign of w (never 0)
  IV4 approx;                           // interval enclosure
  PointFilter fast;                     // the same, for FastSignOfDot
  glm::dvec3 input{0.0};                // kInput only
  const XPoint* p = nullptr;            // kLinePlane: the line
  const XPoint* q = nullptr;
  const XPlane* planes[3] = {nullptr, nullptr, nullptr};  // kLinePlane uses [0]
  ExactCache exact;                     // lazily, thread-safe
  mutable bool has_euclid = false;
  mutable glm::dvec3 euclid{0.0};
  // A query's image of a derived point in its chart of lines (the LineBox
  // of the point alone: lo, hi per axis), made on first use by the query
  // that owns the point: 0 not yet, 1 held, -1 none.
  mutable int8_t chart_state = 0;
  mutable std::array<double, 4> chart{};

  static XPoint Input(const glm::dvec3& x);
  static XPoint LinePlane(const XPoint& p, const XPoint& q, const XPlane& plane);
  static XPoint ThreePlanes(const XPlane& a, const XPlane& b, const XPlane& c);

  // Exact homogeneous coordinates, computed on first use (thread-safe).
  const ZV4& Exact() const;
  void PrecomputeExact() const { (void)Exact(); }
  // Euclidean coordinates in double (from the interval when it is tight,
  // else from the exact value). Cached without synchronization: call it only
  // on input points (set at creation) or on query-local points.
  glm::dvec3 Euclid() const;
};

struct XPlane {
  enum class Kind : uint8_t { kThroughPoints, kParallelThrough, kPointNormal };
  Kind kind = Kind::kThroughPoints;
  // EuclidSide(x) = sign(Dot4(coeffs, x)) * w_sign(x) * o_sign: the sign of
  // the plane's natural Euclidean function (orient3d(p, q, r, x) for
  // ThroughPoints, n . (x - point) for the others).
  int8_t o_sign = 1;
  IV4 approx;
  PlaneFilter fast;
  const XPoint* points[3] = {nullptr, nullptr, nullptr};
  const XPlane* base = nullptr;
  glm::dvec3 normal{0.0};
  ExactCache exact;

  static XPlane ThroughPoints(const XPoint& p, const XPoint& q, const XPoint& r);
  static XPlane ParallelThrough(const XPlane& base, const XPoint& point);
  static XPlane PointNormal(const XPoint& point, const glm::dvec3& normal);

  const ZV4& Exact() const;
  void PrecomputeExact() const { (void)Exact(); }
  // Whether the coefficients are exactly zero (three collinear points).
  bool Degenerate() const;
};

// Sign of the plane's Euclidean function at x (see XPlane::o_sign). The
// fast filter inline (it settles nearly every call), the rest out of line.
int EuclidSideSlow(const XPoint& x, const XPlane& plane);
VISQ_EXACT_INLINE int EuclidSide(const XPoint& x, const XPlane& plane) {
  const int fast = FastSignOfDot(plane.fast, x.fast);
  if (fast != kUncertain) return fast * x.w_sign * plane.o_sign;
  return EuclidSideSlow(x, plane);
}

// orient3d(a, b, c, d) = det[b - a, c - a, d - a] for input doubles: positive
// when d lies on the side of plane(a, b, c) that (b - a) x (c - a) points to.
// Shewchuk's static filter, exact GMP fallback.
int Orient3d(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, const glm::dvec3& d);

// orient3d(p, a, b, x) for many x and one (p, a, b): the normal
// n = (a - p) x (b - p) is formed once, and each x costs the dot product
// n . (x - p) and Shewchuk's static bound on it. The expression is his
// filter's, with its terms grouped by the components of x - p, so the same
// bound holds. Signs the bound leaves open (and tiny magnitudes, where
// underflow would void the bound) go to Orient3d. About 4x cheaper than
// Orient3d per point: what the BSP descent pays at every node.

class Orient3dFan {
 public:
  VISQ_EXACT_INLINE Orient3dFan(const glm::dvec3& p, const glm::dvec3& a, const glm::dvec3& b) : p_(p), a_(a), b_(b) {
    const glm::dvec3 u = a - p, v = b - p;
    normal_ = glm::dvec3(u.y * v.z - u.z * v.y, u.z * v.x - u.x * v.z, u.x * v.y - u.y * v.x);
    magnitude_ = glm::dvec3(std::fabs(u.y * v.z) + std::fabs(u.z * v.y), std::fabs(u.z * v.x) + std::fabs(u.x * v.z),
                            std::fabs(u.x * v.y) + std::fabs(u.y * v.x));
  }
  // An enclosure of the plane (n, -n . p): Dot4 of it with (x, 1) is
  // orient3d(p, a, b, x), so a derived point is tested against the fan by
  // the fast filter, with no exact plane made. Each component of n carries
  // the roundings of the two differences, of the product and of the
  // difference of products: within kFanNormalError of its magnitude, and
  // 2^-1075 a product that underflows (differences are
  // exact there). The offset adds those radii times |p| and the rounding
  // of its own dot product.
  PlaneFilter Filter() const {
    PlaneFilter f;
    double offset = 0.0, offset_rad = 0.0, offset_magnitude = 0.0;
    for (int i = 0; i < 3; ++i) {
      f.mid[i] = normal_[i];
      f.rad[i] = kFanNormalError * magnitude_[i] + 0x1p-1072;
      offset -= normal_[i] * p_[i];
      offset_rad += f.rad[i] * std::fabs(p_[i]);
      offset_magnitude += std::fabs(normal_[i] * p_[i]);
    }
    f.mid[3] = offset;
    f.rad[3] = (offset_rad + Gamma(3) * offset_magnitude) * kOffsetRadiusRounding + 0x1p-1070;
    for (int i = 0; i < 4; ++i) f.wide[i] = std::fabs(f.mid[i]) + f.rad[i];
    f.Summarize();
    return f;
  }

  // The sign of n . (x - base) for another base point (the side of x
  // against the plane through base parallel to the fan's), when the same
  // static bound settles it (its terms are Side's); else kUncertain.
  VISQ_EXACT_INLINE int ParallelSide(const glm::dvec3& base, const glm::dvec3& x) const {
    const glm::dvec3 w = x - base;
    const double det = normal_.x * w.x + normal_.y * w.y + normal_.z * w.z;
    const double permanent =
        magnitude_.x * std::fabs(w.x) + magnitude_.y * std::fabs(w.y) + magnitude_.z * std::fabs(w.z);
    const double bound = kOrient3dFilter * permanent;
    if (permanent > 1e-250) {
      if (det > bound) return 1;
      if (-det > bound) return -1;
    }
    return kUncertain;
  }

  // n = (a - p) x (b - p) as rounded, and the magnitudes that bound its
  // error (each component within kFanNormalError of its magnitude, see Filter).
  const glm::dvec3& Normal() const { return normal_; }
  const glm::dvec3& Magnitude() const { return magnitude_; }

  VISQ_EXACT_INLINE int Side(const glm::dvec3& x) const {
    const glm::dvec3 w = x - p_;
    const double det = normal_.x * w.x + normal_.y * w.y + normal_.z * w.z;
    const double permanent =
        magnitude_.x * std::fabs(w.x) + magnitude_.y * std::fabs(w.y) + magnitude_.z * std::fabs(w.z);
    const double bound = kOrient3dFilter * permanent;  // as in Orient3d
    if (permanent > 1e-250) {
      if (det > bound) return 1;
      if (-det > bound) return -1;
    }
    return Orient3d(p_, a_, b_, x);
  }

 private:
  glm::dvec3 p_, a_, b_, normal_, magnitude_;
};

// 2D orientation of (a, b, c) in the coordinate plane (i, j); exact.
int Orient2d(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, int i, int j);

}  // namespace visq::exact::detail
