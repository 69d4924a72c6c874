#include "common/mesh_gen/builtin_organs.h"

#include <array>
#include <stdexcept>

#include "common/mesh/topology.h"
#include "common/mesh_gen/closed_surface_mesher.h"
#include "common/mesh_gen/isosurface_stuffing.h"
#include "common/mesh_gen/organ_shapes.h"
#include "common/mesh_gen/structured_meshes.h"

namespace somasim::mesh_gen {
namespace {

using Eigen::Vector3d;

constexpr double kCm = 0.01;
constexpr double kMl = 1e-6;  // [m³]

// clang-format off
constexpr std::array<BuiltinOrganSpec, 9> kSpecs = {{
    {"liver4055", "liver", OrganKind::kVolume, "seed 000 (CT liver, 4055 nodes / 9126 tets)",
     "human liver, right and left lobes, ~1.6 L",
     4055, 9126, 0.05, -1.0, 4055, 19403, 18 * kCm, 24 * kCm, 1200 * kMl, 1900 * kMl},
    {"liver288", "", OrganKind::kVolume, "seed 003 (Amira liver, 288 / 1015)",
     "the same liver, coarse",
     288, 1015, 0.05, 0.05, 288, 1019, 18 * kCm, 24 * kCm, 1200 * kMl, 1900 * kMl},
    {"kidney424", "", OrganKind::kVolume, "seed 003 (Amira kidney, 424 / 1665)",
     "kidney, bean-shaped with a hilum",
     424, 1665, 0.05, 0.05, 430, 1633, 10 * kCm, 13 * kCm, 100 * kMl, 250 * kMl},
    {"plate192", "", OrganKind::kVolume, "seed 003 (plate, 192 / 392)",
     "thin plate 200 x 200 x 10 mm",
     192, 392, 0.0, 0.0, 192, 392, 20 * kCm, 20 * kCm, 400 * kMl, 400 * kMl},
    {"tissue45", "", OrganKind::kOpenSurface, "seed 002 (simple tissue, 45 / 66)",
     "open tissue patch, gently domed",
     45, 66, 0.05, 0.05, 45, 66, 2 * kCm, 8 * kCm, 0.0, 0.0},
    {"spleen600", "", OrganKind::kClosedSurface, "seed 002 (spleen, 600 / 1196)",
     "spleen, a curved flattened crescent",
     600, 1196, 0.0, 0.0, 600, 1196, 10 * kCm, 14 * kCm, 80 * kMl, 300 * kMl},
    {"kidney2000", "", OrganKind::kClosedSurface, "seed 002 (kidney, 2000 / 3996)",
     "kidney surface, bean-shaped with a hilum",
     2000, 3996, 0.0, 0.0, 2000, 3996, 10 * kCm, 13 * kCm, 100 * kMl, 250 * kMl},
    {"gallbladder5400", "gallbladder", OrganKind::kClosedSurface,
     "seed 002 (gallbladder, 5400 / 10782)", "gallbladder, pear-shaped",
     5400, 10782, 0.05, 0.05, 5400, 10796, 7 * kCm, 10 * kCm, 20 * kMl, 80 * kMl},
    {"beam19k", "", OrganKind::kVolume, "SOFA CPU benchmark beam (40 x 10 x 10 nodes)",
     "beam 16 x 4 x 4, 6 tets per hexahedron",
     4000, 18954, 0.0, 0.0, 4000, 18954, 16.0, 16.0, 256.0, 256.0},
}};
// clang-format on

mesh::TetMesh Stuff(OrganShape shape, double spacing, const Vector3d& offset) {
  StuffingOptions options;
  options.spacing = spacing;
  options.offset = offset;
  return StuffIsosurface(*MakeOrganShape(shape), options);
}

mesh::SurfaceMesh Fit(OrganShape shape, int num_vertices) {
  const OrganFrame frame = OrganShapeFrame(shape);
  ClosedSurfaceOptions options;
  options.num_vertices = num_vertices;
  options.centre = frame.centre;
  options.long_axis = frame.long_axis;
  return MeshClosedSurface(*MakeOrganShape(shape), options);
}

}  // namespace

const char* OrganKindName(OrganKind kind) {
  switch (kind) {
    case OrganKind::kVolume:
      return "volume";
    case OrganKind::kClosedSurface:
      return "closed surface";
    case OrganKind::kOpenSurface:
      return "open surface";
  }
  return "?";
}

std::span<const BuiltinOrganSpec> BuiltinOrganSpecs() { return kSpecs; }

const BuiltinOrganSpec* FindBuiltinOrgan(std::string_view name) {
  for (const BuiltinOrganSpec& spec : kSpecs) {
    if (name == spec.name || (!spec.alias.empty() && name == spec.alias)) return &spec;
  }
  return nullptr;
}

std::string BuiltinOrganNames() {
  std::string names;
  for (const BuiltinOrganSpec& spec : kSpecs) {
    if (!names.empty()) names += ", ";
    names += spec.name;
    if (!spec.alias.empty()) names += " (" + std::string(spec.alias) + ")";
  }
  return names;
}

BuiltinOrgan GenerateBuiltinOrgan(std::string_view name) {
  const BuiltinOrganSpec* spec = FindBuiltinOrgan(name);
  if (spec == nullptr) {
    throw std::invalid_argument("no built-in organ called \"" + std::string(name) +
                                "\"; the built-in organs are " + BuiltinOrganNames());
  }
  BuiltinOrgan organ;
  organ.spec = spec;
  // Lattice spacings and offsets were chosen by scanning spacing × 64 offsets for the counts
  // nearest the seed's (docs/builtin_organs.md); they are fixed so the meshes never change.
  const std::string_view n = spec->name;
  if (n == "liver4055") {
    organ.volume = Stuff(OrganShape::kLiver, 0.01015, Vector3d(0.75, 0.75, 0.25));
  } else if (n == "liver288") {
    organ.volume = Stuff(OrganShape::kLiver, 0.0275, Vector3d(0.25, 0.25, 0.0));
  } else if (n == "kidney424") {
    organ.volume = Stuff(OrganShape::kKidney, 0.0107, Vector3d(0.5, 0.75, 0.0));
  } else if (n == "plate192") {
    organ.volume = Plate192();
  } else if (n == "beam19k") {
    organ.volume = BoxGridTets(40, 10, 10, Vector3d::Zero(), Vector3d(16.0, 4.0, 4.0));
  } else if (n == "tissue45") {
    organ.surface = TissuePatch45();
  } else if (n == "spleen600") {
    organ.surface = Fit(OrganShape::kSpleen, 600);
  } else if (n == "kidney2000") {
    organ.surface = Fit(OrganShape::kKidney, 2000);
  } else if (n == "gallbladder5400") {
    organ.surface = Fit(OrganShape::kGallbladder, 5400);
  }
  if (spec->kind == OrganKind::kVolume) {
    organ.surface = mesh::CompactSurface(mesh::ExtractBoundarySurface(organ.volume), nullptr);
  }
  return organ;
}

mesh::TetMesh GenerateBuiltinOrganVolume(std::string_view name) {
  BuiltinOrgan organ = GenerateBuiltinOrgan(name);
  switch (organ.spec->kind) {
    case OrganKind::kVolume:
      return std::move(organ.volume);
    case OrganKind::kOpenSurface:
      throw std::invalid_argument("built-in organ " + std::string(organ.spec->name) +
                                  " is an open surface patch: it bounds no volume");
    case OrganKind::kClosedSurface:
      break;
  }
  // Mean edge length of the surface organ: every edge is shared by two triangles.
  double edge_sum = 0.0;
  const mesh::SurfaceMesh& surface = organ.surface;
  for (Eigen::Index t = 0; t < surface.triangles.cols(); ++t) {
    for (int c = 0; c < 3; ++c) {
      edge_sum += (surface.vertices.col(surface.triangles(c, t)) -
                   surface.vertices.col(surface.triangles((c + 1) % 3, t)))
                      .norm();
    }
  }
  const double mean_edge = edge_sum / (3.0 * static_cast<double>(surface.triangles.cols()));
  const std::string_view n = organ.spec->name;
  const OrganShape shape = n == "spleen600"    ? OrganShape::kSpleen
                           : n == "kidney2000" ? OrganShape::kKidney
                                               : OrganShape::kGallbladder;
  return Stuff(shape, 1.5 * mean_edge, Vector3d::Zero());
}

}  // namespace somasim::mesh_gen
