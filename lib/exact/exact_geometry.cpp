#include "exact/exact_geometry.h"

#include <cmath>
#include <limits>

#include "common/check.h"

namespace visq::exact::detail {
namespace {

// Exact integer images of doubles: each nonzero double is m * 2^e with an
// integer |m| < 2^53, so scaling a set of them by 2^-emin (emin the smallest
// such e) gives integers. Determinants of input doubles are then computed in
// mpz, with none of the gcd normalisation mpq pays on every operation.
template <size_t N>
void ToCommonIntegers(const std::array<double, N>& v, std::array<mpz_class, N>* out) {
  int emin = std::numeric_limits<int>::max();
  std::array<int, N> exps{};
  std::array<double, N> mant{};
  for (size_t i = 0; i < N; ++i) {
    if (v[i] == 0.0) continue;
    mant[i] = std::ldexp(std::frexp(v[i], &exps[i]), 53);  // integer, |m| < 2^53
    exps[i] -= 53;
    emin = std::min(emin, exps[i]);
  }
  for (size_t i = 0; i < N; ++i) {
    if (v[i] == 0.0) {
      (*out)[i] = 0;
      continue;
    }
    (*out)[i] = mant[i];  // exact: an integer below 2^53
    mpz_mul_2exp((*out)[i].get_mpz_t(), (*out)[i].get_mpz_t(),
                 static_cast<mp_bitcnt_t>(exps[i] - emin));
  }
}

IV4 InputInterval(const glm::dvec3& x) { return IV4{{Iv(x.x), Iv(x.y), Iv(x.z), Iv(1.0)}}; }

// (x, y, z, 1) scaled by a power of two that makes every coordinate an
// integer: a positive multiple, the same point.
ZV4 InputExact(const glm::dvec3& x) {
  std::array<mpz_class, 4> z;
  ToCommonIntegers(std::array<double, 4>{x.x, x.y, x.z, 1.0}, &z);
  return ZV4{z};
}

// Sign of Dot4(a, b) from intervals, or exactly from the given thunks.
template <typename ExactA, typename ExactB>
int SignOfDot(const IV4& a, const IV4& b, const ExactA& exact_a, const ExactB& exact_b) {
  const int s = SignOf(Dot4(a, b));
  if (s != kUncertain) return s;
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  return sgn(Dot4(exact_a(), exact_b()));
}

}  // namespace

// ---------------------------------------------------------------------------
XPoint XPoint::Input(const glm::dvec3& x) {
  XPoint out;
  out.kind = Kind::kInput;
  out.input = x;
  out.approx = InputInterval(x);
  out.w_sign = 1;
  out.has_euclid = true;
  out.euclid = x;
  out.fast = PointFilter::From(out.approx);
  return out;
}

namespace {
int8_t ExactWSign(const XPoint& point) {
  const int s = SignOf(point.approx[3]);
  if (s != kUncertain) return static_cast<int8_t>(s);
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  return static_cast<int8_t>(sgn(point.Exact()[3]));
}
}  // namespace

XPoint XPoint::LinePlane(const XPoint& p, const XPoint& q, const XPlane& plane) {
  XPoint out;
  out.kind = Kind::kLinePlane;
  out.p = &p;
  out.q = &q;
  out.planes[0] = &plane;
  out.approx = LinePlanePoint(p.approx, q.approx, plane.approx);
  out.fast = PointFilter::From(out.approx);
  out.w_sign = ExactWSign(out);
  VISQ_CHECK(out.w_sign != 0);
  return out;
}

namespace {
// The input point a plane passes through by its definition (ThroughPoints'
// first point, PointNormal's point), or null.
const XPoint* InputApex(const XPlane& plane) {
  if (plane.kind != XPlane::Kind::kThroughPoints && plane.kind != XPlane::Kind::kPointNormal) return nullptr;
  const XPoint* apex = plane.points[0];
  return apex->kind == XPoint::Kind::kInput ? apex : nullptr;
}

// The apex both b and c pass through by their definitions, or null.
const XPoint* SharedApex(const XPlane& b, const XPlane& c) {
  const XPoint* apex = InputApex(b);
  return apex != nullptr && apex == InputApex(c) ? apex : nullptr;
}

// The meeting point of planes a, b and c where b and c pass through `apex`:
// their line is the apex and the direction of their normals' cross product
// (a point at infinity), cut by a (LinePlanePoint). 12 products where Cross4
// takes 36; every fragment split through P makes one. Both the interval and
// the exact value are made so, so the two stay positive multiples.
template <typename T>
V4<T> PencilPoint(const V4<T>& a, const V4<T>& b, const V4<T>& c, const V4<T>& apex) {
  V4<T> direction;
  direction[0] = b[1] * c[2] - b[2] * c[1];
  direction[1] = b[2] * c[0] - b[0] * c[2];
  direction[2] = b[0] * c[1] - b[1] * c[0];
  direction[3] = T(0);
  return LinePlanePoint(apex, direction, a);
}
}  // namespace

XPoint XPoint::ThreePlanes(const XPlane& a, const XPlane& b, const XPlane& c) {
  XPoint out;
  out.kind = Kind::kThreePlanes;
  out.planes[0] = &a;
  out.planes[1] = &b;
  out.planes[2] = &c;
  if (const XPoint* apex = SharedApex(b, c)) {
    out.approx = PencilPoint(a.approx, b.approx, c.approx, apex->approx);
  } else {
    out.approx = Cross4(a.approx, b.approx, c.approx);
  }
  out.fast = PointFilter::From(out.approx);
  out.w_sign = ExactWSign(out);
  VISQ_CHECK(out.w_sign != 0);
  return out;
}

const ZV4& XPoint::Exact() const {
  return exact.Get([this]() -> ZV4 {
    switch (kind) {
      case Kind::kInput:
        return InputExact(input);
      case Kind::kLinePlane:
        return LinePlanePoint(p->Exact(), q->Exact(), planes[0]->Exact());
      case Kind::kThreePlanes:
        break;
    }
    if (const XPoint* apex = SharedApex(*planes[1], *planes[2])) {
      return PencilPoint(planes[0]->Exact(), planes[1]->Exact(), planes[2]->Exact(), apex->Exact());
    }
    return Cross4(planes[0]->Exact(), planes[1]->Exact(), planes[2]->Exact());
  });
}

glm::dvec3 XPoint::Euclid() const {
  if (has_euclid) return euclid;
  // The interval midpoint is good to about the interval width; when that is
  // poor relative to the point (worse than 1e-11 of its size: near-degenerate
  // intersections), convert the exact value instead. 1e-11 keeps areas far
  // inside the 1e-9 we promise, while typical interval widths (1e-14 after
  // ~100 operations) stay clear of the slow path.
  double mid[4], width[4];
  for (int i = 0; i < 4; ++i) {
    mid[i] = approx[i].mid;
    width[i] = 2.0 * approx[i].rad;
  }
  const double w = mid[3];
  const double rel_w = std::fabs(w) > 0.0 ? width[3] / std::fabs(w) : 1.0;
  glm::dvec3 e(mid[0] / w, mid[1] / w, mid[2] / w);
  double err = 0.0, scale = 0.0;
  for (int i = 0; i < 3; ++i) {
    err = std::max(err, (width[i] + std::fabs(mid[i]) * rel_w) / std::fabs(w));
    scale = std::max(scale, std::fabs(e[i]));
  }
  if (rel_w < 1e-9 && std::isfinite(err) && err <= 1e-11 * scale) {
    euclid = e;
  } else {
    // Each integer as a double in [0.5, 1) times a power of two (truncated,
    // within an ulp): the ratio within a few ulps, with no gcd of integers
    // hundreds of bits long.
    const ZV4& q = Exact();
    long w_exp = 0;
    const double w_mantissa = mpz_get_d_2exp(&w_exp, q[3].get_mpz_t());
    for (int i = 0; i < 3; ++i) {
      long exp = 0;
      const double mantissa = mpz_get_d_2exp(&exp, q[i].get_mpz_t());
      euclid[i] = std::ldexp(mantissa / w_mantissa, static_cast<int>(exp - w_exp));
    }
  }
  has_euclid = true;
  return euclid;
}

// ---------------------------------------------------------------------------
XPlane XPlane::ThroughPoints(const XPoint& p, const XPoint& q, const XPoint& r) {
  XPlane out;
  out.kind = Kind::kThroughPoints;
  out.points[0] = &p;
  out.points[1] = &q;
  out.points[2] = &r;
  if (p.kind == XPoint::Kind::kInput && q.kind == XPoint::Kind::kInput &&
      r.kind == XPoint::Kind::kInput) {
    // The common case, 4x cheaper than Cross4: for w = 1 rows,
    // det4(p, q, r, x) = -n . (x - p) with n = (q - p) x (r - p).
    const IV4& a = p.approx;
    const Iv u0 = q.approx[0] - a[0], u1 = q.approx[1] - a[1], u2 = q.approx[2] - a[2];
    const Iv v0 = r.approx[0] - a[0], v1 = r.approx[1] - a[1], v2 = r.approx[2] - a[2];
    const Iv n0 = u1 * v2 - u2 * v1, n1 = u2 * v0 - u0 * v2, n2 = u0 * v1 - u1 * v0;
    out.approx = IV4{{-n0, -n1, -n2, n0 * a[0] + n1 * a[1] + n2 * a[2]}};
  } else {
    out.approx = Cross4(p.approx, q.approx, r.approx);
  }
  // Dot4(coeffs, x) = det4(p, q, r, x) = -wp wq wr wx orient3d(p, q, r, x).
  out.o_sign = static_cast<int8_t>(-p.w_sign * q.w_sign * r.w_sign);
  out.fast = PlaneFilter::From(out.approx);
  return out;
}

XPlane XPlane::ParallelThrough(const XPlane& base, const XPoint& point) {
  XPlane out;
  out.kind = Kind::kParallelThrough;
  out.base = &base;
  out.points[0] = &point;
  const IV4& b = base.approx;
  const IV4& x = point.approx;
  out.approx[0] = b[0] * x[3];
  out.approx[1] = b[1] * x[3];
  out.approx[2] = b[2] * x[3];
  out.approx[3] = -(b[0] * x[0] + b[1] * x[1] + b[2] * x[2]);
  // For Euclidean y: Dot4 = w_x * (b . (y - x)), and the base's natural
  // function grows along o_sign(base) * b.
  out.o_sign = static_cast<int8_t>(base.o_sign * point.w_sign);
  out.fast = PlaneFilter::From(out.approx);
  return out;
}

XPlane XPlane::PointNormal(const XPoint& point, const glm::dvec3& normal) {
  VISQ_CHECK(point.kind == XPoint::Kind::kInput);
  XPlane out;
  out.kind = Kind::kPointNormal;
  out.points[0] = &point;
  out.normal = normal;
  const IV4& x = point.approx;
  out.approx[0] = Iv(normal.x);
  out.approx[1] = Iv(normal.y);
  out.approx[2] = Iv(normal.z);
  out.approx[3] = -(Iv(normal.x) * x[0] + Iv(normal.y) * x[1] + Iv(normal.z) * x[2]);
  out.o_sign = 1;
  out.fast = PlaneFilter::From(out.approx);
  return out;
}

const ZV4& XPlane::Exact() const {
  return exact.Get([this]() -> ZV4 {
    ZV4 r;
    switch (kind) {
      case Kind::kThroughPoints: {
        const XPoint *p = points[0], *q = points[1], *s = points[2];
        if (p->kind != XPoint::Kind::kInput || q->kind != XPoint::Kind::kInput || s->kind != XPoint::Kind::kInput) {
          return Cross4(p->Exact(), q->Exact(), s->Exact());
        }
        // Three input points, as the interval is made (ThroughPoints): on
        // one scale W (p = p' / W), n' = (q' - p') x (s' - p') and the
        // coefficients (-W n', n' . p'), W^3 times the interval's (-n, n . p):
        // 12 products where Cross4 of the points' own scales takes 36 and
        // more, and a grille's crossings of nearly parallel edge planes make
        // a few such planes exact each query (XPoint::Euclid).
        std::array<mpz_class, 10> z;
        ToCommonIntegers(std::array<double, 10>{p->input.x, p->input.y, p->input.z, q->input.x, q->input.y,
                                                q->input.z, s->input.x, s->input.y, s->input.z, 1.0},
                         &z);
        const mpz_class u0 = z[3] - z[0], u1 = z[4] - z[1], u2 = z[5] - z[2];
        const mpz_class v0 = z[6] - z[0], v1 = z[7] - z[1], v2 = z[8] - z[2];
        const mpz_class n0 = u1 * v2 - u2 * v1, n1 = u2 * v0 - u0 * v2, n2 = u0 * v1 - u1 * v0;
        r[0] = -(z[9] * n0);
        r[1] = -(z[9] * n1);
        r[2] = -(z[9] * n2);
        r[3] = n0 * z[0] + n1 * z[1] + n2 * z[2];
        return r;
      }
      case Kind::kParallelThrough: {
        const ZV4& b = base->Exact();
        const ZV4& x = points[0]->Exact();
        r[0] = b[0] * x[3];
        r[1] = b[1] * x[3];
        r[2] = b[2] * x[3];
        r[3] = -(b[0] * x[0] + b[1] * x[1] + b[2] * x[2]);
        return r;
      }
      case Kind::kPointNormal:
        break;
    }
    // n . (y - x) for the integer multiple N of the normal and x = X / w:
    // w N . y - N . X, a positive multiple of the interval's coefficients.
    const ZV4& x = points[0]->Exact();
    std::array<mpz_class, 3> n;
    ToCommonIntegers(std::array<double, 3>{normal.x, normal.y, normal.z}, &n);
    for (int i = 0; i < 3; ++i) r[i] = n[i] * x[3];
    r[3] = -(n[0] * x[0] + n[1] * x[1] + n[2] * x[2]);
    return r;
  });
}

bool XPlane::Degenerate() const {
  bool maybe_zero = true, certainly_zero = true;
  for (int i = 0; i < 4; ++i) {
    maybe_zero &= SignOf(approx[i]) == 0 || SignOf(approx[i]) == kUncertain;
    certainly_zero &= SignOf(approx[i]) == 0;
  }
  if (!maybe_zero) return false;
  if (certainly_zero) return true;
  for (int i = 0; i < 4; ++i) {
    if (sgn(Exact()[i]) != 0) return false;
  }
  return true;
}

int EuclidSideSlow(const XPoint& x, const XPlane& plane) {
  const int s = SignOfDot(
      plane.approx, x.approx, [&]() -> const ZV4& { return plane.Exact(); },
      [&]() -> const ZV4& { return x.Exact(); });
  return s * x.w_sign * plane.o_sign;
}

int Orient3d(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, const glm::dvec3& d) {
  // Repeated points (shared mesh vertices) make the exact answer zero; catch
  // them before the filter, which cannot certify a zero.
  if (a == b || a == c || a == d || b == c || b == d || c == d) return 0;
  // So do four points in one axis-aligned plane (boxes, floors, lights).
  for (int i = 0; i < 3; ++i) {
    if (a[i] == b[i] && a[i] == c[i] && a[i] == d[i]) return 0;
  }
  const double ux = b.x - a.x, uy = b.y - a.y, uz = b.z - a.z;
  const double vx = c.x - a.x, vy = c.y - a.y, vz = c.z - a.z;
  const double wx = d.x - a.x, wy = d.y - a.y, wz = d.z - a.z;
  const double m0 = vy * wz, m1 = vz * wy, m2 = wy * uz, m3 = wz * uy, m4 = uy * vz, m5 = uz * vy;
  const double det = ux * (m0 - m1) + vx * (m2 - m3) + wx * (m4 - m5);
  const double permanent = (std::fabs(m0) + std::fabs(m1)) * std::fabs(ux) +
                           (std::fabs(m2) + std::fabs(m3)) * std::fabs(vx) +
                           (std::fabs(m4) + std::fabs(m5)) * std::fabs(wx);
  const double bound = kOrient3dFilter * permanent;
  if (det > bound) return 1;
  if (-det > bound) return -1;
  // Second stage: the same expression in exactness-tracking intervals, which
  // settles exact zeros of nicely placed points (coplanar box faces).
  {
    const Iv iux = Iv(b.x) - Iv(a.x), iuy = Iv(b.y) - Iv(a.y), iuz = Iv(b.z) - Iv(a.z);
    const Iv ivx = Iv(c.x) - Iv(a.x), ivy = Iv(c.y) - Iv(a.y), ivz = Iv(c.z) - Iv(a.z);
    const Iv iwx = Iv(d.x) - Iv(a.x), iwy = Iv(d.y) - Iv(a.y), iwz = Iv(d.z) - Iv(a.z);
    const int s = SignOf(Det3(iux, iuy, iuz, ivx, ivy, ivz, iwx, iwy, iwz));
    if (s != kUncertain) return s;
  }
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  std::array<mpz_class, 12> z;
  ToCommonIntegers(std::array<double, 12>{a.x, a.y, a.z, b.x, b.y, b.z, c.x, c.y, c.z, d.x, d.y, d.z}, &z);
  const mpz_class ux_ = z[3] - z[0], uy_ = z[4] - z[1], uz_ = z[5] - z[2];
  const mpz_class vx_ = z[6] - z[0], vy_ = z[7] - z[1], vz_ = z[8] - z[2];
  const mpz_class wx_ = z[9] - z[0], wy_ = z[10] - z[1], wz_ = z[11] - z[2];
  const mpz_class q = ux_ * (vy_ * wz_ - vz_ * wy_) + vx_ * (wy_ * uz_ - wz_ * uy_) +
                      wx_ * (uy_ * vz_ - uz_ * vy_);
  return sgn(q);
}

int Orient2d(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, int i, int j) {
  // Shared coordinates make exact zeros that no filter can certify.
  if ((a[i] == b[i] && a[i] == c[i]) || (a[j] == b[j] && a[j] == c[j])) return 0;
  const double detleft = (b[i] - a[i]) * (c[j] - a[j]);
  const double detright = (b[j] - a[j]) * (c[i] - a[i]);
  const double det = detleft - detright;
  const double bound = kOrient2dFilter * (std::fabs(detleft) + std::fabs(detright));
  if (det > bound) return 1;
  if (-det > bound) return -1;
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  std::array<mpz_class, 6> z;
  ToCommonIntegers(std::array<double, 6>{a[i], a[j], b[i], b[j], c[i], c[j]}, &z);
  const mpz_class q = (z[2] - z[0]) * (z[5] - z[1]) - (z[3] - z[1]) * (z[4] - z[0]);
  return sgn(q);
}

}  // namespace visq::exact::detail
