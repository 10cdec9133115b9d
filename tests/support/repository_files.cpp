#include "repository_files.h"

#include <sqlite3.h>

#include <memory>

namespace visq::testing {
namespace fs = std::filesystem;
namespace {

// The first column of each row of `sql` (one text parameter) in the
// repository's catalog, opened read-only.
std::vector<std::string> Column(const fs::path& repo, const char* sql, const std::string& parameter = "") {
  std::vector<std::string> values;
  sqlite3* raw = nullptr;
  const std::string file = (repo / ".visq" / "catalog.sqlite3").string();
  const int rc = sqlite3_open_v2(file.c_str(), &raw, SQLITE_OPEN_READONLY, nullptr);
  std::unique_ptr<sqlite3, decltype(&sqlite3_close_v2)> db(raw, &sqlite3_close_v2);
  if (rc != SQLITE_OK) return values;
  sqlite3_busy_timeout(db.get(), 10000);
  sqlite3_stmt* statement_raw = nullptr;
  if (sqlite3_prepare_v2(db.get(), sql, -1, &statement_raw, nullptr) != SQLITE_OK) return values;
  std::unique_ptr<sqlite3_stmt, decltype(&sqlite3_finalize)> statement(statement_raw, &sqlite3_finalize);
  if (sqlite3_bind_parameter_count(statement.get()) > 0)
    sqlite3_bind_text(statement.get(), 1, parameter.c_str(), -1, SQLITE_TRANSIENT);
  while (sqlite3_step(statement.get()) == SQLITE_ROW)
    values.emplace_back(reinterpret_cast<const char*>(sqlite3_column_text(statement.get(), 0)));
  return values;
}

}  // namespace

std::vector<std::string> StoredSceneNames(const fs::path& repo) {
  return Column(repo, "SELECT name FROM visq_scenes ORDER BY name");
}

std::vector<std::string> StoredFiles(const fs::path& repo, const std::string& name) {
  return Column(repo,
                "SELECT f.path FROM visq_version_files f JOIN visq_scenes s ON s.version = f.version "
                "WHERE s.name = ? ORDER BY f.path",
                name);
}

int StagingEntries(const fs::path& repo) {
  int count = 0;
  std::error_code ec;
  for (const auto& replica : fs::directory_iterator(repo / ".visq" / "staging", ec))
    for (const auto& entry : fs::directory_iterator(replica.path(), ec)) count += entry.path().filename() != ".owner";
  return count;
}

}  // namespace visq::testing
