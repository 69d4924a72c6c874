// somasim's FEM against an independent finite-element code: CalculiX (ccx 2.20, Debian's
// calculix-ccx, run as a program). Both solve the same discrete problem — the same linear
// tetrahedra (C3D4: one integration point, like ours), the same material in the Abaqus
// convention, the same supports and nodal loads — so every node's displacement must agree to
// the solvers' tolerances, for small strain (linear) and for large deformation (NLGEOM: St
// Venant–Kirchhoff, neo-Hookean, reduced polynomial N = 3, the form of seed 000's liver law
// that CalculiX accepts; it reads at most N = 3).
#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "common/mesh_io/mesh_io.h"
#include "tests/server/solve/solve_fixtures.h"
#include "tests/support/mesh_fixtures.h"
#include "tests/support/run_program.h"

namespace somasim::solve {
namespace {

constexpr double kLength = 0.1, kWidth = 0.02;  // [m] a cantilever bar, bent along -y

struct Case {
  const char* name;
  const char* ccx_material;  // the *MATERIAL cards
  bool nlgeom;               // CalculiX: geometric nonlinearity
  const char* scene_model;   // somasim's model and material
  const char* scene_material;
  double force;  // [N], total along -y on the free end
};

// CalculiX's input: nodes and C3D4 elements (1-based; corner order as ours: positive volume),
// the clamped face, nodal loads shared equally by the free end's nodes, tight convergence.
std::string CalculixInput(const mesh_io::MeshData& bar, const Case& c) {
  std::ostringstream out;
  out.precision(17);
  out << "*NODE, NSET=NALL\n";
  std::vector<int64_t> clamped, loaded;
  for (Eigen::Index i = 0; i < bar.vertices.cols(); ++i) {
    out << i + 1 << ", " << bar.vertices(0, i) << ", " << bar.vertices(1, i) << ", "
        << bar.vertices(2, i) << "\n";
    if (bar.vertices(0, i) < 1e-9) clamped.push_back(i + 1);
    if (bar.vertices(0, i) > kLength - 1e-9) loaded.push_back(i + 1);
  }
  out << "*ELEMENT, TYPE=C3D4, ELSET=EALL\n";
  for (Eigen::Index e = 0; e < bar.tetrahedra.cols(); ++e) {
    out << e + 1;
    for (int a = 0; a < 4; ++a) out << ", " << bar.tetrahedra(a, e) + 1;
    out << "\n";
  }
  out << "*NSET, NSET=CLAMPED\n";
  for (const int64_t n : clamped) out << n << ",\n";
  out << "*MATERIAL, NAME=M\n" << c.ccx_material << "\n*SOLID SECTION, ELSET=EALL, MATERIAL=M\n";
  out << (c.nlgeom ? "*STEP, NLGEOM, INC=1000\n" : "*STEP\n") << "*STATIC\n0.1, 1.0, 1e-6, 0.2\n"
      << "*CONTROLS, PARAMETERS=FIELD\n1e-10, 1e-10\n*BOUNDARY\nCLAMPED, 1, 3\n*CLOAD\n";
  for (const int64_t n : loaded) {
    out << n << ", 2, " << -c.force / static_cast<double>(loaded.size()) << "\n";
  }
  out << "*NODE PRINT, NSET=NALL\nU\n*END STEP\n";
  return out.str();
}

// The displacements of the last "displacements (vx,vy,vz) for set NALL" block of a .dat file,
// 3 per node in node order.
std::vector<double> CalculixDisplacements(const std::string& dat, int64_t nodes) {
  const size_t at = dat.rfind("displacements (vx,vy,vz)");
  std::vector<double> u(3 * static_cast<size_t>(nodes), std::nan(""));
  if (at == std::string::npos) return u;
  std::istringstream in(dat.substr(dat.find('\n', at)));
  int64_t node = 0;
  double x = 0.0, y = 0.0, z = 0.0;
  while (in >> node >> x >> y >> z) {
    if (node < 1 || node > nodes) break;
    const auto i = static_cast<size_t>(node - 1);
    u[3 * i] = x;
    u[3 * i + 1] = y;
    u[3 * i + 2] = z;
  }
  return u;
}

class CalculixCrossCheck : public ::testing::TestWithParam<Case> {};

TEST_P(CalculixCrossCheck, EveryNodeMovesAsInCalculix) {
  if (somasim::testing::RunCommand("command -v ccx").status != 0) {
    GTEST_SKIP() << "ccx (Debian package calculix-ccx, which deploy/install-deps.sh installs) "
                    "is not on PATH";
  }
  const Case& c = GetParam();
  const std::string dir = somasim::testing::MakeTempDir(std::string("ccx_") + c.name);
  const mesh_io::MeshData bar = somasim::testing::BoxTets(8, 2, 2, kLength, kWidth, kWidth);
  mesh_io::WriteMeshFile(dir + "/bar.vtu", bar, {});
  somasim::testing::WriteBytes(dir + "/job.inp", CalculixInput(bar, c));
  const somasim::testing::ToolRun ccx =
      somasim::testing::RunCommand("cd " + dir + " && ccx -i job");
  ASSERT_EQ(ccx.status, 0) << ccx.out;
  ASSERT_TRUE(somasim::testing::Contains(ccx.out, "Job finished")) << ccx.out;
  const int64_t n = bar.vertices.cols();
  const std::vector<double> reference =
      CalculixDisplacements(somasim::testing::Slurp(dir + "/job.dat"), n);

  const std::string scene =
      std::string(
          "format_version: 1\nname: \"bar\"\norgan {\n  id: \"bar\"\n  file: \"bar.vtu\"\n") +
      "  model { " + c.scene_model + " }\n  material { density: 1000 " + c.scene_material +
      " }\n  fixed { box { min { x: -1 y: -1 z: -1 } max { x: 1e-9 y: 1 z: 1 } } }\n}\n"
      "load {\n  organ: \"bar\"\n  region { box { min { x: 0.0999999 y: -1 z: -1 } "
      "max { x: 1 y: 1 z: 1 } } }\n  force { y: " +
      std::to_string(-c.force) + " }\n}\nanalysis { static_solve { load_steps: 4 } }\n";
  const SolveSummary summary = somasim::testing::SolveText(dir, scene);
  ASSERT_TRUE(summary.converged);
  const std::vector<double> ours =
      somasim::testing::ReadVtu(dir + "/out/bar_0.vtu", "displacement").values;
  ASSERT_EQ(ours.size(), reference.size());
  double largest = 0.0, worst = 0.0;
  for (size_t k = 0; k < ours.size(); ++k) {
    ASSERT_TRUE(std::isfinite(reference[k])) << "CalculIX printed no displacement " << k;
    largest = std::max(largest, std::abs(reference[k]));
    worst = std::max(worst, std::abs(ours[k] - reference[k]));
  }
  // CalculiX prints 7 significant digits; both stop Newton near 1e-8 of the load.
  EXPECT_LT(worst, 2e-5 * largest) << c.name << ": tip deflection " << largest << " m";
  EXPECT_GT(largest, c.nlgeom ? 0.015 : 1e-3) << "the case should bend the bar visibly";
  std::cout << c.name << ": largest displacement " << largest << " m, largest difference " << worst
            << " m\n";
  RecordProperty("largest_m", std::to_string(largest));
  RecordProperty("worst_difference_m", std::to_string(worst));
}

INSTANTIATE_TEST_SUITE_P(
    Bar, CalculixCrossCheck,
    ::testing::Values(
        Case{"linear", "*ELASTIC\n10000, 0.3", false, "fem_linear {}",
             "youngs_modulus: 10000 poisson_ratio: 0.3", 1e-3},
        Case{"stvk", "*ELASTIC\n10000, 0.3", true, "fem_hyperelastic {}",
             "youngs_modulus: 10000 poisson_ratio: 0.3 stvk {}", 0.03},
        Case{"neo_hookean", "*HYPERELASTIC, NEO HOOKE\n1700, 4e-5", true, "fem_hyperelastic {}",
             "neo_hookean { c10: 1700 d1: 4e-5 }", 0.04},
        Case{"reduced_polynomial3",
             "*HYPERELASTIC, REDUCED POLYNOMIAL, N=3\n883.8, 1707.9, 1449.9, 2.278e-5, 1e-6, 1e-6",
             true, "fem_hyperelastic {}",
             "reduced_polynomial { c: [883.8, 1707.9, 1449.9] d: [2.278e-5, 1e-6, 1e-6] }", 0.03}),
    [](const ::testing::TestParamInfo<Case>& p) { return std::string(p.param.name); });

}  // namespace
}  // namespace somasim::solve
