// A streamed answer whose client reads nothing is ended by the stall limit
// that every stream shares (--stream-stall-seconds), whether its writer still
// produces it or has put it, whole, in the queue for the client: before,
// an answer that fit the queue (64 MiB) waited for its reader as long as
// the connection lived, holding its memory.
#include <chrono>
#include <thread>

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include "proto_builders.h"
#include "server_process.h"
#include "test_support.h"
#include "visq/v1/visq.grpc.pb.h"

namespace visq {
namespace {

using testing::ScratchDir;
using testing::ServerProcess;
using testing::SetPatch;

// A 512 x 512 map of the Cornell box with its bitmasks (32 words a texel:
// 32 MiB), far past what HTTP/2 flow control lets through to a client that
// reads nothing, and within the writer's queue.
v1::HiddenSampleMapRequest LargeMap() {
  v1::HiddenSampleMapRequest request;
  request.mutable_scene()->set_name("cornell_box_visq");
  SetPatch(request.mutable_source(), {-0.25, 1.99, -0.25}, {0.5, 0, 0}, {0, 0, 0.5});
  request.mutable_samples()->set_count(1024);
  SetPatch(request.mutable_receiver(), {-0.999, 0.001, -0.999}, {1.998, 0, 0}, {0, 0, 1.998});
  request.set_width(512);
  request.set_height(512);
  request.set_want_bitmasks(true);
  request.set_method(v1::RASTER);
  return request;
}

// Reads what `reader` has, after `wait` without reading; the call's status.
grpc::Status ReadAfter(grpc::ClientReader<v1::HiddenSampleMapResponse>& reader, std::chrono::seconds wait,
                       size_t* messages) {
  std::this_thread::sleep_for(wait);
  *messages = 0;
  for (v1::HiddenSampleMapResponse m; reader.Read(&m);) ++*messages;
  return reader.Finish();
}

TEST(StreamStall, AnAnswerWhoseClientReadsNothingEndsAtTheStallLimit) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(), {"--seed-samples", "--stream-stall-seconds", "1"}});
  ASSERT_NE(server, nullptr);
  auto stub = v1::VisibilityService::NewStub(grpc::CreateChannel(server->address(), grpc::InsecureChannelCredentials()));

  // A reader that keeps up gets the whole answer under the same limit.
  const auto start = std::chrono::steady_clock::now();
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(300));
    auto reader = stub->HiddenSampleMap(&context, LargeMap());
    size_t messages = 0;
    const grpc::Status status = ReadAfter(*reader, std::chrono::seconds(0), &messages);
    ASSERT_TRUE(status.ok()) << status.error_message();
    EXPECT_GT(messages, 2u);
  }
  // One that reads nothing until the map is made (as long again as the
  // first took) and the limit has passed twice over: the server ended the
  // call at its limit.
  const auto wait = std::chrono::seconds(3) + 2 * std::chrono::ceil<std::chrono::seconds>(
                                                     std::chrono::steady_clock::now() - start);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(300));
  auto reader = stub->HiddenSampleMap(&context, LargeMap());
  size_t messages = 0;
  const grpc::Status status = ReadAfter(*reader, wait, &messages);
  EXPECT_FALSE(status.ok()) << "read " << messages << " messages after " << wait.count()
                            << " s: the answer waited for its reader";
  EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED) << status.error_message();
}

// A produced answer larger than what its call may queue unsent
// (--stream-queue-bytes) waits for its reader in the work budget's spare
// memory, not on a worker: with one worker thread, a small map asked while
// a large one's client reads nothing is answered at once, and the large
// answer then reaches its reader whole. Before, the large map's work waited
// on the worker for its reader, and the small map behind it until the stall
// limit.
TEST(StreamStall, AnUnreadAnswerParksInTheBudgetAndFreesItsWorker) {
  ScratchDir repo;
  auto server = ServerProcess::Start({repo.path(),
                                      {"--seed-samples", "--worker-threads", "1", "--stream-stall-seconds", "600",
                                       "--stream-queue-bytes", "1048576", "--map-band-bytes", "1048576"}});
  ASSERT_NE(server, nullptr);
  auto stub = v1::VisibilityService::NewStub(grpc::CreateChannel(server->address(), grpc::InsecureChannelCredentials()));

  grpc::ClientContext large_context;
  large_context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(900));
  auto large = stub->HiddenSampleMap(&large_context, LargeMap());

  v1::HiddenSampleMapRequest small_request = LargeMap();
  small_request.set_width(8);
  small_request.set_height(8);
  small_request.set_want_bitmasks(false);
  grpc::ClientContext small_context;
  small_context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(120));
  auto small = stub->HiddenSampleMap(&small_context, small_request);
  size_t small_messages = 0;
  const grpc::Status small_status = ReadAfter(*small, std::chrono::seconds(0), &small_messages);
  EXPECT_TRUE(small_status.ok()) << "code " << static_cast<int>(small_status.error_code()) << " "
                                 << small_status.error_message()
                                 << ": the small map waited behind the large one's unread answer";

  uint64_t bitmask_words = 0;
  size_t large_messages = 0;
  for (v1::HiddenSampleMapResponse m; large->Read(&m);) {
    ++large_messages;
    bitmask_words += m.blocked_bits_size();
  }
  const grpc::Status large_status = large->Finish();
  ASSERT_TRUE(large_status.ok()) << large_status.error_message();
  EXPECT_GT(large_messages, 16u);
  EXPECT_EQ(bitmask_words, uint64_t{512} * 512 * 32);
}

}  // namespace
}  // namespace visq
