// The catalog in PostgreSQL, through libpq: for replicas on several
// machines that share one repository (blobs on a shared file system, the
// catalog in one database they all reach).
#include <libpq-fe.h>

#include <absl/strings/match.h>

#include "core/catalog_db.h"

namespace visq::core {
namespace {

struct FinishConnection {
  void operator()(PGconn* connection) const { PQfinish(connection); }
};
struct ClearResult {
  void operator()(PGresult* result) const { PQclear(result); }
};
using Result = std::unique_ptr<PGresult, ClearResult>;

// Any key for the advisory lock under which the schema is made: CREATE
// TABLE IF NOT EXISTS run by two sessions at once can still collide.
constexpr const char* kSchemaLockKey = "7604211459";

// SQLSTATE classes: 08 connection, 57 the server shutting down (worth
// retrying once it is back), 53 out of resources, 40 a transaction rolled
// back by the server (try again), 42501 a role without the grants (the
// operator's to fix).
Status PostgresError(const PGresult* result, PGconn* connection, absl::string_view what) {
  const char* state = result != nullptr ? PQresultErrorField(result, PG_DIAG_SQLSTATE) : nullptr;
  std::string text = result != nullptr ? PQresultErrorMessage(result) : "";
  if (text.empty() && connection != nullptr) text = PQerrorMessage(connection);
  while (!text.empty() && (text.back() == '\n' || text.back() == ' ')) text.pop_back();
  const std::string message = absl::StrCat("scene catalog (postgresql): ", what, ": ", text);
  const std::string code = state != nullptr ? state : "";
  if (code.empty() || absl::StartsWith(code, "08") || absl::StartsWith(code, "57"))
    return absl::UnavailableError(absl::StrCat(message, " (is the database of --catalog reachable?)"));
  if (absl::StartsWith(code, "53")) return absl::ResourceExhaustedError(message);
  if (absl::StartsWith(code, "40")) return absl::AbortedError(message);
  if (code == "42501") return absl::FailedPreconditionError(absl::StrCat(message, " (the role of --catalog lacks a grant)"));
  return absl::InternalError(message);
}

// '?' placeholders (the SQL both databases share) as PostgreSQL's $1, $2...
// The catalog's statements hold no '?' in a literal.
std::string NumberPlaceholders(const std::string& sql) {
  std::string out;
  int n = 0;
  for (char c : sql) {
    if (c == '?')
      absl::StrAppend(&out, "$", ++n);
    else
      out.push_back(c);
  }
  return out;
}

class PostgresCatalog final : public CatalogDb {
 public:
  explicit PostgresCatalog(std::unique_ptr<PGconn, FinishConnection> connection)
      : connection_(std::move(connection)) {}

  StatusOr<std::vector<CatalogRow>> Query(const std::string& sql, const std::vector<std::string>& params) override {
    VISQ_RETURN_IF_ERROR(Reconnect());
    std::vector<const char*> values;
    values.reserve(params.size());
    for (const std::string& p : params) values.push_back(p.c_str());
    Result result(PQexecParams(connection_.get(), NumberPlaceholders(sql).c_str(), static_cast<int>(values.size()),
                               nullptr, values.data(), nullptr, nullptr, /*resultFormat=text*/ 0));
    const ExecStatusType status = result ? PQresultStatus(result.get()) : PGRES_FATAL_ERROR;
    if (status != PGRES_TUPLES_OK && status != PGRES_COMMAND_OK)
      return PostgresError(result.get(), connection_.get(), sql.substr(0, sql.find(' ')));
    std::vector<CatalogRow> rows(static_cast<size_t>(PQntuples(result.get())));
    const int columns = PQnfields(result.get());
    for (size_t r = 0; r < rows.size(); ++r) {
      rows[r].resize(static_cast<size_t>(columns));
      for (int c = 0; c < columns; ++c)
        if (!PQgetisnull(result.get(), static_cast<int>(r), c))
          rows[r][static_cast<size_t>(c)] =
              std::string(PQgetvalue(result.get(), static_cast<int>(r), c),
                          static_cast<size_t>(PQgetlength(result.get(), static_cast<int>(r), c)));
    }
    return rows;
  }

  // READ COMMITTED: each statement sees what was committed before it ran,
  // so once SceneCatalog has locked the counter row (and waited for the
  // writer holding it) its reads see that writer's commit.
  Status BeginWrite() override {
    Status begun = Query("BEGIN ISOLATION LEVEL READ COMMITTED", {}).status();
    in_transaction_ = begun.ok();
    return begun;
  }
  Status Commit() override {
    in_transaction_ = false;
    return Query("COMMIT", {}).status();
  }
  void Rollback() override {
    in_transaction_ = false;
    if (PQstatus(connection_.get()) == CONNECTION_OK) Result(PQexec(connection_.get(), "ROLLBACK"));
  }

  Status CreateSchema(const std::vector<std::string>& schema) override {
    VISQ_RETURN_IF_ERROR(BeginWrite());
    Status done = Query(absl::StrCat("SELECT pg_advisory_xact_lock(", kSchemaLockKey, ")"), {}).status();
    for (size_t i = 0; done.ok() && i < schema.size(); ++i) done = Query(schema[i], {}).status();
    if (!done.ok()) {
      Rollback();
      return done;
    }
    return Commit();
  }

  std::string Describe() const override {
    return absl::StrCat("postgresql ", PQhost(connection_.get()), ":", PQport(connection_.get()), "/",
                        PQdb(connection_.get()));
  }
  std::string Kind() const override { return "postgresql"; }

 private:
  // A connection the database dropped (a restart, a failover) is made again
  // before the next statement, but never inside a transaction: that one is
  // gone, and its caller is told.
  Status Reconnect() {
    if (PQstatus(connection_.get()) == CONNECTION_OK) return absl::OkStatus();
    if (in_transaction_) return PostgresError(nullptr, connection_.get(), "connection lost in a transaction");
    PQreset(connection_.get());
    if (PQstatus(connection_.get()) != CONNECTION_OK) return PostgresError(nullptr, connection_.get(), "reconnect");
    return absl::OkStatus();
  }

  std::unique_ptr<PGconn, FinishConnection> connection_;
  bool in_transaction_ = false;
};

void DropNotice(void*, const char*) {}  // "relation already exists, skipping" and the like

}  // namespace

StatusOr<std::unique_ptr<CatalogDb>> OpenPostgresCatalog(const std::string& conninfo) {
  std::unique_ptr<PGconn, FinishConnection> connection(PQconnectdb(conninfo.c_str()));
  if (connection == nullptr) return absl::ResourceExhaustedError("scene catalog (postgresql): out of memory");
  if (PQstatus(connection.get()) != CONNECTION_OK) {
    // libpq's message names the host and the reason, never the password.
    return PostgresError(nullptr, connection.get(), "connect (--catalog)");
  }
  PQsetNoticeProcessor(connection.get(), DropNotice, nullptr);
  auto catalog = std::make_unique<PostgresCatalog>(std::move(connection));
  // Notices ("relation already exists, skipping") are not worth a line.
  VISQ_RETURN_IF_ERROR(catalog->Query("SET client_min_messages TO warning", {}).status());
  return std::unique_ptr<CatalogDb>(std::move(catalog));
}

}  // namespace visq::core
