#include "server/organs/organ_builder.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <stdexcept>

#include "common/mesh/geometry.h"
#include "common/mesh/topology.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/mesh_io/mesh_io.h"
#include "server/models/mass_spring_model.h"
#include "server/models/molecular_model.h"
#include "server/models/position_based_model.h"
#include "server/organs/reduced_file.h"

namespace somasim::organs {
namespace {

using scene::Model;

const char* ModelName(const Model& model) {
  switch (model.kind_case()) {
    case Model::kMassSpring:
      return "mass_spring";
    case Model::kMolecular:
      return "molecular";
    case Model::kPositionBased:
      return "position_based";
    case Model::kFemLinear:
      return "fem_linear";
    case Model::kFemCorotational:
      return "fem_corotational";
    case Model::kFemHyperelastic:
      return "fem_hyperelastic";
    case Model::kReducedKl:
      return "reduced_kl";
    case Model::kEfg:
      return "efg";
    case Model::kEfgHybrid:
      return "efg_hybrid";
    case Model::KIND_NOT_SET:
      break;
  }
  return "none";
}

models::fem::FemParameters FemParametersOf(const scene::Organ& organ) {
  namespace fem = models::fem;
  const scene::Material& m = organ.material();
  fem::FemParameters p;
  p.density = m.density();
  p.youngs_modulus = m.youngs_modulus();
  p.poisson_ratio = m.poisson_ratio();
  p.rayleigh_mass = m.rayleigh_mass();
  p.rayleigh_stiffness = m.rayleigh_stiffness();
  switch (organ.model().kind_case()) {
    case Model::kFemLinear:
      p.kind = fem::FemKind::kLinear;
      break;
    case Model::kFemHyperelastic:
      p.kind = fem::FemKind::kHyperelastic;
      break;
    default:
      p.kind = fem::FemKind::kCorotational;
  }
  switch (m.law_case()) {
    case scene::Material::kLiverNava2008: {
      const double nu = m.liver_nava2008().poisson_ratio();
      p.hyperelastic = fem::LiverNava2008(nu > 0.0 ? nu : 0.49);
      break;
    }
    case scene::Material::kNeoHookean:
      p.hyperelastic = fem::NeoHookean(m.neo_hookean().c10(), m.neo_hookean().d1());
      break;
    case scene::Material::kStvk:
      p.hyperelastic = fem::StVenantKirchhoff(m.youngs_modulus(), m.poisson_ratio());
      break;
    case scene::Material::kReducedPolynomial: {  // sizes checked by the scene loader
      const scene::ReducedPolynomial& rp = m.reduced_polynomial();
      p.hyperelastic = fem::HyperelasticMaterial{};
      for (int k = 0; k < rp.c_size() && k < 5; ++k)
        p.hyperelastic.c[static_cast<size_t>(k)] = rp.c(k);
      for (int k = 0; k < rp.d_size() && k < 3; ++k)
        p.hyperelastic.d[static_cast<size_t>(k)] = rp.d(k);
      break;
    }
    case scene::Material::LAW_NOT_SET:
      break;
  }
  if (m.liver_nava2008_prony()) p.prony = fem::LiverNava2008Prony();
  for (const scene::PronyTerm& t : m.prony()) p.prony.push_back({t.gamma(), t.tau()});
  if (organ.model().solver_tolerance() > 0.0) p.cg_tolerance = organ.model().solver_tolerance();
  if (organ.model().solver_max_iterations() > 0) {
    p.cg_max_iterations = organ.model().solver_max_iterations();
  }
  return p;
}

// E, ν and ρ from the material (as the linear FEM takes them); the rest from `e` (model.efg, or
// model.efg_hybrid.efg), unset fields keeping the model's defaults (efg_model.h).
models::meshless::EfgParameters EfgParametersOf(const scene::Organ& organ, const scene::Efg& e) {
  const scene::Material& m = organ.material();
  models::meshless::EfgParameters p;
  p.youngs_modulus = m.youngs_modulus();
  p.poisson_ratio = m.poisson_ratio();
  p.density = m.density();
  if (e.has_gauss_points()) p.gauss_points = e.gauss_points();
  if (e.has_support_scale()) p.mls.support_scale = e.support_scale();
  if (e.has_support_neighbours()) p.mls.support_neighbours = e.support_neighbours();
  if (e.has_penalty_factor()) p.penalty_factor = e.penalty_factor();
  if (e.has_rayleigh_mass()) p.rayleigh_mass = e.rayleigh_mass();
  if (e.has_rayleigh_stiffness()) p.rayleigh_stiffness = e.rayleigh_stiffness();
  return p;
}

// The EFG part as EfgParametersOf (model.efg_hybrid.efg), the surgical region's from
// model.efg_hybrid, unset fields keeping the model's defaults (efg_hybrid_model.h): an unset
// region_centre stays non-finite (the tool decides).
models::meshless::EfgHybridParameters EfgHybridParametersOf(const scene::Organ& organ) {
  const scene::EfgHybrid& h = organ.model().efg_hybrid();
  models::meshless::EfgHybridParameters p;
  p.efg = EfgParametersOf(organ, h.efg());
  if (h.has_region_radius()) p.region_radius = h.region_radius();
  if (h.has_region_centre()) {
    const scene::Vec3& c = h.region_centre();
    p.region_centre = Eigen::Vector3d(c.x(), c.y(), c.z());
  }
  if (h.has_follow_tool()) p.follow_tool = h.follow_tool();
  if (h.has_follow_fraction()) p.follow_fraction = h.follow_fraction();
  if (h.has_max_region_nodes()) p.max_region_nodes = h.max_region_nodes();
  if (h.has_adaptive()) p.adaptive = h.adaptive();
  if (h.has_adapt_interval()) p.adapt_interval = h.adapt_interval();
  if (h.has_refine_threshold()) p.refine_threshold = h.refine_threshold();
  if (h.has_coarsen_threshold()) p.coarsen_threshold = h.coarsen_threshold();
  return p;
}

// The particle models' parameters share E, ρ and ζ (docs/models.md maps them to springs).
template <typename Parameters>
Parameters ParticleParametersOf(const scene::Organ& organ) {
  Parameters p;
  p.youngs_modulus = organ.material().youngs_modulus();
  p.density = organ.material().density();
  return p;
}

std::unique_ptr<models::TissueModel> MakeParticleModel(const scene::Organ& organ,
                                                       const mesh::TetMesh& volume,
                                                       const mesh::SurfaceMesh& surface) {
  const Model& model = organ.model();
  const bool on_volume = volume.tetrahedra.cols() > 0;
  switch (model.kind_case()) {
    case Model::kMassSpring: {
      auto p = ParticleParametersOf<models::MassSpringParameters>(organ);
      p.damping_ratio = organ.material().damping_ratio();
      if (model.mass_spring().implicit()) {
        p.integrator = models::MassSpringIntegrator::kImplicitEuler;
      }
      if (model.solver_tolerance() > 0.0) p.cg_tolerance = model.solver_tolerance();
      if (model.solver_max_iterations() > 0) p.cg_max_iterations = model.solver_max_iterations();
      p.anchor_stiffness = model.mass_spring().anchor_stiffness();
      return on_volume ? models::MassSpringModel::FromTetMesh(volume, p)
                       : models::MassSpringModel::FromSurface(surface, p);
    }
    case Model::kMolecular: {
      auto p = ParticleParametersOf<models::MolecularParameters>(organ);
      p.damping_ratio = organ.material().damping_ratio();
      return models::MolecularModel::FromSurface(surface, p);
    }
    case Model::kPositionBased: {
      auto p = ParticleParametersOf<models::PositionBasedParameters>(organ);
      if (model.position_based().iterations() > 0) {
        p.iterations = model.position_based().iterations();
      }
      if (model.solver_tolerance() > 0.0) p.tolerance = model.solver_tolerance();
      return on_volume ? models::PositionBasedModel::FromTetMesh(volume, p)
                       : models::PositionBasedModel::FromSurface(surface, p);
    }
    default:
      break;
  }
  throw std::logic_error("MakeParticleModel: not a particle model");
}

// True when three of `nodes` are not on one line (relative to the organ's size).
bool SpansAPlane(const mesh::Points& x, const std::vector<int32_t>& nodes, double size) {
  if (nodes.size() < 3) return false;
  const Eigen::Vector3d a = x.col(nodes[0]);
  size_t far = 0;
  for (size_t k = 1; k < nodes.size(); ++k) {
    if ((x.col(nodes[k]) - a).norm() > (x.col(nodes[far]) - a).norm()) far = k;
  }
  const Eigen::Vector3d b = x.col(nodes[far]);
  if ((b - a).norm() <= 1e-9 * size) return false;
  for (const int32_t c : nodes) {
    if ((b - a).cross(x.col(c) - a).norm() > 1e-9 * size * size) return true;
  }
  return false;
}

}  // namespace

std::string UnheldParts(const BuiltOrgan& organ, const std::vector<int32_t>& held) {
  const mesh::Tetrahedra& tets = organ.volume.tetrahedra;
  const mesh::Points& x = organ.rest();
  const auto n = static_cast<int32_t>(x.cols());
  const auto m = static_cast<int32_t>(tets.cols());
  if (m == 0) return "";
  // Face-connected parts, by flood fill over shared faces.
  const auto neighbours = mesh::TetFaceNeighbours(n, tets);
  std::vector<int32_t> part(static_cast<size_t>(m), -1), stack;
  int32_t parts = 0;
  for (int32_t seed = 0; seed < m; ++seed) {
    if (part[static_cast<size_t>(seed)] >= 0) continue;
    part[static_cast<size_t>(seed)] = parts;
    stack.push_back(seed);
    while (!stack.empty()) {
      const int32_t t = stack.back();
      stack.pop_back();
      for (int f = 0; f < 4; ++f) {
        const int32_t u = neighbours(f, t);
        if (u >= 0 && part[static_cast<size_t>(u)] < 0) {
          part[static_cast<size_t>(u)] = parts;
          stack.push_back(u);
        }
      }
    }
    ++parts;
  }
  // Each part's nodes (sorted, unique).
  std::vector<std::vector<int32_t>> nodes(static_cast<size_t>(parts));
  for (int32_t t = 0; t < m; ++t) {
    for (int a = 0; a < 4; ++a)
      nodes[static_cast<size_t>(part[static_cast<size_t>(t)])].push_back(tets(a, t));
  }
  for (auto& v : nodes) {
    std::sort(v.begin(), v.end());
    v.erase(std::unique(v.begin(), v.end()), v.end());
  }
  // Held parts, grown until nothing changes: a node of a held part holds the parts it is in.
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(x);
  const double size = (box.max - box.min).norm();
  std::vector<char> node_held(static_cast<size_t>(n), 0);
  for (const int32_t i : held) node_held[static_cast<size_t>(i)] = 1;
  std::vector<char> part_held(static_cast<size_t>(parts), 0);
  for (bool changed = true; changed;) {
    changed = false;
    for (int32_t p = 0; p < parts; ++p) {
      if (part_held[static_cast<size_t>(p)] != 0) continue;
      std::vector<int32_t> anchors;
      for (const int32_t i : nodes[static_cast<size_t>(p)]) {
        if (node_held[static_cast<size_t>(i)] != 0) anchors.push_back(i);
      }
      if (!SpansAPlane(x, anchors, size)) continue;
      part_held[static_cast<size_t>(p)] = 1;
      for (const int32_t i : nodes[static_cast<size_t>(p)]) node_held[static_cast<size_t>(i)] = 1;
      changed = true;
    }
  }
  int32_t free_parts = 0;
  int64_t free_tets = 0;
  for (int32_t t = 0; t < m; ++t)
    free_tets += part_held[static_cast<size_t>(part[static_cast<size_t>(t)])] == 0 ? 1 : 0;
  for (int32_t p = 0; p < parts; ++p) free_parts += part_held[static_cast<size_t>(p)] == 0 ? 1 : 0;
  if (free_parts == 0) return "";
  if (parts == 1) {
    return "nothing holds the organ (it needs fixed or displaced nodes that are not all on one "
           "line): a static solve has no unique answer";
  }
  return "the mesh falls into " + std::to_string(parts) + " parts joined face to face; " +
         std::to_string(free_parts) + " of them (" + std::to_string(free_tets) +
         " tetrahedra) are held by nothing or hang on the rest only at a vertex or along an edge, "
         "so they can move or turn freely and a static solve has no unique answer: hold them "
         "with a fixed region, or run a dynamic analysis";
}

std::vector<int32_t> SelectRegion(const scene::Region& region, const mesh::Points& rest,
                                  const std::string& field, const scene::SceneLines& lines) {
  const int64_t n = rest.cols();
  std::vector<int32_t> nodes;
  switch (region.kind_case()) {
    case scene::Region::kBox: {
      const scene::Box& b = region.box();
      const Eigen::Vector3d lo(b.min().x(), b.min().y(), b.min().z());
      const Eigen::Vector3d hi(b.max().x(), b.max().y(), b.max().z());
      for (int64_t i = 0; i < n; ++i) {
        if ((rest.col(i).array() >= lo.array()).all() &&
            (rest.col(i).array() <= hi.array()).all()) {
          nodes.push_back(static_cast<int32_t>(i));
        }
      }
      break;
    }
    case scene::Region::kSphere: {
      const scene::Sphere& s = region.sphere();
      const Eigen::Vector3d c(s.center().x(), s.center().y(), s.center().z());
      for (int64_t i = 0; i < n; ++i) {
        if ((rest.col(i) - c).norm() <= s.radius()) nodes.push_back(static_cast<int32_t>(i));
      }
      break;
    }
    case scene::Region::kNodes:
      for (int k = 0; k < region.nodes().id_size(); ++k) {
        const int32_t id = region.nodes().id(k);
        if (id < 0 || id >= n) {
          throw lines.Error(field + ".nodes.id[" + std::to_string(k) + "]",
                            "node " + std::to_string(id) + " is out of range: the mesh has " +
                                std::to_string(n) + " nodes (0.." + std::to_string(n - 1) + ")");
        }
        nodes.push_back(id);
      }
      break;
    case scene::Region::KIND_NOT_SET:
      break;
  }
  std::sort(nodes.begin(), nodes.end());
  nodes.erase(std::unique(nodes.begin(), nodes.end()), nodes.end());
  if (nodes.empty()) throw lines.Error(field, "selects no node of the mesh (on its rest shape)");
  return nodes;
}

double HistoryScale(const scene::Load& load, double t) {
  const auto& h = load.history();
  if (h.empty()) return 1.0;
  if (t <= h[0].t()) return h[0].scale();
  for (int k = 1; k < h.size(); ++k) {
    if (t <= h[k].t()) {
      const double a = (t - h[k - 1].t()) / (h[k].t() - h[k - 1].t());
      return (1.0 - a) * h[k - 1].scale() + a * h[k].scale();
    }
  }
  return h[h.size() - 1].scale();
}

mesh::Points PressureForces(const mesh::Points& rest, const mesh::Triangles& triangles,
                            const std::vector<int32_t>& nodes, double pressure) {
  mesh::Points f = mesh::Points::Zero(3, rest.cols());
  const auto in = [&](int32_t i) { return std::binary_search(nodes.begin(), nodes.end(), i); };
  for (Eigen::Index t = 0; t < triangles.cols(); ++t) {
    const int32_t a = triangles(0, t), b = triangles(1, t), c = triangles(2, t);
    if (!in(a) || !in(b) || !in(c)) continue;
    // ½ (b - a) × (c - a) = A n (outward): the pressure pushes along -n.
    const Eigen::Vector3d area_normal =
        0.5 * (rest.col(b) - rest.col(a)).cross(rest.col(c) - rest.col(a));
    const Eigen::Vector3d share = -pressure * area_normal / 3.0;
    f.col(a) += share;
    f.col(b) += share;
    f.col(c) += share;
  }
  return f;
}

BuiltOrgan BuildOrgan(const scene::Scene& scene, int index, const scene::SceneLines& lines,
                      const std::string& scene_dir) {
  const scene::Organ& organ = scene.organ(index);
  BuiltOrgan out;
  out.id = organ.id();
  out.field = "organ[" + std::to_string(index) + "]";
  out.model_name = ModelName(organ.model());
  const bool fem = scene::IsFemModel(organ.model());
  const bool volume_model =  // needs tetrahedra
      fem || organ.model().has_reduced_kl() || organ.model().has_efg() ||
      organ.model().has_efg_hybrid();
  mesh::SurfaceMesh surface;
  if (organ.mesh_case() == scene::Organ::kBuiltin) {
    out.mesh_name = "builtin:" + organ.builtin();
    out.unit = "m";
    const mesh_gen::BuiltinOrganSpec* spec = mesh_gen::FindBuiltinOrgan(organ.builtin());
    if (spec == nullptr) throw lines.Error(out.field + ".builtin", "unknown organ");
    if (spec->kind == mesh_gen::OrganKind::kVolume) {
      out.volume = mesh_gen::GenerateBuiltinOrgan(spec->name).volume;
    } else if (volume_model) {
      if (spec->kind == mesh_gen::OrganKind::kOpenSurface) {
        throw lines.Error(
            out.field + ".builtin",
            std::string(spec->name) +
                " is an open surface and bounds no volume: FEM, EFG and reduced models need "
                "tetrahedra (use a particle model)");
      }
      // A closed surface filled with tetrahedra (a new node numbering: see builtin_organs.h).
      out.volume = mesh_gen::GenerateBuiltinOrganVolume(spec->name);
    } else {
      surface = mesh_gen::GenerateBuiltinOrgan(spec->name).surface;
    }
  } else {
    out.mesh_name = organ.file();
    std::filesystem::path path(organ.file());
    if (path.is_relative()) path = std::filesystem::path(scene_dir) / path;
    mesh_io::ReadOptions read;
    const auto unit = mesh_io::ParseUnit(organ.unit().empty() ? "m" : organ.unit());
    read.unit = unit.value_or(mesh_io::Unit::kMetre);
    out.unit = mesh_io::UnitName(read.unit);
    mesh_io::MeshData data = mesh_io::ReadMeshFile(path.string(), read);
    if (data.tetrahedra.cols() > 0) {
      out.volume.vertices = std::move(data.vertices);
      out.volume.tetrahedra = std::move(data.tetrahedra);
    } else if (volume_model) {
      throw lines.Error(
          out.field + ".file",
          "\"" + organ.file() +
              "\" holds no tetrahedra: FEM, EFG and reduced models need a volume mesh (fill a "
              "closed surface with: somasim-mesh tetrahedralize)");
    } else {
      surface.vertices = std::move(data.vertices);
      surface.triangles = std::move(data.triangles);
    }
  }
  if (out.volume.tetrahedra.cols() > 0) {
    if (organ.model().kind_case() == Model::kMolecular) {
      throw lines.Error(out.field + ".model.molecular",
                        "the molecular model runs on a surface mesh; " + out.mesh_name +
                            " is a volume (use mass_spring or position_based, or a FEM model)");
    }
    out.triangles = mesh::ExtractBoundarySurface(out.volume).triangles;
  } else {
    out.volume.vertices = surface.vertices;
    out.triangles = surface.triangles;
  }

  // Nodes in no element have no mass and no stiffness: they are held still, and reported.
  out.unused_nodes = mesh::UnreferencedNodes(static_cast<int32_t>(out.rest().cols()), out.triangles,
                                             out.volume.tetrahedra);

  try {
    if (fem) {
      auto model = models::fem::FemModel::FromTetMesh(out.volume, FemParametersOf(organ));
      out.fem = model.get();
      out.model = std::move(model);
    } else if (organ.model().has_efg()) {
      auto model = models::meshless::EfgModel::FromTetMesh(
          out.volume, EfgParametersOf(organ, organ.model().efg()));
      out.efg = model.get();
      out.model = std::move(model);
    } else if (organ.model().has_efg_hybrid()) {
      auto model =
          models::meshless::EfgHybridModel::FromTetMesh(out.volume, EfgHybridParametersOf(organ));
      out.efg_hybrid = model.get();
      out.model = std::move(model);
    } else if (organ.model().has_reduced_kl()) {
      std::filesystem::path path(organ.model().reduced_kl().file());
      if (path.is_relative()) path = std::filesystem::path(scene_dir) / path;
      try {
        out.model = LoadReducedModel(path.string(), &out.volume).Release();
      } catch (const ReducedFileError& e) {
        throw lines.Error(out.field + ".model.reduced_kl.file", e.what());
      }
    } else {
      out.model = MakeParticleModel(organ, out.volume, surface);
    }
  } catch (const std::invalid_argument& e) {
    throw lines.Error(out.field, out.mesh_name + ": " + e.what());
  }
  out.dt = organ.model().dt() > 0.0 ? organ.model().dt() : 1e-3;
  out.solver_tolerance = organ.model().solver_tolerance();
  out.solver_max_iterations = organ.model().solver_max_iterations();
  for (int k = 0; k < organ.fixed_size(); ++k) {
    const std::vector<int32_t> held = SelectRegion(
        organ.fixed(k), out.rest(), out.field + ".fixed[" + std::to_string(k) + "]", lines);
    out.fixed_nodes.insert(out.fixed_nodes.end(), held.begin(), held.end());
  }
  out.fixed_nodes.insert(out.fixed_nodes.end(), out.unused_nodes.begin(), out.unused_nodes.end());
  std::sort(out.fixed_nodes.begin(), out.fixed_nodes.end());
  out.fixed_nodes.erase(std::unique(out.fixed_nodes.begin(), out.fixed_nodes.end()),
                        out.fixed_nodes.end());
  return out;
}

}  // namespace somasim::organs
