// The server's physics thread (SPEC §1, §7): a Session ticked at its step, paced to the wall
// clock (or as fast as possible, or at a replay's speed), fed by lock-free hand-offs and
// handing its results on through them — it does no DDS, no logging on the tick path, and
// allocates nothing per tick (tested):
//  in:  tool commands through a single-producer ring (the intake thread, net/tool_link.h), or a
//       recording's inputs (replay); pause, resume and reset as atomic requests;
//  out: per tool, the tick's local force model with what the grasp holds, through a seqlock
//       slot and an eventfd that wakes the force-model writer (net/tool_link.h); per organ, its
//       positions and (after a cut or a reset) its topology, and the rigid bodies' poses,
//       through triple buffers for the publisher (net/publisher.h); the session's events
//       through a ring; counters and step-time percentiles as atomics.
// The recorder (server/recording) hears every applied command, event and checkpoint from here.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <vector>

#include "common/force_model/local_force_model.h"
#include "common/lockfree/latest_slot.h"
#include "common/lockfree/spsc_ring.h"
#include "common/lockfree/triple_buffer.h"
#include "server/recording/recorder.h"
#include "server/recording/replay.h"
#include "server/runner/step_time_histogram.h"
#include "server/session/session.h"

namespace somasim::runner {

using server::RecordedInputs;
using server::Recorder;
using server::Session;
using server::SessionEventRecord;
using server::ToolCommandInput;

struct RunnerOptions {
  double duration = 0.0;     // [s] of session time; 0 = until stopped
  bool realtime = true;      // pace session time to the wall clock
  double speed = 1.0;        // replay: session time per wall-clock time
  double replay_from = 0.0;  // replay: fast-forward (unpaced, unpublished) to this time [s]
  int rt_priority = 0;       // SCHED_FIFO priority of the physics thread; 0 = normal
};

// A checked tool command for the physics (the intake thread's product).
struct ToolCommandMsg {
  int32_t tool = -1;  // index into the session's tools
  ToolCommandInput input;
};

inline constexpr int32_t kMaxHeld = 64;  // grasped nodes handed on per tool (the wire's cap)

// One tool's output of a tick: plain data for a seqlock slot.
struct ToolOutput {
  force_model::LocalForceModel model;
  uint64_t command_seq = 0;  // the newest tool command the step used
  int32_t organ = -1;        // the organ the model comes from (-1: none)
  int32_t num_held = 0;      // grasped nodes of that organ
  int32_t held[kMaxHeld] = {};
};

// An organ's positions at a tick [m], 3 × num_nodes.
struct PositionsSnapshot {
  std::vector<double> positions;
  double sim_time = 0.0;  // [s]
};

// An organ's topology after a cut or a reset: which tetrahedra are alive (cut organs; empty
// otherwise), the rest positions [m] (3 × num_nodes), and its version.
struct TopologySnapshot {
  uint32_t version = 0;
  std::vector<uint8_t> alive;
  std::vector<double> rest;
};

struct RigidPose {
  double position[3] = {};               // [m] the centre
  double orientation[4] = {1, 0, 0, 0};  // w x y z
  bool grasped = false;
};
struct RigidSnapshot {
  std::vector<RigidPose> bodies;  // the session's rigid bodies in order
  double sim_time = 0.0;
};

// Per tool, what the server saw of the force (for the report): the force model evaluated at
// the commanded tip each tick. Written by the physics thread only; read after Run returns.
struct ToolStats {
  double contact_time = 0.0;  // [s] in contact or grasping
  double max_force = 0.0;     // [N]
  double force_sum = 0.0;     // [N s] over contact time
};

// What the physics thread counts, for the metrics and the heartbeat (other threads read).
struct RunnerCounters {
  std::atomic<uint64_t> steps{0};           // organ steps
  std::atomic<uint64_t> rejected_steps{0};  // organ steps a model rejected
  std::atomic<uint64_t> ticks{0};           // Session::Step calls (the recording's step count)
  std::atomic<uint64_t> behind{0};          // times the physics fell > 0.5 s behind real time
  std::atomic<uint64_t> commands_applied{0};
  std::atomic<uint64_t> events_dropped{0};   // the event ring was full
  std::atomic<bool> replay_diverged{false};  // replay: the recording's inputs diverged
  std::atomic<bool> fast_forwarded{false};   // replay: --from reached, publishing from here
  std::atomic<double> sim_time{0.0};
  std::atomic<double> p50{0.0};  // [µs] step time over the last second
  std::atomic<double> p99{0.0};
  std::atomic<double> pmax{0.0};
  std::atomic<double> rate{0.0};  // [Hz] ticks over the last second
};

class PhysicsRunner {
 public:
  // Sizes every hand-off for `session` (which, like `recorder` and `replay`, outlives the
  // runner). `replay`: the recording's inputs drive the session instead of commands.
  PhysicsRunner(Session& session, const RunnerOptions& options, Recorder* recorder,
                RecordedInputs* replay = nullptr);
  ~PhysicsRunner();
  PhysicsRunner(const PhysicsRunner&) = delete;
  PhysicsRunner& operator=(const PhysicsRunner&) = delete;

  // The physics loop on the calling thread, until the duration, the replay's end, Stop() or a
  // stop signal. Sets the thread's scheduling (rt_priority) first.
  void Run();
  // One tick (commands in, Session::Step, outputs out), unpaced: for tests and Run.
  void Tick();
  void Stop() { stop_.store(true); }

  // In, from other threads.
  bool PushCommand(const ToolCommandMsg& command) { return commands_.Push(command); }
  void SetPaused(bool paused) { paused_.store(paused); }
  bool paused() const { return paused_.load(); }
  void RequestReset() { reset_.store(true); }

  // Out.
  lockfree::LatestSlot<ToolOutput>& tool_output(int32_t tool) {
    return *tool_outputs_[static_cast<size_t>(tool)];
  }
  int tool_wake_fd() const { return wake_fd_; }  // readable after each tick's tool outputs
  lockfree::TripleBuffer<PositionsSnapshot>& positions(int32_t organ) {
    return *positions_[static_cast<size_t>(organ)];
  }
  lockfree::TripleBuffer<TopologySnapshot>& topology(int32_t organ) {
    return *topologies_[static_cast<size_t>(organ)];
  }
  lockfree::TripleBuffer<RigidSnapshot>& rigid() { return *rigid_; }
  lockfree::SpscRing<SessionEventRecord, 1024>& events() { return events_; }
  const RunnerCounters& counters() const { return counters_; }
  // After Run: the step-time histogram over the whole run, its sum, the wall time.
  const StepTimeHistogram& total() const { return total_; }
  double total_sum_us() const { return total_sum_us_; }
  double wall_time() const { return wall_time_; }
  const std::vector<ToolStats>& tool_stats() const { return tool_stats_; }
  const Session& session() const { return session_; }

 private:
  void TakeCommands();
  bool ApplyReplay();   // whether a recorded reset came
  void StepOnce();      // Session::Step with its timing, and every output of the tick
  bool HandOnEvents();  // the session's events on (and recorded); whether a reset came
  void HandOnTools();
  void HandOnPositions();
  void HandOnTopologies();
  void HandOnRigidBodies();

  Session& session_;
  RunnerOptions options_;
  Recorder* recorder_ = nullptr;
  RecordedInputs* replay_ = nullptr;
  uint64_t checkpoint_interval_ = 1;
  std::atomic<bool> stop_{false};
  std::atomic<bool> paused_{false};
  std::atomic<bool> reset_{false};
  lockfree::SpscRing<ToolCommandMsg, 256> commands_;
  lockfree::SpscRing<SessionEventRecord, 1024> events_;
  std::vector<std::unique_ptr<lockfree::LatestSlot<ToolOutput>>> tool_outputs_;
  std::vector<uint64_t> last_command_;  // per tool: the newest command's sequence
  std::vector<ToolStats> tool_stats_;
  ToolOutput scratch_;
  int wake_fd_ = -1;
  std::vector<std::unique_ptr<lockfree::TripleBuffer<PositionsSnapshot>>> positions_;
  std::vector<std::unique_ptr<lockfree::TripleBuffer<TopologySnapshot>>> topologies_;
  std::vector<uint32_t> handed_version_;  // per organ: the last topology version handed on
  std::unique_ptr<lockfree::TripleBuffer<RigidSnapshot>> rigid_;
  bool fast_forward_ = false;  // a replay from --from on its way there: nothing is published
  RunnerCounters counters_;
  StepTimeHistogram window_;
  StepTimeHistogram total_;
  double total_sum_us_ = 0.0;
  double wall_time_ = 0.0;
};

}  // namespace somasim::runner
