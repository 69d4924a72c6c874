// A child process (the demo runs the server and the mock haptic node; tests run them to kill
// them): started with posix_spawn, its stdout and stderr to files, signalled, waited for with a
// timeout. The destructor kills (SIGKILL) and reaps a child still running.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <string>
#include <vector>

namespace somasim::app {

class ChildProcess {
 public:
  // Starts argv[0] (a path) with the arguments; stdout and stderr go to `output_file` ("" keeps
  // the parent's). Throws std::runtime_error naming the program when it cannot start.
  ChildProcess(const std::vector<std::string>& argv, const std::string& output_file);
  ~ChildProcess();
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  pid_t pid() const { return pid_; }
  void Signal(int signal);
  // Waits up to `timeout` for the child to end. Returns its exit code, 128 + the signal that
  // ended it, or -1 if it still runs.
  int Wait(std::chrono::milliseconds timeout);
  bool running() const { return !reaped_; }

 private:
  pid_t pid_ = -1;
  bool reaped_ = false;
  int status_ = -1;
};

}  // namespace somasim::app
