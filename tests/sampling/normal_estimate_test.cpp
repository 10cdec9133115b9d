// The quantiles the stated estimates use (common/normal_estimate.h): the
// normal's and Student's t against published tables, the t's closed form
// against its definition, and both sides of the expansion's switch.
#include "common/normal_estimate.h"

#include <cmath>

#include <gtest/gtest.h>

namespace visq {
namespace {

TEST(NormalEstimate, NormalQuantileMatchesTheTable) {
  EXPECT_NEAR(TwoSidedNormalQuantile(0.95), 1.959964, 1e-6);
  EXPECT_NEAR(TwoSidedNormalQuantile(0.99), 2.575829, 1e-6);
  EXPECT_TRUE(std::isinf(TwoSidedNormalQuantile(1.0)));
}

// Two-sided 95 % and 99 % points of Student's t (Fisher & Yates's table,
// to the table's 3 decimals), across the closed form's range and beyond.
TEST(NormalEstimate, StudentQuantileMatchesTheTable) {
  struct Row {
    int dof;
    double at95, at99;
  };
  for (const Row& row : {Row{1, 12.706, 63.657}, Row{2, 4.303, 9.925}, Row{3, 3.182, 5.841}, Row{5, 2.571, 4.032},
                         Row{10, 2.228, 3.169}, Row{30, 2.042, 2.750}, Row{60, 2.000, 2.660}, Row{120, 1.980, 2.617}}) {
    EXPECT_NEAR(TwoSidedStudentQuantile(0.95, row.dof), row.at95, 6e-4) << row.dof;
    EXPECT_NEAR(TwoSidedStudentQuantile(0.99, row.dof), row.at99, 6e-4) << row.dof;
  }
  EXPECT_NEAR(TwoSidedStudentQuantile(0.95, 1000000), TwoSidedNormalQuantile(0.95), 1e-5);
  EXPECT_TRUE(std::isinf(TwoSidedStudentQuantile(0.95, 0)));
  EXPECT_TRUE(std::isinf(TwoSidedStudentQuantile(0.0, 5)));
}

// The closed form is the t density's integral (Simpson on a fine grid), and
// the expansion beyond 64 degrees of freedom meets the bisection at 64.
TEST(NormalEstimate, StudentMassIsTheDensitysIntegral) {
  for (int dof : {1, 2, 3, 4, 7, 12, 40, 64}) {
    const double nu = dof, scale = std::exp(std::lgamma((nu + 1) / 2) - std::lgamma(nu / 2)) / std::sqrt(nu * M_PI);
    auto density = [&](double t) { return scale * std::pow(1 + t * t / nu, -(nu + 1) / 2); };
    for (double t : {0.3, 1.0, 2.0, 4.5}) {
      const int steps = 20000;
      double sum = density(0) + density(t);
      for (int k = 1; k < steps; ++k) sum += (k % 2 ? 4 : 2) * density(t * k / steps);
      EXPECT_NEAR(StudentTwoSidedMass(t, dof), 2 * sum * t / (3 * steps), 1e-9) << dof << " " << t;
    }
  }
  for (double confidence : {0.9, 0.95, 0.99}) {
    const double at64 = TwoSidedStudentQuantile(confidence, 64), at65 = TwoSidedStudentQuantile(confidence, 65);
    EXPECT_GT(at64, at65);
    EXPECT_LT(at64 - at65, 2e-3) << "the expansion beyond 64 meets the bisection";
    EXPECT_NEAR(StudentTwoSidedMass(at65, 65), confidence, 5e-6);
  }
}

}  // namespace
}  // namespace visq
