// Replicas sharing one repository (issue 45 §1): three real visq-server
// processes on loopback over one --scene-repo race creates, replaces,
// deletes and first-use loads of a few names, while one of them at a time
// is killed (SIGKILL) at random moments (every 0.15-0.6 s, at least 15
// times) and started again. Then a fresh
// server checks what the repository holds.
//
// Every upload is unique and says which it is twice: its .bin puts the
// triangle at x = id, its .gltf moves the node to y = id. A scene loaded
// with its bounds' minimum at (a, b) with a != b is a mixture of two
// uploads. Asserted: no mixture, no version that names two uploads (or an
// upload of another name), no acknowledged upload lost (the final state is
// that upload, a later one, or explained by a delete that may have come
// after it; a create never replaced an acknowledged upload that no delete
// removed first), no staging left, no blob that no version names.
//
// The catalog is SQLite (the default) in one test, and a PostgreSQL cluster
// of the test's own in the other (skipped where PostgreSQL is not installed).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <mutex>
#include <random>
#include <thread>

#include <gtest/gtest.h>

#include "postgres_cluster.h"
#include "repository_files.h"
#include "server_process.h"
#include "test_support.h"
#include "visq_client.h"

namespace visq {
namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
using client::Client;
using testing::ScratchDir;
using testing::ServerProcess;

constexpr int kReplicas = 3;
constexpr int kWorkers = 4;
constexpr int kMinOperations = 2000;
constexpr size_t kMinKills = 15;
const std::vector<std::string> kNames = {"alpha", "beta", "gamma", "delta", "epsilon"};

// Upload `id`: one triangle at x = id (the .bin), its node moved to y = id
// (the .gltf).
fs::path WriteUpload(const fs::path& folder, int id) {
  fs::create_directories(folder);
  const float x = static_cast<float>(id);
  const float positions[9] = {x, 0, 0, x + 1, 0, 0, x, 1, 0};
  const uint16_t indices[4] = {0, 1, 2, 0};
  std::string bin(sizeof(positions) + sizeof(indices), '\0');
  std::memcpy(bin.data(), positions, sizeof(positions));
  std::memcpy(bin.data() + sizeof(positions), indices, sizeof(indices));
  std::ofstream(folder / "scene.bin", std::ios::binary) << bin;
  const std::string y = std::to_string(id);
  std::ofstream(folder / "scene.gltf")
      << R"({"asset":{"version":"2.0"},"scenes":[{"nodes":[0]}],"scene":0,"nodes":[{"mesh":0,"translation":[0,)" << y
      << R"(,0]}],"meshes":[{"primitives":[{"attributes":{"POSITION":0},"indices":1}]}],
  "buffers":[{"uri":"scene.bin","byteLength":44}],
  "bufferViews":[{"buffer":0,"byteOffset":0,"byteLength":36},{"buffer":0,"byteOffset":36,"byteLength":6}],
  "accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[100000,100000,0]},
               {"bufferView":1,"componentType":5123,"count":3,"type":"SCALAR"}]})";
  return folder / "scene.gltf";
}

// Which upload a scene's answer holds: (from the .bin, from the .gltf).
std::pair<int, int> UploadOf(const v1::SceneInfo& info) {
  return {static_cast<int>(std::lround(info.bounds_min().x())), static_cast<int>(std::lround(info.bounds_min().y()))};
}

enum class Kind { kCreate, kReplace, kDelete, kLoad };

struct Event {
  Kind kind;
  std::string name;
  int id = -1;  // the upload sent (creates and replaces)
  Clock::time_point start, end;
  absl::StatusCode code = absl::StatusCode::kUnknown;
  uint64_t version = 0;
  std::pair<int, int> held{-1, -1};  // what the answer's scene holds (OK uploads and loads)
};

// A replica slot: its server (restarted after each kill) under a lock.
struct Slot {
  std::mutex mutex;
  std::unique_ptr<ServerProcess> server;
  std::string address;
};

struct RaceResult {
  size_t operations = 0, acknowledged_uploads = 0, deletes = 0, loads = 0, kills = 0;
  double seconds = 0;
};

class ReplicaRace {
 public:
  ReplicaRace(const fs::path& repo, std::vector<std::string> catalog_args)
      : repo_(repo), catalog_args_(std::move(catalog_args)) {}

  std::unique_ptr<ServerProcess> StartReplica(int slot) const {
    std::vector<std::string> args = {"--no-preload", "--replica-id", "r" + std::to_string(slot), "--server-id",
                                     "r" + std::to_string(slot)};
    args.insert(args.end(), catalog_args_.begin(), catalog_args_.end());
    return ServerProcess::Start({repo_, args});
  }

  RaceResult Run() {
    RaceResult result;
    const auto begin = Clock::now();
    for (int s = 0; s < kReplicas; ++s) {
      slots_[s].server = StartReplica(s);
      if (slots_[s].server == nullptr) return result;
      slots_[s].address = slots_[s].server->address();
    }
    std::atomic<bool> stop{false};
    std::vector<std::thread> workers;
    for (int w = 0; w < kWorkers; ++w) workers.emplace_back([&, w] { Work(w, stop); });
    // The killer: one replica at a time, at random moments, started again.
    std::mt19937 rng(12345);
    const auto give_up = begin + std::chrono::seconds(90);
    while ((operations_.load() < kMinOperations || result.kills < kMinKills) && Clock::now() < give_up) {
      std::this_thread::sleep_for(std::chrono::milliseconds(std::uniform_int_distribution<int>(150, 600)(rng)));
      const int s = std::uniform_int_distribution<int>(0, kReplicas - 1)(rng);
      std::unique_ptr<ServerProcess> killed;
      {
        std::lock_guard lock(slots_[s].mutex);
        killed = std::move(slots_[s].server);
        slots_[s].address.clear();
      }
      killed->Kill();
      ++result.kills;
      auto restarted = StartReplica(s);
      if (restarted == nullptr) break;
      std::lock_guard lock(slots_[s].mutex);
      slots_[s].address = restarted->address();
      slots_[s].server = std::move(restarted);
    }
    stop = true;
    for (std::thread& t : workers) t.join();
    // A last crash of everyone: what the repository holds must still hold.
    for (Slot& slot : slots_) slot.server->Kill();
    result.seconds = std::chrono::duration<double>(Clock::now() - begin).count();
    for (const Event& e : events_) {
      ++result.operations;
      const bool ok = e.code == absl::StatusCode::kOk;
      result.acknowledged_uploads += ok && (e.kind == Kind::kCreate || e.kind == Kind::kReplace);
      result.deletes += ok && e.kind == Kind::kDelete;
      result.loads += ok && e.kind == Kind::kLoad;
    }
    return result;
  }

  // Checks the repository with a fresh server; each finding is a failure.
  void Verify() {
    auto server = ServerProcess::Start({repo_, [&] {
                                          std::vector<std::string> args = {"--no-preload", "--replica-id", "verify"};
                                          args.insert(args.end(), catalog_args_.begin(), catalog_args_.end());
                                          return args;
                                        }()});
    ASSERT_NE(server, nullptr);
    EXPECT_EQ(testing::StagingEntries(repo_), 0) << "staging left by killed replicas after a start";
    Client client({.address = server->address(), .deadline = std::chrono::seconds(30)});
    std::map<std::string, Event> final_state;  // absent: not stored
    for (const std::string& name : kNames) {
      Event e{Kind::kLoad, name};
      auto loaded = client.LoadFromRepository(name, true);
      if (loaded.ok()) {
        e.code = absl::StatusCode::kOk;
        e.version = loaded->version();
        e.held = UploadOf(*loaded);
        final_state[name] = e;
        events_.push_back(e);
      } else {
        EXPECT_EQ(loaded.status().code(), absl::StatusCode::kNotFound) << name << ": " << loaded.status();
      }
    }
    size_t blob_files = 0;
    for (const auto& entry : fs::recursive_directory_iterator(repo_ / ".visq" / "blobs")) blob_files += entry.is_regular_file();
    EXPECT_EQ(blob_files, 2 * final_state.size()) << "blobs no version names are collected at a start";

    // Mixtures, and versions naming two uploads (or another name's).
    size_t mixtures = 0, two_contents = 0, checked = 0;
    std::map<uint64_t, std::pair<std::string, int>> upload_of_version;
    for (const Event& e : events_) {
      if (e.code != absl::StatusCode::kOk || e.kind == Kind::kDelete) continue;
      ++checked;
      if (e.held.first != e.held.second || (e.id >= 0 && e.held.first != e.id)) {
        ++mixtures;
        ADD_FAILURE() << e.name << " v" << e.version << " holds .bin of " << e.held.first << " and .gltf of "
                      << e.held.second << (e.id >= 0 ? ", sent " + std::to_string(e.id) : "");
        continue;
      }
      const auto sent = upload_names_.find(e.held.first);
      const std::string name_of_upload = sent == upload_names_.end() ? "(never sent)" : sent->second;
      auto [it, fresh] = upload_of_version.emplace(e.version, std::make_pair(e.name, e.held.first));
      if (!fresh && it->second != std::make_pair(e.name, e.held.first)) {
        ++two_contents;
        ADD_FAILURE() << "v" << e.version << " names " << it->second.first << "#" << it->second.second << " and "
                      << e.name << "#" << e.held.first;
      }
      if (name_of_upload != e.name) {
        ++two_contents;
        ADD_FAILURE() << e.name << " v" << e.version << " holds upload " << e.held.first << " of " << name_of_upload;
      }
    }
    EXPECT_EQ(mixtures, 0u) << "of " << checked << " scenes answered";
    EXPECT_EQ(two_contents, 0u) << "of " << upload_of_version.size() << " versions seen";

    // Acknowledged uploads lost: the final version of the name is older (or
    // the name is gone), and no delete of it that may have come after the
    // upload explains why. Versions follow the order of commits.
    size_t lost = 0;
    for (const Event& u : events_) {
      if (u.code != absl::StatusCode::kOk || (u.kind != Kind::kCreate && u.kind != Kind::kReplace)) continue;
      auto f = final_state.find(u.name);
      if (f != final_state.end() && f->second.version >= u.version) continue;
      const bool explained = std::any_of(events_.begin(), events_.end(), [&](const Event& d) {
        return d.kind == Kind::kDelete && d.name == u.name && d.code != absl::StatusCode::kNotFound && d.end > u.start;
      });
      if (!explained) {
        ++lost;
        ADD_FAILURE() << u.name << " upload " << u.id << " (v" << u.version << ") acknowledged, then lost; final "
                      << (f == final_state.end() ? std::string("absent") : "v" + std::to_string(f->second.version));
      }
    }
    // A create (no replace) stores only where the name is free: every
    // acknowledged upload of that name committed before it (a lower version)
    // was deleted in between, by a delete that may have run then.
    for (const Event& c : events_) {
      if (c.code != absl::StatusCode::kOk || c.kind != Kind::kCreate) continue;
      for (const Event& u : events_) {
        if (u.code != absl::StatusCode::kOk || (u.kind != Kind::kCreate && u.kind != Kind::kReplace) ||
            u.name != c.name || u.version >= c.version)
          continue;
        const bool deleted_between = std::any_of(events_.begin(), events_.end(), [&](const Event& d) {
          return d.kind == Kind::kDelete && d.name == u.name && d.code != absl::StatusCode::kNotFound &&
                 d.end > u.start && d.start < c.end;
        });
        if (!deleted_between) {
          ++lost;
          ADD_FAILURE() << c.name << ": create " << c.id << " (v" << c.version << ") replaced upload " << u.id << " (v"
                        << u.version << "), both acknowledged";
        }
      }
    }
    EXPECT_EQ(lost, 0u) << "acknowledged uploads lost";
  }

 private:
  void Work(int worker, std::atomic<bool>& stop) {
    std::mt19937 rng(1000 + worker);
    ScratchDir files;
    std::map<std::string, std::unique_ptr<Client>> clients;  // by address
    while (!stop) {
      const int s = std::uniform_int_distribution<int>(0, kReplicas - 1)(rng);
      std::string address;
      {
        std::lock_guard lock(slots_[s].mutex);
        address = slots_[s].address;
      }
      if (address.empty()) {  // being restarted
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        continue;
      }
      std::unique_ptr<Client>& client = clients[address];
      if (!client) client = std::make_unique<Client>(client::ClientOptions{.address = address,
                                                                            .deadline = std::chrono::seconds(30)});
      Event e;
      e.name = kNames[std::uniform_int_distribution<size_t>(0, kNames.size() - 1)(rng)];
      const int r = std::uniform_int_distribution<int>(0, 99)(rng);
      e.kind = r < 20 ? Kind::kCreate : r < 50 ? Kind::kReplace : r < 60 ? Kind::kDelete : Kind::kLoad;
      if (e.kind == Kind::kCreate || e.kind == Kind::kReplace) {
        e.id = next_id_++;
        {
          std::lock_guard lock(events_mutex_);
          upload_names_[e.id] = e.name;
        }
        const fs::path gltf = WriteUpload(files.path() / std::to_string(e.id), e.id);
        e.start = Clock::now();
        auto sent = client->UploadScene(gltf, e.name, e.kind == Kind::kReplace);
        e.end = Clock::now();
        e.code = sent.status().code();
        if (sent.ok()) {
          e.version = sent->version();
          e.held = UploadOf(*sent);
        }
      } else if (e.kind == Kind::kDelete) {
        e.start = Clock::now();
        auto deleted = client->UnloadScene(e.name, /*delete_from_repository=*/true);
        e.end = Clock::now();
        e.code = deleted.status().code();
        // A delete whose answer was lost may have happened: counted as such.
        if (e.code == absl::StatusCode::kOk && !deleted->deleted_from_repository()) e.code = absl::StatusCode::kNotFound;
      } else {
        // A first use of the stored scene on this replica (replace: read
        // from the repository whether resident or not).
        e.start = Clock::now();
        auto loaded = client->LoadFromRepository(e.name, /*replace=*/true);
        e.end = Clock::now();
        e.code = loaded.status().code();
        if (loaded.ok()) {
          e.version = loaded->version();
          e.held = UploadOf(*loaded);
        }
      }
      std::lock_guard lock(events_mutex_);
      events_.push_back(e);
      ++operations_;
    }
  }

  fs::path repo_;
  std::vector<std::string> catalog_args_;
  Slot slots_[kReplicas];
  std::atomic<int> next_id_{1};
  std::atomic<size_t> operations_{0};
  std::mutex events_mutex_;
  std::vector<Event> events_;
  std::map<int, std::string> upload_names_;
};

void RunRace(const fs::path& repo, const std::vector<std::string>& catalog_args) {
  ReplicaRace race(repo, catalog_args);
  const RaceResult result = race.Run();
  std::printf("replica race: %zu operations in %.1f s (%zu uploads acknowledged, %zu deletes, %zu loads), %zu kills\n",
              result.operations, result.seconds, result.acknowledged_uploads, result.deletes, result.loads,
              result.kills);
  ::testing::Test::RecordProperty("operations", static_cast<int>(result.operations));
  ::testing::Test::RecordProperty("kills", static_cast<int>(result.kills));
  ASSERT_GE(result.operations, static_cast<size_t>(kMinOperations));
  EXPECT_GE(result.kills, kMinKills);
  EXPECT_GT(result.acknowledged_uploads, 100u);
  EXPECT_GT(result.loads, 100u);
  race.Verify();
}

TEST(ReplicaRace, SqliteCatalogLosesAndMixesNothingUnderKills) {
  ScratchDir repo;
  RunRace(repo.path(), {});
}

TEST(ReplicaRace, PostgresqlCatalogLosesAndMixesNothingUnderKills) {
  if (!testing::PostgresCluster::Installed())
    GTEST_SKIP() << "PostgreSQL is not installed (no /usr/lib/postgresql/<major>/bin/initdb and pg_ctl; "
                    "deploy/install-deps.sh installs it): the PostgreSQL catalog's race is not run";
  std::string why;
  auto cluster = testing::PostgresCluster::Start(&why);
  ASSERT_NE(cluster, nullptr) << why;
  ASSERT_TRUE(cluster->CreateDatabase("visq_race"));
  ScratchDir repo;
  RunRace(repo.path(), {"--catalog", cluster->Uri("visq_race")});
}

}  // namespace
}  // namespace visq
