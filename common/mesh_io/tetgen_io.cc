#include "common/mesh_io/tetgen_io.h"

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io {
namespace {

using Tokens = std::vector<std::string_view>;

// One TetGen file read as lines of numbers; '#' starts a comment anywhere, blank lines are
// skipped. Errors name the file and the line.
class TetGenText {
 public:
  TetGenText(std::string_view text, const std::string& name) : reader_(text, name) {}

  // The next line holding data, split into tokens; false at the end of the file.
  bool Next(Tokens* tokens) {
    while (std::optional<std::string_view> line = reader_.TryLine()) {
      line_ = reader_.token_location().line;
      std::string_view text = *line;
      const size_t hash = text.find('#');
      if (hash != std::string_view::npos) text = text.substr(0, hash);
      tokens->clear();
      SplitTokens(text, tokens);
      if (!tokens->empty()) return true;
    }
    line_ = reader_.line();
    return false;
  }

  int64_t line() const { return line_; }
  SourceLocation where() const { return SourceLocation::Line(line_); }
  const std::string& name() const { return reader_.file_name(); }
  void CheckCount(int64_t count, int64_t min_bytes_each, std::string_view what) const {
    reader_.CheckCount(count, min_bytes_each, what);
  }

  [[noreturn]] void Fail(MeshErrorKind kind, const std::string& fault) const {
    reader_.FailAt(kind, where(), fault);
  }

  int64_t Int(std::string_view token, const std::string& what) const {
    return reader_.IntOf(token, what, where());
  }
  double Double(std::string_view token, const std::string& what) const {
    return reader_.DoubleOf(token, what, where());
  }

  // The header line: `min_fields` required numbers, up to `fields.size()` in all (TetGen gives
  // the missing trailing ones their defaults, which `fields` holds on entry).
  void Header(size_t min_fields, const std::vector<std::string>& names,
              std::vector<int64_t>* fields) {
    Tokens tokens;
    std::string layout;
    for (const std::string& n : names) layout += (layout.empty() ? "<" : " <") + n + ">";
    if (!Next(&tokens)) {
      Fail(MeshErrorKind::kSyntax, "empty file: expected the header line '" + layout + "'");
    }
    if (tokens.size() < min_fields || tokens.size() > names.size()) {
      Fail(MeshErrorKind::kSyntax, "the header line has " + std::to_string(tokens.size()) +
                                       " values; expected '" + layout + "'");
    }
    for (size_t i = 0; i < tokens.size(); ++i) (*fields)[i] = Int(tokens[i], names[i]);
  }

  // Checks that the index of the i-th item is base + i, naming a duplicate or a jump.
  void CheckIndex(std::string_view token, const std::string& what, int64_t base, int64_t i,
                  std::vector<int64_t>* lines) {
    const int64_t index = Int(token, what + " index");
    const int64_t expected = base + i;
    if (index != expected) {
      if (index >= base && index < expected) {
        Fail(MeshErrorKind::kIndex,
             what + " index " + std::to_string(index) + " is duplicated (first on line " +
                 std::to_string((*lines)[static_cast<size_t>(index - base)]) + ")");
      }
      Fail(MeshErrorKind::kIndex, what + " index " + std::to_string(index) +
                                      " is out of sequence: expected " + std::to_string(expected) +
                                      " (indices must be consecutive from " + std::to_string(base) +
                                      ")");
    }
    lines->push_back(line_);
  }

  // After the declared number of items: anything but comments is a count mismatch.
  void ExpectEnd(int64_t count, const std::string& what) {
    Tokens tokens;
    if (Next(&tokens)) {
      Fail(MeshErrorKind::kCount,
           "the header says " + std::to_string(count) + " " + what + " but more data follows");
    }
  }
  [[noreturn]] void FailShort(int64_t count, int64_t read, const std::string& what) const {
    reader_.FailAt(MeshErrorKind::kCount, SourceLocation::Line(reader_.line()),
                   "the header says " + std::to_string(count) + " " + what +
                       " but the file ends after " + std::to_string(read) + " (truncated file?)");
  }

 private:
  TextReader reader_;
  int64_t line_ = 0;
};

struct Nodes {
  int64_t base = 0;  // index of the first point: 0 or 1
  int64_t count = 0;
  std::vector<double> coords;  // 3 per point, file unit
};

Nodes ReadNodes(std::string_view text, const std::string& name, MeshBuilder* builder) {
  TetGenText in(text, name);
  std::vector<int64_t> h = {0, 3, 0, 0};
  in.Header(1, {"#points", "dimension", "#attributes", "boundary markers 0|1"}, &h);
  const int64_t count = h[0], dim = h[1], num_attributes = h[2], markers = h[3];
  if (dim != 3) {
    in.Fail(MeshErrorKind::kUnsupported,
            "dimension " + std::to_string(dim) + ": only 3-D TetGen meshes can be read");
  }
  in.CheckCount(num_attributes, 2, "attributes per point");
  if (markers != 0 && markers != 1) {
    in.Fail(MeshErrorKind::kSyntax,
            "the boundary marker flag is " + std::to_string(markers) + "; expected 0 or 1");
  }
  const int64_t fields = 4 + num_attributes + markers;
  // Each field takes at least one byte (and most a separator too): a bound loose enough that a
  // short line is reported as such, tight enough that an absurd count fails before any allocation.
  in.CheckCount(count, fields, "points");

  Nodes nodes;
  nodes.count = count;
  nodes.coords.reserve(3 * static_cast<size_t>(count));
  builder->Reserve(count, 0, 0);
  std::vector<int64_t> lines;
  lines.reserve(static_cast<size_t>(count));
  Tokens tokens;
  for (int64_t i = 0; i < count; ++i) {
    if (!in.Next(&tokens)) in.FailShort(count, i, "points");
    if (static_cast<int64_t>(tokens.size()) != fields) {
      in.Fail(MeshErrorKind::kSyntax,
              "point line has " + std::to_string(tokens.size()) + " values; the header implies " +
                  std::to_string(fields) + " (index, x, y, z, " + std::to_string(num_attributes) +
                  " attributes, " + std::to_string(markers) + " boundary marker)");
    }
    if (i == 0) {
      nodes.base = in.Int(tokens[0], "point index");
      if (nodes.base != 0 && nodes.base != 1) {
        in.Fail(MeshErrorKind::kIndex, "the first point has index " + std::to_string(nodes.base) +
                                           "; TetGen numbers from 0 or 1");
      }
    }
    in.CheckIndex(tokens[0], "point", nodes.base, i, &lines);
    const int64_t label = nodes.base + i;
    double x[3];
    for (int k = 0; k < 3; ++k) {
      x[k] =
          in.Double(tokens[static_cast<size_t>(k) + 1], std::string(1, static_cast<char>('x' + k)) +
                                                            " of point " + std::to_string(label));
    }
    for (int64_t a = 0; a < num_attributes + markers; ++a) {
      in.Double(tokens[static_cast<size_t>(4 + a)],
                "an attribute or marker of point " + std::to_string(label));
    }
    builder->AddNode(x[0], x[1], x[2], in.where(), label);
    nodes.coords.insert(nodes.coords.end(), x, x + 3);
  }
  in.ExpectEnd(count, "points");
  return nodes;
}

// A node reference of an element, converted to a 0-based index after a range check in the
// .node file's numbering.
int64_t NodeRef(const TetGenText& in, std::string_view token, const Nodes& nodes,
                const std::string& element) {
  const int64_t ref = in.Int(token, "a node of " + element);
  if (ref < nodes.base || ref - nodes.base >= nodes.count) {
    in.Fail(MeshErrorKind::kIndex,
            element + " refers to node " + std::to_string(ref) +
                (nodes.count == 0
                     ? std::string(", but the .node file has no points")
                     : ", but the .node file numbers its points " + std::to_string(nodes.base) +
                           ".." + std::to_string(nodes.base + nodes.count - 1)));
  }
  return ref - nodes.base;
}

struct Tets {
  std::vector<int64_t> corners;  // 4 per tetrahedron, 0-based
  bool quadratic = false;        // 10-node tetrahedra
};

Tets ReadTets(std::string_view text, const std::string& name, const Nodes& nodes,
              MeshBuilder* builder) {
  TetGenText in(text, name);
  std::vector<int64_t> h = {0, 4, 0};
  in.Header(1, {"#tetrahedra", "nodes per tetrahedron 4|10", "#region attributes"}, &h);
  const int64_t count = h[0], per_tet = h[1], num_attributes = h[2];
  if (per_tet != 4 && per_tet != 10) {
    in.Fail(MeshErrorKind::kSyntax,
            "nodes per tetrahedron is " + std::to_string(per_tet) + "; expected 4 or 10");
  }
  in.CheckCount(num_attributes, 2, "attributes per tetrahedron");
  const int64_t fields = 1 + per_tet + num_attributes;
  in.CheckCount(count, fields, "tetrahedra");

  Tets tets;
  tets.quadratic = per_tet == 10;
  tets.corners.reserve(4 * static_cast<size_t>(count));
  builder->Reserve(0, 0, count);
  std::vector<int64_t> lines;
  lines.reserve(static_cast<size_t>(count));
  Tokens tokens;
  for (int64_t i = 0; i < count; ++i) {
    if (!in.Next(&tokens)) in.FailShort(count, i, "tetrahedra");
    if (static_cast<int64_t>(tokens.size()) != fields) {
      in.Fail(MeshErrorKind::kSyntax, "tetrahedron line has " + std::to_string(tokens.size()) +
                                          " values; the header implies " + std::to_string(fields) +
                                          " (index, " + std::to_string(per_tet) + " nodes, " +
                                          std::to_string(num_attributes) + " attributes)");
    }
    // Elements are numbered like the points (TetGen's -z numbers everything from 0).
    in.CheckIndex(tokens[0], "tetrahedron", nodes.base, i, &lines);
    const std::string element = "tetrahedron " + std::to_string(nodes.base + i);
    int64_t v[4];
    for (int64_t k = 0; k < per_tet; ++k) {
      const int64_t ref = NodeRef(in, tokens[static_cast<size_t>(1 + k)], nodes, element);
      if (k < 4) v[k] = ref;  // the 6 mid-edge nodes of a 10-node tetrahedron follow the corners
    }
    for (int64_t a = 0; a < num_attributes; ++a) {
      in.Double(tokens[static_cast<size_t>(1 + per_tet + a)], "an attribute of " + element);
    }
    builder->AddTetrahedron(v[0], v[1], v[2], v[3], in.where());
    tets.corners.insert(tets.corners.end(), v, v + 4);
  }
  in.ExpectEnd(count, "tetrahedra");
  return tets;
}

struct Faces {
  std::vector<int64_t> corners;  // 3 per face, 0-based, as in the file
  std::vector<int64_t> lines;
  bool quadratic = false;  // 6-node faces (tetgen -o2)
};

Faces ReadFaces(std::string_view text, const std::string& name, const Nodes& nodes) {
  TetGenText in(text, name);
  std::vector<int64_t> h = {0, 0};
  in.Header(1, {"#faces", "boundary markers 0|1"}, &h);
  const int64_t count = h[0], markers = h[1];
  if (markers != 0 && markers != 1) {
    in.Fail(MeshErrorKind::kSyntax,
            "the boundary marker flag is " + std::to_string(markers) + "; expected 0 or 1");
  }
  in.CheckCount(count, 4 + markers, "faces");

  // Line layout: index, 3 corners, [3 mid-edge nodes (-o2)], [marker], [2 adjacent
  // tetrahedra (-nn)]. The header does not say which optional parts are there; the first line
  // decides and every line must agree.
  Faces faces;
  faces.corners.reserve(3 * static_cast<size_t>(count));
  faces.lines.reserve(static_cast<size_t>(count));
  std::vector<int64_t> index_lines;
  index_lines.reserve(static_cast<size_t>(count));
  int64_t per_face = 3;
  int64_t adjacency = 0;
  int64_t fields = 0;
  Tokens tokens;
  for (int64_t i = 0; i < count; ++i) {
    if (!in.Next(&tokens)) in.FailShort(count, i, "faces");
    const int64_t n = static_cast<int64_t>(tokens.size());
    if (i == 0) {
      const int64_t base = 4 + markers;
      if (n == base + 3 || n == base + 5) per_face = 6;
      if (n == base + 2 || n == base + 5) adjacency = 2;
      fields = 1 + per_face + markers + adjacency;
      if (n != fields) {
        in.Fail(MeshErrorKind::kSyntax,
                "face line has " + std::to_string(n) + " values; expected " + std::to_string(base) +
                    " (index, 3 nodes" + (markers ? ", marker" : "") + "), " +
                    std::to_string(base + 2) + " (and 2 adjacent tetrahedra, tetgen -nn), " +
                    std::to_string(base + 3) + " (6-node faces, tetgen -o2) or " +
                    std::to_string(base + 5) + " (both)");
      }
      faces.quadratic = per_face == 6;
    } else if (n != fields) {
      in.Fail(MeshErrorKind::kSyntax, "face line has " + std::to_string(n) +
                                          " values, but the first face line had " +
                                          std::to_string(fields));
    }
    in.CheckIndex(tokens[0], "face", nodes.base, i, &index_lines);
    const std::string element = "face " + std::to_string(nodes.base + i);
    for (int64_t k = 0; k < per_face; ++k) {
      const int64_t ref = NodeRef(in, tokens[static_cast<size_t>(1 + k)], nodes, element);
      if (k < 3) faces.corners.push_back(ref);
    }
    for (int64_t k = 1 + per_face; k < n; ++k) {
      in.Int(tokens[static_cast<size_t>(k)], "a marker or adjacent tetrahedron of " + element);
    }
    faces.lines.push_back(in.line());
  }
  in.ExpectEnd(count, "faces");
  return faces;
}

// TetGen orients the faces it writes differently by mode (tetgen 1.5.0: inward for a PLC
// mesh, -p; outward on the convex hull of a point set). somasim's triangles face outwards, so a
// face that bounds exactly one tetrahedron is turned to face away from it. Interior faces and
// faces of no tetrahedron keep their order. Returns how many faces were turned.
int64_t OrientBoundaryFacesOutward(const Nodes& nodes, const Tets& tets, Faces* faces) {
  using Key = std::array<int64_t, 3>;
  struct KeyHash {
    size_t operator()(const Key& k) const {
      uint64_t h = 0x9E3779B97F4A7C15ull;
      for (int64_t v : k) {
        h ^= static_cast<uint64_t>(v) + 0x9E3779B97F4A7C15ull + (h << 6) + (h >> 2);
      }
      return static_cast<size_t>(h);
    }
  };
  const auto sorted = [](int64_t a, int64_t b, int64_t c) {
    Key k = {a, b, c};
    std::sort(k.begin(), k.end());
    return k;
  };
  // Faces with the same three corners (written twice, in either order) share a slot.
  struct Slot {
    int hits = 0;           // tetrahedra having this face
    int64_t opposite = -1;  // corner of the (last) such tetrahedron not on the face
  };
  const size_t num_faces = faces->corners.size() / 3;
  std::unordered_map<Key, size_t, KeyHash> slot_of;
  slot_of.reserve(num_faces);
  std::vector<size_t> face_slot(num_faces);
  for (size_t f = 0; f < num_faces; ++f) {
    const int64_t* v = &faces->corners[3 * f];
    face_slot[f] = slot_of.try_emplace(sorted(v[0], v[1], v[2]), slot_of.size()).first->second;
  }
  std::vector<Slot> slots(slot_of.size());
  const size_t num_tets = tets.corners.size() / 4;
  for (size_t t = 0; t < num_tets; ++t) {
    const int64_t* v = &tets.corners[4 * t];
    for (int skip = 0; skip < 4; ++skip) {
      int64_t tri[3];
      int m = 0;
      for (int k = 0; k < 4; ++k) {
        if (k != skip) tri[m++] = v[k];
      }
      const auto it = slot_of.find(sorted(tri[0], tri[1], tri[2]));
      if (it == slot_of.end()) continue;
      ++slots[it->second].hits;
      slots[it->second].opposite = v[skip];
    }
  }
  const auto point = [&](int64_t i) {
    const size_t k = 3 * static_cast<size_t>(i);
    return Eigen::Vector3d(nodes.coords[k], nodes.coords[k + 1], nodes.coords[k + 2]);
  };
  int64_t turned = 0;
  for (size_t f = 0; f < num_faces; ++f) {
    const Slot& slot = slots[face_slot[f]];
    if (slot.hits != 1) continue;
    int64_t* v = &faces->corners[3 * f];
    const Eigen::Vector3d a = point(v[0]);
    const double towards_tet =
        (point(v[1]) - a).cross(point(v[2]) - a).dot(point(slot.opposite) - a);
    if (towards_tet > 0) {
      std::swap(v[1], v[2]);
      ++turned;
    }
  }
  return turned;
}

void AppendIndexLine(std::string* out, int64_t index, const int32_t* v, int n) {
  *out += std::to_string(index);
  for (int k = 0; k < n; ++k) {
    *out += ' ';
    *out += std::to_string(v[k]);
  }
  *out += '\n';
}

}  // namespace

MeshData ReadTetGen(const TetGenInput& input, const ReadOptions& options) {
  // One builder per file, so that the builder's checks name the file the element is in.
  MeshBuilder node_builder(input.node_name, "TetGen");
  const Nodes nodes = ReadNodes(input.node, input.node_name, &node_builder);
  const auto add_nodes = [&](MeshBuilder* b) {
    b->Reserve(nodes.count, 0, 0);
    for (int64_t i = 0; i < nodes.count; ++i) {
      const size_t k = 3 * static_cast<size_t>(i);
      b->AddNode(nodes.coords[k], nodes.coords[k + 1], nodes.coords[k + 2], {});
    }
  };

  Tets tets;
  MeshBuilder ele_builder(input.ele_name, "TetGen");
  if (input.ele) {
    add_nodes(&ele_builder);
    tets = ReadTets(*input.ele, input.ele_name, nodes, &ele_builder);
  }
  Faces faces;
  int64_t turned = 0;
  MeshBuilder face_builder(input.face_name, "TetGen");
  if (input.face) {
    faces = ReadFaces(*input.face, input.face_name, nodes);
    turned = OrientBoundaryFacesOutward(nodes, tets, &faces);
    add_nodes(&face_builder);
    face_builder.Reserve(0, static_cast<int64_t>(faces.lines.size()), 0);
    for (size_t f = 0; f < faces.lines.size(); ++f) {
      const int64_t* v = &faces.corners[3 * f];
      face_builder.AddTriangle(v[0], v[1], v[2], SourceLocation::Line(faces.lines[f]));
    }
  }

  MeshData mesh = node_builder.Finish(options);
  if (input.ele) {
    MeshData volume = ele_builder.Finish(options);
    mesh.tetrahedra = std::move(volume.tetrahedra);
    mesh.num_flipped = volume.num_flipped;
  }
  if (input.face) mesh.triangles = face_builder.Finish(options).triangles;

  std::vector<std::string> notes;
  if (tets.quadratic) notes.push_back("10-node tetrahedra read as their 4 corners");
  if (faces.quadratic) notes.push_back("6-node faces read as their 3 corners");
  if (turned > 0) {
    notes.push_back(std::to_string(turned) + " boundary face" + (turned == 1 ? "" : "s") +
                    " turned to face outwards");
  }
  for (size_t i = 0; i < notes.size(); ++i) mesh.format += (i == 0 ? " (" : "; ") + notes[i];
  if (!notes.empty()) mesh.format += ")";
  return mesh;
}

TetGenFiles WriteTetGen(const MeshData& mesh) {
  const Eigen::Index n = mesh.vertices.cols();
  const auto check = [&](const int32_t* v, Eigen::Index size, const char* what) {
    for (Eigen::Index i = 0; i < size; ++i) {
      if (v[i] < 0 || v[i] >= n) {
        throw MeshError(MeshErrorKind::kIndex, "", {},
                        std::string("cannot write TetGen: a ") + what + " refers to node " +
                            std::to_string(v[i]) + " of " + std::to_string(n));
      }
    }
  };
  check(mesh.tetrahedra.data(), mesh.tetrahedra.size(), "tetrahedron");
  check(mesh.triangles.data(), mesh.triangles.size(), "triangle");

  TetGenFiles files;
  files.node = std::to_string(n) + "  3  0  0\n";
  files.node.reserve(static_cast<size_t>(n) * 48 + 16);
  for (Eigen::Index i = 0; i < n; ++i) {
    files.node += std::to_string(i);
    for (int k = 0; k < 3; ++k) {
      files.node += ' ';
      AppendDouble(&files.node, mesh.vertices(k, i));
    }
    files.node += '\n';
  }
  // TetGen's tetrahedra have the orientation of mesh_types.h (checked against tetgen 1.5.0):
  // written as they are.
  if (mesh.tetrahedra.cols() > 0) {
    files.ele = std::to_string(mesh.tetrahedra.cols()) + "  4  0\n";
    for (Eigen::Index t = 0; t < mesh.tetrahedra.cols(); ++t) {
      AppendIndexLine(&files.ele, t, &mesh.tetrahedra(0, t), 4);
    }
  }
  if (mesh.triangles.cols() > 0) {
    files.face = std::to_string(mesh.triangles.cols()) + "  0\n";
    for (Eigen::Index t = 0; t < mesh.triangles.cols(); ++t) {
      AppendIndexLine(&files.face, t, &mesh.triangles(0, t), 3);
    }
  }
  return files;
}

}  // namespace somasim::mesh_io
