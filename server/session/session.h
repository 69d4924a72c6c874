// A running session's physics (SPEC §1, §5): every organ of a scene on its tissue model, the
// scene's tools with their contact, grasp and local force model, and its rigid bodies, advanced
// tick by tick. Pure: no DDS, no I/O, no logging, no clock — the server application
// (server/app/) feeds it tool commands and publishes what it produces. Built at start-up (which
// allocates); Step allocates nothing.
//
// Time: the session ticks at the smallest model step of its organs; an organ with a longer step
// advances when its own time falls behind the session's (organs at 1 ms and 10 ms coexist).
// Tools act on every organ: one contact (god-object proxy and grasp) per tool and organ. The
// local force model of a tool comes from the organ it grasps, else the one it touches (the
// first in the scene's order), else says "no contact".
// A step a model rejects (it diverged: SPEC §7) leaves the organ at its last good state, at rest
// (velocities zeroed, so the next step does not repeat the divergence), and is reported.
// A scalpel with its cut button held (kCutButton) cuts: each tick its blade's sweep since the
// last tick goes to every organ (FEM: cutting::TetCutter, then FemModel::ApplyCut; particle
// models: TissueModel::Cut), before the organs step; while it cuts, the blade is in the tissue
// and its tip does not push it (no contact springs, no force model: the hand feels no
// resistance yet). A blade step that removes elements bumps the organ's topology_version; an
// incision (cut button pressed to released, or to a jump) that removed any emits one kCut. The
// contact surface stays the organ's original outer surface (the inner faces of a cut do not collide
// yet). Rigid bodies (spheres) lie in the organ whose bounding box holds their centre at start-up
// (the nearest organ otherwise) and meet the tool whose tip is nearest to them.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/force_model/local_force_model.h"
#include "common/scene/scene.h"
#include "server/contact/contact_pipeline.h"
#include "server/contact/rigid_body.h"
#include "server/cutting/tet_cutter.h"
#include "server/organs/organ_builder.h"

namespace somasim::server {

// What happened during a tick, for the session's event stream (idl/session.idl SessionEvent
// kinds). Fixed size: the physics allocates nothing to report it.
struct SessionEventRecord {
  enum class Kind : uint32_t {
    kGrasp = 3,
    kRelease = 4,
    kContactBegins = 5,
    kContactEnds = 6,
    kStepRejected = 7,
    kForceModelRefused = 15,  // the contact gave a model MakeLocalForceModel refused
    kReset = 16,              // every organ back to rest (Session::Reset)
    kCut = 13,  // an incision that cut tissue ended (detail: elements or springs it removed)
  };
  Kind kind = Kind::kGrasp;
  double sim_time = 0.0;  // [s]
  int32_t organ = -1;     // index into the session's organs, or -1
  int32_t tool = -1;      // index into the session's tools, or -1
  int32_t detail = 0;     // kGrasp: nodes held; kStepRejected: models::StepStatus; kCut: removed
};

// What a tool command sets (server/app/ checks the sample before it gets here).
struct ToolCommandInput {
  contact::ToolPose pose;
  uint32_t buttons = 0;
  uint64_t sequence = 0;
};

struct SessionOrgan {
  organs::BuiltOrgan built;
  std::unique_ptr<models::TissueState> state;
  std::unique_ptr<contact::OrganSurface> surface;
  std::unique_ptr<contact::FemCompliance> compliance;  // FEM organs that are held; else null
  std::vector<models::Attachment> attachments;         // this step's springs (capacity fixed)
  int32_t num_attachments = 0;
  double time = 0.0;  // [s] of this organ's accepted and rejected steps
  int64_t rejected_steps = 0;
  // Cutting (SPEC §5.3). FEM organs: the vertex-preserving cutter on the volume, and the
  // positions before a blade step (3 × num_nodes, scratch). Particle organs whose model
  // SupportsCutting are cut by the model itself. Others (reduced models) cannot be cut.
  std::unique_ptr<cutting::TetCutter> cutter;
  mesh::Points cut_before;
  // The organ's topology (its volume's alive elements, its rest positions, its surface): 1 at
  // start, +1 whenever a cut removes elements or a reset puts them back, never decreasing.
  uint32_t topology_version = 1;
  int64_t elements_cut = 0;  // elements (FEM) or springs/constraints (particles) removed
};

struct SessionTool {
  std::string id;
  contact::ToolShape shape;
  ToolCommandInput command;
  bool commanded = false;                                       // a command has arrived
  std::vector<std::unique_ptr<contact::ToolContact>> contacts;  // one per organ (none: camera)
  force_model::LocalForceModel force_model;
  int32_t force_organ = -1;  // the organ the force model comes from, or -1
  bool was_touching = false;
  bool was_grasping = false;
  // Scalpel: the blade PQ [m] at the last tick, and whether the cut button was held then.
  bool blade_engaged = false;
  Eigen::Vector3d blade_p = Eigen::Vector3d::Zero();
  Eigen::Vector3d blade_q = Eigen::Vector3d::Zero();
  int32_t incision_removed = 0;  // elements or springs this incision removed so far
  int32_t incision_organ = -1;   // the organ it last cut
};

// Tool-command buttons (idl/tool.idl): bit 2 engages a scalpel's blade.
inline constexpr uint32_t kCutButton = 4;
// A blade that jumps further than this [m] in one tick (a late command, a clutch) starts a new
// incision there instead of cutting through everything between.
inline constexpr double kMaxBladeStep = 0.02;

struct SessionRigid {
  std::string id;
  std::unique_ptr<contact::RigidSphere> sphere;
  contact::RigidSphereSettings settings;
  Eigen::Vector3d start = Eigen::Vector3d::Zero();  // [m] where the scene puts its centre
  int32_t organ = -1;  // the organ it lies in (-1: none, it only falls and meets tools)
};

class Session {
 public:
  // Builds every organ, tool and rigid body of `scene` (files relative to `scene_dir`). Throws
  // scene::SceneError for what the meshes refuse, mesh_io::MeshError for an unreadable mesh,
  // std::invalid_argument for a tool or rigid body the contact code refuses.
  Session(const scene::Scene& scene, const scene::SceneLines& lines, const std::string& scene_dir,
          const contact::ContactSettings& contact_settings = {});
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // Advances one tick of dt(). Allocation-free.
  void Step();
  // Sets what tool `tool` (0 .. num_tools-1) does from the next tick on.
  void SetToolCommand(int32_t tool, const ToolCommandInput& command);
  // Every organ back to rest, rigid bodies back where the scene puts them, tools' contacts and
  // grasps forgotten, time 0; emits kReset. Allocates (not for the physics path).
  void Reset();

  double time() const { return time_; }  // [s]
  double dt() const { return dt_; }      // [s] the tick
  uint64_t ticks() const { return ticks_; }
  const scene::Scene& scene() const { return scene_; }

  int32_t num_organs() const { return static_cast<int32_t>(organs_.size()); }
  const SessionOrgan& organ(int32_t i) const { return *organs_[static_cast<size_t>(i)]; }
  int32_t OrganIndex(std::string_view id) const;  // -1 when unknown

  int32_t num_tools() const { return static_cast<int32_t>(tools_.size()); }
  const SessionTool& tool(int32_t i) const { return *tools_[static_cast<size_t>(i)]; }
  int32_t ToolIndex(std::string_view id) const;  // -1 when unknown
  // The nodes of tool i's force organ its grasp holds (none when it holds nothing), into `out`
  // (at most out.size(), the nearest to the jaws first); how many. Allocation-free.
  int32_t HeldNodes(int32_t i, std::span<int32_t> out) const;

  int32_t num_rigid() const { return static_cast<int32_t>(rigid_.size()); }
  const SessionRigid& rigid(int32_t i) const { return *rigid_[static_cast<size_t>(i)]; }

  // Events since the last TakeEvents (oldest first; at most kMaxEvents are kept, the oldest
  // dropped beyond that and counted in events_dropped()). Clears them.
  static constexpr int32_t kMaxEvents = 256;
  std::span<const SessionEventRecord> TakeEvents();
  uint64_t events_dropped() const { return events_dropped_; }

  // Counters since start.
  uint64_t organ_steps() const { return organ_steps_; }
  uint64_t rejected_steps() const { return rejected_steps_; }

 private:
  void StepOrgan(int32_t k);
  // The scalpel `t`'s blade step since the last tick, cutting every organ it crosses.
  void Cut(int32_t t);
  void UpdateForceModel(int32_t t);
  void Emit(SessionEventRecord::Kind kind, int32_t organ, int32_t tool, int32_t detail);

  scene::Scene scene_;
  Eigen::Vector3d gravity_ = Eigen::Vector3d::Zero();
  contact::ContactSettings contact_settings_;
  std::vector<std::unique_ptr<SessionOrgan>> organs_;
  std::vector<std::unique_ptr<SessionTool>> tools_;
  std::vector<std::unique_ptr<SessionRigid>> rigid_;
  double time_ = 0.0;
  double dt_ = 1e-3;
  uint64_t ticks_ = 0;
  uint64_t organ_steps_ = 0;
  uint64_t rejected_steps_ = 0;
  std::array<SessionEventRecord, kMaxEvents> events_{};
  std::array<SessionEventRecord, kMaxEvents> taken_{};
  int32_t num_events_ = 0;
  uint64_t events_dropped_ = 0;
};

// The scene the server runs for `builtin:NAME`: scene::DefaultScene(NAME) run as dynamics (FEM
// organs at a 10 ms step, the interactive rate of SPEC §1's 0.1–10 ms range for volume FEM, with
// at most 30 conjugate-gradient iterations per step and light Rayleigh damping; seed 002's closed
// surfaces spleen600, kidney2000 and gallbladder5400 as it runs them, implicit mass-spring shells
// at a 5 ms step with every node anchored to its rest position, see session.cc), with four tools:
// "probe", "grasper" (jaws 15 mm, grasp radius 3 mm), "scalpel" (blade 10 mm) and the
// "laparoscope" (a camera: a pose, no contact). Throws std::invalid_argument for an unknown
// organ.
scene::Scene ServerDefaultScene(std::string_view organ);

// A scene tool's shape (defaults for zero dimensions, as idl/scene.proto gives them).
contact::ToolShape ToolShapeOf(const scene::Tool& tool);

}  // namespace somasim::server
