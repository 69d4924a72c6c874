// The session recorder and replay (server/recording/): a session with probing, an incision
// and a reset, recorded as the server does it, replays with every checkpoint bit for bit; a
// changed checkpoint is found as the first divergence; a truncated recording replays up to its
// last good record; a full queue becomes a Gap record; a full disk stops the recording and says
// so without disturbing the session; the physics thread's calls allocate nothing.
#include "server/recording/recorder.h"

#include <gtest/gtest.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include "common/recording/recording_file.h"
#include "server/recording/replay.h"
#include "tests/support/allocation_counter.h"
#include "tests/support/full_disk_sink.h"
#include "tests/support/temp_files.h"

namespace somasim::server {
namespace {

// `name` in this process's folder (removed when the test passes), no file there yet.
std::string TempPath(const std::string& name) {
  const std::string dir = somasim::testing::ProcessTempDir("somasim-session-recording");
  std::string path = dir + "/" + name;
  std::filesystem::remove(path);
  return path;
}

std::unique_ptr<recording::Sink> FileSink(const std::string& path) {
  std::string error;
  auto sink = recording::CreateFileSink(path, &error);
  EXPECT_NE(sink, nullptr) << error;
  return sink;
}

// What the server's physics thread does each tick, with a recorder: commands applied and
// recorded before the step, events and checkpoints after it.
struct Driver {
  Session& session;
  Recorder& recorder;
  uint64_t steps = 0;
  uint64_t interval = 25;
  void Command(int32_t tool, const ToolCommandInput& c) {
    session.SetToolCommand(tool, c);
    recorder.ToolCommand(steps, session.time(), tool, c);
  }
  void Reset() {
    session.Reset();
    for (const SessionEventRecord& e : session.TakeEvents())
      recorder.Event(steps, session.time(), e);
  }
  void Step() {
    session.Step();
    ++steps;
    for (const SessionEventRecord& e : session.TakeEvents())
      recorder.Event(steps, session.time(), e);
    if (steps % interval == 0) recorder.Checkpoint(steps, session.time(), session);
  }
};

ToolCommandInput At(const Eigen::Vector3d& tip, uint32_t buttons, uint64_t seq) {
  ToolCommandInput c;
  c.pose.tip = tip;
  c.buttons = buttons;
  c.sequence = seq;
  return c;
}

// Probing the kidney's top, an incision across it, a reset, probing again: 200 steps.
void PlayScenario(Driver* d) {
  Session& s = d->session;
  const int32_t probe = s.ToolIndex("probe"), scalpel = s.ToolIndex("scalpel");
  const Eigen::Vector3d top(0.0, 0.0, 0.0224);
  uint64_t seq = 0;
  for (int i = 0; i < 40; ++i) {
    d->Command(probe, At(top + Eigen::Vector3d(0, 0, 0.004 - 0.0002 * i), 0, ++seq));
    d->Step();
  }
  d->Command(probe, At(top + Eigen::Vector3d(0, 0, 0.05), 0, ++seq));
  for (int i = 0; i <= 80; ++i) {
    const double u = i / 80.0;
    d->Command(scalpel, At(top + Eigen::Vector3d(-0.02 + 0.04 * u, 0.0, -0.006), 4, ++seq));
    d->Step();
  }
  d->Command(scalpel, At(top + Eigen::Vector3d(0.03, 0.0, 0.03), 0, ++seq));
  for (int i = 0; i < 20; ++i) d->Step();
  d->Reset();
  for (int i = 0; i < 59; ++i) {
    d->Command(probe, At(top + Eigen::Vector3d(0.005, 0, 0.002 - 0.0002 * i), 0, ++seq));
    d->Step();
  }
}

std::string RecordScenario(const std::string& name, uint64_t* steps) {
  std::string path = TempPath(name);
  Session session(ServerDefaultScene("kidney424"), scene::SceneLines("kidney"), ".");
  Recorder recorder(FileSink(path), Recorder::MakeHeader(session, ".", "rec", "trainee-07", "test"),
                    session);
  Driver d{session, recorder};
  PlayScenario(&d);
  EXPECT_GT(session.organ(0).topology_version, 1U) << "the scenario cut nothing";
  recorder.Finish(d.steps, "done");
  EXPECT_FALSE(recorder.failed()) << recorder.stats().error;
  *steps = d.steps;
  return path;
}

TEST(Replay, ARecordedSessionReplaysBitForBit) {
  uint64_t steps = 0;
  const std::string path = RecordScenario("scenario.somarec", &steps);
  const ReplayResult r = Replay(path);
  EXPECT_FALSE(r.diverged) << r.divergence;
  EXPECT_EQ(r.steps, steps);
  EXPECT_EQ(r.checkpoints_matched, steps / 25);  // one every 25 steps, the reset's included
  EXPECT_TRUE(r.ended_cleanly);
  EXPECT_FALSE(r.truncated);
  EXPECT_FALSE(r.gap);
  EXPECT_EQ(r.software_version, "test");
}

// Rewrites the recording at `path` with one position of its `which`-th checkpoint nudged by one
// unit in the last place.
std::string WithAChangedCheckpoint(const std::string& path, int which) {
  recording::Reader reader(path);
  std::string out = TempPath("changed.somarec");
  recording::Writer w(FileSink(out));
  EXPECT_TRUE(w.WriteHeader(reader.header()));
  recording::Record r;
  int seen = 0;
  while (reader.Next(&r)) {
    if (r.has_checkpoint() && seen++ == which) {
      double* x = r.mutable_checkpoint()->mutable_organs(0)->mutable_positions()->Mutable(30);
      *x = std::nextafter(*x, 1.0);
    }
    EXPECT_TRUE(w.WriteRecord(r));
  }
  return out;
}

TEST(Replay, TheFirstDivergenceIsFoundAndNamed) {
  uint64_t steps = 0;
  const std::string path = RecordScenario("diverge.somarec", &steps);
  const ReplayResult r = Replay(WithAChangedCheckpoint(path, 4));
  EXPECT_TRUE(r.diverged);
  EXPECT_EQ(r.checkpoints_matched, 4U);
  EXPECT_NE(r.divergence.find("step 125"), std::string::npos) << r.divergence;
  EXPECT_NE(r.divergence.find("node 10 position x"), std::string::npos) << r.divergence;
}

TEST(Replay, ATruncatedRecordingReplaysUpToItsLastGoodRecord) {
  uint64_t steps = 0;
  const std::string path = RecordScenario("whole.somarec", &steps);
  std::ifstream in(path, std::ios::binary);
  std::ostringstream read;
  read << in.rdbuf();
  const std::string bytes = read.str();
  const std::string cut = TempPath("cut.somarec");
  std::ofstream(cut, std::ios::binary) << bytes.substr(0, bytes.size() * 2 / 3 + 3);
  const ReplayResult r = Replay(cut);
  EXPECT_TRUE(r.truncated);
  EXPECT_FALSE(r.ended_cleanly);
  EXPECT_FALSE(r.diverged) << r.divergence;
  EXPECT_GT(r.steps, 50U);
  EXPECT_LT(r.steps, steps);
  EXPECT_LE(r.end_offset, bytes.size() * 2 / 3 + 3);
  EXPECT_GT(r.checkpoints_matched, 1U);
}

TEST(Recorder, AFullQueueBecomesAGapRecordNeverASilentHole) {
  const std::string path = TempPath("gap.somarec");
  Session session(ServerDefaultScene("kidney424"), scene::SceneLines("kidney"), ".");
  {
    Recorder recorder(FileSink(path), Recorder::MakeHeader(session, ".", "gap", "", "test"),
                      session, 4);
    // Far more than the queue holds, faster than the writer takes them.
    for (uint64_t i = 0; i < 20000; ++i) {
      recorder.ToolCommand(0, 0.0, 0, At(Eigen::Vector3d(0, 0, 0.05), 0, i));
    }
    recorder.Finish(0, "done");
    EXPECT_GT(recorder.stats().gaps, 0U);
    EXPECT_GT(recorder.stats().lost, 0U);
  }
  recording::Reader reader(path);
  recording::Record r;
  uint64_t commands = 0, lost = 0;
  while (reader.Next(&r)) {
    commands += r.has_tool_command() ? 1 : 0;
    lost += r.has_gap() ? r.gap().tool_commands() : 0;
  }
  EXPECT_EQ(commands + lost, 20000U) << "every command is either written or counted in a gap";
  const ReplayResult replay = Replay(path);
  EXPECT_TRUE(replay.gap);
}

TEST(Recorder, AFullDiskStopsTheRecordingAndSaysSoWhileTheSessionGoesOn) {
  Session session(ServerDefaultScene("kidney424"), scene::SceneLines("kidney"), ".");
  Recorder recorder(std::make_unique<testing::FullDiskSink>(60000),
                    Recorder::MakeHeader(session, ".", "full", "", "test"), session);
  Driver d{session, recorder};
  for (int i = 0; i < 200 && !recorder.failed(); ++i) {
    d.Step();
    if (i % 10 == 0) std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  for (int i = 0; i < 200 && !recorder.failed(); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_TRUE(recorder.failed());
  EXPECT_NE(recorder.stats().error.find("No space left"), std::string::npos)
      << recorder.stats().error;
  for (int i = 0; i < 20; ++i) d.Step();  // the session goes on
  recorder.Finish(d.steps, "done");
  EXPECT_TRUE(recorder.stats().failed);
  EXPECT_EQ(session.rejected_steps(), 0U);
}

TEST(Recorder, ThePhysicsThreadsCallsAllocateNothing) {
  const std::string path = TempPath("alloc.somarec");
  Session session(ServerDefaultScene("kidney424"), scene::SceneLines("kidney"), ".");
  Recorder recorder(FileSink(path), Recorder::MakeHeader(session, ".", "alloc", "", "test"),
                    session);
  const SessionEventRecord event{};
  int64_t allocations = 0;
  for (int i = 0; i < 50; ++i) {
    testing::AllocationCounter counter;
    recorder.ToolCommand(static_cast<uint64_t>(i), 0.0, 0,
                         At(Eigen::Vector3d(0, 0, 0.05), 0, static_cast<uint64_t>(i)));
    recorder.Event(static_cast<uint64_t>(i), 0.0, event);
    if (i % 10 == 0) recorder.Checkpoint(static_cast<uint64_t>(i), 0.0, session);
    allocations += counter.count();
  }
  EXPECT_EQ(allocations, 0);
  recorder.Finish(50, "done");
}

}  // namespace
}  // namespace somasim::server
