// What a server's scene repository holds, read from its files (the SQLite
// catalog and the staging folders) while the server runs or after it is
// gone: tests check that nothing half-written or unwanted was kept.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

namespace visq::testing {

// The scenes the catalog holds, sorted.
std::vector<std::string> StoredSceneNames(const std::filesystem::path& repo);
// The files (paths as uploaded) of the version the catalog holds for `name`.
std::vector<std::string> StoredFiles(const std::filesystem::path& repo, const std::string& name);
// Uploads in flight and loads' views in every replica's staging.
int StagingEntries(const std::filesystem::path& repo);

}  // namespace visq::testing
