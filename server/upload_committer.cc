#include "server/upload_committer.h"

#include <vector>

namespace crowdmap {

absl::StatusOr<EnqueueOutcome> UploadCommitter::Commit(NewPassage passage) {
  Pending me{std::move(passage), std::nullopt};
  std::unique_lock<std::mutex> lock(mu_);
  waiting_.push_back(&me);
  while (!me.outcome.has_value()) {
    if (committing_) {
      done_.wait(lock);
      continue;
    }
    // Lead one batch: everything waiting (up to max_batch_), committed together.
    committing_ = true;
    std::vector<Pending*> batch;
    while (!waiting_.empty() && static_cast<int>(batch.size()) < max_batch_) {
      batch.push_back(waiting_.front());
      waiting_.pop_front();
    }
    lock.unlock();
    std::vector<NewPassage> passages;
    passages.reserve(batch.size());
    for (Pending* p : batch) passages.push_back(std::move(p->passage));
    auto outcomes = store_->EnqueuePassages(passages, max_queue_);
    lock.lock();
    for (size_t i = 0; i < batch.size(); ++i) {
      if (outcomes.ok()) {
        batch[i]->outcome = std::move((*outcomes)[i]);
      } else {
        batch[i]->outcome = absl::StatusOr<EnqueueOutcome>(outcomes.status());
      }
    }
    committing_ = false;
    done_.notify_all();
  }
  return std::move(*me.outcome);
}

}  // namespace crowdmap
