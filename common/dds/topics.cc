#include "common/dds/topics.h"

#include <fstream>
#include <sstream>
#include <stdexcept>

namespace somasim::dds {
namespace {

constexpr std::chrono::milliseconds kReliableBlocking{100};

Qos Base(const std::string& session) {
  Qos q;
  q.Partition(session);
  return q;
}

}  // namespace

std::string SessionNameError(std::string_view name) {
  if (name.empty()) return "is empty";
  if (name.size() > 64) return "is longer than 64 characters";
  for (const char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '-';
    if (!ok) return "may hold only letters, digits, '_' and '-'";
  }
  return "";
}

Qos SessionQos(const std::string& session) {
  Qos q = Base(session);
  q.Reliable(kReliableBlocking).TransientLocal().KeepLast(1).DurabilityService(1, 1);
  return q;
}

Qos TopologyQos(const std::string& session) {
  Qos q = Base(session);
  q.Reliable(kReliableBlocking).TransientLocal().KeepLast(1).DurabilityService(1, 256);
  return q;
}

Qos FrameQos(const std::string& session) {
  Qos q = Base(session);
  q.BestEffort().Volatile().KeepLast(4);
  return q;
}

Qos ToolCommandQos(const std::string& session) {
  Qos q = Base(session);
  q.BestEffort().Volatile().KeepLast(1).Deadline(kLease).ManualLiveliness(kLease);
  return q;
}

Qos ForceModelQos(const std::string& session) { return ToolCommandQos(session); }

Qos EventQos(const std::string& session) {
  Qos q = Base(session);
  q.Reliable(kReliableBlocking).TransientLocal().KeepLast(64).DurabilityService(64, 1);
  return q;
}

Qos InstructorQos(const std::string& session) {
  Qos q = Base(session);
  q.Reliable(kReliableBlocking).Volatile().KeepAll();
  return q;
}

Qos HeartbeatQos(const std::string& session) {
  Qos q = Base(session);
  q.BestEffort().Volatile().KeepLast(1).Deadline(kLease).ManualLiveliness(kLease);
  return q;
}

Qos MetricsQos(const std::string& session) {
  Qos q = Base(session);
  q.BestEffort().Volatile().KeepLast(1);
  return q;
}

Topics::Topics(const Participant& participant)
    : session(participant, somasim_wire_SessionInfo_desc, kSessionTopic),
      topology(participant, somasim_wire_OrganTopology_desc, kTopologyTopic),
      frame(participant, somasim_wire_MeshFrame_desc, kFrameTopic),
      tool_command(participant, somasim_wire_ToolCommand_desc, kToolCommandTopic),
      force_model(participant, somasim_wire_ForceModel_desc, kForceModelTopic),
      event(participant, somasim_wire_SessionEvent_desc, kEventTopic),
      instructor(participant, somasim_wire_InstructorCommand_desc, kInstructorTopic),
      heartbeat(participant, somasim_wire_Heartbeat_desc, kHeartbeatTopic),
      metrics(participant, somasim_wire_ServerMetrics_desc, kMetricsTopic) {}

std::string ReadDdsConfig(const std::string& path) {
  if (path.empty()) return "";
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot read the DDS configuration");
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace somasim::dds
