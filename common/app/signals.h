// Clean shutdown on SIGINT and SIGTERM: the handler only sets a flag that the process's loops
// poll (async-signal-safe), so every thread finishes its work and every file is closed.
#pragma once

#include <atomic>

namespace somasim::app {

// Installs the handlers (once; later calls do nothing).
void InstallStopSignals();
// True once SIGINT or SIGTERM has arrived (or RequestStop was called).
bool StopRequested();
void RequestStop();
// The signal that asked to stop (0: none or RequestStop).
int StopSignal();

}  // namespace somasim::app
