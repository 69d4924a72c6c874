#include "common/app/realtime.h"

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

namespace somasim::app {

RealtimeResult SetFifoScheduling(int priority) {
  if (priority < 1 || priority > 99) {
    throw std::invalid_argument("SCHED_FIFO priority " + std::to_string(priority) +
                                " is not within 1..99");
  }
  sched_param param{};
  param.sched_priority = priority;
  const int rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
  RealtimeResult r;
  if (rc == 0) {
    r.applied = true;
    r.detail = "SCHED_FIFO priority " + std::to_string(priority);
    return r;
  }
  rlimit limit{};
  getrlimit(RLIMIT_RTPRIO, &limit);
  r.detail = std::string("SCHED_FIFO refused: ") + std::strerror(rc) + " (RLIMIT_RTPRIO is " +
             (limit.rlim_cur == RLIM_INFINITY ? std::string("unlimited")
                                              : std::to_string(limit.rlim_cur)) +
             "); grant rtprio " + std::to_string(priority) +
             " in /etc/security/limits.d or CAP_SYS_NICE; running on the fair scheduler";
  return r;
}

RealtimeResult LockAllMemory() {
  RealtimeResult r;
  rlimit limit{};
  getrlimit(RLIMIT_MEMLOCK, &limit);
  if (limit.rlim_cur != RLIM_INFINITY && geteuid() != 0) {
    r.detail = "mlockall not tried: RLIMIT_MEMLOCK is " + std::to_string(limit.rlim_cur) +
               " bytes (locking all memory could make later allocations fail); grant memlock "
               "unlimited in /etc/security/limits.d or CAP_IPC_LOCK; pages may fault in the loop";
    return r;
  }
  if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0) {
    r.detail = std::string("mlockall refused: ") + std::strerror(errno);
    return r;
  }
  r.applied = true;
  r.detail = "all memory locked";
  return r;
}

}  // namespace somasim::app
