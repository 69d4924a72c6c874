#include "server/session/session.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <stdexcept>

#include "common/mesh/geometry.h"
#include "common/mesh_gen/builtin_organs.h"

namespace somasim::server {
namespace {

constexpr double kDefaultFemStep = 0.01;  // [s] the built-in scenes' FEM step (100 Hz)
constexpr int kInteractiveCgIterations = 30;
constexpr double kDefaultSurfaceStep = 0.005;  // [s] the built-in closed surfaces' step (200 Hz)
constexpr double kSurfacePoisson = 0.45;       // [-] for the anchors' flat-punch rule

// Seed 002's closed surfaces (spleen600, kidney2000, gallbladder5400) run as it runs them: an
// implicit mass-spring shell on the surface mesh, with a zero-rest-length anchor at every node
// (seed 001 eq. 10) standing in for the interior it does not simulate. The anchor's k_s is the
// stiffness of the node's share of the surface pressed into a half-space of the material: a rigid
// flat punch of radius a on an elastic half-space, k = 2 E a / (1 - ν²) (Sneddon 1965), with
// π a² = the organ's area / its node count. gallbladder5400 (E = 19.6 kPa): a = 1.1 mm, k_s ≈ 53
// N/m.
void MakeShapeRetainingSurface(scene::Organ* organ, const mesh_gen::BuiltinOrganSpec& spec) {
  const mesh::SurfaceMesh surface = mesh_gen::GenerateBuiltinOrgan(spec.name).surface;
  const double area = mesh::SurfaceArea(surface);  // [m²]
  const double node_radius =
      std::sqrt(area / (std::numbers::pi * static_cast<double>(surface.vertices.cols())));  // [m]
  scene::Material* m = organ->mutable_material();
  const double anchor =
      2.0 * m->youngs_modulus() * node_radius / (1.0 - kSurfacePoisson * kSurfacePoisson);  // [N/m]
  scene::Model* model = organ->mutable_model();
  model->Clear();
  model->mutable_mass_spring()->set_implicit(true);
  model->mutable_mass_spring()->set_anchor_stiffness(anchor);
  model->set_dt(kDefaultSurfaceStep);
  m->clear_poisson_ratio();
  m->set_damping_ratio(0.5);  // settles within a few tenths of a second after a touch
}

// Capacity of an organ's per-step springs: each tool's contact (3 corners) and grasp, and each
// rigid body's tissue contacts (3 corners per touching triangle).
int32_t AttachmentCapacity(int32_t num_tools, const contact::ContactSettings& settings,
                           int32_t num_rigid, const contact::RigidSphereSettings& rigid) {
  return num_tools * (3 + settings.grasp.max_nodes) + num_rigid * 3 * rigid.max_tissue_contacts;
}

}  // namespace

contact::ToolShape ToolShapeOf(const scene::Tool& tool) {
  contact::ToolShape shape;
  switch (tool.kind_case()) {
    case scene::Tool::kGrasper:
      shape.kind = contact::ToolKind::kGrasper;
      if (tool.grasper().jaw_length() > 0.0) shape.jaw_length = tool.grasper().jaw_length();
      if (tool.grasper().grasp_radius() > 0.0) shape.grasp_radius = tool.grasper().grasp_radius();
      break;
    case scene::Tool::kScalpel:
      shape.kind = contact::ToolKind::kScalpel;
      if (tool.scalpel().blade_length() > 0.0) shape.blade_length = tool.scalpel().blade_length();
      break;
    case scene::Tool::kCamera:
      shape.kind = contact::ToolKind::kCamera;
      break;
    case scene::Tool::kProbe:
    case scene::Tool::KIND_NOT_SET:
      shape.kind = contact::ToolKind::kProbe;
      break;
  }
  if (tool.shaft_length() > 0.0) shape.shaft_length = tool.shaft_length();
  if (tool.shaft_radius() > 0.0) shape.shaft_radius = tool.shaft_radius();
  return shape;
}

scene::Scene ServerDefaultScene(std::string_view organ) {
  scene::Scene s = scene::DefaultScene(organ);
  s.clear_analysis();
  for (scene::Organ& o : *s.mutable_organ()) {
    const mesh_gen::BuiltinOrganSpec* spec = mesh_gen::FindBuiltinOrgan(o.builtin());
    if (spec != nullptr && spec->kind == mesh_gen::OrganKind::kClosedSurface) {
      MakeShapeRetainingSurface(&o, *spec);
      continue;
    }
    if (!scene::IsFemModel(o.model())) continue;
    o.mutable_model()->set_dt(kDefaultFemStep);
    // An interactive budget: the conjugate gradients stop after 30 iterations, warm-started
    // from the last step (the offline solver converges fully instead).
    o.mutable_model()->set_solver_max_iterations(kInteractiveCgIterations);
    // Some damping, so that the organ settles after it is pressed or pulled [1/s], [s].
    o.mutable_material()->set_rayleigh_mass(0.5);
    o.mutable_material()->set_rayleigh_stiffness(0.001);
  }
  scene::Tool* probe = s.add_tool();
  probe->set_id("probe");
  probe->mutable_probe();
  scene::Tool* grasper = s.add_tool();
  grasper->set_id("grasper");
  grasper->mutable_grasper()->set_jaw_length(0.015);
  grasper->mutable_grasper()->set_grasp_radius(0.003);
  scene::Tool* scalpel = s.add_tool();
  scalpel->set_id("scalpel");
  scalpel->mutable_scalpel()->set_blade_length(0.010);
  scene::Tool* laparoscope = s.add_tool();  // a pose only: the viewers' l key looks through it
  laparoscope->set_id("laparoscope");
  laparoscope->mutable_camera();
  return s;
}

Session::Session(const scene::Scene& scene, const scene::SceneLines& lines,
                 const std::string& scene_dir, const contact::ContactSettings& contact_settings)
    : scene_(scene), contact_settings_(contact_settings) {
  gravity_ = Eigen::Vector3d(scene.gravity().x(), scene.gravity().y(), scene.gravity().z());
  if (scene.organ_size() == 0) throw std::invalid_argument("scene: no organ");
  const contact::RigidSphereSettings rigid_defaults;
  const int32_t capacity = AttachmentCapacity(scene.tool_size(), contact_settings_,
                                              scene.rigid_body_size(), rigid_defaults);
  dt_ = std::numeric_limits<double>::infinity();
  for (int k = 0; k < scene.organ_size(); ++k) {
    auto o = std::make_unique<SessionOrgan>();
    o->built = organs::BuildOrgan(scene, k, lines, scene_dir);
    o->state = o->built.model->MakeState();
    o->surface = std::make_unique<contact::OrganSurface>(o->state->positions, o->built.triangles);
    if (o->built.fem != nullptr && !o->built.fixed_nodes.empty()) {
      o->compliance = std::make_unique<contact::FemCompliance>(*o->built.fem, o->built.fixed_nodes);
      // Every surface node's compliance now, so that the first touch costs the physics nothing.
      std::vector<int32_t> surface_nodes(o->built.triangles.data(),
                                         o->built.triangles.data() + o->built.triangles.size());
      std::sort(surface_nodes.begin(), surface_nodes.end());
      surface_nodes.erase(std::unique(surface_nodes.begin(), surface_nodes.end()),
                          surface_nodes.end());
      o->compliance->Precompute(surface_nodes);
    }
    if (o->built.fem != nullptr && o->built.volume.tetrahedra.cols() > 0) {
      o->cutter =
          std::make_unique<cutting::TetCutter>(o->built.volume.tetrahedra, o->state->positions);
      o->cut_before = o->state->positions;
    }
    o->attachments.resize(static_cast<size_t>(capacity));
    dt_ = std::min(dt_, o->built.dt);
    organs_.push_back(std::move(o));
  }
  for (const scene::Tool& t : scene.tool()) {
    auto tool = std::make_unique<SessionTool>();
    tool->id = t.id();
    tool->shape = ToolShapeOf(t);
    // Tools wait above the scene until their first command.
    tool->command.pose.tip = Eigen::Vector3d(0.0, 0.0, 10.0);
    contact::ContactSettings settings = contact_settings_;
    if (t.stiffness() > 0.0) settings.tool_stiffness = t.stiffness();
    if (tool->shape.kind != contact::ToolKind::kCamera) {
      for (size_t k = 0; k < organs_.size(); ++k) {
        tool->contacts.push_back(
            std::make_unique<contact::ToolContact>(tool->shape, settings, tool->command.pose));
      }
    }
    tool->force_model.damping = settings.damping;
    tool->force_model.force_limit = settings.force_limit;
    tools_.push_back(std::move(tool));
  }
  for (const scene::RigidBody& r : scene.rigid_body()) {
    auto rigid = std::make_unique<SessionRigid>();
    rigid->id = r.id();
    contact::RigidSphereSettings settings;
    settings.radius = r.sphere().radius();
    if (r.density() > 0.0) settings.density = r.density();
    const Eigen::Vector3d centre(r.sphere().center().x(), r.sphere().center().y(),
                                 r.sphere().center().z());
    rigid->sphere = std::make_unique<contact::RigidSphere>(settings, centre);
    rigid->settings = settings;
    rigid->start = centre;
    double best = std::numeric_limits<double>::infinity();
    for (size_t k = 0; k < organs_.size(); ++k) {
      const mesh::BoundingBox box = mesh::ComputeBoundingBox(organs_[k]->state->positions);
      // Distance from the centre to the box (0 inside).
      const Eigen::Vector3d outside =
          (box.min - centre).cwiseMax(centre - box.max).cwiseMax(Eigen::Vector3d::Zero());
      if (outside.norm() < best) {
        best = outside.norm();
        rigid->organ = static_cast<int32_t>(k);
      }
    }
    rigid_.push_back(std::move(rigid));
  }
}

Session::~Session() = default;

int32_t Session::OrganIndex(std::string_view id) const {
  for (size_t k = 0; k < organs_.size(); ++k) {
    if (organs_[k]->built.id == id) return static_cast<int32_t>(k);
  }
  return -1;
}

int32_t Session::ToolIndex(std::string_view id) const {
  for (size_t t = 0; t < tools_.size(); ++t) {
    if (tools_[t]->id == id) return static_cast<int32_t>(t);
  }
  return -1;
}

void Session::SetToolCommand(int32_t tool, const ToolCommandInput& command) {
  if (tool < 0 || tool >= num_tools()) return;
  SessionTool& t = *tools_[static_cast<size_t>(tool)];
  if (!contact::ToolPoseError(command.pose).empty()) return;  // the app checked; stay safe
  t.command = command;
  t.commanded = true;
}

void Session::Emit(SessionEventRecord::Kind kind, int32_t organ, int32_t tool, int32_t detail) {
  if (num_events_ == kMaxEvents) {
    // Keep the newest: drop the oldest.
    std::copy(events_.begin() + 1, events_.end(), events_.begin());
    --num_events_;
    ++events_dropped_;
  }
  SessionEventRecord& e = events_[static_cast<size_t>(num_events_++)];
  e.kind = kind;
  e.sim_time = time_;
  e.organ = organ;
  e.tool = tool;
  e.detail = detail;
}

std::span<const SessionEventRecord> Session::TakeEvents() {
  std::copy(events_.begin(), events_.begin() + num_events_, taken_.begin());
  const size_t n = static_cast<size_t>(num_events_);
  num_events_ = 0;
  return {taken_.data(), n};
}

void Session::Step() {
  time_ += dt_;
  ++ticks_;
  for (int32_t t = 0; t < num_tools(); ++t) {
    if (tools_[static_cast<size_t>(t)]->shape.kind == contact::ToolKind::kScalpel) Cut(t);
  }
  for (int32_t k = 0; k < num_organs(); ++k) {
    SessionOrgan& o = *organs_[static_cast<size_t>(k)];
    // Half a tick of slack so that rounding in the sums never skips a step.
    if (o.time + 0.5 * dt_ <= time_) StepOrgan(k);
  }
  for (int32_t t = 0; t < num_tools(); ++t) UpdateForceModel(t);
}

void Session::StepOrgan(int32_t k) {
  SessionOrgan& o = *organs_[static_cast<size_t>(k)];
  const mesh::Points& x = o.state->positions;
  o.surface->Refit(x);
  o.num_attachments = 0;
  const auto append = [&o](std::span<const models::Attachment> springs) {
    const size_t room = o.attachments.size() - static_cast<size_t>(o.num_attachments);
    const size_t n = std::min(room, springs.size());
    std::copy_n(springs.begin(), n, o.attachments.begin() + o.num_attachments);
    o.num_attachments += static_cast<int32_t>(n);
  };
  for (auto& tool : tools_) {
    if (tool->contacts.empty()) continue;
    contact::ToolContact& c = *tool->contacts[static_cast<size_t>(k)];
    if (tool->blade_engaged) {  // the blade is in the tissue: it cuts, it does not push
      c.Reset(tool->command.pose);
      continue;
    }
    c.Update(tool->command.pose, *o.surface, x);
    append(c.attachments());
  }
  for (auto& r : rigid_) {
    if (r->organ != k) continue;
    r->sphere->CollectTissueContacts(o.surface->tree(), x);
    append(r->sphere->attachments());
  }
  models::StepInputs inputs;
  inputs.dt = o.built.dt;
  inputs.gravity = gravity_;
  inputs.fixed_nodes = o.built.fixed_nodes;
  inputs.attachments = {o.attachments.data(), static_cast<size_t>(o.num_attachments)};
  const models::StepStatus status = o.built.model->Step(inputs, o.state.get());
  o.time += o.built.dt;
  ++organ_steps_;
  if (status != models::StepStatus::kOk) {
    if (status != models::StepStatus::kBadInput) {
      // The model restored its last good state. Started again from it with the same inputs, the
      // step would diverge again, and the organ would freeze: take its kinetic energy out, so
      // the next step starts at rest where the last good one ended.
      o.state->velocities.setZero();
    }
    ++o.rejected_steps;
    ++rejected_steps_;
    Emit(SessionEventRecord::Kind::kStepRejected, k, -1, static_cast<int32_t>(status));
  }
  for (auto& r : rigid_) {
    if (r->organ != k) continue;
    // The tool nearest to the sphere meets it.
    const SessionTool* nearest = nullptr;
    double best = std::numeric_limits<double>::infinity();
    for (const auto& tool : tools_) {
      if (tool->shape.kind == contact::ToolKind::kCamera || !tool->commanded) continue;
      const double d = (tool->command.pose.tip - r->sphere->position()).squaredNorm();
      if (d < best) {
        best = d;
        nearest = tool.get();
      }
    }
    if (nearest != nullptr) r->sphere->UpdateTool(nearest->shape, nearest->command.pose);
    r->sphere->Step(o.built.dt, gravity_, o.state->positions);
  }
}

void Session::Cut(int32_t t) {
  SessionTool& tool = *tools_[static_cast<size_t>(t)];
  const contact::ToolPose& pose = tool.command.pose;
  const Eigen::Vector3d p = pose.tip;
  const Eigen::Vector3d q = contact::PointOnShaft(pose, tool.shape.blade_length);
  const bool engaged = tool.commanded && (tool.command.buttons & kCutButton) != 0;
  const bool jumped =
      (p - tool.blade_p).norm() > kMaxBladeStep || (q - tool.blade_q).norm() > kMaxBladeStep;
  if (tool.blade_engaged && (!engaged || jumped) && tool.incision_removed > 0) {
    // The incision ends: one event for it, with what it removed.
    Emit(SessionEventRecord::Kind::kCut, tool.incision_organ, t, tool.incision_removed);
    tool.incision_removed = 0;
  }
  if (engaged && (!tool.blade_engaged || jumped)) {
    for (auto& o : organs_) {
      if (o->cutter) o->cutter->BeginIncision();
    }
  } else if (engaged) {
    const models::SweptQuad sweep{tool.blade_p, tool.blade_q, p, q};
    for (int32_t k = 0; k < num_organs(); ++k) {
      SessionOrgan& o = *organs_[static_cast<size_t>(k)];
      int32_t removed = 0;
      if (o.cutter) {
        o.cut_before = o.state->positions;  // same size: no allocation
        const cutting::CutStepResult r = o.cutter->Step(sweep, &o.state->positions);
        if (r.removed > 0 || r.relocated > 0) {
          o.built.fem->ApplyCut(o.cutter->removed_tets(), o.cutter->moved_nodes(), o.cut_before,
                                o.state.get());
        }
        removed = r.removed;
        if (removed > 0) ++o.topology_version;
      } else if (o.built.model->SupportsCutting()) {
        removed = o.built.model->Cut(sweep, o.state.get());
      }
      if (removed > 0) {
        o.elements_cut += removed;
        tool.incision_removed += removed;
        tool.incision_organ = k;
      }
    }
  }
  tool.blade_engaged = engaged;
  tool.blade_p = p;
  tool.blade_q = q;
}

void Session::UpdateForceModel(int32_t t) {
  SessionTool& tool = *tools_[static_cast<size_t>(t)];
  if (tool.contacts.empty()) return;
  int32_t chosen = -1;
  for (int32_t k = 0; k < num_organs() && chosen < 0; ++k) {
    if (tool.contacts[static_cast<size_t>(k)]->grasp().holding()) chosen = k;
  }
  for (int32_t k = 0; k < num_organs() && chosen < 0; ++k) {
    if (tool.contacts[static_cast<size_t>(k)]->proxy().in_contact()) chosen = k;
  }
  const uint64_t sequence = tool.force_model.sequence + 1;
  const bool touching =
      chosen >= 0 && tool.contacts[static_cast<size_t>(chosen)]->proxy().in_contact();
  const bool grasping =
      chosen >= 0 && tool.contacts[static_cast<size_t>(chosen)]->grasp().holding();
  force_model::LocalForceModel model;
  model.damping = tool.force_model.damping;
  model.force_limit = tool.force_model.force_limit;
  if (chosen >= 0) {
    SessionOrgan& o = *organs_[static_cast<size_t>(chosen)];
    const contact::ToolContact& c = *tool.contacts[static_cast<size_t>(chosen)];
    try {
      model = contact::MakeLocalForceModel(
          c.ForLocalModel(*o.built.model, *o.state, o.compliance.get()), sequence, time_);
    } catch (const std::invalid_argument&) {
      Emit(SessionEventRecord::Kind::kForceModelRefused, chosen, t, 0);
      chosen = -1;
    }
  }
  for (const auto& r : rigid_) {
    if (r->sphere->grasped() || r->sphere->tool_force().squaredNorm() > 0.0) {
      // A held or pushed stone: its force on the tool, the same at every device position.
      force_model::Vec(model.bias_force) += r->sphere->tool_force();
    }
  }
  model.sequence = sequence;
  model.sim_time = time_;
  tool.force_model = model;
  tool.force_organ = chosen;
  if (touching != tool.was_touching) {
    Emit(touching ? SessionEventRecord::Kind::kContactBegins
                  : SessionEventRecord::Kind::kContactEnds,
         chosen, t, 0);
    tool.was_touching = touching;
  }
  if (grasping != tool.was_grasping) {
    const int32_t held =
        grasping ? tool.contacts[static_cast<size_t>(chosen)]->grasp().num_held() : 0;
    Emit(grasping ? SessionEventRecord::Kind::kGrasp : SessionEventRecord::Kind::kRelease, chosen,
         t, held);
    tool.was_grasping = grasping;
  }
}

int32_t Session::HeldNodes(int32_t t, std::span<int32_t> out) const {
  const SessionTool& tool = *tools_[static_cast<size_t>(t)];
  if (tool.force_organ < 0 || !tool.force_model.grasping) return 0;
  const contact::Grasp& grasp = tool.contacts[static_cast<size_t>(tool.force_organ)]->grasp();
  const std::span<const models::Attachment> held = grasp.attachments();
  const size_t n = std::min(held.size(), out.size());
  for (size_t i = 0; i < n; ++i) out[i] = held[i].node;
  return static_cast<int32_t>(n);
}

void Session::Reset() {
  for (auto& o : organs_) {
    if (o->elements_cut > 0) {  // the cut is undone: a new topology
      if (o->cutter) {
        o->cutter = std::make_unique<cutting::TetCutter>(o->built.volume.tetrahedra,
                                                         o->built.volume.vertices);
      }
      ++o->topology_version;
      o->elements_cut = 0;
    }
    o->state = o->built.model->MakeState();
    o->surface->Refit(o->state->positions);
    o->time = 0.0;
    o->num_attachments = 0;
  }
  for (auto& tool : tools_) {
    for (auto& c : tool->contacts) c->Reset(tool->command.pose);
    tool->was_touching = false;
    tool->was_grasping = false;
    tool->blade_engaged = false;
    tool->incision_removed = 0;
    tool->force_organ = -1;
  }
  for (auto& r : rigid_) r->sphere = std::make_unique<contact::RigidSphere>(r->settings, r->start);
  time_ = 0.0;
  ticks_ = 0;
  Emit(SessionEventRecord::Kind::kReset, -1, -1, 0);
}

}  // namespace somasim::server
