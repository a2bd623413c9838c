#include "core/map/sparse_threads.h"

#include <omp.h>

namespace crowdmap {

void FactorizeOnThisThreadOnly() {
  // No nested level may be active: every parallel region started here gets a team of one (OpenMP
  // 5.0; libgomp reads 0 so).
  thread_local const bool confined = [] {
    omp_set_max_active_levels(0);
    return true;
  }();
  (void)confined;
}

}  // namespace crowdmap
