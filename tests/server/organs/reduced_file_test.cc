// The reduced-model file (server/organs/reduced_file.h): a round trip keeps every array bit for
// bit; a file that is truncated anywhere, corrupted anywhere, of another version, for another
// mesh, inconsistent or holding a model that is not one is refused with its reason.
#include "server/organs/reduced_file.h"

#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "common/mesh_gen/structured_meshes.h"
#include "server/models/fem/fem_model.h"
#include "server/models/fem/hyperelastic.h"
#include "server/models/reduced/pod.h"
#include "server/models/reduced/reduce_fem.h"
#include "tests/support/temp_files.h"

namespace somasim::organs {
namespace {

using Eigen::Vector3d;
using models::reduced::KlModelData;

struct Fixture {
  Fixture() {
    mesh = mesh_gen::BoxGridTets(5, 3, 3, Vector3d::Zero(), Vector3d(0.08, 0.03, 0.03));
    models::fem::FemParameters p;
    p.kind = models::fem::FemKind::kLinear;
    p.youngs_modulus = 5000.0;
    p.poisson_ratio = 0.4;
    const auto fem = models::fem::FemModel::FromTetMesh(mesh, p);
    // Modes: three smooth fields (not a solution: the file does not care), zero at x = 0.
    Eigen::MatrixXd q(3 * fem->num_nodes(), 3);
    for (int32_t i = 0; i < fem->num_nodes(); ++i) {
      const double x = mesh.vertices(0, i);
      for (int a = 0; a < 3; ++a) {
        q(3 * i + a, 0) = a == 2 ? x * x : 0.0;
        q(3 * i + a, 1) = a == 1 ? x * x * x : 0.0;
        q(3 * i + a, 2) = a == 0 ? x : 0.1 * x * mesh.vertices(1, i);
      }
    }
    models::reduced::PodSettings settings;
    settings.energy_fraction = 1.0;
    data = models::reduced::KlDataFromFem(*fem, mesh.vertices,
                                          models::reduced::ModesOfSnapshots(q, settings).modes);
    data.creep = {{7, 0.5, {1.0, 1.3, 1.4}}, {12, 0.25, {1.0, 1.1}}};
    metadata.set_kind("kl_seed000");
    metadata.set_organ("beam");
    metadata.set_mesh("test beam");
    metadata.set_mesh_hash(MeshHash(mesh));
    metadata.set_num_nodes(static_cast<uint64_t>(mesh.vertices.cols()));
    metadata.set_num_tets(static_cast<uint64_t>(mesh.tetrahedra.cols()));
    metadata.set_command("test");
  }
  std::string Bytes() const { return EncodeReducedModel(metadata, data); }
  mesh::TetMesh mesh;
  KlModelData data;
  reduced::ReducedModelMetadata metadata;
};

std::string Refusal(const std::string& bytes, const mesh::TetMesh* mesh) {
  try {
    DecodeReducedModel(bytes, "f.somared", mesh);
  } catch (const ReducedFileError& e) {
    return e.what();
  }
  return "accepted";
}

TEST(ReducedFile, RoundTripKeepsEveryArrayBitForBit) {
  const Fixture f;
  const std::string path = somasim::testing::MakeTempDir("reduced") + "/beam.somared";
  WriteReducedModel(path, f.metadata, f.data);
  const LoadedReducedModel loaded = LoadReducedModel(path, &f.mesh);
  const KlModelData& d = loaded.model->data();
  EXPECT_EQ(d.rest, f.data.rest);
  EXPECT_EQ(d.masses, f.data.masses);
  EXPECT_EQ(d.modes, f.data.modes);
  EXPECT_EQ(d.stiffness_modes, f.data.stiffness_modes);
  EXPECT_EQ(d.reduced_stiffness, f.data.reduced_stiffness);
  ASSERT_EQ(d.creep.size(), 2u);
  EXPECT_EQ(d.creep[1].node, 12);
  EXPECT_EQ(d.creep[1].interval, 0.25);
  EXPECT_EQ(d.creep[0].multiplier, f.data.creep[0].multiplier);
  EXPECT_EQ(loaded.metadata.organ(), "beam");
  EXPECT_EQ(loaded.model->num_modes(), 3);
  // Never overwritten.
  try {
    WriteReducedModel(path, f.metadata, f.data);
    ADD_FAILURE() << "overwrote " << path;
  } catch (const ReducedFileError& e) {
    EXPECT_NE(std::string(e.what()).find("never overwritten"), std::string::npos) << e.what();
  }
  std::filesystem::remove(path);  // for the "cannot read" below
  EXPECT_NE(Refusal("", nullptr).find("no SOMARED magic"), std::string::npos);
  try {
    LoadReducedModel(path, nullptr);
    ADD_FAILURE();
  } catch (const ReducedFileError& e) {
    EXPECT_NE(std::string(e.what()).find("cannot read"), std::string::npos);
  }
}

TEST(ReducedFile, RefusesATruncatedFileAtEveryLength) {
  const Fixture f;
  const std::string bytes = f.Bytes();
  for (size_t n = 0; n < bytes.size(); n += (n < 64 ? 1 : 97)) {
    const std::string why = Refusal(bytes.substr(0, n), &f.mesh);
    EXPECT_TRUE(why.find("truncated at byte " + std::to_string(n)) != std::string::npos ||
                (n < 8 && why.find("magic") != std::string::npos))
        << n << ": " << why;
  }
  EXPECT_NE(Refusal(bytes + "x", &f.mesh).find("1 bytes after the last array"), std::string::npos);
}

TEST(ReducedFile, RefusesACorruptedByteAnywhere) {
  const Fixture f;
  const std::string bytes = f.Bytes();
  for (size_t at = 20; at < bytes.size(); at += 131) {
    std::string bad = bytes;
    bad[at] = static_cast<char>(bad[at] ^ 0x10);
    const std::string why = Refusal(bad, &f.mesh);
    EXPECT_TRUE(why.find("checksum") != std::string::npos) << at << ": " << why;
  }
  std::string version = bytes;
  version[8] = 2;
  EXPECT_NE(Refusal(version, &f.mesh)
                .find("format version 2; this build reads version 1 (made "
                      "by a newer somasim)"),
            std::string::npos);
}

TEST(ReducedFile, RefusesAFileMadeForAnotherMesh) {
  const Fixture f;
  const std::string bytes = f.Bytes();
  mesh::TetMesh moved = f.mesh;
  moved.vertices(2, 5) += 1e-6;
  EXPECT_NE(Refusal(bytes, &moved).find("made for another mesh (mesh hash"), std::string::npos);
  const mesh::TetMesh other =
      mesh_gen::BoxGridTets(6, 3, 3, Vector3d::Zero(), Vector3d(0.08, 0.03, 0.03));
  EXPECT_NE(Refusal(bytes, &other).find("made for a mesh of 45 nodes"), std::string::npos);
  EXPECT_EQ(Refusal(bytes, nullptr), "accepted");
}

TEST(ReducedFile, RefusesInconsistentMetadataAndBadModelsByName) {
  const Fixture f;
  Fixture g;
  g.metadata.set_num_nodes(44);
  EXPECT_NE(Refusal(g.Bytes(), nullptr).find("'rest' is not 3 × num_nodes (44)"),
            std::string::npos);
  g = Fixture();
  g.metadata.set_kind("pca");
  EXPECT_NE(Refusal(g.Bytes(), nullptr).find("unknown reduced model kind 'pca'"),
            std::string::npos);
  g = Fixture();
  g.data.reduced_stiffness(1, 1) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(Refusal(g.Bytes(), nullptr).find("reduced stiffness is not finite"), std::string::npos);
  g = Fixture();
  g.data.creep[1].node = 4000;
  EXPECT_NE(Refusal(g.Bytes(), nullptr).find("creep curve 1: node 4000 out of range"),
            std::string::npos);
  g = Fixture();
  g.data.reduced_stiffness.conservativeResize(2, 2);
  EXPECT_NE(Refusal(g.Bytes(), nullptr).find("'reduced_stiffness' is not n × n (n = 3)"),
            std::string::npos);
}

// The nonlinear model's file: its material, Prony terms, sampled elements and weights.
struct NonlinearFixture {
  NonlinearFixture() {
    const Fixture f;
    mesh = f.mesh;
    data.rest = mesh.vertices;
    data.masses = f.data.masses;
    data.modes = f.data.modes;
    data.tets = mesh.tetrahedra.leftCols(5);
    data.weights = {1.5, 2.0, 0.25, 3.0, 1.0};
    data.elements = {0, 1, 2, 3, 4};
    data.material = models::fem::LiverNava2008();
    data.prony = models::fem::LiverNava2008Prony();
    metadata = f.metadata;
    metadata.set_kind("");
  }
  std::string Bytes() const { return EncodeReducedModel(metadata, data); }
  mesh::TetMesh mesh;
  models::reduced::NonlinearModelData data;
  reduced::ReducedModelMetadata metadata;
};

using Damage = std::pair<std::function<void(NonlinearFixture*)>, std::string>;

// Each damage done to a copy of each fixture: refused, the message naming what is wrong; and
// each fixture cut 100 bytes short: refused as truncated.
void ExpectRefused(const std::vector<NonlinearFixture>& fixtures,
                   const std::vector<Damage>& damages) {
  for (const NonlinearFixture& f : fixtures) {
    for (const auto& [damage, message] : damages) {
      NonlinearFixture g = f;
      damage(&g);
      const std::string refusal = Refusal(g.Bytes(), nullptr);
      EXPECT_NE(refusal.find(message), std::string::npos) << refusal;
    }
    const std::string bytes = f.Bytes();
    EXPECT_NE(Refusal(bytes.substr(0, bytes.size() - 100), &f.mesh).find("truncated at byte"),
              std::string::npos);
  }
}

TEST(ReducedFile, TheNonlinearModelRoundTripsWithItsMaterialAndCubature) {
  const NonlinearFixture f;
  const LoadedReducedModel loaded = DecodeReducedModel(f.Bytes(), "nl.somared", &f.mesh);
  ASSERT_EQ(loaded.model, nullptr);
  ASSERT_NE(loaded.nonlinear, nullptr);
  EXPECT_EQ(loaded.metadata.kind(), "ecsw_nonlinear");
  const models::reduced::NonlinearModelData& d = loaded.nonlinear->data();
  EXPECT_EQ(d.rest, f.data.rest);
  EXPECT_EQ(d.modes, f.data.modes);
  EXPECT_EQ(d.tets, f.data.tets);
  EXPECT_EQ(d.weights, f.data.weights);
  EXPECT_EQ(d.elements, f.data.elements);
  EXPECT_EQ(d.material.c, f.data.material.c);
  EXPECT_EQ(d.material.d, f.data.material.d);
  ASSERT_EQ(d.prony.size(), 2u);
  EXPECT_EQ(d.prony[1].tau, f.data.prony[1].tau);
  EXPECT_EQ(loaded.num_modes(), 3);
  // Released as the tissue model it is.
  LoadedReducedModel again = DecodeReducedModel(f.Bytes(), "nl.somared", &f.mesh);
  const std::unique_ptr<models::TissueModel> model = again.Release();
  EXPECT_EQ(model->num_nodes(), f.mesh.vertices.cols());
  // Truncated anywhere, or for another mesh: refused.
  const std::string bytes = f.Bytes();
  for (size_t n = 64; n < bytes.size(); n += 211) {
    EXPECT_NE(Refusal(bytes.substr(0, n), &f.mesh).find("truncated at byte"), std::string::npos);
  }
  mesh::TetMesh moved = f.mesh;
  moved.vertices(0, 3) += 1e-6;
  EXPECT_NE(Refusal(bytes, &moved).find("made for another mesh"), std::string::npos);
}

TEST(ReducedFile, TheNonlinearModelsStaticCorrectionRoundTripsAndIsChecked) {
  NonlinearFixture f;
  const Eigen::Index dofs = f.data.modes.rows();
  f.data.correction_nodes = {2, 5};
  f.data.corrections = Eigen::MatrixXd::Random(dofs, 6) * 1e-3;
  f.data.correction_magnitudes = {0.1, 0.5};
  f.data.correction_scales = Eigen::MatrixXd::Constant(2, 2, 0.75);
  const LoadedReducedModel loaded = DecodeReducedModel(f.Bytes(), "nl.somared", &f.mesh);
  ASSERT_NE(loaded.nonlinear, nullptr);
  EXPECT_EQ(loaded.metadata.arrays_size(), 10);
  EXPECT_EQ(loaded.nonlinear->data().correction_nodes, f.data.correction_nodes);
  EXPECT_EQ(loaded.nonlinear->data().corrections, f.data.corrections);
  EXPECT_EQ(loaded.nonlinear->data().correction_magnitudes, f.data.correction_magnitudes);
  EXPECT_EQ(loaded.nonlinear->data().correction_scales, f.data.correction_scales);
  // Without one the file has its 6 arrays, as before the correction existed.
  EXPECT_EQ(
      DecodeReducedModel(NonlinearFixture().Bytes(), "nl.somared", &f.mesh).metadata.arrays_size(),
      6);
  // Each damaged copy is refused, naming what is wrong.
  const std::vector<Damage> damages = {
      {[dofs](NonlinearFixture* g) { g->data.corrections = Eigen::MatrixXd::Zero(dofs, 3); },
       "'corrections' is not 3 num_nodes × 3c"},  // 3 columns for 2 nodes
      {[](NonlinearFixture* g) {
         g->data.correction_nodes = {2, 4000};
       },
       "'correction_nodes' holds 4000"},
      {[](NonlinearFixture* g) {
         g->data.correction_scales = Eigen::MatrixXd::Constant(3, 2, 0.75);
       },
       "'correction_scales' is not M × c"},  // 3 rows for 2 magnitudes
      {[](NonlinearFixture* g) {
         g->data.correction_magnitudes = {0.5, 0.1};
       },
       "increasing"},
      {[](NonlinearFixture* g) { g->data.correction_scales(1, 1) = -0.5; },
       "a correction scale is not finite and >= 0"},
      {[](NonlinearFixture* g) {
         g->data.correction_nodes = {2, 2};
       },
       "listed twice"},
      {[](NonlinearFixture* g) {
         g->data.corrections(7, 4) = std::numeric_limits<double>::infinity();
       },
       "a correction is not finite"},
  };
  ExpectRefused({f}, damages);  // and truncated inside the corrections
}

// A Petrov–Galerkin model's test basis Ψ: the last array, with or without the correction.
TEST(ReducedFile, ThePetrovGalerkinTestBasisRoundTripsAndIsChecked) {
  NonlinearFixture f;
  const Eigen::Index dofs = f.data.modes.rows();
  f.data.test_modes = Eigen::MatrixXd::Random(dofs, f.data.modes.cols()) * 1e-2;
  const LoadedReducedModel loaded = DecodeReducedModel(f.Bytes(), "nl.somared", &f.mesh);
  ASSERT_NE(loaded.nonlinear, nullptr);
  EXPECT_EQ(loaded.metadata.arrays_size(), 7);
  EXPECT_EQ(loaded.metadata.arrays(6).name(), "test_modes");
  EXPECT_EQ(loaded.nonlinear->data().test_modes, f.data.test_modes);
  EXPECT_TRUE(loaded.nonlinear->petrov_galerkin());
  NonlinearFixture both = f;
  both.data.correction_nodes = {2, 5};
  both.data.corrections = Eigen::MatrixXd::Random(dofs, 6) * 1e-3;
  const LoadedReducedModel loaded_both = DecodeReducedModel(both.Bytes(), "nl.somared", &f.mesh);
  ASSERT_NE(loaded_both.nonlinear, nullptr);
  EXPECT_EQ(loaded_both.metadata.arrays_size(), 11);
  EXPECT_EQ(loaded_both.nonlinear->data().test_modes, f.data.test_modes);
  EXPECT_EQ(loaded_both.nonlinear->data().corrections, both.data.corrections);
  // A Galerkin model has none.
  EXPECT_FALSE(DecodeReducedModel(NonlinearFixture().Bytes(), "nl.somared", &f.mesh)
                   .nonlinear->petrov_galerkin());
  const std::vector<Damage> damages = {
      {[dofs](NonlinearFixture* g) { g->data.test_modes = Eigen::MatrixXd::Zero(dofs, 2); },
       "'test_modes' is not 3 num_nodes × n like 'modes'"},
      {[dofs](NonlinearFixture* g) { g->data.test_modes = Eigen::MatrixXd::Zero(dofs - 3, 3); },
       "'test_modes' is not 3 num_nodes × n like 'modes'"},
      {[](NonlinearFixture* g) { g->data.test_modes(4, 1) = std::nan(""); },
       "a test mode is not finite"},
  };
  ExpectRefused({f, both}, damages);
}

// The correction's part in the modes: after the correction's four arrays, before the test basis.
TEST(ReducedFile, TheCorrectionsPartInTheModesRoundTripsAndIsChecked) {
  NonlinearFixture f;
  const Eigen::Index dofs = f.data.modes.rows(), n = f.data.modes.cols();
  f.data.correction_nodes = {2, 5};
  f.data.corrections = Eigen::MatrixXd::Random(dofs, 6) * 1e-3;
  f.data.correction_magnitudes = {0.1, 0.5};
  f.data.correction_scales = Eigen::MatrixXd::Constant(2, 2, 0.75);
  f.data.correction_coefficients = Eigen::MatrixXd::Random(n, 16) * 1e-2;  // n × 4 M c
  NonlinearFixture all = f;
  all.data.test_modes = Eigen::MatrixXd::Random(dofs, n) * 1e-2;
  for (const NonlinearFixture* g : {&f, &all}) {
    const LoadedReducedModel loaded = DecodeReducedModel(g->Bytes(), "nl.somared", &g->mesh);
    ASSERT_NE(loaded.nonlinear, nullptr);
    EXPECT_EQ(loaded.metadata.arrays_size(), g == &f ? 11 : 12);
    EXPECT_EQ(loaded.metadata.arrays(10).name(), "correction_coefficients");
    EXPECT_EQ(loaded.nonlinear->data().correction_coefficients, f.data.correction_coefficients);
    EXPECT_EQ(loaded.nonlinear->data().test_modes, g->data.test_modes);
  }
  const std::vector<Damage> damages = {
      {[n](NonlinearFixture* g) { g->data.correction_coefficients = Eigen::MatrixXd::Zero(n, 12); },
       "'correction_coefficients' is not n × 4Mc"},
      {[n](NonlinearFixture* g) {
         g->data.correction_coefficients = Eigen::MatrixXd::Zero(n + 1, 16);
       },
       "'correction_coefficients' is not n × 4Mc"},
      {[](NonlinearFixture* g) { g->data.correction_coefficients(1, 7) = std::nan(""); },
       "a correction coefficient is not finite"},
  };
  ExpectRefused({f, all}, damages);
}

TEST(ReducedFile, RefusesABadNonlinearModelByName) {
  const auto refused = [](const NonlinearFixture& g) { return Refusal(g.Bytes(), nullptr); };
  NonlinearFixture g;
  g.data.weights[2] = -1.0;
  EXPECT_NE(refused(g).find("a weight is not > 0"), std::string::npos) << refused(g);
  g = NonlinearFixture();
  g.data.weights.pop_back();
  EXPECT_NE(refused(g).find("'weights' is not m × 1"), std::string::npos) << refused(g);
  g = NonlinearFixture();
  g.data.tets(2, 1) = 4000;
  EXPECT_NE(refused(g).find("'tets' holds 4000"), std::string::npos) << refused(g);
  g = NonlinearFixture();
  g.data.material.c[0] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(refused(g).find("material"), std::string::npos) << refused(g);
  g = NonlinearFixture();
  g.data.prony = {{0.9, 1.0}, {0.9, 2.0}};
  EXPECT_NE(refused(g).find("the Prony gammas sum above 1"), std::string::npos) << refused(g);
  g = NonlinearFixture();
  g.metadata.mutable_hyperelastic()->set_law("ogden");
  // EncodeReducedModel writes the law from the data: corrupt it after encoding instead.
  std::string bytes = g.Bytes();
  const size_t at = bytes.find("reduced_polynomial");
  ASSERT_NE(at, std::string::npos);
  bytes.replace(at, 5, "ogden");  // the metadata's checksum then fails first
  EXPECT_NE(Refusal(bytes, nullptr).find("checksum"), std::string::npos);
  g = NonlinearFixture();
  g.data.elements = {0, 1, -1, 3, 4};
  EXPECT_NE(refused(g).find("'elements' mixes indices and -1"), std::string::npos) << refused(g);
}

}  // namespace
}  // namespace somasim::organs
