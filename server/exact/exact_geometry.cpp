#include "exact/exact_geometry.h"

#include "common/check.h"

namespace visq::exact::detail {
namespace {

IV4 InputInterval(const glm::dvec3& x) { return IV4{{Iv(x.x), Iv(x.y), Iv(x.z), Iv(1.0)}}; }

QV4 InputExact(const glm::dvec3& x) {
  return QV4{{mpq_class(x.x), mpq_class(x.y), mpq_class(x.z), mpq_class(1)}};
}

// Sign of Dot4(a, b) from intervals, or exactly from the given thunks.
template <typename ExactA, typename ExactB>
int SignOfDot(const IV4& a, const IV4& b, const ExactA& exact_a, const ExactB& exact_b) {
  const int s = SignOf(Dot4(a, b));
  if (s != kUncertain) return s;
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  return SignOf(mpq_class(Dot4(exact_a(), exact_b())));
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
  out.w_sign = ExactWSign(out);
  VISQ_CHECK(out.w_sign != 0);
  return out;
}

XPoint XPoint::ThreePlanes(const XPlane& a, const XPlane& b, const XPlane& c) {
  XPoint out;
  out.kind = Kind::kThreePlanes;
  out.planes[0] = &a;
  out.planes[1] = &b;
  out.planes[2] = &c;
  out.approx = Cross4(a.approx, b.approx, c.approx);
  out.w_sign = ExactWSign(out);
  VISQ_CHECK(out.w_sign != 0);
  return out;
}

const QV4& XPoint::Exact() const {
  if (exact) return *exact;
  switch (kind) {
    case Kind::kInput:
      exact = std::make_unique<QV4>(InputExact(input));
      break;
    case Kind::kLinePlane:
      exact = std::make_unique<QV4>(LinePlanePoint(p->Exact(), q->Exact(), planes[0]->Exact()));
      break;
    case Kind::kThreePlanes:
      exact = std::make_unique<QV4>(
          Cross4(planes[0]->Exact(), planes[1]->Exact(), planes[2]->Exact()));
      break;
  }
  return *exact;
}

glm::dvec3 XPoint::Euclid() const {
  if (has_euclid) return euclid;
  // The interval midpoint is good to about the interval width; when that is
  // poor relative to the point (near-degenerate intersections), convert the
  // exact value instead.
  double mid[4], width[4];
  for (int i = 0; i < 4; ++i) {
    mid[i] = 0.5 * (approx[i].lo + approx[i].hi);
    width[i] = approx[i].hi - approx[i].lo;
  }
  const double w = mid[3];
  const double rel_w = std::fabs(w) > 0.0 ? width[3] / std::fabs(w) : 1.0;
  glm::dvec3 e(mid[0] / w, mid[1] / w, mid[2] / w);
  double err = 0.0, scale = 0.0;
  for (int i = 0; i < 3; ++i) {
    err = std::max(err, (width[i] + std::fabs(mid[i]) * rel_w) / std::fabs(w));
    scale = std::max(scale, std::fabs(e[i]));
  }
  if (rel_w < 1e-6 && std::isfinite(err) && err <= 1e-13 * scale) {
    euclid = e;
  } else {
    const QV4& q = Exact();
    for (int i = 0; i < 3; ++i) euclid[i] = mpq_class(q[i] / q[3]).get_d();
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
  out.approx = Cross4(p.approx, q.approx, r.approx);
  // Dot4(coeffs, x) = det4(p, q, r, x) = -wp wq wr wx orient3d(p, q, r, x).
  out.o_sign = static_cast<int8_t>(-p.w_sign * q.w_sign * r.w_sign);
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
  return out;
}

const QV4& XPlane::Exact() const {
  if (exact) return *exact;
  switch (kind) {
    case Kind::kThroughPoints:
      exact = std::make_unique<QV4>(
          Cross4(points[0]->Exact(), points[1]->Exact(), points[2]->Exact()));
      break;
    case Kind::kParallelThrough: {
      const QV4& b = base->Exact();
      const QV4& x = points[0]->Exact();
      QV4 r;
      r[0] = b[0] * x[3];
      r[1] = b[1] * x[3];
      r[2] = b[2] * x[3];
      r[3] = -(b[0] * x[0] + b[1] * x[1] + b[2] * x[2]);
      exact = std::make_unique<QV4>(std::move(r));
      break;
    }
    case Kind::kPointNormal: {
      const QV4& x = points[0]->Exact();
      QV4 r;
      r[0] = normal.x;
      r[1] = normal.y;
      r[2] = normal.z;
      r[3] = -(r[0] * x[0] + r[1] * x[1] + r[2] * x[2]);
      exact = std::make_unique<QV4>(std::move(r));
      break;
    }
  }
  return *exact;
}

bool XPlane::Degenerate() const {
  bool maybe_zero = true;
  for (int i = 0; i < 4; ++i) maybe_zero &= SignOf(approx[i]) == 0 || SignOf(approx[i]) == kUncertain;
  if (!maybe_zero) return false;
  for (int i = 0; i < 4; ++i) {
    if (sgn(Exact()[i]) != 0) return false;
  }
  return true;
}

int EuclidSide(const XPoint& x, const XPlane& plane) {
  const int s = SignOfDot(
      plane.approx, x.approx, [&]() -> const QV4& { return plane.Exact(); },
      [&]() -> const QV4& { return x.Exact(); });
  return s * x.w_sign * plane.o_sign;
}

// ---------------------------------------------------------------------------
int Orient3d(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, const glm::dvec3& d) {
  // Repeated points (shared mesh vertices) make the exact answer zero; catch
  // them before the filter, which cannot certify a zero.
  if (a == b || a == c || a == d || b == c || b == d || c == d) return 0;
  const double ux = b.x - a.x, uy = b.y - a.y, uz = b.z - a.z;
  const double vx = c.x - a.x, vy = c.y - a.y, vz = c.z - a.z;
  const double wx = d.x - a.x, wy = d.y - a.y, wz = d.z - a.z;
  const double m0 = vy * wz, m1 = vz * wy, m2 = wy * uz, m3 = wz * uy, m4 = uy * vz, m5 = uz * vy;
  const double det = ux * (m0 - m1) + vx * (m2 - m3) + wx * (m4 - m5);
  const double permanent = (std::fabs(m0) + std::fabs(m1)) * std::fabs(ux) +
                           (std::fabs(m2) + std::fabs(m3)) * std::fabs(vx) +
                           (std::fabs(m4) + std::fabs(m5)) * std::fabs(wx);
  const double bound = 7.7715611723761027e-16 * permanent;  // (7 + 56 eps) eps
  if (det > bound) return 1;
  if (-det > bound) return -1;
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  const mpq_class qux = mpq_class(b.x) - a.x, quy = mpq_class(b.y) - a.y, quz = mpq_class(b.z) - a.z;
  const mpq_class qvx = mpq_class(c.x) - a.x, qvy = mpq_class(c.y) - a.y, qvz = mpq_class(c.z) - a.z;
  const mpq_class qwx = mpq_class(d.x) - a.x, qwy = mpq_class(d.y) - a.y, qwz = mpq_class(d.z) - a.z;
  const mpq_class q = qux * (qvy * qwz - qvz * qwy) + qvx * (qwy * quz - qwz * quy) +
                      qwx * (quy * qvz - quz * qvy);
  return sgn(q);
}

int Orient2d(const glm::dvec3& a, const glm::dvec3& b, const glm::dvec3& c, int i, int j) {
  const double detleft = (b[i] - a[i]) * (c[j] - a[j]);
  const double detright = (b[j] - a[j]) * (c[i] - a[i]);
  const double det = detleft - detright;
  const double bound = 3.3306690738754716e-16 * (std::fabs(detleft) + std::fabs(detright));
  if (det > bound) return 1;
  if (-det > bound) return -1;
  g_exact_fallbacks.fetch_add(1, std::memory_order_relaxed);
  const mpq_class q = (mpq_class(b[i]) - a[i]) * (mpq_class(c[j]) - a[j]) -
                      (mpq_class(b[j]) - a[j]) * (mpq_class(c[i]) - a[i]);
  return sgn(q);
}

}  // namespace visq::exact::detail
