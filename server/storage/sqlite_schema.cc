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
      // 1 -> 2: row counts kept by triggers in the writing transaction, so that the map's
      // statistics (GetMapInfo) do not scan tables that grow with the map and its history.
      // Landmarks and cross-covariances are written by upsert (an INSERT OR REPLACE would not fire
      // the delete trigger) and never deleted today; the delete triggers keep the counts right if
      // they ever are.
      R"sql(
      CREATE TABLE row_counts (
        name TEXT PRIMARY KEY,
        n INTEGER NOT NULL
      ) STRICT, WITHOUT ROWID;
      INSERT INTO row_counts (name, n)
        SELECT 'landmarks', COUNT(*) FROM landmarks
        UNION ALL SELECT 'cross_covariances', COUNT(*) FROM cross_covariances
        UNION ALL SELECT 'passages_' || s.state, (SELECT COUNT(*) FROM passages WHERE passages.state = s.state)
          FROM (SELECT 0 AS state UNION ALL SELECT 1 UNION ALL SELECT 2 UNION ALL SELECT 3 UNION ALL SELECT 4
                UNION ALL SELECT 5) AS s;
      CREATE TRIGGER count_landmark_insert AFTER INSERT ON landmarks
        BEGIN UPDATE row_counts SET n = n + 1 WHERE name = 'landmarks'; END;
      CREATE TRIGGER count_landmark_delete AFTER DELETE ON landmarks
        BEGIN UPDATE row_counts SET n = n - 1 WHERE name = 'landmarks'; END;
      CREATE TRIGGER count_cross_insert AFTER INSERT ON cross_covariances
        BEGIN UPDATE row_counts SET n = n + 1 WHERE name = 'cross_covariances'; END;
      CREATE TRIGGER count_cross_delete AFTER DELETE ON cross_covariances
        BEGIN UPDATE row_counts SET n = n - 1 WHERE name = 'cross_covariances'; END;
      CREATE TRIGGER count_passage_insert AFTER INSERT ON passages
        BEGIN UPDATE row_counts SET n = n + 1 WHERE name = 'passages_' || NEW.state; END;
      CREATE TRIGGER count_passage_state AFTER UPDATE OF state ON passages WHEN OLD.state <> NEW.state
        BEGIN
          UPDATE row_counts SET n = n - 1 WHERE name = 'passages_' || OLD.state;
          UPDATE row_counts SET n = n + 1 WHERE name = 'passages_' || NEW.state;
        END;
      CREATE TRIGGER count_passage_delete AFTER DELETE ON passages
        BEGIN UPDATE row_counts SET n = n - 1 WHERE name = 'passages_' || OLD.state; END;
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
