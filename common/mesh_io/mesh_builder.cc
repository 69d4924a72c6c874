#include "common/mesh_io/mesh_builder.h"

#include <cmath>
#include <limits>
#include <utility>

#include "common/mesh/quality.h"

namespace somasim::mesh_io {
namespace {

std::string Ordinal(const char* what, size_t index) {
  return std::string(what) + " #" + std::to_string(index + 1);
}

std::string Corners(const int32_t* v, int n) {
  std::string s = "(";
  for (int i = 0; i < n; ++i) {
    if (i > 0) s += ", ";
    s += std::to_string(v[i]);
  }
  return s + ")";
}

}  // namespace

MeshBuilder::MeshBuilder(std::string file_name, std::string format)
    : file_name_(std::move(file_name)), format_(std::move(format)) {}

void MeshBuilder::Reserve(int64_t num_nodes, int64_t num_triangles, int64_t num_tets) {
  if (num_nodes > 0) coords_.reserve(3 * static_cast<size_t>(num_nodes));
  if (num_triangles > 0) {
    tris_.reserve(3 * static_cast<size_t>(num_triangles));
    tri_where_.reserve(static_cast<size_t>(num_triangles));
  }
  if (num_tets > 0) {
    tets_.reserve(4 * static_cast<size_t>(num_tets));
    tet_where_.reserve(static_cast<size_t>(num_tets));
  }
}

void MeshBuilder::AddNode(double x, double y, double z, SourceLocation where) {
  AddNode(x, y, z, where, num_nodes() + 1);
}

void MeshBuilder::AddNode(double x, double y, double z, SourceLocation where, int64_t label) {
  if (!std::isfinite(x) || !std::isfinite(y) || !std::isfinite(z)) {
    Fail(MeshErrorKind::kValue, where,
         "node " + std::to_string(label) + " has a non-finite coordinate (" + std::to_string(x) +
             ", " + std::to_string(y) + ", " + std::to_string(z) + ")");
  }
  if (num_nodes() >= std::numeric_limits<int32_t>::max()) {
    Fail(MeshErrorKind::kCount, where, "more than 2^31-1 nodes");
  }
  coords_.push_back(x);
  coords_.push_back(y);
  coords_.push_back(z);
}

void MeshBuilder::AddTriangle(int64_t a, int64_t b, int64_t c, SourceLocation where) {
  for (int64_t v : {a, b, c}) {
    if (v < 0 || v >= std::numeric_limits<int32_t>::max()) {
      Fail(MeshErrorKind::kIndex, where,
           Ordinal("triangle", tri_where_.size()) + " refers to node index " + std::to_string(v) +
               ", outside the valid range");
    }
    tris_.push_back(static_cast<int32_t>(v));
  }
  tri_where_.push_back(where);
}

void MeshBuilder::AddTetrahedron(int64_t a, int64_t b, int64_t c, int64_t d, SourceLocation where) {
  for (int64_t v : {a, b, c, d}) {
    if (v < 0 || v >= std::numeric_limits<int32_t>::max()) {
      Fail(MeshErrorKind::kIndex, where,
           Ordinal("tetrahedron", tet_where_.size()) + " refers to node index " +
               std::to_string(v) + ", outside the valid range");
    }
    tets_.push_back(static_cast<int32_t>(v));
  }
  tet_where_.push_back(where);
}

void MeshBuilder::Skip(std::string_view type, int64_t count) { AddSkipped(&skipped_, type, count); }

void MeshBuilder::Fail(MeshErrorKind kind, SourceLocation where, const std::string& fault) const {
  throw MeshError(kind, file_name_, where, fault);
}

MeshData MeshBuilder::Finish(const ReadOptions& options) {
  const int64_t n = num_nodes();
  if (n == 0) {
    // An empty file, or one with no geometry, is never what a user meant to load.
    Fail(MeshErrorKind::kSyntax, {},
         "the file holds no nodes (empty file, or not a " + format_ + " mesh)");
  }
  const auto node = [&](int32_t i) {
    const size_t k = 3 * static_cast<size_t>(i);
    return Eigen::Vector3d(coords_[k], coords_[k + 1], coords_[k + 2]);
  };
  const auto check_range = [&](const int32_t* v, int count, const char* what, size_t e,
                               SourceLocation where) {
    for (int i = 0; i < count; ++i) {
      if (v[i] >= n) {
        Fail(MeshErrorKind::kIndex, where,
             Ordinal(what, e) + " refers to node index " + std::to_string(v[i]) +
                 " (0-based) but the file has " + std::to_string(n) + " nodes");
      }
    }
    for (int i = 0; i < count; ++i) {
      for (int j = i + 1; j < count; ++j) {
        if (v[i] == v[j]) {
          Fail(MeshErrorKind::kElement, where,
               Ordinal(what, e) + " is degenerate: node " + std::to_string(v[i]) +
                   " appears twice in " + Corners(v, count) + " (0-based)");
        }
      }
    }
  };

  for (size_t t = 0; t < tri_where_.size(); ++t) {
    const int32_t* v = &tris_[3 * t];
    check_range(v, 3, "triangle", t, tri_where_[t]);
    const Eigen::Vector3d a = node(v[0]), b = node(v[1]), c = node(v[2]);
    const double longest =
        std::max({(b - a).squaredNorm(), (c - b).squaredNorm(), (a - c).squaredNorm()});
    const double area2 = (b - a).cross(c - a).norm();
    // Scale-free flatness test: twice the area against the squared longest edge.
    if (!(area2 > 1e-12 * longest)) {
      Fail(MeshErrorKind::kElement, tri_where_[t],
           Ordinal("triangle", t) + " " + Corners(v, 3) +
               " is degenerate: its corners are collinear or coincident (area " +
               std::to_string(area2 / 2) + ")");
    }
  }

  int64_t flipped = 0;
  for (size_t t = 0; t < tet_where_.size(); ++t) {
    int32_t* v = &tets_[4 * t];
    check_range(v, 4, "tetrahedron", t, tet_where_[t]);
    const Eigen::Vector3d a = node(v[0]), b = node(v[1]), c = node(v[2]), d = node(v[3]);
    const double normalised = mesh::TetNormalisedVolume(a, b, c, d);
    if (!(std::abs(normalised) >= mesh::kDegenerateTetNormalisedVolume)) {
      Fail(MeshErrorKind::kElement, tet_where_[t],
           Ordinal("tetrahedron", t) + " " + Corners(v, 4) +
               " is degenerate: its corners are (nearly) coplanar (6V/L^3 = " +
               std::to_string(normalised) + ")");
    }
    if (normalised < 0) {
      if (!options.fix_orientation) {
        Fail(MeshErrorKind::kElement, tet_where_[t],
             Ordinal("tetrahedron", t) + " " + Corners(v, 4) +
                 " is inverted (negative signed volume); re-orient it or read with "
                 "--fix-orientation");
      }
      std::swap(v[2], v[3]);
      ++flipped;
    }
  }

  MeshData out;
  out.format = format_;
  out.num_flipped = flipped;
  out.skipped = skipped_;
  const double scale = UnitToMetres(options.unit);
  out.vertices.resize(3, n);
  for (int64_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      const double x = coords_[3 * static_cast<size_t>(i) + static_cast<size_t>(k)];
      out.vertices(k, i) = scale == 1.0 ? x : x * scale;
    }
  }
  out.triangles.resize(3, num_triangles());
  if (!tris_.empty()) std::copy(tris_.begin(), tris_.end(), out.triangles.data());
  out.tetrahedra.resize(4, num_tets());
  if (!tets_.empty()) std::copy(tets_.begin(), tets_.end(), out.tetrahedra.data());
  return out;
}

}  // namespace somasim::mesh_io
