// The choice of OpenBLAS kernels (common/app/blas_kernels.h): made only when OpenBLAS fell back to
// generic kernels on a CPU that runs better ones, never against the user's own setting, and the
// programs that use it run again with it (the kernels then reported are the chosen ones).
#include "common/app/blas_kernels.h"

#include <dlfcn.h>
#include <gtest/gtest.h>

#include <cstdlib>
#include <string>

#include "tests/support/run_program.h"

namespace somasim::app {
namespace {

// Sets (or, with nullptr, unsets) an environment variable for one scope.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const char* value) : name_(name) {
    const char* old = std::getenv(name);
    had_ = old != nullptr;
    if (had_) old_ = old;
    if (value != nullptr) {
      setenv(name, value, 1);
    } else {
      unsetenv(name);
    }
  }
  ~ScopedEnv() {
    if (had_) {
      setenv(name_.c_str(), old_.c_str(), 1);
    } else {
      unsetenv(name_.c_str());
    }
  }
  ScopedEnv(const ScopedEnv&) = delete;
  ScopedEnv& operator=(const ScopedEnv&) = delete;

 private:
  std::string name_, old_;
  bool had_ = false;
};

bool Generic(const std::string& kernels) {
  return kernels == "Prescott" || kernels == "Core2" || kernels == "Nehalem" || kernels == "Atom" ||
         kernels == "PRESCOTT" || kernels == "CORE2" || kernels == "NEHALEM" || kernels == "ATOM";
}

TEST(BlasKernels, TheUsersOwnSettingIsNeverOverridden) {
  {
    const ScopedEnv set("OPENBLAS_CORETYPE", "Haswell");
    const BlasKernelChoice choice = ChooseBlasKernels();
    EXPECT_TRUE(choice.wanted.empty()) << choice.reason;
  }
  {
    const ScopedEnv unset("OPENBLAS_CORETYPE", nullptr);
    const ScopedEnv keep("SOMASIM_BLAS_KERNELS", "keep");
    const BlasKernelChoice choice = ChooseBlasKernels();
    EXPECT_TRUE(choice.wanted.empty()) << choice.reason;
  }
}

// Neither variable set, and OpenBLAS in the process (the programs get it through CHOLMOD; these
// tests load it themselves).
class BlasKernelsUnset : public ::testing::Test {
 protected:
  void SetUp() override {
    if (dlopen("libopenblas.so.0", RTLD_NOW | RTLD_GLOBAL) == nullptr) {
      GTEST_SKIP() << "no OpenBLAS here: " << dlerror();
    }
  }
  const ScopedEnv unset_{"OPENBLAS_CORETYPE", nullptr};
  const ScopedEnv unset_own_{"SOMASIM_BLAS_KERNELS", nullptr};
};

TEST_F(BlasKernelsUnset, OnlyGenericKernelsOnACapableCpuAreReplaced) {
  const BlasKernelChoice choice = ChooseBlasKernels();
  EXPECT_FALSE(choice.reason.empty());
  ASSERT_FALSE(choice.loaded.empty()) << choice.reason;
  __builtin_cpu_init();
  const bool avx2 = __builtin_cpu_supports("avx2") != 0 && __builtin_cpu_supports("fma") != 0;
  if (Generic(choice.loaded) && avx2) {
    EXPECT_TRUE(choice.wanted == "Haswell" || choice.wanted == "SkylakeX") << choice.wanted;
  } else {
    EXPECT_TRUE(choice.wanted.empty()) << choice.loaded << ": " << choice.reason;
  }
}

TEST_F(BlasKernelsUnset, TheSolverRunsAgainWithTheChosenKernelsOnlyWhenItShould) {
  const BlasKernelChoice choice = ChooseBlasKernels();
  // A run that fails at once on its scene (exit 3) after choosing its kernels.
  const testing::ToolRun run =
      testing::RunProgram("somasim-solve", "builtin:no_such_organ --out /nonexistent/out");
  EXPECT_EQ(run.status, 3) << run.out;
  const bool said = run.out.find("running again with OPENBLAS_CORETYPE=") != std::string::npos;
  EXPECT_EQ(said, !choice.wanted.empty()) << run.out;
  if (!choice.wanted.empty()) {
    EXPECT_NE(run.out.find("OPENBLAS_CORETYPE=" + choice.wanted), std::string::npos) << run.out;
    // Said once: the second run sees SOMASIM_BLAS_KERNELS and goes on.
    EXPECT_EQ(run.out.find("running again", run.out.find("running again") + 1), std::string::npos)
        << run.out;
  }
  EXPECT_NE(run.out.find("unknown organ \"no_such_organ\""), std::string::npos) << run.out;
  // --version needs no kernels: it never runs again.
  const testing::ToolRun version = testing::RunProgram("somasim-solve", "--version");
  EXPECT_EQ(version.status, 0);
  EXPECT_EQ(version.out.find("running again"), std::string::npos) << version.out;
  EXPECT_NE(version.out.find("somasim-solve "), std::string::npos) << version.out;
}

}  // namespace
}  // namespace somasim::app
