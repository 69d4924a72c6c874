// The arm's shared memory (common/arm_shm): the node's and the driver's mappings share both
// records; a valid existing block is reused, an unusable one refused naming the field (magic,
// version, sizes, joints, a truncated object); the seqlock hands over whole records only, 10^7
// reads under a concurrent writer; a writer that died mid-write is never read as data; states
// with NaN, out-of-range or unknown values are refused by name.
#include "common/arm_shm/arm_shm.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/mman.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstring>
#include <limits>
#include <string>
#include <thread>

#include "tests/support/sanitizer.h"

namespace somasim::arm_shm {
namespace {

// A name no other test (or run) uses; the object is removed when the test ends.
class Named {
 public:
  explicit Named(const std::string& what) : name_(what + "-" + std::to_string(getpid())) {
    ArmBlock::Unlink(name_);
  }
  ~Named() { ArmBlock::Unlink(name_); }
  const std::string& name() const { return name_; }

 private:
  std::string name_;
};

template <typename F>
std::string ErrorOf(F&& f) {
  try {
    f();
  } catch (const ArmShmError& e) {
    return e.what();
  }
  return "(no error)";
}

TEST(ArmShm, NodeAndDriverShareBothRecords) {
  Named n("share");
  auto node = ArmBlock::Create(n.name(), 6);
  auto driver = ArmBlock::Open(n.name());
  EXPECT_EQ(driver->num_joints(), 6u);
  EXPECT_EQ(driver->HeaderError(), "");
  EXPECT_EQ(node->object_name(), "/somasim-arm-" + n.name());
  somasim_arm_state_t state{};
  EXPECT_EQ(ReadState(node->block().state, &state), ReadResult::kNoData);
  state.heartbeat = 7;
  state.num_joints = 6;
  state.buttons = SOMASIM_ARM_BUTTON_CLUTCH;
  for (int k = 0; k < 6; ++k) state.joint[k] = 0.1 * k;
  state.gripper = 0.5;
  WriteState(&driver->block().state, state);
  somasim_arm_state_t got{};
  ASSERT_EQ(ReadState(node->block().state, &got), ReadResult::kOk);
  EXPECT_EQ(got.heartbeat, state.heartbeat);
  EXPECT_EQ(got.driver_time_ns, state.driver_time_ns);
  EXPECT_EQ(got.buttons, state.buttons);
  EXPECT_EQ(got.num_joints, state.num_joints);
  for (int k = 0; k < SOMASIM_ARM_MAX_JOINTS; ++k) EXPECT_EQ(got.joint[k], state.joint[k]);
  EXPECT_EQ(got.gripper, state.gripper);
  somasim_arm_command_t command{};
  command.heartbeat = 3;
  command.enable = 1;
  command.num_joints = 6;
  command.torque[2] = -0.25;
  command.force[2] = 1.5;
  WriteCommand(&node->block().command, command);
  somasim_arm_command_t seen{};
  ASSERT_EQ(ReadCommand(driver->block().command, &seen), ReadResult::kOk);
  EXPECT_EQ(seen.heartbeat, command.heartbeat);
  EXPECT_EQ(seen.enable, command.enable);
  EXPECT_EQ(seen.num_joints, command.num_joints);
  for (int k = 0; k < SOMASIM_ARM_MAX_JOINTS; ++k) EXPECT_EQ(seen.torque[k], command.torque[k]);
  for (int k = 0; k < 3; ++k) EXPECT_EQ(seen.force[k], command.force[k]);
  EXPECT_EQ(driver->block().command.sequence, 2u);  // one whole write: odd, then even
}

TEST(ArmShm, ANodeReattachesToAValidBlockAndRefusesAnotherArmsJointCount) {
  Named n("reattach");
  auto first = ArmBlock::Create(n.name(), 3);
  somasim_arm_state_t state{};
  state.heartbeat = 42;
  WriteState(&first->block().state, state);
  auto again = ArmBlock::Create(n.name(), 3);  // a node restarted while the driver ran
  somasim_arm_state_t got{};
  ASSERT_EQ(ReadState(again->block().state, &got), ReadResult::kOk);
  EXPECT_EQ(got.heartbeat, 42u);
  const std::string e = ErrorOf([&] { ArmBlock::Create(n.name(), 6); });
  EXPECT_NE(e.find("for 3 joints, the arm has 6"), std::string::npos) << e;
}

TEST(ArmShm, RefusesBadNamesJointCountsAndMissingBlocks) {
  EXPECT_NE(ErrorOf([] { ArmBlock::Create("", 3); }).find("1 to 32 characters"), std::string::npos);
  EXPECT_NE(ErrorOf([] { ArmBlock::Create("a/b", 3); }).find("only letters"), std::string::npos);
  EXPECT_NE(ErrorOf([] { ArmBlock::Create(std::string(33, 'a'), 3); }).find("1 to 32"),
            std::string::npos);
  EXPECT_NE(ErrorOf([] { ArmBlock::Create("zero-joints", 0); }).find("not 0"), std::string::npos);
  EXPECT_NE(ErrorOf([] { ArmBlock::Create("nine-joints", 9); }).find("not 9"), std::string::npos);
  const std::string missing =
      ErrorOf([] { ArmBlock::Open("no-such-arm-" + std::to_string(getpid())); });
  EXPECT_NE(missing.find("cannot open"), std::string::npos) << missing;
}

// Every header field the node checks, corrupted one at a time: Open refuses naming it, and a
// live mapping sees the corruption too (HeaderError).
TEST(ArmShm, RefusesACorruptedHeaderNamingTheField) {
  Named n("corrupt");
  auto node = ArmBlock::Create(n.name(), 6);
  struct Case {
    void (*corrupt)(somasim_arm_block_t*);
    const char* expected;
  };
  const Case cases[] = {
      {[](somasim_arm_block_t* b) { b->magic = 0x12345678; }, "magic is 0x12345678"},
      {[](somasim_arm_block_t* b) { b->abi_version = 2; }, "abi_version is 2, this node's is 1"},
      {[](somasim_arm_block_t* b) { b->block_size = 4096; }, "block_size is 4096"},
      {[](somasim_arm_block_t* b) { b->state_size = 97; }, "state_size is 97, this node's is 96"},
      {[](somasim_arm_block_t* b) { b->command_size = 0; }, "command_size is 0"},
      {[](somasim_arm_block_t* b) { b->num_joints = 0; }, "num_joints is 0, not 1..8"},
      {[](somasim_arm_block_t* b) { b->num_joints = 1000; }, "num_joints is 1000"},
  };
  for (const Case& c : cases) {
    const somasim_arm_block_t saved = node->block();
    c.corrupt(&node->block());
    EXPECT_NE(node->HeaderError().find(c.expected), std::string::npos) << node->HeaderError();
    EXPECT_NE(node->HeaderProblem(), nullptr) << c.expected;  // the loop's check agrees
    const std::string e = ErrorOf([&] { ArmBlock::Open(n.name(), 0); });
    EXPECT_NE(e.find(c.expected), std::string::npos) << e;
    EXPECT_NE(e.find("/somasim-arm-" + n.name()), std::string::npos) << e;
    node->block() = saved;
    EXPECT_EQ(node->HeaderError(), "");
    EXPECT_EQ(node->HeaderProblem(), nullptr);
  }
  // A node finding a corrupted block says how to clear it.
  node->block().magic = 0;
  const std::string e = ErrorOf([&] { ArmBlock::Create(n.name(), 6); });
  EXPECT_NE(e.find("remove /dev/shm/somasim-arm-"), std::string::npos) << e;
}

TEST(ArmShm, RefusesATruncatedBlock) {
  Named n("short");
  const std::string object = ShmObjectName(n.name());
  const int fd = shm_open(object.c_str(), O_RDWR | O_CREAT | O_EXCL, 0600);
  ASSERT_GE(fd, 0);
  ASSERT_EQ(ftruncate(fd, 100), 0);
  close(fd);
  const std::string e = ErrorOf([&] { ArmBlock::Open(n.name(), 0); });
  EXPECT_NE(e.find("size in bytes is 100, this node's is 320"), std::string::npos) << e;
}

// 10^7 reads (10^6 under the sanitizers, which slow each tenfold) while another thread writes
// as fast as it can: every record a read accepts is one write's, whole (its fields agree with
// each other), and reads do succeed.
TEST(ArmShm, SeqlockAcceptsNoTornRecordUnderAConcurrentWriter) {
  Named n("seqlock");
  auto node = ArmBlock::Create(n.name(), 8);
  auto driver = ArmBlock::Open(n.name());
  std::atomic<bool> stop{false};
  std::thread writer([&] {
    somasim_arm_state_t s{};
    s.num_joints = 8;
    for (uint64_t i = 1; !stop.load(std::memory_order_relaxed); ++i) {
      s.heartbeat = i;
      s.driver_time_ns = 3 * i;
      s.buttons = static_cast<uint32_t>(i & 7U);
      for (int k = 0; k < 8; ++k) s.joint[k] = static_cast<double>(i) + k;
      s.gripper = static_cast<double>(i % 1000) * 1e-3;
      WriteState(&driver->block().state, s);
    }
  });
  const int64_t reads = somasim::testing::kUnderSanitizer ? 1000000 : 10000000;
  int64_t ok = 0, torn = 0, bad = 0;
  uint64_t last = 0;
  bool monotonic = true;
  somasim_arm_state_t got{};
  for (int64_t r = 0; r < reads; ++r) {
    const ReadResult result = ReadState(node->block().state, &got, 4);
    if (result == ReadResult::kTorn) ++torn;
    if (result != ReadResult::kOk) continue;
    ++ok;
    const uint64_t i = got.heartbeat;
    bool whole = got.driver_time_ns == 3 * i && got.buttons == (i & 7U) && got.num_joints == 8 &&
                 got.gripper == static_cast<double>(i % 1000) * 1e-3;
    for (int k = 0; k < 8; ++k) whole = whole && got.joint[k] == static_cast<double>(i) + k;
    bad += whole ? 0 : 1;
    monotonic = monotonic && i >= last;
    last = i;
  }
  stop = true;
  writer.join();
  EXPECT_EQ(bad, 0) << "torn records accepted";
  EXPECT_TRUE(monotonic);
  // Reads do get through, even against a writer that never pauses (a driver writes at 1 kHz).
  EXPECT_GT(ok, 1000) << "torn " << torn;
  std::printf("seqlock: %lld reads, %lld whole, %lld retried out, last heartbeat %llu\n",
              static_cast<long long>(reads), static_cast<long long>(ok),
              static_cast<long long>(torn), static_cast<unsigned long long>(last));
}

// A driver that died in the middle of a write leaves the sequence odd: the node reads "torn",
// never the half-written record, however often it tries.
TEST(ArmShm, AWriterThatDiedMidWriteIsNeverReadAsData) {
  Named n("died");
  auto node = ArmBlock::Create(n.name(), 2);
  somasim_arm_state_t s{};
  s.heartbeat = 5;
  WriteState(&node->block().state, s);
  node->block().state.sequence += 1;  // began a write, never finished
  node->block().state.data.heartbeat = 6;
  somasim_arm_state_t got{};
  EXPECT_EQ(ReadState(node->block().state, &got, 1000), ReadResult::kTorn);
}

TEST(ArmShm, StateErrorNamesWhatIsWrong) {
  somasim_arm_state_t s{};
  s.num_joints = 3;
  s.gripper = 0.5;
  EXPECT_EQ(StateError(s, 3), "");
  const auto with = [&](auto change) {
    somasim_arm_state_t t = s;
    change(&t);
    std::string error = StateError(t, 3);
    EXPECT_EQ(error.empty(), StateProblem(t, 3) == nullptr) << error;  // the loop's check agrees
    return error;
  };
  EXPECT_NE(with([](auto* t) { t->num_joints = 4; }).find("num_joints is 4, the arm has 3"),
            std::string::npos);
  EXPECT_NE(with([](auto* t) {
              t->joint[1] = std::numeric_limits<double>::quiet_NaN();
            }).find("joint 1 is nan"),
            std::string::npos);
  EXPECT_NE(with([](auto* t) {
              t->joint[2] = std::numeric_limits<double>::infinity();
            }).find("joint 2 is inf"),
            std::string::npos);
  EXPECT_NE(with([](auto* t) { t->joint[0] = 1e9; }).find("joint 0"), std::string::npos);
  EXPECT_EQ(with([](auto* t) { t->joint[5] = std::numeric_limits<double>::quiet_NaN(); }), "")
      << "joints beyond the arm's are not read";
  EXPECT_NE(with([](auto* t) { t->gripper = 2.0; }).find("gripper is 2"), std::string::npos);
  EXPECT_NE(with([](auto* t) { t->gripper = std::nan(""); }).find("gripper"), std::string::npos);
  EXPECT_NE(with([](auto* t) { t->buttons = 0x80; }).find("unknown bits 0x80"), std::string::npos);
  EXPECT_EQ(with([](auto* t) { t->buttons = SOMASIM_ARM_BUTTON_EMERGENCY_STOP; }), "");
}

}  // namespace
}  // namespace somasim::arm_shm
