#include "common/mesh_io/obj_io.h"

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numbers>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/mesh_io/byte_reader.h"
#include "common/mesh_io/mesh_builder.h"
#include "common/mesh_io/text_reader.h"

namespace somasim::mesh_io {
namespace {

// Statements that carry no geometry somasim uses (texture and normal data, grouping, materials,
// display and rendering attributes), and the free-form statements that only qualify a curve or
// surface: ignored. A `curv` or `surf` body itself is refused, see below.
constexpr std::string_view kIgnoredStatements[] = {
    "vt",       "vn",     "vp",     "g",    "o",          "s",         "mg",    "usemtl",
    "mtllib",   "usemap", "maplib", "lod",  "shadow_obj", "trace_obj", "bevel", "c_interp",
    "d_interp", "cstype", "deg",    "bmat", "step",       "curv2",     "parm",  "trim",
    "hole",     "scrv",   "sp",     "end",  "con"};

// One `f` statement, its corners resolved to 0-based vertex indices (not yet range-checked:
// positive indices may refer to vertices defined further down the file).
struct Polygon {
  size_t first = 0;  // into the corner array
  size_t count = 0;
  int64_t line = 0;
};

class ObjParser {
 public:
  ObjParser(std::string_view bytes, const std::string& file_name)
      : reader_(bytes, file_name), builder_(file_name, "Wavefront OBJ") {}

  MeshData Parse(const ReadOptions& options);

 private:
  [[noreturn]] void Fail(MeshErrorKind kind, const std::string& fault) const {
    reader_.FailAt(kind, SourceLocation::Line(line_), fault);
  }
  void Statement(const std::vector<std::string_view>& tokens);
  void Vertex(const std::vector<std::string_view>& tokens);
  void Face(const std::vector<std::string_view>& tokens);
  int64_t Corner(std::string_view token, size_t position);
  void CheckConvex(const Polygon& polygon) const;

  TextReader reader_;
  MeshBuilder builder_;
  int64_t line_ = 0;            // first line of the current statement
  std::vector<double> coords_;  // 3 per vertex, as read (for the convexity test)
  std::vector<int64_t> corners_;
  std::vector<Polygon> polygons_;
  int64_t num_polylines_ = 0;
  int64_t num_points_ = 0;
};

MeshData ObjParser::Parse(const ReadOptions& options) {
  std::vector<std::string_view> tokens;
  while (std::optional<std::string_view> line = reader_.TryLine()) {
    line_ = reader_.token_location().line;
    tokens.clear();
    // A statement continues on the next line when its line ends with a backslash.
    for (;;) {
      std::string_view text = *line;
      const size_t hash = text.find('#');
      if (hash != std::string_view::npos) text = text.substr(0, hash);
      while (!text.empty() && IsSpace(text.back())) text.remove_suffix(1);
      const bool continued = !text.empty() && text.back() == '\\';
      if (continued) text.remove_suffix(1);
      SplitTokens(text, &tokens);
      if (!continued) break;
      line = reader_.TryLine();
      if (!line) break;
    }
    if (!tokens.empty()) Statement(tokens);
  }

  // Faces are checked once every vertex is known: OBJ allows vertices after the faces.
  const int64_t num_vertices = static_cast<int64_t>(coords_.size() / 3);
  int64_t num_fanned = 0;
  int64_t num_fan_triangles = 0;
  for (const Polygon& p : polygons_) {
    const int64_t* v = &corners_[p.first];
    const SourceLocation where = SourceLocation::Line(p.line);
    if (p.count > 3) {
      // Out-of-range corners are left for the builder to report.
      const bool in_range =
          std::all_of(v, v + p.count, [&](int64_t i) { return i >= 0 && i < num_vertices; });
      if (in_range) CheckConvex(p);
      ++num_fanned;
      num_fan_triangles += static_cast<int64_t>(p.count) - 2;
    }
    for (size_t k = 1; k + 1 < p.count; ++k) builder_.AddTriangle(v[0], v[k], v[k + 1], where);
  }
  if (num_polylines_ > 0) builder_.Skip("polyline (OBJ l)", num_polylines_);
  if (num_points_ > 0) builder_.Skip("point (OBJ p)", num_points_);

  MeshData mesh = builder_.Finish(options);
  if (num_fanned > 0) {
    // Not a Skip(): nothing was dropped. The format string is what tells the user.
    mesh.format += " (" + std::to_string(num_fanned) + " polygon face" +
                   (num_fanned == 1 ? "" : "s") +
                   " with more than 3 corners fan-triangulated into " +
                   std::to_string(num_fan_triangles) + " triangles)";
  }
  return mesh;
}

void ObjParser::Statement(const std::vector<std::string_view>& tokens) {
  const std::string_view keyword = tokens[0];
  if (keyword == "v") {
    Vertex(tokens);
  } else if (keyword == "f") {
    Face(tokens);
  } else if (keyword == "l") {
    ++num_polylines_;
  } else if (keyword == "p") {
    num_points_ += static_cast<int64_t>(tokens.size()) - 1;
  } else if (keyword == "curv" || keyword == "surf") {
    Fail(MeshErrorKind::kUnsupported,
         "free-form geometry ('" + std::string(keyword) +
             "') cannot be read: somasim reads polygonal OBJ only (export the model as a "
             "triangle mesh)");
  } else if (std::find(std::begin(kIgnoredStatements), std::end(kIgnoredStatements), keyword) ==
             std::end(kIgnoredStatements)) {
    Fail(MeshErrorKind::kSyntax, "unknown OBJ statement " + QuoteToken(keyword));
  }
}

void ObjParser::Vertex(const std::vector<std::string_view>& tokens) {
  const size_t n = tokens.size() - 1;
  const int64_t label = static_cast<int64_t>(coords_.size() / 3) + 1;
  if (n != 3 && n != 4 && n != 6) {
    Fail(MeshErrorKind::kSyntax,
         "vertex " + std::to_string(label) + " has " + std::to_string(n) +
             " numbers; expected 3 (x y z), 4 (x y z w) or 6 (x y z r g b)");
  }
  static constexpr const char* kNames[] = {"x", "y", "z", "4th", "5th", "6th"};
  double values[6] = {};
  for (size_t i = 0; i < n; ++i) {
    if (!ParseDouble(tokens[i + 1], &values[i])) {
      Fail(MeshErrorKind::kSyntax, "expected a number for the " + std::string(kNames[i]) +
                                       " value of vertex " + std::to_string(label) + ", found " +
                                       QuoteToken(tokens[i + 1]));
    }
  }
  // The homogeneous w (4 numbers) and the r g b colour extension (6 numbers) are not used.
  builder_.AddNode(values[0], values[1], values[2], SourceLocation::Line(line_), label);
  coords_.insert(coords_.end(), values, values + 3);
}

// Vertex part of one face corner `i`, `i/t`, `i//n` or `i/t/n`, as a 0-based index.
int64_t ObjParser::Corner(std::string_view token, size_t position) {
  std::string_view parts[3];
  size_t num_parts = 0;
  size_t start = 0;
  for (;;) {
    const size_t slash = token.find('/', start);
    if (num_parts == 3) {
      num_parts = 4;  // too many slashes
      break;
    }
    parts[num_parts++] =
        token.substr(start, slash == std::string_view::npos ? slash : slash - start);
    if (slash == std::string_view::npos) break;
    start = slash + 1;
  }
  const std::string corner = "corner " + std::to_string(position) + " " + QuoteToken(token);
  // Valid shapes: i, i/t, i//n, i/t/n (texture index empty only when a normal index follows).
  const bool shape_ok = num_parts <= 3 && !(num_parts == 2 && parts[1].empty()) &&
                        !(num_parts == 3 && parts[2].empty());
  if (!shape_ok) {
    Fail(MeshErrorKind::kSyntax,
         "face " + corner + " is malformed; expected v, v/vt, v//vn or v/vt/vn");
  }
  int64_t values[3] = {};
  for (size_t i = 0; i < num_parts; ++i) {
    if (i == 1 && parts[i].empty()) continue;
    if (!ParseInt64(parts[i], &values[i])) {
      Fail(MeshErrorKind::kSyntax, "face " + corner +
                                       " is malformed: expected integer indices (v, v/vt, v//vn "
                                       "or v/vt/vn)");
    }
    if (values[i] == 0) {
      Fail(MeshErrorKind::kIndex,
           "face " + corner + " uses index 0; OBJ indices start at 1 (negative ones count back)");
    }
  }
  const int64_t num_vertices = static_cast<int64_t>(coords_.size() / 3);
  if (values[0] > 0) return values[0] - 1;
  const int64_t resolved = num_vertices + values[0];
  if (resolved < 0) {
    Fail(MeshErrorKind::kIndex, "face " + corner + " counts back " + std::to_string(-values[0]) +
                                    " vertices but only " + std::to_string(num_vertices) +
                                    " are defined before it");
  }
  return resolved;
}

void ObjParser::Face(const std::vector<std::string_view>& tokens) {
  const size_t n = tokens.size() - 1;
  if (n < 3) {
    Fail(MeshErrorKind::kSyntax, "face has " + std::to_string(n) + " corner" + (n == 1 ? "" : "s") +
                                     "; a face needs at least 3");
  }
  Polygon p;
  p.first = corners_.size();
  p.count = n;
  p.line = line_;
  for (size_t i = 0; i < n; ++i) corners_.push_back(Corner(tokens[i + 1], i + 1));
  polygons_.push_back(p);
}

// A fan from the first corner is a faithful triangulation only of a convex polygon. The test
// works in the plane of the polygon's (Newell) normal, which also copes with slightly warped
// quads: every corner must turn the same way and the boundary must wind around once.
void ObjParser::CheckConvex(const Polygon& p) const {
  const auto point = [&](size_t k) {
    const size_t i = 3 * static_cast<size_t>(corners_[p.first + k % p.count]);
    return Eigen::Vector3d(coords_[i], coords_[i + 1], coords_[i + 2]);
  };
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  double longest = 0.0;
  for (size_t k = 0; k < p.count; ++k) {
    const Eigen::Vector3d a = point(k), b = point(k + 1);
    normal += a.cross(b);
    longest = std::max(longest, (b - a).squaredNorm());
  }
  const std::string what = "polygon face with " + std::to_string(p.count) + " corners";
  if (!(normal.norm() > 1e-12 * longest)) {
    reader_.FailAt(MeshErrorKind::kElement, SourceLocation::Line(p.line),
                   what + " is degenerate (zero area)");
  }
  normal.normalize();
  const Eigen::Vector3d u = normal.unitOrthogonal();
  const Eigen::Vector3d w = normal.cross(u);
  double turning = 0.0;
  for (size_t k = 0; k < p.count; ++k) {
    const Eigen::Vector3d e1 = point(k + 1) - point(k);
    const Eigen::Vector3d e2 = point(k + 2) - point(k + 1);
    const double x1 = e1.dot(u), y1 = e1.dot(w), x2 = e2.dot(u), y2 = e2.dot(w);
    // Repeated corners give a zero edge; the builder refuses the degenerate fan triangle.
    if ((x1 == 0 && y1 == 0) || (x2 == 0 && y2 == 0)) continue;
    const double angle = std::atan2(x1 * y2 - y1 * x2, x1 * x2 + y1 * y2);
    if (angle < -1e-9) {
      reader_.FailAt(MeshErrorKind::kUnsupported, SourceLocation::Line(p.line),
                     what + " is not convex (at its corner " +
                         std::to_string((k + 1) % p.count + 1) +
                         "), so it cannot be split into a fan of triangles; triangulate the model "
                         "before import");
    }
    turning += angle;
  }
  if (turning > 2 * std::numbers::pi + 1e-6) {
    reader_.FailAt(MeshErrorKind::kUnsupported, SourceLocation::Line(p.line),
                   what +
                       " is not convex (its boundary winds around more than once), so it "
                       "cannot be split into a fan of triangles; triangulate the model before "
                       "import");
  }
}

}  // namespace

MeshData ReadObj(std::string_view bytes, const std::string& file_name, const ReadOptions& options) {
  ObjParser parser(bytes, file_name);
  return parser.Parse(options);
}

std::string WriteObj(const MeshData& mesh) {
  std::string out = "# Wavefront OBJ written by somasim\n";
  out.reserve(out.size() + static_cast<size_t>(mesh.vertices.cols()) * 48 +
              static_cast<size_t>(mesh.triangles.cols()) * 24);
  for (Eigen::Index i = 0; i < mesh.vertices.cols(); ++i) {
    out += 'v';
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      AppendDouble(&out, mesh.vertices(k, i));
    }
    out += '\n';
  }
  for (Eigen::Index t = 0; t < mesh.triangles.cols(); ++t) {
    out += 'f';
    for (int k = 0; k < 3; ++k) {
      out += ' ';
      out += std::to_string(static_cast<int64_t>(mesh.triangles(k, t)) + 1);
    }
    out += '\n';
  }
  return out;
}

}  // namespace somasim::mesh_io
