// The server's wire adapters (server/net/wire_adapters.h): a tool command from the network is
// applied only when every field is usable, and refused naming the field otherwise (NaN,
// infinities, beyond 10 m, not a unit quaternion, a jaw out of range, an unknown tool, another
// format); a tool's output travels with its command and its grasped nodes.
#include "server/net/wire_adapters.h"

#include <gtest/gtest.h>

#include <limits>
#include <string>

#include "common/dds/topics.h"
#include "common/force_model/force_model_wire.h"

namespace somasim::net {
namespace {

somasim_wire_ToolCommand Good() {
  somasim_wire_ToolCommand c{};
  c.tool = const_cast<char*>("probe");
  c.format_version = dds::kWireFormatVersion;
  c.seq = 7;
  c.position[2] = 0.05;
  c.orientation[0] = 1.0;
  c.jaw_closure = 0.25;
  c.buttons = 4;
  return c;
}

std::string Check(const somasim_wire_ToolCommand& c, const server::Session& s) {
  int32_t tool = -1;
  server::ToolCommandInput input;
  return CheckToolCommand(c, s, &tool, &input);
}

TEST(WireAdapters, AToolCommandIsAppliedOnlyWhenEveryFieldIsUsable) {
  const server::Session session(server::ServerDefaultScene("kidney424"),
                                scene::SceneLines("kidney"), ".");
  int32_t tool = -1;
  server::ToolCommandInput input;
  ASSERT_EQ(CheckToolCommand(Good(), session, &tool, &input), "");
  EXPECT_EQ(tool, 0);
  EXPECT_EQ(input.sequence, 7u);
  EXPECT_EQ(input.buttons, 4u);
  EXPECT_DOUBLE_EQ(input.pose.jaw_opening, 0.75);
  EXPECT_EQ(input.pose.tip, Eigen::Vector3d(0, 0, 0.05));
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  auto c = Good();
  c.format_version = 99;
  EXPECT_EQ(Check(c, session), "format_version 99 is not 1");
  c = Good();
  c.tool = const_cast<char*>("scalpelx");
  EXPECT_EQ(Check(c, session), "unknown tool \"scalpelx\"");
  c = Good();
  c.tool = nullptr;
  EXPECT_EQ(Check(c, session), "unknown tool \"\"");
  for (const double bad : {nan, inf, 11.0}) {
    c = Good();
    c.position[1] = bad;
    EXPECT_EQ(Check(c, session), "position is not finite or beyond 10 m") << bad;
  }
  for (const double bad : {nan, 0.9, 2.0}) {
    c = Good();
    c.orientation[0] = bad;
    EXPECT_EQ(Check(c, session), "orientation is not a unit quaternion") << bad;
  }
  for (const double bad : {nan, -0.1, 1.1}) {
    c = Good();
    c.jaw_closure = bad;
    EXPECT_EQ(Check(c, session), "jaw_closure is not in [0, 1]") << bad;
  }
}

TEST(WireAdapters, AToolsOutputTravelsWithItsCommandAndGraspedNodes) {
  runner::ToolOutput out;
  out.model.sequence = 3;
  out.model.grasping = true;
  out.command_seq = 42;
  out.num_held = 3;
  out.held[0] = 5;
  out.held[1] = 1;
  out.held[2] = 9;
  somasim_wire_ForceModel w{};
  ToolOutputToWire(out, &w);
  EXPECT_EQ(w.seq, 3u);
  EXPECT_EQ(w.command_seq, 42u);
  EXPECT_TRUE(w.grasping);
  std::vector<uint32_t> held;
  EXPECT_EQ(force_model::HeldNodesFromWire(w, 10, &held), "");
  EXPECT_EQ(held, (std::vector<uint32_t>{5, 1, 9}));
}

}  // namespace
}  // namespace somasim::net
