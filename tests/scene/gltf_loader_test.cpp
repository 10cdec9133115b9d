// The glTF loader on the conformance assets and real scenes of
// ../shared/scenes (triangle counts from its SOURCES.md), on scenes written
// by the project's own writer, and on malformed input.
#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>
#include <random>

#include <gtest/gtest.h>

#include "scene/gltf_loader.h"
#include "scene/placement_checks.h"
#include "scene/gltf_writer.h"
#include "scene/sample_scenes.h"
#include "scene/scene_edit.h"
#include "test_support.h"
#include "large_scene.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using testing::ScratchDir;

struct CountCase {
  const char* path;
  size_t triangles;
};

class SharedSceneCounts : public ::testing::TestWithParam<CountCase> {};

TEST_P(SharedSceneCounts, TriangleCountMatchesSources) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  GltfLoadReport report;
  StatusOr<Scene> scene = LoadGltfFile(scenes / GetParam().path, &report);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->TriangleCount(), GetParam().triangles);
  // The record's unplaced triangles; the placed ones through their meshes.
  EXPECT_EQ(scene->triangle_material.size(), scene->triangles.size());
  EXPECT_EQ(scene->triangle_node.size(), scene->triangles.size());
  EXPECT_TRUE(ValidatePlacements(*scene).ok()) << ValidatePlacements(*scene);
  EXPECT_FALSE(scene->bounds.Empty());
  for (const auto& t : scene->triangles)
    for (int c = 0; c < 3; ++c) ASSERT_LT(t[c], scene->positions.size());
  // A resident scene holds no growth slack.
  EXPECT_EQ(scene->positions.capacity(), scene->positions.size());
  EXPECT_EQ(scene->triangles.capacity(), scene->triangles.size());
  EXPECT_EQ(scene->triangle_material.capacity(), scene->triangle_material.size());
  EXPECT_EQ(scene->triangle_node.capacity(), scene->triangle_node.size());
  EXPECT_EQ(scene->lightmap_uvs.capacity(), scene->lightmap_uvs.size());
}

constexpr const char* kKhronos = "gltf_conformance/khronos_sample_assets/";
INSTANTIATE_TEST_SUITE_P(
    Conformance, SharedSceneCounts,
    ::testing::Values(
        CountCase{"gltf_conformance/khronos_sample_assets/Box/glTF/Box.gltf", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/Box/glTF-Binary/Box.glb", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/Box/glTF-Embedded/Box.gltf", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/BoxInterleaved/glTF/BoxInterleaved.gltf", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/BoxVertexColors/glTF/BoxVertexColors.gltf", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/SimpleSparseAccessor/glTF/SimpleSparseAccessor.gltf", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/SimpleSparseAccessor/glTF-Embedded/SimpleSparseAccessor.gltf", 12},
        CountCase{"gltf_conformance/khronos_sample_assets/SimpleMeshes/glTF/SimpleMeshes.gltf", 2},
        CountCase{"gltf_conformance/khronos_sample_assets/MultipleScenes/glTF/MultipleScenes.gltf", 2},
        CountCase{"gltf_conformance/khronos_sample_assets/Triangle/glTF/Triangle.gltf", 1},
        CountCase{"gltf_conformance/khronos_sample_assets/TriangleWithoutIndices/glTF/TriangleWithoutIndices.gltf", 1},
        CountCase{"gltf_conformance/khronos_sample_assets/MeshPrimitiveModes/glTF/MeshPrimitiveModes.gltf", 16},
        CountCase{"gltf_conformance/khronos_sample_assets/OrientationTest/glTF-Binary/OrientationTest.glb", 524},
        CountCase{"gltf_conformance/khronos_sample_assets/NegativeScaleTest/glTF/NegativeScaleTest.gltf", 7724},
        // One 12-triangle cube drawn 125 times by EXT_mesh_gpu_instancing
        // (SOURCES.md counts the cube a loader without the extension sees).
        CountCase{"gltf_conformance/khronos_sample_assets/SimpleInstancing/glTF/SimpleInstancing.gltf", 12 * 125},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_04.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_05.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_06.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_11.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_12.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_13.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_14.gltf", 2},
        CountCase{"gltf_conformance/asset_generator_Mesh_PrimitiveMode/Mesh_PrimitiveMode_15.gltf", 2}));

INSTANTIATE_TEST_SUITE_P(
    RealScenes, SharedSceneCounts,
    ::testing::Values(CountCase{"cornell_box/cornell_box.gltf", 36}, CountCase{"bunny/bunny.gltf", 69451},
                      CountCase{"sponza_dabrovic/sponza.gltf", 66454},
                      CountCase{"tree_kenney/tree_palmDetailedTall.glb", 336},
                      CountCase{"tree_kenney/tree_detailed.glb", 402},
                      CountCase{"foliage_glass_vase_flowers/GlassVaseFlowers.gltf", 14036},
                      CountCase{"interior_veach_ajar/veach_ajar.gltf", 382690},
                      CountCase{"characters/DamagedHelmet/DamagedHelmet.gltf", 15452},
                      CountCase{"characters/Fox/Fox.gltf", 576},
                      CountCase{"characters/CesiumMan/CesiumMan.gltf", 4672}));

TEST(GltfLoader, PrimitiveModeFilesWithoutTrianglesAreRejected) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  // Points, lines, line loops and line strips (_00.._03, _07.._10) hold no triangle.
  for (int i : {0, 1, 2, 3, 7, 8, 9, 10}) {
    const auto path = scenes / "gltf_conformance/asset_generator_Mesh_PrimitiveMode" /
                      fmt::format("Mesh_PrimitiveMode_{:02d}.gltf", i);
    StatusOr<Scene> scene = LoadGltfFile(path);
    ASSERT_FALSE(scene.ok()) << path;
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(scene.status().message().find("no triangles"), absl::string_view::npos) << scene.status();
  }
}

TEST(GltfLoader, SparseAccessorOverridesPositions) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  StatusOr<Scene> scene =
      LoadGltfFile(scenes / kKhronos / "SimpleSparseAccessor/glTF/SimpleSparseAccessor.gltf");
  ASSERT_TRUE(scene.ok()) << scene.status();
  // The base grid has y in {0, 1}; the sparse values lift vertices to y = 2, 3, 4.
  EXPECT_DOUBLE_EQ(scene->bounds.max.y, 4.0);
}

TEST(GltfLoader, MultipleScenesUsesTheDefaultSceneAndSaysWhatWasDropped) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  GltfLoadReport report;
  StatusOr<Scene> scene = LoadGltfFile(scenes / kKhronos / "MultipleScenes/glTF/MultipleScenes.gltf", &report);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->TriangleCount(), 2u);
  ASSERT_FALSE(report.dropped.empty());
  EXPECT_NE(report.dropped[0].find("non-default scene"), std::string::npos);
}

TEST(GltfLoader, NegativeScaleFlipsWindingSoInstancesAgree) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  StatusOr<Scene> scene = LoadGltfFile(scenes / kKhronos / "NegativeScaleTest/glTF/NegativeScaleTest.gltf");
  ASSERT_TRUE(scene.ok()) << scene.status();
  // The signed volume of a node's triangles about their centroid (sum of
  // v0 . (v1 x v2) / 6) changes sign with the winding. A mesh instanced once
  // plainly and once through a mirroring transform must keep its sign.
  auto signed_volume = [&](const std::string& name) {
    for (const auto& node : scene->nodes) {
      if (node.name != name) continue;
      glm::dvec3 centroid(0.0);
      for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t)
        for (int c = 0; c < 3; ++c) centroid += scene->Vertex(t, c);
      centroid /= 3.0 * node.triangle_count;
      double volume = 0;
      for (uint32_t t = node.first_triangle; t < node.first_triangle + node.triangle_count; ++t)
        volume += glm::dot(scene->Vertex(t, 0) - centroid,
                           glm::cross(scene->Vertex(t, 1) - centroid, scene->Vertex(t, 2) - centroid)) / 6.0;
      return volume;
    }
    ADD_FAILURE() << "no node " << name;
    return 0.0;
  };
  for (const auto& [plain, mirrored] : {std::pair{"NotShiny1", "NotShinyMinus1"}, std::pair{"Shiny1", "ShinyMinus1"},
                                        std::pair{"Dark1", "DarkMinus1"}}) {
    const double a = signed_volume(plain), b = signed_volume(mirrored);
    EXPECT_GT(std::abs(a), 1e-6) << plain;
    EXPECT_NEAR(a, b, 1e-6 * std::abs(a)) << plain << " vs " << mirrored;
  }
}

TEST(GltfLoader, SkinnedCharacterKeepsBindPoseAndReportsDroppedContent) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  GltfLoadReport report;
  StatusOr<Scene> scene = LoadGltfFile(scenes / "characters/Fox/Fox.gltf", &report);
  ASSERT_TRUE(scene.ok()) << scene.status();
  std::string all;
  for (const auto& d : report.dropped) all += d + ";";
  EXPECT_NE(all.find("animation"), std::string::npos) << all;
  EXPECT_NE(all.find("skin"), std::string::npos) << all;
}

TEST(GltfLoader, CornellBoxMaterialsCarryReflectivityAndEmission) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  StatusOr<Scene> scene = LoadGltfFile(scenes / "cornell_box/cornell_box.gltf");
  ASSERT_TRUE(scene.ok()) << scene.status();
  double max_emission = 0;
  bool red_wall = false;
  for (const auto& m : scene->materials) {
    max_emission = std::max(max_emission, m.emission.r);
    red_wall |= std::abs(m.reflectivity.r - 0.63) < 1e-6 && std::abs(m.reflectivity.g - 0.065) < 1e-6;
  }
  EXPECT_NEAR(max_emission, 17.0, 1e-6);  // emissiveFactor x KHR_materials_emissive_strength
  EXPECT_TRUE(red_wall);
}

// --- Scenes written by the project's writer --------------------------------

// A reflectivity is glTF's baseColorFactor, in [0, 1], which the obscurance
// bounds rest on: beyond a rounding of the range the file is refused, naming
// the field; within it, clamped.
TEST(GltfLoader, BaseColorOutsideGltfsRangeIsRefusedAndARoundingClamped) {
  ScratchDir dir;
  Scene scene = MakeCornellBox();
  scene.materials[0].reflectivity = glm::dvec3(0.5, 5.0, 0.5);
  ASSERT_TRUE(WriteGltfFile(scene, dir.path() / "bright.gltf").ok());
  StatusOr<Scene> bright = LoadGltfFile(dir.path() / "bright.gltf");
  ASSERT_FALSE(bright.ok());
  EXPECT_EQ(bright.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bright.status().message().find("materials[0].pbrMetallicRoughness.baseColorFactor[1]"),
            absl::string_view::npos)
      << bright.status();
  scene.materials[0].reflectivity = glm::dvec3(1.0 + 1e-7, 0.5, -1e-7);
  ASSERT_TRUE(WriteGltfFile(scene, dir.path() / "rounded.gltf").ok());
  StatusOr<Scene> rounded = LoadGltfFile(dir.path() / "rounded.gltf");
  ASSERT_TRUE(rounded.ok()) << rounded.status();
  EXPECT_EQ(rounded->materials[0].reflectivity, glm::dvec3(1.0, 0.5, 0.0));
}

TEST(GltfWriter, GeneratedCornellBoxRoundTrips) {
  ScratchDir dir;
  const Scene original = MakeCornellBox();
  for (const char* file : {"box.gltf", "box.glb"}) {
    ASSERT_TRUE(WriteGltfFile(original, dir.path() / file).ok());
    StatusOr<Scene> loaded = LoadGltfFile(dir.path() / file);
    ASSERT_TRUE(loaded.ok()) << loaded.status();
    EXPECT_EQ(loaded->TriangleCount(), original.TriangleCount());
    EXPECT_EQ(loaded->materials.size(), original.materials.size());
    ASSERT_EQ(loaded->nodes.size(), original.nodes.size());
    EXPECT_EQ(loaded->nodes[5].name, "light");
    const Material& light = loaded->materials[loaded->triangle_material[loaded->nodes[5].first_triangle]];
    EXPECT_NEAR(light.emission.r, 17.0, 1e-4);
    EXPECT_NEAR(light.emission.b, 4.0, 1e-4);
    for (int a = 0; a < 3; ++a) {
      EXPECT_NEAR(loaded->bounds.min[a], original.bounds.min[a], 1e-6);
      EXPECT_NEAR(loaded->bounds.max[a], original.bounds.max[a], 1e-6);
    }
  }
}

// What no query reads but the export writes back: the palm's normals (world
// space through node TRS with non-uniform scale, unit) and TEXCOORD_0 are
// kept, come back through the writer as they were, and a move turns the
// normals with the node.
TEST(GltfWriter, NormalsAndUvSetsRoundTripAndMoveWithTheirNode) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  StatusOr<Scene> palm = LoadGltfFile(scenes / "tree_kenney/tree_palmDetailedTall.glb");
  ASSERT_TRUE(palm.ok()) << palm.status();
  ASSERT_EQ(palm->normals.size(), palm->positions.size());
  ASSERT_EQ(palm->texcoords.size(), 1u);
  ASSERT_EQ(palm->texcoords[0].size(), palm->positions.size());
  EXPECT_TRUE(palm->lightmap_uvs.empty());
  for (const glm::vec3& n : palm->normals) ASSERT_NEAR(glm::length(n), 1.0f, 1e-5f);
  // Smooth normals face the way of their triangles' winding.
  size_t facing = 0;
  for (size_t t = 0; t < palm->TriangleCount(); ++t) {
    const glm::dvec3 face = glm::cross(palm->Vertex(t, 1) - palm->Vertex(t, 0), palm->Vertex(t, 2) - palm->Vertex(t, 0));
    facing += glm::dot(face, glm::dvec3(palm->normals[palm->triangles[t][0]])) > 0.0;
  }
  EXPECT_GT(facing, palm->TriangleCount() * 9 / 10);

  ScratchDir dir;
  ASSERT_TRUE(WriteGltfFile(*palm, dir.path() / "palm.glb").ok());
  StatusOr<Scene> back = LoadGltfFile(dir.path() / "palm.glb");
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->TriangleCount(), palm->TriangleCount());
  EXPECT_EQ(back->positions.size(), palm->positions.size());
  ASSERT_EQ(back->texcoords.size(), 1u);
  for (size_t t = 0; t < palm->TriangleCount(); ++t)
    for (int c = 0; c < 3; ++c) {
      const uint32_t a = palm->triangles[t][c], b = back->triangles[t][c];
      ASSERT_LT(glm::length(back->positions[b] - palm->positions[a]), 1e-5);
      ASSERT_LT(glm::length(back->normals[b] - palm->normals[a]), 1e-6f);
      ASSERT_EQ(back->texcoords[0][b], palm->texcoords[0][a]);
    }

  // A quarter turn about y of every root: every normal turns with it.
  const glm::dmat4 turn(glm::dvec4(0, 0, -1, 0), glm::dvec4(0, 1, 0, 0), glm::dvec4(1, 0, 0, 0), glm::dvec4(0, 0, 0, 1));
  Scene moved = *palm;
  for (uint32_t root = 0; root < palm->nodes.size(); ++root)
    if (palm->nodes[root].parent < 0)
      ASSERT_TRUE(MoveNodeSubtree(moved, root, turn * palm->nodes[root].world).ok());
  for (size_t i = 0; i < palm->normals.size(); ++i)
    ASSERT_LT(glm::length(glm::dvec3(moved.normals[i]) - glm::dmat3(turn) * glm::dvec3(palm->normals[i])), 1e-6) << i;
}

// --- Malformed input ---------------------------------------------------------

// Writes a .gltf whose single buffer is `bin` (as a .bin beside it).
fs::path WriteGltf(const ScratchDir& dir, const std::string& name, const std::string& json,
                   const std::vector<unsigned char>& bin = {}) {
  if (!bin.empty()) {
    std::ofstream b(dir.path() / (name + ".bin"), std::ios::binary);
    b.write(reinterpret_cast<const char*>(bin.data()), static_cast<std::streamsize>(bin.size()));
  }
  const fs::path path = dir.path() / (name + ".gltf");
  std::ofstream(path) << json;
  return path;
}

std::vector<unsigned char> TriangleBuffer(float x0, uint16_t i2) {
  std::vector<unsigned char> bin;
  const float positions[9] = {x0, 0, 0, 1, 0, 0, 0, 1, 0};
  const uint16_t indices[4] = {0, 1, i2, 0};
  bin.resize(sizeof(positions) + sizeof(indices));
  std::memcpy(bin.data(), positions, sizeof(positions));
  std::memcpy(bin.data() + sizeof(positions), indices, sizeof(indices));
  return bin;
}

std::string TriangleJson(const std::string& name, const std::string& extra = "") {
  return R"({"asset":{"version":"2.0"},)" + extra +
         R"("scenes":[{"nodes":[0]}],"scene":0,"nodes":[{"mesh":0}],
     "meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]}],
     "buffers":[{"uri":")" + name + R"(.bin","byteLength":44}],
     "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":6}],
     "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                  {"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}]})";
}

void ExpectInvalid(const fs::path& path, const std::string& needle) {
  StatusOr<Scene> scene = LoadGltfFile(path);
  ASSERT_FALSE(scene.ok()) << path;
  EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << scene.status();
  EXPECT_NE(std::string(scene.status().message()).find(needle), std::string::npos)
      << "message '" << scene.status().message() << "' lacks '" << needle << "'";
}

TEST(GltfLoaderBadInput, ValidTriangleLoads) {
  ScratchDir dir;
  StatusOr<Scene> scene = LoadGltfFile(WriteGltf(dir, "ok", TriangleJson("ok"), TriangleBuffer(0, 2)));
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->TriangleCount(), 1u);
}

TEST(GltfLoaderBadInput, MalformedJson) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "bad", "{\"asset\": {\"version\": \"2.0\"}, \"nodes\": [ {"), "malformed glTF");
}

TEST(GltfLoaderBadInput, IndexOutOfRange) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "idx", TriangleJson("idx"), TriangleBuffer(0, 7)), "out of range");
}

// Found by the glTF fuzz target (the input is kept in its corpus; its first
// byte chose .glb): tinygltf threw std::out_of_range from vector::at on this
// GLB instead of reporting an error, which would have ended the server.
TEST(GltfLoaderBadInput, GlbThatMadeTheParserThrow) {
  std::ifstream in(VISQ_FUZZ_CORPUS_DIR "/gltf/regression-glb-parser-throws-out-of-range", std::ios::binary);
  ASSERT_TRUE(in) << "corpus file missing";
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  ASSERT_GT(bytes.size(), 1u);
  ScratchDir dir;
  const fs::path path = dir.path() / "thrower.glb";
  std::ofstream(path, std::ios::binary) << bytes.substr(1);
  ExpectInvalid(path, "the parser gave up");
}

TEST(GltfLoaderBadInput, NanPosition) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "nan", TriangleJson("nan"), TriangleBuffer(std::nanf(""), 2)), "NaN");
}

TEST(GltfLoaderBadInput, InfinitePosition) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "inf", TriangleJson("inf"), TriangleBuffer(INFINITY, 2)), "Inf");
}

TEST(GltfLoaderBadInput, UnsupportedRequiredExtension) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "ext",
                          TriangleJson("ext", R"("extensionsUsed":["VENDOR_subdivision_surfaces"],
                                                 "extensionsRequired":["VENDOR_subdivision_surfaces"],)"),
                          TriangleBuffer(0, 2)),
                "unsupported required extension VENDOR_subdivision_surfaces");
}

TEST(GltfLoaderBadInput, NoTriangles) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "empty", R"({"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"nodes":[{}]})"),
                "no triangles");
}

TEST(GltfLoaderBadInput, AccessorPastEndOfBuffer) {
  ScratchDir dir;
  std::string json = TriangleJson("short");
  json.replace(json.find("\"count\":3,\"type\":\"VEC3\""), 24, "\"count\":30,\"type\":\"VEC3\"");
  const fs::path path = WriteGltf(dir, "short", json, TriangleBuffer(0, 2));
  StatusOr<Scene> scene = LoadGltfFile(path);
  ASSERT_FALSE(scene.ok());
  EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << scene.status();
}

TEST(GltfLoaderBadInput, NodeCycle) {
  ScratchDir dir;
  std::string json = TriangleJson("cycle");
  json.replace(json.find("\"nodes\":[{\"mesh\":0}]"), 20, "\"nodes\":[{\"mesh\":0,\"children\":[1]},{\"children\":[0]}]");
  ExpectInvalid(WriteGltf(dir, "cycle", json, TriangleBuffer(0, 2)), "");
}

TEST(GltfLoaderBadInput, MissingBufferFile) {
  ScratchDir dir;
  ExpectInvalid(WriteGltf(dir, "nobin", TriangleJson("nobin")), "");
}

TEST(GltfLoaderBadInput, NotAGltfFile) {
  ScratchDir dir;
  std::ofstream(dir.path() / "scene.obj") << "v 0 0 0\n";
  ExpectInvalid(dir.path() / "scene.obj", "not a .gltf or .glb");
}

TEST(GltfLoaderBadInput, TruncatedGlb) {
  ScratchDir dir;
  std::ofstream(dir.path() / "t.glb", std::ios::binary) << "glTF\x02\x00\x00\x00";
  ExpectInvalid(dir.path() / "t.glb", "malformed glTF");
}

// --- Hostile files ------------------------------------------------
// Each case is a file an attacker can upload; the loader must refuse it with
// a status, never read outside the upload, crash or expand without bound.

// A triangle whose buffer URI is `uri` (as written in the JSON).
std::string TriangleJsonWithUri(const std::string& uri) {
  std::string json = TriangleJson("x");
  json.replace(json.find("x.bin"), 5, uri);
  return json;
}

// A file outside the upload whose bytes would become a triangle at x = 7777.
void PlantSecret(const fs::path& path) {
  fs::create_directories(path.parent_path());
  const std::vector<unsigned char> bin = TriangleBuffer(7777.0f, 2);
  std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(bin.data()), bin.size());
}

TEST(GltfLoaderHostile, BufferUrisNeverLeaveTheUpload) {
  ScratchDir dir;
  const fs::path upload = dir.path() / "repo" / "scene";
  fs::create_directories(upload);
  PlantSecret(dir.path() / "repo" / "secret.bin");
  PlantSecret(dir.path() / "secret.bin");
  PlantSecret(upload / ".hidden.bin");
  // The working directory: tinygltf's default callbacks also try "./" + URI.
  const fs::path cwd = fs::current_path();
  fs::current_path(dir.path());
  for (const std::string& uri : std::vector<std::string>{"../secret.bin", "../../secret.bin", "%2e%2e/secret.bin", "%2E%2E%2Fsecret.bin",
                                (dir.path() / "secret.bin").string(), "secret.bin", ".hidden.bin",
                                "sub/../../secret.bin"}) {
    std::ofstream(upload / "main.gltf") << TriangleJsonWithUri(uri);
    GltfLoadLimits limits;
    limits.file_root = upload;
    StatusOr<Scene> scene = LoadGltfFile(upload / "main.gltf", nullptr, limits);
    EXPECT_FALSE(scene.ok()) << "URI " << uri << " loaded a file outside the upload";
    if (!scene.ok()) {
      EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << uri << ": " << scene.status();
      if (uri[0] != '/') {  // the message may echo the URI, never more of the server's folders
        EXPECT_EQ(std::string(scene.status().message()).find(dir.path().string()), std::string::npos)
          << "the message names the server's folders: " << scene.status();
      }
    }
  }
  fs::current_path(cwd);
}

TEST(GltfLoaderHostile, SymlinkOutOfTheUploadIsRefused) {
  ScratchDir dir;
  const fs::path upload = dir.path() / "scene";
  fs::create_directories(upload);
  PlantSecret(dir.path() / "secret.bin");
  fs::create_symlink(dir.path() / "secret.bin", upload / "link.bin");
  std::ofstream(upload / "main.gltf") << TriangleJsonWithUri("link.bin");
  StatusOr<Scene> scene = LoadGltfFile(upload / "main.gltf");
  ASSERT_FALSE(scene.ok());
  EXPECT_NE(std::string(scene.status().message()).find("resolves outside"), std::string::npos) << scene.status();
}

TEST(GltfLoaderHostile, UrisInsideTheUploadStillLoad) {
  ScratchDir dir;
  const fs::path upload = dir.path() / "scene";
  PlantSecret(upload / "buffers" / "tri.bin");
  fs::create_directories(upload / "gltf");
  // From a subfolder up to a sibling folder, percent-encoded: still the upload's own file.
  std::ofstream(upload / "gltf" / "main.gltf") << TriangleJsonWithUri("..%2Fbuffers/tri.bin");
  GltfLoadLimits limits;
  limits.file_root = upload;
  StatusOr<Scene> scene = LoadGltfFile(upload / "gltf" / "main.gltf", nullptr, limits);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_FLOAT_EQ(static_cast<float>(scene->bounds.min.x), 0.0f);
  EXPECT_FLOAT_EQ(static_cast<float>(scene->bounds.max.x), 7777.0f);
}

// `levels` nodes, node i the only child of node i-1, the last one a triangle.
std::string NodeChainJson(int levels) {
  std::string nodes;
  for (int i = 0; i < levels; ++i) {
    if (i) nodes += ",";
    nodes += i + 1 < levels ? absl::StrCat("{\"children\":[", i + 1, "]}") : std::string("{\"mesh\":0}");
  }
  std::string json = TriangleJson("chain");
  json.replace(json.find("\"nodes\":[{\"mesh\":0}]"), 20, "\"nodes\":[" + nodes + "]");
  return json;
}

TEST(GltfLoaderHostile, DeepNodeChainIsRefusedNotACrash) {
  ScratchDir dir;
  // 5,000 levels crashed the recursive visit (SIGSEGV); 100,000 make sure.
  for (int levels : {5000, 100000}) {
    const fs::path path = WriteGltf(dir, "chain", NodeChainJson(levels), TriangleBuffer(0, 2));
    ExpectInvalid(path, "deeper than 1024 levels");
  }
  const fs::path ok = WriteGltf(dir, "chain", NodeChainJson(1000), TriangleBuffer(0, 2));
  StatusOr<Scene> scene = LoadGltfFile(ok);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->nodes.size(), 1000u);
}

// A 1 KB file whose nodes share children flattens to 2^levels triangles.
std::string NodeDagJson(int levels) {
  std::string nodes;
  for (int i = 0; i < levels; ++i)
    nodes += absl::StrCat("{\"children\":[", i + 1, ",", i + 1, "]},");
  nodes += "{\"mesh\":0}";
  std::string json = TriangleJson("dag");
  json.replace(json.find("\"nodes\":[{\"mesh\":0}]"), 20, "\"nodes\":[" + nodes + "]");
  return json;
}

TEST(GltfLoaderHostile, SharedChildrenAreCountedBeforeFlattening) {
  ScratchDir dir;
  GltfLoadLimits limits;
  limits.max_scene_bytes = 10'000'000;
  for (int levels : {22, 40, 63, 200}) {
    const fs::path path = WriteGltf(dir, "dag", NodeDagJson(levels), TriangleBuffer(0, 2));
    StatusOr<Scene> scene = LoadGltfFile(path, nullptr, limits);
    ASSERT_FALSE(scene.ok()) << levels;
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kResourceExhausted) << scene.status();
  }
  // Shared children are legal: a small DAG flattens once per path.
  const fs::path small = WriteGltf(dir, "dag", NodeDagJson(4), TriangleBuffer(0, 2));
  StatusOr<Scene> scene = LoadGltfFile(small, nullptr, limits);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->TriangleCount(), 16u);
}

TEST(GltfLoaderHostile, AccessorArithmeticThatWouldWrapIsRefused) {
  ScratchDir dir;
  struct Case {
    const char* from;
    const char* to;
  };
  const Case cases[] = {
      // count 2^62 + 1 with stride 12 wraps (count - 1) * stride to 0.
      {"\"count\":3,\"type\":\"VEC3\"", "\"count\":4611686018427387905,\"type\":\"VEC3\""},
      // byteLength 2^64 - 8: byteOffset + byteLength wraps.
      {"\"byteOffset\":0,\"byteLength\":36", "\"byteOffset\":8,\"byteLength\":18446744073709551608"},
      // accessor byteOffset 2^64 - 10: byteOffset + needed wraps.
      {"\"bufferView\":0,\"componentType\":5126", "\"bufferView\":0,\"byteOffset\":18446744073709551606,\"componentType\":5126"},
      // Found by gltf_structure_fuzz: an empty index accessor whose byteOffset
      // lies past its view made a pointer outside the buffer.
      {"{\"bufferView\":1,\"componentType\":5123,\"count\":3", "{\"bufferView\":1,\"byteOffset\":18446744073709551612,\"componentType\":5123,\"count\":0"},
  };
  for (const Case& c : cases) {
    std::string json = TriangleJson("wrap");
    ASSERT_NE(json.find(c.from), std::string::npos) << c.from;
    json.replace(json.find(c.from), std::strlen(c.from), c.to);
    StatusOr<Scene> scene = LoadGltfFile(WriteGltf(dir, "wrap", json, TriangleBuffer(0, 2)));
    EXPECT_FALSE(scene.ok()) << c.to << " loaded";
  }
}

// Found by gltf_structure_fuzz: tinygltf's recursive JSON parse overflowed
// the stack on extras nested 20,000 deep (a 40 KB file).
TEST(GltfLoaderHostile, DeeplyNestedJsonIsRefused) {
  ScratchDir dir;
  std::string json = TriangleJson("deep");
  const std::string extras = "\"extras\":" + std::string(20000, '[') + std::string(20000, ']') + ",";
  json.insert(1, extras);
  ExpectInvalid(WriteGltf(dir, "deep", json, TriangleBuffer(0, 2)), "JSON nested deeper than 256");
  // Brackets inside strings are text, not nesting.
  std::string quoted = TriangleJson("quoted");
  quoted.insert(1, "\"extras\":\"" + std::string(1000, '[') + "\",");
  StatusOr<Scene> scene = LoadGltfFile(WriteGltf(dir, "quoted", quoted, TriangleBuffer(0, 2)));
  EXPECT_TRUE(scene.ok()) << scene.status();
}

TEST(GltfLoaderHostile, CoordinatesBeyondTheRangeAreRefused) {
  ScratchDir dir;
  std::string json = TriangleJson("far");
  json.replace(json.find("\"nodes\":[{\"mesh\":0}]"), 20, "\"nodes\":[{\"mesh\":0,\"scale\":[1e300,1,1]}]");
  ExpectInvalid(WriteGltf(dir, "far", json, TriangleBuffer(1, 2)), "beyond");
}

// An upload whose one chunk is "a.gltf/x" makes its main file a folder:
// reading it through an ifstream threw (EISDIR) out of the loader, and the
// server ended.
TEST(GltfLoaderHostile, MainFileThatIsAFolderIsRefusedByName) {
  ScratchDir dir;
  fs::create_directories(dir.path() / "a.gltf");
  std::ofstream(dir.path() / "a.gltf" / "x") << "abcd";
  StatusOr<Scene> scene = LoadGltfFile(dir.path() / "a.gltf");
  ASSERT_FALSE(scene.ok());
  EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << scene.status();
  EXPECT_NE(scene.status().message().find("a.gltf: not a regular file"), std::string::npos) << scene.status();
}

// A triangle, and a mesh without a single vertex placed `instances` times
// through EXT_mesh_gpu_instancing by a sparse TRANSLATION accessor holding
// one value: a kilobyte whatever the count.
std::string EmptyMeshInstancedJson(uint64_t instances) {
  return absl::StrCat(R"({"asset":{"version":"2.0"},"extensionsUsed":["EXT_mesh_gpu_instancing"],
     "scenes":[{"nodes":[0,1]}],"scene":0,
     "nodes":[{"mesh":0},{"mesh":1,"extensions":{"EXT_mesh_gpu_instancing":{"attributes":{"TRANSLATION":2}}}}],
     "meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]},
               {"primitives":[{"attributes":{"POSITION":3}}]}],
     "buffers":[{"uri":"inst.bin","byteLength":60}],
     "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":6},
                    {"buffer":0,"byteOffset":44,"byteLength":4},{"buffer":0,"byteOffset":48,"byteLength":12}],
     "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]},
                  {"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"},
                  {"componentType":5126,"count":)", instances, R"(,"type":"VEC3",
                   "sparse":{"count":1,"indices":{"bufferView":2,"componentType":5125},"values":{"bufferView":3}}},
                  {"bufferView":0,"componentType":5126,"count":0,"type":"VEC3"}]})");
}

std::vector<unsigned char> EmptyMeshInstancedBuffer() {
  std::vector<unsigned char> bin = TriangleBuffer(0, 2);
  const uint32_t index = 1;
  const float translation[3] = {5, 0, 0};
  bin.resize(60);
  std::memcpy(bin.data() + 44, &index, 4);
  std::memcpy(bin.data() + 48, translation, 12);
  return bin;
}

// 2^40 placements of a mesh without triangles: nothing counted them, and
// the loader reserved 2^40 matrices (std::bad_alloc, the server aborted);
// 2^20 under a 1 MB cap were accepted (2^23 cost 2.3 GB and 28 s).
TEST(GltfLoaderHostile, PlacementsCountWhateverTheirTriangles) {
  ScratchDir dir;
  const auto bin = EmptyMeshInstancedBuffer();
  {
    StatusOr<Scene> scene = LoadGltfFile(WriteGltf(dir, "inst", EmptyMeshInstancedJson(uint64_t{1} << 40), bin));
    ASSERT_FALSE(scene.ok());
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kResourceExhausted) << scene.status();
    EXPECT_NE(scene.status().message().find("places meshes 1099511627777 times"), std::string::npos)
        << scene.status();
  }
  {
    GltfLoadLimits limits;
    limits.max_scene_bytes = 1'000'000;
    StatusOr<Scene> scene =
        LoadGltfFile(WriteGltf(dir, "inst", EmptyMeshInstancedJson(uint64_t{1} << 20), bin), nullptr, limits);
    ASSERT_FALSE(scene.ok()) << "2^20 placements loaded under a 1 MB cap";
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kResourceExhausted) << scene.status();
    EXPECT_NE(scene.status().message().find("--max-scene-bytes"), std::string::npos) << scene.status();
  }
  {
    GltfLoadLimits limits;
    limits.max_placements = 1000;
    StatusOr<Scene> scene =
        LoadGltfFile(WriteGltf(dir, "inst", EmptyMeshInstancedJson(1001), bin), nullptr, limits);
    ASSERT_FALSE(scene.ok());
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kResourceExhausted) << scene.status();
  }
  // A few instances of it are harmless: the triangle loads.
  StatusOr<Scene> few = LoadGltfFile(WriteGltf(dir, "inst", EmptyMeshInstancedJson(16), bin));
  ASSERT_TRUE(few.ok()) << few.status();
  EXPECT_EQ(few->TriangleCount(), 1u);
}

// The triangle with lightmap UVs (TEXCOORD_1) (0,0) (1,0) (third_u, 1).
fs::path WriteTriangleWithLightmapUvs(const ScratchDir& dir, float third_u) {
  std::string json = TriangleJson("uv");
  auto replace = [&](const std::string& from, const std::string& to) {
    ASSERT_NE(json.find(from), std::string::npos) << from;
    json.replace(json.find(from), from.size(), to);
  };
  replace("\"attributes\":{\"POSITION\":0}", "\"attributes\":{\"POSITION\":0,\"TEXCOORD_1\":2}");
  replace("\"byteLength\":44}", "\"byteLength\":68}");
  replace("\"byteOffset\":36,\"byteLength\":6}", "\"byteOffset\":36,\"byteLength\":6},"
                                                 "{\"buffer\":0,\"byteOffset\":44,\"byteLength\":24}");
  replace("\"type\":\"SCALAR\"}", "\"type\":\"SCALAR\"},{\"bufferView\":2,\"componentType\":5126,\"count\":3,"
                                  "\"type\":\"VEC2\"}");
  std::vector<unsigned char> bin = TriangleBuffer(0, 2);
  const float uvs[6] = {0, 0, 1, 0, third_u, 1};
  bin.resize(68);
  std::memcpy(bin.data() + 44, uvs, sizeof(uvs));
  return WriteGltf(dir, "uv", json, bin);
}

// NaN, Inf and 1e30 lightmap UVs were accepted, baked, and exported into
// the .glb as NaN.
TEST(GltfLoaderHostile, LightmapUvsAreValidatedLikePositions) {
  ScratchDir dir;
  for (float bad : {std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity(),
                    -std::numeric_limits<float>::infinity(), 1e30f, -2000.0f}) {
    StatusOr<Scene> scene = LoadGltfFile(WriteTriangleWithLightmapUvs(dir, bad));
    ASSERT_FALSE(scene.ok()) << bad << " loaded";
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << scene.status();
    EXPECT_NE(scene.status().message().find("meshes[0].primitives[0].TEXCOORD_1[2] (accessors[2])"),
              std::string::npos)
        << scene.status();
  }
  // UVs a little past [0, 1] are a lightmap's own business.
  StatusOr<Scene> scene = LoadGltfFile(WriteTriangleWithLightmapUvs(dir, 1.25f));
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_EQ(scene->lightmap_uvs.size(), 3u);
  EXPECT_EQ(scene->lightmap_uvs[2].x, 1.25f);
}

// A placement that only scales and translates is bounded by its mesh's
// bounds placed (a level's thousands of placements are not placed point by
// point for their bounds and range): the same numbers as placing every
// point, whatever the scales' signs; any other transform is placed point by
// point. PlacementsInRange checks each mesh once and agrees with
// PlacementInRange.
TEST(ScenePlacements, BoundsWithoutRotationAreThePlacedPointsBounds) {
  const Scene grid = testing::MakeRippledGrid(12);
  const Bounds local = BoundsOf(grid.positions);
  auto by_points = [&](const glm::dmat4& world) {
    Bounds bounds;
    for (const glm::dvec3& p : grid.positions) bounds.Extend(PlacePoint(world, p));
    return bounds;
  };
  for (const glm::dvec3& scale : {glm::dvec3(1.0), glm::dvec3(-3.0, 0.7, 1e-3), glm::dvec3(2.5, -1.0, -1e5),
                                  glm::dvec3(1.0 / 3.0, 7.0, -0.1)}) {
    for (const glm::dvec3& move : {glm::dvec3(0.0), glm::dvec3(1e6 + 0.1, -3.3, 12345.678), glm::dvec3(-1e-9)}) {
      const glm::dmat4 world = glm::scale(glm::translate(glm::dmat4(1.0), move), scale);
      const std::optional<Bounds> placed = PlacedBoundsWithoutRotation(world, local);
      ASSERT_TRUE(placed.has_value());
      const Bounds reference = by_points(world);
      EXPECT_EQ(placed->min, reference.min) << "scale " << scale.x << " move " << move.x;
      EXPECT_EQ(placed->max, reference.max) << "scale " << scale.x << " move " << move.x;
    }
  }
  const glm::dmat4 turned = glm::rotate(glm::dmat4(1.0), 0.3, glm::dvec3(0, 1, 0));
  EXPECT_FALSE(PlacedBoundsWithoutRotation(turned, local).has_value());

  std::vector<glm::dmat4> worlds = testing::CopyWorlds(grid, 4);
  worlds[2] = turned * worlds[2];
  worlds[3] = glm::scale(worlds[3], glm::dvec3(-2.0, 1.0, 0.5));
  const Scene placed = testing::PlaceMesh(grid, worlds);
  ASSERT_EQ(placed.placements.size(), 4u);
  Bounds reference;
  for (const glm::dmat4& world : worlds) {
    const Bounds one = by_points(world);
    reference.Extend(one.min);
    reference.Extend(one.max);
  }
  EXPECT_EQ(PositionBounds(placed).min, reference.min);
  EXPECT_EQ(PositionBounds(placed).max, reference.max);
  const std::vector<uint8_t> in_range = PlacementsInRange(placed);
  ASSERT_EQ(in_range.size(), placed.placements.size());
  for (size_t k = 0; k < placed.placements.size(); ++k)
    EXPECT_EQ(in_range[k] != 0, PlacementInRange(placed, placed.placements[k])) << k;
  Scene broken = placed;
  broken.meshes[0].triangles[5].y = static_cast<uint32_t>(broken.meshes[0].positions.size());
  for (uint8_t ok : PlacementsInRange(broken)) EXPECT_EQ(ok, 0) << "a corner past the mesh's positions";
}

// Copies of a turned mesh that differ by their translation (a level's
// prefabs) are bounded from the few points at the top and bottom of each
// row's order, the same numbers as placing every point: from the origin to
// 1e12 away, at tiny and huge scales, for a mesh whose extremes tie (a
// grid's flat sides, turned by 90 degrees in float, as Sponza's nodes are)
// and for random points. A linear part is placed point by point the first
// time it is seen, and so is a placement moved past kMaxOrderedTranslation.
TEST(ScenePlacements, TurnedCopiesAreBoundedByTheirOrderedExtremes) {
  std::vector<std::vector<glm::dvec3>> meshes = {testing::MakeRippledGrid(16).positions, {}, {}};
  std::mt19937_64 random(7);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  for (int i = 0; i < 2000; ++i) meshes[1].push_back(glm::dvec3(unit(random), unit(random), 1e-3 * unit(random)));
  const double swap = 1.7881390590446244e-07;  // Sponza's node: y and z swapped in float
  std::vector<glm::dmat4> turns = {
      glm::dmat4(1, 0, 0, 0, 0, swap, 0.9999997615814209, 0, 0, -0.9999997615814209, swap, 0, 0, 0, 0, 1),
      glm::rotate(glm::dmat4(1.0), 0.3, glm::normalize(glm::dvec3(1, 2, 3))),
      glm::scale(glm::rotate(glm::dmat4(1.0), 2.0, glm::dvec3(0, 0, 1)), glm::dvec3(1e-6, 3.0, -2.0)),
      glm::scale(glm::rotate(glm::dmat4(1.0), -1.1, glm::dvec3(0, 1, 0)), glm::dvec3(1e4))};
  // Extremes tied in exact arithmetic: for each row of the second turn, 300
  // points on a line across that row's direction, at its top and bottom;
  // their placed values differ only by rounding, which picks the extreme.
  for (int row = 0; row < 3; ++row) {
    const glm::dvec3 along = glm::normalize(glm::dvec3(turns[1][0][row], turns[1][1][row], turns[1][2][row]));
    const glm::dvec3 across = glm::normalize(glm::cross(along, glm::dvec3(0.6, -0.2, 0.77)));
    for (double side : {2.0, -2.0})
      for (int i = 0; i < 300; ++i) meshes[2].push_back(side * along + 0.5 * unit(random) * across);
  }
  for (size_t m = 0; m < meshes.size(); ++m) {
    const std::vector<glm::dvec3>& positions = meshes[m];
    PlacedMeshBounds placed(positions);
    uint64_t asked = 0;
    for (const glm::dmat4& turn : turns) {
      for (const glm::dvec3& move : {glm::dvec3(0.0), glm::dvec3(40.0, 0.0, 80.0), glm::dvec3(1e6 + 0.1, -3.3, 7.25),
                                     glm::dvec3(-1e12, 1e9 / 3.0, 0.5), glm::dvec3(40.0, 40.0 / 3.0, 28.0),
                                     glm::dvec3(-7.1, 13.7, 0.3), glm::dvec3(1e-9, -1e-300, 0.0)}) {
        const glm::dmat4 world = glm::translate(glm::dmat4(1.0), move) * turn;
        Bounds reference;
        for (const glm::dvec3& x : positions) reference.Extend(PlacePoint(world, x));
        const Bounds bounds = placed.Of(world, positions);
        ++asked;
        EXPECT_EQ(bounds.min, reference.min) << "mesh " << m << " move " << move.x;
        EXPECT_EQ(bounds.max, reference.max) << "mesh " << m << " move " << move.x;
      }
    }
    // Each turn is placed point by point the first time, and 1e12 away.
    EXPECT_EQ(placed.answered_by_extremes(), asked - 2 * turns.size()) << "mesh " << m;
    const glm::dmat4 fifth = glm::rotate(glm::dmat4(1.0), 0.7, glm::dvec3(1, 0, 0));
    placed.Of(fifth, positions);
    placed.Of(fifth, positions);
    EXPECT_EQ(placed.answered_by_extremes(), asked - 2 * turns.size() + 1) << "a fifth linear part seen twice";
  }
}

// A level of nine placed copies of a grid: the scene of record holds the
// grid once and nine placements (no flattened copy), answers per triangle
// through the placements with the flattened scene's bits, flattens the
// whole scene or a part of it on request to the same bits, and counts the
// flattened scene in its bytes once built. An edit that moves one copy
// keeps the other eight held once.
TEST(ScenePlacements, HeldOnceAndFlattenedOnRequestToTheSameBits) {
  const Scene grid = testing::MakeRippledGrid(20);
  const std::vector<glm::dmat4> worlds = testing::CopyWorlds(grid, 9);
  Scene reference;  // flattened by hand
  reference.materials = grid.materials;
  reference.nodes = grid.nodes;
  for (const glm::dmat4& world : worlds) {
    const auto base = static_cast<uint32_t>(reference.positions.size());
    for (const glm::dvec3& p : grid.positions) reference.positions.push_back(PlacePoint(world, p));
    for (const glm::uvec3& t : grid.triangles) reference.triangles.push_back(t + glm::uvec3(base));
    reference.triangle_material.insert(reference.triangle_material.end(), grid.triangle_material.begin(),
                                       grid.triangle_material.end());
    reference.triangle_node.insert(reference.triangle_node.end(), grid.triangle_node.begin(), grid.triangle_node.end());
  }
  const Scene placed = testing::PlaceMesh(grid, worlds);
  ASSERT_TRUE(ValidatePlacements(placed).ok()) << ValidatePlacements(placed);
  EXPECT_EQ(placed.placements.size(), 9u);
  EXPECT_TRUE(placed.triangles.empty()) << "every triangle is placed";
  EXPECT_EQ(placed.TriangleCount(), reference.TriangleCount());
  EXPECT_EQ(placed.PositionCount(), reference.positions.size());
  EXPECT_LT(placed.CpuBytes(), reference.CpuBytes() / 5) << "one grid and nine placements";
  for (size_t t = 0; t < reference.TriangleCount(); ++t) {
    for (int c = 0; c < 3; ++c) ASSERT_EQ(placed.Vertex(t, c), reference.Vertex(t, c)) << "triangle " << t;
    ASSERT_EQ(placed.MaterialOf(t), reference.triangle_material[t]);
    ASSERT_EQ(placed.NodeOf(t), reference.triangle_node[t]);
  }
  EXPECT_EQ(PositionBounds(placed).min, PositionBounds(reference).min);
  EXPECT_EQ(PositionBounds(placed).max, PositionBounds(reference).max);

  // A part: every other triangle, over the positions it uses.
  std::vector<uint8_t> skip(reference.TriangleCount(), 0);
  for (size_t t = 0; t < skip.size(); t += 2) skip[t] = 1;
  const FlattenedPart part = FlattenPart(placed, skip);
  ASSERT_EQ(part.triangles.size(), skip.size() / 2);
  for (size_t i = 0; i < part.triangles.size(); ++i)
    for (int c = 0; c < 3; ++c)
      ASSERT_EQ(part.positions[part.triangles[i][c]], reference.Vertex(part.scene_triangle[i], c));
  EXPECT_FALSE(placed.FlattenedBuilt()) << "a part flattens nothing else";

  const size_t held_bytes = placed.CpuBytes();
  const Scene& flat = placed.Flattened();
  EXPECT_TRUE(placed.FlattenedBuilt());
  EXPECT_EQ(flat.positions, reference.positions);
  EXPECT_EQ(flat.triangles, reference.triangles);
  EXPECT_EQ(flat.triangle_material, reference.triangle_material);
  EXPECT_EQ(flat.triangle_node, reference.triangle_node);
  EXPECT_GT(placed.CpuBytes(), held_bytes + reference.positions.size() * sizeof(glm::dvec3));
  EXPECT_FALSE(Scene(placed).FlattenedBuilt()) << "a copy starts without it";

  // Moving the node every copy's triangles belong to: the copies stay
  // placements, placed by the move after their world, and nothing is
  // flattened.
  Scene edited = placed;
  const glm::dmat4 up = glm::translate(glm::dmat4(1.0), glm::dvec3(0, 1, 0));
  const Status moved = MoveNodeSubtree(edited, 0, up * edited.nodes[0].world);
  ASSERT_TRUE(moved.ok()) << moved;
  ASSERT_EQ(edited.placements.size(), 9u);
  EXPECT_TRUE(ValidatePlacements(edited).ok()) << ValidatePlacements(edited);
  EXPECT_FALSE(edited.FlattenedBuilt());
  EXPECT_EQ(edited.TriangleCount(), reference.TriangleCount());
  const glm::dmat4 delta = up * placed.nodes[0].world * glm::inverse(placed.nodes[0].world);
  for (size_t k = 0; k < worlds.size(); ++k) {
    const glm::dmat4 world = edited.placements[k].world;
    EXPECT_EQ(world, delta * placed.placements[k].world) << k;
    const size_t t = edited.placements[k].first_triangle + 5;
    EXPECT_EQ(edited.Vertex(t, 1), PlacePoint(world, grid.positions[grid.triangles[5][1]])) << k;
    EXPECT_NEAR(edited.Vertex(t, 1).y, reference.Vertex(t, 1).y + 1.0, 1e-12) << k;
  }
  Bounds moved_bounds;
  for (size_t t = 0; t < edited.TriangleCount(); ++t)
    for (int c = 0; c < 3; ++c) moved_bounds.Extend(edited.Vertex(t, c));
  EXPECT_EQ(edited.bounds.min, moved_bounds.min);
  EXPECT_EQ(edited.bounds.max, moved_bounds.max);
  EXPECT_TRUE(placed.FlattenedBuilt()) << "the original is untouched";
}

}  // namespace
}  // namespace visq
