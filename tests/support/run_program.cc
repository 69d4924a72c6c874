#include "tests/support/run_program.h"

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <filesystem>

namespace somasim::testing {

ToolRun RunCommand(const std::string& command) {
  ToolRun run;
  FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (pipe == nullptr) return run;
  std::array<char, 4096> buffer;
  size_t n = 0;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) run.out.append(buffer.data(), n);
  const int status = pclose(pipe);
  run.status = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return run;
}

ToolRun RunProgram(const std::string& program, const std::string& args) {
  const char* env = std::getenv("SOMASIM_BIN_DIR");
  const std::string bin =
      env != nullptr ? std::string(env)
                     : std::filesystem::read_symlink("/proc/self/exe").parent_path().string();
  return RunCommand(bin + "/" + program + " " + args);
}

}  // namespace somasim::testing
