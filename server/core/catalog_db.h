// The database under the scene catalog: SQLite (embedded, one machine) or
// PostgreSQL (replicas on several machines). The catalog's SQL is written
// once, in the subset both speak ('?' placeholders, ON CONFLICT, RETURNING);
// this interface only runs it. Not thread-safe: SceneCatalog serializes its
// use.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/status.h"

namespace visq::core {

// One result row; a NULL is nullopt.
using CatalogRow = std::vector<std::optional<std::string>>;

class CatalogDb {
 public:
  virtual ~CatalogDb() = default;
  // Runs one statement with text parameters (the database converts them to
  // the columns' types) and returns its rows.
  [[nodiscard]] virtual StatusOr<std::vector<CatalogRow>> Query(const std::string& sql,
                                                                const std::vector<std::string>& params = {}) = 0;
  // A transaction that writes. Writers of every replica take the catalog's
  // one write lock at its start (SQLite: BEGIN IMMEDIATE; PostgreSQL: the
  // counter row, locked by SceneCatalog's first statement), so their reads
  // see everything committed before and nobody commits in between.
  [[nodiscard]] virtual Status BeginWrite() = 0;
  [[nodiscard]] virtual Status Commit() = 0;
  virtual void Rollback() = 0;
  // Runs `schema` (statements separated by ';') once, however many replicas
  // start at the same moment.
  [[nodiscard]] virtual Status CreateSchema(const std::vector<std::string>& schema) = 0;
  // "sqlite <file>" or "postgresql <host>:<port>/<database>", for the log
  // (never a password).
  virtual std::string Describe() const = 0;
  // "sqlite" or "postgresql": the repository remembers which one holds its
  // catalog, so that a replica started with the other finds out.
  virtual std::string Kind() const = 0;
};

// SQLite in `file` (made if absent): WAL, synchronous FULL, waits up to
// 60 s for another process's write lock.
[[nodiscard]] StatusOr<std::unique_ptr<CatalogDb>> OpenSqliteCatalog(const std::string& file);
// PostgreSQL through libpq: `conninfo` is a postgresql:// URI or a
// key=value string; a password may come from it, PGPASSWORD or ~/.pgpass.
[[nodiscard]] StatusOr<std::unique_ptr<CatalogDb>> OpenPostgresCatalog(const std::string& conninfo);

// Rolls back a transaction that was not committed when it goes out of scope.
class CatalogTransaction {
 public:
  explicit CatalogTransaction(CatalogDb& db) : db_(db) {}
  ~CatalogTransaction() {
    if (open_) db_.Rollback();
  }
  CatalogTransaction(const CatalogTransaction&) = delete;
  CatalogTransaction& operator=(const CatalogTransaction&) = delete;
  [[nodiscard]] Status BeginWrite() {
    VISQ_RETURN_IF_ERROR(db_.BeginWrite());
    open_ = true;
    return absl::OkStatus();
  }
  [[nodiscard]] Status Commit() {
    open_ = false;
    return db_.Commit();
  }

 private:
  CatalogDb& db_;
  bool open_ = false;
};

}  // namespace visq::core
