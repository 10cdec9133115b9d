// The extension cases of the structure-aware glTF fuzzer
// (gltf_structure_fuzz.cpp, whose header comment lists them):
// EXT_mesh_gpu_instancing, EXT_meshopt_compression and
// KHR_draco_mesh_compression built from real encoder output and then lied
// about, and lightmap UVs (TEXCOORD_1) at the float edges.
#pragma once

#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

namespace visq_fuzz {

using Bytes = std::vector<uint8_t>;

// The generator's decisions: from FuzzedDataProvider when fuzzing, from a
// script when writing seeds (gltf_structure_fuzz.cpp).
class Choices {
 public:
  virtual ~Choices() = default;
  // A value in [0, span]; `name` identifies the decision for seed scripts.
  virtual uint64_t Span(const std::string& name, uint64_t span) = 0;
  // Up to n raw bytes (fewer when a fuzz input runs out).
  virtual Bytes Raw(const std::string& name, size_t n) = 0;
  bool Flag(const std::string& name) { return Span(name, 1) != 0; }
};

// "data:application/octet-stream;base64,..." (gltf_structure_fuzz.cpp).
std::string DataUri(const Bytes& b);

struct ExtensionCases {
  bool added = false;  // false: `g` and `files` are untouched
  // A stream was cut or had bytes flipped, so what it decodes to is not the
  // generator's values: the check for the sentinels' value does not apply.
  bool opaque_values = false;
};

// Adds the extension cases the decisions ask for to a complete document `g`
// (which has buffers, bufferViews, accessors, meshes and nodes). It reads its
// decisions after all of the document's others, and with every decision 0
// changes nothing. New bytes go into one new buffer: a data: uri, or (as
// decided) the file "x.bin" appended to `files`.
ExtensionCases AddExtensionCases(Choices& c, nlohmann::json& g, std::vector<std::pair<std::string, Bytes>>& files);

}  // namespace visq_fuzz
