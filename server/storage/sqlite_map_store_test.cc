#include "server/storage/map_store.h"

#include <sqlite3.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <thread>

#include "gtest/gtest.h"
#include "server/storage/cached_map_store.h"
#include "server/storage/sqlite_db.h"
#include "server/storage/sqlite_schema.h"
#include "core/map/map_window.h"
#include <Eigen/LU>
#include "server/testing/temp_dir.h"

namespace crowdmap {
namespace {

NewPassage MakeUpload(const std::string& vehicle, const std::string& passage, const std::string& payload = "bytes") {
  return NewPassage{vehicle, passage, payload, 1000};
}

Landmark MakeLandmark(LandmarkId id, double lat, double lon, int64_t version) {
  Landmark l;
  l.id = id;
  l.position = {lat, lon};
  l.anchor = {lat - 1e-6, lon + 2e-6};
  l.cov_en_m2 << 0.5, 0.1, 0.1, 0.7;
  l.version = version;
  l.passages_seen = 1;
  l.last_seen_unix_ms = 42;
  return l;
}

// A factor whose information is the inverse of `cov` (its landmarks at their anchors).
MapFactor MakeFactor(int64_t id, const std::vector<LandmarkId>& ids, const Eigen::MatrixXd& cov) {
  MapFactor f;
  f.id = id;
  f.vehicle_id = "v";
  f.passage_id = "p" + std::to_string(id);
  f.landmarks = ids;
  const Eigen::MatrixXd inverse = cov.inverse();
  f.information = 0.5 * (inverse + inverse.transpose());  // symmetric, as the core's are
  f.information_vector = Eigen::VectorXd::LinSpaced(cov.rows(), 0.5, 1.5);
  return f;
}

// The joint covariance of two landmarks with the marginals of MakeLandmark and cross block `c`.
Eigen::MatrixXd PairCovariance(const Eigen::Matrix2d& c) {
  Eigen::MatrixXd cov(4, 4);
  cov << 0.5, 0.1, c(0, 0), c(0, 1), 0.1, 0.7, c(1, 0), c(1, 1), c(0, 0), c(1, 0), 0.5, 0.1, c(0, 1), c(1, 1), 0.1, 0.7;
  return cov;
}

std::unique_ptr<MapStoreInterface> OpenStore(const std::string& path) {
  auto store = CreateSqliteMapStore(path);
  EXPECT_TRUE(store.ok()) << store.status();
  return store.ok() ? std::move(*store) : nullptr;
}

// Enqueues and claims one passage so that a map change can be committed for it.
int64_t EnqueueAndClaim(MapStoreInterface* store, const std::string& passage_id) {
  auto out = store->EnqueuePassages({MakeUpload("v", passage_id)}, 0);
  EXPECT_TRUE(out.ok());
  auto claimed = store->ClaimNextPassage();
  EXPECT_TRUE(claimed.ok() && claimed->has_value());
  return (*claimed)->record.id;
}

int64_t SqlInt(const std::string& path, const std::string& sql) {
  sqlite3* db = nullptr;
  sqlite3_open(path.c_str(), &db);
  sqlite3_stmt* stmt = nullptr;
  sqlite3_prepare_v2(db, sql.c_str(), -1, &stmt, nullptr);
  int64_t v = -1;
  if (sqlite3_step(stmt) == SQLITE_ROW) v = sqlite3_column_int64(stmt, 0);
  sqlite3_finalize(stmt);
  sqlite3_close(db);
  return v;
}

std::string SqlText(const std::string& path, const std::string& sql) {
  sqlite3* db = nullptr;
  sqlite3_open(path.c_str(), &db);
  sqlite3_stmt* stmt = nullptr;
  sqlite3_prepare_v2(db, sql.c_str(), -1, &stmt, nullptr);
  std::string v;
  if (sqlite3_step(stmt) == SQLITE_ROW) v = reinterpret_cast<const char*>(sqlite3_column_text(stmt, 0));
  sqlite3_finalize(stmt);
  sqlite3_close(db);
  return v;
}

TEST(SqliteMapStore, CreatesMigratedWalDatabaseOnFirstOpen) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  { auto store = OpenStore(path); }
  EXPECT_GE(SqlInt(path, "PRAGMA user_version"), 1);
  EXPECT_EQ(SqlText(path, "PRAGMA journal_mode"), "wal");
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM sqlite_master WHERE name = 'landmark_boxes'"), 1);
  // Reopening an up-to-date file runs no migration and keeps the data.
  auto store = OpenStore(path);
  ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "p")}, 0).ok());
  store.reset();
  store = OpenStore(path);
  EXPECT_TRUE(store->FindPassage("v", "p").ok());
}

TEST(SqliteConnection, OnProgressIsCalledDuringALongStatementUntilRemoved) {
  TempDir dir;
  auto db = SqliteConnection::Open(dir.File("progress.db"), 1000, /*read_only=*/false);
  ASSERT_TRUE(db.ok()) << db.status();
  const std::string insert =
      "WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n WHERE i < 10000) INSERT INTO t SELECT i FROM n";
  ASSERT_TRUE((*db)->Exec("CREATE TABLE t (x INTEGER)").ok());
  int calls = 0;
  (*db)->OnProgress(1000, [&calls] { ++calls; });
  ASSERT_TRUE((*db)->Exec(insert).ok());
  EXPECT_GT(calls, 10);  // some 10 steps per row
  const int before = calls;
  (*db)->OnProgress(0, nullptr);
  ASSERT_TRUE((*db)->Exec(insert).ok());
  EXPECT_EQ(calls, before);
  EXPECT_EQ(SqlInt(dir.File("progress.db"), "SELECT COUNT(*) FROM t"), 20000);
}

// Commits leave checkpoints to the file's own thread (SqliteFile::kCheckpointPages): a commit's
// pages reach the database file with no further write of the writer's.
TEST(SqliteFile, ALongWriteAheadLogIsCheckpointedAfterItsCommit) {
  TempDir dir;
  const std::string path = dir.File("log.db");
  auto file = SqliteFile::Open(path, 1000, 1);
  ASSERT_TRUE(file.ok()) << file.status();
  {
    SqliteFile::Writer writer = (*file)->LockWriter();
    ASSERT_TRUE(writer.db->Exec("CREATE TABLE t (b BLOB NOT NULL)").ok());
    auto txn = SqliteWriteTransaction::Begin(writer.db);
    ASSERT_TRUE(txn.ok());
    auto insert = writer.db->Prepare("INSERT INTO t (b) VALUES (zeroblob(4000))");
    ASSERT_TRUE(insert.ok());
    for (int i = 0; i < 2 * SqliteFile::kCheckpointPages; ++i) ASSERT_TRUE(insert->Run().ok());
    ASSERT_TRUE(txn->Commit().ok());
  }
  const auto file_size = [&] {
    std::error_code ec;
    const auto size = std::filesystem::file_size(path, ec);
    return ec ? 0 : size;
  };
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (file_size() < 8'000'000 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  EXPECT_GE(file_size(), 8'000'000u) << "the log was not copied into the database";
}

TEST(SqliteConnection, AFullDatabaseAnswersResourceExhaustedWithAMessage) {
  // max_page_count caps this connection's database as a full disk would.
  TempDir dir;
  auto db = SqliteConnection::Open(dir.File("full.db"), 1000, /*read_only=*/false);
  ASSERT_TRUE(db.ok()) << db.status();
  ASSERT_TRUE((*db)->Exec("CREATE TABLE t (x BLOB)").ok());
  ASSERT_TRUE((*db)->PragmaInt("max_page_count = 16").ok());
  absl::Status s;
  for (int i = 0; i < 100 && s.ok(); ++i) s = (*db)->Exec("INSERT INTO t VALUES (zeroblob(4000))");
  EXPECT_EQ(s.code(), absl::StatusCode::kResourceExhausted) << s;
  EXPECT_NE(s.message().find("no space left"), std::string::npos) << s;
}

TEST(SqliteMapStore, RefusesNegativeWriteYieldSteps) {
  TempDir dir;
  SqliteMapStoreOptions options;
  options.write_yield_vm_steps = -1;
  auto store = CreateSqliteMapStore(dir.File("map.db"), options);
  ASSERT_FALSE(store.ok());
  EXPECT_NE(store.status().message().find("write_yield_vm_steps"), std::string::npos);
}

TEST(SqliteMapStore, RefusesDatabaseFromNewerSchema) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  { auto store = OpenStore(path); }
  sqlite3* db = nullptr;
  sqlite3_open(path.c_str(), &db);
  sqlite3_exec(db, "PRAGMA user_version = 999", nullptr, nullptr, nullptr);
  sqlite3_close(db);
  auto store = CreateSqliteMapStore(path);
  EXPECT_EQ(store.status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST(SqliteMapStore, EnqueueAssignsIdsInArrivalOrderAndStoresPayload) {
  TempDir dir;
  auto store = OpenStore(dir.File("map.db"));
  auto out = store->EnqueuePassages({MakeUpload("v1", "a", "AAA"), MakeUpload("v2", "b", "BBBB")}, 0);
  ASSERT_TRUE(out.ok());
  ASSERT_EQ(out->size(), 2u);
  ASSERT_TRUE((*out)[0].ok() && (*out)[1].ok());
  EXPECT_LT((*out)[0]->record.id, (*out)[1]->record.id);
  EXPECT_EQ((*out)[0]->record.state, PassageState::kQueued);
  EXPECT_FALSE((*out)[0]->duplicate);
  EXPECT_EQ((*out)[1]->record.size_bytes, 4);
  auto payload = store->GetPassagePayload((*out)[1]->record.id);
  ASSERT_TRUE(payload.ok());
  EXPECT_EQ(*payload, "BBBB");
}

TEST(SqliteMapStore, DuplicateKeyReturnsOriginalRecordAndStoresNothingNew) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  auto first = store->EnqueuePassages({MakeUpload("v", "p", "first")}, 0);
  ASSERT_TRUE(first.ok() && (*first)[0].ok());
  // Again later, and twice inside one batch.
  auto again = store->EnqueuePassages({MakeUpload("v", "p", "second"), MakeUpload("w", "q"), MakeUpload("w", "q")}, 0);
  ASSERT_TRUE(again.ok());
  EXPECT_TRUE((*again)[0]->duplicate);
  EXPECT_EQ((*again)[0]->record.id, (*first)[0]->record.id);
  EXPECT_FALSE((*again)[1]->duplicate);
  EXPECT_TRUE((*again)[2]->duplicate);
  EXPECT_EQ((*again)[2]->record.id, (*again)[1]->record.id);
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages"), 2);
  EXPECT_EQ(*store->GetPassagePayload((*first)[0]->record.id), "first");
}

TEST(SqliteMapStore, TheSameContentUnderANewKeyIsRefusedNamingTheFirstUpload) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  const std::string digest(32, '\x7f'), other(32, '\x01');
  {
    auto store = OpenStore(path);
    NewPassage first = MakeUpload("v", "p", "first");
    first.content_digest = digest;
    auto out = store->EnqueuePassages({first}, 0);
    ASSERT_TRUE(out.ok() && (*out)[0].ok());
  }
  // After a restart: its own key is still the idempotent duplicate; a new key with the same
  // content is refused, in a batch whose other uploads go through.
  auto store = OpenStore(path);
  NewPassage retry = MakeUpload("v", "p", "first");
  retry.content_digest = digest;
  NewPassage replay = MakeUpload("w", "q", "first");
  replay.content_digest = digest;
  NewPassage fresh = MakeUpload("w", "r", "other");
  fresh.content_digest = other;
  NewPassage untagged = MakeUpload("w", "s", "first");  // no digest: not compared
  auto out = store->EnqueuePassages({retry, replay, fresh, untagged}, 0);
  ASSERT_TRUE(out.ok());
  ASSERT_TRUE((*out)[0].ok());
  EXPECT_TRUE((*out)[0]->duplicate);
  EXPECT_EQ((*out)[1].status().code(), absl::StatusCode::kAlreadyExists);
  // Another vehicle's upload is named by its queue id and state, not by its ids.
  EXPECT_NE((*out)[1].status().message().find("another vehicle (id 1, queued)"), std::string::npos)
      << (*out)[1].status();
  EXPECT_EQ((*out)[1].status().message().find("v/p"), std::string::npos) << (*out)[1].status();
  ASSERT_TRUE((*out)[2].ok());
  EXPECT_FALSE((*out)[2]->duplicate);
  EXPECT_TRUE((*out)[3].ok());
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages"), 3);
  EXPECT_FALSE(store->FindPassage("w", "q").ok());
  // Inside one batch as well.
  NewPassage a = MakeUpload("x", "1"), b = MakeUpload("x", "2");
  a.content_digest = b.content_digest = std::string(32, '\x02');
  auto batch = store->EnqueuePassages({a, b}, 0);
  ASSERT_TRUE(batch.ok());
  EXPECT_TRUE((*batch)[0].ok());
  EXPECT_EQ((*batch)[1].status().code(), absl::StatusCode::kAlreadyExists);
  EXPECT_NE((*batch)[1].status().message().find("passage x/1 (id"), std::string::npos) << (*batch)[1].status();
}

TEST(SqliteMapStore, FullQueueRejectsNewUploadsButAnswersDuplicates) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  auto out = store->EnqueuePassages({MakeUpload("v", "1"), MakeUpload("v", "2"), MakeUpload("v", "3")}, 2);
  ASSERT_TRUE(out.ok());
  EXPECT_TRUE((*out)[0].ok());
  EXPECT_TRUE((*out)[1].ok());
  EXPECT_EQ((*out)[2].status().code(), absl::StatusCode::kResourceExhausted);
  auto dup = store->EnqueuePassages({MakeUpload("v", "1")}, 2);
  ASSERT_TRUE(dup.ok() && (*dup)[0].ok());
  EXPECT_TRUE((*dup)[0]->duplicate);
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages"), 2);
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passage_payloads"), 2);
}

TEST(SqliteMapStore, ClaimTakesOldestQueuedAndCountsAttempts) {
  TempDir dir;
  auto store = OpenStore(dir.File("map.db"));
  ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "1", "one"), MakeUpload("v", "2", "two")}, 0).ok());
  auto first = store->ClaimNextPassage();
  ASSERT_TRUE(first.ok() && first->has_value());
  EXPECT_EQ((*first)->record.passage_id, "1");
  EXPECT_EQ((*first)->record.state, PassageState::kProcessing);
  EXPECT_EQ((*first)->record.attempts, 1);
  EXPECT_EQ((*first)->payload, "one");
  // Released unstarted, its claim is not counted, and it is taken again first.
  ASSERT_TRUE(store->ReleaseClaimedPassage((*first)->record.id).ok());
  EXPECT_EQ(store->ReleaseClaimedPassage((*first)->record.id).code(), absl::StatusCode::kFailedPrecondition);
  first = store->ClaimNextPassage();
  ASSERT_TRUE(first.ok() && first->has_value());
  EXPECT_EQ((*first)->record.passage_id, "1");
  EXPECT_EQ((*first)->record.attempts, 1);
  // A retry goes back to the queue and is taken again before the younger passage.
  ASSERT_TRUE(store->FinishPassageWithoutChange((*first)->record.id, PassageState::kQueued, "try again").ok());
  auto retry = store->ClaimNextPassage();
  ASSERT_TRUE(retry.ok() && retry->has_value());
  EXPECT_EQ((*retry)->record.passage_id, "1");
  EXPECT_EQ((*retry)->record.attempts, 2);
  ASSERT_TRUE(store->FinishPassageWithoutChange((*retry)->record.id, PassageState::kFailed, "solver unusable").ok());
  auto failed = store->GetPassage((*retry)->record.id);
  ASSERT_TRUE(failed.ok());
  EXPECT_EQ(failed->state, PassageState::kFailed);
  EXPECT_EQ(failed->error, "solver unusable");
  EXPECT_GT(failed->finished_unix_ms, 0);
  auto second = store->ClaimNextPassage();
  ASSERT_TRUE(second.ok() && second->has_value());
  EXPECT_EQ((*second)->record.passage_id, "2");
  auto none = store->ClaimNextPassage();
  ASSERT_TRUE(none.ok());
  EXPECT_FALSE(none->has_value());
}

TEST(SqliteMapStore, AnOperatorRequeuesOrDiscardsOnlyFailedAndQuarantinedPassages) {
  TempDir dir;
  auto store = OpenStore(dir.File("map.db"));
  const int64_t id = EnqueueAndClaim(store.get(), "1");
  const std::vector<PassageState> badly = {PassageState::kFailed, PassageState::kQuarantined};
  EXPECT_EQ(store->MovePassage(id, badly, PassageState::kQueued, false).status().code(), absl::StatusCode::kFailedPrecondition)
      << "processing";
  ASSERT_TRUE(store->FinishPassageWithoutChange(id, PassageState::kQuarantined, "inconsistent: chi2").ok());
  EXPECT_EQ(store->GetStats()->passages_by_state[static_cast<int>(PassageState::kQuarantined)], 1);
  absl::StatusOr<StoredPassage> requeued = store->MovePassage(id, badly, PassageState::kQueued, false);
  ASSERT_TRUE(requeued.ok()) << requeued.status();
  EXPECT_EQ(requeued->state, PassageState::kQueued);
  EXPECT_EQ(requeued->attempts, 0);
  EXPECT_EQ(requeued->error, "");
  auto claimed = store->ClaimNextPassage();
  ASSERT_TRUE(claimed.ok() && claimed->has_value());
  EXPECT_EQ((*claimed)->record.attempts, 1);
  ASSERT_TRUE(store->FinishPassageWithoutChange(id, PassageState::kFailed, "solver unusable").ok());
  absl::StatusOr<StoredPassage> discarded = store->MovePassage(id, badly, PassageState::kDiscarded, false);
  ASSERT_TRUE(discarded.ok()) << discarded.status();
  EXPECT_EQ(discarded->state, PassageState::kDiscarded);
  EXPECT_EQ(discarded->error, "solver unusable") << "the last reason stays on record";
  auto stats = store->GetStats();
  EXPECT_EQ(stats->passages_by_state[static_cast<int>(PassageState::kDiscarded)], 1);
  EXPECT_EQ(stats->passages_by_state[static_cast<int>(PassageState::kQuarantined)], 0);
  EXPECT_EQ(stats->passages_by_state[static_cast<int>(PassageState::kFailed)], 0);
  EXPECT_EQ(store->MovePassage(id, badly, PassageState::kQueued, false).status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(store->MovePassage(999, badly, PassageState::kQueued, false).status().code(), absl::StatusCode::kNotFound);
}

TEST(SqliteMapStore, ProcessingPassagesReturnToQueueOnRequeue) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto store = OpenStore(path);
    ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "1")}, 0).ok());
    ASSERT_TRUE(store->ClaimNextPassage().ok());
  }
  auto store = OpenStore(path);
  EXPECT_EQ(store->FindPassage("v", "1")->state, PassageState::kProcessing);
  EXPECT_EQ(store->FindPassage("v", "1")->attempts, 1);
  auto requeued = store->RequeueProcessingPassages();
  ASSERT_TRUE(requeued.ok());
  EXPECT_EQ(*requeued, 1);
  absl::StatusOr<StoredPassage> after = store->FindPassage("v", "1");
  EXPECT_EQ(after->state, PassageState::kQueued);
  EXPECT_EQ(after->attempts, 0) << "the interrupted attempt does not count";
  EXPECT_EQ(after->interruptions, 1);
}

// A crash counts an interruption only for the passages being applied: a passage a worker had
// claimed ahead, among which it chooses, was not (a passage that crashes the server must not take
// the ones claimed after it down with it).
TEST(SqliteMapStore, ACrashCountsAnInterruptionOnlyForThePassagesStarted) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto store = OpenStore(path);
    ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "1"), MakeUpload("v", "2", "b"), MakeUpload("v", "3", "c")}, 0)
                    .ok());
    for (int i = 0; i < 3; ++i) ASSERT_TRUE(store->ClaimNextPassageAhead().ok());
    ASSERT_TRUE(store->MarkPassageStarted(store->FindPassage("v", "2")->id).ok());
    EXPECT_EQ(store->MarkPassageStarted(999).code(), absl::StatusCode::kFailedPrecondition);
  }
  auto store = OpenStore(path);  // as after a crash
  auto requeued = store->RequeueProcessingPassages();
  ASSERT_TRUE(requeued.ok()) << requeued.status();
  EXPECT_EQ(*requeued, 3);
  for (const char* id : {"1", "2", "3"}) {
    const StoredPassage record = *store->FindPassage("v", id);
    EXPECT_EQ(record.state, PassageState::kQueued) << id;
    EXPECT_EQ(record.attempts, 0) << id;
    EXPECT_EQ(record.interruptions, std::string(id) == "2" ? 1 : 0) << id;
  }
  // Claimed again, ahead then started: the mark of the earlier run does not carry over.
  ASSERT_TRUE(store->ClaimNextPassageAhead().ok());
  ASSERT_TRUE(store->ClaimNextPassageAhead().ok());
  ASSERT_TRUE(store->RequeueProcessingPassages().ok());
  EXPECT_EQ(store->FindPassage("v", "2")->interruptions, 1);
}

TEST(SqliteMapStore, CommitWritesMapVersionAndResultTogether) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  const int64_t id = EnqueueAndClaim(store.get(), "p");
  MapDelta delta;
  delta.base_version = 0;
  delta.version = 2;
  delta.landmarks[7] = MakeLandmark(7, 48.7, 2.17, 2);
  delta.landmarks[9] = MakeLandmark(9, 48.7001, 2.1701, 1);
  Eigen::Matrix2d block;
  block << 0.01, 0.02, 0.03, 0.04;
  delta.added_factors[1] = MakeFactor(1, {7, 9}, PairCovariance(block));
  PassageResult result;
  result.landmarks_created = 2;
  result.subgraphs = 2;
  result.map_version = 2;
  result.strategy = "cc-gsd";
  ASSERT_TRUE(store->CommitPassageApplied(id, delta, result).ok());

  auto record = store->GetPassage(id);
  ASSERT_TRUE(record.ok());
  EXPECT_EQ(record->state, PassageState::kApplied);
  ASSERT_TRUE(record->result.has_value());
  EXPECT_EQ(record->result->landmarks_created, 2);
  EXPECT_EQ(record->result->strategy, "cc-gsd");

  MapState map;
  ASSERT_TRUE(store->LoadMap(&map).ok());
  EXPECT_EQ(map.version(), 2);
  ASSERT_EQ(map.landmark_count(), 2u);
  EXPECT_EQ(map.FindLandmark(7)->position.lat_deg, 48.7);
  EXPECT_EQ(map.FindLandmark(7)->cov_en_m2, delta.landmarks[7].cov_en_m2);
  EXPECT_EQ(map.FindLandmark(7)->anchor.lon_deg, delta.landmarks[7].anchor.lon_deg);
  ASSERT_EQ(map.factor_count(), 1u);
  const MapFactor& factor = *map.FindFactor(1);
  EXPECT_EQ(factor.landmarks, (std::vector<LandmarkId>{7, 9}));
  EXPECT_EQ(factor.passage_id, "p1");
  EXPECT_EQ(factor.information, delta.added_factors[1].information) << "stored bit for bit";
  EXPECT_EQ(factor.information_vector, delta.added_factors[1].information_vector);
  EXPECT_EQ(map.last_factor_id(), 1);
  auto stats = store->GetStats();
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->map_version, 2);
  EXPECT_EQ(stats->landmark_count, 2);
  EXPECT_EQ(stats->factor_count, 1);
  EXPECT_EQ(stats->passages_by_state[static_cast<int>(PassageState::kApplied)], 1);
  EXPECT_EQ(stats->queue_depth(), 0);
}

// GetStats reads counts kept by triggers; they must equal the tables' own counts.
void ExpectStatsEqualTableCounts(MapStoreInterface* store, const std::string& path) {
  auto stats = store->GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->landmark_count, SqlInt(path, "SELECT COUNT(*) FROM landmarks"));
  EXPECT_EQ(stats->factor_count, SqlInt(path, "SELECT COUNT(*) FROM factors"));
  for (int state = 1; state <= 6; ++state) {
    EXPECT_EQ(stats->passages_by_state[state],
              SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages WHERE state = " + std::to_string(state)))
        << "state " << state;
  }
}

// A landmark's R*Tree box reaches about a metre around it and is rewritten only once the landmark
// leaves it; region reads test the exact position, so they find it just inside an edge it has
// crossed and not just outside, whether its R*Tree box moved or not.
TEST(SqliteMapStore, ALandmarkKeepsItsRtreeBoxUntilItLeavesIt) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  const std::string box_sql = "SELECT min_lat * 1e9 FROM landmark_boxes WHERE id = 7";
  const double lat = 48.7, lon = 2.17;
  auto commit = [&](int64_t version, double at_lat) {
    MapDelta delta;
    delta.base_version = version - 1;
    delta.version = version;
    delta.landmarks[7] = MakeLandmark(7, at_lat, lon, version);
    const absl::Status committed =
        store->CommitPassageApplied(EnqueueAndClaim(store.get(), std::to_string(version)), delta, PassageResult());
    ASSERT_TRUE(committed.ok()) << committed;
  };
  auto ids_in = [&](double min_lat, double max_lat) {
    std::vector<LandmarkId> ids;
    auto page = store->QueryRegion(BoundingBox{min_lat, lon - 1e-4, max_lat, lon + 1e-4}, 0, 10, false);
    EXPECT_TRUE(page.ok());
    if (page.ok()) {
      for (const Landmark& l : page->landmarks) ids.push_back(l.id);
    }
    return ids;
  };
  const std::vector<LandmarkId> found{7}, none;
  commit(1, lat);
  const int64_t written = SqlInt(path, box_sql);
  EXPECT_LT(written, static_cast<int64_t>((lat - 5e-6) * 1e9)) << "the box reaches half a metre south and more";
  // 55 cm north: the same box; a read whose southern edge lies between the old and new position
  // finds it, one whose northern edge does finds nothing.
  const double moved = lat + 5e-6;
  commit(2, moved);
  EXPECT_EQ(SqlInt(path, box_sql), written);
  EXPECT_EQ(ids_in(lat + 2.5e-6, lat + 1e-5), found);
  EXPECT_EQ(ids_in(lat - 1e-5, lat + 2.5e-6), none);
  // 50 m north: out of its box, which moves with it.
  const double far = lat + 4.5e-4;
  commit(3, far);
  EXPECT_GT(SqlInt(path, box_sql), written);
  EXPECT_EQ(ids_in(far - 1e-6, far + 1e-6), found);
  EXPECT_EQ(ids_in(lat - 1e-6, lat + 1e-6), none);
}

// The writer keeps each landmark's R*Tree box and tile in memory instead of reading them for every
// landmark it writes. A commit that fails must leave them as the file has them, and a reopened
// store reads them from the file: a landmark moved out of its box and tile then gets new ones, and
// one moved inside its box keeps it.
TEST(SqliteMapStore, AFailedCommitOrAReopenLeavesTheWriterWithTheFilesBoxesAndTiles) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  const std::string box_sql = "SELECT min_lat * 1e9 FROM landmark_boxes WHERE id = 7";
  const std::string tile_sql = "SELECT tile_y FROM landmarks WHERE id = 7";
  const double lat = 48.7, lon = 2.17;
  const double far = lat + 0.01;  // 1.1 km north: another z16 tile
  ASSERT_NE(TileContaining({lat, lon}).y, TileContaining({far, lon}).y);
  auto commit = [&](int64_t version, double at_lat, bool bad_factor) {
    MapDelta delta;
    delta.base_version = version - 1;
    delta.version = version;
    delta.landmarks[7] = MakeLandmark(7, at_lat, lon, version);
    if (bad_factor) {  // refused after the landmarks are written: the transaction rolls back
      MapFactor factor = MakeFactor(1, {7}, Eigen::Matrix2d::Identity());
      factor.information(0, 0) = std::nan("");
      delta.added_factors[1] = factor;
    }
    return store->CommitPassageApplied(EnqueueAndClaim(store.get(), std::to_string(version) + (bad_factor ? "x" : "")),
                                       delta, PassageResult());
  };
  auto ids_near = [&](double at_lat) {
    std::vector<LandmarkId> ids;
    auto page = store->QueryRegion(BoundingBox{at_lat - 1e-6, lon - 1e-6, at_lat + 1e-6, lon + 1e-6}, 0, 10, false);
    EXPECT_TRUE(page.ok());
    if (page.ok()) {
      for (const Landmark& l : page->landmarks) ids.push_back(l.id);
    }
    return ids;
  };
  auto tile_ids = [&](double at_lat) {
    std::vector<LandmarkId> ids;
    auto page = store->GetTile(TileContaining({at_lat, lon}), false);
    EXPECT_TRUE(page.ok());
    if (page.ok()) {
      for (const Landmark& l : page->landmarks) ids.push_back(l.id);
    }
    return ids;
  };
  const std::vector<LandmarkId> found{7}, none;
  ASSERT_TRUE(commit(1, lat, false).ok());
  const int64_t box_at_lat = SqlInt(path, box_sql);

  EXPECT_EQ(commit(2, far, true).code(), absl::StatusCode::kInternal);
  EXPECT_EQ(SqlInt(path, box_sql), box_at_lat);
  EXPECT_EQ(SqlInt(path, tile_sql), TileContaining({lat, lon}).y);
  // The same move committed: a writer that had kept the failed commit's box and tile would write
  // neither.
  ASSERT_TRUE(commit(2, far, false).ok());
  const int64_t box_at_far = SqlInt(path, box_sql);
  EXPECT_GT(box_at_far, box_at_lat);
  EXPECT_EQ(SqlInt(path, tile_sql), TileContaining({far, lon}).y);
  EXPECT_EQ(ids_near(far), found);
  EXPECT_EQ(tile_ids(far), found);
  EXPECT_EQ(tile_ids(lat), none);

  store.reset();
  store = OpenStore(path);
  ASSERT_TRUE(commit(3, far + 5e-6, false).ok());  // 55 cm: inside its box
  EXPECT_EQ(SqlInt(path, box_sql), box_at_far);
  ASSERT_TRUE(commit(4, lat, false).ok());  // back south: a new box and tile
  EXPECT_EQ(SqlInt(path, box_sql), box_at_lat);
  EXPECT_EQ(SqlInt(path, tile_sql), TileContaining({lat, lon}).y);
  EXPECT_EQ(ids_near(lat), found);
  EXPECT_EQ(ids_near(far), none);
  EXPECT_EQ(tile_ids(lat), found);
  EXPECT_EQ(tile_ids(far), none);
}

TEST(SqliteMapStore, StatsFollowEveryWriteWithoutScanningTheTables) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "1"), MakeUpload("v", "2"), MakeUpload("v", "3"),
                                      MakeUpload("v", "4"), MakeUpload("v", "1")},
                                     0)
                  .ok());
  ExpectStatsEqualTableCounts(store.get(), path);
  Eigen::Matrix2d block;
  block << 0.01, 0.02, 0.03, 0.04;
  // First commit: three new landmarks and two factors.
  auto first = store->ClaimNextPassage();
  ASSERT_TRUE(first.ok() && first->has_value());
  MapDelta delta;
  delta.base_version = 0;
  delta.version = 1;
  for (LandmarkId id : {1, 2, 3}) delta.landmarks[id] = MakeLandmark(id, 48.7 + 1e-4 * id, 2.17, 1);
  delta.added_factors[1] = MakeFactor(1, {1, 2}, PairCovariance(block));
  delta.added_factors[2] = MakeFactor(2, {3}, Eigen::Matrix2d::Identity());
  ASSERT_TRUE(store->CommitPassageApplied((*first)->record.id, delta, PassageResult()).ok());
  ExpectStatsEqualTableCounts(store.get(), path);
  // Second commit rewrites them all, replaces a factor and removes a landmark.
  auto second = store->ClaimNextPassage();
  ASSERT_TRUE(second.ok() && second->has_value());
  delta.base_version = 1;
  delta.version = 2;
  for (LandmarkId id : {1, 2, 3, 4}) delta.landmarks[id] = MakeLandmark(id, 48.7 + 2e-4 * id, 2.17, 2);
  delta.added_factors.clear();
  delta.added_factors[3] = MakeFactor(3, {3, 4}, PairCovariance(block));
  delta.removed_factors = {2};
  delta.landmarks.erase(1);
  delta.removed_landmarks = {1};
  ASSERT_TRUE(store->CommitPassageApplied((*second)->record.id, delta, PassageResult()).ok());
  ExpectStatsEqualTableCounts(store.get(), path);
  EXPECT_EQ(store->GetStats()->landmark_count, 3);
  EXPECT_EQ(store->GetStats()->factor_count, 2);
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM landmark_boxes WHERE id = 1"), 0) << "its box went with it";
  EXPECT_EQ(SqlInt(path, "SELECT value FROM map_meta WHERE key = 'last_factor_id'"), 3);
  // A rejection, a claim left processing and returned to the queue.
  auto third = store->ClaimNextPassage();
  ASSERT_TRUE(third.ok() && third->has_value());
  ASSERT_TRUE(store->FinishPassageWithoutChange((*third)->record.id, PassageState::kRejected, "bad").ok());
  ASSERT_TRUE(store->ClaimNextPassage().ok());
  ExpectStatsEqualTableCounts(store.get(), path);
  ASSERT_TRUE(store->RequeueProcessingPassages().ok());
  ExpectStatsEqualTableCounts(store.get(), path);
  EXPECT_EQ(store->GetStats()->queue_depth(), 1);
}

// A database written by schema 2 (the dense covariance as cross blocks), opened by this release.
class SchemaTwoDatabase : public ::testing::Test {
 protected:
  void SetUp() override {
    path_ = dir_.File("map.db");
    auto db = SqliteConnection::Open(path_, 5000, /*read_only=*/false);
    ASSERT_TRUE(db.ok()) << db.status();
    ASSERT_TRUE(MigrateSchema(db->get(), 2).ok());
    // Three landmarks: 1 and 2 correlated, 3 alone; two queued passages.
    ASSERT_TRUE((*db)->Exec(R"sql(
        INSERT INTO landmarks (id, lat_deg, lon_deg, cov_ee, cov_en, cov_ne, cov_nn, version, passages_seen,
                               last_seen_unix_ms, state, tile_x, tile_y)
          VALUES (1, 48.70, 2.17, 0.5, 0.1, 0.1, 0.7, 4, 3, 0, 1, 0, 0),
                 (2, 48.701, 2.17, 0.6, 0.0, 0.0, 0.6, 4, 3, 0, 1, 0, 0),
                 (3, 48.702, 2.17, 0.9, 0.0, 0.0, 0.4, 4, 1, 0, 1, 0, 0);
        INSERT INTO cross_covariances (a, b, c_ee, c_en, c_ne, c_nn) VALUES (1, 2, 0.2, 0.05, -0.03, 0.25);
        INSERT INTO passages (vehicle_id, passage_id, state, received_unix_ms, size_bytes)
          VALUES ('v', '1', 1, 0, 5), ('v', '2', 1, 0, 5);
        UPDATE map_meta SET value = 4 WHERE key = 'map_version';
        )sql")
                    .ok());
  }
  TempDir dir_;
  std::string path_;
};

TEST_F(SchemaTwoDatabase, MigrationTurnsTheDenseCovarianceIntoTheSameGaussian) {
  auto store = OpenStore(path_);
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(SqlInt(path_, "PRAGMA user_version"), LatestSchemaVersion());
  EXPECT_EQ(SqlInt(path_, "SELECT COUNT(*) FROM sqlite_master WHERE name = 'cross_covariances'"), 0);
  ExpectStatsEqualTableCounts(store.get(), path_);
  EXPECT_EQ(store->GetStats()->factor_count, 2) << "one factor per correlated group";
  EXPECT_EQ(store->GetStats()->passages_by_state[static_cast<int>(PassageState::kQueued)], 2);
  MapState map;
  ASSERT_TRUE(store->LoadMap(&map).ok());
  EXPECT_EQ(map.version(), 4);
  EXPECT_EQ(map.FindLandmark(2)->Offset().norm(), 0.0) << "anchored at its position";
  absl::StatusOr<Eigen::MatrixXd> cov = JointCovariance(map, {1, 2, 3});
  ASSERT_TRUE(cov.ok()) << cov.status();
  Eigen::MatrixXd expected = Eigen::MatrixXd::Zero(6, 6);
  expected << 0.5, 0.1, 0.2, 0.05, 0, 0,  //
      0.1, 0.7, -0.03, 0.25, 0, 0,        //
      0.2, -0.03, 0.6, 0, 0, 0,           //
      0.05, 0.25, 0, 0.6, 0, 0,           //
      0, 0, 0, 0, 0.9, 0,                 //
      0, 0, 0, 0, 0, 0.4;
  EXPECT_LT((*cov - expected).cwiseAbs().maxCoeff(), 1e-12);
  // The map's estimate stays where it was.
  absl::StatusOr<MapWindow> window = MapWindow::Build(map, {1, 2, 3}, {});
  ASSERT_TRUE(window.ok());
  EXPECT_LT(window->offsets().cwiseAbs().maxCoeff(), 1e-12);
}

TEST_F(SchemaTwoDatabase, CovarianceThatIsNotPositiveDefiniteStopsTheMigrationWithoutAChange) {
  {
    auto db = SqliteConnection::Open(path_, 5000, /*read_only=*/false);
    ASSERT_TRUE((*db)->Exec("UPDATE cross_covariances SET c_ee = 5.0").ok());
  }
  EXPECT_EQ(CreateSqliteMapStore(path_).status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(SqlInt(path_, "PRAGMA user_version"), 2) << "the migration's transaction rolled back";
  EXPECT_EQ(SqlInt(path_, "SELECT COUNT(*) FROM cross_covariances"), 1);
}

// A passage's change to an empty map: landmarks 1 and 2 and one factor on them (id 1), version 1.
MapDelta TwoLandmarksOneFactor() {
  MapDelta applied;
  applied.version = 1;
  applied.landmarks[1] = MakeLandmark(1, 48.7, 2.17, 1);
  applied.landmarks[2] = MakeLandmark(2, 48.7001, 2.17, 1);
  applied.added_factors[1] = MakeFactor(1, {1, 2}, PairCovariance(Eigen::Matrix2d::Constant(0.01)));
  return applied;
}

// Its exclusion: the factor and both landmarks removed, version 2.
MapDelta ExclusionOfTwoLandmarksOneFactor() {
  MapDelta exclusion;
  exclusion.base_version = 1;
  exclusion.version = 2;
  exclusion.removed_factors = {1};
  exclusion.removed_landmarks = {1, 2};
  return exclusion;
}

TEST(SqliteMapStore, ExclusionWritesItsDeltaAndMarksThePassageInOneTransaction) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  const int64_t id = EnqueueAndClaim(store.get(), "p");
  const MapDelta applied = TwoLandmarksOneFactor();
  // Only an applied passage can be excluded.
  EXPECT_EQ(store->CommitPassageExcluded(id, MapDelta()).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(store->CommitPassageApplied(id, applied, {}).ok());

  const MapDelta exclusion = ExclusionOfTwoLandmarksOneFactor();
  MapDelta stale = exclusion;
  stale.base_version = 0;
  EXPECT_EQ(store->CommitPassageExcluded(id, stale).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(store->GetPassage(id)->state, PassageState::kApplied) << "refused: nothing changed";
  ASSERT_TRUE(store->CommitPassageExcluded(id, exclusion).ok());
  EXPECT_EQ(store->GetPassage(id)->state, PassageState::kExcluded);
  ExpectStatsEqualTableCounts(store.get(), path);
  EXPECT_EQ(store->GetStats()->passages_by_state[static_cast<int>(PassageState::kExcluded)], 1);
  MapState map;
  ASSERT_TRUE(store->LoadMap(&map).ok());
  EXPECT_EQ(map.landmark_count(), 0u);
  EXPECT_EQ(map.factor_count(), 0u);
  EXPECT_EQ(map.version(), 2);
  EXPECT_EQ(map.last_factor_id(), 1) << "factor ids are not reused";
  // Watchers are told where the removed landmarks were, from the version before the removal.
  const BoundingBox around{48.69, 2.16, 48.71, 2.18};
  const BoundingBox elsewhere{48.0, 2.0, 48.1, 2.1};
  EXPECT_EQ(store->ChangedLandmarks(around, 1)->removed, (std::vector<LandmarkId>{1, 2}));
  EXPECT_TRUE(store->ChangedLandmarks(around, 2)->removed.empty());
  EXPECT_TRUE(store->ChangedLandmarks(elsewhere, 0)->removed.empty());
  EXPECT_EQ(store->CommitPassageExcluded(id, exclusion).code(), absl::StatusCode::kFailedPrecondition)
      << "already excluded";
}


TEST(SqliteMapStore, RelinearizationReplacesTheFactorsAndLeavesThePassageApplied) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  const int64_t id = EnqueueAndClaim(store.get(), "p");
  const MapDelta applied = TwoLandmarksOneFactor();
  // Only an applied passage can be re-linearised.
  EXPECT_EQ(store->CommitPassageRelinearized(id, MapDelta()).code(), absl::StatusCode::kFailedPrecondition);
  PassageResult result;
  result.map_version = 1;
  ASSERT_TRUE(store->CommitPassageApplied(id, applied, result).ok());

  MapDelta relinearized;
  relinearized.base_version = 1;
  relinearized.version = 2;
  relinearized.removed_factors = {1};
  relinearized.added_factors[2] = MakeFactor(2, {1, 2}, PairCovariance(Eigen::Matrix2d::Constant(0.02)));
  relinearized.added_factors[2].passage_id = applied.added_factors.at(1).passage_id;
  relinearized.landmarks[1] = MakeLandmark(1, 48.70001, 2.17, 2);
  MapDelta stale = relinearized;
  stale.base_version = 0;
  EXPECT_EQ(store->CommitPassageRelinearized(id, stale).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(store->CommitPassageRelinearized(id, relinearized).ok());
  const absl::StatusOr<StoredPassage> record = store->GetPassage(id);
  ASSERT_TRUE(record.ok());
  EXPECT_EQ(record->state, PassageState::kApplied);
  ASSERT_TRUE(record->result.has_value());
  EXPECT_EQ(record->result->map_version, 1) << "the passage's result is its application's";
  ExpectStatsEqualTableCounts(store.get(), path);
  MapState map;
  ASSERT_TRUE(store->LoadMap(&map).ok());
  EXPECT_EQ(map.version(), 2);
  EXPECT_EQ(map.factor_count(), 1u);
  ASSERT_NE(map.FindFactor(2), nullptr);
  EXPECT_EQ(map.FindFactor(1), nullptr);
  EXPECT_EQ(map.FindLandmark(1)->position.lat_deg, 48.70001);
  std::vector<int64_t> ids;
  map.AppendPassageFactorIds(applied.added_factors.at(1).vehicle_id, applied.added_factors.at(1).passage_id, &ids);
  EXPECT_EQ(ids, std::vector<int64_t>{2}) << "the new factor keeps the passage's provenance";
}

// Another process's write transaction on one of the store's files, held until destroyed.
class ForeignWriteLock {
 public:
  explicit ForeignWriteLock(const std::string& path) {
    sqlite3_open(path.c_str(), &db_);
    locked_ = sqlite3_exec(db_, "BEGIN IMMEDIATE", nullptr, nullptr, nullptr) == SQLITE_OK;
  }
  ~ForeignWriteLock() {
    sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
    sqlite3_close(db_);
  }
  bool locked() const { return locked_; }

 private:
  sqlite3* db_ = nullptr;
  bool locked_ = false;
};

std::unique_ptr<MapStoreInterface> OpenStoreWithBusyTimeout(const std::string& path, int busy_timeout_ms) {
  SqliteMapStoreOptions options;
  options.busy_timeout_ms = busy_timeout_ms;
  auto store = CreateSqliteMapStore(path, options);
  EXPECT_TRUE(store.ok()) << store.status();
  return store.ok() ? std::move(*store) : nullptr;
}

// Deletes a database file with its write-ahead log and shared memory, as a restore must.
void RemoveDatabaseFile(const std::string& path) {
  for (const char* suffix : {"", "-wal", "-shm"}) std::remove((path + suffix).c_str());
}

MapDelta OneLandmarkDelta(int64_t base_version) {
  MapDelta delta;
  delta.base_version = base_version;
  delta.version = base_version + 1;
  delta.landmarks[1] = MakeLandmark(1, 48.7, 2.17, delta.version);
  delta.added_factors[base_version + 1] = MakeFactor(base_version + 1, {1}, Eigen::Matrix2d::Identity());
  return delta;
}

PassageResult SomeResult() {
  PassageResult result;
  result.nodes = 17;
  result.map_version = 1;
  result.strategy = "cc";
  return result;
}

TEST(SqliteMapStore, UploadsAndClaimsNeverWaitForTheMapFile) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStoreWithBusyTimeout(path, 200);
  ForeignWriteLock map_locked(path);  // as if a long map commit were under way
  ASSERT_TRUE(map_locked.locked());
  auto out = store->EnqueuePassages({MakeUpload("v", "1"), MakeUpload("v", "2")}, 0);
  ASSERT_TRUE(out.ok()) << out.status();
  ASSERT_TRUE((*out)[0].ok());
  auto claimed = store->ClaimNextPassage();
  ASSERT_TRUE(claimed.ok() && claimed->has_value()) << claimed.status();
  // The map's commit does wait for the map file, and changes nothing when it cannot get it.
  const int64_t id = (*claimed)->record.id;
  EXPECT_FALSE(store->CommitPassageApplied(id, OneLandmarkDelta(0), SomeResult()).ok());
  EXPECT_EQ(store->GetPassage(id)->state, PassageState::kProcessing);
  EXPECT_EQ(store->GetStats()->queue_depth(), 2);
}

TEST(SqliteMapStore, AMapCommitTheQueueCouldNotRecordIsRecordedByTheNextQueueWrite) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStoreWithBusyTimeout(path, 100);
  const int64_t id = EnqueueAndClaim(store.get(), "p");
  {
    ForeignWriteLock queue_locked(SqliteQueuePath(path));
    ASSERT_TRUE(queue_locked.locked());
    // The map's commit is durable: it is not undone because the queue is busy.
    ASSERT_TRUE(store->CommitPassageApplied(id, OneLandmarkDelta(0), SomeResult()).ok());
    EXPECT_EQ(SqlInt(path, "SELECT state FROM map_passages WHERE id = " + std::to_string(id)), 3);
    EXPECT_EQ(store->GetPassage(id)->state, PassageState::kProcessing);
  }
  // Nothing queued: the claim finds no passage but records the pending change first.
  auto next = store->ClaimNextPassage();
  ASSERT_TRUE(next.ok());
  EXPECT_FALSE(next->has_value());
  auto record = store->GetPassage(id);
  ASSERT_TRUE(record.ok());
  EXPECT_EQ(record->state, PassageState::kApplied);
  ASSERT_TRUE(record->result.has_value());
  EXPECT_EQ(record->result->nodes, 17);
}

TEST(SqliteMapStore, ACrashBetweenTheMapAndQueueCommitsIsReconciledAtStartAndNeverAppliedTwice) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  int64_t id = 0;
  {
    auto store = OpenStoreWithBusyTimeout(path, 100);
    id = EnqueueAndClaim(store.get(), "p");
    ForeignWriteLock queue_locked(SqliteQueuePath(path));
    ASSERT_TRUE(store->CommitPassageApplied(id, OneLandmarkDelta(0), SomeResult()).ok());
    // The store goes away with its pending change, as in a crash.
  }
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT state FROM passages WHERE id = " + std::to_string(id)), 2);
  auto store = OpenStore(path);
  ASSERT_NE(store, nullptr);
  auto requeued = store->RequeueProcessingPassages();
  ASSERT_TRUE(requeued.ok());
  EXPECT_EQ(*requeued, 0) << "the passage is in the map: it must not be applied again";
  auto record = store->GetPassage(id);
  EXPECT_EQ(record->state, PassageState::kApplied);
  ASSERT_TRUE(record->result.has_value());
  EXPECT_EQ(record->result->strategy, "cc");
  ExpectStatsEqualTableCounts(store.get(), path);
}

TEST(SqliteMapStore, AMapRestoredFromAnOlderBackupHasItsMissingPassagesAppliedAgain) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  int64_t applied = 0, excluded = 0;
  {
    auto store = OpenStore(path);
    applied = EnqueueAndClaim(store.get(), "applied");
    ASSERT_TRUE(store->CommitPassageApplied(applied, OneLandmarkDelta(0), SomeResult()).ok());
    excluded = EnqueueAndClaim(store.get(), "excluded");
    ASSERT_TRUE(store->CommitPassageApplied(excluded, OneLandmarkDelta(1), SomeResult()).ok());
    MapDelta exclusion;
    exclusion.base_version = 2;
    exclusion.version = 3;
    exclusion.removed_factors = {2};
    ASSERT_TRUE(store->CommitPassageExcluded(excluded, exclusion).ok());
  }
  // The map as an earlier backup had it: without the first passage, the second still applied.
  sqlite3* db = nullptr;
  sqlite3_open(path.c_str(), &db);
  ASSERT_EQ(sqlite3_exec(db,
                         ("DELETE FROM map_passages WHERE id = " + std::to_string(applied) +
                          "; UPDATE map_passages SET state = 3 WHERE id = " + std::to_string(excluded))
                             .c_str(),
                         nullptr, nullptr, nullptr),
            SQLITE_OK);
  sqlite3_close(db);
  auto store = OpenStore(path);
  EXPECT_EQ(store->GetPassage(applied)->state, PassageState::kQueued);
  EXPECT_EQ(store->GetPassage(excluded)->state, PassageState::kApplied);
  EXPECT_NE(store->GetPassage(excluded)->error.find("exclude it again"), std::string::npos);
  ExpectStatsEqualTableCounts(store.get(), path);
}

// A map restored from a backup older than its queue's is at a version clients may have seen with
// other contents: it is raised above every version the queue recorded, and every landmark carries
// it, so that a client watching from any version it saw reads them all again.
TEST(SqliteMapStore, AMapRestoredFromAnOlderBackupIsRaisedAboveEveryVersionItsQueueRecorded) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  const std::string backup = dir.File("map.backup");
  {
    auto store = OpenStore(path);
    const int64_t first = EnqueueAndClaim(store.get(), "first");
    ASSERT_TRUE(store->CommitPassageApplied(first, OneLandmarkDelta(0), SomeResult()).ok());
  }
  std::filesystem::copy_file(path, backup);  // closed: its log is checkpointed
  {
    // A landmark the backed-up map had removed: its record is restamped too.
    auto db = SqliteConnection::Open(backup, 5000, /*read_only=*/false);
    ASSERT_TRUE(db.ok()) << db.status();
    ASSERT_TRUE((*db)->Exec("INSERT INTO removed_landmarks VALUES (99, 48.7, 2.17, 1)").ok());
  }
  {
    auto store = OpenStore(path);
    int64_t version = 1;
    for (const char* name : {"second", "third"}) {
      const int64_t id = EnqueueAndClaim(store.get(), name);
      ASSERT_TRUE(store->CommitPassageApplied(id, OneLandmarkDelta(version++), SomeResult()).ok());
    }
  }
  const std::string map_version = "SELECT value FROM map_meta WHERE key = 'map_version'";
  ASSERT_EQ(SqlInt(path, map_version), 3);
  RemoveDatabaseFile(path);
  std::filesystem::copy_file(backup, path);
  auto store = OpenStore(path);
  ASSERT_NE(store, nullptr);
  const int64_t raised = int64_t{1} << 32;  // a new range: clients may have seen versions after 3
  EXPECT_EQ(SqlInt(path, map_version), raised);
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM landmarks WHERE version <> " + std::to_string(raised)), 0);
  EXPECT_EQ(SqlInt(path, "SELECT version FROM removed_landmarks WHERE id = 99"), raised);
  EXPECT_EQ(store->FindPassage("v", "second")->state, PassageState::kQueued);
  store.reset();
  auto again = OpenStore(path);
  EXPECT_EQ(SqlInt(path, map_version), raised) << "raised once";
}

// Both files restored from one backup: the queue knows no later version, but the version mark
// beside them holds the last one clients may have seen.
TEST(SqliteMapStore, AMapAndQueueRestoredTogetherAreRaisedAboveTheVersionMark) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  const std::string queue = SqliteQueuePath(path);
  {
    auto store = OpenStore(path);
    const int64_t first = EnqueueAndClaim(store.get(), "first");
    ASSERT_TRUE(store->CommitPassageApplied(first, OneLandmarkDelta(0), SomeResult()).ok());
  }
  std::filesystem::copy_file(path, dir.File("map.backup"));
  std::filesystem::copy_file(queue, dir.File("queue.backup"));
  {
    auto store = OpenStore(path);
    const int64_t second = EnqueueAndClaim(store.get(), "second");
    ASSERT_TRUE(store->CommitPassageApplied(second, OneLandmarkDelta(1), SomeResult()).ok());
  }
  std::ifstream mark(path + ".version");
  int64_t marked = 0;
  mark >> marked;
  EXPECT_EQ(marked, 2) << "written after each commit";
  for (const std::string& file : {path, queue}) RemoveDatabaseFile(file);
  std::filesystem::copy_file(dir.File("map.backup"), path);
  std::filesystem::copy_file(dir.File("queue.backup"), queue);
  auto store = OpenStore(path);
  ASSERT_NE(store, nullptr);
  const int64_t raised = int64_t{1} << 32;
  EXPECT_EQ(SqlInt(path, "SELECT value FROM map_meta WHERE key = 'map_version'"), raised);
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM landmarks WHERE version <> " + std::to_string(raised)), 0);
  store.reset();
  std::remove((path + ".version").c_str());  // a restore on another machine, without the mark
  auto again = OpenStore(path);
  EXPECT_EQ(SqlInt(path, "SELECT value FROM map_meta WHERE key = 'map_version'"), raised) << "not raised again";
}

TEST(SqliteMapStore, PruningDeletesOnlyTheUploadsOfAppliedPassages) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  const std::string queue = SqliteQueuePath(path);
  auto store = OpenStore(path);
  const int64_t applied = EnqueueAndClaim(store.get(), "applied");
  ASSERT_TRUE(store->CommitPassageApplied(applied, OneLandmarkDelta(0), SomeResult()).ok());
  ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "queued")}, 0).ok());
  const int64_t queued = store->FindPassage("v", "queued")->id;

  auto pruned = store->PrunePassagePayloads({{"v", "applied"}, {"v", "queued"}, {"v", "unknown"}});
  ASSERT_TRUE(pruned.ok()) << pruned.status();
  EXPECT_EQ(*pruned, 1);
  EXPECT_GT(store->GetPassage(applied)->payload_pruned_unix_ms, 0);
  EXPECT_EQ(store->GetPassage(applied)->state, PassageState::kApplied) << "the record stays";
  const absl::StatusOr<std::string> gone = store->GetPassagePayload(applied);
  EXPECT_EQ(gone.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(gone.status().message().find("folded into the map's base"), std::string::npos) << gone.status();
  EXPECT_EQ(store->GetPassage(queued)->payload_pruned_unix_ms, 0);
  EXPECT_EQ(*store->GetPassagePayload(queued), "bytes");
  EXPECT_EQ(SqlInt(queue, "SELECT COUNT(*) FROM passage_payloads"), 1);
  EXPECT_EQ(*store->PrunePassagePayloads({{"v", "applied"}}), 0) << "once";
  EXPECT_EQ(*store->PrunePassagePayloads({}), 0);
  ExpectStatsEqualTableCounts(store.get(), path);
}

TEST(SqliteMapStore, SettledUploadsAreDeletedAfterTheirRetentionAndOnlyThose) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  const std::string queue = SqliteQueuePath(path);
  auto store = OpenStore(path);
  // Excluded (applied, then taken out again), rejected, discarded (failed, then an operator's
  // discard); failed and quarantined, which an operator may still requeue; one still queued.
  const int64_t excluded = EnqueueAndClaim(store.get(), "excluded");
  ASSERT_TRUE(store->CommitPassageApplied(excluded, TwoLandmarksOneFactor(), {}).ok());
  ASSERT_TRUE(store->CommitPassageExcluded(excluded, ExclusionOfTwoLandmarksOneFactor()).ok());
  const int64_t rejected = EnqueueAndClaim(store.get(), "rejected");
  ASSERT_TRUE(store->FinishPassageWithoutChange(rejected, PassageState::kRejected, "bad").ok());
  const int64_t discarded = EnqueueAndClaim(store.get(), "discarded");
  ASSERT_TRUE(store->FinishPassageWithoutChange(discarded, PassageState::kFailed, "solver unusable").ok());
  ASSERT_TRUE(store->MovePassage(discarded, {PassageState::kFailed}, PassageState::kDiscarded, false).ok());
  const int64_t failed = EnqueueAndClaim(store.get(), "failed");
  ASSERT_TRUE(store->FinishPassageWithoutChange(failed, PassageState::kFailed, "solver unusable").ok());
  const int64_t quarantined = EnqueueAndClaim(store.get(), "quarantined");
  ASSERT_TRUE(store->FinishPassageWithoutChange(quarantined, PassageState::kQuarantined, "inconsistent").ok());
  ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "queued")}, 0).ok());
  const int64_t queued = store->FindPassage("v", "queued")->id;

  const int64_t now = NowUnixMs();
  EXPECT_EQ(*store->PruneSettledPayloads(now - 86400000, 1000), 0) << "none finished a day ago";
  EXPECT_EQ(*store->PruneSettledPayloads(now + 1000, 0), 0);
  // Oldest first, at most the limit per call.
  EXPECT_EQ(*store->PruneSettledPayloads(now + 1000, 2), 2);
  EXPECT_GT(store->GetPassage(excluded)->payload_pruned_unix_ms, 0);
  EXPECT_GT(store->GetPassage(rejected)->payload_pruned_unix_ms, 0);
  EXPECT_EQ(store->GetPassage(discarded)->payload_pruned_unix_ms, 0);
  EXPECT_EQ(*store->PruneSettledPayloads(now + 1000, 1000), 1);
  EXPECT_EQ(*store->PruneSettledPayloads(now + 1000, 1000), 0) << "once";

  for (const int64_t id : {excluded, rejected, discarded}) {
    const absl::StatusOr<std::string> gone = store->GetPassagePayload(id);
    EXPECT_EQ(gone.status().code(), absl::StatusCode::kNotFound) << id;
    EXPECT_NE(gone.status().message().find("was deleted after the retention of settled uploads"), std::string::npos)
        << gone.status();
  }
  EXPECT_EQ(store->GetPassage(rejected)->state, PassageState::kRejected) << "the record stays";
  EXPECT_EQ(store->GetPassage(rejected)->error, "bad");
  for (const int64_t id : {failed, quarantined, queued}) {
    EXPECT_EQ(*store->GetPassagePayload(id), "bytes") << id;
    EXPECT_EQ(store->GetPassage(id)->payload_pruned_unix_ms, 0) << id;
  }
  EXPECT_EQ(SqlInt(queue, "SELECT COUNT(*) FROM passage_payloads"), 3);
  ExpectStatsEqualTableCounts(store.get(), path);
}

TEST(SqliteMapStore, APrunedPassageAMapRestoredFromAnOlderBackupLacksFailsWithTheReason) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  int64_t applied = 0;
  {
    auto store = OpenStore(path);
    applied = EnqueueAndClaim(store.get(), "applied");
    ASSERT_TRUE(store->CommitPassageApplied(applied, OneLandmarkDelta(0), SomeResult()).ok());
    ASSERT_EQ(*store->PrunePassagePayloads({{"v", "applied"}}), 1);
  }
  sqlite3* db = nullptr;
  sqlite3_open(path.c_str(), &db);
  ASSERT_EQ(sqlite3_exec(db, ("DELETE FROM map_passages WHERE id = " + std::to_string(applied)).c_str(), nullptr,
                         nullptr, nullptr),
            SQLITE_OK);
  sqlite3_close(db);
  auto store = OpenStore(path);
  const StoredPassage record = *store->GetPassage(applied);
  EXPECT_EQ(record.state, PassageState::kFailed) << "not queued: its upload is gone";
  EXPECT_NE(record.error.find("upload it again"), std::string::npos) << record.error;
  EXPECT_FALSE(store->ClaimNextPassage()->has_value());
  ExpectStatsEqualTableCounts(store.get(), path);

  // An operator's requeue is refused: the queue would stop at a passage it cannot read.
  const absl::StatusOr<StoredPassage> requeued =
      store->MovePassage(applied, {PassageState::kFailed}, PassageState::kQueued, false);
  EXPECT_EQ(requeued.status().code(), absl::StatusCode::kFailedPrecondition) << requeued.status();
  EXPECT_NE(requeued.status().message().find("upload the drive again"), std::string::npos) << requeued.status();
  EXPECT_EQ(store->GetPassage(applied)->state, PassageState::kFailed);

  // Uploaded again under the same ids, the drive is taken again under its record.
  auto again = store->EnqueuePassages({MakeUpload("v", "applied")}, 0);
  ASSERT_TRUE(again.ok()) << again.status();
  ASSERT_TRUE((*again)[0].ok()) << (*again)[0].status();
  EXPECT_FALSE((*again)[0]->duplicate);
  EXPECT_EQ((*again)[0]->record.id, applied);
  const StoredPassage revived = *store->GetPassage(applied);
  EXPECT_EQ(revived.state, PassageState::kQueued);
  EXPECT_EQ(revived.payload_pruned_unix_ms, 0);
  EXPECT_EQ(revived.error, "");
  auto claimed = store->ClaimNextPassage();
  ASSERT_TRUE(claimed.ok() && claimed->has_value()) << claimed.status();
  EXPECT_EQ((*claimed)->record.id, applied);
  EXPECT_EQ((*claimed)->payload, "bytes");
  ExpectStatsEqualTableCounts(store.get(), path);
  auto once_more = store->EnqueuePassages({MakeUpload("v", "applied")}, 0);
  ASSERT_TRUE(once_more.ok() && (*once_more)[0].ok());
  EXPECT_TRUE((*once_more)[0]->duplicate) << "taken again once";
}

// A queued passage whose upload is missing (a damaged queue file) is failed when it is claimed,
// and the claims go on with the next: it must not stop the queue.
TEST(SqliteMapStore, AQueuedPassageWithoutItsUploadIsFailedAndTheQueueGoesOn) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "damaged"), MakeUpload("v", "next", "other")}, 0).ok());
  const int64_t damaged = store->FindPassage("v", "damaged")->id;
  sqlite3* db = nullptr;
  sqlite3_open(SqliteQueuePath(path).c_str(), &db);
  ASSERT_EQ(sqlite3_exec(db, ("DELETE FROM passage_payloads WHERE id = " + std::to_string(damaged)).c_str(), nullptr,
                         nullptr, nullptr),
            SQLITE_OK);
  sqlite3_close(db);
  const auto first = store->ClaimNextPassage();
  EXPECT_EQ(first.status().code(), absl::StatusCode::kDataLoss) << first.status();
  const StoredPassage record = *store->GetPassage(damaged);
  EXPECT_EQ(record.state, PassageState::kFailed);
  EXPECT_NE(record.error.find("upload it again"), std::string::npos) << record.error;
  const auto next = store->ClaimNextPassage();
  ASSERT_TRUE(next.ok() && next->has_value()) << next.status();
  EXPECT_EQ((*next)->record.passage_id, "next");
  ExpectStatsEqualTableCounts(store.get(), path);
}

TEST(SqliteMapStore, AMapWithoutItsQueueFileIsRefused) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto store = OpenStore(path);
    const int64_t id = EnqueueAndClaim(store.get(), "p");
    ASSERT_TRUE(store->CommitPassageApplied(id, OneLandmarkDelta(0), SomeResult()).ok());
  }
  RemoveDatabaseFile(SqliteQueuePath(path));
  auto store = CreateSqliteMapStore(path);
  ASSERT_FALSE(store.ok());
  EXPECT_EQ(store.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(store.status().message().find("queue"), std::string_view::npos) << store.status();
}

// A map file of schema 4 held its queue: opening it moves the queue to its own file, once.
TEST(SqliteMapStore, ASchemaFourFileHasItsQueueMovedToTheQueueFile) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto db = SqliteConnection::Open(path, 5000, /*read_only=*/false);
    ASSERT_TRUE(db.ok()) << db.status();
    ASSERT_TRUE(MigrateSchema(db->get(), 4).ok());
    ASSERT_TRUE((*db)->Exec(R"sql(
        INSERT INTO passages (id, vehicle_id, passage_id, state, attempts, received_unix_ms, finished_unix_ms,
                              size_bytes, interruptions)
          VALUES (1, 'v', 'applied', 3, 1, 10, 20, 5, 0), (2, 'v', 'excluded', 6, 1, 11, 21, 5, 0),
                 (3, 'w', 'queued', 1, 0, 12, 0, 5, 2);
        INSERT INTO passage_payloads (id, payload) VALUES (1, CAST('one' AS BLOB)), (2, CAST('two' AS BLOB)), (3, CAST('three' AS BLOB));
        INSERT INTO passage_results (id, nodes, subgraphs, landmarks_updated, landmarks_created,
                                     landmarks_conditioned, detections_used, detections_dropped, solver_iterations,
                                     final_cost, solve_ms, covariance_ms, total_ms, map_version, strategy)
          VALUES (1, 40, 1, 0, 3, 0, 9, 0, 5, 1.5, 2, 3, 4, 1, 'cc'), (2, 41, 1, 0, 1, 0, 9, 0, 5, 1.5, 2, 3, 4, 2, 'cc');
        )sql")
                    .ok());
  }
  for (int open = 0; open < 2; ++open) {
    auto store = OpenStore(path);
    ASSERT_NE(store, nullptr);
    EXPECT_EQ(SqlInt(path, "PRAGMA user_version"), LatestSchemaVersion());
    EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM sqlite_master WHERE name = 'passages'"), 0);
    EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM map_passages"), 2) << "the applied and the excluded one";
    EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages"), 3 + open) << "copied once";
    EXPECT_EQ(*store->GetPassagePayload(3), "three");
    EXPECT_EQ(store->FindPassage("v", "applied")->result->nodes, 40);
    EXPECT_EQ(store->GetPassage(3)->interruptions, 2);
    ExpectStatsEqualTableCounts(store.get(), path);
    // Ids continue after the moved ones.
    if (open == 0) {
      auto out = store->EnqueuePassages({MakeUpload("w", "new")}, 0);
      ASSERT_TRUE(out.ok() && (*out)[0].ok());
      EXPECT_EQ((*out)[0]->record.id, 4);
    }
  }
}

// A start that copied a schema-4 file's queue and then failed before the map's own migration (a
// full disk, say), followed by a rollback to the release before: that release takes uploads into
// the map's file. The next start copies them too.
TEST(SqliteMapStore, UploadsTakenBySchemaFourAfterAnInterruptedUpgradeAreCopiedToo) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto db = SqliteConnection::Open(path, 5000, /*read_only=*/false);
    ASSERT_TRUE(db.ok()) << db.status();
    ASSERT_TRUE(MigrateSchema(db->get(), 4).ok());
    ASSERT_TRUE((*db)->Exec("INSERT INTO passages (id, vehicle_id, passage_id, state, attempts, received_unix_ms, "
                            "finished_unix_ms, size_bytes, interruptions) VALUES (1, 'v', 'before', 1, 0, 10, 0, 5, 0);"
                            "INSERT INTO passage_payloads (id, payload) VALUES (1, CAST('one' AS BLOB));")
                    .ok());
    auto queue = SqliteConnection::Open(SqliteQueuePath(path), 5000, /*read_only=*/false);
    ASSERT_TRUE(queue.ok()) << queue.status();
    ASSERT_TRUE(MigrateQueueSchema(queue->get()).ok());
    ASSERT_TRUE(ImportQueueFromMapFile(queue->get(), path).ok());  // then the start failed
    EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages"), 1);
    // The release before takes an upload into the map's file.
    ASSERT_TRUE((*db)->Exec("INSERT INTO passages (id, vehicle_id, passage_id, state, attempts, received_unix_ms, "
                            "finished_unix_ms, size_bytes, interruptions) VALUES (2, 'v', 'after', 1, 0, 11, 0, 5, 0);"
                            "INSERT INTO passage_payloads (id, payload) VALUES (2, CAST('two' AS BLOB));"
                            "UPDATE passages SET state = 4, error = 'rejected by the release before' WHERE id = 1;")
                    .ok());
  }
  auto store = OpenStore(path);
  ASSERT_NE(store, nullptr);
  ASSERT_TRUE(store->FindPassage("v", "after").ok()) << "the upload the release before took is not lost";
  EXPECT_EQ(*store->GetPassagePayload(2), "two");
  EXPECT_EQ(store->GetPassage(1)->state, PassageState::kRejected) << "the map file's queue is the truth";
  ExpectStatsEqualTableCounts(store.get(), path);
}

// A map file created anew beside a queue that has served (the map lost, to be rebuilt from the
// queue; or a schema-4 map restored beside it) starts at schema 4 with a queue of its own, empty or
// older: the queue file is kept, and its applied passages are queued again.
TEST(SqliteMapStore, AMapCreatedAnewBesideAServedQueueKeepsTheQueue) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto store = OpenStore(path);
    const int64_t first = EnqueueAndClaim(store.get(), "first");
    ASSERT_TRUE(store->CommitPassageApplied(first, OneLandmarkDelta(0), SomeResult()).ok());
    ASSERT_TRUE(store->EnqueuePassages({MakeUpload("v", "queued", "other")}, 0).ok());
  }
  RemoveDatabaseFile(path);
  auto store = OpenStore(path);
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passages"), 2);
  EXPECT_EQ(SqlInt(SqliteQueuePath(path), "SELECT COUNT(*) FROM passage_payloads"), 2);
  EXPECT_EQ(store->FindPassage("v", "first")->state, PassageState::kQueued) << "applied again to the new map";
  EXPECT_EQ(store->FindPassage("v", "queued")->state, PassageState::kQueued);
}

// A queue file older than its map (restored from an earlier backup than the map's, or emptied)
// would hand out ids the map already holds and let passages it contains be applied again: the
// store refuses to open, and changes nothing.
TEST(SqliteMapStore, AQueueFileOlderThanItsMapIsRefused) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  const std::string queue = SqliteQueuePath(path);
  const std::string old_queue = dir.File("queue.backup");
  {
    auto store = OpenStore(path);
    const int64_t first = EnqueueAndClaim(store.get(), "first");
    ASSERT_TRUE(store->CommitPassageApplied(first, OneLandmarkDelta(0), SomeResult()).ok());
  }
  std::filesystem::copy_file(queue, old_queue);  // the store closed: its log is checkpointed
  {
    auto store = OpenStore(path);
    const int64_t second = EnqueueAndClaim(store.get(), "second");
    ASSERT_TRUE(store->CommitPassageApplied(second, OneLandmarkDelta(1), SomeResult()).ok());
  }
  RemoveDatabaseFile(queue);
  std::filesystem::copy_file(old_queue, queue);
  auto refused = CreateSqliteMapStore(path);
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("id 2 missing"), std::string_view::npos) << refused.status();
  EXPECT_NE(refused.status().message().find("one backup"), std::string_view::npos) << refused.status();
  EXPECT_EQ(SqlInt(queue, "SELECT COUNT(*) FROM passages"), 1) << "nothing changed";

  // An empty queue file likewise.
  RemoveDatabaseFile(queue);
  std::ofstream(queue).close();
  auto empty = CreateSqliteMapStore(path);
  ASSERT_FALSE(empty.ok());
  EXPECT_NE(empty.status().message().find("2 passage(s)"), std::string_view::npos) << empty.status();
}

// A value SQLite cannot bind (over its length limit) fails the statement, naming the parameter,
// instead of being stored as NULL and reported as some constraint of the table.
TEST(SqliteStatement, AValueThatCannotBeBoundFailsTheStepAndIsNotStoredAsNull) {
  TempDir dir;
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(dir.File("t.db").c_str(), &db), SQLITE_OK);
  ASSERT_EQ(sqlite3_exec(db, "CREATE TABLE t (b BLOB NOT NULL)", nullptr, nullptr, nullptr), SQLITE_OK);
  sqlite3_limit(db, SQLITE_LIMIT_LENGTH, 100);
  sqlite3_stmt* raw = nullptr;
  ASSERT_EQ(sqlite3_prepare_v2(db, "INSERT INTO t (b) VALUES (?1)", -1, &raw, nullptr), SQLITE_OK);
  {
    SqliteStatement insert(db, raw);
    const absl::Status too_big = insert.BindBlob(1, std::string(1000, 'x')).Run();
    EXPECT_EQ(too_big.code(), absl::StatusCode::kInvalidArgument) << too_big;
    EXPECT_NE(too_big.message().find("bind of parameter 1"), std::string_view::npos) << too_big;
    EXPECT_TRUE(insert.BindBlob(1, std::string(10, 'x')).Run().ok()) << "the next step binds afresh";
  }
  sqlite3_finalize(raw);
  sqlite3_stmt* count = nullptr;
  ASSERT_EQ(sqlite3_prepare_v2(db, "SELECT COUNT(*), MAX(LENGTH(b)) FROM t", -1, &count, nullptr), SQLITE_OK);
  ASSERT_EQ(sqlite3_step(count), SQLITE_ROW);
  EXPECT_EQ(sqlite3_column_int(count, 0), 1);
  EXPECT_EQ(sqlite3_column_int(count, 1), 10);
  sqlite3_finalize(count);
  sqlite3_close(db);
}

VehicleCalibration MakeVehicle(const std::string& id, double yaw_rad, int64_t passages, int64_t version) {
  VehicleCalibration v;
  v.vehicle_id = id;
  v.camera_yaw_offset_rad = yaw_rad;
  v.camera_yaw_variance_rad2 = 1e-6 * passages;
  v.camera_yaw_information = 9e5 / passages;
  v.camera_yaw_map_term = 3.0 + passages;
  v.passages = passages;
  v.version = version;
  v.updated_unix_ms = 1000 + passages;
  return v;
}

void ExpectSameVehicle(const VehicleCalibration& a, const VehicleCalibration& b) {
  EXPECT_EQ(a.vehicle_id, b.vehicle_id);
  EXPECT_EQ(a.camera_yaw_offset_rad, b.camera_yaw_offset_rad) << a.vehicle_id << ": stored bit for bit";
  EXPECT_EQ(a.camera_yaw_variance_rad2, b.camera_yaw_variance_rad2) << a.vehicle_id;
  EXPECT_EQ(a.camera_yaw_information, b.camera_yaw_information) << a.vehicle_id;
  EXPECT_EQ(a.camera_yaw_map_term, b.camera_yaw_map_term) << a.vehicle_id;
  EXPECT_EQ(a.passages, b.passages) << a.vehicle_id;
  EXPECT_EQ(a.version, b.version) << a.vehicle_id;
  EXPECT_EQ(a.updated_unix_ms, b.updated_unix_ms) << a.vehicle_id;
}

TEST(SqliteMapStore, VehicleCalibrationsAreWrittenWithTheMapChangeAndReadBackAfterReopening) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto store = OpenStore(path);
    const int64_t first = EnqueueAndClaim(store.get(), "p1");
    MapDelta delta;
    delta.version = 1;
    delta.landmarks[7] = MakeLandmark(7, 48.7, 2.17, 1);
    delta.vehicles["veh-b"] = MakeVehicle("veh-b", 0.009, 1, 1);
    delta.vehicles["veh-a"] = MakeVehicle("veh-a", -0.004, 1, 1);
    ASSERT_TRUE(store->CommitPassageApplied(first, delta, PassageResult()).ok());
    // A later passage of one vehicle replaces its record.
    const int64_t second = EnqueueAndClaim(store.get(), "p2");
    MapDelta next;
    next.base_version = 1;
    next.version = 2;
    next.vehicles["veh-a"] = MakeVehicle("veh-a", -0.0035, 2, 2);
    ASSERT_TRUE(store->CommitPassageApplied(second, next, PassageResult()).ok());
  }
  for (bool cached : {false, true}) {
    std::unique_ptr<MapStoreInterface> store = OpenStore(path);
    if (cached) {
      auto wrapped = CachedMapStore::Create(std::move(store));
      ASSERT_TRUE(wrapped.ok()) << wrapped.status();
      store = std::move(*wrapped);
    }
    auto a = store->GetVehicle("veh-a");
    ASSERT_TRUE(a.ok()) << a.status();
    ExpectSameVehicle(*a, MakeVehicle("veh-a", -0.0035, 2, 2));
    auto missing = store->GetVehicle("veh-c");
    EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
    EXPECT_NE(missing.status().message().find("veh-c"), std::string::npos) << missing.status();
    auto all = store->ListVehicles();
    ASSERT_TRUE(all.ok()) << all.status();
    ASSERT_EQ(all->size(), 2u);
    EXPECT_EQ((*all)[0].vehicle_id, "veh-a");
    ExpectSameVehicle((*all)[1], MakeVehicle("veh-b", 0.009, 1, 1));
    // Pages: after a vehicle_id, at most a limit.
    auto first = store->ListVehicles("", 1);
    ASSERT_TRUE(first.ok()) << first.status();
    ASSERT_EQ(first->size(), 1u);
    EXPECT_EQ(first->front().vehicle_id, "veh-a");
    auto rest = store->ListVehicles("veh-a", 1);
    ASSERT_TRUE(rest.ok()) << rest.status();
    ASSERT_EQ(rest->size(), 1u);
    EXPECT_EQ(rest->front().vehicle_id, "veh-b");
    auto past = store->ListVehicles("veh-b", 10);
    ASSERT_TRUE(past.ok()) << past.status();
    EXPECT_TRUE(past->empty());
    MapState map;
    ASSERT_TRUE(store->LoadMap(&map).ok());
    ASSERT_NE(map.FindVehicle("veh-b"), nullptr);
    ExpectSameVehicle(*map.FindVehicle("veh-b"), (*all)[1]);
    EXPECT_TRUE(CheckStoredMap(map).ok());
  }
}

TEST(SqliteMapStore, ASchemaFiveMapGainsTheVehiclesTableAndRoomierBoxesAndKeepsItsMap) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  {
    auto store = OpenStore(path);
    const int64_t id = EnqueueAndClaim(store.get(), "p1");
    MapDelta delta;
    delta.version = 1;
    delta.landmarks[7] = MakeLandmark(7, 48.7, 2.17, 1);
    ASSERT_TRUE(store->CommitPassageApplied(id, delta, PassageResult()).ok());
  }
  // Back to the file schema 5 wrote: migration 5 -> 6 only adds the vehicles table, 6 -> 7 widens
  // the R*Tree boxes, which schema 5 wrote as points, 7 -> 8 adds the removed landmarks' table.
  ASSERT_EQ(LatestSchemaVersion(), 8);
  {
    auto db = SqliteConnection::Open(path, 5000, /*read_only=*/false);
    ASSERT_TRUE(db.ok()) << db.status();
    ASSERT_TRUE((*db)->Exec("DROP TABLE vehicles; DROP TABLE removed_landmarks; UPDATE landmark_boxes SET min_lat = 48.7, max_lat = 48.7, "
                            "min_lon = 2.17, max_lon = 2.17; PRAGMA user_version = 5;")
                    .ok());
  }
  ASSERT_EQ(SqlInt(path, "SELECT COUNT(*) FROM sqlite_master WHERE name = 'vehicles'"), 0);
  const std::string box_sql = "SELECT (max_lat - min_lat) * 1e9 FROM landmark_boxes WHERE id = 7";
  ASSERT_LT(SqlInt(path, box_sql), 10000);  // float rounding only
  auto store = OpenStore(path);
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(SqlInt(path, "PRAGMA user_version"), 8);
  EXPECT_GT(SqlInt(path, box_sql), 19000);  // 2e-5 degrees
  auto none = store->ListVehicles();
  ASSERT_TRUE(none.ok()) << none.status();
  EXPECT_TRUE(none->empty());
  MapState map;
  ASSERT_TRUE(store->LoadMap(&map).ok());
  EXPECT_EQ(map.landmark_count(), 1u);
  EXPECT_EQ(map.version(), 1);
  const int64_t id = EnqueueAndClaim(store.get(), "p2");
  MapDelta next;
  next.base_version = 1;
  next.version = 2;
  next.vehicles["veh-a"] = MakeVehicle("veh-a", 0.001, 1, 2);
  ASSERT_TRUE(store->CommitPassageApplied(id, next, PassageResult()).ok());
  EXPECT_EQ(store->GetVehicle("veh-a")->passages, 1);
}

TEST(SqliteMapStore, FoldedFactorsMoveIntoTheBaseAndTheMapStaysTheSame) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  MapDelta first;
  first.version = 1;
  for (LandmarkId id : {1, 2, 3}) first.landmarks[id] = MakeLandmark(id, 48.7 + 1e-4 * id, 2.17, 1);
  first.added_factors[1] = MakeFactor(1, {1, 2}, PairCovariance(Eigen::Matrix2d::Constant(0.01)));
  first.added_factors[2] = MakeFactor(2, {3, 2}, PairCovariance(Eigen::Matrix2d::Constant(-0.02)));
  ASSERT_TRUE(store->CommitPassageApplied(EnqueueAndClaim(store.get(), "a"), first, {}).ok());
  MapState before;
  ASSERT_TRUE(store->LoadMap(&before).ok());

  MapDelta fold;
  fold.base_version = 1;
  fold.version = 2;
  fold.folded_factors = {1, 2};
  ASSERT_TRUE(store->CommitPassageApplied(EnqueueAndClaim(store.get(), "b"), fold, {}).ok());
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM factors"), 0);
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM base_blocks"), 5) << "(1,1) (1,2) (2,2) (2,3) (3,3)";
  ExpectStatsEqualTableCounts(store.get(), path);
  MapState after;
  ASSERT_TRUE(store->LoadMap(&after).ok());
  EXPECT_EQ(after.factor_count(), 0u);
  for (LandmarkId a : {1, 2, 3}) {
    EXPECT_LT((after.InformationVector(a) - before.InformationVector(a)).cwiseAbs().maxCoeff(), 1e-12) << a;
    for (LandmarkId b : {1, 2, 3}) {
      EXPECT_LT((after.Information(a, b).value - before.Information(a, b).value).cwiseAbs().maxCoeff(), 1e-12)
          << a << "," << b;
      EXPECT_EQ(after.Information(a, b).factors > 0, before.Information(a, b).factors > 0) << a << "," << b;
    }
  }
  absl::StatusOr<Eigen::MatrixXd> cov_before = JointCovariance(before, {1, 2, 3});
  absl::StatusOr<Eigen::MatrixXd> cov_after = JointCovariance(after, {1, 2, 3});
  ASSERT_TRUE(cov_before.ok() && cov_after.ok());
  EXPECT_LT((*cov_after - *cov_before).cwiseAbs().maxCoeff(), 1e-12);
  // A window of one link around landmark 1 holds {1, 2}, and landmark 2's link to 3 leaves it: a
  // kept factor before the fold, the base loaded from the file after it.
  CovarianceBound bound = CovarianceBound::kExact;
  ASSERT_TRUE(JointCovariance(before, {1}, MapWindowOptions{1}, &bound).ok());
  EXPECT_EQ(bound, CovarianceBound::kConservative);
  ASSERT_TRUE(JointCovariance(after, {1}, MapWindowOptions{1}, &bound).ok());
  EXPECT_EQ(bound, CovarianceBound::kMayBeNarrower);
}

TEST(SqliteMapStore, CommitAgainstStaleVersionChangesNothing) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto store = OpenStore(path);
  const int64_t id = EnqueueAndClaim(store.get(), "p");
  MapDelta delta;
  delta.base_version = 5;
  delta.version = 6;
  delta.landmarks[1] = MakeLandmark(1, 48.7, 2.17, 6);
  EXPECT_EQ(store->CommitPassageApplied(id, delta, {}).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(SqlInt(path, "SELECT COUNT(*) FROM landmarks"), 0);
  EXPECT_EQ(SqlInt(path, "SELECT value FROM map_meta WHERE key = 'map_version'"), 0);
  EXPECT_EQ(store->GetPassage(id)->state, PassageState::kProcessing);
}

TEST(SqliteMapStore, CommitTwiceForOnePassageIsRefused) {
  TempDir dir;
  auto store = OpenStore(dir.File("map.db"));
  const int64_t id = EnqueueAndClaim(store.get(), "p");
  MapDelta delta;
  delta.version = 1;
  delta.landmarks[1] = MakeLandmark(1, 48.7, 2.17, 1);
  ASSERT_TRUE(store->CommitPassageApplied(id, delta, {}).ok());
  delta.base_version = 1;
  delta.version = 2;
  EXPECT_EQ(store->CommitPassageApplied(id, delta, {}).code(), absl::StatusCode::kFailedPrecondition);
}

// The map reads, on the SQLite store and on the in-memory cache in front of it.
class SqliteMapStoreReads : public ::testing::TestWithParam<bool> {
 protected:
  void SetUp() override {
    store_ = OpenStore(dir_.File("map.db"));
    if (GetParam()) {
      auto cached = CachedMapStore::Create(std::move(store_));
      ASSERT_TRUE(cached.ok()) << cached.status();
      store_ = std::move(*cached);
    }
    const int64_t id = EnqueueAndClaim(store_.get(), "p");
    MapDelta delta;
    delta.version = 3;
    // A 5 x 5 grid about 100 m apart; versions 1..3 by row.
    for (int i = 0; i < 5; ++i) {
      for (int j = 0; j < 5; ++j) {
        const LandmarkId lid = 100 + i * 5 + j;
        delta.landmarks[lid] = MakeLandmark(lid, 48.70 + 0.001 * i, 2.17 + 0.0015 * j, 1 + i % 3);
      }
    }
    // One joint factor on 100 and 101 (cross block 0.01), one factor on each other landmark.
    delta.added_factors[1] = MakeFactor(1, {100, 101}, PairCovariance(Eigen::Matrix2d::Constant(0.01)));
    for (LandmarkId lid = 102; lid < 125; ++lid) {
      delta.added_factors[lid] = MakeFactor(lid, {lid}, delta.landmarks[lid].cov_en_m2);
    }
    ASSERT_TRUE(store_->CommitPassageApplied(id, delta, {}).ok());
  }

  TempDir dir_;
  std::unique_ptr<MapStoreInterface> store_;
};

// The covariance SqliteMapStoreReads' map gives a page of its landmarks: each landmark's own, and
// every cross block zero but that of 100 and 101 (their joint factor).
void ExpectTheReadsCovariance(const LandmarkPage& page) {
  const size_t n = page.landmarks.size();
  ASSERT_EQ(page.covariance.rows(), static_cast<Eigen::Index>(2 * n));
  ASSERT_EQ(page.covariance.cols(), static_cast<Eigen::Index>(2 * n));
  for (size_t i = 0; i < n; ++i) {
    const Landmark& a = page.landmarks[i];
    EXPECT_LT((a.cov_en_m2 - MakeLandmark(a.id, 0, 0, 0).cov_en_m2).cwiseAbs().maxCoeff(), 1e-12) << a.id;
    EXPECT_EQ(Eigen::Matrix2d(page.covariance.block<2, 2>(2 * i, 2 * i)), a.cov_en_m2) << a.id;
    for (size_t j = 0; j < n; ++j) {
      if (i == j) continue;
      const Landmark& b = page.landmarks[j];
      const bool linked = std::minmax(a.id, b.id) == std::minmax(LandmarkId{100}, LandmarkId{101});
      const Eigen::Matrix2d block = page.covariance.block<2, 2>(2 * i, 2 * j);
      EXPECT_LT((block - Eigen::Matrix2d::Constant(linked ? 0.01 : 0.0)).cwiseAbs().maxCoeff(), 1e-12)
          << a.id << "," << b.id;
    }
  }
}

TEST_P(SqliteMapStoreReads, QueryRegionReturnsExactlyTheLandmarksInsideTheBox) {
  // Rows 0..1 and columns 0..2.
  BoundingBox box{48.6995, 2.1695, 48.7015, 2.1735};
  auto page = store_->QueryRegion(box, 0, 100, true);
  ASSERT_TRUE(page.ok());
  std::vector<LandmarkId> ids;
  for (const Landmark& l : page->landmarks) ids.push_back(l.id);
  EXPECT_EQ(ids, (std::vector<LandmarkId>{100, 101, 102, 105, 106, 107}));
  EXPECT_FALSE(page->more);
  EXPECT_EQ(page->map_version, 3);
  // Every pair among them, from the factors: only 100 and 101 are correlated.
  ExpectTheReadsCovariance(*page);
}

TEST_P(SqliteMapStoreReads, ProvenanceListsThePassagesOfTheLandmarksFactors) {
  auto provenance = store_->GetLandmarkProvenance(100);
  ASSERT_TRUE(provenance.ok()) << provenance.status();
  EXPECT_EQ(provenance->landmark.id, 100);
  EXPECT_EQ(provenance->map_version, 3);
  ASSERT_EQ(provenance->passages.size(), 1u);
  EXPECT_EQ(provenance->passages[0], (std::pair<std::string, std::string>{"v", "p1"}));
  EXPECT_EQ(store_->GetLandmarkProvenance(99).status().code(), absl::StatusCode::kNotFound);
}

TEST_P(SqliteMapStoreReads, QueryRegionPagesInIdOrder) {
  BoundingBox box{48.0, 2.0, 49.0, 3.0};
  std::vector<LandmarkId> ids;
  LandmarkId after = 0;
  int pages = 0;
  while (true) {
    auto page = store_->QueryRegion(box, after, 10, false);
    ASSERT_TRUE(page.ok());
    ++pages;
    for (const Landmark& l : page->landmarks) ids.push_back(l.id);
    if (!page->more) break;
    after = page->landmarks.back().id;
  }
  EXPECT_EQ(pages, 3);
  ASSERT_EQ(ids.size(), 25u);
  EXPECT_TRUE(std::is_sorted(ids.begin(), ids.end()));
}

TEST_P(SqliteMapStoreReads, TileHoldsTheLandmarksItContains) {
  const TileId tile = TileContaining({48.70, 2.17});
  auto page = store_->GetTile(tile, false);
  ASSERT_TRUE(page.ok());
  ASSERT_FALSE(page->landmarks.empty());
  for (const Landmark& l : page->landmarks) EXPECT_EQ(TileContaining(l.position), tile);
  int expected = 0;
  for (int i = 0; i < 5; ++i)
    for (int j = 0; j < 5; ++j) expected += TileContaining({48.70 + 0.001 * i, 2.17 + 0.0015 * j}) == tile;
  EXPECT_EQ(static_cast<int>(page->landmarks.size()), expected);
  EXPECT_EQ(store_->GetTile(TileId{15, 1, 1}, false).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_P(SqliteMapStoreReads, ChangedLandmarksAreThoseAboveTheVersion) {
  BoundingBox box{48.0, 2.0, 49.0, 3.0};
  auto page = store_->ChangedLandmarks(box, 2);
  ASSERT_TRUE(page.ok());
  ASSERT_FALSE(page->landmarks.empty());
  for (const Landmark& l : page->landmarks) EXPECT_EQ(l.version, 3);
  EXPECT_EQ(page->landmarks.size(), 5u);  // row i = 2
}

TEST_P(SqliteMapStoreReads, GetLandmarksReturnsTheMappedOnesOfTheIdsWithTheirCovariance) {
  // Unordered, repeated, and two ids the map does not hold.
  auto page = store_->GetLandmarks({107, 101, 99, 100, 101, 500}, true);
  ASSERT_TRUE(page.ok()) << page.status();
  EXPECT_EQ(page->map_version, 3);
  std::vector<LandmarkId> ids;
  for (const Landmark& l : page->landmarks) ids.push_back(l.id);
  EXPECT_EQ(ids, (std::vector<LandmarkId>{100, 101, 107}));
  // The same blocks as a box read of them gives: only 100 and 101 are correlated.
  ExpectTheReadsCovariance(*page);
  auto without = store_->GetLandmarks({124}, false);
  ASSERT_TRUE(without.ok());
  ASSERT_EQ(without->landmarks.size(), 1u);
  EXPECT_EQ(without->covariance.size(), 0);
  auto none = store_->GetLandmarks({}, true);
  ASSERT_TRUE(none.ok());
  EXPECT_TRUE(none->landmarks.empty());
}

INSTANTIATE_TEST_SUITE_P(Store, SqliteMapStoreReads, ::testing::Values(false, true),
                         [](const ::testing::TestParamInfo<bool>& info) { return info.param ? "Cached" : "Sqlite"; });

void ExpectSamePage(const absl::StatusOr<LandmarkPage>& got, const absl::StatusOr<LandmarkPage>& want) {
  ASSERT_TRUE(got.ok()) << got.status();
  ASSERT_TRUE(want.ok()) << want.status();
  EXPECT_EQ(got->map_version, want->map_version);
  EXPECT_EQ(got->more, want->more);
  ASSERT_EQ(got->landmarks.size(), want->landmarks.size());
  for (size_t i = 0; i < got->landmarks.size(); ++i) {
    const Landmark& a = got->landmarks[i];
    const Landmark& b = want->landmarks[i];
    EXPECT_EQ(a.id, b.id);
    EXPECT_EQ(a.position.lat_deg, b.position.lat_deg);
    EXPECT_EQ(a.position.lon_deg, b.position.lon_deg);
    EXPECT_EQ(a.cov_en_m2, b.cov_en_m2);
    EXPECT_EQ(a.version, b.version);
    EXPECT_EQ(a.passages_seen, b.passages_seen);
    EXPECT_EQ(a.last_seen_unix_ms, b.last_seen_unix_ms);
  }
  EXPECT_EQ(got->removed, want->removed);
}

// Landmarks created, moved across tile borders, updated, removed and brought back over many
// commits: after each one the cache answers every read exactly as SQLite does, the removals
// included; a refused commit changes neither.
TEST(CachedMapStore, AnswersLikeSqliteAcrossCommitsThatMoveLandmarksBetweenTiles) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto cached = CachedMapStore::Create(OpenStore(path));
  ASSERT_TRUE(cached.ok()) << cached.status();
  auto sqlite = OpenStore(path);  // a second connection to the same file, for reference
  const TileId home = TileContaining({48.70, 2.17});
  const BoundingBox tile_box = TileBounds(home);
  const BoundingBox around{tile_box.min_lat_deg - 0.002, tile_box.min_lon_deg - 0.002, tile_box.max_lat_deg + 0.002,
                           tile_box.max_lon_deg + 0.002};
  int64_t version = 0;
  for (int step = 0; step < 12; ++step) {
    const int64_t id = EnqueueAndClaim(cached->get(), "p" + std::to_string(step));
    MapDelta delta;
    delta.base_version = version;
    delta.version = ++version;
    for (LandmarkId lid = 1; lid <= 8; ++lid) {
      if ((lid + step) % 3 == 0) continue;  // some landmarks untouched by this commit
      // Walk each landmark across the tile's eastern and northern borders and back.
      const double t = 0.0004 * ((step * 5 + lid * 3) % 11) - 0.002;
      delta.landmarks[lid] = MakeLandmark(lid, tile_box.max_lat_deg + t * (lid % 2 ? 1 : -1),
                                          tile_box.max_lon_deg + t, version);
    }
    if (step % 3 == 2) {
      // Two landmarks removed (the next commits bring them back), one of them again.
      for (LandmarkId lid : {LandmarkId{1} + step % 8, LandmarkId{1} + (step + 3) % 8}) {
        delta.landmarks.erase(lid);
        delta.removed_landmarks.push_back(lid);
      }
    }
    ASSERT_TRUE((*cached)->CommitPassageApplied(id, delta, {}).ok());
    ExpectSamePage((*cached)->ChangedLandmarks(around, 0), sqlite->ChangedLandmarks(around, 0));
    if (step % 3 == 2) {
      auto changed = (*cached)->ChangedLandmarks(around, version - 1);
      ASSERT_TRUE(changed.ok());
      EXPECT_EQ(changed->removed.size(), 2u) << "step " << step;
    }
    for (LandmarkId after : {0, 3}) {
      ExpectSamePage((*cached)->QueryRegion(around, after, 0, false), sqlite->QueryRegion(around, after, 0, false));
      ExpectSamePage((*cached)->QueryRegion(around, after, 3, false), sqlite->QueryRegion(around, after, 3, false));
      ExpectSamePage((*cached)->QueryRegion(tile_box, after, 0, false),
                     sqlite->QueryRegion(tile_box, after, 0, false));
    }
    for (int dx = 0; dx <= 1; ++dx) {
      for (int dy = -1; dy <= 0; ++dy) {
        const TileId tile{kStorageZoom, home.x + dx, home.y + dy};
        ExpectSamePage((*cached)->GetTile(tile, false), sqlite->GetTile(tile, false));
      }
    }
    ExpectSamePage((*cached)->ChangedLandmarks(around, version - 1), sqlite->ChangedLandmarks(around, version - 1));
    // The whole world: more tiles in range than in the map.
    ExpectSamePage((*cached)->QueryRegion({-85, -180, 85, 180}, 0, 0, false),
                   sqlite->QueryRegion({-85, -180, 85, 180}, 0, 0, false));
  }

  // A commit the store refuses (stale base version) is not published.
  const int64_t id = EnqueueAndClaim(cached->get(), "stale");
  MapDelta stale;
  stale.base_version = version - 1;
  stale.version = version + 1;
  stale.landmarks[99] = MakeLandmark(99, 48.70, 2.17, version + 1);
  EXPECT_EQ((*cached)->CommitPassageApplied(id, stale, {}).code(), absl::StatusCode::kFailedPrecondition);
  ExpectSamePage((*cached)->QueryRegion(around, 0, 0, false), sqlite->QueryRegion(around, 0, 0, false));

  // A cache opened on the file later starts from what is stored.
  auto reopened = CachedMapStore::Create(OpenStore(path));
  ASSERT_TRUE(reopened.ok());
  ExpectSamePage((*reopened)->QueryRegion(around, 0, 0, false), (*cached)->QueryRegion(around, 0, 0, false));
  ExpectSamePage((*reopened)->ChangedLandmarks(around, 0), (*cached)->ChangedLandmarks(around, 0));
}

// Reads with covariances share one factorisation of the whole map per version, and on a small
// map its whole covariance (the parameter: the largest map that keeps it; 0 = never): after every
// commit (each changes the information), twice in a row, they equal SQLite's, which factorises per
// read.
class CachedMapStoreCovariance : public ::testing::TestWithParam<int> {};

TEST_P(CachedMapStoreCovariance, ReadsFollowEveryCommit) {
  TempDir dir;
  const std::string path = dir.File("map.db");
  auto cached = CachedMapStore::Create(OpenStore(path), /*covariance_window_hops=*/0, GetParam());
  ASSERT_TRUE(cached.ok()) << cached.status();
  auto sqlite = OpenStore(path);
  const BoundingBox box{48.69, 2.16, 48.72, 2.18};
  for (int step = 0; step < 6; ++step) {
    const int64_t id = EnqueueAndClaim(cached->get(), "p" + std::to_string(step));
    MapDelta delta;
    delta.base_version = step;
    delta.version = step + 1;
    for (LandmarkId lid : {1, 2, 3}) delta.landmarks[lid] = MakeLandmark(lid, 48.70 + 1e-4 * lid, 2.17, step + 1);
    Eigen::Matrix2d block;
    block << 0.01 * (step + 1), 0.02, -0.01, 0.03;
    delta.added_factors[step + 1] = MakeFactor(step + 1, {step % 2 ? 1 : 2, 3}, PairCovariance(block));
    if (step == 0) delta.added_factors[100] = MakeFactor(100, {1, 2}, PairCovariance(-block));
    ASSERT_TRUE((*cached)->CommitPassageApplied(id, delta, {}).ok());
    for (int read = 0; read < 2; ++read) {
      auto got = (*cached)->QueryRegion(box, 0, 0, true);
      auto want = sqlite->QueryRegion(box, 0, 0, true);
      ASSERT_TRUE(got.ok() && want.ok()) << got.status() << want.status();
      ASSERT_EQ(got->landmarks.size(), 3u);
      ASSERT_EQ(got->covariance.rows(), 6);
      ASSERT_EQ(want->covariance.rows(), 6);
      EXPECT_LT((got->covariance - want->covariance).cwiseAbs().maxCoeff(), 1e-12)
          << "step " << step << " read " << read;
      for (size_t i = 0; i < got->landmarks.size(); ++i) {
        EXPECT_LT((got->landmarks[i].cov_en_m2 - want->landmarks[i].cov_en_m2).cwiseAbs().maxCoeff(), 1e-12)
            << "step " << step << " read " << read;
      }
      // Two of the three, out of order: the same blocks.
      auto some = (*cached)->GetLandmarks({3, 1}, true);
      auto some_want = sqlite->GetLandmarks({3, 1}, true);
      ASSERT_TRUE(some.ok() && some_want.ok()) << some.status() << some_want.status();
      ASSERT_EQ(some->landmarks.size(), 2u);
      ASSERT_EQ(some->covariance.rows(), 4);
      EXPECT_LT((some->covariance - some_want->covariance).cwiseAbs().maxCoeff(), 1e-12);
      EXPECT_LT((some->landmarks[1].cov_en_m2 - some_want->landmarks[1].cov_en_m2).cwiseAbs().maxCoeff(), 1e-12);
    }
  }
}

INSTANTIATE_TEST_SUITE_P(CacheSize, CachedMapStoreCovariance,
                         ::testing::Values(0, 2, CachedMapStore::kDefaultCovarianceCacheLandmarks));

TEST(CachedMapStore, RefusesANegativeCovarianceCacheSize) {
  TempDir dir;
  EXPECT_EQ(CachedMapStore::Create(OpenStore(dir.File("map.db")), 0, -1).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace crowdmap
