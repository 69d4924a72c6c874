// One tick of the haptic node's 1 kHz loop with an arm (issue 9, SPEC §1, §7), pure: the caller
// reads the arm's state from shared memory and the newest local force model from its slot,
// passes them with the node's clock, and writes the command this returns. No I/O, no clock, no
// lock, no allocation (tested).
//
// Each tick:
//  1. The device: the block's header (the caller's check), the state read (torn reads: one is
//     a driver preempted mid-write, a tick without news; torn for `arm_timeout`, a fault), the
//     state's values (arm_shm StateProblem) and the driver's heartbeat (still for `arm_timeout`
//     while running, over as many of the loop's own ticks: a node held up by its host does not
//     blame the arm). Until the driver's heartbeat is first seen moving the loop waits for the
//     arm (motors disabled, no fault); after that an unusable device latches a fault.
//  2. The pose: joints from encoders (homing offsets), forward kinematics with the Jacobian,
//     into the scene (the configuration's workspace mapping). The hand's velocity: the handle's
//     displacement per tick, low-passed (`velocity_cutoff`).
//  3. The clutch (SOMASIM_ARM_BUTTON_CLUTCH): while held the tool stays where it was and no force
//     is rendered, so the arm can be repositioned; on release the tool follows the arm again from
//     where it was left (the offset between arm and tool changes, position and orientation).
//  4. The force: the newest local force model evaluated at the tool (server/contact: the
//     god-object proxy's virtual coupling, the grasp spring, damping), into the arm's frame, then
//     the one output stage (force_output.h: faults, emergency stop, staleness on the node's clock,
//     engagement, clamp, rate limit, passivity), then J^T F clamped per motor.
//  5. The command: heartbeat + 1 every tick; enable only while running without a fault or an
//     emergency stop.
// A fault clears only by an operator's act: the clutch pressed and released once the device
// has been usable for `rearm_after`; force then engages again as on start.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

#include "common/arm_shm/arm_shm.h"
#include "haptic_node/force_output.h"
#include "haptic_node/kinematics.h"
#include "server/contact/local_force_model.h"

namespace somasim::haptic {

// A local force model as plain data for a LatestSlot (latest_slot.h), with when the node
// received it. The tissue stiffness (display only) is not carried.
struct PackedForceModel {
  uint64_t sequence = 0;
  int64_t received_ns = 0;  // the node's monotonic clock
  double sim_time = 0.0;    // [s]
  uint32_t in_contact = 0;
  uint32_t grasping = 0;
  double contact_point[3] = {};    // [m]
  double normal[3] = {};           // unit
  double contact_stiffness = 0;    // [N/m]
  double grasp_anchor[3] = {};     // [m]
  double grasp_stiffness[9] = {};  // [N/m] row-major
  double bias_force[3] = {};       // [N]
  double damping = 0;              // [N s/m]
  double force_limit = 0;          // [N]
};
PackedForceModel Pack(const contact::LocalForceModel& model, int64_t received_ns);
contact::LocalForceModel Unpack(const PackedForceModel& packed);

// The tool's pose for the server: the loop's output, the DDS thread's input (through a slot).
struct ToolPoseSample {
  int64_t time_ns = 0;                   // the tick's time on the node's monotonic clock
  double position[3] = {};               // [m] scene
  double orientation[4] = {1, 0, 0, 0};  // w x y z, the tool frame (shaft +z) in the scene
  double jaw = 0.0;                      // 0 open .. 1 closed (the arm's gripper)
  uint32_t buttons = 0;                  // SOMASIM_ARM_BUTTON_* as the arm reports them
  uint32_t valid = 0;                    // 0 until the arm's pose is known
};

struct HapticLoopSettings {
  ForceOutputSettings output;      // max_force: the arm's (ArmKinematics::max_force)
  double arm_timeout = 0.010;      // [s] the driver's heartbeat may be still this long
  double velocity_cutoff = 100.0;  // [Hz] low-pass of the hand's velocity
  double rearm_after = 0.5;        // [s] a usable device before the clutch may clear a fault
};

struct HapticLoopInput {
  int64_t now_ns = 0;                    // the node's monotonic clock
  const char* header_problem = nullptr;  // arm::HeaderProblem of the block, or nullptr
  arm::ReadResult read = arm::ReadResult::kNoData;
  somasim_arm_state_t state{};              // valid when read == kOk
  const PackedForceModel* model = nullptr;  // the newest model, nullptr: none yet
};

enum class LoopPhase { kWaitingForArm, kRunning };

struct HapticLoopCounters {
  uint64_t ticks = 0;
  uint64_t waiting_ticks = 0;  // before the driver's heartbeat moved
  uint64_t torn_reads = 0;
  uint64_t bad_states = 0;  // a header, state or heartbeat problem
  uint64_t clutch_ticks = 0;
  uint64_t emergency_stop_ticks = 0;
  uint64_t fault_clears = 0;
  uint64_t torque_clamped_ticks = 0;
};

class HapticLoop {
 public:
  // Throws std::invalid_argument for settings that are not finite and positive (the output
  // stage's, and the loop's own).
  HapticLoop(const ArmKinematics& kinematics, const HapticLoopSettings& settings);

  // One tick: the command to write to the arm.
  const somasim_arm_command_t& Tick(const HapticLoopInput& in);

  LoopPhase phase() const { return phase_; }
  bool fault() const { return output_.fault(); }
  // Why the fault latched (static; "" when none): the device's problem or the output stage's.
  const char* fault_reason() const;
  const ToolPoseSample& tool() const { return tool_; }
  bool clutched() const { return clutched_; }
  const Eigen::Vector3d& scene_force() const { return scene_force_; }  // [N] the model's
  const Eigen::Vector3d& arm_force() const { return arm_force_; }      // [N] rendered, arm frame
  const Eigen::Vector3d& arm_velocity() const { return velocity_; }    // [m/s] filtered
  const ForceOutput& output() const { return output_; }
  const HapticLoopCounters& counters() const { return counters_; }

 private:
  const ArmKinematics& kinematics_;
  HapticLoopSettings s_;
  ForceOutput output_;
  LoopPhase phase_ = LoopPhase::kWaitingForArm;
  const char* device_problem_ = nullptr;  // what latched the fault, if the device did
  int64_t last_now_ns_ = 0;
  bool seen_heartbeat_ = false;
  uint64_t last_heartbeat_ = 0;
  int64_t heartbeat_changed_ns_ = 0;
  int64_t still_ticks_ = 0;        // our ticks since the driver's heartbeat last moved
  int64_t torn_streak_ = 0;        // consecutive torn reads
  int64_t healthy_since_ns_ = -1;  // the device usable since (< 0: not now)
  bool have_pose_ = false;
  Eigen::Vector3d last_arm_position_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d velocity_ = Eigen::Vector3d::Zero();
  Jacobian jacobian_ = Jacobian::Zero();
  bool clutched_ = false;
  Eigen::Vector3d offset_position_ = Eigen::Vector3d::Zero();      // tool = arm + offset (scene)
  Eigen::Matrix3d offset_rotation_ = Eigen::Matrix3d::Identity();  // tool R = offset R · arm R
  Eigen::Vector3d tool_position_ = Eigen::Vector3d::Zero();
  Eigen::Matrix3d tool_rotation_ = Eigen::Matrix3d::Identity();
  Eigen::Vector3d scene_force_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d arm_force_ = Eigen::Vector3d::Zero();
  uint64_t heartbeat_ = 0;
  ToolPoseSample tool_;
  somasim_arm_command_t command_{};
  HapticLoopCounters counters_;
};

}  // namespace somasim::haptic
