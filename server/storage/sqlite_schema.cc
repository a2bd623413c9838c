#include "server/storage/sqlite_schema.h"

#include <functional>
#include <map>
#include <numeric>
#include <string>
#include <vector>

#include <Eigen/Cholesky>

#include "absl/strings/str_cat.h"
#include "server/storage/factor_codec.h"
#include "server/storage/map_store.h"

namespace crowdmap {
namespace {

// Schema 2 kept the dense joint covariance as 2x2 blocks. Each connected group of landmarks (joined
// by stored blocks) becomes one factor with the inverse of the group's joint covariance: the same
// Gaussian, so the map is unchanged. Anchors are the positions, so the information vectors are 0.
absl::Status ConvertCrossCovariancesToFactors(SqliteConnection* db) {
  auto rows = db->Prepare("SELECT id, cov_ee, cov_en, cov_ne, cov_nn FROM landmarks ORDER BY id");
  if (!rows.ok()) return rows.status();
  std::map<int64_t, int> index;
  std::vector<int64_t> ids;
  std::vector<Eigen::Matrix2d> marginal;
  while (true) {
    auto row = rows->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    index[rows->Int(0)] = static_cast<int>(ids.size());
    ids.push_back(rows->Int(0));
    Eigen::Matrix2d c;
    c << rows->Double(1), rows->Double(2), rows->Double(3), rows->Double(4);
    marginal.push_back(c);
  }
  std::vector<int> parent(ids.size());
  std::iota(parent.begin(), parent.end(), 0);
  std::function<int(int)> root = [&](int i) { return parent[i] == i ? i : parent[i] = root(parent[i]); };
  struct Block {
    int a, b;
    Eigen::Matrix2d value;
  };
  std::vector<Block> blocks;
  auto cross = db->Prepare("SELECT a, b, c_ee, c_en, c_ne, c_nn FROM cross_covariances");
  if (!cross.ok()) return cross.status();
  while (true) {
    auto row = cross->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    if (!index.count(cross->Int(0)) || !index.count(cross->Int(1))) continue;
    Block b{index[cross->Int(0)], index[cross->Int(1)], Eigen::Matrix2d()};
    b.value << cross->Double(2), cross->Double(3), cross->Double(4), cross->Double(5);
    blocks.push_back(b);
    parent[root(b.a)] = root(b.b);
  }
  std::map<int, std::vector<int>> groups;
  for (size_t i = 0; i < ids.size(); ++i) groups[root(static_cast<int>(i))].push_back(static_cast<int>(i));
  std::map<int, int> position_in_group;
  for (const auto& [r, members] : groups) {
    for (size_t k = 0; k < members.size(); ++k) position_in_group[members[k]] = static_cast<int>(k);
  }
  std::map<int, Eigen::MatrixXd> covariance;
  for (const auto& [r, members] : groups) {
    Eigen::MatrixXd& cov = covariance[r];
    cov.setZero(2 * members.size(), 2 * members.size());
    for (size_t k = 0; k < members.size(); ++k) cov.block<2, 2>(2 * k, 2 * k) = marginal[members[k]];
  }
  for (const Block& b : blocks) {
    Eigen::MatrixXd& cov = covariance[root(b.a)];
    const int i = position_in_group[b.a], j = position_in_group[b.b];
    cov.block<2, 2>(2 * i, 2 * j) = b.value;
    cov.block<2, 2>(2 * j, 2 * i) = b.value.transpose();
  }
  int64_t factor_id = 0;
  for (const auto& [r, members] : groups) {
    const Eigen::MatrixXd& cov = covariance[r];
    Eigen::LLT<Eigen::MatrixXd> llt(0.5 * (cov + cov.transpose()));
    if (llt.info() != Eigen::Success) {
      return absl::DataLossError(absl::StrCat("schema 3: the stored covariance of the ", members.size(),
                                              " landmarks around landmark ", ids[members[0]],
                                              " is not positive definite and cannot be converted"));
    }
    MapFactor f;
    f.id = ++factor_id;
    f.passage_id = "schema-2-covariance";
    for (int m : members) f.landmarks.push_back(ids[m]);
    f.information = llt.solve(Eigen::MatrixXd::Identity(cov.rows(), cov.cols()));
    f.information = 0.5 * (f.information + f.information.transpose());
    f.information_vector = Eigen::VectorXd::Zero(cov.rows());
    if (auto s = InsertFactorRow(db, f); !s.ok()) return s;
  }
  auto last = db->Prepare("UPDATE map_meta SET value = ?1 WHERE key = 'last_factor_id'");
  if (!last.ok()) return last.status();
  last->Bind(1, factor_id);
  if (auto s = last->Run(); !s.ok()) return s;
  return db->Exec(R"sql(
      DROP TRIGGER count_cross_insert;
      DROP TRIGGER count_cross_delete;
      DROP TABLE cross_covariances;
      DELETE FROM row_counts WHERE name = 'cross_covariances';
      )sql");
}

// The columns of a passage's result (passage_results in the queue file, map_passages in the map file).
constexpr char kResultColumns[] =
    "nodes, subgraphs, landmarks_updated, landmarks_created, landmarks_conditioned, detections_used, "
    "detections_dropped, solver_iterations, final_cost, solve_ms, covariance_ms, total_ms, map_version, strategy";

struct Migration {
  std::string sql;
  std::function<absl::Status(SqliteConnection*)> then;  // may be empty
};

// Migration i takes the schema from user_version i to i + 1. Append only; never edit a released one.
const std::vector<Migration>& Migrations() {
  static const std::vector<Migration> kMigrations = {
      // 0 -> 1: durable passage queue, map, R*Tree index, cross-covariance blocks, map version.
      {R"sql(
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
      )sql", nullptr},
      // 1 -> 2: row counts kept by triggers in the writing transaction, so that the map's
      // statistics (GetMapInfo) do not scan tables that grow with the map and its history.
      // Landmarks and cross-covariances are written by upsert (an INSERT OR REPLACE would not fire
      // the delete trigger) and never deleted today; the delete triggers keep the counts right if
      // they ever are.
      {R"sql(
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
      )sql", nullptr},
      // 2 -> 3: the map in information form. Landmarks get a fixed anchor (their estimate is an
      // East/North offset from it); the map's information is a sum of factors, one per applied
      // subgraph, kept with the passage they came from. The dense cross-covariance blocks are
      // converted to factors (ConvertCrossCovariancesToFactors) and dropped.
      {R"sql(
      ALTER TABLE landmarks ADD COLUMN anchor_lat_deg REAL NOT NULL DEFAULT 0;
      ALTER TABLE landmarks ADD COLUMN anchor_lon_deg REAL NOT NULL DEFAULT 0;
      UPDATE landmarks SET anchor_lat_deg = lat_deg, anchor_lon_deg = lon_deg;
      INSERT INTO map_meta (key, value) VALUES ('last_factor_id', 0);
      CREATE TABLE factors (
        id INTEGER PRIMARY KEY,
        vehicle_id TEXT NOT NULL,
        passage_id TEXT NOT NULL,
        landmark_ids BLOB NOT NULL,        -- k int64
        information BLOB NOT NULL,         -- upper triangle of the 2k x 2k information, row by row, doubles
        information_vector BLOB NOT NULL   -- 2k doubles
      ) STRICT;
      CREATE INDEX factors_by_passage ON factors (vehicle_id, passage_id);
      -- The base: factors folded in after the retention window, summed. Information blocks (a, b),
      -- a <= b, rows in a's offsets and columns in b's, row-major; the information vector per landmark.
      CREATE TABLE base_blocks (
        a INTEGER NOT NULL,
        b INTEGER NOT NULL,
        ee REAL NOT NULL, en REAL NOT NULL, ne REAL NOT NULL, nn REAL NOT NULL,
        PRIMARY KEY (a, b),
        CHECK (a <= b)
      ) STRICT, WITHOUT ROWID;
      CREATE TABLE base_vectors (
        id INTEGER PRIMARY KEY,
        e REAL NOT NULL,
        n REAL NOT NULL
      ) STRICT;
      INSERT INTO row_counts (name, n) VALUES ('factors', 0), ('passages_6', 0);
      CREATE TRIGGER count_factor_insert AFTER INSERT ON factors
        BEGIN UPDATE row_counts SET n = n + 1 WHERE name = 'factors'; END;
      CREATE TRIGGER count_factor_delete AFTER DELETE ON factors
        BEGIN UPDATE row_counts SET n = n - 1 WHERE name = 'factors'; END;
      )sql",
       ConvertCrossCovariancesToFactors},
      // 3 -> 4: passages can be quarantined (7) and discarded (8); a passage counts the times it
      // was interrupted (a restart or crash while it was applied) apart from its attempts.
      {R"sql(
      INSERT INTO row_counts (name, n) VALUES ('passages_7', 0), ('passages_8', 0);
      ALTER TABLE passages ADD COLUMN interruptions INTEGER NOT NULL DEFAULT 0;
      )sql", nullptr},
      // 4 -> 5: the passage queue moves to its own file (SqliteQueuePath; copied there by
      // ImportQueueFromMapFile before this runs), so that uploads never wait for a map commit. The
      // map file keeps, per passage it contains, its state and result: written in the map's own
      // transaction, they let the queue be reconciled after a crash between the two commits.
      {absl::StrCat(R"sql(
      CREATE TABLE map_passages (
        id INTEGER PRIMARY KEY,               -- the queue's passage id
        state INTEGER NOT NULL,               -- 3 applied, 6 excluded
        finished_unix_ms INTEGER NOT NULL,
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
      INSERT INTO map_passages (id, state, finished_unix_ms, )sql",
                    kResultColumns, R"sql()
        SELECT p.id, p.state, p.finished_unix_ms, r.nodes, r.subgraphs, r.landmarks_updated, r.landmarks_created,
               r.landmarks_conditioned, r.detections_used, r.detections_dropped, r.solver_iterations, r.final_cost,
               r.solve_ms, r.covariance_ms, r.total_ms, r.map_version, r.strategy
        FROM passages p JOIN passage_results r ON r.id = p.id WHERE p.state IN (3, 6);
      DROP TABLE passage_results;
      DROP TABLE passage_payloads;
      DROP TABLE passages;
      DELETE FROM row_counts WHERE name LIKE 'passages_%';
      )sql"),
       nullptr},
      // 5 -> 6: each vehicle's camera yaw offset as its passages estimated it (VehicleCalibration),
      // written in the transaction of the map change that estimated it.
      {R"sql(
      CREATE TABLE vehicles (
        vehicle_id TEXT PRIMARY KEY,
        camera_yaw_offset_rad REAL NOT NULL,
        camera_yaw_variance_rad2 REAL NOT NULL,
        camera_yaw_information REAL NOT NULL,
        camera_yaw_map_term REAL NOT NULL,
        passages INTEGER NOT NULL,
        version INTEGER NOT NULL,
        updated_unix_ms INTEGER NOT NULL
      ) STRICT, WITHOUT ROWID;
      )sql",
       nullptr},
      // 6 -> 7: R*Tree boxes reach 1e-5 degrees (about a metre) around the position they were
      // written for, so that a landmark's box is rewritten only once it leaves it
      // (SqliteMapStore::WriteLandmark); region reads test the exact position on the row.
      {R"sql(
      UPDATE landmark_boxes SET min_lat = min_lat - 1e-5, max_lat = max_lat + 1e-5,
                                min_lon = min_lon - 1e-5, max_lon = max_lon + 1e-5;
      )sql",
       nullptr},
      // 7 -> 8: where each removed landmark last was, and the version that removed it, so that a
      // watcher whose copy holds it is told (SqliteMapStore::WriteMapDelta; ChangedLandmarks).
      {R"sql(
      CREATE TABLE removed_landmarks (
        id INTEGER PRIMARY KEY,
        lat_deg REAL NOT NULL,
        lon_deg REAL NOT NULL,
        version INTEGER NOT NULL
      ) STRICT;
      CREATE INDEX removed_landmarks_by_version ON removed_landmarks (version);
      )sql",
       nullptr},
  };
  return kMigrations;
}

// The queue file's own schema, versioned apart from the map's.
const std::vector<Migration>& QueueMigrations() {
  static const std::vector<Migration> kMigrations = {
      // 0 -> 1: the passage queue as it stood in the map file at schema 4, with its row counts.
      {absl::StrCat(R"sql(
      CREATE TABLE queue_meta (
        key TEXT PRIMARY KEY,
        value INTEGER NOT NULL
      ) STRICT;
      CREATE TABLE passages (
        id INTEGER PRIMARY KEY,               -- arrival order
        vehicle_id TEXT NOT NULL,
        passage_id TEXT NOT NULL,
        state INTEGER NOT NULL,               -- PassageState
        attempts INTEGER NOT NULL DEFAULT 0,
        error TEXT NOT NULL DEFAULT '',
        received_unix_ms INTEGER NOT NULL,
        finished_unix_ms INTEGER NOT NULL DEFAULT 0,
        size_bytes INTEGER NOT NULL,
        interruptions INTEGER NOT NULL DEFAULT 0,
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
      CREATE TABLE row_counts (
        name TEXT PRIMARY KEY,
        n INTEGER NOT NULL
      ) STRICT, WITHOUT ROWID;
      INSERT INTO row_counts (name, n) VALUES ('passages_0', 0), ('passages_1', 0), ('passages_2', 0),
        ('passages_3', 0), ('passages_4', 0), ('passages_5', 0), ('passages_6', 0), ('passages_7', 0),
        ('passages_8', 0);
      CREATE TRIGGER count_passage_insert AFTER INSERT ON passages
        BEGIN UPDATE row_counts SET n = n + 1 WHERE name = 'passages_' || NEW.state; END;
      CREATE TRIGGER count_passage_state AFTER UPDATE OF state ON passages WHEN OLD.state <> NEW.state
        BEGIN
          UPDATE row_counts SET n = n - 1 WHERE name = 'passages_' || OLD.state;
          UPDATE row_counts SET n = n + 1 WHERE name = 'passages_' || NEW.state;
        END;
      CREATE TRIGGER count_passage_delete AFTER DELETE ON passages
        BEGIN UPDATE row_counts SET n = n - 1 WHERE name = 'passages_' || OLD.state; END;
      )sql"),
       nullptr},
      // 1 -> 2: an operator can release a quarantined passage (ResolvePassage RELEASE): it is
      // queued again and applied once with the map's consistency checks off.
      {"ALTER TABLE passages ADD COLUMN released INTEGER NOT NULL DEFAULT 0;", nullptr},
      // 2 -> 3: the upload of a passage whose factors were folded into the map's base is deleted
      // (nothing can take it again: it can no longer be excluded, and the young map's joint solves
      // are over by then); the record stays, with the time.
      {"ALTER TABLE passages ADD COLUMN payload_pruned_unix_ms INTEGER NOT NULL DEFAULT 0;", nullptr},
      // 3 -> 4: the SHA-256 of each upload's measurements (PassageContentDigest), so that the same
      // drive sent again under other ids is refused. NULL for uploads queued before.
      {R"sql(
      ALTER TABLE passages ADD COLUMN content_digest BLOB;
      CREATE INDEX passages_by_content ON passages (content_digest) WHERE content_digest IS NOT NULL;
      )sql",
       nullptr},
      // 4 -> 5: whether a processing passage was started or only claimed ahead by a worker, so
      // that a crash counts an interruption only for the passages being applied. Those processing
      // before the upgrade count as started, as they did.
      {R"sql(
      ALTER TABLE passages ADD COLUMN started INTEGER NOT NULL DEFAULT 0;
      UPDATE passages SET started = 1 WHERE state = 2;
      )sql",
       nullptr},
  };
  return kMigrations;
}

absl::Status Migrate(SqliteConnection* db, const std::vector<Migration>& migrations, int target_version,
                     const char* what) {
  const int latest = static_cast<int>(migrations.size());
  if (target_version < 0) target_version = latest;
  while (true) {
    auto txn = SqliteWriteTransaction::Begin(db);
    if (!txn.ok()) return txn.status();
    auto version = db->PragmaInt("user_version");
    if (!version.ok()) return version.status();
    if (*version >= target_version && *version <= latest) return txn->Commit();
    if (*version > latest || *version < 0) {
      return absl::FailedPreconditionError(
          absl::StrCat(what, " schema version ", *version, " is newer than this server's ", latest));
    }
    const Migration& migration = migrations[*version];
    if (auto s = db->Exec(migration.sql); !s.ok()) return s;
    if (migration.then) {
      if (auto s = migration.then(db); !s.ok()) return s;
    }
    if (auto s = db->Exec(absl::StrCat("PRAGMA user_version = ", *version + 1)); !s.ok()) return s;
    if (auto s = txn->Commit(); !s.ok()) return s;
  }
}

// Runs `body` on `db` with the map file attached as `m`, detaching afterwards whatever happens.
absl::Status WithMapAttached(SqliteConnection* db, const std::string& map_path,
                             const std::function<absl::Status()>& body) {
  auto attach = db->Prepare("ATTACH DATABASE ?1 AS m");
  if (!attach.ok()) return attach.status();
  attach->Bind(1, std::string_view(map_path));
  if (auto s = attach->Run(); !s.ok()) return s;
  absl::Status status = body();
  absl::Status detached = db->Exec("DETACH DATABASE m");
  return status.ok() ? detached : status;
}

}  // namespace

int LatestSchemaVersion() { return static_cast<int>(Migrations().size()); }
int LatestQueueSchemaVersion() { return static_cast<int>(QueueMigrations().size()); }

absl::Status MigrateSchema(SqliteConnection* db, int target_version) {
  return Migrate(db, Migrations(), target_version, "database");
}

absl::Status MigrateQueueSchema(SqliteConnection* queue) { return Migrate(queue, QueueMigrations(), -1, "queue database"); }

absl::Status ImportQueueFromMapFile(SqliteConnection* queue, const std::string& map_path) {
  return WithMapAttached(queue, map_path, [&]() -> absl::Status {
    auto txn = SqliteWriteTransaction::Begin(queue);
    if (!txn.ok()) return txn.status();
    // Until a start has completed on it (MarkQueueServed), the queue file has taken no upload: a
    // start that fails between the copy and the map's migration serves nothing. Until then the map
    // file's queue is the truth, and is copied whole on every start: after a rollback to an older
    // release, uploads taken into the map's file meanwhile come over too. Once served, the queue
    // file is never replaced: a map file created anew, or a schema-4 map restored, beside it has
    // nothing the queue lacks.
    auto served = queue->Prepare("SELECT COUNT(*) FROM queue_meta WHERE key = 'served'");
    if (!served.ok()) return served.status();
    if (auto row = served->Step(); !row.ok()) return row.status();
    if (served->Int(0) > 0) return txn->Commit();
    auto has_queue = queue->Prepare("SELECT COUNT(*) FROM m.sqlite_master WHERE type = 'table' AND name = 'passages'");
    if (!has_queue.ok()) return has_queue.status();
    if (auto row = has_queue->Step(); !row.ok()) return row.status();
    if (has_queue->Int(0) == 0) return txn->Commit();
    // A queue file of an earlier release carries no 'served' key: it is replaced only when the
    // map's queue holds every passage it holds.
    auto newer = queue->Prepare("SELECT COUNT(*) FROM passages WHERE id NOT IN (SELECT id FROM m.passages)");
    if (!newer.ok()) return newer.status();
    if (auto row = newer->Step(); !row.ok()) return row.status();
    if (newer->Int(0) > 0) return txn->Commit();
    if (auto s = queue->Exec(absl::StrCat(
            "DELETE FROM passage_results; DELETE FROM passage_payloads; DELETE FROM passages;"
            "INSERT INTO passages (id, vehicle_id, passage_id, state, attempts, error, received_unix_ms, "
            "finished_unix_ms, size_bytes, interruptions) SELECT id, vehicle_id, passage_id, state, attempts, error, "
            "received_unix_ms, finished_unix_ms, size_bytes, interruptions FROM m.passages ORDER BY id;"
            "INSERT INTO passage_payloads (id, payload) SELECT id, payload FROM m.passage_payloads;"
            "INSERT INTO passage_results (id, ", kResultColumns, ") SELECT id, ", kResultColumns,
            " FROM m.passage_results;"
            "INSERT OR REPLACE INTO queue_meta (key, value) VALUES ('imported_from_map', 1)"));
        !s.ok()) {
      return s;
    }
    return txn->Commit();
  });
}

absl::Status MarkQueueServed(SqliteConnection* queue) {
  return queue->Exec("INSERT OR REPLACE INTO queue_meta (key, value) VALUES ('served', 1)");
}

absl::StatusOr<int> ReconcileQueueWithMap(SqliteConnection* queue, const std::string& map_path) {
  int reconciled = 0;
  absl::Status status = WithMapAttached(queue, map_path, [&]() -> absl::Status {
    auto txn = SqliteWriteTransaction::Begin(queue);
    if (!txn.ok()) return txn.status();
    // Every passage the map holds must be in the queue, applied or excluded there (or processing,
    // the crash case below). Otherwise the queue file is older than the map, or another map's: its
    // next ids would be ids the map already holds, and passages the map contains would be applied
    // again. Nothing is changed; the operator restores a matching pair.
    auto stray = queue->Prepare(
        "SELECT mp.id, p.state FROM m.map_passages mp LEFT JOIN passages p ON p.id = mp.id "
        "WHERE p.id IS NULL OR p.state NOT IN (2, 3, 6) ORDER BY mp.id");
    if (!stray.ok()) return stray.status();
    int strays = 0;
    std::string examples;
    while (true) {
      auto row = stray->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      if (++strays <= 5) {
        absl::StrAppend(&examples, strays > 1 ? ", " : "", "id ", stray->Int(0), " ",
                        stray->IsNull(1) ? std::string("missing")
                                         : absl::StrCat("in state ", PassageStateName(static_cast<PassageState>(stray->Int(1)))));
      }
    }
    if (strays > 0) {
      return absl::FailedPreconditionError(absl::StrCat(
          "db: the map ", map_path, " holds ", strays, " passage(s) that its queue file does not have as applied (",
          examples, strays > 5 ? ", ..." : "",
          "): the queue file is older than the map, or belongs to another map. Nothing was changed. Restore the map "
          "and its queue from one backup (the map's copy taken first, then the queue's)"));
    }
    // A passage applied in the map but still processing in the queue, or excluded in the map but
    // still applied in the queue: the map's commit landed and the queue's did not.
    constexpr char kBehind[] =
        "SELECT mp.id FROM m.map_passages mp JOIN passages p ON p.id = mp.id "
        "WHERE (mp.state = 3 AND p.state = 2) OR (mp.state = 6 AND p.state = 3)";
    if (auto s = queue->Exec(absl::StrCat("INSERT OR REPLACE INTO passage_results (id, ", kResultColumns,
                                          ") SELECT id, ", kResultColumns, " FROM m.map_passages WHERE id IN (",
                                          kBehind, ");"));
        !s.ok()) {
      return s;
    }
    if (auto s = queue->Exec(absl::StrCat(
            "UPDATE passages SET error = '', "
            "state = (SELECT mp.state FROM m.map_passages mp WHERE mp.id = passages.id), "
            "finished_unix_ms = (SELECT mp.finished_unix_ms FROM m.map_passages mp WHERE mp.id = passages.id) "
            "WHERE id IN (", kBehind, ")"));
        !s.ok()) {
      return s;
    }
    reconciled = queue->Changes();
    // The other way round, the map is behind the queue: it was restored from a backup taken
    // before the queue's (back up the map first, then the queue). Its missing passages are applied
    // again; a passage excluded after the backup is applied in it again and must be excluded again.
    // Unless its upload was deleted after its factors were folded into the base (the backup is
    // older than the retention window): then it cannot be applied again.
    if (auto s = queue->Exec(
            "UPDATE passages SET state = 5, "
            "error = 'the map (restored from an earlier backup) does not contain it, and its upload was deleted "
            "when its factors were folded into the base: upload it again' "
            "WHERE state = 3 AND payload_pruned_unix_ms > 0 AND id NOT IN (SELECT id FROM m.map_passages)");
        !s.ok()) {
      return s;
    }
    reconciled += queue->Changes();
    if (auto s = queue->Exec(
            "UPDATE passages SET state = 1, attempts = 0, finished_unix_ms = 0, "
            "error = 'queued again at start: the map does not contain it (restored from an earlier backup)' "
            "WHERE state = 3 AND id NOT IN (SELECT id FROM m.map_passages)");
        !s.ok()) {
      return s;
    }
    reconciled += queue->Changes();
    if (auto s = queue->Exec(
            "UPDATE passages SET state = 3, "
            "error = 'the map (restored from an earlier backup) contains this excluded passage again: exclude it again' "
            "WHERE state = 6 AND id IN (SELECT id FROM m.map_passages WHERE state = 3)");
        !s.ok()) {
      return s;
    }
    reconciled += queue->Changes();
    return txn->Commit();
  });
  if (!status.ok()) return status;
  return reconciled;
}

}  // namespace crowdmap
