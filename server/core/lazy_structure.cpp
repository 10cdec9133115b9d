#include "core/lazy_structure.h"

namespace visq::core {

StructureBuilds::~StructureBuilds() {
  stopping_ = true;
  std::vector<Running> running;
  {
    std::lock_guard lock(mutex_);
    running.swap(running_);
  }
  for (Running& r : running) r.thread.join();
}

void StructureBuilds::Start(std::function<void()> build) {
  std::lock_guard lock(mutex_);
  // Join the threads whose builds are over (their last step was to say so).
  std::erase_if(running_, [](Running& r) {
    if (!r.done->load()) return false;
    r.thread.join();
    return true;
  });
  auto done = std::make_shared<std::atomic<bool>>(false);
  running_.push_back({std::thread([build = std::move(build), done] {
                        build();
                        done->store(true);
                      }),
                      done});
}

}  // namespace visq::core
