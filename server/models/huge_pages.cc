#include "server/models/huge_pages.h"

#include <cstdint>
#include <cstdlib>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace somasim::models {
namespace {

#if defined(__linux__)
#ifndef MADV_COLLAPSE
constexpr int MADV_COLLAPSE = 25;  // Linux 6.1 (<linux/mman.h>), newer than glibc 2.36's headers
#endif
#endif

size_t RoundUpToHugePages(size_t bytes) {
  return (bytes + kHugePageSize - 1) / kHugePageSize * kHugePageSize;
}

}  // namespace

void* AllocateHugePages(size_t bytes) {
  const size_t rounded = RoundUpToHugePages(bytes);
  void* data = std::aligned_alloc(kHugePageSize, rounded);
  if (data == nullptr) throw std::bad_alloc();
#if defined(__linux__)
  // A request: refused (EINVAL without transparent huge pages), the pages are ordinary ones.
  static_cast<void>(madvise(data, rounded, MADV_HUGEPAGE));
#endif
  return data;
}

void FreeHugePages(void* data) { std::free(data); }

bool AdviseHugePages(void* data, size_t bytes) {
#if defined(__linux__)
  const auto begin = reinterpret_cast<uintptr_t>(data);
  const uintptr_t first = (begin + kHugePageSize - 1) / kHugePageSize * kHugePageSize;
  const uintptr_t last = (begin + bytes) / kHugePageSize * kHugePageSize;
  if (last <= first) return false;
  void* const start = static_cast<char*>(data) + (first - begin);
  const size_t length = last - first;
  static_cast<void>(madvise(start, length, MADV_HUGEPAGE));
  // Already touched memory is collapsed now (Linux 6.1 and later) rather than whenever
  // khugepaged comes by; older kernels refuse MADV_COLLAPSE and leave it to khugepaged.
  static_cast<void>(madvise(start, length, MADV_COLLAPSE));
  return true;
#else
  static_cast<void>(data);
  static_cast<void>(bytes);
  return false;
#endif
}

}  // namespace somasim::models
