// VTK XML unstructured grid (.vtu): DataArrays in ascii, inline base64 binary, or appended data
// (raw or base64), either byte order, UInt32 or UInt64 block headers, optionally zlib-compressed.
#pragma once

#include <string>
#include <string_view>

#include "common/mesh_io/mesh_data.h"

namespace somasim::mesh_io {

enum class VtuEncoding { kAscii, kBase64, kAppendedRaw };

struct VtuWriteOptions {
  VtuEncoding encoding = VtuEncoding::kAscii;
  bool big_endian = false;  // byte_order of binary data
};

MeshData ReadVtu(std::string_view bytes, const std::string& file_name,
                 const ReadOptions& options);
std::string WriteVtu(const MeshData& mesh, const VtuWriteOptions& options);

}  // namespace somasim::mesh_io
