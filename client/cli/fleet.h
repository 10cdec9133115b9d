// The fleet view: `visq list` and `visq stats` over every replica at once.
// Through the router each call reaches one replica of its choosing, so these
// flags name the replicas themselves: a list of addresses, or a DNS name
// whose every address is a replica (a headless Service).
#pragma once

#include <string>
#include <vector>

#include "cli_common.h"

namespace visq::cli {

struct FleetFlags {
  std::vector<std::string> addresses;  // --fleet HOST[:PORT],...
  std::vector<std::string> dns;        // --fleet-dns NAME[:PORT],...
  bool set() const { return !addresses.empty() || !dns.empty(); }
};
void AddFleetFlags(CLI::App* command, FleetFlags& fleet);

// One row per replica (a replica reached at two addresses counts once, by
// its server id) and the fleet's totals; a replica that does not answer is
// a row saying why, and the exit status is 1.
Status RunFleetStats(const FleetFlags& fleet, Cli& cli);
// Every scene resident anywhere, one row per name and version, with the
// replicas that hold it.
Status RunFleetList(const FleetFlags& fleet, Cli& cli);

}  // namespace visq::cli
