#ifndef CROWDMAP_SERVER_STORAGE_SQLITE_DB_H_
#define CROWDMAP_SERVER_STORAGE_SQLITE_DB_H_

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <thread>
#include <unordered_map>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

struct sqlite3;
struct sqlite3_stmt;

namespace crowdmap {

// A prepared statement borrowed from a connection's cache; reset and unbound when it goes out of
// scope so the next user starts clean. Bind indices are 1-based, column indices 0-based.
class SqliteStatement {
 public:
  SqliteStatement(sqlite3* db, sqlite3_stmt* stmt) : db_(db), stmt_(stmt) {}
  SqliteStatement(SqliteStatement&& other) noexcept
      : db_(other.db_), stmt_(other.stmt_), bind_rc_(other.bind_rc_), bind_index_(other.bind_index_) {
    other.stmt_ = nullptr;
  }
  SqliteStatement(const SqliteStatement&) = delete;
  SqliteStatement& operator=(const SqliteStatement&) = delete;
  ~SqliteStatement();

  SqliteStatement& Bind(int index, int64_t value);
  SqliteStatement& Bind(int index, double value);
  SqliteStatement& Bind(int index, std::string_view text);
  SqliteStatement& BindBlob(int index, std::string_view bytes);
  SqliteStatement& BindNull(int index);

  // Advances; true when a row is available, false when done. A value that could not be bound
  // fails the step instead (e.g. InvalidArgument for one over SQLite's length limit).
  absl::StatusOr<bool> Step();
  // Runs a statement that returns no rows.
  absl::Status Run();

  int64_t Int(int column) const;
  double Double(int column) const;
  std::string Text(int column) const;
  std::string Blob(int column) const;
  bool IsNull(int column) const;

 private:
  void Bound(int rc, int index);  // keeps the first failed bind for Step

  sqlite3* db_;
  sqlite3_stmt* stmt_;
  int bind_rc_ = 0;  // SQLITE_OK, or the first bind's error since the last step
  int bind_index_ = 0;
};

// One SQLite connection with a cache of prepared statements. Not thread-safe: one user at a time.
class SqliteConnection {
 public:
  // Opens `path` (a writer creates it when missing and enables WAL), with busy_timeout and
  // synchronous=FULL. A read-only connection requires an existing database.
  static absl::StatusOr<std::unique_ptr<SqliteConnection>> Open(const std::string& path, int busy_timeout_ms,
                                                                bool read_only);
  ~SqliteConnection();
  SqliteConnection(const SqliteConnection&) = delete;
  SqliteConnection& operator=(const SqliteConnection&) = delete;

  // Runs one or more statements without results.
  absl::Status Exec(const std::string& sql);
  // A cached prepared statement for `sql`.
  absl::StatusOr<SqliteStatement> Prepare(const std::string& sql);
  // Value of a pragma that returns one integer row (e.g. "user_version").
  absl::StatusOr<int64_t> PragmaInt(const std::string& pragma);

  int64_t LastInsertRowId() const;
  int Changes() const;

  // Calls `callback` about every `vm_steps` virtual machine instructions of a statement
  // (sqlite3_progress_handler), e.g. to yield the CPU during a long write. vm_steps 0 or an empty
  // callback removes it.
  void OnProgress(int vm_steps, std::function<void()> callback);

  // Calls `callback` with the number of pages in the write-ahead log after each of this
  // connection's commits (sqlite3_wal_hook). It replaces SQLite's automatic checkpoint, which ran
  // inside the committing call: the callback's owner checkpoints instead.
  void OnWalCommit(std::function<void(int pages)> callback);
  // Copies into the database what the write-ahead log holds and no reader still needs
  // (SQLITE_CHECKPOINT_PASSIVE: it waits for no reader and no writer).
  absl::Status CheckpointPassive();

 private:
  explicit SqliteConnection(sqlite3* db) : db_(db) {}
  sqlite3* db_;
  std::unordered_map<std::string, sqlite3_stmt*> cache_;
  std::function<void()> on_progress_;
  std::function<void(int)> on_wal_commit_;
};

// BEGIN IMMEDIATE ... COMMIT; rolls back when destroyed uncommitted.
class SqliteWriteTransaction {
 public:
  static absl::StatusOr<SqliteWriteTransaction> Begin(SqliteConnection* db);
  SqliteWriteTransaction(SqliteWriteTransaction&& other) noexcept : db_(other.db_) { other.db_ = nullptr; }
  SqliteWriteTransaction(const SqliteWriteTransaction&) = delete;
  ~SqliteWriteTransaction();
  absl::Status Commit();

 private:
  explicit SqliteWriteTransaction(SqliteConnection* db) : db_(db) {}
  SqliteConnection* db_;
};

// BEGIN (deferred) ... COMMIT for a consistent multi-statement read snapshot.
class SqliteReadTransaction {
 public:
  static absl::StatusOr<SqliteReadTransaction> Begin(SqliteConnection* db);
  SqliteReadTransaction(SqliteReadTransaction&& other) noexcept : db_(other.db_) { other.db_ = nullptr; }
  SqliteReadTransaction(const SqliteReadTransaction&) = delete;
  ~SqliteReadTransaction();

 private:
  explicit SqliteReadTransaction(SqliteConnection* db) : db_(db) {}
  SqliteConnection* db_;
};


// One database file: a writer connection behind a mutex (every write is one BEGIN IMMEDIATE
// transaction) and a pool of reader connections (WAL lets them read a consistent snapshot while
// the writer commits). The write-ahead log is checkpointed on a thread of the file's own, so that
// no commit waits for one.
class SqliteFile {
 public:
  // Opens (creating when missing) `path` for writing; readers are opened on demand.
  static absl::StatusOr<std::unique_ptr<SqliteFile>> Open(const std::string& path, int busy_timeout_ms,
                                                          int max_idle_readers);
  ~SqliteFile();
  SqliteFile(const SqliteFile&) = delete;
  SqliteFile& operator=(const SqliteFile&) = delete;

  // Checkpoints run once a commit leaves the log at this many pages or more (SQLite's own
  // automatic checkpoint used the same threshold).
  static constexpr int kCheckpointPages = 1000;

  // A pooled reader connection, returned to the pool when the lease ends.
  class ReaderLease {
   public:
    ReaderLease(SqliteFile* file, std::unique_ptr<SqliteConnection> db) : file_(file), db_(std::move(db)) {}
    ReaderLease(ReaderLease&&) = default;
    ~ReaderLease();
    SqliteConnection* operator->() { return db_.get(); }
    SqliteConnection* get() { return db_.get(); }

   private:
    SqliteFile* file_;
    std::unique_ptr<SqliteConnection> db_;
  };
  absl::StatusOr<ReaderLease> AcquireReader();

  // The writer connection, for as long as the lock is held.
  struct Writer {
    std::unique_lock<std::mutex> lock;
    SqliteConnection* db;
  };
  Writer LockWriter() { return Writer{std::unique_lock<std::mutex>(writer_mu_), writer_.get()}; }

  const std::string& path() const { return path_; }

 private:
  SqliteFile(std::string path, int busy_timeout_ms, int max_idle_readers, std::unique_ptr<SqliteConnection> writer,
             std::unique_ptr<SqliteConnection> checkpointer);
  void ReleaseReader(std::unique_ptr<SqliteConnection> db);
  // The checkpoint thread: one passive checkpoint each time a commit asks for one.
  void CheckpointLoop();

  const std::string path_;
  const int busy_timeout_ms_;
  const int max_idle_readers_;
  std::mutex writer_mu_;
  std::unique_ptr<SqliteConnection> writer_;
  std::mutex readers_mu_;
  std::vector<std::unique_ptr<SqliteConnection>> idle_readers_;
  // The checkpoint thread's connection, and what it is told.
  std::unique_ptr<SqliteConnection> checkpointer_;
  std::mutex checkpoint_mu_;
  std::condition_variable checkpoint_cv_;
  bool checkpoint_due_ = false;  // guarded by checkpoint_mu_
  bool closing_ = false;         // guarded by checkpoint_mu_
  std::thread checkpoint_thread_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_SQLITE_DB_H_
