#include "server/storage/sqlite_db.h"

#include <sqlite3.h>

#include "absl/strings/str_cat.h"
#include "spdlog/spdlog.h"

namespace crowdmap {
namespace {

absl::Status SqliteError(sqlite3* db, int rc, std::string_view what) {
  const std::string message = absl::StrCat("sqlite ", std::string(what), ": ", db ? sqlite3_errmsg(db) : sqlite3_errstr(rc));
  switch (rc & 0xff) {
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
      return absl::UnavailableError(message);
    case SQLITE_CONSTRAINT:
      return absl::AlreadyExistsError(message);
    case SQLITE_CORRUPT:
    case SQLITE_NOTADB:
      return absl::DataLossError(message);
    case SQLITE_TOOBIG:
      return absl::InvalidArgumentError(absl::StrCat(message, " (over the database's length limit)"));
    case SQLITE_FULL:
      return absl::ResourceExhaustedError(absl::StrCat(message, " (no space left for the database; retry later)"));
    case SQLITE_IOERR:
      return absl::UnavailableError(message);
    default:
      return absl::InternalError(message);
  }
}

}  // namespace

SqliteStatement::~SqliteStatement() {
  if (stmt_ == nullptr) return;
  sqlite3_reset(stmt_);
  sqlite3_clear_bindings(stmt_);
}

void SqliteStatement::Bound(int rc, int index) {
  if (rc == SQLITE_OK || bind_rc_ != SQLITE_OK) return;
  bind_rc_ = rc;
  bind_index_ = index;
}

SqliteStatement& SqliteStatement::Bind(int index, int64_t value) {
  Bound(sqlite3_bind_int64(stmt_, index, value), index);
  return *this;
}

SqliteStatement& SqliteStatement::Bind(int index, double value) {
  Bound(sqlite3_bind_double(stmt_, index, value), index);
  return *this;
}

SqliteStatement& SqliteStatement::Bind(int index, std::string_view text) {
  Bound(sqlite3_bind_text64(stmt_, index, text.data(), text.size(), SQLITE_TRANSIENT, SQLITE_UTF8), index);
  return *this;
}

SqliteStatement& SqliteStatement::BindBlob(int index, std::string_view bytes) {
  Bound(sqlite3_bind_blob64(stmt_, index, bytes.data(), bytes.size(), SQLITE_TRANSIENT), index);
  return *this;
}

SqliteStatement& SqliteStatement::BindNull(int index) {
  Bound(sqlite3_bind_null(stmt_, index), index);
  return *this;
}

absl::StatusOr<bool> SqliteStatement::Step() {
  if (bind_rc_ != SQLITE_OK) {
    const int rc = bind_rc_;
    bind_rc_ = SQLITE_OK;
    // Not the connection's message: a failed bind does not set it.
    return SqliteError(nullptr, rc, absl::StrCat("bind of parameter ", bind_index_, " of '", sqlite3_sql(stmt_), "'"));
  }
  const int rc = sqlite3_step(stmt_);
  if (rc == SQLITE_ROW) return true;
  if (rc == SQLITE_DONE) return false;
  return SqliteError(db_, rc, absl::StrCat("step '", sqlite3_sql(stmt_), "'"));
}

absl::Status SqliteStatement::Run() {
  auto row = Step();
  if (!row.ok()) return row.status();
  return absl::OkStatus();
}

int64_t SqliteStatement::Int(int column) const { return sqlite3_column_int64(stmt_, column); }
double SqliteStatement::Double(int column) const { return sqlite3_column_double(stmt_, column); }
bool SqliteStatement::IsNull(int column) const { return sqlite3_column_type(stmt_, column) == SQLITE_NULL; }

std::string SqliteStatement::Text(int column) const {
  const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(stmt_, column));
  return p ? std::string(p, sqlite3_column_bytes(stmt_, column)) : std::string();
}

std::string SqliteStatement::Blob(int column) const {
  const auto* p = static_cast<const char*>(sqlite3_column_blob(stmt_, column));
  return p ? std::string(p, sqlite3_column_bytes(stmt_, column)) : std::string();
}

absl::StatusOr<std::unique_ptr<SqliteConnection>> SqliteConnection::Open(const std::string& path,
                                                                          int busy_timeout_ms, bool read_only) {
  sqlite3* raw = nullptr;
  // Readers open read-write (a WAL reader must be able to update the shared-memory index) and
  // then switch to query_only.
  const int flags = SQLITE_OPEN_READWRITE | (read_only ? 0 : SQLITE_OPEN_CREATE) | SQLITE_OPEN_NOMUTEX;
  const int rc = sqlite3_open_v2(path.c_str(), &raw, flags, nullptr);
  if (rc != SQLITE_OK) {
    absl::Status status = SqliteError(raw, rc, absl::StrCat("open ", path));
    sqlite3_close(raw);
    return status;
  }
  std::unique_ptr<SqliteConnection> db(new SqliteConnection(raw));
  sqlite3_extended_result_codes(raw, 1);
  sqlite3_busy_timeout(raw, busy_timeout_ms);
  // WAL lets readers proceed while the worker writes; FULL makes every commit durable before it
  // is acknowledged. The journal mode is persistent, so read-only connections only check it.
  if (!read_only) {
    auto mode = db->Prepare("PRAGMA journal_mode=WAL");
    if (!mode.ok()) return mode.status();
    auto row = mode->Step();
    if (!row.ok()) return row.status();
    if (!*row || mode->Text(0) != "wal") return absl::InternalError(absl::StrCat("sqlite: cannot enable WAL on ", path));
  }
  if (auto s = db->Exec("PRAGMA synchronous=FULL; PRAGMA foreign_keys=ON;"); !s.ok()) return s;
  if (read_only) {
    if (auto s = db->Exec("PRAGMA query_only=1;"); !s.ok()) return s;
  }
  return db;
}

void SqliteConnection::OnProgress(int vm_steps, std::function<void()> callback) {
  on_progress_ = std::move(callback);
  if (vm_steps <= 0 || !on_progress_) {
    sqlite3_progress_handler(db_, 0, nullptr, nullptr);
    return;
  }
  sqlite3_progress_handler(
      db_, vm_steps,
      [](void* self) {
        static_cast<SqliteConnection*>(self)->on_progress_();
        return 0;  // continue the statement
      },
      this);
}

void SqliteConnection::OnWalCommit(std::function<void(int pages)> callback) {
  on_wal_commit_ = std::move(callback);
  if (!on_wal_commit_) {
    sqlite3_wal_autocheckpoint(db_, SqliteFile::kCheckpointPages);
    return;
  }
  sqlite3_wal_hook(
      db_,
      [](void* self, sqlite3*, const char*, int pages) {
        static_cast<SqliteConnection*>(self)->on_wal_commit_(pages);
        return SQLITE_OK;
      },
      this);
}

absl::Status SqliteConnection::CheckpointPassive() {
  const int rc = sqlite3_wal_checkpoint_v2(db_, nullptr, SQLITE_CHECKPOINT_PASSIVE, nullptr, nullptr);
  if (rc == SQLITE_OK) return absl::OkStatus();
  return SqliteError(db_, rc, "checkpoint");
}

SqliteConnection::~SqliteConnection() {
  for (auto& [sql, stmt] : cache_) sqlite3_finalize(stmt);
  sqlite3_close(db_);
}

absl::Status SqliteConnection::Exec(const std::string& sql) {
  char* error = nullptr;
  const int rc = sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error);
  if (rc == SQLITE_OK) return absl::OkStatus();
  // SqliteError adds the error message itself; name the statement instead (its start).
  absl::Status status = SqliteError(db_, rc, absl::StrCat("exec '", absl::string_view(sql).substr(0, 60), "'"));
  sqlite3_free(error);
  return status;
}

absl::StatusOr<SqliteStatement> SqliteConnection::Prepare(const std::string& sql) {
  auto it = cache_.find(sql);
  if (it == cache_.end()) {
    sqlite3_stmt* stmt = nullptr;
    const int rc = sqlite3_prepare_v3(db_, sql.c_str(), static_cast<int>(sql.size()), SQLITE_PREPARE_PERSISTENT,
                                      &stmt, nullptr);
    if (rc != SQLITE_OK) return SqliteError(db_, rc, absl::StrCat("prepare '", sql, "'"));
    it = cache_.emplace(sql, stmt).first;
  }
  return SqliteStatement(db_, it->second);
}

absl::StatusOr<int64_t> SqliteConnection::PragmaInt(const std::string& pragma) {
  auto stmt = Prepare(absl::StrCat("PRAGMA ", pragma));
  if (!stmt.ok()) return stmt.status();
  auto row = stmt->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::InternalError(absl::StrCat("PRAGMA ", pragma, " returned no row"));
  return stmt->Int(0);
}

int64_t SqliteConnection::LastInsertRowId() const { return sqlite3_last_insert_rowid(db_); }
int SqliteConnection::Changes() const { return sqlite3_changes(db_); }

absl::StatusOr<SqliteWriteTransaction> SqliteWriteTransaction::Begin(SqliteConnection* db) {
  if (auto s = db->Exec("BEGIN IMMEDIATE"); !s.ok()) return s;
  return SqliteWriteTransaction(db);
}

SqliteWriteTransaction::~SqliteWriteTransaction() {
  if (db_ != nullptr) db_->Exec("ROLLBACK").IgnoreError();
}

absl::Status SqliteWriteTransaction::Commit() {
  absl::Status status = db_->Exec("COMMIT");
  if (status.ok()) db_ = nullptr;
  return status;
}

absl::StatusOr<SqliteReadTransaction> SqliteReadTransaction::Begin(SqliteConnection* db) {
  if (auto s = db->Exec("BEGIN"); !s.ok()) return s;
  return SqliteReadTransaction(db);
}

SqliteReadTransaction::~SqliteReadTransaction() {
  if (db_ != nullptr) db_->Exec("COMMIT").IgnoreError();
}


absl::StatusOr<std::unique_ptr<SqliteFile>> SqliteFile::Open(const std::string& path, int busy_timeout_ms,
                                                             int max_idle_readers) {
  auto writer = SqliteConnection::Open(path, busy_timeout_ms, /*read_only=*/false);
  if (!writer.ok()) return writer.status();
  auto checkpointer = SqliteConnection::Open(path, busy_timeout_ms, /*read_only=*/false);
  if (!checkpointer.ok()) return checkpointer.status();
  return std::unique_ptr<SqliteFile>(
      new SqliteFile(path, busy_timeout_ms, max_idle_readers, std::move(*writer), std::move(*checkpointer)));
}

SqliteFile::SqliteFile(std::string path, int busy_timeout_ms, int max_idle_readers,
                       std::unique_ptr<SqliteConnection> writer, std::unique_ptr<SqliteConnection> checkpointer)
    : path_(std::move(path)),
      busy_timeout_ms_(busy_timeout_ms),
      max_idle_readers_(max_idle_readers),
      writer_(std::move(writer)),
      checkpointer_(std::move(checkpointer)) {
  // A checkpoint copies the log's pages into the database and syncs it: inside a commit (SQLite's
  // default) it took a tenth of a map commit's time at 100k landmarks, and commits are serial.
  checkpoint_thread_ = std::thread([this] { CheckpointLoop(); });
  writer_->OnWalCommit([this](int pages) {
    if (pages < kCheckpointPages) return;
    std::lock_guard<std::mutex> lock(checkpoint_mu_);
    checkpoint_due_ = true;
    checkpoint_cv_.notify_one();
  });
}

SqliteFile::~SqliteFile() {
  {
    std::lock_guard<std::mutex> lock(checkpoint_mu_);
    closing_ = true;
    checkpoint_cv_.notify_one();
  }
  checkpoint_thread_.join();
}

void SqliteFile::CheckpointLoop() {
  std::unique_lock<std::mutex> lock(checkpoint_mu_);
  while (true) {
    checkpoint_cv_.wait(lock, [this] { return checkpoint_due_ || closing_; });
    if (closing_) return;
    checkpoint_due_ = false;
    lock.unlock();
    // A failed checkpoint loses nothing (the log keeps the pages) and the next commit asks again.
    if (absl::Status s = checkpointer_->CheckpointPassive(); !s.ok()) {
      spdlog::warn("storage: checkpoint of {} failed: {}", path_, std::string(s.message()));
    }
    lock.lock();
  }
}

SqliteFile::ReaderLease::~ReaderLease() {
  if (db_ != nullptr) file_->ReleaseReader(std::move(db_));
}

absl::StatusOr<SqliteFile::ReaderLease> SqliteFile::AcquireReader() {
  {
    std::lock_guard<std::mutex> lock(readers_mu_);
    if (!idle_readers_.empty()) {
      std::unique_ptr<SqliteConnection> db = std::move(idle_readers_.back());
      idle_readers_.pop_back();
      return ReaderLease(this, std::move(db));
    }
  }
  auto db = SqliteConnection::Open(path_, busy_timeout_ms_, /*read_only=*/true);
  if (!db.ok()) return db.status();
  return ReaderLease(this, std::move(*db));
}

void SqliteFile::ReleaseReader(std::unique_ptr<SqliteConnection> db) {
  std::lock_guard<std::mutex> lock(readers_mu_);
  if (static_cast<int>(idle_readers_.size()) < max_idle_readers_) idle_readers_.push_back(std::move(db));
}

}  // namespace crowdmap
