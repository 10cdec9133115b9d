// visq: the command-line client. Each subcommand is a thin wrapper over
// visq::client::Client (cli_common.h); --json prints the response message as
// JSON. The subcommand groups live in *_commands.cpp.
#include <algorithm>
#include <cstring>
#include <optional>
#include <string>
#include <vector>

#include <fmt/format.h>

#include "cli_common.h"
#include "common/version.h"

namespace {

// Global options that take a value, so the scan below can skip it.
constexpr const char* kValueOptions[] = {"--server", "--timeout", "--token-file", "--tls-ca", "--tls-cert", "--tls-key"};

// The first word that is no option nor an option's value: the subcommand.
std::optional<std::string> FirstWord(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--") return std::nullopt;
    if (arg.rfind('-', 0) == 0) {
      const bool takes_value = std::any_of(std::begin(kValueOptions), std::end(kValueOptions),
                                           [&](const char* option) { return arg == option; });
      if (takes_value) ++i;
      continue;
    }
    return arg;
  }
  return std::nullopt;
}

size_t EditDistance(const std::string& a, const std::string& b) {
  std::vector<size_t> row(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    size_t diagonal = row[0];
    row[0] = i;
    for (size_t j = 1; j <= b.size(); ++j) {
      const size_t above = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = above;
    }
  }
  return row[b.size()];
}

}  // namespace

int main(int argc, char** argv) {
  visq::cli::Cli cli;
  CLI::App& app = cli.app;
  app.set_version_flag("--version", std::string("visq ") + visq::kVersion + " (" + visq::kBuildCommit + ")");
  app.require_subcommand(1);
  app.footer("Global flags (--server, --json, --timeout, --token-file, --tls-*) go before or after the subcommand.");
  visq::cli::AddGlobalFlags(cli);
  visq::cli::AddSceneCommands(cli);
  visq::cli::AddSamplingCommands(cli);
  visq::cli::AddLightCommands(cli);
  visq::cli::AddVoxelCommands(cli);
  visq::cli::AddObscuranceCommands(cli);

  // CLI11 calls an unknown word "not expected" or asks for a subcommand;
  // name it as what it is, with the nearest subcommand.
  if (const auto word = FirstWord(argc, argv)) {
    std::vector<std::string> names;
    for (const CLI::App* command : app.get_subcommands([](CLI::App*) { return true; }))
      names.push_back(command->get_name());
    if (std::find(names.begin(), names.end(), *word) == names.end()) {
      std::string nearest;
      size_t best = 3;  // a suggestion only within two edits
      for (const auto& name : names)
        if (const size_t d = EditDistance(*word, name); d < best) {
          best = d;
          nearest = name;
        }
      std::string all;
      for (const auto& name : names) all += (all.empty() ? "" : ", ") + name;
      fmt::print(stderr, "visq: unknown subcommand '{}'{}; the subcommands are {}\n", *word,
                 nearest.empty() ? "" : fmt::format(" (did you mean '{}'?)", nearest), all);
      return 2;
    }
  }
  CLI11_PARSE(app, argc, argv);
  return cli.exit_code;
}
