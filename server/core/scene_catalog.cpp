#include "core/scene_catalog.h"

#include <absl/strings/numbers.h>

#include <algorithm>
#include <set>

namespace visq::core {
namespace {

constexpr int kSchemaVersion = 1;

// The schema, in the SQL both databases accept. Old versions' rows go when
// they are replaced; the blobs they named go once no version names them.
const std::vector<std::string>& Schema() {
  static const std::vector<std::string> schema = {
      "CREATE TABLE IF NOT EXISTS visq_meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
      // One row; every writer locks it first, so writers of all replicas
      // take turns, and its value is the last version number handed out.
      "CREATE TABLE IF NOT EXISTS visq_counter (id INTEGER PRIMARY KEY, last_version BIGINT NOT NULL)",
      "INSERT INTO visq_counter (id, last_version) VALUES (1, 0) ON CONFLICT (id) DO NOTHING",
      "CREATE TABLE IF NOT EXISTS visq_scenes (name TEXT PRIMARY KEY, version BIGINT NOT NULL UNIQUE)",
      "CREATE TABLE IF NOT EXISTS visq_versions (version BIGINT PRIMARY KEY, name TEXT NOT NULL, "
      "main_file TEXT NOT NULL)",
      "CREATE TABLE IF NOT EXISTS visq_version_files (version BIGINT NOT NULL REFERENCES visq_versions (version) "
      "ON DELETE CASCADE, path TEXT NOT NULL, blob TEXT NOT NULL, size BIGINT NOT NULL, PRIMARY KEY (version, path))",
      "CREATE INDEX IF NOT EXISTS visq_version_files_blob ON visq_version_files (blob)",
      absl::StrCat("INSERT INTO visq_meta (key, value) VALUES ('schema', '", kSchemaVersion,
                   "') ON CONFLICT (key) DO NOTHING"),
  };
  return schema;
}

StatusOr<uint64_t> ParseNumber(const std::optional<std::string>& text, absl::string_view what) {
  uint64_t value = 0;
  if (!text || !absl::SimpleAtoi(*text, &value))
    return absl::InternalError(absl::StrCat("scene catalog: ", what, " is not a number"));
  return value;
}

// A file's path, blob and size from `row`, starting at column `at`.
StatusOr<CatalogFile> ParseFile(const CatalogRow& row, size_t at) {
  CatalogFile file{row[at].value_or(""), row[at + 1].value_or(""), 0};
  VISQ_ASSIGN_OR_RETURN(file.size, ParseNumber(row[at + 2], "a file size"));
  return file;
}

void SortByPath(std::vector<CatalogFile>& files) {
  std::sort(files.begin(), files.end(), [](const CatalogFile& a, const CatalogFile& b) { return a.path < b.path; });
}

}  // namespace

StatusOr<std::unique_ptr<SceneCatalog>> SceneCatalog::Open(std::unique_ptr<CatalogDb> db) {
  VISQ_RETURN_IF_ERROR(db->CreateSchema(Schema()));
  std::unique_ptr<SceneCatalog> catalog(new SceneCatalog(std::move(db)));
  VISQ_ASSIGN_OR_RETURN(const std::optional<std::string> schema, catalog->Meta("schema"));
  int version = 0;
  if (!schema || !absl::SimpleAtoi(*schema, &version) || version > kSchemaVersion)
    return absl::FailedPreconditionError(absl::StrCat("scene catalog ", catalog->Describe(), ": schema ",
                                                      schema.value_or("(none)"), ", this server knows ",
                                                      kSchemaVersion, " (a newer server made it?)"));
  return catalog;
}

Status SceneCatalog::LockForWrite() {
  return db_->Query("UPDATE visq_counter SET last_version = last_version WHERE id = 1").status();
}

StatusOr<std::vector<std::string>> SceneCatalog::Names() {
  std::lock_guard lock(mutex_);
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows, db_->Query("SELECT name FROM visq_scenes ORDER BY name"));
  std::vector<std::string> names;
  for (const CatalogRow& row : rows) names.push_back(row[0].value_or(""));
  // ORDER BY follows the database's collation; callers expect byte order.
  std::sort(names.begin(), names.end());
  return names;
}

StatusOr<std::optional<CatalogVersion>> SceneCatalog::Current(absl::string_view name) {
  std::lock_guard lock(mutex_);
  // One statement: one snapshot of the scene, its version and the files of
  // that version, whatever other replicas commit meanwhile.
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows,
                        db_->Query("SELECT s.version, v.main_file, f.path, f.blob, f.size FROM visq_scenes s "
                                   "JOIN visq_versions v ON v.version = s.version "
                                   "JOIN visq_version_files f ON f.version = s.version WHERE s.name = ?",
                                   {std::string(name)}));
  if (rows.empty()) return std::optional<CatalogVersion>();
  CatalogVersion found;
  found.name = std::string(name);
  VISQ_ASSIGN_OR_RETURN(found.version, ParseNumber(rows[0][0], "a version"));
  found.main_file = rows[0][1].value_or("");
  for (const CatalogRow& row : rows) {
    VISQ_ASSIGN_OR_RETURN(CatalogFile file, ParseFile(row, 2));
    found.files.push_back(std::move(file));
  }
  SortByPath(found.files);
  return std::optional<CatalogVersion>(std::move(found));
}

StatusOr<uint64_t> SceneCatalog::NextVersion() {
  std::lock_guard lock(mutex_);
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows,
                        db_->Query("UPDATE visq_counter SET last_version = last_version + 1 WHERE id = 1 "
                                   "RETURNING last_version"));
  if (rows.size() != 1) return absl::InternalError("scene catalog: the version counter row is missing");
  VISQ_ASSIGN_OR_RETURN(const uint64_t version, ParseNumber(rows[0][0], "the version counter"));
  VISQ_RETURN_IF_ERROR(transaction.Commit());
  return version;
}

Status SceneCatalog::RaiseCounter(uint64_t floor) {
  std::lock_guard lock(mutex_);
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_RETURN_IF_ERROR(RaiseCounterLocked(floor));
  return transaction.Commit();
}

Status SceneCatalog::RaiseCounterLocked(uint64_t floor) {
  const std::string value = absl::StrCat(floor);
  return db_
      ->Query("UPDATE visq_counter SET last_version = CASE WHEN last_version < ? THEN ? ELSE last_version END "
              "WHERE id = 1",
              {value, value})
      .status();
}

Status SceneCatalog::InsertVersionRows(const std::string& version, const std::string& name,
                                       const std::string& main_file, const std::vector<CatalogFile>& files) {
  VISQ_RETURN_IF_ERROR(
      db_->Query("INSERT INTO visq_versions (version, name, main_file) VALUES (?, ?, ?)", {version, name, main_file})
          .status());
  for (const CatalogFile& file : files)
    VISQ_RETURN_IF_ERROR(db_->Query("INSERT INTO visq_version_files (version, path, blob, size) VALUES (?, ?, ?, ?)",
                                    {version, file.path, file.blob, absl::StrCat(file.size)})
                             .status());
  return absl::OkStatus();
}

StatusOr<SceneCatalog::Committed> SceneCatalog::Commit(const CommitRequest& request,
                                                       const std::function<Status(const CatalogFile&)>& publish) {
  std::lock_guard lock(mutex_);
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_RETURN_IF_ERROR(LockForWrite());
  // What the name holds now, seen after every earlier writer committed.
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> current,
                        db_->Query("SELECT s.version, v.main_file FROM visq_scenes s "
                                   "JOIN visq_versions v ON v.version = s.version WHERE s.name = ?",
                                   {request.name}));
  Committed committed;
  std::optional<uint64_t> old_version;
  if (!current.empty()) {
    VISQ_ASSIGN_OR_RETURN(old_version, ParseNumber(current[0][0], "a version"));
    if (!request.replace)
      return absl::AlreadyExistsError(absl::StrCat("scene '", request.name,
                                                   "' already exists (stored meanwhile by another replica?); "
                                                   "nothing stored: set replace to replace it"));
    VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> old_files,
                          db_->Query("SELECT path, blob, size FROM visq_version_files WHERE version = ?",
                                     {absl::StrCat(*old_version)}));
    std::vector<CatalogFile> before;
    for (const CatalogRow& row : old_files) {
      VISQ_ASSIGN_OR_RETURN(CatalogFile file, ParseFile(row, 0));
      before.push_back(std::move(file));
      committed.released.push_back(before.back().blob);
    }
    std::vector<CatalogFile> after = request.files;
    SortByPath(before);
    SortByPath(after);
    if (request.unless_unchanged && before == after && current[0][1].value_or("") == request.main_file) {
      committed.version = *old_version;
      committed.stored = false;
      committed.released.clear();
      return committed;
    }
  }
  // The blobs reach the disk before the rows that name them are committed.
  for (const CatalogFile& file : request.files) VISQ_RETURN_IF_ERROR(publish(file));

  // The number: a migrated one if no version holds it, else the counter's next.
  uint64_t version = 0;
  if (request.keep_version != 0) {
    VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> taken,
                          db_->Query("SELECT 1 FROM visq_versions WHERE version = ?",
                                     {absl::StrCat(request.keep_version)}));
    if (taken.empty()) version = request.keep_version;
  }
  if (version == 0) {
    VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows,
                          db_->Query("UPDATE visq_counter SET last_version = last_version + 1 WHERE id = 1 "
                                     "RETURNING last_version"));
    if (rows.size() != 1) return absl::InternalError("scene catalog: the version counter row is missing");
    VISQ_ASSIGN_OR_RETURN(version, ParseNumber(rows[0][0], "the version counter"));
  }
  const std::string version_text = absl::StrCat(version);
  VISQ_RETURN_IF_ERROR(InsertVersionRows(version_text, request.name, request.main_file, request.files));
  if (old_version) {
    VISQ_RETURN_IF_ERROR(db_->Query("UPDATE visq_scenes SET version = ? WHERE name = ?", {version_text, request.name})
                             .status());
    // Cascades to the old version's files.
    VISQ_RETURN_IF_ERROR(
        db_->Query("DELETE FROM visq_versions WHERE version = ?", {absl::StrCat(*old_version)}).status());
  } else {
    VISQ_RETURN_IF_ERROR(
        db_->Query("INSERT INTO visq_scenes (name, version) VALUES (?, ?)", {request.name, version_text}).status());
  }
  VISQ_RETURN_IF_ERROR(transaction.Commit());
  committed.version = version;
  return committed;
}

StatusOr<std::vector<std::string>> SceneCatalog::Remove(absl::string_view name) {
  std::lock_guard lock(mutex_);
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_RETURN_IF_ERROR(LockForWrite());
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> current,
                        db_->Query("SELECT version FROM visq_scenes WHERE name = ?", {std::string(name)}));
  if (current.empty()) return absl::NotFoundError(absl::StrCat("scene '", name, "' is not in the repository"));
  const std::string version = current[0][0].value_or("");
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> files,
                        db_->Query("SELECT blob FROM visq_version_files WHERE version = ?", {version}));
  VISQ_RETURN_IF_ERROR(db_->Query("DELETE FROM visq_scenes WHERE name = ?", {std::string(name)}).status());
  VISQ_RETURN_IF_ERROR(db_->Query("DELETE FROM visq_versions WHERE version = ?", {version}).status());
  VISQ_RETURN_IF_ERROR(transaction.Commit());
  std::vector<std::string> released;
  for (const CatalogRow& row : files) released.push_back(row[0].value_or(""));
  return released;
}

Status SceneCatalog::CollectBlobs(const std::vector<std::string>& candidates,
                                  const std::function<Status(const std::string&)>& remove) {
  if (candidates.empty()) return absl::OkStatus();
  std::lock_guard lock(mutex_);
  // A start offers every blob: those named now are set aside in one read,
  // without the lock, so that other replicas' commits wait only for the
  // few left (each checked again under the lock).
  std::vector<std::string> unnamed = candidates;
  if (candidates.size() > 16) {
    VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> named,
                          db_->Query("SELECT DISTINCT blob FROM visq_version_files"));
    std::set<std::string> in_use;
    for (const CatalogRow& row : named) in_use.insert(row[0].value_or(""));
    std::erase_if(unnamed, [&](const std::string& blob) { return in_use.count(blob) > 0; });
    if (unnamed.empty()) return absl::OkStatus();
  }
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_RETURN_IF_ERROR(LockForWrite());
  for (const std::string& blob : unnamed) {
    VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> named,
                          db_->Query("SELECT 1 FROM visq_version_files WHERE blob = ? LIMIT 1", {blob}));
    if (named.empty()) VISQ_RETURN_IF_ERROR(remove(blob));
  }
  // Nothing was written: the transaction only held the lock.
  return transaction.Commit();
}

StatusOr<std::optional<std::string>> SceneCatalog::Meta(absl::string_view key) {
  std::lock_guard lock(mutex_);
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows,
                        db_->Query("SELECT value FROM visq_meta WHERE key = ?", {std::string(key)}));
  if (rows.empty()) return std::optional<std::string>();
  return rows[0][0];
}

Status SceneCatalog::SetMeta(absl::string_view key, absl::string_view value) {
  std::lock_guard lock(mutex_);
  return SetMetaLocked(key, value);
}

Status SceneCatalog::SetMetaLocked(absl::string_view key, absl::string_view value) {
  return db_
      ->Query("INSERT INTO visq_meta (key, value) VALUES (?, ?) ON CONFLICT (key) DO UPDATE SET value = excluded.value",
              {std::string(key), std::string(value)})
      .status();
}

StatusOr<std::string> SceneCatalog::MetaOrInit(absl::string_view key, absl::string_view value) {
  std::lock_guard lock(mutex_);
  VISQ_RETURN_IF_ERROR(db_->Query("INSERT INTO visq_meta (key, value) VALUES (?, ?) ON CONFLICT (key) DO NOTHING",
                                  {std::string(key), std::string(value)})
                           .status());
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows,
                        db_->Query("SELECT value FROM visq_meta WHERE key = ?", {std::string(key)}));
  if (rows.size() != 1 || !rows[0][0]) return absl::InternalError(absl::StrCat("scene catalog: meta '", key, "' lost"));
  return *rows[0][0];
}

StatusOr<SceneCatalog::Contents> SceneCatalog::ReadAll() {
  std::lock_guard lock(mutex_);
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_RETURN_IF_ERROR(LockForWrite());
  Contents contents;
  // Every scene's current version with its files, a row per file.
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> rows,
                        db_->Query("SELECT s.name, s.version, v.main_file, f.path, f.blob, f.size FROM visq_scenes s "
                                   "JOIN visq_versions v ON v.version = s.version "
                                   "JOIN visq_version_files f ON f.version = s.version"));
  std::map<std::string, CatalogVersion> by_name;
  for (const CatalogRow& row : rows) {
    CatalogVersion& scene = by_name[row[0].value_or("")];
    if (scene.files.empty()) {
      scene.name = row[0].value_or("");
      VISQ_ASSIGN_OR_RETURN(scene.version, ParseNumber(row[1], "a version"));
      scene.main_file = row[2].value_or("");
    }
    VISQ_ASSIGN_OR_RETURN(CatalogFile file, ParseFile(row, 3));
    scene.files.push_back(std::move(file));
  }
  for (auto& [name, scene] : by_name) {
    SortByPath(scene.files);
    contents.scenes.push_back(std::move(scene));
  }
  // The counter and the meta values.
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> counter,
                        db_->Query("SELECT last_version FROM visq_counter WHERE id = 1"));
  if (counter.size() != 1) return absl::InternalError("scene catalog: the version counter row is missing");
  VISQ_ASSIGN_OR_RETURN(contents.counter, ParseNumber(counter[0][0], "the version counter"));
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> meta,
                        db_->Query("SELECT key, value FROM visq_meta WHERE key <> 'schema'"));
  for (const CatalogRow& row : meta) contents.meta[row[0].value_or("")] = row[1].value_or("");
  // Nothing was written: the transaction only held the lock.
  VISQ_RETURN_IF_ERROR(transaction.Commit());
  return contents;
}

StatusOr<SceneCatalog::TakenOver> SceneCatalog::TakeOver(const Contents& from, absl::string_view mark,
                                                         absl::string_view mark_value) {
  std::lock_guard lock(mutex_);
  CatalogTransaction transaction(*db_);
  VISQ_RETURN_IF_ERROR(transaction.BeginWrite());
  VISQ_RETURN_IF_ERROR(LockForWrite());
  // Seen under the lock: a replica that moved it first has committed.
  TakenOver taken;
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> marked,
                        db_->Query("SELECT value FROM visq_meta WHERE key = ?", {std::string(mark)}));
  if (!marked.empty() && marked[0][0] == std::string(mark_value)) {
    taken.outcome = TakenOver::Outcome::kAlreadyMoved;
    return taken;
  }
  VISQ_ASSIGN_OR_RETURN(const std::vector<CatalogRow> held, db_->Query("SELECT COUNT(*) FROM visq_scenes"));
  VISQ_ASSIGN_OR_RETURN(taken.scenes, ParseNumber(held.empty() ? std::nullopt : held[0][0], "a count"));
  if (taken.scenes > 0) {
    taken.outcome = TakenOver::Outcome::kOccupied;
    return taken;
  }

  // Every scene under its own number, then the counter past them all.
  uint64_t highest = from.counter;
  for (const CatalogVersion& scene : from.scenes) {
    const std::string version = absl::StrCat(scene.version);
    VISQ_RETURN_IF_ERROR(InsertVersionRows(version, scene.name, scene.main_file, scene.files));
    VISQ_RETURN_IF_ERROR(
        db_->Query("INSERT INTO visq_scenes (name, version) VALUES (?, ?)", {scene.name, version}).status());
    highest = std::max(highest, scene.version);
    taken.files += scene.files.size();
  }
  VISQ_RETURN_IF_ERROR(RaiseCounterLocked(highest));
  for (const auto& [key, value] : from.meta)
    if (key != mark) VISQ_RETURN_IF_ERROR(SetMetaLocked(key, value));
  VISQ_RETURN_IF_ERROR(SetMetaLocked(mark, mark_value));
  VISQ_RETURN_IF_ERROR(transaction.Commit());
  taken.scenes = from.scenes.size();
  return taken;
}

}  // namespace visq::core
