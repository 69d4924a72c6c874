// An organ's shown or published positions as files, for exactness checks (somasim-server
// --dump-final, somasim-viewer --dump-positions write the same): DIR/<organ>.f32 (float32 x y z
// per node, as held) and DIR/<organ>.frame (the frame number, text).
#pragma once

#include <cstdint>
#include <span>
#include <string>

namespace somasim::wire {

// Creates DIR if needed; false on an I/O error.
bool WriteFrameDump(const std::string& dir, const std::string& organ,
                    std::span<const float> positions, uint64_t frame);

}  // namespace somasim::wire
