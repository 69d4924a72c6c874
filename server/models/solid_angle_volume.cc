#include "server/models/solid_angle_volume.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"

namespace somasim::models {
namespace {

using Eigen::Matrix3d;
using Eigen::Vector3d;

constexpr double kTwoPi = 2.0 * std::numbers::pi;
constexpr double kFourPi = 4.0 * std::numbers::pi;
// Smallest |s_j × s_{j+1}| accepted at rest: below it two consecutive neighbours are in line
// with the node and the factor z_j of the solid angle vanishes (arg undefined).
constexpr double kMinSine = 1e-10;
// Step of LocalStiffness' central differences, relative to the node's mean ring edge.
constexpr double kRelativeStep = 1e-6;

[[noreturn]] void Fail(const std::string& message) {
  throw std::invalid_argument("solid-angle volume: " + message);
}

std::string Str(double value) {
  char buffer[32];
  std::snprintf(buffer, sizeof buffer, "%.17g", value);
  return buffer;
}

void CheckParameter(double value, const char* name) {
  if (!checks::FiniteNonNegative(value)) {
    Fail(std::string(name) + " must be finite and >= 0 (got " + Str(value) + ")");
  }
}

// Direction from node i to one ring node: s = u/|u|, u = x_k − x_i, and 1/|u|.
struct Direction {
  Vector3d s;
  double inverse_length = 0.0;
  int32_t node = 0;
};

template <typename Position>
Direction MakeDirection(const Vector3d& xi, int32_t node, const Position& position) {
  const Vector3d u = position(node) - xi;
  const double inverse_length = 1.0 / u.norm();
  return {u * inverse_length, inverse_length, node};
}

// Calls factor(a, b, c) for the ring's consecutive triples (s_{j−1}, s_j, s_{j+1}), j = 0..n−1
// cyclic, normalising each direction once.
template <typename Position, typename Factor>
void ForEachTriple(const int32_t* ring, int32_t n, const Vector3d& xi, const Position& position,
                   const Factor& factor) {
  const Direction first = MakeDirection(xi, ring[0], position);
  const Direction last = MakeDirection(xi, ring[n - 1], position);
  Direction a = last;
  Direction b = first;
  for (int32_t j = 0; j < n; ++j) {
    const Direction c = j == n - 1   ? first
                        : j == n - 2 ? last
                                     : MakeDirection(xi, ring[j + 1], position);
    factor(a, b, c);
    a = b;
    b = c;
  }
}

// Ω_i = 2π − Σ_j atan2(Im z_j, Re z_j), seed 004 (Mazonka 2012):
// z_j = (s_{j−1}·s_j)(s_j·s_{j+1}) − s_{j−1}·s_{j+1} + i s_{j−1}·(s_j × s_{j+1}).
template <typename Position>
double RingSolidAngle(const int32_t* ring, int32_t n, const Vector3d& xi,
                      const Position& position) {
  double turning = 0.0;
  ForEachTriple(ring, n, xi, position,
                [&turning](const Direction& a, const Direction& b, const Direction& c) {
                  const double re = a.s.dot(b.s) * b.s.dot(c.s) - a.s.dot(c.s);
                  const double im = a.s.dot(b.s.cross(c.s));
                  turning += std::atan2(im, re);
                });
  return kTwoPi - turning;
}

// The exact gradient of Ω_i: calls ring_sink(k, ∂Ω_i/∂x_k) once per (factor, ring corner), so
// several times per ring node (the contributions add up), and returns ∂Ω_i/∂x_i, which is minus
// the sum of all of them (Ω_i depends on x_i only through the differences x_k − x_i).
// Per factor, with θ = atan2(Im z, Re z): dθ = (Re z dIm z − Im z dRe z)/|z|²,
//   ∂Re/∂a = (b·c) b − c,  ∂Re/∂b = (b·c) a + (a·b) c,  ∂Re/∂c = (a·b) b − a,
//   ∂Im/∂a = b × c,        ∂Im/∂b = c × a,              ∂Im/∂c = a × b,
// then through s = u/|u|: ∂s/∂u = (I − s sᵀ)/|u|, and Ω = 2π − Σθ.
template <typename Position, typename Sink>
Vector3d RingSolidAngleGradient(const int32_t* ring, int32_t n, const Vector3d& xi,
                                const Position& position, const Sink& ring_sink) {
  Vector3d gradient_i = Vector3d::Zero();
  const auto emit = [&](const Direction& dir, const Vector3d& dtheta_ds) {
    const Vector3d g = -dir.inverse_length * (dtheta_ds - dtheta_ds.dot(dir.s) * dir.s);
    ring_sink(dir.node, g);
    gradient_i -= g;
  };
  ForEachTriple(ring, n, xi, position,
                [&emit](const Direction& a, const Direction& b, const Direction& c) {
                  const double ab = a.s.dot(b.s);
                  const double bc = b.s.dot(c.s);
                  const Vector3d b_x_c = b.s.cross(c.s);
                  const double re = ab * bc - a.s.dot(c.s);
                  const double im = a.s.dot(b_x_c);
                  const double inverse_norm2 = 1.0 / (re * re + im * im);
                  const double d_re = -im * inverse_norm2;  // ∂θ/∂Re z
                  const double d_im = re * inverse_norm2;   // ∂θ/∂Im z
                  emit(a, d_re * (bc * b.s - c.s) + d_im * b_x_c);
                  emit(b, d_re * (bc * a.s + ab * c.s) + d_im * c.s.cross(a.s));
                  emit(c, d_re * (ab * b.s - a.s) + d_im * a.s.cross(b.s));
                });
  return gradient_i;
}

// E_i(d) and dE_i/dd: σ± d²/2 + γ± |d|³/3 and σ± d + γ± d|d|, ± the sign of d.
struct Reaction {
  double energy = 0.0;
  double derivative = 0.0;
};

Reaction EvalReaction(const SolidAngleVolumeParameters& p, double d) {
  const double sigma = d > 0.0 ? p.sigma_plus : p.sigma_minus;
  const double gamma = d > 0.0 ? p.gamma_plus : p.gamma_minus;
  const double abs_d = std::abs(d);
  return {d * d * (0.5 * sigma + gamma * abs_d / 3.0), d * (sigma + gamma * abs_d)};
}

}  // namespace

SolidAngleVolumeTerm SolidAngleVolumeTerm::Build(const mesh::SurfaceMesh& surface,
                                                 const SolidAngleVolumeParameters& parameters) {
  return Build(surface.vertices, surface.triangles, parameters);
}

SolidAngleVolumeTerm SolidAngleVolumeTerm::Build(const mesh::Points& rest,
                                                 const mesh::Triangles& triangles,
                                                 const SolidAngleVolumeParameters& parameters) {
  CheckParameter(parameters.gamma_plus, "gamma_plus");
  CheckParameter(parameters.sigma_plus, "sigma_plus");
  CheckParameter(parameters.gamma_minus, "gamma_minus");
  CheckParameter(parameters.sigma_minus, "sigma_minus");
  if (triangles.cols() == 0) Fail("no triangles");
  const auto num_points = static_cast<int32_t>(rest.cols());
  for (Eigen::Index t = 0; t < triangles.cols(); ++t) {
    for (int corner = 0; corner < 3; ++corner) {
      const int32_t k = triangles(corner, t);
      if (k < 0 || k >= num_points) {
        Fail("triangle " + std::to_string(t) + " has node index " + std::to_string(k) +
             " out of range [0, " + std::to_string(num_points) + ")");
      }
      if (triangles((corner + 1) % 3, t) == k) {
        Fail("triangle " + std::to_string(t) + " repeats node " + std::to_string(k));
      }
      if (!rest.col(k).allFinite()) Fail("vertex " + std::to_string(k) + " is not finite");
    }
  }

  // Corners per node (CSR): each corner gives, at its node a of triangle (a, b, c), the pair
  // (c → b), the clockwise successor of c around a seen from outside.
  std::vector<int32_t> corner_offsets(static_cast<size_t>(num_points) + 1, 0);
  for (Eigen::Index t = 0; t < triangles.cols(); ++t) {
    for (int corner = 0; corner < 3; ++corner) {
      ++corner_offsets[static_cast<size_t>(triangles(corner, t)) + 1];
    }
  }
  for (size_t k = 0; k < static_cast<size_t>(num_points); ++k) {
    corner_offsets[k + 1] += corner_offsets[k];
  }
  std::vector<int32_t> from(static_cast<size_t>(corner_offsets.back()));
  std::vector<int32_t> to(from.size());
  {
    std::vector<int32_t> fill(corner_offsets.begin(), corner_offsets.end() - 1);
    for (Eigen::Index t = 0; t < triangles.cols(); ++t) {
      for (int corner = 0; corner < 3; ++corner) {
        const auto slot = static_cast<size_t>(fill[static_cast<size_t>(triangles(corner, t))]++);
        from[slot] = triangles((corner + 2) % 3, t);
        to[slot] = triangles((corner + 1) % 3, t);
      }
    }
  }

  SolidAngleVolumeTerm term;
  term.num_points_ = num_points;
  term.parameters_ = parameters;
  term.term_of_node_.assign(static_cast<size_t>(num_points), -1);
  term.ring_offsets_.push_back(0);
  for (int32_t a = 0; a < num_points; ++a) {
    const auto begin = static_cast<size_t>(corner_offsets[static_cast<size_t>(a)]);
    const auto end = static_cast<size_t>(corner_offsets[static_cast<size_t>(a) + 1]);
    if (begin == end) continue;
    const std::string at = "node " + std::to_string(a) + ": ";
    // The pairs must form a permutation of the neighbours: every directed edge k → a and a → k
    // once, and each edge in both directions.
    for (size_t p = begin; p < end; ++p) {
      for (size_t q = p + 1; q < end; ++q) {
        if (from[p] == from[q]) {
          Fail(at + "edge (" + std::to_string(from[p]) + ", " + std::to_string(a) +
               ") is used twice in the same direction (non-manifold edge or inconsistent "
               "orientation)");
        }
        if (to[p] == to[q]) {
          Fail(at + "edge (" + std::to_string(a) + ", " + std::to_string(to[p]) +
               ") is used twice in the same direction (non-manifold edge or inconsistent "
               "orientation)");
        }
      }
    }
    for (size_t p = begin; p < end; ++p) {
      if (std::find(to.begin() + static_cast<std::ptrdiff_t>(begin),
                    to.begin() + static_cast<std::ptrdiff_t>(end),
                    from[p]) == to.begin() + static_cast<std::ptrdiff_t>(end)) {
        Fail(at + "edge (" + std::to_string(a) + ", " + std::to_string(from[p]) +
             ") has a triangle on one side only (open surface or inconsistent orientation)");
      }
    }
    if (end - begin < 3) {
      Fail(at + "only " + std::to_string(end - begin) + " neighbours (a degenerate fan)");
    }
    // Walk the successor map from the first pair; a single cycle must cover every pair.
    const size_t ring_begin = term.ring_.size();
    int32_t current = from[begin];
    do {
      term.ring_.push_back(current);
      size_t p = begin;
      while (from[p] != current) ++p;
      current = to[p];
    } while (current != from[begin]);
    if (term.ring_.size() - ring_begin != end - begin) {
      Fail(at + "its triangles form more than one fan (non-manifold vertex)");
    }

    // Rest geometry: no coincident neighbour, no zero-angle corner, an unfolded ring.
    const int32_t* ring = term.ring_.data() + ring_begin;
    const auto n = static_cast<int32_t>(end - begin);
    const Vector3d xi = rest.col(a);
    for (int32_t j = 0; j < n; ++j) {
      if (!((rest.col(ring[j]) - xi).norm() > 0.0)) {
        Fail(at + "neighbour " + std::to_string(ring[j]) + " is at the node's position");
      }
    }
    for (int32_t j = 0; j < n; ++j) {
      const Vector3d u = rest.col(ring[j]) - xi;
      const Vector3d v = rest.col(ring[(j + 1) % n]) - xi;
      if (!(u.normalized().cross(v.normalized()).norm() > kMinSine)) {
        Fail(at + "neighbours " + std::to_string(ring[j]) + " and " +
             std::to_string(ring[(j + 1) % n]) +
             " are in line with it (a zero-angle triangle corner)");
      }
    }
    const double omega0 =
        RingSolidAngle(ring, n, xi, [&rest](int32_t k) -> Vector3d { return rest.col(k); });
    if (!(omega0 > 0.0 && omega0 < kFourPi)) {
      Fail(at + "folded ring at rest (solid angle " + Str(omega0) + " sr outside (0, 4π))");
    }
    term.term_of_node_[static_cast<size_t>(a)] = static_cast<int32_t>(term.nodes_.size());
    term.nodes_.push_back(a);
    term.rest_angle_.push_back(omega0);
    term.ring_offsets_.push_back(static_cast<int32_t>(term.ring_.size()));
  }
  return term;
}

bool SolidAngleVolumeTerm::HasTerm(int32_t node) const {
  return node >= 0 && node < num_points_ && term_of_node_[static_cast<size_t>(node)] >= 0;
}

std::vector<int32_t> SolidAngleVolumeTerm::Ring(int32_t node) const {
  assert(HasTerm(node));
  const auto t = static_cast<size_t>(term_of_node_[static_cast<size_t>(node)]);
  return {ring_.begin() + ring_offsets_[t], ring_.begin() + ring_offsets_[t + 1]};
}

double SolidAngleVolumeTerm::RestSolidAngle(int32_t node) const {
  assert(HasTerm(node));
  return rest_angle_[static_cast<size_t>(term_of_node_[static_cast<size_t>(node)])];
}

double SolidAngleVolumeTerm::SolidAngle(const mesh::Points& x, int32_t node) const {
  if (!HasTerm(node)) {
    throw std::out_of_range("solid-angle volume: node " + std::to_string(node) +
                            " is not a surface vertex");
  }
  assert(x.cols() == num_points_);
  const auto t = static_cast<size_t>(term_of_node_[static_cast<size_t>(node)]);
  return RingSolidAngle(ring_.data() + ring_offsets_[t], ring_offsets_[t + 1] - ring_offsets_[t],
                        x.col(node), [&x](int32_t k) -> Vector3d { return x.col(k); });
}

double SolidAngleVolumeTerm::Energy(const mesh::Points& x) const {
  assert(x.cols() == num_points_);
  const auto position = [&x](int32_t k) -> Vector3d { return x.col(k); };
  double energy = 0.0;
  for (size_t t = 0; t < nodes_.size(); ++t) {
    const double omega =
        RingSolidAngle(ring_.data() + ring_offsets_[t], ring_offsets_[t + 1] - ring_offsets_[t],
                       x.col(nodes_[t]), position);
    energy += EvalReaction(parameters_, omega - rest_angle_[t]).energy;
  }
  return energy;
}

void SolidAngleVolumeTerm::AddForces(const mesh::Points& x, mesh::Points* forces) const {
  assert(x.cols() == num_points_ && forces->cols() == num_points_);
  const auto position = [&x](int32_t k) -> Vector3d { return x.col(k); };
  for (size_t t = 0; t < nodes_.size(); ++t) {
    const int32_t* ring = ring_.data() + ring_offsets_[t];
    const int32_t n = ring_offsets_[t + 1] - ring_offsets_[t];
    const Vector3d xi = x.col(nodes_[t]);
    const double omega = RingSolidAngle(ring, n, xi, position);
    // f = −E_i'(d) ∂Ω_i/∂x on node i and its ring; nothing at rest (d = 0 exactly there).
    const double scale = EvalReaction(parameters_, omega - rest_angle_[t]).derivative;
    if (scale == 0.0) continue;
    const Vector3d gradient_i = RingSolidAngleGradient(
        ring, n, xi, position,
        [scale, forces](int32_t k, const Vector3d& g) { forces->col(k) -= scale * g; });
    forces->col(nodes_[t]) -= scale * gradient_i;
  }
}

Eigen::Matrix3d SolidAngleVolumeTerm::LocalStiffness(const mesh::Points& x, int32_t node) const {
  assert(x.cols() == num_points_);
  if (!HasTerm(node)) return Matrix3d::Zero();
  const auto own = static_cast<size_t>(term_of_node_[static_cast<size_t>(node)]);
  const int32_t* own_ring = ring_.data() + ring_offsets_[own];
  const int32_t own_n = ring_offsets_[own + 1] - ring_offsets_[own];

  // The total reaction on `node` placed at p: its own term and each neighbour's term (on a
  // closed manifold surface the neighbours are exactly the terms whose ring holds `node`).
  const auto force_on_node = [&](const Vector3d& p) {
    const auto position = [&x, &p, node](int32_t k) -> Vector3d {
      return k == node ? p : Vector3d(x.col(k));
    };
    Vector3d force = Vector3d::Zero();
    for (int32_t j = -1; j < own_n; ++j) {
      const auto t =
          j < 0 ? own : static_cast<size_t>(term_of_node_[static_cast<size_t>(own_ring[j])]);
      const int32_t* ring = ring_.data() + ring_offsets_[t];
      const int32_t n = ring_offsets_[t + 1] - ring_offsets_[t];
      const Vector3d xi = position(nodes_[t]);
      const double scale =
          EvalReaction(parameters_, RingSolidAngle(ring, n, xi, position) - rest_angle_[t])
              .derivative;
      Vector3d gradient = Vector3d::Zero();
      const Vector3d gradient_i = RingSolidAngleGradient(
          ring, n, xi, position, [&gradient, node](int32_t k, const Vector3d& g) {
            if (k == node) gradient += g;
          });
      force -= scale * (j < 0 ? gradient_i : gradient);
    }
    return force;
  };

  double mean_edge = 0.0;
  for (int32_t j = 0; j < own_n; ++j) mean_edge += (x.col(own_ring[j]) - x.col(node)).norm();
  const double h = kRelativeStep * mean_edge / own_n;
  const Vector3d x0 = x.col(node);
  Matrix3d stiffness;
  for (int axis = 0; axis < 3; ++axis) {
    const Vector3d step = h * Vector3d::Unit(axis);
    stiffness.col(axis) = -(force_on_node(x0 + step) - force_on_node(x0 - step)) / (2.0 * h);
  }
  return 0.5 * (stiffness + stiffness.transpose());
}

}  // namespace somasim::models
