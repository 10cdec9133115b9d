// What uploads may hold: how many are in flight at once (in all, and per
// client), and how long one may send nothing before it is aborted. A client
// that opens uploads and sends nothing would otherwise hold descriptors and
// staging folders until the server runs out of them.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "common/status.h"

namespace visq::service {

class UploadLimits {
 public:
  struct Options {
    int max_in_flight = 64;    // --max-uploads-in-flight
    int max_per_client = 8;    // --max-uploads-per-client
    std::chrono::milliseconds idle{std::chrono::seconds(60)};  // --upload-idle-seconds
    // An answer's stream whose client reads nothing for this long is
    // cancelled, its memory freed: every streamed answer shares it.
    std::chrono::milliseconds stream_stall{std::chrono::seconds(60)};  // --stream-stall-seconds
    // What a produced answer holds unsent within its call's reservation
    // before further messages park in the work budget's spare memory or the
    // work waits (core::kStreamedAnswerQueueBytes, which the call's estimate
    // counts, at most).
    uint64_t stream_queue_bytes = uint64_t{64} << 20;  // --stream-queue-bytes
  };

  // A place among the uploads in flight, given back with the object.
  class Slot {
   public:
    ~Slot();
    Slot(const Slot&) = delete;
    Slot& operator=(const Slot&) = delete;

   private:
    friend class UploadLimits;
    Slot(UploadLimits& limits, std::string client) : limits_(limits), client_(std::move(client)) {}
    UploadLimits& limits_;
    std::string client_;
  };

  // A stream watched for idleness: `on_idle` runs once, on the watchdog's
  // thread, when nothing was Touch()ed for the idle limit. The destructor
  // waits for an `on_idle` in progress, so what it uses lives until then.
  class Watch {
   public:
    ~Watch();
    Watch(const Watch&) = delete;
    Watch& operator=(const Watch&) = delete;
    void Touch();
    // The stream has ended: what follows (parsing, storing) is not idling.
    void Stop();
    // Watching again from now (an answer's stream: from each write on).
    void Resume();

   private:
    friend class UploadLimits;
    struct Entry;
    Watch(UploadLimits& limits, std::shared_ptr<Entry> entry) : limits_(limits), entry_(std::move(entry)) {}
    UploadLimits& limits_;
    std::shared_ptr<Entry> entry_;
  };

  explicit UploadLimits(Options options);
  ~UploadLimits();  // every Slot and Watch goes first
  UploadLimits(const UploadLimits&) = delete;
  UploadLimits& operator=(const UploadLimits&) = delete;

  const Options& options() const { return options_; }

  // A place for an upload from `client` (its address, without the port);
  // RESOURCE_EXHAUSTED naming the flag when either cap is reached.
  [[nodiscard]] StatusOr<std::unique_ptr<Slot>> Acquire(const std::string& client);
  std::unique_ptr<Watch> StartWatch(std::function<void()> on_idle);
  // A watch of an answer's stream by the stall limit: `on_stall` runs once
  // when a write has waited for the client for that long. It watches only
  // while Resume()d (a write in flight), not while the answer is computed.
  std::unique_ptr<Watch> StartStallWatch(std::function<void()> on_stall);

  // The client part of a gRPC peer string: "ipv4:10.0.0.7:51234" ->
  // "ipv4:10.0.0.7", "ipv6:[::1]:5" -> "ipv6:[::1]"; others as they are.
  static std::string ClientOfPeer(const std::string& peer);

 private:
  void Release(const std::string& client);
  std::unique_ptr<Watch> StartWatch(std::function<void()> on_idle, std::chrono::milliseconds limit, bool watching);
  void WatchLoop();

  const Options options_;
  std::mutex mutex_;
  int in_flight_ = 0;
  std::map<std::string, int> per_client_;
  std::map<Watch::Entry*, std::shared_ptr<Watch::Entry>> watched_;
  std::condition_variable wake_;
  bool stopping_ = false;
  std::thread watchdog_;
};

}  // namespace visq::service
