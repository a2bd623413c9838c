#include "server/storage/writer_preferring_mutex.h"

#include <atomic>
#include <chrono>
#include <mutex>
#include <shared_mutex>
#include <thread>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// Readers share it and exclude a writer; a reader that comes while a writer waits for the reads
// under way waits behind the writer (std::shared_mutex on glibc lets it in, and a stream of such
// readers keeps the writer out).
TEST(WriterPreferringMutex, AWaitingWriterGoesBeforeLaterReaders) {
  WriterPreferringMutex mu;
  std::shared_lock<WriterPreferringMutex> first(mu);
  {
    std::shared_lock<WriterPreferringMutex> second(mu, std::try_to_lock);
    EXPECT_TRUE(second.owns_lock()) << "readers share it";
  }
  EXPECT_FALSE(mu.try_lock()) << "a reader excludes a writer";

  std::atomic<bool> written{false};
  std::thread writer([&] {
    std::unique_lock<WriterPreferringMutex> lock(mu);
    written = true;
  });
  // Once the writer waits, a new reader no longer gets in.
  bool later_reader_refused = false;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!later_reader_refused && std::chrono::steady_clock::now() < deadline) {
    if (mu.try_lock_shared()) {
      mu.unlock_shared();
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    } else {
      later_reader_refused = true;
    }
  }
  EXPECT_TRUE(later_reader_refused);
  EXPECT_FALSE(written) << "the writer waits for the read under way";
  first.unlock();
  writer.join();
  EXPECT_TRUE(written);
  std::shared_lock<WriterPreferringMutex> after(mu, std::try_to_lock);
  EXPECT_TRUE(after.owns_lock());
}

}  // namespace
}  // namespace crowdmap
