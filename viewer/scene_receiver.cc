#include "viewer/scene_receiver.h"

#include <algorithm>
#include <cmath>
#include <iterator>

#include "common/wire/mesh_frame_view.h"

namespace somasim::viewer {

namespace {

constexpr size_t kMaxMessages = 8;  // scenario messages kept for the heads-up display

}  // namespace

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
}

SceneReceiver::~SceneReceiver() = default;

void SceneReceiver::SeeServer(uint64_t id) {
  if (id == server_id_) return;
  if (server_id_ != 0) ++counters_.server_restarts;
  // A new server (a restart): what the old one published no longer holds.
  server_id_ = id;
  organs_.clear();
  tools_.clear();
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
    has_heartbeat_ = true;
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
        std::copy(std::begin(c.position), std::end(c.position), t.position);
        std::copy(std::begin(c.orientation), std::end(c.orientation), t.orientation);
        t.jaw_closure = std::clamp(c.jaw_closure, 0.0, 1.0);
        t.has_pose = true;
        t.last_command = std::chrono::steady_clock::now();
      },
      256);
  force_models_->Take([this](const somasim_wire_ForceModel& m, const dds_sample_info_t&) {
    if (m.format_version != dds::kWireFormatVersion || m.tool == nullptr) {
      ++counters_.wrong_format_version;
      return;
    }
    const auto it = tools_.find(m.tool);
    if (it == tools_.end() || m.server_id != server_id_) return;
    bool finite = true;
    for (const double v : m.contact_point) finite = finite && std::isfinite(v);
    for (const double v : m.normal) finite = finite && std::isfinite(v);
    for (const double v : m.grasp_anchor) finite = finite && std::isfinite(v);
    if (!finite) {
      ++counters_.bad_tool_samples;
      return;
    }
    ToolScene& t = it->second;
    t.in_contact = m.in_contact;
    std::copy(std::begin(m.contact_point), std::end(m.contact_point), t.contact_point);
    std::copy(std::begin(m.normal), std::end(m.normal), t.normal);
    t.grasping = m.grasping;
    std::copy(std::begin(m.grasp_anchor), std::end(m.grasp_anchor), t.grasp_anchor);
  });
  return changed;
}

bool SceneReceiver::complete() const {
  if (!has_session_ || organ_ids_.empty()) return false;
  return std::all_of(organ_ids_.begin(), organ_ids_.end(), [this](const std::string& id) {
    const auto it = organs_.find(id);
    return it != organs_.end() && it->second.has_shape();
  });
}

bool SceneReceiver::server_gone(std::chrono::steady_clock::time_point now) const {
  return !has_heartbeat_ || now - last_heartbeat_ > dds::kLease;
}

}  // namespace somasim::viewer
