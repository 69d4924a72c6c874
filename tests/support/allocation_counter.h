// Counts heap allocations in a scope, to prove that real-time paths (a physics step, a haptic
// tick, a cut update) allocate nothing. Linking this file replaces the global operator new of
// the test executable with one that counts while a counter is alive.
#pragma once

#include <cstdint>

namespace somasim::testing {

class AllocationCounter {
 public:
  AllocationCounter();   // starts counting (counters do not nest)
  ~AllocationCounter();  // stops
  AllocationCounter(const AllocationCounter&) = delete;
  AllocationCounter& operator=(const AllocationCounter&) = delete;
  int64_t count() const;  // allocations since construction, on any thread
};

}  // namespace somasim::testing
