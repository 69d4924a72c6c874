// The legacy VTK reader's structure: the header lines, the geometry sections (POINTS, the cell
// arrays of POLYDATA and UNSTRUCTURED_GRID, CELL_TYPES), the explanation of a binary block whose
// count does not match its data, and the mesh built once the whole file has been parsed.
#include "common/mesh_io/vtk_legacy_reader.h"

#include <algorithm>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"
#include "common/mesh_io/vtk_legacy_io.h"

namespace somasim::mesh_io {
namespace vtk_legacy_internal {

KeywordLine LegacyReader::NextKeyword(std::string_view what) {
  KeywordLine kw;
  const std::string_view token = in_.Token(what);
  kw.offset = in_.offset() - token.size();
  kw.where = At(kw.offset);
  kw.keyword = Upper(token);
  const std::optional<std::string_view> rest = in_.TryLine();
  if (rest) SplitTokens(*rest, &kw.args);
  return kw;
}

void LegacyReader::ExpectArgs(const KeywordLine& kw, size_t min, size_t max,
                              std::string_view usage) const {
  if (kw.args.size() < min || kw.args.size() > max) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         kw.keyword + " line has " + std::to_string(kw.args.size()) + " arguments; expected '" +
             std::string(usage) + "'");
  }
}

int64_t LegacyReader::ArgInt(const KeywordLine& kw, size_t i, std::string_view what) const {
  int64_t value = 0;
  if (!ParseInt64(kw.args[i], &value)) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         "expected an integer for " + std::string(what) + " on the " + kw.keyword +
             " line, found " + QuoteToken(kw.args[i]));
  }
  if (value < 0) {
    Fail(MeshErrorKind::kCount, kw.where,
         kw.keyword + " gives a negative " + std::string(what) + ": " + std::to_string(value));
  }
  return value;
}

Scalar LegacyReader::ArgType(const KeywordLine& kw, size_t i) const {
  const std::optional<Scalar> type = ParseScalar(kw.args[i]);
  if (!type) {
    if (Upper(kw.args[i]) == "VARIANT") {
      Fail(MeshErrorKind::kUnsupported, kw.where,
           "arrays of type 'variant' are not supported (" + kw.keyword + ")");
    }
    Fail(MeshErrorKind::kSyntax, kw.where,
         "unknown data type " + QuoteToken(kw.args[i]) + " on the " + kw.keyword + " line");
  }
  return *type;
}

bool LegacyReader::PeekKeyword(std::string_view upper) {
  const std::string_view rest = in_.rest();
  size_t i = 0;
  // In BINARY files the bytes right after a keyword line are data: do not skip them as spaces.
  if (!binary_) {
    while (i < rest.size() && IsSpace(rest[i])) ++i;
  }
  if (rest.size() - i < upper.size()) return false;
  for (size_t k = 0; k < upper.size(); ++k) {
    if (ToUpper(rest[i + k]) != upper[k]) return false;
  }
  return i + upper.size() == rest.size() || IsSpace(rest[i + upper.size()]);
}

void LegacyReader::UnknownKeyword(const KeywordLine& kw, std::string_view expected) const {
  if (binary_ && last_block_.valid) {
    const size_t end = last_block_.begin + last_block_.bytes;
    bool right_after = kw.offset >= end;
    for (size_t i = end; right_after && i < kw.offset; ++i) {
      right_after = IsSpace(in_.text()[i]);
    }
    if (right_after) ExplainBinaryMismatch(kw);
  }
  Fail(MeshErrorKind::kSyntax, kw.where,
       "unknown keyword " + QuoteToken(kw.keyword) + " (expected " + std::string(expected) + ")");
}

// A keyword was expected right after a block of binary data but something else is there: the
// count before the block does not match the data. Finds where the next section really starts,
// and whether the data was mangled into text (backslash escapes of bytes), to say exactly what
// is wrong.
void LegacyReader::ExplainBinaryMismatch(const KeywordLine& kw) const {
  const std::string_view text = in_.text();
  const BinaryBlock& block = last_block_;
  size_t next = std::string_view::npos;
  std::string next_keyword;
  for (const char* k : kSectionKeywords) {
    for (const char* sep : {" ", "\n", "\r\n"}) {
      const std::string needle = "\n" + std::string(k) + sep;
      const size_t pos = text.find(needle, block.begin);
      if (pos != std::string_view::npos && pos < next) {
        next = pos;
        next_keyword = k;
      }
    }
  }
  const size_t scan_end = next == std::string_view::npos ? text.size() : next;
  int64_t escapes = 0;
  std::string example;
  const auto is_hex = [](char c) {
    return (c >= '0' && c <= '9') || (c >= 'A' && c <= 'F') || (c >= 'a' && c <= 'f');
  };
  for (size_t i = block.begin; i + 2 < scan_end; ++i) {
    if (text[i] == '\\' && is_hex(text[i + 1]) && is_hex(text[i + 2])) {
      if (example.empty()) example = std::string(text.substr(i, 3));
      ++escapes;
      i += 2;
    }
  }
  std::string fault = block.section + " declares " + block.detail + ", i.e. " +
                      std::to_string(block.bytes) + " bytes of binary data, but ";
  if (next != std::string_view::npos) {
    fault += "the next section (" + next_keyword + " at byte " + std::to_string(next + 1) +
             ") begins " + std::to_string(next - block.begin) +
             " bytes after the data starts: the count in " + block.section +
             " does not match the data";
  } else {
    fault += "what follows those bytes is " + QuoteToken(kw.keyword) +
             ", not a section keyword: the count in " + block.section + " does not match the data";
  }
  if (escapes > 0) {
    fault += "; the binary data is also corrupt: it contains " + std::to_string(escapes) +
             " backslash escapes such as '" + example +
             "' (binary bytes rewritten as text, e.g. by an editor or a text-mode copy)";
  }
  Fail(MeshErrorKind::kCount, SourceLocation::Byte(static_cast<int64_t>(block.keyword_offset)),
       fault);
}

void LegacyReader::ReadPoints(const KeywordLine& kw) {
  ExpectArgs(kw, 2, 2, "POINTS <count> <data type>");
  if (have_points_) Fail(MeshErrorKind::kSyntax, kw.where, "a second POINTS section");
  have_points_ = true;
  const int64_t n = ArgInt(kw, 0, "point count");
  const Scalar type = ArgType(kw, 1);
  if (type == Scalar::kBit || type == Scalar::kString) {
    Fail(MeshErrorKind::kSyntax, kw.where,
         "POINTS must have a numeric data type, not " + QuoteToken(kw.args[1]));
  }
  CheckCount(n, 6, 3 * ScalarBytes(type), "points", kw.where);
  last_block_.section = "POINTS";
  last_block_.detail = std::to_string(n) + " points of " + std::string(kw.args[1]);
  std::vector<SourceLocation> where;
  coords_ = ReadValues<double>(type, 3 * n, "point coordinates", kw, &where);
  point_where_.reserve(static_cast<size_t>(n));
  for (size_t i = 0; i < where.size(); i += 3) point_where_.push_back(where[i]);
}

Cells LegacyReader::ReadCells(const KeywordLine& kw) {
  ExpectArgs(kw, 2, 2, kw.keyword + " <cell count> <entry count>");
  const int64_t a = ArgInt(kw, 0, "cell count");
  const int64_t b = ArgInt(kw, 1, "entry count");
  // VTK 5.1 files follow the line with OFFSETS and CONNECTIVITY arrays; older ones with the
  // entries "n id1 .. idn" of each cell.
  Cells cells = PeekKeyword("OFFSETS") ? ReadOffsetCells(kw, a, b) : ReadClassicCells(kw, a, b);
  cells.keyword_where = kw.where;
  return cells;
}

Cells LegacyReader::ReadClassicCells(const KeywordLine& kw, int64_t n, int64_t size) {
  CheckCount(size, 2, 4, kw.keyword + " entries", kw.where);
  if (n > size) {
    Fail(MeshErrorKind::kCount, kw.where,
         kw.keyword + " says " + std::to_string(n) + " cells in " + std::to_string(size) +
             " entries, but every cell takes at least one entry (its point count)");
  }
  last_block_.section = kw.keyword;
  last_block_.detail = std::to_string(size) + " entries of int";
  std::vector<SourceLocation> where;
  const std::vector<int64_t> entries =
      ReadValues<int64_t>(Scalar::kInt32, size, kw.keyword + " entries", kw, &where);
  Cells cells;
  cells.present = true;
  cells.start.reserve(static_cast<size_t>(n) + 1);
  cells.where.reserve(static_cast<size_t>(n));
  cells.conn.reserve(static_cast<size_t>(size - n));
  size_t used = 0;
  for (int64_t i = 0; i < n; ++i) {
    if (used >= entries.size()) {
      Fail(MeshErrorKind::kCount, kw.where,
           kw.keyword + " says " + std::to_string(n) + " cells in " + std::to_string(size) +
               " entries, but the entries run out after " + std::to_string(i) + " cells");
    }
    const int64_t npts = entries[used];
    const SourceLocation at = where[used];
    if (npts < 0) {
      Fail(MeshErrorKind::kCount, at,
           kw.keyword + " cell #" + std::to_string(i + 1) + " has a negative point count (" +
               std::to_string(npts) + ")");
    }
    if (npts > static_cast<int64_t>(entries.size() - used - 1)) {
      Fail(MeshErrorKind::kCount, at,
           kw.keyword + " says " + std::to_string(size) + " entries, but cell #" +
               std::to_string(i + 1) + " (" + std::to_string(npts) +
               " points) runs past them: the entry count or a point count is wrong");
    }
    cells.conn.insert(cells.conn.end(), entries.begin() + static_cast<std::ptrdiff_t>(used) + 1,
                      entries.begin() + static_cast<std::ptrdiff_t>(used) + 1 +
                          static_cast<std::ptrdiff_t>(npts));
    cells.start.push_back(static_cast<int64_t>(cells.conn.size()));
    cells.where.push_back(at);
    used += 1 + static_cast<size_t>(npts);
  }
  if (used != entries.size()) {
    Fail(MeshErrorKind::kCount, kw.where,
         kw.keyword + " says " + std::to_string(size) + " entries but its " + std::to_string(n) +
             " cells use " + std::to_string(used));
  }
  return cells;
}

Cells LegacyReader::ReadOffsetCells(const KeywordLine& kw, int64_t n_offsets, int64_t n_conn) {
  const KeywordLine off = NextKeyword("OFFSETS");
  ExpectArgs(off, 1, 1, "OFFSETS <data type>");
  const Scalar off_type = ArgType(off, 0);
  last_block_.section = "OFFSETS";
  last_block_.detail = std::to_string(n_offsets) + " offsets of " + std::string(off.args[0]);
  std::vector<SourceLocation> where;
  const std::vector<int64_t> offsets =
      ReadValues<int64_t>(off_type, n_offsets, kw.keyword + " offsets", off, &where);
  KeywordLine con = NextKeyword("CONNECTIVITY");
  while (con.keyword == "METADATA") {
    SkipMetadata(con);
    con = NextKeyword("CONNECTIVITY");
  }
  if (con.keyword != "CONNECTIVITY") {
    UnknownKeyword(con, "CONNECTIVITY after the OFFSETS of " + kw.keyword);
  }
  ExpectArgs(con, 1, 1, "CONNECTIVITY <data type>");
  const Scalar con_type = ArgType(con, 0);
  last_block_.section = "CONNECTIVITY";
  last_block_.detail = std::to_string(n_conn) + " indices of " + std::string(con.args[0]);
  Cells cells;
  cells.present = true;
  cells.conn = ReadValues<int64_t>(con_type, n_conn, kw.keyword + " connectivity", con, nullptr);
  if (offsets.empty()) {
    if (n_conn != 0) {
      Fail(MeshErrorKind::kCount, kw.where,
           kw.keyword + " has no offsets but " + std::to_string(n_conn) + " connectivity entries");
    }
    return cells;
  }
  if (offsets[0] != 0) {
    Fail(MeshErrorKind::kCount, where[0],
         kw.keyword + " offsets must start at 0, not " + std::to_string(offsets[0]));
  }
  cells.start.reserve(offsets.size());
  cells.where.reserve(offsets.size() - 1);
  for (size_t i = 1; i < offsets.size(); ++i) {
    if (offsets[i] < offsets[i - 1]) {
      Fail(MeshErrorKind::kCount, where[i],
           kw.keyword + " offset #" + std::to_string(i + 1) + " (" + std::to_string(offsets[i]) +
               ") is smaller than the one before (" + std::to_string(offsets[i - 1]) + ")");
    }
    if (offsets[i] > n_conn) {
      Fail(MeshErrorKind::kCount, where[i],
           kw.keyword + " offset #" + std::to_string(i + 1) + " (" + std::to_string(offsets[i]) +
               ") is past the end of the " + std::to_string(n_conn) + " connectivity entries");
    }
    cells.start.push_back(offsets[i]);
    cells.where.push_back(where[i - 1]);
  }
  if (offsets.back() != n_conn) {
    Fail(MeshErrorKind::kCount, where.back(),
         kw.keyword + " offsets end at " + std::to_string(offsets.back()) + " but " +
             std::to_string(n_conn) + " connectivity entries were given");
  }
  return cells;
}

void LegacyReader::ReadCellTypes(const KeywordLine& kw) {
  ExpectArgs(kw, 1, 1, "CELL_TYPES <count>");
  if (have_types_) Fail(MeshErrorKind::kSyntax, kw.where, "a second CELL_TYPES section");
  have_types_ = true;
  types_keyword_where_ = kw.where;
  const int64_t n = ArgInt(kw, 0, "cell count");
  last_block_.section = "CELL_TYPES";
  last_block_.detail = std::to_string(n) + " cell types of int";
  types_ = ReadValues<int64_t>(Scalar::kInt32, n, "cell types", kw, &type_where_);
}

// Turns what was read into nodes and elements; done once the whole file has been parsed so
// that structural faults (miscounted binary blocks) are reported before value faults that
// misread data would cause.
void LegacyReader::Build(MeshBuilder* builder) {
  const int64_t n = static_cast<int64_t>(coords_.size() / 3);
  for (int64_t i = 0; i < n; ++i) {
    const size_t k = 3 * static_cast<size_t>(i);
    builder->AddNode(coords_[k], coords_[k + 1], coords_[k + 2],
                     point_where_[static_cast<size_t>(i)]);
  }
  if (polydata_) {
    if (verts_.count() > 0) builder->Skip("vertex", verts_.count());
    if (lines_.count() > 0) builder->Skip("line", lines_.count());
    for (size_t c = 0; c < static_cast<size_t>(polys_.count()); ++c) {
      const int64_t* v = polys_.conn.data() + polys_.start[c];
      if (polys_.points(c) == 3) {
        builder->AddTriangle(v[0], v[1], v[2], polys_.where[c]);
      } else {
        builder->Skip("polygon");
      }
    }
    int64_t degenerate = 0;
    for (size_t c = 0; c < static_cast<size_t>(strips_.count()); ++c) {
      const int64_t* v = strips_.conn.data() + strips_.start[c];
      const int64_t m = strips_.points(c);
      if (m < 3) {
        Fail(MeshErrorKind::kCount, strips_.where[c],
             "triangle strip #" + std::to_string(c + 1) + " has " + std::to_string(m) +
                 " points; a strip needs at least 3");
      }
      // VTK's strip convention: triangle i is (i, i+1, i+2) for even i and (i+1, i, i+2) for
      // odd i, so that all triangles have the orientation of the first.
      for (int64_t i = 0; i + 2 < m; ++i) {
        const int64_t a = (i % 2 == 0) ? v[i] : v[i + 1];
        const int64_t b = (i % 2 == 0) ? v[i + 1] : v[i];
        const int64_t c3 = v[i + 2];
        // Strips join and turn with repeated points; those zero-area triangles are not part of
        // the surface.
        if (a == b || b == c3 || a == c3) {
          ++degenerate;
          continue;
        }
        builder->AddTriangle(a, b, c3, strips_.where[c]);
      }
    }
    if (degenerate > 0) builder->Skip("degenerate triangle of a strip", degenerate);
    return;
  }
  if (cells_.present != have_types_) {
    Fail(MeshErrorKind::kSyntax, have_types_ ? types_keyword_where_ : cells_.keyword_where,
         cells_.present ? "UNSTRUCTURED_GRID has CELLS but no CELL_TYPES section"
                        : "UNSTRUCTURED_GRID has CELL_TYPES but no CELLS section");
  }
  if (cells_.count() != static_cast<int64_t>(types_.size())) {
    Fail(MeshErrorKind::kCount, types_keyword_where_,
         "CELL_TYPES lists " + std::to_string(types_.size()) + " types but CELLS has " +
             std::to_string(cells_.count()) + " cells");
  }
  for (size_t c = 0; c < types_.size(); ++c) {
    const int64_t type = types_[c];
    const VtkCellTypeInfo info = VtkCellType(type);
    if (info.name == nullptr) {
      Fail(MeshErrorKind::kSyntax, type_where_[c],
           "cell #" + std::to_string(c + 1) + " has unknown VTK cell type " + std::to_string(type));
    }
    const int64_t m = cells_.points(c);
    if (info.num_points >= 0 && m != info.num_points) {
      Fail(MeshErrorKind::kCount, cells_.where[c],
           "cell #" + std::to_string(c + 1) + " is a " + info.name + " but has " +
               std::to_string(m) + " points instead of " + std::to_string(info.num_points));
    }
    const int64_t* v = cells_.conn.data() + cells_.start[c];
    if (type == kVtkTriangle) {
      builder->AddTriangle(v[0], v[1], v[2], cells_.where[c]);
    } else if (type == kVtkTetra) {
      builder->AddTetrahedron(v[0], v[1], v[2], v[3], cells_.where[c]);
    } else {
      builder->Skip(info.name);
    }
  }
}

MeshData LegacyReader::Read(const ReadOptions& options) {
  const std::string_view header = in_.Line("the header line");
  constexpr std::string_view kMagic = "# VTK DATAFILE VERSION";
  if (header.size() < kMagic.size() || Upper(header.substr(0, kMagic.size())) != kMagic) {
    Fail(MeshErrorKind::kSyntax, SourceLocation::Line(1),
         "not a legacy VTK file: the first line must be '# vtk DataFile Version x.y', found " +
             QuoteToken(header));
  }
  std::vector<std::string_view> version;
  SplitTokens(header.substr(kMagic.size()), &version);
  in_.Line("the title line");
  const KeywordLine encoding = NextKeyword("ASCII or BINARY");
  if (encoding.keyword == "BINARY") {
    binary_ = true;
  } else if (encoding.keyword != "ASCII") {
    Fail(MeshErrorKind::kSyntax, encoding.where,
         "the third line must say ASCII or BINARY, found " + QuoteToken(encoding.keyword));
  }
  ExpectArgs(encoding, 0, 0, encoding.keyword);
  const KeywordLine dataset = NextKeyword("DATASET");
  if (dataset.keyword != "DATASET") {
    Fail(MeshErrorKind::kSyntax, dataset.where,
         "expected 'DATASET <type>' after the " + encoding.keyword + " line, found " +
             QuoteToken(dataset.keyword));
  }
  ExpectArgs(dataset, 1, 1, "DATASET <type>");
  const std::string type = Upper(dataset.args[0]);
  if (type == "POLYDATA") {
    polydata_ = true;
  } else if (type != "UNSTRUCTURED_GRID") {
    if (type == "STRUCTURED_POINTS" || type == "STRUCTURED_GRID" || type == "RECTILINEAR_GRID" ||
        type == "FIELD") {
      Fail(MeshErrorKind::kUnsupported, dataset.where,
           "DATASET " + type +
               " is not supported: only POLYDATA and UNSTRUCTURED_GRID hold "
               "triangles or tetrahedra");
    }
    Fail(MeshErrorKind::kSyntax, dataset.where,
         "unknown DATASET type " + QuoteToken(dataset.args[0]));
  }
  const char* geometry_keywords =
      polydata_ ? "POINTS, VERTICES, LINES, POLYGONS, TRIANGLE_STRIPS, FIELD, POINT_DATA or "
                  "CELL_DATA"
                : "POINTS, CELLS, CELL_TYPES, FIELD, POINT_DATA or CELL_DATA";
  SourceLocation end_of_geometry = dataset.where;
  while (!in_.AtEnd()) {
    const KeywordLine kw = NextKeyword("section keyword");
    const std::string& k = kw.keyword;
    if (k == "POINTS") {
      ReadPoints(kw);
    } else if (k == "METADATA") {
      SkipMetadata(kw);
    } else if (k == "FIELD") {
      SkipField(kw, -1);
    } else if (k == "POINT_DATA" || k == "CELL_DATA") {
      ReadAttributes(kw);
      break;
    } else if (polydata_ &&
               (k == "VERTICES" || k == "LINES" || k == "POLYGONS" || k == "TRIANGLE_STRIPS")) {
      Cells& cells = k == "VERTICES"   ? verts_
                     : k == "LINES"    ? lines_
                     : k == "POLYGONS" ? polys_
                                       : strips_;
      if (cells.present) Fail(MeshErrorKind::kSyntax, kw.where, "a second " + k + " section");
      cells = ReadCells(kw);
    } else if (!polydata_ && k == "CELLS") {
      if (cells_.present) Fail(MeshErrorKind::kSyntax, kw.where, "a second CELLS section");
      cells_ = ReadCells(kw);
    } else if (!polydata_ && k == "CELL_TYPES") {
      ReadCellTypes(kw);
    } else {
      UnknownKeyword(kw, geometry_keywords);
    }
    end_of_geometry = kw.where;
  }
  if (!have_points_) {
    Fail(MeshErrorKind::kSyntax, end_of_geometry,
         "the file has no POINTS section (truncated file?)");
  }
  std::string format = "VTK legacy";
  if (!version.empty()) format += " " + std::string(version[0]);
  format += binary_ ? " BINARY " : " ASCII ";
  format += polydata_ ? "POLYDATA" : "UNSTRUCTURED_GRID";
  MeshBuilder builder(file_name_, format);
  Build(&builder);
  return builder.Finish(options);
}

}  // namespace vtk_legacy_internal

MeshData ReadVtkLegacy(std::string_view bytes, const std::string& file_name,
                       const ReadOptions& options) {
  vtk_legacy_internal::LegacyReader reader(bytes, file_name);
  return reader.Read(options);
}

}  // namespace somasim::mesh_io
