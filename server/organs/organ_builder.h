// Building a scene's organs (idl/scene.proto) into tissue models on their meshes: the mesh
// (built-in or file, in metres, in the input's node order), the model with its material, the
// held nodes, and the node sets of regions. Faults only a mesh can reveal (a node id out of
// range, a region that selects no node, a FEM or EFG model on a surface) are SceneErrors naming
// the file, line and field.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/mesh/mesh_types.h"
#include "common/scene/scene.h"
#include "server/models/fem/fem_model.h"
#include "server/models/meshless/efg_hybrid_model.h"
#include "server/models/meshless/efg_model.h"
#include "server/models/tissue_model.h"

namespace somasim::organs {

struct BuiltOrgan {
  std::string id;
  std::string field;       // "organ[k]", for errors
  std::string model_name;  // the Model kind's field name, e.g. "fem_hyperelastic"
  std::string mesh_name;   // "builtin:liver4055" or the file as the scene gives it
  std::string unit;        // what the file's coordinates were taken to be: "m", "cm", "mm"
  // The mesh the model runs on, in the input's node order [m]: tetrahedra for volume models
  // (and for particle models on a volume), triangles for a surface (empty tetrahedra).
  mesh::TetMesh volume;
  mesh::Triangles triangles;  // the surface's triangles; a volume's boundary (for pressure)
  std::unique_ptr<models::TissueModel> model;
  const models::fem::FemModel* fem = nullptr;       // model, when it is a FEM model
  const models::meshless::EfgModel* efg = nullptr;  // model, when it is the EFG model
  // model, when it is the EFG hybrid (efg stays null: the hybrid is a model of its own)
  const models::meshless::EfgHybridModel* efg_hybrid = nullptr;
  double dt = 1e-3;                   // [s], the model's step
  double solver_tolerance = 0.0;      // the scene's, 0 = the model's default
  int solver_max_iterations = 0;      // the scene's, 0 = the model's default
  std::vector<int32_t> fixed_nodes;   // sorted, unique: the fixed regions
  std::vector<int32_t> unused_nodes;  // in no element: held still, reported
  const mesh::Points& rest() const { return volume.vertices; }
};

// Builds organ `index` of the scene. Files are relative to `scene_dir`. Throws SceneError (via
// `lines`) for what the mesh refuses; mesh_io::MeshError for an unreadable or malformed file.
BuiltOrgan BuildOrgan(const scene::Scene& scene, int index, const scene::SceneLines& lines,
                      const std::string& scene_dir);

// The nodes of `rest` (3 × n) a region selects, sorted and unique. `field` names the region in
// errors (e.g. "load[2].region"); a region that selects nothing, or a node id >= n, is refused.
std::vector<int32_t> SelectRegion(const scene::Region& region, const mesh::Points& rest,
                                  const std::string& field, const scene::SceneLines& lines);

// Why a static solve of the organ held at `held` (sorted node ids) has no unique answer, or ""
// when it has one. The tetrahedra fall into face-connected parts; a part is held when it has
// three non-collinear held nodes, or shares them with held parts. A part that is not — a body
// nothing holds, or a piece joined to the rest only at a vertex or along an edge (non-manifold
// meshes, e.g. SOFA's raptor) — can move or turn freely, so its stiffness is singular.
// The test is conservative: pieces that hold one another only jointly (each held along a line)
// are refused too.
std::string UnheldParts(const BuiltOrgan& organ, const std::vector<int32_t>& held);

// A load's scale at time t [s]: piecewise linear through the history, held before the first and
// after the last point; 1 for an empty history.
double HistoryScale(const scene::Load& load, double t);

// Nodal forces [N] (3 × n) of a dead pressure p [Pa] on the triangles (3 × m, outward oriented)
// whose three corners are all in `nodes` (sorted): -p A n / 3 at each corner, on `rest`.
mesh::Points PressureForces(const mesh::Points& rest, const mesh::Triangles& triangles,
                            const std::vector<int32_t>& nodes, double pressure);

}  // namespace somasim::organs
