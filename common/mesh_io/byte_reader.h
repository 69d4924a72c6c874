// Bounds-checked reader of binary data with explicit byte order, for binary mesh formats.
#pragma once

#include <bit>
#include <cstdint>
#include <cstring>
#include <string>
#include <string_view>
#include <type_traits>

#include "common/mesh_io/mesh_error.h"

namespace somasim::mesh_io {

enum class Endian { kLittle, kBig };

class ByteReader {
 public:
  // `bytes` is a view into the file; `base_offset` is where it starts in the file, so that
  // errors report file offsets.
  ByteReader(std::string_view bytes, std::string file_name, int64_t base_offset = 0)
      : bytes_(bytes), file_name_(std::move(file_name)), base_(base_offset) {}

  size_t offset() const { return pos_; }
  size_t remaining() const { return bytes_.size() - pos_; }
  int64_t file_offset() const { return base_ + static_cast<int64_t>(pos_); }

  // Fails with a truncation error unless n bytes remain.
  void Require(size_t n, std::string_view what) const;
  // Same as TextReader::CheckCount, for binary data.
  void CheckCount(int64_t count, int64_t bytes_each, std::string_view what) const;

  std::string_view Bytes(size_t n, std::string_view what);

  // Reads one arithmetic value of type T in the given byte order.
  template <typename T>
  T Read(Endian endian, std::string_view what) {
    static_assert(std::is_arithmetic_v<T>);
    Require(sizeof(T), what);
    unsigned char raw[sizeof(T)];
    std::memcpy(raw, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    const bool native_little = std::endian::native == std::endian::little;
    if ((endian == Endian::kLittle) != native_little) {
      for (size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(raw[i], raw[sizeof(T) - 1 - i]);
    }
    T value;
    std::memcpy(&value, raw, sizeof(T));
    return value;
  }

  [[noreturn]] void Fail(MeshErrorKind kind, const std::string& fault) const;

 private:
  std::string_view bytes_;
  std::string file_name_;
  int64_t base_;
  size_t pos_ = 0;
};

// Appends the bytes of value in the given byte order (for binary writers).
template <typename T>
void AppendBinary(std::string* out, T value, Endian endian) {
  static_assert(std::is_arithmetic_v<T>);
  unsigned char raw[sizeof(T)];
  std::memcpy(raw, &value, sizeof(T));
  const bool native_little = std::endian::native == std::endian::little;
  if ((endian == Endian::kLittle) != native_little) {
    for (size_t i = 0; i < sizeof(T) / 2; ++i) std::swap(raw[i], raw[sizeof(T) - 1 - i]);
  }
  out->append(reinterpret_cast<const char*>(raw), sizeof(T));
}

// Shortest decimal text that reads back to exactly the same double (std::to_chars).
std::string FormatDouble(double value);
void AppendDouble(std::string* out, double value);

}  // namespace somasim::mesh_io
