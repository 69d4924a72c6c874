#include "common/scene/scene.h"

#include <google/protobuf/io/tokenizer.h>
#include <google/protobuf/text_format.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <fstream>
#include <set>
#include <sstream>
#include <string>

#include "common/mesh/geometry.h"
#include "common/mesh_gen/builtin_organs.h"
#include "common/scene/first_error.h"

namespace somasim::scene {
namespace {

using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::TextFormat;

std::string Format(const std::string& file, int line, const std::string& field,
                   const std::string& message) {
  std::string out = file;
  if (line > 0) out += ":" + std::to_string(line);
  out += ": ";
  if (!field.empty()) out += field + ": ";
  return out + message;
}

// A position in the scene being checked: the message, its field path and its location tree,
// so that a fault names the field and its line (or the enclosing value's line when the field
// was not written).
class Where {
 public:
  Where(const std::string* file, const TextFormat::ParseInfoTree* tree, const Message* message,
        std::string path, int line, SceneLines* lines)
      : file_(file),
        tree_(tree),
        message_(message),
        path_(std::move(path)),
        line_(line),
        lines_(lines) {
    if (lines_ != nullptr && !path_.empty()) lines_->Record(path_, line_);
  }

  int LineOf(const char* field, int index = -1) const {
    const FieldDescriptor* fd = message_->GetDescriptor()->FindFieldByName(field);
    if (tree_ != nullptr && fd != nullptr) {
      const auto location = tree_->GetLocation(fd, fd->is_repeated() ? index : -1);
      if (location.line >= 0) return location.line + 1;
    }
    return line_;
  }
  std::string PathOf(const char* field, int index = -1) const {
    std::string p = path_.empty() ? std::string(field) : path_ + "." + field;
    if (index >= 0) p += "[" + std::to_string(index) + "]";
    return p;
  }
  Where Child(const char* field, const Message& child, int index = -1) const {
    const FieldDescriptor* fd = message_->GetDescriptor()->FindFieldByName(field);
    const TextFormat::ParseInfoTree* nested = nullptr;
    if (tree_ != nullptr && fd != nullptr) {
      nested = tree_->GetTreeForNested(fd, fd->is_repeated() ? index : -1);
    }
    return {file_, nested, &child, PathOf(field, index), LineOf(field, index), lines_};
  }
  [[noreturn]] void Fail(const char* field, const std::string& message, int index = -1) const {
    throw SceneError(*file_, LineOf(field, index), PathOf(field, index), message);
  }
  [[noreturn]] void FailHere(const std::string& message) const {
    throw SceneError(*file_, line_, path_, message);
  }
  void Positive(const char* field, double value) const {
    if (!(value > 0.0) || !std::isfinite(value)) Fail(field, "must be a finite value > 0");
  }
  void NonNegative(const char* field, double value) const {
    if (!(value >= 0.0) || !std::isfinite(value)) Fail(field, "must be a finite value >= 0");
  }
  void Finite(const char* field, const Vec3& v) const {
    if (!std::isfinite(v.x()) || !std::isfinite(v.y()) || !std::isfinite(v.z())) {
      Fail(field, "must have finite x, y and z");
    }
  }

 private:
  const std::string* file_;
  const TextFormat::ParseInfoTree* tree_;
  const Message* message_;
  std::string path_;
  int line_;
  SceneLines* lines_;
};

void CheckRegion(const Where& w, const Region& region) {
  switch (region.kind_case()) {
    case Region::kBox: {
      const Where b = w.Child("box", region.box());
      b.Finite("min", region.box().min());
      b.Finite("max", region.box().max());
      if (!(region.box().min().x() < region.box().max().x()) ||
          !(region.box().min().y() < region.box().max().y()) ||
          !(region.box().min().z() < region.box().max().z())) {
        b.Fail("max", "must be greater than min on every axis");
      }
      return;
    }
    case Region::kSphere: {
      const Where s = w.Child("sphere", region.sphere());
      s.Finite("center", region.sphere().center());
      s.Positive("radius", region.sphere().radius());
      return;
    }
    case Region::kNodes: {
      const Where n = w.Child("nodes", region.nodes());
      if (region.nodes().id_size() == 0) n.FailHere("lists no node");
      for (int k = 0; k < region.nodes().id_size(); ++k) {
        if (region.nodes().id(k) < 0) n.Fail("id", "must be >= 0 (a 0-based node index)", k);
      }
      return;
    }
    case Region::KIND_NOT_SET:
      break;
  }
  w.FailHere("needs a box, a sphere or nodes");
}

void CheckPoisson(const Where& m, double nu) {
  if (!(nu > -1.0 && nu < 0.5)) m.Fail("poisson_ratio", "must lie in (-1, 0.5)");
}

void CheckMaterial(const Where& m, const Material& material, const Model& model) {
  m.Positive("density", material.density());
  m.NonNegative("damping_ratio", material.damping_ratio());
  m.NonNegative("rayleigh_mass", material.rayleigh_mass());
  m.NonNegative("rayleigh_stiffness", material.rayleigh_stiffness());
  const bool hyperelastic = model.kind_case() == Model::kFemHyperelastic;
  if (material.law_case() != Material::LAW_NOT_SET && !hyperelastic) {
    m.FailHere(
        "a named law (liver_nava2008, neo_hookean, stvk, reduced_polynomial) needs the "
        "fem_hyperelastic model");
  }
  if (hyperelastic) {
    switch (material.law_case()) {
      case Material::kLiverNava2008: {
        const double nu = material.liver_nava2008().poisson_ratio();
        if (!(nu >= 0.0 && nu < 0.5)) {
          m.Child("liver_nava2008", material.liver_nava2008())
              .Fail("poisson_ratio", "must lie in [0, 0.5) (0: the default 0.49)");
        }
        break;
      }
      case Material::kNeoHookean: {
        const Where n = m.Child("neo_hookean", material.neo_hookean());
        n.Positive("c10", material.neo_hookean().c10());
        n.Positive("d1", material.neo_hookean().d1());
        break;
      }
      case Material::kStvk:
        m.Positive("youngs_modulus", material.youngs_modulus());
        CheckPoisson(m, material.poisson_ratio());
        break;
      case Material::kReducedPolynomial: {
        const ReducedPolynomial& rp = material.reduced_polynomial();
        const Where r = m.Child("reduced_polynomial", rp);
        if (rp.c_size() < 1 || rp.c_size() > 5) r.FailHere("needs 1 to 5 coefficients c");
        if (rp.d_size() < 1 || rp.d_size() > 3) r.FailHere("needs 1 to 3 coefficients d");
        for (int k = 0; k < rp.c_size(); ++k) {
          if (!std::isfinite(rp.c(k)) || (k == 0 && !(rp.c(k) > 0.0))) {
            r.Fail("c", k == 0 ? "C10 must be a finite value > 0" : "must be finite", k);
          }
        }
        for (int k = 0; k < rp.d_size(); ++k) {
          if (!std::isfinite(rp.d(k)) || (k == 0 ? !(rp.d(k) > 0.0) : !(rp.d(k) >= 0.0))) {
            r.Fail("d", k == 0 ? "D1 must be a finite value > 0" : "must be a finite value >= 0",
                   k);
          }
        }
        break;
      }
      case Material::LAW_NOT_SET:
        m.FailHere(
            "fem_hyperelastic needs a law: liver_nava2008, neo_hookean, stvk or "
            "reduced_polynomial");
    }
  } else {
    m.Positive("youngs_modulus", material.youngs_modulus());
    const bool efg = model.has_efg() || model.has_efg_hybrid();
    if (IsFemModel(model) || efg) CheckPoisson(m, material.poisson_ratio());
  }
  if (model.has_efg() || model.has_efg_hybrid()) {  // its damping is the model's (α and β)
    const std::string kind = model.has_efg() ? "efg" : "efg_hybrid";
    const std::string from = model.has_efg() ? "model.efg." : "model.efg_hybrid.efg.";
    if (material.rayleigh_mass() != 0.0) {
      m.Fail("rayleigh_mass",
             "the " + kind + " model takes its damping from " + from + "rayleigh_mass");
    }
    if (material.rayleigh_stiffness() != 0.0) {
      m.Fail("rayleigh_stiffness",
             "the " + kind + " model takes its damping from " + from + "rayleigh_stiffness");
    }
  }
  const bool viscous = material.prony_size() > 0 || material.liver_nava2008_prony();
  if (viscous && !IsFemModel(model)) m.FailHere("prony terms (QLV) need a FEM model");
  if (material.prony_size() > 0 && material.liver_nava2008_prony()) {
    m.Fail("liver_nava2008_prony", "give either prony terms or liver_nava2008_prony, not both");
  }
  if (material.prony_size() > 4) m.Fail("prony", "at most 4 terms", 4);
  double sum = 0.0;
  for (int k = 0; k < material.prony_size(); ++k) {
    const Where p = m.Child("prony", material.prony(k), k);
    p.NonNegative("gamma", material.prony(k).gamma());
    p.Positive("tau", material.prony(k).tau());
    sum += material.prony(k).gamma();
  }
  if (sum > 1.0) m.Fail("prony", "the gammas sum to more than 1 (G(0) = 1)", 0);
}

// An organ's, rigid body's or tool's id: present, of letters, digits, '_' and '-', and unique
// among all three (`ids` collects them).
void CheckId(const Where& w, const std::string& id, std::set<std::string>* ids) {
  if (id.empty()) w.Fail("id", "is missing");
  for (const char c : id) {
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-')) {
      w.Fail("id", "\"" + id + "\" may hold only letters, digits, '_' and '-'");
    }
  }
  if (!ids->insert(id).second) w.Fail("id", "\"" + id + "\" is used twice");
}

// A dimension left 0 takes its default; a given one must lie in (0, max].
void CheckDimension(const Where& w, const char* field, double value, double max) {
  if (value == 0.0) return;
  if (!(value > 0.0 && value <= max)) {
    std::ostringstream message;
    message << "must be a finite value in (0, " << max << "] m (0: the default)";
    w.Fail(field, message.str());
  }
}

void CheckRigidBody(const Where& r, const RigidBody& body, std::set<std::string>* ids) {
  CheckId(r, body.id(), ids);
  if (!body.has_sphere()) r.FailHere("needs a sphere (its shape and starting place)");
  const Where s = r.Child("sphere", body.sphere());
  s.Finite("center", body.sphere().center());
  if (!(body.sphere().radius() > 0.0 && body.sphere().radius() <= 0.2)) {
    s.Fail("radius", "must be a finite value in (0, 0.2] m");
  }
  if (body.density() != 0.0) r.Positive("density", body.density());
}

void CheckTool(const Where& t, const Tool& tool, std::set<std::string>* ids) {
  CheckId(t, tool.id(), ids);
  CheckDimension(t, "shaft_length", tool.shaft_length(), 2.0);
  CheckDimension(t, "shaft_radius", tool.shaft_radius(), 0.05);
  if (tool.stiffness() != 0.0) t.Positive("stiffness", tool.stiffness());
  const double shaft = tool.shaft_length() > 0.0 ? tool.shaft_length() : 0.30;
  switch (tool.kind_case()) {
    case Tool::kGrasper: {
      const Where g = t.Child("grasper", tool.grasper());
      CheckDimension(g, "jaw_length", tool.grasper().jaw_length(), shaft);
      CheckDimension(g, "grasp_radius", tool.grasper().grasp_radius(), 0.05);
      break;
    }
    case Tool::kScalpel:
      CheckDimension(t.Child("scalpel", tool.scalpel()), "blade_length",
                     tool.scalpel().blade_length(), shaft);
      break;
    case Tool::kProbe:
    case Tool::kCamera:
      break;
    case Tool::KIND_NOT_SET:
      t.FailHere("needs a kind: probe, grasper, scalpel or camera");
  }
}

// The EFG model's settings (unset: the model's defaults).
void CheckEfg(const Where& e, const Efg& efg) {
  if (efg.has_gauss_points() && efg.gauss_points() != 4 && efg.gauss_points() != 14) {
    e.Fail("gauss_points", "must be 4 or 14 (points per tetrahedron)");
  }
  if (efg.has_support_scale() &&
      !(efg.support_scale() >= 1.0 && std::isfinite(efg.support_scale()))) {
    e.Fail("support_scale", "must be a finite value >= 1");
  }
  if (efg.has_support_neighbours() &&
      !(efg.support_neighbours() >= 1 && efg.support_neighbours() <= 64)) {
    e.Fail("support_neighbours", "must lie in 1..64");
  }
  if (efg.has_penalty_factor()) e.Positive("penalty_factor", efg.penalty_factor());
  if (efg.has_rayleigh_mass()) e.NonNegative("rayleigh_mass", efg.rayleigh_mass());
  if (efg.has_rayleigh_stiffness()) e.NonNegative("rayleigh_stiffness", efg.rayleigh_stiffness());
}

// The EFG hybrid's settings (unset: the model's defaults): its nested efg as an efg model's, and
// the surgical region's.
void CheckEfgHybrid(const Where& h, const EfgHybrid& hybrid) {
  CheckEfg(h.Child("efg", hybrid.efg()), hybrid.efg());
  if (hybrid.has_region_radius()) h.Positive("region_radius", hybrid.region_radius());
  if (hybrid.has_region_centre()) h.Finite("region_centre", hybrid.region_centre());
  if (hybrid.has_follow_fraction() &&
      !(hybrid.follow_fraction() > 0.0 && hybrid.follow_fraction() <= 1.0)) {
    h.Fail("follow_fraction", "must lie in (0, 1] (× region_radius)");
  }
  if (hybrid.has_max_region_nodes() &&
      !(hybrid.max_region_nodes() >= 1 && hybrid.max_region_nodes() <= 4096)) {
    h.Fail("max_region_nodes", "must lie in 1..4096");
  }
  if (hybrid.has_adapt_interval() && hybrid.adapt_interval() < 1) {
    h.Fail("adapt_interval", "must be >= 1 (steps)");
  }
  const double refine = hybrid.has_refine_threshold() ? hybrid.refine_threshold() : 0.01;
  if (!(refine > 0.0 && refine <= 1.0)) h.Fail("refine_threshold", "must lie in (0, 1]");
  if (hybrid.has_coarsen_threshold() &&
      !(hybrid.coarsen_threshold() >= 0.0 && hybrid.coarsen_threshold() <= refine)) {
    h.Fail("coarsen_threshold", "must lie in [0, refine_threshold]");
  }
}

void CheckOrgan(const Where& o, const Organ& organ, std::set<std::string>* ids) {
  CheckId(o, organ.id(), ids);
  switch (organ.mesh_case()) {
    case Organ::kBuiltin:
      if (mesh_gen::FindBuiltinOrgan(organ.builtin()) == nullptr) {
        o.Fail("builtin", "unknown organ \"" + organ.builtin() +
                              "\"; built in: " + mesh_gen::BuiltinOrganNames());
      }
      break;
    case Organ::kFile:
      if (organ.file().empty()) o.Fail("file", "is empty");
      break;
    case Organ::MESH_NOT_SET:
      o.FailHere("needs a mesh: builtin or file");
  }
  if (!organ.unit().empty() && organ.unit() != "m" && organ.unit() != "cm" &&
      organ.unit() != "mm") {
    o.Fail("unit", "must be m, cm or mm, not \"" + organ.unit() + "\"");
  }
  const Where m = o.Child("model", organ.model());
  const Model& model = organ.model();
  if (model.kind_case() == Model::KIND_NOT_SET) {
    m.FailHere(
        "needs a kind: mass_spring, molecular, position_based, fem_linear, fem_corotational, "
        "fem_hyperelastic, reduced_kl, efg or efg_hybrid");
  }
  m.NonNegative("dt", model.dt());
  m.NonNegative("solver_tolerance", model.solver_tolerance());
  if (model.solver_max_iterations() < 0) m.Fail("solver_max_iterations", "must be >= 0");
  if (model.has_mass_spring()) {
    m.Child("mass_spring", model.mass_spring())
        .NonNegative("anchor_stiffness", model.mass_spring().anchor_stiffness());
  }
  if (model.has_position_based() && model.position_based().iterations() < 0) {
    m.Child("position_based", model.position_based()).Fail("iterations", "must be >= 0");
  }
  if (model.has_efg()) CheckEfg(m.Child("efg", model.efg()), model.efg());
  if (model.has_efg_hybrid()) {
    CheckEfgHybrid(m.Child("efg_hybrid", model.efg_hybrid()), model.efg_hybrid());
  }
  if (model.has_reduced_kl()) {  // the material is in the reduced model's file
    if (model.reduced_kl().file().empty()) {
      m.Child("reduced_kl", model.reduced_kl()).Fail("file", "is empty");
    }
  } else {
    CheckMaterial(o.Child("material", organ.material()), organ.material(), model);
  }
  for (int k = 0; k < organ.fixed_size(); ++k) {
    CheckRegion(o.Child("fixed", organ.fixed(k), k), organ.fixed(k));
  }
}

void CheckScene(const Where& s, const Scene& scene) {
  if (scene.format_version() != kSceneFormatVersion) {
    s.Fail("format_version", "is " + std::to_string(scene.format_version()) +
                                 "; this somasim reads version " +
                                 std::to_string(kSceneFormatVersion));
  }
  if (scene.organ_size() == 0) s.FailHere("has no organ");
  std::set<std::string> ids;
  for (int k = 0; k < scene.organ_size(); ++k) {
    CheckOrgan(s.Child("organ", scene.organ(k), k), scene.organ(k), &ids);
  }
  const std::set<std::string> organ_ids = ids;
  for (int k = 0; k < scene.rigid_body_size(); ++k) {
    CheckRigidBody(s.Child("rigid_body", scene.rigid_body(k), k), scene.rigid_body(k), &ids);
  }
  for (int k = 0; k < scene.tool_size(); ++k) {
    CheckTool(s.Child("tool", scene.tool(k), k), scene.tool(k), &ids);
  }
  for (int k = 0; k < scene.load_size(); ++k) {
    const Load& load = scene.load(k);
    const Where l = s.Child("load", load, k);
    if (organ_ids.count(load.organ()) == 0) {
      l.Fail("organ", "\"" + load.organ() + "\" is not an organ of the scene");
    }
    CheckRegion(l.Child("region", load.region()), load.region());
    switch (load.kind_case()) {
      case Load::kForce:
        l.Finite("force", load.force());
        break;
      case Load::kDisplacement:
        l.Finite("displacement", load.displacement());
        break;
      case Load::kPressure:
        if (!std::isfinite(load.pressure())) l.Fail("pressure", "must be finite");
        break;
      case Load::KIND_NOT_SET:
        l.FailHere("needs a force, a displacement or a pressure");
    }
    for (int h = 0; h < load.history_size(); ++h) {
      const Where p = l.Child("history", load.history(h), h);
      if (!std::isfinite(load.history(h).t()) || !std::isfinite(load.history(h).scale())) {
        p.FailHere("t and scale must be finite");
      }
      if (h > 0 && !(load.history(h).t() > load.history(h - 1).t())) {
        p.Fail("t", "must increase from one point to the next");
      }
    }
  }
  s.Finite("gravity", scene.gravity());
  const Analysis& analysis = scene.analysis();
  const Where a = s.Child("analysis", analysis);
  switch (analysis.kind_case()) {
    case Analysis::kStaticSolve:
      if (analysis.static_solve().load_steps() < 0) {
        a.Child("static_solve", analysis.static_solve()).Fail("load_steps", "must be >= 0");
      }
      break;
    case Analysis::kQuasiStatic: {
      const Where q = a.Child("quasi_static", analysis.quasi_static());
      q.Positive("end_time", analysis.quasi_static().end_time());
      q.Positive("dt", analysis.quasi_static().dt());
      break;
    }
    case Analysis::kDynamic:
      a.Child("dynamic", analysis.dynamic()).Positive("end_time", analysis.dynamic().end_time());
      break;
    case Analysis::KIND_NOT_SET:
      break;  // the server runs the scene interactively
  }
  std::set<std::string> reduced;
  for (int k = 0; k < scene.reduction_size(); ++k) {
    const Reduction& r = scene.reduction(k);
    const Where w = s.Child("reduction", r, k);
    if (organ_ids.count(r.organ()) == 0) {
      w.Fail("organ", "\"" + r.organ() + "\" is not an organ of the scene");
    }
    if (!reduced.insert(r.organ()).second) w.Fail("organ", "has another reduction");
    for (int i = 0; i < scene.organ_size(); ++i) {
      if (scene.organ(i).id() == r.organ() && !IsFemModel(scene.organ(i).model())) {
        w.Fail("organ", "\"" + r.organ() + "\" needs a FEM model to be reduced");
      }
    }
    if (r.interaction_size() == 0) w.FailHere("needs an interaction region");
    for (int i = 0; i < r.interaction_size(); ++i) {
      CheckRegion(w.Child("interaction", r.interaction(i), i), r.interaction(i));
    }
    if (r.points_per_region() < 0) w.Fail("points_per_region", "must be >= 0");
    for (int i = 0; i < r.force_size(); ++i) {
      if (!(r.force(i) > 0.0) || !std::isfinite(r.force(i))) {
        w.Fail("force", "must be a finite value > 0", i);
      }
    }
    if (r.directions() != 0 && r.directions() != 1 && r.directions() != 3) {
      w.Fail("directions", "must be 1 (the inward normal) or 3 (and two tangents)");
    }
    w.NonNegative("creep_duration", r.creep_duration());
    w.NonNegative("creep_interval", r.creep_interval());
    if (!(r.energy_fraction() >= 0.0 && r.energy_fraction() <= 1.0)) {
      w.Fail("energy_fraction", "must lie in [0, 1] (0: the default 0.9999)");
    }
    if (r.max_modes() < 0) w.Fail("max_modes", "must be >= 0");
    w.NonNegative("creep_radius", r.creep_radius());
    if (r.nonlinear_max_modes() < 0) w.Fail("nonlinear_max_modes", "must be >= 0");
    if (!(r.cubature_tolerance() >= 0.0 && r.cubature_tolerance() < 1.0)) {
      w.Fail("cubature_tolerance", "must lie in [0, 1) (0: the default 0.01)");
    }
    if (r.nonlinear_tilts() < 0) w.Fail("nonlinear_tilts", "must be >= 0");
    if (!(r.nonlinear_tilt_deg() >= 0.0 && r.nonlinear_tilt_deg() < 90.0)) {
      w.Fail("nonlinear_tilt_deg", "must lie in [0, 90) (0: the default 35)");
    }
    for (int i = 0; i < r.nonlinear_force_size(); ++i) {
      if (!(r.nonlinear_force(i) > 0.0) || !std::isfinite(r.nonlinear_force(i))) {
        w.Fail("nonlinear_force", "must be a finite value > 0", i);
      }
    }
  }
  const Output& output = scene.output();
  for (int k = 0; k < output.time_size(); ++k) {
    const Where o = s.Child("output", output);
    if (!(output.time(k) >= 0.0) || !std::isfinite(output.time(k))) {
      o.Fail("time", "must be a finite time >= 0", k);
    }
    if (k > 0 && !(output.time(k) > output.time(k - 1))) o.Fail("time", "must increase", k);
  }
}

}  // namespace

SceneError::SceneError(const std::string& file, int line, const std::string& field,
                       const std::string& message)
    : std::runtime_error(Format(file, line, field, message)),
      file_(file),
      line_(line),
      field_(field) {}

bool IsFemModel(const Model& model) {
  return model.kind_case() == Model::kFemLinear || model.kind_case() == Model::kFemCorotational ||
         model.kind_case() == Model::kFemHyperelastic;
}

int SceneLines::LineOf(const std::string& field) const {
  std::string f = field;
  while (!f.empty()) {
    const auto it = lines_.find(f);
    if (it != lines_.end()) return it->second;
    const size_t cut = f.find_last_of(".[");
    if (cut == std::string::npos) break;
    f.resize(cut);
  }
  return 0;
}

SceneError SceneLines::Error(const std::string& field, const std::string& message) const {
  return {file_, LineOf(field), field, message};
}

Scene ParseScene(std::string_view text, const std::string& file_name, SceneLines* lines) {
  Scene scene;
  TextFormat::Parser parser;
  FirstError errors("not a scene in protobuf text format");
  TextFormat::ParseInfoTree tree;
  parser.RecordErrorsTo(&errors);
  parser.WriteLocationsTo(&tree);
  google::protobuf::io::ArrayInputStream input(text.data(), static_cast<int>(text.size()));
  if (text.size() > (1u << 26) ||  // 64 MiB: a scene is a few kilobytes
      !parser.Parse(&input, &scene)) {
    throw SceneError(
        file_name, std::max(errors.line(), 0), "",
        text.size() > (1u << 26) ? "larger than 64 MiB: not a scene" : errors.message());
  }
  if (lines != nullptr) *lines = SceneLines(file_name);
  CheckScene(Where(&file_name, &tree, &scene, "", 1, lines), scene);
  return scene;
}

Scene LoadSceneFile(const std::string& path, SceneLines* lines) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw SceneError(path, 0, "", "cannot open the file");
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) throw SceneError(path, 0, "", "cannot read the file");
  return ParseScene(text.str(), path, lines);
}

Scene DefaultScene(std::string_view organ) {
  const mesh_gen::BuiltinOrganSpec* spec = mesh_gen::FindBuiltinOrgan(organ);
  if (spec == nullptr) {
    throw std::invalid_argument("unknown organ \"" + std::string(organ) +
                                "\"; built in: " + mesh_gen::BuiltinOrganNames());
  }
  const bool sheet = spec->kind == mesh_gen::OrganKind::kOpenSurface;
  // The extent only: a closed surface's filling keeps its boundary vertices, so the surface's box
  // is the volume's (and costs no tetrahedralisation).
  const mesh_gen::BuiltinOrgan generated = mesh_gen::GenerateBuiltinOrgan(spec->name);
  const mesh::Points& rest = spec->kind == mesh_gen::OrganKind::kVolume
                                 ? generated.volume.vertices
                                 : generated.surface.vertices;
  const mesh::BoundingBox box = mesh::ComputeBoundingBox(rest);
  const Eigen::Vector3d size = box.max - box.min;
  Scene scene;
  scene.set_format_version(kSceneFormatVersion);
  scene.set_name("builtin:" + std::string(spec->name));
  Organ* o = scene.add_organ();
  o->set_id(std::string(spec->name));
  o->set_builtin(std::string(spec->name));
  Material* m = o->mutable_material();
  m->set_density(1000.0);  // [kg/m³]
  // Soft tissue, E >= 5 kPa, and at least 20 ρ g L (L the longest side) so that the weight strains
  // the body by a few per cent at most: the small strains the corotational model is right for
  // (a 5 kPa liver on a table lets its lobes flop by 15 cm, which needs fem_hyperelastic).
  // liver4055: 46 kPa; SOFA's 16 m beam: 3.1 MPa.
  m->set_youngs_modulus(std::max(5e3, 20.0 * 1000.0 * 9.81 * size.maxCoeff()));  // [Pa]
  if (sheet) {
    o->mutable_model()->mutable_mass_spring()->set_implicit(true);
    o->mutable_model()->set_dt(1e-3);
    m->set_damping_ratio(0.5);  // settles within the second
    scene.mutable_analysis()->mutable_dynamic()->set_end_time(1.0);
  } else {
    o->mutable_model()->mutable_fem_corotational();
    m->set_poisson_ratio(0.45);
    scene.mutable_analysis()->mutable_static_solve()->set_load_steps(2);
  }
  // Resting on a table: everything within 10 % of the height from the lowest z is held (a
  // margin of one diagonal around the other axes). The patch is held along its lowest-x edge.
  const double margin = size.norm();
  Box* held = o->add_fixed()->mutable_box();
  held->mutable_min()->set_x(box.min.x() - margin);
  held->mutable_min()->set_y(box.min.y() - margin);
  held->mutable_min()->set_z(box.min.z() - margin);
  held->mutable_max()->set_x(sheet ? box.min.x() + 0.1 * size.x() : box.max.x() + margin);
  held->mutable_max()->set_y(box.max.y() + margin);
  held->mutable_max()->set_z(sheet ? box.max.z() + margin : box.min.z() + 0.1 * size.z());
  scene.mutable_gravity()->set_z(-9.81);  // [m/s²]
  return scene;
}

}  // namespace somasim::scene
