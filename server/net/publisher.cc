#include "server/net/publisher.h"

#include <google/protobuf/text_format.h>

#include <algorithm>
#include <chrono>
#include <thread>

#include "common/app/log.h"
#include "common/app/signals.h"
#include "common/wire/frame_dump.h"
#include "server/net/wire_adapters.h"

namespace somasim::net {
namespace {

using Clock = std::chrono::steady_clock;
using app::Log;
using app::LogLevel;
using runner::SessionEventRecord;

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }

}  // namespace

Publisher::Publisher(const PublisherOptions& options, runner::PhysicsRunner& runner,
                     Endpoints& endpoints, const ToolLink& link, uint64_t server_id,
                     runner::Recorder* recorder, runner::RecordedInputs* replay)
    : options_(options),
      runner_(runner),
      session_(runner.session()),
      endpoints_(endpoints),
      link_(link),
      server_id_(server_id),
      recorder_(recorder),
      replay_(replay) {
  for (int32_t k = 0; k < session_.num_organs(); ++k) {
    const server::SessionOrgan& o = session_.organ(k);
    organ_ids_.push_back(o.built.id);
    encoders_.push_back(std::make_unique<wire::FrameEncoder>(o.built.model->num_nodes(),
                                                             options.keyframe_interval));
    published_version_.push_back(o.topology_version);
    cut_surfaces_.push_back(o.cutter ? std::make_unique<cutting::CutSurface>(
                                           o.built.model->num_nodes(), o.built.volume.tetrahedra)
                                     : nullptr);
  }
  for (int32_t k = 0; k < session_.num_rigid(); ++k) rigid_ids_.push_back(session_.rigid(k).id);
  grasps_.assign(static_cast<size_t>(session_.num_tools()), 0);
}

void Publisher::PublishStart() {
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
    const server::SessionTool& st = session_.tool(t);
    somasim_wire_ToolInfo& w = tools[static_cast<size_t>(t)];
    w.id = dds::CString(st.id);
    w.kind = const_cast<char*>(contact::ToolKindName(st.shape.kind));
    w.shaft_length = st.shape.shaft_length;
    w.shaft_radius = st.shape.shaft_radius;
    w.jaw_length = st.shape.kind == contact::ToolKind::kGrasper ? st.shape.jaw_length : 0.0;
    w.blade_length = st.shape.kind == contact::ToolKind::kScalpel ? st.shape.blade_length : 0.0;
  }
  const std::string scene_name = session_.scene().name();
  somasim_wire_SessionInfo info{};
  info.format_version = dds::kWireFormatVersion;
  info.server_id = server_id_;
  info.session = dds::CString(options_.session);
  info.scene_name = dds::CString(scene_name);
  info.scene_text = dds::CString(text);
  info.server_version = dds::CString(options_.software_version);
  info.frame_rate = options_.frame_rate;
  info.keyframe_interval = options_.keyframe_interval;
  info.organs._buffer = organs.data();
  info.organs._length = info.organs._maximum = static_cast<uint32_t>(organs.size());
  info.tools._buffer = tools.data();
  info.tools._length = info.tools._maximum = static_cast<uint32_t>(tools.size());
  endpoints_.session.Write(info);
  for (int32_t k = 0; k < session_.num_organs(); ++k) {
    const organs::BuiltOrgan& b = session_.organ(k).built;
    const std::vector<uint8_t> inner(static_cast<size_t>(b.triangles.cols()), 0);
    PublishTopology(k, published_version_[static_cast<size_t>(k)],
                    {b.rest().data(), static_cast<size_t>(b.rest().size())}, b.triangles, inner);
  }
  Heartbeat(2);
  PublishEvent(11, "", "session starts: " + session_.scene().name());
  start_ = Clock::now();
}

void Publisher::PublishEnd() {
  Heartbeat(4);
  PublishEvent(12, "", "session ends");
}

// One organ's topology: rest positions (3 × num_nodes [m]), surface triangles and their
// inner-face marks, under `version`.
void Publisher::PublishTopology(int32_t k, uint32_t version, std::span<const double> rest,
                                const mesh::Triangles& surface,
                                std::span<const uint8_t> inner_faces) {
  const organs::BuiltOrgan& b = session_.organ(k).built;
  std::vector<float> rest_f(rest.size());
  for (size_t i = 0; i < rest.size(); ++i) rest_f[i] = static_cast<float>(rest[i]);
  std::vector<uint32_t> triangles(static_cast<size_t>(surface.size()));
  for (size_t i = 0; i < triangles.size(); ++i) {
    triangles[i] = static_cast<uint32_t>(surface.data()[i]);
  }
  somasim_wire_OrganTopology t{};
  t.organ = dds::CString(b.id);
  t.format_version = dds::kWireFormatVersion;
  t.server_id = server_id_;
  t.version = version;
  t.num_nodes = static_cast<uint32_t>(b.model->num_nodes());
  t.rest_positions._buffer = rest_f.data();
  t.rest_positions._length = t.rest_positions._maximum = static_cast<uint32_t>(rest_f.size());
  t.triangles._buffer = triangles.data();
  t.triangles._length = t.triangles._maximum = static_cast<uint32_t>(triangles.size());
  t.inner_face._buffer = const_cast<uint8_t*>(inner_faces.data());  // the writer only reads
  t.inner_face._length = t.inner_face._maximum = static_cast<uint32_t>(inner_faces.size());
  endpoints_.topology.Write(t);
}

// The topologies the physics handed on (a cut, a reset): the surface re-extracted with the cut's
// inner faces marked, then a keyframe, as a subscriber needs one to start the new topology's
// frames.
void Publisher::PublishTopologies() {
  for (int32_t k = 0; k < session_.num_organs(); ++k) {
    const auto i = static_cast<size_t>(k);
    lockfree::TripleBuffer<runner::TopologySnapshot>& buffer = runner_.topology(k);
    if (!buffer.Take()) continue;
    const runner::TopologySnapshot& snapshot = buffer.front();
    const organs::BuiltOrgan& b = session_.organ(k).built;
    mesh::Triangles triangles = b.triangles;
    std::vector<uint8_t> inner(static_cast<size_t>(b.triangles.cols()), 0);
    if (cut_surfaces_[i]) cut_surfaces_[i]->Extract(snapshot.alive, &triangles, &inner);
    published_version_[i] = snapshot.version;
    PublishTopology(k, snapshot.version, snapshot.rest, triangles, inner);
    encoders_[i]->ForceKeyframe();
    Log(LogLevel::kInfo, "topology_republished",
        {{"organ", organ_ids_[i]},
         {"version", snapshot.version},
         {"triangles", triangles.cols()},
         {"inner_faces", std::count(inner.begin(), inner.end(), uint8_t{1})}});
  }
}

void Publisher::PublishFrames() {
  for (size_t k = 0; k < encoders_.size(); ++k) {
    lockfree::TripleBuffer<runner::PositionsSnapshot>& buffer =
        runner_.positions(static_cast<int32_t>(k));
    buffer.Take();  // the newest, if any arrived; else the last one again (an empty delta)
    const runner::PositionsSnapshot& snapshot = buffer.front();
    const wire::FrameView v = encoders_[k]->Encode(snapshot.positions);
    somasim_wire_MeshFrame f{};
    f.organ = dds::CString(organ_ids_[k]);
    f.format_version = dds::kWireFormatVersion;
    f.server_id = server_id_;
    f.frame = v.frame;
    f.base_frame = v.base_frame;
    f.keyframe = v.keyframe;
    f.sim_time = snapshot.sim_time;
    f.topology_version = published_version_[k];
    f.num_nodes = v.num_nodes;
    f.sender_time_ns =
        std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch())
            .count();
    f.indices._buffer = const_cast<uint32_t*>(v.indices.data());
    f.indices._length = f.indices._maximum = static_cast<uint32_t>(v.indices.size());
    f.positions._buffer = const_cast<float*>(v.positions.data());
    f.positions._length = f.positions._maximum = static_cast<uint32_t>(v.positions.size());
    if (endpoints_.frame.TryWrite(f) == DDS_RETCODE_OK) ++frames_published_;
  }
}

// Each rigid body's newest pose, with the frames.
void Publisher::PublishRigidBodies() {
  if (!endpoints_.rigid_body) return;
  lockfree::TripleBuffer<runner::RigidSnapshot>& buffer = runner_.rigid();
  buffer.Take();
  const runner::RigidSnapshot& snapshot = buffer.front();
  for (size_t k = 0; k < rigid_ids_.size(); ++k) {
    const runner::RigidPose& p = snapshot.bodies[k];
    somasim_wire_RigidBodyState b{};
    b.body = dds::CString(rigid_ids_[k]);
    b.format_version = dds::kWireFormatVersion;
    b.server_id = server_id_;
    b.sim_time = snapshot.sim_time;
    b.radius = session_.rigid(static_cast<int32_t>(k)).sphere->radius();  // fixed at start-up
    for (int i = 0; i < 3; ++i) b.position[i] = p.position[i];
    for (int i = 0; i < 4; ++i) b.orientation[i] = p.orientation[i];
    b.grasped = p.grasped;
    endpoints_.rigid_body->TryWrite(b);
  }
}

void Publisher::Run(const std::atomic<bool>& done) {
  const auto frame_period = std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double>(1.0 / options_.frame_rate));
  Clock::time_point next_frame = Clock::now();
  Clock::time_point next_heartbeat = next_frame;
  Clock::time_point next_metrics = next_frame + std::chrono::seconds(1);
  int32_t matched = 0;
  while (!done.load() && !app::StopRequested()) {
    Clock::time_point now = Clock::now();
    if (now >= next_frame) {
      const int32_t readers = endpoints_.frame.MatchedReaders();
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
      Heartbeat(runner_.paused() ? 3 : 2);
      next_heartbeat += dds::kHeartbeatPeriod;
      if (now > next_heartbeat) next_heartbeat = now + dds::kHeartbeatPeriod;
    }
    if (now >= next_metrics) {
      PublishMetrics();
      next_metrics += std::chrono::seconds(1);
    }
    SessionEventRecord e;
    while (runner_.events().Pop(&e)) PublishSessionEvent(e);
    TakeInstructorCommands();
    ReportRunnerNotices();
    ReportRecordingFailure();
    const Clock::time_point wake = std::min({next_frame, next_heartbeat, next_metrics});
    now = Clock::now();
    if (wake > now) {
      std::this_thread::sleep_for(
          std::min<Clock::duration>(wake - now, std::chrono::milliseconds(5)));
    }
  }
  SessionEventRecord e;
  while (runner_.events().Pop(&e)) PublishSessionEvent(e);
  ReportRunnerNotices();
  // The final shape, as a keyframe so that every subscriber can take it.
  PublishTopologies();
  for (auto& encoder : encoders_) encoder->ForceKeyframe();
  PublishFrames();
  PublishRigidBodies();
}

bool Publisher::DumpFinal(const std::string& dir) const {
  for (size_t k = 0; k < encoders_.size(); ++k) {
    if (!wire::WriteFrameDump(dir, organ_ids_[k], encoders_[k]->published(),
                              encoders_[k]->last_frame())) {
      return false;
    }
  }
  return true;
}

void Publisher::Heartbeat(uint32_t state) {
  somasim_wire_Heartbeat h{};
  h.format_version = dds::kWireFormatVersion;
  h.server_id = server_id_;
  h.seq = ++heartbeat_seq_;
  h.sim_time = runner_.counters().sim_time.load();
  h.state = state;
  endpoints_.heartbeat.TryWrite(h);
}

void Publisher::PublishMetrics() {
  const runner::RunnerCounters& c = runner_.counters();
  const LinkCounters& l = link_.counters();
  somasim_wire_ServerMetrics m{};
  m.format_version = dds::kWireFormatVersion;
  m.server_id = server_id_;
  m.sim_time = c.sim_time.load();
  m.wall_time = Seconds(Clock::now() - start_);
  m.steps = c.steps.load();
  m.rejected_steps = c.rejected_steps.load();
  m.step_p50_us = c.p50.load();
  m.step_p99_us = c.p99.load();
  m.step_max_us = c.pmax.load();
  m.physics_rate_hz = c.rate.load();
  m.frames_published = frames_published_;
  m.force_models_published = l.force_models.load();
  m.tool_commands_received = l.commands_received.load();
  m.tool_commands_rejected = l.commands_rejected.load();
  m.instructor_commands_received = instructor_received_;
  m.publish_overruns = publish_overruns_;
  endpoints_.metrics.TryWrite(m);
  if (options_.verbose) {
    Log(LogLevel::kInfo, "metrics",
        {{"sim_time", m.sim_time},
         {"step_p50_us", m.step_p50_us},
         {"step_p99_us", m.step_p99_us},
         {"rate_hz", m.physics_rate_hz},
         {"frames", m.frames_published}});
  }
}

void Publisher::PublishEvent(uint32_t kind, const std::string& subject, const std::string& text) {
  somasim_wire_SessionEvent e{};
  e.format_version = dds::kWireFormatVersion;
  e.server_id = server_id_;
  e.seq = ++event_seq_;
  e.sim_time = runner_.counters().sim_time.load();
  e.kind = kind;
  e.subject = dds::CString(subject);
  e.text = dds::CString(text);
  const dds_return_t rc = endpoints_.event.TryWrite(e);
  if (rc != DDS_RETCODE_OK) {
    Log(LogLevel::kWarning, "event_not_sent", {{"text", text}, {"code", rc}});
  }
  Log(LogLevel::kInfo, "session_event",
      {{"kind", kind}, {"subject", subject}, {"text", text}, {"sim_time", e.sim_time}});
}

void Publisher::PublishSessionEvent(const SessionEventRecord& e) {
  using Kind = SessionEventRecord::Kind;
  if (e.kind == Kind::kReset) {
    PublishEvent(0, "", "session reset to rest by an instructor");
    return;
  }
  std::string subject;
  std::string text = EventText(e.kind);
  if (e.tool >= 0) subject = session_.tool(e.tool).id;
  if (e.organ >= 0) {
    const std::string& organ = organ_ids_[static_cast<size_t>(e.organ)];
    if (subject.empty()) {
      subject = organ;
    } else {
      text += ": " + organ;
    }
  }
  if (e.kind == Kind::kGrasp) {
    text += " (" + std::to_string(e.detail) + " nodes held)";
    if (e.tool >= 0) ++grasps_[static_cast<size_t>(e.tool)];
  }
  if (e.kind == Kind::kCut) text += " (" + std::to_string(e.detail) + " removed)";
  if (e.kind == Kind::kStepRejected) {
    text += std::string(" (") + models::StepStatusName(static_cast<models::StepStatus>(e.detail)) +
            "; the organ was restored to its last good step)";
  }
  ++event_counts_[EventText(e.kind)];
  const auto kind = static_cast<uint32_t>(e.kind);
  PublishEvent(e.kind == Kind::kForceModelRefused ? 1 : kind, subject, text);
}

void Publisher::TakeInstructorCommands() {
  endpoints_.instructor.Take([this](const somasim_wire_InstructorCommand& c,
                                    const dds_sample_info_t&) {
    ++instructor_received_;
    const std::string who = c.instructor == nullptr ? "" : c.instructor;
    const std::string text = c.text == nullptr ? "" : c.text;
    if (c.format_version != dds::kWireFormatVersion) {
      Log(LogLevel::kWarning, "instructor_command_dropped",
          {{"reason", "format_version " + std::to_string(c.format_version)}});
      return;
    }
    const runner::RunnerCounters& counters = runner_.counters();
    if (recorder_ != nullptr) {
      recorder_->Instructor(counters.ticks.load(), counters.sim_time.load(), c.kind, who, text);
    }
    switch (c.kind) {
      case 1:
        runner_.SetPaused(true);
        PublishEvent(8, who, "paused by instructor " + who);
        break;
      case 2:
        runner_.SetPaused(false);
        PublishEvent(9, who, "resumed by instructor " + who);
        break;
      case 3:
        if (replay_ != nullptr) {
          PublishEvent(1, who, "a replay cannot be reset: it plays the recording");
        } else {
          runner_.RequestReset();
        }
        break;
      case 4:
        PublishEvent(10, who, text);
        break;
      default:
        PublishEvent(1, who,
                     "instructor command " + std::to_string(c.kind) + " is not supported; ignored");
        break;
    }
  });
}

// What the physics thread counts but does not say itself (it does not log while it runs).
void Publisher::ReportRunnerNotices() {
  const runner::RunnerCounters& c = runner_.counters();
  if (!behind_reported_ && c.behind.load() > 0) {
    behind_reported_ = true;
    Log(LogLevel::kWarning, "physics_behind_real_time",
        {{"sim_time", c.sim_time.load()}, {"detail", "more than 0.5 s behind the wall clock"}});
  }
  if (!fast_forward_reported_ && c.fast_forwarded.load()) {
    fast_forward_reported_ = true;
    Log(LogLevel::kInfo, "replay_from",
        {{"sim_time", c.sim_time.load()}, {"step", c.ticks.load()}});
  }
  if (replay_ != nullptr && !divergence_reported_ && c.replay_diverged.load()) {
    divergence_reported_ = true;
    Log(LogLevel::kWarning, "replay_diverged", {{"divergence", replay_->result().divergence}});
  }
}

void Publisher::ReportRecordingFailure() {
  if (recorder_ == nullptr || recording_failure_reported_ || !recorder_->failed()) return;
  recording_failure_reported_ = true;
  const std::string error = recorder_->stats().error;
  Log(LogLevel::kError, "recording_stopped",
      {{"file", options_.record}, {"error", error}, {"detail", "the session goes on unrecorded"}});
  PublishEvent(2, "", "RECORDING STOPPED: " + error + " — the session goes on unrecorded");
}

}  // namespace somasim::net
