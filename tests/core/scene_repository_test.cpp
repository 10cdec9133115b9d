// The scene repository on a real folder and a real SQLite catalog: names,
// uploads committed or abandoned, replacement, deletion and the blobs it
// frees, versions that never repeat across reopenings, replicas' staging,
// the move of a repository of the layout before the catalog, and the move of
// a SQLite catalog into PostgreSQL (a cluster of the suite's own).
#include "core/scene_repository.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <set>
#include <thread>

#include <gtest/gtest.h>

#include "postgres_cluster.h"
#include "test_support.h"

namespace visq::core {
namespace {

namespace fs = std::filesystem;

std::string ReadFile(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

void WriteFile(const fs::path& path, const std::string& body) {
  fs::create_directories(path.parent_path());
  std::ofstream(path, std::ios::binary) << body;
}

StatusOr<SceneRepository::Stored> Store(SceneRepository& repo, const std::string& name,
                                        const std::map<std::string, std::string>& files, bool replace = true) {
  VISQ_ASSIGN_OR_RETURN(std::unique_ptr<UploadStaging> staging, repo.BeginUpload(name, name + ".gltf", 1 << 20));
  VISQ_RETURN_IF_ERROR(staging->Append(name + ".gltf", files.count("") ? files.at("") : "{}"));
  for (const auto& [file, body] : files)
    if (!file.empty()) VISQ_RETURN_IF_ERROR(staging->Append(file, body));
  return repo.Commit(*staging, replace);
}

StatusOr<SceneRepository::Stored> Store(SceneRepository& repo, const std::string& name, const std::string& body) {
  return Store(repo, name, {{"", body}});
}

// The main file's bytes of the version `name` holds now.
std::string StoredBody(SceneRepository& repo, const std::string& name) {
  auto view = repo.Checkout(name);
  if (!view.ok()) return "(" + std::string(view.status().message()) + ")";
  return ReadFile((*view)->main_file());
}

size_t BlobCount(const fs::path& root) {
  size_t count = 0;
  for (const auto& entry : fs::recursive_directory_iterator(root / ".visq" / "blobs")) count += entry.is_regular_file();
  return count;
}

// What a replica's staging holds, its lock file aside.
size_t StagingEntries(const fs::path& root, const std::string& replica) {
  size_t count = 0;
  for (const auto& entry : fs::directory_iterator(root / ".visq" / "staging" / replica))
    count += entry.path().filename() != ".owner";
  return count;
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
  {
    auto view = (*repo)->Checkout("box");
    ASSERT_TRUE(view.ok()) << view.status();
    EXPECT_EQ((*view)->version(), first->version);
    EXPECT_EQ(ReadFile((*view)->main_file()), "{\"asset\":{\"version\":\"2.0\"}}");
  }

  auto second = Store(**repo, "box", "{\"asset\":{\"version\":\"2.0\"},\"scenes\":[]}");
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_GT(second->version, first->version);
  EXPECT_EQ((*repo)->List(), std::vector<std::string>{"box"});
  EXPECT_NE(StoredBody(**repo, "box").find("scenes"), std::string::npos) << "the replacement is what is stored";
  EXPECT_EQ(BlobCount((*repo)->root()), 1u) << "the replaced version's blob is collected";

  EXPECT_TRUE((*repo)->Remove("box").ok());
  EXPECT_TRUE((*repo)->List().empty());
  EXPECT_FALSE((*repo)->Contains("box"));
  EXPECT_EQ((*repo)->Checkout("box").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ((*repo)->Remove("box").code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(BlobCount((*repo)->root()), 0u);
  EXPECT_EQ(StagingEntries((*repo)->root(), (*repo)->replica_id()), 0u) << "loads and uploads leave no staging";
}

// A blob is named by the SHA-256 of its bytes; two scenes that hold the
// same file share it, and deleting one keeps what the other names.
TEST(SceneRepository, BlobsAreContentAddressedSharedAndCollectedWhenNoVersionNamesThem) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path());
  ASSERT_TRUE(repo.ok()) << repo.status();
  const std::string shared(1000, 's');
  ASSERT_TRUE(Store(**repo, "a", {{"", "{\"a\":1}"}, {"data/shared.bin", shared}}).ok());
  ASSERT_TRUE(Store(**repo, "b", {{"", "{\"b\":1}"}, {"other/path.bin", shared}}).ok());
  EXPECT_EQ(BlobCount(dir.path()), 3u) << "two main files and one shared buffer";
  Sha256 hash;
  hash.Update(shared);
  const std::string digest = hash.HexDigest();
  const fs::path blob = dir.path() / ".visq" / "blobs" / digest.substr(0, 2) / digest;
  ASSERT_TRUE(fs::is_regular_file(blob));
  EXPECT_EQ(ReadFile(blob), shared);

  ASSERT_TRUE((*repo)->Remove("a").ok());
  EXPECT_TRUE(fs::is_regular_file(blob)) << "b still names it";
  EXPECT_EQ(BlobCount(dir.path()), 2u);
  auto view = (*repo)->Checkout("b");
  ASSERT_TRUE(view.ok()) << view.status();
  EXPECT_EQ(ReadFile((*view)->dir() / "other/path.bin"), shared);
  ASSERT_TRUE((*repo)->Remove("b").ok());
  EXPECT_FALSE(fs::exists(blob));
  // The view links the bytes: a load that had checked out b reads them still.
  EXPECT_EQ(ReadFile((*view)->dir() / "other/path.bin"), shared);
}

// A start collects the blobs no version names (a commit that failed after
// publishing them, a crash between a delete and its collection), however
// many, and keeps every one a version names.
TEST(SceneRepository, AStartCollectsEveryBlobNoVersionNames) {
  testing::ScratchDir dir;
  {
    auto repo = SceneRepository::Open(dir.path());
    ASSERT_TRUE(repo.ok()) << repo.status();
    for (int i = 0; i < 10; ++i)
      ASSERT_TRUE(Store(**repo, "s" + std::to_string(i), {{"", "{" + std::to_string(i) + "}"}, {"b.bin", "b"}}).ok());
  }
  EXPECT_EQ(BlobCount(dir.path()), 11u) << "ten main files and one shared buffer";
  for (int i = 0; i < 30; ++i) {
    Sha256 hash;
    hash.Update("orphan " + std::to_string(i));
    const std::string digest = hash.HexDigest();
    WriteFile(dir.path() / ".visq" / "blobs" / digest.substr(0, 2) / digest, "orphan " + std::to_string(i));
  }
  EXPECT_EQ(BlobCount(dir.path()), 41u);
  auto repo = SceneRepository::Open(dir.path());
  ASSERT_TRUE(repo.ok()) << repo.status();
  EXPECT_EQ(BlobCount(dir.path()), 11u);
  for (int i = 0; i < 10; ++i) EXPECT_EQ(StoredBody(**repo, "s" + std::to_string(i)), "{" + std::to_string(i) + "}");
}

TEST(SceneRepository, AnAbandonedUploadLeavesNothing) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path() / "repo");
  ASSERT_TRUE(repo.ok()) << repo.status();
  {
    auto staging = (*repo)->BeginUpload("half", "half.gltf", 1 << 20);
    ASSERT_TRUE(staging.ok()) << staging.status();
    ASSERT_TRUE((*staging)->Append("half.gltf", "{").ok());
    EXPECT_EQ(StagingEntries((*repo)->root(), (*repo)->replica_id()), 1u);
  }  // never committed
  EXPECT_TRUE((*repo)->List().empty());
  EXPECT_FALSE((*repo)->Contains("half"));
  EXPECT_EQ(StagingEntries((*repo)->root(), (*repo)->replica_id()), 0u);
  EXPECT_EQ(BlobCount((*repo)->root()), 0u);
}

TEST(SceneRepository, UploadFilesStayInsideTheirFolderAndUnderTheirCap) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path() / "repo");
  ASSERT_TRUE(repo.ok()) << repo.status();
  auto staging = (*repo)->BeginUpload("s", "s.gltf", 8);
  ASSERT_TRUE(staging.ok()) << staging.status();
  EXPECT_EQ((*staging)->Append("../escape.bin", "x").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*staging)->Append("/etc/passwd", "x").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*staging)->Append(".visq/x", "x").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(fs::exists(dir.path() / "escape.bin"));
  EXPECT_TRUE((*staging)->Append("s.gltf", "12345678").ok());
  EXPECT_EQ((*staging)->Append("s.gltf", "9").code(), absl::StatusCode::kResourceExhausted);
  for (const char* bad : {"../x.gltf", "x.txt", ""})
    EXPECT_EQ((*repo)->BeginUpload("s", bad, 8).status().code(), absl::StatusCode::kInvalidArgument) << bad;
  EXPECT_EQ((*repo)->BeginUpload("../s", "s.gltf", 8).status().code(), absl::StatusCode::kInvalidArgument);
}

// A main file no chunk carried is the client's mistake, named; nothing is
// stored.
TEST(SceneRepository, ACommitWithoutItsMainFileStoresNothing) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path());
  ASSERT_TRUE(repo.ok());
  auto staging = (*repo)->BeginUpload("s", "s.gltf", 1 << 20);
  ASSERT_TRUE(staging.ok());
  ASSERT_TRUE((*staging)->Append("other.bin", "x").ok());
  const auto committed = (*repo)->Commit(**staging, false);
  EXPECT_EQ(committed.status().code(), absl::StatusCode::kInvalidArgument) << committed.status();
  EXPECT_NE(committed.status().message().find("upload_main_file"), std::string::npos) << committed.status();
  EXPECT_TRUE((*repo)->List().empty());
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
    auto stored = Store(**repo, "s" + std::to_string(opening), "{}");
    ASSERT_TRUE(stored.ok()) << stored.status();
    EXPECT_TRUE(seen.insert(stored->version).second) << "version " << stored->version << " repeated";
  }
}

// Two replicas creating the same new name: one stores, the other is told the
// name exists; neither upload is silently lost.
TEST(SceneRepository, ConcurrentCreatesOfOneNameStoreOneAndRefuseTheOther) {
  testing::ScratchDir dir;
  auto first = SceneRepository::Open({dir.path(), "", "first"});
  auto second = SceneRepository::Open({dir.path(), "", "second"});
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
  EXPECT_EQ(StoredBody(**second, "same"), "first") << "the acknowledged upload is the one stored";
  // With replace, the second takes its place.
  auto c = (*second)->BeginUpload("same", "same.gltf", 1 << 20);
  ASSERT_TRUE(c.ok());
  ASSERT_TRUE((*c)->Append("same.gltf", "third").ok());
  EXPECT_TRUE((*second)->Commit(**c, /*replace=*/true).ok());
  EXPECT_EQ(StoredBody(**first, "same"), "third");
}

// A replica's start removes its own staging (left by its last run) and that
// of replicas no longer running, never an upload in flight on a live one.
TEST(SceneRepository, AStartKeepsAnotherReplicasUploadInFlight) {
  testing::ScratchDir dir;
  auto running = SceneRepository::Open({dir.path(), "", "running"});
  ASSERT_TRUE(running.ok());
  auto in_flight = (*running)->BeginUpload("busy", "busy.gltf", 1 << 20);
  ASSERT_TRUE(in_flight.ok());
  ASSERT_TRUE((*in_flight)->Append("busy.gltf", "half").ok());
  // What a crashed run of "starting" left, and a replica long gone.
  const fs::path own_crash = dir.path() / ".visq" / "staging" / "starting" / "upload-0000000000000001";
  const fs::path gone_crash = dir.path() / ".visq" / "staging" / "gone" / "upload-0000000000000002";
  WriteFile(own_crash / "x.gltf", "x");
  WriteFile(gone_crash / "y.gltf", "y");

  auto starting = SceneRepository::Open({dir.path(), "", "starting"});  // another replica starts
  ASSERT_TRUE(starting.ok()) << starting.status();
  EXPECT_FALSE(fs::exists(own_crash)) << "its own leftovers go";
  EXPECT_FALSE(fs::exists(gone_crash)) << "a replica that is not running has none in flight";
  EXPECT_TRUE(fs::exists((*in_flight)->dir())) << "a live upload's folder stays";
  ASSERT_TRUE((*in_flight)->Append("busy.gltf", ", then done").ok());
  EXPECT_TRUE((*running)->Commit(**in_flight, /*replace=*/false).ok());
  EXPECT_EQ(StoredBody(**starting, "busy"), "half, then done");

  // A replica name a live server holds is refused, naming the flag.
  auto twin = SceneRepository::Open({dir.path(), "", "running"});
  EXPECT_EQ(twin.status().code(), absl::StatusCode::kFailedPrecondition) << twin.status();
  EXPECT_NE(twin.status().message().find("--replica-id"), std::string::npos) << twin.status();
}

// Every input naming a place is checked: a bad flag is refused by name.
TEST(SceneRepository, BadFlagsAreNamed) {
  testing::ScratchDir dir;
  auto bad_id = SceneRepository::Open({dir.path(), "", "../evil"});
  EXPECT_EQ(bad_id.status().code(), absl::StatusCode::kInvalidArgument) << bad_id.status();
  EXPECT_NE(bad_id.status().message().find("--replica-id"), std::string::npos) << bad_id.status();
  auto bad_catalog = SceneRepository::Open({dir.path(), "mysql://root:hunter2@db/x", ""});
  EXPECT_EQ(bad_catalog.status().code(), absl::StatusCode::kInvalidArgument) << bad_catalog.status();
  EXPECT_NE(bad_catalog.status().message().find("--catalog"), std::string::npos) << bad_catalog.status();
  EXPECT_EQ(bad_catalog.status().message().find("hunter2"), std::string::npos) << "a password is never repeated";
  // A repository whose catalog is in PostgreSQL is not opened as SQLite's:
  // the replica would serve an empty catalog. (SQLite's moves to PostgreSQL:
  // SqliteToPostgres below.)
  ASSERT_TRUE(SceneRepository::Open(dir.path()).ok());
  WriteFile(dir.path() / ".visq" / "catalog-kind", "postgresql\n");
  auto other = SceneRepository::Open(dir.path());
  EXPECT_EQ(other.status().code(), absl::StatusCode::kFailedPrecondition) << other.status();
  EXPECT_NE(other.status().message().find("--catalog"), std::string::npos) << other.status();
}

// Each version's files are linked out of the blobs it was committed with:
// a (scene, version) names one content, and versions never name two.
TEST(SceneRepository, AVersionNamesOneContent) {
  testing::ScratchDir dir;
  auto repo = SceneRepository::Open(dir.path());
  ASSERT_TRUE(repo.ok());
  std::map<uint64_t, std::string> content_of;
  for (int i = 0; i < 6; ++i) {
    const std::string body = "body " + std::to_string(i % 2);
    auto stored = Store(**repo, "s", {{"", body}, {"b.bin", body + " bin"}});
    ASSERT_TRUE(stored.ok()) << stored.status();
    EXPECT_TRUE(content_of.emplace(stored->version, body).second) << "a version number given twice";
    auto view = (*repo)->Checkout("s");
    ASSERT_TRUE(view.ok());
    EXPECT_EQ((*view)->version(), stored->version);
    EXPECT_EQ(ReadFile((*view)->main_file()), body);
    EXPECT_EQ(ReadFile((*view)->dir() / "b.bin"), body + " bin");
  }
}

// An upload's blobs and folders are its owner's alone, as is the catalog; a
// name past what a file system holds, and a file where another chunk made a
// folder, are the client's mistakes, named as such.
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
  for (const auto& entry : fs::recursive_directory_iterator(dir.path() / ".visq")) {
    EXPECT_EQ(fs::status(entry.path()).permissions() & (fs::perms::group_all | fs::perms::others_all), fs::perms::none)
        << entry.path();
    ++checked;
  }
  EXPECT_GE(checked, 6u) << "the blobs, their folders, the catalog and the staging";

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

// A repository of the layout before the catalog (upload folders with their
// markers, a counter file, a hand-placed .glb, a .gltf with its buffer
// beside it, an interrupted upload's staging) is moved over on its first
// start: every scene in the catalog with its bytes, uploads keeping their
// versions, numbers going on past the old counter, the old entries gone.
// A second start changes nothing.
TEST(SceneRepository, AnOldRepositoryIsMovedOverOnFirstStart) {
  testing::ScratchDir dir;
  const fs::path root = dir.path();
  WriteFile(root / "uploaded" / "scene.gltf", "{\"uploaded\":1}");
  WriteFile(root / "uploaded" / "data" / "x.bin", "uploaded bytes");
  WriteFile(root / "uploaded" / ".visq-main", "scene.gltf\n");
  WriteFile(root / "uploaded" / ".visq-version", "7\n");
  WriteFile(root / ".visq-version-counter", "9\n");
  WriteFile(root / "by_hand" / "only.glb", "glb bytes");
  WriteFile(root / "plain.gltf", R"({"buffers":[{"uri":"plain%20data.bin","byteLength":3},{"uri":"data:,x"}]})");
  WriteFile(root / "plain data.bin", "abc");
  WriteFile(root / "stray.bin", "not a scene");
  WriteFile(root / ".staging-old-0000000000000001" / "half.gltf", "{");
  WriteFile(root / "two" / "a.gltf", "{}");
  WriteFile(root / "two" / "b.gltf", "{}");  // no main marker, two glTFs: not a scene

  std::map<std::string, uint64_t> versions;
  {
    auto repo = SceneRepository::Open(root);
    ASSERT_TRUE(repo.ok()) << repo.status();
    EXPECT_EQ((*repo)->List(), (std::vector<std::string>{"by_hand", "plain", "uploaded"}));
    for (const std::string& name : (*repo)->List()) {
      auto view = (*repo)->Checkout(name);
      ASSERT_TRUE(view.ok()) << view.status();
      versions[name] = (*view)->version();
    }
    EXPECT_EQ(versions["uploaded"], 7u) << "an upload keeps the version it was committed with";
    EXPECT_GT(versions["by_hand"], 9u) << "new numbers go on past the old counter";
    EXPECT_GT(versions["plain"], 9u);
    EXPECT_NE(versions["by_hand"], versions["plain"]);
    auto uploaded = (*repo)->Checkout("uploaded");
    ASSERT_TRUE(uploaded.ok());
    EXPECT_EQ(ReadFile((*uploaded)->main_file()), "{\"uploaded\":1}");
    EXPECT_EQ(ReadFile((*uploaded)->dir() / "data" / "x.bin"), "uploaded bytes");
    EXPECT_FALSE(fs::exists((*uploaded)->dir() / ".visq-main")) << "the old markers are not scene files";
    auto plain = (*repo)->Checkout("plain");
    ASSERT_TRUE(plain.ok());
    EXPECT_EQ(ReadFile((*plain)->dir() / "plain data.bin"), "abc");
    auto next = (*repo)->NextVersion();
    ASSERT_TRUE(next.ok());
    EXPECT_GT(*next, 9u);
  }
  for (const char* gone : {"uploaded", "by_hand", "plain.gltf", "plain data.bin", ".staging-old-0000000000000001"})
    EXPECT_FALSE(fs::exists(root / gone)) << gone;
  EXPECT_TRUE(fs::exists(root / "stray.bin")) << "what is no scene is left alone";
  EXPECT_TRUE(fs::exists(root / "two" / "a.gltf")) << "what cannot be imported is left where it is";

  // A crash after the import's commit and before the removal leaves the
  // entry in place: the next start finds it unchanged and stores nothing.
  WriteFile(root / "uploaded" / "scene.gltf", "{\"uploaded\":1}");
  WriteFile(root / "uploaded" / "data" / "x.bin", "uploaded bytes");
  WriteFile(root / "uploaded" / ".visq-main", "scene.gltf\n");
  {
    auto repo = SceneRepository::Open(root);
    ASSERT_TRUE(repo.ok()) << repo.status();
    for (const auto& [name, version] : versions) {
      auto view = (*repo)->Checkout(name);
      ASSERT_TRUE(view.ok()) << view.status();
      EXPECT_EQ((*view)->version(), version) << name << ": a second start changes nothing";
    }
    EXPECT_FALSE(fs::exists(root / "uploaded"));
    // A scene placed by hand while the server runs is taken in on first use,
    // as the newest version of its name.
    WriteFile(root / "uploaded.glb", "newer bytes");
    EXPECT_TRUE((*repo)->Contains("uploaded"));
    WriteFile(root / "late.glb", "late bytes");
    EXPECT_TRUE((*repo)->Contains("late"));
    EXPECT_EQ(StoredBody(**repo, "late"), "late bytes");
    EXPECT_FALSE(fs::exists(root / "late.glb"));
  }
  {
    auto repo = SceneRepository::Open(root);
    ASSERT_TRUE(repo.ok()) << repo.status();
    EXPECT_EQ(StoredBody(**repo, "uploaded"), "newer bytes") << "placed by hand: the newest version at the next start";
    auto view = (*repo)->Checkout("uploaded");
    ASSERT_TRUE(view.ok());
    EXPECT_GT((*view)->version(), versions["plain"]);
  }
}

// A repository's catalog moved from SQLite to PostgreSQL at the first start
// with a PostgreSQL URI: one cluster for the suite, a database per test.
class SqliteToPostgres : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!testing::PostgresCluster::Installed()) return;
    std::string why;
    cluster_ = testing::PostgresCluster::Start(&why).release();
    if (cluster_ == nullptr) start_failure_ = new std::string(why);
  }
  static void TearDownTestSuite() {
    delete cluster_;
    cluster_ = nullptr;
  }
  void SetUp() override {
    if (!testing::PostgresCluster::Installed())
      GTEST_SKIP() << "PostgreSQL is not installed (no /usr/lib/postgresql/<major>/bin/initdb and pg_ctl; "
                      "deploy/install-deps.sh installs it): the move to PostgreSQL is not tried";
    ASSERT_NE(cluster_, nullptr) << (start_failure_ ? *start_failure_ : "");
  }
  // A database of the test's own.
  std::string Database(const std::string& name) {
    EXPECT_TRUE(cluster_->CreateDatabase(name));
    return cluster_->Uri(name);
  }

  static testing::PostgresCluster* cluster_;
  static std::string* start_failure_;
};
testing::PostgresCluster* SqliteToPostgres::cluster_ = nullptr;
std::string* SqliteToPostgres::start_failure_ = nullptr;

// What a repository serves: each scene's version and its files' bytes.
using ServedScenes = std::map<std::string, std::pair<uint64_t, std::map<std::string, std::string>>>;
ServedScenes Served(SceneRepository& repo) {
  ServedScenes served;
  for (const std::string& name : repo.List()) {
    auto view = repo.Checkout(name);
    if (!view.ok()) {
      ADD_FAILURE() << name << ": " << view.status();
      continue;
    }
    auto& [version, files] = served[name];
    version = (*view)->version();
    for (const auto& entry : fs::recursive_directory_iterator((*view)->dir()))
      if (entry.is_regular_file()) files[fs::relative(entry.path(), (*view)->dir()).string()] = ReadFile(entry.path());
  }
  return served;
}

// Several scenes (one with a buffer in a folder, one replaced, one deleted)
// stored through SQLite are served by PostgreSQL with the same names,
// versions and bytes; new versions take numbers past SQLite's; the SQLite
// file stays, and a server started with sqlite again is refused.
TEST_F(SqliteToPostgres, AMovedRepositoryServesTheSameScenesAndNumbersGoOn) {
  testing::ScratchDir dir;
  const fs::path root = dir.path();
  uint64_t sqlite_counter = 0;
  ServedScenes before;
  {
    auto repo = SceneRepository::Open(root);
    ASSERT_TRUE(repo.ok()) << repo.status();
    ASSERT_TRUE(Store(**repo, "hall", {{"", "{\"hall\":1}"}, {"data/hall.bin", "hall bytes"}}).ok());
    ASSERT_TRUE(Store(**repo, "replaced", "first").ok());
    ASSERT_TRUE(Store(**repo, "gone", "deleted").ok());
    ASSERT_TRUE(Store(**repo, "replaced", "second").ok());
    ASSERT_TRUE((*repo)->Remove("gone").ok());
    ASSERT_TRUE(Store(**repo, "last", "{}").ok());
    auto counter = (*repo)->NextVersion();  // an edit's number: the counter is past every scene's
    ASSERT_TRUE(counter.ok());
    sqlite_counter = *counter;
    before = Served(**repo);
  }
  ASSERT_EQ(before.size(), 3u);
  ASSERT_EQ(before["hall"].second["data/hall.bin"], "hall bytes");

  const std::string uri = Database("moved");
  {
    auto repo = SceneRepository::Open({root, uri, ""});
    ASSERT_TRUE(repo.ok()) << repo.status();
    EXPECT_EQ((*repo)->DescribeCatalog().rfind("postgresql", 0), 0u) << (*repo)->DescribeCatalog();
    EXPECT_EQ(Served(**repo), before) << "the same names, versions and bytes";
    auto stored = Store(**repo, "replaced", "third");
    ASSERT_TRUE(stored.ok()) << stored.status();
    EXPECT_GT(stored->version, sqlite_counter) << "a new version's number is past every number SQLite gave";
    auto created = Store(**repo, "new", "{}");
    ASSERT_TRUE(created.ok()) << created.status();
    EXPECT_GT(created->version, sqlite_counter);
  }
  EXPECT_TRUE(fs::exists(root / ".visq" / "catalog.sqlite3")) << "the SQLite file stays";
  {
    // A second start finds the move made and changes nothing.
    auto repo = SceneRepository::Open({root, uri, ""});
    ASSERT_TRUE(repo.ok()) << repo.status();
    EXPECT_EQ((*repo)->List(), (std::vector<std::string>{"hall", "last", "new", "replaced"}));
    EXPECT_EQ(StoredBody(**repo, "replaced"), "third");
    EXPECT_EQ(Served(**repo)["hall"], before["hall"]);
  }
  // Back to SQLite is refused: its catalog no longer says what there is.
  auto back = SceneRepository::Open(root);
  EXPECT_EQ(back.status().code(), absl::StatusCode::kFailedPrecondition) << back.status();
  EXPECT_NE(back.status().message().find("--catalog"), std::string::npos) << back.status();
}

// A start killed (SIGKILL) at any moment of its move leaves PostgreSQL's
// catalog with every scene or none (and the kind unrecorded until it has
// them all); the next start finishes the move. The kills come every few
// milliseconds, from before the move to after it.
TEST_F(SqliteToPostgres, AStartKilledDuringItsMoveLeavesAllOrNothing) {
  testing::ScratchDir dir;
  const fs::path root = dir.path();
  ASSERT_TRUE(SceneRepository::Open(root).ok());
  // Rows enough that the move's transaction takes tens of milliseconds,
  // written straight into the SQLite catalog (the blobs they name are not
  // needed: this test reads the catalogs, not the scenes).
  std::vector<CatalogVersion> sqlite_scenes;
  {
    auto db = OpenSqliteCatalog((root / ".visq" / "catalog.sqlite3").string());
    ASSERT_TRUE(db.ok()) << db.status();
    auto catalog = SceneCatalog::Open(*std::move(db));
    ASSERT_TRUE(catalog.ok()) << catalog.status();
    for (int i = 0; i < 6; ++i) {
      SceneCatalog::CommitRequest request{.name = "s" + std::to_string(i), .main_file = "s.gltf"};
      for (int f = 0; f < 60; ++f)
        request.files.push_back(CatalogFile{"f" + std::to_string(f) + ".bin", std::string(63, 'a') + char('a' + i),
                                            static_cast<uint64_t>(f)});
      ASSERT_TRUE((*catalog)->Commit(request, [](const CatalogFile&) { return absl::OkStatus(); }).ok());
    }
    auto contents = (*catalog)->ReadAll();
    ASSERT_TRUE(contents.ok()) << contents.status();
    sqlite_scenes = contents->scenes;
  }
  const std::string uri = Database("killed");
  auto in_postgres = [&]() -> std::vector<CatalogVersion> {
    auto db = OpenPostgresCatalog(uri);
    EXPECT_TRUE(db.ok()) << db.status();
    if (!db.ok()) return {};
    auto catalog = SceneCatalog::Open(*std::move(db));
    EXPECT_TRUE(catalog.ok()) << catalog.status();
    auto contents = catalog.ok() ? (*catalog)->ReadAll() : catalog.status();
    EXPECT_TRUE(contents.ok()) << contents.status();
    return contents.ok() ? contents->scenes : std::vector<CatalogVersion>{};
  };
  const fs::path kind_file = root / ".visq" / "catalog-kind";
  int left_nothing = 0;
  for (int delay_ms = 1; delay_ms < 4000 && ReadFile(kind_file) == "sqlite\n"; delay_ms += 2 + delay_ms / 3) {
    const pid_t child = ::fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      auto repo = SceneRepository::Open({root, uri, "killed"});
      ::_exit(repo.ok() ? 0 : 1);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms));
    ::kill(child, SIGKILL);
    int wait_status = 0;
    ASSERT_EQ(::waitpid(child, &wait_status, 0), child);
    const std::vector<CatalogVersion> moved = in_postgres();
    EXPECT_TRUE(moved.empty() || moved == sqlite_scenes)
        << "killed after " << delay_ms << " ms: " << moved.size() << " of " << sqlite_scenes.size() << " scenes";
    EXPECT_TRUE(ReadFile(kind_file) == "sqlite\n" || moved == sqlite_scenes) << "the kind is recorded after the move";
    left_nothing += moved.empty();
  }
  EXPECT_GT(left_nothing, 0) << "no kill came before the move's commit";
  auto finished = SceneRepository::Open({root, uri, ""});
  ASSERT_TRUE(finished.ok()) << finished.status();
  EXPECT_EQ(in_postgres(), sqlite_scenes);
}

// Replicas starting together on one SQLite repository and one database move
// it once: the later ones wait for the first's write lock and find its mark
// (a second copy would find the scenes there and be refused).
TEST_F(SqliteToPostgres, ReplicasStartingTogetherMoveItOnce) {
  testing::ScratchDir dir;
  const fs::path root = dir.path();
  ServedScenes before;
  {
    auto repo = SceneRepository::Open(root);
    ASSERT_TRUE(repo.ok()) << repo.status();
    for (int i = 0; i < 6; ++i)
      ASSERT_TRUE(Store(**repo, "s" + std::to_string(i), {{"", "{}"}, {"b.bin", std::to_string(i)}}).ok());
    before = Served(**repo);
  }
  const std::string uri = Database("together");
  constexpr int kReplicas = 3;
  std::vector<StatusOr<std::unique_ptr<SceneRepository>>> opened;
  for (int r = 0; r < kReplicas; ++r) opened.emplace_back(absl::UnknownError("not run"));
  {
    std::vector<std::jthread> starts;
    for (int r = 0; r < kReplicas; ++r)
      starts.emplace_back([&, r] {
        opened[static_cast<size_t>(r)] = SceneRepository::Open({root, uri, "r" + std::to_string(r)});
      });
  }
  for (auto& repo : opened) {
    ASSERT_TRUE(repo.ok()) << repo.status();
    EXPECT_EQ(Served(**repo), before);
  }
  auto stored = Store(**opened[0], "s0", "newer");
  ASSERT_TRUE(stored.ok());
  EXPECT_EQ(StoredBody(**opened[1], "s0"), "newer") << "one catalog for all";
}

// A PostgreSQL catalog that holds another repository's scenes is not taken
// over: the start is refused naming --catalog, and both repositories stay
// as they were.
TEST_F(SqliteToPostgres, AnotherRepositorysCatalogIsRefusedAndLeftAlone) {
  const std::string uri = Database("foreign");
  testing::ScratchDir other_dir;
  uint64_t theirs = 0;
  {
    auto other = SceneRepository::Open({other_dir.path(), uri, ""});
    ASSERT_TRUE(other.ok()) << other.status();
    auto stored = Store(**other, "theirs", "their bytes");
    ASSERT_TRUE(stored.ok());
    theirs = stored->version;
  }
  testing::ScratchDir dir;
  {
    auto repo = SceneRepository::Open(dir.path());
    ASSERT_TRUE(repo.ok()) << repo.status();
    ASSERT_TRUE(Store(**repo, "mine", "my bytes").ok());
  }
  auto refused = SceneRepository::Open({dir.path(), uri, ""});
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition) << refused.status();
  EXPECT_NE(refused.status().message().find("--catalog"), std::string::npos) << refused.status();
  EXPECT_NE(refused.status().message().find("already holds 1 scene"), std::string::npos) << refused.status();
  EXPECT_EQ(refused.status().message().find("postgresql://"), std::string::npos) << "no URI (nor password) repeated";

  auto other = SceneRepository::Open({other_dir.path(), uri, ""});
  ASSERT_TRUE(other.ok()) << other.status();
  EXPECT_EQ((*other)->List(), std::vector<std::string>{"theirs"});
  auto view = (*other)->Checkout("theirs");
  ASSERT_TRUE(view.ok());
  EXPECT_EQ((*view)->version(), theirs);
  {
    auto mine = SceneRepository::Open(dir.path());
    ASSERT_TRUE(mine.ok()) << mine.status() << ": the repository is still SQLite's";
    EXPECT_EQ((*mine)->List(), std::vector<std::string>{"mine"});
    EXPECT_EQ(StoredBody(**mine, "mine"), "my bytes");
  }
  // A database of its own takes it (the cluster's first, empty: no
  // other test of the suite uses it, and createdb costs a few 100 ms).
  auto moved = SceneRepository::Open({dir.path(), cluster_->Uri(), ""});
  ASSERT_TRUE(moved.ok()) << moved.status();
  EXPECT_EQ(StoredBody(**moved, "mine"), "my bytes");
}

}  // namespace
}  // namespace visq::core
