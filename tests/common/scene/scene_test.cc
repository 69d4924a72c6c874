// Scenes: a good scene loads with every field; a bad one is refused with the file, the line and
// the field named — syntax errors, unknown fields, out-of-range and non-finite values, unknown
// organs and references, histories that go back in time — and never half-loaded.
#include "common/scene/scene.h"

#include <google/protobuf/text_format.h>
#include <gtest/gtest.h>

#include <string>

namespace somasim::scene {
namespace {

const char* const kGood = R"(format_version: 1
name: "two organs"
organ {
  id: "kidney"
  builtin: "kidney424"
  model { fem_corotational {} dt: 0.01 }
  material { density: 1050 youngs_modulus: 5000 poisson_ratio: 0.45 rayleigh_mass: 0.1 }
  fixed { sphere { center { x: 0 y: 0 z: 0 } radius: 0.01 } }
}
organ {
  id: "patch"
  file: "patch.obj"
  unit: "mm"
  model { mass_spring { implicit: true } }
  material { density: 1000 youngs_modulus: 3000 damping_ratio: 0.1 }
}
load {
  organ: "kidney"
  region { nodes { id: 3 id: 4 } }
  force { z: -0.5 }
  history { t: 0 scale: 0 }
  history { t: 1 scale: 1 }
}
gravity { z: -9.81 }
analysis { quasi_static { end_time: 2 dt: 0.1 } }
output { time: 1 time: 2 }
)";

// Parses `text`; expects a SceneError whose message names `line` and contains `what`.
void ExpectRefused(const std::string& text, int line, const std::string& field,
                   const std::string& what) {
  try {
    ParseScene(text, "bad.scene.txtpb");
    ADD_FAILURE() << "accepted a scene that should fail with: " << what;
  } catch (const SceneError& e) {
    EXPECT_EQ(e.line(), line) << e.what();
    EXPECT_EQ(e.field(), field) << e.what();
    EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    EXPECT_EQ(std::string(e.what()).rfind("bad.scene.txtpb", 0), 0u) << e.what();
  }
}

// kGood with the first occurrence of `from` replaced by `to`.
std::string Edit(const std::string& from, const std::string& to) {
  std::string text = kGood;
  const size_t at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  return text.replace(at, from.size(), to);
}

TEST(Scene, LoadsEveryField) {
  const Scene scene = ParseScene(kGood, "good.scene.txtpb");
  ASSERT_EQ(scene.organ_size(), 2);
  EXPECT_EQ(scene.organ(0).builtin(), "kidney424");
  EXPECT_TRUE(scene.organ(0).model().has_fem_corotational());
  EXPECT_DOUBLE_EQ(scene.organ(0).material().poisson_ratio(), 0.45);
  EXPECT_EQ(scene.organ(1).unit(), "mm");
  EXPECT_TRUE(scene.organ(1).model().mass_spring().implicit());
  ASSERT_EQ(scene.load_size(), 1);
  EXPECT_EQ(scene.load(0).region().nodes().id_size(), 2);
  EXPECT_DOUBLE_EQ(scene.gravity().z(), -9.81);
  EXPECT_DOUBLE_EQ(scene.analysis().quasi_static().dt(), 0.1);
  EXPECT_EQ(scene.output().time_size(), 2);
}

TEST(Scene, TheExampleScenesLoad) {
  for (const char* name : {"liver_creep", "liver_creep_half"}) {
    const Scene scene =
        LoadSceneFile(std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/" + name + ".scene.txtpb");
    EXPECT_EQ(scene.organ(0).builtin(), "liver4055");
    EXPECT_TRUE(scene.organ(0).material().liver_nava2008_prony());
    EXPECT_EQ(scene.load(0).region().nodes().id(0), 1738);
  }
}

TEST(Scene, RefusesSyntaxErrorsWithTheirLine) {
  ExpectRefused(Edit("density: 1050", "density: 1050 }"), 7, "",
                "no field named \"youngs_modulus\"");
  ExpectRefused(Edit("name: \"two organs\"", "name: \"two organs\"\nspeed: 3"), 3, "",
                "no field named \"speed\"");
  ExpectRefused(Edit("radius: 0.01", "radius: \"big\""), 8, "", "Expected double");
  ExpectRefused("", 1, "format_version", "reads version 1");
  ExpectRefused("format_version: 1", 1, "", "has no organ");
}

TEST(Scene, RefusesBadValuesNamingTheField) {
  ExpectRefused(Edit("format_version: 1", "format_version: 2"), 1, "format_version",
                "reads version 1");
  ExpectRefused(Edit("density: 1050", "density: -1"), 7, "organ[0].material.density", "> 0");
  ExpectRefused(Edit("youngs_modulus: 5000", "youngs_modulus: nan"), 7,
                "organ[0].material.youngs_modulus", "finite");
  ExpectRefused(Edit("poisson_ratio: 0.45", "poisson_ratio: 0.5"), 7,
                "organ[0].material.poisson_ratio", "(-1, 0.5)");
  ExpectRefused(Edit("radius: 0.01", "radius: 0"), 8, "organ[0].fixed[0].sphere.radius", "> 0");
  ExpectRefused(Edit("dt: 0.01", "dt: -0.01"), 6, "organ[0].model.dt", ">= 0");
  ExpectRefused(Edit("implicit: true", "implicit: true anchor_stiffness: -5"), 14,
                "organ[1].model.mass_spring.anchor_stiffness", ">= 0");
  ExpectRefused(Edit("implicit: true", "implicit: true anchor_stiffness: nan"), 14,
                "organ[1].model.mass_spring.anchor_stiffness", "finite");
  ExpectRefused(Edit("unit: \"mm\"", "unit: \"inch\""), 13, "organ[1].unit", "m, cm or mm");
  ExpectRefused(Edit("id: 3 id: 4", "id: 3 id: -4"), 19, "load[0].region.nodes.id[1]", ">= 0");
  ExpectRefused(Edit("force { z: -0.5 }", "force { z: inf }"), 20, "load[0].force", "finite");
  ExpectRefused(Edit("force { z: -0.5 }", "pressure: nan"), 20, "load[0].pressure", "finite");
  ExpectRefused(Edit("gravity { z: -9.81 }", "gravity { z: nan }"), 24, "gravity", "finite");
  ExpectRefused(Edit("end_time: 2 dt: 0.1", "end_time: 2 dt: 0"), 25, "analysis.quasi_static.dt",
                "> 0");
  ExpectRefused(Edit("time: 1 time: 2", "time: 2 time: 1"), 26, "output.time[1]", "increase");
}

TEST(Scene, RefusesUnknownNamesAndReferences) {
  ExpectRefused(Edit("builtin: \"kidney424\"", "builtin: \"heart9\""), 5, "organ[0].builtin",
                "unknown organ \"heart9\"");
  ExpectRefused(Edit("id: \"patch\"", "id: \"kidney\""), 11, "organ[1].id", "used twice");
  ExpectRefused(Edit("id: \"patch\"", "id: \"my patch\""), 11, "organ[1].id", "letters");
  ExpectRefused(Edit("organ: \"kidney\"", "organ: \"liver\""), 18, "load[0].organ", "not an organ");
  ExpectRefused(Edit("history { t: 1 scale: 1 }", "history { t: 0 scale: 1 }"), 22,
                "load[0].history[1].t", "increase");
  ExpectRefused(Edit("  model { mass_spring { implicit: true } }\n", ""), 10, "organ[1].model",
                "needs a kind");
  ExpectRefused(Edit("  region { nodes { id: 3 id: 4 } }\n", ""), 17, "load[0].region",
                "needs a box, a sphere or nodes");
}

const char* const kStone = R"(format_version: 1
organ { id: "kidney" builtin: "kidney424" model { fem_corotational {} }
        material { density: 1050 youngs_modulus: 20000 } }
rigid_body {
  id: "stone"
  sphere { center { z: 0.02 } radius: 0.006 }
}
tool { id: "left" grasper { jaw_length: 0.02 } }
tool { id: "right" probe {} stiffness: 500 }
tool { id: "knife" scalpel {} shaft_length: 0.35 }
tool { id: "scope" camera {} }
)";

// kStone with the first occurrence of `from` replaced by `to`.
std::string EditStone(const std::string& from, const std::string& to) {
  std::string text = kStone;
  const size_t at = text.find(from);
  EXPECT_NE(at, std::string::npos) << from;
  return text.replace(at, from.size(), to);
}

TEST(Scene, RigidBodiesAndToolsLoadAndTheirValuesAreChecked) {
  const Scene scene = ParseScene(kStone, "stone.scene.txtpb");
  ASSERT_EQ(scene.rigid_body_size(), 1);
  EXPECT_DOUBLE_EQ(scene.rigid_body(0).sphere().radius(), 0.006);
  ASSERT_EQ(scene.tool_size(), 4);
  EXPECT_DOUBLE_EQ(scene.tool(0).grasper().jaw_length(), 0.02);
  EXPECT_DOUBLE_EQ(scene.tool(1).stiffness(), 500.0);
  EXPECT_TRUE(scene.tool(3).has_camera());

  ExpectRefused(EditStone("radius: 0.006", "radius: 0.3"), 6, "rigid_body[0].sphere.radius",
                "(0, 0.2]");
  ExpectRefused(EditStone("center { z: 0.02 }", "center { z: nan }"), 6,
                "rigid_body[0].sphere.center", "finite");
  ExpectRefused(EditStone("  sphere { center { z: 0.02 } radius: 0.006 }\n", "  density: 2000\n"),
                4, "rigid_body[0]", "needs a sphere");
  ExpectRefused(EditStone("  id: \"stone\"", "  id: \"stone\" density: -3"), 5,
                "rigid_body[0].density", "> 0");
  ExpectRefused(EditStone("id: \"stone\"", "id: \"kidney\""), 5, "rigid_body[0].id", "used twice");
  ExpectRefused(EditStone("id: \"right\"", "id: \"left\""), 9, "tool[1].id", "used twice");
  ExpectRefused(EditStone("jaw_length: 0.02", "jaw_length: 0.5"), 8, "tool[0].grasper.jaw_length",
                "(0, 0.3]");
  ExpectRefused(EditStone("stiffness: 500", "stiffness: -500"), 9, "tool[1].stiffness", "> 0");
  ExpectRefused(EditStone("shaft_length: 0.35", "shaft_length: inf"), 10, "tool[2].shaft_length",
                "finite");
  ExpectRefused(EditStone("scope\" camera {}", "scope\""), 11, "tool[3]", "needs a kind");
  // A load names an organ, never a tool or a rigid body.
  ExpectRefused(
      std::string(kStone) + "load { organ: \"stone\" region { nodes { id: 1 } } force {} }", 12,
      "load[0].organ", "not an organ");
}

TEST(Scene, RefusesMaterialsTheModelCannotUse) {
  ExpectRefused(Edit("rayleigh_mass: 0.1", "rayleigh_mass: 0.1 neo_hookean { c10: 1 d1: 1 }"), 7,
                "organ[0].material", "fem_hyperelastic");
  ExpectRefused(Edit("damping_ratio: 0.1", "damping_ratio: 0.1 prony { gamma: 0.5 tau: 1 }"), 15,
                "organ[1].material", "FEM model");
  ExpectRefused(Edit("fem_corotational {}", "fem_hyperelastic {}"), 7, "organ[0].material",
                "needs a law");
  ExpectRefused(Edit("rayleigh_mass: 0.1",
                     "rayleigh_mass: 0.1 prony { gamma: 0.7 tau: 1 } prony { gamma: 0.5 tau: 2 }"),
                7, "organ[0].material.prony[0]", "sum to more than 1");
  ExpectRefused(Edit("rayleigh_mass: 0.1", "rayleigh_mass: 0.1 prony { gamma: 0.2 tau: 0 }"), 7,
                "organ[0].material.prony[0].tau", "> 0");
}

// Every prefix of a good scene either parses (when the cut falls between complete fields) or is
// refused with a SceneError; nothing else escapes.
TEST(Scene, EveryTruncationIsRefusedOrComplete) {
  const std::string text = kGood;
  int refused = 0;
  for (size_t n = 0; n < text.size(); ++n) {
    try {
      ParseScene(std::string_view(text).substr(0, n), "cut.scene.txtpb");
    } catch (const SceneError&) {
      ++refused;
    }
  }
  EXPECT_GT(refused, static_cast<int>(text.size()) / 2);
}

TEST(Scene, ReducedPolynomialNeedsItsCoefficients) {
  const std::string head =
      "format_version: 1\norgan {\n  id: \"o\"\n  builtin: \"plate192\"\n"
      "  model { fem_hyperelastic {} }\n  material {\n    density: 1000\n";  // lines 1–7
  const auto scene = [&](const std::string& law) { return head + law + "\n  }\n}\n"; };
  const Scene good = ParseScene(scene("reduced_polynomial { c: [1000, 500] d: [1e-4, 0] }"), "s");
  EXPECT_EQ(good.organ(0).material().reduced_polynomial().c_size(), 2);
  ExpectRefused(scene("reduced_polynomial { d: 1e-4 }"), 8, "organ[0].material.reduced_polynomial",
                "1 to 5 coefficients c");
  ExpectRefused(scene("reduced_polynomial { c: [1, 2, 3, 4, 5, 6] d: 1e-4 }"), 8,
                "organ[0].material.reduced_polynomial", "1 to 5 coefficients c");
  ExpectRefused(scene("reduced_polynomial { c: 1 }"), 8, "organ[0].material.reduced_polynomial",
                "1 to 3 coefficients d");
  ExpectRefused(scene("reduced_polynomial { c: [0, 1] d: 1e-4 }"), 8,
                "organ[0].material.reduced_polynomial.c[0]", "C10");
  ExpectRefused(scene("reduced_polynomial { c: [1, nan] d: 1e-4 }"), 8,
                "organ[0].material.reduced_polynomial.c[1]", "finite");
  ExpectRefused(scene("reduced_polynomial { c: 1 d: [1e-4, -1] }"), 8,
                "organ[0].material.reduced_polynomial.d[1]", ">= 0");
}

// somasim-reduce's sampling plans (reduction blocks) and reduced organs (reduced_kl): the
// repository's reduction scenes load; bad plans are refused by line and field.
TEST(Scene, ReductionPlansAndReducedOrgansAreChecked) {
  for (const char* name : {"liver_reduction", "kidney_reduction"}) {
    const Scene scene =
        LoadSceneFile(std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/" + name + ".scene.txtpb");
    ASSERT_EQ(scene.reduction_size(), 1) << name;
    EXPECT_GE(scene.reduction(0).interaction_size(), 2) << name;
  }
  const std::string plan = std::string(kGood) +
                           "reduction {\n"                        // line 27
                           "  organ: \"kidney\"\n"                // 28
                           "  interaction { nodes { id: 5 } }\n"  // 29
                           "  force: 0.1\n"                       // 30
                           "  directions: 3\n"                    // 31
                           "  energy_fraction: 0.99\n"            // 32
                           "}\n";
  EXPECT_EQ(ParseScene(plan, "s").reduction(0).force(0), 0.1);
  const auto edit = [&](const std::string& from, const std::string& to) {
    std::string text = plan;
    const size_t at = text.rfind(from);
    EXPECT_NE(at, std::string::npos) << from;
    return text.replace(at, from.size(), to);
  };
  ExpectRefused(edit("organ: \"kidney\"", "organ: \"liver\""), 28, "reduction[0].organ",
                "not an organ of the scene");
  ExpectRefused(edit("organ: \"kidney\"", "organ: \"patch\""), 28, "reduction[0].organ",
                "needs a FEM model");
  ExpectRefused(edit("force: 0.1", "force: -0.1"), 30, "reduction[0].force[0]", "> 0");
  ExpectRefused(edit("directions: 3", "directions: 2"), 31, "reduction[0].directions",
                "1 (the inward normal) or 3");
  ExpectRefused(edit("energy_fraction: 0.99", "energy_fraction: 1.5"), 32,
                "reduction[0].energy_fraction", "[0, 1]");
  ExpectRefused(edit("  interaction { nodes { id: 5 } }\n", ""), 27, "reduction[0]",
                "needs an interaction region");
  ExpectRefused(plan + "reduction { organ: \"kidney\" interaction { nodes { id: 1 } } }\n", 34,
                "reduction[1].organ", "has another reduction");
  // A reduced organ needs its file; its material is the file's (none is asked for).
  const Scene reduced =
      ParseScene(Edit("model { fem_corotational {} dt: 0.01 }\n  material { density: 1050 "
                      "youngs_modulus: 5000 poisson_ratio: 0.45 rayleigh_mass: 0.1 }",
                      "model { reduced_kl { file: \"kidney.somared\" } }"),
                 "s");
  EXPECT_EQ(reduced.organ(0).model().reduced_kl().file(), "kidney.somared");
  ExpectRefused(Edit("model { fem_corotational {} dt: 0.01 }", "model { reduced_kl {} }"), 6,
                "organ[0].model.reduced_kl.file", "is empty");
}

// The EFG model (efg): its settings are optional (unset: the model's defaults), checked when
// given; E, ν and ρ come from the material, whose FEM damping fields it refuses (its damping is
// in model.efg). The repository's EFG scene loads.
TEST(Scene, EfgModelSettingsAreChecked) {
  const Scene file =
      LoadSceneFile(std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/liver288_efg.scene.txtpb");
  EXPECT_TRUE(file.organ(0).model().has_efg());
  EXPECT_FALSE(file.organ(0).model().efg().has_gauss_points());
  const std::string head =
      "format_version: 1\norgan {\n  id: \"o\"\n  builtin: \"liver288\"\n";  // lines 1-4
  const auto scene = [&](const std::string& efg, const std::string& material) {
    return head + "  model { efg { " + efg + " } }\n" +                                // line 5
           "  material { density: 1055 youngs_modulus: 5000 " + material + " }\n}\n";  // 6
  };
  const Scene good = ParseScene(scene("gauss_points: 14 support_scale: 2.5 support_neighbours: 6 "
                                      "penalty_factor: 1e4 rayleigh_mass: 0 rayleigh_stiffness: 0",
                                      "poisson_ratio: 0.35"),
                                "s");
  const Efg& efg = good.organ(0).model().efg();
  EXPECT_EQ(efg.gauss_points(), 14);
  EXPECT_DOUBLE_EQ(efg.support_scale(), 2.5);
  EXPECT_EQ(efg.support_neighbours(), 6);
  EXPECT_DOUBLE_EQ(efg.penalty_factor(), 1e4);
  EXPECT_TRUE(efg.has_rayleigh_mass());  // 0 given: no mass damping, not the default
  EXPECT_DOUBLE_EQ(efg.rayleigh_mass(), 0.0);
  const std::string nu = "poisson_ratio: 0.35";
  ExpectRefused(scene("gauss_points: 5", nu), 5, "organ[0].model.efg.gauss_points", "4 or 14");
  ExpectRefused(scene("gauss_points: 0", nu), 5, "organ[0].model.efg.gauss_points", "4 or 14");
  ExpectRefused(scene("support_scale: 0.5", nu), 5, "organ[0].model.efg.support_scale", ">= 1");
  ExpectRefused(scene("support_scale: inf", nu), 5, "organ[0].model.efg.support_scale", "finite");
  ExpectRefused(scene("support_neighbours: 0", nu), 5, "organ[0].model.efg.support_neighbours",
                "1..64");
  ExpectRefused(scene("support_neighbours: 65", nu), 5, "organ[0].model.efg.support_neighbours",
                "1..64");
  ExpectRefused(scene("penalty_factor: 0", nu), 5, "organ[0].model.efg.penalty_factor", "> 0");
  ExpectRefused(scene("penalty_factor: nan", nu), 5, "organ[0].model.efg.penalty_factor", "finite");
  ExpectRefused(scene("rayleigh_mass: -1", nu), 5, "organ[0].model.efg.rayleigh_mass", ">= 0");
  ExpectRefused(scene("rayleigh_stiffness: nan", nu), 5, "organ[0].model.efg.rayleigh_stiffness",
                "finite");
  // The material: ν in (-1, 0.5) as for FEM; no FEM damping, no QLV terms.
  ExpectRefused(scene("", "poisson_ratio: 0.5"), 6, "organ[0].material.poisson_ratio", "(-1, 0.5)");
  ExpectRefused(scene("", "poisson_ratio: nan"), 6, "organ[0].material.poisson_ratio", "(-1, 0.5)");
  ExpectRefused(scene("", "poisson_ratio: 0.35 rayleigh_mass: 0.5"), 6,
                "organ[0].material.rayleigh_mass", "model.efg.rayleigh_mass");
  ExpectRefused(scene("", "poisson_ratio: 0.35 rayleigh_stiffness: 0.001"), 6,
                "organ[0].material.rayleigh_stiffness", "model.efg.rayleigh_stiffness");
  ExpectRefused(scene("", "poisson_ratio: 0.35 prony { gamma: 0.5 tau: 1 }"), 6,
                "organ[0].material", "FEM model");
  ExpectRefused(head + "  model { efg {} }\n  material { density: 1055 poisson_ratio: 0.35 }\n}\n",
                6, "organ[0].material.youngs_modulus", "> 0");
}

// The EFG hybrid (efg_hybrid): its EFG settings are the nested efg message, checked as model.efg
// is; its surgical region's settings are optional (unset: the model's defaults; no
// region_centre: the tool decides) and checked when given, each fault named by field and line.
// The repository's hybrid scene loads.
TEST(Scene, EfgHybridModelSettingsAreChecked) {
  const Scene file =
      LoadSceneFile(std::string(SOMASIM_TEST_DATA_DIR) + "/scenes/liver288_efg_hybrid.scene.txtpb");
  ASSERT_TRUE(file.organ(0).model().has_efg_hybrid());
  const EfgHybrid& defaults = file.organ(0).model().efg_hybrid();
  EXPECT_DOUBLE_EQ(defaults.region_radius(), 0.05);
  EXPECT_FALSE(defaults.has_region_centre());
  EXPECT_FALSE(defaults.has_follow_tool());
  EXPECT_FALSE(defaults.has_efg());
  const std::string head =
      "format_version: 1\norgan {\n  id: \"o\"\n  builtin: \"liver288\"\n"  // lines 1-4
      "  model {\n    efg_hybrid {\n";                                      // lines 5-6
  const auto scene = [&](const std::string& efg, const std::string& hybrid,
                         const std::string& material) {
    return head + "      efg { " + efg + " }\n" +                                      // line 7
           "      " + hybrid + "\n    }\n  }\n" +                                      // lines 8-10
           "  material { density: 1055 youngs_modulus: 5000 " + material + " }\n}\n";  // 11
  };
  const std::string nu = "poisson_ratio: 0.35";
  const Scene good = ParseScene(
      scene("gauss_points: 14 support_scale: 2.5 support_neighbours: 6 penalty_factor: 1e4 "
            "rayleigh_mass: 0 rayleigh_stiffness: 0.02",
            "region_radius: 0.03 region_centre { x: 0.01 y: -0.02 z: 0.05 } follow_tool: false "
            "follow_fraction: 1 max_region_nodes: 4096",
            nu),
      "s");
  const EfgHybrid& h = good.organ(0).model().efg_hybrid();
  EXPECT_EQ(h.efg().gauss_points(), 14);
  EXPECT_DOUBLE_EQ(h.efg().support_scale(), 2.5);
  EXPECT_EQ(h.efg().support_neighbours(), 6);
  EXPECT_DOUBLE_EQ(h.efg().penalty_factor(), 1e4);
  EXPECT_TRUE(h.efg().has_rayleigh_mass());
  EXPECT_DOUBLE_EQ(h.efg().rayleigh_mass(), 0.0);
  EXPECT_DOUBLE_EQ(h.efg().rayleigh_stiffness(), 0.02);
  EXPECT_DOUBLE_EQ(h.region_radius(), 0.03);
  ASSERT_TRUE(h.has_region_centre());
  EXPECT_DOUBLE_EQ(h.region_centre().y(), -0.02);
  EXPECT_TRUE(h.has_follow_tool());  // false given: not the default
  EXPECT_FALSE(h.follow_tool());
  EXPECT_DOUBLE_EQ(h.follow_fraction(), 1.0);
  EXPECT_EQ(h.max_region_nodes(), 4096);
  // A block without an efg message takes the EFG's defaults.
  EXPECT_NO_THROW(ParseScene(head + "    }\n  }\n  material { density: 1055 youngs_modulus: "
                                    "5000 poisson_ratio: 0.35 }\n}\n",
                             "s"));
  // The nested efg: as model.efg's, on line 7.
  const std::string efg = "organ[0].model.efg_hybrid.efg.";
  ExpectRefused(scene("gauss_points: 5", "", nu), 7, efg + "gauss_points", "4 or 14");
  ExpectRefused(scene("support_scale: 0.5", "", nu), 7, efg + "support_scale", ">= 1");
  ExpectRefused(scene("support_neighbours: 65", "", nu), 7, efg + "support_neighbours", "1..64");
  ExpectRefused(scene("penalty_factor: nan", "", nu), 7, efg + "penalty_factor", "finite");
  ExpectRefused(scene("rayleigh_mass: -1", "", nu), 7, efg + "rayleigh_mass", ">= 0");
  ExpectRefused(scene("rayleigh_stiffness: inf", "", nu), 7, efg + "rayleigh_stiffness", "finite");
  // The surgical region, on line 8.
  const std::string hybrid = "organ[0].model.efg_hybrid.";
  ExpectRefused(scene("", "region_radius: 0", nu), 8, hybrid + "region_radius", "> 0");
  ExpectRefused(scene("", "region_radius: -0.05", nu), 8, hybrid + "region_radius", "> 0");
  ExpectRefused(scene("", "region_radius: inf", nu), 8, hybrid + "region_radius", "finite");
  ExpectRefused(scene("", "region_centre { x: nan }", nu), 8, hybrid + "region_centre",
                "finite x, y and z");
  ExpectRefused(scene("", "follow_fraction: 0", nu), 8, hybrid + "follow_fraction", "(0, 1]");
  ExpectRefused(scene("", "follow_fraction: 1.5", nu), 8, hybrid + "follow_fraction", "(0, 1]");
  ExpectRefused(scene("", "follow_fraction: nan", nu), 8, hybrid + "follow_fraction", "(0, 1]");
  ExpectRefused(scene("", "max_region_nodes: 0", nu), 8, hybrid + "max_region_nodes", "1..4096");
  ExpectRefused(scene("", "max_region_nodes: 4097", nu), 8, hybrid + "max_region_nodes", "1..4096");
  // Seed 001's adaptivity, on line 8.
  const Scene adaptive = ParseScene(
      scene("", "adaptive: true adapt_interval: 100 refine_threshold: 0.05 coarsen_threshold: 0",
            nu),
      "s");
  EXPECT_TRUE(adaptive.organ(0).model().efg_hybrid().adaptive());
  EXPECT_EQ(adaptive.organ(0).model().efg_hybrid().adapt_interval(), 100);
  ExpectRefused(scene("", "adapt_interval: 0", nu), 8, hybrid + "adapt_interval", ">= 1");
  ExpectRefused(scene("", "refine_threshold: 0", nu), 8, hybrid + "refine_threshold", "(0, 1]");
  ExpectRefused(scene("", "refine_threshold: nan", nu), 8, hybrid + "refine_threshold", "(0, 1]");
  ExpectRefused(scene("", "coarsen_threshold: 0.02", nu), 8, hybrid + "coarsen_threshold",
                "[0, refine_threshold]");
  ExpectRefused(scene("", "refine_threshold: 0.5 coarsen_threshold: -1", nu), 8,
                hybrid + "coarsen_threshold", "[0, refine_threshold]");
  // The material, on line 11: ν in (-1, 0.5); no FEM damping (the hybrid's is in its efg), no
  // QLV terms.
  ExpectRefused(scene("", "", "poisson_ratio: 0.5"), 11, "organ[0].material.poisson_ratio",
                "(-1, 0.5)");
  ExpectRefused(scene("", "", "poisson_ratio: 0.35 rayleigh_mass: 0.5"), 11,
                "organ[0].material.rayleigh_mass", "model.efg_hybrid.efg.rayleigh_mass");
  ExpectRefused(scene("", "", "poisson_ratio: 0.35 rayleigh_stiffness: 0.001"), 11,
                "organ[0].material.rayleigh_stiffness", "model.efg_hybrid.efg.rayleigh_stiffness");
  ExpectRefused(scene("", "", "poisson_ratio: 0.35 prony { gamma: 0.5 tau: 1 }"), 11,
                "organ[0].material", "FEM model");
  ExpectRefused(head + "    }\n  }\n  material { density: 1055 poisson_ratio: 0.35 }\n}\n", 9,
                "organ[0].material.youngs_modulus", "> 0");
}

TEST(SceneLines, NameTheLineOfAFieldOrOfItsNearestParent) {
  SceneLines lines;
  ParseScene(kGood, "good.scene.txtpb", &lines);
  EXPECT_EQ(lines.file(), "good.scene.txtpb");
  EXPECT_EQ(lines.LineOf("organ[1]"), 10);
  EXPECT_EQ(lines.LineOf("organ[0].fixed[0]"), 8);
  EXPECT_EQ(lines.LineOf("organ[0].fixed[0].sphere.radius"), 8);  // its parent's line
  EXPECT_EQ(lines.LineOf("load[0].region.nodes.id[7]"), 19);
  EXPECT_EQ(lines.LineOf("nothing.here"), 0);
  const SceneError e = lines.Error("load[0].region", "selects no node");
  EXPECT_STREQ(e.what(), "good.scene.txtpb:19: load[0].region: selects no node");
}

TEST(DefaultScene, EveryBuiltinOrganHasAValidOne) {
  for (const char* organ : {"liver4055", "liver", "plate192", "tissue45", "spleen600", "beam19k"}) {
    const Scene scene = DefaultScene(organ);
    std::string text;
    ASSERT_TRUE(google::protobuf::TextFormat::PrintToString(scene, &text));
    const Scene again = ParseScene(text, std::string("builtin:") + organ);  // passes every check
    EXPECT_EQ(again.organ_size(), 1);
    EXPECT_TRUE(again.organ(0).fixed_size() == 1) << organ;
    EXPECT_GE(again.organ(0).material().youngs_modulus(), 5e3) << organ;
  }
  EXPECT_TRUE(DefaultScene("tissue45").analysis().has_dynamic());
  EXPECT_TRUE(DefaultScene("kidney424").analysis().has_static_solve());
  EXPECT_NEAR(DefaultScene("beam19k").organ(0).material().youngs_modulus(),
              20.0 * 1000.0 * 9.81 * 16.0, 1e-6);  // the 16 m beam: stiffened
  EXPECT_THROW(DefaultScene("heart9"), std::invalid_argument);
}

TEST(Scene, RefusesAFileItCannotRead) {
  try {
    LoadSceneFile("/nonexistent/none.scene.txtpb");
    ADD_FAILURE();
  } catch (const SceneError& e) {
    EXPECT_EQ(e.line(), 0);
    EXPECT_NE(std::string(e.what()).find("cannot open"), std::string::npos);
  }
}

}  // namespace
}  // namespace somasim::scene
