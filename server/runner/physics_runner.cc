#include "server/runner/physics_runner.h"

#include <sys/eventfd.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <stdexcept>
#include <string>
#include <thread>

#include "common/app/log.h"
#include "common/app/realtime.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"

namespace somasim::runner {
namespace {

using Clock = std::chrono::steady_clock;
using app::Log;
using app::LogLevel;

double Seconds(Clock::duration d) { return std::chrono::duration<double>(d).count(); }
Clock::duration FromSeconds(double s) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
}

// Start-up only: the physics thread's scheduling, said in the log.
void SetUpThread(int rt_priority) {
  app::LogSchedulerSlice(app::SetSchedulerSlice(std::chrono::microseconds(0)), "physics thread");
  if (rt_priority <= 0) return;
  const app::RealtimeResult r = app::SetFifoScheduling(rt_priority);
  if (r.applied) {
    Log(LogLevel::kInfo, "realtime", {{"policy", "SCHED_FIFO"}, {"priority", rt_priority}});
  } else {
    Log(LogLevel::kWarning, "realtime_refused",
        {{"detail", r.detail + "; the physics thread runs at normal priority"}});
  }
}

}  // namespace

PhysicsRunner::PhysicsRunner(Session& session, const RunnerOptions& options, Recorder* recorder,
                             RecordedInputs* replay)
    : session_(session),
      options_(options),
      recorder_(recorder),
      replay_(replay),
      checkpoint_interval_(Recorder::CheckpointInterval(session.dt())) {
  const auto tools = static_cast<size_t>(session.num_tools());
  for (size_t t = 0; t < tools; ++t) {
    tool_outputs_.push_back(std::make_unique<lockfree::LatestSlot<ToolOutput>>());
  }
  last_command_.assign(tools, 0);
  tool_stats_.resize(tools);
  wake_fd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake_fd_ < 0) throw std::runtime_error(std::string("eventfd: ") + std::strerror(errno));
  for (int32_t k = 0; k < session.num_organs(); ++k) {
    const server::SessionOrgan& o = session.organ(k);
    const auto& x = o.state->positions;
    PositionsSnapshot p;
    p.positions.assign(x.data(), x.data() + x.size());
    positions_.push_back(std::make_unique<lockfree::TripleBuffer<PositionsSnapshot>>(p));
    TopologySnapshot t;
    t.version = o.topology_version;
    t.alive.assign(o.cutter ? static_cast<size_t>(o.cutter->num_tets()) : 0, 1);
    t.rest.assign(o.built.rest().data(), o.built.rest().data() + o.built.rest().size());
    topologies_.push_back(std::make_unique<lockfree::TripleBuffer<TopologySnapshot>>(t));
    handed_version_.push_back(o.topology_version);
  }
  RigidSnapshot r;
  r.bodies.resize(static_cast<size_t>(session.num_rigid()));
  rigid_ = std::make_unique<lockfree::TripleBuffer<RigidSnapshot>>(r);
  HandOnRigidBodies();
}

PhysicsRunner::~PhysicsRunner() {
  if (wake_fd_ >= 0) close(wake_fd_);
}

void PhysicsRunner::Run() {
  SetUpThread(options_.rt_priority);
  const Clock::time_point start = Clock::now();
  Clock::time_point paced_start = start;
  Clock::time_point window_start = start;
  fast_forward_ = replay_ != nullptr && options_.replay_from > 0.0;
  while (!app::StopRequested() && !stop_.load()) {
    if (replay_ != nullptr) {
      if (ApplyReplay()) paced_start = Clock::now();  // a recorded reset: time starts at 0
      if (replay_->finished()) break;
    } else {
      TakeCommands();
    }
    if (reset_.exchange(false)) {
      session_.Reset();  // an instructor's act: it may allocate
      paced_start = Clock::now();
      HandOnEvents();
    }
    if (paused_.load()) {
      const Clock::time_point before = Clock::now();
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      paced_start += Clock::now() - before;  // the pause does not count as lag
      continue;
    }
    StepOnce();
    const Clock::time_point now = Clock::now();
    if (fast_forward_ && session_.time() >= options_.replay_from - 1e-9) {
      // A replay from --from: the fast-forward is over; publish and pace from here.
      fast_forward_ = false;
      HandOnPositions();
      HandOnRigidBodies();
      paced_start = now - FromSeconds(session_.time() / options_.speed);
      counters_.fast_forwarded.store(true);
    }
    if (now - window_start >= std::chrono::seconds(1)) {
      counters_.p50 = window_.Quantile(0.5);
      counters_.p99 = window_.Quantile(0.99);
      counters_.pmax = window_.max();
      counters_.rate = static_cast<double>(window_.count()) / Seconds(now - window_start);
      window_.Clear();
      window_start = now;
    }
    if (options_.duration > 0.0 && session_.time() >= options_.duration - 1e-9) break;
    if (options_.realtime && !fast_forward_) {
      const Clock::time_point target = paced_start + FromSeconds(session_.time() / options_.speed);
      if (now < target) {
        std::this_thread::sleep_until(target);
      } else if (now - target > std::chrono::milliseconds(500)) {
        // Slower than real time: counted (the publisher says so), and the lost time is not
        // caught up.
        counters_.behind.fetch_add(1);
        paced_start += now - target;
      }
    }
  }
  wall_time_ = Seconds(Clock::now() - start);
}

void PhysicsRunner::Tick() {
  TakeCommands();
  StepOnce();
}

void PhysicsRunner::StepOnce() {
  const Clock::time_point t0 = Clock::now();
  session_.Step();
  const Clock::time_point t1 = Clock::now();
  const double us = std::chrono::duration<double, std::micro>(t1 - t0).count();
  window_.Add(us);
  total_.Add(us);
  total_sum_us_ += us;
  counters_.ticks.fetch_add(1);
  counters_.steps = session_.organ_steps();
  counters_.rejected_steps = session_.rejected_steps();
  counters_.sim_time = session_.time();
  HandOnTools();
  HandOnEvents();
  const uint64_t ticks = counters_.ticks.load();
  if (recorder_ != nullptr && ticks % checkpoint_interval_ == 0) {
    recorder_->Checkpoint(ticks, session_.time(), session_);
  }
  if (!fast_forward_) {
    HandOnPositions();
    HandOnRigidBodies();
  }
  HandOnTopologies();
}

void PhysicsRunner::TakeCommands() {
  ToolCommandMsg c;
  while (commands_.Pop(&c)) {
    session_.SetToolCommand(c.tool, c.input);
    if (recorder_ != nullptr) {
      recorder_->ToolCommand(counters_.ticks.load(), session_.time(), c.tool, c.input);
    }
    last_command_[static_cast<size_t>(c.tool)] = c.input.sequence;
    counters_.commands_applied.fetch_add(1);
  }
}

bool PhysicsRunner::ApplyReplay() {
  replay_->ApplyUpTo(counters_.ticks.load(), &session_);
  const bool reset = HandOnEvents();
  if (replay_->result().diverged) counters_.replay_diverged.store(true);
  return reset;
}

bool PhysicsRunner::HandOnEvents() {
  bool reset = false;
  for (const SessionEventRecord& e : session_.TakeEvents()) {
    if (!events_.Push(e)) counters_.events_dropped.fetch_add(1);
    if (recorder_ != nullptr) recorder_->Event(counters_.ticks.load(), session_.time(), e);
    reset |= e.kind == SessionEventRecord::Kind::kReset;
  }
  return reset;
}

// Each commanded tool's force model (with what its grasp holds) into its slot, and what the
// server saw of the force at the commanded tip for the report; then the writer is woken.
void PhysicsRunner::HandOnTools() {
  const double dt = session_.dt();
  bool any = false;
  for (int32_t t = 0; t < session_.num_tools(); ++t) {
    const server::SessionTool& tool = session_.tool(t);
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
    scratch_.model = m;
    scratch_.command_seq = last_command_[static_cast<size_t>(t)];
    scratch_.organ = tool.force_organ;
    scratch_.num_held = session_.HeldNodes(t, {scratch_.held, static_cast<size_t>(kMaxHeld)});
    tool_outputs_[static_cast<size_t>(t)]->Write(scratch_);
    any = true;
  }
  if (any) {
    const uint64_t one = 1;
    [[maybe_unused]] const ssize_t w = write(wake_fd_, &one, sizeof one);
  }
}

void PhysicsRunner::HandOnPositions() {
  for (int32_t k = 0; k < session_.num_organs(); ++k) {
    lockfree::TripleBuffer<PositionsSnapshot>& buffer = *positions_[static_cast<size_t>(k)];
    const auto& x = session_.organ(k).state->positions;
    PositionsSnapshot& out = buffer.back();
    std::copy_n(x.data(), std::min(out.positions.size(), static_cast<size_t>(x.size())),
                out.positions.begin());
    out.sim_time = session_.time();
    buffer.Publish();
  }
}

// Each organ whose topology version changed (a cut, a reset): its alive flags and rest
// positions, for the publisher to extract and republish the surface.
void PhysicsRunner::HandOnTopologies() {
  for (int32_t k = 0; k < session_.num_organs(); ++k) {
    const auto i = static_cast<size_t>(k);
    const server::SessionOrgan& o = session_.organ(k);
    if (o.topology_version == handed_version_[i]) continue;
    handed_version_[i] = o.topology_version;
    TopologySnapshot& out = topologies_[i]->back();
    out.version = o.topology_version;
    if (o.cutter) {
      const std::vector<uint8_t>& alive = o.cutter->alive_flags();
      std::copy_n(alive.begin(), std::min(alive.size(), out.alive.size()), out.alive.begin());
    }
    const mesh::Points& rest =
        o.built.fem != nullptr ? o.built.fem->RestPositions(*o.state) : o.built.rest();
    std::copy_n(rest.data(), std::min(out.rest.size(), static_cast<size_t>(rest.size())),
                out.rest.begin());
    topologies_[i]->Publish();
  }
}

void PhysicsRunner::HandOnRigidBodies() {
  RigidSnapshot& out = rigid_->back();
  for (int32_t k = 0; k < session_.num_rigid(); ++k) {
    const contact::RigidSphere& body = *session_.rigid(k).sphere;
    RigidPose& p = out.bodies[static_cast<size_t>(k)];
    for (int i = 0; i < 3; ++i) p.position[i] = body.position()[i];
    p.orientation[0] = body.orientation().w();
    p.orientation[1] = body.orientation().x();
    p.orientation[2] = body.orientation().y();
    p.orientation[3] = body.orientation().z();
    p.grasped = body.grasped();
  }
  out.sim_time = session_.time();
  rigid_->Publish();
}

}  // namespace somasim::runner
