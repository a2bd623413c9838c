// The map side of the SQLite map store: open, reader pool, map commit and map reads.
#include "server/storage/sqlite_map_store.h"

#include <sched.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <unordered_set>

#include <Eigen/LU>

#include "absl/strings/str_cat.h"
#include "spdlog/spdlog.h"
#include "server/storage/map_reads.h"
#include "server/storage/factor_codec.h"
#include "server/storage/sqlite_schema.h"

namespace crowdmap {
namespace {

// Schema 5 moved the passage queue out of the map's file.
constexpr int kLastSchemaWithQueue = 4;

constexpr char kLandmarkColumns[] =
    "SELECT l.id, l.lat_deg, l.lon_deg, l.cov_ee, l.cov_en, l.cov_ne, l.cov_nn, l.version, l.passages_seen, "
    "l.last_seen_unix_ms, l.state, l.anchor_lat_deg, l.anchor_lon_deg FROM landmarks l ";
// Candidates from the R*Tree (float boxes, rounded outwards), then the exact test on the row.
constexpr char kInBox[] =
    "JOIN landmark_boxes b ON b.id = l.id "
    "WHERE b.max_lat >= ?1 AND b.min_lat <= ?3 AND b.max_lon >= ?2 AND b.min_lon <= ?4 "
    "AND l.lat_deg BETWEEN ?1 AND ?3 AND l.lon_deg BETWEEN ?2 AND ?4 ";

// How far a landmark's R*Tree box reaches beyond the position it was written for: about a metre
// (1.1 m north-south, 0.7 m east-west at 50 degrees), against landmarks 8 m and more apart.
constexpr double kBoxMarginDeg = 1e-5;

Landmark LandmarkFromRow(const SqliteStatement& s) {
  Landmark l;
  l.id = s.Int(0);
  l.position = LatLon{s.Double(1), s.Double(2)};
  l.cov_en_m2 << s.Double(3), s.Double(4), s.Double(5), s.Double(6);
  l.version = s.Int(7);
  l.passages_seen = s.Int(8);
  l.last_seen_unix_ms = s.Int(9);
  l.state = static_cast<LandmarkState>(s.Int(10));
  l.anchor = LatLon{s.Double(11), s.Double(12)};
  return l;
}

void BindBox(SqliteStatement& stmt, const BoundingBox& box) {
  stmt.Bind(1, box.min_lat_deg).Bind(2, box.min_lon_deg).Bind(3, box.max_lat_deg).Bind(4, box.max_lon_deg);
}

absl::Status ReadLandmarks(SqliteStatement& stmt, LandmarkPage* page, int limit) {
  while (true) {
    auto row = stmt.Step();
    if (!row.ok()) return row.status();
    if (!*row) return absl::OkStatus();
    if (limit > 0 && static_cast<int>(page->landmarks.size()) == limit) {
      page->more = true;
      return absl::OkStatus();
    }
    page->landmarks.push_back(LandmarkFromRow(stmt));
  }
}

}  // namespace

absl::Status SqliteMapStoreOptions::Validate() const {
  if (busy_timeout_ms < 0) return absl::InvalidArgumentError("busy_timeout_ms must be >= 0");
  if (max_idle_readers < 0) return absl::InvalidArgumentError("max_idle_readers must be >= 0");
  if (write_yield_vm_steps < 0) return absl::InvalidArgumentError("write_yield_vm_steps must be >= 0");
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<MapStoreInterface>> CreateSqliteMapStore(const std::string& path,
                                                                        const SqliteMapStoreOptions& options) {
  auto store = SqliteMapStore::Open(path, options);
  if (!store.ok()) return store.status();
  return std::unique_ptr<MapStoreInterface>(std::move(*store));
}

std::string SqliteQueuePath(const std::string& map_path) { return map_path + ".queue"; }

absl::StatusOr<std::unique_ptr<SqliteMapStore>> SqliteMapStore::Open(const std::string& path,
                                                                    const SqliteMapStoreOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  const std::string queue_path = SqliteQueuePath(path);
  std::error_code ec;
  const bool queue_existed = std::filesystem::exists(queue_path, ec);
  auto map = SqliteFile::Open(path, options.busy_timeout_ms, options.max_idle_readers);
  if (!map.ok()) return map.status();
  {
    SqliteFile::Writer writer = (*map)->LockWriter();
    // Up to the last schema with the queue inside the map's file, so that its queue can move out.
    if (auto s = MigrateSchema(writer.db, kLastSchemaWithQueue); !s.ok()) return s;
    auto version = writer.db->PragmaInt("user_version");
    if (!version.ok()) return version.status();
    if (*version > kLastSchemaWithQueue && !queue_existed) {
      return absl::FailedPreconditionError(
          absl::StrCat("db: the passage queue of ", path, " (", queue_path,
                       ") is missing; restore it from the backup taken with the map, or move the map aside"));
    }
  }
  auto queue = SqliteFile::Open(queue_path, options.busy_timeout_ms, options.max_idle_readers);
  if (!queue.ok()) return queue.status();
  {
    SqliteFile::Writer writer = (*queue)->LockWriter();
    if (auto s = MigrateQueueSchema(writer.db); !s.ok()) return s;
    if (auto s = ImportQueueFromMapFile(writer.db, path); !s.ok()) return s;
  }
  {
    SqliteFile::Writer writer = (*map)->LockWriter();
    if (auto s = MigrateSchema(writer.db); !s.ok()) return s;
    writer.db->OnProgress(options.write_yield_vm_steps, [] { sched_yield(); });
  }
  absl::StatusOr<int64_t> version;  // the map's, once reconciled with the queue
  {
    SqliteFile::Writer writer = (*queue)->LockWriter();
    if (auto n = ReconcileQueueWithMap(writer.db, path); !n.ok()) return n.status();
    SqliteFile::Writer map_writer = (*map)->LockWriter();
    version = RaiseRestoredMapVersion(map_writer.db, writer.db, ReadVersionMark(VersionMarkPath(path)));
    if (!version.ok()) return version.status();
    if (auto s = MarkQueueServed(writer.db); !s.ok()) return s;
  }
  auto store = std::unique_ptr<SqliteMapStore>(
      new SqliteMapStore(options, std::move(*map), std::move(*queue), VersionMarkPath(path)));
  store->WriteVersionMark(*version);
  return store;
}

absl::StatusOr<int64_t> SqliteMapStore::ReadMapVersion(SqliteConnection* db) {
  auto stmt = db->Prepare("SELECT value FROM map_meta WHERE key = 'map_version'");
  if (!stmt.ok()) return stmt.status();
  auto row = stmt->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::DataLossError("map_meta has no map_version");
  return stmt->Int(0);
}

absl::StatusOr<SqliteMapStore::Placements> SqliteMapStore::ReadPlacements(SqliteConnection* db) {
  auto stmt = db->Prepare(
      "SELECT b.id, b.min_lat, b.max_lat, b.min_lon, b.max_lon, l.tile_x, l.tile_y "
      "FROM landmark_boxes b JOIN landmarks l ON l.id = b.id");
  if (!stmt.ok()) return stmt.status();
  Placements placements;
  while (true) {
    auto row = stmt->Step();
    if (!row.ok()) return row.status();
    if (!*row) return placements;
    placements[stmt->Int(0)] = StoredPlacement{stmt->Double(1), stmt->Double(2), stmt->Double(3), stmt->Double(4),
                                               TileId{kStorageZoom, static_cast<int>(stmt->Int(5)),
                                                      static_cast<int>(stmt->Int(6))}};
  }
}

absl::Status SqliteMapStore::WriteLandmark(SqliteConnection* db, const Landmark& l, const StoredPlacement* stored,
                                           StoredPlacement* written) {
  if (!std::isfinite(l.position.lat_deg) || !std::isfinite(l.position.lon_deg) || !l.cov_en_m2.allFinite()) {
    return absl::InternalError(absl::StrCat("landmark ", l.id, " has a non-finite position or covariance"));
  }
  // A map with a non-positive-definite marginal cannot serve as a prior: refuse to store it.
  if (l.cov_en_m2(0, 0) <= 0.0 || l.cov_en_m2(1, 1) <= 0.0 || l.cov_en_m2.determinant() <= 0.0) {
    return absl::InternalError(absl::StrCat("landmark ", l.id, " covariance is not positive definite"));
  }
  const TileId tile = TileContaining(l.position);
  const bool same_tile = stored != nullptr && stored->tile == tile;
  // Rows whose tile stays are updated without the tile's columns, so that SQLite leaves the tile
  // index alone (it rewrites an index whose columns are set, whatever their values).
  auto stmt = same_tile ? db->Prepare(
                              "UPDATE landmarks SET lat_deg = ?2, lon_deg = ?3, cov_ee = ?4, cov_en = ?5, "
                              "cov_ne = ?6, cov_nn = ?7, version = ?8, passages_seen = ?9, last_seen_unix_ms = ?10, "
                              "state = ?11, anchor_lat_deg = ?14, anchor_lon_deg = ?15 WHERE id = ?1")
                        : db->Prepare(
                              "INSERT INTO landmarks (id, lat_deg, lon_deg, cov_ee, cov_en, cov_ne, cov_nn, version, "
                              "passages_seen, last_seen_unix_ms, state, tile_x, tile_y, anchor_lat_deg, "
                              "anchor_lon_deg) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, "
                              "?15) ON CONFLICT (id) DO UPDATE SET lat_deg = excluded.lat_deg, "
                              "lon_deg = excluded.lon_deg, cov_ee = excluded.cov_ee, cov_en = excluded.cov_en, "
                              "cov_ne = excluded.cov_ne, cov_nn = excluded.cov_nn, version = excluded.version, "
                              "passages_seen = excluded.passages_seen, last_seen_unix_ms = excluded.last_seen_unix_ms, "
                              "state = excluded.state, tile_x = excluded.tile_x, tile_y = excluded.tile_y, "
                              "anchor_lat_deg = excluded.anchor_lat_deg, anchor_lon_deg = excluded.anchor_lon_deg");
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, static_cast<int64_t>(l.id))
      .Bind(2, l.position.lat_deg)
      .Bind(3, l.position.lon_deg)
      .Bind(4, l.cov_en_m2(0, 0))
      .Bind(5, l.cov_en_m2(0, 1))
      .Bind(6, l.cov_en_m2(1, 0))
      .Bind(7, l.cov_en_m2(1, 1))
      .Bind(8, l.version)
      .Bind(9, l.passages_seen)
      .Bind(10, l.last_seen_unix_ms)
      .Bind(11, static_cast<int64_t>(l.state));
  if (!same_tile) stmt->Bind(12, static_cast<int64_t>(tile.x)).Bind(13, static_cast<int64_t>(tile.y));
  stmt->Bind(14, l.anchor.lat_deg).Bind(15, l.anchor.lon_deg);
  if (auto s = stmt->Run(); !s.ok()) return s;
  if (same_tile && db->Changes() != 1) {
    return absl::InternalError(absl::StrCat("landmark ", l.id, ": its row is missing from the map file"));
  }
  // The R*Tree's box is rewritten only when the landmark has left it. A passage on a city map
  // moves some 3,000 landmarks by millimetres (its window's solve), and rewriting each one's
  // R*Tree entry took 23 of a commit's 53 ms (docs/results.md, "Two workers once updates got
  // faster"). Boxes reach kBoxMarginDeg beyond the position they were written for, so that such
  // moves stay inside; region reads test the exact position on the row (kInBox), and the margin
  // only adds candidates to that test.
  *written = stored != nullptr ? *stored : StoredPlacement{};
  written->tile = tile;
  if (stored != nullptr && stored->min_lat <= l.position.lat_deg && l.position.lat_deg <= stored->max_lat &&
      stored->min_lon <= l.position.lon_deg && l.position.lon_deg <= stored->max_lon) {
    return absl::OkStatus();
  }
  auto box = db->Prepare("INSERT OR REPLACE INTO landmark_boxes (id, min_lat, max_lat, min_lon, max_lon) "
                         "VALUES (?1, ?2 - ?4, ?2 + ?4, ?3 - ?4, ?3 + ?4)");
  if (!box.ok()) return box.status();
  box->Bind(1, static_cast<int64_t>(l.id)).Bind(2, l.position.lat_deg).Bind(3, l.position.lon_deg).Bind(4, kBoxMarginDeg);
  // The R*Tree rounds its bounds outwards to floats: the box kept here lies inside the stored one.
  written->min_lat = l.position.lat_deg - kBoxMarginDeg;
  written->max_lat = l.position.lat_deg + kBoxMarginDeg;
  written->min_lon = l.position.lon_deg - kBoxMarginDeg;
  written->max_lon = l.position.lon_deg + kBoxMarginDeg;
  return box->Run();
}

absl::Status SqliteMapStore::CheckBaseVersion(SqliteConnection* db, const MapDelta& delta) {
  auto version = ReadMapVersion(db);
  if (!version.ok()) return version.status();
  if (*version != delta.base_version) {
    return absl::FailedPreconditionError(absl::StrCat("map delta computed against version ", delta.base_version,
                                                      " but the stored map is at version ", *version));
  }
  return absl::OkStatus();
}

absl::Status SqliteMapStore::CheckPassageState(SqliteConnection* db, int64_t id, PassageState state) {
  auto passage = ReadPassage(db, id);
  if (!passage.ok()) return passage.status();
  if (!passage->has_value()) return absl::FailedPreconditionError(absl::StrCat("passage id ", id, ": not found"));
  if ((*passage)->state != state) {
    return absl::FailedPreconditionError(absl::StrCat("passage id ", id, " is ", PassageStateName((*passage)->state),
                                                      ", not ", PassageStateName(state)));
  }
  return absl::OkStatus();
}

absl::Status SqliteMapStore::WriteMapDelta(SqliteConnection* db, const MapDelta& delta, const Placements& stored,
                                           Placements* written) {
  const int64_t version = std::max(delta.version, delta.base_version);
  written->reserve(delta.landmarks.size());
  for (const auto& [lid, landmark] : delta.landmarks) {
    const auto it = stored.find(lid);
    if (it == stored.end()) {
      // A landmark that comes back is no longer removed.
      auto stmt = db->Prepare("DELETE FROM removed_landmarks WHERE id = ?1");
      if (!stmt.ok()) return stmt.status();
      stmt->Bind(1, static_cast<int64_t>(lid));
      if (auto s = stmt->Run(); !s.ok()) return s;
    }
    if (auto s = WriteLandmark(db, landmark, it == stored.end() ? nullptr : &it->second, &(*written)[lid]); !s.ok()) {
      return s;
    }
  }
  for (LandmarkId lid : delta.removed_landmarks) {
    // Where it last was, for the watchers whose copies hold it (ChangedLandmarks).
    auto record = db->Prepare(
        "INSERT OR REPLACE INTO removed_landmarks (id, lat_deg, lon_deg, version) "
        "SELECT id, lat_deg, lon_deg, ?2 FROM landmarks WHERE id = ?1");
    if (!record.ok()) return record.status();
    record->Bind(1, static_cast<int64_t>(lid)).Bind(2, version);
    if (auto s = record->Run(); !s.ok()) return s;
    for (const char* sql : {"DELETE FROM landmarks WHERE id = ?1", "DELETE FROM landmark_boxes WHERE id = ?1"}) {
      auto stmt = db->Prepare(sql);
      if (!stmt.ok()) return stmt.status();
      stmt->Bind(1, static_cast<int64_t>(lid));
      if (auto s = stmt->Run(); !s.ok()) return s;
    }
  }
  for (int64_t fid : delta.removed_factors) {
    auto stmt = db->Prepare("DELETE FROM factors WHERE id = ?1");
    if (!stmt.ok()) return stmt.status();
    stmt->Bind(1, fid);
    if (auto s = stmt->Run(); !s.ok()) return s;
  }
  for (int64_t fid : delta.folded_factors) {
    if (auto s = FoldFactor(db, fid); !s.ok()) return s;
  }
  for (const auto& [vehicle_id, vehicle] : delta.vehicles) {
    if (auto s = WriteVehicle(db, vehicle); !s.ok()) return s;
  }
  int64_t last_factor_id = 0;
  for (const auto& [fid, factor] : delta.added_factors) {
    if (!factor.information.allFinite() || !factor.information_vector.allFinite()) {
      return absl::InternalError(absl::StrCat("factor ", fid, " has non-finite numbers"));
    }
    if (factor.id != fid) return absl::InternalError(absl::StrCat("factor ", fid, " is filed under id ", factor.id));
    if (auto s = InsertFactorRow(db, factor); !s.ok()) return s;
    last_factor_id = std::max(last_factor_id, fid);
  }
  if (last_factor_id > 0) {
    auto stmt = db->Prepare("UPDATE map_meta SET value = MAX(value, ?1) WHERE key = 'last_factor_id'");
    if (!stmt.ok()) return stmt.status();
    stmt->Bind(1, last_factor_id);
    if (auto s = stmt->Run(); !s.ok()) return s;
  }
  auto set_version = db->Prepare("UPDATE map_meta SET value = ?1 WHERE key = 'map_version'");
  if (!set_version.ok()) return set_version.status();
  set_version->Bind(1, version);
  if (auto s = set_version->Run(); !s.ok()) return s;

  return absl::OkStatus();
}

absl::Status SqliteMapStore::WriteVehicle(SqliteConnection* db, const VehicleCalibration& v) {
  auto stmt = db->Prepare(
      "INSERT OR REPLACE INTO vehicles (vehicle_id, camera_yaw_offset_rad, camera_yaw_variance_rad2, "
      "camera_yaw_information, camera_yaw_map_term, passages, version, updated_unix_ms) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)");
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, v.vehicle_id);
  stmt->Bind(2, v.camera_yaw_offset_rad);
  stmt->Bind(3, v.camera_yaw_variance_rad2);
  stmt->Bind(4, v.camera_yaw_information);
  stmt->Bind(5, v.camera_yaw_map_term);
  stmt->Bind(6, v.passages);
  stmt->Bind(7, v.version);
  stmt->Bind(8, v.updated_unix_ms);
  return stmt->Run();
}

absl::StatusOr<std::vector<VehicleCalibration>> SqliteMapStore::ReadVehicles(
    SqliteConnection* db, const std::string& where, const std::function<void(SqliteStatement&)>& bind) {
  auto stmt = db->Prepare(absl::StrCat(
      "SELECT vehicle_id, camera_yaw_offset_rad, camera_yaw_variance_rad2, camera_yaw_information, "
      "camera_yaw_map_term, passages, version, updated_unix_ms "
      "FROM vehicles ",
      where));
  if (!stmt.ok()) return stmt.status();
  bind(*stmt);
  std::vector<VehicleCalibration> out;
  while (true) {
    auto row = stmt->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    VehicleCalibration v;
    v.vehicle_id = stmt->Text(0);
    v.camera_yaw_offset_rad = stmt->Double(1);
    v.camera_yaw_variance_rad2 = stmt->Double(2);
    v.camera_yaw_information = stmt->Double(3);
    v.camera_yaw_map_term = stmt->Double(4);
    v.passages = stmt->Int(5);
    v.version = stmt->Int(6);
    v.updated_unix_ms = stmt->Int(7);
    out.push_back(std::move(v));
  }
  return out;
}

absl::StatusOr<VehicleCalibration> SqliteMapStore::GetVehicle(const std::string& vehicle_id) {
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  absl::StatusOr<std::vector<VehicleCalibration>> found =
      ReadVehicles(db->get(), "WHERE vehicle_id = ?1", [&](SqliteStatement& s) { s.Bind(1, vehicle_id); });
  if (!found.ok()) return found.status();
  if (found->empty()) {
    return absl::NotFoundError(absl::StrCat("vehicle_id: no camera calibration estimated for '", vehicle_id, "'"));
  }
  return found->front();
}

absl::StatusOr<std::vector<VehicleCalibration>> SqliteMapStore::ListVehicles(const std::string& after, int limit) {
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  return ReadVehicles(db->get(), "WHERE vehicle_id > ?1 ORDER BY vehicle_id LIMIT ?2", [&](SqliteStatement& s) {
    s.Bind(1, after);
    s.Bind(2, limit > 0 ? static_cast<int64_t>(limit) : int64_t{-1});  // SQLite: a negative limit is none
  });
}

absl::Status SqliteMapStore::FoldFactor(SqliteConnection* db, int64_t id) {
  absl::StatusOr<MapFactor> factor = absl::InternalError(absl::StrCat("factor ", id, " to fold is not stored"));
  {
    auto read = db->Prepare(
        "SELECT vehicle_id, passage_id, landmark_ids, information, information_vector FROM factors WHERE id = ?1");
    if (!read.ok()) return read.status();
    read->Bind(1, id);
    auto row = read->Step();
    if (!row.ok()) return row.status();
    if (*row) {
      factor = DecodeFactor(id, read->Text(0), read->Text(1),
                            EncodedFactor{read->Blob(2), read->Blob(3), read->Blob(4)});
    }
  }
  if (!factor.ok()) return factor.status();
  const std::vector<LandmarkId>& ids = factor->landmarks;
  for (size_t i = 0; i < ids.size(); ++i) {
    for (size_t j = 0; j < ids.size(); ++j) {
      if (ids[i] > ids[j] || (ids[i] == ids[j] && i != j)) continue;
      const Eigen::Matrix2d v = factor->information.block<2, 2>(2 * i, 2 * j);
      auto block = db->Prepare(
          "INSERT INTO base_blocks (a, b, ee, en, ne, nn) VALUES (?1, ?2, ?3, ?4, ?5, ?6) ON CONFLICT (a, b) DO "
          "UPDATE SET ee = ee + excluded.ee, en = en + excluded.en, ne = ne + excluded.ne, nn = nn + excluded.nn");
      if (!block.ok()) return block.status();
      block->Bind(1, static_cast<int64_t>(ids[i]))
          .Bind(2, static_cast<int64_t>(ids[j]))
          .Bind(3, v(0, 0))
          .Bind(4, v(0, 1))
          .Bind(5, v(1, 0))
          .Bind(6, v(1, 1));
      if (auto s = block->Run(); !s.ok()) return s;
    }
    const Eigen::Vector2d e = factor->information_vector.segment<2>(2 * i);
    auto vector = db->Prepare(
        "INSERT INTO base_vectors (id, e, n) VALUES (?1, ?2, ?3) ON CONFLICT (id) DO UPDATE "
        "SET e = e + excluded.e, n = n + excluded.n");
    if (!vector.ok()) return vector.status();
    vector->Bind(1, static_cast<int64_t>(ids[i])).Bind(2, e.x()).Bind(3, e.y());
    if (auto s = vector->Run(); !s.ok()) return s;
  }
  auto erase = db->Prepare("DELETE FROM factors WHERE id = ?1");
  if (!erase.ok()) return erase.status();
  erase->Bind(1, id);
  return erase->Run();
}

absl::Status SqliteMapStore::CommitMapChange(int64_t id, const MapDelta& delta, PassageState from, PassageState to,
                                             const std::optional<PassageResult>& result) {
  // Only the worker moves a passage out of processing or applied, one change at a time, so the
  // state checked here still holds when the queue records the change.
  {
    auto queue = queue_->AcquireReader();
    if (!queue.ok()) return queue.status();
    if (auto s = CheckPassageState(queue->get(), id, from); !s.ok()) return s;
  }
  PendingConfirmation change{id, from, to, NowUnixMs(), result, std::max(delta.version, delta.base_version)};
  {
    SqliteFile::Writer writer = map_->LockWriter();
    SqliteConnection* db = writer.db;
    auto txn = SqliteWriteTransaction::Begin(db);
    if (!txn.ok()) return txn.status();
    if (auto s = CheckBaseVersion(db, delta); !s.ok()) return s;
    if (!placements_) {
      auto read = ReadPlacements(db);
      if (!read.ok()) return read.status();
      placements_ = std::move(*read);
    }
    Placements written;
    if (auto s = WriteMapDelta(db, delta, *placements_, &written); !s.ok()) {
      // Nothing of it stays, but the error may come from placements that disagree with the file.
      placements_.reset();
      return s;
    }
    if (result) {
      if (auto s = WriteResult(db, "map_passages", id, *result); !s.ok()) return s;
    }
    auto mark = db->Prepare("UPDATE map_passages SET state = ?2, finished_unix_ms = ?3 WHERE id = ?1");
    if (!mark.ok()) return mark.status();
    mark->Bind(1, id).Bind(2, static_cast<int64_t>(to)).Bind(3, change.finished_unix_ms);
    if (auto s = mark->Run(); !s.ok()) return s;
    if (auto s = txn->Commit(); !s.ok()) {
      placements_.reset();  // read again, whether or not a failed COMMIT left anything written
      return s;
    }
    for (auto& [lid, placement] : written) (*placements_)[lid] = placement;
    for (LandmarkId lid : delta.removed_landmarks) placements_->erase(lid);
    WriteVersionMark(change.map_version);
  }
  SqliteFile::Writer writer = queue_->LockWriter();
  pending_.push_back(std::move(change));
  ConfirmPending(writer.db);
  return absl::OkStatus();
}

absl::Status SqliteMapStore::RecordMapChange(SqliteConnection* queue, const PendingConfirmation& change) {
  auto txn = SqliteWriteTransaction::Begin(queue);
  if (!txn.ok()) return txn.status();
  auto mark = queue->Prepare(
      "UPDATE passages SET state = ?3, error = '', finished_unix_ms = ?2 WHERE id = ?1 AND state = ?4");
  if (!mark.ok()) return mark.status();
  mark->Bind(1, change.id)
      .Bind(2, change.finished_unix_ms)
      .Bind(3, static_cast<int64_t>(change.to))
      .Bind(4, static_cast<int64_t>(change.from));
  if (auto s = mark->Run(); !s.ok()) return s;
  if (queue->Changes() != 1) {
    return absl::InternalError(absl::StrCat("passage id ", change.id, " left ", PassageStateName(change.from),
                                            " while its map change was committed"));
  }
  if (change.result) {
    if (auto s = WriteResult(queue, "passage_results", change.id, *change.result); !s.ok()) return s;
  }
  if (auto s = RecordMapVersionSeen(queue, change.map_version); !s.ok()) return s;
  return txn->Commit();
}

absl::Status SqliteMapStore::RecordMapVersionSeen(SqliteConnection* queue, int64_t version) {
  auto seen = queue->Prepare(
      "INSERT INTO queue_meta (key, value) VALUES ('map_version_seen', ?1) "
      "ON CONFLICT (key) DO UPDATE SET value = MAX(value, excluded.value)");
  if (!seen.ok()) return seen.status();
  seen->Bind(1, version);
  return seen->Run();
}

int64_t SqliteMapStore::ReadVersionMark(const std::string& path) {
  std::ifstream in(path);
  int64_t version = 0;
  if (!(in >> version) || version < 0) return 0;
  return version;
}

void SqliteMapStore::WriteVersionMark(int64_t version) const {
  // Written whole each time (a few bytes): a torn write leaves an unreadable mark, read as none.
  std::ofstream out(version_mark_path_, std::ios::trunc);
  out << version << "\n";
  if (!out.flush()) spdlog::warn("event=version_mark_failed path={} version={}", version_mark_path_, version);
}

absl::StatusOr<int64_t> SqliteMapStore::RaiseRestoredMapVersion(SqliteConnection* map, SqliteConnection* queue,
                                                                int64_t marked) {
  // Queues written before the key existed: the versions of their applied passages' results.
  auto seen = queue->Prepare(
      "SELECT MAX(COALESCE((SELECT value FROM queue_meta WHERE key = 'map_version_seen'), 0), "
      "COALESCE((SELECT MAX(map_version) FROM passage_results), 0))");
  if (!seen.ok()) return seen.status();
  if (auto row = seen->Step(); !row.ok()) return row.status();
  const int64_t seen_version = std::max(seen->Int(0), marked);
  auto txn = SqliteWriteTransaction::Begin(map);
  if (!txn.ok()) return txn.status();
  absl::StatusOr<int64_t> version = ReadMapVersion(map);
  if (!version.ok()) return version.status();
  if (*version < seen_version) {
    // A new range of versions: the queue was backed up after the map, and the server went on
    // past what it recorded, to versions clients saw. Above any of them, however far it went.
    const int64_t raised = (seen_version / kRestoredVersionStep + 1) * kRestoredVersionStep;
    if (auto s = map->Exec(absl::StrCat("UPDATE map_meta SET value = ", raised, " WHERE key = 'map_version';",
                                        "UPDATE landmarks SET version = ", raised, ";",
                                        "UPDATE removed_landmarks SET version = ", raised, ";"));
        !s.ok()) {
      return s;
    }
    spdlog::warn(
        "event=map_version_raised from={} to={} (the map is older than its queue or its version mark, restored from a "
        "backup: every landmark is stamped with the new version, so that watchers read them again)",
        *version, raised);
    *version = raised;
  }
  if (auto s = txn->Commit(); !s.ok()) return s;
  auto txn_queue = SqliteWriteTransaction::Begin(queue);
  if (!txn_queue.ok()) return txn_queue.status();
  if (auto s = RecordMapVersionSeen(queue, *version); !s.ok()) return s;
  if (auto s = txn_queue->Commit(); !s.ok()) return s;
  return version;
}

void SqliteMapStore::ConfirmPending(SqliteConnection* queue) {
  std::vector<PendingConfirmation> still;
  for (PendingConfirmation& change : pending_) {
    absl::Status s = RecordMapChange(queue, change);
    if (absl::IsInternal(s)) {
      spdlog::error("storage: {}", std::string(s.message()));  // nothing to retry: the queue moved on
    } else if (!s.ok()) {
      spdlog::warn("storage: passage id {} is {} in the map but not yet in the queue ({}); retried at the next queue "
                   "write or start",
                   change.id, PassageStateName(change.to), std::string(s.message()));
      still.push_back(std::move(change));
    }
  }
  pending_ = std::move(still);
}

absl::Status SqliteMapStore::CommitPassageExcluded(int64_t id, const MapDelta& delta) {
  return CommitMapChange(id, delta, PassageState::kApplied, PassageState::kExcluded, std::nullopt);
}

absl::Status SqliteMapStore::CommitPassageRelinearized(int64_t id, const MapDelta& delta) {
  return CommitMapChange(id, delta, PassageState::kApplied, PassageState::kApplied, std::nullopt);
}

absl::Status SqliteMapStore::CommitPassageApplied(int64_t id, const MapDelta& delta, const PassageResult& result) {
  return CommitMapChange(id, delta, PassageState::kProcessing, PassageState::kApplied, result);
}

absl::Status SqliteMapStore::WriteResult(SqliteConnection* db, const std::string& table, int64_t id,
                                         const PassageResult& result) {
  // map_passages also has state and finished_unix_ms, set by the caller after this row exists.
  const bool map_side = table == "map_passages";
  auto res = db->Prepare(absl::StrCat(
      "INSERT OR REPLACE INTO ", table, " (id, nodes, subgraphs, landmarks_updated, landmarks_created, "
      "landmarks_conditioned, detections_used, detections_dropped, solver_iterations, final_cost, solve_ms, "
      "covariance_ms, total_ms, map_version, strategy", map_side ? ", state, finished_unix_ms" : "",
      ") VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15", map_side ? ", 0, 0" : "", ")"));
  if (!res.ok()) return res.status();
  res->Bind(1, id)
      .Bind(2, static_cast<int64_t>(result.nodes))
      .Bind(3, static_cast<int64_t>(result.subgraphs))
      .Bind(4, static_cast<int64_t>(result.landmarks_updated))
      .Bind(5, static_cast<int64_t>(result.landmarks_created))
      .Bind(6, static_cast<int64_t>(result.landmarks_conditioned))
      .Bind(7, static_cast<int64_t>(result.detections_used))
      .Bind(8, static_cast<int64_t>(result.detections_dropped))
      .Bind(9, static_cast<int64_t>(result.solver_iterations))
      .Bind(10, result.final_cost)
      .Bind(11, result.solve_ms)
      .Bind(12, result.covariance_ms)
      .Bind(13, result.total_ms)
      .Bind(14, result.map_version)
      .Bind(15, std::string_view(result.strategy));
  return res->Run();
}

absl::Status SqliteMapStore::LoadMap(MapState* map) {
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  auto snapshot = SqliteReadTransaction::Begin(db->get());
  if (!snapshot.ok()) return snapshot.status();
  return ReadMap(db->get(), map);
}

absl::Status SqliteMapStore::ReadMap(SqliteConnection* db, MapState* map) {
  auto landmarks = db->Prepare(absl::StrCat(kLandmarkColumns, "ORDER BY l.id"));
  if (!landmarks.ok()) return landmarks.status();
  while (true) {
    auto row = landmarks->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    map->PutLandmark(LandmarkFromRow(*landmarks));
  }
  auto factors = db->Prepare(
      "SELECT id, vehicle_id, passage_id, landmark_ids, information, information_vector FROM factors ORDER BY id");
  if (!factors.ok()) return factors.status();
  while (true) {
    auto row = factors->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    absl::StatusOr<MapFactor> factor = DecodeFactor(
        factors->Int(0), factors->Text(1), factors->Text(2),
        EncodedFactor{factors->Blob(3), factors->Blob(4), factors->Blob(5)});
    if (!factor.ok()) return factor.status();
    map->PutFactor(*std::move(factor));
  }
  auto blocks = db->Prepare("SELECT a, b, ee, en, ne, nn FROM base_blocks");
  if (!blocks.ok()) return blocks.status();
  while (true) {
    auto row = blocks->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    Eigen::Matrix2d v;
    v << blocks->Double(2), blocks->Double(3), blocks->Double(4), blocks->Double(5);
    map->PutBaseBlock(blocks->Int(0), blocks->Int(1), v);
  }
  auto vectors = db->Prepare("SELECT id, e, n FROM base_vectors");
  if (!vectors.ok()) return vectors.status();
  while (true) {
    auto row = vectors->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    map->PutBaseVector(vectors->Int(0), Eigen::Vector2d(vectors->Double(1), vectors->Double(2)));
  }
  absl::StatusOr<std::vector<VehicleCalibration>> vehicles = ReadVehicles(db, "", [](SqliteStatement&) {});
  if (!vehicles.ok()) return vehicles.status();
  for (const VehicleCalibration& v : *vehicles) map->PutVehicle(v);
  auto last = db->Prepare("SELECT value FROM map_meta WHERE key = 'last_factor_id'");
  if (!last.ok()) return last.status();
  if (auto row = last->Step(); !row.ok()) return row.status();
  map->set_last_factor_id(last->Int(0));
  auto version = ReadMapVersion(db);
  if (!version.ok()) return version.status();
  map->set_version(*version);
  return absl::OkStatus();
}

absl::StatusOr<LandmarkPage> SqliteMapStore::ReadPage(
    const std::string& where, const std::function<void(SqliteStatement&)>& bind, int limit, bool include_cross,
    const std::function<absl::Status(SqliteConnection*, LandmarkPage*)>& read_more) {
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  // One read transaction: the version, the landmarks and their blocks come from the same commit.
  auto snapshot = SqliteReadTransaction::Begin(db->get());
  if (!snapshot.ok()) return snapshot.status();
  LandmarkPage page;
  auto version = ReadMapVersion(db->get());
  if (!version.ok()) return version.status();
  page.map_version = *version;
  auto stmt = (*db)->Prepare(absl::StrCat(kLandmarkColumns, where));
  if (!stmt.ok()) return stmt.status();
  bind(*stmt);
  if (auto s = ReadLandmarks(*stmt, &page, limit); !s.ok()) return s;
  if (read_more) {
    if (auto s = read_more(db->get(), &page); !s.ok()) return s;
  }
  if (include_cross && !page.landmarks.empty()) {
    // Without a map in memory (CachedMapStore has one), the whole map is read in the snapshot.
    MapState map;
    if (auto s = ReadMap(db->get(), &map); !s.ok()) return s;
    if (auto s = AppendCrossCovariances(map, options_.covariance_window_hops, &page); !s.ok()) return s;
  }
  return page;
}

absl::StatusOr<LandmarkPage> SqliteMapStore::QueryRegion(const BoundingBox& box, LandmarkId after_id, int limit,
                                                         bool include_cross) {
  return ReadPage(
      absl::StrCat(kInBox, "AND l.id > ?5 ORDER BY l.id LIMIT ?6"),
      [&](SqliteStatement& stmt) {
        BindBox(stmt, box);
        // One more than the page tells whether more follow; a negative LIMIT is none (limit 0).
        stmt.Bind(5, static_cast<int64_t>(after_id)).Bind(6, limit > 0 ? static_cast<int64_t>(limit) + 1 : -1);
      },
      limit, include_cross);
}

absl::StatusOr<LandmarkPage> SqliteMapStore::GetTile(const TileId& tile, bool include_cross) {
  if (tile.z != kStorageZoom || !IsValidTile(tile)) {
    return absl::InvalidArgumentError(absl::StrCat("tile: ", tile.z, "/", tile.x, "/", tile.y,
                                                   " is not a valid tile at the storage zoom ", kStorageZoom));
  }
  return ReadPage(
      "WHERE l.tile_x = ?1 AND l.tile_y = ?2 ORDER BY l.id",
      [&](SqliteStatement& stmt) { stmt.Bind(1, static_cast<int64_t>(tile.x)).Bind(2, static_cast<int64_t>(tile.y)); },
      0, include_cross);
}

absl::StatusOr<LandmarkPage> SqliteMapStore::GetLandmarks(const std::vector<LandmarkId>& ids, bool include_cross) {
  std::string list = "[";
  for (size_t i = 0; i < ids.size(); ++i) absl::StrAppend(&list, i ? "," : "", ids[i]);
  list += "]";
  return ReadPage(
      "WHERE l.id IN (SELECT value FROM json_each(?1)) ORDER BY l.id",
      [&](SqliteStatement& stmt) { stmt.Bind(1, list); }, 0, include_cross);
}

absl::StatusOr<LandmarkPage> SqliteMapStore::ChangedLandmarks(const BoundingBox& box, int64_t since_version) {
  return ReadPage(
      absl::StrCat(kInBox, "AND l.version > ?5 ORDER BY l.id"),
      [&](SqliteStatement& stmt) {
        BindBox(stmt, box);
        stmt.Bind(5, since_version);
      },
      0, /*include_cross=*/false, [&](SqliteConnection* db, LandmarkPage* page) -> absl::Status {
        auto stmt = db->Prepare(
            "SELECT id FROM removed_landmarks WHERE version > ?5 AND lat_deg BETWEEN ?1 AND ?3 "
            "AND lon_deg BETWEEN ?2 AND ?4 ORDER BY id");
        if (!stmt.ok()) return stmt.status();
        BindBox(*stmt, box);
        stmt->Bind(5, since_version);
        while (true) {
          auto row = stmt->Step();
          if (!row.ok()) return row.status();
          if (!*row) return absl::OkStatus();
          page->removed.push_back(stmt->Int(0));
        }
      });
}

absl::StatusOr<std::vector<RemovedLandmark>> SqliteMapStore::RemovedLandmarks() {
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  auto stmt = (*db)->Prepare("SELECT id, lat_deg, lon_deg, version FROM removed_landmarks ORDER BY id");
  if (!stmt.ok()) return stmt.status();
  std::vector<RemovedLandmark> out;
  while (true) {
    auto row = stmt->Step();
    if (!row.ok()) return row.status();
    if (!*row) return out;
    out.push_back({stmt->Int(0), LatLon{stmt->Double(1), stmt->Double(2)}, stmt->Int(3)});
  }
}

absl::StatusOr<LandmarkProvenance> SqliteMapStore::GetLandmarkProvenance(LandmarkId id) {
  // Without a map in memory (CachedMapStore has one) the whole map is read in one snapshot.
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  auto snapshot = SqliteReadTransaction::Begin(db->get());
  if (!snapshot.ok()) return snapshot.status();
  MapState map;
  if (auto s = ReadMap(db->get(), &map); !s.ok()) return s;
  return ProvenanceOf(map, id);
}

absl::StatusOr<MapStats> SqliteMapStore::GetStats() {
  auto db = map_->AcquireReader();
  if (!db.ok()) return db.status();
  auto snapshot = SqliteReadTransaction::Begin(db->get());
  if (!snapshot.ok()) return snapshot.status();
  MapStats stats;
  auto version = ReadMapVersion(db->get());
  if (!version.ok()) return version.status();
  stats.map_version = *version;
  // Kept by the schema's triggers (migration 2), so no table is scanned.
  auto counts = (*db)->Prepare("SELECT name, n FROM row_counts");
  if (!counts.ok()) return counts.status();
  while (true) {
    auto row = counts->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    const std::string name = counts->Text(0);
    const int64_t n = counts->Int(1);
    if (name == "landmarks") {
      stats.landmark_count = n;
    } else if (name == "factors") {
      stats.factor_count = n;
    }
  }
  // The passages' counts, from the queue file's own (a separate snapshot: a passage's map change
  // may show there a moment later).
  auto queue = queue_->AcquireReader();
  if (!queue.ok()) return queue.status();
  auto passages = (*queue)->Prepare("SELECT name, n FROM row_counts");
  if (!passages.ok()) return passages.status();
  while (true) {
    auto row = passages->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    const std::string name = passages->Text(0);
    for (int state = 1; state < kPassageStateCount; ++state) {
      if (name == absl::StrCat("passages_", state)) stats.passages_by_state[state] = passages->Int(1);
    }
  }
  return stats;
}

}  // namespace crowdmap
