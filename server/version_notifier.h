#ifndef CROWDMAP_SERVER_VERSION_NOTIFIER_H_
#define CROWDMAP_SERVER_VERSION_NOTIFIER_H_

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>

namespace crowdmap {

// Publishes the committed map version to waiting readers (WatchRegion streams).
class VersionNotifier {
 public:
  void Publish(int64_t version) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (version > version_) version_ = version;
    }
    changed_.notify_all();
  }

  // Wakes every waiter, e.g. at shutdown; later waits return at once.
  void Close() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      closed_ = true;
    }
    changed_.notify_all();
  }

  // The current version once it exceeds `version`, or when closed, or after `timeout`.
  int64_t WaitAbove(int64_t version, std::chrono::milliseconds timeout) {
    std::unique_lock<std::mutex> lock(mu_);
    changed_.wait_for(lock, timeout, [&] { return closed_ || version_ > version; });
    return version_;
  }

  bool closed() const {
    std::lock_guard<std::mutex> lock(mu_);
    return closed_;
  }

  int64_t version() const {
    std::lock_guard<std::mutex> lock(mu_);
    return version_;
  }

 private:
  mutable std::mutex mu_;
  std::condition_variable changed_;
  int64_t version_ = 0;
  bool closed_ = false;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_VERSION_NOTIFIER_H_
