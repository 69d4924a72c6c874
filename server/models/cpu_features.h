// What the CPU offers the hand-vectorised kernels: each kernel with an AVX-512 path asks here,
// once, and takes its scalar path on CPUs without it (and on targets other than x86-64).
#pragma once

namespace somasim::models {

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
// AVX-512 F and VL (the 512- and 256-bit forms the kernels use).
inline bool CpuHasAvx512() {
  static const bool has = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx512f") != 0 && __builtin_cpu_supports("avx512vl") != 0;
  }();
  return has;
}
#else
inline bool CpuHasAvx512() { return false; }
#endif

}  // namespace somasim::models
