// visq list --fleet, visq stats --fleet: every replica asked directly, in
// parallel, and their answers put side by side and added up.
#include "fleet.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <sys/socket.h>

#include <algorithm>
#include <cstdio>
#include <map>
#include <set>
#include <thread>

#include <fmt/format.h>
#include <nlohmann/json.hpp>

namespace visq::cli {
namespace {

// Every address NAME[:PORT] resolves to, as HOST:PORT ([V6]:PORT).
StatusOr<std::vector<std::string>> Resolve(const std::string& entry) {
  std::string name = entry, port = "50051";
  if (const size_t colon = entry.rfind(':'); colon != std::string::npos) {
    name = entry.substr(0, colon);
    port = entry.substr(colon + 1);
  }
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* found = nullptr;
  if (const int error = ::getaddrinfo(name.c_str(), port.c_str(), &hints, &found); error != 0)
    return absl::NotFoundError(fmt::format("--fleet-dns: cannot resolve {}: {}", entry, ::gai_strerror(error)));
  std::vector<std::string> out;
  for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
    char text[INET6_ADDRSTRLEN] = {};
    if (a->ai_family == AF_INET) {
      ::inet_ntop(AF_INET, &reinterpret_cast<const sockaddr_in*>(a->ai_addr)->sin_addr, text, sizeof(text));
      out.push_back(fmt::format("{}:{}", text, port));
    } else if (a->ai_family == AF_INET6) {
      ::inet_ntop(AF_INET6, &reinterpret_cast<const sockaddr_in6*>(a->ai_addr)->sin6_addr, text, sizeof(text));
      out.push_back(fmt::format("[{}]:{}", text, port));
    }
  }
  ::freeaddrinfo(found);
  return out;
}

StatusOr<std::vector<std::string>> Addresses(const FleetFlags& fleet) {
  std::vector<std::string> out;
  auto add = [&out](const std::string& address) {
    if (std::find(out.begin(), out.end(), address) == out.end()) out.push_back(address);
  };
  for (const auto& address : fleet.addresses) {
    if (auto checked = client::WithDefaultPort(address); !checked.ok())
      return absl::InvalidArgumentError(fmt::format("--fleet: {}", checked.status().message()));
    add(address);
  }
  for (const auto& entry : fleet.dns) {
    VISQ_ASSIGN_OR_RETURN(const auto resolved, Resolve(entry));
    for (const auto& address : resolved) add(address);
  }
  return out;
}

// What one address answered.
struct Answer {
  std::string address;
  Status status;
  v1::ServerStats stats;
  v1::ListScenesResponse scenes;
};

// Asks every address at once: a fleet view takes as long as its slowest
// replica, not their sum.
std::vector<Answer> Ask(const std::vector<std::string>& addresses, const GlobalFlags& flags, bool list) {
  std::vector<Answer> answers(addresses.size());
  std::vector<std::thread> threads;
  for (size_t i = 0; i < addresses.size(); ++i)
    threads.emplace_back([&, i] {
      Answer& a = answers[i];
      a.address = addresses[i];
      GlobalFlags one = flags;
      one.server = a.address;
      client::Client client = MakeClient(one);
      // GetStats names the replica (its server id) for both views.
      auto stats = client.GetStats();
      a.status = stats.status();
      if (!stats.ok()) return;
      a.stats = *std::move(stats);
      if (!list) return;
      auto scenes = client.ListScenes();
      a.status = scenes.status();
      if (scenes.ok()) a.scenes = *std::move(scenes);
    });
  for (auto& t : threads) t.join();
  return answers;
}

// A replica: its first answer, and every address that gave its server id.
struct Replica {
  const Answer* answer;
  std::vector<std::string> addresses;
};

struct Fleet {
  std::vector<Replica> replicas;       // answered, in the order first asked
  std::vector<const Answer*> failures;  // addresses that did not answer
};

Fleet Group(const std::vector<Answer>& answers) {
  Fleet fleet;
  for (const Answer& a : answers) {
    if (!a.status.ok()) {
      fleet.failures.push_back(&a);
      continue;
    }
    auto same = std::find_if(fleet.replicas.begin(), fleet.replicas.end(),
                             [&](const Replica& r) { return r.answer->stats.server_id() == a.stats.server_id(); });
    if (same == fleet.replicas.end()) fleet.replicas.push_back({&a, {a.address}});
    else same->addresses.push_back(a.address);
  }
  return fleet;
}

std::string Join(const std::vector<std::string>& parts) {
  std::string out;
  for (const auto& p : parts) out += (out.empty() ? "" : ", ") + p;
  return out;
}

nlohmann::ordered_json Failure(const Answer& a) {
  return {{"address", a.address},
          {"error", {{"code", absl::StatusCodeToString(a.status.code())}, {"message", std::string(a.status.message())}}}};
}

// Says on stderr which addresses did not answer; the command then exits 1.
void ReportFailures(const Fleet& fleet, Cli& cli) {
  std::fflush(stdout);  // the table or JSON first, then what is missing from it
  for (const Answer* a : fleet.failures)
    fmt::print(stderr, "visq: replica {}: {}: {}\n", a->address, absl::StatusCodeToString(a->status.code()),
               a->status.message());
  if (!fleet.failures.empty()) cli.exit_code = 1;
}

}  // namespace

void AddFleetFlags(CLI::App* command, FleetFlags& fleet) {
  command->add_option("--fleet", fleet.addresses, "Ask every replica: HOST[:PORT],... (each as --server takes it)")
      ->delimiter(',');
  command->add_option("--fleet-dns", fleet.dns,
                      "Ask every address NAME[:PORT] resolves to (a headless Service: visq-replicas.visq.svc)")
      ->delimiter(',');
}

Status RunFleetStats(const FleetFlags& flags, Cli& cli) {
  VISQ_ASSIGN_OR_RETURN(const auto addresses, Addresses(flags));
  const std::vector<Answer> answers = Ask(addresses, cli.flags, /*list=*/false);
  const Fleet fleet = Group(answers);

  // The fleet's sums; per RPC, calls and errors add up, the mean is
  // weighted by calls, the maximum is the largest (percentiles do not add:
  // each replica's are in its own row of `visq stats --server`).
  struct Method {
    uint64_t calls = 0, errors = 0;
    double total_ms = 0, max_ms = 0;
  };
  std::map<std::string, Method> methods;
  uint64_t scenes = 0, cpu = 0, gpu = 0, calls = 0, errors = 0, gpu_queue = 0, worker_queue = 0, lost = 0;
  std::set<std::string> versions;
  for (const Replica& r : fleet.replicas) {
    const auto& s = r.answer->stats;
    scenes += s.scenes_resident();
    cpu += s.scene_memory().cpu_bytes();
    gpu += s.scene_memory().gpu_bytes();
    gpu_queue += s.gpu_queue_depth();
    worker_queue += s.worker_queue_depth();
    lost += s.gpu_contexts_lost();
    versions.insert(fmt::format("{} ({})", s.server_version(), s.build_commit()));
    for (const auto& m : s.methods()) {
      Method& f = methods[m.method()];
      f.calls += m.calls();
      f.errors += m.errors();
      f.total_ms += m.mean_ms() * static_cast<double>(m.calls());
      f.max_ms = std::max(f.max_ms, m.max_ms());
      calls += m.calls();
      errors += m.errors();
    }
  }

  if (cli.flags.json) {
    auto out = nlohmann::ordered_json::object();
    out["replicas"] = nlohmann::ordered_json::array();
    for (const Replica& r : fleet.replicas)
      out["replicas"].push_back({{"server_id", r.answer->stats.server_id()},
                                 {"addresses", r.addresses},
                                 {"stats", nlohmann::ordered_json::parse(ToJson(r.answer->stats))}});
    for (const Answer* a : fleet.failures) out["replicas"].push_back(Failure(*a));
    auto rpcs = nlohmann::ordered_json::array();
    for (const auto& [name, m] : methods)
      rpcs.push_back({{"method", name},
                      {"calls", m.calls},
                      {"errors", m.errors},
                      {"mean_ms", m.calls ? m.total_ms / static_cast<double>(m.calls) : 0.0},
                      {"max_ms", m.max_ms}});
    out["totals"] = {{"replicas", fleet.replicas.size()},
                     {"unreachable", fleet.failures.size()},
                     {"versions", versions},
                     {"scenes_resident", scenes},
                     {"scene_memory", {{"cpu_bytes", cpu}, {"gpu_bytes", gpu}}},
                     {"calls", calls},
                     {"errors", errors},
                     {"gpu_queue_depth", gpu_queue},
                     {"worker_queue_depth", worker_queue},
                     {"gpu_contexts_lost", lost},
                     {"methods", rpcs}};
    fmt::print("{}\n", out.dump(2));
    ReportFailures(fleet, cli);
    return absl::OkStatus();
  }

  constexpr auto kRow = "{:<24} {:<24} {:<10} {:>8} {:>6} {:>10} {:>10} {:>8} {:>7} {:>5} {:>6} {:>5}\n";
  fmt::print(kRow, "REPLICA", "ADDRESS", "VERSION", "UP s", "SCENES", "CPU", "GPU", "CALLS", "ERRORS", "GPU Q",
             "WORK Q", "LOST");
  for (const Replica& r : fleet.replicas) {
    const auto& s = r.answer->stats;
    uint64_t c = 0, e = 0;
    for (const auto& m : s.methods()) {
      c += m.calls();
      e += m.errors();
    }
    fmt::print(kRow, s.server_id(), Join(r.addresses), s.server_version(), fmt::format("{:.0f}", s.uptime_s()),
               s.scenes_resident(), Bytes(s.scene_memory().cpu_bytes()), Bytes(s.scene_memory().gpu_bytes()), c, e,
               s.gpu_queue_depth(), s.worker_queue_depth(), s.gpu_contexts_lost());
  }
  for (const Answer* a : fleet.failures)
    fmt::print("{:<24} {:<24} unreachable: {}\n", "-", a->address, absl::StatusCodeToString(a->status.code()));
  const std::string version =
      versions.size() == 1 ? fleet.replicas.front().answer->stats.server_version() : versions.empty() ? "-" : "MIXED";
  fmt::print(kRow, "TOTAL",
             fmt::format("{} of {} answered", fleet.replicas.size(), fleet.replicas.size() + fleet.failures.size()),
             version, "", scenes, Bytes(cpu), Bytes(gpu), calls, errors, gpu_queue, worker_queue, lost);
  if (versions.size() > 1) fmt::print("versions differ: {}\n", Join({versions.begin(), versions.end()}));
  if (!methods.empty()) {
    fmt::print("\n{:<24} {:>8} {:>7} {:>10} {:>10}\n", "RPC (fleet)", "CALLS", "ERRORS", "MEAN ms", "MAX ms");
    for (const auto& [name, m] : methods)
      fmt::print("{:<24} {:>8} {:>7} {:>10.2f} {:>10.2f}\n", name, m.calls, m.errors,
                 m.calls ? m.total_ms / static_cast<double>(m.calls) : 0.0, m.max_ms);
  }
  ReportFailures(fleet, cli);
  return absl::OkStatus();
}

Status RunFleetList(const FleetFlags& flags, Cli& cli) {
  VISQ_ASSIGN_OR_RETURN(const auto addresses, Addresses(flags));
  const std::vector<Answer> answers = Ask(addresses, cli.flags, /*list=*/true);
  const Fleet fleet = Group(answers);

  // One row per (name, version): replicas holding another version of a
  // scene show as a row of their own, which is what an operator looks for.
  struct Row {
    v1::SceneInfo info;  // the first holder's; memory summed over the holders
    std::vector<std::string> replicas;
  };
  std::map<std::pair<std::string, uint64_t>, Row> rows;
  for (const Replica& r : fleet.replicas)
    for (const auto& scene : r.answer->scenes.scenes()) {
      Row& row = rows[{scene.name(), scene.version()}];
      if (row.replicas.empty()) {
        row.info = scene;
      } else {
        auto* memory = row.info.mutable_memory();
        memory->set_cpu_bytes(memory->cpu_bytes() + scene.memory().cpu_bytes());
        memory->set_gpu_bytes(memory->gpu_bytes() + scene.memory().gpu_bytes());
      }
      row.replicas.push_back(r.answer->stats.server_id());
    }

  if (cli.flags.json) {
    auto out = nlohmann::ordered_json::object();
    out["scenes"] = nlohmann::ordered_json::array();
    for (const auto& [key, row] : rows) {
      auto scene = nlohmann::ordered_json::parse(ToJson(row.info));
      scene["replicas"] = row.replicas;
      out["scenes"].push_back(scene);
    }
    out["replicas"] = nlohmann::ordered_json::array();
    for (const Replica& r : fleet.replicas)
      out["replicas"].push_back({{"server_id", r.answer->stats.server_id()}, {"addresses", r.addresses}});
    for (const Answer* a : fleet.failures) out["replicas"].push_back(Failure(*a));
    fmt::print("{}\n", out.dump(2));
    ReportFailures(fleet, cli);
    return absl::OkStatus();
  }
  fmt::print("{:<32} {:>8} {:>12} {:>12} {:>12}  {}\n", "NAME", "VERSION", "TRIANGLES", "CPU", "GPU", "REPLICAS");
  for (const auto& [key, row] : rows)
    fmt::print("{:<32} {:>8} {:>12} {:>12} {:>12}  {}\n", row.info.name(), row.info.version(),
               row.info.triangle_count(), Bytes(row.info.memory().cpu_bytes()), Bytes(row.info.memory().gpu_bytes()),
               Join(row.replicas));
  fmt::print("{} scene(s) on {} of {} replica(s); CPU and GPU summed over the replicas holding each\n", rows.size(),
             fleet.replicas.size(), fleet.replicas.size() + fleet.failures.size());
  ReportFailures(fleet, cli);
  return absl::OkStatus();
}

}  // namespace visq::cli
