#include "server/contact/contact_pipeline.h"

#include <cmath>
#include <stdexcept>
#include <string>

#include "common/mesh/topology.h"

namespace somasim::contact {

OrganSurface::OrganSurface(const mesh::Points& positions, const mesh::Triangles& triangles)
    : tree_(positions, triangles) {
  mesh::SurfaceMesh surface;
  surface.vertices = positions;
  surface.triangles = triangles;
  closed_ = mesh::AnalyseSurfaceTopology(surface).watertight;
}

namespace {

const ContactSettings& CheckedSettings(const ContactSettings& settings) {
  const auto positive = [](double value) { return std::isfinite(value) && value > 0.0; };
  if (!positive(settings.tool_stiffness)) {
    throw std::invalid_argument("contact: tool_stiffness must be finite and > 0 N/m");
  }
  if (!std::isfinite(settings.damping) || settings.damping < 0.0) {
    throw std::invalid_argument("contact: damping must be finite and >= 0 N s/m");
  }
  if (!positive(settings.force_limit)) {
    throw std::invalid_argument("contact: force_limit must be finite and > 0 N");
  }
  return settings;
}

const ToolShape& CheckedShape(const ToolShape& shape) {
  const std::string error = ToolShapeError(shape);
  if (!error.empty()) throw std::invalid_argument("tool shape: " + error);
  return shape;
}

}  // namespace

ToolContact::ToolContact(const ToolShape& shape, const ContactSettings& settings,
                         const ToolPose& start)
    : shape_(CheckedShape(shape)),
      settings_(CheckedSettings(settings)),
      pose_(start),
      proxy_(settings.proxy_offset),
      grasp_(settings.grasp),
      attachments_(3 + static_cast<size_t>(settings.grasp.max_nodes)) {
  const std::string error = ToolPoseError(start);
  if (!error.empty()) throw std::invalid_argument("tool pose: " + error);
  proxy_.Reset(start.tip);
}

void ToolContact::Reset(const ToolPose& pose) {
  if (ToolPoseError(pose).empty()) pose_ = pose;
  proxy_.Reset(pose_.tip);
  grasp_.Release();
  num_attachments_ = 0;
  touching_ = false;
}

void ToolContact::Update(const ToolPose& pose, const OrganSurface& surface,
                         const mesh::Points& positions) {
  if (ToolPoseError(pose).empty()) pose_ = pose;
  num_attachments_ = 0;
  touching_ = false;
  if (shape_.kind == ToolKind::kCamera) {
    proxy_.Reset(pose_.tip);
    return;
  }
  const AabbTree& tree = surface.tree();
  proxy_.Update(tree, pose_.tip, surface.closed());
  grasp_.Update(shape_, pose_, tree, positions);
  if (grasp_.holding()) {
    // The jaws hold the tissue: the grasp's springs carry the force both ways.
    for (const models::Attachment& a : grasp_.attachments()) {
      attachments_[static_cast<size_t>(num_attachments_++)] = a;
    }
    return;
  }
  if (!proxy_.in_contact()) return;
  const SurfacePoint& touched = proxy_.contact();
  const Eigen::Vector3d push = proxy_.device() - touched.point;
  const auto corners = tree.triangles().col(touched.triangle);
  touching_ = true;
  for (int c = 0; c < 3; ++c) {
    contact_nodes_[static_cast<size_t>(c)] = corners[c];
    const double w = touched.barycentric[c];
    if (!(w > 0.0)) continue;
    models::Attachment& a = attachments_[static_cast<size_t>(num_attachments_++)];
    a.node = corners[c];
    a.target = positions.col(corners[c]) + push;
    a.stiffness = w * settings_.tool_stiffness;
  }
}

Eigen::Vector3d ToolContact::ToolForce(const mesh::Points& positions) const {
  // Each spring pulls its node towards its target; the tool feels the opposite.
  Eigen::Vector3d force = Eigen::Vector3d::Zero();
  for (const models::Attachment& a : attachments()) {
    force += a.stiffness * (positions.col(a.node) - a.target);
  }
  return force;
}

ContactForModel ToolContact::ForLocalModel(const models::TissueModel& model,
                                           const models::TissueState& state,
                                           FemCompliance* fem) const {
  ContactForModel out;
  out.device = pose_.tip;
  out.damping = settings_.damping;
  out.force_limit = settings_.force_limit;
  out.tool_stiffness = settings_.tool_stiffness;
  const mesh::Points& x = state.positions;
  if (grasp_.holding()) {
    out.grasping = true;
    out.grasp_force = grasp_.ToolForce(x);
    out.tool_stiffness = settings_.grasp.stiffness;
    out.tissue_compliance = LocalCompliance(model, state, grasp_.attachments()[0].node, fem);
    return out;
  }
  if (!touching_) return out;
  // The proxy on the surface as the step left it: the touched point moved with the tissue, and
  // the triangle turned with it.
  const SurfacePoint& touched = proxy_.contact();
  Eigen::Vector3d surface = Eigen::Vector3d::Zero();
  int c_max = 0;
  for (int c = 0; c < 3; ++c) {
    surface += touched.barycentric[c] * x.col(contact_nodes_[static_cast<size_t>(c)]);
    if (touched.barycentric[c] > touched.barycentric[c_max]) c_max = c;
  }
  const Eigen::Vector3d n = (x.col(contact_nodes_[1]) - x.col(contact_nodes_[0]))
                                .cross(x.col(contact_nodes_[2]) - x.col(contact_nodes_[0]));
  out.in_contact = true;
  out.normal = proxy_.normal();
  if (n.norm() > 0.0) out.normal = n.normalized() * (n.dot(proxy_.normal()) >= 0.0 ? 1.0 : -1.0);
  out.proxy = surface;
  out.tissue_compliance =
      LocalCompliance(model, state, contact_nodes_[static_cast<size_t>(c_max)], fem);
  return out;
}

}  // namespace somasim::contact
