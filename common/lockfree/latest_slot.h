// A single-writer "newest value" slot between two threads of one process: the haptic node's
// wire thread hands the newest local force model to the 1 kHz loop through one and the loop
// hands the tool pose back through another; the server's physics thread hands each tool's force
// model to its writer thread. A seqlock, as the arm's shared memory (arm_abi.h): the writer
// never waits, the reader retries while a write is under way and never sees a torn value. No
// lock, no allocation, no system call.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <type_traits>

namespace somasim::lockfree {

template <typename T>
class LatestSlot {
  static_assert(std::is_trivially_copyable_v<T>, "a slot holds plain data");

 public:
  // Exactly one thread writes.
  void Write(const T& value) {
    std::array<uint64_t, kWords> words{};
    std::memcpy(words.data(), &value, sizeof(T));
    const uint64_t s = sequence_.load(std::memory_order_relaxed);
    sequence_.store(s + 1, std::memory_order_relaxed);
    std::atomic_thread_fence(std::memory_order_release);
    for (size_t i = 0; i < kWords; ++i) words_[i].store(words[i], std::memory_order_relaxed);
    sequence_.store(s + 2, std::memory_order_release);
  }

  // The newest value into `out` and the number of writes it is the result of (0: nothing
  // written yet, `out` untouched). Returns false when the writer kept writing through every
  // attempt (`out` untouched).
  bool Read(T* out, uint64_t* version, int attempts = 64) const {
    std::array<uint64_t, kWords> words{};
    for (int a = 0; a < attempts; ++a) {
      const uint64_t s1 = sequence_.load(std::memory_order_acquire);
      if ((s1 & 1U) != 0) continue;
      if (s1 == 0) {
        *version = 0;
        return true;
      }
      for (size_t i = 0; i < kWords; ++i) words[i] = words_[i].load(std::memory_order_relaxed);
      std::atomic_thread_fence(std::memory_order_acquire);
      if (sequence_.load(std::memory_order_relaxed) != s1) continue;
      std::memcpy(static_cast<void*>(out), words.data(), sizeof(T));
      *version = s1 / 2;
      return true;
    }
    return false;
  }

  // Writes so far.
  uint64_t version() const { return sequence_.load(std::memory_order_acquire) / 2; }

 private:
  static constexpr size_t kWords = (sizeof(T) + 7) / 8;
  alignas(64) std::atomic<uint64_t> sequence_{0};
  std::array<std::atomic<uint64_t>, kWords> words_{};
};

}  // namespace somasim::lockfree
