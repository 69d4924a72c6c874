// somasim-viewer (issue 8). Its receiver against samples this test writes on its own domain:
// good ones are shown, malformed ones (sizes, indices, NaN, format version, unknown topology
// version) are dropped and counted, a new server id forgets the old shapes. The program under
// Xvfb against a real somasim-server over Cyclone DDS on loopback: a screenshot has organ pixels
// where the organ is; a viewer that joins late shows exactly the server's last frame (its
// --dump-positions equals the server's --dump-final byte for byte); bad command lines are
// refused by name; an observe-only viewer has no writer on any topic; a station drives a tool
// without an arm; it lists the running sessions. Domains 193..199 (193 is also the
// viewer benchmark's: the two never run together).
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <thread>
#include <vector>

#include "common/dds/topics.h"
#include "tests/server/app/session_client.h"
#include "tests/support/sanitizer.h"
#include "viewer/scene_receiver.h"

namespace somasim::viewer {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;
using testing::LoopbackConfigFile;
using testing::ReadText;
using testing::StartProgram;
using testing::TempDir;

// ---- the receiver against hand-written samples ------------------------------------------------

template <typename T>
void SetSequence(T* seq, void* buffer, uint32_t length) {
  seq->_buffer = static_cast<decltype(seq->_buffer)>(buffer);
  seq->_length = length;
  seq->_maximum = length;
  seq->_release = false;
}

struct Samples {
  Samples() : domain(196, dds::LoopbackConfig()), participant(196), topics(participant) {}
  dds::Domain domain;
  dds::Participant participant;
  dds::Topics topics;
};

somasim_wire_OrganTopology Topology(const char* organ, uint64_t server, uint32_t version,
                                    std::vector<float>* rest, std::vector<uint32_t>* triangles,
                                    std::vector<uint8_t>* inner) {
  somasim_wire_OrganTopology t{};
  t.organ = const_cast<char*>(organ);
  t.format_version = dds::kWireFormatVersion;
  t.server_id = server;
  t.version = version;
  t.num_nodes = static_cast<uint32_t>(rest->size() / 3);
  SetSequence(&t.rest_positions, rest->data(), static_cast<uint32_t>(rest->size()));
  SetSequence(&t.triangles, triangles->data(), static_cast<uint32_t>(triangles->size()));
  SetSequence(&t.inner_face, inner->data(), static_cast<uint32_t>(inner->size()));
  return t;
}

somasim_wire_MeshFrame Keyframe(const char* organ, uint64_t server, uint32_t topology_version,
                                uint64_t frame, std::vector<float>* positions) {
  somasim_wire_MeshFrame f{};
  f.organ = const_cast<char*>(organ);
  f.format_version = dds::kWireFormatVersion;
  f.server_id = server;
  f.frame = frame;
  f.keyframe = true;
  f.topology_version = topology_version;
  f.num_nodes = static_cast<uint32_t>(positions->size() / 3);
  SetSequence(&f.positions, positions->data(), static_cast<uint32_t>(positions->size()));
  return f;
}

bool PollUntil(SceneReceiver* r, const std::function<bool()>& pred) {
  const auto end = std::chrono::steady_clock::now() + seconds(5);
  while (std::chrono::steady_clock::now() < end) {
    r->Poll();
    if (pred()) return true;
    std::this_thread::sleep_for(milliseconds(2));
  }
  return false;
}

TEST(SceneReceiver, ShowsGoodSamplesAndDropsAndCountsMalformedOnes) {
  Samples s;
  SceneReceiver r(s.participant, s.topics, "rx");
  dds::Writer<somasim_wire_SessionInfo> session(s.participant, s.topics.session,
                                                dds::SessionQos("rx"));
  dds::Writer<somasim_wire_OrganTopology> topology(s.participant, s.topics.topology,
                                                   dds::TopologyQos("rx"));
  dds::Writer<somasim_wire_MeshFrame> frames(s.participant, s.topics.frame, dds::FrameQos("rx"));
  // The session: one organ "a", from server 7.
  somasim_wire_OrganInfo organ{};
  organ.id = const_cast<char*>("a");
  somasim_wire_SessionInfo info{};
  info.format_version = dds::kWireFormatVersion;
  info.server_id = 7;
  info.scene_name = const_cast<char*>("hand-written");
  SetSequence(&info.organs, &organ, 1);
  session.Write(info);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.has_session(); }));
  EXPECT_EQ(r.server_id(), 7u);
  EXPECT_FALSE(r.complete());

  // Malformed topologies, each under its own organ key (so keep-last 1 keeps every one).
  std::vector<float> rest = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1};  // a tetrahedron's corners
  std::vector<uint32_t> tris = {0, 1, 2, 0, 1, 3};
  std::vector<uint8_t> inner = {0, 1};
  std::vector<uint32_t> out_of_range = {0, 1, 4, 0, 1, 3};
  std::vector<float> nan_rest = rest;
  nan_rest[4] = std::numeric_limits<float>::quiet_NaN();
  std::vector<uint8_t> short_inner = {0};
  topology.Write(Topology("bad-index", 7, 1, &rest, &out_of_range, &inner));
  topology.Write(Topology("bad-nan", 7, 1, &nan_rest, &tris, &inner));
  topology.Write(Topology("bad-marks", 7, 1, &rest, &tris, &short_inner));
  somasim_wire_OrganTopology bad_size = Topology("bad-size", 7, 1, &rest, &tris, &inner);
  bad_size.num_nodes = 5;  // rest holds 4
  topology.Write(bad_size);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.counters().bad_topologies == 4; }))
      << r.counters().bad_topologies;
  EXPECT_TRUE(r.organs().empty());

  // The good topology, then frames: one for a topology version not seen, one with a NaN, one
  // of another format version, one of an organ without topology; then a good keyframe.
  topology.Write(Topology("a", 7, 1, &rest, &tris, &inner));
  ASSERT_TRUE(PollUntil(&r, [&] { return r.organs().count("a") == 1; }));
  EXPECT_EQ(r.organs().at("a").triangles, tris);
  EXPECT_EQ(r.organs().at("a").inner_face, inner);
  std::vector<float> moved = rest;
  moved[0] = 0.25F;
  frames.Write(Keyframe("a", 7, 2, 1, &moved));  // topology version 2: not seen
  std::vector<float> nan = moved;
  nan[5] = std::numeric_limits<float>::infinity();
  frames.Write(Keyframe("a", 7, 1, 1, &nan));
  somasim_wire_MeshFrame old = Keyframe("a", 7, 1, 1, &moved);
  old.format_version = dds::kWireFormatVersion + 1;
  frames.Write(old);
  frames.Write(Keyframe("nobody", 7, 1, 1, &moved));
  ASSERT_TRUE(PollUntil(&r,
                        [&] {
                          return r.counters().frames_waiting_for_topology == 2 &&
                                 r.counters().bad_frames == 1 &&
                                 r.counters().wrong_format_version == 1;
                        }))
      << r.counters().frames_waiting_for_topology << " " << r.counters().bad_frames << " "
      << r.counters().wrong_format_version;
  EXPECT_FALSE(r.organs().at("a").has_shape());
  EXPECT_EQ(r.organs().at("a").positions()[0], 0.0F);  // the rest shape until a keyframe
  frames.Write(Keyframe("a", 7, 1, 2, &moved));
  ASSERT_TRUE(PollUntil(&r, [&] { return r.complete(); }));
  EXPECT_EQ(r.organs().at("a").positions()[0], 0.25F);
  EXPECT_EQ(std::vector<float>(r.organs().at("a").positions(),
                               r.organs().at("a").positions() + moved.size()),
            moved);

  // A new server id (a restart): the old shapes are forgotten until the new server's arrive.
  info.server_id = 8;
  session.Write(info);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.server_id() == 8u; }));
  EXPECT_EQ(r.counters().server_restarts, 1u);
  EXPECT_TRUE(r.organs().empty());
  EXPECT_FALSE(r.complete());
}

// ---- the program under Xvfb ---------------------------------------------------------------

// An Xvfb server on a free display number, DISPLAY set to it for the children started after.
class Xvfb {
 public:
  Xvfb() {
    for (int attempt = 0; attempt < 8 && !process_; ++attempt) {
      const int display = 300 + static_cast<int>((getpid() * 7 + attempt * 131) % 600);
      const std::string socket = "/tmp/.X11-unix/X" + std::to_string(display);
      if (std::filesystem::exists("/tmp/.X" + std::to_string(display) + "-lock")) continue;
      auto p = std::make_unique<app::ChildProcess>(
          std::vector<std::string>{"/usr/bin/Xvfb", ":" + std::to_string(display), "-screen", "0",
                                   "1024x768x24", "-nolisten", "tcp"},
          TempDir("xvfb") + "/xvfb.log");
      for (int i = 0; i < 500 && p->Wait(milliseconds(0)) == -1; ++i) {
        if (std::filesystem::exists(socket)) {
          display_ = ":" + std::to_string(display);
          setenv("DISPLAY", display_.c_str(), 1);
          process_ = std::move(p);
          break;
        }
        std::this_thread::sleep_for(milliseconds(10));
      }
    }
  }
  bool ok() const { return process_ != nullptr; }

 private:
  std::unique_ptr<app::ChildProcess> process_;
  std::string display_;
};

struct Png {
  int width = 0, height = 0;
  std::vector<uint8_t> rgb;  // top row first
};

uint32_t BigEndian(const unsigned char* p) {
  return (uint32_t{p[0]} << 24) | (uint32_t{p[1]} << 16) | (uint32_t{p[2]} << 8) | p[3];
}

// Decodes an 8-bit RGB, non-interlaced PNG (what render::EncodePng writes); empty on failure.
Png DecodePng(const std::string& bytes) {
  Png png;
  if (bytes.size() < 8 || bytes.compare(0, 8, "\x89PNG\r\n\x1a\n") != 0) return png;
  std::string idat;
  size_t at = 8;
  while (at + 12 <= bytes.size()) {
    const auto* p = reinterpret_cast<const unsigned char*>(bytes.data() + at);
    const uint32_t length = BigEndian(p);
    const std::string type = bytes.substr(at + 4, 4);
    if (at + 12 + length > bytes.size()) return {};
    if (type == "IHDR") {
      png.width = static_cast<int>(BigEndian(p + 8));
      png.height = static_cast<int>(BigEndian(p + 12));
      if (p[16] != 8 || p[17] != 2 || p[20] != 0) return {};
    } else if (type == "IDAT") {
      idat.append(bytes, at + 8, length);
    }
    at += 12 + length;
  }
  const size_t row = 3 * static_cast<size_t>(png.width);
  std::vector<uint8_t> raw((row + 1) * static_cast<size_t>(png.height));
  uLongf size = raw.size();
  if (png.width <= 0 ||
      uncompress(raw.data(), &size, reinterpret_cast<const Bytef*>(idat.data()), idat.size()) !=
          Z_OK ||
      size != raw.size()) {
    return {};
  }
  png.rgb.assign(row * static_cast<size_t>(png.height), 0);
  for (size_t y = 0; y < static_cast<size_t>(png.height); ++y) {
    const uint8_t filter = raw[y * (row + 1)];
    const uint8_t* in = raw.data() + y * (row + 1) + 1;
    uint8_t* out = png.rgb.data() + y * row;
    const uint8_t* up = y > 0 ? out - row : nullptr;
    for (size_t x = 0; x < row; ++x) {
      const int a = x >= 3 ? out[x - 3] : 0;
      const int b = up != nullptr ? up[x] : 0;
      const int c = (x >= 3 && up != nullptr) ? up[x - 3] : 0;
      int pred = 0;
      if (filter == 1) pred = a;
      if (filter == 2) pred = b;
      if (filter == 3) pred = (a + b) / 2;
      if (filter == 4) {
        const int pa = std::abs(b - c), pb = std::abs(a - c), pc = std::abs(a + b - 2 * c);
        pred = pa <= pb && pa <= pc ? a : (pb <= pc ? b : c);
      }
      out[x] = static_cast<uint8_t>(in[x] + pred);
    }
  }
  return png;
}

std::vector<std::string> ServerArgs(const std::string& session, uint32_t domain,
                                    std::vector<std::string> extra) {
  std::vector<std::string> args{"--scene",      "builtin:kidney424", "--session",
                                session,        "--domain",          std::to_string(domain),
                                "--dds-config", LoopbackConfigFile()};
  args.insert(args.end(), extra.begin(), extra.end());
  return args;
}

// Starts somasim-viewer. Under the sanitizers its leak check is off: Mesa's software driver,
// loaded and unloaded by libGL, leaks its own buffers at exit (allocated from a module already
// gone, so no suppression can name it); the viewer's own code is leak-checked in this process
// (SceneReceiver's test), and AddressSanitizer's other checks stay on.
std::unique_ptr<app::ChildProcess> StartViewer(const std::vector<std::string>& args,
                                               const std::string& log) {
  if (!somasim::testing::kUnderSanitizer) return StartProgram("somasim-viewer", args, log);
  const char* old = std::getenv("ASAN_OPTIONS");
  const std::string saved = old != nullptr ? old : "";
  setenv("ASAN_OPTIONS", (saved.empty() ? "" : saved + ":").append("detect_leaks=0").c_str(), 1);
  auto p = StartProgram("somasim-viewer", args, log);
  if (old != nullptr) {
    setenv("ASAN_OPTIONS", saved.c_str(), 1);
  } else {
    unsetenv("ASAN_OPTIONS");
  }
  return p;
}

std::vector<std::string> ViewerArgs(const std::string& session, uint32_t domain,
                                    std::vector<std::string> extra) {
  std::vector<std::string> args{"--session",    session,
                                "--domain",     std::to_string(domain),
                                "--dds-config", LoopbackConfigFile(),
                                "--width",      "320",
                                "--height",     "240"};
  args.insert(args.end(), extra.begin(), extra.end());
  return args;
}

TEST(ViewerProgram, ScreenshotHasOrganPixelsWhereTheOrganIs) {
  Xvfb x;
  ASSERT_TRUE(x.ok()) << "Xvfb did not start";
  const std::string dir = TempDir("shot");
  auto server = StartProgram("somasim-server", ServerArgs("shot", 197, {"--duration", "30"}),
                             dir + "/server.log");
  auto viewer = StartViewer(
      ViewerArgs("shot", 197,
                 {"--screenshot", dir + "/shot.png", "--after-frames", "10", "--timeout", "60"}),
      dir + "/viewer.log");
  ASSERT_EQ(viewer->Wait(seconds(90)), 0) << ReadText(dir + "/viewer.log");
  server->Signal(SIGTERM);
  EXPECT_EQ(server->Wait(seconds(20)), 0) << ReadText(dir + "/server.log");
  const Png png = DecodePng(ReadText(dir + "/shot.png"));
  ASSERT_EQ(png.width, 320);
  ASSERT_EQ(png.height, 240);
  // Organ pixels: reddish (the tissue colour lit by the headlight), far from the dark
  // background and from the grey heads-up text. The camera frames the organ, so they cover a
  // good part of the picture around its centre.
  int organ = 0;
  double cx = 0.0, cy = 0.0;
  for (int y = 0; y < png.height; ++y) {
    for (int xx = 0; xx < png.width; ++xx) {
      const uint8_t* p = png.rgb.data() + 3 * (static_cast<size_t>(y) * 320 + xx);
      if (p[0] > 60 && p[0] > p[1] + 30 && p[0] > p[2] + 30) {
        ++organ;
        cx += xx;
        cy += y;
      }
    }
  }
  ASSERT_GT(organ, 320 * 240 / 20) << "organ pixels: " << organ;
  EXPECT_LT(organ, 320 * 240 * 9 / 10);
  EXPECT_NEAR(cx / organ, 160.0, 40.0);
  EXPECT_NEAR(cy / organ, 120.0, 40.0);
}

std::vector<float> ReadFloats(const std::string& path) {
  const std::string bytes = ReadText(path);
  std::vector<float> out(bytes.size() / sizeof(float));
  std::memcpy(out.data(), bytes.data(), out.size() * sizeof(float));
  return out;
}

TEST(ViewerProgram, LateViewerShowsExactlyTheServersLastFrame) {
  Xvfb x;
  ASSERT_TRUE(x.ok()) << "Xvfb did not start";
  const std::string dir = TempDir("late");
  auto server =
      StartProgram("somasim-server", ServerArgs("late", 198, {"--dump-final", dir + "/server"}),
                   dir + "/server.log");
  std::this_thread::sleep_for(milliseconds(1500));  // the viewer joins late
  auto viewer = StartViewer(ViewerArgs("late", 198, {"--dump-positions", dir + "/viewer"}),
                            dir + "/viewer.log");
  // Until the viewer shows the whole scene (however slowly a loaded machine starts it), then a
  // little longer so that it follows deltas too.
  for (int i = 0;
       i < 3000 && ReadText(dir + "/viewer.log").find("scene_complete") == std::string::npos; ++i) {
    std::this_thread::sleep_for(milliseconds(10));
  }
  ASSERT_NE(ReadText(dir + "/viewer.log").find("scene_complete"), std::string::npos)
      << ReadText(dir + "/viewer.log");
  std::this_thread::sleep_for(milliseconds(1000));
  server->Signal(SIGTERM);  // the server's last frame is a keyframe
  ASSERT_EQ(server->Wait(seconds(20)), 0) << ReadText(dir + "/server.log");
  std::this_thread::sleep_for(milliseconds(1500));
  viewer->Signal(SIGTERM);
  ASSERT_EQ(viewer->Wait(seconds(20)), 0) << ReadText(dir + "/viewer.log");
  const std::string server_frame = ReadText(dir + "/server/kidney424.frame");
  ASSERT_FALSE(server_frame.empty());
  EXPECT_EQ(ReadText(dir + "/viewer/kidney424.frame"), server_frame)
      << ReadText(dir + "/viewer.log");
  const std::vector<float> expected = ReadFloats(dir + "/server/kidney424.f32");
  const std::vector<float> shown = ReadFloats(dir + "/viewer/kidney424.f32");
  ASSERT_EQ(shown.size(), expected.size());
  EXPECT_EQ(0, std::memcmp(shown.data(), expected.data(), shown.size() * sizeof(float)));
}

// Readers on every topic of a session, in the test's own participant.
struct AllTopics {
  AllTopics(uint32_t id, const std::string& session)
      : domain(id, dds::LoopbackConfig()),
        participant(id),
        topics(participant),
        session_info(participant, topics.session, dds::SessionQos(session)),
        topology(participant, topics.topology, dds::TopologyQos(session)),
        frame(participant, topics.frame, dds::FrameQos(session)),
        tool_command(participant, topics.tool_command, dds::ToolCommandQos(session)),
        force_model(participant, topics.force_model, dds::ForceModelQos(session)),
        event(participant, topics.event, dds::EventQos(session)),
        instructor(participant, topics.instructor, dds::InstructorQos(session)),
        heartbeat(participant, topics.heartbeat, dds::HeartbeatQos(session)),
        metrics(participant, topics.metrics, dds::MetricsQos(session)) {}
  // Writers matched on each topic, in Topics' order.
  std::vector<int32_t> Writers() {
    return {session_info.Status().matched_writers, topology.Status().matched_writers,
            frame.Status().matched_writers,        tool_command.Status().matched_writers,
            force_model.Status().matched_writers,  event.Status().matched_writers,
            instructor.Status().matched_writers,   heartbeat.Status().matched_writers,
            metrics.Status().matched_writers};
  }
  dds::Domain domain;
  dds::Participant participant;
  dds::Topics topics;
  dds::Reader<somasim_wire_SessionInfo> session_info;
  dds::Reader<somasim_wire_OrganTopology> topology;
  dds::Reader<somasim_wire_MeshFrame> frame;
  dds::Reader<somasim_wire_ToolCommand> tool_command;
  dds::Reader<somasim_wire_ForceModel> force_model;
  dds::Reader<somasim_wire_SessionEvent> event;
  dds::Reader<somasim_wire_InstructorCommand> instructor;
  dds::Reader<somasim_wire_Heartbeat> heartbeat;
  dds::Reader<somasim_wire_ServerMetrics> metrics;
};

bool WaitForLog(const std::string& path, const std::string& event) {
  for (int i = 0; i < 3000; ++i) {
    if (ReadText(path).find(event) != std::string::npos) return true;
    std::this_thread::sleep_for(milliseconds(10));
  }
  return false;
}

// An instructor's observe-only viewer, showing the session, has no writer on any topic: every
// topic has exactly the server's writers, and nothing arrives on the two the server never
// writes (tool and instructor commands).
TEST(ViewerProgram, ObserveOnlyPublishesNothing) {
  Xvfb x;
  ASSERT_TRUE(x.ok()) << "Xvfb did not start";
  const std::string dir = TempDir("observe");
  AllTopics all(194, "obs");
  auto server = StartProgram("somasim-server", ServerArgs("obs", 194, {"--duration", "60"}),
                             dir + "/server.log");
  // The server's writers: everything but the tool and instructor commands.
  const std::vector<int32_t> server_only = {1, 1, 1, 0, 1, 1, 0, 1, 1};
  for (int i = 0; i < 1000 && all.Writers() != server_only; ++i) {
    std::this_thread::sleep_for(milliseconds(10));
  }
  ASSERT_EQ(all.Writers(), server_only);
  auto viewer = StartViewer(ViewerArgs("obs", 194, {"--observe", "--station", "instructor-1"}),
                            dir + "/viewer.log");
  ASSERT_TRUE(WaitForLog(dir + "/viewer.log", "scene_complete")) << ReadText(dir + "/viewer.log");
  int samples = 0;
  for (int i = 0; i < 150; ++i) {  // 1.5 s of an instructor watching
    EXPECT_EQ(all.Writers(), server_only);
    samples += all.tool_command.Take([](const auto&, const auto&) {});
    samples += all.instructor.Take([](const auto&, const auto&) {});
    std::this_thread::sleep_for(milliseconds(10));
  }
  EXPECT_EQ(samples, 0);
  viewer->Signal(SIGTERM);
  EXPECT_EQ(viewer->Wait(seconds(20)), 0) << ReadText(dir + "/viewer.log");
  server->Signal(SIGTERM);
  EXPECT_EQ(server->Wait(seconds(20)), 0) << ReadText(dir + "/server.log");
}

// A station without an arm drives a tool from the viewer: its tool commands reach the wire
// (named by tool and station, finite, the tip above the organ) and the server takes them.
TEST(ViewerProgram, StationDrivesAToolWithoutAnArm) {
  Xvfb x;
  ASSERT_TRUE(x.ok()) << "Xvfb did not start";
  const std::string dir = TempDir("station");
  AllTopics all(195, "station");
  auto server = StartProgram("somasim-server", ServerArgs("station", 195, {"--duration", "60"}),
                             dir + "/server.log");
  auto viewer =
      StartViewer(ViewerArgs("station", 195, {"--drive", "probe", "--station", "station-3"}),
                  dir + "/viewer.log");
  int commands = 0;
  bool well_formed = true;
  uint64_t received_by_server = 0;
  for (int i = 0; i < 1000 && (commands < 20 || received_by_server == 0); ++i) {
    all.tool_command.Take([&](const somasim_wire_ToolCommand& c, const dds_sample_info_t&) {
      ++commands;
      well_formed = well_formed && std::string(c.tool) == "probe" &&
                    std::string(c.station) == "station-3" && std::isfinite(c.position[2]) &&
                    c.orientation[0] == 1.0;
    });
    all.metrics.Take([&](const somasim_wire_ServerMetrics& m, const dds_sample_info_t&) {
      received_by_server = m.tool_commands_received;
    });
    std::this_thread::sleep_for(milliseconds(10));
  }
  EXPECT_GE(commands, 20);
  EXPECT_TRUE(well_formed);
  EXPECT_GT(received_by_server, 0u) << ReadText(dir + "/server.log");
  EXPECT_NE(ReadText(dir + "/viewer.log").find("\"driving\""), std::string::npos);
  viewer->Signal(SIGTERM);
  EXPECT_EQ(viewer->Wait(seconds(20)), 0) << ReadText(dir + "/viewer.log");
  server->Signal(SIGTERM);
  EXPECT_EQ(server->Wait(seconds(20)), 0) << ReadText(dir + "/server.log");
}

// An instructor asks which sessions are running: two servers on the domain, two names; none
// once they have stopped. No display needed.
TEST(ViewerProgram, ListsTheRunningSessions) {
  const std::string dir = TempDir("list");
  auto ward1 = StartProgram("somasim-server", ServerArgs("ward-1", 193, {"--duration", "60"}),
                            dir + "/ward1.log");
  auto ward2 = StartProgram("somasim-server", ServerArgs("ward-2", 193, {"--duration", "60"}),
                            dir + "/ward2.log");
  const auto list = [&](const std::string& log) {
    auto p =
        StartViewer({"--list-sessions", "--domain", "193", "--dds-config", LoopbackConfigFile()},
                    dir + "/" + log);
    EXPECT_EQ(p->Wait(seconds(30)), 0) << ReadText(dir + "/" + log);
    return ReadText(dir + "/" + log);
  };
  for (int i = 0;
       i < 200 && (ReadText(dir + "/ward1.log").find("\"running\"") == std::string::npos ||
                   ReadText(dir + "/ward2.log").find("\"running\"") == std::string::npos);
       ++i) {
    std::this_thread::sleep_for(milliseconds(50));
  }
  EXPECT_EQ(list("both.log"), "ward-1\nward-2\n");
  ward1->Signal(SIGTERM);
  ward2->Signal(SIGTERM);
  EXPECT_EQ(ward1->Wait(seconds(20)), 0) << ReadText(dir + "/ward1.log");
  EXPECT_EQ(ward2->Wait(seconds(20)), 0) << ReadText(dir + "/ward2.log");
  EXPECT_EQ(list("none.log"), "");
}

TEST(ViewerProgram, RefusesBadCommandLinesByName) {
  const std::string dir = TempDir("cli");
  const auto run = [&](const std::vector<std::string>& args, const std::string& log) {
    auto p = StartViewer(args, dir + "/" + log);
    return p->Wait(seconds(20));
  };
  EXPECT_EQ(run({"--after-frames", "0"}, "frames.log"), 2);
  EXPECT_NE(ReadText(dir + "/frames.log").find("--after-frames"), std::string::npos);
  EXPECT_EQ(run({"--session", "two words"}, "session.log"), 2);
  EXPECT_NE(ReadText(dir + "/session.log").find("--session"), std::string::npos);
  EXPECT_EQ(run({"--domain", "999"}, "domain.log"), 2);
  EXPECT_EQ(run({"--observe", "--drive", "probe"}, "modes.log"), 2);
  EXPECT_NE(ReadText(dir + "/modes.log").find("--observe"), std::string::npos);
  EXPECT_EQ(run({"--dds-config", dir + "/missing.xml", "--domain", "199"}, "config.log"), 5)
      << ReadText(dir + "/config.log");
  // No display: a clear message, not a crash inside GLUT.
  const char* display = std::getenv("DISPLAY");
  const std::string saved = display != nullptr ? display : "";
  unsetenv("DISPLAY");
  EXPECT_EQ(run({"--domain", "199"}, "display.log"), 6);
  EXPECT_NE(ReadText(dir + "/display.log").find("DISPLAY"), std::string::npos);
  if (!saved.empty()) setenv("DISPLAY", saved.c_str(), 1);
}

}  // namespace
}  // namespace somasim::viewer
