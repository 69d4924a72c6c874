#include "server/contact/god_object.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

#include "server/contact/triangle_queries.h"

namespace somasim::contact {
namespace {

// A constraint met during one update: the proxy stays where n·(x - point) >= offset.
struct Plane {
  Eigen::Vector3d point;
  Eigen::Vector3d normal;  // unit, towards the proxy's side
};

// The unit normal of triangle t at the tree's positions (counter-clockwise front), or zero for
// a degenerate triangle.
Eigen::Vector3d TriangleNormal(const AabbTree& tree, int32_t t) {
  const auto& x = tree.positions();
  const auto tri = tree.triangles().col(t);
  const Eigen::Vector3d n = (x.col(tri[1]) - x.col(tri[0])).cross(x.col(tri[2]) - x.col(tri[0]));
  const double length = n.norm();
  return length > 0.0 ? Eigen::Vector3d(n / length) : Eigen::Vector3d::Zero();
}

Eigen::Vector3d SurfacePosition(const AabbTree& tree, int32_t t, const Eigen::Vector3d& w) {
  const auto& x = tree.positions();
  const auto tri = tree.triangles().col(t);
  return w[0] * x.col(tri[0]) + w[1] * x.col(tri[1]) + w[2] * x.col(tri[2]);
}

// The point nearest to `x` that lies `offset` outside every plane of `planes` (k <= 3 of them,
// as equalities), y = x + Σ μ_j n_j with Σ_j (n_i·n_j) μ_j = offset - n_i·(x - p_i). A plane whose
// μ would be negative pulls instead of pushing (x is already outside it): it is dropped and the
// rest solved again (the active set of the god-object's quadratic program). Planes left
// active stay first in `planes`; returns how many, and 0 if the planes' normals are dependent.
int ProjectOntoPlanes(const Eigen::Vector3d& x, Plane* planes, int k, double offset,
                      Eigen::Vector3d* y) {
  while (k > 0) {
    Eigen::Matrix3d gram = Eigen::Matrix3d::Identity();
    Eigen::Vector3d rhs = Eigen::Vector3d::Zero();
    for (int i = 0; i < k; ++i) {
      for (int j = 0; j < k; ++j) gram(i, j) = planes[i].normal.dot(planes[j].normal);
      rhs[i] = offset - planes[i].normal.dot(x - planes[i].point);
    }
    // Independent unit normals have a Gram determinant well above zero; two planes within
    // ~0.1° of each other are one constraint.
    if (gram.determinant() < 1e-6) return 0;
    const Eigen::Vector3d mu = gram.inverse() * rhs;
    int most_negative = -1;
    for (int i = 0; i < k; ++i) {
      if (mu[i] < 0.0 && (most_negative < 0 || mu[i] < mu[most_negative])) most_negative = i;
    }
    if (most_negative < 0) {
      *y = x;
      for (int i = 0; i < k; ++i) *y += mu[i] * planes[i].normal;
      return k;
    }
    for (int i = most_negative; i + 1 < k; ++i) planes[i] = planes[i + 1];
    --k;
  }
  *y = x;
  return 0;
}

}  // namespace

GodObject::GodObject(double offset) : offset_(offset) {
  if (!std::isfinite(offset) || offset <= 0.0) {
    throw std::invalid_argument("god-object proxy offset must be finite and > 0 m");
  }
}

void GodObject::Reset(const Eigen::Vector3d& device) {
  proxy_ = device;
  device_ = device;
  in_contact_ = false;
  contact_ = SurfacePoint{};
}

void GodObject::Update(const AabbTree& tree, const Eigen::Vector3d& device, bool closed) {
  if (!device.allFinite()) return;
  device_ = device;
  const bool moved = &tree != last_tree_ || tree.refits() != last_refits_;
  last_tree_ = &tree;
  last_refits_ = tree.refits();
  if (closed && moved && !in_contact_) ComeOutIfSwallowed(tree);
  if (in_contact_ && contact_.triangle >= 0 && contact_.triangle < tree.num_triangles()) {
    // The surface moved since the last update: the proxy rides with the point it touches.
    const Eigen::Vector3d n = TriangleNormal(tree, contact_.triangle);
    if (n.squaredNorm() > 0.0) normal_ = side_ * n;
    contact_.point = SurfacePosition(tree, contact_.triangle, contact_.barycentric);
    proxy_ = contact_.point + offset_ * normal_;
  }
  MoveTowardsDevice(tree);
}

namespace {

// Moves `proxy` along the checked segment towards `goal`, stopping `offset` short of the first
// triangle it would cross (or staying, if already that close). Returns false (and moves to
// `goal`) when the segment crosses nothing; else the hit and the crossed plane's normal, turned
// towards the proxy's side.
bool MoveUntilHit(const AabbTree& tree, const Eigen::Vector3d& goal, double offset,
                  Eigen::Vector3d* proxy, SegmentHit* hit, Eigen::Vector3d* normal) {
  const Eigen::Vector3d step = goal - *proxy;
  if (!tree.FirstHit(*proxy, goal, hit)) {
    *proxy = goal;
    return false;
  }
  Eigen::Vector3d n = TriangleNormal(tree, hit->triangle);
  if (n.squaredNorm() == 0.0) n = -step.normalized();  // a degenerate triangle: back off
  double height = n.dot(*proxy - hit->point);
  if (height < 0.0 || (height == 0.0 && n.dot(step) > 0.0)) {
    n = -n;
    height = -height;
  }
  const double approach = n.dot(step);  // < 0: the segment goes into the plane
  if (approach < 0.0 && height > offset) {
    *proxy += std::min(hit->t, (offset - height) / approach) * step;
  }
  *normal = n;
  return true;
}

}  // namespace

void GodObject::MoveTowardsDevice(const AabbTree& tree) {
  // Each pass moves the proxy along one checked segment. A slide along a plane may leave the
  // surface where it curves away (a convex region): the proxy then aims at the device again and
  // meets the surface further on, converging on the device's nearest reachable surface point.
  constexpr int kMaxMoves = 8;
  Plane planes[3];
  int active = 0;
  bool touched = false;
  bool on_surface = false;  // the last move ended at a crossing (not in the air)
  Eigen::Vector3d last_hit = proxy_;
  int32_t last_triangle = -1;
  Eigen::Vector3d goal = device_;
  for (int move = 0; move < kMaxMoves; ++move) {
    if ((goal - proxy_).squaredNorm() <= 1e-24) break;  // within 1e-12 m: arrived
    SegmentHit hit;
    Eigen::Vector3d n;
    if (!MoveUntilHit(tree, goal, offset_, &proxy_, &hit, &n)) {
      on_surface = false;
      if (active == 0) break;  // the device itself: free
      active = 0;              // slid off the planes met so far: aim at the device again
      goal = device_;
      continue;
    }
    touched = true;
    on_surface = true;
    last_hit = hit.point;
    last_triangle = hit.triangle;
    // Slide: the next goal is the device projected onto the planes met so far.
    if (active == 3) break;  // a corner: the proxy stays
    planes[active++] = Plane{hit.point, n};
    active = ProjectOntoPlanes(device_, planes, active, offset_, &goal);
    if (active == 0) break;
  }
  if (touched && !on_surface && (device_ - proxy_).squaredNorm() > 1e-24) {
    // Out of moves in the air above a curved surface: settle onto it towards the device.
    SegmentHit hit;
    Eigen::Vector3d n;
    if (MoveUntilHit(tree, device_, offset_, &proxy_, &hit, &n)) {
      last_hit = hit.point;
      last_triangle = hit.triangle;
    }
  }
  if (touched && (device_ - proxy_).squaredNorm() > 1e-24) {
    TouchNearest(tree, last_triangle, (proxy_ - last_hit).norm() + 2.0 * offset_);
  } else {
    in_contact_ = false;
  }
}

void GodObject::TouchNearest(const AabbTree& tree, int32_t last_triangle, double reach) {
  SurfacePoint nearest;
  // The triangle the proxy last stopped at is nearly always the nearest (the proxy stopped
  // `offset` from it); only near its edge may a neighbour be nearer, and then the tree is asked.
  const auto& x = tree.positions();
  const auto tri = tree.triangles().col(last_triangle);
  nearest.triangle = last_triangle;
  nearest.barycentric =
      ClosestPointBarycentric(proxy_, x.col(tri[0]), x.col(tri[1]), x.col(tri[2]));
  nearest.point = nearest.barycentric[0] * x.col(tri[0]) + nearest.barycentric[1] * x.col(tri[1]) +
                  nearest.barycentric[2] * x.col(tri[2]);
  nearest.distance = (proxy_ - nearest.point).norm();
  if (nearest.distance > offset_ * (1.0 + 1e-6) && !tree.Nearest(proxy_, &nearest, reach)) {
    in_contact_ = false;
    return;
  }
  in_contact_ = true;
  contact_ = nearest;
  const Eigen::Vector3d n = TriangleNormal(tree, nearest.triangle);
  if (n.squaredNorm() > 0.0) {
    side_ = n.dot(proxy_ - nearest.point) >= 0.0 ? 1.0 : -1.0;
    normal_ = side_ * n;
  }
}

void GodObject::ComeOutIfSwallowed(const AabbTree& tree) {
  SurfacePoint nearest;
  if (!tree.Nearest(proxy_, &nearest, kCaptureDepth) || nearest.distance == 0.0) return;
  // The pseudo-normal at the nearest point: the normals of the triangles that share it, each
  // weighted by its angle there (a face: its own normal; an edge: the two faces'; a vertex:
  // the angle-weighted fan). Its sign against (proxy - point) is exact for a closed,
  // consistently oriented surface (Bærentzen & Aanæs 2005).
  const double touch = 1e-9 * (1.0 + nearest.point.cwiseAbs().maxCoeff());
  const int32_t found =
      std::min(tree.SphereQuery(nearest.point, touch, {around_.data(), around_.size()}),
               static_cast<int32_t>(around_.size()));
  const auto& x = tree.positions();
  Eigen::Vector3d pseudo = Eigen::Vector3d::Zero();
  for (int32_t k = 0; k < found; ++k) {
    const int32_t t = around_[static_cast<size_t>(k)];
    const auto tri = tree.triangles().col(t);
    const Eigen::Vector3d n = TriangleNormal(tree, t);
    // The angle of triangle t at the point: at a corner it touches, the corner's angle; on an
    // edge or inside, π (the point's neighbourhood in t is a half or whole disc: any constant
    // weight does, both faces of an edge get the same).
    double weight = std::numbers::pi;
    for (int c = 0; c < 3; ++c) {
      if ((x.col(tri[c]) - nearest.point).norm() <= touch) {
        const Eigen::Vector3d u = x.col(tri[(c + 1) % 3]) - x.col(tri[c]);
        const Eigen::Vector3d v = x.col(tri[(c + 2) % 3]) - x.col(tri[c]);
        weight = std::atan2(u.cross(v).norm(), u.dot(v));
      }
    }
    pseudo += weight * n;
  }
  if (found == 0) pseudo = TriangleNormal(tree, nearest.triangle);
  if (pseudo.dot(proxy_ - nearest.point) >= 0.0) return;  // outside
  // Swallowed: back out to the nearest point, offset along the touched face's outward normal.
  const Eigen::Vector3d n = TriangleNormal(tree, nearest.triangle);
  const Eigen::Vector3d out = pseudo.norm() > 0.0 ? Eigen::Vector3d(pseudo.normalized()) : n;
  proxy_ = nearest.point + offset_ * out;
  in_contact_ = true;
  contact_ = nearest;
  side_ = 1.0;
  normal_ = n.squaredNorm() > 0.0 ? n : out;
}

Eigen::Vector3d GodObject::DeviceForce(double tool_stiffness) const {
  if (!in_contact_) return Eigen::Vector3d::Zero();
  return tool_stiffness * (proxy_ - device_);
}

}  // namespace somasim::contact
