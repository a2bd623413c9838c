#include "server/storage/sqlite_schema.h"

#include <functional>
#include <map>
#include <numeric>
#include <vector>

#include <Eigen/Cholesky>

#include "absl/strings/str_cat.h"
#include "server/storage/factor_codec.h"

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

struct Migration {
  const char* sql;
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
      // 3 -> 4: passages can be quarantined (7) and discarded (8).
      {R"sql(
      INSERT INTO row_counts (name, n) VALUES ('passages_7', 0), ('passages_8', 0);
      )sql", nullptr},
  };
  return kMigrations;
}

}  // namespace

int LatestSchemaVersion() { return static_cast<int>(Migrations().size()); }

absl::Status MigrateSchema(SqliteConnection* db, int target_version) {
  if (target_version < 0) target_version = LatestSchemaVersion();
  while (true) {
    auto txn = SqliteWriteTransaction::Begin(db);
    if (!txn.ok()) return txn.status();
    auto version = db->PragmaInt("user_version");
    if (!version.ok()) return version.status();
    if (*version >= target_version && *version <= LatestSchemaVersion()) return txn->Commit();
    if (*version > LatestSchemaVersion() || *version < 0) {
      return absl::FailedPreconditionError(absl::StrCat("database schema version ", *version,
                                                        " is newer than this server's ", LatestSchemaVersion()));
    }
    const Migration& migration = Migrations()[*version];
    if (auto s = db->Exec(migration.sql); !s.ok()) return s;
    if (migration.then) {
      if (auto s = migration.then(db); !s.ok()) return s;
    }
    if (auto s = db->Exec(absl::StrCat("PRAGMA user_version = ", *version + 1)); !s.ok()) return s;
    if (auto s = txn->Commit(); !s.ok()) return s;
  }
}

}  // namespace crowdmap
