#include "common/arm_shm/arm_shm.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <thread>

namespace somasim::arm_shm {

namespace {

// Words of a record's payload, read and written as relaxed atomics (the seqlock's sequence
// orders them), through a type that may alias the payload's doubles.
using Word = uint64_t __attribute__((may_alias));

template <typename Payload>
void SeqlockWrite(uint64_t* sequence, Payload* slot, const Payload& value) {
  static_assert(sizeof(Payload) % 8 == 0 && alignof(Payload) == 8);
  const uint64_t s = __atomic_load_n(sequence, __ATOMIC_RELAXED);
  __atomic_store_n(sequence, s + 1, __ATOMIC_RELAXED);
  __atomic_thread_fence(__ATOMIC_RELEASE);
  Word* out = reinterpret_cast<Word*>(slot);
  const Word* in = reinterpret_cast<const Word*>(&value);
  for (size_t k = 0; k < sizeof(Payload) / 8; ++k)
    __atomic_store_n(out + k, in[k], __ATOMIC_RELAXED);
  __atomic_store_n(sequence, s + 2, __ATOMIC_RELEASE);
}

template <typename Payload>
ReadResult SeqlockRead(const uint64_t* sequence, const Payload* slot, Payload* out, int attempts) {
  static_assert(sizeof(Payload) % 8 == 0 && alignof(Payload) == 8);
  const Word* in = reinterpret_cast<const Word*>(slot);
  Word* copy = reinterpret_cast<Word*>(out);
  for (int attempt = 0; attempt < attempts; ++attempt) {
    const uint64_t s1 = __atomic_load_n(sequence, __ATOMIC_ACQUIRE);
    if (s1 == 0) return ReadResult::kNoData;
    if ((s1 & 1U) != 0) continue;
    for (size_t k = 0; k < sizeof(Payload) / 8; ++k) {
      copy[k] = __atomic_load_n(in + k, __ATOMIC_RELAXED);
    }
    __atomic_thread_fence(__ATOMIC_ACQUIRE);
    if (__atomic_load_n(sequence, __ATOMIC_RELAXED) == s1) return ReadResult::kOk;
  }
  return ReadResult::kTorn;
}

std::string Errno(const std::string& what) { return what + ": " + std::strerror(errno); }

}  // namespace

std::string ArmNameError(std::string_view name) {
  if (name.empty() || name.size() > 32) return "must be 1 to 32 characters";
  for (const char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '-';
    if (!ok) return "may hold only letters, digits, '_' and '-'";
  }
  return "";
}

std::string ShmObjectName(std::string_view name) {
  return SOMASIM_ARM_SHM_PREFIX + std::string(name);
}

std::string HeaderError(const somasim_arm_block_t& b, uint64_t mapped_bytes) {
  const auto mismatch = [](const char* field, uint64_t got, uint64_t want) {
    return std::string(field) + " is " + std::to_string(got) + ", this node's is " +
           std::to_string(want);
  };
  if (mapped_bytes < sizeof(somasim_arm_block_t)) {
    return mismatch("the block's size in bytes", mapped_bytes, sizeof(somasim_arm_block_t));
  }
  const uint32_t magic = __atomic_load_n(&b.magic, __ATOMIC_ACQUIRE);
  if (magic != SOMASIM_ARM_MAGIC) {
    char text[96];
    std::snprintf(text, sizeof text, "magic is 0x%08X, not 0x%08X (\"SARM\"): not an arm block",
                  magic, SOMASIM_ARM_MAGIC);
    return text;
  }
  if (b.abi_version != SOMASIM_ARM_ABI_VERSION) {
    return mismatch("abi_version", b.abi_version, SOMASIM_ARM_ABI_VERSION);
  }
  if (b.block_size != sizeof(somasim_arm_block_t)) {
    return mismatch("block_size", b.block_size, sizeof(somasim_arm_block_t));
  }
  if (b.state_size != sizeof(somasim_arm_state_t)) {
    return mismatch("state_size", b.state_size, sizeof(somasim_arm_state_t));
  }
  if (b.command_size != sizeof(somasim_arm_command_t)) {
    return mismatch("command_size", b.command_size, sizeof(somasim_arm_command_t));
  }
  if (b.num_joints < 1 || b.num_joints > SOMASIM_ARM_MAX_JOINTS) {
    return "num_joints is " + std::to_string(b.num_joints) + ", not 1.." +
           std::to_string(SOMASIM_ARM_MAX_JOINTS);
  }
  return "";
}

const char* HeaderProblem(const somasim_arm_block_t& b, uint64_t mapped_bytes) {
  if (mapped_bytes < sizeof(somasim_arm_block_t)) return "the block is too small";
  if (__atomic_load_n(&b.magic, __ATOMIC_ACQUIRE) != SOMASIM_ARM_MAGIC) return "bad magic";
  if (b.abi_version != SOMASIM_ARM_ABI_VERSION) return "another abi_version";
  if (b.block_size != sizeof(somasim_arm_block_t)) return "another block_size";
  if (b.state_size != sizeof(somasim_arm_state_t)) return "another state_size";
  if (b.command_size != sizeof(somasim_arm_command_t)) return "another command_size";
  if (b.num_joints < 1 || b.num_joints > SOMASIM_ARM_MAX_JOINTS) return "num_joints out of range";
  return nullptr;
}

ArmBlock::ArmBlock(std::string object, somasim_arm_block_t* block, uint64_t bytes)
    : object_(std::move(object)), block_(block), bytes_(bytes) {}

ArmBlock::~ArmBlock() { munmap(block_, bytes_); }

std::string ArmBlock::HeaderError() const { return arm_shm::HeaderError(*block_, bytes_); }
const char* ArmBlock::HeaderProblem() const { return arm_shm::HeaderProblem(*block_, bytes_); }

std::unique_ptr<ArmBlock> ArmBlock::Create(std::string_view name, uint32_t num_joints) {
  if (const std::string bad = ArmNameError(name); !bad.empty()) {
    throw ArmShmError("arm name \"" + std::string(name) + "\" " + bad);
  }
  if (num_joints < 1 || num_joints > SOMASIM_ARM_MAX_JOINTS) {
    throw ArmShmError("an arm has 1.." + std::to_string(SOMASIM_ARM_MAX_JOINTS) + " joints, not " +
                      std::to_string(num_joints));
  }
  const std::string object = ShmObjectName(name);
  const int fd = shm_open(object.c_str(), O_RDWR | O_CREAT | O_EXCL, 0660);
  if (fd < 0 && errno == EEXIST) {
    std::unique_ptr<ArmBlock> existing;
    try {
      existing = Open(name, 1000);
    } catch (const ArmShmError& e) {
      throw ArmShmError(std::string(e.what()) + " (if no driver uses it, remove /dev/shm" + object +
                        ")");
    }
    if (existing->num_joints() != num_joints) {
      throw ArmShmError(object + ": the existing block is for " +
                        std::to_string(existing->num_joints()) + " joints, the arm has " +
                        std::to_string(num_joints));
    }
    return existing;
  }
  if (fd < 0) throw ArmShmError(Errno(object + ": cannot create"));
  const size_t bytes = sizeof(somasim_arm_block_t);
  if (ftruncate(fd, static_cast<off_t>(bytes)) != 0) {
    const std::string error = Errno(object + ": cannot size");
    close(fd);
    shm_unlink(object.c_str());
    throw ArmShmError(error);
  }
  void* p = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  close(fd);
  if (p == MAP_FAILED) {
    const std::string error = Errno(object + ": cannot map");
    shm_unlink(object.c_str());
    throw ArmShmError(error);
  }
  auto* b = static_cast<somasim_arm_block_t*>(p);
  std::memset(p, 0, bytes);  // ftruncate zeroed it already; say so
  b->abi_version = SOMASIM_ARM_ABI_VERSION;
  b->block_size = sizeof(somasim_arm_block_t);
  b->state_size = sizeof(somasim_arm_state_t);
  b->command_size = sizeof(somasim_arm_command_t);
  b->num_joints = num_joints;
  __atomic_store_n(&b->magic, SOMASIM_ARM_MAGIC, __ATOMIC_RELEASE);  // last: the header is whole
  return std::unique_ptr<ArmBlock>(new ArmBlock(object, b, bytes));
}

std::unique_ptr<ArmBlock> ArmBlock::Open(std::string_view name, int wait_ms) {
  if (const std::string bad = ArmNameError(name); !bad.empty()) {
    throw ArmShmError("arm name \"" + std::string(name) + "\" " + bad);
  }
  const std::string object = ShmObjectName(name);
  const int fd = shm_open(object.c_str(), O_RDWR, 0);
  if (fd < 0) {
    throw ArmShmError(Errno(object + ": cannot open (is the haptic node or the driver running?)"));
  }
  struct stat st {};
  if (fstat(fd, &st) != 0) {
    const std::string error = Errno(object + ": cannot stat");
    close(fd);
    throw ArmShmError(error);
  }
  const auto bytes = static_cast<uint64_t>(st.st_size);
  if (bytes < sizeof(somasim_arm_block_t)) {
    close(fd);
    throw ArmShmError(object + ": " +
                      arm_shm::HeaderError(somasim_arm_block_t{}, bytes));  // names the size
  }
  void* p = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  close(fd);
  if (p == MAP_FAILED) throw ArmShmError(Errno(object + ": cannot map"));
  auto block =
      std::unique_ptr<ArmBlock>(new ArmBlock(object, static_cast<somasim_arm_block_t*>(p), bytes));
  // The creator stores the magic last: a block being made has none yet.
  const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(wait_ms);
  while (__atomic_load_n(&block->block_->magic, __ATOMIC_ACQUIRE) == 0 &&
         std::chrono::steady_clock::now() < end) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  if (const std::string bad = block->HeaderError(); !bad.empty()) {
    throw ArmShmError(object + ": " + bad);
  }
  return block;
}

bool ArmBlock::Unlink(std::string_view name) {
  return shm_unlink(ShmObjectName(name).c_str()) == 0;
}

void WriteState(somasim_arm_state_record_t* record, const somasim_arm_state_t& value) {
  SeqlockWrite(&record->sequence, &record->data, value);
}

void WriteCommand(somasim_arm_command_record_t* record, const somasim_arm_command_t& value) {
  SeqlockWrite(&record->sequence, &record->data, value);
}

ReadResult ReadState(const somasim_arm_state_record_t& record, somasim_arm_state_t* out,
                     int attempts) {
  return SeqlockRead(&record.sequence, &record.data, out, attempts);
}

ReadResult ReadCommand(const somasim_arm_command_record_t& record, somasim_arm_command_t* out,
                       int attempts) {
  return SeqlockRead(&record.sequence, &record.data, out, attempts);
}

const char* StateProblem(const somasim_arm_state_t& s, uint32_t num_joints) {
  if (s.num_joints != num_joints) return "another num_joints";
  for (uint32_t k = 0; k < num_joints; ++k) {
    if (!std::isfinite(s.joint[k]) || std::abs(s.joint[k]) >= 1e3) return "a bad joint value";
  }
  if (!std::isfinite(s.gripper) || s.gripper < -1e-6 || s.gripper > 1.0 + 1e-6) {
    return "a bad gripper value";
  }
  constexpr uint32_t kKnown =
      SOMASIM_ARM_BUTTON_CLUTCH | SOMASIM_ARM_BUTTON_EMERGENCY_STOP | SOMASIM_ARM_BUTTON_CUT;
  if ((s.buttons & ~kKnown) != 0) return "unknown button bits";
  return nullptr;
}

std::string StateError(const somasim_arm_state_t& s, uint32_t num_joints) {
  if (s.num_joints != num_joints) {
    return "num_joints is " + std::to_string(s.num_joints) + ", the arm has " +
           std::to_string(num_joints);
  }
  for (uint32_t k = 0; k < num_joints; ++k) {
    if (!std::isfinite(s.joint[k]) || std::abs(s.joint[k]) >= 1e3) {
      return "joint " + std::to_string(k) + " is " + std::to_string(s.joint[k]) +
             ": not a finite value below 1e3";
    }
  }
  if (!std::isfinite(s.gripper) || s.gripper < -1e-6 || s.gripper > 1.0 + 1e-6) {
    return "gripper is " + std::to_string(s.gripper) + ", not within [0, 1]";
  }
  constexpr uint32_t kKnown =
      SOMASIM_ARM_BUTTON_CLUTCH | SOMASIM_ARM_BUTTON_EMERGENCY_STOP | SOMASIM_ARM_BUTTON_CUT;
  if ((s.buttons & ~kKnown) != 0) {
    return "buttons has unknown bits 0x" + [&] {
      char hex[16];
      std::snprintf(hex, sizeof hex, "%X", s.buttons & ~kKnown);
      return std::string(hex);
    }();
  }
  return "";
}

}  // namespace somasim::arm_shm
