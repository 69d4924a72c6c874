// The VTU reader's pieces: the arrays of a <Piece> inspected and checked against its
// NumberOfPoints and NumberOfCells (every disagreement reported at once, before anything large
// is decoded), its attribute data checked, then its points and cells added to the mesh.
#include <cstdint>
#include <optional>
#include <pugixml.hpp>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtk_legacy_io.h"  // VtkCellType
#include "common/mesh_io/vtu_reader.h"

namespace somasim::mesh_io::vtu_internal {

// Where value #index of an array is: its line for ASCII, its byte for uncompressed binary data,
// the start of the array's data for compressed data (whose bytes cannot be pointed at).
SourceLocation VtuReader::ValueLocation(const ArrayRef& a, const std::vector<int64_t>& lines,
                                        size_t index) const {
  if (a.format == Format::kAscii) {
    return index < lines.size() ? SourceLocation::Line(lines[index]) : a.where;
  }
  if (a.compressed) return ByteAt(a.data_offset);
  const uint64_t byte = a.header_bytes + index * static_cast<uint64_t>(a.type.bytes);
  return ByteAt(a.data_offset + static_cast<size_t>(a.base64 ? byte / 3 * 4 : byte));
}

// Point and cell data are not kept, but they must be well-formed and of the right length.
void VtuReader::CheckAttributeArrays(const pugi::xml_node& data, int64_t tuples, const char* what) {
  CheckChildren(data, {"DataArray", "Array"});
  for (const pugi::xml_node& node : data.children()) {
    if (node.type() != pugi::node_element) continue;
    const ArrayRef a = Inspect(node);
    const int64_t n = a.tuples.value_or(tuples);
    if (tuples >= 0 && a.tuples && *a.tuples != tuples) {
      Fail(MeshErrorKind::kCount, a.where,
           a.label + " in <" + what + "> has NumberOfTuples " + std::to_string(*a.tuples) +
               " but the piece has " + std::to_string(tuples));
    }
    if (n >= 0 && a.type.scalar != Scalar::kOther &&
        (a.value_count % a.components != 0 || a.value_count / a.components != n)) {
      Fail(MeshErrorKind::kCount, a.where,
           a.label + " in <" + what + "> holds " + std::to_string(a.value_count) +
               " values; expected " + std::to_string(n) + " tuples of " +
               std::to_string(a.components) + " components");
    }
    Decode(a, false);
  }
}

void VtuReader::ReadPiece(const pugi::xml_node& piece, int piece_index, MeshBuilder* builder) {
  PieceCounts counts;
  counts.piece_index = piece_index;
  counts.where = NodeLine(piece);
  counts.num_points = CountAttribute(piece, "NumberOfPoints", true, 0);
  counts.num_cells = CountAttribute(piece, "NumberOfCells", true, 0);
  CheckChildren(piece, {"PointData", "CellData", "Points", "Cells"});
  const pugi::xml_node points = OnlyChild(piece, "Points");
  const pugi::xml_node cells = OnlyChild(piece, "Cells");
  if (!points && counts.num_points > 0) {
    Fail(MeshErrorKind::kSyntax, counts.where,
         "<Piece> has NumberOfPoints=" + std::to_string(counts.num_points) + " but no <Points>");
  }
  if (!cells && counts.num_cells > 0) {
    Fail(MeshErrorKind::kSyntax, counts.where,
         "<Piece> has NumberOfCells=" + std::to_string(counts.num_cells) + " but no <Cells>");
  }

  // Inspect the arrays first: their lengths are known without decoding, so every count that
  // disagrees with the data can be reported at once, before anything large is allocated.
  PieceArrays arrays;
  if (points) arrays.pts = InspectPoints(points);
  if (cells) InspectCells(cells, &arrays);
  Values offsets;
  std::vector<int64_t> offset_lines;
  CheckPieceCounts(arrays, counts, &offsets, &offset_lines);

  for (const pugi::xml_node& node : piece.children("PointData")) {
    CheckAttributeArrays(node, counts.num_points, "PointData");
  }
  for (const pugi::xml_node& node : piece.children("CellData")) {
    CheckAttributeArrays(node, counts.num_cells, "CellData");
  }

  const int64_t base = builder->num_nodes();
  if (arrays.pts) AddPoints(*arrays.pts, counts.num_points, builder);
  if (!cells) return;
  AddCells(arrays, counts, offsets.ints, offset_lines, base, builder);
}

// The piece's only child element called `name` (a null node when there is none).
pugi::xml_node VtuReader::OnlyChild(const pugi::xml_node& piece, const char* name) const {
  pugi::xml_node found;
  for (const pugi::xml_node& child : piece.children(name)) {
    if (found) {
      Fail(MeshErrorKind::kSyntax, NodeLine(child),
           std::string("a second <") + name + "> in the same <Piece>");
    }
    found = child;
  }
  return found;
}

// The one DataArray of <Points>: numbers, 3 components.
ArrayRef VtuReader::InspectPoints(const pugi::xml_node& points) {
  std::optional<ArrayRef> pts;
  CheckChildren(points, {"DataArray"});
  for (const pugi::xml_node& node : points.children("DataArray")) {
    if (pts) Fail(MeshErrorKind::kSyntax, NodeLine(node), "<Points> has more than one DataArray");
    pts = Inspect(node);
  }
  if (!pts) Fail(MeshErrorKind::kSyntax, NodeLine(points), "<Points> has no DataArray");
  if (pts->type.scalar == Scalar::kOther) {
    Fail(MeshErrorKind::kSyntax, pts->where,
         "the Points " + pts->label + " has type " + pts->type_name + "; points need numbers");
  }
  if (pts->components != 3) {
    Fail(MeshErrorKind::kCount, pts->where,
         "the Points " + pts->label + " has NumberOfComponents=" + std::to_string(pts->components) +
             "; points need 3");
  }
  return std::move(*pts);
}

// The connectivity, offsets and types arrays of <Cells> (each once, all three present);
// polyhedron face arrays are decoded to be checked, then dropped.
void VtuReader::InspectCells(const pugi::xml_node& cells, PieceArrays* arrays) {
  CheckChildren(cells, {"DataArray"});
  for (const pugi::xml_node& node : cells.children("DataArray")) {
    const std::string_view name = node.attribute("Name").as_string("");
    std::optional<ArrayRef>* slot = name == "connectivity" ? &arrays->conn
                                    : name == "offsets"    ? &arrays->offs
                                    : name == "types"      ? &arrays->types
                                                           : nullptr;
    if (slot == nullptr) {
      // Polyhedron faces (VTK_POLYHEDRON cells are skipped, but their arrays checked).
      if (name == "faces" || name == "faceoffsets" || name == "face_connectivity" ||
          name == "face_offsets" || name == "polyhedron_to_faces" || name == "polyhedron_offsets") {
        Decode(Inspect(node), false);
        continue;
      }
      Fail(MeshErrorKind::kSyntax, NodeLine(node),
           "unknown DataArray " + QuoteToken(name) +
               " in <Cells> (expected connectivity, offsets and types)");
    }
    if (*slot) {
      Fail(MeshErrorKind::kSyntax, NodeLine(node),
           "a second DataArray " + QuoteToken(name) + " in <Cells>");
    }
    *slot = Inspect(node);
  }
  for (const auto& [slot, name] :
       {std::pair{&arrays->conn, "connectivity"}, std::pair{&arrays->offs, "offsets"},
        std::pair{&arrays->types, "types"}}) {
    if (!*slot) {
      Fail(MeshErrorKind::kSyntax, NodeLine(cells),
           std::string("<Cells> has no DataArray named '") + name + "'");
    }
  }
}

// Every count of the piece that disagrees with its arrays' lengths, reported at once. The
// offsets are decoded here (their last one is the connectivity's length) and handed back.
void VtuReader::CheckPieceCounts(const PieceArrays& arrays, const PieceCounts& counts,
                                 Values* offsets, std::vector<int64_t>* offset_lines) {
  const std::optional<ArrayRef>& pts = arrays.pts;
  const std::optional<ArrayRef>& conn = arrays.conn;
  const std::optional<ArrayRef>& offs = arrays.offs;
  const std::optional<ArrayRef>& types = arrays.types;
  const int64_t num_points = counts.num_points;
  const int64_t num_cells = counts.num_cells;
  std::vector<std::string> problems;
  if (pts && pts->value_count != 3 * num_points) {
    problems.push_back("NumberOfPoints is " + std::to_string(num_points) +
                       " but the Points array (line " + std::to_string(pts->where.line) +
                       ") holds " + std::to_string(pts->value_count) + " values (" +
                       (pts->value_count % 3 == 0
                            ? std::to_string(pts->value_count / 3) + " points)"
                            : "not a whole number of points)"));
  }
  if (offs && offs->value_count != num_cells) {
    problems.push_back("NumberOfCells is " + std::to_string(num_cells) +
                       " but the offsets array (line " + std::to_string(offs->where.line) +
                       ") has " + std::to_string(offs->value_count) + " entries");
  }
  if (types && types->value_count != num_cells) {
    problems.push_back("NumberOfCells is " + std::to_string(num_cells) +
                       " but the types array (line " + std::to_string(types->where.line) +
                       ") has " + std::to_string(types->value_count) + " entries");
  }
  if (offs) {
    *offsets = DecodeIndices(*offs, offset_lines);
    const int64_t last = offsets->ints.empty() ? 0 : offsets->ints.back();
    if (conn && conn->value_count != last) {
      problems.push_back("the last offset is " + std::to_string(last) +
                         " but the connectivity array (line " + std::to_string(conn->where.line) +
                         ") has " + std::to_string(conn->value_count) + " entries");
    }
  }
  if (!problems.empty()) {
    std::string fault =
        "Piece #" + std::to_string(counts.piece_index + 1) + " disagrees with its data: ";
    for (size_t i = 0; i < problems.size(); ++i) fault += (i > 0 ? "; " : "") + problems[i];
    Fail(MeshErrorKind::kCount, counts.where, fault);
  }
}

// An index array (offsets, types, connectivity) as integers; for ASCII data also the line of
// each value. A non-integral type fails, naming it.
Values VtuReader::DecodeIndices(const ArrayRef& a, std::vector<int64_t>* lines) {
  if (a.format != Format::kAscii) return Decode(a, true);
  if (!IsIntegral(a.type.scalar)) Decode(a, true);  // fails naming the type
  Values values;
  DecodeAscii(a, true, &values, lines);
  return values;
}

void VtuReader::AddPoints(const ArrayRef& pts, int64_t num_points, MeshBuilder* builder) {
  std::vector<int64_t> lines;
  Values p;
  if (pts.format == Format::kAscii) {
    p.reals.reserve(static_cast<size_t>(pts.value_count));
    DecodeAscii(pts, false, &p, &lines);
  } else {
    p = Decode(pts, false);
  }
  for (size_t i = 0; i < static_cast<size_t>(num_points); ++i) {
    builder->AddNode(p.reals[3 * i], p.reals[3 * i + 1], p.reals[3 * i + 2],
                     ValueLocation(pts, lines, 3 * i));
  }
}

// The piece's triangles and tetrahedra (other cell types counted as skipped); point ids are the
// piece's, shifted by `base`, the nodes of the pieces before it.
void VtuReader::AddCells(const PieceArrays& arrays, const PieceCounts& counts,
                         const std::vector<int64_t>& ends, const std::vector<int64_t>& offset_lines,
                         int64_t base, MeshBuilder* builder) {
  const ArrayRef& offs = *arrays.offs;
  const ArrayRef& types = *arrays.types;
  const ArrayRef& conn = *arrays.conn;
  int64_t previous = 0;
  for (size_t c = 0; c < ends.size(); ++c) {
    if (ends[c] < previous) {
      Fail(MeshErrorKind::kCount, ValueLocation(offs, offset_lines, c),
           "offsets must not decrease, but offset #" + std::to_string(c + 1) + " is " +
               std::to_string(ends[c]) + " after " + std::to_string(previous));
    }
    previous = ends[c];
  }
  std::vector<int64_t> type_lines;
  const Values type_values = DecodeIndices(types, &type_lines);
  std::vector<int64_t> conn_lines;
  const Values connectivity = DecodeIndices(conn, &conn_lines);
  const std::vector<int64_t>& ids = connectivity.ints;
  const int64_t num_points = counts.num_points;
  for (size_t c = 0; c < static_cast<size_t>(counts.num_cells); ++c) {
    const int64_t start = c == 0 ? 0 : ends[c - 1];
    const int64_t count = ends[c] - start;
    const int64_t type = type_values.ints[c];
    const SourceLocation where = count > 0
                                     ? ValueLocation(conn, conn_lines, static_cast<size_t>(start))
                                     : ValueLocation(types, type_lines, c);
    const VtkCellTypeInfo info = VtkCellType(type);
    if (info.name == nullptr) {
      Fail(MeshErrorKind::kSyntax, ValueLocation(types, type_lines, c),
           "cell #" + std::to_string(c + 1) + " has unknown VTK cell type " + std::to_string(type));
    }
    if (info.num_points >= 0 && count != info.num_points) {
      Fail(MeshErrorKind::kCount, where,
           "cell #" + std::to_string(c + 1) + " is a " + info.name + " but has " +
               std::to_string(count) + " points instead of " + std::to_string(info.num_points));
    }
    if (type != kVtkTriangle && type != kVtkTetra) {
      builder->Skip(info.name);
      continue;
    }
    int64_t v[4] = {0, 0, 0, 0};
    for (int64_t k = 0; k < count; ++k) {
      const int64_t id = ids[static_cast<size_t>(start + k)];
      if (id < 0 || id >= num_points) {
        Fail(MeshErrorKind::kIndex, where,
             "cell #" + std::to_string(c + 1) + " of piece #" +
                 std::to_string(counts.piece_index + 1) + " refers to point " + std::to_string(id) +
                 " but the piece has " + std::to_string(num_points) + " points");
      }
      v[k] = id + base;
    }
    if (type == kVtkTriangle) {
      builder->AddTriangle(v[0], v[1], v[2], where);
    } else {
      builder->AddTetrahedron(v[0], v[1], v[2], v[3], where);
    }
  }
}

}  // namespace somasim::mesh_io::vtu_internal
