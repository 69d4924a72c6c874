#include "tests/server/solve/solve_fixtures.h"

#include <gtest/gtest.h>

#include <pugixml.hpp>
#include <sstream>

#include "common/scene/scene.h"

namespace somasim::testing {
namespace {

std::vector<double> ParseNumbers(const char* text) {
  std::istringstream in(text);
  std::vector<double> v;
  double x = 0.0;
  while (in >> x) v.push_back(x);
  return v;
}

}  // namespace

solve::SolveSummary SolveText(const std::string& dir, const std::string& text) {
  scene::SceneLines lines;
  const scene::Scene s = scene::ParseScene(text, dir + "/test.scene.txtpb", &lines);
  solve::SolveOptions options;
  options.scene_dir = dir;
  options.out_dir = dir + "/out";
  return solve::RunSolve(s, lines, options);
}

VtuArrays ReadVtu(const std::string& path, const std::string& name) {
  pugi::xml_document doc;
  EXPECT_TRUE(doc.load_file(path.c_str())) << path;
  const pugi::xml_node piece = doc.child("VTKFile").child("UnstructuredGrid").child("Piece");
  VtuArrays out;
  out.points = ParseNumbers(piece.child("Points").child("DataArray").text().get());
  for (const pugi::xml_node& a : piece.child("PointData").children("DataArray")) {
    if (name == a.attribute("Name").value()) out.values = ParseNumbers(a.text().get());
  }
  return out;
}

}  // namespace somasim::testing
