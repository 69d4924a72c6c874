// A received somasim_wire_MeshFrame (idl/mesh.idl) as the FrameView that FrameDecoder::Apply
// takes: no copy, the spans point into the sample (valid while the sample is, e.g. inside a
// Reader::Take callback). Kept apart from frame_codec.h, which stays free of the wire types.
#pragma once

#include "common/wire/frame_codec.h"
#include "idl/mesh.h"

namespace somasim::wire {

inline FrameView ViewOf(const somasim_wire_MeshFrame& f) {
  FrameView v;
  v.frame = f.frame;
  v.base_frame = f.base_frame;
  v.keyframe = f.keyframe;
  v.num_nodes = f.num_nodes;
  v.indices = {f.indices._buffer, f.indices._length};
  v.positions = {f.positions._buffer, f.positions._length};
  return v;
}

}  // namespace somasim::wire
