// Base64 (RFC 4648, standard alphabet with '=' padding), as used by VTK XML files.
#pragma once

#include <cstddef>
#include <string>
#include <string_view>

namespace somasim::mesh_io {

// Encodes bytes, padding the last group with '='.
std::string Base64Encode(std::string_view bytes);
void AppendBase64(std::string* out, std::string_view bytes);

// Decodes base64 text in pieces, skipping whitespace. Padded groups may occur in the middle of
// the text: VTK writes the header and the data of a compressed array as two separately padded
// base64 strings one after the other, so the decoder treats the text as a concatenation of
// such strings.
class Base64Decoder {
 public:
  explicit Base64Decoder(std::string_view text) : text_(text) {}

  // Appends exactly n decoded bytes to *out. Returns false (and sets error()) when the text
  // ends first or holds a character that is not base64.
  bool Read(size_t n, std::string* out);
  // True when only whitespace remains (and no decoded byte is pending).
  bool AtEnd();
  // Characters of the text consumed so far (to locate errors).
  size_t position() const { return pos_; }
  const std::string& error() const { return error_; }

 private:
  bool DecodeGroup();

  std::string_view text_;
  size_t pos_ = 0;
  unsigned char pending_[3] = {0, 0, 0};
  size_t pending_size_ = 0;
  size_t pending_pos_ = 0;
  std::string error_;
};

// Decodes the whole text (whitespace ignored). Returns false and sets *error on bad input.
bool Base64Decode(std::string_view text, std::string* out, std::string* error);

}  // namespace somasim::mesh_io
