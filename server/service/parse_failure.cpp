#include "service/parse_failure.h"

#include <cstdint>

#include <absl/strings/str_cat.h>
#include <google/protobuf/unknown_field_set.h>

namespace visq::service {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::UnknownField;
using google::protobuf::UnknownFieldSet;

// Well-formed UTF-8 as protobuf checks it: shortest forms only, no
// surrogates, nothing above U+10FFFF.
bool IsValidUtf8(std::string_view s) {
  size_t i = 0;
  while (i < s.size()) {
    const auto c = static_cast<uint8_t>(s[i]);
    size_t length = 0;
    uint32_t code = 0;
    if (c < 0x80) {
      ++i;
      continue;
    }
    if ((c & 0xE0) == 0xC0) length = 2, code = c & 0x1F;
    else if ((c & 0xF0) == 0xE0) length = 3, code = c & 0x0F;
    else if ((c & 0xF8) == 0xF0) length = 4, code = c & 0x07;
    else return false;
    if (i + length > s.size()) return false;
    for (size_t k = 1; k < length; ++k) {
      const auto next = static_cast<uint8_t>(s[i + k]);
      if ((next & 0xC0) != 0x80) return false;
      code = (code << 6) | (next & 0x3F);
    }
    static constexpr uint32_t kShortest[5] = {0, 0, 0x80, 0x800, 0x10000};
    if (code < kShortest[length] || code > 0x10FFFF || (code >= 0xD800 && code <= 0xDFFF)) return false;
    i += length;
  }
  return true;
}

// The first string field under `fields` (of `type`) that is not UTF-8, as
// "prefix.field"; empty when there is none.
std::string FindInvalidString(const Descriptor& type, const UnknownFieldSet& fields, const std::string& prefix,
                              int depth) {
  for (int i = 0; i < fields.field_count(); ++i) {
    const UnknownField& field = fields.field(i);
    if (field.type() != UnknownField::TYPE_LENGTH_DELIMITED) continue;
    const FieldDescriptor* described = type.FindFieldByNumber(field.number());
    if (described == nullptr) continue;
    const std::string path = prefix + described->name();
    if (described->type() == FieldDescriptor::TYPE_STRING && !IsValidUtf8(field.length_delimited()))
      return path;
    if (described->type() == FieldDescriptor::TYPE_MESSAGE && depth < 32) {
      UnknownFieldSet inner;
      if (!inner.ParseFromString(field.length_delimited())) continue;
      std::string found = FindInvalidString(*described->message_type(), inner, path + ".", depth + 1);
      if (!found.empty()) return found;
    }
  }
  return {};
}

}  // namespace

std::string DescribeParseFailure(const Descriptor& type, std::string_view bytes) {
  UnknownFieldSet fields;
  if (fields.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
    const std::string field = FindInvalidString(type, fields, "", 0);
    if (!field.empty()) return absl::StrCat(field, ": invalid UTF-8 (a string field must be UTF-8)");
  }
  return absl::StrCat("not a valid ", type.name(), " (", bytes.size(), " bytes: truncated or malformed)");
}

}  // namespace visq::service
