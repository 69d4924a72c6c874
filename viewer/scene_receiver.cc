#include "viewer/scene_receiver.h"

#include <google/protobuf/io/tokenizer.h>
#include <google/protobuf/text_format.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <iterator>

#include "common/force_model/force_model_wire.h"
#include "common/wire/mesh_frame_view.h"
#include "idl/scene.pb.h"

namespace somasim::viewer {

namespace {

constexpr size_t kMaxMessages = 8;  // scenario messages kept for the heads-up display

// Silences protobuf's parse errors: a scene text the viewer cannot read only costs it the
// grasp radii (their defaults stay).
class QuietErrors : public google::protobuf::io::ErrorCollector {
 public:
  void AddError(int, int, const std::string&) override {}
};

}  // namespace

Eigen::Vector3d ToolScene::Force() const {
  if (!has_model || !has_pose) return Eigen::Vector3d::Zero();
  return force_model::EvaluateLocalForceModel(
             model, Eigen::Vector3d(position[0], position[1], position[2]), Eigen::Vector3d::Zero())
      .force;
}

const float* OrganScene::positions() const {
  return has_shape() ? decoder->positions().data() : rest.data();
}

SceneReceiver::SceneReceiver(const dds::Participant& participant, const dds::Topics& topics,
                             const std::string& session) {
  session_ = std::make_unique<dds::Reader<somasim_wire_SessionInfo>>(participant, topics.session,
                                                                     dds::SessionQos(session));
  topology_ = std::make_unique<dds::Reader<somasim_wire_OrganTopology>>(
      participant, topics.topology, dds::TopologyQos(session));
  frames_ = std::make_unique<dds::Reader<somasim_wire_MeshFrame>>(participant, topics.frame,
                                                                  dds::FrameQos(session));
  heartbeat_ = std::make_unique<dds::Reader<somasim_wire_Heartbeat>>(participant, topics.heartbeat,
                                                                     dds::HeartbeatQos(session));
  metrics_reader_ = std::make_unique<dds::Reader<somasim_wire_ServerMetrics>>(
      participant, topics.metrics, dds::MetricsQos(session));
  events_ = std::make_unique<dds::Reader<somasim_wire_SessionEvent>>(participant, topics.event,
                                                                     dds::EventQos(session));
  tool_commands_ = std::make_unique<dds::Reader<somasim_wire_ToolCommand>>(
      participant, topics.tool_command, dds::ToolCommandQos(session));
  force_models_ = std::make_unique<dds::Reader<somasim_wire_ForceModel>>(
      participant, topics.force_model, dds::ForceModelQos(session));
  rigid_reader_ = std::make_unique<dds::Reader<somasim_wire_RigidBodyState>>(
      participant, topics.rigid_body, dds::RigidBodyQos(session));
}

SceneReceiver::~SceneReceiver() = default;

void SceneReceiver::SeeServer(uint64_t id) {
  if (id == server_id_) return;
  if (server_id_ != 0) ++counters_.server_restarts;
  // A new server (a restart): what the old one published no longer holds.
  server_id_ = id;
  // Heard from now (its session, topology or frame arrived): alive for a lease even before its
  // first heartbeat, which may come after the transient-local samples.
  last_heartbeat_ = std::chrono::steady_clock::now();
  organs_.clear();
  tools_.clear();
  rigid_bodies_.clear();
  has_session_ = false;
}

void SceneReceiver::OnSession(const somasim_wire_SessionInfo& s) {
  if (s.format_version != dds::kWireFormatVersion) {
    ++counters_.wrong_format_version;
    return;
  }
  SeeServer(s.server_id);
  has_session_ = true;
  scene_name_ = s.scene_name != nullptr ? s.scene_name : "";
  for (uint32_t k = 0; k < s.tools._length; ++k) {
    const somasim_wire_ToolInfo& info = s.tools._buffer[k];
    if (info.id == nullptr) continue;
    ToolScene& tool = tools_[info.id];
    tool.kind = info.kind != nullptr ? info.kind : "";
    const bool sane = std::isfinite(info.shaft_length) && std::isfinite(info.shaft_radius) &&
                      info.shaft_length >= 0.0 && info.shaft_length < 10.0 &&
                      info.shaft_radius >= 0.0 && info.shaft_radius < 1.0;
    tool.shaft_length = sane ? info.shaft_length : 0.0;
    tool.shaft_radius = sane ? info.shaft_radius : 0.0;
    tool.jaw_length = std::isfinite(info.jaw_length) && info.jaw_length >= 0.0 &&
                              info.jaw_length <= tool.shaft_length
                          ? info.jaw_length
                          : 0.0;
  }
  // The grasp radii are in the scene's text only (the session description has no field).
  if (s.scene_text != nullptr) {
    scene::Scene scene;
    google::protobuf::TextFormat::Parser parser;
    QuietErrors quiet;
    parser.RecordErrorsTo(&quiet);
    if (parser.ParseFromString(s.scene_text, &scene)) {
      for (const scene::Tool& t : scene.tool()) {
        const auto it = tools_.find(t.id());
        const double r = t.grasper().grasp_radius();
        if (it != tools_.end() && t.has_grasper() && std::isfinite(r) && r > 0.0 && r <= 0.05) {
          it->second.grasp_radius = r;
        }
      }
    }
  }
  organ_ids_.clear();
  for (uint32_t k = 0; k < s.organs._length; ++k) {
    const char* id = s.organs._buffer[k].id;
    organ_ids_.emplace_back(id != nullptr ? id : "");
  }
}

void SceneReceiver::OnTopology(const somasim_wire_OrganTopology& t) {
  if (t.format_version != dds::kWireFormatVersion) {
    ++counters_.wrong_format_version;
    return;
  }
  const uint64_t n = t.num_nodes;
  const uint64_t triangles = t.triangles._length / 3;
  bool ok = t.organ != nullptr && n > 0 && n <= (1U << 24) && t.rest_positions._length == 3 * n &&
            t.triangles._length % 3 == 0 && t.inner_face._length == triangles;
  for (uint32_t k = 0; ok && k < t.triangles._length; ++k) ok = t.triangles._buffer[k] < n;
  for (uint32_t k = 0; ok && k < t.rest_positions._length; ++k) {
    ok = std::isfinite(t.rest_positions._buffer[k]);
  }
  if (!ok) {
    ++counters_.bad_topologies;
    return;
  }
  SeeServer(t.server_id);
  OrganScene& o = organs_[t.organ];
  if (o.decoder && o.topology_version == t.version && o.num_nodes == t.num_nodes) return;
  o.topology_version = t.version;
  o.num_nodes = t.num_nodes;
  o.rest.assign(t.rest_positions._buffer, t.rest_positions._buffer + t.rest_positions._length);
  o.triangles.assign(t.triangles._buffer, t.triangles._buffer + t.triangles._length);
  o.inner_face.assign(t.inner_face._buffer, t.inner_face._buffer + t.inner_face._length);
  o.decoder = std::make_unique<wire::FrameDecoder>(static_cast<int32_t>(t.num_nodes));
}

bool SceneReceiver::OnFrame(const somasim_wire_MeshFrame& f) {
  if (f.format_version != dds::kWireFormatVersion) {
    ++counters_.wrong_format_version;
    return false;
  }
  if (f.organ == nullptr || f.server_id != server_id_) {
    ++counters_.frames_waiting_for_topology;  // from a server whose topology is not here yet
    return false;
  }
  const auto it = organs_.find(f.organ);
  if (it == organs_.end() || !it->second.decoder ||
      it->second.topology_version != f.topology_version) {
    ++counters_.frames_waiting_for_topology;
    return false;
  }
  OrganScene& o = it->second;
  const wire::FrameDecoder::Result r = o.decoder->Apply(wire::ViewOf(f));
  if (r == wire::FrameDecoder::Result::kBad) ++counters_.bad_frames;
  if (r != wire::FrameDecoder::Result::kApplied) return false;
  o.sim_time = f.sim_time;
  o.sender_time_ns = f.sender_time_ns;
  ++o.frames_applied;
  return true;
}

bool SceneReceiver::Poll() {
  bool changed = false;
  session_->Take(
      [this](const somasim_wire_SessionInfo& s, const dds_sample_info_t&) { OnSession(s); });
  topology_->Take([this, &changed](const somasim_wire_OrganTopology& t, const dds_sample_info_t&) {
    OnTopology(t);
    changed = true;
  });
  frames_->Take([this, &changed](const somasim_wire_MeshFrame& f,
                                 const dds_sample_info_t&) { changed = OnFrame(f) || changed; },
                256);
  heartbeat_->Take([this](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
    if (h.format_version != dds::kWireFormatVersion) {
      ++counters_.wrong_format_version;
      return;
    }
    server_state_ = h.state;
    sim_time_ = std::isfinite(h.sim_time) ? h.sim_time : sim_time_;
    last_heartbeat_ = std::chrono::steady_clock::now();
  });
  metrics_reader_->Take([this](const somasim_wire_ServerMetrics& m, const dds_sample_info_t&) {
    if (m.format_version != dds::kWireFormatVersion) {
      ++counters_.wrong_format_version;
      return;
    }
    metrics_ = m;
    has_metrics_ = true;
  });
  events_->Take([this](const somasim_wire_SessionEvent& e, const dds_sample_info_t&) {
    if (e.format_version != dds::kWireFormatVersion || e.text == nullptr) {
      ++counters_.wrong_format_version;
      return;
    }
    messages_.emplace_back(e.text);
    if (messages_.size() > kMaxMessages) messages_.erase(messages_.begin());
  });
  tool_commands_->Take(
      [this](const somasim_wire_ToolCommand& c, const dds_sample_info_t&) {
        if (c.format_version != dds::kWireFormatVersion || c.tool == nullptr) {
          ++counters_.wrong_format_version;
          return;
        }
        const auto it = tools_.find(c.tool);
        if (it == tools_.end()) return;  // not a tool of this session
        bool finite = std::isfinite(c.jaw_closure);
        for (const double v : c.position) finite = finite && std::isfinite(v);
        for (const double v : c.orientation) finite = finite && std::isfinite(v);
        if (!finite) {
          ++counters_.bad_tool_samples;
          return;
        }
        ToolScene& t = it->second;
        const auto now = std::chrono::steady_clock::now();
        const std::string station = c.station != nullptr ? c.station : "";
        if (station != t.station || c.seq < t.rate_seq ||
            t.rate_start == std::chrono::steady_clock::time_point{}) {
          t.station = station;  // a new sender: start counting again
          t.rate_seq = c.seq;
          t.rate_start = now;
          t.command_rate_hz = 0.0;
        } else if (now - t.rate_start >= std::chrono::seconds(1)) {
          t.command_rate_hz = static_cast<double>(c.seq - t.rate_seq) /
                              std::chrono::duration<double>(now - t.rate_start).count();
          t.rate_seq = c.seq;
          t.rate_start = now;
        }
        std::copy(std::begin(c.position), std::end(c.position), t.position);
        std::copy(std::begin(c.orientation), std::end(c.orientation), t.orientation);
        t.jaw_closure = std::clamp(c.jaw_closure, 0.0, 1.0);
        t.has_pose = true;
        t.last_command = std::chrono::steady_clock::now();
      },
      256);
  force_models_->Take(
      [this](const somasim_wire_ForceModel& m, const dds_sample_info_t&) { OnForceModel(m); });
  rigid_reader_->Take(
      [this](const somasim_wire_RigidBodyState& b, const dds_sample_info_t&) { OnRigidBody(b); },
      256);
  return changed;
}

void SceneReceiver::OnForceModel(const somasim_wire_ForceModel& m) {
  if (m.format_version != dds::kWireFormatVersion || m.tool == nullptr) {
    ++counters_.wrong_format_version;
    return;
  }
  const auto it = tools_.find(m.tool);
  if (it == tools_.end() || m.server_id != server_id_) return;
  force_model::LocalForceModel model;
  if (!force_model::FromWire(m, dds::kWireFormatVersion, &model).empty()) {
    ++counters_.bad_tool_samples;  // non-finite, asymmetric, negative stiffness, ...
    return;
  }
  // The grasped nodes the server publishes, checked against the organ they name.
  const std::string organ = m.organ != nullptr ? m.organ : "";
  std::vector<uint32_t> held;
  if (model.grasping) {
    const auto o = organs_.find(organ);
    const uint32_t num_nodes = o != organs_.end() ? o->second.num_nodes : 0;
    if (!force_model::HeldNodesFromWire(m, num_nodes, &held).empty()) {
      ++counters_.bad_tool_samples;  // too many, or not the organ's
      return;
    }
  }
  ToolScene& t = it->second;
  t.has_model = true;
  t.model = model;
  t.organ = organ;
  t.in_contact = model.in_contact;
  t.grasping = model.grasping;
  for (int k = 0; k < 3; ++k) {
    t.contact_point[k] = model.contact_point[k];
    t.normal[k] = model.normal[k];
    t.grasp_anchor[k] = model.grasp_anchor[k];
  }
  t.held_nodes = std::move(held);
  t.held_organ = model.grasping ? organ : std::string();
}

void SceneReceiver::OnRigidBody(const somasim_wire_RigidBodyState& b) {
  if (b.format_version != dds::kWireFormatVersion || b.body == nullptr) {
    ++counters_.wrong_format_version;
    return;
  }
  if (b.server_id != server_id_) return;  // an old server's, or one not yet seen
  bool ok =
      std::isfinite(b.radius) && b.radius > 0.0 && b.radius <= 0.2 && std::isfinite(b.sim_time);
  for (const double v : b.position) ok = ok && std::isfinite(v) && std::abs(v) < 1e3;
  double q2 = 0.0;
  for (const double v : b.orientation) {
    ok = ok && std::isfinite(v);
    q2 += v * v;
  }
  ok = ok && q2 > 0.25 && q2 < 4.0;  // a unit quaternion, give or take rounding and sloppiness
  if (!ok) {
    ++counters_.bad_rigid_bodies;
    return;
  }
  RigidBodyScene& r = rigid_bodies_[b.body];
  r.radius = b.radius;
  std::copy(std::begin(b.position), std::end(b.position), r.position);
  std::copy(std::begin(b.orientation), std::end(b.orientation), r.orientation);
  r.grasped = b.grasped;
  r.sim_time = b.sim_time;
}

bool SceneReceiver::complete() const {
  if (!has_session_ || organ_ids_.empty()) return false;
  return std::all_of(organ_ids_.begin(), organ_ids_.end(), [this](const std::string& id) {
    const auto it = organs_.find(id);
    return it != organs_.end() && it->second.has_shape();
  });
}

bool SceneReceiver::server_gone(std::chrono::steady_clock::time_point now) const {
  return server_id_ == 0 || now - last_heartbeat_ > dds::kLease;
}

}  // namespace somasim::viewer
