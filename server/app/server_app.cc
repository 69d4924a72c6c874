#include "server/app/server_app.h"

#include <google/protobuf/text_format.h>
#include <pthread.h>
#include <sched.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <array>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <exception>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <span>
#include <thread>

#include "common/app/log.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"
#include "common/dds/topics.h"
#include "common/mesh_io/mesh_error.h"
#include "common/wire/frame_codec.h"
#include "common/wire/frame_dump.h"
#include "server/app/snapshot_buffer.h"
#include "common/force_model/force_model_wire.h"
#include "server/recording/recorder.h"
#include "server/recording/replay.h"
#include "server/session/session.h"

#ifndef SOMASIM_VERSION
#define SOMASIM_VERSION "0.0.0"
#endif

namespace somasim::server {
namespace {

using Clock = std::chrono::steady_clock;
using app::Log;
using app::LogLevel;

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

// A single-producer single-consumer ring of session events (physics → publisher).
class EventRing {
 public:
  bool Push(const SessionEventRecord& e) {
    const uint32_t head = head_.load(std::memory_order_relaxed);
    if (head - tail_.load(std::memory_order_acquire) == kSize) return false;
    items_[head % kSize] = e;
    head_.store(head + 1, std::memory_order_release);
    return true;
  }
  bool Pop(SessionEventRecord* e) {
    const uint32_t tail = tail_.load(std::memory_order_relaxed);
    if (tail == head_.load(std::memory_order_acquire)) return false;
    *e = items_[tail % kSize];
    tail_.store(tail + 1, std::memory_order_release);
    return true;
  }

 private:
  static constexpr uint32_t kSize = 1024;
  std::array<SessionEventRecord, kSize> items_{};
  std::atomic<uint32_t> head_{0};
  std::atomic<uint32_t> tail_{0};
};

// What a tool command must be to move a tool (SPEC §7: bad samples are dropped and counted).
// Returns "" when usable, else what is wrong; fills `input`.
// Empty when `trainee` is a usable pseudonym for a recording's header, else why not.
std::string TraineeError(const std::string& trainee) {
  if (trainee.size() > 32) return "is longer than 32 characters";
  for (const char c : trainee) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') {
      return "may hold only letters, digits, - and _ (a pseudonym such as trainee-07)";
    }
  }
  return "";
}

std::string CheckToolCommand(const somasim_wire_ToolCommand& c, const Session& session,
                             int32_t* tool, ToolCommandInput* input) {
  if (c.format_version != dds::kWireFormatVersion) {
    return "format_version " + std::to_string(c.format_version) + " is not " +
           std::to_string(dds::kWireFormatVersion);
  }
  const std::string id = c.tool == nullptr ? std::string() : std::string(c.tool);
  *tool = session.ToolIndex(id);
  if (*tool < 0) return "unknown tool \"" + id.substr(0, 64) + "\"";
  const Eigen::Vector3d p(c.position[0], c.position[1], c.position[2]);
  if (!p.allFinite() || p.norm() > 10.0) return "position is not finite or beyond 10 m";
  const Eigen::Vector4d q(c.orientation[0], c.orientation[1], c.orientation[2], c.orientation[3]);
  if (!q.allFinite() || std::abs(q.norm() - 1.0) > 1e-3) {
    return "orientation is not a unit quaternion";
  }
  if (!std::isfinite(c.jaw_closure) || c.jaw_closure < 0.0 || c.jaw_closure > 1.0) {
    return "jaw_closure is not in [0, 1]";
  }
  input->pose.tip = p;
  input->pose.orientation = Eigen::Quaterniond(q[0], q[1], q[2], q[3]).normalized();
  input->pose.jaw_opening = 1.0 - c.jaw_closure;
  input->buttons = c.buttons;
  input->sequence = c.seq;
  return "";
}

const char* EventText(SessionEventRecord::Kind kind) {
  switch (kind) {
    case SessionEventRecord::Kind::kGrasp:
      return "grasp";
    case SessionEventRecord::Kind::kRelease:
      return "release";
    case SessionEventRecord::Kind::kContactBegins:
      return "contact begins";
    case SessionEventRecord::Kind::kContactEnds:
      return "contact ends";
    case SessionEventRecord::Kind::kStepRejected:
      return "step rejected";
    case SessionEventRecord::Kind::kForceModelRefused:
      return "force model refused";
    case SessionEventRecord::Kind::kReset:
      return "reset";
    case SessionEventRecord::Kind::kCut:
      return "cut";
  }
  return "event";
}

// Per tool, what the server saw of the force (for the report): the force model evaluated at the
// commanded tip, each tick.
struct ToolStats {
  double contact_time = 0.0;  // [s] in contact or grasping
  double max_force = 0.0;     // [N]
  double force_sum = 0.0;     // [N s] over contact time
  uint64_t grasps = 0;
};

struct Shared {
  std::atomic<bool> done{false};
  std::atomic<bool> paused{false};
  std::atomic<bool> reset{false};
  std::atomic<uint64_t> commands_received{0};
  std::atomic<uint64_t> commands_rejected{0};
  std::atomic<uint64_t> instructor_received{0};
  std::atomic<uint64_t> force_models{0};
  std::atomic<uint64_t> steps{0};
  std::atomic<uint64_t> rejected_steps{0};
  std::atomic<uint64_t> behind{0};       // times the physics fell > 0.5 s behind the wall clock
  std::atomic<uint64_t> steps_taken{0};  // Session::Step calls (the recording's step count)
  std::atomic<double> sim_time{0.0};
  std::atomic<double> p50{0.0};
  std::atomic<double> p99{0.0};
  std::atomic<double> pmax{0.0};
  std::atomic<double> rate{0.0};
  EventRing events;
};

class Server {
 public:
  Server(const ServerOptions& options, Session& session, const std::string& dds_config,
         Recorder* recorder, RecordedInputs* replay = nullptr)
      : options_(options), session_(session), recorder_(recorder), replay_(replay) {
    std::random_device rd;
    server_id_ = (static_cast<uint64_t>(rd()) << 32) ^ rd();
    // Cyclone's threads and the publisher (created from here on) wait on the wire: a short slice
    // wakes them promptly next to the busy physics thread, which returns to the default slice.
    LogSlice(app::SetSchedulerSlice(app::kWireSlice), "dds and publisher threads");
    if (!dds_config.empty()) {
      domain_ = std::make_unique<dds::Domain>(options.domain, dds_config);
    }
    participant_ = std::make_unique<dds::Participant>(options.domain);
    topics_ = std::make_unique<dds::Topics>(*participant_);
    const std::string& s = options.session;
    session_writer_ = std::make_unique<dds::Writer<somasim_wire_SessionInfo>>(
        *participant_, topics_->session, dds::SessionQos(s));
    topology_writer_ = std::make_unique<dds::Writer<somasim_wire_OrganTopology>>(
        *participant_, topics_->topology, dds::TopologyQos(s));
    frame_writer_ = std::make_unique<dds::Writer<somasim_wire_MeshFrame>>(
        *participant_, topics_->frame, dds::FrameQos(s));
    force_writer_ = std::make_unique<dds::Writer<somasim_wire_ForceModel>>(
        *participant_, topics_->force_model, dds::ForceModelQos(s));
    event_writer_ = std::make_unique<dds::Writer<somasim_wire_SessionEvent>>(
        *participant_, topics_->event, dds::EventQos(s));
    heartbeat_writer_ = std::make_unique<dds::Writer<somasim_wire_Heartbeat>>(
        *participant_, topics_->heartbeat, dds::HeartbeatQos(s));
    metrics_writer_ = std::make_unique<dds::Writer<somasim_wire_ServerMetrics>>(
        *participant_, topics_->metrics, dds::MetricsQos(s));
    command_reader_ = std::make_unique<dds::Reader<somasim_wire_ToolCommand>>(
        *participant_, topics_->tool_command, dds::ToolCommandQos(s));
    instructor_reader_ = std::make_unique<dds::Reader<somasim_wire_InstructorCommand>>(
        *participant_, topics_->instructor, dds::InstructorQos(s));
    for (int32_t k = 0; k < session.num_organs(); ++k) {
      const int32_t n = session.organ(k).built.model->num_nodes();
      snapshots_.push_back(std::make_unique<SnapshotBuffer>(3 * static_cast<size_t>(n)));
      encoders_.push_back(std::make_unique<wire::FrameEncoder>(n, options.keyframe_interval));
      organ_ids_.push_back(session.organ(k).built.id);
      const auto& x = session.organ(k).state->positions;
      snapshots_.back()->Write({x.data(), static_cast<size_t>(x.size())}, 0.0);
    }
    // Topologies after a cut or a reset: the alive flags of the organ's tetrahedra (cut organs)
    // and its rest positions, handed over like the positions when the organ's version changes;
    // the publisher extracts the new surface with its own copy of the cutter's adjacency.
    for (int32_t k = 0; k < session.num_organs(); ++k) {
      const SessionOrgan& o = session.organ(k);
      const size_t tets = o.cutter ? static_cast<size_t>(o.cutter->num_tets()) : 0;
      topology_scratch_.emplace_back(tets + static_cast<size_t>(o.built.rest().size()), 0.0);
      topology_snapshots_.push_back(
          std::make_unique<SnapshotBuffer>(topology_scratch_.back().size()));
      surface_cutters_.push_back(
          o.cutter ? std::make_unique<cutting::TetCutter>(o.built.volume.tetrahedra, o.built.rest())
                   : nullptr);
      handed_version_.push_back(o.topology_version);
      published_version_.push_back(o.topology_version);
    }
    // Rigid bodies: x y z, w x y z, grasped (0/1) each, handed over like the organs' positions.
    rigid_scratch_.assign(kRigidValues * static_cast<size_t>(session.num_rigid()), 0.0);
    rigid_snapshot_ = std::make_unique<SnapshotBuffer>(rigid_scratch_.size());
    for (int32_t k = 0; k < session.num_rigid(); ++k) rigid_ids_.push_back(session.rigid(k).id);
    SnapshotRigidBodies();
    if (session.num_rigid() > 0) {
      rigid_writer_ = std::make_unique<dds::Writer<somasim_wire_RigidBodyState>>(
          *participant_, topics_->rigid_body, dds::RigidBodyQos(s));
    }
    tool_stats_.resize(static_cast<size_t>(session.num_tools()));
    force_samples_.resize(static_cast<size_t>(session.num_tools()));
    last_command_.assign(static_cast<size_t>(session.num_tools()), 0);
  }

  int Run() {
    PublishSessionAndTopology();
    Heartbeat(2);
    PublishEvent(11, "", "session starts: " + session_.scene().name());
    start_ = Clock::now();
    std::thread publisher([this] {
      try {
        PublisherLoop();
      } catch (const std::exception& e) {
        // A DDS failure while publishing: stop the session cleanly rather than abort.
        Log(LogLevel::kError, "publisher_failed", {{"error", e.what()}});
        app::RequestStop();
      }
    });
    try {
      PhysicsLoop();
    } catch (...) {
      shared_.done = true;
      publisher.join();
      throw;
    }
    shared_.done = true;
    publisher.join();
    if (recorder_ != nullptr) {
      recorder_->Finish(steps_, app::StopRequested() ? "stopped by a signal" : "the session ended");
      ReportRecordingFailure();
    }
    Heartbeat(4);
    PublishEvent(12, "", "session ends");
    return kExitOk;
  }

  nlohmann::ordered_json Report() const {
    nlohmann::ordered_json r;
    r["session"] = options_.session;
    r["scene"] = session_.scene().name();
    r["server_id"] = server_id_;
    r["sim_time_s"] = session_.time();
    r["wall_time_s"] = wall_time_;
    r["realtime_factor"] = wall_time_ > 0.0 ? session_.time() / wall_time_ : 0.0;
    r["ticks"] = session_.ticks();
    r["organ_steps"] = session_.organ_steps();
    r["rejected_steps"] = session_.rejected_steps();
    r["step_time_us"] = {
        {"mean", total_.count() > 0 ? total_sum_us_ / static_cast<double>(total_.count()) : 0.0},
        {"p50", total_.Quantile(0.5)},
        {"p90", total_.Quantile(0.9)},
        {"p99", total_.Quantile(0.99)},
        {"max", total_.max()}};
    r["frames_published"] = frames_published_;
    r["force_models_published"] = shared_.force_models.load();
    r["tool_commands_received"] = shared_.commands_received.load();
    r["tool_commands_rejected"] = shared_.commands_rejected.load();
    r["instructor_commands_received"] = shared_.instructor_received.load();
    r["publish_overruns"] = publish_overruns_;
    r["fell_behind_real_time"] = shared_.behind.load();
    nlohmann::ordered_json events = nlohmann::ordered_json::object();
    for (const auto& [name, count] : event_counts_) events[name] = count;
    r["events"] = events;
    nlohmann::ordered_json tools = nlohmann::ordered_json::array();
    for (int32_t t = 0; t < session_.num_tools(); ++t) {
      const ToolStats& s = tool_stats_[static_cast<size_t>(t)];
      tools.push_back(
          {{"id", session_.tool(t).id},
           {"contact_time_s", s.contact_time},
           {"max_force_n", s.max_force},
           {"mean_force_in_contact_n", s.contact_time > 0.0 ? s.force_sum / s.contact_time : 0.0},
           {"grasps", s.grasps}});
    }
    r["tools"] = tools;
    nlohmann::ordered_json organs = nlohmann::ordered_json::array();
    for (int32_t k = 0; k < session_.num_organs(); ++k) {
      const SessionOrgan& o = session_.organ(k);
      organs.push_back({{"id", o.built.id},
                        {"topology_version", o.topology_version},
                        {"elements_cut", o.elements_cut}});
    }
    r["organs"] = organs;
    if (recorder_ != nullptr) {
      const RecorderStats rs = recorder_->stats();
      r["recording"] = {{"file", options_.record}, {"records", rs.records},   {"bytes", rs.bytes},
                        {"gaps", rs.gaps},         {"records_lost", rs.lost}, {"failed", rs.failed},
                        {"error", rs.error}};
    }
    return r;
  }

 private:
  void PublishSessionAndTopology() {
    std::string text;
    google::protobuf::TextFormat::PrintToString(session_.scene(), &text);
    std::vector<somasim_wire_OrganInfo> organs(static_cast<size_t>(session_.num_organs()));
    for (int32_t k = 0; k < session_.num_organs(); ++k) {
      const organs::BuiltOrgan& b = session_.organ(k).built;
      somasim_wire_OrganInfo& o = organs[static_cast<size_t>(k)];
      o.id = dds::CString(b.id);
      o.model = dds::CString(b.model_name);
      o.mesh = dds::CString(b.mesh_name);
      o.dt = b.dt;
      o.num_nodes = static_cast<uint32_t>(b.model->num_nodes());
      o.num_triangles = static_cast<uint32_t>(b.triangles.cols());
    }
    std::vector<somasim_wire_ToolInfo> tools(static_cast<size_t>(session_.num_tools()));
    for (int32_t t = 0; t < session_.num_tools(); ++t) {
      const SessionTool& st = session_.tool(t);
      somasim_wire_ToolInfo& w = tools[static_cast<size_t>(t)];
      w.id = dds::CString(st.id);
      w.kind = const_cast<char*>(contact::ToolKindName(st.shape.kind));
      w.shaft_length = st.shape.shaft_length;
      w.shaft_radius = st.shape.shaft_radius;
      w.jaw_length = st.shape.kind == contact::ToolKind::kGrasper ? st.shape.jaw_length : 0.0;
      w.blade_length = st.shape.kind == contact::ToolKind::kScalpel ? st.shape.blade_length : 0.0;
    }
    const std::string version = SOMASIM_VERSION;
    const std::string scene_name = session_.scene().name();
    somasim_wire_SessionInfo info{};
    info.format_version = dds::kWireFormatVersion;
    info.server_id = server_id_;
    info.session = dds::CString(options_.session);
    info.scene_name = dds::CString(scene_name);
    info.scene_text = dds::CString(text);
    info.server_version = dds::CString(version);
    info.frame_rate = options_.frame_rate;
    info.keyframe_interval = options_.keyframe_interval;
    info.organs._buffer = organs.data();
    info.organs._length = info.organs._maximum = static_cast<uint32_t>(organs.size());
    info.tools._buffer = tools.data();
    info.tools._length = info.tools._maximum = static_cast<uint32_t>(tools.size());
    session_writer_->Write(info);
    for (int32_t k = 0; k < session_.num_organs(); ++k) {
      const organs::BuiltOrgan& b = session_.organ(k).built;
      const std::vector<uint8_t> inner(static_cast<size_t>(b.triangles.cols()), 0);
      PublishTopology(k, published_version_[static_cast<size_t>(k)],
                      {b.rest().data(), static_cast<size_t>(b.rest().size())}, b.triangles, inner);
    }
  }

  // One organ's topology: rest positions (3 × num_nodes [m]), surface triangles and their
  // inner-face marks, under `version`.
  void PublishTopology(int32_t k, uint32_t version, std::span<const double> rest_positions,
                       const mesh::Triangles& surface, const std::vector<uint8_t>& inner_faces) {
    const organs::BuiltOrgan& b = session_.organ(k).built;
    std::vector<float> rest(rest_positions.size());
    for (size_t i = 0; i < rest.size(); ++i) rest[i] = static_cast<float>(rest_positions[i]);
    std::vector<uint32_t> triangles(static_cast<size_t>(surface.size()));
    for (size_t i = 0; i < triangles.size(); ++i) {
      triangles[i] = static_cast<uint32_t>(surface.data()[i]);
    }
    std::vector<uint8_t> inner = inner_faces;
    somasim_wire_OrganTopology t{};
    t.organ = dds::CString(b.id);
    t.format_version = dds::kWireFormatVersion;
    t.server_id = server_id_;
    t.version = version;
    t.num_nodes = static_cast<uint32_t>(b.model->num_nodes());
    t.rest_positions._buffer = rest.data();
    t.rest_positions._length = t.rest_positions._maximum = static_cast<uint32_t>(rest.size());
    t.triangles._buffer = triangles.data();
    t.triangles._length = t.triangles._maximum = static_cast<uint32_t>(triangles.size());
    t.inner_face._buffer = inner.data();
    t.inner_face._length = t.inner_face._maximum = static_cast<uint32_t>(inner.size());
    topology_writer_->Write(t);
  }

  // Physics thread: hands over each organ whose topology version changed (a cut, a reset) — its
  // alive flags and rest positions. Allocation-free.
  void SnapshotTopologies() {
    for (int32_t k = 0; k < session_.num_organs(); ++k) {
      const auto i = static_cast<size_t>(k);
      const SessionOrgan& o = session_.organ(k);
      if (o.topology_version == handed_version_[i]) continue;
      handed_version_[i] = o.topology_version;
      std::vector<double>& out = topology_scratch_[i];
      size_t at = 0;
      if (o.cutter) {
        for (const uint8_t alive : o.cutter->alive_flags()) out[at++] = alive != 0 ? 1.0 : 0.0;
      }
      const mesh::Points& rest =
          o.built.fem != nullptr ? o.built.fem->RestPositions(*o.state) : o.built.rest();
      std::copy_n(rest.data(), rest.size(), out.begin() + static_cast<std::ptrdiff_t>(at));
      topology_snapshots_[i]->Write(out, static_cast<double>(o.topology_version));
    }
  }

  // Publisher thread: republishes the topologies handed over (the surface re-extracted with
  // the cut's inner faces marked), then a keyframe, as a subscriber needs one to start the new
  // topology's frames.
  void PublishTopologies() {
    for (int32_t k = 0; k < session_.num_organs(); ++k) {
      const auto i = static_cast<size_t>(k);
      SnapshotBuffer& snapshot = *topology_snapshots_[i];
      if (!snapshot.Take()) continue;
      const auto version = static_cast<uint32_t>(snapshot.time());
      const std::span<const double> values = snapshot.values();
      const organs::BuiltOrgan& b = session_.organ(k).built;
      size_t tets = 0;
      mesh::Triangles triangles = b.triangles;
      std::vector<uint8_t> inner(static_cast<size_t>(b.triangles.cols()), 0);
      if (surface_cutters_[i]) {
        tets = static_cast<size_t>(surface_cutters_[i]->num_tets());
        std::vector<uint8_t> alive(tets);
        for (size_t t = 0; t < tets; ++t) alive[t] = values[t] != 0.0 ? 1 : 0;
        surface_cutters_[i]->ExtractSurface(alive, &triangles, &inner);
      }
      published_version_[i] = version;
      PublishTopology(k, version, values.subspan(tets), triangles, inner);
      encoders_[i]->ForceKeyframe();
      Log(LogLevel::kInfo, "topology_republished",
          {{"organ", organ_ids_[i]},
           {"version", version},
           {"triangles", triangles.cols()},
           {"inner_faces", std::count(inner.begin(), inner.end(), uint8_t{1})}});
    }
  }

  void Heartbeat(uint32_t state) {
    somasim_wire_Heartbeat h{};
    h.format_version = dds::kWireFormatVersion;
    h.server_id = server_id_;
    h.seq = ++heartbeat_seq_;
    h.sim_time = shared_.sim_time.load();
    h.state = state;
    heartbeat_writer_->TryWrite(h);
  }

  void PublishEvent(uint32_t kind, const std::string& subject, const std::string& text) {
    somasim_wire_SessionEvent e{};
    e.format_version = dds::kWireFormatVersion;
    e.server_id = server_id_;
    e.seq = ++event_seq_;
    e.sim_time = shared_.sim_time.load();
    e.kind = kind;
    e.subject = dds::CString(subject);
    e.text = dds::CString(text);
    const dds_return_t rc = event_writer_->TryWrite(e);
    if (rc != DDS_RETCODE_OK) {
      Log(LogLevel::kWarning, "event_not_sent", {{"text", text}, {"code", rc}});
    }
    Log(LogLevel::kInfo, "session_event",
        {{"kind", kind}, {"subject", subject}, {"text", text}, {"sim_time", e.sim_time}});
  }

  // Physics thread: commands in, one tick, force models out, snapshots for the publisher.
  void PhysicsLoop() {
    LogSlice(app::SetSchedulerSlice(std::chrono::microseconds(0)), "physics thread");
    RequestRealtimePriority();
    Clock::time_point paced_start = Clock::now();
    Clock::time_point window_start = paced_start;
    uint64_t window_steps = 0;
    bool fast_forward = replay_ != nullptr && options_.replay_from > 0.0;
    while (!app::StopRequested()) {
      if (replay_ != nullptr) {
        if (ApplyReplay()) paced_start = Clock::now();  // a recorded reset: time starts at 0
        if (replay_->finished()) break;
      } else {
        DrainToolCommands();
      }
      if (shared_.reset.exchange(false)) {
        session_.Reset();
        paced_start = Clock::now();
        for (const SessionEventRecord& e : session_.TakeEvents()) {
          shared_.events.Push(e);
          if (recorder_ != nullptr) recorder_->Event(steps_, session_.time(), e);
        }
      }
      if (shared_.paused.load()) {
        const Clock::time_point before = Clock::now();
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
        paced_start += Clock::now() - before;  // the pause does not count as lag
        continue;
      }
      const Clock::time_point t0 = Clock::now();
      session_.Step();
      const Clock::time_point t1 = Clock::now();
      ++steps_;
      shared_.steps_taken = steps_;
      const double us = std::chrono::duration<double, std::micro>(t1 - t0).count();
      window_.Add(us);
      total_.Add(us);
      total_sum_us_ += us;
      ++window_steps;
      shared_.steps = session_.organ_steps();
      shared_.rejected_steps = session_.rejected_steps();
      shared_.sim_time = session_.time();
      PublishForceModels();
      for (const SessionEventRecord& e : session_.TakeEvents()) {
        shared_.events.Push(e);
        if (recorder_ != nullptr) recorder_->Event(steps_, session_.time(), e);
      }
      if (recorder_ != nullptr && steps_ % checkpoint_interval_ == 0) {
        recorder_->Checkpoint(steps_, session_.time(), session_);
      }
      if (fast_forward && session_.time() >= options_.replay_from - 1e-9) {
        // A replay from --from: the fast-forward is over; publish and pace from here.
        fast_forward = false;
        paced_start =
            Clock::now() - std::chrono::duration_cast<Clock::duration>(
                               std::chrono::duration<double>(session_.time() / options_.speed));
        Log(LogLevel::kInfo, "replay_from", {{"sim_time", session_.time()}, {"step", steps_}});
      }
      if (!fast_forward) {
        for (int32_t k = 0; k < session_.num_organs(); ++k) {
          const auto& x = session_.organ(k).state->positions;
          snapshots_[static_cast<size_t>(k)]->Write({x.data(), static_cast<size_t>(x.size())},
                                                    session_.time());
        }
        SnapshotRigidBodies();
      }
      SnapshotTopologies();
      if (t1 - window_start >= std::chrono::seconds(1)) {
        shared_.p50 = window_.Quantile(0.5);
        shared_.p99 = window_.Quantile(0.99);
        shared_.pmax = window_.max();
        shared_.rate = static_cast<double>(window_steps) / Seconds(t1 - window_start);
        window_.Clear();
        window_steps = 0;
        window_start = t1;
      }
      if (options_.duration > 0.0 && session_.time() >= options_.duration - 1e-9) break;
      if (options_.realtime && !fast_forward) {
        const Clock::time_point target =
            paced_start + std::chrono::duration_cast<Clock::duration>(
                              std::chrono::duration<double>(session_.time() / options_.speed));
        const Clock::time_point now = Clock::now();
        if (now < target) {
          std::this_thread::sleep_until(target);
        } else if (now - target > std::chrono::milliseconds(500)) {
          // Slower than real time: say so, and stop trying to catch up on the lost time.
          if (shared_.behind++ == 0) {
            Log(LogLevel::kWarning, "physics_behind_real_time",
                {{"sim_time", session_.time()}, {"lag_s", Seconds(now - target)}});
          }
          paced_start += now - target;
        }
      }
    }
    wall_time_ = Seconds(Clock::now() - start_);
  }

  // Physics thread, replay mode: the recording's inputs up to this step (tool commands, resets;
  // checkpoints compared). Whether a reset came.
  bool ApplyReplay() {
    replay_->ApplyUpTo(steps_, &session_);
    bool reset = false;
    for (const SessionEventRecord& e : session_.TakeEvents()) {
      shared_.events.Push(e);
      reset |= e.kind == SessionEventRecord::Kind::kReset;
    }
    const ReplayResult& r = replay_->result();
    if (r.diverged && !divergence_reported_) {
      divergence_reported_ = true;
      Log(LogLevel::kWarning, "replay_diverged", {{"divergence", r.divergence}});
    }
    return reset;
  }

  static void LogSlice(const app::SliceResult& r, const char* threads) {
    if (r.applied) {
      Log(LogLevel::kInfo, "scheduler_slice",
          {{"threads", threads}, {"slice_us", app::SchedulerSliceUs()}});
    } else {
      Log(LogLevel::kWarning, "scheduler_slice_not_applied",
          {{"threads", threads}, {"detail", r.detail}});
    }
  }

  void RequestRealtimePriority() {
    if (options_.rt_priority <= 0) return;
    sched_param param{};
    param.sched_priority = options_.rt_priority;
    const int rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param);
    if (rc != 0) {
      Log(LogLevel::kWarning, "realtime_refused",
          {{"detail", "SCHED_FIFO was refused (" + std::string(std::strerror(rc)) +
                          "); the physics thread runs at normal priority"}});
    } else {
      Log(LogLevel::kInfo, "realtime",
          {{"policy", "SCHED_FIFO"}, {"priority", options_.rt_priority}});
    }
  }

  void DrainToolCommands() {
    command_reader_->Take(
        [this](const somasim_wire_ToolCommand& c, const dds_sample_info_t&) {
          ++shared_.commands_received;
          int32_t tool = -1;
          ToolCommandInput input;
          const std::string error = CheckToolCommand(c, session_, &tool, &input);
          if (!error.empty()) {
            const uint64_t n = ++shared_.commands_rejected;
            if (n <= 10 || n % 1000 == 0) {
              Log(LogLevel::kWarning, "tool_command_dropped",
                  {{"reason", error}, {"dropped_so_far", n}});
            }
            return;
          }
          session_.SetToolCommand(tool, input);
          if (recorder_ != nullptr) recorder_->ToolCommand(steps_, session_.time(), tool, input);
          last_command_[static_cast<size_t>(tool)] = c.seq;
        },
        256);
  }

  void PublishForceModels() {
    const double dt = session_.dt();
    for (int32_t t = 0; t < session_.num_tools(); ++t) {
      const SessionTool& tool = session_.tool(t);
      if (tool.contacts.empty() || !tool.commanded) continue;
      const force_model::LocalForceModel& m = tool.force_model;
      ToolStats& stats = tool_stats_[static_cast<size_t>(t)];
      if (m.in_contact || m.grasping) {
        const double f =
            force_model::EvaluateLocalForceModel(m, tool.command.pose.tip, Eigen::Vector3d::Zero())
                .force.norm();
        stats.contact_time += dt;
        stats.force_sum += f * dt;
        stats.max_force = std::max(stats.max_force, f);
      }
      somasim_wire_ForceModel& w = force_samples_[static_cast<size_t>(t)];
      force_model::ToWire(m, &w);
      std::array<int32_t, force_model::kMaxHeldNodes> held{};
      const int32_t num_held = session_.HeldNodes(t, held);
      force_model::HeldNodesToWire({held.data(), static_cast<size_t>(num_held)}, &w);
      w.tool = dds::CString(tool.id);
      w.format_version = dds::kWireFormatVersion;
      w.server_id = server_id_;
      w.command_seq = last_command_[static_cast<size_t>(t)];
      w.organ = tool.force_organ >= 0
                    ? dds::CString(organ_ids_[static_cast<size_t>(tool.force_organ)])
                    : const_cast<char*>("");
      if (force_writer_->TryWrite(w) == DDS_RETCODE_OK) ++shared_.force_models;
    }
  }

  // Publisher thread: frames at the frame rate, heartbeat, metrics, events, instructor commands.
  void PublisherLoop() {
    const auto frame_period = std::chrono::duration_cast<Clock::duration>(
        std::chrono::duration<double>(1.0 / options_.frame_rate));
    Clock::time_point next_frame = Clock::now();
    Clock::time_point next_heartbeat = next_frame;
    Clock::time_point next_metrics = next_frame + std::chrono::seconds(1);
    int32_t matched = 0;
    while (!shared_.done.load() && !app::StopRequested()) {
      Clock::time_point now = Clock::now();
      if (now >= next_frame) {
        const int32_t readers = frame_writer_->MatchedReaders();
        if (readers > matched) {
          // A new viewer: a keyframe now rather than at the next interval.
          for (auto& e : encoders_) e->ForceKeyframe();
        }
        matched = readers;
        PublishTopologies();
        PublishFrames();
        PublishRigidBodies();
        next_frame += frame_period;
        if (now - next_frame > 2 * frame_period) {
          ++publish_overruns_;
          next_frame = now + frame_period;
        }
      }
      if (now >= next_heartbeat) {
        Heartbeat(shared_.paused.load() ? 3 : 2);
        next_heartbeat += dds::kHeartbeatPeriod;
        if (now > next_heartbeat) next_heartbeat = now + dds::kHeartbeatPeriod;
      }
      if (now >= next_metrics) {
        PublishMetrics();
        next_metrics += std::chrono::seconds(1);
      }
      SessionEventRecord e;
      while (shared_.events.Pop(&e)) PublishSessionEvent(e);
      TakeInstructorCommands();
      ReportRecordingFailure();
      const Clock::time_point wake = std::min({next_frame, next_heartbeat, next_metrics});
      now = Clock::now();
      if (wake > now)
        std::this_thread::sleep_for(
            std::min<Clock::duration>(wake - now, std::chrono::milliseconds(5)));
    }
    SessionEventRecord e;
    while (shared_.events.Pop(&e)) PublishSessionEvent(e);
    // The final shape, as a keyframe so that every subscriber can take it.
    PublishTopologies();
    for (auto& encoder : encoders_) encoder->ForceKeyframe();
    PublishFrames();
    PublishRigidBodies();
  }

 public:
  // Writes each organ's last published frame (ServerOptions::dump_final). False on an I/O error.
  bool DumpFinal(const std::string& dir) const {
    for (size_t k = 0; k < encoders_.size(); ++k) {
      if (!wire::WriteFrameDump(dir, organ_ids_[k], encoders_[k]->published(),
                                encoders_[k]->last_frame())) {
        return false;
      }
    }
    return true;
  }

 private:
  void PublishFrames() {
    for (size_t k = 0; k < encoders_.size(); ++k) {
      SnapshotBuffer& snapshot = *snapshots_[k];
      snapshot.Take();  // the newest, if any arrived; else the last one again (an empty delta)
      const wire::FrameView v = encoders_[k]->Encode(snapshot.values());
      somasim_wire_MeshFrame f{};
      f.organ = dds::CString(organ_ids_[k]);
      f.format_version = dds::kWireFormatVersion;
      f.server_id = server_id_;
      f.frame = v.frame;
      f.base_frame = v.base_frame;
      f.keyframe = v.keyframe;
      f.sim_time = snapshot.time();
      f.topology_version = published_version_[k];
      f.num_nodes = v.num_nodes;
      f.sender_time_ns =
          std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch())
              .count();
      f.indices._buffer = const_cast<uint32_t*>(v.indices.data());
      f.indices._length = f.indices._maximum = static_cast<uint32_t>(v.indices.size());
      f.positions._buffer = const_cast<float*>(v.positions.data());
      f.positions._length = f.positions._maximum = static_cast<uint32_t>(v.positions.size());
      if (frame_writer_->TryWrite(f) == DDS_RETCODE_OK) ++frames_published_;
    }
  }

  // Physics thread (and start-up): the rigid bodies' poses into their snapshot. Allocation-free.
  void SnapshotRigidBodies() {
    for (int32_t k = 0; k < session_.num_rigid(); ++k) {
      const contact::RigidSphere& body = *session_.rigid(k).sphere;
      double* out = rigid_scratch_.data() + kRigidValues * static_cast<size_t>(k);
      for (int i = 0; i < 3; ++i) out[i] = body.position()[i];
      out[3] = body.orientation().w();
      out[4] = body.orientation().x();
      out[5] = body.orientation().y();
      out[6] = body.orientation().z();
      out[7] = body.grasped() ? 1.0 : 0.0;
    }
    if (!rigid_scratch_.empty()) rigid_snapshot_->Write(rigid_scratch_, session_.time());
  }

  // Publisher thread: each rigid body's newest pose, with the frames.
  void PublishRigidBodies() {
    if (!rigid_writer_) return;
    rigid_snapshot_->Take();
    const std::span<const double> v = rigid_snapshot_->values();
    for (size_t k = 0; k < rigid_ids_.size(); ++k) {
      const double* in = v.data() + kRigidValues * k;
      somasim_wire_RigidBodyState b{};
      b.body = dds::CString(rigid_ids_[k]);
      b.format_version = dds::kWireFormatVersion;
      b.server_id = server_id_;
      b.sim_time = rigid_snapshot_->time();
      b.radius = session_.rigid(static_cast<int32_t>(k)).sphere->radius();  // fixed at start-up
      for (int i = 0; i < 3; ++i) b.position[i] = in[i];
      for (int i = 0; i < 4; ++i) b.orientation[i] = in[3 + i];
      b.grasped = in[7] != 0.0;
      rigid_writer_->TryWrite(b);
    }
  }

  // Publisher thread: a recording that stopped (a full disk, an fsync error) is said loudly,
  // once: an error event to every subscriber and an error in the log.
  void ReportRecordingFailure() {
    if (recorder_ == nullptr || recording_failure_reported_ || !recorder_->failed()) return;
    recording_failure_reported_ = true;
    const std::string error = recorder_->stats().error;
    Log(LogLevel::kError, "recording_stopped",
        {{"file", options_.record},
         {"error", error},
         {"detail", "the session goes on unrecorded"}});
    PublishEvent(2, "", "RECORDING STOPPED: " + error + " — the session goes on unrecorded");
  }

  void PublishMetrics() {
    somasim_wire_ServerMetrics m{};
    m.format_version = dds::kWireFormatVersion;
    m.server_id = server_id_;
    m.sim_time = shared_.sim_time.load();
    m.wall_time = Seconds(Clock::now() - start_);
    m.steps = shared_.steps.load();
    m.rejected_steps = shared_.rejected_steps.load();
    m.step_p50_us = shared_.p50.load();
    m.step_p99_us = shared_.p99.load();
    m.step_max_us = shared_.pmax.load();
    m.physics_rate_hz = shared_.rate.load();
    m.frames_published = frames_published_;
    m.force_models_published = shared_.force_models.load();
    m.tool_commands_received = shared_.commands_received.load();
    m.tool_commands_rejected = shared_.commands_rejected.load();
    m.instructor_commands_received = shared_.instructor_received.load();
    m.publish_overruns = publish_overruns_;
    metrics_writer_->TryWrite(m);
    if (options_.verbose) {
      Log(LogLevel::kInfo, "metrics",
          {{"sim_time", m.sim_time},
           {"step_p50_us", m.step_p50_us},
           {"step_p99_us", m.step_p99_us},
           {"rate_hz", m.physics_rate_hz},
           {"frames", m.frames_published}});
    }
  }

  void PublishSessionEvent(const SessionEventRecord& e) {
    std::string subject;
    std::string text = EventText(e.kind);
    if (e.kind == SessionEventRecord::Kind::kReset) {
      PublishEvent(0, "", "session reset to rest by an instructor");
      return;
    }
    if (e.tool >= 0) subject = session_.tool(e.tool).id;
    if (e.organ >= 0) {
      const std::string& organ = organ_ids_[static_cast<size_t>(e.organ)];
      if (subject.empty()) {
        subject = organ;
      } else {
        text += ": " + organ;
      }
    }
    if (e.kind == SessionEventRecord::Kind::kGrasp) {
      text += " (" + std::to_string(e.detail) + " nodes held)";
      if (e.tool >= 0) ++tool_stats_[static_cast<size_t>(e.tool)].grasps;
    }
    if (e.kind == SessionEventRecord::Kind::kCut) {
      text += " (" + std::to_string(e.detail) + " removed)";
    }
    if (e.kind == SessionEventRecord::Kind::kStepRejected) {
      text += std::string(" (") +
              models::StepStatusName(static_cast<models::StepStatus>(e.detail)) +
              "; the organ was restored to its last good step)";
    }
    ++event_counts_[EventText(e.kind)];
    const uint32_t kind = static_cast<uint32_t>(e.kind);
    PublishEvent(e.kind == SessionEventRecord::Kind::kForceModelRefused ? 1 : kind, subject, text);
  }

  void TakeInstructorCommands() {
    instructor_reader_->Take(
        [this](const somasim_wire_InstructorCommand& c, const dds_sample_info_t&) {
          ++shared_.instructor_received;
          const std::string who = c.instructor == nullptr ? "" : c.instructor;
          const std::string text = c.text == nullptr ? "" : c.text;
          if (c.format_version != dds::kWireFormatVersion) {
            Log(LogLevel::kWarning, "instructor_command_dropped",
                {{"reason", "format_version " + std::to_string(c.format_version)}});
            return;
          }
          if (recorder_ != nullptr) {
            recorder_->Instructor(shared_.steps_taken.load(), shared_.sim_time.load(), c.kind, who,
                                  text);
          }
          switch (c.kind) {
            case 1:
              shared_.paused = true;
              PublishEvent(8, who, "paused by instructor " + who);
              break;
            case 2:
              shared_.paused = false;
              PublishEvent(9, who, "resumed by instructor " + who);
              break;
            case 3:
              if (replay_ != nullptr) {
                PublishEvent(1, who, "a replay cannot be reset: it plays the recording");
              } else {
                shared_.reset = true;
              }
              break;
            case 4:
              PublishEvent(10, who, text);
              break;
            default:
              PublishEvent(
                  1, who,
                  "instructor command " + std::to_string(c.kind) + " is not supported; ignored");
              break;
          }
        });
  }

  const ServerOptions& options_;
  Session& session_;
  Recorder* recorder_ = nullptr;      // none: not recording
  RecordedInputs* replay_ = nullptr;  // replay mode: the recording's inputs instead of DDS's
  bool divergence_reported_ = false;
  uint64_t steps_ = 0;  // physics thread: Session::Step calls
  uint64_t checkpoint_interval_ = Recorder::CheckpointInterval(session_.dt());
  bool recording_failure_reported_ = false;
  uint64_t server_id_ = 0;
  std::unique_ptr<dds::Domain> domain_;
  std::unique_ptr<dds::Participant> participant_;
  std::unique_ptr<dds::Topics> topics_;
  std::unique_ptr<dds::Writer<somasim_wire_SessionInfo>> session_writer_;
  std::unique_ptr<dds::Writer<somasim_wire_OrganTopology>> topology_writer_;
  std::unique_ptr<dds::Writer<somasim_wire_MeshFrame>> frame_writer_;
  std::unique_ptr<dds::Writer<somasim_wire_ForceModel>> force_writer_;
  std::unique_ptr<dds::Writer<somasim_wire_SessionEvent>> event_writer_;
  std::unique_ptr<dds::Writer<somasim_wire_Heartbeat>> heartbeat_writer_;
  std::unique_ptr<dds::Writer<somasim_wire_ServerMetrics>> metrics_writer_;
  std::unique_ptr<dds::Reader<somasim_wire_ToolCommand>> command_reader_;
  std::unique_ptr<dds::Reader<somasim_wire_InstructorCommand>> instructor_reader_;
  std::vector<std::unique_ptr<SnapshotBuffer>> snapshots_;
  std::vector<std::unique_ptr<SnapshotBuffer>> topology_snapshots_;   // per organ
  std::vector<std::vector<double>> topology_scratch_;                 // physics thread's
  std::vector<std::unique_ptr<cutting::TetCutter>> surface_cutters_;  // publisher's; null: uncut
  std::vector<uint32_t> handed_version_;     // physics thread: the last version handed over
  std::vector<uint32_t> published_version_;  // publisher thread: the last version published
  static constexpr size_t kRigidValues = 8;  // per rigid body: x y z, w x y z, grasped
  std::unique_ptr<dds::Writer<somasim_wire_RigidBodyState>> rigid_writer_;  // none: no bodies
  std::unique_ptr<SnapshotBuffer> rigid_snapshot_;
  std::vector<double> rigid_scratch_;  // physics thread: kRigidValues × bodies
  std::vector<std::string> rigid_ids_;
  std::vector<std::unique_ptr<wire::FrameEncoder>> encoders_;
  std::vector<std::string> organ_ids_;
  std::vector<ToolStats> tool_stats_;
  std::vector<somasim_wire_ForceModel> force_samples_;
  std::vector<uint64_t> last_command_;
  Shared shared_;
  StepTimeHistogram window_;
  StepTimeHistogram total_;
  double total_sum_us_ = 0.0;
  Clock::time_point start_ = Clock::now();
  double wall_time_ = 0.0;
  uint64_t heartbeat_seq_ = 0;
  uint64_t event_seq_ = 0;
  uint64_t frames_published_ = 0;
  uint64_t publish_overruns_ = 0;
  std::map<std::string, uint64_t> event_counts_;
};

}  // namespace

double StepTimeHistogram::Quantile(double q) const {
  if (count_ == 0) return 0.0;
  const auto target = static_cast<uint64_t>(std::ceil(q * static_cast<double>(count_)));
  uint64_t seen = 0;
  for (int i = 0; i < kBins; ++i) {
    seen += bins_[static_cast<size_t>(i)];
    if (seen >= target) return std::min(max_, std::pow(1.02, i + 1));
  }
  return max_;
}

int StepTimeHistogram::Bin(double microseconds) {
  if (!(microseconds > 1.0)) return 0;
  const int bin = static_cast<int>(std::log(microseconds) / std::log(1.02));
  return std::clamp(bin, 0, kBins - 1);
}

int ServerMain(int argc, char** argv) {
  app::SetLogProcess("server");
  ServerOptions options;
  CLI::App cli{
      "somasim-server: runs a session's physics and publishes it over Cyclone DDS.\n"
      "Exit codes: 0 done, 2 usage, 3 bad scene or mesh, 4 I/O, 5 DDS, 70 bug."};
  cli.set_version_flag("--version", std::string("somasim-server ") + SOMASIM_VERSION);
  cli.add_option("--scene", options.scene, "a .scene.txtpb file, or builtin:NAME")
      ->capture_default_str();
  cli.add_option("--session", options.session, "the session's name (its DDS partition)")
      ->capture_default_str();
  cli.add_flag("--headless", options.headless, "no window (the server never opens one)");
  cli.add_option("--duration", options.duration,
                 "seconds of session time to run; 0 runs until SIGINT/SIGTERM")
      ->check(CLI::NonNegativeNumber);
  cli.add_option("--domain", options.domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--dds-config", options.dds_config,
                 "Cyclone DDS XML configuration (deploy/cyclonedds-*.xml); default: "
                 "CYCLONEDDS_URI or Cyclone's defaults");
  cli.add_option("--frame-rate", options.frame_rate, "mesh frames per second")
      ->check(CLI::Range(1.0, 1000.0))
      ->capture_default_str();
  cli.add_option("--keyframe-interval", options.keyframe_interval,
                 "a full keyframe every this many frames")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  bool fast = false;
  cli.add_flag("--as-fast-as-possible", fast,
               "do not pace session time to the wall clock (offline runs, tests)");
  cli.add_option("--report", options.report, "write a JSON report here at the end");
  cli.add_option("--record", options.record,
                 "record the session to this new file (.somarec; never overwritten), for "
                 "somasim-replay");
  cli.add_option("--trainee", options.trainee,
                 "the trainee's pseudonym in the recording (letters, digits, - and _; at most 32; "
                 "never a person's name)");
  cli.add_option("--rt-priority", options.rt_priority,
                 "run the physics thread under SCHED_FIFO at this priority (1-99; needs "
                 "CAP_SYS_NICE; refused: says so and runs at normal priority). A physics "
                 "slower than real time then holds its core")
      ->check(CLI::Range(0, 99));
  cli.add_option("--dump-final", options.dump_final,
                 "at the end, write each organ's last published frame to DIR/<organ>.f32 "
                 "(float32 x y z per node) and DIR/<organ>.frame (for exactness checks)");
  cli.add_flag("-v,--verbose", options.verbose, "log metrics every second");
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  options.realtime = !fast;
  if (const std::string bad = dds::SessionNameError(options.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-server: --session \"%s\" %s\n", options.session.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  if (const std::string bad = TraineeError(options.trainee); !bad.empty()) {
    std::fprintf(stderr, "somasim-server: --trainee \"%s\" %s\n", options.trainee.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  app::InstallStopSignals();
  std::unique_ptr<Session> session;
  std::string scene_dir = ".";
  try {
    scene::Scene scene;
    scene::SceneLines lines(options.scene);
    if (options.scene.rfind("builtin:", 0) == 0) {
      scene = ServerDefaultScene(options.scene.substr(8));
    } else {
      scene = scene::LoadSceneFile(options.scene, &lines);
      scene_dir = std::filesystem::path(options.scene).parent_path().string();
      if (scene_dir.empty()) scene_dir = ".";
    }
    Log(LogLevel::kInfo, "building", {{"scene", options.scene}});
    session = std::make_unique<Session>(scene, lines, scene_dir);
  } catch (const scene::SceneError& e) {
    Log(LogLevel::kError, "bad_scene", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: %s\n", e.what());
    return kExitBadInput;
  } catch (const mesh_io::MeshError& e) {
    Log(LogLevel::kError, "bad_mesh", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: %s\n", e.what());
    return kExitBadInput;
  } catch (const std::invalid_argument& e) {
    Log(LogLevel::kError, "bad_scene", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: %s: %s\n", options.scene.c_str(), e.what());
    return kExitBadInput;
  }
  std::string dds_config;
  try {
    dds_config = dds::ReadDdsConfig(options.dds_config);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-server: %s\n", e.what());
    return kExitIo;
  }
  std::unique_ptr<Recorder> recorder;
  if (!options.record.empty()) {
    std::string error;
    std::unique_ptr<recording::Sink> sink = recording::CreateFileSink(options.record, &error);
    try {
      if (!sink) throw std::runtime_error(error);
      recorder =
          std::make_unique<Recorder>(std::move(sink),
                                     Recorder::MakeHeader(*session, scene_dir, options.session,
                                                          options.trainee, SOMASIM_VERSION),
                                     *session);
    } catch (const std::runtime_error& e) {
      Log(LogLevel::kError, "recording_refused", {{"file", options.record}, {"error", e.what()}});
      std::fprintf(stderr, "somasim-server: %s\n", e.what());
      return kExitIo;
    }
    Log(LogLevel::kInfo, "recording", {{"file", options.record}});
  }
  nlohmann::ordered_json report;
  try {
    Server server(options, *session, dds_config, recorder.get());
    Log(LogLevel::kInfo, "running",
        {{"session", options.session},
         {"domain", options.domain},
         {"organs", session->num_organs()},
         {"tools", session->num_tools()},
         {"tick_s", session->dt()},
         {"duration_s", options.duration}});
    server.Run();
    report = server.Report();
    if (!options.dump_final.empty() && !server.DumpFinal(options.dump_final)) {
      std::fprintf(stderr, "somasim-server: cannot write %s\n", options.dump_final.c_str());
      return kExitIo;
    }
  } catch (const dds::DdsError& e) {
    Log(LogLevel::kError, "dds", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: DDS: %s\n", e.what());
    return kExitDds;
  }
  Log(LogLevel::kInfo, "stopped",
      {{"signal", app::StopSignal()},
       {"sim_time", report["sim_time_s"]},
       {"organ_steps", report["organ_steps"]}});
  if (!options.report.empty()) {
    std::ofstream out(options.report);
    out << report.dump(2) << "\n";
    if (!out) {
      std::fprintf(stderr, "somasim-server: cannot write the report %s\n", options.report.c_str());
      return kExitIo;
    }
  }
  return kExitOk;
}

int ReplayServerMain(const ServerOptions& given, const std::string& file) {
  app::SetLogProcess("replay");
  ServerOptions options = given;
  if (const std::string bad = dds::SessionNameError(options.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-replay: --session \"%s\" %s\n", options.session.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  app::InstallStopSignals();
  std::unique_ptr<RecordedInputs> inputs;
  std::unique_ptr<Session> session;
  try {
    inputs = std::make_unique<RecordedInputs>(file);
    session = inputs->MakeSession();
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return kExitBadInput;
  }
  // The checkpoint nearest to --from.
  const double every = static_cast<double>(inputs->header().checkpoint_interval()) * session->dt();
  if (options.replay_from > 0.0 && every > 0.0) {
    options.replay_from = std::round(options.replay_from / every) * every;
  }
  std::string dds_config;
  try {
    dds_config = dds::ReadDdsConfig(options.dds_config);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return kExitIo;
  }
  nlohmann::ordered_json report;
  try {
    Server server(options, *session, dds_config, nullptr, inputs.get());
    Log(LogLevel::kInfo, "replaying",
        {{"file", file},
         {"session", options.session},
         {"domain", options.domain},
         {"speed", options.speed},
         {"from_s", options.replay_from}});
    server.Run();
    report = server.Report();
  } catch (const dds::DdsError& e) {
    std::fprintf(stderr, "somasim-replay: DDS: %s\n", e.what());
    return kExitDds;
  } catch (const std::exception& e) {  // a corrupt record met while publishing
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return kExitBadInput;
  }
  const ReplayResult& r = inputs->result();
  report["replay"] = {{"file", file},
                      {"checkpoints_matched", r.checkpoints_matched},
                      {"diverged", r.diverged},
                      {"divergence", r.divergence},
                      {"gap", r.gap},
                      {"truncated", r.truncated},
                      {"ended_cleanly", r.ended_cleanly},
                      {"finished", inputs->finished()}};
  std::printf(
      "published the replay of %s in session %s: %.3f s of session time, %llu "
      "checkpoints reproduced bit for bit%s\n",
      file.c_str(), options.session.c_str(), session->time(),
      static_cast<unsigned long long>(r.checkpoints_matched),
      r.diverged ? (", then DIVERGED: " + r.divergence).c_str() : "");
  if (!options.report.empty()) {
    std::ofstream out(options.report);
    out << report.dump(2) << "\n";
    if (!out) return kExitIo;
  }
  return r.diverged ? 1 : kExitOk;
}

}  // namespace somasim::server
