// The baked glTF (ExportObscurances, `visq obscurance-export --gltf`) as the
// studio's tools read it, end to end through the real server and the visq
// CLI on real scenes: the Khronos glTF validator finds no error and no
// warning in it, the input's attributes come back with the bake added, and
// Debian's Blender imports it with the occlusion texture wired to the atlas
// UV layer and W there equal to the bake's triangle_w.
//
// The validator is npm's gltf-validator, which `npm ci` installs into the
// build directory before these tests (the visq_gltf_validator_install
// fixture, tests/gltf_export/validator/package-lock.json); node and blender
// come from deploy/install-deps.sh. A machine without them skips, saying so.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "scene/gltf_loader.h"
#include "scene/gltf_writer.h"
#include "shared_server_suite.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;

bool HaveCommand(const std::string& name) {
  int status = 0;
  testing::RunCommand("command -v " + name + " >/dev/null 2>&1", &status);
  return status == 0;
}

std::string ReadFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// The JSON chunk of a .glb.
nlohmann::json GlbJson(const std::string& glb) {
  uint32_t json_length = 0;
  std::memcpy(&json_length, glb.data() + 12, 4);
  return nlohmann::json::parse(glb.substr(20, json_length));
}

struct Baked {
  fs::path glb;
  Scene input;                 // the input as the server loaded it (its triangle order is the answer's)
  client::ObscuranceBake bake;
  client::ObscuranceExport exported;
};

class GltfExportTest : public testing::SharedServerSuite<GltfExportTest> {
 protected:
  // Uploads `file`, bakes it (the ray-cast estimator, averages and bounds
  // wanted) and exports it with the CLI into dir_ as NAME.glb; the atlas
  // UVs come from the client library, for the checks.
  void BakeAndExport(const fs::path& file, const std::string& name, double d_max, Baked& out) {
    ASSERT_TRUE(client_->UploadScene(file, name, /*replace=*/true).ok());
    StatusOr<Scene> input = LoadGltfFile(file);
    ASSERT_TRUE(input.ok()) << input.status();
    out.input = std::move(*input);
    v1::ComputeObscurancesRequest bake;
    bake.mutable_scene()->set_name(name);
    bake.set_resolution(512);
    bake.set_d_max(d_max);
    bake.set_method(v1::ComputeObscurancesRequest::RAYCAST);
    bake.set_rays_per_patch(64);
    bake.set_want_averages(true);
    bake.set_want_errors(true);
    auto result = client_->ComputeObscurances(bake);
    ASSERT_TRUE(result.ok()) << result.status();
    out.bake = std::move(*result);
    v1::ExportObscurancesRequest request;
    request.mutable_scene()->set_name(name);
    request.set_want_atlas_uvs(true);
    auto exported = client_->ExportObscurances(request);
    ASSERT_TRUE(exported.ok()) << exported.status();
    out.exported = std::move(*exported);
    out.glb = dir_.path() / (name + ".glb");
    int status = 0;
    const std::string output = testing::RunCommand(std::string(VISQ_CLI_BINARY) + " obscurance-export " + name +
                                                       " --vertex-colors --gltf " + out.glb.string() + " --server " +
                                                       server_->address() + " 2>&1",
                                                   &status);
    ASSERT_EQ(status, 0) << output;
  }

  // The validator's report on `glb`: zero errors and zero warnings wanted.
  void ExpectValid(const fs::path& glb) {
    int status = 0;
    const std::string report = testing::RunCommand("node " + std::string(VISQ_GLTF_VALIDATE_SCRIPT) + " " +
                                                       VISQ_GLTF_VALIDATOR_MODULES + " " + glb.string() + " 2>&1",
                                                   &status);
    const size_t json_start = report.find('{');
    ASSERT_NE(json_start, std::string::npos) << report;
    const size_t json_end = report.rfind('}');
    const nlohmann::json doc = nlohmann::json::parse(report.substr(json_start, json_end - json_start + 1));
    const auto& issues = doc["issues"];
    std::string listed;
    for (const auto& message : issues["messages"])
      if (message["severity"].get<int>() <= 1)  // 0 error, 1 warning
        listed += message["code"].get<std::string>() + " at " + message.value("pointer", "") + ": " +
                  message["message"].get<std::string>() + "\n";
    std::printf("%s: validator %d errors, %d warnings, %d infos, %d hints; %s vertices\n", glb.filename().c_str(),
                issues["numErrors"].get<int>(), issues["numWarnings"].get<int>(), issues["numInfos"].get<int>(),
                issues["numHints"].get<int>(), doc["info"]["totalVertexCount"].dump().c_str());
    EXPECT_EQ(issues["numErrors"].get<int>(), 0) << listed;
    EXPECT_EQ(issues["numWarnings"].get<int>(), 0) << listed;
    EXPECT_EQ(status, 0) << report.substr(0, 4000);
  }

  testing::ScratchDir dir_;
};

// Every vertex count of a .glb's primitives.
uint64_t GlbVertices(const nlohmann::json& doc) {
  uint64_t vertices = 0;
  for (const auto& mesh : doc["meshes"])
    for (const auto& primitive : mesh["primitives"])
      vertices += doc["accessors"][primitive["attributes"]["POSITION"].get<size_t>()]["count"].get<uint64_t>();
  return vertices;
}

// Sponza, the Cornell box (positions only: the atlas becomes TEXCOORD_0)
// and Kenney's palm (normals and TEXCOORD_0: the atlas becomes TEXCOORD_1),
// each baked on an atlas the server built, export clean. Sponza's vertices:
// the input's 62,754 split only along the atlas's chart seams, against one
// per corner (199,362) before.
TEST_F(GltfExportTest, TheKhronosValidatorFindsNoErrorOrWarning) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  if (!HaveCommand("node") || !fs::exists(fs::path(VISQ_GLTF_VALIDATOR_MODULES) / "gltf-validator"))
    GTEST_SKIP() << "node or npm's gltf-validator (in " << VISQ_GLTF_VALIDATOR_MODULES
                 << ") is absent: deploy/install-deps.sh installs nodejs and npm, the visq_gltf_validator_install "
                    "fixture the validator";
  struct Case {
    const char* name;
    fs::path file;
    double d_max;
    int input_uv_sets;
  };
  for (const Case& c : {Case{"sponza", scenes / "sponza_dabrovic/sponza.gltf", 2.0, 0},
                        Case{"cornell", scenes / "cornell_box/cornell_box.gltf", 0.5, 0},
                        Case{"palm", scenes / "tree_kenney/tree_palmDetailedTall.glb", 0.5, 1}}) {
    SCOPED_TRACE(c.name);
    Baked baked;
    ASSERT_NO_FATAL_FAILURE(BakeAndExport(c.file, c.name, c.d_max, baked));
    ExpectValid(baked.glb);

    // The input's attributes, the atlas as the set after them, W read
    // through it, and W per vertex; indexed, split only where charts cut.
    const std::string bytes = ReadFile(baked.glb);
    const nlohmann::json doc = GlbJson(bytes);
    const bool normals = !baked.input.normals.empty();
    for (const auto& mesh : doc["meshes"])
      for (const auto& primitive : mesh["primitives"]) {
        const auto& attributes = primitive["attributes"];
        EXPECT_EQ(attributes.contains("NORMAL"), normals);
        for (int set = 0; set <= c.input_uv_sets; ++set)
          EXPECT_TRUE(attributes.contains("TEXCOORD_" + std::to_string(set))) << attributes.dump();
        EXPECT_FALSE(attributes.contains("TEXCOORD_" + std::to_string(c.input_uv_sets + 1))) << attributes.dump();
        EXPECT_TRUE(attributes.contains("COLOR_0")) << attributes.dump();
        EXPECT_TRUE(primitive.contains("indices"));
      }
    for (const auto& material : doc["materials"])
      EXPECT_EQ(material["occlusionTexture"].value("texCoord", 0), c.input_uv_sets);  // 0 is the default, left out
    const uint64_t vertices = GlbVertices(doc), corners = 3 * baked.input.triangles.size();
    std::printf("%s: %zu input positions, %zu triangles, %llu exported vertices (%llu corners)\n", c.name,
                baked.input.positions.size(), baked.input.triangles.size(), static_cast<unsigned long long>(vertices),
                static_cast<unsigned long long>(corners));
    EXPECT_LE(vertices, corners);
    if (std::string(c.name) == "sponza") {
      EXPECT_LT(vertices, corners / 2) << "corners that share a position and an atlas UV are one vertex";
    }

    // Read back by visq's own loader: the same triangles and positions, the
    // input's UV sets and normals as they were, the atlas UVs on the new set.
    StatusOr<Scene> back = LoadGltfFile(baked.glb);
    ASSERT_TRUE(back.ok()) << back.status();
    ASSERT_EQ(back->triangles.size(), baked.input.triangles.size());
    ASSERT_EQ(back->texcoords.size(), static_cast<size_t>(c.input_uv_sets + 1));
    double position_error = 0, normal_error = 0, uv_error = 0, atlas_error = 0;
    const std::vector<float>& atlas = baked.exported.atlas_uv;
    for (size_t t = 0; t < back->triangles.size(); ++t)
      for (int corner = 0; corner < 3; ++corner) {
        const uint32_t v = back->triangles[t][corner], input = baked.input.triangles[t][corner];
        position_error = std::max(position_error, glm::length(back->positions[v] - baked.input.positions[input]));
        if (normals) normal_error = std::max(normal_error, double(glm::length(back->normals[v] - baked.input.normals[input])));
        for (int set = 0; set < c.input_uv_sets; ++set)
          uv_error = std::max(uv_error, double(glm::length(back->texcoords[set][v] - baked.input.texcoords[set][input])));
        atlas_error = std::max(atlas_error, double(glm::length(back->texcoords[c.input_uv_sets][v] -
                                                               glm::vec2(atlas[6 * t + 2 * corner],
                                                                         atlas[6 * t + 2 * corner + 1]))));
      }
    EXPECT_LT(position_error, 1e-4);  // float32 accessors
    EXPECT_LT(normal_error, 1e-6);
    EXPECT_EQ(uv_error, 0.0);
    EXPECT_EQ(atlas_error, 0.0);
  }
}

// A scene with its own lightmap UVs (TEXCOORD_1): the bake is on them, and
// the export reads W through them instead of adding a set.
TEST_F(GltfExportTest, ALightmapUvSetCarriesTheBakeItself) {
  if (!HaveCommand("node") || !fs::exists(fs::path(VISQ_GLTF_VALIDATOR_MODULES) / "gltf-validator"))
    GTEST_SKIP() << "node or npm's gltf-validator is absent";
  // The lightmap: the palm's export from a bake on an atlas the server
  // built, whose atlas UVs are its TEXCOORD_1 (charts that do not overlap,
  // as an artist's lightmap set is).
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  Baked atlas;
  ASSERT_NO_FATAL_FAILURE(BakeAndExport(scenes / "tree_kenney/tree_palmDetailedTall.glb", "palm_atlas", 0.5, atlas));
  const fs::path input = atlas.glb;
  Baked baked;
  ASSERT_NO_FATAL_FAILURE(BakeAndExport(input, "palm_lightmap", 0.5, baked));
  EXPECT_TRUE(baked.exported.figures.from_lightmap_uvs());
  ExpectValid(baked.glb);
  const nlohmann::json doc = GlbJson(ReadFile(baked.glb));
  for (const auto& material : doc["materials"]) EXPECT_EQ(material["occlusionTexture"].value("texCoord", 0), 1);
  for (const auto& mesh : doc["meshes"])
    for (const auto& primitive : mesh["primitives"])
      EXPECT_FALSE(primitive["attributes"].contains("TEXCOORD_2")) << primitive["attributes"].dump();
  EXPECT_EQ(GlbVertices(doc), baked.input.positions.size()) << "no corner split: the lightmap UVs are the input's";
}

// Debian's Blender imports the export with the occlusion texture wired to a
// UV layer of the mesh, and W read there at each triangle's centre is the
// W atlas at the atlas UVs' centre (to its 8 bits) and the bake's
// triangle_w within the stated bounds (tests/gltf_export/blender_check.py).
// Built atlases (the atlas a UV map of its own) and a lightmap UV set (the
// bake read through the artist's second UV map).
TEST_F(GltfExportTest, BlenderImportsTheBakeOnTheMesh) {
  VISQ_REQUIRE_SHARED_SCENES(scenes);
  if (!HaveCommand("blender"))
    GTEST_SKIP() << "blender is absent (deploy/install-deps.sh installs Debian's blender)";
  struct Case {
    const char* name;
    fs::path file;
    double d_max;
  };
  // The lightmap case bakes the palm's export (the case before it), whose
  // TEXCOORD_1 is the atlas the server built.
  const fs::path lightmap_palm = dir_.path() / "palm_blender.glb";
  for (const Case& c : {Case{"cornell_blender", scenes / "cornell_box/cornell_box.gltf", 0.5},
                        Case{"palm_blender", scenes / "tree_kenney/tree_palmDetailedTall.glb", 0.5},
                        Case{"palm_lightmap_blender", lightmap_palm, 0.5},
                        Case{"sponza_blender", scenes / "sponza_dabrovic/sponza.gltf", 2.0}}) {
    SCOPED_TRACE(c.name);
    Baked baked;
    ASSERT_NO_FATAL_FAILURE(BakeAndExport(c.file, c.name, c.d_max, baked));
    // What Blender checks, per triangle: its centre (glTF axes), triangle_w,
    // its own bound, and the W atlas at the atlas UVs' centre.
    const uint32_t width = baked.exported.figures.width(), height = baked.exported.figures.height();
    const std::vector<float>& uv = baked.exported.atlas_uv;
    nlohmann::json triangles = nlohmann::json::array();
    for (size_t t = 0; t < baked.input.triangles.size(); ++t) {
      const glm::dvec3 centre = (baked.input.Vertex(t, 0) + baked.input.Vertex(t, 1) + baked.input.Vertex(t, 2)) / 3.0;
      const double u = (uv[6 * t] + uv[6 * t + 2] + uv[6 * t + 4]) / 3.0;
      const double v = (uv[6 * t + 1] + uv[6 * t + 3] + uv[6 * t + 5]) / 3.0;
      const uint32_t x = std::min<uint32_t>(width - 1, static_cast<uint32_t>(u * width));
      const uint32_t y = std::min<uint32_t>(height - 1, static_cast<uint32_t>(v * height));
      triangles.push_back({centre.x, centre.y, centre.z, baked.bake.triangle_w[3 * t],
                           baked.bake.triangle_w_error[t], baked.bake.w[3 * (size_t(y) * width + x)]});
    }
    const nlohmann::json expected = {{"triangles", triangles},
                                     {"bound", baked.bake.figures.accuracy().error_bound()},
                                     {"atlas_texcoord", baked.exported.figures.from_lightmap_uvs()
                                                            ? size_t{1}
                                                            : baked.input.texcoords.size()}};
    const fs::path expected_file = dir_.path() / (std::string(c.name) + ".json");
    std::ofstream(expected_file) << expected.dump();
    int status = 0;
    const std::string output = testing::RunCommand(
        "blender -b --factory-startup --python-exit-code 1 --python " + std::string(VISQ_BLENDER_CHECK_SCRIPT) +
            " -- " + c.file.string() + " " + baked.glb.string() + " " + expected_file.string() + " 2>&1",
        &status);
    const size_t line = output.find("blender_check:");
    std::printf("%s: %s\n", c.name,
                line == std::string::npos ? "(no result line)" : output.substr(line, output.find('\n', line) - line).c_str());
    EXPECT_EQ(status, 0) << output.substr(output.size() > 6000 ? output.size() - 6000 : 0);
  }
}

}  // namespace
}  // namespace visq
