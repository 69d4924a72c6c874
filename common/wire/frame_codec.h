// Mesh frames as keyframes and deltas (SPEC §1, idl/mesh.idl MeshFrame): the server turns an
// organ's positions into a stream of frames; a viewer applies them and converges to exactly the
// server's published float positions, whatever it missed. Pure: no DDS, no I/O.
//
// Frame k (from 1) is a keyframe (every node) when k = 1, every keyframe_interval-th frame
// (k = 1, 1 + I, 1 + 2I, … for an interval I), or after ForceKeyframe(); otherwise a delta against
// frame k-1: the nodes whose float32 position (any of x, y, z) differs bit for bit from what frame
// k-1 published, ascending, with their new absolute float values. A receiver that holds frame k-1
// applies the delta; one that does not (it joined late or lost a frame) waits for the next
// keyframe. Encode and Apply allocate nothing after construction.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace somasim::wire {

// A frame as it travels (a view: the spans point into the encoder's or the sample's buffers).
struct FrameView {
  uint64_t frame = 0;       // >= 1
  uint64_t base_frame = 0;  // a delta's reference (frame - 1); 0 for a keyframe
  bool keyframe = false;
  uint32_t num_nodes = 0;
  std::span<const uint32_t> indices;  // delta: ascending node ids < num_nodes; keyframe: empty
  std::span<const float> positions;   // [m] 3 per index (delta) or 3 × num_nodes (keyframe)
};

class FrameEncoder {
 public:
  // num_nodes > 0; keyframe_interval >= 1 (1: every frame is a keyframe). Throws
  // std::invalid_argument otherwise.
  FrameEncoder(int32_t num_nodes, uint32_t keyframe_interval);
  // The next frame from `positions` [m] (3 × num_nodes doubles, x y z per node, each rounded to
  // float). The view is valid until the next Encode. Throws std::invalid_argument when
  // positions.size() != 3 × num_nodes. Non-finite values are encoded as they are (the physics
  // never publishes them; a decoder refuses them).
  FrameView Encode(std::span<const double> positions);
  // The next frame is a keyframe (after a topology change, or when a new reader appears).
  void ForceKeyframe();
  // What a receiver holds after the last frame (3 × num_nodes floats).
  std::span<const float> published() const;
  uint64_t last_frame() const;
  int32_t num_nodes() const;

 private:
  int32_t num_nodes_;
  uint32_t keyframe_interval_;
  uint64_t last_frame_ = 0;
  bool force_keyframe_ = false;
  std::vector<float> published_;         // 3 × num_nodes [m], what frame last_frame_ left
  std::vector<uint32_t> delta_indices_;  // capacity num_nodes; the last delta's first n used
  std::vector<float> delta_positions_;   // capacity 3 × num_nodes; 3 per delta index
};

class FrameDecoder {
 public:
  enum class Result {
    kApplied,             // the frame is now the receiver's shape
    kWaitingForKeyframe,  // a delta whose base frame the receiver does not hold
    kStale,               // not newer than the frame held (duplicate or reordered)
    kBad,                 // wrong sizes, unsorted or out-of-range indices, non-finite values,
                          // a node count other than the decoder's: nothing changed
  };
  explicit FrameDecoder(int32_t num_nodes);  // > 0, else std::invalid_argument
  // Applies a frame; on kBad, *error (when given) names what was wrong.
  Result Apply(const FrameView& frame, std::string* error = nullptr);
  // Forgets the shape (a new topology, a server restart): the next keyframe starts again.
  void Reset();
  bool has_shape() const;                    // a keyframe has been applied since Reset
  uint64_t frame() const;                    // the frame held (0: none)
  std::span<const float> positions() const;  // 3 × num_nodes [m]
  int32_t num_nodes() const;
  // Counters since construction.
  uint64_t applied() const;
  uint64_t waited() const;  // deltas dropped for want of their base frame
  uint64_t stale() const;
  uint64_t bad() const;

 private:
  // Whether `frame` is well formed whatever the receiver holds; when not, *error (when given)
  // names the fault (a message is formatted only then: a good frame allocates nothing).
  bool IsWellFormed(const FrameView& frame, std::string* error) const;

  int32_t num_nodes_;
  bool has_shape_ = false;
  uint64_t frame_ = 0;
  std::vector<float> positions_;  // 3 × num_nodes [m]
  uint64_t applied_ = 0;
  uint64_t waited_ = 0;
  uint64_t stale_ = 0;
  uint64_t bad_ = 0;
};

}  // namespace somasim::wire
