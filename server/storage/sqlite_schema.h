#ifndef CROWDMAP_SERVER_STORAGE_SQLITE_SCHEMA_H_
#define CROWDMAP_SERVER_STORAGE_SQLITE_SCHEMA_H_

#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "server/storage/sqlite_db.h"

namespace crowdmap {

// Latest schema version (PRAGMA user_version after migration).
int LatestSchemaVersion();

// Brings the database to the latest schema (or to `target_version`, for tests of a migration), one
// migration per transaction. FailedPrecondition when the file comes from a newer release.
absl::Status MigrateSchema(SqliteConnection* db, int target_version = -1);

// The passage queue's own file has a schema of its own.
int LatestQueueSchemaVersion();
absl::Status MigrateQueueSchema(SqliteConnection* queue);

// Copies the passage queue of a map file at schema 4 (the queue shared the map's file) into the
// queue file, replacing what the queue file held, as long as no start has completed on the queue
// file (MarkQueueServed): until then the map file's queue is the truth (a start that failed in
// between served nothing, and an older release run after it took uploads into the map's file).
// Run before MigrateSchema takes the map file past schema 4.
absl::Status ImportQueueFromMapFile(SqliteConnection* queue, const std::string& map_path);
// Records that a start completed on the queue file: from then on it takes uploads, and no map
// file's queue replaces it.
absl::Status MarkQueueServed(SqliteConnection* queue);

// Brings the queue in line with the map file, which is the truth about what the map contains.
// FailedPrecondition, nothing changed, when the map holds a passage the queue lacks or holds in
// another state than applied, excluded or processing (a queue file older than the map, or another
// map's). Otherwise:
// - a passage the map holds as applied (or excluded) while the queue has it processing (or
//   applied), after a crash between the map's commit and the queue's: recorded, with its result;
// - a passage applied in the queue that the map does not contain (a map restored from a backup
//   older than the queue's): queued again;
// - a passage excluded in the queue that such a map contains: applied, with a note to exclude it
//   again.
// Returns how many passages changed.
absl::StatusOr<int> ReconcileQueueWithMap(SqliteConnection* queue, const std::string& map_path);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_SQLITE_SCHEMA_H_
