#include "server/http_thread_stacks.h"

#include <pthread.h>

#include <gtest/gtest.h>

namespace crowdmap {
namespace {

// civetweb's compiled-in request gets the headroom for thread-local storage on top.
TEST(HttpThreadStacks, AnExplicitStackSizeGetsTheHeadroom) {
  EXPECT_EQ(HttpThreadStackBytes(), 102400 + kThreadLocalStorageHeadroom);
}

// A thread started with the smallest stack a program may ask for runs with the headroom added.
TEST(HttpThreadStacks, AThreadOnASmallStackStartsWithTheHeadroom) {
  pthread_attr_t attr;
  ASSERT_EQ(pthread_attr_init(&attr), 0);
  ASSERT_EQ(pthread_attr_setstacksize(&attr, PTHREAD_STACK_MIN), 0);
  size_t granted = 0;
  pthread_t thread;
  ASSERT_EQ(pthread_create(
                &thread, &attr,
                [](void* out) -> void* {
                  pthread_attr_t own;
                  if (pthread_getattr_np(pthread_self(), &own) == 0) {
                    pthread_attr_getstacksize(&own, static_cast<size_t*>(out));
                    pthread_attr_destroy(&own);
                  }
                  return nullptr;
                },
                &granted),
            0);
  pthread_join(thread, nullptr);
  pthread_attr_destroy(&attr);
  EXPECT_GE(granted, static_cast<size_t>(PTHREAD_STACK_MIN) + kThreadLocalStorageHeadroom);
}

}  // namespace
}  // namespace crowdmap
