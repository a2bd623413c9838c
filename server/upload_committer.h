#ifndef CROWDMAP_SERVER_UPLOAD_COMMITTER_H_
#define CROWDMAP_SERVER_UPLOAD_COMMITTER_H_

#include <condition_variable>
#include <deque>
#include <mutex>
#include <optional>

#include "absl/status/statusor.h"
#include "server/storage/map_store.h"

namespace crowdmap {

// Group commit for uploads: concurrent callers are gathered into one durable transaction (one
// fsync) instead of one each. A caller returns only after the transaction holding its upload has
// committed, so an acknowledgement always follows a durable write.
class UploadCommitter {
 public:
  UploadCommitter(MapStoreInterface* store, int64_t max_queue, int max_batch = 128)
      : store_(store), max_queue_(max_queue), max_batch_(max_batch) {}

  // The stored record (or the original one for a duplicate key), or ResourceExhausted when the
  // queue is full, or the store's error.
  absl::StatusOr<EnqueueOutcome> Commit(NewPassage passage);

 private:
  struct Pending {
    NewPassage passage;
    std::optional<absl::StatusOr<EnqueueOutcome>> outcome;
  };

  MapStoreInterface* const store_;
  const int64_t max_queue_;
  const int max_batch_;
  std::mutex mu_;
  std::condition_variable done_;
  std::deque<Pending*> waiting_;
  bool committing_ = false;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_UPLOAD_COMMITTER_H_
