#include "common/render/png_encoder.h"

#include <zlib.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace somasim::render {
namespace {

constexpr int kBytesPerPixel = 3;  // 8-bit RGB
// zlib's default level: on rendered images level 9 is about 6× slower for files ~2.5 % smaller.
constexpr int kZlibLevel = 6;

void AppendU32(std::string* out, uint32_t v) {
  out->push_back(static_cast<char>((v >> 24) & 0xFF));
  out->push_back(static_cast<char>((v >> 16) & 0xFF));
  out->push_back(static_cast<char>((v >> 8) & 0xFF));
  out->push_back(static_cast<char>(v & 0xFF));
}

// A chunk: length, type, data, CRC-32 of type and data (PNG spec §5.3).
void AppendChunk(std::string* out, std::string_view type, std::string_view data) {
  if (data.size() > 0x7FFFFFFFu) {
    throw std::invalid_argument("EncodePng: image too large for one PNG chunk");
  }
  AppendU32(out, static_cast<uint32_t>(data.size()));
  const size_t start = out->size();
  out->append(type);
  out->append(data);
  uLong crc = crc32(0L, Z_NULL, 0);
  crc = crc32(crc, reinterpret_cast<const Bytef*>(out->data() + start),
              static_cast<uInt>(out->size() - start));
  AppendU32(out, static_cast<uint32_t>(crc));
}

// Paeth predictor (PNG spec §9.4).
uint8_t Paeth(int a, int b, int c) {
  const int p = a + b - c;
  const int pa = std::abs(p - a);
  const int pb = std::abs(p - b);
  const int pc = std::abs(p - c);
  if (pa <= pb && pa <= pc) return static_cast<uint8_t>(a);
  if (pb <= pc) return static_cast<uint8_t>(b);
  return static_cast<uint8_t>(c);
}

// Writes the filter-type byte and filtered bytes of one row into `out` (1 + row.size() bytes).
// `prev` is the previous unfiltered row (all zero for the first row).
void FilterRow(int type, const uint8_t* row, const uint8_t* prev, size_t n, uint8_t* out) {
  out[0] = static_cast<uint8_t>(type);
  for (size_t i = 0; i < n; ++i) {
    const int x = row[i];
    const int a = i >= kBytesPerPixel ? row[i - kBytesPerPixel] : 0;
    const int b = prev[i];
    const int c = i >= kBytesPerPixel ? prev[i - kBytesPerPixel] : 0;
    int predicted = 0;
    switch (type) {
      case 0:
        break;
      case 1:
        predicted = a;
        break;
      case 2:
        predicted = b;
        break;
      case 3:
        predicted = (a + b) / 2;
        break;
      default:
        predicted = Paeth(a, b, c);
        break;
    }
    out[i + 1] = static_cast<uint8_t>((x - predicted) & 0xFF);
  }
}

// Sum of the filtered bytes read as signed values, the heuristic of PNG spec §12.8.
uint64_t SignedSum(const uint8_t* filtered, size_t n) {
  uint64_t sum = 0;
  for (size_t i = 0; i < n; ++i) {
    const int v = filtered[i + 1];
    sum += static_cast<uint64_t>(v < 128 ? v : 256 - v);
  }
  return sum;
}

}  // namespace

std::string EncodePng(const Image& image) {
  if (image.width < 1 || image.height < 1) {
    throw std::invalid_argument("EncodePng: width and height must be >= 1 (got " +
                                std::to_string(image.width) + "x" + std::to_string(image.height) +
                                ")");
  }
  const size_t row_bytes = static_cast<size_t>(image.width) * kBytesPerPixel;
  const size_t height = static_cast<size_t>(image.height);
  if (image.rgb.size() / row_bytes != height || image.rgb.size() % row_bytes != 0) {
    throw std::invalid_argument("EncodePng: rgb holds " + std::to_string(image.rgb.size()) +
                                " bytes, expected 3 * " + std::to_string(image.width) + " * " +
                                std::to_string(image.height));
  }

  // Filter each row with the type that minimises the heuristic; ties go to the lower type.
  const size_t stride = row_bytes + 1;
  std::vector<uint8_t> filtered(stride * height);
  std::vector<uint8_t> zero_row(row_bytes, 0);
  std::vector<uint8_t> candidate(stride);
  for (size_t y = 0; y < height; ++y) {
    const uint8_t* row = image.rgb.data() + y * row_bytes;
    const uint8_t* prev = y > 0 ? row - row_bytes : zero_row.data();
    uint8_t* best = filtered.data() + y * stride;
    FilterRow(0, row, prev, row_bytes, best);
    uint64_t best_sum = SignedSum(best, row_bytes);
    for (int type = 1; type <= 4; ++type) {
      FilterRow(type, row, prev, row_bytes, candidate.data());
      const uint64_t sum = SignedSum(candidate.data(), row_bytes);
      if (sum < best_sum) {
        best_sum = sum;
        std::copy(candidate.begin(), candidate.end(), best);
      }
    }
  }

  uLongf compressed_size = compressBound(static_cast<uLong>(filtered.size()));
  std::string compressed(compressed_size, '\0');
  const int rc = compress2(reinterpret_cast<Bytef*>(compressed.data()), &compressed_size,
                           filtered.data(), static_cast<uLong>(filtered.size()), kZlibLevel);
  if (rc != Z_OK) {
    throw std::runtime_error("EncodePng: zlib compress2 failed with code " + std::to_string(rc));
  }
  compressed.resize(compressed_size);

  std::string png("\x89PNG\r\n\x1a\n", 8);
  std::string ihdr;
  AppendU32(&ihdr, static_cast<uint32_t>(image.width));
  AppendU32(&ihdr, static_cast<uint32_t>(image.height));
  ihdr.push_back(8);  // bit depth
  ihdr.push_back(2);  // colour type: truecolour
  ihdr.push_back(0);  // compression method: deflate
  ihdr.push_back(0);  // filter method: adaptive, five types
  ihdr.push_back(0);  // no interlace
  AppendChunk(&png, "IHDR", ihdr);
  AppendChunk(&png, "IDAT", compressed);
  AppendChunk(&png, "IEND", {});
  return png;
}

}  // namespace somasim::render
