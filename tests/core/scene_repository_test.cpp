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
  return repo.Commit(*staging, /*replace=*/true);
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

// Two replicas creating the same new name: one stores, the other is told the
// name exists; neither upload is silently lost.
TEST(SceneRepository, ConcurrentCreatesOfOneNameStoreOneAndRefuseTheOther) {
  testing::ScratchDir dir;
  auto first = SceneRepository::Open(dir.path());
  auto second = SceneRepository::Open(dir.path());
  ASSERT_TRUE(first.ok() && second.ok());
  auto a = (*first)->BeginUpload("same", "same.gltf", 1 << 20);
  auto b = (*second)->BeginUpload("same", "same.gltf", 1 << 20);
  ASSERT_TRUE(a.ok() && b.ok());
  ASSERT_TRUE((*a)->Append("same.gltf", "first").ok());
  ASSERT_TRUE((*b)->Append("same.gltf", "second").ok());
  // Both checked that the name was free; both commit without replace.
  auto stored = (*first)->Commit(**a, /*replace=*/false);
  ASSERT_TRUE(stored.ok()) << stored.status();
  auto refused = (*second)->Commit(**b, /*replace=*/false);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kAlreadyExists) << refused.status();
  std::ifstream in(stored->main_file);
  std::string body((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_EQ(body, "first") << "the acknowledged upload is the one stored";
  // With replace, the second takes its place.
  auto c = (*second)->BeginUpload("same", "same.gltf", 1 << 20);
  ASSERT_TRUE(c.ok());
  ASSERT_TRUE((*c)->Append("same.gltf", "third").ok());
  EXPECT_TRUE((*second)->Commit(**c, /*replace=*/true).ok());
}

// A replica's start removes the staging folders a crash left, not those of
// uploads in flight on another replica of the same repository.
TEST(SceneRepository, AStartKeepsAnotherReplicasUploadInFlight) {
  testing::ScratchDir dir;
  auto running = SceneRepository::Open(dir.path());
  ASSERT_TRUE(running.ok());
  auto in_flight = (*running)->BeginUpload("busy", "busy.gltf", 1 << 20);
  ASSERT_TRUE(in_flight.ok());
  ASSERT_TRUE((*in_flight)->Append("busy.gltf", "half").ok());
  // A folder a crashed upload left, beside the live one.
  const fs::path crashed = dir.path() / ".staging-gone-0000000000000001";
  fs::create_directory(crashed);

  auto starting = SceneRepository::Open(dir.path());  // another replica starts
  ASSERT_TRUE(starting.ok());
  EXPECT_FALSE(fs::exists(crashed)) << "a crash's leftovers go";
  EXPECT_TRUE(fs::exists((*in_flight)->dir())) << "a live upload's folder stays";
  ASSERT_TRUE((*in_flight)->Append("busy.gltf", ", then done").ok());
  EXPECT_TRUE((*running)->Commit(**in_flight, /*replace=*/false).ok());
}

// A commit gives the stored scene a new identity (folder and version), which
// is how a load tells that the files it read were replaced meanwhile.
TEST(SceneRepository, AReplaceChangesTheStoredIdentity) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path());
  ASSERT_TRUE(repo.ok());
  ASSERT_TRUE(Store(**repo, "s", "one").ok());
  const SceneRepository::Identity before = (*repo)->StoredIdentity("s");
  EXPECT_GT(before.version, 0u);
  EXPECT_EQ((*repo)->StoredIdentity("s"), before);
  ASSERT_TRUE(Store(**repo, "s", "two").ok());
  const SceneRepository::Identity after = (*repo)->StoredIdentity("s");
  EXPECT_NE(after.version, before.version);
  EXPECT_NE(after.inode, before.inode);
}

// An upload's folders and files are its owner's alone; a name past what a
// file system holds, and a file where another chunk made a folder, are the
// client's mistakes, named as such.
TEST(SceneRepository, UploadsAreTheOwnersAloneAndBadLayoutsAreTheClientsMistake) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path());
  ASSERT_TRUE(repo.ok());
  auto staging = (*repo)->BeginUpload("private", "private.gltf", 1 << 20);
  ASSERT_TRUE(staging.ok());
  ASSERT_TRUE((*staging)->Append("private.gltf", "{}").ok());
  ASSERT_TRUE((*staging)->Append("buffers/data.bin", "bytes").ok());
  auto stored = (*repo)->Commit(**staging, /*replace=*/false);
  ASSERT_TRUE(stored.ok()) << stored.status();
  size_t checked = 0;
  const fs::path folder = stored->main_file.parent_path();
  for (const auto& entry : fs::recursive_directory_iterator(folder)) {
    EXPECT_EQ(fs::status(entry.path()).permissions() & (fs::perms::group_all | fs::perms::others_all), fs::perms::none)
        << entry.path();
    ++checked;
  }
  EXPECT_GE(checked, 4u) << "the main file, the folder, its file and the markers";
  EXPECT_EQ(fs::status(folder).permissions() & (fs::perms::group_all | fs::perms::others_all), fs::perms::none);

  auto bad = (*repo)->BeginUpload("bad", "bad.gltf", 1 << 20);
  ASSERT_TRUE(bad.ok());
  const Status long_name = (*bad)->Append(std::string(300, 'a') + ".bin", "x");
  EXPECT_EQ(long_name.code(), absl::StatusCode::kInvalidArgument) << long_name;
  EXPECT_NE(long_name.message().find("chunk.file"), std::string::npos) << long_name;
  ASSERT_TRUE((*bad)->Append("a/x.bin", "x").ok());
  const Status clash = (*bad)->Append("a", "y");
  EXPECT_EQ(clash.code(), absl::StatusCode::kInvalidArgument) << clash;
  EXPECT_NE(clash.message().find("chunk.file"), std::string::npos) << clash;
}

}  // namespace
}  // namespace visq::core
