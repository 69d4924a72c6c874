// Tokeniser over a whole text file held in memory, tracking line numbers for error messages.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/mesh_error.h"

namespace somasim::mesh_io {

// Whitespace as the text readers see it: ' ', '\t', '\n', '\r', '\v' and '\f' (those of the
// C locale, independent of the locale actually set).
bool IsSpace(char c);

// Appends the whitespace-separated tokens of `text` to `tokens`, as views into `text`.
void SplitTokens(std::string_view text, std::vector<std::string_view>* tokens);

// Strict number parsing: the whole token must be the number (a leading '+' is accepted).
// ParseDouble accepts "nan"/"inf" so that callers can name the non-finite value precisely.
bool ParseInt64(std::string_view token, int64_t* value);
bool ParseDouble(std::string_view token, double* value);

// A token shown in an error message: quoted, at most 40 characters, control and non-ASCII
// bytes replaced by '?' (so binary garbage cannot garble a terminal).
std::string QuoteToken(std::string_view token);

class TextReader {
 public:
  TextReader(std::string_view text, std::string file_name);

  // True when only whitespace remains.
  bool AtEnd();
  // Next whitespace-separated token (newlines count as whitespace). Fails at end of input,
  // naming `what` ("unexpected end of file while reading <what>").
  std::string_view Token(std::string_view what);
  std::optional<std::string_view> TryToken();
  // A token parsed as a number; fails naming `what` when it is not one.
  int64_t Int(std::string_view what);
  double Double(std::string_view what);
  // Int() that must lie in [lo, hi].
  int64_t IntInRange(std::string_view what, int64_t lo, int64_t hi);
  // A token already taken from this reader (e.g. out of a Line()) parsed as a number; fails
  // naming `what` as Int() and Double() do, at the last token's line or at `where`.
  int64_t IntOf(std::string_view token, std::string_view what) const {
    return IntOf(token, what, token_location());
  }
  int64_t IntOf(std::string_view token, std::string_view what, SourceLocation where) const;
  double DoubleOf(std::string_view token, std::string_view what) const {
    return DoubleOf(token, what, token_location());
  }
  double DoubleOf(std::string_view token, std::string_view what, SourceLocation where) const;

  // The rest of the current line (without "\n" or "\r\n"); advances to the next line.
  // Fails at end of input.
  std::string_view Line(std::string_view what);
  std::optional<std::string_view> TryLine();
  // Skips whitespace up to and including the next newline (fails if a token is on the way).
  void EndOfLine(std::string_view what);

  // Count check before any allocation: `count` items of at least `min_bytes_each` bytes must
  // fit in what remains of the input. Fails with kCount otherwise (also for count < 0).
  void CheckCount(int64_t count, int64_t min_bytes_each, std::string_view what) const;

  // Moves forward over n raw bytes (e.g. a binary block inside a text format).
  void Skip(size_t n);

  size_t offset() const { return pos_; }
  size_t size() const { return text_.size(); }
  size_t remaining() const { return text_.size() - pos_; }
  std::string_view rest() const { return text_.substr(pos_); }
  std::string_view text() const { return text_; }
  const std::string& file_name() const { return file_name_; }
  // Line of the next unread character, and of the last token or line returned.
  int64_t line() const { return line_; }
  SourceLocation token_location() const { return SourceLocation::Line(token_line_); }

  // Throws MeshError at the last token's line.
  [[noreturn]] void Fail(MeshErrorKind kind, const std::string& fault) const;
  [[noreturn]] void FailAt(MeshErrorKind kind, SourceLocation where,
                           const std::string& fault) const;

 private:
  void SkipSpace();

  std::string_view text_;
  std::string file_name_;
  size_t pos_ = 0;
  int64_t line_ = 1;
  int64_t token_line_ = 1;
};

}  // namespace somasim::mesh_io
