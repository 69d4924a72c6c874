// Running the project's executables from tests (exit codes, printed output).
#pragma once

#include <string>

namespace somasim::testing {

struct ToolRun {
  int status = -1;  // the exit code, or -1 when the program did not exit normally
  std::string out;  // stdout, with stderr appended
};

// Runs a shell command line, stdout captured and stderr appended to it.
ToolRun RunCommand(const std::string& command);

// Runs build/bin/<program> with arguments (quoted by the caller). CTest sets SOMASIM_BIN_DIR;
// run by hand, the program is looked up beside the test executable.
ToolRun RunProgram(const std::string& program, const std::string& args);

}  // namespace somasim::testing
