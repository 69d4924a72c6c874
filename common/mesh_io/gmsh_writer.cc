// Gmsh .msh writer: versions 1 (ASCII), 2.2 and 4.1 (ASCII and binary).
#include <array>
#include <charconv>
#include <cstdint>
#include <limits>
#include <string>
#include <string_view>
#include <utility>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/gmsh_element_types.h"
#include "common/mesh_io/gmsh_io.h"
#include "common/mesh_io/mesh_error.h"

namespace somasim::mesh_io {
namespace {

using gmsh_internal::kTetrahedronType;
using gmsh_internal::kTriangleType;

void AppendInt(std::string* out, int64_t value) {
  char buffer[24];
  const auto [ptr, ec] = std::to_chars(buffer, buffer + sizeof(buffer), value);
  out->append(buffer, ptr);
}

// Refuses meshes whose indices would make an unreadable file.
void CheckWritable(const MeshData& mesh) {
  const int64_t n = mesh.vertices.cols();
  const auto check = [&](const auto& elements, const char* what) {
    for (Eigen::Index e = 0; e < elements.cols(); ++e) {
      for (Eigen::Index k = 0; k < elements.rows(); ++k) {
        const int64_t v = elements(k, e);
        if (v < 0 || v >= n) {
          throw MeshError(MeshErrorKind::kIndex, "Gmsh output", SourceLocation{},
                          std::string(what) + " #" + std::to_string(e + 1) +
                              " refers to node index " + std::to_string(v) + " but the mesh has " +
                              std::to_string(n) + " nodes");
        }
      }
    }
  };
  check(mesh.triangles, "triangle");
  check(mesh.tetrahedra, "tetrahedron");
}

struct Box {
  std::array<double, 3> min{0, 0, 0};
  std::array<double, 3> max{0, 0, 0};
};

Box BoundingBox(const mesh::Points& points) {
  Box box;
  if (points.cols() == 0) return box;
  for (int k = 0; k < 3; ++k) {
    box.min[static_cast<size_t>(k)] = points.row(k).minCoeff();
    box.max[static_cast<size_t>(k)] = points.row(k).maxCoeff();
  }
  return box;
}

class GmshWriter {
 public:
  GmshWriter(const MeshData& mesh, bool binary) : mesh_(mesh), binary_(binary) {}

  std::string Version1() {
    Text("$NOD\n");
    Int(num_nodes());
    Text("\n");
    for (int64_t i = 0; i < num_nodes(); ++i) AsciiNode(i);
    Text("$ENDNOD\n$ELM\n");
    Int(num_tets() + num_triangles());
    Text("\n");
    int64_t id = 1;
    // id type reg-phys reg-elem number-of-nodes nodes...
    for (Eigen::Index t = 0; t < mesh_.tetrahedra.cols(); ++t) {
      Int(id++);
      Text(" 4 1 1 4");
      AsciiCorners(mesh_.tetrahedra.col(t));
    }
    for (Eigen::Index t = 0; t < mesh_.triangles.cols(); ++t) {
      Int(id++);
      Text(" 2 1 1 3");
      AsciiCorners(mesh_.triangles.col(t));
    }
    Text("$ENDELM\n");
    return std::move(out_);
  }

  std::string Version22() {
    if (num_nodes() > std::numeric_limits<int32_t>::max() ||
        num_tets() + num_triangles() > std::numeric_limits<int32_t>::max()) {
      throw MeshError(MeshErrorKind::kUnsupported, "Gmsh output", SourceLocation{},
                      "too many nodes or elements for Gmsh 2.2 (32-bit ids)");
    }
    MeshFormat("2.2");
    Text("$Nodes\n");
    Int(num_nodes());
    Text("\n");
    for (int64_t i = 0; i < num_nodes(); ++i) {
      if (binary_) {
        AppendBinary(&out_, static_cast<int32_t>(i + 1), Endian::kLittle);
        for (int k = 0; k < 3; ++k) AppendBinary(&out_, mesh_.vertices(k, i), Endian::kLittle);
      } else {
        AsciiNode(i);
      }
    }
    if (binary_) Text("\n");
    Text("$EndNodes\n$Elements\n");
    Int(num_tets() + num_triangles());
    Text("\n");
    // Two tags: physical group 1, elementary entity 1.
    int32_t id = 1;
    const auto block = [&](const auto& elements, int32_t type) {
      if (elements.cols() == 0) return;
      if (binary_) {
        for (const int32_t v : {type, static_cast<int32_t>(elements.cols()), int32_t{2}}) {
          AppendBinary(&out_, v, Endian::kLittle);
        }
      }
      for (Eigen::Index e = 0; e < elements.cols(); ++e) {
        if (binary_) {
          for (const int32_t v : {id++, int32_t{1}, int32_t{1}})
            AppendBinary(&out_, v, Endian::kLittle);
          for (Eigen::Index k = 0; k < elements.rows(); ++k) {
            AppendBinary(&out_, static_cast<int32_t>(elements(k, e) + 1), Endian::kLittle);
          }
        } else {
          Int(id++);
          Text(" ");
          Int(type);
          Text(" 2 1 1");
          AsciiCorners(elements.col(e));
        }
      }
    };
    block(mesh_.tetrahedra, kTetrahedronType);
    block(mesh_.triangles, kTriangleType);
    if (binary_) Text("\n");
    Text("$EndElements\n");
    return std::move(out_);
  }

  // One volume entity (tag 1) holding the tetrahedra and the nodes, and one surface entity (tag
  // 1) holding the triangles; a mesh of triangles only has its nodes on the surface.
  std::string Version41() {
    const bool has_volume = num_tets() > 0 || num_triangles() == 0;
    const bool has_surface = num_triangles() > 0;
    const Box box = BoundingBox(mesh_.vertices);
    MeshFormat("4.1");

    Text("$Entities\n");
    Size(0, " ");
    Size(0, " ");
    Size(has_surface ? 1 : 0, " ");
    Size(has_volume ? 1 : 0, "\n");
    const auto entity = [&]() {
      // tag, bounding box, no physical tags, no bounding entities
      Tag(1, " ");
      for (const double v : box.min) Double(v, " ");
      for (const double v : box.max) Double(v, " ");
      Size(0, " ");
      Size(0, "\n");
    };
    if (has_surface) entity();
    if (has_volume) entity();
    EndBinary();
    Text("$EndEntities\n");

    const int64_t n = num_nodes();
    Text("$Nodes\n");
    const int64_t node_blocks = n > 0 ? 1 : 0;
    Size(node_blocks, " ");
    Size(n, " ");
    Size(n > 0 ? 1 : 0, " ");
    Size(n, "\n");
    if (n > 0) {
      Tag(has_volume ? 3 : 2, " ");  // entity dimension
      Tag(1, " ");                   // entity tag
      Tag(0, " ");                   // not parametric
      Size(n, "\n");
      for (int64_t i = 0; i < n; ++i) Size(i + 1, "\n");
      for (int64_t i = 0; i < n; ++i) {
        Double(mesh_.vertices(0, i), " ");
        Double(mesh_.vertices(1, i), " ");
        Double(mesh_.vertices(2, i), "\n");
      }
    }
    EndBinary();
    Text("$EndNodes\n");

    const int64_t m = num_tets() + num_triangles();
    Text("$Elements\n");
    Size((num_tets() > 0 ? 1 : 0) + (num_triangles() > 0 ? 1 : 0), " ");
    Size(m, " ");
    Size(m > 0 ? 1 : 0, " ");
    Size(m, "\n");
    int64_t id = 1;
    const auto block = [&](const auto& elements, int dim, int type) {
      if (elements.cols() == 0) return;
      Tag(dim, " ");
      Tag(1, " ");
      Tag(type, " ");
      Size(elements.cols(), "\n");
      for (Eigen::Index e = 0; e < elements.cols(); ++e) {
        Size(id++, " ");
        for (Eigen::Index k = 0; k < elements.rows(); ++k) {
          Size(elements(k, e) + 1, k + 1 < elements.rows() ? " " : "\n");
        }
      }
    };
    block(mesh_.tetrahedra, 3, kTetrahedronType);
    block(mesh_.triangles, 2, kTriangleType);
    EndBinary();
    Text("$EndElements\n");
    return std::move(out_);
  }

 private:
  int64_t num_nodes() const { return mesh_.vertices.cols(); }
  int64_t num_tets() const { return mesh_.tetrahedra.cols(); }
  int64_t num_triangles() const { return mesh_.triangles.cols(); }

  void Text(std::string_view s) { out_.append(s); }
  void Int(int64_t v) { AppendInt(&out_, v); }

  void MeshFormat(const char* version) {
    Text("$MeshFormat\n");
    Text(version);
    Text(binary_ ? " 1 8\n" : " 0 8\n");
    if (binary_) {
      AppendBinary(&out_, int32_t{1}, Endian::kLittle);
      Text("\n");
    }
    Text("$EndMeshFormat\n");
  }

  // Version 4.1 numbers: in binary, `int` tags and `size_t` sizes; in ASCII, text followed by
  // the separator.
  void Tag(int v, std::string_view separator) {
    if (binary_) {
      AppendBinary(&out_, int32_t{v}, Endian::kLittle);
    } else {
      Int(v);
      Text(separator);
    }
  }
  void Size(int64_t v, std::string_view separator) {
    if (binary_) {
      AppendBinary(&out_, static_cast<uint64_t>(v), Endian::kLittle);
    } else {
      Int(v);
      Text(separator);
    }
  }
  void Double(double v, std::string_view separator) {
    if (binary_) {
      AppendBinary(&out_, v, Endian::kLittle);
    } else {
      AppendDouble(&out_, v);
      Text(separator);
    }
  }
  // Binary section data is followed by a newline before the end marker.
  void EndBinary() {
    if (binary_) Text("\n");
  }

  void AsciiNode(int64_t i) {
    Int(i + 1);
    for (int k = 0; k < 3; ++k) {
      Text(" ");
      AppendDouble(&out_, mesh_.vertices(k, i));
    }
    Text("\n");
  }

  template <typename Column>
  void AsciiCorners(const Column& corners) {
    for (Eigen::Index k = 0; k < corners.rows(); ++k) {
      Text(" ");
      Int(int64_t{corners(k)} + 1);
    }
    Text("\n");
  }

  const MeshData& mesh_;
  bool binary_;
  std::string out_;
};

}  // namespace

std::string WriteGmsh(const MeshData& mesh, GmshVersion version, Encoding encoding) {
  const bool binary = encoding == Encoding::kBinary;
  if (version == GmshVersion::kV1 && binary) {
    throw MeshError(MeshErrorKind::kUnsupported, "Gmsh output", SourceLocation{},
                    "Gmsh version 1 has no binary form; write version 1 as ASCII, or version "
                    "2.2 or 4.1 as binary");
  }
  CheckWritable(mesh);
  GmshWriter writer(mesh, binary);
  switch (version) {
    case GmshVersion::kV1:
      return writer.Version1();
    case GmshVersion::kV22:
      return writer.Version22();
    case GmshVersion::kV41:
      return writer.Version41();
  }
  return {};
}

}  // namespace somasim::mesh_io
