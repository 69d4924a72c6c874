// The stations' side of the server, on two threads of its own so the physics never waits on
// the network and the network never waits on the physics (SPEC §1):
//  - intake: tool commands as they arrive (a DDS waitset), checked (wire_adapters.h), into the
//    physics runner's command ring; bad ones dropped, counted, the first ten and every
//    thousandth logged. Not started for a replay (the recording drives the tools).
//  - force models: woken by the physics after each tick, each tool's newest output from its
//    slot into a best-effort ForceModel sample.
#pragma once

#include <atomic>
#include <cstdint>
#include <string>
#include <thread>
#include <vector>

#include "server/net/endpoints.h"
#include "server/runner/physics_runner.h"

namespace somasim::net {

struct LinkCounters {
  std::atomic<uint64_t> commands_received{0};
  std::atomic<uint64_t> commands_rejected{0};  // bad samples, and commands the ring had no room for
  std::atomic<uint64_t> force_models{0};       // written
};

class ToolLink {
 public:
  // `runner`, `endpoints` outlive the link. `intake`: take tool commands (not for a replay).
  ToolLink(runner::PhysicsRunner& runner, Endpoints& endpoints, uint64_t server_id, bool intake);
  ~ToolLink();  // stops and joins
  ToolLink(const ToolLink&) = delete;
  ToolLink& operator=(const ToolLink&) = delete;

  void Start();
  void Stop();
  const LinkCounters& counters() const { return counters_; }

 private:
  void IntakeLoop();
  void ForceModelLoop();
  void WriteForceModels();

  runner::PhysicsRunner& runner_;
  Endpoints& endpoints_;
  uint64_t server_id_;
  bool intake_;
  std::vector<std::string> tool_ids_;
  std::vector<std::string> organ_ids_;
  std::vector<uint64_t> written_version_;  // per tool: the slot version last written
  std::vector<somasim_wire_ForceModel> samples_;
  LinkCounters counters_;
  std::atomic<bool> stop_{false};
  std::thread intake_thread_;
  std::thread force_thread_;
};

}  // namespace somasim::net
