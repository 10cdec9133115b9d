// The process's pool: every index exactly once, chunks as asked, the
// thread cap kept, and loops that nest (a loop inside a pool thread's
// chunk) finish.
#include "common/parallel.h"

#include <atomic>
#include <mutex>
#include <set>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

namespace visq::core {
namespace {

TEST(ParallelFor, VisitsEveryIndexOnceInChunksOfTheGrain) {
  for (const size_t count : {size_t{0}, size_t{1}, size_t{7}, size_t{1000}, size_t{100003}}) {
    std::vector<std::atomic<int>> visits(count);
    std::atomic<size_t> oversized{0};
    ParallelFor(count, 64, [&](size_t begin, size_t end) {
      if (end - begin > 64 || begin % 64 != 0) oversized.fetch_add(1);
      for (size_t i = begin; i < end; ++i) visits[i].fetch_add(1);
    });
    EXPECT_EQ(oversized.load(), 0u) << count;
    for (size_t i = 0; i < count; ++i) ASSERT_EQ(visits[i].load(), 1) << "index " << i << " of " << count;
  }
}

TEST(ParallelFor, OneThreadRunsOnTheCaller) {
  std::set<std::thread::id> threads;
  std::mutex mutex;
  ParallelFor(5000, 10, [&](size_t, size_t) {
    std::lock_guard lock(mutex);
    threads.insert(std::this_thread::get_id());
  }, /*max_threads=*/1);
  ASSERT_EQ(threads.size(), 1u);
  EXPECT_EQ(*threads.begin(), std::this_thread::get_id());
}

TEST(ParallelFor, NestedLoopsFinish) {
  std::atomic<uint64_t> sum{0};
  ParallelFor(64, 1, [&](size_t outer, size_t) {
    ParallelFor(1000, 7, [&](size_t begin, size_t end) {
      for (size_t i = begin; i < end; ++i) sum.fetch_add(outer * 1000 + i);
    });
  });
  const uint64_t n = 64 * 1000;
  EXPECT_EQ(sum.load(), n * (n - 1) / 2);
}

TEST(ParallelFor, ConcurrentCallersShareThePool) {
  std::atomic<uint64_t> total{0};
  std::vector<std::thread> callers;
  for (int c = 0; c < 4; ++c)
    callers.emplace_back([&] {
      ParallelFor(10000, 16, [&](size_t begin, size_t end) { total.fetch_add(end - begin); });
    });
  for (std::thread& t : callers) t.join();
  EXPECT_EQ(total.load(), 40000u);
  EXPECT_GE(ParallelWorkers(), 1u);
}

}  // namespace
}  // namespace visq::core
