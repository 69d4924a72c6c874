#include "common/render/rasterizer.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/mesh/topology.h"

namespace somasim::render {
namespace {

using Eigen::Vector3d;

// Lighting, as fractions of the surface colour in linear light. A key light near the camera
// (a headlight raised up and to the left, so that faces turned towards the viewer are bright and
// relief still shows), a weak fill from the lower right so that nothing facing the viewer is
// left at ambient alone, and a faint white Blinn–Phong highlight for the wet look of tissue.
constexpr double kAmbient = 0.07;
constexpr double kKeyDiffuse = 0.88;
constexpr double kFillDiffuse = 0.12;
constexpr double kSpecular = 0.10;
constexpr int kShininessSquarings = 5;  // highlight exponent 2^5 = 32

// Samples rasterised at once. The frame is processed in horizontal bands of at most this many
// samples (12 bytes each: depth and visible triangle), so memory stays at about 3 MB whatever
// the image size and supersampling.
constexpr int64_t kMaxBandSamples = int64_t{1} << 18;

// Resolution of the linear → sRGB lookup table (enough that adjacent entries differ by < 1
// output level everywhere).
constexpr int kSrgbTableSize = 4096;

[[noreturn]] void Fail(const std::string& what) { throw std::invalid_argument("render: " + what); }

std::string Str(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

// sRGB transfer functions (IEC 61966-2-1).
double SrgbToLinear(double c) {
  return c <= 0.04045 ? c / 12.92 : std::pow((c + 0.055) / 1.055, 2.4);
}
double LinearToSrgb(double c) {
  return c <= 0.0031308 ? 12.92 * c : 1.055 * std::pow(c, 1.0 / 2.4) - 0.055;
}

void CheckColour(const Eigen::Vector3d& c, const char* field) {
  for (int k = 0; k < 3; ++k) {
    if (!(c[k] >= 0.0 && c[k] <= 1.0)) {
      Fail(std::string("RenderOptions.") + field + " channels must be in [0, 1] (got " + Str(c[0]) +
           ", " + Str(c[1]) + ", " + Str(c[2]) + ")");
    }
  }
}

void CheckOptions(const RenderOptions& o) {
  if (o.width < 1 || o.width > kMaxImageSize || o.height < 1 || o.height > kMaxImageSize) {
    Fail("RenderOptions width and height must be in 1.." + std::to_string(kMaxImageSize) +
         " (got " + std::to_string(o.width) + "x" + std::to_string(o.height) + ")");
  }
  if (!o.view_direction.allFinite() || !(o.view_direction.cwiseAbs().maxCoeff() > 0.0)) {
    Fail("RenderOptions.view_direction must be finite and non-zero");
  }
  if (!o.up.allFinite()) Fail("RenderOptions.up must be finite");
  CheckColour(o.surface_color, "surface_color");
  CheckColour(o.background_color, "background_color");
  if (!(o.crease_angle_deg > 0.0 && o.crease_angle_deg <= 180.0)) {
    Fail("RenderOptions.crease_angle_deg must be in (0, 180] (got " + Str(o.crease_angle_deg) +
         ")");
  }
  if (!(o.edge_width_px > 0.0 && o.edge_width_px <= 100.0)) {
    Fail("RenderOptions.edge_width_px must be in (0, 100] (got " + Str(o.edge_width_px) + ")");
  }
  if (!(o.edge_darkening >= 0.0 && o.edge_darkening <= 1.0)) {
    Fail("RenderOptions.edge_darkening must be in [0, 1] (got " + Str(o.edge_darkening) + ")");
  }
  if (o.supersampling < 1 || o.supersampling > 4) {
    Fail("RenderOptions.supersampling must be in 1..4 (got " + std::to_string(o.supersampling) +
         ")");
  }
  if (!(o.margin >= 0.0 && o.margin <= 0.45)) {
    Fail("RenderOptions.margin must be in [0, 0.45] (got " + Str(o.margin) + ")");
  }
}

void CheckVertices(const mesh::Points& vertices) {
  for (Eigen::Index j = 0; j < vertices.cols(); ++j) {
    if (!vertices.col(j).allFinite()) {
      Fail("vertex " + std::to_string(j) + " has a non-finite coordinate (" + Str(vertices(0, j)) +
           ", " + Str(vertices(1, j)) + ", " + Str(vertices(2, j)) + ")");
    }
  }
}

template <typename Elements>
void CheckIndices(const Elements& elements, Eigen::Index num_vertices, const char* kind) {
  for (Eigen::Index t = 0; t < elements.cols(); ++t) {
    for (Eigen::Index k = 0; k < elements.rows(); ++k) {
      const int32_t v = elements(k, t);
      if (v < 0 || v >= num_vertices) {
        Fail(std::string(kind) + " " + std::to_string(t) + " uses vertex " + std::to_string(v) +
             ", outside 0.." + std::to_string(num_vertices - 1));
      }
    }
  }
}

// Orthonormal camera frame: forward = view direction, right = forward × up, so that (right, up,
// -forward) is right-handed like OpenGL eye space.
struct Camera {
  Vector3d right, up, forward;
};

// v / |v|, scaled first by its largest component so that neither huge nor subnormal
// components overflow or underflow the norm; zero for a zero vector.
Vector3d Direction(const Vector3d& v) {
  const double largest = v.cwiseAbs().maxCoeff();
  if (!(largest > 0.0)) return Vector3d::Zero();
  const Vector3d scaled = v / largest;
  return scaled / scaled.norm();
}

Camera MakeCamera(const RenderOptions& o) {
  Camera cam;
  cam.forward = Direction(o.view_direction);
  const Vector3d up = Direction(o.up);
  Vector3d across = up - up.dot(cam.forward) * cam.forward;
  if (!(across.norm() > 1e-9)) {
    // No usable up: take the world axis most orthogonal to the view (lowest index on ties).
    Eigen::Index axis = 0;
    cam.forward.cwiseAbs().minCoeff(&axis);
    const Vector3d a = Vector3d::Unit(axis);
    across = a - a.dot(cam.forward) * cam.forward;
  }
  cam.up = across.normalized();
  cam.right = cam.forward.cross(cam.up);
  return cam;
}

// Angle [rad] of triangle t at its corner k.
double CornerAngle(const mesh::SurfaceMesh& s, Eigen::Index t, int k) {
  const Vector3d p = s.vertices.col(s.triangles(k, t));
  const Vector3d e1 = s.vertices.col(s.triangles((k + 1) % 3, t)) - p;
  const Vector3d e2 = s.vertices.col(s.triangles((k + 2) % 3, t)) - p;
  return std::atan2(e1.cross(e2).norm(), e1.dot(e2));
}

// Shading normals at the three corners of every triangle (3 per triangle, corner-major): the
// angle-weighted mean (Thürmer & Wüthrich 1998, "Computing vertex normals from polygonal
// facets") of the normals of the triangles round the corner's vertex that lie within the crease
// angle of the triangle's own normal. Sharp features stay sharp, curved parts look smooth, and
// neighbours with inconsistent orientation (normals far apart) do not spoil each other.
std::vector<Vector3d> CornerNormals(const mesh::SurfaceMesh& s,
                                    const std::vector<Vector3d>& face_normals,
                                    double crease_angle_deg) {
  const Eigen::Index m = s.triangles.cols();
  const mesh::Adjacency around =
      mesh::NodeToTriangles(static_cast<int32_t>(s.vertices.cols()), s.triangles);
  const double cos_crease = std::cos(crease_angle_deg * std::numbers::pi / 180.0);
  std::vector<Vector3d> normals(static_cast<size_t>(3 * m), Vector3d::Zero());
  for (Eigen::Index t = 0; t < m; ++t) {
    const Vector3d& nt = face_normals[static_cast<size_t>(t)];
    for (int k = 0; k < 3; ++k) {
      const int32_t v = s.triangles(k, t);
      Vector3d sum = Vector3d::Zero();
      for (int32_t e = around.offsets[static_cast<size_t>(v)];
           e < around.offsets[static_cast<size_t>(v) + 1]; ++e) {
        const int32_t f = around.entries[static_cast<size_t>(e)];
        const Vector3d& nf = face_normals[static_cast<size_t>(f)];
        if (nf.dot(nt) < cos_crease - 1e-12) continue;
        int corner = 0;
        while (corner < 2 && s.triangles(corner, f) != v) ++corner;
        sum += CornerAngle(s, f, corner) * nf;
      }
      const double norm = sum.norm();
      normals[static_cast<size_t>(3 * t + k)] = norm > 0.0 ? Vector3d(sum / norm) : nt;
    }
  }
  return normals;
}

// A triangle in sample coordinates (x right, y down, sample (i, j) centred at (i+½, j+½)).
// Edge k is the one opposite corner k. Its edge function w_k(p) = a·px + b·py + c is evaluated
// with the edge's endpoints in ascending vertex-index order, so the two triangles sharing an
// edge compute exactly opposite values: no sample falls in a crack between them. side_k makes
// w_k positive inside. Plain arrays rather than Eigen keep the per-sample code fast in
// unoptimised (sanitizer) builds too.
struct ScreenTriangle {
  double depth[3];  // along the view direction [m], per corner
  double a[3], b[3], c[3], side[3], inv_length[3];
  double normal[3][3];                   // shading normal per corner, turned towards the viewer
  double edge_strength = 0.0;            // darkening of the wireframe lines on this triangle
  int x0 = 0, x1 = -1, y0 = 0, y1 = -1;  // sample bounding box, inclusive, clipped to the frame
  bool back = false;                     // seen from behind
};

// The edge functions of `t` at (px, py), made positive inside; true when the sample is inside
// or on the boundary. Both passes call this, so they agree exactly.
inline bool Cover(const ScreenTriangle& t, double px, double py, double w[3]) {
  for (int k = 0; k < 3; ++k) {
    w[k] = t.side[k] * (t.a[k] * px + t.b[k] * py + t.c[k]);
    if (!(w[k] >= 0.0)) return false;
  }
  return w[0] + w[1] + w[2] > 0.0;
}

struct Frame {
  int samples_x = 0, samples_y = 0;  // supersampled frame size
  std::vector<double> x, y, depth;   // per vertex, sample coordinates and depth (used ones only)
};

Frame Project(const mesh::SurfaceMesh& s, const Camera& cam, const RenderOptions& o) {
  Frame f;
  f.samples_x = o.width * o.supersampling;
  f.samples_y = o.height * o.supersampling;
  const size_t n = static_cast<size_t>(s.vertices.cols());
  std::vector<char> used(n, 0);
  for (Eigen::Index i = 0; i < s.triangles.size(); ++i) {
    used[static_cast<size_t>(s.triangles.data()[i])] = 1;
  }
  f.x.assign(n, 0.0);
  f.y.assign(n, 0.0);
  f.depth.assign(n, 0.0);
  double min_x = std::numeric_limits<double>::infinity(), max_x = -min_x;
  double min_y = min_x, max_y = max_x;
  for (size_t v = 0; v < n; ++v) {
    if (!used[v]) continue;
    const Vector3d p = s.vertices.col(static_cast<Eigen::Index>(v));
    f.x[v] = p.dot(cam.right);
    f.y[v] = p.dot(cam.up);
    f.depth[v] = p.dot(cam.forward);
    min_x = std::min(min_x, f.x[v]);
    max_x = std::max(max_x, f.x[v]);
    min_y = std::min(min_y, f.y[v]);
    max_y = std::max(max_y, f.y[v]);
  }
  const double extent_x = max_x - min_x, extent_y = max_y - min_y;
  for (size_t v = 0; v < n; ++v) {
    if (used[v] && !std::isfinite(f.depth[v])) {
      Fail("coordinates too large to project (vertex " + std::to_string(v) + ")");
    }
  }
  if (!std::isfinite(extent_x) || !std::isfinite(extent_y)) {
    Fail("coordinates too large: the projected extent overflows");
  }
  // Fit: the larger relative extent fills the frame minus the margins.
  const double usable_x = f.samples_x * (1.0 - 2.0 * o.margin);
  const double usable_y = f.samples_y * (1.0 - 2.0 * o.margin);
  double scale = std::numeric_limits<double>::infinity();
  if (extent_x > 0.0) scale = std::min(scale, usable_x / extent_x);
  if (extent_y > 0.0) scale = std::min(scale, usable_y / extent_y);
  if (!std::isfinite(scale)) scale = 1.0;  // a single point (or denormal extent): nothing to fit
  // min + extent/2 rather than (min + max)/2, which can overflow for huge coordinates.
  const double centre_x = min_x + 0.5 * extent_x, centre_y = min_y + 0.5 * extent_y;
  for (size_t v = 0; v < n; ++v) {
    if (!used[v]) continue;
    f.x[v] = 0.5 * f.samples_x + (f.x[v] - centre_x) * scale;
    f.y[v] = 0.5 * f.samples_y - (f.y[v] - centre_y) * scale;  // rows go down
  }
  return f;
}

// Screen-space set-up of every triangle with a non-zero projected area.
// Shading normals come from `corner_normals` (3 per triangle) when smooth, else the face normal.
std::vector<ScreenTriangle> SetUpTriangles(const mesh::SurfaceMesh& s, const Frame& f,
                                           const Camera& cam,
                                           const std::vector<Vector3d>& face_normals,
                                           const std::vector<Vector3d>& corner_normals,
                                           const RenderOptions& o) {
  std::vector<ScreenTriangle> out;
  out.reserve(static_cast<size_t>(s.triangles.cols()));
  for (Eigen::Index t = 0; t < s.triangles.cols(); ++t) {
    ScreenTriangle st;
    std::array<size_t, 3> v;
    for (int k = 0; k < 3; ++k) v[static_cast<size_t>(k)] = static_cast<size_t>(s.triangles(k, t));
    bool degenerate = false;
    for (size_t k = 0; k < 3; ++k) {
      size_t p = v[(k + 1) % 3], q = v[(k + 2) % 3];
      if (p == q) {
        degenerate = true;
        break;
      }
      if (p > q) std::swap(p, q);
      st.a[k] = f.y[p] - f.y[q];
      st.b[k] = f.x[q] - f.x[p];
      st.c[k] = f.x[p] * f.y[q] - f.x[q] * f.y[p];
      const double at_opposite = st.a[k] * f.x[v[k]] + st.b[k] * f.y[v[k]] + st.c[k];
      if (!(at_opposite != 0.0)) {
        degenerate = true;  // zero area on screen (seen edge-on, or collapsed)
        break;
      }
      st.side[k] = at_opposite > 0.0 ? 1.0 : -1.0;
      st.inv_length[k] = 1.0 / std::hypot(st.a[k], st.b[k]);
      st.depth[k] = f.depth[v[k]];
    }
    if (degenerate) continue;
    const double min_x = std::min({f.x[v[0]], f.x[v[1]], f.x[v[2]]});
    const double max_x = std::max({f.x[v[0]], f.x[v[1]], f.x[v[2]]});
    const double min_y = std::min({f.y[v[0]], f.y[v[1]], f.y[v[2]]});
    const double max_y = std::max({f.y[v[0]], f.y[v[1]], f.y[v[2]]});
    st.x0 = static_cast<int>(std::clamp(std::ceil(min_x - 0.5), 0.0, f.samples_x - 1.0));
    st.x1 = static_cast<int>(std::clamp(std::floor(max_x - 0.5), -1.0, f.samples_x - 1.0));
    st.y0 = static_cast<int>(std::clamp(std::ceil(min_y - 0.5), 0.0, f.samples_y - 1.0));
    st.y1 = static_cast<int>(std::clamp(std::floor(max_y - 0.5), -1.0, f.samples_y - 1.0));
    if (st.x1 < st.x0 || st.y1 < st.y0) continue;  // covers no sample centre
    const Vector3d& face_normal = face_normals[static_cast<size_t>(t)];
    st.back = face_normal.dot(cam.forward) > 0.0;
    const double flip = st.back ? -1.0 : 1.0;  // two-sided: light the side the viewer sees
    for (size_t k = 0; k < 3; ++k) {
      const Vector3d& n =
          corner_normals.empty() ? face_normal : corner_normals[static_cast<size_t>(3 * t) + k];
      for (int d = 0; d < 3; ++d) st.normal[k][d] = flip * n[d];
    }
    if (o.draw_edges) {
      // Fade the lines on triangles only a few pixels across, so that a fine mesh shows its
      // shape rather than a dark mesh of lines: full strength from a smallest height of 8 px.
      const double twice_area = std::abs(st.a[0] * f.x[v[0]] + st.b[0] * f.y[v[0]] + st.c[0]);
      double min_height = std::numeric_limits<double>::infinity();
      for (size_t k = 0; k < 3; ++k)
        min_height = std::min(min_height, twice_area * st.inv_length[k]);
      const double height_px = min_height / o.supersampling;
      st.edge_strength = o.edge_darkening * std::clamp(height_px / 8.0, 0.35, 1.0);
    }
    out.push_back(st);
  }
  return out;
}

// b^(2^n) by repeated squaring (a cheap, deterministic specular power).
double PowerOfTwoPower(double b, int n) {
  for (int i = 0; i < n; ++i) b *= b;
  return b;
}

// Unit vectors towards the key and fill lights, and Blinn's half vector of the key light.
struct Lights {
  double key[3], fill[3], half[3];
};

Lights MakeLights(const Camera& cam) {
  const Vector3d to_camera = -cam.forward;
  const Vector3d key = (1.0 * to_camera + 0.9 * cam.up - 0.6 * cam.right).normalized();
  const Vector3d fill = (0.6 * to_camera - 0.3 * cam.up + 0.75 * cam.right).normalized();
  const Vector3d half = (key + to_camera).normalized();
  Lights l;
  for (int d = 0; d < 3; ++d) {
    l.key[d] = key[d];
    l.fill[d] = fill[d];
    l.half[d] = half[d];
  }
  return l;
}

double Dot(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

// Everything the per-sample shading needs besides the triangle.
struct Shading {
  Lights lights;
  double front[3], back[3];      // surface colours in linear light
  double edge_half_width = 0.0;  // [samples]
  bool edges = false;
};

// Linear-light colour of triangle t at a covered sample with edge functions w (Lambert with
// ambient, key and fill, plus a Blinn–Phong highlight; darker along the triangle's edges).
void Shade(const ScreenTriangle& t, const double w[3], const Shading& s, float out[3]) {
  const double sum = w[0] + w[1] + w[2];
  double n[3];
  for (int d = 0; d < 3; ++d) {
    n[d] = (w[0] * t.normal[0][d] + w[1] * t.normal[1][d] + w[2] * t.normal[2][d]) / sum;
  }
  const double length = std::sqrt(Dot(n, n));
  if (length > 1e-12) {
    for (double& v : n) v /= length;
  }
  const double light = kAmbient + kKeyDiffuse * std::max(0.0, Dot(n, s.lights.key)) +
                       kFillDiffuse * std::max(0.0, Dot(n, s.lights.fill));
  const double highlight =
      kSpecular * PowerOfTwoPower(std::max(0.0, Dot(n, s.lights.half)), kShininessSquarings);
  double darken = 1.0;
  if (s.edges) {
    // Distance [samples] to the nearest edge; a one-sample ramp softens the line's sides.
    const double distance =
        std::min({w[0] * t.inv_length[0], w[1] * t.inv_length[1], w[2] * t.inv_length[2]});
    darken = 1.0 - t.edge_strength * std::clamp(s.edge_half_width + 0.5 - distance, 0.0, 1.0);
  }
  const double* base = t.back ? s.back : s.front;
  for (int d = 0; d < 3; ++d) out[d] = static_cast<float>(darken * (base[d] * light + highlight));
}

}  // namespace

Image RenderSurface(const mesh::SurfaceMesh& surface, const RenderOptions& options) {
  CheckOptions(options);
  CheckVertices(surface.vertices);
  CheckIndices(surface.triangles, surface.vertices.cols(), "triangle");

  const int ss = options.supersampling;
  Image image;
  image.width = options.width;
  image.height = options.height;
  image.rgb.resize(static_cast<size_t>(image.width) * static_cast<size_t>(image.height) * 3);
  uint8_t background_bytes[3];
  double background_linear[3];
  for (int k = 0; k < 3; ++k) {
    background_bytes[k] = static_cast<uint8_t>(std::lround(255.0 * options.background_color[k]));
    background_linear[k] = SrgbToLinear(options.background_color[k]);
  }
  if (surface.triangles.cols() == 0) {
    for (size_t i = 0; i < image.rgb.size(); ++i) image.rgb[i] = background_bytes[i % 3];
    return image;
  }

  const Camera cam = MakeCamera(options);
  const Frame frame = Project(surface, cam, options);
  std::vector<Vector3d> face_normals(static_cast<size_t>(surface.triangles.cols()));
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    const Vector3d p0 = surface.vertices.col(surface.triangles(0, t));
    const Vector3d n = (surface.vertices.col(surface.triangles(1, t)) - p0)
                           .cross(surface.vertices.col(surface.triangles(2, t)) - p0);
    const double norm = n.norm();
    face_normals[static_cast<size_t>(t)] = norm > 0.0 ? Vector3d(n / norm) : Vector3d::Zero();
  }
  std::vector<Vector3d> corner_normals;
  if (options.smooth_shading) {
    corner_normals = CornerNormals(surface, face_normals, options.crease_angle_deg);
  }
  const std::vector<ScreenTriangle> triangles =
      SetUpTriangles(surface, frame, cam, face_normals, corner_normals, options);
  if (triangles.size() > static_cast<size_t>(std::numeric_limits<int32_t>::max())) {
    Fail("more than 2^31 - 1 triangles");
  }

  Shading shading;
  shading.lights = MakeLights(cam);
  for (int k = 0; k < 3; ++k) {
    shading.front[k] = SrgbToLinear(options.surface_color[k]);
    shading.back[k] = kBackFaceFactor * shading.front[k];
  }
  shading.edges = options.draw_edges;
  shading.edge_half_width = 0.5 * options.edge_width_px * ss;

  uint8_t to_srgb[kSrgbTableSize];
  for (int i = 0; i < kSrgbTableSize; ++i) {
    to_srgb[i] = static_cast<uint8_t>(
        std::lround(255.0 * LinearToSrgb(static_cast<double>(i) / (kSrgbTableSize - 1))));
  }

  // The frame in bands of whole output rows. Pass 1 finds the nearest triangle at each sample
  // (z-buffer); pass 2 shades each sample once, with its visible triangle, and box-filters the
  // samples of each pixel in linear light.
  const int width = frame.samples_x;
  const int band_rows = static_cast<int>(
      std::min<int64_t>(frame.samples_y, std::max<int64_t>(ss, kMaxBandSamples / width / ss * ss)));
  const size_t band_size = static_cast<size_t>(band_rows) * static_cast<size_t>(width);
  std::vector<double> depth(band_size);
  std::vector<int32_t> owner(band_size);
  for (int band_y = 0; band_y < frame.samples_y; band_y += band_rows) {
    const int rows = std::min(band_rows, frame.samples_y - band_y);
    std::fill(depth.begin(), depth.end(), std::numeric_limits<double>::infinity());
    std::fill(owner.begin(), owner.end(), -1);
    for (size_t ti = 0; ti < triangles.size(); ++ti) {
      const ScreenTriangle& t = triangles[ti];
      const int y0 = std::max(t.y0, band_y), y1 = std::min(t.y1, band_y + rows - 1);
      for (int j = y0; j <= y1; ++j) {
        const double py = j + 0.5;
        size_t at = static_cast<size_t>(j - band_y) * static_cast<size_t>(width) +
                    static_cast<size_t>(t.x0);
        for (int i = t.x0; i <= t.x1; ++i, ++at) {
          double w[3];
          if (!Cover(t, i + 0.5, py, w)) continue;
          const double z =
              (w[0] * t.depth[0] + w[1] * t.depth[1] + w[2] * t.depth[2]) / (w[0] + w[1] + w[2]);
          if (z < depth[at]) {  // ties keep the earlier triangle
            depth[at] = z;
            owner[at] = static_cast<int32_t>(ti);
          }
        }
      }
    }

    // Pixels no triangle touched keep the exact background bytes.
    for (int oy = band_y / ss; oy < (band_y + rows) / ss; ++oy) {
      for (int ox = 0; ox < options.width; ++ox) {
        double sum[3] = {0.0, 0.0, 0.0};
        bool covered = false;
        for (int sy = 0; sy < ss; ++sy) {
          const int j = oy * ss + sy;
          for (int sx = 0; sx < ss; ++sx) {
            const int i = ox * ss + sx;
            const size_t at = static_cast<size_t>(j - band_y) * static_cast<size_t>(width) +
                              static_cast<size_t>(i);
            float colour[3] = {0.0f, 0.0f, 0.0f};
            if (owner[at] < 0) {
              for (int k = 0; k < 3; ++k) sum[k] += background_linear[k];
              continue;
            }
            covered = true;
            const ScreenTriangle& t = triangles[static_cast<size_t>(owner[at])];
            double w[3] = {0.0, 0.0, 0.0};
            Cover(t, i + 0.5, j + 0.5, w);  // true: the same test won pass 1
            Shade(t, w, shading, colour);
            for (int k = 0; k < 3; ++k) sum[k] += static_cast<double>(colour[k]);
          }
        }
        const size_t out = image.Index(ox, oy);
        for (int k = 0; k < 3; ++k) {
          if (!covered) {
            image.rgb[out + static_cast<size_t>(k)] = background_bytes[k];
            continue;
          }
          const double v = std::clamp(sum[k] / (ss * ss), 0.0, 1.0);
          image.rgb[out + static_cast<size_t>(k)] = to_srgb[std::lround(v * (kSrgbTableSize - 1))];
        }
      }
    }
  }
  return image;
}

Image RenderTetMesh(const mesh::TetMesh& mesh, const RenderOptions& options) {
  CheckOptions(options);
  CheckVertices(mesh.vertices);
  CheckIndices(mesh.tetrahedra, mesh.vertices.cols(), "tetrahedron");
  return RenderSurface(mesh::ExtractBoundarySurface(mesh), options);
}

}  // namespace somasim::render
