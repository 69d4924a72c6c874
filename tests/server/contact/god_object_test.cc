#include "server/contact/god_object.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

#include "server/contact/aabb_tree.h"
#include "tests/server/contact/contact_test_meshes.h"
#include "tests/support/allocation_counter.h"

namespace somasim::contact {
namespace {

using testing::WindingNumber;

constexpr double kOffset = 1e-6;  // [m]

Eigen::Vector3d RandomPointIn(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi,
                              std::mt19937* rng) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  return lo + Eigen::Vector3d(u(*rng), u(*rng), u(*rng)).cwiseProduct(hi - lo);
}

TEST(GodObject, PressingIntoAFlatSurfaceGivesTheSpringForceAlongTheNormal) {
  const mesh::SurfaceMesh patch = testing::FlatPatch(8, 0.05);
  const AabbTree tree(patch.vertices, patch.triangles);
  GodObject proxy(kOffset);
  proxy.Reset({0.011, -0.007, 0.02});
  proxy.Update(tree, {0.011, -0.007, -0.003});  // 3 mm in, in one jump
  ASSERT_TRUE(proxy.in_contact());
  EXPECT_NEAR((proxy.proxy() - Eigen::Vector3d(0.011, -0.007, kOffset)).norm(), 0.0, 1e-12);
  EXPECT_NEAR((proxy.normal() - Eigen::Vector3d::UnitZ()).norm(), 0.0, 1e-12);
  const Eigen::Vector3d f = proxy.DeviceForce(500.0);  // seed 002 eq. 12
  EXPECT_NEAR(f.z(), 500.0 * (0.003 + kOffset), 1e-9);
  EXPECT_NEAR(f.head<2>().norm(), 0.0, 1e-9);
  // Sliding underneath: the proxy follows the device's projection (frictionless).
  proxy.Update(tree, {-0.02, 0.013, -0.004});
  ASSERT_TRUE(proxy.in_contact());
  EXPECT_NEAR((proxy.proxy() - Eigen::Vector3d(-0.02, 0.013, kOffset)).norm(), 0.0, 1e-12);
  // Leaving: the proxy is the device again.
  proxy.Update(tree, {0.0, 0.0, 0.01});
  EXPECT_FALSE(proxy.in_contact());
  EXPECT_EQ(proxy.proxy(), Eigen::Vector3d(0.0, 0.0, 0.01));
  EXPECT_EQ(proxy.DeviceForce(500.0), Eigen::Vector3d::Zero());
}

TEST(GodObject, AnOpenSheetIsPushedFromTheSideTheToolCameFrom) {
  const mesh::SurfaceMesh patch = testing::FlatPatch(4, 0.05);
  const AabbTree tree(patch.vertices, patch.triangles);
  GodObject proxy(kOffset);
  proxy.Reset({0.0, 0.0, -0.02});  // underneath
  proxy.Update(tree, {0.003, 0.001, 0.5});
  ASSERT_TRUE(proxy.in_contact());
  EXPECT_LT(proxy.proxy().z(), 0.0);
  EXPECT_NEAR((proxy.normal() + Eigen::Vector3d::UnitZ()).norm(), 0.0, 1e-12);
  EXPECT_LT(proxy.DeviceForce(100.0).z(), 0.0);
}

TEST(GodObject, StopsInTheCornerWhereThreeFacesMeet) {
  // From inside a closed box the faces are constraints too: a device far beyond a corner
  // leaves the proxy in the corner, `offset` from each of the three faces.
  const testing::OrganWithSurface box =
      testing::BoxOrgan(3, Eigen::Vector3d(-1, -1, -1), Eigen::Vector3d(1, 1, 1));
  const AabbTree tree(box.volume.vertices, box.surface);
  GodObject proxy(kOffset);
  proxy.Reset(Eigen::Vector3d(0.1, 0.2, 0.3));
  proxy.Update(tree, Eigen::Vector3d(3.0, 2.5, 4.0));
  ASSERT_TRUE(proxy.in_contact());
  EXPECT_NEAR((proxy.proxy() - Eigen::Vector3d::Constant(1.0 - kOffset)).norm(), 0.0, 1e-9);
  // Beyond an edge (two faces): the proxy slides along the edge to the device's height.
  proxy.Reset(Eigen::Vector3d(0.0, 0.0, 0.0));
  proxy.Update(tree, Eigen::Vector3d(2.0, 3.0, 0.25));
  ASSERT_TRUE(proxy.in_contact());
  EXPECT_NEAR((proxy.proxy() - Eigen::Vector3d(1.0 - kOffset, 1.0 - kOffset, 0.25)).norm(), 0.0,
              1e-9);
}

TEST(GodObject, RidingStaysOutsideBothFacesOfANarrowingCrease) {
  // A V-shaped trough with its crease along x at the origin. A device below the crease holds
  // the proxy in it, near the crease on one face. Then the trough narrows from 60° to 30°
  // between its faces: riding out along that one face's normal would now carry the proxy
  // behind the other face; the mean normal of the faces there does not.
  auto trough = [](double opening_deg) {
    const double h = 1.0 / std::tan(0.5 * opening_deg * M_PI / 180.0);
    mesh::Points x(3, 6);
    x << -1, 1, -1, 1, -1, 1,  //
        0, 0, -1, -1, 1, 1,    //
        0, 0, h, h, h, h;
    return x;
  };
  mesh::Triangles triangles(3, 4);
  triangles << 0, 0, 0, 0,  //
      2, 3, 1, 5,           //
      3, 1, 5, 4;
  AabbTree tree(trough(60.0), triangles);
  GodObject proxy(kOffset);
  proxy.Reset({0.3, 0.1, 1.0});
  for (int update = 0; update < 6; ++update) {
    const double opening = update == 0 ? 60.0 : std::max(10.0, 60.0 - 12.5 * update);
    const mesh::Points x = trough(opening);
    tree.Refit(x);
    proxy.Update(tree, {0.3, 0.0, -0.5});
    ASSERT_TRUE(proxy.in_contact());
    // Inside the trough: on the inner side of both faces' planes.
    const double h = x(2, 2);
    const Eigen::Vector3d left = Eigen::Vector3d(0.0, h, 1.0).normalized();
    const Eigen::Vector3d right = Eigen::Vector3d(0.0, -h, 1.0).normalized();
    EXPECT_GT(left.dot(proxy.proxy()), 0.0) << "update " << update;
    EXPECT_GT(right.dot(proxy.proxy()), 0.0) << "update " << update;
    EXPECT_NEAR(proxy.proxy().x(), 0.3, 1e-9);
  }
}

TEST(GodObject, AnOrganMovingOntoAToolHeldStillPushesItsProxyOut) {
  // A breathing organ moves onto a tip held still: the proxy, free until then, must not end up
  // inside. 1 mm per update, over the tip and 2 cm beyond.
  const testing::OrganWithSurface kidney = testing::VolumeOrgan("kidney424");
  const mesh::Points rest = kidney.volume.vertices;
  const Eigen::Vector3d lo = rest.rowwise().minCoeff(), hi = rest.rowwise().maxCoeff();
  const Eigen::Vector3d tip(hi.x() + 0.005, 0.5 * (lo.y() + hi.y()), 0.5 * (lo.z() + hi.z()));
  AabbTree tree(rest, kidney.surface);
  GodObject proxy(kOffset);
  proxy.Reset(tip);
  mesh::Points x = rest;
  int touching = 0;
  for (int update = 1; update <= 25; ++update) {
    x = rest.colwise() + Eigen::Vector3d(0.001 * update, 0.0, 0.0);
    tree.Refit(x);
    proxy.Update(tree, tip, /*closed=*/true);
    ASSERT_LT(WindingNumber(x, kidney.surface, proxy.proxy()), 0.5) << "update " << update;
    if (proxy.in_contact()) {
      ++touching;
      EXPECT_GT(proxy.DeviceForce(1000.0).x(), 0.0);  // the organ pushes the hand along +x
    }
  }
  EXPECT_GT(touching, 5);  // from when the surface reached the tip (the hilum is concave)
  // The same without `closed` (an open sheet has no inside): the proxy stays where the tip is.
  GodObject open(kOffset);
  open.Reset(tip);
  open.Update(tree, tip);
  EXPECT_FALSE(open.in_contact());
  EXPECT_EQ(open.proxy(), tip);
  // A tip outside, next to a closed organ, stays free.
  const Eigen::Vector3d beside =
      Eigen::Vector3d(x.rowwise().maxCoeff()) + Eigen::Vector3d(0.002, 0, 0);
  GodObject outside(kOffset);
  outside.Reset(beside);
  outside.Update(tree, beside, /*closed=*/true);
  EXPECT_FALSE(outside.in_contact());
}

TEST(GodObject, NeverEntersAClosedOrganOnRandomFastTrajectories) {
  const testing::OrganWithSurface kidney = testing::VolumeOrgan("kidney424");
  const mesh::Points& x = kidney.volume.vertices;
  const AabbTree tree(x, kidney.surface);
  const Eigen::Vector3d lo = x.rowwise().minCoeff(), hi = x.rowwise().maxCoeff();
  const Eigen::Vector3d margin = 0.3 * (hi - lo);
  std::mt19937 rng(6);
  GodObject proxy(kOffset);
  proxy.Reset(hi + margin);  // outside
  int touching = 0;
  for (int update = 0; update < 3000; ++update) {
    // Jumps anywhere in and around the organ: across it in one update, at any speed.
    const Eigen::Vector3d device = RandomPointIn(lo - margin, hi + margin, &rng);
    proxy.Update(tree, device, /*closed=*/true);
    ASSERT_LT(WindingNumber(x, kidney.surface, proxy.proxy()), 0.5) << "update " << update;
    if (proxy.in_contact()) {
      ++touching;
      // On the surface, at most `offset` outside it.
      EXPECT_LE(proxy.contact().distance, kOffset * (1.0 + 1e-6));
      EXPECT_GE(proxy.DeviceForce(1.0).dot(proxy.normal()), 0.0);
    } else {
      EXPECT_EQ(proxy.proxy(), device);
    }
  }
  EXPECT_GT(touching, 300);  // the trajectories did go in
}

TEST(GodObject, RidesADeformingOrganWithoutEnteringIt) {
  const testing::OrganWithSurface kidney = testing::VolumeOrgan("kidney424");
  const mesh::Points rest = kidney.volume.vertices;
  const Eigen::Vector3d lo = rest.rowwise().minCoeff(), hi = rest.rowwise().maxCoeff();
  const Eigen::Vector3d centre = 0.5 * (lo + hi), margin = 0.3 * (hi - lo);
  AabbTree tree(rest, kidney.surface);
  std::mt19937 rng(11);
  GodObject proxy(kOffset);
  proxy.Reset(hi + margin);
  mesh::Points x = rest;
  for (int update = 0; update < 1500; ++update) {
    // Breathing and bending: up to ±15 % radial and a sideways wave.
    const double s = 0.15 * std::sin(0.05 * update);
    for (Eigen::Index i = 0; i < x.cols(); ++i) {
      const Eigen::Vector3d r = rest.col(i) - centre;
      x.col(i) = centre + (1.0 + s) * r +
                 Eigen::Vector3d(0.0, 0.0, 0.3 * s * std::sin(20.0 * r.x()) * (hi - lo).z());
    }
    tree.Refit(x);
    const Eigen::Vector3d device =
        update % 3 == 0 ? RandomPointIn(lo - margin, hi + margin, &rng) : centre;
    proxy.Update(tree, device, /*closed=*/true);
    ASSERT_LT(WindingNumber(x, kidney.surface, proxy.proxy()), 0.5) << "update " << update;
  }
}

TEST(GodObject, UpdatesAllocateNothing) {
  const testing::OrganWithSurface kidney = testing::VolumeOrgan("kidney424");
  const AabbTree tree(kidney.volume.vertices, kidney.surface);
  const Eigen::Vector3d lo = kidney.volume.vertices.rowwise().minCoeff();
  const Eigen::Vector3d hi = kidney.volume.vertices.rowwise().maxCoeff();
  std::mt19937 rng(3);
  std::vector<Eigen::Vector3d> devices;
  devices.reserve(200);
  for (int i = 0; i < 200; ++i) devices.push_back(RandomPointIn(lo, hi, &rng));
  GodObject proxy(kOffset);
  proxy.Reset(2.0 * hi);
  const testing::AllocationCounter counter;
  for (const Eigen::Vector3d& d : devices) proxy.Update(tree, d);
  EXPECT_EQ(counter.count(), 0);
}

TEST(GodObject, NonFiniteDevicePositionsAreIgnored) {
  const mesh::SurfaceMesh patch = testing::FlatPatch(4, 0.05);
  const AabbTree tree(patch.vertices, patch.triangles);
  GodObject proxy(kOffset);
  proxy.Reset({0.0, 0.0, 0.01});
  proxy.Update(tree, {0.0, 0.0, -0.002});
  const Eigen::Vector3d before = proxy.proxy();
  proxy.Update(tree, {std::nan(""), 0.0, 0.0});
  proxy.Update(tree, {0.0, std::numeric_limits<double>::infinity(), 0.0});
  EXPECT_EQ(proxy.proxy(), before);
  EXPECT_TRUE(proxy.in_contact());
  EXPECT_TRUE(proxy.DeviceForce(100.0).allFinite());
  EXPECT_THROW(GodObject(0.0), std::invalid_argument);
  EXPECT_THROW(GodObject(std::nan("")), std::invalid_argument);
}

}  // namespace
}  // namespace somasim::contact
