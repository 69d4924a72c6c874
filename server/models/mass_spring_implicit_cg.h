// The conjugate-gradient operators of the mass-spring implicit step (mass_spring_implicit_cg.cc):
// the multicolour symmetric block Gauss-Seidel preconditioner, the product A x and CG's vector
// updates on the solver's layout, each scalar (the reference) and with AVX-512. Internal to
// server/models.
#pragma once

#include <cstddef>
#include <cstdint>

namespace somasim::models {

constexpr size_t kImplicitLanes = 8;   // lanes of a group: one AVX-512 register of doubles
constexpr size_t kImplicitRecord = 8;  // doubles per spring in MassSpringState::implicit_springs

// Raw views of the solver's layout (see MassSpringModel's implicit-step data). Vectors are
// 3 blocks x, y, z of P doubles each.
struct ImplicitLayout {
  size_t padded = 0;  // P
  size_t groups = 0;
  size_t colours = 0;
  const int32_t* colour_start = nullptr;
  const int32_t* row_start = nullptr;
  const int32_t* lower_rows = nullptr;
  const int32_t* neighbour = nullptr;
  const double* rows = nullptr;             // rows × 32
  const double* inverse = nullptr;          // 6 × P
  const double* diagonal = nullptr;         // 6 × P
  const double* keep = nullptr;             // P
  const uint8_t* massless_group = nullptr;  // groups: 1 if a lane has no mass
};

// z = P⁻¹ r: a forward sweep over the lower-colour slots (y, dy = its right-hand sides), a
// backward sweep over the higher-colour ones, then a pass over the lower slots again, which with
// the sweeps' by-products gives az = A z; returns r · z.
double PreconditionScalar(const ImplicitLayout& l, const double* r, double* dy, double* z,
                          double* az);

// q = A x (held lanes 0).
void ProductScalar(const ImplicitLayout& l, const double* x, double* q);

// CG's step along the last direction, done inside the next preconditioner application (its
// forward sweep reads r anyway, its last pass p): r -= α q, Δv += α p, and the stop when |r|² <=
// threshold2 (then only Δv is updated).
struct CgUpdate {
  double alpha = 0.0;
  double threshold2 = 0.0;
  double* dv = nullptr;
};

// Unless `first`, first CG's step along the last direction (see CgUpdate; the forward sweep
// updates r and sums |r|² into *residual_norm2, returning 0 at once if that converged). Then z =
// P⁻¹ r as PreconditionScalar, fused with CG's direction update: p = z + β p and q = A z + β q
// with β = (r · z) / rz_before (p = z, q = A z when `first`); returns r · z and sets *curvature =
// p · q. A z is formed as in PreconditionScalar, its lower-colour part in the last pass, which
// updates Δv, p and q right away. zg (4 × P): the records of y, then z, that the sweeps read at
// other nodes (z itself is read back from them); az holds D z - s on groups with a massless lane.
// Compiled for AVX-512 F and VL: only for CPUs that have them.
double PreconditionAvx512(const ImplicitLayout& l, const CgUpdate& update, double* r, double* dy,
                          double* az, double* zg, bool first, double rz_before, double* search,
                          double* q, double* curvature, double* residual_norm2);

// q = A x; xg (4 × P) receives the records of x. AVX-512 F and VL.
void ProductAvx512(const ImplicitLayout& l, const double* x, double* q, double* xg);

// CG's fused vector updates over `size` doubles (a multiple of 8).
// dv += α p, r -= α q; returns |r|².
double StepScalar(double alpha, size_t size, const double* p, const double* q, double* dv,
                  double* r);
// p = z + β p, q = az + β q; returns p · q.
double DirectionScalar(double beta, size_t size, const double* z, const double* az, double* p,
                       double* q);
// a · b (the AVX-512 one: F and VL, in a fixed order of 8 partial sums).
double DotScalar(size_t size, const double* a, const double* b);
double DotAvx512(size_t size, const double* a, const double* b);

}  // namespace somasim::models
