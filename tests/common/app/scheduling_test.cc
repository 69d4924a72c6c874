// The scheduler slice request (common/app/scheduling.h), on threads of its own so that the test
// process's main thread keeps its defaults.
#include "common/app/scheduling.h"

#include <gtest/gtest.h>
#include <pthread.h>
#include <sched.h>

#include <chrono>
#include <stdexcept>
#include <thread>

namespace somasim::app {
namespace {

using std::chrono::microseconds;

// Runs `body` on a new thread and waits for it.
template <typename F>
void OnThread(F body) {
  std::thread t(body);
  t.join();
}

TEST(SchedulerSlice, AShortSliceIsAppliedAndInheritedOrTheReasonIsGiven) {
  OnThread([] {
    const long long before = SchedulerSliceUs();
    ASSERT_GE(before, 0) << "sched_getattr should work on any Linux since 3.14";
    const SliceResult r = SetSchedulerSlice(kWireSlice);
    if (!r.applied) {
      // A kernel before 6.12: said, not silent, and nothing changed.
      EXPECT_FALSE(r.detail.empty());
      EXPECT_EQ(SchedulerSliceUs(), before);
      GTEST_SKIP() << "not applied here: " << r.detail;
    }
    EXPECT_TRUE(r.detail.empty());
    EXPECT_EQ(SchedulerSliceUs(), 100);
    long long child_slice = -2;
    OnThread([&child_slice] { child_slice = SchedulerSliceUs(); });
    EXPECT_EQ(child_slice, 100) << "threads created afterwards inherit the request";
    // 0 returns to the kernel's default.
    EXPECT_TRUE(SetSchedulerSlice(microseconds(0)).applied);
    EXPECT_EQ(SchedulerSliceUs(), before);
  });
}

TEST(SchedulerSlice, SlicesOutsideTheKernelsRangeAreRefusedAndChangeNothing) {
  OnThread([] {
    const long long before = SchedulerSliceUs();
    for (const long long us : {-1LL, 1LL, 99LL, 100'001LL, 10'000'000LL}) {
      try {
        SetSchedulerSlice(microseconds(us));
        ADD_FAILURE() << us << " µs was accepted";
      } catch (const std::invalid_argument& e) {
        EXPECT_NE(std::string(e.what()).find("100..100000"), std::string::npos) << e.what();
      }
      EXPECT_EQ(SchedulerSliceUs(), before);
    }
  });
}

TEST(SchedulerSlice, ARealTimeThreadIsToldItsSliceDoesNotApply) {
  OnThread([] {
    sched_param param{};
    param.sched_priority = 1;
    if (pthread_setschedparam(pthread_self(), SCHED_FIFO, &param) != 0) {
      GTEST_SKIP() << "SCHED_FIFO refused here (no CAP_SYS_NICE)";
    }
    const SliceResult r = SetSchedulerSlice(kWireSlice);
    EXPECT_FALSE(r.applied);
    EXPECT_NE(r.detail.find("not on the fair scheduler"), std::string::npos) << r.detail;
  });
}

}  // namespace
}  // namespace somasim::app
