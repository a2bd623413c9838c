#ifndef CROWDMAP_SERVER_HTTP_THREAD_STACKS_H_
#define CROWDMAP_SERVER_HTTP_THREAD_STACKS_H_

#include <cstddef>

namespace crowdmap {

// glibc carves a thread's static thread-local storage (that of every library loaded at start-up)
// out of the stack size the thread is created with (glibc bug 11787). civetweb, behind the map
// viewer and prometheus-cpp's metrics endpoint, creates its threads with a stack size fixed when
// Debian compiled it (102,400 bytes), and OpenBLAS's pthread build, the BLAS that
// scripts/setup.sh selects, holds about 60 KB of thread-local storage: pthread_create then fails
// with EINVAL and neither the viewer nor the metrics start.
//
// http_thread_stacks.cc therefore defines pthread_attr_setstacksize for the process: a stack size
// that a library sets explicitly gets kThreadLocalStorageHeadroom added before glibc's own
// function sees it. Sizes only grow, and threads created with glibc's default stack (8 MiB) are
// not affected.
inline constexpr std::size_t kThreadLocalStorageHeadroom = 256 * 1024;

// The stack a thread gets when it asks for civetweb's compiled-in 102,400 bytes: logged when the
// viewer and the metrics start (and a reference that keeps the definition above in the binary).
std::size_t HttpThreadStackBytes();

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_HTTP_THREAD_STACKS_H_
