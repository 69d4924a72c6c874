// The one error type of mesh input/output: names the file, where in it, and the fault.
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>

#include "common/app/exit_codes.h"

namespace somasim::mesh_io {

// Where in a file a fault is. Text formats give a 1-based line; binary ones a byte offset.
struct SourceLocation {
  int64_t line = 0;   // 1-based; 0 = unknown
  int64_t byte = -1;  // 0-based offset; -1 = unknown
  static SourceLocation Line(int64_t l) { return {l, -1}; }
  static SourceLocation Byte(int64_t b) { return {0, b}; }
};

// Kinds of fault, so that callers (and tests) can tell them apart without parsing messages.
enum class MeshErrorKind {
  kIo,           // cannot open, read or write the file
  kSyntax,       // malformed text or binary layout, truncation, unknown section or keyword
  kCount,        // counts that disagree with the data, absurd sizes
  kIndex,        // node index out of range, duplicated id
  kValue,        // NaN/Inf coordinate
  kElement,      // inverted or degenerate element
  kUnsupported,  // a valid file using a feature somasim does not read
};

const char* MeshErrorKindName(MeshErrorKind kind);

class MeshError : public std::runtime_error {
 public:
  MeshError(MeshErrorKind kind, std::string file, SourceLocation where, std::string fault);

  MeshErrorKind kind() const { return kind_; }
  const std::string& file() const { return file_; }
  const SourceLocation& where() const { return where_; }
  const std::string& fault() const { return fault_; }

 private:
  MeshErrorKind kind_;
  std::string file_;
  SourceLocation where_;
  std::string fault_;
};

// The exit code a program ends with on this error (common/app/exit_codes.h): kExitIo when the
// file could not be read or written, kExitBadInput when it was refused.
inline int ExitCodeOf(const MeshError& e) {
  return e.kind() == MeshErrorKind::kIo ? app::kExitIo : app::kExitBadInput;
}

}  // namespace somasim::mesh_io
