// The conversion layer alone: every request names its scene the same way,
// unknown enum values and bad fields are refused naming the field, defaults
// are filled, and a map's answer streams back as the client reassembles it.
#include "service/convert.h"

#include <gtest/gtest.h>

namespace visq::service {
namespace {

template <typename Request>
void ExpectSceneNameRequired() {
  Request request;
  auto query = FromProto(request);
  ASSERT_FALSE(query.ok());
  EXPECT_EQ(query.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(query.status().message(), "scene.name: empty");
}

TEST(Convert, EveryQueryNeedsASceneName) {
  ExpectSceneNameRequired<v1::HiddenSampleMapRequest>();
  ExpectSceneNameRequired<v1::PatchVisibilityRequest>();
  ExpectSceneNameRequired<v1::VolumetricShadowRequest>();
  ExpectSceneNameRequired<v1::VoxelizeRequest>();
  ExpectSceneNameRequired<v1::TransmittanceRequest>();
  ExpectSceneNameRequired<v1::ObscurancePreviewRequest>();
  v1::LightVisibilityRequest light;
  auto query = FromProto(light, nullptr);
  EXPECT_EQ(query.status().message(), "scene.name: empty");
}

TEST(Convert, SceneRefCarriesNameAndVersion) {
  v1::SceneRef ref;
  ref.set_name("sponza");
  ref.set_version(7);
  std::string name;
  uint64_t version = 0;
  ASSERT_TRUE(SceneRefFromProto(ref, name, version).ok());
  EXPECT_EQ(name, "sponza");
  EXPECT_EQ(version, 7u);
}

TEST(Convert, UnknownEnumValuesAreRefusedByField) {
  v1::VoxelizeRequest voxelize;
  voxelize.mutable_scene()->set_name("s");
  voxelize.set_mode(static_cast<v1::VoxelizeRequest::Mode>(99));
  auto v = FromProto(voxelize);
  EXPECT_EQ(v.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(v.status().message().find("mode"), absl::string_view::npos) << v.status();

  voxelize.set_mode(v1::VoxelizeRequest::SURFACE);
  voxelize.set_depth_axis(3);
  v = FromProto(voxelize);
  EXPECT_NE(v.status().message().find("depth_axis"), absl::string_view::npos) << v.status();

  v1::VolumetricShadowRequest volumetric;
  volumetric.mutable_scene()->set_name("s");
  volumetric.set_method(static_cast<v1::VolumetricShadowRequest::Method>(42));
  auto s = FromProto(volumetric);
  EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.status().message().find("method"), absl::string_view::npos) << s.status();
}

TEST(Convert, VoxelizeDefaultsFillUnsetSizes) {
  v1::VoxelizeRequest request;
  request.mutable_scene()->set_name("s");
  auto query = FromProto(request);
  ASSERT_TRUE(query.ok()) << query.status();
  EXPECT_EQ(query->params.width, 128u);
  EXPECT_EQ(query->params.height, 128u);
  EXPECT_EQ(query->params.slices, 128u);
  EXPECT_FALSE(query->box.has_value());
}

// A map's bands as the stream sends them: each array's chunks carry the
// offset of their first element in the whole map (texels, or words for the
// bitmasks), so bands written one after another rebuild the map; the first
// message holds the sizes, the last the accuracy.
TEST(Convert, HiddenSampleMapBandsStreamEveryTexelAtItsOffset) {
  core::HiddenSampleMapAnswer answer;
  sampling::HiddenSampleMapResult& map = answer.result;
  map.width = 3;
  map.height = 2;
  map.sample_count = 40;
  map.words_per_texel = 2;
  const std::vector<float> fractions = {1, 0.5f, 0.25f, 0, 1, 1};
  const std::vector<uint32_t> words = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12};
  const std::vector<float> lookup = {0, 0.1f, 0, 0.2f, 0, 0.3f};

  core::HiddenSampleMapQuery query;  // want_texel_error unset: no texel bounds sent
  std::vector<v1::HiddenSampleMapResponse> sent = {FirstMessage(map)};
  auto write = [&](v1::HiddenSampleMapResponse m) {
    sent.push_back(std::move(m));
    return absl::OkStatus();
  };
  for (size_t row = 0; row < 2; ++row) {
    sampling::HiddenSampleMapBand band;
    band.first = row * 3;
    band.visible_fraction.assign(fractions.begin() + row * 3, fractions.begin() + row * 3 + 3);
    band.blocked_bits.assign(words.begin() + row * 6, words.begin() + row * 6 + 6);
    band.lookup_error.assign(lookup.begin() + row * 3, lookup.begin() + row * 3 + 3);
    ASSERT_TRUE(WriteBand(query, map, band, write, /*chunk_elements=*/2).ok());
  }
  map.error.sampling = 0.125;
  answer.accuracy =
      core::SampledVisibilityStatement(map.error, core::VisibilityMethod::kRaster, sampling::LookupMode::kHough,
                                       map.sample_count);
  sent.push_back(LastMessage(answer));

  EXPECT_EQ(sent.front().width(), 3u);
  EXPECT_EQ(sent.front().words_per_texel(), 2u);
  EXPECT_FALSE(sent.front().has_accuracy());
  EXPECT_TRUE(sent.back().has_accuracy());
  EXPECT_EQ(sent.back().accuracy().method(), "raster-hough-lookup");
  std::vector<float> got_fractions(fractions.size(), -1), got_lookup(lookup.size(), -1);
  std::vector<uint32_t> got_words(words.size(), 0);
  for (const v1::HiddenSampleMapResponse& m : sent) {
    const int arrays = (m.visible_fraction_size() > 0) + (m.blocked_bits_size() > 0) + (m.lookup_error_size() > 0);
    EXPECT_LE(arrays, 1) << "one array chunk per message";
    EXPECT_LE(m.visible_fraction_size() + m.blocked_bits_size() + m.lookup_error_size(), 2);
    for (int i = 0; i < m.visible_fraction_size(); ++i) got_fractions.at(m.offset() + i) = m.visible_fraction(i);
    for (int i = 0; i < m.blocked_bits_size(); ++i) got_words.at(m.offset() + i) = m.blocked_bits(i);
    for (int i = 0; i < m.lookup_error_size(); ++i) got_lookup.at(m.offset() + i) = m.lookup_error(i);
  }
  EXPECT_EQ(got_fractions, fractions);
  EXPECT_EQ(got_words, words);
  EXPECT_EQ(got_lookup, lookup);
}

// The transport adds nothing to the core's statement and drops nothing.
TEST(Convert, AccuracyStatementCopiedFieldByField) {
  core::AccuracyStatement statement;
  statement.method = "slicemap-conservative-uniform";
  statement.error_bound = 0.25;
  statement.confidence = 1.0;
  statement.note = "why";
  statement.parameters = {{"samples", 64.0}, {"directions", 8.0}};
  statement.predicted_ms = 12.5;
  v1::Accuracy out;
  ToProto(statement, &out);
  EXPECT_EQ(out.method(), statement.method);
  EXPECT_EQ(out.error_bound(), statement.error_bound);
  EXPECT_EQ(out.confidence(), statement.confidence);
  EXPECT_EQ(out.note(), statement.note);
  ASSERT_EQ(out.parameters_size(), 2);
  EXPECT_EQ(out.parameters().at("samples"), 64.0);
  EXPECT_EQ(out.parameters().at("directions"), 8.0);
  EXPECT_EQ(out.predicted_ms(), 12.5);
}

// A write that fails (the client went away) stops the band there.
TEST(Convert, HiddenSampleMapBandStopsAtAFailedWrite) {
  sampling::HiddenSampleMapBand band;
  band.visible_fraction.assign(10, 0.5f);
  int writes = 0;
  sampling::HiddenSampleMapResult map;
  map.words_per_texel = 1;
  const Status status = WriteBand(
      core::HiddenSampleMapQuery{}, map, band,
      [&](v1::HiddenSampleMapResponse) {
        ++writes;
        return absl::CancelledError("gone");
      },
      /*chunk_elements=*/2);
  EXPECT_EQ(status.code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(writes, 1);
}

}  // namespace
}  // namespace visq::service
