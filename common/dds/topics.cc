#include "common/dds/topics.h"

#include <chrono>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string_view>
#include <thread>

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

Qos RigidBodyQos(const std::string& session) {
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
      metrics(participant, somasim_wire_ServerMetrics_desc, kMetricsTopic),
      rigid_body(participant, somasim_wire_RigidBodyState_desc, kRigidBodyTopic) {}

std::vector<std::string> RunningSessions(const Participant& participant,
                                         std::chrono::milliseconds wait) {
  const dds_entity_t reader =
      dds_create_reader(participant.handle(), DDS_BUILTIN_TOPIC_DCPSPUBLICATION, nullptr, nullptr);
  if (reader < 0) throw DdsError("dds_create_reader(DCPSPublication)", reader);
  // Writer instance → its partitions, for the heartbeat writers alive now.
  std::map<dds_instance_handle_t, std::vector<std::string>> alive;
  const auto end = std::chrono::steady_clock::now() + wait;
  do {
    constexpr size_t kMax = 64;
    void* samples[kMax] = {};
    dds_sample_info_t infos[kMax];
    const dds_return_t n = dds_take(reader, samples, infos, kMax, kMax);
    for (dds_return_t k = 0; k < n; ++k) {
      const dds_sample_info_t& info = infos[k];
      if (info.instance_state != DDS_IST_ALIVE) {
        alive.erase(info.instance_handle);
        continue;
      }
      if (!info.valid_data) continue;
      const auto* endpoint = static_cast<const dds_builtintopic_endpoint_t*>(samples[k]);
      if (endpoint->topic_name == nullptr ||
          std::string_view(endpoint->topic_name) != kHeartbeatTopic) {
        continue;
      }
      uint32_t count = 0;
      char** names = nullptr;
      std::vector<std::string> partitions;
      if (endpoint->qos != nullptr && dds_qget_partition(endpoint->qos, &count, &names)) {
        for (uint32_t p = 0; p < count; ++p) {
          partitions.emplace_back(names[p]);
          dds_free(names[p]);
        }
        dds_free(names);
      }
      alive[info.instance_handle] = std::move(partitions);
    }
    if (n > 0) dds_return_loan(reader, samples, n);
    if (std::chrono::steady_clock::now() >= end) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  } while (true);
  dds_delete(reader);
  std::set<std::string> sessions;
  for (const auto& [handle, partitions] : alive)
    sessions.insert(partitions.begin(), partitions.end());
  return {sessions.begin(), sessions.end()};
}

std::string ReadDdsConfig(const std::string& path) {
  if (path.empty()) return "";
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path + ": cannot read the DDS configuration");
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace somasim::dds
