// RenderSurface / RenderTetMesh: coverage of a known projection, fitting whatever the unit, the
// z-buffer, shading that follows the light, two-sided drawing, edges, determinism, and refusal
// of bad options and meshes. Small images keep it quick under the sanitizers.
#include "common/render/rasterizer.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <cmath>
#include <limits>
#include <numbers>
#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::render {
namespace {

using Eigen::Vector3d;

// A w × h rectangle centred at `centre` spanning the directions `u` and `v` (unit vectors),
// as two triangles counter-clockwise seen from the side u × v points to.
mesh::SurfaceMesh Rectangle(const Vector3d& centre, const Vector3d& u, const Vector3d& v,
                            double w = 1.0, double h = 1.0) {
  mesh::SurfaceMesh s;
  s.vertices.resize(3, 4);
  s.vertices.col(0) = centre - 0.5 * w * u - 0.5 * h * v;
  s.vertices.col(1) = centre + 0.5 * w * u - 0.5 * h * v;
  s.vertices.col(2) = centre + 0.5 * w * u + 0.5 * h * v;
  s.vertices.col(3) = centre - 0.5 * w * u + 0.5 * h * v;
  s.triangles.resize(3, 2);
  s.triangles << 0, 0,  //
      1, 2,             //
      2, 3;
  return s;
}

mesh::SurfaceMesh Append(const mesh::SurfaceMesh& a, const mesh::SurfaceMesh& b) {
  mesh::SurfaceMesh s;
  s.vertices.resize(3, a.vertices.cols() + b.vertices.cols());
  s.vertices << a.vertices, b.vertices;
  s.triangles.resize(3, a.triangles.cols() + b.triangles.cols());
  s.triangles << a.triangles, (b.triangles.array() + static_cast<int32_t>(a.vertices.cols()));
  return s;
}

mesh::SurfaceMesh UnitCube() {
  const mesh_io::MeshData box = testing::BoxSurface(1, 1, 1);
  return {box.vertices, box.triangles};
}

// Looking down -z with y up: x goes right and y up in the picture.
RenderOptions HeadOn(int width, int height) {
  RenderOptions o;
  o.width = width;
  o.height = height;
  o.view_direction = Vector3d(0, 0, -1);
  o.up = Vector3d::UnitY();
  o.supersampling = 2;
  return o;
}

bool IsBackground(const Image& image, int x, int y, const RenderOptions& o) {
  for (int c = 0; c < 3; ++c) {
    if (image.rgb[image.Index(x, y, c)] != std::lround(255.0 * o.background_color[c])) {
      return false;
    }
  }
  return true;
}

int Brightness(const Image& image, int x, int y) {
  return image.rgb[image.Index(x, y, 0)] + image.rgb[image.Index(x, y, 1)] +
         image.rgb[image.Index(x, y, 2)];
}

std::string ErrorOf(const mesh::SurfaceMesh& s, const RenderOptions& o) {
  try {
    RenderSurface(s, o);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "no exception";
}

TEST(RenderSurface, HeadOnCubeFillsTheFittedSquareAndNothingElse) {
  RenderOptions o = HeadOn(100, 80);
  o.margin = 0.1;
  const Image image = RenderSurface(UnitCube(), o);
  ASSERT_EQ(image.width, 100);
  ASSERT_EQ(image.height, 80);
  ASSERT_EQ(image.rgb.size(), 100u * 80u * 3u);
  // The unit square fills the height minus the margins: 64 px, centred → x 18..82, y 8..72.
  const double side = 80 * (1 - 2 * o.margin), x0 = 50 - side / 2, y0 = 40 - side / 2;
  int covered = 0;
  for (int y = 0; y < o.height; ++y) {
    for (int x = 0; x < o.width; ++x) {
      const double cx = x + 0.5, cy = y + 0.5;  // pixel centre
      const bool inside = cx > x0 + 1 && cx < x0 + side - 1 && cy > y0 + 1 && cy < y0 + side - 1;
      const bool outside = cx < x0 - 1 || cx > x0 + side + 1 || cy < y0 - 1 || cy > y0 + side + 1;
      if (inside) {
        EXPECT_FALSE(IsBackground(image, x, y, o)) << x << "," << y;
      }
      if (outside) {
        EXPECT_TRUE(IsBackground(image, x, y, o)) << x << "," << y;
      }
      covered += IsBackground(image, x, y, o) ? 0 : 1;
    }
  }
  EXPECT_NEAR(covered, side * side, 4 * side);
  for (const auto& [x, y] : {std::pair{0, 0}, {99, 0}, {0, 79}, {99, 79}}) {
    EXPECT_TRUE(IsBackground(image, x, y, o));
  }
}

TEST(RenderSurface, FitsTheFrameWhateverTheUnit) {
  // Scaling by a power of two is exact in floating point, so the pictures are identical.
  const mesh::SurfaceMesh metres = UnitCube();
  mesh::SurfaceMesh tiny = metres;
  tiny.vertices *= 1.0 / 1024.0;
  RenderOptions o;
  o.width = 48;
  o.height = 40;
  o.supersampling = 2;
  EXPECT_EQ(RenderSurface(metres, o).rgb, RenderSurface(tiny, o).rgb);
  // A shifted, millimetre-sized copy covers the same pixels to within one pixel's fringe.
  mesh::SurfaceMesh mm = metres;
  mm.vertices = (mm.vertices * 1000.0).colwise() + Vector3d(-3e4, 2e5, 7.0);
  const Image a = RenderSurface(metres, o), b = RenderSurface(mm, o);
  int differ = 0;
  for (int y = 0; y < o.height; ++y) {
    for (int x = 0; x < o.width; ++x) {
      differ += IsBackground(a, x, y, o) != IsBackground(b, x, y, o) ? 1 : 0;
    }
  }
  EXPECT_LE(differ, 4);
}

TEST(RenderSurface, UnusedVerticesDoNotAffectTheFit) {
  mesh::SurfaceMesh cube = UnitCube();
  mesh::SurfaceMesh with_far_vertex = cube;
  with_far_vertex.vertices.conservativeResize(3, cube.vertices.cols() + 1);
  with_far_vertex.vertices.col(cube.vertices.cols()) = Vector3d(1e6, -1e6, 1e6);
  const RenderOptions o = HeadOn(40, 30);
  EXPECT_EQ(RenderSurface(cube, o).rgb, RenderSurface(with_far_vertex, o).rgb);
}

TEST(RenderSurface, FaceTowardsTheViewerIsBrighterThanAGrazingOne) {
  RenderOptions o = HeadOn(32, 32);
  o.draw_edges = false;  // the diagonal would cross the centre pixel
  const Vector3d x = Vector3d::UnitX(), y = Vector3d::UnitY();
  const int head_on = Brightness(RenderSurface(Rectangle(Vector3d::Zero(), x, y), o), 16, 16);
  for (const double angle_deg : {75.0, -75.0}) {
    // Turned about the vertical axis: seen almost edge-on, still from the front.
    const Eigen::AngleAxisd turn(angle_deg * std::numbers::pi / 180.0, y);
    const Image grazing = RenderSurface(Rectangle(Vector3d::Zero(), turn * x, y), o);
    EXPECT_GT(head_on, Brightness(grazing, 16, 16) + 30) << angle_deg;
  }
  EXPECT_GT(head_on, 0);
}

TEST(RenderSurface, BackFacesAreDrawnAndDarker) {
  RenderOptions o = HeadOn(32, 32);
  o.draw_edges = false;
  const Vector3d x = Vector3d::UnitX(), y = Vector3d::UnitY();
  const Image front = RenderSurface(Rectangle(Vector3d::Zero(), x, y), o);
  const Image back = RenderSurface(Rectangle(Vector3d::Zero(), -x, y), o);  // normal along -z
  EXPECT_FALSE(IsBackground(back, 16, 16, o));
  // Lit like the front (not left at ambient), in a darker colour: in linear light the ratio is
  // kBackFaceFactor, give or take the faint white highlight.
  const auto linear_red = [](const Image& image) {
    const double c = image.rgb[image.Index(16, 16, 0)] / 255.0;
    return c <= 0.04045 ? c / 12.92 : std::pow((c + 0.055) / 1.055, 2.4);
  };
  EXPECT_NEAR(linear_red(back) / linear_red(front), kBackFaceFactor, 0.05);
}

TEST(RenderSurface, NearerSurfaceHidesFartherOneWhateverTheOrder) {
  RenderOptions o = HeadOn(40, 40);
  o.draw_edges = false;
  const Vector3d x = Vector3d::UnitX(), y = Vector3d::UnitY();
  // A large back-facing rectangle behind (z = -1) a small front-facing one (z = +1).
  const mesh::SurfaceMesh far = Rectangle(Vector3d(0, 0, -1), -x, y, 2.0, 2.0);
  const mesh::SurfaceMesh near = Rectangle(Vector3d(0, 0, 1), x, y, 0.5, 0.5);
  const Image near_last = RenderSurface(Append(far, near), o);
  const Image near_first = RenderSurface(Append(near, far), o);
  const Image near_alone_colour = RenderSurface(Rectangle(Vector3d(0, 0, 1), x, y, 2.0, 2.0), o);
  EXPECT_EQ(near_last.rgb, near_first.rgb);
  for (int c = 0; c < 3; ++c) {
    EXPECT_EQ(near_last.rgb[near_last.Index(20, 20, c)],
              near_alone_colour.rgb[near_alone_colour.Index(20, 20, c)]);
  }
  // Outside the small rectangle the far one shows, darker (its back).
  EXPECT_LT(Brightness(near_last, 3, 3), Brightness(near_last, 20, 20));
  EXPECT_FALSE(IsBackground(near_last, 3, 3, o));
}

TEST(RenderSurface, NoCracksBetweenTrianglesSharingAnEdge) {
  // A patch of many thin triangles rotated in the view plane: every pixel inside it is covered,
  // including those whose sample lies on a shared edge.
  mesh::SurfaceMesh fan;
  const int n = 40;
  fan.vertices.resize(3, n + 1);
  fan.vertices.col(0).setZero();
  fan.triangles.resize(3, n);
  for (int i = 0; i < n; ++i) {
    const double angle = 2 * std::numbers::pi * i / n + 0.1;
    fan.vertices.col(i + 1) = Vector3d(std::cos(angle), std::sin(angle), 0.0);
    fan.triangles.col(i) << 0, i + 1, (i + 1) % n + 1;
  }
  RenderOptions o = HeadOn(61, 61);
  o.supersampling = 1;
  o.draw_edges = false;
  const Image image = RenderSurface(fan, o);
  const double radius = 0.5 * 61 * (1 - 2 * o.margin) * std::cos(std::numbers::pi / n);
  int checked = 0;
  for (int y = 0; y < 61; ++y) {
    for (int x = 0; x < 61; ++x) {
      if (std::hypot(x + 0.5 - 30.5, y + 0.5 - 30.5) < radius - 1.5) {
        EXPECT_FALSE(IsBackground(image, x, y, o)) << x << "," << y;
        ++checked;
      }
    }
  }
  EXPECT_GT(checked, 2000);
}

TEST(RenderSurface, EdgesDarkenOnlyPixelsNearTriangleEdges) {
  RenderOptions o = HeadOn(40, 40);
  o.margin = 0.0;
  o.draw_edges = false;
  const mesh::SurfaceMesh square =
      Rectangle(Vector3d::Zero(), Vector3d::UnitX(), Vector3d::UnitY());
  const Image plain = RenderSurface(square, o);
  o.draw_edges = true;
  const Image edged = RenderSurface(square, o);
  // The diagonal runs from (0, 40) to (40, 0) in pixels: x + y = 40.
  int darker_on_diagonal = 0;
  for (int y = 0; y < 40; ++y) {
    for (int x = 0; x < 40; ++x) {
      const double distance = std::abs((x + 0.5) + (y + 0.5) - 40.0) / std::sqrt(2.0);
      const bool near_border = x < 2 || y < 2 || x > 37 || y > 37;
      if (distance > 2.0 && !near_border) {
        EXPECT_EQ(Brightness(plain, x, y), Brightness(edged, x, y)) << x << "," << y;
      }
      if (distance < 0.3 && !near_border) {
        darker_on_diagonal += Brightness(edged, x, y) < Brightness(plain, x, y) ? 1 : 0;
      }
    }
  }
  EXPECT_GE(darker_on_diagonal, 30);
}

TEST(RenderSurface, CreaseAngleKeepsCubeFacesFlatAndSmoothingAllCurvesThem) {
  RenderOptions o;
  o.width = 48;
  o.height = 48;
  o.supersampling = 1;
  o.draw_edges = false;
  // Looking at the front face (normal +z) head-on but tilted slightly so others show too.
  o.view_direction = Vector3d(-0.2, -0.2, -1.0);
  const auto spread_of_front_face = [&](const Image& image) {
    int lo = 1000, hi = 0;
    for (int y = 20; y < 28; ++y) {
      for (int x = 20; x < 28; ++x) {
        lo = std::min(lo, Brightness(image, x, y));
        hi = std::max(hi, Brightness(image, x, y));
      }
    }
    return hi - lo;
  };
  EXPECT_LE(spread_of_front_face(RenderSurface(UnitCube(), o)), 3);
  o.crease_angle_deg = 180.0;
  EXPECT_GT(spread_of_front_face(RenderSurface(UnitCube(), o)), 10);
}

TEST(RenderSurface, IsDeterministic) {
  const mesh_io::MeshData box = testing::BoxTets(3, 2, 2, 0.1, 0.05, 0.04);
  const mesh::SurfaceMesh s = mesh::ExtractBoundarySurface({box.vertices, box.tetrahedra});
  RenderOptions o;
  o.width = 64;
  o.height = 48;
  EXPECT_EQ(RenderSurface(s, o).rgb, RenderSurface(s, o).rgb);
}

TEST(RenderSurface, EmptyMeshGivesTheBackground) {
  RenderOptions o;
  o.width = 7;
  o.height = 5;
  o.background_color = Vector3d(0.2, 0.4, 0.6);
  const Image image = RenderSurface({}, o);
  ASSERT_EQ(image.rgb.size(), 7u * 5u * 3u);
  for (int y = 0; y < 5; ++y) {
    for (int x = 0; x < 7; ++x) EXPECT_TRUE(IsBackground(image, x, y, o));
  }
  // Vertices without triangles draw nothing either.
  EXPECT_EQ(RenderSurface({mesh::Points::Random(3, 4), {}}, o).rgb, image.rgb);
}

TEST(RenderSurface, UpParallelToTheViewStillRenders) {
  RenderOptions o = HeadOn(24, 24);
  o.up = Vector3d(0, 0, 5);
  const Image image = RenderSurface(UnitCube(), o);
  EXPECT_FALSE(IsBackground(image, 12, 12, o));
}

TEST(RenderSurface, OnlyTheDirectionOfViewAndUpMatters) {
  // Lengths whose squares overflow or underflow a double still give the same picture.
  RenderOptions o;
  o.width = 32;
  o.height = 24;
  const Image reference = RenderSurface(UnitCube(), o);
  for (const int exponent : {1000, -1000}) {
    RenderOptions scaled = o;
    scaled.view_direction = o.view_direction * std::ldexp(1.0, exponent);
    scaled.up = o.up * std::ldexp(1.0, -exponent);
    EXPECT_EQ(RenderSurface(UnitCube(), scaled).rgb, reference.rgb) << exponent;
  }
}

TEST(RenderSurface, LargeFramesJoinSeamlesslyAcrossBands) {
  // 500 × 600 samples exceed one band (2^18 samples, here 524 rows), so the square crosses a
  // band boundary: its column of pixels must still be one unbroken run of the fitted length.
  RenderOptions o = HeadOn(500, 600);
  o.supersampling = 1;
  o.margin = 0.0;
  o.draw_edges = false;
  const Image image = RenderSurface(UnitCube(), o);
  int covered = 0, runs = 0;
  for (int y = 0; y < o.height; ++y) {
    const bool hit = !IsBackground(image, 250, y, o);
    covered += hit ? 1 : 0;
    runs += (hit && (y == 0 || IsBackground(image, 250, y - 1, o))) ? 1 : 0;
  }
  EXPECT_NEAR(covered, 500, 1);  // the square spans the width, centred vertically
  EXPECT_EQ(runs, 1);
  EXPECT_EQ(Brightness(image, 250, 523), Brightness(image, 250, 524));
}

TEST(RenderSurface, RefusesBadOptionsNamingTheField) {
  const mesh::SurfaceMesh cube = UnitCube();
  const auto error_with = [&](auto change) {
    RenderOptions o;
    o.width = 8;
    o.height = 8;
    change(o);
    return ErrorOf(cube, o);
  };
  EXPECT_NE(error_with([](RenderOptions& o) { o.width = 0; }).find("width and height"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.height = 8193; }).find("1..8192"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.view_direction.setZero(); }).find("view_direction"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) {
              o.view_direction.x() = std::numeric_limits<double>::quiet_NaN();
            }).find("view_direction"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) {
              o.up.y() = std::numeric_limits<double>::infinity();
            }).find("up"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.surface_color.x() = 1.5; }).find("surface_color"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) {
              o.background_color.z() = std::numeric_limits<double>::quiet_NaN();
            }).find("background_color"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.supersampling = 5; }).find("supersampling"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.margin = 0.5; }).find("margin"), std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.edge_width_px = 0; }).find("edge_width_px"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.edge_darkening = -0.1; }).find("edge_darkening"),
            std::string::npos);
  EXPECT_NE(error_with([](RenderOptions& o) { o.crease_angle_deg = 0; }).find("crease_angle_deg"),
            std::string::npos);
}

TEST(RenderSurface, RefusesNonFiniteCoordinatesAndBadIndicesUpFront) {
  RenderOptions o;
  o.width = 8;
  o.height = 8;
  mesh::SurfaceMesh nan = UnitCube();
  nan.vertices(1, 2) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(ErrorOf(nan, o).find("vertex 2 has a non-finite coordinate"), std::string::npos)
      << ErrorOf(nan, o);
  mesh::SurfaceMesh high = UnitCube();
  high.triangles(2, 3) = static_cast<int32_t>(high.vertices.cols());
  EXPECT_NE(ErrorOf(high, o).find("triangle 3 uses vertex 8, outside 0..7"), std::string::npos)
      << ErrorOf(high, o);
  mesh::SurfaceMesh negative = UnitCube();
  negative.triangles(0, 0) = -1;
  EXPECT_NE(ErrorOf(negative, o).find("triangle 0 uses vertex -1"), std::string::npos);
  mesh::SurfaceMesh huge = UnitCube();
  huge.vertices.row(0) *= 1.7e308;
  huge.vertices(0, 0) = -1.7e308;
  EXPECT_NE(ErrorOf(huge, o).find("too large"), std::string::npos) << ErrorOf(huge, o);
}

TEST(RenderTetMesh, DrawsTheBoundarySurface) {
  const mesh_io::MeshData box = testing::BoxTets(2, 2, 1);
  const mesh::TetMesh tets{box.vertices, box.tetrahedra};
  RenderOptions o;
  o.width = 40;
  o.height = 30;
  EXPECT_EQ(RenderTetMesh(tets, o).rgb, RenderSurface(mesh::ExtractBoundarySurface(tets), o).rgb);
}

TEST(RenderTetMesh, RefusesBadIndicesAndCoordinates) {
  RenderOptions o;
  o.width = 8;
  o.height = 8;
  const auto error_of = [&](const mesh::TetMesh& m) -> std::string {
    try {
      RenderTetMesh(m, o);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "no exception";
  };
  const mesh_io::MeshData box = testing::BoxTets(1, 1, 1);
  mesh::TetMesh bad{box.vertices, box.tetrahedra};
  bad.tetrahedra(3, 5) = 1000;
  EXPECT_NE(error_of(bad).find("tetrahedron 5 uses vertex 1000"), std::string::npos)
      << error_of(bad);
  mesh::TetMesh inf{box.vertices, box.tetrahedra};
  inf.vertices(0, 1) = -std::numeric_limits<double>::infinity();
  EXPECT_NE(error_of(inf).find("vertex 1 has a non-finite"), std::string::npos) << error_of(inf);
}

}  // namespace
}  // namespace somasim::render
