// The RAII wrapper over Cyclone DDS (common/dds/dds.h), with real Cyclone on loopback: in one
// process (two participants of one domain) and across processes (this executable re-run as a
// publishing child). Every test has its own domain id in 100..129 so `ctest -j` cannot cross
// them.
#include "common/dds/dds.h"

#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "idl/mesh.h"
#include "idl/session.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/sanitizer.h"

extern char** environ;

namespace somasim::dds {
namespace {

using std::chrono::milliseconds;
using Clock = std::chrono::steady_clock;

// The environment variable that turns this executable into the cross-process tests' publisher:
// "<domain id> <partition> <role>", role "heartbeat" or "mesh".
constexpr const char* kChildEnv = "SOMASIM_DDS_TEST_CHILD";
constexpr uint32_t kMeshNodes = 5400;  // 3 × 5400 float32 = 64.8 kB of positions

// Polls `done` every 5 ms until it holds or `timeout` passes; returns whether it held.
bool PollUntil(const std::function<bool()>& done, milliseconds timeout) {
  const auto deadline = Clock::now() + timeout;
  while (!done()) {
    if (Clock::now() > deadline) return false;
    std::this_thread::sleep_for(milliseconds(5));
  }
  return true;
}

Qos ReliableQos(const std::string& partition) {
  return Qos().Reliable(milliseconds(1000)).KeepAll().Partition(partition);
}

// Manual-by-topic liveliness with the product's 500 ms lease (common/dds/topics.h), best-effort
// (as the heartbeat topic) or reliable. The child asserts every 50 ms: a tenfold margin, so a
// loaded CI machine that delays it by a few scheduler slices does not lapse it.
constexpr milliseconds kTestLease{500};
Qos LivelinessQos(const std::string& partition, bool reliable) {
  Qos qos;
  if (reliable) {
    qos.Reliable(milliseconds(1000));
  } else {
    qos.BestEffort();
  }
  return qos.KeepLast(1).ManualLiveliness(kTestLease).Partition(partition);
}

somasim_wire_Heartbeat MakeHeartbeat(uint64_t server_id, uint64_t seq) {
  somasim_wire_Heartbeat h;
  h.format_version = 1;
  h.server_id = server_id;
  h.seq = seq;
  h.sim_time = 0.001 * static_cast<double>(seq);
  h.state = 2;
  return h;
}

// Positions of the test mesh frame, 3·kMeshNodes, distinct and not representable exactly in
// fewer bits than a float carries, so any corrupted or misplaced fragment shows.
std::vector<float> MeshPositions() {
  std::vector<float> positions(3 * kMeshNodes);
  for (size_t i = 0; i < positions.size(); ++i) {
    positions[i] = 0.001f * static_cast<float>(i) + 1.0f / 3.0f;
  }
  return positions;
}

std::vector<somasim_wire_Heartbeat> TakeHeartbeats(Reader<somasim_wire_Heartbeat>& reader) {
  std::vector<somasim_wire_Heartbeat> got;
  reader.Take(
      [&got](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) { got.push_back(h); });
  return got;
}

// --- The child role ------------------------------------------------------------------------------

// Publishes to the parent test over loopback: waits for its reader, writes, and waits until the
// reader has acknowledged everything. Exit codes: 0 done, 1 exception, 2 no reader matched,
// 3 not acknowledged, 4 bad spec.
int RunChild(const std::string& spec) {
  std::istringstream in(spec);
  uint32_t domain_id = 0;
  std::string partition;
  std::string role;
  if (!(in >> domain_id >> partition >> role)) return 4;
  try {
    const Domain domain(domain_id, LoopbackConfig());
    const Participant participant(domain_id);
    const uint64_t server_id = static_cast<uint64_t>(getpid());
    if (role == "heartbeat") {
      const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat");
      Writer<somasim_wire_Heartbeat> writer(participant, topic, ReliableQos(partition));
      if (!PollUntil([&] { return writer.MatchedReaders() >= 1; }, milliseconds(4000))) return 2;
      for (uint64_t seq = 1; seq <= 5; ++seq) writer.Write(MakeHeartbeat(server_id, seq));
      return dds_wait_for_acks(writer.handle(), DDS_SECS(3)) == DDS_RETCODE_OK ? 0 : 3;
    }
    if (role == "liveliness-besteffort" || role == "liveliness-reliable") {
      // Seq 1, then 800 ms of AssertLiveliness every 50 ms without writing, then seq 2 (the
      // parent's mark), then silence while this process lives on for 2.5 s.
      const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat");
      Writer<somasim_wire_Heartbeat> writer(
          participant, topic, LivelinessQos(partition, role == "liveliness-reliable"));
      if (!PollUntil([&] { return writer.MatchedReaders() >= 1; }, milliseconds(4000))) return 2;
      writer.Write(MakeHeartbeat(server_id, 1));
      for (int i = 0; i < 16; ++i) {
        std::this_thread::sleep_for(milliseconds(50));
        writer.AssertLiveliness();
      }
      writer.Write(MakeHeartbeat(server_id, 2));
      std::this_thread::sleep_for(milliseconds(2500));
      return 0;
    }
    if (role == "mesh") {
      const Topic<somasim_wire_MeshFrame> topic(participant, somasim_wire_MeshFrame_desc,
                                                "test_frame");
      Writer<somasim_wire_MeshFrame> writer(participant, topic, ReliableQos(partition));
      if (!PollUntil([&] { return writer.MatchedReaders() >= 1; }, milliseconds(4000))) return 2;
      std::vector<float> positions = MeshPositions();
      const std::string organ = "liver";
      somasim_wire_MeshFrame frame;
      std::memset(&frame, 0, sizeof(frame));
      frame.organ = CString(organ);
      frame.format_version = 1;
      frame.server_id = server_id;
      frame.frame = 7;
      frame.keyframe = true;
      frame.sim_time = 0.25;
      frame.topology_version = 1;
      frame.num_nodes = kMeshNodes;
      frame.positions._buffer = positions.data();
      frame.positions._length = static_cast<uint32_t>(positions.size());
      frame.positions._maximum = frame.positions._length;
      frame.positions._release = false;
      writer.Write(frame);
      return dds_wait_for_acks(writer.handle(), DDS_SECS(3)) == DDS_RETCODE_OK ? 0 : 3;
    }
    return 4;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "dds_test child: %s\n", e.what());
    return 1;
  }
}

// Runs before main when this executable was started as the child, and never returns then (so the
// child runs no tests and prints no gtest output).
[[maybe_unused]] const bool kIsChild = [] {
  const char* spec = std::getenv(kChildEnv);
  if (spec == nullptr) return false;
  std::_Exit(RunChild(spec));
}();

// This executable re-run as the child; killed by the destructor if the test ends before it did.
class ChildProcess {
 public:
  explicit ChildProcess(const std::string& spec) {
    std::vector<std::string> env;
    for (char** e = environ; *e != nullptr; ++e) env.emplace_back(*e);
    env.push_back(std::string(kChildEnv) + "=" + spec);
    std::vector<char*> envp;
    envp.reserve(env.size() + 1);
    for (std::string& e : env) envp.push_back(e.data());
    envp.push_back(nullptr);
    std::string exe = "/proc/self/exe";
    char* argv[] = {exe.data(), nullptr};
    const int err = posix_spawn(&pid_, "/proc/self/exe", nullptr, nullptr, argv, envp.data());
    if (err != 0) pid_ = -1;
  }
  ~ChildProcess() {
    if (pid_ > 0) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
  }
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;
  pid_t pid() const { return pid_; }
  // The child's exit code, or -1 when it did not exit normally within `timeout`.
  int Wait(milliseconds timeout) {
    int status = 0;
    const bool exited = PollUntil([&] { return waitpid(pid_, &status, WNOHANG) == pid_; }, timeout);
    if (!exited) return -1;
    pid_ = -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  }

 private:
  pid_t pid_ = -1;
};

std::string ReadDeployFile(const std::string& name) {
  // The deploy profiles live at ${PROJECT_SOURCE_DIR}/deploy (not found through __FILE__, which
  // a compiler launcher may make relative to the build tree).
  const std::filesystem::path path = std::filesystem::path(SOMASIM_DEPLOY_DIR) / name;
  std::ifstream file(path);
  std::stringstream text;
  text << file.rdbuf();
  return text.str();
}

// --- Tests ---------------------------------------------------------------------------------------

TEST(DdsPubSub, HeartbeatArrivesFieldByFieldInItsPartition) {
  const Domain domain(100, LoopbackConfig());
  const Participant pub_participant(100);
  const Participant sub_participant(100);
  const Topic<somasim_wire_Heartbeat> pub_topic(pub_participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat");
  const Topic<somasim_wire_Heartbeat> sub_topic(sub_participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat");
  Writer<somasim_wire_Heartbeat> writer(pub_participant, pub_topic, ReliableQos("session-a"));
  Reader<somasim_wire_Heartbeat> reader(sub_participant, sub_topic, ReliableQos("session-a"));
  ASSERT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 1; }, milliseconds(3000)));

  somasim_wire_Heartbeat sent = MakeHeartbeat(0x0123456789abcdefULL, 42);
  sent.sim_time = 12.625;
  sent.state = 3;
  writer.Write(sent);
  ASSERT_TRUE(reader.WaitForData(milliseconds(3000)));
  const std::vector<somasim_wire_Heartbeat> got = TakeHeartbeats(reader);
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].format_version, 1u);
  EXPECT_EQ(got[0].server_id, 0x0123456789abcdefULL);
  EXPECT_EQ(got[0].seq, 42u);
  EXPECT_EQ(got[0].sim_time, 12.625);
  EXPECT_EQ(got[0].state, 3u);
  EXPECT_EQ(reader.Status().matched_writers, 1);
  // Taken samples are gone, and WaitForData says so after its timeout.
  EXPECT_FALSE(reader.WaitForData(milliseconds(20)));
  EXPECT_EQ(reader.Take([](const somasim_wire_Heartbeat&, const dds_sample_info_t&) {}), 0);
}

TEST(DdsPubSub, TwoPartitionsOnOneDomainNeverSeeEachOther) {
  const Domain domain(101, LoopbackConfig());
  const Participant participant(101);
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat");
  Writer<somasim_wire_Heartbeat> writer_a(participant, topic, ReliableQos("session-a"));
  Writer<somasim_wire_Heartbeat> writer_b(participant, topic, ReliableQos("session-b"));
  Reader<somasim_wire_Heartbeat> reader_a(participant, topic, ReliableQos("session-a"));
  Reader<somasim_wire_Heartbeat> reader_b(participant, topic, ReliableQos("session-b"));
  ASSERT_TRUE(PollUntil([&] { return writer_a.MatchedReaders() >= 1; }, milliseconds(3000)));
  ASSERT_TRUE(PollUntil([&] { return writer_b.MatchedReaders() >= 1; }, milliseconds(3000)));

  for (uint64_t seq = 1; seq <= 3; ++seq) {
    writer_a.Write(MakeHeartbeat(0xa, seq));
    writer_b.Write(MakeHeartbeat(0xb, seq));
  }
  std::vector<somasim_wire_Heartbeat> got_a;
  std::vector<somasim_wire_Heartbeat> got_b;
  PollUntil(
      [&] {
        for (const auto& h : TakeHeartbeats(reader_a)) got_a.push_back(h);
        for (const auto& h : TakeHeartbeats(reader_b)) got_b.push_back(h);
        return got_a.size() >= 3 && got_b.size() >= 3;
      },
      milliseconds(3000));
  // Anything crossing over would arrive with the samples of the reader's own partition.
  std::this_thread::sleep_for(milliseconds(50));
  for (const auto& h : TakeHeartbeats(reader_a)) got_a.push_back(h);
  for (const auto& h : TakeHeartbeats(reader_b)) got_b.push_back(h);
  ASSERT_EQ(got_a.size(), 3u);
  ASSERT_EQ(got_b.size(), 3u);
  for (const auto& h : got_a) EXPECT_EQ(h.server_id, 0xau);
  for (const auto& h : got_b) EXPECT_EQ(h.server_id, 0xbu);
  EXPECT_EQ(writer_a.MatchedReaders(), 1);
  EXPECT_EQ(writer_b.MatchedReaders(), 1);
  EXPECT_EQ(reader_a.Status().matched_writers, 1);
}

TEST(DdsPubSub, LateReaderGetsEveryOrgansNewestTopologyFromTransientLocal) {
  const Domain domain(102, LoopbackConfig());
  const Participant pub_participant(102);
  const Participant sub_participant(102);
  // The topology topic's QoS (idl/mesh.idl): reliable, transient-local, keep-last 1 per organ,
  // with a durability service for the late joiners.
  const Qos qos = Qos()
                      .Reliable(milliseconds(1000))
                      .TransientLocal()
                      .KeepLast(1)
                      .DurabilityService(1, 16)
                      .Partition("session-a");
  const Topic<somasim_wire_OrganTopology> pub_topic(
      pub_participant, somasim_wire_OrganTopology_desc, "test_topology", qos);
  Writer<somasim_wire_OrganTopology> writer(pub_participant, pub_topic, qos);
  const std::string organs[] = {"liver", "gallbladder"};
  for (uint32_t version = 1; version <= 3; ++version) {
    for (const std::string& organ : organs) {
      somasim_wire_OrganTopology t;
      std::memset(&t, 0, sizeof(t));
      t.organ = CString(organ);
      t.format_version = 1;
      t.version = version;
      t.num_nodes = static_cast<uint32_t>(organ.size());
      writer.Write(t);
    }
  }

  // Only now does a reader exist (in another participant).
  const Topic<somasim_wire_OrganTopology> sub_topic(
      sub_participant, somasim_wire_OrganTopology_desc, "test_topology", qos);
  Reader<somasim_wire_OrganTopology> reader(sub_participant, sub_topic, qos);
  std::vector<std::pair<std::string, uint32_t>> got;
  PollUntil(
      [&] {
        reader.Take([&got](const somasim_wire_OrganTopology& t, const dds_sample_info_t&) {
          got.emplace_back(t.organ, t.version);
        });
        return got.size() >= 2;
      },
      milliseconds(3000));
  std::this_thread::sleep_for(milliseconds(50));  // older versions would follow now
  reader.Take([&got](const somasim_wire_OrganTopology& t, const dds_sample_info_t&) {
    got.emplace_back(t.organ, t.version);
  });
  ASSERT_EQ(got.size(), 2u);
  std::sort(got.begin(), got.end());
  EXPECT_EQ(got[0], std::make_pair(std::string("gallbladder"), 3u));
  EXPECT_EQ(got[1], std::make_pair(std::string("liver"), 3u));
}

TEST(DdsQos, DeadlineMissedGrowsWhenTheWriterStopsButNotWhileItWrites) {
  const Domain domain(103, LoopbackConfig());
  const Participant participant(103);
  // Requested deadline must be >= offered deadline for the two to match.
  const Qos qos = Qos()
                      .Reliable(milliseconds(1000))
                      .KeepLast(1)
                      .Deadline(milliseconds(100))
                      .Partition("session-a");
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat", qos);
  Writer<somasim_wire_Heartbeat> writer(participant, topic, qos);
  Reader<somasim_wire_Heartbeat> reader(participant, topic, qos);
  ASSERT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 1; }, milliseconds(3000)));

  // Writing every 20 ms (5 per deadline period) misses nothing.
  for (uint64_t seq = 1; seq <= 15; ++seq) {
    writer.Write(MakeHeartbeat(1, seq));
    std::this_thread::sleep_for(milliseconds(20));
  }
  TakeHeartbeats(reader);
  const uint32_t while_writing = reader.Status().deadline_missed;
  EXPECT_EQ(while_writing, 0u);

  // Silent for 3+ periods: one miss per period.
  const auto stopped = Clock::now();
  ASSERT_TRUE(PollUntil([&] { return reader.Status().deadline_missed >= while_writing + 3; },
                        milliseconds(2000)));
  const auto elapsed = std::chrono::duration_cast<milliseconds>(Clock::now() - stopped).count();
  EXPECT_GE(elapsed, 250) << "3 misses of a 100 ms deadline came too early";
  // The count is cumulative: reading it again does not reset it.
  EXPECT_GE(reader.Status().deadline_missed, while_writing + 3);
}

// Liveliness in one process: participants of one domain share its Cyclone instance.
TEST(DdsQos, ManualLivelinessWriterThatStopsBecomesNotAliveWithinItsLease) {
  if (testing::kUnderSanitizer) GTEST_SKIP() << "a timing deadline: run in the Release build";
  const Domain domain(104, LoopbackConfig());
  const Participant pub_participant(104);
  const Participant sub_participant(104);
  const Qos qos = Qos()
                      .Reliable(milliseconds(1000))
                      .KeepLast(1)
                      .ManualLiveliness(kTestLease)
                      .Partition("session-a");
  const Topic<somasim_wire_Heartbeat> pub_topic(pub_participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat", qos);
  const Topic<somasim_wire_Heartbeat> sub_topic(sub_participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat", qos);
  Writer<somasim_wire_Heartbeat> writer(pub_participant, pub_topic, qos);
  Reader<somasim_wire_Heartbeat> reader(sub_participant, sub_topic, qos);
  ASSERT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 1; }, milliseconds(3000)));

  writer.Write(MakeHeartbeat(1, 1));
  ASSERT_TRUE(PollUntil([&] { return reader.Status().alive_writers == 1; }, milliseconds(1000)));
  const auto last_write = Clock::now();
  ASSERT_TRUE(PollUntil(
      [&] {
        const ReaderStatus s = reader.Status();
        return s.alive_writers == 0 && s.not_alive_writers == 1;
      },
      milliseconds(2000)));
  const auto elapsed = std::chrono::duration_cast<milliseconds>(Clock::now() - last_write).count();
  std::printf("not alive %lld ms after the last write (lease %lld ms)\n",
              static_cast<long long>(elapsed), static_cast<long long>(kTestLease.count()));
  EXPECT_GE(elapsed, kTestLease.count() * 3 / 4) << "declared not alive before its lease ran out";

  // A new write makes it alive again.
  writer.Write(MakeHeartbeat(1, 2));
  EXPECT_TRUE(PollUntil([&] { return reader.Status().alive_writers == 1; }, milliseconds(1000)));
}

TEST(DdsQos, AssertLivelinessKeepsAManualWriterAliveWithoutWriting) {
  if (testing::kUnderSanitizer) GTEST_SKIP() << "a timing deadline: run in the Release build";
  const Domain domain(105, LoopbackConfig());
  const Participant pub_participant(105);
  const Participant sub_participant(105);
  const Qos qos = Qos()
                      .Reliable(milliseconds(1000))
                      .KeepLast(1)
                      .ManualLiveliness(kTestLease)
                      .Partition("session-a");
  const Topic<somasim_wire_Heartbeat> pub_topic(pub_participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat", qos);
  const Topic<somasim_wire_Heartbeat> sub_topic(sub_participant, somasim_wire_Heartbeat_desc,
                                                "test_heartbeat", qos);
  Writer<somasim_wire_Heartbeat> writer(pub_participant, pub_topic, qos);
  Reader<somasim_wire_Heartbeat> reader(sub_participant, sub_topic, qos);
  ASSERT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 1; }, milliseconds(3000)));
  writer.Write(MakeHeartbeat(1, 1));
  ASSERT_TRUE(PollUntil([&] { return reader.Status().alive_writers == 1; }, milliseconds(1000)));

  // Two leases' worth of asserting every 50 ms, no writes.
  for (int i = 0; i < 20; ++i) {
    writer.AssertLiveliness();
    std::this_thread::sleep_for(milliseconds(50));
    const ReaderStatus s = reader.Status();
    ASSERT_EQ(s.alive_writers, 1) << "after " << (i + 1) * 50 << " ms of asserting";
    ASSERT_EQ(s.not_alive_writers, 0);
  }
  // Stopping shows that the asserting was what kept it alive.
  EXPECT_TRUE(
      PollUntil([&] { return reader.Status().not_alive_writers == 1; }, milliseconds(2000)));
}

TEST(DdsCrossProcess, ChildProcessHeartbeatsReachThisProcessOverLoopback) {
  const Domain domain(106, LoopbackConfig());
  const Participant participant(106);
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat");
  Reader<somasim_wire_Heartbeat> reader(participant, topic, ReliableQos("session-x"));
  ChildProcess child("106 session-x heartbeat");
  ASSERT_GT(child.pid(), 0);

  std::vector<somasim_wire_Heartbeat> got;
  PollUntil(
      [&] {
        if (reader.WaitForData(milliseconds(50))) {
          for (const auto& h : TakeHeartbeats(reader)) got.push_back(h);
        }
        return got.size() >= 5;
      },
      milliseconds(5000));
  ASSERT_EQ(got.size(), 5u);
  for (size_t i = 0; i < got.size(); ++i) {
    EXPECT_EQ(got[i].seq, i + 1);
    EXPECT_EQ(got[i].server_id, static_cast<uint64_t>(child.pid())) << "not the child's sample";
  }
  EXPECT_EQ(child.Wait(milliseconds(4000)), 0);
}

// What the server's clients rely on: a manual-by-topic writer in another process stays alive
// while it asserts liveliness without writing, and is reported not alive about one lease after it
// falls silent, while its process (and its participant) still run.
void CheckCrossProcessLiveliness(uint32_t domain_id, bool reliable) {
  if (testing::kUnderSanitizer) GTEST_SKIP() << "a timing deadline: run in the Release build";
  const Domain domain(domain_id, LoopbackConfig());
  const Participant participant(domain_id);
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat");
  Reader<somasim_wire_Heartbeat> reader(participant, topic, LivelinessQos("session-x", reliable));
  ChildProcess child(std::to_string(domain_id) + " session-x " +
                     (reliable ? "liveliness-reliable" : "liveliness-besteffort"));
  ASSERT_GT(child.pid(), 0);

  bool saw_alive = false;
  bool got_mark = false;
  int not_alive_before_mark = 0;
  Clock::time_point mark_time;
  const bool marked = PollUntil(
      [&] {
        const ReaderStatus s = reader.Status();
        saw_alive = saw_alive || s.alive_writers == 1;
        if (saw_alive && s.not_alive_writers > 0) ++not_alive_before_mark;
        reader.Take([&](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) {
          if (h.seq == 2) got_mark = true;
        });
        return got_mark;
      },
      milliseconds(4000));
  mark_time = Clock::now();
  ASSERT_TRUE(marked) << "the child's seq 2 never arrived";
  EXPECT_TRUE(saw_alive);
  EXPECT_EQ(not_alive_before_mark, 0) << "not alive while the child asserted liveliness";
  ASSERT_TRUE(PollUntil(
      [&] {
        const ReaderStatus s = reader.Status();
        return s.alive_writers == 0 && s.not_alive_writers == 1;
      },
      milliseconds(2000)))
      << "still alive after the child fell silent";
  const auto elapsed = std::chrono::duration_cast<milliseconds>(Clock::now() - mark_time).count();
  std::printf(
      "%s writer in another process: not alive %lld ms after its last write "
      "(lease %lld ms)\n",
      reliable ? "reliable" : "best-effort", static_cast<long long>(elapsed),
      static_cast<long long>(kTestLease.count()));
  EXPECT_GE(elapsed, kTestLease.count() / 2) << "declared not alive well before its lease ran out";
  EXPECT_EQ(reader.Status().matched_writers, 1) << "the child's writer should still exist";
  EXPECT_EQ(child.Wait(milliseconds(4000)), 0);
}

TEST(DdsCrossProcess, BestEffortManualLivelinessLapsesOneLeaseAfterSilenceNotBefore) {
  CheckCrossProcessLiveliness(115, false);
}

TEST(DdsCrossProcess, ReliableManualLivelinessLapsesOneLeaseAfterSilenceNotBefore) {
  CheckCrossProcessLiveliness(116, true);
}

TEST(DdsCrossProcess, A65kBMeshFrameArrivesIntactInFragments) {
  const Domain domain(107, LoopbackConfig());
  const Participant participant(107);
  const Topic<somasim_wire_MeshFrame> topic(participant, somasim_wire_MeshFrame_desc, "test_frame");
  Reader<somasim_wire_MeshFrame> reader(participant, topic, ReliableQos("session-x"));
  ChildProcess child("107 session-x mesh");
  ASSERT_GT(child.pid(), 0);

  int frames = 0;
  std::string organ;
  uint64_t frame_number = 0;
  bool keyframe = false;
  uint32_t num_nodes = 0;
  uint32_t num_indices = 1;
  std::vector<float> positions;
  PollUntil(
      [&] {
        if (reader.WaitForData(milliseconds(50))) {
          frames += reader.Take([&](const somasim_wire_MeshFrame& f, const dds_sample_info_t&) {
            organ = f.organ;
            frame_number = f.frame;
            keyframe = f.keyframe;
            num_nodes = f.num_nodes;
            num_indices = f.indices._length;
            positions.assign(f.positions._buffer, f.positions._buffer + f.positions._length);
          });
        }
        return frames >= 1;
      },
      milliseconds(5000));
  ASSERT_EQ(frames, 1);
  EXPECT_EQ(organ, "liver");
  EXPECT_EQ(frame_number, 7u);
  EXPECT_TRUE(keyframe);
  EXPECT_EQ(num_nodes, kMeshNodes);
  EXPECT_EQ(num_indices, 0u);
  const std::vector<float> expected = MeshPositions();
  ASSERT_EQ(positions.size(), expected.size());
  EXPECT_EQ(std::memcmp(positions.data(), expected.data(), expected.size() * sizeof(float)), 0);
  EXPECT_EQ(reader.Status().samples_lost, 0u);
  EXPECT_EQ(child.Wait(milliseconds(4000)), 0);
}

TEST(DdsPubSub, TakeHonoursMaxAndLoopsPastItsStackBatch) {
  const Domain domain(111, LoopbackConfig());
  const Participant participant(111);
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat");
  Writer<somasim_wire_Heartbeat> writer(participant, topic, ReliableQos("session-a"));
  Reader<somasim_wire_Heartbeat> reader(participant, topic, ReliableQos("session-a"));
  ASSERT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 1; }, milliseconds(3000)));
  for (uint64_t seq = 1; seq <= 150; ++seq) writer.Write(MakeHeartbeat(1, seq));
  // Local delivery is synchronous in Cyclone, but do not rely on it.
  std::this_thread::sleep_for(milliseconds(20));

  std::vector<uint64_t> seqs;
  const auto collect = [&seqs](const somasim_wire_Heartbeat& h, const dds_sample_info_t& info) {
    EXPECT_TRUE(info.valid_data);
    seqs.push_back(h.seq);
  };
  EXPECT_EQ(reader.Take(collect, 10), 10);
  EXPECT_EQ(reader.Take(collect, 100), 100);  // two batches: 64 + 36
  EXPECT_EQ(reader.Take(collect, 100), 40);   // what is left
  EXPECT_EQ(reader.Take(collect, 100), 0);
  ASSERT_EQ(seqs.size(), 150u);
  for (size_t i = 0; i < seqs.size(); ++i) EXPECT_EQ(seqs[i], i + 1) << "oldest first";
}

// Take, WaitForData and Status are called every tick by the server and the viewer: the wrapper
// adds no C++ heap allocation to Cyclone's own (which is C and not counted here).
TEST(DdsPubSub, TakeWaitAndStatusAllocateNothingOnTheCppHeap) {
  const Domain domain(117, LoopbackConfig());
  const Participant participant(117);
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat");
  Writer<somasim_wire_Heartbeat> writer(participant, topic, ReliableQos("session-a"));
  Reader<somasim_wire_Heartbeat> reader(participant, topic, ReliableQos("session-a"));
  ASSERT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 1; }, milliseconds(3000)));
  for (uint64_t seq = 1; seq <= 100; ++seq) writer.Write(MakeHeartbeat(1, seq));
  ASSERT_TRUE(reader.WaitForData(milliseconds(1000)));

  uint64_t seq_sum = 0;
  int taken = 0;
  int64_t allocations = 0;
  {
    const testing::AllocationCounter counter;
    const bool ready = reader.WaitForData(milliseconds(0));
    taken = reader.Take(
        [&seq_sum](const somasim_wire_Heartbeat& h, const dds_sample_info_t&) { seq_sum += h.seq; },
        100);
    const ReaderStatus status = reader.Status();
    (void)ready;
    (void)status;
    allocations = counter.count();
  }
  EXPECT_EQ(taken, 100);
  EXPECT_EQ(seq_sum, 5050u);
  EXPECT_EQ(allocations, 0);
}

TEST(DdsPubSub, WriterCountsItsMatchedReaders) {
  const Domain domain(112, LoopbackConfig());
  const Participant participant(112);
  const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc,
                                            "test_heartbeat");
  Writer<somasim_wire_Heartbeat> writer(participant, topic, ReliableQos("session-a"));
  EXPECT_EQ(writer.MatchedReaders(), 0);
  {
    Reader<somasim_wire_Heartbeat> reader1(participant, topic, ReliableQos("session-a"));
    Reader<somasim_wire_Heartbeat> reader2(participant, topic, ReliableQos("session-a"));
    Reader<somasim_wire_Heartbeat> other(participant, topic, ReliableQos("session-b"));
    EXPECT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 2; }, milliseconds(3000)));
    std::this_thread::sleep_for(milliseconds(50));
    EXPECT_EQ(writer.MatchedReaders(), 2) << "the other partition's reader must not count";
  }
  EXPECT_TRUE(PollUntil([&] { return writer.MatchedReaders() == 0; }, milliseconds(3000)));
}

// Expects Domain(domain_id, xml) to throw a DdsError whose message has `needle`.
void ExpectDomainThrows(uint32_t domain_id, const std::string& xml, const std::string& needle) {
  try {
    const Domain domain(domain_id, xml);
    ADD_FAILURE() << "accepted: " << xml;
  } catch (const DdsError& e) {
    EXPECT_NE(
        std::string(e.what()).find("dds_create_domain(domain " + std::to_string(domain_id) + ")"),
        std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
}

TEST(DdsErrors, MalformedConfigurationXmlThrowsNamingTheConfiguration) {
  // Truncated: Cyclone itself would close the open elements and accept it.
  ExpectDomainThrows(108, "<CycloneDDS><Domain id=\"any\"><General>", "truncated");
  ExpectDomainThrows(108, "<CycloneDDS><Domain", "truncated");
  // What Cyclone's parser rejects.
  ExpectDomainThrows(108, "<CycloneDDS><Domain id=\"any\"></General></Domain></CycloneDDS>",
                     "tag mismatch");
  ExpectDomainThrows(108, "<CycloneDDS><Domain id=\"any\"><NoSuchElement/></Domain></CycloneDDS>",
                     "NoSuchElement: unknown element");
  ExpectDomainThrows(108,
                     "<CycloneDDS><Domain id=\"any\"><General><AllowMulticast>maybe"
                     "</AllowMulticast></General></Domain></CycloneDDS>",
                     "'maybe'");
  ExpectDomainThrows(108,
                     "<CycloneDDS><Domain id=\"any\"><General><Interfaces><NetworkInterface "
                     "name=\"no_such_if9\"/></Interfaces></General></Domain></CycloneDDS>",
                     "no_such_if9: does not match an available interface");
  // Text that is not XML is a file name to Cyclone.
  ExpectDomainThrows(108, "no/such/cyclonedds.xml",
                     "can't open configuration file no/such/cyclonedds.xml");
  // Nothing was left behind: the id is still free.
  EXPECT_NO_THROW(Domain(108, LoopbackConfig()));
}

TEST(DdsErrors, AnEmptyConfigurationReadsCycloneddsUri) {
  const char* saved = std::getenv("CYCLONEDDS_URI");
  const std::string saved_value = saved != nullptr ? saved : "";
  setenv("CYCLONEDDS_URI", "no/such/uri_file.xml", 1);
  ExpectDomainThrows(118, "", "can't open configuration file no/such/uri_file.xml");
  if (saved != nullptr) {
    setenv("CYCLONEDDS_URI", saved_value.c_str(), 1);
  } else {
    unsetenv("CYCLONEDDS_URI");
  }
}

TEST(DdsErrors, ASecondDomainWithTheSameIdThrowsPreconditionNotMet) {
  const Domain domain(109, LoopbackConfig());
  try {
    const Domain again(109, LoopbackConfig());
    FAIL() << "a second domain 109 was created";
  } catch (const DdsError& e) {
    EXPECT_EQ(e.code(), DDS_RETCODE_PRECONDITION_NOT_MET);
    EXPECT_NE(std::string(e.what()).find("already exists"), std::string::npos) << e.what();
  }
}

TEST(DdsErrors, ADomainAfterAParticipantOfItsIdThrowsPreconditionNotMet) {
  // The participant creates domain 119 implicitly, from CYCLONEDDS_URI (loopback here, so
  // nothing reaches the real network).
  const char* saved = std::getenv("CYCLONEDDS_URI");
  const std::string saved_value = saved != nullptr ? saved : "";
  setenv("CYCLONEDDS_URI", LoopbackConfig().c_str(), 1);
  {
    const Participant participant(119);
    try {
      const Domain domain(119, LoopbackConfig());
      ADD_FAILURE() << "a domain was created under an existing participant's";
    } catch (const DdsError& e) {
      EXPECT_EQ(e.code(), DDS_RETCODE_PRECONDITION_NOT_MET) << e.what();
    }
  }
  if (saved != nullptr) {
    setenv("CYCLONEDDS_URI", saved_value.c_str(), 1);
  } else {
    unsetenv("CYCLONEDDS_URI");
  }
}

TEST(DdsErrors, BadTopicsAndConfigArgumentsThrow) {
  const Domain domain(110, LoopbackConfig());
  const Participant participant(110);
  try {
    const Topic<somasim_wire_Heartbeat> topic(participant, somasim_wire_Heartbeat_desc, "");
    FAIL() << "an empty topic name was accepted";
  } catch (const DdsError& e) {
    EXPECT_EQ(e.code(), DDS_RETCODE_BAD_PARAMETER);
    EXPECT_NE(std::string(e.what()).find("empty topic name"), std::string::npos) << e.what();
  }
  // A descriptor of another type than T.
  EXPECT_THROW(Topic<somasim_wire_Heartbeat>(participant, somasim_wire_MeshFrame_desc, "x"),
               DdsError);
  // Cyclone's own check: characters not allowed in a topic name.
  EXPECT_THROW(Topic<somasim_wire_Heartbeat>(participant, somasim_wire_Heartbeat_desc, "a b*"),
               DdsError);
  EXPECT_THROW(LoopbackConfig(0), DdsError);
  EXPECT_THROW(LoopbackConfig(1000), DdsError);
}

TEST(DdsQos, CopiesAreIndependent) {
  Qos a;
  a.Partition("session-a").KeepLast(3);
  Qos b(a);
  b.Partition("session-b");
  Qos c;
  c = b;
  const Qos& alias = c;
  c = alias;  // self-assignment keeps it
  char** names = nullptr;
  uint32_t n = 0;
  ASSERT_TRUE(dds_qget_partition(a.get(), &n, &names));
  ASSERT_EQ(n, 1u);
  EXPECT_STREQ(names[0], "session-a");
  for (uint32_t i = 0; i < n; ++i) dds_free(names[i]);
  dds_free(names);
  ASSERT_TRUE(dds_qget_partition(c.get(), &n, &names));
  ASSERT_EQ(n, 1u);
  EXPECT_STREQ(names[0], "session-b");
  for (uint32_t i = 0; i < n; ++i) dds_free(names[i]);
  dds_free(names);
  dds_history_kind_t kind;
  int32_t depth = 0;
  ASSERT_TRUE(dds_qget_history(c.get(), &kind, &depth));
  EXPECT_EQ(kind, DDS_HISTORY_KEEP_LAST);
  EXPECT_EQ(depth, 3);
}

TEST(DdsDeploy, LoopbackProfileCreatesAParticipant) {
  const std::string xml = ReadDeployFile("cyclonedds-loopback.xml");
  ASSERT_FALSE(xml.empty()) << "deploy/cyclonedds-loopback.xml not found";
  const Domain domain(113, xml);
  EXPECT_NO_THROW(Participant(113));
}

TEST(DdsDeploy, LabProfileCreatesAParticipantWithItsInterfaceSetToLo) {
  std::string xml = ReadDeployFile("cyclonedds-lab.xml");
  ASSERT_FALSE(xml.empty()) << "deploy/cyclonedds-lab.xml not found";
  const std::string placeholder = "name=\"eth0\"";
  const size_t at = xml.find(placeholder);
  ASSERT_NE(at, std::string::npos) << "the lab profile's interface placeholder moved";
  xml.replace(at, placeholder.size(), "name=\"lo\"");
  const Domain domain(114, xml);
  EXPECT_NO_THROW(Participant(114));
}

}  // namespace
}  // namespace somasim::dds
