// somasim-viewer's receiver (issue 8) against samples this test writes on its own domain: good
// ones are shown, malformed ones (sizes, indices, NaN, format version, unknown topology version)
// are dropped and counted, a new server id forgets the old shapes; the haptic rate, rigid bodies,
// a server gone after its lease, the rendered force and the grasped points. The program itself
// under Xvfb: viewer_program_test.cc.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <Eigen/Core>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "common/dds/topics.h"
#include "common/force_model/force_model_wire.h"
#include "tests/support/sanitizer.h"
#include "viewer/scene_receiver.h"

namespace somasim::viewer {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

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

// The haptic rate a viewer shows is the sender's command rate: its sequence numbers over a
// second, not the samples the (keep-last 1) reader happened to take. Here a sender numbers its
// commands by milliseconds (a 1 kHz loop) but publishes only every 10 ms.
TEST(SceneReceiver, MeasuresTheHapticRateFromSequenceNumbers) {
  Samples s;
  SceneReceiver r(s.participant, s.topics, "rate");
  dds::Writer<somasim_wire_SessionInfo> session(s.participant, s.topics.session,
                                                dds::SessionQos("rate"));
  dds::Writer<somasim_wire_ToolCommand> commands(s.participant, s.topics.tool_command,
                                                 dds::ToolCommandQos("rate"));
  somasim_wire_ToolInfo tool{};
  tool.id = const_cast<char*>("probe");
  tool.kind = const_cast<char*>("probe");
  somasim_wire_SessionInfo info{};
  info.format_version = dds::kWireFormatVersion;
  info.server_id = 31;
  info.scene_name = const_cast<char*>("rate");
  SetSequence(&info.tools, &tool, 1);
  session.Write(info);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.has_session(); }));
  const auto start = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - start < milliseconds(2300)) {
    somasim_wire_ToolCommand c{};
    c.tool = const_cast<char*>("probe");
    c.format_version = dds::kWireFormatVersion;
    c.station = const_cast<char*>("station-7");
    c.seq = 1 + static_cast<uint64_t>(std::chrono::duration_cast<milliseconds>(
                                          std::chrono::steady_clock::now() - start)
                                          .count());
    c.orientation[0] = 1.0;
    commands.Write(c);
    std::this_thread::sleep_for(milliseconds(10));
    r.Poll();
  }
  const ToolScene& t = r.tools().at("probe");
  EXPECT_EQ(t.station, "station-7");
  EXPECT_NEAR(t.command_rate_hz, 1000.0, 50.0);
}

// Rigid bodies (a kidney stone) are shown where the server has them; samples with non-finite
// poses, radii outside (0, 0.2] m or no unit quaternion are dropped and counted, one from
// another server is ignored, a new server forgets the old one's bodies.
TEST(SceneReceiver, ShowsRigidBodiesAndDropsMalformedOnes) {
  Samples s;
  SceneReceiver r(s.participant, s.topics, "stone");
  dds::Writer<somasim_wire_SessionInfo> session(s.participant, s.topics.session,
                                                dds::SessionQos("stone"));
  dds::Writer<somasim_wire_RigidBodyState> bodies(s.participant, s.topics.rigid_body,
                                                  dds::RigidBodyQos("stone"));
  somasim_wire_SessionInfo info{};
  info.format_version = dds::kWireFormatVersion;
  info.server_id = 21;
  info.scene_name = const_cast<char*>("stone");
  session.Write(info);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.has_session(); }));
  const auto body = [](const char* id, uint64_t server) {
    somasim_wire_RigidBodyState b{};
    b.body = const_cast<char*>(id);
    b.format_version = dds::kWireFormatVersion;
    b.server_id = server;
    b.sim_time = 1.5;
    b.radius = 0.004;
    b.position[2] = 0.0265;
    b.orientation[0] = 1.0;
    return b;
  };
  // Malformed, each under its own key (keep-last 1 per body keeps every one).
  somasim_wire_RigidBodyState nan = body("nan", 21);
  nan.position[1] = std::numeric_limits<double>::quiet_NaN();
  somasim_wire_RigidBodyState big = body("big", 21);
  big.radius = 0.5;
  somasim_wire_RigidBodyState flat = body("flat", 21);
  flat.radius = 0.0;
  somasim_wire_RigidBodyState spin = body("spin", 21);
  spin.orientation[0] = 0.0;  // not a rotation
  somasim_wire_RigidBodyState far = body("far", 21);
  far.position[0] = 1e6;
  for (const auto& b : {nan, big, flat, spin, far}) bodies.Write(b);
  bodies.Write(body("elsewhere", 99));  // another server's
  ASSERT_TRUE(PollUntil(&r, [&] { return r.counters().bad_rigid_bodies == 5; }))
      << r.counters().bad_rigid_bodies;
  EXPECT_TRUE(r.rigid_bodies().empty());
  somasim_wire_RigidBodyState stone = body("stone", 21);
  stone.grasped = true;
  bodies.Write(stone);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.rigid_bodies().count("stone") == 1; }));
  const RigidBodyScene& shown = r.rigid_bodies().at("stone");
  EXPECT_EQ(shown.radius, 0.004);
  EXPECT_EQ(shown.position[2], 0.0265);
  EXPECT_TRUE(shown.grasped);
  EXPECT_EQ(r.rigid_bodies().size(), 1u);
  // A restarted server: the old bodies are gone until the new one publishes its own.
  info.server_id = 22;
  session.Write(info);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.server_id() == 22u; }));
  EXPECT_TRUE(r.rigid_bodies().empty());
}

// A server is alive while its heartbeats come and for a lease (500 ms) after the last; one just
// heard of (its session arrived, its first heartbeat not yet) is alive for a lease too, so a
// viewer that gets the transient-local samples first does not call a starting server gone.
TEST(SceneReceiver, ShowsAServerGoneOnlyWhenItsHeartbeatStopsForALease) {
  Samples s;
  SceneReceiver r(s.participant, s.topics, "beat");
  EXPECT_TRUE(r.server_gone(std::chrono::steady_clock::now()));  // none seen yet
  dds::Writer<somasim_wire_SessionInfo> session(s.participant, s.topics.session,
                                                dds::SessionQos("beat"));
  dds::Writer<somasim_wire_Heartbeat> heartbeat(s.participant, s.topics.heartbeat,
                                                dds::HeartbeatQos("beat"));
  somasim_wire_SessionInfo info{};
  info.format_version = dds::kWireFormatVersion;
  info.server_id = 11;
  info.scene_name = const_cast<char*>("beat");
  session.Write(info);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.has_session(); }));
  const auto now = [] { return std::chrono::steady_clock::now(); };
  EXPECT_FALSE(r.server_gone(now()));  // just heard of, no heartbeat yet
  EXPECT_TRUE(r.server_gone(now() + milliseconds(600)));
  somasim_wire_Heartbeat beat{};
  beat.format_version = dds::kWireFormatVersion;
  beat.server_id = 11;
  beat.state = 2;
  for (uint64_t i = 0; i < 8; ++i) {  // 0.8 s of heartbeats every 100 ms: alive throughout
    beat.seq = i + 1;
    heartbeat.Write(beat);
    std::this_thread::sleep_for(milliseconds(100));
    r.Poll();
    EXPECT_FALSE(r.server_gone(now())) << i;
  }
  EXPECT_EQ(r.server_state(), 2u);
  std::this_thread::sleep_for(milliseconds(300));  // silent, within the lease
  r.Poll();
  if (!somasim::testing::kUnderSanitizer) {  // a 200 ms margin
    EXPECT_FALSE(r.server_gone(now()));
  }
  std::this_thread::sleep_for(milliseconds(400));  // silent for 0.7 s: gone
  r.Poll();
  EXPECT_TRUE(r.server_gone(now()));
}

// A grasper's force and grasped points from the server's local force models: the force the
// model gives at the commanded tip, the surface nodes within the scene's grasp radius of the
// jaws when the grasp begins (the scene text's 5 mm, not the 3 mm default), none after the
// release; a model that is not usable (NaN, asymmetric stiffness) is dropped and counted.
TEST(SceneReceiver, ShowsTheRenderedForceAndTheGraspedPoints) {
  Samples s;
  SceneReceiver r(s.participant, s.topics, "grasp");
  dds::Writer<somasim_wire_SessionInfo> session(s.participant, s.topics.session,
                                                dds::SessionQos("grasp"));
  dds::Writer<somasim_wire_OrganTopology> topology(s.participant, s.topics.topology,
                                                   dds::TopologyQos("grasp"));
  dds::Writer<somasim_wire_MeshFrame> frames(s.participant, s.topics.frame, dds::FrameQos("grasp"));
  dds::Writer<somasim_wire_ToolCommand> commands(s.participant, s.topics.tool_command,
                                                 dds::ToolCommandQos("grasp"));
  dds::Writer<somasim_wire_ForceModel> models(s.participant, s.topics.force_model,
                                              dds::ForceModelQos("grasp"));
  somasim_wire_OrganInfo organ{};
  organ.id = const_cast<char*>("a");
  somasim_wire_ToolInfo tool{};
  tool.id = const_cast<char*>("jaws");
  tool.kind = const_cast<char*>("grasper");
  tool.shaft_length = 0.3;
  tool.shaft_radius = 0.0025;
  tool.jaw_length = 0.015;
  somasim_wire_SessionInfo info{};
  info.format_version = dds::kWireFormatVersion;
  info.server_id = 9;
  info.scene_name = const_cast<char*>("grasp");
  info.scene_text = const_cast<char*>(
      "format_version: 1 tool { id: \"jaws\" grasper { jaw_length: 0.015 grasp_radius: 0.005 } }");
  SetSequence(&info.organs, &organ, 1);
  SetSequence(&info.tools, &tool, 1);
  session.Write(info);
  // Nodes 0 and 1 lie 1 mm and 4.1 mm from the jaws below; 2 and 3 10 cm away.
  std::vector<float> rest = {0, 0, 0, 0.004F, 0, 0, 0.1F, 0, 0, 0, 0.1F, 0};
  std::vector<uint32_t> tris = {0, 1, 2, 0, 2, 3};
  std::vector<uint8_t> inner = {0, 0};
  topology.Write(Topology("a", 9, 1, &rest, &tris, &inner));
  ASSERT_TRUE(PollUntil(&r, [&] { return r.organs().count("a") == 1; }));
  frames.Write(Keyframe("a", 9, 1, 1, &rest));
  ASSERT_TRUE(PollUntil(&r, [&] { return r.complete(); }));
  EXPECT_EQ(r.tools().at("jaws").grasp_radius, 0.005);
  EXPECT_EQ(r.tools().at("jaws").jaw_length, 0.015);

  const auto command = [&](double z, uint64_t seq) {
    somasim_wire_ToolCommand c{};
    c.tool = const_cast<char*>("jaws");
    c.format_version = dds::kWireFormatVersion;
    c.station = const_cast<char*>("test");
    c.seq = seq;
    c.position[2] = z;
    c.orientation[0] = 1.0;
    commands.Write(c);
    ASSERT_TRUE(PollUntil(&r, [&] { return r.tools().at("jaws").position[2] == z; }));
  };
  const auto model = [&](const force_model::LocalForceModel& m,
                         const std::vector<int32_t>& held = {}, uint32_t num_held = 0) {
    somasim_wire_ForceModel w{};
    force_model::ToWire(m, &w);
    force_model::HeldNodesToWire(held, &w);
    if (num_held > 0) w.num_held = num_held;  // a hostile count
    w.tool = const_cast<char*>("jaws");
    w.format_version = dds::kWireFormatVersion;
    w.server_id = 9;
    w.organ = const_cast<char*>("a");
    models.Write(w);
  };
  // In contact 2 mm below the surface z = 0 at k_n = 500 N/m: 1 N up.
  command(-0.002, 1);
  force_model::LocalForceModel touch;
  touch.sequence = 1;
  touch.in_contact = true;
  touch.contact_stiffness = 500.0;
  model(touch);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.tools().at("jaws").in_contact; }));
  EXPECT_NEAR(r.tools().at("jaws").Force().z(), 1.0, 1e-12);
  EXPECT_EQ(r.tools().at("jaws").Force().head<2>().norm(), 0.0);
  EXPECT_EQ(r.tools().at("jaws").organ, "a");
  EXPECT_TRUE(r.tools().at("jaws").held_nodes.empty());

  // Unusable models: dropped and counted, the last good one kept.
  force_model::LocalForceModel bad = touch;
  bad.sequence = 2;
  bad.contact_stiffness = std::numeric_limits<double>::quiet_NaN();
  model(bad);  // keep-last 1 per tool: one at a time
  ASSERT_TRUE(PollUntil(&r, [&] { return r.counters().bad_tool_samples == 1; }));
  bad = touch;
  bad.sequence = 3;
  force_model::Mat(bad.tissue_stiffness)(0, 1) = 100.0;  // not symmetric
  model(bad);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.counters().bad_tool_samples == 2; }))
      << r.counters().bad_tool_samples;
  EXPECT_NEAR(r.tools().at("jaws").Force().z(), 1.0, 1e-12);

  // The jaws close 1 mm above node 0: the server holds nodes 0 and 1, nearest first, and says so.
  command(0.001, 2);
  force_model::LocalForceModel grasp;
  grasp.sequence = 4;
  grasp.grasping = true;
  force_model::Vec(grasp.grasp_anchor) = Eigen::Vector3d(0.0, 0.0, 0.0);
  force_model::Mat(grasp.grasp_stiffness) = 200.0 * Eigen::Matrix3d::Identity();
  model(grasp, {0, 1});
  ASSERT_TRUE(PollUntil(&r, [&] { return r.tools().at("jaws").grasping; }));
  EXPECT_EQ(r.tools().at("jaws").held_nodes, (std::vector<uint32_t>{0, 1}));
  EXPECT_EQ(r.tools().at("jaws").held_organ, "a");
  EXPECT_NEAR(r.tools().at("jaws").Force().z(), -0.2, 1e-12);  // pulled back to the anchor
  // A sample whose held nodes are not the organ's, or too many: dropped and counted, the last
  // good grasp kept.
  grasp.sequence = 5;
  model(grasp, {0, 1000});
  ASSERT_TRUE(PollUntil(&r, [&] { return r.counters().bad_tool_samples == 3; }));
  model(grasp, {0}, 100000);
  ASSERT_TRUE(PollUntil(&r, [&] { return r.counters().bad_tool_samples == 4; }));
  EXPECT_EQ(r.tools().at("jaws").held_nodes, (std::vector<uint32_t>{0, 1}));
  // Released: no grasped points.
  force_model::LocalForceModel open;
  open.sequence = 6;
  model(open);
  ASSERT_TRUE(PollUntil(&r, [&] { return !r.tools().at("jaws").grasping; }));
  EXPECT_TRUE(r.tools().at("jaws").held_nodes.empty());
  EXPECT_EQ(r.tools().at("jaws").Force().norm(), 0.0);
}

}  // namespace
}  // namespace somasim::viewer
