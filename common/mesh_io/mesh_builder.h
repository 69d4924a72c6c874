// Collects what a reader parses and turns it into a checked MeshData.
//
// Every reader feeds nodes and elements through this class, so the checks that do not depend on
// the format (finite coordinates, index range, degenerate and inverted elements, unit scaling)
// are written once and name the file and the element's location.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/mesh_data.h"
#include "common/mesh_io/mesh_error.h"

namespace somasim::mesh_io {

class MeshBuilder {
 public:
  explicit MeshBuilder(std::string file_name, std::string format);

  // Optional capacity hints; counts must already have been checked against the input size.
  void Reserve(int64_t num_nodes, int64_t num_triangles, int64_t num_tets);

  // Coordinates in the file's unit. Fails (kValue) on NaN/Inf, naming the node (0-based
  // position in the file; `label` is how the file names it, e.g. its id).
  void AddNode(double x, double y, double z, SourceLocation where);
  void AddNode(double x, double y, double z, SourceLocation where, int64_t label);

  // 0-based node indices. Range is checked in Finish() against the final node count;
  // values that do not fit in int32 fail at once (kIndex).
  void AddTriangle(int64_t a, int64_t b, int64_t c, SourceLocation where);
  void AddTetrahedron(int64_t a, int64_t b, int64_t c, int64_t d, SourceLocation where);
  // An element kind that is neither a triangle nor a tetrahedron.
  void Skip(std::string_view type, int64_t count = 1);

  int64_t num_nodes() const { return static_cast<int64_t>(coords_.size() / 3); }
  int64_t num_triangles() const { return static_cast<int64_t>(tris_.size() / 3); }
  int64_t num_tets() const { return static_cast<int64_t>(tets_.size() / 4); }
  const std::string& file_name() const { return file_name_; }

  // Checks indices (kIndex), repeated corners and flat elements (kElement), orientation of
  // tetrahedra (kElement unless options.fix_orientation), then scales to metres.
  MeshData Finish(const ReadOptions& options);

  [[noreturn]] void Fail(MeshErrorKind kind, SourceLocation where, const std::string& fault) const;

 private:
  std::string file_name_;
  std::string format_;
  std::vector<double> coords_;  // 3·num_nodes, file unit
  std::vector<int32_t> tris_;   // 3·num_triangles
  std::vector<int32_t> tets_;   // 4·num_tets
  std::vector<SourceLocation> tri_where_;
  std::vector<SourceLocation> tet_where_;
  std::vector<SkippedElements> skipped_;
};

}  // namespace somasim::mesh_io
