#include "server/models/reduced/modal_field.h"

#include <algorithm>

#include "server/models/cpu_features.h"

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SOMASIM_MODAL_AVX512 1
#endif

namespace somasim::models::reduced {
namespace {

struct Pass {
  const float* modes;
  size_t stride;
  int32_t n;
  const double* xi;
  const double* rate;  // ξ̇ [1/s]
  const double* rest;
  double* x;
  double* v;
};

void ReconstructRange(const Pass& r, size_t begin, size_t end) {
  for (size_t k = begin; k < end; ++k) {
    double u = 0.0, w = 0.0;
    for (int32_t j = 0; j < r.n; ++j) {
      const auto b = static_cast<double>(r.modes[static_cast<size_t>(j) * r.stride + k]);
      u += r.xi[j] * b;
      w += r.rate[j] * b;
    }
    r.x[k] = r.rest[k] + u;
    r.v[k] = w;
  }
}

#ifdef SOMASIM_MODAL_AVX512
// 32 DOFs at a time: four 8-double accumulators for x and four for v, each column's 32 floats
// converted as loaded (ξ_j and ξ̇_j broadcast once per column and chunk).
__attribute__((target("avx512f"))) void ReconstructAvx512(const Pass& r, size_t count) {
  size_t k = 0;
  for (; k + 32 <= count; k += 32) {
    __m512d u[4], w[4];
    for (int q = 0; q < 4; ++q) u[q] = w[q] = _mm512_setzero_pd();
    const float* column = r.modes + k;
    for (int32_t j = 0; j < r.n; ++j, column += r.stride) {
      const __m512d xi = _mm512_set1_pd(r.xi[j]);
      const __m512d rate = _mm512_set1_pd(r.rate[j]);
      for (int q = 0; q < 4; ++q) {
        const __m512d b = _mm512_maskz_cvtps_pd(0xFF, _mm256_loadu_ps(column + 8 * q));
        u[q] = _mm512_fmadd_pd(b, xi, u[q]);
        w[q] = _mm512_fmadd_pd(b, rate, w[q]);
      }
    }
    for (int q = 0; q < 4; ++q) {
      const size_t at = k + 8 * static_cast<size_t>(q);
      _mm512_storeu_pd(r.x + at, _mm512_add_pd(_mm512_loadu_pd(r.rest + at), u[q]));
      _mm512_storeu_pd(r.v + at, w[q]);
    }
  }
  ReconstructRange(r, k, count);
}
#endif

}  // namespace

ModalField::ModalField(const Eigen::MatrixXd& modes)
    : dofs_(static_cast<size_t>(modes.rows())), n_(static_cast<int32_t>(modes.cols())) {
  stride_ = (dofs_ + 15) / 16 * 16;
  modes_.assign(stride_ * static_cast<size_t>(n_), 0.0F);
  for (Eigen::Index j = 0; j < modes.cols(); ++j) {
    for (Eigen::Index k = 0; k < modes.rows(); ++k) {
      modes_[static_cast<size_t>(j) * stride_ + static_cast<size_t>(k)] =
          static_cast<float>(modes(k, j));
    }
  }
}

void ModalField::Reconstruct(const double* xi, const double* rate, const double* rest, double* x,
                             double* v) const {
  const Pass r{modes_.data(), stride_, n_, xi, rate, rest, x, v};
#ifdef SOMASIM_MODAL_AVX512
  if (CpuHasAvx512()) {
    ReconstructAvx512(r, dofs_);
    return;
  }
#endif
  ReconstructRange(r, 0, dofs_);
}

void ModalState::InitialiseModal(const ModalField& modal_field, const double* rest_positions) {
  xi = Eigen::VectorXd::Zero(modal_field.num_modes());
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
  field_->Reconstruct(xi.data(), rate.data(), rest_, positions.data(), velocities.data());
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

int32_t AddProjectedLoads(const Eigen::MatrixXd& modes, const mesh::Points& f, Eigen::VectorXd* r) {
  const Eigen::Index nodes = f.cols();
  const auto* bits = reinterpret_cast<const uint64_t*>(f.data());
  constexpr Eigen::Index kBlock = 8;
  int32_t loaded = -1;
  double largest = 0.0;
  for (Eigen::Index first = 0; first < nodes; first += kBlock) {
    const Eigen::Index last = std::min(nodes, first + kBlock);
    uint64_t any = 0;
    for (Eigen::Index k = 3 * first; k < 3 * last; ++k) any |= bits[k] << 1U;
    if (any == 0) continue;
    for (Eigen::Index i = first; i < last; ++i) {
      const double norm2 = f.col(i).squaredNorm();
      if (norm2 == 0.0) continue;
      r->noalias() += modes.middleRows(3 * i, 3).transpose() * f.col(i);
      if (norm2 > largest) {
        largest = norm2;
        loaded = static_cast<int32_t>(i);
      }
    }
  }
  return loaded;
}

bool SpringTerms(const Eigen::MatrixXd& modes, const mesh::Points& rest, const uint8_t* moves,
                 double penalty, const StepInputs& inputs, const mesh::Points& positions,
                 Eigen::MatrixXd* matrix, Eigen::VectorXd* rhs) {
  bool any = false;
  const auto spring = [&](int32_t node, const Eigen::Vector3d& target, double k) {
    if (k == 0.0) return;
    if (!any) {
      matrix->setZero();
      rhs->setZero();
      any = true;
    }
    const auto rows = modes.middleRows(3 * node, 3);
    matrix->noalias() += k * rows.transpose() * rows;
    rhs->noalias() += k * rows.transpose() * (target - rest.col(node));
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
