// The local force model to and from the wire (common/force_model/force_model_wire.h), with the
// grasped nodes it carries: bad counts and out-of-range indices are refused by name.
#include "common/force_model/force_model_wire.h"

#include <gtest/gtest.h>

#include <cstdint>
#include <limits>
#include <vector>

namespace somasim::force_model {
namespace {

LocalForceModel Sample() {
  LocalForceModel m;
  m.sequence = 42;
  m.sim_time = 1.25;
  m.in_contact = true;
  Vec(m.contact_point) = Eigen::Vector3d(0.01, -0.02, 0.03);
  Vec(m.normal) = Eigen::Vector3d(0.0, 0.6, 0.8);
  m.contact_stiffness = 750.0;
  m.grasping = true;
  Vec(m.grasp_anchor) = Eigen::Vector3d(0.1, 0.2, 0.3);
  Mat(m.grasp_stiffness) << 900, 10, 20, 10, 800, 30, 20, 30, 700;  // symmetric, positive definite
  Vec(m.bias_force) = Eigen::Vector3d(0.0, 0.0, -0.05);
  Mat(m.tissue_stiffness) << 300, 1, 2, 1, 200, 3, 2, 3, 100;
  m.damping = 2.0;
  m.force_limit = 8.0;
  return m;
}

TEST(ForceModelWire, RoundTripKeepsEveryFieldAndMatricesAreRowMajor) {
  const LocalForceModel m = Sample();
  somasim_wire_ForceModel w{};
  ToWire(m, &w);
  EXPECT_EQ(w.grasp_stiffness[1], 10.0);  // row 0, column 1
  EXPECT_EQ(w.tissue_stiffness[5], 3.0);  // row 1, column 2
  w.format_version = 1;
  LocalForceModel back;
  ASSERT_EQ(FromWire(w, 1, &back), "");
  EXPECT_EQ(back.sequence, m.sequence);
  EXPECT_EQ(back.sim_time, m.sim_time);
  EXPECT_EQ(back.in_contact, m.in_contact);
  EXPECT_EQ(Vec(back.contact_point), Vec(m.contact_point));
  EXPECT_EQ(Vec(back.normal), Vec(m.normal));
  EXPECT_EQ(back.contact_stiffness, m.contact_stiffness);
  EXPECT_EQ(back.grasping, m.grasping);
  EXPECT_EQ(Vec(back.grasp_anchor), Vec(m.grasp_anchor));
  EXPECT_EQ(Mat(back.grasp_stiffness), Mat(m.grasp_stiffness));
  EXPECT_EQ(Vec(back.bias_force), Vec(m.bias_force));
  EXPECT_EQ(Mat(back.tissue_stiffness), Mat(m.tissue_stiffness));
  EXPECT_EQ(back.damping, m.damping);
  EXPECT_EQ(back.force_limit, m.force_limit);
}

TEST(ForceModelWire, AnUnknownVersionOrABadValueIsRefusedWithItsReason) {
  somasim_wire_ForceModel w{};
  ToWire(Sample(), &w);
  w.format_version = 9;
  LocalForceModel back;
  EXPECT_EQ(FromWire(w, 1, &back), "format_version 9");
  w.format_version = 1;
  w.normal[2] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(FromWire(w, 1, &back), "");
  ToWire(Sample(), &w);
  w.format_version = 1;
  w.damping = -1.0;
  EXPECT_NE(FromWire(w, 1, &back), "");
  ToWire(Sample(), &w);
  w.format_version = 1;
  w.grasp_stiffness[1] = 500.0;  // no longer symmetric
  EXPECT_NE(FromWire(w, 1, &back), "");
}

// The grasped nodes: the first kMaxHeldNodes go on the wire; a receiver takes them only when the
// count and every index fit the organ it knows.
TEST(ForceModelWire, HeldNodesTravelAndBadOnesAreRefusedByName) {
  somasim_wire_ForceModel w{};
  const std::vector<int32_t> held = {7, 3, 11};
  HeldNodesToWire(held, &w);
  EXPECT_EQ(w.num_held, 3u);
  std::vector<uint32_t> nodes = {99};
  EXPECT_EQ(HeldNodesFromWire(w, 12, &nodes), "");
  EXPECT_EQ(nodes, (std::vector<uint32_t>{7, 3, 11}));
  // An index out of the organ: refused, the receiver's list untouched.
  EXPECT_EQ(HeldNodesFromWire(w, 11, &nodes), "held node 11 is not below the organ's 11 nodes");
  EXPECT_EQ(nodes, (std::vector<uint32_t>{7, 3, 11}));
  // A hostile count.
  w.num_held = 65;
  EXPECT_EQ(HeldNodesFromWire(w, 1000, &nodes), "num_held 65 is over 64");
  w.num_held = UINT32_MAX;
  EXPECT_NE(HeldNodesFromWire(w, 1000, &nodes), "");
  // More than fit: the first 64 (the nearest to the jaws), the rest of the array zeroed.
  std::vector<int32_t> many(100);
  for (int32_t i = 0; i < 100; ++i) many[static_cast<size_t>(i)] = 100 - i;
  HeldNodesToWire(many, &w);
  EXPECT_EQ(w.num_held, kMaxHeldNodes);
  EXPECT_EQ(w.held_nodes[0], 100u);
  EXPECT_EQ(w.held_nodes[63], 37u);
  HeldNodesToWire({}, &w);
  EXPECT_EQ(w.num_held, 0u);
  EXPECT_EQ(w.held_nodes[0], 0u);
  EXPECT_EQ(HeldNodesFromWire(w, 0, &nodes), "");
  EXPECT_TRUE(nodes.empty());
}

}  // namespace
}  // namespace somasim::force_model
