// Invariant checks that print the values involved (pbrt-v4 style). They guard
// programming errors, not user input: user input gets a Status.
#pragma once

#include <cstdlib>
#include <sstream>
#include <spdlog/spdlog.h>

namespace visq::detail {
[[noreturn]] inline void CheckFailed(const char* file, int line, const std::string& what) {
  spdlog::critical("{}:{}: check failed: {}", file, line, what);
  std::abort();
}
template <typename A, typename B>
std::string DescribeComparison(const char* text, const A& a, const B& b) {
  std::ostringstream out;
  out << text << " (" << a << " vs " << b << ")";
  return out.str();
}
}  // namespace visq::detail

#define VISQ_CHECK(cond) \
  do { if (!(cond)) ::visq::detail::CheckFailed(__FILE__, __LINE__, #cond); } while (false)
#define VISQ_CHECK_OP(a, op, b)                                                        \
  do {                                                                                 \
    const auto& visq_a_ = (a);                                                         \
    const auto& visq_b_ = (b);                                                         \
    if (!(visq_a_ op visq_b_))                                                         \
      ::visq::detail::CheckFailed(                                                     \
          __FILE__, __LINE__,                                                          \
          ::visq::detail::DescribeComparison(#a " " #op " " #b, visq_a_, visq_b_));    \
  } while (false)
#define VISQ_CHECK_EQ(a, b) VISQ_CHECK_OP(a, ==, b)
#define VISQ_CHECK_LT(a, b) VISQ_CHECK_OP(a, <, b)
#define VISQ_CHECK_LE(a, b) VISQ_CHECK_OP(a, <=, b)

// Debug checks: on in debug builds and in the optimized builds visq.sh
// makes (VISQ_DCHECKS=ON for serve and test alike, so they share one build;
// a few dozen value checks at invariants, none per ray or fragment); off in
// a build configured without it.
#if !defined(NDEBUG) || defined(VISQ_ENABLE_DCHECKS)
#define VISQ_DCHECK(cond) VISQ_CHECK(cond)
#define VISQ_DCHECK_EQ(a, b) VISQ_CHECK_EQ(a, b)
#define VISQ_DCHECK_LT(a, b) VISQ_CHECK_LT(a, b)
#define VISQ_DCHECK_LE(a, b) VISQ_CHECK_LE(a, b)
#else
#define VISQ_DCHECK(cond) do { (void)sizeof(cond); } while (false)
#define VISQ_DCHECK_EQ(a, b) do { (void)sizeof(a); (void)sizeof(b); } while (false)
#define VISQ_DCHECK_LT(a, b) do { (void)sizeof(a); (void)sizeof(b); } while (false)
#define VISQ_DCHECK_LE(a, b) do { (void)sizeof(a); (void)sizeof(b); } while (false)
#endif
