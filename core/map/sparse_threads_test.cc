#include "core/map/sparse_threads.h"

#include <omp.h>

#include <algorithm>
#include <thread>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// The threads of a parallel region asking for a team of 4, started on the calling thread.
int TeamOfFour() {
  int threads = 0;
#pragma omp parallel num_threads(4)
  {
#pragma omp atomic
    ++threads;
  }
  return threads;
}

// CHOLMOD's regions ask for a fixed team size, as this one does; after the call they run on the
// calling thread alone, and only there (OpenMP keeps the setting per thread).
TEST(FactorizeOnThisThreadOnly, ConfinesTheCallingThreadsParallelRegions) {
  if (omp_get_thread_limit() < 4) GTEST_SKIP() << "OMP_THREAD_LIMIT is below 4";
  int before = 0, after = 0, other_thread = 0;
  std::thread([&] {
    before = TeamOfFour();
    FactorizeOnThisThreadOnly();
    after = TeamOfFour();
    FactorizeOnThisThreadOnly();  // again: no change
    after = std::max(after, TeamOfFour());
  }).join();
  std::thread([&] { other_thread = TeamOfFour(); }).join();
  EXPECT_EQ(before, 4);
  EXPECT_EQ(after, 1);
  EXPECT_EQ(other_thread, 4);
}

}  // namespace
}  // namespace crowdmap
