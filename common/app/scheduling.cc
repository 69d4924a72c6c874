#include "common/app/scheduling.h"

#include <sched.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstring>
#include <stdexcept>

#include "common/app/log.h"

namespace somasim::app {
namespace {

// struct sched_attr of sched_setattr(2) (glibc 2.36 has no wrapper); the first 48 bytes
// (SCHED_ATTR_SIZE_VER0) are what every kernel since 3.14 knows.
struct SchedAttr {
  uint32_t size;
  uint32_t sched_policy;
  uint64_t sched_flags;
  int32_t sched_nice;
  uint32_t sched_priority;
  uint64_t sched_runtime;  // [ns]; for SCHED_OTHER the EEVDF slice request (Linux >= 6.12)
  uint64_t sched_deadline;
  uint64_t sched_period;
};
static_assert(sizeof(SchedAttr) == 48);

constexpr std::chrono::microseconds kMinSlice{100};
constexpr std::chrono::microseconds kMaxSlice{100'000};

bool GetAttr(SchedAttr* attr) {
  std::memset(attr, 0, sizeof(*attr));
  return syscall(SYS_sched_getattr, 0, attr, sizeof(*attr), 0) == 0;
}

}  // namespace

SliceResult SetSchedulerSlice(std::chrono::microseconds slice) {
  if (slice.count() != 0 && (slice < kMinSlice || slice > kMaxSlice)) {
    throw std::invalid_argument("scheduler slice " + std::to_string(slice.count()) +
                                " µs: must be 0 (the default) or 100..100000 µs");
  }
  SliceResult result;
  SchedAttr attr{};
  if (!GetAttr(&attr)) {
    result.detail = std::string("sched_getattr failed: ") + std::strerror(errno);
    return result;
  }
  if (attr.sched_policy != SCHED_OTHER && attr.sched_policy != SCHED_BATCH) {
    result.detail = "the thread is not on the fair scheduler (policy " +
                    std::to_string(attr.sched_policy) + "); its slice does not apply";
    return result;
  }
  attr.size = sizeof(attr);
  attr.sched_flags = 0;
  attr.sched_runtime = static_cast<uint64_t>(slice.count()) * 1000u;
  if (syscall(SYS_sched_setattr, 0, &attr, 0) != 0) {
    result.detail = std::string("sched_setattr refused the slice: ") + std::strerror(errno);
    return result;
  }
  const long long now = SchedulerSliceUs();
  if (slice.count() != 0 && now != slice.count()) {
    result.detail =
        "the kernel does not keep a slice request (EEVDF slices need Linux 6.12 or later)";
    return result;
  }
  result.applied = true;
  return result;
}

long long SchedulerSliceUs() {
  SchedAttr attr{};
  if (!GetAttr(&attr)) return -1;
  return static_cast<long long>(attr.sched_runtime / 1000u);
}

void LogSchedulerSlice(const SliceResult& r, const char* threads) {
  if (r.applied) {
    Log(LogLevel::kInfo, "scheduler_slice",
        {{"threads", threads}, {"slice_us", SchedulerSliceUs()}});
  } else {
    Log(LogLevel::kWarning, "scheduler_slice_not_applied",
        {{"threads", threads}, {"detail", r.detail}});
  }
}

}  // namespace somasim::app
