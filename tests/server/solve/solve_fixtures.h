// Shared by the solve tests: running a scene text in-process and reading back the VTU results.
#pragma once

#include <string>
#include <vector>

#include "server/solve/solve_runner.h"

namespace somasim::testing {

// Parses `text` as dir/test.scene.txtpb and runs it with results in dir/out.
solve::SolveSummary SolveText(const std::string& dir, const std::string& text);

// The points and the point-data array `name` of a VTU file the solver wrote (ASCII), 3 values per
// node for vectors.
struct VtuArrays {
  std::vector<double> points, values;
};
VtuArrays ReadVtu(const std::string& path, const std::string& name);

}  // namespace somasim::testing
