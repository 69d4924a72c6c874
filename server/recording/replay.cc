#include "server/recording/replay.h"

#include <bit>
#include <cstdint>
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
      for (int i = 0; i < n; ++i) {
        // Bit for bit (a NaN never matches, -0 differs from +0).
        if (std::bit_cast<uint64_t>(replayed[i]) == std::bit_cast<uint64_t>(recorded[i])) continue;
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

RecordedInputs::RecordedInputs(const std::string& path)
    : path_(path),
      reader_(std::make_unique<recording::Reader>(path)),
      next_(std::make_unique<recording::Record>()) {
  const recording::RecordingHeader& h = reader_->header();
  result_.software_version = h.software_version();
  if (recording::TextHash(h.scene_text()) != h.scene_hash()) {
    throw recording::RecordingError(path + ": the scene does not match its hash", 12);
  }
}

RecordedInputs::~RecordedInputs() = default;

const recording::RecordingHeader& RecordedInputs::header() const { return reader_->header(); }

std::unique_ptr<Session> RecordedInputs::MakeSession() const {
  const recording::RecordingHeader& h = reader_->header();
  scene::SceneLines lines(path_ + " (recorded scene)");
  const scene::Scene scene = scene::ParseScene(h.scene_text(), path_ + " (recorded scene)", &lines);
  auto session =
      std::make_unique<Session>(scene, lines, h.scene_dir().empty() ? "." : h.scene_dir());
  if (session->dt() != h.dt()) {
    throw std::runtime_error(path_ + ": the recorded scene ticks at " + std::to_string(h.dt()) +
                             " s; rebuilt, it ticks at " + std::to_string(session->dt()) + " s");
  }
  return session;
}

void RecordedInputs::ApplyUpTo(uint64_t steps, Session* session) {
  while (!finished_) {
    if (!has_next_) {
      if (!reader_->Next(next_.get())) {
        finished_ = true;
        result_.truncated = reader_->truncated();
        result_.end_offset = reader_->end_offset();
        break;
      }
      has_next_ = true;
      ++result_.records;
      result_.end_offset = reader_->end_offset();
    }
    const recording::Record& r = *next_;
    if (r.step() > steps) break;
    has_next_ = false;
    last_step_ = r.step();
    switch (r.kind_case()) {
      case recording::Record::kToolCommand: {
        const recording::ToolCommand& c = r.tool_command();
        if (c.tool() < 0 || c.tool() >= session->num_tools() ||
            session->tool(c.tool()).id != c.tool_id() || c.tip_size() != 3 ||
            c.orientation_size() != 4) {
          throw std::runtime_error(path_ + ": the tool command of " + Where(r) +
                                   " does not fit the scene's tools");
        }
        ToolCommandInput input;
        input.pose.tip = Eigen::Vector3d(c.tip(0), c.tip(1), c.tip(2));
        input.pose.orientation = Eigen::Quaterniond(c.orientation(0), c.orientation(1),
                                                    c.orientation(2), c.orientation(3));
        input.pose.jaw_opening = c.jaw_opening();
        input.buttons = c.buttons();
        input.sequence = c.sequence();
        session->SetToolCommand(c.tool(), input);
        break;
      }
      case recording::Record::kEvent:
        if (r.event().kind() == static_cast<uint32_t>(SessionEventRecord::Kind::kReset)) {
          session->Reset();
        }
        break;
      case recording::Record::kCheckpoint:
        if (!result_.gap && !result_.diverged) {
          result_.divergence = Compare(r.checkpoint(), *session, r);
          if (result_.divergence.empty()) {
            ++result_.checkpoints_matched;
          } else {
            result_.diverged = true;
            finished_ = true;
          }
        }
        break;
      case recording::Record::kGap:
        if (!result_.gap) {
          result_.gap = true;
          result_.gap_step = r.step();
        }
        break;
      case recording::Record::kEnd:
        result_.ended_cleanly = true;
        finished_ = true;
        break;
      case recording::Record::kInstructor:
      case recording::Record::KIND_NOT_SET:
        break;
    }
  }
}

ReplayResult Replay(const std::string& path, const ReplayOptions& options) {
  RecordedInputs inputs(path);
  const std::unique_ptr<Session> session = inputs.MakeSession();
  uint64_t steps = 0;
  while (true) {
    inputs.ApplyUpTo(steps, session.get());
    (void)session->TakeEvents();
    if (inputs.finished()) break;
    session->Step();
    (void)session->TakeEvents();
    ++steps;
    if (options.on_step && !options.on_step(*session, steps)) break;
  }
  ReplayResult result = inputs.result();
  result.steps = steps;
  result.sim_time = session->time();
  return result;
}

}  // namespace somasim::server
