// Compressed, quantized and instanced glTF, as studios' pipelines write it
// (gltfpack, gltf-transform): each form of the Stanford bunny from
// ../shared/scenes must load to the geometry of the plain file, exactly
// where the encoding is lossless and within its step where it quantizes.
// Malformed streams are refused by the buffer view or primitive they sit in.
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>

#include <draco/compression/encode.h>
#include <draco/mesh/mesh.h>
#include <gtest/gtest.h>
#include <meshoptimizer.h>
#include <nlohmann/json.hpp>

#include "scene/gltf_loader.h"
#include "test_support.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;
using testing::ScratchDir;

// The bunny as float positions and 32-bit corner indices.
struct Mesh {
  std::vector<float> positions;  // xyz per vertex
  std::vector<uint32_t> indices;
  size_t vertices() const { return positions.size() / 3; }
};

std::optional<Mesh> LoadBunny(const fs::path& scenes) {
  StatusOr<Scene> scene = LoadGltfFile(scenes / "bunny/bunny.gltf");
  if (!scene.ok()) return std::nullopt;
  Mesh mesh;
  for (const auto& p : scene->positions)
    for (int a = 0; a < 3; ++a) mesh.positions.push_back(static_cast<float>(p[a]));
  for (const auto& t : scene->triangles)
    for (int c = 0; c < 3; ++c) mesh.indices.push_back(t[c]);
  return mesh;
}

template <typename T>
void Append(std::vector<unsigned char>& bin, const T* data, size_t count) {
  const size_t at = bin.size();
  bin.resize(at + count * sizeof(T));
  std::memcpy(bin.data() + at, data, count * sizeof(T));
  while (bin.size() % 4 != 0) bin.push_back(0);
}

// A document with one buffer (`name`.bin beside the .gltf) that the caller
// fills with views, accessors and meshes.
struct Document {
  json gltf = {{"asset", {{"version", "2.0"}}}, {"scene", 0}, {"scenes", {{{"nodes", {0}}}}},
               {"nodes", {{{"mesh", 0}}}}, {"bufferViews", json::array()}, {"accessors", json::array()}};
  std::vector<unsigned char> bin;

  int View(const void* data, size_t bytes, int stride = 0) {
    const size_t at = bin.size();
    Append(bin, static_cast<const unsigned char*>(data), bytes);
    json view = {{"buffer", 0}, {"byteOffset", at}, {"byteLength", bytes}};
    if (stride > 0) view["byteStride"] = stride;
    gltf["bufferViews"].push_back(view);
    return static_cast<int>(gltf["bufferViews"].size()) - 1;
  }
  int Accessor(int view, int component_type, size_t count, const char* type, bool normalized = false) {
    json accessor = {{"componentType", component_type}, {"count", count}, {"type", type}};
    if (view >= 0) accessor["bufferView"] = view;
    if (normalized) accessor["normalized"] = true;
    gltf["accessors"].push_back(accessor);
    return static_cast<int>(gltf["accessors"].size()) - 1;
  }
  void Primitive(int positions, int indices, json extensions = nullptr) {
    json primitive = {{"attributes", {{"POSITION", positions}}}, {"indices", indices}};
    if (!extensions.is_null()) primitive["extensions"] = extensions;
    gltf["meshes"] = {{{"primitives", {primitive}}}};
  }
  fs::path Write(const ScratchDir& dir, const std::string& name) {
    gltf["buffers"] = json::array({{{"uri", name + ".bin"}, {"byteLength", bin.size()}}});
    if (gltf.contains("extra_buffers"))
      for (const auto& b : gltf["extra_buffers"]) gltf["buffers"].push_back(b);
    gltf.erase("extra_buffers");
    std::ofstream(dir.path() / (name + ".bin"), std::ios::binary)
        .write(reinterpret_cast<const char*>(bin.data()), static_cast<std::streamsize>(bin.size()));
    const fs::path path = dir.path() / (name + ".gltf");
    std::ofstream(path) << gltf.dump();
    return path;
  }
};

fs::path WritePlain(const ScratchDir& dir, const Mesh& mesh) {
  Document doc;
  const int p = doc.Accessor(doc.View(mesh.positions.data(), mesh.positions.size() * 4), 5126, mesh.vertices(), "VEC3");
  const int i = doc.Accessor(doc.View(mesh.indices.data(), mesh.indices.size() * 4), 5125, mesh.indices.size(),
                             "SCALAR");
  doc.Primitive(p, i);
  return doc.Write(dir, "plain");
}

// EXT_meshopt_compression as gltfpack writes it: the compressed streams in
// buffer 0, and a fallback buffer without a uri that the views point at.
Document MeshoptDocument(const Mesh& mesh) {
  Document doc;
  doc.gltf["extensionsUsed"] = {"EXT_meshopt_compression"};
  doc.gltf["extensionsRequired"] = {"EXT_meshopt_compression"};
  std::vector<unsigned char> vertices(meshopt_encodeVertexBufferBound(mesh.vertices(), 12));
  vertices.resize(meshopt_encodeVertexBuffer(vertices.data(), vertices.size(), mesh.positions.data(), mesh.vertices(), 12));
  std::vector<unsigned char> indices(meshopt_encodeIndexBufferBound(mesh.indices.size(), mesh.vertices()));
  indices.resize(meshopt_encodeIndexBuffer(indices.data(), indices.size(), mesh.indices.data(), mesh.indices.size()));
  auto compressed_view = [&](const std::vector<unsigned char>& stream, size_t count, int stride, const char* mode,
                             size_t fallback_offset) {
    const size_t at = doc.bin.size();
    Append(doc.bin, stream.data(), stream.size());
    doc.gltf["bufferViews"].push_back(
        {{"buffer", 1}, {"byteOffset", fallback_offset}, {"byteLength", count * stride},
         {"extensions",
          {{"EXT_meshopt_compression",
            {{"buffer", 0}, {"byteOffset", at}, {"byteLength", stream.size()}, {"byteStride", stride},
             {"count", count}, {"mode", mode}}}}}});
    if (std::string(mode) == "ATTRIBUTES") doc.gltf["bufferViews"].back()["byteStride"] = stride;
    return static_cast<int>(doc.gltf["bufferViews"].size()) - 1;
  };
  const int p = doc.Accessor(compressed_view(vertices, mesh.vertices(), 12, "ATTRIBUTES", 0), 5126, mesh.vertices(),
                             "VEC3");
  const int i = doc.Accessor(compressed_view(indices, mesh.indices.size(), 4, "TRIANGLES", mesh.vertices() * 12), 5125,
                             mesh.indices.size(), "SCALAR");
  doc.Primitive(p, i);
  doc.gltf["extra_buffers"] = {{{"byteLength", mesh.vertices() * 12 + mesh.indices.size() * 4},
                                {"extensions", {{"EXT_meshopt_compression", {{"fallback", true}}}}}}};
  return doc;
}

// The same document as one .glb (JSON chunk, then the BIN chunk).
fs::path WriteGlb(const ScratchDir& dir, Document doc, const std::string& name) {
  doc.gltf["buffers"] = json::array({{{"byteLength", doc.bin.size()}}});
  for (const auto& b : doc.gltf["extra_buffers"]) doc.gltf["buffers"].push_back(b);
  doc.gltf.erase("extra_buffers");
  std::string text = doc.gltf.dump();
  while (text.size() % 4 != 0) text.push_back(' ');
  auto u32 = [](std::string& out, uint32_t v) { out.append(reinterpret_cast<const char*>(&v), 4); };
  std::string glb = "glTF";
  u32(glb, 2);
  u32(glb, static_cast<uint32_t>(12 + 8 + text.size() + 8 + doc.bin.size()));
  u32(glb, static_cast<uint32_t>(text.size()));
  glb += "JSON";
  glb += text;
  u32(glb, static_cast<uint32_t>(doc.bin.size()));
  glb.append("BIN\0", 4);
  glb.append(reinterpret_cast<const char*>(doc.bin.data()), doc.bin.size());
  const fs::path path = dir.path() / (name + ".glb");
  std::ofstream(path, std::ios::binary) << glb;
  return path;
}

// A triangle's corners from its lowest index on, so that encoders that
// rotate corners (meshopt's index codec does) keep the same triangle.
glm::uvec3 Canonical(glm::uvec3 t) {
  while (t[0] > t[1] || t[0] > t[2]) t = glm::uvec3(t[1], t[2], t[0]);
  return t;
}

void ExpectSameGeometry(const Scene& loaded_record, const Scene& reference_record, double tolerance) {
  const Scene& loaded = loaded_record.Flattened();
  const Scene& reference = reference_record.Flattened();
  ASSERT_EQ(loaded.triangles.size(), reference.triangles.size());
  ASSERT_EQ(loaded.positions.size(), reference.positions.size());
  double worst = 0;
  for (size_t v = 0; v < loaded.positions.size(); ++v)
    for (int a = 0; a < 3; ++a) worst = std::max(worst, std::abs(loaded.positions[v][a] - reference.positions[v][a]));
  EXPECT_LE(worst, tolerance);
  size_t differing = 0;
  for (size_t t = 0; t < loaded.triangles.size(); ++t)
    differing += Canonical(loaded.triangles[t]) != Canonical(reference.triangles[t]);
  EXPECT_EQ(differing, 0u);
}

class CompressedBunny : public ::testing::Test {
 protected:
  void SetUp() override {
    auto scenes = testing::SharedScenesDir();
    if (!scenes) GTEST_SKIP() << "../shared/scenes is absent: real-scene test skipped";
    auto bunny = LoadBunny(*scenes);
    ASSERT_TRUE(bunny);
    mesh_ = *bunny;
    StatusOr<Scene> plain = LoadGltfFile(WritePlain(dir_, mesh_));
    ASSERT_TRUE(plain.ok()) << plain.status();
    reference_ = *std::move(plain);
    ASSERT_EQ(reference_.triangles.size(), 69451u);
  }
  ScratchDir dir_;
  Mesh mesh_;
  Scene reference_;
};

TEST_F(CompressedBunny, MeshoptBufferViewsDecodeToTheSameBits) {
  StatusOr<Scene> gltf = LoadGltfFile(MeshoptDocument(mesh_).Write(dir_, "meshopt"));
  ASSERT_TRUE(gltf.ok()) << gltf.status();
  ExpectSameGeometry(*gltf, reference_, 0.0);
  // In a .glb the fallback buffer would otherwise be filled from the BIN chunk.
  StatusOr<Scene> glb = LoadGltfFile(WriteGlb(dir_, MeshoptDocument(mesh_), "meshopt"));
  ASSERT_TRUE(glb.ok()) << glb.status();
  ExpectSameGeometry(*glb, reference_, 0.0);
}

TEST_F(CompressedBunny, QuantizedPositionsLoadWithinTheirStep) {
  // KHR_mesh_quantization: normalized 16-bit positions, the box restored by
  // the node's scale and translation (as gltfpack writes them).
  glm::dvec3 lo(1e9), hi(-1e9);
  for (size_t v = 0; v < mesh_.vertices(); ++v)
    for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], double(mesh_.positions[3 * v + a])),
                                hi[a] = std::max(hi[a], double(mesh_.positions[3 * v + a]));
  const double extent = std::max({hi.x - lo.x, hi.y - lo.y, hi.z - lo.z});
  std::vector<uint16_t> quantized;
  for (size_t v = 0; v < mesh_.vertices(); ++v)
    for (int a = 0; a < 3; ++a)
      quantized.push_back(static_cast<uint16_t>(std::lround((mesh_.positions[3 * v + a] - lo[a]) / extent * 65535.0)));
  // Attributes are 4-byte aligned: three shorts take a stride of 8 bytes.
  std::vector<uint16_t> strided(mesh_.vertices() * 4, 0);
  for (size_t v = 0; v < mesh_.vertices(); ++v)
    for (int a = 0; a < 3; ++a) strided[4 * v + a] = quantized[3 * v + a];
  Document doc;
  doc.gltf["extensionsUsed"] = {"KHR_mesh_quantization"};
  doc.gltf["extensionsRequired"] = {"KHR_mesh_quantization"};
  doc.gltf["nodes"][0]["translation"] = {lo.x, lo.y, lo.z};
  doc.gltf["nodes"][0]["scale"] = {extent, extent, extent};
  const int p = doc.Accessor(doc.View(strided.data(), strided.size() * 2, 8), 5123, mesh_.vertices(), "VEC3", true);
  const int i = doc.Accessor(doc.View(mesh_.indices.data(), mesh_.indices.size() * 4), 5125, mesh_.indices.size(),
                             "SCALAR");
  doc.Primitive(p, i);
  StatusOr<Scene> scene = LoadGltfFile(doc.Write(dir_, "quantized"));
  ASSERT_TRUE(scene.ok()) << scene.status();
  // Half a step of 16 bits, plus the float rounding of the file's numbers.
  ExpectSameGeometry(*scene, reference_, 0.5 * extent / 65535.0 + 1e-7 * extent);
}

TEST_F(CompressedBunny, DracoPrimitivesDecodeWithinTheirQuantization) {
  draco::Mesh mesh;
  mesh.set_num_points(static_cast<uint32_t>(mesh_.vertices()));
  draco::GeometryAttribute position;
  position.Init(draco::GeometryAttribute::POSITION, nullptr, 3, draco::DT_FLOAT32, false, 12, 0);
  const int attribute = mesh.AddAttribute(position, true, static_cast<uint32_t>(mesh_.vertices()));
  for (size_t v = 0; v < mesh_.vertices(); ++v)
    mesh.attribute(attribute)->SetAttributeValue(draco::AttributeValueIndex(static_cast<uint32_t>(v)),
                                                 &mesh_.positions[3 * v]);
  for (size_t t = 0; t < mesh_.indices.size(); t += 3)
    mesh.AddFace({draco::PointIndex(mesh_.indices[t]), draco::PointIndex(mesh_.indices[t + 1]),
                  draco::PointIndex(mesh_.indices[t + 2])});
  draco::Encoder encoder;
  encoder.SetAttributeQuantization(draco::GeometryAttribute::POSITION, 16);
  encoder.SetEncodingMethod(draco::MESH_SEQUENTIAL_ENCODING);  // keeps the point and face order
  draco::EncoderBuffer stream;
  ASSERT_TRUE(encoder.EncodeMeshToBuffer(mesh, &stream).ok());

  Document doc;
  doc.gltf["extensionsUsed"] = {"KHR_draco_mesh_compression"};
  doc.gltf["extensionsRequired"] = {"KHR_draco_mesh_compression"};
  const int view = doc.View(stream.data(), stream.size());
  const int p = doc.Accessor(-1, 5126, mesh_.vertices(), "VEC3");
  const int i = doc.Accessor(-1, 5125, mesh_.indices.size(), "SCALAR");
  const json draco = {{"KHR_draco_mesh_compression",
                       {{"bufferView", view},
                        {"attributes", {{"POSITION", mesh.attribute(attribute)->unique_id()}}}}}};
  doc.Primitive(p, i, draco);
  StatusOr<Scene> scene = LoadGltfFile(doc.Write(dir_, "draco"));
  ASSERT_TRUE(scene.ok()) << scene.status();
  const double extent = 0.16;  // the bunny's largest extent, rounded up
  ExpectSameGeometry(*scene, reference_, extent / 65535.0 + 1e-7);

  // A stream cut short is refused by its primitive, not decoded to garbage.
  doc.bin.resize(doc.gltf["bufferViews"][view]["byteOffset"].get<size_t>() + stream.size() / 2);
  doc.gltf["bufferViews"][view]["byteLength"] = stream.size() / 2;
  StatusOr<Scene> cut = LoadGltfFile(doc.Write(dir_, "draco_cut"));
  ASSERT_FALSE(cut.ok());
  EXPECT_EQ(cut.status().code(), absl::StatusCode::kInvalidArgument) << cut.status();
  EXPECT_NE(cut.status().message().find("meshes[0].primitives[0].extensions.KHR_draco_mesh_compression"),
            std::string::npos)
      << cut.status();
}

TEST_F(CompressedBunny, MalformedOrOversizedMeshoptStreamsAreRefusedByTheirView) {
  {
    Document doc = MeshoptDocument(mesh_);
    for (size_t b = 0; b < 64 && b < doc.bin.size(); ++b) doc.bin[b] ^= 0x5a;  // the vertex stream's header
    StatusOr<Scene> scene = LoadGltfFile(doc.Write(dir_, "garbled"));
    ASSERT_FALSE(scene.ok());
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << scene.status();
    EXPECT_NE(scene.status().message().find("bufferViews[0].extensions.EXT_meshopt_compression"), std::string::npos)
        << scene.status();
  }
  {
    // A count that would decode to 12 GiB: refused before any is allocated.
    Document doc = MeshoptDocument(mesh_);
    doc.gltf["bufferViews"][0]["extensions"]["EXT_meshopt_compression"]["count"] = uint64_t{1} << 30;
    doc.gltf["bufferViews"][0]["byteLength"] = (uint64_t{1} << 30) * 12;
    StatusOr<Scene> scene = LoadGltfFile(doc.Write(dir_, "huge"));
    ASSERT_FALSE(scene.ok());
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kResourceExhausted) << scene.status();
  }
  {
    Document doc = MeshoptDocument(mesh_);
    doc.gltf["bufferViews"][1]["extensions"]["EXT_meshopt_compression"]["mode"] = "STRIPS";
    StatusOr<Scene> scene = LoadGltfFile(doc.Write(dir_, "mode"));
    ASSERT_FALSE(scene.ok());
    EXPECT_NE(scene.status().message().find("bufferViews[1].extensions.EXT_meshopt_compression.mode"),
              std::string::npos)
        << scene.status();
  }
}

// EXT_mesh_gpu_instancing against the same placements written as nodes.
TEST_F(CompressedBunny, GpuInstancesLoadAsTheNodesTheyStandFor) {
  const std::vector<std::array<float, 3>> translations = {{0, 0, 0}, {1.5f, 0, 0}, {0, 0, -2.25f}, {-3, 0.5f, 1}};
  const std::vector<std::array<float, 4>> rotations = {
      {0, 0, 0, 1}, {0, 0.70710677f, 0, 0.70710677f}, {0, 1, 0, 0}, {0.5f, 0.5f, 0.5f, 0.5f}};
  const std::vector<std::array<float, 3>> scales = {{1, 1, 1}, {2, 2, 2}, {1, 0.5f, 1}, {-1, 1, 1}};
  const size_t n = translations.size();

  Document instanced;
  const int p = instanced.Accessor(instanced.View(mesh_.positions.data(), mesh_.positions.size() * 4), 5126,
                                   mesh_.vertices(), "VEC3");
  const int i = instanced.Accessor(instanced.View(mesh_.indices.data(), mesh_.indices.size() * 4), 5125,
                                   mesh_.indices.size(), "SCALAR");
  instanced.Primitive(p, i);
  const int t = instanced.Accessor(instanced.View(translations.data(), n * 12), 5126, n, "VEC3");
  const int r = instanced.Accessor(instanced.View(rotations.data(), n * 16), 5126, n, "VEC4");
  const int s = instanced.Accessor(instanced.View(scales.data(), n * 12), 5126, n, "VEC3");
  instanced.gltf["extensionsUsed"] = {"EXT_mesh_gpu_instancing"};
  instanced.gltf["nodes"][0]["extensions"] = {
      {"EXT_mesh_gpu_instancing", {{"attributes", {{"TRANSLATION", t}, {"ROTATION", r}, {"SCALE", s}}}}}};
  StatusOr<Scene> loaded = LoadGltfFile(instanced.Write(dir_, "instanced"));
  ASSERT_TRUE(loaded.ok()) << loaded.status();

  Document nodes;
  const int np = nodes.Accessor(nodes.View(mesh_.positions.data(), mesh_.positions.size() * 4), 5126,
                                mesh_.vertices(), "VEC3");
  const int ni = nodes.Accessor(nodes.View(mesh_.indices.data(), mesh_.indices.size() * 4), 5125,
                                mesh_.indices.size(), "SCALAR");
  nodes.Primitive(np, ni);
  nodes.gltf["nodes"] = json::array();
  for (size_t k = 0; k < n; ++k)
    nodes.gltf["nodes"].push_back({{"mesh", 0},
                                   {"translation", translations[k]},
                                   {"rotation", rotations[k]},
                                   {"scale", scales[k]}});
  nodes.gltf["scenes"][0]["nodes"] = {0, 1, 2, 3};
  StatusOr<Scene> flattened = LoadGltfFile(nodes.Write(dir_, "nodes"));
  ASSERT_TRUE(flattened.ok()) << flattened.status();

  EXPECT_EQ(loaded->TriangleCount(), n * reference_.triangles.size());
  ExpectSameGeometry(*loaded, *flattened, 0.0);  // the mirrored instance flips its winding too
  EXPECT_EQ(loaded->nodes.size(), 1u);
  EXPECT_EQ(loaded->nodes[0].triangle_count, loaded->TriangleCount());
  // The bunny is kept once for the three unmirrored placements, in both
  // forms; the mirrored one, placed once, is flattened only.
  for (const Scene* scene : {&*loaded, &*flattened}) {
    ASSERT_EQ(scene->meshes.size(), 1u);
    EXPECT_EQ(scene->meshes[0].triangles.size(), reference_.triangles.size());
    ASSERT_EQ(scene->placements.size(), 3u);
    EXPECT_EQ(scene->placements[1].first_triangle, reference_.triangles.size());
    EXPECT_TRUE(ValidatePlacements(*scene).ok()) << ValidatePlacements(*scene);
  }

  // Instances count before they are flattened: 4 bunnies do not fit under a
  // cap of 3.
  GltfLoadLimits limits;
  limits.max_triangles = 3 * reference_.triangles.size();
  StatusOr<Scene> capped = LoadGltfFile(dir_.path() / "instanced.gltf", nullptr, limits);
  ASSERT_FALSE(capped.ok());
  EXPECT_EQ(capped.status().code(), absl::StatusCode::kResourceExhausted) << capped.status();

  // Attributes that disagree on the number of instances are refused by name.
  instanced.gltf["accessors"][s]["count"] = n - 1;
  StatusOr<Scene> mismatched = LoadGltfFile(instanced.Write(dir_, "mismatched"));
  ASSERT_FALSE(mismatched.ok());
  EXPECT_NE(mismatched.status().message().find("nodes[0].extensions.EXT_mesh_gpu_instancing.attributes"),
            std::string::npos)
      << mismatched.status();
}

// The fuzz corpus's seeds of each form (tests/fuzz/corpus/gltf, a first
// byte choosing the container) load, so that the fuzzers start from inputs
// that reach the decoders.
TEST(CompressedSeeds, TheFuzzCorpusSeedsReachTheDecoders) {
  const struct {
    const char* seed;
    size_t triangles;
  } seeds[] = {{"meshopt_box_glb", 12},
               {"draco_sequential_box_glb", 12},
               {"draco_edgebreaker_box_glb", 12},
               {"quantized_instanced_box_glb", 36}};
  ScratchDir dir;
  for (const auto& s : seeds) {
    std::ifstream in(fs::path(VISQ_FUZZ_CORPUS_DIR) / "gltf" / s.seed, std::ios::binary);
    const std::string bytes(std::istreambuf_iterator<char>(in), {});
    ASSERT_GT(bytes.size(), 1u) << s.seed;
    const fs::path path = dir.path() / (std::string(s.seed) + ".glb");
    std::ofstream(path, std::ios::binary) << bytes.substr(1);
    StatusOr<Scene> scene = LoadGltfFile(path);
    ASSERT_TRUE(scene.ok()) << s.seed << ": " << scene.status();
    EXPECT_EQ(scene->triangles.size(), s.triangles) << s.seed;
  }
}

// --- Hostile streams: sizes checked before anything is allocated -----------

// What a load did in a child process (fork), and how far the child's peak
// resident memory rose while it ran: the child starts from this process's
// pages, so memory that was allocated and freed before does not hide it.
struct ChildLoad {
  int code = -1;  // absl::StatusCode; -1: the child died
  std::string message;
  int64_t peak_growth_bytes = 0;
};

ChildLoad LoadInChild(const fs::path& path, const GltfLoadLimits& limits) {
  int fds[2];
  if (pipe(fds) != 0) return {};
  const pid_t pid = fork();
  if (pid == 0) {
    close(fds[0]);
    rusage before{}, after{};
    getrusage(RUSAGE_SELF, &before);
    StatusOr<Scene> scene = LoadGltfFile(path, nullptr, limits);
    getrusage(RUSAGE_SELF, &after);
    const int64_t growth = (int64_t{after.ru_maxrss} - before.ru_maxrss) * 1024;
    const int code = static_cast<int>(scene.status().code());
    const std::string message(scene.status().message());
    std::string out(reinterpret_cast<const char*>(&code), sizeof(code));
    out.append(reinterpret_cast<const char*>(&growth), sizeof(growth));
    out += message;
    for (size_t at = 0; at < out.size();) {
      const ssize_t n = write(fds[1], out.data() + at, out.size() - at);
      if (n <= 0) break;
      at += static_cast<size_t>(n);
    }
    _exit(0);
  }
  close(fds[1]);
  std::string in;
  char buffer[4096];
  for (ssize_t n; (n = read(fds[0], buffer, sizeof(buffer))) > 0;) in.append(buffer, static_cast<size_t>(n));
  close(fds[0]);
  int status = 0;
  waitpid(pid, &status, 0);
  ChildLoad result;
  if (in.size() < sizeof(int) + sizeof(int64_t)) return result;
  std::memcpy(&result.code, in.data(), sizeof(int));
  std::memcpy(&result.peak_growth_bytes, in.data() + sizeof(int), sizeof(int64_t));
  result.message = in.substr(sizeof(int) + sizeof(int64_t));
  return result;
}

// An n × n grid of quads in the z = 0 plane, two triangles each.
Mesh Grid(int n) {
  Mesh mesh;
  for (int y = 0; y <= n; ++y)
    for (int x = 0; x <= n; ++x) mesh.positions.insert(mesh.positions.end(), {float(x), float(y), 0.0f});
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const uint32_t a = y * (n + 1) + x, b = a + 1, c = a + n + 1, d = c + 1;
      mesh.indices.insert(mesh.indices.end(), {a, b, d, a, d, c});
    }
  return mesh;
}

// 847 bytes announcing 1 GiB made the loader allocate and zero all of it
// before meshopt looked at the stream.
TEST(HostileCompressedStreams, MeshoptCountBeyondWhatItsStreamEncodesIsRefusedBeforeAllocating) {
  ScratchDir dir;
  Document doc = MeshoptDocument(Grid(3));
  const uint64_t count = uint64_t{1} << 26;  // × 12 bytes: 768 MiB
  doc.gltf["bufferViews"][0]["extensions"]["EXT_meshopt_compression"]["count"] = count;
  doc.gltf["bufferViews"][0]["byteLength"] = count * 12;
  const fs::path path = doc.Write(dir, "announces");
  ASSERT_LT(fs::file_size(dir.path() / "announces.bin") + fs::file_size(path), 2000u);
  const ChildLoad load = LoadInChild(path, GltfLoadLimits{});
  ASSERT_NE(load.code, -1) << "the load ended its process";
  EXPECT_EQ(load.code, static_cast<int>(absl::StatusCode::kInvalidArgument)) << load.message;
  EXPECT_NE(load.message.find("bufferViews[0].extensions.EXT_meshopt_compression: count × byteStride"),
            std::string::npos)
      << load.message;
  EXPECT_NE(load.message.find("stream can encode"), std::string::npos) << load.message;
  EXPECT_LT(load.peak_growth_bytes, int64_t{64} << 20) << "the refusal came after the allocation";
}

// The bound is meshopt's own: the most compressible stream there is (every
// vertex the same) still loads.
TEST(HostileCompressedStreams, MeshoptBoundAdmitsTheMostCompressibleStream) {
  ScratchDir dir;
  Mesh mesh;
  mesh.positions.assign(3 * 65536, 0.0f);
  mesh.indices = {0, 1, 2};
  const fs::path path = MeshoptDocument(mesh).Write(dir, "zeros");
  StatusOr<Scene> scene = LoadGltfFile(path);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->positions.size(), 65536u);
}

// A Draco-compressed grid (draco::Encoder with the given method), as one
// primitive.
Document DracoGridDocument(const Mesh& grid, draco::MeshEncoderMethod method) {
  draco::Mesh mesh;
  mesh.set_num_points(static_cast<uint32_t>(grid.vertices()));
  draco::GeometryAttribute position;
  position.Init(draco::GeometryAttribute::POSITION, nullptr, 3, draco::DT_FLOAT32, false, 12, 0);
  const int attribute = mesh.AddAttribute(position, true, static_cast<uint32_t>(grid.vertices()));
  for (size_t v = 0; v < grid.vertices(); ++v)
    mesh.attribute(attribute)->SetAttributeValue(draco::AttributeValueIndex(static_cast<uint32_t>(v)),
                                                 &grid.positions[3 * v]);
  for (size_t t = 0; t < grid.indices.size(); t += 3)
    mesh.AddFace({draco::PointIndex(grid.indices[t]), draco::PointIndex(grid.indices[t + 1]),
                  draco::PointIndex(grid.indices[t + 2])});
  draco::Encoder encoder;
  encoder.SetAttributeQuantization(draco::GeometryAttribute::POSITION, 14);
  encoder.SetEncodingMethod(method);
  draco::EncoderBuffer stream;
  EXPECT_TRUE(encoder.EncodeMeshToBuffer(mesh, &stream).ok());
  Document doc;
  doc.gltf["extensionsUsed"] = {"KHR_draco_mesh_compression"};
  doc.gltf["extensionsRequired"] = {"KHR_draco_mesh_compression"};
  const int view = doc.View(stream.data(), stream.size());
  const int p = doc.Accessor(-1, 5126, grid.vertices(), "VEC3");
  const int i = doc.Accessor(-1, 5125, grid.indices.size(), "SCALAR");
  doc.Primitive(p, i, {{"KHR_draco_mesh_compression",
                        {{"bufferView", view}, {"attributes", {{"POSITION", mesh.attribute(attribute)->unique_id()}}}}}});
  return doc;
}

// The counts come from the stream's header, as Draco reads them, for both
// of its methods: the grid loads, and under a cap one byte short of what it
// decodes to (its positions and corner indices) it is refused by its counts.
TEST(HostileCompressedStreams, DracoHeaderCountsAreReadForBothMethods) {
  ScratchDir dir;
  const Mesh grid = Grid(8);  // 81 points, 128 faces
  for (auto method : {draco::MESH_SEQUENTIAL_ENCODING, draco::MESH_EDGEBREAKER_ENCODING}) {
    const fs::path path = DracoGridDocument(grid, method).Write(dir, "grid");
    StatusOr<Scene> scene = LoadGltfFile(path);
    ASSERT_TRUE(scene.ok()) << "method " << method << ": " << scene.status();
    EXPECT_EQ(scene->TriangleCount(), 128u);
    GltfLoadLimits limits;
    limits.max_scene_bytes = 81 * 12 + 128 * 12 - 1;
    scene = LoadGltfFile(path, nullptr, limits);
    ASSERT_FALSE(scene.ok()) << "method " << method;
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kResourceExhausted) << scene.status();
    EXPECT_NE(scene.status().message().find("the Draco stream announces 128 faces and 81 points"), std::string::npos)
        << scene.status();
  }
}

// A 615 KB stream added 550 MB under a 10 MB cap: Draco decoded the whole
// mesh before visq counted it.
TEST(HostileCompressedStreams, DracoStreamsBeyondTheCapAreRefusedBeforeDecoding) {
  ScratchDir dir;
  const fs::path path = DracoGridDocument(Grid(600), draco::MESH_EDGEBREAKER_ENCODING).Write(dir, "big");
  GltfLoadLimits limits;
  limits.max_scene_bytes = 1'000'000;
  const ChildLoad load = LoadInChild(path, limits);
  ASSERT_NE(load.code, -1) << "the load ended its process";
  EXPECT_EQ(load.code, static_cast<int>(absl::StatusCode::kResourceExhausted)) << load.message;
  EXPECT_NE(load.message.find("the Draco stream announces 720000 faces and 361201 points"), std::string::npos)
      << load.message;
  EXPECT_LT(load.peak_growth_bytes, int64_t{16} << 20) << "the refusal came after the decoding";
}

}  // namespace
}  // namespace visq
