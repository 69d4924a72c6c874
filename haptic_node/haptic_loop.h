// One tick of the haptic node's 1 kHz loop (issue 9, SPEC §1, §7), pure, for every device: an
// arm through its shared memory (joint encoders in, torques out, the arm's kinematics between)
// or a Cartesian device — the mock script's emulated handle, which reports its pose in the
// scene. The caller reads the device and the newest local force model, passes them with the
// node's clock, and writes the command this returns. No I/O, no clock, no lock, no allocation
// (tested).
//
// Each tick:
//  1. The device: the arm block's header (the caller's check), the state read (torn reads: one
//     is a driver preempted mid-write, a tick without news; torn for `arm_timeout`, a fault),
//     the state's values and the device's heartbeat (still for `arm_timeout` while running,
//     over as many of the loop's own ticks: a node held up by its host does not blame the
//     device). Until the heartbeat is first seen moving the loop waits (motors disabled, no
//     fault); after that an unusable device latches a fault.
//  2. The pose: an arm's joints from encoders (homing offsets), forward kinematics with the
//     Jacobian, into the scene (the configuration's workspace mapping); a Cartesian device's
//     pose as it is. The hand's velocity: the handle's displacement per tick, low-passed
//     (`velocity_cutoff`).
//  3. The clutch (SOMASIM_ARM_BUTTON_CLUTCH): while held the tool stays where it was and no
//     model force is rendered, so the device can be repositioned; on release the tool follows
//     the device again from where it was left.
//  4. The force: the newest local force model (common/force_model) evaluated at the tool, into
//     the device's frame, then the one output stage (force_output.h: faults, emergency stop,
//     staleness on the node's clock, engagement, clamp, rate limit, passivity); for an arm
//     J^T F clamped per motor.
//  5. The command: heartbeat + 1 every tick; enable only while running without a fault or an
//     emergency stop.
// A fault clears only by an operator's act: the clutch pressed and released once the device
// has been usable for `rearm_after`; force then engages again as on start.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

#include "common/arm_shm/arm_shm.h"
#include "common/force_model/local_force_model.h"
#include "haptic_node/force_output.h"
#include "haptic_node/kinematics.h"

namespace somasim::haptic {

// A local force model with when the node received it: what the wire thread hands the loop
// through a slot (common/lockfree/latest_slot.h).
struct ReceivedForceModel {
  force_model::LocalForceModel model;
  int64_t received_ns = 0;  // the node's monotonic clock
};

// The tool's pose for the server: the loop's output, the wire thread's input (through a slot).
struct ToolPoseSample {
  int64_t time_ns = 0;                   // the tick's time on the node's monotonic clock
  uint32_t tool = 0;                     // which of the node's tools the device drives
  double position[3] = {};               // [m] scene
  double orientation[4] = {1, 0, 0, 0};  // w x y z, the tool frame (shaft +z) in the scene
  double jaw = 0.0;                      // 0 open .. 1 closed (the device's gripper)
  uint32_t buttons = 0;                  // SOMASIM_ARM_BUTTON_* as the device reports them
  uint32_t valid = 0;                    // 0 until the device's pose is known
};

// A Cartesian device's state: the handle's pose in the scene frame, as the mock script's
// emulated device (or a device SDK giving Cartesian poses) reports it.
struct CartesianState {
  uint64_t heartbeat = 0;                // + 1 per update of a live device
  double position[3] = {};               // [m] scene
  double orientation[4] = {1, 0, 0, 0};  // w x y z unit quaternion, shaft +z
  double gripper = 0.0;                  // 0 open .. 1 closed
  uint32_t buttons = 0;                  // SOMASIM_ARM_BUTTON_*
};

struct HapticLoopSettings {
  ForceOutputSettings output;      // max_force: the arm's (ArmKinematics::max_force)
  double arm_timeout = 0.010;      // [s] the device's heartbeat may be still this long
  double velocity_cutoff = 100.0;  // [Hz] low-pass of the hand's velocity
  double rearm_after = 0.5;        // [s] a usable device before the clutch may clear a fault
};

struct HapticLoopInput {
  int64_t now_ns = 0;  // the node's monotonic clock
  // An arm: the block's header problem (arm_shm::HeaderProblem, or nullptr), the state read.
  const char* header_problem = nullptr;
  arm_shm::ReadResult read = arm_shm::ReadResult::kNoData;
  somasim_arm_state_t state{};  // valid when read == kOk
  // A Cartesian device (a loop made without kinematics): its state, read == kOk.
  CartesianState cartesian;
  uint32_t tool = 0;                          // the tool the device drives now
  const ReceivedForceModel* model = nullptr;  // the newest model for that tool, nullptr: none yet
};

enum class LoopPhase { kWaitingForArm, kRunning };

struct HapticLoopCounters {
  uint64_t ticks = 0;
  uint64_t waiting_ticks = 0;  // before the device's heartbeat moved
  uint64_t torn_reads = 0;
  uint64_t bad_states = 0;  // a header, state or heartbeat problem
  uint64_t clutch_ticks = 0;
  uint64_t emergency_stop_ticks = 0;
  uint64_t fault_clears = 0;
  uint64_t torque_clamped_ticks = 0;
};

class HapticLoop {
 public:
  // An arm: `kinematics` outlives the loop. Throws std::invalid_argument for settings that are
  // not finite and positive (the output stage's, and the loop's own).
  HapticLoop(const ArmKinematics& kinematics, const HapticLoopSettings& settings);
  // A Cartesian device: poses in the scene frame, forces out in it, no joints.
  explicit HapticLoop(const HapticLoopSettings& settings);

  // One tick: the command to write to the device (a Cartesian device takes command.force).
  const somasim_arm_command_t& Tick(const HapticLoopInput& in);

  LoopPhase phase() const { return phase_; }
  bool fault() const { return output_.fault(); }
  // Why the fault latched (static; "" when none): the device's problem or the output stage's.
  const char* fault_reason() const;
  const ToolPoseSample& tool() const { return tool_; }
  bool clutched() const { return clutched_; }
  const Eigen::Vector3d& scene_force() const { return scene_force_; }  // [N] the model's
  const Eigen::Vector3d& arm_force() const { return arm_force_; }      // [N] rendered, device frame
  const Eigen::Vector3d& arm_velocity() const { return velocity_; }    // [m/s] filtered
  // This tick's model said the tool touches (and is below its plane) or grasps.
  bool in_contact() const { return in_contact_; }
  bool grasping() const { return grasping_; }
  const ForceOutput& output() const { return output_; }
  const HapticLoopCounters& counters() const { return counters_; }

 private:
  // The device's pose this tick: in the device's frame (its velocity) and in the scene.
  struct DevicePose {
    Eigen::Vector3d position = Eigen::Vector3d::Zero();  // [m] device frame
    Eigen::Vector3d scene_position = Eigen::Vector3d::Zero();
    Eigen::Matrix3d scene_rotation = Eigen::Matrix3d::Identity();
    uint32_t buttons = 0;
    double jaw = 0.0;
  };
  // 1. What is wrong with the device this tick (nullptr: nothing); whether its state is usable.
  const char* CheckDevice(const HapticLoopInput& in, bool* have_state);
  DevicePose Pose(const HapticLoopInput& in);
  // 2–3. The velocity, the clutch and the tool's pose from a usable state.
  void FollowDevice(const DevicePose& pose, double dt, int64_t now_ns);
  // 4. The model's force at the tool, into the device's frame (what the output stage gets);
  // sets in_contact_ and grasping_, which Tick has cleared.
  ForceInput ModelForce(const HapticLoopInput& in, bool estop, bool device_ok);

  const ArmKinematics* kinematics_ = nullptr;  // nullptr: a Cartesian device
  HapticLoopSettings s_;
  ForceOutput output_;
  LoopPhase phase_ = LoopPhase::kWaitingForArm;
  const char* device_problem_ = nullptr;  // what latched the fault, if the device did
  int64_t last_now_ns_ = 0;
  bool seen_heartbeat_ = false;
  uint64_t last_heartbeat_ = 0;
  int64_t heartbeat_changed_ns_ = 0;
  int64_t still_ticks_ = 0;        // our ticks since the device's heartbeat last moved
  int64_t torn_streak_ = 0;        // consecutive torn reads
  int64_t healthy_since_ns_ = -1;  // the device usable since (< 0: not now)
  bool have_pose_ = false;
  Eigen::Vector3d last_arm_position_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d velocity_ = Eigen::Vector3d::Zero();
  Jacobian jacobian_ = Jacobian::Zero();
  bool clutched_ = false;
  Eigen::Vector3d offset_position_ = Eigen::Vector3d::Zero();      // tool = device + offset
  Eigen::Matrix3d offset_rotation_ = Eigen::Matrix3d::Identity();  // tool R = offset R · dev R
  Eigen::Vector3d tool_position_ = Eigen::Vector3d::Zero();
  Eigen::Matrix3d tool_rotation_ = Eigen::Matrix3d::Identity();
  Eigen::Vector3d scene_force_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d arm_force_ = Eigen::Vector3d::Zero();
  bool in_contact_ = false;
  bool grasping_ = false;
  uint64_t heartbeat_ = 0;
  ToolPoseSample tool_;
  somasim_arm_command_t command_{};
  HapticLoopCounters counters_;
};

// Why a Cartesian device's state cannot be used (nullptr: it can): a position that is not
// finite or beyond 10 m, an orientation that is not a unit quaternion (1e-3), a gripper
// outside [0, 1].
const char* CartesianStateProblem(const CartesianState& state);

}  // namespace somasim::haptic
