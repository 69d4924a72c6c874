// A small FEM organ for the contact tests: kidney424 (corotational, held at its lowest 10 % in
// z), with its boundary surface and the model's inputs.
#pragma once

#include <memory>
#include <vector>

#include "server/contact/contact_pipeline.h"
#include "server/models/fem/fem_model.h"
#include "tests/server/contact/contact_test_meshes.h"

namespace somasim::testing {

struct HeldOrgan {
  OrganWithSurface mesh;
  std::unique_ptr<models::fem::FemModel> model;
  std::unique_ptr<models::TissueState> state;
  std::vector<int32_t> held;
  int32_t top = 0;  // the highest surface node
};
HeldOrgan HeldKidney();

// One physics step with the tool's springs: StepInputs from `held` and `contact`.
models::StepStatus StepWithTool(const HeldOrgan& organ, const contact::ToolContact& tool, double dt,
                                models::TissueState* state);

}  // namespace somasim::testing
