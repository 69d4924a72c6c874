// The lock-free hand-offs between threads (common/lockfree/): a seqlock slot whose reader never
// sees a half-written value under a concurrent writer, a single-producer ring that keeps order
// and refuses when full, and a triple buffer whose reader always gets the newest complete value.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <thread>
#include <vector>

#include "common/lockfree/latest_slot.h"
#include "common/lockfree/spsc_ring.h"
#include "common/lockfree/triple_buffer.h"
#include "tests/support/sanitizer.h"

namespace somasim::lockfree {
namespace {

// The slot the wire thread hands models through: a reader never sees a half-written value.
TEST(LatestSlot, AReaderUnderAConcurrentWriterNeverSeesATornValue) {
  struct Value {
    uint64_t words[24];
  };
  LatestSlot<Value> slot;
  Value v{};
  uint64_t version = 99;
  EXPECT_TRUE(slot.Read(&v, &version));
  EXPECT_EQ(version, 0u);
  std::atomic<bool> done{false};
  std::thread writer([&] {
    Value w{};
    for (uint64_t i = 1; !done.load(std::memory_order_relaxed); ++i) {
      for (uint64_t& x : w.words) x = i;
      slot.Write(w);
      // A breath between writes (the real writer writes at 200 Hz), so reads also get through.
      const auto until = std::chrono::steady_clock::now() + std::chrono::microseconds(2);
      while (std::chrono::steady_clock::now() < until) {
      }
    }
  });
  // The writer's first value, before counting (on a loaded machine the reads could otherwise
  // all finish before the writer thread first runs).
  while (!slot.Read(&v, &version) || version == 0) std::this_thread::yield();
  const int reads = testing::kUnderSanitizer ? 100000 : 2000000;
  int ok = 0;
  uint64_t last = 0;
  for (int i = 0; i < reads; ++i) {
    if (!slot.Read(&v, &version)) continue;
    if (version == 0) continue;
    ++ok;
    for (uint64_t x : v.words) ASSERT_EQ(x, v.words[0]) << "torn at read " << i;
    ASSERT_GE(version, last);  // never older than what was read before
    last = version;
  }
  done = true;
  writer.join();
  EXPECT_GT(ok, reads / 100);  // reads that overlap a write retry; none may tear
}

// The ring between two threads: every item arrives once, in order; a full ring refuses.
TEST(SpscRing, KeepsOrderAcrossThreadsAndRefusesWhenFull) {
  SpscRing<uint64_t, 8> full;
  for (uint64_t i = 0; i < 8; ++i) EXPECT_TRUE(full.Push(i));
  EXPECT_FALSE(full.Push(99));
  uint64_t out = 0;
  EXPECT_TRUE(full.Pop(&out));
  EXPECT_EQ(out, 0u);
  EXPECT_TRUE(full.Push(8));

  SpscRing<uint64_t, 64> ring;
  const uint64_t n = testing::kUnderSanitizer ? 20000 : 500000;
  std::thread producer([&] {
    for (uint64_t i = 1; i <= n;) {
      if (ring.Push(i)) ++i;
    }
  });
  uint64_t expected = 1;
  while (expected <= n) {
    uint64_t v = 0;
    if (!ring.Pop(&v)) continue;
    ASSERT_EQ(v, expected);
    ++expected;
  }
  producer.join();
  EXPECT_FALSE(ring.Pop(&out));
}

// The triple buffer: nothing new until published; the newest value wins; a value is never
// mixed with another even while the writer keeps publishing.
TEST(TripleBuffer, TheReaderGetsTheNewestCompleteValue) {
  TripleBuffer<std::vector<uint64_t>> buffer(std::vector<uint64_t>(256, 0));
  EXPECT_FALSE(buffer.Take());
  EXPECT_EQ(buffer.front()[0], 0u);
  for (uint64_t v = 1; v <= 3; ++v) {
    std::fill(buffer.back().begin(), buffer.back().end(), v);
    buffer.Publish();
  }
  EXPECT_TRUE(buffer.Take());
  EXPECT_EQ(buffer.front()[0], 3u);
  EXPECT_FALSE(buffer.Take());

  std::atomic<bool> done{false};
  std::thread writer([&] {
    for (uint64_t v = 4; !done.load(std::memory_order_relaxed); ++v) {
      std::fill(buffer.back().begin(), buffer.back().end(), v);
      buffer.Publish();
    }
  });
  uint64_t last = 3;
  const int reads = testing::kUnderSanitizer ? 2000 : 200000;
  for (int i = 0; i < reads; ++i) {
    if (!buffer.Take()) continue;
    const std::vector<uint64_t>& v = buffer.front();
    for (const uint64_t x : v) ASSERT_EQ(x, v[0]) << "mixed at read " << i;
    ASSERT_GT(v[0], last);  // newer than anything read before
    last = v[0];
  }
  done = true;
  writer.join();
}

}  // namespace
}  // namespace somasim::lockfree
