// The mesh frame codec on the server's publisher thread (60 Hz per organ) and in the viewer, in
// the worst case: every node of the organ moves every frame, so each delta carries all of them.
//   BM_DeltaEncode/gallbladder5400  one FrameEncoder::Encode of the organ's 5400 nodes (double →
//                                   float rounding, bit comparison with the last published
//                                   floats, the delta of every node)
//   BM_DeltaDecode/gallbladder5400  one FrameDecoder::Apply of such a delta (validation: sizes,
//                                   ascending indices, finite values; then the copy)
// Bytes per second count the delta's wire payload: 4 bytes per index + 12 per node.
// Inputs: two shapes (the organ's vertices and the same nudged by 1 µm) alternate, so every node
// differs from the previous frame; the keyframe interval is large enough that no keyframe falls
// inside the measurement.
#include <benchmark/benchmark.h>

#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <vector>

#include "common/mesh_gen/builtin_organs.h"
#include "common/wire/frame_codec.h"

namespace somasim::wire {
namespace {

constexpr uint32_t kNoKeyframe = std::numeric_limits<uint32_t>::max();

// Two shapes of the organ that differ at every node: 3 × num_nodes [m] each.
struct TwoShapes {
  int32_t num_nodes = 0;
  std::vector<double> a;
  std::vector<double> b;
};

TwoShapes MakeTwoShapes(const std::string& organ) {
  const mesh::SurfaceMesh surface = mesh_gen::GenerateBuiltinOrgan(organ).surface;
  TwoShapes s;
  s.num_nodes = static_cast<int32_t>(surface.vertices.cols());
  s.a.assign(surface.vertices.data(), surface.vertices.data() + surface.vertices.size());
  s.b = s.a;
  for (double& v : s.b) v += 1e-6;  // [m] far above float resolution at organ scale (~1e-8)
  return s;
}

int64_t WireBytes(size_t indices) { return static_cast<int64_t>(indices * (4 + 12)); }

void BM_DeltaEncode(benchmark::State& state, const std::string& organ) {
  const TwoShapes shapes = MakeTwoShapes(organ);
  FrameEncoder encoder(shapes.num_nodes, kNoKeyframe);
  encoder.Encode(shapes.a);  // the keyframe
  bool odd = true;
  size_t indices = 0;
  for (auto _ : state) {
    const FrameView frame = encoder.Encode(odd ? shapes.b : shapes.a);
    benchmark::DoNotOptimize(frame.positions.data());
    indices = frame.indices.size();
    odd = !odd;
  }
  if (indices != static_cast<size_t>(shapes.num_nodes)) state.SkipWithError("not every node");
  state.SetBytesProcessed(state.iterations() * WireBytes(indices));
  state.counters["nodes"] = static_cast<double>(shapes.num_nodes);
}

void BM_DeltaDecode(benchmark::State& state, const std::string& organ) {
  const TwoShapes shapes = MakeTwoShapes(organ);
  FrameEncoder encoder(shapes.num_nodes, kNoKeyframe);
  FrameDecoder decoder(shapes.num_nodes);
  decoder.Apply(encoder.Encode(shapes.a));
  // One delta of every node, applied again and again: its frame numbers are rewritten each
  // iteration so that it always follows the frame the decoder holds.
  const FrameView delta = encoder.Encode(shapes.b);
  const std::vector<uint32_t> indices(delta.indices.begin(), delta.indices.end());
  const std::vector<float> positions(delta.positions.begin(), delta.positions.end());
  FrameView frame = delta;
  frame.indices = indices;
  frame.positions = positions;
  bool ok = true;
  for (auto _ : state) {
    frame.base_frame = decoder.frame();
    frame.frame = frame.base_frame + 1;
    ok = decoder.Apply(frame) == FrameDecoder::Result::kApplied && ok;
    benchmark::DoNotOptimize(decoder.positions().data());
  }
  if (!ok || indices.size() != static_cast<size_t>(shapes.num_nodes)) {
    state.SkipWithError("the delta was not applied, or not every node");
  }
  state.SetBytesProcessed(state.iterations() * WireBytes(indices.size()));
  state.counters["nodes"] = static_cast<double>(shapes.num_nodes);
}

BENCHMARK_CAPTURE(BM_DeltaEncode, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_DeltaDecode, gallbladder5400, std::string("gallbladder5400"))
    ->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace somasim::wire
