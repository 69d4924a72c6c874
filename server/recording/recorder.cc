#include "server/recording/recorder.h"

#include <google/protobuf/text_format.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <stdexcept>

namespace somasim::server {
namespace {

using Clock = std::chrono::steady_clock;

void ToRecord(const ToolCommandInput& c, int32_t tool, const std::string& tool_id,
              recording::ToolCommand* out) {
  out->set_tool(tool);
  out->set_tool_id(tool_id);
  out->clear_tip();
  out->clear_orientation();
  for (int i = 0; i < 3; ++i) out->add_tip(c.pose.tip[i]);
  out->add_orientation(c.pose.orientation.w());
  out->add_orientation(c.pose.orientation.x());
  out->add_orientation(c.pose.orientation.y());
  out->add_orientation(c.pose.orientation.z());
  out->set_jaw_opening(c.pose.jaw_opening);
  out->set_buttons(c.buttons);
  out->set_sequence(c.sequence);
}

}  // namespace

uint64_t Recorder::CheckpointInterval(double dt) {
  return std::max<uint64_t>(1, static_cast<uint64_t>(std::llround(1.0 / dt)));
}

recording::RecordingHeader Recorder::MakeHeader(const Session& session,
                                                const std::string& scene_dir,
                                                const std::string& session_name,
                                                const std::string& trainee,
                                                const std::string& software_version) {
  recording::RecordingHeader h;
  std::string text;
  google::protobuf::TextFormat::PrintToString(session.scene(), &text);
  h.set_software_version(software_version);
  h.set_scene_text(text);
  h.set_scene_hash(recording::TextHash(text));
  std::error_code ec;
  const std::filesystem::path dir = std::filesystem::absolute(scene_dir, ec);
  h.set_scene_dir(ec ? scene_dir : dir.lexically_normal().string());
  h.set_session(session_name);
  h.set_trainee(trainee);
  h.set_dt(session.dt());
  h.set_checkpoint_interval(CheckpointInterval(session.dt()));
  h.set_started_unix_ns(std::chrono::duration_cast<std::chrono::nanoseconds>(
                            std::chrono::system_clock::now().time_since_epoch())
                            .count());
  return h;
}

Recorder::Recorder(std::unique_ptr<recording::Sink> sink, const recording::RecordingHeader& header,
                   const Session& session, size_t queue)
    : writer_(std::move(sink)) {
  if (!writer_.WriteHeader(header) || !writer_.Sync()) {
    throw std::runtime_error("cannot start the recording: " + writer_.error());
  }
  size_t size = 0;
  for (int32_t k = 0; k < session.num_organs(); ++k) {
    organ_ids_.push_back(session.organ(k).built.id);
    organ_offsets_.push_back(size);
    size += 6 * static_cast<size_t>(session.organ(k).state->positions.cols());
  }
  organ_offsets_.push_back(size);
  for (auto& b : checkpoint_) b.assign(size + 2 * organ_ids_.size(), 0.0);
  for (int32_t t = 0; t < session.num_tools(); ++t) tool_ids_.push_back(session.tool(t).id);
  ring_.resize(std::max<size_t>(queue, 2));
  {
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.bytes = writer_.bytes_written();
  }
  thread_ = std::thread([this] { WriterLoop(); });
}

Recorder::~Recorder() { Finish(0, "the server stopped"); }

bool Recorder::Push(const Item& item) {
  const uint64_t head = head_.load(std::memory_order_relaxed);
  if (head - tail_.load(std::memory_order_acquire) >= ring_.size()) return false;
  ring_[head % ring_.size()] = item;
  head_.store(head + 1, std::memory_order_release);
  return true;
}

void Recorder::ToolCommand(uint64_t step, double time, int32_t tool,
                           const ToolCommandInput& command) {
  Item item;
  item.type = Item::Type::kToolCommand;
  item.step = step;
  item.time = time;
  item.tool = tool;
  item.command = command;
  if (!Push(item)) lost_commands_.fetch_add(1);
}

void Recorder::Event(uint64_t step, double time, const SessionEventRecord& event) {
  Item item;
  item.type = Item::Type::kEvent;
  item.step = step;
  item.time = time;
  item.event = event;
  if (!Push(item)) lost_events_.fetch_add(1);
}

void Recorder::Checkpoint(uint64_t step, double time, const Session& session) {
  int free = -1;
  for (int b = 0; b < kCheckpointBuffers && free < 0; ++b) {
    if (checkpoint_state_[b].load(std::memory_order_acquire) == 0) free = b;
  }
  if (free < 0 || head_.load() - tail_.load() >= ring_.size()) {
    lost_checkpoints_.fetch_add(1);
    return;
  }
  std::vector<double>& out = checkpoint_[free];
  const size_t organs = organ_ids_.size();
  for (size_t k = 0; k < organs; ++k) {
    const SessionOrgan& o = session.organ(static_cast<int32_t>(k));
    const auto n = static_cast<size_t>(o.state->positions.size());
    std::copy_n(o.state->positions.data(), n,
                out.begin() + static_cast<std::ptrdiff_t>(organ_offsets_[k]));
    std::copy_n(o.state->velocities.data(), n,
                out.begin() + static_cast<std::ptrdiff_t>(organ_offsets_[k] + n));
    out[organ_offsets_[organs] + 2 * k] = static_cast<double>(o.topology_version);
    out[organ_offsets_[organs] + 2 * k + 1] = static_cast<double>(o.elements_cut);
  }
  checkpoint_state_[free].store(1, std::memory_order_release);
  Item item;
  item.type = Item::Type::kCheckpoint;
  item.step = step;
  item.time = time;
  item.buffer = free;
  if (!Push(item)) {  // cannot happen: room was checked, and only this thread pushes
    checkpoint_state_[free].store(0);
    lost_checkpoints_.fetch_add(1);
  }
}

void Recorder::Instructor(uint64_t step, double time, uint32_t kind, const std::string& instructor,
                          const std::string& text) {
  recording::Record r;
  r.set_step(step);
  r.set_sim_time(time);
  r.mutable_instructor()->set_kind(kind);
  r.mutable_instructor()->set_instructor(instructor);
  r.mutable_instructor()->set_text(text);
  std::lock_guard<std::mutex> lock(instructor_mutex_);
  instructor_.push_back(std::move(r));
}

void Recorder::Write(const recording::Record& record) {
  if (failed_.load()) return;  // a failed recording writes nothing more
  if (!writer_.WriteRecord(record)) {
    failed_ = true;
    std::lock_guard<std::mutex> lock(stats_mutex_);
    stats_.failed = true;
    stats_.error = writer_.error();
    return;
  }
  std::lock_guard<std::mutex> lock(stats_mutex_);
  stats_.records = writer_.records_written();
  stats_.bytes = writer_.bytes_written();
}

void Recorder::WriteGapIfAny(uint64_t step, double time) {
  const uint64_t commands = lost_commands_.load(), events = lost_events_.load(),
                 checkpoints = lost_checkpoints_.load();
  if (commands == gap_commands_ && events == gap_events_ && checkpoints == gap_checkpoints_) {
    return;
  }
  recording::Record& r = scratch_;
  r.Clear();
  r.set_step(step);
  r.set_sim_time(time);
  recording::Gap* gap = r.mutable_gap();
  gap->set_tool_commands(commands - gap_commands_);
  gap->set_events(events - gap_events_);
  gap->set_checkpoints(checkpoints - gap_checkpoints_);
  const uint64_t lost =
      (commands - gap_commands_) + (events - gap_events_) + (checkpoints - gap_checkpoints_);
  gap_commands_ = commands;
  gap_events_ = events;
  gap_checkpoints_ = checkpoints;
  Write(r);
  std::lock_guard<std::mutex> lock(stats_mutex_);
  ++stats_.gaps;
  stats_.lost += lost;
}

bool Recorder::Drain() {
  bool any = false;
  const uint64_t head = head_.load(std::memory_order_acquire);
  uint64_t tail = tail_.load(std::memory_order_relaxed);
  for (; tail < head; ++tail) {
    const Item& item = ring_[tail % ring_.size()];
    WriteGapIfAny(item.step, item.time);  // what was lost came before this item
    recording::Record& r = scratch_;
    r.Clear();
    r.set_step(item.step);
    r.set_sim_time(item.time);
    switch (item.type) {
      case Item::Type::kToolCommand:
        ToRecord(item.command, item.tool,
                 item.tool >= 0 && static_cast<size_t>(item.tool) < tool_ids_.size()
                     ? tool_ids_[static_cast<size_t>(item.tool)]
                     : std::string(),
                 r.mutable_tool_command());
        break;
      case Item::Type::kEvent: {
        recording::Event* e = r.mutable_event();
        e->set_kind(static_cast<uint32_t>(item.event.kind));
        e->set_organ(item.event.organ);
        e->set_tool(item.event.tool);
        e->set_detail(item.event.detail);
        break;
      }
      case Item::Type::kCheckpoint: {
        const std::vector<double>& b = checkpoint_[item.buffer];
        const size_t organs = organ_ids_.size();
        recording::Checkpoint* c = r.mutable_checkpoint();
        for (size_t k = 0; k < organs; ++k) {
          recording::OrganState* o = c->add_organs();
          o->set_organ(organ_ids_[k]);
          const size_t n = (organ_offsets_[k + 1] - organ_offsets_[k]) / 2;
          const double* p = b.data() + organ_offsets_[k];
          o->mutable_positions()->Assign(p, p + n);
          o->mutable_velocities()->Assign(p + n, p + 2 * n);
          o->set_topology_version(static_cast<uint32_t>(b[organ_offsets_[organs] + 2 * k]));
          o->set_elements_cut(static_cast<int64_t>(b[organ_offsets_[organs] + 2 * k + 1]));
        }
        checkpoint_state_[item.buffer].store(0, std::memory_order_release);
        break;
      }
    }
    tail_.store(tail + 1, std::memory_order_release);
    Write(r);
    any = true;
  }
  std::deque<recording::Record> instructor;
  {
    std::lock_guard<std::mutex> lock(instructor_mutex_);
    instructor.swap(instructor_);
  }
  for (const recording::Record& r : instructor) {
    Write(r);
    any = true;
  }
  return any;
}

void Recorder::WriterLoop() {
  Clock::time_point last_sync = Clock::now();
  while (!stop_.load()) {
    const bool wrote = Drain();
    if (Clock::now() - last_sync >= std::chrono::milliseconds(500)) {
      if (!failed_.load() && !writer_.Sync()) {
        failed_ = true;
        std::lock_guard<std::mutex> lock(stats_mutex_);
        stats_.failed = true;
        stats_.error = writer_.error();
      }
      last_sync = Clock::now();
    }
    if (!wrote) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  Drain();
}

void Recorder::Finish(uint64_t steps, const std::string& reason) {
  std::lock_guard<std::mutex> lock(finish_mutex_);
  if (finished_) return;
  finished_ = true;
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  WriteGapIfAny(steps, 0.0);
  recording::Record r;
  r.set_step(steps);
  r.mutable_end()->set_steps(steps);
  r.mutable_end()->set_reason(reason);
  Write(r);
  if (!failed_.load() && !writer_.Sync()) {
    failed_ = true;
    std::lock_guard<std::mutex> stats_lock(stats_mutex_);
    stats_.failed = true;
    stats_.error = writer_.error();
  }
}

RecorderStats Recorder::stats() const {
  std::lock_guard<std::mutex> lock(stats_mutex_);
  return stats_;
}

}  // namespace somasim::server
