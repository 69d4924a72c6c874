// The node's and the driver's side of the arm's shared memory (common/arm_shm/arm_abi.h): making
// and attaching the POSIX shared-memory block with its header checked, and the single-writer
// seqlock records. Reads and writes allocate nothing, take no lock and make no system call: they
// run in the 1 kHz haptic loop and in the arm simulator's.
#pragma once

#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <string_view>

#include "common/arm_shm/arm_abi.h"

namespace somasim::arm_shm {

// A block that cannot be made or used; what() names the object and what is wrong.
class ArmShmError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// "" when `name` can name an arm (1-32 letters, digits, '_' or '-'), else what is wrong.
std::string ArmNameError(std::string_view name);
// "/somasim-arm-<name>".
std::string ShmObjectName(std::string_view name);

// "" when a header can be used: the magic, ABI version and the three sizes are this build's, the
// joint count is 1..SOMASIM_ARM_MAX_JOINTS, and `mapped_bytes` holds the whole block; else what
// is wrong, naming the field and both values.
std::string HeaderError(const somasim_arm_block_t& block, uint64_t mapped_bytes);

// The same checks for the 1 kHz loop, allocation-free: nullptr when the header can be used, else
// which check failed (a static string; HeaderError gives the values).
const char* HeaderProblem(const somasim_arm_block_t& block, uint64_t mapped_bytes);

// One mapping of an arm's block.
class ArmBlock {
 public:
  // The node's side: makes /somasim-arm-<name> (mode 0660) for an arm of `num_joints` joints,
  // or, when a valid block of that arm already exists (the driver, or a node before a restart,
  // made it), attaches to it. Its records keep what they hold. Throws ArmShmError.
  static std::unique_ptr<ArmBlock> Create(std::string_view name, uint32_t num_joints);
  // The driver's side: attaches to an existing block, waiting up to `wait_ms` for its creator
  // to finish the header. Throws ArmShmError: no such block, too small, bad header.
  static std::unique_ptr<ArmBlock> Open(std::string_view name, int wait_ms = 1000);
  // Removes /somasim-arm-<name> (mappings stay valid until unmapped); false if absent.
  static bool Unlink(std::string_view name);

  ~ArmBlock();
  ArmBlock(const ArmBlock&) = delete;
  ArmBlock& operator=(const ArmBlock&) = delete;

  somasim_arm_block_t& block() { return *block_; }
  const somasim_arm_block_t& block() const { return *block_; }
  uint32_t num_joints() const { return block_->num_joints; }
  // The header checked again (the other side, or anything else, may have overwritten it).
  std::string HeaderError() const;
  const char* HeaderProblem() const;  // allocation-free, for the loop
  const std::string& object_name() const { return object_; }

 private:
  ArmBlock(std::string object, somasim_arm_block_t* block, uint64_t bytes);
  std::string object_;
  somasim_arm_block_t* block_;
  uint64_t bytes_;
};

enum class ReadResult {
  kOk,      // a whole record, as one write left it
  kNoData,  // nothing written yet (sequence 0)
  kTorn,    // the writer kept writing through every attempt (or died mid-write: sequence odd)
};

// The seqlock (arm_abi.h): one writer per record; readers retry up to `attempts` times.
void WriteState(somasim_arm_state_record_t* record, const somasim_arm_state_t& value);
void WriteCommand(somasim_arm_command_record_t* record, const somasim_arm_command_t& value);
ReadResult ReadState(const somasim_arm_state_record_t& record, somasim_arm_state_t* out,
                     int attempts = 64);
ReadResult ReadCommand(const somasim_arm_command_record_t& record, somasim_arm_command_t* out,
                       int attempts = 64);

// "" when the driver's state can be used for an arm of `num_joints` joints: num_joints
// matches, every joint value and the gripper finite (|q| < 1e3), the gripper within [0, 1]
// (± 1e-6), no unknown button bits; else what is wrong.
std::string StateError(const somasim_arm_state_t& state, uint32_t num_joints);
// The same checks, allocation-free: nullptr when usable, else which check failed (static).
const char* StateProblem(const somasim_arm_state_t& state, uint32_t num_joints);

}  // namespace somasim::arm_shm
