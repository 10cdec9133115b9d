// The scene catalog: name -> current version -> the files of that version,
// each a blob named by its hash. One schema in SQLite or PostgreSQL
// (CatalogDb); create, replace and delete are transactions, and version
// numbers come from one counter row in the database, so a number is handed
// out once, whichever replica asks. Thread-safe (one connection, used by one
// thread at a time).
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "core/catalog_db.h"

namespace visq::core {

struct CatalogFile {
  std::string path;  // relative to the scene's folder, as uploaded
  std::string blob;  // its SHA-256
  uint64_t size = 0;
  bool operator==(const CatalogFile&) const = default;
};

struct CatalogVersion {
  std::string name;
  uint64_t version = 0;
  std::string main_file;
  std::vector<CatalogFile> files;  // sorted by path
  bool operator==(const CatalogVersion&) const = default;
};

class SceneCatalog {
 public:
  // Makes the schema if absent; refuses a schema newer than this server's.
  [[nodiscard]] static StatusOr<std::unique_ptr<SceneCatalog>> Open(std::unique_ptr<CatalogDb> db);

  std::string Describe() const { return db_->Describe(); }
  std::string Kind() const { return db_->Kind(); }

  [[nodiscard]] StatusOr<std::vector<std::string>> Names();
  // The current version of `name`, read in one statement (one snapshot):
  // nullopt when the catalog has no such scene.
  [[nodiscard]] StatusOr<std::optional<CatalogVersion>> Current(absl::string_view name);
  // A version number no one was given before (edits take these).
  [[nodiscard]] StatusOr<uint64_t> NextVersion();
  // Raises the counter to at least `floor` (a migrated repository's).
  [[nodiscard]] Status RaiseCounter(uint64_t floor);

  struct CommitRequest {
    std::string name;
    std::string main_file;
    std::vector<CatalogFile> files;
    bool replace = false;
    // An import: nothing is stored when the current version holds exactly
    // these files (a hand-placed scene met again after a crash, or by a
    // second replica).
    bool unless_unchanged = false;
    // A migrated scene keeps the number it was committed with, when no
    // version in the catalog has it; 0: a new number.
    uint64_t keep_version = 0;
  };
  struct Committed {
    uint64_t version = 0;
    bool stored = true;                 // false: unless_unchanged found it current
    std::vector<std::string> released;  // blobs of the version it replaced
  };
  // In one write transaction: ALREADY_EXISTS when `name` exists and not
  // `replace`; else `publish` makes each file's blob present (it runs under
  // the write lock, so no collection removes a blob between its check and
  // the rows that name it), a version number is taken, and the rows of the
  // new version replace those of the old.
  [[nodiscard]] StatusOr<Committed> Commit(const CommitRequest& request,
                                           const std::function<Status(const CatalogFile&)>& publish);
  // Deletes `name` (NOT_FOUND if absent); returns the blobs it named.
  [[nodiscard]] StatusOr<std::vector<std::string>> Remove(absl::string_view name);
  // Under the write lock, calls `remove` for each of `candidates` that no
  // version names. Collection and Commit's publish never interleave, so a
  // blob that a commit found present stays until a later delete.
  [[nodiscard]] Status CollectBlobs(const std::vector<std::string>& candidates,
                                    const std::function<Status(const std::string&)>& remove);
  // Meta values (the migration's mark).
  [[nodiscard]] StatusOr<std::optional<std::string>> Meta(absl::string_view key);
  [[nodiscard]] Status SetMeta(absl::string_view key, absl::string_view value);
  // The value of `key`, set to `value` first if absent (whichever replica
  // sets it first, every one reads the same).
  [[nodiscard]] StatusOr<std::string> MetaOrInit(absl::string_view key, absl::string_view value);

  // What a catalog holds: every scene's current version, the counter and
  // the meta values other than the schema's.
  struct Contents {
    std::vector<CatalogVersion> scenes;  // sorted by name
    uint64_t counter = 0;
    std::map<std::string, std::string> meta;
  };
  // Read under the write lock, so that no writer commits between its
  // statements: one consistent state.
  [[nodiscard]] StatusOr<Contents> ReadAll();
  // Takes over another catalog's contents (a move from SQLite to
  // PostgreSQL) in one write transaction, so that a crash leaves all of it
  // or none. `mark` = `mark_value` in the meta records it: a catalog already
  // marked so is left as it is (another replica moved it first, or a start
  // that crashed before it recorded the move elsewhere); one holding scenes
  // (another repository's) is left untouched and kOccupied; else every scene
  // keeps its number and files, the counter rises to at least `from`'s, and
  // the meta values are copied.
  struct TakenOver {
    enum class Outcome { kMoved, kAlreadyMoved, kOccupied } outcome = Outcome::kMoved;
    size_t scenes = 0;  // moved, or (kOccupied) held already
    size_t files = 0;   // moved
  };
  [[nodiscard]] StatusOr<TakenOver> TakeOver(const Contents& from, absl::string_view mark,
                                             absl::string_view mark_value);

 private:
  explicit SceneCatalog(std::unique_ptr<CatalogDb> db) : db_(std::move(db)) {}
  // Takes the catalog's write lock inside an open write transaction.
  Status LockForWrite();
  // Statements of an open write transaction, the mutex held.
  Status InsertVersionRows(const std::string& version, const std::string& name, const std::string& main_file,
                           const std::vector<CatalogFile>& files);
  Status RaiseCounterLocked(uint64_t floor);
  Status SetMetaLocked(absl::string_view key, absl::string_view value);

  std::mutex mutex_;
  std::unique_ptr<CatalogDb> db_;
};

}  // namespace visq::core
