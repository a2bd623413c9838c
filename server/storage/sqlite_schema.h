#ifndef CROWDMAP_SERVER_STORAGE_SQLITE_SCHEMA_H_
#define CROWDMAP_SERVER_STORAGE_SQLITE_SCHEMA_H_

#include "absl/status/status.h"
#include "server/storage/sqlite_db.h"

namespace crowdmap {

// Latest schema version (PRAGMA user_version after migration).
int LatestSchemaVersion();

// Brings the database to the latest schema (or to `target_version`, for tests of a migration), one
// migration per transaction. FailedPrecondition when the file comes from a newer release.
absl::Status MigrateSchema(SqliteConnection* db, int target_version = -1);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_SQLITE_SCHEMA_H_
