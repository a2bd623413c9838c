#ifndef CROWDMAP_CORE_MAP_SPARSE_THREADS_H_
#define CROWDMAP_CORE_MAP_SPARSE_THREADS_H_

#include "absl/status/status.h"

namespace crowdmap {

// CHOLMOD, as Debian builds it, runs each supernodal factorisation's updates on an OpenMP team of
// a size fixed when it was compiled (OMP_NUM_THREADS does not change it). On this project's
// factorisations (a window of a few thousand unknowns, a subgraph's normal equations) waking that
// team and waiting for it costs more than it saves, and on a 2-core server it takes the core the
// other worker or the readers need: a 500 m box's covariance read took 42 ms of wall time with the
// team and 28 ms without (map_covariance_benchmark, 1 link; docs/results.md, "One thread per
// factorisation").
//
// Makes the OpenMP parallel regions started on the calling thread (CHOLMOD's, called by MapWindow
// or by Ceres) run on that thread alone. OpenMP keeps this per thread, so each thread that
// factorises calls it; after the first call on a thread it costs a thread-local read. It calls
// KeepBlasOnTheCallingThread too.
void FactorizeOnThisThreadOnly();

// The same for the BLAS: OpenBLAS's pthread and OpenMP builds (the pthread one is what
// scripts/setup.sh selects) split a call over a pool of their own threads, which then spin beside
// the map's threads. 4 threads making 1000 small Cholesky factorisations and products each
// (DenseKernels.ThreadsCallingAtOnceGetTheirOwnResults) took 23 s with the pool and 0.17 s with
// one thread. The first call in the process sets the pool to one thread, so that every BLAS call
// runs on the thread that makes it; later calls cost a read. MapWindow's and Ceres's
// factorisations (through FactorizeOnThisThreadOnly) and each dense kernel call it. Its first call
// also calls KeepLargeBuffersInTheHeap.
void KeepBlasOnTheCallingThread();

// Each passage's factorisations allocate and free buffers of megabytes (a window's information and
// its factor, CHOLMOD's workspace, dense covariances). glibc's malloc serves a block over its
// mmap threshold (128 KiB, raised as such blocks are freed, up to 32 MiB) with a fresh mapping and
// returns the top of its heap to the system beyond 128 KiB free, so these buffers were mapped and
// faulted in again on every passage: on a virtual machine whose page faults are costly, a 1k city
// passage took 271-386 ms, of which about a third in page faults, and 123-141 ms with the buffers
// kept (map_updater_benchmark; docs/results.md, "Large buffers kept in the heap"). Whether glibc
// maps them depends on what the process freed before (its threshold rises); these settings do not.
//
// With glibc, sets the mmap threshold to 32 MiB, the trim threshold to 256 MiB and the heap's top
// pad to 64 MiB, once per process: the freed buffers stay in the heap for the next passage, at
// the cost of at most 256 MiB of free memory held per malloc arena. Does nothing when the
// environment sets any of these (MALLOC_MMAP_THRESHOLD_, MALLOC_TRIM_THRESHOLD_, MALLOC_TOP_PAD_,
// or glibc.malloc tunables in GLIBC_TUNABLES), so an operator can choose otherwise. Returns whether
// it set them.
bool KeepLargeBuffersInTheHeap();

// The map's threads (the workers beside the readers) call the BLAS at the same time. Debian's
// single-threaded OpenBLAS (libopenblas0-serial) has no locking: concurrent callers share its
// work buffers and get wrong numbers, which pass unnoticed where they stay positive definite
// (docs/results.md, "OpenBLAS called from several threads"). Returns FailedPrecondition naming
// the library when the BLAS loaded in this process is such a build, OK otherwise (OpenBLAS's
// pthread and OpenMP builds, ATLAS, BLIS, the reference BLAS).
absl::Status CheckBlasIsSafeForConcurrentCalls();

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_SPARSE_THREADS_H_
