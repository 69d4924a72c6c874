#include "tests/server/app/session_client.h"

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <sstream>
#include <thread>

#include "common/wire/mesh_frame_view.h"
#include "tests/support/temp_files.h"

namespace somasim::testing {
namespace {

// One Domain per domain id per process (Cyclone refuses a second).
dds::Domain& DomainFor(uint32_t id) {
  static std::mutex mutex;
  static std::map<uint32_t, std::unique_ptr<dds::Domain>> domains;
  const std::lock_guard<std::mutex> lock(mutex);
  auto& d = domains[id];
  if (!d) d = std::make_unique<dds::Domain>(id, dds::LoopbackConfig());
  return *d;
}

}  // namespace

std::string LoopbackConfigFile() {
  std::string path = TempDir("dds") + "/loopback.xml";
  std::ofstream(path) << dds::LoopbackConfig();
  return path;
}

std::string BinPath(const std::string& program) {
  const char* env = std::getenv("SOMASIM_BIN_DIR");
  const std::string bin =
      env != nullptr ? std::string(env)
                     : std::filesystem::read_symlink("/proc/self/exe").parent_path().string();
  return bin + "/" + program;
}

std::string TempDir(const std::string& name) {
  // Under this process's somasim-test-<pid>-XXXXXX, which the temp files' registry removes.
  const std::filesystem::path dir = std::filesystem::path(ProcessTempDir("somasim-test")) / name;
  std::filesystem::create_directories(dir);
  return dir.string();
}

std::unique_ptr<app::ChildProcess> StartProgram(const std::string& program,
                                                const std::vector<std::string>& args,
                                                const std::string& log) {
  std::vector<std::string> argv{BinPath(program)};
  argv.insert(argv.end(), args.begin(), args.end());
  return std::make_unique<app::ChildProcess>(argv, log);
}

std::string ReadText(const std::string& path) {
  std::ifstream in(path);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

SessionClient::SessionClient(uint32_t domain, const std::string& session) {
  DomainFor(domain);
  participant_ = std::make_unique<dds::Participant>(domain);
  topics_ = std::make_unique<dds::Topics>(*participant_);
  session_ = std::make_unique<dds::Reader<somasim_wire_SessionInfo>>(
      *participant_, topics_->session, dds::SessionQos(session));
  topology_ = std::make_unique<dds::Reader<somasim_wire_OrganTopology>>(
      *participant_, topics_->topology, dds::TopologyQos(session));
  frames_ = std::make_unique<dds::Reader<somasim_wire_MeshFrame>>(*participant_, topics_->frame,
                                                                  dds::FrameQos(session));
  heartbeat_ = std::make_unique<dds::Reader<somasim_wire_Heartbeat>>(
      *participant_, topics_->heartbeat, dds::HeartbeatQos(session));
  metrics_reader_ = std::make_unique<dds::Reader<somasim_wire_ServerMetrics>>(
      *participant_, topics_->metrics, dds::MetricsQos(session));
  events_ = std::make_unique<dds::Reader<somasim_wire_SessionEvent>>(*participant_, topics_->event,
                                                                     dds::EventQos(session));
  force_ = std::make_unique<dds::Reader<somasim_wire_ForceModel>>(
      *participant_, topics_->force_model, dds::ForceModelQos(session));
  commands_ = std::make_unique<dds::Writer<somasim_wire_ToolCommand>>(
      *participant_, topics_->tool_command, dds::ToolCommandQos(session));
  instructor_ = std::make_unique<dds::Writer<somasim_wire_InstructorCommand>>(
      *participant_, topics_->instructor, dds::InstructorQos(session));
}

SessionClient::~SessionClient() = default;

void SessionClient::Poll() {
  session_->Take([this](const somasim_wire_SessionInfo& s, const dds_sample_info_t&) {
    has_session_ = true;
    server_id_ = s.server_id;
    session_organs_ = s.organs._length;
    server_ids_.insert(s.server_id);
  });
  topology_->Take([this](const somasim_wire_OrganTopology& t, const dds_sample_info_t&) {
    OrganView& o = organs_[t.organ];
    if (t.version != o.topology_version || !o.decoder) {
      o.topology_version = t.version;
      o.num_nodes = t.num_nodes;
      o.rest.assign(t.rest_positions._buffer, t.rest_positions._buffer + t.rest_positions._length);
      o.triangles.assign(t.triangles._buffer, t.triangles._buffer + t.triangles._length);
      o.inner_face.assign(t.inner_face._buffer, t.inner_face._buffer + t.inner_face._length);
      ++o.topologies_received;
      o.decoder = std::make_unique<wire::FrameDecoder>(static_cast<int32_t>(t.num_nodes));
    }
    server_ids_.insert(t.server_id);
  });
  frames_->Take([this](const somasim_wire_MeshFrame& f, const dds_sample_info_t&) { OnFrame(f); },
                256);
  heartbeat_->Take([this](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
    ++heartbeats_;
    last_state_ = h.state;
    last_sim_time_ = h.sim_time;
    last_heartbeat_ = std::chrono::steady_clock::now();
    server_ids_.insert(h.server_id);
  });
  metrics_reader_->Take([this](const somasim_wire_ServerMetrics& m, const dds_sample_info_t&) {
    metrics_.push_back(m);
    server_ids_.insert(m.server_id);
  });
  events_->Take([this](const somasim_wire_SessionEvent& e, const dds_sample_info_t&) {
    event_texts_.push_back(e.text);
  });
  force_->Take([this](const somasim_wire_ForceModel& m, const dds_sample_info_t&) {
    ++force_models_;
    server_ids_.insert(m.server_id);
  });
}

void SessionClient::OnFrame(const somasim_wire_MeshFrame& f) {
  server_ids_.insert(f.server_id);
  auto it = organs_.find(f.organ);
  if (it == organs_.end() || !it->second.decoder) return;  // no topology yet
  OrganView& o = it->second;
  ++o.frames_received;
  if (f.topology_version != o.topology_version) ++o.frames_of_other_topology;
  if (drop_fraction_ > 0.0 &&
      std::uniform_real_distribution<double>(0.0, 1.0)(rng_) < drop_fraction_) {
    ++o.frames_dropped_on_purpose;
    return;
  }
  const wire::FrameDecoder::Result r = o.decoder->Apply(wire::ViewOf(f));
  if (r == wire::FrameDecoder::Result::kBad) ++o.bad_frames;
  if (r == wire::FrameDecoder::Result::kApplied && on_applied) {
    const std::span<const float> p = o.decoder->positions();
    on_applied(f.organ, f.frame, std::vector<float>(p.begin(), p.end()));
  }
}

bool SessionClient::PollUntil(const std::function<bool()>& pred,
                              std::chrono::milliseconds timeout) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (true) {
    Poll();
    if (pred()) return true;
    if (std::chrono::steady_clock::now() > end) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
}

void SessionClient::SendToolCommand(const somasim_wire_ToolCommand& command) {
  commands_->Write(command);
}

void SessionClient::SendInstructorCommand(uint32_t kind, const std::string& text) {
  somasim_wire_InstructorCommand c{};
  const std::string who = "instructor-test";
  c.format_version = dds::kWireFormatVersion;
  c.seq = ++instructor_seq_;
  c.instructor = dds::CString(who);
  c.kind = kind;
  c.text = dds::CString(text);
  instructor_->Write(c);
}

somasim_wire_ToolCommand ToolCommandAt(const char* tool, double x, double y, double z,
                                       uint64_t seq) {
  somasim_wire_ToolCommand c{};
  c.tool = const_cast<char*>(tool);
  c.format_version = dds::kWireFormatVersion;
  c.station = const_cast<char*>("test");
  c.seq = seq;
  c.position[0] = x;
  c.position[1] = y;
  c.position[2] = z;
  c.orientation[0] = 1.0;
  c.jaw_closure = 0.0;
  return c;
}

}  // namespace somasim::testing
