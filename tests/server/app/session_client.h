// A DDS client of a session for the server's tests: joins the session's partition on the
// test's own domain (LoopbackConfig), takes what the server publishes — description,
// topologies, mesh frames (decoded with FrameDecoder, optionally dropping some on purpose),
// heartbeats, metrics, events, force models — and writes tool and instructor commands.
// Also starts the project's programs (somasim-server, somasim-haptic) as child processes.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "common/app/child_process.h"
#include "common/dds/topics.h"
#include "common/wire/frame_codec.h"

namespace somasim::testing {

// The Cyclone configuration every process of a test uses (loopback, unicast), as a file.
std::string LoopbackConfigFile();
// build/bin/<program> (SOMASIM_BIN_DIR, else beside the test).
std::string BinPath(const std::string& program);
// The folder `name` in this process's temporary folder (made on first use; removed at the end
// of the process when its tests passed, see tests/support/temp_files.h).
std::string TempDir(const std::string& name);

// Starts build/bin/<program> with `args`; its output goes to `log`.
std::unique_ptr<app::ChildProcess> StartProgram(const std::string& program,
                                                const std::vector<std::string>& args,
                                                const std::string& log);
// The file's text ("" if unreadable).
std::string ReadText(const std::string& path);

struct OrganView {
  uint32_t topology_version = 0;
  uint32_t num_nodes = 0;
  std::vector<float> rest;
  std::vector<uint32_t> triangles;   // 3 per surface triangle
  std::vector<uint8_t> inner_face;   // per triangle: 1 = the inner face of a cut
  uint32_t topologies_received = 0;  // versions taken (a cut republishes)
  std::unique_ptr<wire::FrameDecoder> decoder;
  uint64_t frames_of_other_topology = 0;  // frames stamped with another topology version
  uint64_t frames_received = 0;
  uint64_t frames_dropped_on_purpose = 0;
  uint64_t bad_frames = 0;
  uint64_t last_server_id = 0;
};

class SessionClient {
 public:
  // A participant on `domain` (a Domain with LoopbackConfig() is made when no other client of
  // this process has made it) in partition `session`.
  SessionClient(uint32_t domain, const std::string& session);
  ~SessionClient();

  // Drop this fraction of received frames before decoding (0..1), with a seeded generator.
  void DropFrames(double fraction, uint32_t seed) {
    drop_fraction_ = fraction;
    rng_.seed(seed);
  }
  // Called after every frame this client applies (organ, frame number, positions).
  std::function<void(const std::string&, uint64_t, const std::vector<float>&)> on_applied;

  // Takes everything that has arrived.
  void Poll();
  // Polls until pred() or the timeout; returns pred().
  bool PollUntil(const std::function<bool()>& pred, std::chrono::milliseconds timeout);

  void SendToolCommand(const somasim_wire_ToolCommand& command);
  void SendInstructorCommand(uint32_t kind, const std::string& text);

  bool has_session() const { return has_session_; }
  uint64_t server_id() const { return server_id_; }
  uint32_t session_organs() const { return session_organs_; }
  std::map<std::string, OrganView>& organs() { return organs_; }
  uint64_t heartbeats() const { return heartbeats_; }
  uint32_t last_state() const { return last_state_; }
  double last_sim_time() const { return last_sim_time_; }
  std::chrono::steady_clock::time_point last_heartbeat() const { return last_heartbeat_; }
  const std::set<uint64_t>& server_ids_seen() const { return server_ids_; }
  const std::vector<somasim_wire_ServerMetrics>& metrics() const { return metrics_; }
  const std::vector<std::string>& event_texts() const { return event_texts_; }
  uint64_t force_models() const { return force_models_; }

 private:
  void OnFrame(const somasim_wire_MeshFrame& f);

  std::unique_ptr<dds::Participant> participant_;
  std::unique_ptr<dds::Topics> topics_;
  std::unique_ptr<dds::Reader<somasim_wire_SessionInfo>> session_;
  std::unique_ptr<dds::Reader<somasim_wire_OrganTopology>> topology_;
  std::unique_ptr<dds::Reader<somasim_wire_MeshFrame>> frames_;
  std::unique_ptr<dds::Reader<somasim_wire_Heartbeat>> heartbeat_;
  std::unique_ptr<dds::Reader<somasim_wire_ServerMetrics>> metrics_reader_;
  std::unique_ptr<dds::Reader<somasim_wire_SessionEvent>> events_;
  std::unique_ptr<dds::Reader<somasim_wire_ForceModel>> force_;
  std::unique_ptr<dds::Writer<somasim_wire_ToolCommand>> commands_;
  std::unique_ptr<dds::Writer<somasim_wire_InstructorCommand>> instructor_;
  bool has_session_ = false;
  uint64_t server_id_ = 0;
  uint32_t session_organs_ = 0;
  std::map<std::string, OrganView> organs_;
  uint64_t heartbeats_ = 0;
  uint32_t last_state_ = 0;
  double last_sim_time_ = 0.0;
  std::chrono::steady_clock::time_point last_heartbeat_{};
  std::set<uint64_t> server_ids_;
  std::vector<somasim_wire_ServerMetrics> metrics_;
  std::vector<std::string> event_texts_;
  uint64_t force_models_ = 0;
  uint64_t instructor_seq_ = 0;
  double drop_fraction_ = 0.0;
  std::mt19937 rng_{1};
};

// A well-formed command for `tool` at tip position (x, y, z) [m], identity orientation.
somasim_wire_ToolCommand ToolCommandAt(const char* tool, double x, double y, double z,
                                       uint64_t seq);

}  // namespace somasim::testing
