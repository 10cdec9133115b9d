// The catalog in SQLite: the embedded default, for one machine (several
// server processes on it may share the file; WAL needs them on one host).
#include <sqlite3.h>

#include <absl/strings/str_split.h>
#include <absl/strings/strip.h>

#include "core/catalog_db.h"

namespace visq::core {
namespace {

struct CloseDb {
  void operator()(sqlite3* db) const { sqlite3_close_v2(db); }
};
struct FinalizeStatement {
  void operator()(sqlite3_stmt* statement) const { sqlite3_finalize(statement); }
};

// A busy database (another process held the write lock past the timeout)
// is worth retrying; a full disk is the caller's to act on; a file the
// server may not write is the operator's.
Status SqliteError(sqlite3* db, int rc, absl::string_view what) {
  const std::string message =
      absl::StrCat("scene catalog (sqlite): ", what, ": ", db != nullptr ? sqlite3_errmsg(db) : sqlite3_errstr(rc));
  switch (rc & 0xff) {
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
      return absl::UnavailableError(message);
    case SQLITE_FULL:
      return absl::ResourceExhaustedError(message);
    case SQLITE_READONLY:
    case SQLITE_PERM:
    case SQLITE_CANTOPEN:
    case SQLITE_AUTH:
      return absl::FailedPreconditionError(absl::StrCat(message, " (the scene repository, --scene-repo, is not writable)"));
    default:
      return absl::InternalError(message);
  }
}

class SqliteCatalog final : public CatalogDb {
 public:
  SqliteCatalog(std::unique_ptr<sqlite3, CloseDb> db, std::string file) : db_(std::move(db)), file_(std::move(file)) {}

  StatusOr<std::vector<CatalogRow>> Query(const std::string& sql, const std::vector<std::string>& params) override {
    sqlite3_stmt* raw = nullptr;
    int rc = sqlite3_prepare_v2(db_.get(), sql.c_str(), static_cast<int>(sql.size()), &raw, nullptr);
    std::unique_ptr<sqlite3_stmt, FinalizeStatement> statement(raw);
    if (rc != SQLITE_OK) return SqliteError(db_.get(), rc, "prepare");
    for (size_t i = 0; i < params.size(); ++i) {
      rc = sqlite3_bind_text(statement.get(), static_cast<int>(i + 1), params[i].data(),
                             static_cast<int>(params[i].size()), SQLITE_TRANSIENT);
      if (rc != SQLITE_OK) return SqliteError(db_.get(), rc, "bind");
    }
    std::vector<CatalogRow> rows;
    while ((rc = sqlite3_step(statement.get())) == SQLITE_ROW) {
      const int columns = sqlite3_column_count(statement.get());
      CatalogRow row(static_cast<size_t>(columns));
      for (int c = 0; c < columns; ++c) {
        if (sqlite3_column_type(statement.get(), c) == SQLITE_NULL) continue;
        const auto* text = reinterpret_cast<const char*>(sqlite3_column_text(statement.get(), c));
        row[static_cast<size_t>(c)] = std::string(text, static_cast<size_t>(sqlite3_column_bytes(statement.get(), c)));
      }
      rows.push_back(std::move(row));
    }
    if (rc != SQLITE_DONE) return SqliteError(db_.get(), rc, "step");
    return rows;
  }

  // IMMEDIATE takes the write lock now, waiting (busy timeout) for another
  // process's writer: a read-then-write transaction never finds that the
  // data it read changed under it.
  Status BeginWrite() override { return Exec("BEGIN IMMEDIATE"); }
  Status Commit() override {
    Status committed = Exec("COMMIT");
    if (!committed.ok()) Rollback();  // SQLite keeps a transaction whose COMMIT failed open
    return committed;
  }
  void Rollback() override {
    if (!sqlite3_get_autocommit(db_.get())) sqlite3_exec(db_.get(), "ROLLBACK", nullptr, nullptr, nullptr);
  }

  Status CreateSchema(const std::vector<std::string>& schema) override {
    VISQ_RETURN_IF_ERROR(BeginWrite());
    for (const std::string& statement : schema) {
      Status done = Exec(statement);
      if (!done.ok()) {
        Rollback();
        return done;
      }
    }
    return Commit();
  }

  std::string Describe() const override { return absl::StrCat("sqlite ", file_); }
  std::string Kind() const override { return "sqlite"; }

 private:
  Status Exec(const std::string& sql) {
    const int rc = sqlite3_exec(db_.get(), sql.c_str(), nullptr, nullptr, nullptr);
    if (rc != SQLITE_OK) return SqliteError(db_.get(), rc, sql.substr(0, sql.find(' ')));
    return absl::OkStatus();
  }

  std::unique_ptr<sqlite3, CloseDb> db_;
  std::string file_;
};

}  // namespace

StatusOr<std::unique_ptr<CatalogDb>> OpenSqliteCatalog(const std::string& file) {
  sqlite3* raw = nullptr;
  // NOMUTEX: SceneCatalog serializes every use of the connection itself.
  const int rc = sqlite3_open_v2(file.c_str(), &raw,
                                 SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_NOMUTEX, nullptr);
  std::unique_ptr<sqlite3, CloseDb> db(raw);
  if (rc != SQLITE_OK) return SqliteError(db.get(), rc, "open");
  // Another process's write lock is waited for, not failed on: replicas
  // commit one at a time.
  sqlite3_busy_timeout(db.get(), 60000);
  sqlite3_extended_result_codes(db.get(), 1);
  auto catalog = std::make_unique<SqliteCatalog>(std::move(db), file);
  // WAL: readers (loads) never wait for a writer. synchronous FULL: a
  // commit that returned is on the disk, so an acknowledged upload survives
  // a power cut as well as a kill -9.
  for (const char* pragma : {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=FULL", "PRAGMA foreign_keys=ON"})
    VISQ_RETURN_IF_ERROR(catalog->Query(pragma, {}).status());
  return std::unique_ptr<CatalogDb>(std::move(catalog));
}

}  // namespace visq::core
