// The local force model to and from the wire (server/contact/force_model_wire.h).
#include "server/contact/force_model_wire.h"

#include <gtest/gtest.h>

#include <limits>

namespace somasim::contact {
namespace {

LocalForceModel Sample() {
  LocalForceModel m;
  m.sequence = 42;
  m.sim_time = 1.25;
  m.in_contact = true;
  m.contact_point = Eigen::Vector3d(0.01, -0.02, 0.03);
  m.normal = Eigen::Vector3d(0.0, 0.6, 0.8);
  m.contact_stiffness = 750.0;
  m.grasping = true;
  m.grasp_anchor = Eigen::Vector3d(0.1, 0.2, 0.3);
  m.grasp_stiffness << 900, 10, 20, 10, 800, 30, 20, 30, 700;  // symmetric, positive definite
  m.bias_force = Eigen::Vector3d(0.0, 0.0, -0.05);
  m.tissue_stiffness << 300, 1, 2, 1, 200, 3, 2, 3, 100;
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
  EXPECT_EQ(back.contact_point, m.contact_point);
  EXPECT_EQ(back.normal, m.normal);
  EXPECT_EQ(back.contact_stiffness, m.contact_stiffness);
  EXPECT_EQ(back.grasping, m.grasping);
  EXPECT_EQ(back.grasp_anchor, m.grasp_anchor);
  EXPECT_EQ(back.grasp_stiffness, m.grasp_stiffness);
  EXPECT_EQ(back.bias_force, m.bias_force);
  EXPECT_EQ(back.tissue_stiffness, m.tissue_stiffness);
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

}  // namespace
}  // namespace somasim::contact
