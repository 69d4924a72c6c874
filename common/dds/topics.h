// The project's DDS topics (idl/*.idl) and the QoS of each stream (SPEC §1; docs/topics.md says
// why each was chosen). Every process makes its entities through these, so writers and readers
// always match. All entities live in the session's partition (`--session NAME`).
#pragma once

#include <chrono>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "common/dds/dds.h"
#include "idl/mesh.h"
#include "idl/session.h"
#include "idl/tool.h"

namespace somasim::dds {

// The version every wire type carries in format_version; a receiver drops (and counts) others.
inline constexpr uint32_t kWireFormatVersion = 1;

// Deadline and liveliness lease of the tool commands, force models and heartbeat: a peer that
// falls silent this long is gone (SPEC §7; Cyclone's default lease is 10 s).
inline constexpr std::chrono::milliseconds kLease{500};
// How often the server's heartbeat is sent.
inline constexpr std::chrono::milliseconds kHeartbeatPeriod{100};

inline constexpr char kSessionTopic[] = "somasim_session";
inline constexpr char kTopologyTopic[] = "somasim_topology";
inline constexpr char kFrameTopic[] = "somasim_frame";
inline constexpr char kToolCommandTopic[] = "somasim_tool_command";
inline constexpr char kForceModelTopic[] = "somasim_force_model";
inline constexpr char kEventTopic[] = "somasim_event";
inline constexpr char kInstructorTopic[] = "somasim_instructor";
inline constexpr char kHeartbeatTopic[] = "somasim_heartbeat";
inline constexpr char kMetricsTopic[] = "somasim_metrics";
inline constexpr char kRigidBodyTopic[] = "somasim_rigid_body";

// Empty when `name` can be a session (a DDS partition): 1–64 letters, digits, '_' or '-' (no
// partition wildcards), else what is wrong.
std::string SessionNameError(std::string_view name);

// QoS per stream, for writers and readers alike, in the partition `session`.
// Session description: reliable, transient-local, keep-last 1 (late joiners get it).
Qos SessionQos(const std::string& session);
// Topology per organ: reliable, transient-local, keep-last 1 per organ, durability service
// keep-last 1 for up to 256 organs (a late joiner gets every organ's newest topology).
Qos TopologyQos(const std::string& session);
// Mesh frames: best-effort, volatile, keep-last 4 per organ: never blocks the server; a lost
// frame is recovered at the next keyframe.
Qos FrameQos(const std::string& session);
// Tool commands and force models: best-effort, volatile, keep-last 1 per tool (only the newest
// matters), deadline and manual-by-topic liveliness kLease.
Qos ToolCommandQos(const std::string& session);
Qos ForceModelQos(const std::string& session);
// Session events: reliable, transient-local, keep-last 64 (history kept for late joiners).
Qos EventQos(const std::string& session);
// Instructor commands: reliable, volatile, keep-all.
Qos InstructorQos(const std::string& session);
// Heartbeat: best-effort, volatile, keep-last 1, deadline and manual-by-topic liveliness kLease.
Qos HeartbeatQos(const std::string& session);
// Metrics: best-effort, volatile, keep-last 1.
Qos MetricsQos(const std::string& session);
// Rigid bodies' poses: best-effort, volatile, keep-last 1 per body (sent with every frame: only
// the newest matters).
Qos RigidBodyQos(const std::string& session);

// Every topic on one participant.
struct Topics {
  explicit Topics(const Participant& participant);
  Topic<somasim_wire_SessionInfo> session;
  Topic<somasim_wire_OrganTopology> topology;
  Topic<somasim_wire_MeshFrame> frame;
  Topic<somasim_wire_ToolCommand> tool_command;
  Topic<somasim_wire_ForceModel> force_model;
  Topic<somasim_wire_SessionEvent> event;
  Topic<somasim_wire_InstructorCommand> instructor;
  Topic<somasim_wire_Heartbeat> heartbeat;
  Topic<somasim_wire_ServerMetrics> metrics;
  Topic<somasim_wire_RigidBodyState> rigid_body;
};

// The sessions running on the participant's domain: the partitions of the servers' heartbeat
// writers that discovery has seen alive, sorted, each once. Discovery takes a moment after a
// participant is made: this polls Cyclone's built-in publication topic for `wait` and answers
// with what it found. Throws DdsError when the built-in reader cannot be made.
std::vector<std::string> RunningSessions(const Participant& participant,
                                         std::chrono::milliseconds wait);

// The Cyclone configuration a process uses: the file named by --dds-config (read whole), else
// "" (Cyclone's defaults, or the CYCLONEDDS_URI environment variable). Throws
// std::runtime_error naming the file when it cannot be read.
std::string ReadDdsConfig(const std::string& path);

}  // namespace somasim::dds
