#include "common/mesh_io/byte_reader.h"

#include <charconv>

namespace somasim::mesh_io {

void ByteReader::Require(size_t n, std::string_view what) const {
  if (n > remaining()) {
    Fail(MeshErrorKind::kSyntax, "unexpected end of data while reading " + std::string(what) +
                                     ": need " + std::to_string(n) + " bytes, " +
                                     std::to_string(remaining()) + " remain (truncated file?)");
  }
}

void ByteReader::CheckCount(int64_t count, int64_t bytes_each, std::string_view what) const {
  if (count < 0) {
    Fail(MeshErrorKind::kCount,
         "negative count of " + std::string(what) + ": " + std::to_string(count));
  }
  const int64_t left = static_cast<int64_t>(remaining());
  if (bytes_each > 0 && count > left / bytes_each) {
    Fail(MeshErrorKind::kCount, "the file claims " + std::to_string(count) + " " +
                                    std::string(what) + " but only " + std::to_string(left) +
                                    " bytes remain (truncated file or wrong count)");
  }
}

std::string_view ByteReader::Bytes(size_t n, std::string_view what) {
  Require(n, what);
  std::string_view out = bytes_.substr(pos_, n);
  pos_ += n;
  return out;
}

void ByteReader::Fail(MeshErrorKind kind, const std::string& fault) const {
  throw MeshError(kind, file_name_, SourceLocation::Byte(file_offset()), fault);
}

std::string FormatDouble(double value) {
  char buffer[32];
  auto [ptr, ec] = std::to_chars(buffer, buffer + sizeof(buffer), value);
  return std::string(buffer, ptr);
}

void AppendDouble(std::string* out, double value) {
  char buffer[32];
  auto [ptr, ec] = std::to_chars(buffer, buffer + sizeof(buffer), value);
  out->append(buffer, ptr);
}

}  // namespace somasim::mesh_io
