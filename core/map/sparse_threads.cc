#include "core/map/sparse_threads.h"

#include <dlfcn.h>
#include <omp.h>

#include <cstdlib>
#include <cstring>
#include <string>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace crowdmap {
namespace {

// OpenBLAS's C entry points, looked up in the process: absent when the BLAS is another one.
template <typename Fn>
Fn OpenBlasFunction(const char* name) {
  return reinterpret_cast<Fn>(dlsym(RTLD_DEFAULT, name));
}

}  // namespace

bool KeepLargeBuffersInTheHeap() {
  static const bool kept = [] {
#if defined(__GLIBC__)
    for (const char* name : {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_"}) {
      if (std::getenv(name) != nullptr) return false;
    }
    const char* tunables = std::getenv("GLIBC_TUNABLES");
    if (tunables != nullptr && std::strstr(tunables, "glibc.malloc.") != nullptr) return false;
    constexpr int kMiB = 1 << 20;
    return mallopt(M_MMAP_THRESHOLD, 32 * kMiB) == 1 && mallopt(M_TRIM_THRESHOLD, 256 * kMiB) == 1 &&
           mallopt(M_TOP_PAD, 64 * kMiB) == 1;
#else
    return false;
#endif
  }();
  return kept;
}

void KeepBlasOnTheCallingThread() {
  static const bool confined = [] {
    if (auto set_threads = OpenBlasFunction<void (*)(int)>("openblas_set_num_threads")) set_threads(1);
    KeepLargeBuffersInTheHeap();
    return true;
  }();
  (void)confined;
}

void FactorizeOnThisThreadOnly() {
  KeepBlasOnTheCallingThread();
  // No nested level may be active: every parallel region started here gets a team of one (OpenMP
  // 5.0; libgomp reads 0 so).
  thread_local const bool confined = [] {
    omp_set_max_active_levels(0);
    return true;
  }();
  (void)confined;
}

absl::Status CheckBlasIsSafeForConcurrentCalls() {
  // 0: the sequential build, 1: pthreads, 2: OpenMP (OpenBLAS's cblas.h).
  auto get_parallel = OpenBlasFunction<int (*)()>("openblas_get_parallel");
  if (get_parallel == nullptr || get_parallel() != 0) return absl::OkStatus();
  Dl_info info{};
  const char* file = dladdr(reinterpret_cast<void*>(get_parallel), &info) != 0 && info.dli_fname != nullptr
                         ? info.dli_fname
                         : "libblas.so.3";
  return absl::FailedPreconditionError(
      std::string("BLAS: ") + file +
      " is a single-threaded OpenBLAS, which gives wrong results when the map's threads call it at once; "
      "select a thread-safe libblas.so.3 and liblapack.so.3 (scripts/setup.sh selects OpenBLAS's pthread build: "
      "update-alternatives --set libblas.so.3-<multiarch> .../openblas-pthread/libblas.so.3, the same for "
      "liblapack.so.3)");
}

}  // namespace crowdmap
