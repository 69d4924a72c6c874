#include "common/mesh_io/mesh_error.h"

#include <utility>

namespace somasim::mesh_io {
namespace {

std::string Compose(const std::string& file, const SourceLocation& where,
                    const std::string& fault) {
  std::string text = file;
  if (where.line > 0) {
    text += ":" + std::to_string(where.line);
  } else if (where.byte >= 0) {
    text += ": byte " + std::to_string(where.byte);
  }
  text += ": " + fault;
  return text;
}

}  // namespace

const char* MeshErrorKindName(MeshErrorKind kind) {
  switch (kind) {
    case MeshErrorKind::kIo:
      return "io";
    case MeshErrorKind::kSyntax:
      return "syntax";
    case MeshErrorKind::kCount:
      return "count";
    case MeshErrorKind::kIndex:
      return "index";
    case MeshErrorKind::kValue:
      return "value";
    case MeshErrorKind::kElement:
      return "element";
    case MeshErrorKind::kUnsupported:
      return "unsupported";
  }
  return "unknown";
}

MeshError::MeshError(MeshErrorKind kind, std::string file, SourceLocation where, std::string fault)
    : std::runtime_error(Compose(file, where, fault)),
      kind_(kind),
      file_(std::move(file)),
      where_(where),
      fault_(std::move(fault)) {}

}  // namespace somasim::mesh_io
