#include "tests/server/contact/contact_fixtures.h"

namespace somasim::testing {

HeldOrgan HeldKidney() {
  HeldOrgan organ;
  organ.mesh = VolumeOrgan("kidney424");
  models::fem::FemParameters p;
  p.kind = models::fem::FemKind::kCorotational;
  p.youngs_modulus = 20e3;
  p.poisson_ratio = 0.45;
  p.density = 1000.0;
  p.rayleigh_mass = 30.0;
  p.rayleigh_stiffness = 0.002;
  organ.model = models::fem::FemModel::FromTetMesh(organ.mesh.volume, p);
  organ.state = organ.model->MakeState();
  const mesh::Points& x = organ.mesh.volume.vertices;
  const double z_lo = x.row(2).minCoeff(), z_hi = x.row(2).maxCoeff();
  for (Eigen::Index i = 0; i < x.cols(); ++i) {
    if (x(2, i) <= z_lo + 0.1 * (z_hi - z_lo)) organ.held.push_back(static_cast<int32_t>(i));
  }
  double best = -1e300;
  for (Eigen::Index t = 0; t < organ.mesh.surface.cols(); ++t) {
    for (int c = 0; c < 3; ++c) {
      const int32_t node = organ.mesh.surface(c, t);
      if (x(2, node) > best) {
        best = x(2, node);
        organ.top = node;
      }
    }
  }
  return organ;
}

models::StepStatus StepWithTool(const HeldOrgan& organ, const contact::ToolContact& tool, double dt,
                                models::TissueState* state) {
  models::StepInputs inputs;
  inputs.dt = dt;
  inputs.fixed_nodes = organ.held;
  inputs.attachments = tool.attachments();
  return organ.model->Step(inputs, state);
}

}  // namespace somasim::testing
