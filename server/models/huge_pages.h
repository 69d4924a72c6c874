// Transparent huge pages for a model's large arrays (the explicit mass-spring pass's streams,
// ring and window; the tissue state's positions and velocities). A pass that walks megabytes of
// arrays and reads a ring and a window at scattered places needs hundreds of 4 KiB TLB entries,
// and under a hypervisor every miss is a two-level page walk; one 2 MiB page covers 512 small
// ones (docs/benchmarks.md). Linux only, and a request: where the kernel gives no huge pages the
// memory is ordinary and everything works the same, only slower.
#pragma once

#include <cstddef>
#include <memory>
#include <new>
#include <vector>

namespace somasim::models {

// Below this an array is allocated as usual (a huge page would be mostly unused) [bytes].
constexpr size_t kHugePageThreshold = size_t{256} << 10;
constexpr size_t kHugePageSize = size_t{2} << 20;  // [bytes], x86-64's

// Allocates `bytes` (>= kHugePageThreshold) on 2 MiB boundaries, rounded up to whole huge pages,
// with the kernel asked for huge pages before the memory is touched; FreeHugePages releases it.
// Throws std::bad_alloc when out of memory.
void* AllocateHugePages(size_t bytes);
void FreeHugePages(void* data);

// Asks for huge pages on the 2 MiB-aligned part of [data, data + bytes), already allocated
// elsewhere (Eigen's arrays): the kernel collapses it into huge pages where it can. Returns
// whether it was asked (false off Linux, or when the range holds no whole huge page).
bool AdviseHugePages(void* data, size_t bytes);

// An allocator for std::vector that puts arrays of kHugePageThreshold bytes or more on huge
// pages (AllocateHugePages) and smaller ones where std::allocator would.
template <typename T>
struct HugePageAllocator {
  using value_type = T;
  HugePageAllocator() = default;
  template <typename U>
  explicit HugePageAllocator(const HugePageAllocator<U>& /*other*/) {}
  T* allocate(size_t n) {
    if (n > static_cast<size_t>(-1) / sizeof(T)) throw std::bad_array_new_length();
    if (n * sizeof(T) < kHugePageThreshold) return std::allocator<T>().allocate(n);
    return static_cast<T*>(AllocateHugePages(n * sizeof(T)));
  }
  void deallocate(T* data, size_t n) {
    if (n * sizeof(T) < kHugePageThreshold) {
      std::allocator<T>().deallocate(data, n);
    } else {
      FreeHugePages(data);
    }
  }
  template <typename U>
  bool operator==(const HugePageAllocator<U>& /*other*/) const {
    return true;
  }
};

template <typename T>
using HugePageVector = std::vector<T, HugePageAllocator<T>>;

}  // namespace somasim::models
