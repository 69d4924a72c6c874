#include "server/recording/replay.h"

#include <cstring>
#include <memory>
#include <stdexcept>

#include "common/recording/recording_file.h"
#include "common/scene/scene.h"

namespace somasim::server {
namespace {

std::string Where(const recording::Record& r) {
  return "step " + std::to_string(r.step()) + " (t = " + std::to_string(r.sim_time()) + " s)";
}

// The first difference between the checkpoint and the session, or "".
std::string Compare(const recording::Checkpoint& c, const Session& session,
                    const recording::Record& r) {
  if (c.organs_size() != session.num_organs()) {
    return "the checkpoint at " + Where(r) + " has " + std::to_string(c.organs_size()) +
           " organs; the scene has " + std::to_string(session.num_organs());
  }
  for (int32_t k = 0; k < session.num_organs(); ++k) {
    const recording::OrganState& o = c.organs(k);
    const SessionOrgan& s = session.organ(k);
    const auto n = static_cast<int>(s.state->positions.size());
    if (o.organ() != s.built.id || o.positions_size() != n || o.velocities_size() != n) {
      return "the checkpoint at " + Where(r) + " does not fit organ " + s.built.id;
    }
    for (int which = 0; which < 2; ++which) {
      const double* replayed = which == 0 ? s.state->positions.data() : s.state->velocities.data();
      const auto& recorded = which == 0 ? o.positions() : o.velocities();
      if (std::memcmp(replayed, recorded.data(), sizeof(double) * static_cast<size_t>(n)) == 0) {
        continue;
      }
      for (int i = 0; i < n; ++i) {
        if (std::memcmp(&replayed[i], &recorded[i], sizeof(double)) == 0) continue;
        return "first divergence at " + Where(r) + ": organ " + s.built.id + " node " +
               std::to_string(i / 3) + (which == 0 ? " position" : " velocity") + " " +
               "xyz"[i % 3] + " replayed " + std::to_string(replayed[i]) + ", recorded " +
               std::to_string(recorded[i]);
      }
    }
    if (o.topology_version() != s.topology_version || o.elements_cut() != s.elements_cut) {
      return "first divergence at " + Where(r) + ": organ " + s.built.id + " topology version " +
             std::to_string(s.topology_version) + " (recorded " +
             std::to_string(o.topology_version()) + ")";
    }
  }
  return "";
}

}  // namespace

ReplayResult Replay(const std::string& path, const ReplayOptions& options) {
  recording::Reader reader(path);
  const recording::RecordingHeader& h = reader.header();
  ReplayResult result;
  result.software_version = h.software_version();
  if (recording::TextHash(h.scene_text()) != h.scene_hash()) {
    throw recording::RecordingError(path + ": the scene does not match its hash", 12);
  }
  scene::SceneLines lines(path + " (recorded scene)");
  const scene::Scene scene = scene::ParseScene(h.scene_text(), path + " (recorded scene)", &lines);
  Session session(scene, lines, h.scene_dir().empty() ? "." : h.scene_dir());
  if (session.dt() != h.dt()) {
    throw std::runtime_error(path + ": the recorded scene ticks at " + std::to_string(h.dt()) +
                             " s; rebuilt, it ticks at " + std::to_string(session.dt()) + " s");
  }
  bool stopped = false;
  const auto step_to = [&](uint64_t step) {
    while (result.steps < step && !stopped) {
      session.Step();
      (void)session.TakeEvents();
      ++result.steps;
      if (options.on_step && !options.on_step(session, result.steps)) stopped = true;
    }
  };
  recording::Record r;
  while (!stopped && !result.diverged && reader.Next(&r)) {
    ++result.records;
    step_to(r.step());
    if (stopped) break;
    switch (r.kind_case()) {
      case recording::Record::kToolCommand: {
        const recording::ToolCommand& c = r.tool_command();
        if (c.tool() < 0 || c.tool() >= session.num_tools() ||
            session.tool(c.tool()).id != c.tool_id() || c.tip_size() != 3 ||
            c.orientation_size() != 4) {
          throw std::runtime_error(path + ": the tool command at byte " +
                                   std::to_string(reader.end_offset()) + " (" + Where(r) +
                                   ") does not fit the scene's tools");
        }
        ToolCommandInput input;
        input.pose.tip = Eigen::Vector3d(c.tip(0), c.tip(1), c.tip(2));
        input.pose.orientation = Eigen::Quaterniond(c.orientation(0), c.orientation(1),
                                                    c.orientation(2), c.orientation(3));
        input.pose.jaw_opening = c.jaw_opening();
        input.buttons = c.buttons();
        input.sequence = c.sequence();
        session.SetToolCommand(c.tool(), input);
        break;
      }
      case recording::Record::kEvent:
        if (r.event().kind() == static_cast<uint32_t>(SessionEventRecord::Kind::kReset)) {
          session.Reset();
          (void)session.TakeEvents();
        }
        break;
      case recording::Record::kCheckpoint:
        if (!result.gap) {
          result.divergence = Compare(r.checkpoint(), session, r);
          if (result.divergence.empty()) {
            ++result.checkpoints_matched;
          } else {
            result.diverged = true;
          }
        }
        break;
      case recording::Record::kGap:
        if (!result.gap) {
          result.gap = true;
          result.gap_step = r.step();
        }
        break;
      case recording::Record::kEnd:
        result.ended_cleanly = true;
        break;
      case recording::Record::kInstructor:
      case recording::Record::KIND_NOT_SET:
        break;
    }
  }
  result.truncated = reader.truncated();
  result.end_offset = reader.end_offset();
  result.sim_time = session.time();
  return result;
}

}  // namespace somasim::server
