#include "server/http_thread_stacks.h"

#include <dlfcn.h>
#include <pthread.h>

#include <cerrno>

// Interposes glibc's function for every library of the process (see the header): the executable's
// definition comes first in the dynamic linker's search.
extern "C" int pthread_attr_setstacksize(pthread_attr_t* attr, size_t stack_size) {
  using SetStackSize = int (*)(pthread_attr_t*, size_t);
  static const auto glibc = reinterpret_cast<SetStackSize>(dlsym(RTLD_NEXT, "pthread_attr_setstacksize"));
  if (glibc == nullptr) return ENOSYS;
  return glibc(attr, stack_size + crowdmap::kThreadLocalStorageHeadroom);
}

namespace crowdmap {

std::size_t HttpThreadStackBytes() {
  constexpr std::size_t kCivetwebStack = 102400;
  pthread_attr_t attr;
  if (pthread_attr_init(&attr) != 0) return 0;
  std::size_t size = 0;
  if (pthread_attr_setstacksize(&attr, kCivetwebStack) != 0 || pthread_attr_getstacksize(&attr, &size) != 0) size = 0;
  pthread_attr_destroy(&attr);
  return size;
}

}  // namespace crowdmap
