// The haptic local force model (common/force_model/local_force_model.h, made by
// server/contact/force_model_maker.h): consistency with the server's force, the
// series-stiffness law, unilateral frictionless contact, damping, the clamp, and boundedness for
// any model whatever its bits (SPEC §7: NaN/Inf never reaches the arm).
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <Eigen/LU>
#include <Eigen/QR>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "server/contact/force_model_maker.h"
#include "tests/support/allocation_counter.h"

namespace somasim::contact {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;
using force_model::EvaluateLocalForceModel;
using force_model::ForceSample;
using force_model::LocalForceModelError;
using force_model::Mat;
using force_model::Vec;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();

// A random symmetric positive definite compliance [m/N] with eigenvalues in [1e-3, 2e-2].
Matrix3d RandomCompliance(std::mt19937* rng) {
  std::normal_distribution<double> gauss;
  std::uniform_real_distribution<double> uniform(1e-3, 2e-2);
  Matrix3d a;
  for (int i = 0; i < 9; ++i) a(i / 3, i % 3) = gauss(*rng);
  const Matrix3d q = a.householderQr().householderQ();
  const Vector3d c(uniform(*rng), uniform(*rng), uniform(*rng));
  const Matrix3d m = q * c.asDiagonal() * q.transpose();
  return 0.5 * (m + m.transpose());
}

Vector3d RandomUnit(std::mt19937* rng) {
  std::normal_distribution<double> gauss;
  Vector3d v;
  for (int i = 0; i < 3; ++i) v[i] = gauss(*rng);  // in order (argument order is unspecified)
  return v.normalized();
}

// The server's view of a probe pressed `depth` [m] below the proxy on a tissue of compliance c.
ContactForModel PressedContact(const Matrix3d& c, const Vector3d& n, double depth) {
  ContactForModel contact;
  contact.in_contact = true;
  contact.device = Vector3d(0.01, -0.02, 0.05);
  contact.proxy = contact.device + depth * n;
  contact.normal = n;
  contact.tool_stiffness = 800.0;
  contact.tissue_compliance = c;
  contact.force_limit = 20.0;
  return contact;
}

// In contact, the model gives back the proxy force K_t (proxy - device) at the device; in a grasp
// it gives back the grasp force.
TEST(LocalForceModel, ReproducesTheServersForceAtTheDevice) {
  std::mt19937 rng(1);
  for (int trial = 0; trial < 200; ++trial) {
    const Matrix3d c = RandomCompliance(&rng);
    const Vector3d n = RandomUnit(&rng);
    const ContactForModel contact = PressedContact(c, n, 0.003);
    const LocalForceModel model = MakeLocalForceModel(contact, 7, 0.5);
    EXPECT_EQ(LocalForceModelError(model), nullptr);
    EXPECT_EQ(model.sequence, 7u);
    EXPECT_EQ(model.sim_time, 0.5);
    const ForceSample s = EvaluateLocalForceModel(model, contact.device, Vector3d::Zero());
    const Vector3d want = contact.tool_stiffness * (contact.proxy - contact.device);
    EXPECT_TRUE(s.in_contact);
    EXPECT_FALSE(s.clamped);
    EXPECT_LE((s.force - want).norm(), 1e-12 * want.norm());

    ContactForModel grasp;
    grasp.grasping = true;
    grasp.device = Vector3d(0.0, 0.1, 0.02);
    grasp.grasp_force = 2.0 * RandomUnit(&rng);
    grasp.tool_stiffness = 500.0;
    grasp.tissue_compliance = c;
    const LocalForceModel g = MakeLocalForceModel(grasp, 8, 0.5);
    EXPECT_EQ(LocalForceModelError(g), nullptr);
    const ForceSample gs = EvaluateLocalForceModel(g, grasp.device, Vector3d::Zero());
    EXPECT_LE((gs.force - grasp.grasp_force).norm(), 1e-12 * grasp.grasp_force.norm());
  }
}

// k_n = 1 / (1/K_t + nᵀ C n) and K_g = (K_t⁻¹ I + C)⁻¹, by hand on a diagonal compliance; the
// contact force grows as k_n d with the penetration below the unloaded plane.
TEST(LocalForceModel, SeriesStiffnessesFollowTheHandComputation) {
  const Matrix3d c = Vector3d(0.01, 0.02, 0.03).asDiagonal();  // [m/N]
  ContactForModel contact = PressedContact(c, Vector3d::UnitZ(), 0.002);
  contact.tool_stiffness = 1000.0;
  contact.grasping = true;
  const LocalForceModel model = MakeLocalForceModel(contact, 1, 0.0);
  const double kn = 1.0 / (1.0 / 1000.0 + 0.03);  // 32.258... N/m
  EXPECT_NEAR(model.contact_stiffness, kn, 1e-12 * kn);
  const Matrix3d kg =
      Vector3d(1.0 / (0.001 + 0.01), 1.0 / (0.001 + 0.02), 1.0 / (0.001 + 0.03)).asDiagonal();
  EXPECT_LE((Mat(model.grasp_stiffness) - kg).norm(), 1e-12 * kg.norm());
  const Matrix3d k_tissue = Vector3d(100.0, 50.0, 1.0 / 0.03).asDiagonal();
  EXPECT_LE((Mat(model.tissue_stiffness) - k_tissue).norm(), 1e-12 * k_tissue.norm());
  // The unloaded plane: the proxy force 1000 N/m × 2 mm = 2 N moved the surface by 2 N × 0.03
  // m/N = 6 cm inward, so it lies 6 cm above the proxy.
  EXPECT_NEAR(model.contact_point[2], contact.proxy.z() + 0.06, 1e-12);
  LocalForceModel contact_only = model;
  contact_only.grasping = false;
  for (const double d : {1e-4, 1e-3, 5e-3}) {
    const Vector3d x = Vec(contact_only.contact_point) - d * Vector3d::UnitZ();
    const ForceSample s = EvaluateLocalForceModel(contact_only, x, Vector3d::Zero());
    EXPECT_TRUE(s.in_contact);
    EXPECT_NEAR(s.force.z(), kn * d, 1e-12);
  }
}

// Above the plane nothing pushes (and nothing pulls); below it the force is along the normal
// only, whatever the tangential offset (the proxy slides frictionless).
TEST(LocalForceModel, ContactIsUnilateralAndNormalOnly) {
  std::mt19937 rng(2);
  std::uniform_real_distribution<double> offset(-0.05, 0.05);
  for (int trial = 0; trial < 200; ++trial) {
    const Vector3d n = RandomUnit(&rng);
    const LocalForceModel model =
        MakeLocalForceModel(PressedContact(RandomCompliance(&rng), n, 0.002), 1, 0.0);
    const Vector3d tangent = RandomUnit(&rng).cross(n).normalized();
    const double t = offset(rng);
    const Vector3d above = Vec(model.contact_point) + 1e-4 * n + t * tangent;
    const ForceSample s = EvaluateLocalForceModel(model, above, Vector3d::Zero());
    EXPECT_FALSE(s.in_contact);
    EXPECT_EQ(s.force, Vector3d::Zero());
    const Vector3d below = Vec(model.contact_point) - 1e-3 * n + t * tangent;
    const ForceSample b = EvaluateLocalForceModel(model, below, Vector3d::Zero());
    EXPECT_TRUE(b.in_contact);
    EXPECT_GT(b.force.dot(n), 0.0);
    EXPECT_LE((b.force - b.force.dot(n) * n).norm(), 1e-14);
  }
}

// Damping resists the velocity: pressing in raises the contact force, pulling out lowers it but
// never below zero (the surface does not pull); in a grasp it is -b v in full.
TEST(LocalForceModel, DampingResistsVelocityAndNeverMakesContactPull) {
  ContactForModel contact =
      PressedContact(Vector3d(0.01, 0.01, 0.01).asDiagonal(), Vector3d::UnitZ(), 0.002);
  contact.damping = 2.0;  // [N s/m]
  const LocalForceModel model = MakeLocalForceModel(contact, 1, 0.0);
  const Vector3d x = contact.device;
  const double still = EvaluateLocalForceModel(model, x, Vector3d::Zero()).force.z();
  const Vector3d in(0.3, 0.0, -0.1);  // [m/s], tangential part ignored
  EXPECT_NEAR(EvaluateLocalForceModel(model, x, in).force.z(), still + 0.2, 1e-12);
  EXPECT_NEAR(EvaluateLocalForceModel(model, x, -in).force.z(), still - 0.2, 1e-12);
  EXPECT_EQ(EvaluateLocalForceModel(model, x, Vector3d(0.0, 0.0, 100.0)).force, Vector3d::Zero());
  EXPECT_EQ(EvaluateLocalForceModel(model, x, in).force.head<2>(), Eigen::Vector2d::Zero());

  ContactForModel grasp;
  grasp.grasping = true;
  grasp.tissue_compliance = Vector3d(0.01, 0.02, 0.03).asDiagonal();
  grasp.damping = 2.0;
  const LocalForceModel g = MakeLocalForceModel(grasp, 1, 0.0);
  const Vector3d v(0.1, -0.2, 0.3);
  const Vector3d xg(0.001, 0.002, -0.001);
  const Vector3d change = EvaluateLocalForceModel(g, xg, v).force -
                          EvaluateLocalForceModel(g, xg, Vector3d::Zero()).force;
  EXPECT_LE((change + 2.0 * v).norm(), 1e-12);
}

// A force above force_limit comes back at the limit, in the same direction, and says so.
TEST(LocalForceModel, ForceIsClampedToTheLimitKeepingItsDirection) {
  std::mt19937 rng(3);
  for (int trial = 0; trial < 100; ++trial) {
    ContactForModel grasp;
    grasp.grasping = true;
    grasp.in_contact = true;
    grasp.normal = RandomUnit(&rng);
    grasp.tissue_compliance = RandomCompliance(&rng);
    grasp.force_limit = 3.0;
    const LocalForceModel model = MakeLocalForceModel(grasp, 1, 0.0);
    const Vector3d x = 0.5 * RandomUnit(&rng);  // far: ~10-100 N unclamped
    LocalForceModel unlimited = model;
    unlimited.force_limit = 1e9;
    const ForceSample free = EvaluateLocalForceModel(unlimited, x, Vector3d::Zero());
    ASSERT_GT(free.force.norm(), 3.0);
    EXPECT_FALSE(free.clamped);
    const ForceSample s = EvaluateLocalForceModel(model, x, Vector3d::Zero());
    EXPECT_TRUE(s.clamped);
    EXPECT_NEAR(s.force.norm(), 3.0, 1e-12);
    EXPECT_LE((s.force.normalized() - free.force.normalized()).norm(), 1e-12);
  }
  // Huge but finite numbers: still the limit, still finite.
  LocalForceModel huge;
  huge.grasping = true;
  Mat(huge.grasp_stiffness) = 1e200 * Matrix3d::Identity();
  huge.force_limit = 5.0;
  const ForceSample s = EvaluateLocalForceModel(huge, Vector3d(1.0, 2.0, 3.0), Vector3d::Zero());
  EXPECT_TRUE(s.clamped);
  EXPECT_NEAR(s.force.norm(), 5.0, 1e-12);
  EXPECT_LE((s.force.normalized() + Vector3d(1.0, 2.0, 3.0).normalized()).norm(), 1e-12);
}

// Every double of a model, for the tests that spoil one at a time.
std::vector<double*> Doubles(LocalForceModel* m) {
  std::vector<double*> d = {&m->sim_time, &m->contact_stiffness, &m->damping, &m->force_limit};
  for (int i = 0; i < 3; ++i) {
    d.push_back(&m->contact_point[i]);
    d.push_back(&m->normal[i]);
    d.push_back(&m->grasp_anchor[i]);
    d.push_back(&m->bias_force[i]);
  }
  for (int i = 0; i < 9; ++i) {
    d.push_back(&m->grasp_stiffness[i]);
    d.push_back(&m->tissue_stiffness[i]);
  }
  return d;
}

LocalForceModel GoodModel() {
  ContactForModel c =
      PressedContact(Vector3d(0.01, 0.02, 0.03).asDiagonal(), Vector3d(0.0, 0.6, 0.8), 0.002);
  c.grasping = true;
  c.damping = 0.5;
  c.grasp_force = Vector3d(0.1, 0.2, 0.3);
  return MakeLocalForceModel(c, 3, 1.0);
}

// A NaN or an infinity anywhere the evaluation reads — any field of the model or the device's
// position or velocity — gives zero force, flagged invalid.
TEST(LocalForceModel, NonFiniteModelOrDeviceStateGivesZeroForceFlaggedInvalid) {
  const LocalForceModel good = GoodModel();
  const Vector3d x = Vec(good.contact_point) - 0.001 * Vec(good.normal);
  ASSERT_FALSE(EvaluateLocalForceModel(good, x, Vector3d::Zero()).invalid);
  ASSERT_NE(EvaluateLocalForceModel(good, x, Vector3d::Zero()).force, Vector3d::Zero());
  LocalForceModel copy = good;
  const size_t count = Doubles(&copy).size();
  for (const double bad : {kNaN, kInf, -kInf}) {
    for (size_t k = 0; k < count; ++k) {
      LocalForceModel model = good;
      *Doubles(&model)[k] = bad;
      const ForceSample s = EvaluateLocalForceModel(model, x, Vector3d::Zero());
      // sim_time and tissue_stiffness are for display: the evaluation need not read them, but
      // LocalForceModelError refuses the model all the same.
      EXPECT_NE(LocalForceModelError(model), nullptr) << "field " << k;
      const double* field = Doubles(&model)[k];
      const bool display_only = field == &model.sim_time || (field >= model.tissue_stiffness &&
                                                             field < model.tissue_stiffness + 9);
      if (display_only) continue;
      EXPECT_TRUE(s.invalid) << "field " << k;
      EXPECT_EQ(s.force, Vector3d::Zero()) << "field " << k;
    }
    for (int i = 0; i < 3; ++i) {
      Vector3d bx = x, bv = Vector3d::Zero();
      bx[i] = bad;
      EXPECT_TRUE(EvaluateLocalForceModel(good, bx, Vector3d::Zero()).invalid);
      EXPECT_EQ(EvaluateLocalForceModel(good, bx, Vector3d::Zero()).force, Vector3d::Zero());
      bv[i] = bad;
      EXPECT_TRUE(EvaluateLocalForceModel(good, x, bv).invalid);
      EXPECT_EQ(EvaluateLocalForceModel(good, x, bv).force, Vector3d::Zero());
    }
  }
}

// A rigid body held in the jaws weighs on the hand wherever the hand goes: the bias force is
// added at every position, passed on by MakeLocalForceModel, and clamped with the rest.
TEST(LocalForceModel, ABiasForceIsAddedEverywhereAndClampedWithTheRest) {
  ContactForModel carried;
  carried.device = Vector3d(0.0, 0.0, 0.1);
  carried.bias_force = Vector3d(0.0, 0.0, -0.0177);  // a 1.8 g stone
  const LocalForceModel model = MakeLocalForceModel(carried, 1, 0.0);
  EXPECT_EQ(LocalForceModelError(model), nullptr);
  for (const Vector3d& x : {Vector3d(0.0, 0.0, 0.1), Vector3d(0.3, -0.2, 0.5)}) {
    const ForceSample at = EvaluateLocalForceModel(model, x, Vector3d::Zero());
    EXPECT_FALSE(at.invalid);
    EXPECT_EQ(at.force, carried.bias_force);
  }
  LocalForceModel heavy = model;
  Vec(heavy.bias_force) = Vector3d(0.0, 0.0, -50.0);
  const ForceSample s = EvaluateLocalForceModel(heavy, Vector3d::Zero(), Vector3d::Zero());
  EXPECT_TRUE(s.clamped);
  EXPECT_NEAR(s.force.norm(), heavy.force_limit, 1e-12);
  carried.bias_force.x() = kNaN;
  EXPECT_THROW(MakeLocalForceModel(carried, 2, 0.0), std::invalid_argument);
  heavy.bias_force[1] = kInf;
  EXPECT_NE(std::string(LocalForceModelError(heavy)).find("bias_force"), std::string::npos);
}

// Models of random bits in every field (NaNs, infinities, subnormals, 1e300s): the force is
// always finite and within force_limit — or zero when force_limit itself is not a usable limit.
TEST(LocalForceModel, RandomGarbageModelsGiveBoundedFiniteForces) {
  std::mt19937_64 rng(4);
  std::uniform_real_distribution<double> near(-0.1, 0.1);
  const auto garbage = [&rng] {
    const uint64_t bits = rng();
    double value;
    std::memcpy(&value, &bits, sizeof value);
    return value;
  };
  int64_t valid = 0;
  for (int trial = 0; trial < 200000; ++trial) {
    LocalForceModel model;
    model.sequence = rng();
    model.in_contact = (rng() & 1) != 0;
    model.grasping = (rng() & 1) != 0;
    // Mix of pure garbage and plausible-but-wild values, so that both paths get exercised.
    const bool wild = (trial % 2) == 0;
    for (double* d : Doubles(&model))
      *d = wild ? garbage() : near(rng) * std::pow(10.0, (trial % 13) - 4);
    if (trial % 3 == 0) model.force_limit = std::abs(model.force_limit);
    Vector3d x, v;
    for (int i = 0; i < 3; ++i) {
      x[i] = (trial % 5 == 0) ? garbage() : near(rng);
      v[i] = (trial % 7 == 0) ? garbage() : near(rng);
    }
    const ForceSample s = EvaluateLocalForceModel(model, x, v);
    ASSERT_TRUE(s.force.allFinite()) << "trial " << trial;
    const double limit = model.force_limit;
    if (std::isfinite(limit) && limit >= std::numeric_limits<double>::min()) {
      ASSERT_LE(s.force.stableNorm(), limit * (1.0 + 1e-12)) << "trial " << trial;
    } else {
      ASSERT_EQ(s.force, Vector3d::Zero()) << "trial " << trial;
      ASSERT_TRUE(s.invalid);
    }
    if (s.invalid) {
      ASSERT_EQ(s.force, Vector3d::Zero());
    }
    valid += s.invalid ? 0 : 1;
  }
  EXPECT_GT(valid, 10000);  // the garbage did reach the arithmetic, not only the checks
}

TEST(LocalForceModel, MakingAndEvaluatingAllocateNothing) {
  {
    ContactForModel c =
        PressedContact(Vector3d(0.01, 0.02, 0.03).asDiagonal(), Vector3d(0.0, 0.6, 0.8), 0.002);
    c.grasping = true;
    somasim::testing::AllocationCounter counter;
    const LocalForceModel made = MakeLocalForceModel(c, 1, 0.0);
    EXPECT_EQ(counter.count(), 0);
    EXPECT_TRUE(made.in_contact);
  }
  const LocalForceModel model = GoodModel();
  std::vector<Vector3d> xs;
  xs.reserve(64);
  for (int i = 0; i < 64; ++i)
    xs.push_back(Vec(model.contact_point) + 1e-4 * (i - 32) * Vec(model.normal));
  Vector3d sum = Vector3d::Zero();
  {
    somasim::testing::AllocationCounter counter;
    for (int k = 0; k < 100000; ++k) {
      sum += EvaluateLocalForceModel(model, xs[static_cast<size_t>(k) % xs.size()],
                                     Vector3d(0.0, 0.0, -0.01))
                 .force;
    }
    EXPECT_EQ(counter.count(), 0);
  }
  EXPECT_TRUE(sum.allFinite());
}

// LocalForceModelError names the bad field, and accepts good models.
TEST(LocalForceModelError, NamesEachBadFieldAndAcceptsGoodModels) {
  const LocalForceModel good = GoodModel();
  EXPECT_EQ(LocalForceModelError(good), nullptr);
  EXPECT_EQ(LocalForceModelError(LocalForceModel()), nullptr);  // the default: nothing touched
  const auto error_of = [&good](const std::function<void(LocalForceModel*)>& spoil) {
    LocalForceModel m = good;
    spoil(&m);
    const char* e = LocalForceModelError(m);
    return std::string(e == nullptr ? "accepted" : e);
  };
  const auto has = [](const std::string& text, const std::string& part) {
    return text.find(part) != std::string::npos;
  };
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->sim_time = kNaN; }), "sim_time"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->contact_point[1] = kInf; }),
                  "contact_point is not finite"));
  EXPECT_TRUE(
      has(error_of([](LocalForceModel* m) { m->normal[0] = kNaN; }), "normal is not finite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->contact_stiffness = -kInf; }),
                  "contact_stiffness is not finite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->grasp_anchor[2] = kNaN; }),
                  "grasp_anchor is not finite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Mat(m->grasp_stiffness)(1, 2) = kInf; }),
                  "grasp_stiffness is not finite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Mat(m->tissue_stiffness)(0, 0) = kNaN; }),
                  "tissue_stiffness is not finite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->damping = kNaN; }), "damping"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->force_limit = kInf; }), "force_limit"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Vec(m->normal) *= 1.001; }),
                  "normal is not a unit vector"));
  // Out of contact the normal is not used: its length does not matter.
  EXPECT_EQ(error_of([](LocalForceModel* m) {
              m->in_contact = false;
              Vec(m->normal) *= 2.0;
            }),
            "accepted");
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->contact_stiffness = -1.0; }),
                  "contact_stiffness is negative"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Mat(m->grasp_stiffness)(0, 1) += 1.0; }),
                  "grasp_stiffness is not symmetric"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Mat(m->grasp_stiffness)(2, 2) = -50.0; }),
                  "grasp_stiffness is not positive semi-definite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) {
                    Mat(m->grasp_stiffness) = Vector3d(10.0, 10.0, 0.0).asDiagonal();
                    Mat(m->grasp_stiffness)(0, 2) = Mat(m->grasp_stiffness)(2, 0) = 1.0;  // det < 0
                  }),
                  "grasp_stiffness is not positive semi-definite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Mat(m->tissue_stiffness)(2, 0) -= 1.0; }),
                  "tissue_stiffness is not symmetric"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { Mat(m->tissue_stiffness) *= -1.0; }),
                  "tissue_stiffness is not positive semi-definite"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->damping = -0.1; }), "damping is negative"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->force_limit = 0.0; }),
                  "force_limit is not positive"));
  EXPECT_TRUE(has(error_of([](LocalForceModel* m) { m->force_limit = -2.0; }),
                  "force_limit is not positive"));
  // A PSD but singular grasp stiffness (a grasp stiff in two directions only) is fine.
  EXPECT_EQ(error_of([](LocalForceModel* m) {
              Mat(m->grasp_stiffness) = Vector3d(10.0, 10.0, 0.0).asDiagonal();
            }),
            "accepted");
}

std::string MakeError(const ContactForModel& c) {
  try {
    MakeLocalForceModel(c, 1, 0.0);
  } catch (const std::invalid_argument& e) {
    return e.what();
  }
  return "accepted";
}

// The server's contact data are checked too: a bad one is refused by name, never turned into a
// model the haptic node would render.
TEST(MakeLocalForceModel, RefusesBadContactData) {
  const ContactForModel good =
      PressedContact(Vector3d(0.01, 0.02, 0.03).asDiagonal(), Vector3d::UnitZ(), 0.002);
  EXPECT_EQ(MakeError(good), "accepted");
  const auto spoiled = [&good](const std::function<void(ContactForModel*)>& spoil) {
    ContactForModel c = good;
    spoil(&c);
    return MakeError(c);
  };
  const auto has = [](const std::string& text, const std::string& part) {
    return text.find(part) != std::string::npos;
  };
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->tool_stiffness = 0.0; }), "tool_stiffness"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->tool_stiffness = kInf; }), "tool_stiffness"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->proxy.x() = kNaN; }), "proxy"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->device.z() = kInf; }), "device"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->tissue_compliance(1, 1) = kNaN; }),
                  "tissue_compliance must be finite"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->tissue_compliance(0, 1) = 0.01; }),
                  "tissue_compliance must be symmetric"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->tissue_compliance(2, 2) = -0.05; }),
                  "tissue_compliance must be positive semi-definite"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->damping = -1.0; }), "damping"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->force_limit = 0.0; }), "force_limit"));
  EXPECT_TRUE(has(spoiled([](ContactForModel* c) { c->normal.setZero(); }), "normal"));
  // A held node (C = 0): the tool's own stiffness, and a finite display stiffness.
  const LocalForceModel rigid = MakeLocalForceModel(
      [&good] {
        ContactForModel c = good;
        c.tissue_compliance.setZero();
        c.grasping = true;
        return c;
      }(),
      1, 0.0);
  EXPECT_EQ(LocalForceModelError(rigid), nullptr);
  EXPECT_NEAR(rigid.contact_stiffness, good.tool_stiffness, 1e-9);
  EXPECT_LE((Mat(rigid.grasp_stiffness) - good.tool_stiffness * Matrix3d::Identity()).norm(), 1e-9);
}

}  // namespace
}  // namespace somasim::contact
