#include "common/app/signals.h"

#include <csignal>

namespace somasim::app {
namespace {

volatile std::sig_atomic_t g_signal = 0;
std::atomic<bool> g_stop{false};

extern "C" void OnStopSignal(int signal) {
  g_signal = signal;
  g_stop.store(true, std::memory_order_relaxed);  // lock-free atomic: async-signal-safe
}

}  // namespace

void InstallStopSignals() {
  static bool installed = false;
  if (installed) return;
  installed = true;
  struct sigaction action {};
  action.sa_handler = OnStopSignal;
  sigemptyset(&action.sa_mask);
  sigaction(SIGINT, &action, nullptr);
  sigaction(SIGTERM, &action, nullptr);
}

bool StopRequested() { return g_stop.load(std::memory_order_relaxed); }
void RequestStop() { g_stop.store(true, std::memory_order_relaxed); }
int StopSignal() { return static_cast<int>(g_signal); }

}  // namespace somasim::app
