#include "common/wire/frame_codec.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "tests/support/allocation_counter.h"

namespace somasim::wire {
namespace {

using Result = FrameDecoder::Result;

constexpr int32_t kNodes = 200;

// A mesh whose coordinates move by small random steps; each frame only some of them move, so
// deltas are partial and some nodes change in one coordinate only.
class DeformingMesh {
 public:
  DeformingMesh(int32_t num_nodes, uint32_t seed, double moving_fraction)
      : rng_(seed), moving_fraction_(moving_fraction) {
    std::uniform_real_distribution<double> u(-0.1, 0.1);
    x_.resize(3 * static_cast<size_t>(num_nodes));
    for (double& v : x_) v = u(rng_);
  }
  void Step() {
    std::uniform_real_distribution<double> pick(0.0, 1.0);
    std::normal_distribution<double> step(0.0, 1e-4);  // [m]
    // Each coordinate on its own: some nodes change only in x, y or z.
    for (double& v : x_) {
      if (pick(rng_) < moving_fraction_) v += step(rng_);
    }
  }
  std::span<const double> positions() const { return x_; }

 private:
  std::mt19937 rng_;
  double moving_fraction_;
  std::vector<double> x_;
};

// A frame that owns its arrays (a view dies at the next Encode), to drop, delay or corrupt.
struct OwnedFrame {
  FrameView meta;
  std::vector<uint32_t> indices;
  std::vector<float> positions;
  FrameView view() const {
    FrameView v = meta;
    v.indices = indices;
    v.positions = positions;
    return v;
  }
};

OwnedFrame Own(const FrameView& v) {
  OwnedFrame f;
  f.meta = v;
  f.indices.assign(v.indices.begin(), v.indices.end());
  f.positions.assign(v.positions.begin(), v.positions.end());
  return f;
}

bool SameBits(std::span<const float> a, std::span<const float> b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size_bytes()) == 0;
}

std::vector<float> Copy(std::span<const float> a) { return {a.begin(), a.end()}; }

std::vector<double> Constant(int32_t num_nodes, double value) {
  return std::vector<double>(3 * static_cast<size_t>(num_nodes), value);
}

TEST(FrameCodec, ReceiverOfEveryFrameHoldsThePublishedBitsExactly) {
  DeformingMesh mesh(kNodes, 1, 0.3);
  FrameEncoder encoder(kNodes, 30);
  FrameDecoder decoder(kNodes);
  int partial_deltas = 0;
  for (int k = 1; k <= 600; ++k) {
    mesh.Step();
    const FrameView frame = encoder.Encode(mesh.positions());
    ASSERT_EQ(frame.frame, static_cast<uint64_t>(k));
    if (!frame.keyframe && !frame.indices.empty() &&
        frame.indices.size() < static_cast<size_t>(kNodes)) {
      ++partial_deltas;
    }
    ASSERT_EQ(decoder.Apply(frame), Result::kApplied) << "frame " << k;
    ASSERT_TRUE(SameBits(decoder.positions(), encoder.published())) << "frame " << k;
    EXPECT_EQ(decoder.frame(), static_cast<uint64_t>(k));
  }
  EXPECT_GT(partial_deltas, 500);
  // What is published is the input rounded to float.
  for (size_t j = 0; j < mesh.positions().size(); ++j) {
    ASSERT_EQ(encoder.published()[j], static_cast<float>(mesh.positions()[j]));
  }
  EXPECT_EQ(decoder.applied(), 600U);
  EXPECT_EQ(decoder.waited() + decoder.stale() + decoder.bad(), 0U);
}

TEST(FrameCodec, LateJoinerWaitsThenConvergesAtTheNextKeyframe) {
  constexpr uint32_t kInterval = 25;
  std::mt19937 rng(7);
  for (int trial = 0; trial < 20; ++trial) {
    DeformingMesh mesh(kNodes, 100 + static_cast<uint32_t>(trial), 0.5);
    FrameEncoder encoder(kNodes, kInterval);
    FrameDecoder decoder(kNodes);
    // Joins at a frame that is not a keyframe (2 .. 200, k - 1 not a multiple of the interval).
    uint64_t join = 0;
    do {
      join = std::uniform_int_distribution<uint64_t>(2, 200)(rng);
    } while ((join - 1) % kInterval == 0);
    const uint64_t next_keyframe = ((join - 1) / kInterval + 1) * kInterval + 1;
    for (uint64_t k = 1; k <= next_keyframe + 40; ++k) {
      mesh.Step();
      const FrameView frame = encoder.Encode(mesh.positions());
      if (k < join) continue;
      const Result r = decoder.Apply(frame);
      if (k < next_keyframe) {
        ASSERT_EQ(r, Result::kWaitingForKeyframe) << "frame " << k << " join " << join;
        ASSERT_FALSE(decoder.has_shape());
      } else {
        ASSERT_TRUE(frame.keyframe || k > next_keyframe);
        ASSERT_EQ(r, Result::kApplied) << "frame " << k << " join " << join;
        ASSERT_TRUE(SameBits(decoder.positions(), encoder.published())) << "frame " << k;
      }
    }
    EXPECT_EQ(decoder.waited(), next_keyframe - join);
  }
}

TEST(FrameCodec, DroppedFramesRecoverAtTheNextKeyframeAndNeverGiveAWrongShape) {
  DeformingMesh mesh(kNodes, 3, 0.3);
  FrameEncoder encoder(kNodes, 20);
  FrameDecoder decoder(kNodes);
  std::mt19937 rng(11);
  std::bernoulli_distribution drop(0.2);
  int dropped = 0;
  int waited = 0;
  int recovered = 0;  // keyframes applied after waiting
  bool waiting = false;
  for (int k = 1; k <= 2000; ++k) {
    mesh.Step();
    const FrameView frame = encoder.Encode(mesh.positions());
    if (drop(rng)) {
      ++dropped;
      continue;
    }
    const Result r = decoder.Apply(frame);
    if (frame.keyframe) {
      ASSERT_EQ(r, Result::kApplied) << "keyframe " << k;  // a keyframe always recovers
      if (waiting) ++recovered;
      waiting = false;
    }
    if (r == Result::kApplied) {
      // Never a wrong shape: whatever was applied is exactly what the server published.
      ASSERT_TRUE(SameBits(decoder.positions(), encoder.published())) << "frame " << k;
      ASSERT_EQ(decoder.frame(), static_cast<uint64_t>(k));
    } else {
      ASSERT_EQ(r, Result::kWaitingForKeyframe) << "frame " << k;
      ++waited;
      waiting = true;
    }
  }
  EXPECT_GT(dropped, 300);
  EXPECT_GT(waited, 300);
  EXPECT_GT(recovered, 30);
  EXPECT_EQ(decoder.waited(), static_cast<uint64_t>(waited));
}

TEST(FrameDecoder, ReorderedAndDuplicateFramesAreStale) {
  DeformingMesh mesh(kNodes, 5, 0.3);
  FrameEncoder encoder(kNodes, 4);    // keyframes 1, 5, 9
  std::vector<OwnedFrame> frames(1);  // frames[k] is frame k
  for (int k = 1; k <= 9; ++k) {
    mesh.Step();
    frames.push_back(Own(encoder.Encode(mesh.positions())));
  }
  ASSERT_TRUE(frames[5].meta.keyframe);
  FrameDecoder decoder(kNodes);
  for (int k = 1; k <= 3; ++k) ASSERT_EQ(decoder.Apply(frames[k].view()), Result::kApplied);
  const std::vector<float> at3 = Copy(decoder.positions());
  EXPECT_EQ(decoder.Apply(frames[3].view()), Result::kStale);  // duplicate
  EXPECT_EQ(decoder.Apply(frames[2].view()), Result::kStale);  // late
  EXPECT_EQ(decoder.Apply(frames[1].view()), Result::kStale);  // an old keyframe
  EXPECT_EQ(decoder.stale(), 3U);
  EXPECT_EQ(decoder.frame(), 3U);
  EXPECT_TRUE(SameBits(decoder.positions(), at3));
  // Frame 6 ahead of 4 and 5: its base is not held, so it waits (and is not remembered: it
  // applies when it comes again after 5).
  EXPECT_EQ(decoder.Apply(frames[6].view()), Result::kWaitingForKeyframe);
  EXPECT_EQ(decoder.Apply(frames[4].view()), Result::kApplied);
  EXPECT_EQ(decoder.Apply(frames[5].view()), Result::kApplied);
  EXPECT_EQ(decoder.Apply(frames[4].view()), Result::kStale);
  EXPECT_EQ(decoder.Apply(frames[7].view()), Result::kWaitingForKeyframe);  // 6 missing
  EXPECT_EQ(decoder.Apply(frames[6].view()), Result::kApplied);
  EXPECT_EQ(decoder.Apply(frames[7].view()), Result::kApplied);
  EXPECT_EQ(decoder.frame(), 7U);
}

TEST(FrameDecoder, ResetForgetsTheShapeAndTheNextKeyframeStartsAgain) {
  FrameEncoder encoder(kNodes, 100);
  FrameDecoder decoder(kNodes);
  const std::vector<double> a = Constant(kNodes, 0.01);
  ASSERT_EQ(decoder.Apply(encoder.Encode(a)), Result::kApplied);
  ASSERT_EQ(decoder.Apply(encoder.Encode(a)), Result::kApplied);
  decoder.Reset();
  EXPECT_FALSE(decoder.has_shape());
  EXPECT_EQ(decoder.frame(), 0U);
  EXPECT_EQ(decoder.Apply(encoder.Encode(a)), Result::kWaitingForKeyframe);
  // A restarted server counts from 1 again: accepted after Reset.
  FrameEncoder restarted(kNodes, 100);
  const std::vector<double> b = Constant(kNodes, -0.02);
  EXPECT_EQ(decoder.Apply(restarted.Encode(b)), Result::kApplied);
  EXPECT_EQ(decoder.frame(), 1U);
  EXPECT_TRUE(SameBits(decoder.positions(), restarted.published()));
}

TEST(FrameEncoder, ForceKeyframeMakesTheNextFrameAKeyframe) {
  FrameEncoder encoder(kNodes, 1000);
  const std::vector<double> a = Constant(kNodes, 0.01);
  EXPECT_TRUE(encoder.Encode(a).keyframe);
  EXPECT_FALSE(encoder.Encode(a).keyframe);
  encoder.ForceKeyframe();
  const FrameView forced = encoder.Encode(a);
  EXPECT_TRUE(forced.keyframe);
  EXPECT_EQ(forced.frame, 3U);
  EXPECT_EQ(forced.base_frame, 0U);
  EXPECT_TRUE(forced.indices.empty());
  EXPECT_EQ(forced.positions.size(), 3 * static_cast<size_t>(kNodes));
  EXPECT_FALSE(encoder.Encode(a).keyframe);
}

TEST(FrameEncoder, KeyframesComeEveryIntervalFramesFromFrameOne) {
  const std::vector<double> a = Constant(kNodes, 0.01);
  FrameEncoder every(kNodes, 1);
  for (int k = 1; k <= 10; ++k) {
    const FrameView f = every.Encode(a);
    EXPECT_TRUE(f.keyframe) << k;
    EXPECT_EQ(f.base_frame, 0U);
  }
  FrameEncoder four(kNodes, 4);
  for (uint64_t k = 1; k <= 13; ++k) {
    const FrameView f = four.Encode(a);
    EXPECT_EQ(f.keyframe, (k - 1) % 4 == 0) << k;
    EXPECT_EQ(f.base_frame, f.keyframe ? 0 : k - 1) << k;
  }
  EXPECT_EQ(four.last_frame(), 13U);
  EXPECT_EQ(four.num_nodes(), kNodes);
}

TEST(FrameEncoder, UnchangedMeshGivesEmptyDeltas) {
  FrameEncoder encoder(kNodes, 50);
  FrameDecoder decoder(kNodes);
  const std::vector<double> a = Constant(kNodes, 0.03);
  ASSERT_EQ(decoder.Apply(encoder.Encode(a)), Result::kApplied);
  for (int k = 2; k <= 49; ++k) {
    const FrameView f = encoder.Encode(a);
    ASSERT_FALSE(f.keyframe);
    EXPECT_TRUE(f.indices.empty());
    EXPECT_TRUE(f.positions.empty());
    EXPECT_EQ(decoder.Apply(f), Result::kApplied);  // an empty delta still advances the frame
  }
  EXPECT_EQ(decoder.frame(), 49U);
}

TEST(FrameEncoder, DeltaHoldsExactlyTheNodesWhoseFloatBitsChanged) {
  constexpr int32_t kFew = 5;
  FrameEncoder encoder(kFew, 100);
  std::vector<double> x = Constant(kFew, 0.25);
  encoder.Encode(x);
  x[3 * 0 + 2] += 1e-3;          // node 0: only z changes
  x[3 * 1 + 2] += 1e-12;         // node 1: below float resolution at 0.25 → the same float
  x[3 * 2 + 0] += 1e-6;          // node 2: x changes
  x[3 * 4 + 1] = -x[3 * 4 + 1];  // node 4: y changes sign
  const FrameView f = encoder.Encode(x);
  ASSERT_FALSE(f.keyframe);
  ASSERT_EQ(f.indices.size(), 3U);
  EXPECT_EQ(f.indices[0], 0U);
  EXPECT_EQ(f.indices[1], 2U);
  EXPECT_EQ(f.indices[2], 4U);
  ASSERT_EQ(f.positions.size(), 9U);
  EXPECT_EQ(f.positions[2], static_cast<float>(x[2]));
  EXPECT_EQ(f.positions[3], static_cast<float>(x[6]));
  EXPECT_EQ(f.positions[7], -0.25F);
  // +0 and -0 compare equal as floats but are different bits: sent.
  std::vector<double> zero = Constant(kFew, 0.0);
  FrameEncoder z(kFew, 100);
  z.Encode(zero);
  zero[3 * 3 + 1] = -0.0;
  const FrameView g = z.Encode(zero);
  ASSERT_EQ(g.indices.size(), 1U);
  EXPECT_EQ(g.indices[0], 3U);
  EXPECT_TRUE(std::signbit(z.published()[3 * 3 + 1]));
}

TEST(FrameCodec, NonFinitePositionsAreEncodedAndRefusedByTheDecoder) {
  FrameEncoder encoder(kNodes, 100);
  FrameDecoder decoder(kNodes);
  std::vector<double> x = Constant(kNodes, 0.01);
  ASSERT_EQ(decoder.Apply(encoder.Encode(x)), Result::kApplied);
  x[17] = std::numeric_limits<double>::quiet_NaN();
  std::string error;
  const FrameView f = encoder.Encode(x);
  EXPECT_EQ(f.indices.size(), 1U);
  EXPECT_EQ(decoder.Apply(f, &error), Result::kBad);
  EXPECT_NE(error.find("not finite"), std::string::npos) << error;
  EXPECT_EQ(decoder.frame(), 1U);
}

// A decoder holding frame 1 of a small mesh, and a valid delta 2 and keyframe 3 to corrupt.
struct BadFrameFixture {
  static constexpr int32_t kFew = 6;
  FrameDecoder decoder{kFew};
  OwnedFrame delta;
  OwnedFrame keyframe;
  std::vector<float> held;
};

BadFrameFixture MakeBadFrameFixture() {
  BadFrameFixture f;
  FrameEncoder encoder(BadFrameFixture::kFew, 2);  // keyframes 1, 3
  std::vector<double> x = Constant(BadFrameFixture::kFew, 0.02);
  if (f.decoder.Apply(encoder.Encode(x)) != Result::kApplied) throw std::logic_error("setup");
  f.held = Copy(f.decoder.positions());
  x[3 * 1] = 0.03;
  x[3 * 3 + 1] = 0.04;
  x[3 * 5 + 2] = 0.05;
  f.delta = Own(encoder.Encode(x));
  f.keyframe = Own(encoder.Encode(x));
  if (f.delta.indices.size() != 3 || !f.keyframe.meta.keyframe) throw std::logic_error("setup");
  return f;
}

struct BadCase {
  const char* name;
  bool keyframe;  // corrupts the keyframe (else the delta)
  std::function<void(OwnedFrame*)> corrupt;
  const char* message;  // a part of the error
};

TEST(FrameDecoder, MalformedFramesAreBadNamedAndLeaveTheShapeUnchanged) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  const std::vector<BadCase> cases = {
      {"wrong num_nodes", false, [](OwnedFrame* f) { f->meta.num_nodes = 7; }, "num_nodes 7"},
      {"keyframe wrong num_nodes", true, [](OwnedFrame* f) { f->meta.num_nodes = 5; },
       "num_nodes 5"},
      {"frame 0", true, [](OwnedFrame* f) { f->meta.frame = 0; }, "frame number 0"},
      {"delta base 0", false, [](OwnedFrame* f) { f->meta.base_frame = 0; }, "base_frame 0"},
      {"delta base not frame-1", false,
       [](OwnedFrame* f) {
         f->meta.frame = 4;
         f->meta.base_frame = 1;
       },
       "base_frame 1, expected 3"},
      {"keyframe with a base", true, [](OwnedFrame* f) { f->meta.base_frame = 2; }, "base_frame 2"},
      {"truncated delta positions", false, [](OwnedFrame* f) { f->positions.pop_back(); },
       "8 position values for 3 indices"},
      {"extra delta position", false, [](OwnedFrame* f) { f->positions.push_back(0.0F); },
       "10 position values"},
      {"missing index", false, [](OwnedFrame* f) { f->indices.pop_back(); },
       "9 position values for 2 indices"},
      {"index out of range", false, [](OwnedFrame* f) { f->indices[2] = 6; },
       "index 6 (entry 2) is out of range [0, 6)"},
      {"huge index", false, [](OwnedFrame* f) { f->indices[0] = 0xffffffffU; }, "out of range"},
      {"unsorted indices", false, [](OwnedFrame* f) { std::swap(f->indices[0], f->indices[1]); },
       "index 1 (entry 1) does not ascend from 3"},
      {"duplicate index", false, [](OwnedFrame* f) { f->indices[1] = f->indices[0]; },
       "does not ascend"},
      {"NaN in a delta", false, [nan](OwnedFrame* f) { f->positions[4] = nan; },
       "position value 4 is not finite"},
      {"infinity in a delta", false, [inf](OwnedFrame* f) { f->positions[8] = -inf; },
       "not finite"},
      {"keyframe with indices", true, [](OwnedFrame* f) { f->indices = {0}; }, "1 indices"},
      {"truncated keyframe", true, [](OwnedFrame* f) { f->positions.pop_back(); },
       "17 position values, expected 3 × 6"},
      {"empty keyframe", true, [](OwnedFrame* f) { f->positions.clear(); }, "0 position values"},
      {"NaN in a keyframe", true, [nan](OwnedFrame* f) { f->positions[17] = nan; },
       "position value 17 is not finite"},
  };
  for (const BadCase& c : cases) {
    BadFrameFixture f = MakeBadFrameFixture();
    OwnedFrame frame = c.keyframe ? f.keyframe : f.delta;
    c.corrupt(&frame);
    std::string error;
    EXPECT_EQ(f.decoder.Apply(frame.view(), &error), Result::kBad) << c.name;
    EXPECT_NE(error.find(c.message), std::string::npos) << c.name << ": " << error;
    EXPECT_EQ(f.decoder.frame(), 1U) << c.name;
    EXPECT_TRUE(SameBits(f.decoder.positions(), f.held)) << c.name;
    EXPECT_EQ(f.decoder.bad(), 1U) << c.name;
    EXPECT_EQ(f.decoder.applied(), 1U) << c.name;
    EXPECT_EQ(f.decoder.Apply(frame.view()), Result::kBad) << c.name << " (no error string)";
    // The uncorrupted frame still applies afterwards.
    EXPECT_EQ(f.decoder.Apply(c.keyframe ? f.keyframe.view() : f.delta.view()), Result::kApplied)
        << c.name;
  }
}

TEST(FrameDecoder, EveryTruncationOfAValidFrameIsBad) {
  BadFrameFixture f = MakeBadFrameFixture();
  for (const OwnedFrame* valid : {&f.delta, &f.keyframe}) {
    for (size_t size = 0; size < valid->positions.size(); ++size) {
      OwnedFrame cut = *valid;
      cut.positions.resize(size);
      EXPECT_EQ(f.decoder.Apply(cut.view()), Result::kBad) << size;
    }
  }
  EXPECT_EQ(f.decoder.frame(), 1U);
  EXPECT_TRUE(SameBits(f.decoder.positions(), f.held));
}

TEST(FrameCodec, ConstructorAndEncodeArgumentsAreChecked) {
  EXPECT_THROW(FrameEncoder(0, 10), std::invalid_argument);
  EXPECT_THROW(FrameEncoder(-3, 10), std::invalid_argument);
  EXPECT_THROW(FrameEncoder(10, 0), std::invalid_argument);
  EXPECT_THROW(FrameDecoder(0), std::invalid_argument);
  EXPECT_THROW(FrameDecoder(-1), std::invalid_argument);
  FrameEncoder encoder(4, 10);
  const std::vector<double> short_positions(11, 0.0);
  const std::vector<double> long_positions(13, 0.0);
  EXPECT_THROW(encoder.Encode(short_positions), std::invalid_argument);
  EXPECT_THROW(encoder.Encode(long_positions), std::invalid_argument);
  EXPECT_EQ(encoder.last_frame(), 0U);  // nothing was encoded
  try {
    FrameEncoder bad(4, 0);
    FAIL() << "no throw";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("keyframe_interval"), std::string::npos);
  }
}

TEST(FrameCodec, EncodeAndApplyAllocateNothingInSteadyState) {
  DeformingMesh mesh(kNodes, 9, 0.4);
  FrameEncoder encoder(kNodes, 10);
  FrameDecoder decoder(kNodes);
  FrameDecoder late(kNodes);
  // Pre-generate the inputs: the mesh's own stepping is not what is measured.
  std::vector<std::vector<double>> inputs;
  for (int k = 0; k < 60; ++k) {
    mesh.Step();
    inputs.emplace_back(mesh.positions().begin(), mesh.positions().end());
  }
  ASSERT_EQ(decoder.Apply(encoder.Encode(inputs[0])), Result::kApplied);
  std::string error;
  error.reserve(256);
  int applied = 0;
  int64_t allocations = 0;
  {
    const testing::AllocationCounter counter;
    for (size_t k = 1; k < inputs.size(); ++k) {
      const FrameView f = encoder.Encode(inputs[k]);
      applied += decoder.Apply(f, &error) == Result::kApplied ? 1 : 0;
      late.Apply(f);     // waits, then applies from the keyframe on
      decoder.Apply(f);  // stale
      if (k == 30) encoder.ForceKeyframe();
    }
    allocations = counter.count();
  }
  EXPECT_EQ(allocations, 0);
  EXPECT_EQ(applied, 59);
  EXPECT_GT(late.waited(), 0U);
  EXPECT_EQ(decoder.stale(), 59U);
  EXPECT_TRUE(SameBits(late.positions(), encoder.published()));
}

}  // namespace
}  // namespace somasim::wire
