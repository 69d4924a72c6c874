// EncodePng: structure (signature, chunk order, lengths, CRCs, IHDR fields) and a pixel-exact
// round trip through an independent decoder written here (zlib inflate + the five PNG filters).
#include "common/render/png_encoder.h"

#include <gtest/gtest.h>
#include <zlib.h>

#include <cstdint>
#include <random>
#include <set>
#include <stdexcept>
#include <string>
#include <vector>

namespace somasim::render {
namespace {

uint32_t ReadU32(const std::string& s, size_t at) {
  return (uint32_t{static_cast<uint8_t>(s[at])} << 24) |
         (uint32_t{static_cast<uint8_t>(s[at + 1])} << 16) |
         (uint32_t{static_cast<uint8_t>(s[at + 2])} << 8) |
         uint32_t{static_cast<uint8_t>(s[at + 3])};
}

struct Chunk {
  std::string type;
  std::string data;
};

// Splits a PNG into chunks, failing the test on a bad signature, a chunk running past the end
// or a CRC mismatch.
std::vector<Chunk> ParseChunks(const std::string& png) {
  std::vector<Chunk> chunks;
  if (png.compare(0, 8, std::string("\x89PNG\r\n\x1a\n", 8)) != 0) {
    ADD_FAILURE() << "bad signature";
    return chunks;
  }
  size_t at = 8;
  while (at < png.size()) {
    if (png.size() - at < 12) {
      ADD_FAILURE() << "truncated chunk header at byte " << at;
      return chunks;
    }
    const uint32_t length = ReadU32(png, at);
    if (length > 0x7FFFFFFFu || png.size() - at - 12 < length) {
      ADD_FAILURE() << "chunk at byte " << at << " runs past the end";
      return chunks;
    }
    Chunk c{png.substr(at + 4, 4), png.substr(at + 8, length)};
    uLong crc = crc32(0L, Z_NULL, 0);
    crc = crc32(crc, reinterpret_cast<const Bytef*>(png.data() + at + 4), length + 4);
    EXPECT_EQ(ReadU32(png, at + 8 + length), static_cast<uint32_t>(crc)) << "CRC of " << c.type;
    chunks.push_back(std::move(c));
    at += 12 + length;
  }
  return chunks;
}

struct Decoded {
  Image image;
  std::set<int> filters_used;
};

int Paeth(int a, int b, int c) {
  const int p = a + b - c, pa = std::abs(p - a), pb = std::abs(p - b), pc = std::abs(p - c);
  return (pa <= pb && pa <= pc) ? a : (pb <= pc ? b : c);
}

// Decodes an 8-bit RGB non-interlaced PNG, checking its structure on the way.
Decoded DecodePng(const std::string& png) {
  Decoded out;
  const std::vector<Chunk> chunks = ParseChunks(png);
  if (chunks.size() < 3) {
    ADD_FAILURE() << "fewer than 3 chunks";
    return out;
  }
  EXPECT_EQ(chunks.front().type, "IHDR");
  EXPECT_EQ(chunks.back().type, "IEND");
  EXPECT_TRUE(chunks.back().data.empty());
  const std::string& ihdr = chunks.front().data;
  if (ihdr.size() != 13) {
    ADD_FAILURE() << "IHDR of " << ihdr.size() << " bytes";
    return out;
  }
  out.image.width = static_cast<int>(ReadU32(ihdr, 0));
  out.image.height = static_cast<int>(ReadU32(ihdr, 4));
  EXPECT_EQ(ihdr[8], 8) << "bit depth";
  EXPECT_EQ(ihdr[9], 2) << "colour type";
  EXPECT_EQ(ihdr[10], 0) << "compression";
  EXPECT_EQ(ihdr[11], 0) << "filter method";
  EXPECT_EQ(ihdr[12], 0) << "interlace";
  std::string idat;
  bool seen_idat = false, idat_ended = false;
  for (size_t i = 1; i + 1 < chunks.size(); ++i) {
    if (chunks[i].type == "IDAT") {
      EXPECT_FALSE(idat_ended) << "IDAT chunks must be consecutive";
      idat += chunks[i].data;
      seen_idat = true;
    } else {
      idat_ended = seen_idat;
      EXPECT_FALSE(chunks[i].type == "IHDR" || chunks[i].type == "IEND")
          << "repeated " << chunks[i].type;
    }
  }
  EXPECT_TRUE(seen_idat);

  const size_t row_bytes = 3 * static_cast<size_t>(out.image.width);
  const size_t h = static_cast<size_t>(out.image.height);
  std::vector<uint8_t> raw(h * (row_bytes + 1) + 1);  // one spare byte detects excess data
  uLongf raw_size = static_cast<uLongf>(raw.size());
  const int rc = uncompress(raw.data(), &raw_size, reinterpret_cast<const Bytef*>(idat.data()),
                            static_cast<uLong>(idat.size()));
  EXPECT_EQ(rc, Z_OK);
  EXPECT_EQ(raw_size, h * (row_bytes + 1)) << "inflated size";
  if (rc != Z_OK || raw_size != h * (row_bytes + 1)) return out;

  out.image.rgb.assign(h * row_bytes, 0);
  for (size_t y = 0; y < h; ++y) {
    const uint8_t* in = raw.data() + y * (row_bytes + 1);
    const int filter = in[0];
    out.filters_used.insert(filter);
    EXPECT_LE(filter, 4) << "row " << y;
    uint8_t* row = out.image.rgb.data() + y * row_bytes;
    const uint8_t* prev = y > 0 ? row - row_bytes : nullptr;
    for (size_t i = 0; i < row_bytes; ++i) {
      const int a = i >= 3 ? row[i - 3] : 0;
      const int b = prev != nullptr ? prev[i] : 0;
      const int c = (prev != nullptr && i >= 3) ? prev[i - 3] : 0;
      const int predictor = filter == 1   ? a
                            : filter == 2 ? b
                            : filter == 3 ? (a + b) / 2
                            : filter == 4 ? Paeth(a, b, c)
                                          : 0;
      row[i] = static_cast<uint8_t>((in[i + 1] + predictor) & 0xFF);
    }
  }
  return out;
}

// A test picture mixing smooth gradients (which favour Sub/Up/Average/Paeth), flat areas and
// seeded noise (which favours None).
Image TestImage(int width, int height, uint32_t seed) {
  Image image{width, height, std::vector<uint8_t>(3 * static_cast<size_t>(width * height))};
  std::mt19937 rng(seed);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      for (int c = 0; c < 3; ++c) {
        uint8_t v = 0;
        if (y < height / 3) {
          v = static_cast<uint8_t>((x * 7 + y * 3 + c * 50) & 0xFF);
        } else if (y < 2 * height / 3) {
          v = static_cast<uint8_t>(200 + c);
        } else {
          v = static_cast<uint8_t>(rng() & 0xFF);
        }
        image.rgb[image.Index(x, y, c)] = v;
      }
    }
  }
  return image;
}

TEST(PngEncoder, DecodesToTheSamePixels) {
  for (const auto& [w, h] : std::vector<std::pair<int, int>>{
           {1, 1}, {1, 7}, {7, 1}, {2, 2}, {13, 9}, {64, 48}, {301, 5}}) {
    const Image image = TestImage(w, h, static_cast<uint32_t>(w * 1000 + h));
    const Decoded decoded = DecodePng(EncodePng(image));
    EXPECT_EQ(decoded.image.width, w);
    EXPECT_EQ(decoded.image.height, h);
    EXPECT_EQ(decoded.image.rgb, image.rgb) << w << "x" << h;
  }
}

TEST(PngEncoder, ChoosesPredictingFiltersForSmoothRows) {
  // Round-tripping only proves the decoder's filters if the encoder used them.
  const Decoded decoded = DecodePng(EncodePng(TestImage(64, 48, 1)));
  EXPECT_GE(decoded.filters_used.size(), 2u);
  EXPECT_TRUE(decoded.filters_used.count(0) == 1) << "noise rows are cheapest unfiltered";
}

TEST(PngEncoder, HasSignatureIhdrIdatIendWithValidCrcs) {
  const std::string png = EncodePng(TestImage(5, 4, 2));
  const std::vector<Chunk> chunks = ParseChunks(png);
  ASSERT_EQ(chunks.size(), 3u);
  EXPECT_EQ(chunks[0].type, "IHDR");
  EXPECT_EQ(chunks[1].type, "IDAT");
  EXPECT_EQ(chunks[2].type, "IEND");
  EXPECT_EQ(ReadU32(chunks[0].data, 0), 5u);
  EXPECT_EQ(ReadU32(chunks[0].data, 4), 4u);
}

TEST(PngEncoder, IsDeterministic) {
  const Image image = TestImage(40, 30, 3);
  EXPECT_EQ(EncodePng(image), EncodePng(image));
}

TEST(PngEncoder, RefusesInconsistentImagesNamingTheProblem) {
  const auto message = [](const Image& image) -> std::string {
    try {
      EncodePng(image);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "no exception";
  };
  EXPECT_NE(message(Image{0, 1, {}}).find("width and height"), std::string::npos);
  EXPECT_NE(message(Image{1, -3, {}}).find("width and height"), std::string::npos);
  EXPECT_NE(message(Image{2, 2, std::vector<uint8_t>(11)}).find("rgb holds 11 bytes"),
            std::string::npos);
  EXPECT_NE(message(Image{2, 2, std::vector<uint8_t>(13)}).find("rgb holds 13 bytes"),
            std::string::npos);
}

}  // namespace
}  // namespace somasim::render
