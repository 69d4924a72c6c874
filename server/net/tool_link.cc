#include "server/net/tool_link.h"

#include <poll.h>
#include <unistd.h>

#include <chrono>

#include "common/app/log.h"
#include "common/dds/topics.h"
#include "server/net/wire_adapters.h"

namespace somasim::net {

using app::Log;
using app::LogLevel;

ToolLink::ToolLink(runner::PhysicsRunner& runner, Endpoints& endpoints, uint64_t server_id,
                   bool intake)
    : runner_(runner), endpoints_(endpoints), server_id_(server_id), intake_(intake) {
  const server::Session& session = runner.session();
  for (int32_t t = 0; t < session.num_tools(); ++t) tool_ids_.push_back(session.tool(t).id);
  for (int32_t k = 0; k < session.num_organs(); ++k) {
    organ_ids_.push_back(session.organ(k).built.id);
  }
  written_version_.assign(tool_ids_.size(), 0);
  samples_.resize(tool_ids_.size());
}

ToolLink::~ToolLink() { Stop(); }

void ToolLink::Start() {
  if (intake_) intake_thread_ = std::thread([this] { IntakeLoop(); });
  force_thread_ = std::thread([this] { ForceModelLoop(); });
}

void ToolLink::Stop() {
  stop_.store(true);
  if (intake_thread_.joinable()) intake_thread_.join();
  if (force_thread_.joinable()) force_thread_.join();
}

void ToolLink::IntakeLoop() {
  const server::Session& session = runner_.session();
  while (!stop_.load()) {
    endpoints_.tool_command.WaitForData(std::chrono::milliseconds(20));
    endpoints_.tool_command.Take(
        [&](const somasim_wire_ToolCommand& c, const dds_sample_info_t&) {
          ++counters_.commands_received;
          runner::ToolCommandMsg m;
          std::string error = CheckToolCommand(c, session, &m.tool, &m.input);
          if (error.empty() && !runner_.PushCommand(m)) error = "the physics is not keeping up";
          if (!error.empty()) {
            const uint64_t n = ++counters_.commands_rejected;
            if (n <= 10 || n % 1000 == 0) {
              Log(LogLevel::kWarning, "tool_command_dropped",
                  {{"reason", error}, {"dropped_so_far", n}});
            }
          }
        },
        256);
  }
}

void ToolLink::ForceModelLoop() {
  const int fd = runner_.tool_wake_fd();
  while (!stop_.load()) {
    pollfd p{fd, POLLIN, 0};
    if (poll(&p, 1, 20) > 0) {
      uint64_t n = 0;
      [[maybe_unused]] const ssize_t r = read(fd, &n, sizeof n);
    }
    WriteForceModels();
  }
  WriteForceModels();
}

void ToolLink::WriteForceModels() {
  for (size_t t = 0; t < tool_ids_.size(); ++t) {
    runner::ToolOutput out;
    uint64_t version = 0;
    if (!runner_.tool_output(static_cast<int32_t>(t)).Read(&out, &version)) continue;
    if (version == 0 || version == written_version_[t]) continue;
    written_version_[t] = version;
    somasim_wire_ForceModel& w = samples_[t];
    ToolOutputToWire(out, &w);
    w.tool = dds::CString(tool_ids_[t]);
    w.format_version = dds::kWireFormatVersion;
    w.server_id = server_id_;
    w.organ = out.organ >= 0 ? dds::CString(organ_ids_[static_cast<size_t>(out.organ)])
                             : const_cast<char*>("");
    if (endpoints_.force_model.TryWrite(w) == DDS_RETCODE_OK) ++counters_.force_models;
  }
}

}  // namespace somasim::net
