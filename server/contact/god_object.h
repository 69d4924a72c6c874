// The god-object proxy (seed 002 §3.1, fig. 8, eq. 12; Zilles & Salisbury 1995, Ruspini et al.
// 1997): where the tool tip would be if it could not enter tissue. While the device point goes
// into an organ the proxy stays on its surface, and the force on the hand is the spring between
// them, f = -K_t (x_device - x_proxy) (seed 002 eq. 12). On a deforming organ the proxy rides
// with the surface point it touches, then moves towards the device again.
//
// Never tunnelling: the proxy only ever moves along straight segments that the AABB tree has
// checked against every triangle (FirstHit), stopping `offset` short of the first crossing and
// then sliding along the crossed triangle's plane (up to three planes: a face, an edge of two, a
// corner of three). However fast the device moves between two updates, the proxy cannot pass
// through a surface; it stays on the side it started on (outside a closed organ; on its own
// side of an open sheet). Allocation-free. Pure.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>

#include "server/contact/aabb_tree.h"

namespace somasim::contact {

class GodObject {
 public:
  // offset [m] (> 0, finite): how far outside the surface the proxy stays, so that it is never
  // exactly on a triangle (whose side would then be ambiguous). Far below tissue's scale.
  explicit GodObject(double offset = 1e-6);

  // The proxy at `device`, touching nothing (a tool entering the scene, outside every organ).
  void Reset(const Eigen::Vector3d& device);
  // One update against a surface whose tree is refitted to the surface's current positions.
  // `device` must be finite (a non-finite one leaves the proxy where it is).
  // `closed`: the surface is watertight with outward normals (a volume organ's boundary, a
  // closed surface organ). Then a free proxy that the moving surface has swallowed since the
  // last update (a breathing organ moving onto a tool held still) is found — within
  // kCaptureDepth of the surface, by the sign of the angle-weighted pseudo-normal at its nearest
  // surface point (Bærentzen & Aanæs 2005) — and put back outside, touching. (Only when the
  // tree was refitted since the last update: a surface that did not move swallows nothing.)
  void Update(const AabbTree& tree, const Eigen::Vector3d& device, bool closed = false);
  // [m] how far a surface may move past a free tool between two updates and still push it
  // out: 5 mm, 0.5 m/s at a 100 Hz physics step (tissue moves far slower).
  static constexpr double kCaptureDepth = 0.005;

  bool in_contact() const { return in_contact_; }
  const Eigen::Vector3d& proxy() const { return proxy_; }    // [m]
  const Eigen::Vector3d& device() const { return device_; }  // [m] of the last update
  // The surface point the proxy touches (valid in contact): triangle, barycentric weights, the
  // point on the surface [m]; and the surface's unit normal there, pointing to the proxy's side.
  const SurfacePoint& contact() const { return contact_; }
  const Eigen::Vector3d& normal() const { return normal_; }
  // seed 002 eq. 12: the force on the device [N], -K_t (x_device - x_proxy) in contact, else 0.
  Eigen::Vector3d DeviceForce(double tool_stiffness) const;

 private:
  // Moves the proxy from proxy_ towards device_, sliding on the planes it meets.
  void MoveTowardsDevice(const AabbTree& tree);
  // Records the surface point nearest to the proxy (within `reach` of it) as the contact;
  // `last_triangle` is the triangle the proxy last stopped at.
  void TouchNearest(const AabbTree& tree, int32_t last_triangle, double reach);
  // A free proxy inside a closed surface (see Update) goes back out, touching it.
  void ComeOutIfSwallowed(const AabbTree& tree);

  double offset_;
  bool in_contact_ = false;
  Eigen::Vector3d proxy_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d device_ = Eigen::Vector3d::Zero();
  SurfacePoint contact_;
  Eigen::Vector3d normal_ = Eigen::Vector3d::UnitZ();
  double side_ = 1.0;  // +1: the proxy is on the front (counter-clockwise) side of its triangle
  std::array<int32_t, 32> around_{};     // triangles at a nearest point (pseudo-normal)
  const AabbTree* last_tree_ = nullptr;  // the tree and its refit count at the last update
  uint64_t last_refits_ = 0;
};

}  // namespace somasim::contact
