// The exact predicates of lib/exact/exact_geometry.h on their own: the
// filters never decide a sign the exact (GMP) values would not, at any scale
// and distance from the origin, and the error constants (lib/exact/rounding.h)
// are the values they were derived to be.
#include "exact/exact_geometry.h"

#include <random>

#include <gtest/gtest.h>

#include "exact/rounding.h"

namespace visq::exact {
namespace {

// Shewchuk's published first-stage bounds, and the typed constants the
// derived ones replaced (each derived one at most the typed one: the typed
// decimals were rounded up).
TEST(ExactPredicatesTest, ErrorConstantsAreTheirDerivations) {
  EXPECT_EQ(kUnitRoundoff, 0x1p-53);
  EXPECT_EQ(kOrient3dFilter, 7.7715611723761027e-16);
  EXPECT_EQ(kOrient2dFilter, 3.3306690738754716e-16);
  for (int n : {3, 4, 5, 18, 36}) {
    const double nu = n * 0x1p-53;
    EXPECT_GE(Gamma(n), nu / (1.0 - nu)) << n;
    EXPECT_LE(Gamma(n), nu / (1.0 - nu) * (1.0 + 1e-15)) << n;
  }
  EXPECT_LE(Gamma(4), 4.5e-16);
  EXPECT_LE(Gamma(3), 3.4e-16);
  EXPECT_LE(kFanNormalError, 5.6e-16);
  EXPECT_GT(kFanNormalError, 4.0 * 0x1p-53 * (1.0 + 2.0 * 0x1p-53) / (1.0 - 2.0 * 0x1p-53));
  EXPECT_LE(kDotFilterRounding, 1.0 + 4e-15);
  EXPECT_GE(kDotFilterRounding, 1.0 + 24 * 0x1p-53);
  EXPECT_LE(kOffsetRadiusRounding, 1.0 + 2e-15);
}

TEST(ExactPredicatesTest, HomogeneousPlanesAgreeWithOrient3d) {
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < 1000; ++i) {
    glm::dvec3 a(u(rng), u(rng), u(rng)), b(u(rng), u(rng), u(rng)), c(u(rng), u(rng), u(rng)),
        d(u(rng), u(rng), u(rng));
    if (i % 10 == 0) d = a + 0.5 * (b - a) + 0.25 * (c - a);  // nearly or exactly coplanar
    const auto pa = detail::XPoint::Input(a), pb = detail::XPoint::Input(b),
               pc = detail::XPoint::Input(c), pd = detail::XPoint::Input(d);
    const auto plane = detail::XPlane::ThroughPoints(pa, pb, pc);
    EXPECT_EQ(detail::EuclidSide(pd, plane), detail::Orient3d(a, b, c, d)) << i;
  }
  // A derived point exactly on a plane is classified 0, not by rounding.
  const auto p0 = detail::XPoint::Input({0.1, 0.2, 0.3}), p1 = detail::XPoint::Input({0.7, -0.3, 0.9});
  const auto q0 = detail::XPoint::Input({0.3, 0.1, 0.0}), q1 = detail::XPoint::Input({0.0, 0.7, 0.2}),
             q2 = detail::XPoint::Input({0.9, 0.9, 1.0});
  const auto plane = detail::XPlane::ThroughPoints(q0, q1, q2);
  const auto x = detail::XPoint::LinePlane(p0, p1, plane);
  EXPECT_EQ(detail::EuclidSide(x, plane), 0);
}

TEST(ExactPredicatesTest, Orient3dFanAgreesWithOrient3d) {
  // Random, nearly coplanar, exactly coplanar, repeated points, and the same
  // at tiny and huge scales and far from the origin: the fan's filter must
  // never decide a sign Orient3d would not.
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> u(-1, 1);
  int zeros = 0;
  for (const double scale : {1e-4, 1.0, 1e5}) {
    for (const double offset : {0.0, 1e6}) {
      for (int i = 0; i < 400; ++i) {
        auto point = [&]() { return offset + scale * glm::dvec3(u(rng), u(rng), u(rng)); };
        const glm::dvec3 p = point(), a = point(), b = point();
        const detail::Orient3dFan fan(p, a, b);
        for (int k = 0; k < 6; ++k) {
          glm::dvec3 x = point();
          if (k == 1) x = p + 0.5 * (a - p) + 0.25 * (b - p);  // on the plane, up to rounding
          if (k == 2) x = a;                                   // a repeated point: exactly 0
          if (k == 3) x = glm::dvec3(p.x, p.y, a.z);           // shares coordinates
          if (k == 4) x = p + (a - p) * 3.0;                   // on the line (p, a), up to rounding
          const int expected = detail::Orient3d(p, a, b, x);
          EXPECT_EQ(fan.Side(x), expected) << scale << " " << offset << " " << i << " " << k;
          zeros += expected == 0;
        }
      }
    }
  }
  EXPECT_GT(zeros, 2400);  // the repeated points at least
}

// The exact sign of orient3d(p, a, b, x) for a derived point x, from the
// GMP values alone: Dot4 of ThroughPoints(p, a, b) with x is -w orient3d.
int ExactOrient(const detail::XPlane& through, const detail::XPoint& x) {
  return -sgn(detail::Dot4(through.Exact(), x.Exact())) * sgn(x.Exact()[3]);
}

TEST(ExactPredicatesTest, IntervalsAndFanFiltersAgreeWithExactSignsNearAPlane) {
  // Derived points on a plane tilted from (p, a, b) by a relative 1e-9 to
  // 1e-16 lie a hair off it: the intervals (midpoint-radius) and the fan's
  // plane filter must decide no sign the exact values do not (the closest
  // are beyond doubles, so a third or so of them go to the exact values);
  // at tiny and huge scales and far from the origin.
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  int decided_by_filter = 0, cases = 0;
  for (const double scale : {1e-4, 1.0, 1e5}) {
    for (const double offset : {0.0, 1e6}) {
      for (int i = 0; i < 200; ++i) {
        auto point = [&]() { return offset + scale * glm::dvec3(u(rng), u(rng), u(rng)); };
        const glm::dvec3 p = point(), a = point(), b = point();
        const double tilt = std::pow(10.0, -9.0 - 7.0 * (i % 8) / 7.0);
        const glm::dvec3 b_tilted = b + tilt * scale * glm::dvec3(u(rng), u(rng), u(rng));
        const auto pp = detail::XPoint::Input(p), pa = detail::XPoint::Input(a), pb = detail::XPoint::Input(b),
                   pbt = detail::XPoint::Input(b_tilted);
        const auto through = detail::XPlane::ThroughPoints(pp, pa, pb);
        const auto tilted = detail::XPlane::ThroughPoints(pp, pa, pbt);
        const detail::PlaneFilter filter = detail::Orient3dFan(p, a, b).Filter();
        for (int k = 0; k < 4; ++k) {
          // A segment across the tilted plane, cut by it.
          const glm::dvec3 mid = p + u(rng) * (a - p) + u(rng) * (b - p);
          const glm::dvec3 normal = glm::cross(a - p, b - p);
          const glm::dvec3 q = mid + 0.3 * scale * glm::normalize(normal) + 0.1 * scale * glm::dvec3(u(rng), u(rng), u(rng));
          const glm::dvec3 r = mid - 0.3 * scale * glm::normalize(normal) + 0.1 * scale * glm::dvec3(u(rng), u(rng), u(rng));
          const auto pq = detail::XPoint::Input(q), pr = detail::XPoint::Input(r);
          if (detail::EuclidSide(pq, tilted) * detail::EuclidSide(pr, tilted) >= 0) continue;
          const auto x = detail::XPoint::LinePlane(pq, pr, tilted);
          const int expected = ExactOrient(through, x);
          ++cases;
          EXPECT_EQ(detail::EuclidSide(x, through), expected) << scale << " " << offset << " " << i << " " << k;
          const int fast = detail::FastSignOfDot(filter, x.fast);
          if (fast != detail::kUncertain) {
            ++decided_by_filter;
            EXPECT_EQ(fast * x.w_sign, expected) << scale << " " << offset << " " << i << " " << k;
          }
        }
      }
    }
  }
  EXPECT_GT(cases, 3000);
  EXPECT_GT(decided_by_filter, cases / 4);
}

TEST(ExactPredicatesTest, ParallelSideAgreesWithTheExactParallelPlane) {
  // The side of x against the plane through `base` parallel to (p, a, b),
  // for x near that plane: the fan's double test, where it decides, is the
  // exact ParallelThrough plane's.
  std::mt19937 rng(4);
  std::uniform_real_distribution<double> u(-1, 1);
  int decided = 0, total = 0;
  for (const double scale : {1e-4, 1.0, 1e5}) {
    for (const double offset : {0.0, 1e6}) {
      for (int i = 0; i < 300; ++i) {
        auto point = [&]() { return offset + scale * glm::dvec3(u(rng), u(rng), u(rng)); };
        const glm::dvec3 p = point(), a = point(), b = point(), base = point();
        const detail::Orient3dFan fan(p, a, b);
        const auto pp = detail::XPoint::Input(p), pa = detail::XPoint::Input(a), pb = detail::XPoint::Input(b),
                   pbase = detail::XPoint::Input(base);
        const auto through = detail::XPlane::ThroughPoints(pp, pa, pb);
        const auto parallel = detail::XPlane::ParallelThrough(through, pbase);
        const glm::dvec3 normal = glm::normalize(glm::cross(a - p, b - p));
        for (int k = 0; k < 4; ++k) {
          const double lift = k == 0 ? 0.0 : std::pow(10.0, -4.0 * k) * scale * u(rng);
          const glm::dvec3 x = base + u(rng) * (a - p) + u(rng) * (b - p) + lift * normal;
          const auto px = detail::XPoint::Input(x);
          const int expected = sgn(detail::Dot4(parallel.Exact(), px.Exact())) * parallel.o_sign;
          EXPECT_EQ(detail::EuclidSide(px, parallel), expected) << scale << " " << offset << " " << i << " " << k;
          const int fast = fan.ParallelSide(base, x);
          ++total;
          if (fast != detail::kUncertain) {
            ++decided;
            EXPECT_EQ(fast, expected) << scale << " " << offset << " " << i << " " << k;
          }
        }
      }
    }
  }
  EXPECT_GT(decided, total / 2);
}

}  // namespace
}  // namespace visq::exact
