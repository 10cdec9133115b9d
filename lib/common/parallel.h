// Loops spread over the machine's cores through one persistent pool for the
// whole process: a request starts no threads of its own, and requests that
// run at once share the cores instead of each starting one thread per core.
//
// ParallelFor cuts [0, count) into chunks of `grain` and runs them on the
// calling thread and on whichever pool threads are free; chunks are taken
// in order, each by one thread. The caller works too and never waits for a
// pool thread that has not started, so loops may nest, and a loop makes
// progress with the pool busy or empty.
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "resource_limits/resource_limits.h"

namespace visq {

namespace parallel_detail {

struct Loop {
  size_t count = 0;
  size_t grain = 1;
  const std::function<void(size_t, size_t)>* body = nullptr;
  std::atomic<size_t> next{0};
  std::mutex mutex;
  std::condition_variable idle;
  size_t active = 0;    // threads inside Work()
  bool closed = false;  // the caller is done: late helpers leave at once

  void Work() {
    for (size_t begin = next.fetch_add(grain); begin < count; begin = next.fetch_add(grain))
      (*body)(begin, std::min(count, begin + grain));
  }
  bool Join() {
    std::lock_guard lock(mutex);
    if (closed) return false;
    ++active;
    return true;
  }
  void Leave() {
    std::lock_guard lock(mutex);
    if (--active == 0) idle.notify_all();
  }
};

class Pool {
 public:
  explicit Pool(size_t threads) {
    for (size_t i = 0; i < threads; ++i) threads_.emplace_back([this] { Serve(); });
  }
  ~Pool() {
    {
      std::lock_guard lock(mutex_);
      stopping_ = true;
    }
    wake_.notify_all();
    for (std::thread& t : threads_) t.join();
  }
  Pool(const Pool&) = delete;
  Pool& operator=(const Pool&) = delete;

  size_t size() const { return threads_.size(); }

  void Offer(const std::shared_ptr<Loop>& loop, size_t helpers) {
    {
      std::lock_guard lock(mutex_);
      for (size_t i = 0; i < helpers; ++i) offers_.push_back(loop);
    }
    if (helpers == 1) wake_.notify_one();
    else wake_.notify_all();
  }

 private:
  void Serve() {
    for (;;) {
      std::shared_ptr<Loop> loop;
      {
        std::unique_lock lock(mutex_);
        wake_.wait(lock, [&] { return stopping_ || !offers_.empty(); });
        if (offers_.empty()) return;
        loop = std::move(offers_.front());
        offers_.pop_front();
      }
      if (loop->Join()) {
        loop->Work();
        loop->Leave();
      }
    }
  }

  std::vector<std::thread> threads_;
  std::mutex mutex_;
  std::condition_variable wake_;
  std::deque<std::shared_ptr<Loop>> offers_;
  bool stopping_ = false;
};

// One thread per CPU this process may use besides the caller's: the CPU
// quota of its cgroup and its affinity mask, not the machine's cores
// (hardware_concurrency()), which in a pod with a quota of 2 on a 64-core
// node would start 63 threads to be throttled.
inline Pool& ProcessPool() {
  static Pool pool(resource_limits::ProcessCpuLimit().cpus - 1);
  return pool;
}

}  // namespace parallel_detail

// The threads a loop can use at most: the caller and the pool.
inline size_t ParallelWorkers() { return parallel_detail::ProcessPool().size() + 1; }

// Runs body(begin, end) over [0, count) in chunks of `grain` (the last may
// be shorter), on at most `max_threads` threads (0: as many as there are),
// and returns when every chunk is done. body must not throw; to stop early,
// let it return at once for the chunks that remain.
inline void ParallelFor(size_t count, size_t grain, const std::function<void(size_t begin, size_t end)>& body,
                        size_t max_threads = 0) {
  grain = std::max<size_t>(grain, 1);
  const size_t chunks = (count + grain - 1) / grain;
  parallel_detail::Pool& pool = parallel_detail::ProcessPool();
  size_t helpers = std::min(pool.size(), chunks > 0 ? chunks - 1 : 0);
  if (max_threads > 0) helpers = std::min(helpers, max_threads - 1);
  if (helpers == 0) {
    for (size_t begin = 0; begin < count; begin += grain) body(begin, std::min(count, begin + grain));
    return;
  }
  auto loop = std::make_shared<parallel_detail::Loop>();
  loop->count = count;
  loop->grain = grain;
  loop->body = &body;
  pool.Offer(loop, helpers);
  loop->Work();
  std::unique_lock lock(loop->mutex);
  loop->closed = true;
  loop->idle.wait(lock, [&] { return loop->active == 0; });
}

}  // namespace visq
