// OpenBLAS kernels for the CPU we run on (CHOLMOD's factorisations: somasim-solve,
// somasim-reduce).
//
// Debian 12's OpenBLAS (0.3.21, one library with kernels for many CPUs, chosen when it loads)
// does not recognise some newer CPUs and falls back to its Prescott (SSE3) kernels: CHOLMOD's
// supernodal factorisations then run several times slower than with the AVX2 or AVX-512 kernels
// the CPU can run (docs/benchmarks.md has the figures). OpenBLAS reads
// OPENBLAS_CORETYPE once, as it loads, so a program can only choose better kernels by setting it
// and executing itself again, before it has done anything else.
#pragma once

#include <string>

namespace somasim::app {

// What PreferFastBlasKernels decided, for tests and logs.
struct BlasKernelChoice {
  std::string loaded;  // the kernels OpenBLAS loaded ("Prescott", ...; "" when not OpenBLAS)
  std::string wanted;  // the OPENBLAS_CORETYPE to run again with, "" for none
  std::string reason;  // why (or why not), one line
};

// The decision alone (no side effects): `wanted` is set when OpenBLAS fell back to its generic
// x86-64 kernels (Prescott, Core2, Nehalem, Atom) on a CPU with AVX2 and FMA ("Haswell") or
// AVX-512 F/CD/BW/DQ/VL ("SkylakeX"), and neither OPENBLAS_CORETYPE nor SOMASIM_BLAS_KERNELS
// (set to "keep", or set by the run before) is in the environment.
BlasKernelChoice ChooseBlasKernels();

// Called first thing in main(): when ChooseBlasKernels() wants other kernels, sets
// OPENBLAS_CORETYPE and SOMASIM_BLAS_KERNELS=rerun, says so on stderr as `program: ...`, and
// executes /proc/self/exe again with the same arguments (same pid, same streams: nothing has
// been written yet). Returns when nothing is to be done or the exec fails (then it says so and
// the program goes on with the kernels it has).
void PreferFastBlasKernels(const char* program, char** argv);

}  // namespace somasim::app
