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

// A map's answer as the stream sends it: figures first, then the fractions
// and bitmask words, each in order from offset 0.
TEST(Convert, HiddenSampleMapAnswerStreamsEveryTexel) {
  HiddenSampleMapAnswer answer;
  sampling::HiddenSampleMapResult& r = answer.result;
  r.width = 3;
  r.height = 2;
  r.sample_count = 40;
  r.words_per_texel = 2;
  r.visible_fraction = {1, 0.5f, 0.25f, 0, 1, 1};
  r.blocked_bits = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12};
  ChunkedResponses<v1::HiddenSampleMapResponse> stream = ToProtoStream(answer);
  v1::HiddenSampleMapResponse m;
  ASSERT_TRUE(stream.Next(m));
  EXPECT_EQ(m.width(), 3u);
  EXPECT_EQ(m.height(), 2u);
  EXPECT_EQ(m.words_per_texel(), 2u);
  std::vector<float> fractions(m.visible_fraction().begin(), m.visible_fraction().end());
  std::vector<uint32_t> bits;
  while (stream.Next(m)) {
    if (m.visible_fraction_size() > 0) {
      EXPECT_EQ(m.offset(), fractions.size());
      fractions.insert(fractions.end(), m.visible_fraction().begin(), m.visible_fraction().end());
    }
    if (m.blocked_bits_size() > 0) {
      EXPECT_EQ(m.offset(), bits.size());
      bits.insert(bits.end(), m.blocked_bits().begin(), m.blocked_bits().end());
    }
  }
  EXPECT_EQ(fractions, r.visible_fraction);
  EXPECT_EQ(bits, r.blocked_bits);
}

}  // namespace
}  // namespace visq::service
