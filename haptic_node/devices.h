// The devices the haptic node's 1 kHz loop drives, one interface (read once per tick, write the
// command once per tick, from the loop's thread; allocation-free, no lock, no system call but
// the shared memory's):
//  - ArmDevice: an arm (or somasim-arm-sim) through its shared memory (common/arm_shm).
//  - ScriptDevice: the mock script (mock_script.h) as an emulated Cartesian device: each tick
//    its handle is where the script says at the loop's time, its heartbeat moving, so the
//    automated tests and the demo run the same tick as an arm.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "common/arm_shm/arm_shm.h"
#include "haptic_node/haptic_loop.h"
#include "haptic_node/mock_script.h"

namespace somasim::haptic {

class Device {
 public:
  virtual ~Device() = default;
  // Fills the device's part of `in` (header, state read, or Cartesian state; the tool it
  // drives) for a tick at now_ns on the node's monotonic clock.
  virtual void Read(int64_t now_ns, HapticLoopInput* in) = 0;
  // Hands the tick's command to the device.
  virtual void Write(const HapticLoopInput& in, const somasim_arm_command_t& command) = 0;
  // The last command when the loop stops: motors disabled, its heartbeat `heartbeat`, stamped
  // `now_ns` (the node's monotonic clock).
  virtual void Stop(uint64_t heartbeat, int64_t now_ns) = 0;
  // Whether the device has nothing more to do (a script that ended).
  virtual bool finished(int64_t now_ns) const = 0;
  // For the log when a fault latches (the wire thread's, not the loop's): what the device's
  // own checks say of it, e.g. an arm block's header with its values; "" when nothing.
  virtual std::string FaultDetail() const { return ""; }
};

class ArmDevice : public Device {
 public:
  explicit ArmDevice(arm_shm::ArmBlock& block) : block_(block) {}
  void Read(int64_t now_ns, HapticLoopInput* in) override;
  void Write(const HapticLoopInput& in, const somasim_arm_command_t& command) override;
  void Stop(uint64_t heartbeat, int64_t now_ns) override;
  bool finished(int64_t) const override { return false; }
  std::string FaultDetail() const override { return block_.HeaderError(); }

 private:
  arm_shm::ArmBlock& block_;
};

class ScriptDevice : public Device {
 public:
  // `script` outlives the device; finished 0.2 s after its last key.
  explicit ScriptDevice(const MockScript& script) : script_(script) {}
  void Read(int64_t now_ns, HapticLoopInput* in) override;
  void Write(const HapticLoopInput&, const somasim_arm_command_t&) override {}
  void Stop(uint64_t, int64_t) override {}
  bool finished(int64_t now_ns) const override;
  // [s] script time at now_ns (0 at the first Read).
  double ScriptTime(int64_t now_ns) const;

 private:
  const MockScript& script_;
  int64_t start_ns_ = -1;  // the first Read's clock
  uint64_t heartbeat_ = 0;
};

}  // namespace somasim::haptic
