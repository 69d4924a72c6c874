#include "common/mesh_io/text_reader.h"

#include <charconv>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <string>

namespace somasim::mesh_io {

bool IsSpace(char c) {
  return c == ' ' || c == '\t' || c == '\n' || c == '\r' || c == '\v' || c == '\f';
}

void SplitTokens(std::string_view text, std::vector<std::string_view>* tokens) {
  size_t i = 0;
  while (i < text.size()) {
    while (i < text.size() && IsSpace(text[i])) ++i;
    const size_t start = i;
    while (i < text.size() && !IsSpace(text[i])) ++i;
    if (i > start) tokens->push_back(text.substr(start, i - start));
  }
}

std::string QuoteToken(std::string_view token) {
  constexpr size_t kMax = 40;
  std::string shown(token.substr(0, kMax));
  for (char& c : shown) {
    if (static_cast<unsigned char>(c) < 0x20 || static_cast<unsigned char>(c) >= 0x7f) c = '?';
  }
  if (token.size() > kMax) shown += "...";
  return "'" + shown + "'";
}

bool ParseInt64(std::string_view token, int64_t* value) {
  if (!token.empty() && token.front() == '+') token.remove_prefix(1);
  if (token.empty()) return false;
  const char* end = token.data() + token.size();
  auto [ptr, ec] = std::from_chars(token.data(), end, *value);
  return ec == std::errc() && ptr == end;
}

bool ParseDouble(std::string_view token, double* value) {
  if (!token.empty() && token.front() == '+') token.remove_prefix(1);
  if (token.empty()) return false;
  const char* end = token.data() + token.size();
  auto [ptr, ec] = std::from_chars(token.data(), end, *value, std::chars_format::general);
  if (ec == std::errc::result_out_of_range) {
    // from_chars leaves the value untouched on overflow/underflow; strtod gives ±inf or a
    // denormal/zero, so the caller can name a non-finite value precisely.
    if (ptr != end) return false;
    const std::string copy(token);
    *value = std::strtod(copy.c_str(), nullptr);
    return true;
  }
  return ec == std::errc() && ptr == end;
}

TextReader::TextReader(std::string_view text, std::string file_name)
    : text_(text), file_name_(std::move(file_name)) {}

void TextReader::SkipSpace() {
  while (pos_ < text_.size() && IsSpace(text_[pos_])) {
    if (text_[pos_] == '\n') ++line_;
    ++pos_;
  }
}

bool TextReader::AtEnd() {
  SkipSpace();
  return pos_ >= text_.size();
}

std::optional<std::string_view> TextReader::TryToken() {
  SkipSpace();
  if (pos_ >= text_.size()) return std::nullopt;
  const size_t start = pos_;
  while (pos_ < text_.size() && !IsSpace(text_[pos_])) ++pos_;
  token_line_ = line_;
  return text_.substr(start, pos_ - start);
}

std::string_view TextReader::Token(std::string_view what) {
  std::optional<std::string_view> token = TryToken();
  if (!token) {
    token_line_ = line_;
    Fail(MeshErrorKind::kSyntax,
         "unexpected end of file while reading " + std::string(what) + " (truncated file?)");
  }
  return *token;
}

int64_t TextReader::Int(std::string_view what) { return IntOf(Token(what), what); }

int64_t TextReader::IntOf(std::string_view token, std::string_view what,
                          SourceLocation where) const {
  int64_t value = 0;
  if (!ParseInt64(token, &value)) {
    FailAt(MeshErrorKind::kSyntax, where,
           "expected an integer for " + std::string(what) + ", found " + QuoteToken(token));
  }
  return value;
}

int64_t TextReader::IntInRange(std::string_view what, int64_t lo, int64_t hi) {
  const int64_t value = Int(what);
  if (value < lo || value > hi) {
    Fail(MeshErrorKind::kCount, std::string(what) + " is " + std::to_string(value) + ", outside " +
                                    std::to_string(lo) + ".." + std::to_string(hi));
  }
  return value;
}

double TextReader::Double(std::string_view what) { return DoubleOf(Token(what), what); }

double TextReader::DoubleOf(std::string_view token, std::string_view what,
                            SourceLocation where) const {
  double value = 0.0;
  if (!ParseDouble(token, &value)) {
    FailAt(MeshErrorKind::kSyntax, where,
           "expected a number for " + std::string(what) + ", found " + QuoteToken(token));
  }
  return value;
}

std::optional<std::string_view> TextReader::TryLine() {
  if (pos_ >= text_.size()) return std::nullopt;
  const size_t start = pos_;
  size_t end = text_.find('\n', pos_);
  token_line_ = line_;
  if (end == std::string_view::npos) {
    pos_ = text_.size();
    end = text_.size();
  } else {
    pos_ = end + 1;
    ++line_;
  }
  std::string_view line = text_.substr(start, end - start);
  if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
  return line;
}

std::string_view TextReader::Line(std::string_view what) {
  std::optional<std::string_view> line = TryLine();
  if (!line) {
    token_line_ = line_;
    Fail(MeshErrorKind::kSyntax,
         "unexpected end of file while reading " + std::string(what) + " (truncated file?)");
  }
  return *line;
}

void TextReader::EndOfLine(std::string_view what) {
  while (pos_ < text_.size() && text_[pos_] != '\n') {
    if (!IsSpace(text_[pos_])) {
      token_line_ = line_;
      const size_t start = pos_;
      while (pos_ < text_.size() && !IsSpace(text_[pos_])) ++pos_;
      Fail(MeshErrorKind::kSyntax, "unexpected " + QuoteToken(text_.substr(start, pos_ - start)) +
                                       " after " + std::string(what));
    }
    ++pos_;
  }
  if (pos_ < text_.size()) {
    ++pos_;
    ++line_;
  }
}

void TextReader::CheckCount(int64_t count, int64_t min_bytes_each, std::string_view what) const {
  if (count < 0) {
    Fail(MeshErrorKind::kCount,
         "negative count of " + std::string(what) + ": " + std::to_string(count));
  }
  const int64_t left = static_cast<int64_t>(remaining());
  if (min_bytes_each > 0 && count > left / min_bytes_each) {
    Fail(MeshErrorKind::kCount, "the file claims " + std::to_string(count) + " " +
                                    std::string(what) + " but only " + std::to_string(left) +
                                    " bytes remain (truncated file or wrong count)");
  }
}

void TextReader::Skip(size_t n) {
  const size_t end = std::min(text_.size(), pos_ + n);
  for (size_t i = pos_; i < end; ++i) {
    if (text_[i] == '\n') ++line_;
  }
  pos_ = end;
}

void TextReader::Fail(MeshErrorKind kind, const std::string& fault) const {
  throw MeshError(kind, file_name_, SourceLocation::Line(token_line_), fault);
}

void TextReader::FailAt(MeshErrorKind kind, SourceLocation where, const std::string& fault) const {
  throw MeshError(kind, file_name_, where, fault);
}

}  // namespace somasim::mesh_io
