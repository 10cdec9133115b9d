#include "scene/gltf_compression.h"

#include <algorithm>
#include <cstring>
#include <map>
#include <memory>
#include <new>
#include <vector>

#include <absl/strings/str_cat.h>
#include <draco/compression/decode.h>
#include <draco/compression/point_cloud/point_cloud_decoder.h>
#include <draco/core/varint_decoding.h>
#include <draco/metadata/metadata_decoder.h>
#include <meshoptimizer.h>
#include <nlohmann/json.hpp>
#include <tiny_gltf.h>

namespace visq {
namespace {

constexpr char kMeshopt[] = "EXT_meshopt_compression";
constexpr char kDraco[] = "KHR_draco_mesh_compression";

Status Invalid(const std::string& what) { return absl::InvalidArgumentError(what); }

// The decoded bytes of one document, counted against its cap.
class DecodedBytes {
 public:
  explicit DecodedBytes(uint64_t cap) : cap_(cap) {}
  Status Reserve(uint64_t bytes, const std::string& what) {
    if (__builtin_add_overflow(total_, bytes, &total_) || total_ > cap_)
      return absl::ResourceExhaustedError(absl::StrCat(what, ": compressed geometry decodes to more than ", cap_,
                                                       " bytes (--max-scene-bytes)"));
    return absl::OkStatus();
  }
  uint64_t left() const { return cap_ - std::min(total_, cap_); }

 private:
  uint64_t cap_;
  uint64_t total_ = 0;
};

// A new buffer and a view of all of it; returns the view's index.
int AppendBufferView(tinygltf::Model& model, std::vector<unsigned char> bytes, int byte_stride) {
  tinygltf::BufferView view;
  view.buffer = static_cast<int>(model.buffers.size());
  view.byteOffset = 0;
  view.byteLength = bytes.size();
  view.byteStride = byte_stride;
  tinygltf::Buffer buffer;
  buffer.data = std::move(bytes);
  model.buffers.push_back(std::move(buffer));
  model.bufferViews.push_back(std::move(view));
  return static_cast<int>(model.bufferViews.size()) - 1;
}

int64_t IntField(const tinygltf::Value& object, const char* name, int64_t fallback) {
  if (!object.Has(name) || !object.Get(name).IsNumber()) return fallback;
  const double v = object.Get(name).GetNumberAsDouble();
  return v >= 0 && v < 9.0e15 && v == static_cast<double>(static_cast<int64_t>(v)) ? static_cast<int64_t>(v) : -1;
}

std::string StringField(const tinygltf::Value& object, const char* name, const char* fallback) {
  if (!object.Has(name) || !object.Get(name).IsString()) return fallback;
  return object.Get(name).Get<std::string>();
}

// The bytes [offset, offset + length) of buffers[buffer], or an error.
StatusOr<const unsigned char*> SourceBytes(const tinygltf::Model& model, int64_t buffer, int64_t offset,
                                           int64_t length, const std::string& label) {
  if (buffer < 0 || buffer >= static_cast<int64_t>(model.buffers.size()))
    return Invalid(absl::StrCat(label, ".buffer: ", buffer, " out of range"));
  const auto& data = model.buffers[buffer].data;
  int64_t end = 0;
  if (offset < 0 || length < 0 || __builtin_add_overflow(offset, length, &end) ||
      end > static_cast<int64_t>(data.size()))
    return Invalid(absl::StrCat(label, ": byteOffset + byteLength past the end of buffer ", buffer));
  return data.data() + offset;
}

// The most bytes a meshopt stream of `length` bytes decodes to, by the
// format itself (meshoptimizer's vertexcodec.cpp and indexcodec.cpp,
// version 0 of the vertex codec):
// - ATTRIBUTES: vertices come in blocks of at most 256; every byte of a
//   vertex costs a block at least a 2-bit header per group of 16 vertices,
//   rounded up to whole bytes: 4 bytes per 256 vertices, so a stream byte
//   decodes to at most 64 bytes.
// - TRIANGLES: a header byte, a 16-byte table and at least one code byte per
//   triangle (the decoder's own first check).
// - INDICES: a header byte, a 4-byte tail and at least one byte per index.
uint64_t MeshoptDecodedBound(const std::string& mode, uint64_t stride, uint64_t length) {
  uint64_t bound = 0;
  if (mode == "ATTRIBUTES") {
    if (__builtin_mul_overflow(length, uint64_t{64}, &bound)) return ~uint64_t{0};
  } else if (mode == "TRIANGLES") {
    bound = length > 17 ? (length - 17) * 3 * stride : 0;
  } else if (mode == "INDICES") {
    bound = length > 5 ? (length - 5) * stride : 0;
  }
  return bound;
}

Status DecodeMeshoptView(tinygltf::Model& model, int view_index, DecodedBytes& decoded) {
  tinygltf::BufferView& view = model.bufferViews[view_index];
  const tinygltf::Value& ext = view.extensions.at(kMeshopt);
  const std::string label = absl::StrCat("bufferViews[", view_index, "].extensions.", kMeshopt);
  const int64_t count = IntField(ext, "count", -1), stride = IntField(ext, "byteStride", -1);
  const int64_t offset = IntField(ext, "byteOffset", 0), length = IntField(ext, "byteLength", -1);
  const std::string mode = StringField(ext, "mode", ""), filter = StringField(ext, "filter", "NONE");
  if (count < 0 || stride <= 0 || stride > 256)
    return Invalid(absl::StrCat(label, ": count and byteStride (1 to 256) are required"));
  VISQ_ASSIGN_OR_RETURN(const unsigned char* source, SourceBytes(model, IntField(ext, "buffer", -1), offset, length,
                                                                 label));
  // tinygltf keeps an extension's integers as int: a count beyond 2^31
  // arrives cut, and the view's own byteLength (a full size) shows it.
  uint64_t bytes = 0;
  if (__builtin_mul_overflow(uint64_t(count), uint64_t(stride), &bytes) || bytes != view.byteLength)
    return Invalid(absl::StrCat(label, ": count × byteStride (", count, " × ", stride,
                                ") is not the buffer view's byteLength ", view.byteLength));
  if (mode == "ATTRIBUTES") {
    if (stride % 4 != 0) return Invalid(absl::StrCat(label, ".byteStride: must be a multiple of 4 for ATTRIBUTES"));
    // EXT_meshopt_compression's vertex streams are version 0 (header 0xA0),
    // the format whose bound MeshoptDecodedBound states.
    if (length > 0 && source[0] != 0xA0)
      return Invalid(absl::StrCat(label, ": malformed ATTRIBUTES stream (header byte ", int(source[0]),
                                  ", expected 0xA0)"));
  } else if (mode == "TRIANGLES" || mode == "INDICES") {
    if (stride != 2 && stride != 4) return Invalid(absl::StrCat(label, ".byteStride: must be 2 or 4 for ", mode));
    if (mode == "TRIANGLES" && count % 3 != 0) return Invalid(absl::StrCat(label, ".count: not a multiple of 3"));
  } else {
    return Invalid(absl::StrCat(label, ".mode: '", mode, "' is not ATTRIBUTES, TRIANGLES or INDICES"));
  }
  // count and byteStride are the file's numbers: before anything is
  // allocated, they must fit the cap, and what the stream itself can hold.
  VISQ_RETURN_IF_ERROR(decoded.Reserve(bytes, label));
  const uint64_t bound = MeshoptDecodedBound(mode, uint64_t(stride), uint64_t(length));
  if (bytes > bound)
    return Invalid(absl::StrCat(label, ": count × byteStride (", count, " × ", stride, " = ", bytes,
                                " bytes) is more than a ", length, "-byte ", mode, " stream can encode (at most ", bound,
                                ")"));
  std::vector<unsigned char> out(bytes);
  int result = -1;
  if (mode == "ATTRIBUTES") {
    result = meshopt_decodeVertexBuffer(out.data(), count, stride, source, length);
  } else {
    result = mode == "TRIANGLES" ? meshopt_decodeIndexBuffer(out.data(), count, stride, source, length)
                                 : meshopt_decodeIndexSequence(out.data(), count, stride, source, length);
  }
  if (result != 0) return Invalid(absl::StrCat(label, ": malformed ", mode, " stream"));
  if (filter == "OCTAHEDRAL" && (stride == 4 || stride == 8)) {
    meshopt_decodeFilterOct(out.data(), count, stride);
  } else if (filter == "QUATERNION" && stride == 8) {
    meshopt_decodeFilterQuat(out.data(), count, stride);
  } else if (filter == "EXPONENTIAL" && stride % 4 == 0) {
    meshopt_decodeFilterExp(out.data(), count, stride);
  } else if (filter != "NONE") {
    return Invalid(absl::StrCat(label, ".filter: '", filter, "' does not fit byteStride ", stride));
  }
  const int decoded_view = AppendBufferView(model, std::move(out), 0);
  tinygltf::BufferView& plain = model.bufferViews[view_index];  // the append may have moved it
  plain.buffer = model.bufferViews[decoded_view].buffer;
  plain.byteOffset = 0;
  plain.byteLength = bytes;
  plain.byteStride = mode == "ATTRIBUTES" ? static_cast<int>(stride) : 0;
  plain.extensions.erase(kMeshopt);
  return absl::OkStatus();
}

// Points one accessor at `values` (FLOAT or UNSIGNED_INT, tightly packed).
void RepointAccessor(tinygltf::Model& model, int accessor_index, std::vector<unsigned char> values, size_t count,
                     int component_type) {
  const int view = AppendBufferView(model, std::move(values), 0);
  tinygltf::Accessor& accessor = model.accessors[accessor_index];
  accessor.bufferView = view;
  accessor.byteOffset = 0;
  accessor.count = count;
  accessor.componentType = component_type;
  accessor.normalized = false;
  accessor.sparse.isSparse = false;
}

// The faces and points a Draco mesh stream announces, read from its
// headers as Draco's decoder reads them (the Draco header, the metadata,
// then the sequential or edgebreaker connectivity header: see the Draco
// bitstream specification), before the decoder builds anything: a stream of
// a few hundred kilobytes can announce, and decode to, millions of faces.
struct DracoCounts {
  uint64_t faces = 0;
  uint64_t points = 0;  // the encoded vertices; seams may add some, at most 3 per face
};

StatusOr<DracoCounts> ReadDracoCounts(const unsigned char* source, size_t length, const std::string& label) {
  draco::DecoderBuffer buffer;
  buffer.Init(reinterpret_cast<const char*>(source), length);
  draco::DracoHeader header;
  if (!draco::PointCloudDecoder::DecodeHeader(&buffer, &header).ok())
    return Invalid(absl::StrCat(label, ": malformed Draco stream (its header)"));
  if (header.encoder_type != draco::TRIANGULAR_MESH)
    return Invalid(absl::StrCat(label, ": the Draco stream is a point cloud, not a triangle mesh"));
  const uint16_t version = DRACO_BITSTREAM_VERSION(header.version_major, header.version_minor);
  if (version > draco::kDracoMeshBitstreamVersion)
    return Invalid(absl::StrCat(label, ": Draco bitstream version ", int(header.version_major), ".",
                                int(header.version_minor), " is newer than this decoder's"));
  buffer.set_bitstream_version(version);
  if (version >= DRACO_BITSTREAM_VERSION(1, 3) && (header.flags & METADATA_FLAG_MASK)) {
    draco::MetadataDecoder metadata_decoder;
    draco::GeometryMetadata metadata;
    if (!metadata_decoder.DecodeGeometryMetadata(&buffer, &metadata))
      return Invalid(absl::StrCat(label, ": malformed Draco stream (its metadata)"));
  }
  // Before 2.2 the counts are 32-bit words; since, varints.
  const bool varints = version >= DRACO_BITSTREAM_VERSION(2, 2);
  auto count = [&](uint32_t* value) {
    return varints ? draco::DecodeVarint(value, &buffer) : buffer.Decode(value);
  };
  uint32_t faces = 0, points = 0;
  bool read = false;
  if (header.encoder_method == draco::MESH_SEQUENTIAL_ENCODING) {
    read = count(&faces) && count(&points);
  } else if (header.encoder_method == draco::MESH_EDGEBREAKER_ENCODING) {
    uint8_t traversal = 0;
    int32_t new_vertices = 0;  // only before 2.0
    read = buffer.Decode(&traversal) && (version >= DRACO_BITSTREAM_VERSION(2, 0) || buffer.Decode(&new_vertices)) &&
           count(&points) && count(&faces);
  } else {
    return Invalid(absl::StrCat(label, ": unknown Draco encoder method ", int(header.encoder_method)));
  }
  if (!read) return Invalid(absl::StrCat(label, ": malformed Draco stream (its connectivity header)"));
  return DracoCounts{faces, points};
}

Status DecodeDracoPrimitive(tinygltf::Model& model, int mesh_index, int primitive_index, DecodedBytes& decoded) {
  const std::string label =
      absl::StrCat("meshes[", mesh_index, "].primitives[", primitive_index, "].extensions.", kDraco);
  // Copies: appending buffers below may move the model's vectors.
  const tinygltf::Primitive primitive = model.meshes[mesh_index].primitives[primitive_index];
  const tinygltf::Value& ext = primitive.extensions.at(kDraco);
  const int64_t view_index = IntField(ext, "bufferView", -1);
  if (view_index < 0 || view_index >= static_cast<int64_t>(model.bufferViews.size()))
    return Invalid(absl::StrCat(label, ".bufferView: missing or out of range"));
  const tinygltf::BufferView& view = model.bufferViews[view_index];
  VISQ_ASSIGN_OR_RETURN(const unsigned char* source,
                        SourceBytes(model, view.buffer, view.byteOffset, view.byteLength,
                                    absl::StrCat("bufferViews[", view_index, "]")));

  // Counted before Draco decodes: the corner indices and positions visq
  // keeps of the mesh at least. Draco's own working set while it decodes is
  // a small multiple of it (its faces, corner table and attribute values).
  VISQ_ASSIGN_OR_RETURN(const DracoCounts counts, ReadDracoCounts(source, view.byteLength, label));
  const uint64_t least = counts.faces * 3 * sizeof(uint32_t) + counts.points * 3 * sizeof(float);
  if (least > decoded.left())
    return absl::ResourceExhaustedError(absl::StrCat(label, ": the Draco stream announces ", counts.faces, " faces and ",
                                                     counts.points, " points (", least, " bytes decoded at least), more ",
                                                     "than the ", decoded.left(), " bytes left under the cap ",
                                                     "(--max-scene-bytes)"));
  draco::DecoderBuffer stream;
  stream.Init(reinterpret_cast<const char*>(source), view.byteLength);
  draco::Decoder decoder;
  std::unique_ptr<draco::Mesh> mesh;
  try {
    auto result = decoder.DecodeMeshFromBuffer(&stream);
    if (!result.ok()) return Invalid(absl::StrCat(label, ": malformed Draco stream (", result.status().error_msg(), ")"));
    mesh = std::move(result).value();
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError(absl::StrCat(label, ": the Draco stream asks for more memory than there is"));
  }
  const uint64_t points = mesh->num_points(), faces = mesh->num_faces();

  // The primitive's accessors describe the decoded data: only POSITION and
  // TEXCOORD_1 are read, and the indices come from the faces.
  if (!ext.Has("attributes") || !ext.Get("attributes").IsObject())
    return Invalid(absl::StrCat(label, ".attributes: missing"));
  const tinygltf::Value& ids = ext.Get("attributes");
  for (const char* name : {"POSITION", "TEXCOORD_1"}) {
    auto accessor = primitive.attributes.find(name);
    if (accessor == primitive.attributes.end()) continue;
    if (accessor->second < 0 || accessor->second >= static_cast<int>(model.accessors.size()))
      return Invalid(absl::StrCat(label, ": accessor of ", name, " out of range"));
    if (!ids.Has(name)) continue;  // stored uncompressed, as a plain accessor
    const int64_t id = IntField(ids, name, -1);
    const draco::PointAttribute* attribute = id >= 0 ? mesh->GetAttributeByUniqueId(static_cast<uint32_t>(id)) : nullptr;
    if (attribute == nullptr) return Invalid(absl::StrCat(label, ".attributes.", name, ": no such Draco attribute"));
    const int components = std::string(name) == "POSITION" ? 3 : 2;
    if (attribute->num_components() != components)
      return Invalid(absl::StrCat(label, ".attributes.", name, ": ", int(attribute->num_components()),
                                  " components, expected ", components));
    const uint64_t bytes = points * components * sizeof(float);
    VISQ_RETURN_IF_ERROR(decoded.Reserve(bytes, label));
    std::vector<unsigned char> values(bytes);
    for (uint32_t p = 0; p < points; ++p) {
      float value[3] = {0, 0, 0};
      if (!attribute->ConvertValue<float>(attribute->mapped_index(draco::PointIndex(p)), components, value))
        return Invalid(absl::StrCat(label, ".attributes.", name, ": values that are not numbers"));
      std::memcpy(values.data() + size_t(p) * components * sizeof(float), value, components * sizeof(float));
    }
    RepointAccessor(model, accessor->second, std::move(values), points, TINYGLTF_COMPONENT_TYPE_FLOAT);
  }
  if (primitive.indices >= 0) {
    if (primitive.indices >= static_cast<int>(model.accessors.size()))
      return Invalid(absl::StrCat(label, ": indices accessor out of range"));
    const uint64_t bytes = faces * 3 * sizeof(uint32_t);
    VISQ_RETURN_IF_ERROR(decoded.Reserve(bytes, label));
    std::vector<unsigned char> indices(bytes);
    for (uint32_t f = 0; f < faces; ++f) {
      const draco::Mesh::Face& face = mesh->face(draco::FaceIndex(f));
      const uint32_t corners[3] = {face[0].value(), face[1].value(), face[2].value()};
      std::memcpy(indices.data() + size_t(f) * sizeof(corners), corners, sizeof(corners));
    }
    RepointAccessor(model, primitive.indices, std::move(indices), faces * 3, TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT);
  }
  model.meshes[mesh_index].primitives[primitive_index].extensions.erase(kDraco);
  return absl::OkStatus();
}

}  // namespace

StatusOr<std::string> PrepareCompressedDocument(std::string bytes, bool binary) {
  // Cheap: most documents use neither extension.
  if (bytes.find(kMeshopt) == std::string::npos && bytes.find(kDraco) == std::string::npos) return bytes;
  size_t json_begin = 0, json_length = bytes.size();
  if (binary) {
    if (bytes.size() < 20) return bytes;  // tinygltf names what is wrong with it
    uint32_t chunk_length = 0;
    std::memcpy(&chunk_length, bytes.data() + 12, 4);  // little endian
    if (chunk_length > bytes.size() - 20) return bytes;
    json_begin = 20;
    json_length = chunk_length;
  }
  nlohmann::json document = nlohmann::json::parse(bytes.begin() + json_begin,
                                                  bytes.begin() + json_begin + json_length, nullptr,
                                                  /*allow_exceptions=*/false);
  if (document.is_discarded() || !document.is_object()) return bytes;
  bool changed = false;
  if (document.contains("buffers") && document["buffers"].is_array()) {
    for (auto& buffer : document["buffers"]) {
      if (!buffer.is_object() || buffer.contains("uri")) continue;
      const auto ext = buffer.find("extensions");
      if (ext == buffer.end() || !ext->is_object() || !ext->contains(kMeshopt)) continue;
      const auto& meshopt = (*ext)[kMeshopt];
      if (!meshopt.is_object() || meshopt.value("fallback", false) != true) continue;
      buffer["uri"] = "data:application/octet-stream;base64,AA==";
      buffer["byteLength"] = 1;
      changed = true;
    }
  }
  // tinygltf insists that an indices accessor has a buffer view; a Draco
  // primitive's has none (its indices are in the Draco stream). It borrows
  // the stream's view until DecodeCompressedGeometry gives it its own.
  if (document.contains("meshes") && document["meshes"].is_array() && document.contains("accessors") &&
      document["accessors"].is_array()) {
    auto& accessors = document["accessors"];
    for (auto& mesh : document["meshes"]) {
      if (!mesh.is_object() || !mesh.contains("primitives") || !mesh["primitives"].is_array()) continue;
      for (auto& primitive : mesh["primitives"]) {
        if (!primitive.is_object() || !primitive.contains("extensions") || !primitive["extensions"].is_object() ||
            !primitive["extensions"].contains(kDraco) || !primitive.contains("indices"))
          continue;
        const auto& draco = primitive["extensions"][kDraco];
        const auto& indices = primitive["indices"];
        if (!draco.is_object() || !draco.contains("bufferView") || !draco["bufferView"].is_number_unsigned() ||
            !indices.is_number_unsigned() || indices.get<uint64_t>() >= accessors.size())
          continue;
        auto& accessor = accessors[indices.get<size_t>()];
        if (!accessor.is_object() || accessor.contains("bufferView")) continue;
        accessor["bufferView"] = draco["bufferView"];
        changed = true;
      }
    }
  }
  if (!changed) return bytes;
  std::string json = document.dump();
  if (!binary) return json;
  while (json.size() % 4 != 0) json.push_back(' ');
  std::string rebuilt = bytes.substr(0, 12);
  const uint32_t new_length = static_cast<uint32_t>(json.size());
  rebuilt.append(reinterpret_cast<const char*>(&new_length), 4);
  rebuilt.append(bytes, 16, 4);  // the chunk type, "JSON"
  rebuilt += json;
  rebuilt.append(bytes, json_begin + json_length);  // the BIN chunk, untouched
  const uint64_t total = rebuilt.size();
  if (total > UINT32_MAX) return absl::ResourceExhaustedError("the rewritten GLB exceeds 4 GiB");
  const uint32_t total32 = static_cast<uint32_t>(total);
  std::memcpy(rebuilt.data() + 8, &total32, 4);
  return rebuilt;
}

Status DecodeCompressedGeometry(tinygltf::Model& model, uint64_t max_decoded_bytes) {
  DecodedBytes decoded(max_decoded_bytes);
  const size_t views = model.bufferViews.size();  // appended views are plain
  for (size_t v = 0; v < views; ++v)
    if (model.bufferViews[v].extensions.count(kMeshopt))
      VISQ_RETURN_IF_ERROR(DecodeMeshoptView(model, static_cast<int>(v), decoded));
  for (size_t m = 0; m < model.meshes.size(); ++m)
    for (size_t p = 0; p < model.meshes[m].primitives.size(); ++p) {
      tinygltf::Primitive& primitive = model.meshes[m].primitives[p];
      if (!primitive.extensions.count(kDraco)) continue;
      // Points and lines are dropped by the loader unread: their streams
      // (point clouds, say) are not decoded at all.
      const int mode = primitive.mode < 0 ? TINYGLTF_MODE_TRIANGLES : primitive.mode;
      if (mode != TINYGLTF_MODE_TRIANGLES && mode != TINYGLTF_MODE_TRIANGLE_STRIP && mode != TINYGLTF_MODE_TRIANGLE_FAN) {
        primitive.extensions.erase(kDraco);
        continue;
      }
      VISQ_RETURN_IF_ERROR(DecodeDracoPrimitive(model, static_cast<int>(m), static_cast<int>(p), decoded));
    }
  return absl::OkStatus();
}

}  // namespace visq
