#include "common/mesh_io/base64.h"

#include "common/mesh_io/text_reader.h"  // IsSpace

namespace somasim::mesh_io {
namespace {

constexpr char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

// 0..63 for a base64 digit, -1 otherwise.
int DigitValue(char c) {
  if (c >= 'A' && c <= 'Z') return c - 'A';
  if (c >= 'a' && c <= 'z') return c - 'a' + 26;
  if (c >= '0' && c <= '9') return c - '0' + 52;
  if (c == '+') return 62;
  if (c == '/') return 63;
  return -1;
}

std::string Shown(char c) {
  const auto u = static_cast<unsigned char>(c);
  if (u >= 0x20 && u < 0x7f) return std::string("'") + c + "'";
  static constexpr char kHex[] = "0123456789ABCDEF";
  return std::string("byte 0x") + kHex[u >> 4] + kHex[u & 15];
}

}  // namespace

void AppendBase64(std::string* out, std::string_view bytes) {
  out->reserve(out->size() + (bytes.size() + 2) / 3 * 4);
  size_t i = 0;
  for (; i + 3 <= bytes.size(); i += 3) {
    const uint32_t v = (static_cast<uint32_t>(static_cast<unsigned char>(bytes[i])) << 16) |
                       (static_cast<uint32_t>(static_cast<unsigned char>(bytes[i + 1])) << 8) |
                       static_cast<uint32_t>(static_cast<unsigned char>(bytes[i + 2]));
    out->push_back(kAlphabet[(v >> 18) & 63]);
    out->push_back(kAlphabet[(v >> 12) & 63]);
    out->push_back(kAlphabet[(v >> 6) & 63]);
    out->push_back(kAlphabet[v & 63]);
  }
  const size_t left = bytes.size() - i;
  if (left == 0) return;
  uint32_t v = static_cast<uint32_t>(static_cast<unsigned char>(bytes[i])) << 16;
  if (left == 2) v |= static_cast<uint32_t>(static_cast<unsigned char>(bytes[i + 1])) << 8;
  out->push_back(kAlphabet[(v >> 18) & 63]);
  out->push_back(kAlphabet[(v >> 12) & 63]);
  out->push_back(left == 2 ? kAlphabet[(v >> 6) & 63] : '=');
  out->push_back('=');
}

std::string Base64Encode(std::string_view bytes) {
  std::string out;
  AppendBase64(&out, bytes);
  return out;
}

bool Base64Decoder::DecodeGroup() {
  int digits[4];
  int count = 0;    // characters of the group seen (digits and padding)
  int padding = 0;  // '=' among them
  while (count < 4) {
    while (pos_ < text_.size() && IsSpace(text_[pos_])) ++pos_;
    if (pos_ >= text_.size()) {
      error_ = count == 0 ? "the base64 data ends early"
                          : "the base64 data ends inside a group of 4 characters";
      return false;
    }
    const char c = text_[pos_];
    if (c == '=') {
      // Padding may only fill the last one or two places of a group.
      if (count < 2) {
        error_ = "misplaced '=' in base64 data";
        return false;
      }
      ++padding;
    } else {
      const int d = DigitValue(c);
      if (d < 0 || padding > 0) {
        error_ = d < 0 ? Shown(c) + " is not a base64 character" : "misplaced '=' in base64 data";
        return false;
      }
      digits[count] = d;
    }
    ++pos_;
    ++count;
  }
  for (int k = 4 - padding; k < 4; ++k) digits[k] = 0;
  const uint32_t v = (static_cast<uint32_t>(digits[0]) << 18) |
                     (static_cast<uint32_t>(digits[1]) << 12) |
                     (static_cast<uint32_t>(digits[2]) << 6) | static_cast<uint32_t>(digits[3]);
  pending_[0] = static_cast<unsigned char>(v >> 16);
  pending_[1] = static_cast<unsigned char>((v >> 8) & 0xff);
  pending_[2] = static_cast<unsigned char>(v & 0xff);
  pending_size_ = static_cast<size_t>(3 - padding);
  pending_pos_ = 0;
  return true;
}

bool Base64Decoder::Read(size_t n, std::string* out) {
  while (n > 0) {
    if (pending_pos_ == pending_size_) {
      if (!DecodeGroup()) return false;
      continue;
    }
    out->push_back(static_cast<char>(pending_[pending_pos_++]));
    --n;
  }
  return true;
}

bool Base64Decoder::AtEnd() {
  if (pending_pos_ != pending_size_) return false;
  while (pos_ < text_.size() && IsSpace(text_[pos_])) ++pos_;
  return pos_ >= text_.size();
}

bool Base64Decode(std::string_view text, std::string* out, std::string* error) {
  Base64Decoder decoder(text);
  out->reserve(out->size() + text.size() / 4 * 3);
  while (!decoder.AtEnd()) {
    if (!decoder.Read(1, out)) {
      *error = decoder.error();
      return false;
    }
  }
  return true;
}

}  // namespace somasim::mesh_io
