#include "gltf_structure_extensions.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <optional>

#include <draco/compression/encode.h>
#include <draco/mesh/triangle_soup_mesh_builder.h>
#include <meshoptimizer.h>

namespace visq_fuzz {
namespace {

using json = nlohmann::json;

constexpr uint64_t kGiB = uint64_t{1} << 30;
constexpr uint8_t kSentinelByte = 0x4B;  // gltf_structure_fuzz.cpp's

// A float at the edges (k in 1..12), else `sane`.
float EdgeFloat(uint64_t k, float sane) {
  static const float kValues[] = {std::numeric_limits<float>::quiet_NaN(),
                                  std::numeric_limits<float>::infinity(),
                                  -std::numeric_limits<float>::infinity(),
                                  1e30f,
                                  -1e30f,
                                  std::numeric_limits<float>::max(),
                                  1e-40f,  // a denormal
                                  0.0f,
                                  -1.0f,
                                  1e-20f,
                                  1e-7f,
                                  1e7f};
  return k >= 1 && k <= 12 ? kValues[k - 1] : sane;
}

// An element count: the truthful one, or one at the edges.
uint64_t Count(Choices& c, const std::string& n, uint64_t sane) {
  static const uint64_t kCounts[] = {0,
                                     uint64_t{1} << 16,
                                     uint64_t{1} << 20,
                                     uint64_t{1} << 23,
                                     uint64_t{1} << 24,
                                     (uint64_t{1} << 24) + 1,
                                     uint64_t{1} << 31,
                                     uint64_t{1} << 32,
                                     uint64_t{1} << 40,
                                     uint64_t{1} << 62,
                                     ~uint64_t{0}};
  const uint64_t k = c.Span(n, 15);
  if (k >= 1 && k <= 11) return kCounts[k - 1];
  if (k == 12) return sane + 1;
  if (k == 13) return c.Span(n + ".raw", ~uint64_t{0});
  return sane;
}

// A count a stream's header announces (32 bits in Draco's).
uint32_t HugeU32(Choices& c, const std::string& n) {
  static const uint32_t kCounts[] = {1u << 20, 1u << 22, (1u << 24) - 1, 1u << 31, 0xFFFFFFFFu};
  const uint64_t k = c.Span(n, 5);
  return k < 5 ? kCounts[k] : static_cast<uint32_t>(c.Span(n + ".raw", 0xFFFFFFFFu));
}

template <typename T>
Bytes AsBytes(const std::vector<T>& values) {
  Bytes b(values.size() * sizeof(T));
  if (!b.empty()) std::memcpy(b.data(), values.data(), b.size());
  return b;
}

// Flips or cuts a stream as decided; true when it did.
bool Garble(Choices& c, const std::string& n, Bytes& stream, bool cut) {
  if (stream.empty()) return false;
  if (cut) {
    stream.resize(c.Span(n + ".keep", stream.size() - 1));
  } else {
    const uint64_t at = c.Span(n + ".at", stream.size() - 1);
    stream[at] ^= static_cast<uint8_t>(1 + c.Span(n + ".xor", 254));
  }
  return true;
}

// The document being extended: its new buffer, views and accessors.
class Builder {
 public:
  Builder(Choices& choices, json& document) : c(choices), g(document) {
    buffer_ = static_cast<int64_t>(g["buffers"].size());
    g["buffers"].push_back(json::object());  // filled by Finish
  }
  Choices& c;
  json& g;
  bool opaque = false;

  int64_t buffer() const { return buffer_; }

  uint64_t Put(const Bytes& b) {
    while (bin_.size() % 4) bin_.push_back(0);
    const uint64_t offset = bin_.size();
    bin_.insert(bin_.end(), b.begin(), b.end());
    return offset;
  }
  int64_t View(json v) {
    g["bufferViews"].push_back(std::move(v));
    return static_cast<int64_t>(g["bufferViews"].size()) - 1;
  }
  int64_t PlainView(const Bytes& b, uint64_t stride = 0) {
    json v = {{"buffer", buffer_}, {"byteOffset", Put(b)}, {"byteLength", b.size()}};
    if (stride) v["byteStride"] = stride;
    return View(std::move(v));
  }
  int64_t Accessor(json a) {
    g["accessors"].push_back(std::move(a));
    return static_cast<int64_t>(g["accessors"].size()) - 1;
  }
  int64_t Mesh(json primitives) {
    g["meshes"].push_back({{"primitives", std::move(primitives)}});
    return static_cast<int64_t>(g["meshes"].size()) - 1;
  }
  void Use(const char* extension, bool required) {
    auto add = [&](json& names) {
      if (std::find(names.begin(), names.end(), extension) == names.end()) names.push_back(extension);
    };
    add(g["extensionsUsed"]);
    if (required) add(g["extensionsRequired"]);
  }
  // Room for a meshopt view's decoded bytes in the fallback buffer: the
  // buffer's index and the view's offset in it.
  std::pair<int64_t, uint64_t> Fallback(uint64_t bytes) {
    if (fallback_ < 0) {
      fallback_ = static_cast<int64_t>(g["buffers"].size());
      g["buffers"].push_back(json::object());
    }
    const uint64_t offset = fallback_length_;
    if (__builtin_add_overflow(fallback_length_, bytes, &fallback_length_)) fallback_length_ = ~uint64_t{0};
    return {fallback_, offset};
  }

  void Finish(std::vector<std::pair<std::string, Bytes>>& files) {
    if (bin_.empty()) bin_.push_back(0);
    for (size_t i = 0; i + 2 < bin_.size(); ++i)  // encoder output is left as it is
      if (bin_[i] == kSentinelByte && bin_[i + 1] == kSentinelByte && bin_[i + 2] == kSentinelByte) opaque = true;
    json& b = g["buffers"][buffer_];
    b["byteLength"] = bin_.size();
    if (c.Flag("x.buf.file")) {
      b["uri"] = "x.bin";
      files.emplace_back("x.bin", bin_);
    } else {
      b["uri"] = DataUri(bin_);
    }
    if (fallback_ < 0) return;
    // EXT_meshopt_compression's fallback: no uri, or one that lies.
    json& f = g["buffers"][fallback_];
    f["byteLength"] = fallback_length_;
    switch (c.Span("x.mo.fallback", 3)) {
      case 1: break;  // no extension, no uri
      case 2:
        f["extensions"]["EXT_meshopt_compression"]["fallback"] = true;
        f["uri"] = DataUri(Bytes(4, 0));
        break;
      case 3: f["extensions"]["EXT_meshopt_compression"]["fallback"] = false; break;
      default: f["extensions"]["EXT_meshopt_compression"]["fallback"] = true; break;
    }
  }

 private:
  Bytes bin_;
  int64_t buffer_ = -1;
  int64_t fallback_ = -1;
  uint64_t fallback_length_ = 0;
};

// ---------------------------------------------------------------------------
// Geometry: a small triangle mesh of its own, with lightmap UVs at the edges.

struct Geometry {
  std::vector<float> positions;  // xyz per vertex
  std::vector<uint32_t> indices;  // three per triangle
  std::vector<float> uvs;         // TEXCOORD_1: uv per vertex, or empty
  uint64_t vertices() const { return positions.size() / 3; }
};

Geometry MakeGeometry(Choices& c) {
  Geometry geo;
  const uint64_t n = 3 + c.Span("x.verts", 61);
  for (uint64_t i = 0; i < n; ++i) {
    geo.positions.push_back(float(i % 8));
    geo.positions.push_back(float(i / 8));
    geo.positions.push_back(float(c.Span("x.z", 16)));
  }
  const uint64_t triangles = c.Flag("x.no_triangles") ? 0 : 1 + c.Span("x.tris", 63);
  const uint64_t shift = c.Span("x.shift", n - 1);
  for (uint64_t t = 0; t < triangles; ++t)
    for (uint64_t k = 0; k < 3; ++k) geo.indices.push_back(static_cast<uint32_t>((t + k + shift) % n));
  if (c.Flag("x.uv")) {
    for (uint64_t i = 0; i < n; ++i) {
      geo.uvs.push_back(float(i % 8) / 8.0f);
      geo.uvs.push_back(float(i / 8) / 8.0f);
    }
    // NaN, Inf, 1e30, ... at one vertex, or (at == n) at every vertex.
    const float edge = EdgeFloat(c.Span("x.uv.edge", 15), 0.5f);
    const uint64_t at = c.Span("x.uv.at", n);
    const uint64_t component = c.Span("x.uv.component", 1);
    for (uint64_t i = 0; i < n; ++i)
      if (at == n || at == i) geo.uvs[2 * i + component] = edge;
  }
  return geo;
}

json PlainPrimitive(Builder& b, const Geometry& geo) {
  json prim;
  prim["attributes"]["POSITION"] = b.Accessor({{"bufferView", b.PlainView(AsBytes(geo.positions), 12)},
                                               {"componentType", 5126},
                                               {"count", geo.vertices()},
                                               {"type", "VEC3"}});
  if (!geo.uvs.empty())
    prim["attributes"]["TEXCOORD_1"] = b.Accessor({{"bufferView", b.PlainView(AsBytes(geo.uvs), 8)},
                                                   {"componentType", 5126},
                                                   {"count", geo.vertices()},
                                                   {"type", "VEC2"}});
  Bytes indices = AsBytes(geo.indices);
  if (indices.empty()) indices.resize(4, 0);  // an empty accessor still needs a view
  prim["indices"] = b.Accessor(
      {{"bufferView", b.PlainView(indices)}, {"componentType", 5125}, {"count", geo.indices.size()},
       {"type", "SCALAR"}});
  return prim;
}

// ---------------------------------------------------------------------------
// EXT_meshopt_compression.

enum class Mode { kAttributes, kTriangles, kIndices };

// One EXT_meshopt_compression view: `raw` (count elements of `stride`
// bytes; for the index modes, uint32 indices decoded at stride 2 or 4)
// encoded by meshoptimizer, then, as decided, lied about: counts that
// announce 64 MiB to 8 GiB from a stream of a few dozen bytes, cut or
// flipped streams, and modes, filters, strides and offsets that do not fit.
int64_t MeshoptView(Builder& b, const std::string& n, const Bytes& raw, uint64_t count, uint64_t stride, Mode mode,
                    const char* filter) {
  Choices& c = b.c;
  Bytes stream;
  if (mode == Mode::kAttributes) {
    stream.resize(meshopt_encodeVertexBufferBound(count, stride));
    stream.resize(meshopt_encodeVertexBuffer(stream.data(), stream.size(), raw.data(), count, stride));
  } else {
    std::vector<uint32_t> indices(count);
    if (count) std::memcpy(indices.data(), raw.data(), count * 4);
    const size_t vertices = indices.empty() ? 1 : *std::max_element(indices.begin(), indices.end()) + size_t{1};
    if (mode == Mode::kTriangles) {
      stream.resize(meshopt_encodeIndexBufferBound(count, vertices));
      stream.resize(meshopt_encodeIndexBuffer(stream.data(), stream.size(), indices.data(), count));
    } else {
      stream.resize(meshopt_encodeIndexSequenceBound(count, vertices));
      stream.resize(meshopt_encodeIndexSequence(stream.data(), stream.size(), indices.data(), count));
    }
  }
  static const char* kModes[] = {"ATTRIBUTES", "TRIANGLES", "INDICES", "", "attributes", "POINTS"};
  static const char* kFilters[] = {"NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL", "BOGUS"};
  static const uint64_t kStrides[] = {0, 1, 2, 3, 4, 6, 8, 16, 256, 257, (uint64_t{1} << 32) + 12};
  std::string mode_name = kModes[static_cast<int>(mode)];
  std::string filter_name = filter;
  uint64_t announced = count, ext_stride = stride, view_length = count * stride;
  json ext_buffer = b.buffer();
  std::optional<json> ext_offset, ext_length;
  const uint64_t lie = c.Span(n + ".lie", 15);
  switch (lie) {
    case 1:  // 1 GiB; 8 GiB, 64 MiB (under the fuzzer's cap) or 4 GiB + 12 (in whole triangles for TRIANGLES)
    case 2: {
      static const uint64_t kAnnounced[] = {8 * kGiB, kGiB / 16, 4 * kGiB + 12};
      announced = (lie == 1 ? kGiB : kAnnounced[c.Span(n + ".size", 2)]) / stride;
      if (mode == Mode::kTriangles) announced -= announced % 3;
      view_length = announced * stride;
      break;
    }
    case 3:  // a few elements more than the stream holds
      announced = count + 1 + c.Span(n + ".more", 255);
      view_length = announced * stride;
      break;
    case 4: view_length += 1 + c.Span(n + ".more", 255); break;  // count × stride is not the view's length
    case 5: b.opaque |= Garble(c, n + ".cut", stream, true); break;
    case 6: b.opaque |= Garble(c, n + ".flip", stream, false); break;
    case 7: mode_name = kModes[c.Span(n + ".mode", 5)]; break;
    case 8: filter_name = kFilters[c.Span(n + ".filter", 4)]; break;
    case 9:
      ext_stride = kStrides[c.Span(n + ".stride", 10)];
      view_length = count * ext_stride;
      break;
    case 10: ext_offset = json((uint64_t{1} << 32) + c.Span(n + ".offset", 255)); break;
    case 11:  // the fallback buffer, or none
      ext_buffer = json(b.buffer() + 1 + static_cast<int64_t>(c.Span(n + ".buffer", 3)));
      break;
    case 12:
      announced = c.Span(n + ".count", ~uint64_t{0});
      view_length = announced * stride;  // may wrap
      break;
    case 13: ext_length = json(stream.size() + (uint64_t{1} << 32)); break;
    case 14: announced = 0; view_length = 0; break;
    case 15: stream.assign(stream.size(), 0); break;  // the right length, no stream
    default: break;
  }
  const uint64_t stream_length = stream.size();
  const uint64_t offset = b.Put(stream);
  json ext = {{"buffer", ext_buffer},
              {"byteOffset", ext_offset ? *ext_offset : json(offset)},
              {"byteLength", ext_length ? *ext_length : json(stream_length)},
              {"byteStride", ext_stride},
              {"count", announced},
              {"mode", mode_name}};
  if (filter_name != "NONE" || c.Flag(n + ".filter_none")) ext["filter"] = filter_name;
  const auto [fallback, fallback_offset] = b.Fallback(view_length);
  json v = {{"buffer", fallback}, {"byteOffset", fallback_offset}, {"byteLength", view_length}};
  if (mode == Mode::kAttributes) v["byteStride"] = stride;
  v["extensions"]["EXT_meshopt_compression"] = ext;
  b.Use("EXT_meshopt_compression", c.Flag("x.mo.required"));
  return b.View(std::move(v));
}

json MeshoptPrimitive(Builder& b, const Geometry& geo) {
  Choices& c = b.c;
  const uint64_t n = geo.vertices();
  json prim;
  // Positions: floats, or the exponential filter's encoding of them.
  Bytes positions = AsBytes(geo.positions);
  const char* filter = "NONE";
  if (c.Flag("x.mo.pos.exp")) {
    std::vector<uint32_t> encoded(3 * n);
    meshopt_encodeFilterExp(encoded.data(), n, 12, 1 + static_cast<int>(c.Span("x.mo.pos.bits", 23)),
                            geo.positions.data());
    positions = AsBytes(encoded);
    filter = "EXPONENTIAL";
  }
  prim["attributes"]["POSITION"] = b.Accessor(
      {{"bufferView", MeshoptView(b, "x.mo.pos", positions, n, 12, Mode::kAttributes, filter)},
       {"componentType", 5126},
       {"count", n},
       {"type", "VEC3"}});
  if (!geo.uvs.empty())
    prim["attributes"]["TEXCOORD_1"] = b.Accessor(
        {{"bufferView", MeshoptView(b, "x.mo.uv", AsBytes(geo.uvs), n, 8, Mode::kAttributes, "NONE")},
         {"componentType", 5126},
         {"count", n},
         {"type", "VEC2"}});
  const uint64_t stride = c.Flag("x.mo.idx.u16") ? 2 : 4;
  const Mode mode = c.Flag("x.mo.idx.sequence") ? Mode::kIndices : Mode::kTriangles;
  prim["indices"] = b.Accessor(
      {{"bufferView", MeshoptView(b, "x.mo.idx", AsBytes(geo.indices), geo.indices.size(), stride, mode, "NONE")},
       {"componentType", stride == 2 ? 5123 : 5125},
       {"count", geo.indices.size()},
       {"type", "SCALAR"}});
  return prim;
}

// ---------------------------------------------------------------------------
// KHR_draco_mesh_compression.

Bytes EncodeDraco(const Geometry& geo, int method, int position_bits) {
  const size_t faces = geo.indices.size() / 3;
  if (faces == 0) return {};
  draco::TriangleSoupMeshBuilder builder;
  builder.Start(static_cast<int>(faces));
  const int position = builder.AddAttribute(draco::GeometryAttribute::POSITION, 3, draco::DT_FLOAT32);
  const int uv = geo.uvs.empty() ? -1 : builder.AddAttribute(draco::GeometryAttribute::TEX_COORD, 2, draco::DT_FLOAT32);
  for (size_t f = 0; f < faces; ++f) {
    const uint32_t* corner = &geo.indices[3 * f];
    builder.SetAttributeValuesForFace(position, draco::FaceIndex(static_cast<uint32_t>(f)),
                                      &geo.positions[3 * corner[0]], &geo.positions[3 * corner[1]],
                                      &geo.positions[3 * corner[2]]);
    if (uv >= 0)
      builder.SetAttributeValuesForFace(uv, draco::FaceIndex(static_cast<uint32_t>(f)), &geo.uvs[2 * corner[0]],
                                        &geo.uvs[2 * corner[1]], &geo.uvs[2 * corner[2]]);
  }
  std::unique_ptr<draco::Mesh> mesh = builder.Finalize();
  if (!mesh) return {};
  draco::Encoder encoder;
  encoder.SetEncodingMethod(method);
  if (position_bits) encoder.SetAttributeQuantization(draco::GeometryAttribute::POSITION, position_bits);
  draco::EncoderBuffer out;
  if (!encoder.EncodeMeshToBuffer(*mesh, &out).ok()) return {};
  return Bytes(out.data(), out.data() + out.size());
}

void PutVarint(Bytes& out, uint32_t v) {
  do {
    out.push_back(static_cast<uint8_t>((v & 0x7F) | (v >= 0x80 ? 0x80 : 0)));
    v >>= 7;
  } while (v);
}

// The stream with the face or point count of its connectivity header
// replaced. Draco 1.5 writes bitstream 2.2: an 11-byte header (no metadata
// here), then the faces and points as varints (sequential), or a traversal
// byte, the points and the faces (edgebreaker): the layout the loader's
// ReadDracoCounts reads.
Bytes PatchDracoCounts(const Bytes& s, std::optional<uint32_t> faces, std::optional<uint32_t> points) {
  size_t at = 11;
  if (s.size() < at + 1 || s[5] != 2 || s[6] != 2) return s;
  const bool edgebreaker = s[8] == 1;
  if (edgebreaker) ++at;
  Bytes out(s.begin(), s.begin() + static_cast<std::ptrdiff_t>(at));
  for (int field = 0; field < 2; ++field) {
    uint32_t value = 0;
    int shift = 0;
    while (at < s.size() && shift < 35) {
      const uint8_t byte = s[at++];
      value |= uint32_t(byte & 0x7F) << shift;
      shift += 7;
      if (!(byte & 0x80)) break;
    }
    const bool is_faces = (field == 0) != edgebreaker;
    const std::optional<uint32_t>& replacement = is_faces ? faces : points;
    PutVarint(out, replacement ? *replacement : value);
  }
  out.insert(out.end(), s.begin() + static_cast<std::ptrdiff_t>(std::min(at, s.size())), s.end());
  return out;
}

json DracoPrimitive(Builder& b, const Geometry& geo) {
  Choices& c = b.c;
  static const int kBits[] = {0, 11, 14};
  const int method = c.Flag("x.draco.edgebreaker") ? draco::MESH_EDGEBREAKER_ENCODING : draco::MESH_SEQUENTIAL_ENCODING;
  Bytes stream = EncodeDraco(geo, method, kBits[c.Span("x.draco.bits", 2)]);
  json position_id = 0, uv_id = 1;
  uint64_t position_count = geo.vertices();
  bool indexed = true;
  std::optional<json> view;
  int64_t extra_length = 0;
  switch (c.Span("x.draco.lie", 15)) {
    case 1: stream = PatchDracoCounts(stream, HugeU32(c, "x.draco.faces"), std::nullopt); break;
    case 2: stream = PatchDracoCounts(stream, std::nullopt, HugeU32(c, "x.draco.points")); break;
    case 3: {
      const uint32_t faces = HugeU32(c, "x.draco.faces");
      stream = PatchDracoCounts(stream, faces, HugeU32(c, "x.draco.points"));
      break;
    }
    case 4: b.opaque |= Garble(c, "x.draco.cut", stream, true); break;
    case 5: b.opaque |= Garble(c, "x.draco.flip", stream, false); break;
    case 6: position_id = 2 + c.Span("x.draco.id", 253); break;  // no such attribute
    case 7: {
      static const json kIds[] = {-1, "0", uint64_t{1} << 31, 0.5, json::array()};
      position_id = kIds[c.Span("x.draco.id", 4)];
      break;
    }
    case 8: std::swap(position_id, uv_id); break;  // 2 components where 3 belong
    case 9: position_count = Count(c, "x.draco.accessor_count", position_count); break;
    case 10: indexed = false; break;
    case 11: view = json(-1 + static_cast<int64_t>(c.Span("x.draco.view", 1)) * (int64_t{1} << 31)); break;
    case 12: extra_length = 1 + static_cast<int64_t>(c.Span("x.draco.more", 4095)); break;  // past the buffer
    case 13:  // a point cloud, an unknown method, a newer version, metadata announced
      if (stream.size() > 9) {
        static const std::pair<size_t, uint8_t> kPatches[] = {{7, 0}, {8, 2}, {5, 9}, {9, 0x80}};
        const auto& [at, value] = kPatches[c.Span("x.draco.header", 3)];
        stream[at] = at == 9 ? stream[at] | value : value;
      }
      break;
    case 14: stream.assign(stream.size(), 0); break;
    case 15: {  // a stream that announces faces just under the cap, read by Draco
      stream = PatchDracoCounts(stream, (1u << 22) + static_cast<uint32_t>(c.Span("x.draco.faces", 255)), std::nullopt);
      break;
    }
    default: break;
  }
  if (stream.empty()) stream.push_back(0);
  if (!view) {
    const uint64_t offset = b.Put(stream);
    view = b.View({{"buffer", b.buffer()}, {"byteOffset", offset}, {"byteLength", stream.size() + extra_length}});
  }
  json prim;
  prim["attributes"]["POSITION"] =
      b.Accessor({{"componentType", 5126}, {"count", position_count}, {"type", "VEC3"}});
  json ids = {{"POSITION", position_id}};
  if (!geo.uvs.empty()) {
    prim["attributes"]["TEXCOORD_1"] =
        b.Accessor({{"componentType", 5126}, {"count", geo.vertices()}, {"type", "VEC2"}});
    ids["TEXCOORD_1"] = uv_id;
  }
  if (indexed)
    prim["indices"] = b.Accessor({{"componentType", 5125}, {"count", geo.indices.size()}, {"type", "SCALAR"}});
  prim["extensions"]["KHR_draco_mesh_compression"] = {{"bufferView", *view}, {"attributes", ids}};
  b.Use("KHR_draco_mesh_compression", true);
  return prim;
}

// ---------------------------------------------------------------------------
// EXT_mesh_gpu_instancing.

enum class Instance { kTranslation, kRotation, kScale };

// One instance attribute's accessor: `count` instances (up to 2^62), of
// which the first few have values, stored densely, as a sparse accessor with
// or without a view under it, or through meshopt.
int64_t InstanceAccessor(Builder& b, const std::string& n, Instance attribute, uint64_t count) {
  Choices& c = b.c;
  const int components = attribute == Instance::kRotation ? 4 : 3;
  const uint64_t written = std::min<uint64_t>(std::max<uint64_t>(count, 1), 16);
  // The values: a row of unit steps, no rotation, unit scale; with edges
  // (NaN, Inf, 1e-40, 0, ...) at one instance or (at == written) at every one.
  std::vector<float> values;
  for (uint64_t i = 0; i < written; ++i)
    for (int k = 0; k < components; ++k) {
      if (attribute == Instance::kTranslation) values.push_back(k == 0 ? float(i) : 0.0f);
      if (attribute == Instance::kRotation) values.push_back(k == 3 ? 1.0f : 0.0f);
      if (attribute == Instance::kScale) values.push_back(1.0f);
    }
  const uint64_t edge = c.Span(n + ".edge", 15);
  const uint64_t at = c.Span(n + ".at", written);
  const uint64_t component = c.Span(n + ".component", components);  // == components: all of them
  for (uint64_t i = 0; i < written; ++i)
    for (int k = 0; k < components; ++k)
      if ((at == written || at == i) && (component == uint64_t(components) || component == uint64_t(k)))
        values[i * components + k] = EdgeFloat(edge, values[i * components + k]);

  // Component type: float, normalized short or byte, unsigned short.
  static const int kTypes[] = {5126, 5122, 5120, 5123};
  const uint64_t type = c.Span(n + ".ct", 3);
  Bytes data;
  for (float v : values) {
    const float clamped = std::isfinite(v) ? std::clamp(v, -1.0f, 1.0f) : 0.0f;
    if (type == 0) {
      const Bytes f = AsBytes(std::vector<float>{v});
      data.insert(data.end(), f.begin(), f.end());
    } else if (type == 1) {
      const auto s = static_cast<int16_t>(std::lround(clamped * 32767.0f));
      data.push_back(static_cast<uint8_t>(s));
      data.push_back(static_cast<uint8_t>(uint16_t(s) >> 8));
    } else if (type == 2) {
      data.push_back(static_cast<uint8_t>(static_cast<int8_t>(std::lround(clamped * 127.0f))));
    } else {
      const auto u = static_cast<uint16_t>(std::isfinite(v) ? std::clamp(v, 0.0f, 65535.0f) : 0.0f);
      data.push_back(static_cast<uint8_t>(u));
      data.push_back(static_cast<uint8_t>(u >> 8));
    }
  }
  json a = {{"componentType", kTypes[type]}, {"count", count}, {"type", components == 4 ? "VEC4" : "VEC3"}};
  if (type == 1 || type == 2) a["normalized"] = true;

  const uint64_t storage = c.Span(n + ".storage", 3);  // dense, sparse without a view, sparse over one, meshopt
  if (storage == 0 || storage == 2) a["bufferView"] = b.PlainView(data);
  if (storage == 3) {
    // meshopt wants whole 4-byte words: floats, and shorts as VEC4
    // (ROTATION, through the QUATERNION filter when decided).
    if (type == 1 && components == 4) {
      Bytes encoded = data;
      const char* filter = "NONE";
      if (c.Flag(n + ".quaternion")) {
        meshopt_encodeFilterQuat(encoded.data(), written, 8, 4 + static_cast<int>(c.Span(n + ".bits", 12)),
                                 values.data());
        filter = "QUATERNION";
      }
      a["bufferView"] = MeshoptView(b, n + ".mo", encoded, written, 8, Mode::kAttributes, filter);
    } else {
      const Bytes floats = AsBytes(values);
      a["componentType"] = 5126;
      a.erase("normalized");
      a["bufferView"] = MeshoptView(b, n + ".mo", floats, written, 4 * uint64_t(components), Mode::kAttributes, "NONE");
    }
  }
  if (storage == 1 || storage == 2) {
    // The written values at the first indices, the last ones, or spread.
    std::vector<uint32_t> indices;
    const uint64_t spread = c.Span(n + ".sparse_at", 2);
    for (uint64_t i = 0; i < written; ++i) {
      uint64_t index = i;
      if (spread == 1 && count > written) index = count - written + i;
      if (spread == 2) index = count / written * i;
      indices.push_back(static_cast<uint32_t>(index));  // cut at 2^32, as a 32-bit index is
    }
    a["sparse"] = {{"count", written},
                   {"indices", {{"bufferView", b.PlainView(AsBytes(indices))}, {"componentType", 5125}}},
                   {"values", {{"bufferView", b.PlainView(data)}}}};
  }
  return b.Accessor(std::move(a));
}

void AddInstancing(Builder& b, uint64_t where) {
  Choices& c = b.c;
  json& nodes = b.g["nodes"];
  // The mesh the instances place: the node's own (mesh 0 when it has none),
  // one without triangles, or none.
  std::optional<json> mesh;
  switch (c.Span("x.inst.mesh", 2)) {
    case 1: {
      const int64_t empty = b.Accessor({{"bufferView", b.PlainView(Bytes(12, 0))},
                                        {"componentType", 5126},
                                        {"count", 0},
                                        {"type", "VEC3"}});
      mesh = b.Mesh(json::array({{{"attributes", {{"POSITION", empty}}}}}));
      break;
    }
    case 2: mesh = json(); break;  // null: no mesh
    default: break;
  }
  // The attributes: TRANSLATION, ROTATION, SCALE as decided (0: TRANSLATION
  // alone), with counts up to 2^62 and one count that may differ.
  const uint64_t which = c.Span("x.inst.attrs", 7);
  const uint64_t count = Count(c, "x.inst.count", 1 + c.Span("x.inst.n", 15));
  const uint64_t odd_one = c.Span("x.inst.mismatch", 3);  // 1..3: that attribute has count + 1
  json attributes = json::object();
  static const std::pair<const char*, Instance> kAttributes[] = {
      {"TRANSLATION", Instance::kTranslation}, {"ROTATION", Instance::kRotation}, {"SCALE", Instance::kScale}};
  for (int k = 0; k < 3; ++k) {
    if (which ? !(which & (1u << k)) : k != 0) continue;
    const auto& [name, attribute] = kAttributes[k];
    attributes[name] = InstanceAccessor(b, std::string("x.inst.") + name, attribute,
                                        count + (odd_one == uint64_t(k) + 1 ? 1 : 0));
  }
  auto instance = [&](json& node) {
    if (mesh) {
      if (mesh->is_null()) node.erase("mesh");
      else node["mesh"] = *mesh;
    } else if (!node.contains("mesh")) {
      node["mesh"] = 0;
    }
    node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"] = attributes;
  };
  // On one node (the first, the last: the deepest of a chain, or a decided
  // one), or on each of the first 64.
  if (where == 1) {
    const uint64_t last = nodes.size() - 1;
    switch (c.Span("x.inst.node", 2)) {
      case 1: instance(nodes[last]); break;
      case 2: instance(nodes[c.Span("x.inst.node_index", last)]); break;
      default: instance(nodes[0]); break;
    }
  } else {
    for (size_t i = 0; i < nodes.size() && i < 64; ++i) instance(nodes[i]);
  }
  b.Use("EXT_mesh_gpu_instancing", c.Flag("x.inst.required"));
}

}  // namespace

ExtensionCases AddExtensionCases(Choices& c, json& g, std::vector<std::pair<std::string, Bytes>>& files) {
  ExtensionCases result;
  const uint64_t geometry = c.Span("x.geo", 3);   // none, plain, meshopt, Draco
  const uint64_t instancing = c.Span("x.inst", 2);  // none, one node, the first 64
  if (!geometry && !instancing) return result;
  if (!g["nodes"].is_array() || g["nodes"].empty() || !g["meshes"].is_array()) return result;
  Builder b(c, g);

  // A primitive of the decided kind in every mesh, in place of theirs or
  // beside them.
  if (geometry) {
    const Geometry geo = MakeGeometry(c);
    json prim;
    if (geometry == 1) prim = PlainPrimitive(b, geo);
    if (geometry == 2) prim = MeshoptPrimitive(b, geo);
    if (geometry == 3) prim = DracoPrimitive(b, geo);
    const bool beside = c.Flag("x.geo.beside");
    for (json& mesh : g["meshes"]) {
      if (!beside) mesh["primitives"] = json::array();
      mesh["primitives"].push_back(prim);
    }
  }
  if (instancing) AddInstancing(b, instancing);
  b.Finish(files);
  result.added = true;
  result.opaque_values = b.opaque;
  return result;
}

}  // namespace visq_fuzz
