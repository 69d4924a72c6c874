#include "haptic_node/devices.h"

namespace somasim::haptic {

void ArmDevice::Read(int64_t, HapticLoopInput* in) {
  in->header_problem = block_.HeaderProblem();
  in->read = arm_shm::ReadState(block_.block().state, &in->state);
  in->tool = 0;
}

void ArmDevice::Write(const HapticLoopInput& in, const somasim_arm_command_t& command) {
  if (in.header_problem == nullptr) arm_shm::WriteCommand(&block_.block().command, command);
}

void ArmDevice::Stop(uint64_t heartbeat, int64_t now_ns) {
  // Motors disabled (the driver's watchdog would also see the heartbeat stop).
  somasim_arm_command_t last{};
  last.node_time_ns = static_cast<uint64_t>(now_ns);
  last.heartbeat = heartbeat;
  last.num_joints = block_.num_joints();
  if (block_.HeaderProblem() == nullptr) arm_shm::WriteCommand(&block_.block().command, last);
}

double ScriptDevice::ScriptTime(int64_t now_ns) const {
  return start_ns_ < 0 ? 0.0 : 1e-9 * static_cast<double>(now_ns - start_ns_);
}

void ScriptDevice::Read(int64_t now_ns, HapticLoopInput* in) {
  if (start_ns_ < 0) start_ns_ = now_ns;
  const ScriptSample s = script_.At(ScriptTime(now_ns));
  CartesianState& c = in->cartesian;
  c.heartbeat = ++heartbeat_;  // the emulated device is alive as long as the loop ticks it
  for (int i = 0; i < 3; ++i) c.position[i] = s.position[i];
  c.orientation[0] = s.orientation.w();
  c.orientation[1] = s.orientation.x();
  c.orientation[2] = s.orientation.y();
  c.orientation[3] = s.orientation.z();
  c.gripper = s.jaw;
  c.buttons = s.buttons;  // the script's bits are the ABI's: clutch, emergency stop, cut
  in->header_problem = nullptr;
  in->read = arm_shm::ReadResult::kOk;
  in->tool = static_cast<uint32_t>(s.tool);
}

bool ScriptDevice::finished(int64_t now_ns) const {
  return start_ns_ >= 0 && ScriptTime(now_ns) > script_.duration() + 0.2;
}

}  // namespace somasim::haptic
