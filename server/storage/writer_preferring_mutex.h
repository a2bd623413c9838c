#ifndef CROWDMAP_SERVER_STORAGE_WRITER_PREFERRING_MUTEX_H_
#define CROWDMAP_SERVER_STORAGE_WRITER_PREFERRING_MUTEX_H_

#include <pthread.h>

namespace crowdmap {

// A shared mutex under which a waiting writer goes before readers that arrive after it (usable with
// std::shared_lock and std::unique_lock). std::shared_mutex on glibc prefers readers: a stream of
// overlapping reads, each holding the lock for a whole covariance recovery (up to hundreds of ms on
// a city map), can keep a writer out for as long as the stream lasts. Here a writer waits for the
// reads under way only. Not recursive: a thread that holds it shared must not take it shared again
// (it would wait behind a waiting writer that waits for it).
class WriterPreferringMutex {
 public:
  WriterPreferringMutex() {
    pthread_rwlockattr_t attr;
    pthread_rwlockattr_init(&attr);
    pthread_rwlockattr_setkind_np(&attr, PTHREAD_RWLOCK_PREFER_WRITER_NONRECURSIVE_NP);
    pthread_rwlock_init(&lock_, &attr);
    pthread_rwlockattr_destroy(&attr);
  }
  ~WriterPreferringMutex() { pthread_rwlock_destroy(&lock_); }
  WriterPreferringMutex(const WriterPreferringMutex&) = delete;
  WriterPreferringMutex& operator=(const WriterPreferringMutex&) = delete;

  void lock() { pthread_rwlock_wrlock(&lock_); }
  bool try_lock() { return pthread_rwlock_trywrlock(&lock_) == 0; }
  void unlock() { pthread_rwlock_unlock(&lock_); }
  void lock_shared() { pthread_rwlock_rdlock(&lock_); }
  bool try_lock_shared() { return pthread_rwlock_tryrdlock(&lock_) == 0; }
  void unlock_shared() { pthread_rwlock_unlock(&lock_); }

 private:
  pthread_rwlock_t lock_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_STORAGE_WRITER_PREFERRING_MUTEX_H_
