// The scene repository on a real folder: names, uploads committed or
// abandoned, replacement, versions that never repeat across reopenings,
// and stale staging left by a crash.
#include "core/scene_repository.h"

#include <filesystem>
#include <fstream>
#include <set>

#include <gtest/gtest.h>

#include "test_support.h"

namespace visq::core {
namespace {

namespace fs = std::filesystem;

StatusOr<SceneRepository::Stored> Store(SceneRepository& repo, const std::string& name, const std::string& body) {
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<UploadStaging> staging, repo.BeginUpload(name, name + ".gltf", 1 << 20));
  VISQ_RETURN_IF_ERROR(staging->Append(name + ".gltf", body));
  return repo.Commit(*staging);
}

TEST(SceneRepository, NamesAreCheckedBeforeAnyFileIsTouched) {
  for (const char* bad : {"", ".hidden", "a/b", "../x", "a b", "x\n", "\xff"})
    EXPECT_EQ(SceneRepository::ValidateName(bad).code(), absl::StatusCode::kInvalidArgument) << bad;
  EXPECT_EQ(SceneRepository::ValidateName(std::string(129, 'a')).code(), absl::StatusCode::kInvalidArgument);
  for (const char* good : {"sponza", "a.b-c_d", "A1"}) EXPECT_TRUE(SceneRepository::ValidateName(good).ok()) << good;
}

TEST(SceneRepository, CommitStoresListsAndReplacesUnderANewVersion) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path() / "repo");
  ASSERT_TRUE(repo.ok()) << repo.status();
  auto first = Store(**repo, "box", "{\"asset\":{\"version\":\"2.0\"}}");
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ((*repo)->List(), std::vector<std::string>{"box"});
  auto main_file = (*repo)->MainFile("box");
  ASSERT_TRUE(main_file.ok()) << main_file.status();
  EXPECT_TRUE(fs::exists(*main_file));
  EXPECT_EQ((*repo)->StoredVersion("box"), first->version);

  auto second = Store(**repo, "box", "{\"asset\":{\"version\":\"2.0\"},\"scenes\":[]}");
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_GT(second->version, first->version);
  EXPECT_EQ((*repo)->List(), std::vector<std::string>{"box"});
  std::ifstream in(*(*repo)->MainFile("box"));
  const std::string stored((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_NE(stored.find("scenes"), std::string::npos) << "the replacement is what is stored";

  EXPECT_TRUE((*repo)->Remove("box").ok());
  EXPECT_TRUE((*repo)->List().empty());
  EXPECT_FALSE((*repo)->Contains("box"));
}

TEST(SceneRepository, AnAbandonedUploadLeavesNothing) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path() / "repo");
  ASSERT_TRUE(repo.ok()) << repo.status();
  {
    auto staging = (*repo)->BeginUpload("half", "half.gltf", 1 << 20);
    ASSERT_TRUE(staging.ok()) << staging.status();
    ASSERT_TRUE((*staging)->Append("half.gltf", "{").ok());
  }  // never committed
  EXPECT_TRUE((*repo)->List().empty());
  EXPECT_FALSE((*repo)->Contains("half"));
}

TEST(SceneRepository, UploadFilesStayInsideTheirFolderAndUnderTheirCap) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path() / "repo");
  ASSERT_TRUE(repo.ok()) << repo.status();
  auto staging = (*repo)->BeginUpload("s", "s.gltf", 8);
  ASSERT_TRUE(staging.ok()) << staging.status();
  EXPECT_EQ((*staging)->Append("../escape.bin", "x").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*staging)->Append("/etc/passwd", "x").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(dir.path() / "escape.bin"));
  EXPECT_TRUE((*staging)->Append("s.gltf", "12345678").ok());
  EXPECT_EQ((*staging)->Append("s.gltf", "9").code(), absl::StatusCode::kResourceExhausted);
}

TEST(SceneRepository, VersionsNeverRepeatAcrossReopenings) {
  testing::ScratchDir dir;
  std::set<uint64_t> seen;
  for (int opening = 0; opening < 3; ++opening) {
    auto repo = SceneRepository::Open(dir.path() / "repo");
    ASSERT_TRUE(repo.ok()) << repo.status();
    for (int k = 0; k < 4; ++k) {
      auto version = (*repo)->NextVersion();
      ASSERT_TRUE(version.ok()) << version.status();
      EXPECT_TRUE(seen.insert(*version).second) << "version " << *version << " repeated";
    }
  }
}

}  // namespace
}  // namespace visq::core
