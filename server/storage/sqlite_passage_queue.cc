// The durable passage queue of the SQLite map store.
#include <algorithm>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "server/storage/sqlite_map_store.h"

namespace crowdmap {
namespace {

constexpr char kPassageColumns[] =
    "SELECT p.id, p.vehicle_id, p.passage_id, p.state, p.attempts, p.error, p.received_unix_ms, "
    "p.finished_unix_ms, p.size_bytes, r.nodes, r.subgraphs, r.landmarks_updated, r.landmarks_created, "
    "r.landmarks_conditioned, r.detections_used, r.detections_dropped, r.solver_iterations, r.final_cost, "
    "r.solve_ms, r.covariance_ms, r.total_ms, r.map_version, r.strategy, p.interruptions, p.released, p.payload_pruned_unix_ms "
    "FROM passages p LEFT JOIN passage_results r ON r.id = p.id ";

StoredPassage PassageFromRow(const SqliteStatement& s) {
  StoredPassage p;
  p.id = s.Int(0);
  p.vehicle_id = s.Text(1);
  p.passage_id = s.Text(2);
  p.state = static_cast<PassageState>(s.Int(3));
  p.attempts = static_cast<int>(s.Int(4));
  p.error = s.Text(5);
  p.received_unix_ms = s.Int(6);
  p.finished_unix_ms = s.Int(7);
  p.size_bytes = s.Int(8);
  p.interruptions = static_cast<int>(s.Int(23));
  p.released = s.Int(24) != 0;
  p.payload_pruned_unix_ms = s.Int(25);
  if (!s.IsNull(9)) {
    PassageResult r;
    r.nodes = static_cast<int>(s.Int(9));
    r.subgraphs = static_cast<int>(s.Int(10));
    r.landmarks_updated = static_cast<int>(s.Int(11));
    r.landmarks_created = static_cast<int>(s.Int(12));
    r.landmarks_conditioned = static_cast<int>(s.Int(13));
    r.detections_used = static_cast<int>(s.Int(14));
    r.detections_dropped = static_cast<int>(s.Int(15));
    r.solver_iterations = static_cast<int>(s.Int(16));
    r.final_cost = s.Double(17);
    r.solve_ms = s.Double(18);
    r.covariance_ms = s.Double(19);
    r.total_ms = s.Double(20);
    r.map_version = s.Int(21);
    r.strategy = s.Text(22);
    p.result = r;
  }
  return p;
}

absl::StatusOr<std::optional<StoredPassage>> ReadOne(SqliteStatement& stmt) {
  auto row = stmt.Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::optional<StoredPassage>();
  return std::optional<StoredPassage>(PassageFromRow(stmt));
}

// Queued and processing passages, from the counts the schema's triggers keep (no scan).
absl::StatusOr<int64_t> CountActive(SqliteConnection* db) {
  auto stmt = db->Prepare("SELECT SUM(n) FROM row_counts WHERE name IN ('passages_1', 'passages_2')");
  if (!stmt.ok()) return stmt.status();
  if (auto row = stmt->Step(); !row.ok()) return row.status();
  return stmt->Int(0);
}

}  // namespace

int64_t NowUnixMs() { return absl::ToUnixMillis(absl::Now()); }

const char* PassageStateName(PassageState state) {
  switch (state) {
    case PassageState::kQueued: return "queued";
    case PassageState::kProcessing: return "processing";
    case PassageState::kApplied: return "applied";
    case PassageState::kRejected: return "rejected";
    case PassageState::kFailed: return "failed";
    case PassageState::kExcluded: return "excluded";
    case PassageState::kQuarantined: return "quarantined";
    case PassageState::kDiscarded: return "discarded";
  }
  return "unknown";
}

absl::StatusOr<std::optional<StoredPassage>> SqliteMapStore::ReadPassage(SqliteConnection* db, int64_t id) {
  auto stmt = db->Prepare(absl::StrCat(kPassageColumns, "WHERE p.id = ?1"));
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, id);
  return ReadOne(*stmt);
}

absl::StatusOr<std::optional<StoredPassage>> SqliteMapStore::ReadPassageByKey(SqliteConnection* db,
                                                                             const std::string& vehicle_id,
                                                                             const std::string& passage_id) {
  auto stmt = db->Prepare(absl::StrCat(kPassageColumns, "WHERE p.vehicle_id = ?1 AND p.passage_id = ?2"));
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, std::string_view(vehicle_id)).Bind(2, std::string_view(passage_id));
  return ReadOne(*stmt);
}

absl::StatusOr<std::optional<StoredPassage>> SqliteMapStore::ReadPassageByContent(SqliteConnection* db,
                                                                                 const std::string& digest) {
  auto stmt = db->Prepare(absl::StrCat(kPassageColumns, "WHERE p.content_digest = ?1 ORDER BY p.id LIMIT 1"));
  if (!stmt.ok()) return stmt.status();
  stmt->BindBlob(1, digest);
  return ReadOne(*stmt);
}

absl::StatusOr<std::vector<absl::StatusOr<EnqueueOutcome>>> SqliteMapStore::EnqueuePassages(
    const std::vector<NewPassage>& passages, int64_t max_queue) {
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  auto depth = CountActive(db);
  if (!depth.ok()) return depth.status();

  std::vector<absl::StatusOr<EnqueueOutcome>> outcomes;
  outcomes.reserve(passages.size());
  for (const NewPassage& p : passages) {
    auto existing = ReadPassageByKey(db, p.vehicle_id, p.passage_id);
    if (!existing.ok()) return existing.status();
    // A failed passage whose upload was deleted (a map restored from a backup older than the fold
    // of its factors) is taken again under its record: its drive is in neither the map nor the queue.
    const bool revive = existing->has_value() && (*existing)->state == PassageState::kFailed &&
                        (*existing)->payload_pruned_unix_ms > 0;
    if (existing->has_value() && !revive) {
      outcomes.push_back(EnqueueOutcome{**existing, true});
      continue;
    }
    if (!p.content_digest.empty()) {
      auto same = ReadPassageByContent(db, p.content_digest);
      if (!same.ok()) return same.status();
      if (same->has_value() && !(revive && (*same)->id == (*existing)->id)) {
        // Another vehicle's ids are not told (its queue id is: operators can look it up, and a
        // vehicle may read only its own passages).
        const StoredPassage& original = **same;
        const std::string which = original.vehicle_id == p.vehicle_id
                                      ? absl::StrCat("passage ", original.vehicle_id, "/", original.passage_id)
                                      : std::string("an upload of another vehicle");
        outcomes.push_back(absl::AlreadyExistsError(
            absl::StrCat("passage: its measurements are identical to those of ", which, " (id ", original.id, ", ",
                         PassageStateName(original.state), "); a drive is taken once, whatever ids it comes under")));
        continue;
      }
    }
    if (max_queue > 0 && *depth >= max_queue) {
      outcomes.push_back(absl::ResourceExhaustedError(
          absl::StrCat("passage queue is full (", *depth, " of ", max_queue, " passages); retry later")));
      continue;
    }
    auto insert = db->Prepare(
        revive ? "UPDATE passages SET state = 1, received_unix_ms = ?3, size_bytes = ?4, content_digest = ?5, "
                 "attempts = 0, interruptions = 0, released = 0, error = '', finished_unix_ms = 0, "
                 "payload_pruned_unix_ms = 0 WHERE vehicle_id = ?1 AND passage_id = ?2"
               : "INSERT INTO passages (vehicle_id, passage_id, state, received_unix_ms, size_bytes, content_digest) "
                 "VALUES (?1, ?2, 1, ?3, ?4, ?5)");
    if (!insert.ok()) return insert.status();
    insert->Bind(1, std::string_view(p.vehicle_id))
        .Bind(2, std::string_view(p.passage_id))
        .Bind(3, p.received_unix_ms)
        .Bind(4, static_cast<int64_t>(p.payload.size()));
    if (p.content_digest.empty()) {
      insert->BindNull(5);
    } else {
      insert->BindBlob(5, p.content_digest);
    }
    if (auto s = insert->Run(); !s.ok()) return s;
    const int64_t id = revive ? (*existing)->id : db->LastInsertRowId();
    if (revive) {  // the result of its first application is not this one's
      auto result = db->Prepare("DELETE FROM passage_results WHERE id = ?1");
      if (!result.ok()) return result.status();
      result->Bind(1, id);
      if (auto s = result->Run(); !s.ok()) return s;
    }
    auto payload = db->Prepare("INSERT INTO passage_payloads (id, payload) VALUES (?1, ?2)");
    if (!payload.ok()) return payload.status();
    payload->Bind(1, id).BindBlob(2, p.payload);
    if (auto s = payload->Run(); !s.ok()) return s;
    ++*depth;

    StoredPassage record;
    record.id = id;
    record.vehicle_id = p.vehicle_id;
    record.passage_id = p.passage_id;
    record.state = PassageState::kQueued;
    record.received_unix_ms = p.received_unix_ms;
    record.size_bytes = static_cast<int64_t>(p.payload.size());
    outcomes.push_back(EnqueueOutcome{std::move(record), false});
  }
  if (auto s = txn->Commit(); !s.ok()) return s;
  return outcomes;
}

absl::StatusOr<StoredPassage> SqliteMapStore::GetPassage(int64_t id) {
  auto db = queue_->AcquireReader();
  if (!db.ok()) return db.status();
  auto record = ReadPassage(db->get(), id);
  if (!record.ok()) return record.status();
  if (!record->has_value()) return PassageIdNotFoundError(id);
  return **record;
}

absl::StatusOr<StoredPassage> SqliteMapStore::FindPassage(const std::string& vehicle_id,
                                                          const std::string& passage_id) {
  auto db = queue_->AcquireReader();
  if (!db.ok()) return db.status();
  auto record = ReadPassageByKey(db->get(), vehicle_id, passage_id);
  if (!record.ok()) return record.status();
  if (!record->has_value()) {
    return absl::NotFoundError(absl::StrCat("passage ", vehicle_id, "/", passage_id, " not found"));
  }
  return **record;
}

absl::StatusOr<std::vector<StoredPassage>> SqliteMapStore::ListPassages(const PassageQuery& query) {
  auto db = queue_->AcquireReader();
  if (!db.ok()) return db.status();
  // Only the filters asked for, written as plain equalities: SQLite then reads a state's passages
  // by its index (state, id) and a vehicle's by (vehicle_id, passage_id), where "?2 = 0 OR ..."
  // made it walk the whole queue by id.
  auto stmt = (*db)->Prepare(absl::StrCat(kPassageColumns, "WHERE p.id > ?1",
                                          query.state ? " AND p.state = ?2" : "",
                                          query.vehicle_id.empty() ? "" : " AND p.vehicle_id = ?3",
                                          " ORDER BY p.id LIMIT ?4"));
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, query.after_id)
      .Bind(2, static_cast<int64_t>(query.state ? static_cast<int>(*query.state) : 0))
      .Bind(3, std::string_view(query.vehicle_id))
      .Bind(4, static_cast<int64_t>(query.limit));
  std::vector<StoredPassage> out;
  while (true) {
    auto row = stmt->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out.push_back(PassageFromRow(*stmt));
  }
  return out;
}

absl::StatusOr<std::string> SqliteMapStore::GetPassagePayload(int64_t id) {
  auto db = queue_->AcquireReader();
  if (!db.ok()) return db.status();
  auto stmt = (*db)->Prepare("SELECT payload FROM passage_payloads WHERE id = ?1");
  if (!stmt.ok()) return stmt.status();
  stmt->Bind(1, id);
  auto row = stmt->Step();
  if (!row.ok()) return row.status();
  if (*row) return stmt->Blob(0);
  auto record = ReadPassage(db->get(), id);
  if (!record.ok()) return record.status();
  if (record->has_value() && (*record)->payload_pruned_unix_ms > 0) {
    if ((*record)->state == PassageState::kApplied) {
      return absl::NotFoundError(absl::StrCat(
          "payload of passage id ", id,
          " was deleted once its factors were folded into the map's base, or after it was excluded (a map restored "
          "from an older backup applies it again)"));
    }
    return absl::NotFoundError(absl::StrCat("payload of passage id ", id, " (", PassageStateName((*record)->state),
                                            ") was deleted after the retention of settled uploads"));
  }
  return absl::NotFoundError(absl::StrCat("payload of passage id ", id, " not found"));
}

absl::StatusOr<int> SqliteMapStore::PrunePassagePayloads(
    const std::vector<std::pair<std::string, std::string>>& passages) {
  if (passages.empty()) return 0;
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  const int64_t now = NowUnixMs();
  int pruned = 0;
  for (const auto& [vehicle_id, passage_id] : passages) {
    int64_t id = 0;
    {
      auto mark = db->Prepare(
          "UPDATE passages SET payload_pruned_unix_ms = ?3 "
          "WHERE vehicle_id = ?1 AND passage_id = ?2 AND state = 3 AND payload_pruned_unix_ms = 0 RETURNING id");
      if (!mark.ok()) return mark.status();
      mark->Bind(1, std::string_view(vehicle_id)).Bind(2, std::string_view(passage_id)).Bind(3, now);
      auto row = mark->Step();
      if (!row.ok()) return row.status();
      if (!*row) continue;  // not applied, or pruned already
      id = mark->Int(0);
      if (auto done = mark->Step(); !done.ok()) return done.status();
    }
    auto erase = db->Prepare("DELETE FROM passage_payloads WHERE id = ?1");
    if (!erase.ok()) return erase.status();
    erase->Bind(1, id);
    if (auto s = erase->Run(); !s.ok()) return s;
    ++pruned;
  }
  if (auto s = txn->Commit(); !s.ok()) return s;
  return pruned;
}

absl::StatusOr<int> SqliteMapStore::PruneSettledPayloads(int64_t finished_before_unix_ms, int limit) {
  if (limit <= 0) return 0;
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  std::vector<int64_t> ids;
  {
    auto mark = db->Prepare(absl::StrCat(
        "UPDATE passages SET payload_pruned_unix_ms = ?3 WHERE id IN (SELECT id FROM passages WHERE state IN (",
        static_cast<int>(PassageState::kRejected), ", ", static_cast<int>(PassageState::kExcluded), ", ",
        static_cast<int>(PassageState::kDiscarded),
        ") AND payload_pruned_unix_ms = 0 AND finished_unix_ms > 0 AND finished_unix_ms < ?1 ORDER BY id LIMIT ?2) "
        "RETURNING id"));
    if (!mark.ok()) return mark.status();
    mark->Bind(1, finished_before_unix_ms).Bind(2, static_cast<int64_t>(limit)).Bind(3, NowUnixMs());
    for (;;) {
      auto row = mark->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      ids.push_back(mark->Int(0));
    }
  }
  for (int64_t id : ids) {
    auto erase = db->Prepare("DELETE FROM passage_payloads WHERE id = ?1");
    if (!erase.ok()) return erase.status();
    erase->Bind(1, id);
    if (auto s = erase->Run(); !s.ok()) return s;
  }
  if (auto s = txn->Commit(); !s.ok()) return s;
  return static_cast<int>(ids.size());
}

absl::StatusOr<std::optional<ClaimedPassage>> SqliteMapStore::Claim(bool started) {
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  ConfirmPending(db);
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  auto next = db->Prepare("SELECT id FROM passages WHERE state = 1 ORDER BY id LIMIT 1");
  if (!next.ok()) return next.status();
  auto row = next->Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::optional<ClaimedPassage>();
  const int64_t id = next->Int(0);

  auto update = db->Prepare("UPDATE passages SET state = 2, attempts = attempts + 1, started = ?2 WHERE id = ?1");
  if (!update.ok()) return update.status();
  update->Bind(1, id).Bind(2, static_cast<int64_t>(started));
  if (auto s = update->Run(); !s.ok()) return s;

  ClaimedPassage claimed;
  auto record = ReadPassage(db, id);
  if (!record.ok()) return record.status();
  claimed.record = **record;
  auto payload = db->Prepare("SELECT payload FROM passage_payloads WHERE id = ?1");
  if (!payload.ok()) return payload.status();
  payload->Bind(1, id);
  auto payload_row = payload->Step();
  if (!payload_row.ok()) return payload_row.status();
  if (!*payload_row) {
    // Failed rather than left first in line, where every later claim would stop at it.
    const std::string error = absl::StrCat("passage id ", id, ": its upload is missing from the queue file");
    auto fail = db->Prepare("UPDATE passages SET state = 5, error = ?2, finished_unix_ms = ?3 WHERE id = ?1");
    if (!fail.ok()) return fail.status();
    fail->Bind(1, id).Bind(2, absl::StrCat(error, ": upload it again")).Bind(3, NowUnixMs());
    if (auto s = fail->Run(); !s.ok()) return s;
    if (auto s = txn->Commit(); !s.ok()) return s;
    return absl::DataLossError(absl::StrCat(error, "; marked failed"));
  }
  claimed.payload = payload->Blob(0);
  if (auto s = txn->Commit(); !s.ok()) return s;
  return std::optional<ClaimedPassage>(std::move(claimed));
}

absl::Status SqliteMapStore::FinishPassageWithoutChange(int64_t id, PassageState state, const std::string& reason) {
  if (state == PassageState::kApplied || state == PassageState::kProcessing) {
    return absl::InvalidArgumentError("FinishPassageWithoutChange: state must not be applied or processing");
  }
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  auto update = db->Prepare(
      "UPDATE passages SET state = ?2, error = ?3, finished_unix_ms = CASE WHEN ?2 = 1 THEN 0 ELSE ?4 END "
      "WHERE id = ?1 AND state = 2");
  if (!update.ok()) return update.status();
  update->Bind(1, id).Bind(2, static_cast<int64_t>(state)).Bind(3, std::string_view(reason)).Bind(4, NowUnixMs());
  if (auto s = update->Run(); !s.ok()) return s;
  if (db->Changes() != 1) return absl::FailedPreconditionError(absl::StrCat("passage id ", id, " is not processing"));
  return txn->Commit();
}

absl::Status SqliteMapStore::UpdateProcessingPassage(int64_t id, const char* set) {
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  auto update = db->Prepare(absl::StrCat("UPDATE passages SET ", set, " WHERE id = ?1 AND state = 2"));
  if (!update.ok()) return update.status();
  update->Bind(1, id);
  if (auto s = update->Run(); !s.ok()) return s;
  if (db->Changes() != 1) return absl::FailedPreconditionError(absl::StrCat("passage id ", id, " is not processing"));
  return txn->Commit();
}

absl::Status SqliteMapStore::MarkPassageStarted(int64_t id) { return UpdateProcessingPassage(id, "started = 1"); }

absl::Status SqliteMapStore::ReleaseClaimedPassage(int64_t id) {
  return UpdateProcessingPassage(id, "state = 1, attempts = MAX(attempts - 1, 0)");
}

absl::StatusOr<int> SqliteMapStore::RecordFailedAttempt(int64_t id, const std::string& reason) {
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  auto update = db->Prepare("UPDATE passages SET attempts = attempts + 1, error = ?2 WHERE id = ?1 AND state = 2");
  if (!update.ok()) return update.status();
  update->Bind(1, id).Bind(2, std::string_view(reason));
  if (auto s = update->Run(); !s.ok()) return s;
  if (db->Changes() != 1) return absl::FailedPreconditionError(absl::StrCat("passage id ", id, " is not processing"));
  auto record = ReadPassage(db, id);
  if (!record.ok()) return record.status();
  if (auto s = txn->Commit(); !s.ok()) return s;
  return (*record)->attempts;
}

absl::StatusOr<StoredPassage> SqliteMapStore::MovePassage(int64_t id, const std::vector<PassageState>& from,
                                                          PassageState to, bool released) {
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  auto record = ReadPassage(db, id);
  if (!record.ok()) return record.status();
  if (!*record) return absl::NotFoundError(absl::StrCat("passage id ", id, ": no such passage"));
  if (std::find(from.begin(), from.end(), (*record)->state) == from.end()) {
    return absl::FailedPreconditionError(
        absl::StrCat("passage ", id, " is ", PassageStateName((*record)->state), ": not in a state this applies to"));
  }
  const bool queued = to == PassageState::kQueued;
  if (queued) {
    auto payload = db->Prepare("SELECT 1 FROM passage_payloads WHERE id = ?1");
    if (!payload.ok()) return payload.status();
    payload->Bind(1, id);
    auto found = payload->Step();
    if (!found.ok()) return found.status();
    if (!*found) {
      return absl::FailedPreconditionError(absl::StrCat(
          "passage ", id, ": its upload is no longer stored",
          (*record)->payload_pruned_unix_ms > 0 ? " (deleted once its factors were folded into the map's base)" : "",
          ", so it cannot be queued again: upload the drive again, under the same vehicle_id and passage_id"));
    }
  }
  auto update = db->Prepare(
      "UPDATE passages SET state = ?2, attempts = CASE WHEN ?3 THEN 0 ELSE attempts END, "
      "error = CASE WHEN ?3 THEN '' ELSE error END, finished_unix_ms = CASE WHEN ?3 THEN 0 ELSE ?4 END, "
      "released = ?5 WHERE id = ?1");
  if (!update.ok()) return update.status();
  update->Bind(1, id)
      .Bind(2, static_cast<int64_t>(to))
      .Bind(3, static_cast<int64_t>(queued))
      .Bind(4, NowUnixMs())
      .Bind(5, static_cast<int64_t>(released));
  if (auto s = update->Run(); !s.ok()) return s;
  auto moved = ReadPassage(db, id);
  if (!moved.ok()) return moved.status();
  if (auto s = txn->Commit(); !s.ok()) return s;
  return **moved;
}

absl::StatusOr<int> SqliteMapStore::RequeueProcessingPassages() {
  SqliteFile::Writer writer = queue_->LockWriter();
  SqliteConnection* db = writer.db;
  // A passage whose map change the queue has yet to record is in the map: never queue it again.
  ConfirmPending(db);
  if (!pending_.empty()) {
    return absl::UnavailableError(absl::StrCat("passage id ", pending_.front().id,
                                               " is in the map but the queue cannot record it yet; retry"));
  }
  auto txn = SqliteWriteTransaction::Begin(db);
  if (!txn.ok()) return txn.status();
  // The interrupted attempt is not counted: it says nothing about the passage. An interruption is,
  // where the passage was being applied (a passage that crashes the server is failed after
  // MapWorkerOptions::max_interruptions); not where a worker had only claimed it ahead.
  if (auto s = db->Exec("UPDATE passages SET state = 1, attempts = MAX(attempts - 1, 0), "
                        "interruptions = interruptions + started, started = 0 WHERE state = 2");
      !s.ok()) {
    return s;
  }
  const int changed = db->Changes();
  if (auto s = txn->Commit(); !s.ok()) return s;
  return changed;
}

}  // namespace crowdmap
