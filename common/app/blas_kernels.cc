#include "common/app/blas_kernels.h"

#include <dlfcn.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <iostream>

namespace somasim::app {
namespace {

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}

// OpenBLAS's name for the kernels it loaded ("" when the BLAS in this process is not OpenBLAS:
// looked up at run time, so nothing here needs OpenBLAS to link).
std::string LoadedOpenBlasKernels() {
  using CoreName = char* (*)();
  void* symbol = dlsym(RTLD_DEFAULT, "openblas_get_corename");
  if (symbol == nullptr) return "";
  CoreName core_name = nullptr;
  static_assert(sizeof(symbol) == sizeof(core_name));
  std::memcpy(&core_name, &symbol, sizeof(symbol));
  const char* name = core_name();
  return name != nullptr ? std::string(name) : std::string();
}

}  // namespace

BlasKernelChoice ChooseBlasKernels() {
  BlasKernelChoice choice;
  choice.loaded = LoadedOpenBlasKernels();
  if (choice.loaded.empty()) {
    choice.reason = "the BLAS is not OpenBLAS";
    return choice;
  }
  if (std::getenv("OPENBLAS_CORETYPE") != nullptr) {
    choice.reason = "OPENBLAS_CORETYPE is set";
    return choice;
  }
  if (std::getenv("SOMASIM_BLAS_KERNELS") != nullptr) {
    choice.reason = "SOMASIM_BLAS_KERNELS is set";
    return choice;
  }
  const std::string loaded = Lower(choice.loaded);
  if (loaded != "prescott" && loaded != "core2" && loaded != "nehalem" && loaded != "atom") {
    choice.reason = "OpenBLAS recognised this CPU";
    return choice;
  }
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
  __builtin_cpu_init();
  const bool avx2 = __builtin_cpu_supports("avx2") != 0 && __builtin_cpu_supports("fma") != 0;
  const bool avx512 =
      __builtin_cpu_supports("avx512f") != 0 && __builtin_cpu_supports("avx512cd") != 0 &&
      __builtin_cpu_supports("avx512bw") != 0 && __builtin_cpu_supports("avx512dq") != 0 &&
      __builtin_cpu_supports("avx512vl") != 0;
  if (avx512) {
    choice.wanted = "SkylakeX";
  } else if (avx2) {
    choice.wanted = "Haswell";
  }
#endif
  choice.reason = choice.wanted.empty()
                      ? "the CPU has no AVX2: OpenBLAS's " + choice.loaded + " kernels are right"
                      : "OpenBLAS loaded its generic " + choice.loaded +
                            " kernels on a CPU that runs its " + choice.wanted + " ones";
  return choice;
}

void PreferFastBlasKernels(const char* program, char** argv) {
  const BlasKernelChoice choice = ChooseBlasKernels();
  if (choice.wanted.empty()) return;
  setenv("OPENBLAS_CORETYPE", choice.wanted.c_str(), 1);
  setenv("SOMASIM_BLAS_KERNELS", "rerun", 1);
  std::cerr << program << ": " << choice.reason
            << "; running again with OPENBLAS_CORETYPE=" << choice.wanted
            << " (set OPENBLAS_CORETYPE, or SOMASIM_BLAS_KERNELS=keep, to choose)" << std::endl;
  execv("/proc/self/exe", argv);
  const int error = errno;
  std::cerr << program << ": could not run again (" << std::strerror(error)
            << "); going on with OpenBLAS's " << choice.loaded << " kernels" << std::endl;
}

}  // namespace somasim::app
