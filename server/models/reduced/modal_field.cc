#include "server/models/reduced/modal_field.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "common/checks/finite.h"
#include "server/models/cpu_features.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_MODAL_AVX512 1
#endif

namespace somasim::models::reduced {
namespace {

struct Pass {
  const float* modes;  // chunk c, mode j: kChunk floats at (c n + j) kChunk
  int32_t n;
  const float* xi;
  const float* rate;  // ξ̇ [1/s]
  const double* rest;
  double* x;
  double* v;
  double component_limit;  // [m/s]
};

// DOFs [begin, end) of one chunk (end - begin <= kChunk), portable.
void ReconstructChunk(const Pass& r, size_t chunk, size_t begin, size_t end, StateCheck* check) {
  const float* block = r.modes + chunk * static_cast<size_t>(r.n) * ModalField::kChunk;
  for (size_t k = begin; k < end; ++k) {
    const size_t d = k - chunk * ModalField::kChunk;
    float u = 0.0F, w = 0.0F;
    for (int32_t j = 0; j < r.n; ++j) {
      const float b = block[static_cast<size_t>(j) * ModalField::kChunk + d];
      u += r.xi[j] * b;
      w += r.rate[j] * b;
    }
    r.x[k] = r.rest[k] + static_cast<double>(u);
    r.v[k] = static_cast<double>(w);
    check->Add(r.x[k], r.v[k], r.component_limit);
  }
}

#ifdef SOMASIM_MODAL_AVX512
// One chunk (32 DOFs) at a time: two 16-float accumulators for u and two for v, one FMA per 16
// DOFs and mode, the chunk's n × 32 floats read in order (one stream for the prefetcher); then
// x = X + u and v in double, checked in registers as they are stored. (The zero-masked forms of
// the extract and convert intrinsics: GCC 12 warns that the plain ones' source may be
// uninitialised.)
__attribute__((target("avx512f"))) StateCheck ReconstructAvx512(const Pass& r, size_t count) {
  static_assert(ModalField::kChunk == 32);
  __mmask8 bad = 0, above = 0;
  const __m512d limit = _mm512_set1_pd(r.component_limit);
  size_t k = 0;
  const float* block = r.modes;
  for (; k + 32 <= count; k += 32) {
    __m512 u0 = _mm512_setzero_ps(), u1 = _mm512_setzero_ps();
    __m512 w0 = _mm512_setzero_ps(), w1 = _mm512_setzero_ps();
    for (int32_t j = 0; j < r.n; ++j, block += 32) {
      const __m512 xi = _mm512_set1_ps(r.xi[j]);
      const __m512 rate = _mm512_set1_ps(r.rate[j]);
      const __m512 b0 = _mm512_loadu_ps(block);
      const __m512 b1 = _mm512_loadu_ps(block + 16);
      u0 = _mm512_fmadd_ps(b0, xi, u0);
      u1 = _mm512_fmadd_ps(b1, xi, u1);
      w0 = _mm512_fmadd_ps(b0, rate, w0);
      w1 = _mm512_fmadd_ps(b1, rate, w1);
    }
    const __m256 halves_u[4] = {
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(u0), 0)),
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(u0), 1)),
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(u1), 0)),
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(u1), 1))};
    const __m256 halves_w[4] = {
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(w0), 0)),
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(w0), 1)),
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(w1), 0)),
        _mm256_castpd_ps(_mm512_maskz_extractf64x4_pd(0xF, _mm512_castps_pd(w1), 1))};
    for (int q = 0; q < 4; ++q) {
      const size_t at = k + 8 * static_cast<size_t>(q);
      const __m512d x =
          _mm512_add_pd(_mm512_loadu_pd(r.rest + at), _mm512_maskz_cvtps_pd(0xFF, halves_u[q]));
      const __m512d v = _mm512_maskz_cvtps_pd(0xFF, halves_w[q]);
      _mm512_storeu_pd(r.x + at, x);
      _mm512_storeu_pd(r.v + at, v);
      bad |= _mm512_cmp_pd_mask(_mm512_sub_pd(x, x), _mm512_sub_pd(v, v), _CMP_UNORD_Q);
      above |= _mm512_cmp_pd_mask(_mm512_abs_pd(v), limit, _CMP_GT_OQ);
    }
  }
  StateCheck check{bad != 0, above != 0};
  if (k < count) ReconstructChunk(r, k / 32, k, count, &check);
  return check;
}
#endif

}  // namespace

ModalField::ModalField(const Eigen::MatrixXd& modes)
    : dofs_(static_cast<size_t>(modes.rows())), n_(static_cast<int32_t>(modes.cols())) {
  const size_t chunks = (dofs_ + kChunk - 1) / kChunk;
  modes_.assign(chunks * static_cast<size_t>(n_) * kChunk, 0.0F);
  for (Eigen::Index j = 0; j < modes.cols(); ++j) {
    for (Eigen::Index k = 0; k < modes.rows(); ++k) {
      const auto dof = static_cast<size_t>(k);
      const size_t chunk = dof / kChunk;
      modes_[(chunk * static_cast<size_t>(n_) + static_cast<size_t>(j)) * kChunk + dof % kChunk] =
          static_cast<float>(modes(k, j));
    }
  }
}

StateCheck ModalField::Reconstruct(const float* xi, const float* rate, const double* rest,
                                   double* x, double* v, double component_limit) const {
  const Pass r{modes_.data(), n_, xi, rate, rest, x, v, component_limit};
#ifdef SOMASIM_MODAL_AVX512
  if (CpuHasAvx512()) return ReconstructAvx512(r, dofs_);
#endif
  StateCheck check;
  for (size_t begin = 0; begin < dofs_; begin += kChunk) {
    ReconstructChunk(r, begin / kChunk, begin, std::min(dofs_, begin + kChunk), &check);
  }
  return check;
}

void ModalState::InitialiseModal(const ModalField& modal_field, const double* rest_positions,
                                 double speed_limit) {
  xi = Eigen::VectorXd::Zero(modal_field.num_modes());
  xi_single_ = Eigen::VectorXf::Zero(modal_field.num_modes());
  rate_single_ = xi_single_;
  component_limit_ = speed_limit / std::sqrt(3.0);
  xi_prev = xi;
  rate = xi;
  good_xi_ = xi;
  good_xi_prev_ = xi;
  field_ = &modal_field;
  rest_ = rest_positions;
}

void ModalState::Rebuild() {
  if (dt > 0.0) {
    rate = (xi - xi_prev) / dt;
  } else {
    rate.setZero();
  }
  xi_single_ = xi.cast<float>();
  rate_single_ = rate.cast<float>();
  const StateCheck check =
      field_->Reconstruct(xi_single_.data(), rate_single_.data(), rest_, positions.data(),
                          velocities.data(), component_limit_);
  checked_non_finite_ = check.non_finite || !xi.allFinite() || !rate.allFinite();
  checked_maybe_too_fast_ = check.maybe_too_fast;
}

void ModalState::SaveModal() {
  good_xi_ = xi;
  good_xi_prev_ = xi_prev;
  good_dt_ = dt;
}

void ModalState::RestoreModal() {
  xi = good_xi_;
  xi_prev = good_xi_prev_;
  dt = good_dt_;
  Rebuild();
}

namespace {

constexpr Eigen::Index kLoadBlock = 8;  // nodes: 24 doubles, three 8-double vectors

// The first block b >= first (of `blocks` whole blocks of kLoadBlock nodes) with a value other
// than ±0, or `blocks` when there is none: an OR of the bits without the sign (vectorised by the
// compiler), or on AVX-512 three compares per block.
Eigen::Index NextLoadedBlockPortable(const double* f, Eigen::Index first, Eigen::Index blocks) {
  const auto* bits = reinterpret_cast<const uint64_t*>(f);
  for (Eigen::Index b = first; b < blocks; ++b) {
    uint64_t any = 0;
    for (Eigen::Index k = 3 * kLoadBlock * b; k < 3 * kLoadBlock * (b + 1); ++k) {
      any |= bits[k] << 1U;
    }
    if (any != 0) return b;
  }
  return blocks;
}

#ifdef SOMASIM_MODAL_AVX512
__attribute__((target("avx512f"))) Eigen::Index NextLoadedBlockAvx512(const double* f,
                                                                      Eigen::Index first,
                                                                      Eigen::Index blocks) {
  static_assert(kLoadBlock == 8);
  const __m512d zero = _mm512_setzero_pd();
  for (Eigen::Index b = first; b < blocks; ++b) {
    const double* p = f + 24 * b;
    // NEQ_UQ: true for NaN too (the model's Step has refused non-finite loads already).
    const __mmask8 any = _mm512_cmp_pd_mask(_mm512_loadu_pd(p), zero, _CMP_NEQ_UQ) |
                         _mm512_cmp_pd_mask(_mm512_loadu_pd(p + 8), zero, _CMP_NEQ_UQ) |
                         _mm512_cmp_pd_mask(_mm512_loadu_pd(p + 16), zero, _CMP_NEQ_UQ);
    if (any != 0) return b;
  }
  return blocks;
}
#endif

Eigen::Index NextLoadedBlock(const double* f, Eigen::Index first, Eigen::Index blocks) {
#ifdef SOMASIM_MODAL_AVX512
  if (CpuHasAvx512()) return NextLoadedBlockAvx512(f, first, blocks);
#endif
  return NextLoadedBlockPortable(f, first, blocks);
}

}  // namespace

void CheckModalData(const mesh::Points& rest, const std::vector<double>& masses,
                    const Eigen::MatrixXd& modes, const std::string& prefix) {
  const auto require = [&prefix](bool ok, const std::string& what) {
    if (!ok) throw std::invalid_argument(prefix + what);
  };
  const Eigen::Index nodes = rest.cols();
  require(nodes >= 1, "rest has no node");
  require(rest.allFinite(), "rest positions are not finite");
  require(static_cast<Eigen::Index>(masses.size()) == nodes,
          "masses: " + std::to_string(masses.size()) + " for " + std::to_string(nodes) + " nodes");
  for (const double m : masses) require(checks::FinitePositive(m), "a mass is not > 0");
  const Eigen::Index n = modes.cols();
  require(modes.rows() == 3 * nodes && n >= 1 && n <= 3 * nodes,
          "modes must be 3N × n with 1 <= n <= 3N, got " + std::to_string(modes.rows()) + " × " +
              std::to_string(n) + " for N = " + std::to_string(nodes));
  require(modes.allFinite(), "a mode is not finite");
}

Eigen::Matrix3d CappedStiffness(const Eigen::Matrix3d& compliance, double max_stiffness) {
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(compliance);
  Eigen::Vector3d stiffness;
  for (int k = 0; k < 3; ++k) {
    const double c = eigen.eigenvalues()(k);
    stiffness(k) = c * max_stiffness > 1.0 ? 1.0 / c : max_stiffness;
  }
  return eigen.eigenvectors() * stiffness.asDiagonal() * eigen.eigenvectors().transpose();
}

int32_t AddProjectedLoads(const Eigen::MatrixXd& modes, const mesh::Points& f, Eigen::VectorXd* r) {
  const Eigen::Index nodes = f.cols();
  const Eigen::Index blocks = nodes / kLoadBlock;  // whole blocks; the rest node by node
  int32_t loaded = -1;
  double largest = 0.0;
  const auto add = [&](Eigen::Index first, Eigen::Index last) {
    for (Eigen::Index i = first; i < last; ++i) {
      const double norm2 = f.col(i).squaredNorm();
      if (norm2 == 0.0) continue;
      r->noalias() += modes.middleRows(3 * i, 3).transpose() * f.col(i);
      if (norm2 > largest) {
        largest = norm2;
        loaded = static_cast<int32_t>(i);
      }
    }
  };
  for (Eigen::Index b = NextLoadedBlock(f.data(), 0, blocks); b < blocks;
       b = NextLoadedBlock(f.data(), b + 1, blocks)) {
    add(kLoadBlock * b, kLoadBlock * (b + 1));
  }
  add(kLoadBlock * blocks, nodes);
  return loaded;
}

bool SpringTerms(const Eigen::MatrixXd& modes, const Eigen::MatrixXd& test_modes,
                 const mesh::Points& rest, const uint8_t* moves, double penalty,
                 const StepInputs& inputs, const mesh::Points& positions, Eigen::MatrixXd* matrix,
                 Eigen::VectorXd* rhs) {
  bool any = false;
  const auto spring = [&](int32_t node, const Eigen::Vector3d& target, double k) {
    if (k == 0.0) return;
    if (!any) {
      matrix->setZero();
      rhs->setZero();
      any = true;
    }
    const auto rows = modes.middleRows(3 * node, 3);
    const auto test_rows = test_modes.middleRows(3 * node, 3);
    matrix->noalias() += k * test_rows.transpose() * rows;
    rhs->noalias() += k * test_rows.transpose() * (target - rest.col(node));
  };
  for (const Attachment& a : inputs.attachments) spring(a.node, a.target, a.stiffness);
  for (size_t p = 0; p < inputs.prescribed_nodes.size(); ++p) {
    spring(inputs.prescribed_nodes[p],
           inputs.prescribed_positions->col(static_cast<Eigen::Index>(p)), penalty);
  }
  for (const int32_t node : inputs.fixed_nodes) {
    if (moves[static_cast<size_t>(node)] != 0) spring(node, positions.col(node), penalty);
  }
  return any;
}

}  // namespace somasim::models::reduced
