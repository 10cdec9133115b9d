#include "service/executor.h"

#include <exception>

#include <spdlog/spdlog.h>

namespace visq::service {

Executor::Executor(int threads) {
  for (int i = 0; i < std::max(threads, 1); ++i) threads_.emplace_back([this] { Loop(); });
}

Executor::~Executor() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  for (auto& t : threads_) t.join();
}

void Executor::Post(std::function<void()> task) {
  {
    std::lock_guard lock(mutex_);
    tasks_.push_back(std::move(task));
  }
  wake_.notify_one();
}

size_t Executor::queued() const {
  std::lock_guard lock(mutex_);
  return tasks_.size();
}

void Executor::Loop() {
  for (;;) {
    std::function<void()> task;
    {
      std::unique_lock lock(mutex_);
      wake_.wait(lock, [&] { return stopping_ || !tasks_.empty(); });
      if (tasks_.empty()) return;
      task = std::move(tasks_.front());
      tasks_.pop_front();
    }
    // The last line of defence: a task's own call catches what its work
    // throws (exception_boundary.h); what still escapes is logged here, and
    // the thread goes on serving the queue instead of ending the process.
    try {
      task();
    } catch (const std::exception& e) {
      spdlog::error("executor: an exception escaped a task: {}", e.what());
    } catch (...) {
      spdlog::error("executor: an exception that is not a std::exception escaped a task");
    }
  }
}

}  // namespace visq::service
