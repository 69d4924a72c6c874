// What a viewer knows of a session (SPEC §1): the session description, each organ's topology
// (rest positions, surface triangles, inner-face marks, version) and its current shape from the
// mesh frames (keyframes + deltas, wire::FrameDecoder), the server's heartbeat, metrics and
// events. A thin DDS client: takes samples, checks them, never links the physics.
//
// Robustness (issue 8): a frame whose topology version the receiver has not seen waits (is
// dropped until that topology arrives; the next keyframe after it converges); a new server id
// (a restart) forgets every shape and topology; malformed samples (wrong format version,
// sizes, indices out of range, non-finite values) are dropped and counted by kind; a heartbeat
// silent for the lease means the server is gone.
#pragma once

#include <Eigen/Core>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "common/dds/topics.h"
#include "common/force_model/local_force_model.h"
#include "common/wire/frame_codec.h"

namespace somasim::viewer {

struct OrganScene {
  uint32_t topology_version = 0;
  uint32_t num_nodes = 0;
  std::vector<float> rest;          // [m] 3 × num_nodes
  std::vector<uint32_t> triangles;  // 3 × T node indices (< num_nodes)
  std::vector<uint8_t> inner_face;  // T: 1 = the inner face of a cut
  std::unique_ptr<wire::FrameDecoder> decoder;
  double sim_time = 0.0;       // [s] of the frame held
  int64_t sender_time_ns = 0;  // the server's steady clock when it wrote that frame
  uint64_t frames_applied = 0;

  bool has_shape() const { return decoder && decoder->has_shape(); }
  // The positions to show: the last frame's, or the rest shape before the first keyframe.
  const float* positions() const;
};

// A tool of the session: its shape (session description, and the grasp radius from the scene's
// text), its last commanded pose (from whichever station drives it) and the server's last local
// force model for it.
struct ToolScene {
  std::string kind;             // "probe", "grasper", "scalpel", "camera"
  double shaft_length = 0.0;    // [m]
  double shaft_radius = 0.0;    // [m]
  double jaw_length = 0.0;      // [m] grasper
  double grasp_radius = 0.003;  // [m] grasper: the scene's, or idl/scene.proto's default
  bool has_pose = false;
  double position[3] = {};                       // [m] the tip
  double orientation[4] = {1.0, 0.0, 0.0, 0.0};  // w x y z, shaft along the tool's +z
  double jaw_closure = 0.0;                      // 0 open .. 1 closed
  std::chrono::steady_clock::time_point last_command{};
  // The commands' rate [Hz]: the sender's sequence numbers over the last whole second (the
  // reader keeps only the newest command, so counting samples would undercount), 0 until a
  // second has passed or when the commands stop; and the sending station.
  double command_rate_hz = 0.0;
  std::string station;
  uint64_t rate_seq = 0;
  std::chrono::steady_clock::time_point rate_start{};
  bool in_contact = false;
  double contact_point[3] = {};  // [m]
  double normal[3] = {};         // outward, unit
  bool grasping = false;
  double grasp_anchor[3] = {};  // [m]
  // The server's last local force model (validated: force_model::FromWire) and the organ it
  // touches or holds ("" for none).
  bool has_model = false;
  force_model::LocalForceModel model;
  std::string organ;
  // The grasped points the server publishes with the model: nodes of held_organ, the nearest
  // to the jaws first (validated: force_model::HeldNodesFromWire).
  std::string held_organ;
  std::vector<uint32_t> held_nodes;

  // The force the local force model gives at the tool's commanded tip, at rest [N] (zero
  // without a model or a pose): what the station's hand feels, up to the haptic node's rate
  // limit.
  Eigen::Vector3d Force() const;
};

// A rigid body of the session (a kidney stone): a sphere where the server last had it.
struct RigidBodyScene {
  double radius = 0.0;                           // [m], in (0, 0.2]
  double position[3] = {};                       // [m] its centre
  double orientation[4] = {1.0, 0.0, 0.0, 0.0};  // w x y z
  bool grasped = false;
  double sim_time = 0.0;  // [s]
};

struct ReceiverCounters {
  uint64_t bad_topologies = 0;
  uint64_t bad_frames = 0;
  uint64_t frames_waiting_for_topology = 0;
  uint64_t wrong_format_version = 0;
  uint64_t server_restarts = 0;
  uint64_t bad_rigid_bodies = 0;  // non-finite poses, radii outside (0, 0.2] m
  uint64_t bad_tool_samples = 0;  // tool commands with non-finite values; unusable force models
                                  // or held nodes
};

class SceneReceiver {
 public:
  // Readers in partition `session` of `participant` (which outlives the receiver). Creates no
  // writer: a receiver publishes nothing.
  SceneReceiver(const dds::Participant& participant, const dds::Topics& topics,
                const std::string& session);
  ~SceneReceiver();

  // Takes everything that has arrived; true when an organ's shape or topology changed.
  bool Poll();

  bool has_session() const { return has_session_; }
  uint64_t server_id() const { return server_id_; }
  const std::string& scene_name() const { return scene_name_; }
  const std::map<std::string, OrganScene>& organs() const { return organs_; }
  const std::map<std::string, ToolScene>& tools() const { return tools_; }
  const std::map<std::string, RigidBodyScene>& rigid_bodies() const { return rigid_bodies_; }
  // Every organ of the session description has a shape.
  bool complete() const;
  // The server's last heartbeat: state (1 starting, 2 running, 3 paused, 4 stopping), session
  // time, and whether the server is gone: nothing heard of it (its first sample, then its
  // heartbeats) for longer than the lease (500 ms); true before any server is seen.
  uint32_t server_state() const { return server_state_; }
  double sim_time() const { return sim_time_; }
  bool server_gone(std::chrono::steady_clock::time_point now) const;
  bool has_metrics() const { return has_metrics_; }
  const somasim_wire_ServerMetrics& metrics() const { return metrics_; }
  const std::vector<std::string>& messages() const { return messages_; }  // newest last
  const ReceiverCounters& counters() const { return counters_; }

 private:
  void OnSession(const somasim_wire_SessionInfo& s);
  void OnTopology(const somasim_wire_OrganTopology& t);
  bool OnFrame(const somasim_wire_MeshFrame& f);
  void SeeServer(uint64_t id);
  void OnForceModel(const somasim_wire_ForceModel& m);
  void OnRigidBody(const somasim_wire_RigidBodyState& b);

  std::unique_ptr<dds::Reader<somasim_wire_SessionInfo>> session_;
  std::unique_ptr<dds::Reader<somasim_wire_OrganTopology>> topology_;
  std::unique_ptr<dds::Reader<somasim_wire_MeshFrame>> frames_;
  std::unique_ptr<dds::Reader<somasim_wire_Heartbeat>> heartbeat_;
  std::unique_ptr<dds::Reader<somasim_wire_ServerMetrics>> metrics_reader_;
  std::unique_ptr<dds::Reader<somasim_wire_SessionEvent>> events_;
  std::unique_ptr<dds::Reader<somasim_wire_ToolCommand>> tool_commands_;
  std::unique_ptr<dds::Reader<somasim_wire_ForceModel>> force_models_;
  std::unique_ptr<dds::Reader<somasim_wire_RigidBodyState>> rigid_reader_;
  bool has_session_ = false;
  uint64_t server_id_ = 0;
  std::string scene_name_;
  std::vector<std::string> organ_ids_;  // the session description's organs
  std::map<std::string, OrganScene> organs_;
  std::map<std::string, ToolScene> tools_;
  std::map<std::string, RigidBodyScene> rigid_bodies_;
  uint32_t server_state_ = 0;
  double sim_time_ = 0.0;
  // The last heartbeat of the current server, or when that server was first heard of.
  std::chrono::steady_clock::time_point last_heartbeat_{};
  bool has_metrics_ = false;
  somasim_wire_ServerMetrics metrics_{};
  std::vector<std::string> messages_;
  ReceiverCounters counters_;
};

}  // namespace somasim::viewer
