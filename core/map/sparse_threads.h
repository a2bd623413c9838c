#ifndef CROWDMAP_CORE_MAP_SPARSE_THREADS_H_
#define CROWDMAP_CORE_MAP_SPARSE_THREADS_H_

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
// factorises calls it; after the first call on a thread it costs a thread-local read.
void FactorizeOnThisThreadOnly();

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_SPARSE_THREADS_H_
