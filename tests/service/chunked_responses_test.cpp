// The chunked answer stream: every element exactly once, in order, in
// chunks no larger than asked, each with its offset, and the answer kept
// alive until the last message is built.
#include "service/chunked_responses.h"

#include <memory>
#include <numeric>
#include <vector>

#include <gtest/gtest.h>

#include "visq/v1/visq.pb.h"

namespace visq::service {
namespace {

using Message = v1::HiddenSampleMapResponse;

std::vector<Message> Drain(ChunkedResponses<Message>& stream) {
  std::vector<Message> out;
  Message m;
  while (stream.Next(m)) out.push_back(m);
  return out;
}

TEST(ChunkedResponses, FiguresThenEveryArrayInOrderedChunks) {
  auto fractions = std::make_shared<std::vector<float>>(10);
  std::iota(fractions->begin(), fractions->end(), 0.0f);
  auto bits = std::make_shared<std::vector<uint32_t>>(7);
  std::iota(bits->begin(), bits->end(), 100u);
  Message first;
  first.set_width(5);
  ChunkedResponses<Message> stream(first, /*first_carries_chunk=*/true, /*chunk_elements=*/4);
  stream.Keep(fractions);
  stream.Keep(bits);
  const std::vector<float>& f = *fractions;
  const std::vector<uint32_t>& b = *bits;
  const std::vector<float> want_fractions = f;
  const std::vector<uint32_t> want_bits = b;
  stream.Add(f.size(), [&f](Message& m, size_t begin, size_t end) {
    m.set_offset(begin);
    AddRange(f, begin, end, m.mutable_visible_fraction());
  });
  stream.Add(0, [](Message&, size_t, size_t) { ADD_FAILURE() << "an empty array sends nothing"; });
  stream.Add(b.size(), [&b](Message& m, size_t begin, size_t end) {
    m.set_offset(begin);
    AddRange(b, begin, end, m.mutable_blocked_bits());
  });
  EXPECT_EQ(stream.MessageCount(), 5u);  // fractions 4+4+2 (the first with the figures), bits 4+3
  // The stream keeps the arrays until its last message is built.
  std::weak_ptr<std::vector<float>> kept = fractions;
  fractions.reset();
  bits.reset();

  const std::vector<Message> messages = Drain(stream);
  ASSERT_EQ(messages.size(), 5u);
  EXPECT_EQ(messages[0].width(), 5u);
  std::vector<float> got_fractions;
  std::vector<uint32_t> got_bits;
  for (const Message& m : messages) {
    EXPECT_LE(m.visible_fraction_size() + m.blocked_bits_size(), 4);
    EXPECT_FALSE(m.visible_fraction_size() > 0 && m.blocked_bits_size() > 0) << "one array per message";
    if (m.visible_fraction_size() > 0) {
      EXPECT_EQ(m.offset(), got_fractions.size());
      got_fractions.insert(got_fractions.end(), m.visible_fraction().begin(), m.visible_fraction().end());
    }
    if (m.blocked_bits_size() > 0) {
      EXPECT_EQ(m.offset(), got_bits.size());
      got_bits.insert(got_bits.end(), m.blocked_bits().begin(), m.blocked_bits().end());
    }
  }
  EXPECT_EQ(got_fractions, want_fractions);
  EXPECT_EQ(got_bits, want_bits);
  EXPECT_TRUE(kept.expired()) << "the answer goes once the last message was built";
  Message after;
  EXPECT_FALSE(stream.Next(after)) << "nothing after the last chunk";
}

TEST(ChunkedResponses, FiguresAloneWhenAsked) {
  std::vector<float> f = {1, 2, 3};
  Message first;
  first.set_height(9);
  ChunkedResponses<Message> stream(first, /*first_carries_chunk=*/false, 2);
  stream.Add(f.size(), [&f](Message& m, size_t begin, size_t end) {
    m.set_offset(begin);
    AddRange(f, begin, end, m.mutable_visible_fraction());
  });
  const std::vector<Message> messages = Drain(stream);
  ASSERT_EQ(messages.size(), 3u);
  EXPECT_EQ(messages[0].height(), 9u);
  EXPECT_EQ(messages[0].visible_fraction_size(), 0);
  EXPECT_EQ(messages[1].visible_fraction_size(), 2);
  EXPECT_EQ(messages[2].offset(), 2u);
  EXPECT_EQ(messages[2].height(), 0u) << "figures only in the first message";
}

TEST(ChunkedResponses, NoArraysIsOneMessage) {
  Message first;
  first.set_sample_count(3);
  ChunkedResponses<Message> stream(first);
  const std::vector<Message> messages = Drain(stream);
  ASSERT_EQ(messages.size(), 1u);
  EXPECT_EQ(messages[0].sample_count(), 3u);
}

TEST(ChunkedResponses, Vec3sGoAsFlatFloats) {
  const std::vector<glm::vec3> values = {{1, 2, 3}, {4, 5, 6}};
  google::protobuf::RepeatedField<float> field;
  AddFlattenedRange(values, 1, 5, &field);
  EXPECT_EQ(std::vector<float>(field.begin(), field.end()), (std::vector<float>{2, 3, 4, 5}));
}

}  // namespace
}  // namespace visq::service
