// libFuzzer target for one mesh reader, chosen at compile time (SOMASIM_FUZZ_FORMAT_<fmt>).
// The only acceptable failure is a MeshError; anything else (crash, sanitizer report, another
// exception, a huge allocation) is a bug.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "common/mesh_io/mesh_io.h"

namespace {

#if defined(SOMASIM_FUZZ_FORMAT_obj)
constexpr somasim::mesh_io::FileFormat kFormat = somasim::mesh_io::FileFormat::kObj;
#elif defined(SOMASIM_FUZZ_FORMAT_stl)
constexpr somasim::mesh_io::FileFormat kFormat = somasim::mesh_io::FileFormat::kStl;
#elif defined(SOMASIM_FUZZ_FORMAT_vtk_legacy)
constexpr somasim::mesh_io::FileFormat kFormat = somasim::mesh_io::FileFormat::kVtkLegacy;
#elif defined(SOMASIM_FUZZ_FORMAT_vtu)
constexpr somasim::mesh_io::FileFormat kFormat = somasim::mesh_io::FileFormat::kVtu;
#elif defined(SOMASIM_FUZZ_FORMAT_gmsh)
constexpr somasim::mesh_io::FileFormat kFormat = somasim::mesh_io::FileFormat::kGmsh;
#else
#error "define SOMASIM_FUZZ_FORMAT_<format>"
#endif

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  somasim::mesh_io::ReadOptions options;
  // Exercise both orientation policies from one corpus.
  options.fix_orientation = size > 0 && (data[size - 1] & 1) != 0;
  try {
    somasim::mesh_io::ReadMeshBytes(kFormat, bytes, "fuzz-input", options);
  } catch (const somasim::mesh_io::MeshError&) {
  }
  return 0;
}
