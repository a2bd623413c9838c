#include "server/storage/sqlite_schema.h"

#include <vector>

#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

// Migration i takes the schema from user_version i to i + 1. Append only; never edit a released one.
const std::vector<const char*>& Migrations() {
  static const std::vector<const char*> kMigrations = {
      // 0 -> 1: durable passage queue, map, R*Tree index, cross-covariance blocks, map version.
      R"sql(
      CREATE TABLE map_meta (
        key TEXT PRIMARY KEY,
        value INTEGER NOT NULL
      ) STRICT;
      INSERT INTO map_meta (key, value) VALUES ('map_version', 0);

      CREATE TABLE passages (
        id INTEGER PRIMARY KEY,               -- arrival order
        vehicle_id TEXT NOT NULL,
        passage_id TEXT NOT NULL,
        state INTEGER NOT NULL,               -- 1 queued, 2 processing, 3 applied, 4 rejected, 5 failed
        attempts INTEGER NOT NULL DEFAULT 0,
        error TEXT NOT NULL DEFAULT '',
        received_unix_ms INTEGER NOT NULL,
        finished_unix_ms INTEGER NOT NULL DEFAULT 0,
        size_bytes INTEGER NOT NULL,
        UNIQUE (vehicle_id, passage_id)
      ) STRICT;
      CREATE INDEX passages_by_state ON passages (state, id);

      CREATE TABLE passage_payloads (
        id INTEGER PRIMARY KEY REFERENCES passages (id),
        payload BLOB NOT NULL                 -- serialized mapservice.v1.Passage
      ) STRICT;

      CREATE TABLE passage_results (
        id INTEGER PRIMARY KEY REFERENCES passages (id),
        nodes INTEGER NOT NULL,
        subgraphs INTEGER NOT NULL,
        landmarks_updated INTEGER NOT NULL,
        landmarks_created INTEGER NOT NULL,
        landmarks_conditioned INTEGER NOT NULL,
        detections_used INTEGER NOT NULL,
        detections_dropped INTEGER NOT NULL,
        solver_iterations INTEGER NOT NULL,
        final_cost REAL NOT NULL,
        solve_ms REAL NOT NULL,
        covariance_ms REAL NOT NULL,
        total_ms REAL NOT NULL,
        map_version INTEGER NOT NULL,
        strategy TEXT NOT NULL
      ) STRICT;

      -- Covariance: East/North at the landmark, metres^2, row-major.
      CREATE TABLE landmarks (
        id INTEGER PRIMARY KEY,
        lat_deg REAL NOT NULL,
        lon_deg REAL NOT NULL,
        cov_ee REAL NOT NULL,
        cov_en REAL NOT NULL,
        cov_ne REAL NOT NULL,
        cov_nn REAL NOT NULL,
        version INTEGER NOT NULL,
        passages_seen INTEGER NOT NULL,
        last_seen_unix_ms INTEGER NOT NULL,
        state INTEGER NOT NULL,
        tile_x INTEGER NOT NULL,              -- z16 tile containing the landmark
        tile_y INTEGER NOT NULL
      ) STRICT;
      CREATE INDEX landmarks_by_tile ON landmarks (tile_x, tile_y);
      CREATE INDEX landmarks_by_version ON landmarks (version);

      CREATE VIRTUAL TABLE landmark_boxes USING rtree (id, min_lat, max_lat, min_lon, max_lon);

      -- Sigma_ab, a < b: rows in a's East/North frame, columns in b's, metres^2, row-major.
      CREATE TABLE cross_covariances (
        a INTEGER NOT NULL,
        b INTEGER NOT NULL,
        c_ee REAL NOT NULL,
        c_en REAL NOT NULL,
        c_ne REAL NOT NULL,
        c_nn REAL NOT NULL,
        PRIMARY KEY (a, b),
        CHECK (a < b)
      ) STRICT, WITHOUT ROWID;
      CREATE INDEX cross_by_b ON cross_covariances (b, a);
      )sql",
  };
  return kMigrations;
}

}  // namespace

int LatestSchemaVersion() { return static_cast<int>(Migrations().size()); }

absl::Status MigrateSchema(SqliteConnection* db) {
  while (true) {
    auto txn = SqliteWriteTransaction::Begin(db);
    if (!txn.ok()) return txn.status();
    auto version = db->PragmaInt("user_version");
    if (!version.ok()) return version.status();
    if (*version == LatestSchemaVersion()) return txn->Commit();
    if (*version > LatestSchemaVersion() || *version < 0) {
      return absl::FailedPreconditionError(absl::StrCat("database schema version ", *version,
                                                        " is newer than this server's ", LatestSchemaVersion()));
    }
    if (auto s = db->Exec(Migrations()[*version]); !s.ok()) return s;
    if (auto s = db->Exec(absl::StrCat("PRAGMA user_version = ", *version + 1)); !s.ok()) return s;
    if (auto s = txn->Commit(); !s.ok()) return s;
  }
}

}  // namespace crowdmap
