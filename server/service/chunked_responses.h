// A large answer as a stream of messages, built one at a time as the
// previous one is written: the figures first, then each array in chunks
// (one chunk per message, in order, each naming its first element's offset).
// At most one chunk's copy of the answer exists at once, instead of a second
// copy of the whole answer in protobuf form.
#pragma once

#include <algorithm>
#include <cstddef>
#include <functional>
#include <memory>
#include <utility>
#include <vector>

#include <absl/status/status.h>
#include <glm/vec3.hpp>
#include <google/protobuf/repeated_field.h>

namespace visq::service {

// 1M floats or words is 4 MiB, well under the default 16 MiB message limit on
// both sides.
inline constexpr size_t kChunkElements = size_t{1} << 20;

template <typename Response>
class ChunkedResponses {
 public:
  // Adds elements [begin, end) of one array to `message`, and sets the
  // offset field that goes with the array.
  using Fill = std::function<void(Response& message, size_t begin, size_t end)>;

  // With `first_carries_chunk`, the first array's first chunk rides in the
  // figures' message; otherwise every chunk has a message of its own.
  explicit ChunkedResponses(Response first, bool first_carries_chunk = true,
                            size_t chunk_elements = kChunkElements)
      : first_(std::move(first)), first_carries_chunk_(first_carries_chunk), chunk_elements_(chunk_elements) {}

  Response& first() { return first_; }

  // An array of `size` elements; empty arrays send nothing.
  void Add(size_t size, Fill fill) {
    if (size > 0) arrays_.push_back({size, std::move(fill)});
  }

  // Keeps what the fills read alive until the last message is built.
  void Keep(std::shared_ptr<const void> owner) { owners_.push_back(std::move(owner)); }

  // Messages still to come, this one included (for logs).
  size_t MessageCount() const {
    size_t count = 1;
    for (const Array& a : arrays_) count += (a.size + chunk_elements_ - 1) / chunk_elements_;
    return first_carries_chunk_ && !arrays_.empty() ? count - 1 : count;
  }

  // The next message into `out`; false once every message was given.
  bool Next(Response& out) {
    if (!first_given_) {
      first_given_ = true;
      out = std::move(first_);
      if (first_carries_chunk_) FillNextChunk(out);
      return true;
    }
    out.Clear();
    return FillNextChunk(out);
  }

 private:
  struct Array {
    size_t size;
    Fill fill;
  };

  bool FillNextChunk(Response& out) {
    while (array_ < arrays_.size() && offset_ >= arrays_[array_].size) {
      ++array_;
      offset_ = 0;
    }
    if (array_ >= arrays_.size()) {
      owners_.clear();
      return false;
    }
    const Array& a = arrays_[array_];
    const size_t end = std::min(a.size, offset_ + chunk_elements_);
    a.fill(out, offset_, end);
    offset_ = end;
    return true;
  }

  Response first_;
  bool first_carries_chunk_;
  size_t chunk_elements_;
  std::vector<Array> arrays_;
  std::vector<std::shared_ptr<const void>> owners_;
  bool first_given_ = false;
  size_t array_ = 0;
  size_t offset_ = 0;
};

// An answer made in parts (a band of a map or a grid), written as it is
// made: elements [0, size) of one array in messages of at most
// `chunk_elements`, each naming in `offset` its first element's index in the
// whole answer (`first_offset` + begin). `fill(message, begin, end)` adds the
// elements. Stops at the first write that fails.
template <typename Response, typename Fill>
[[nodiscard]] absl::Status WriteChunks(size_t size, uint64_t first_offset, size_t chunk_elements,
                                       const std::function<absl::Status(Response)>& write, const Fill& fill) {
  for (size_t begin = 0; begin < size; begin += chunk_elements) {
    const size_t end = std::min(size, begin + chunk_elements);
    Response message;
    message.set_offset(first_offset + begin);
    fill(message, begin, end);
    if (absl::Status written = write(std::move(message)); !written.ok()) return written;
  }
  return absl::OkStatus();
}

// Elements [begin, end) of `values` onto a repeated field.
template <typename T, typename Field>
void AddRange(const std::vector<T>& values, size_t begin, size_t end, Field* field) {
  field->Add(values.begin() + static_cast<std::ptrdiff_t>(begin), values.begin() + static_cast<std::ptrdiff_t>(end));
}

// Floats [begin, end) of `values` read as x, y, z, x, y, z, ...
inline void AddFlattenedRange(const std::vector<glm::vec3>& values, size_t begin, size_t end,
                              google::protobuf::RepeatedField<float>* field) {
  field->Reserve(field->size() + static_cast<int>(end - begin));
  for (size_t i = begin; i < end; ++i) field->Add(values[i / 3][static_cast<int>(i % 3)]);
}

}  // namespace visq::service
