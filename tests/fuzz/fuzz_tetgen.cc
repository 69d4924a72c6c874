// libFuzzer target for the TetGen reader. The input holds the .node, .ele and .face contents
// separated by NUL bytes (missing parts = absent files).
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "common/mesh_io/mesh_error.h"
#include "common/mesh_io/tetgen_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  std::string_view rest(reinterpret_cast<const char*>(data), size);
  somasim::mesh_io::TetGenInput input;
  input.node_name = "fuzz.node";
  input.ele_name = "fuzz.ele";
  input.face_name = "fuzz.face";
  size_t cut = rest.find('\0');
  input.node = rest.substr(0, cut);
  if (cut != std::string_view::npos) {
    rest.remove_prefix(cut + 1);
    cut = rest.find('\0');
    input.ele = rest.substr(0, cut);
    if (cut != std::string_view::npos) input.face = rest.substr(cut + 1);
  }
  try {
    somasim::mesh_io::ReadTetGen(input, {});
  } catch (const somasim::mesh_io::MeshError&) {
  }
  return 0;
}
