// An 8-bit RGB raster image held in memory: what the software renderer produces and the PNG
// encoder consumes.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace somasim::render {

// Pixels row-major, top row first, 3 bytes (R, G, B) per pixel, sRGB-encoded values:
// rgb.size() == 3 · width · height, pixel (x, y) at rgb[3 · (y · width + x) + channel].
struct Image {
  int width = 0;   // pixels
  int height = 0;  // pixels
  std::vector<uint8_t> rgb;

  // Index in rgb of channel c (0 = R, 1 = G, 2 = B) of pixel (x, y); no bounds check.
  size_t Index(int x, int y, int c = 0) const {
    return 3 * (static_cast<size_t>(y) * static_cast<size_t>(width) + static_cast<size_t>(x)) +
           static_cast<size_t>(c);
  }
};

}  // namespace somasim::render
