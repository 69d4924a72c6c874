// PNG encoding of an in-memory RGB image (no file I/O: the caller writes the bytes).
#pragma once

#include <string>

#include "common/render/image.h"

namespace somasim::render {

// The bytes of a PNG file (ISO/IEC 15948, "PNG Second Edition") holding `image` as 8-bit
// truecolour (colour type 2), non-interlaced: signature, IHDR, one IDAT, IEND. Each row gets the
// adaptive filter the specification recommends (§12.8: the one whose output has the smallest sum
// of absolute values as signed bytes); the filtered rows are zlib-compressed (level 6).
// Deterministic: the same image gives the same bytes (with the same zlib).
// Throws std::invalid_argument when width or height is not in 1..2^31-1 or
// rgb.size() != 3 · width · height.
std::string EncodePng(const Image& image);

}  // namespace somasim::render
