#include "core/map/sparse_threads.h"

#include <dlfcn.h>
#include <malloc.h>
#include <omp.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "core/map/dense_kernels.h"

extern "C" void dpotrf_(const char* uplo, const int* n, double* a, const int* lda, int* info);

namespace crowdmap {
namespace {

// Run as a child with CROWDMAP_BLAS_PROBE set (by the test below): makes one BLAS call, prints
// the check's verdict on the BLAS the dynamic linker loaded, and exits before any test runs.
const bool kBlasProbe = [] {
  if (std::getenv("CROWDMAP_BLAS_PROBE") == nullptr) return false;
  Eigen::MatrixXd a = Eigen::MatrixXd::Identity(3, 3);
  CholeskyInPlace(a);
  const absl::Status status = CheckBlasIsSafeForConcurrentCalls();
  std::printf("%s\n", status.ok() ? "safe" : std::string(status.message()).c_str());
  std::fflush(stdout);
  std::_Exit(0);
}();

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

// A 16 MiB buffer, as a window's factorisation allocates, comes from the heap instead of a mapping
// of its own, and stays there once freed (glibc's defaults would map it, then unmap it on free).
TEST(KeepLargeBuffersInTheHeap, ServesAndKeepsMegabyteBuffersInTheHeap) {
  for (const char* name : {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES"}) {
    if (std::getenv(name) != nullptr) GTEST_SKIP() << name << " is set: the allocator is the environment's choice";
  }
  ASSERT_TRUE(KeepLargeBuffersInTheHeap());
  constexpr size_t kBytes = size_t{16} << 20;
  const size_t mappings_before = mallinfo2().hblks;
  {
    std::vector<char> buffer(kBytes, 1);
    EXPECT_EQ(mallinfo2().hblks, mappings_before);
  }
  EXPECT_GE(mallinfo2().fordblks, kBytes);  // freed, and still in the heap
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

// This binary's output when run with `folder` first in the library path (empty: as installed).
std::string ProbeBlasIn(const std::string& folder) {
  const std::string self = std::filesystem::read_symlink("/proc/self/exe").string();
  const std::string command =
      "CROWDMAP_BLAS_PROBE=1 " + (folder.empty() ? std::string() : "LD_LIBRARY_PATH=" + folder + " ") + self;
  FILE* out = popen(command.c_str(), "r");
  std::string text;
  char buffer[512];
  while (out != nullptr && std::fgets(buffer, sizeof(buffer), out) != nullptr) text += buffer;
  if (out != nullptr) pclose(out);
  return text;
}

// Each BLAS build installed beside the selected libblas.so.3 (Debian's alternatives), loaded in
// turn into a child process: only the single-threaded OpenBLAS is refused, by its file name.
TEST(CheckBlasIsSafeForConcurrentCalls, RefusesOnlyTheSingleThreadedOpenBlas) {
  EXPECT_FALSE(kBlasProbe);
  EXPECT_EQ(ProbeBlasIn(""), "safe\n") << "the BLAS selected on this machine (scripts/setup.sh selects a safe one)";
  Dl_info info{};
  ASSERT_NE(dladdr(reinterpret_cast<void*>(&dpotrf_), &info), 0);
  const std::filesystem::path libs = std::filesystem::path(info.dli_fname).parent_path();
  int builds = 0;
  for (const char* safe : {"openblas-pthread", "openblas-openmp", "atlas", "blis-pthread", "blis-serial"}) {
    if (!std::filesystem::exists(libs / safe / "libblas.so.3")) continue;
    ++builds;
    EXPECT_EQ(ProbeBlasIn((libs / safe).string()), "safe\n") << safe;
  }
  const std::filesystem::path serial = libs / "openblas-serial";
  if (std::filesystem::exists(serial / "libblas.so.3")) {
    ++builds;
    const std::string verdict = ProbeBlasIn(serial.string());
    EXPECT_NE(verdict.find("single-threaded OpenBLAS"), std::string::npos) << verdict;
    EXPECT_NE(verdict.find(serial.string() + "/"), std::string::npos) << verdict;
  }
  if (builds == 0) GTEST_SKIP() << "no other BLAS build installed beside " << libs;
}

}  // namespace
}  // namespace crowdmap
