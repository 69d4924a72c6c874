// The legacy VTK reader's attribute data: POINT_DATA and CELL_DATA sections (SCALARS, VECTORS,
// FIELD arrays...) and METADATA blocks. Nothing in them is kept; their sizes are checked so that a
// truncated or miscounted section is refused rather than misread.
#include <algorithm>
#include <cstdint>
#include <string>
#include <string_view>

#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtk_legacy_reader.h"

namespace somasim::mesh_io::vtk_legacy_internal {

// METADATA (VTK 8+) follows an array: COMPONENT_NAMES and INFORMATION lines, ended by an empty
// line. Nothing in it matters for the mesh; a missing end means a truncated file.
void LegacyReader::SkipMetadata(const KeywordLine& kw) {
  ExpectArgs(kw, 0, 0, "METADATA");
  for (;;) {
    const std::string_view line = in_.Line("a METADATA block (it ends with an empty line)");
    if (std::all_of(line.begin(), line.end(), IsSpace)) return;
  }
}

void LegacyReader::SkipField(const KeywordLine& kw, int64_t tuples) {
  ExpectArgs(kw, 2, 2, "FIELD <name> <array count>");
  const int64_t arrays = ArgInt(kw, 1, "array count");
  CheckCount(arrays, 8, 8, "FIELD arrays", kw.where);
  for (int64_t a = 0; a < arrays; ++a) {
    KeywordLine array = NextKeyword("FIELD array");
    if (array.keyword == "METADATA") {
      SkipMetadata(array);
      --a;
      continue;
    }
    if (array.keyword == "NULL_ARRAY") continue;
    const std::string name(in_.text().substr(array.offset, array.keyword.size()));
    array.keyword = "FIELD array " + QuoteToken(name);
    ExpectArgs(array, 3, 3, "<name> <components> <tuples> <data type>");
    const int64_t components = ArgInt(array, 0, "number of components");
    const int64_t n = ArgInt(array, 1, "number of tuples");
    const Scalar type = ArgType(array, 2);
    if (components < 1 || components > (int64_t{1} << 20)) {
      Fail(MeshErrorKind::kCount, array.where,
           array.keyword + " has " + std::to_string(components) + " components");
    }
    if (tuples >= 0 && n != tuples) {
      Fail(MeshErrorKind::kCount, array.where,
           array.keyword + " has " + std::to_string(n) + " tuples but its section has " +
               std::to_string(tuples));
    }
    CheckCount(n, components, components, "tuples of " + array.keyword, array.where);
    last_block_.section = array.keyword;
    last_block_.detail = std::to_string(n) + " tuples of " + std::string(array.args[2]);
    SkipValues(type, n * components, "values of " + array.keyword, array);
  }
}

void LegacyReader::ReadAttributes(KeywordLine kw) {
  const int64_t num_points = static_cast<int64_t>(coords_.size() / 3);
  const int64_t num_cells = polydata_
                                ? verts_.count() + lines_.count() + polys_.count() + strips_.count()
                                : cells_.count();
  bool seen_point_data = false, seen_cell_data = false;
  int64_t n = 0;
  for (;;) {
    const std::string& k = kw.keyword;
    const auto type_at = [&](size_t i) {
      last_block_.section = k;
      last_block_.detail = std::to_string(n) + " values of " + std::string(kw.args[i]);
      return ArgType(kw, i);
    };
    if (k == "POINT_DATA" || k == "CELL_DATA") {
      ExpectArgs(kw, 1, 1, k + " <count>");
      const bool points = k == "POINT_DATA";
      bool& seen = points ? seen_point_data : seen_cell_data;
      if (seen) Fail(MeshErrorKind::kSyntax, kw.where, "a second " + k + " section");
      seen = true;
      n = ArgInt(kw, 0, "count");
      const int64_t expected = points ? num_points : num_cells;
      if (n != expected) {
        Fail(MeshErrorKind::kCount, kw.where,
             k + " says " + std::to_string(n) + " but the dataset has " + std::to_string(expected) +
                 (points ? " points" : " cells"));
      }
    } else if (k == "SCALARS") {
      ExpectArgs(kw, 2, 3, "SCALARS <name> <data type> [<components>]");
      const Scalar type = type_at(1);
      const int64_t components = kw.args.size() == 3 ? ArgInt(kw, 2, "number of components") : 1;
      if (components < 1 || components > 4) {
        Fail(MeshErrorKind::kCount, kw.where,
             "SCALARS must have 1 to 4 components, not " + std::to_string(components));
      }
      if (PeekKeyword("LOOKUP_TABLE")) {
        const KeywordLine table = NextKeyword("LOOKUP_TABLE");
        ExpectArgs(table, 1, 1, "LOOKUP_TABLE <name>");
      }
      SkipValues(type, n * components, "SCALARS values", kw);
    } else if (k == "COLOR_SCALARS") {
      ExpectArgs(kw, 2, 2, "COLOR_SCALARS <name> <components>");
      const int64_t components = ArgInt(kw, 1, "number of components");
      if (components < 1 || components > 4) {
        Fail(MeshErrorKind::kCount, kw.where,
             "COLOR_SCALARS must have 1 to 4 components, not " + std::to_string(components));
      }
      last_block_.section = k;
      last_block_.detail = std::to_string(n) + " colours";
      SkipValues(binary_ ? Scalar::kUInt8 : Scalar::kFloat32, n * components,
                 "COLOR_SCALARS values", kw);
    } else if (k == "LOOKUP_TABLE") {
      ExpectArgs(kw, 2, 2, "LOOKUP_TABLE <name> <size>");
      const int64_t size = ArgInt(kw, 1, "table size");
      CheckCount(size, 8, 4, "LOOKUP_TABLE colours", kw.where);
      last_block_.section = k;
      last_block_.detail = std::to_string(size) + " colours";
      SkipValues(binary_ ? Scalar::kUInt8 : Scalar::kFloat32, 4 * size, "LOOKUP_TABLE values", kw);
    } else if (k == "VECTORS" || k == "NORMALS") {
      ExpectArgs(kw, 2, 2, k + " <name> <data type>");
      SkipValues(type_at(1), 3 * n, k + " values", kw);
    } else if (k == "TEXTURE_COORDINATES") {
      ExpectArgs(kw, 3, 3, "TEXTURE_COORDINATES <name> <dimension> <data type>");
      const int64_t dim = ArgInt(kw, 1, "dimension");
      if (dim < 1 || dim > 3) {
        Fail(MeshErrorKind::kCount, kw.where,
             "TEXTURE_COORDINATES must have dimension 1 to 3, not " + std::to_string(dim));
      }
      SkipValues(type_at(2), dim * n, "TEXTURE_COORDINATES values", kw);
    } else if (k == "TENSORS" || k == "TENSORS6") {
      ExpectArgs(kw, 2, 2, k + " <name> <data type>");
      SkipValues(type_at(1), (k == "TENSORS" ? 9 : 6) * n, k + " values", kw);
    } else if (k == "GLOBAL_IDS" || k == "PEDIGREE_IDS" || k == "EDGE_FLAGS") {
      ExpectArgs(kw, 2, 2, k + " <name> <data type>");
      SkipValues(type_at(1), n, k + " values", kw);
    } else if (k == "FIELD") {
      SkipField(kw, n);
    } else if (k == "METADATA") {
      SkipMetadata(kw);
    } else {
      UnknownKeyword(kw,
                     "an attribute: SCALARS, COLOR_SCALARS, LOOKUP_TABLE, VECTORS, NORMALS, "
                     "TEXTURE_COORDINATES, TENSORS, FIELD, POINT_DATA or CELL_DATA; geometry "
                     "sections must come before POINT_DATA and CELL_DATA");
    }
    if (in_.AtEnd()) return;
    kw = NextKeyword("attribute keyword");
  }
}

}  // namespace somasim::mesh_io::vtk_legacy_internal
