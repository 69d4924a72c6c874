#include "server/app/report.h"

namespace somasim::server {

nlohmann::ordered_json ServerReport(const ServerOptions& options, uint64_t server_id,
                                    const runner::PhysicsRunner& runner,
                                    const net::Publisher& publisher, const net::ToolLink& link,
                                    const Recorder* recorder) {
  const Session& session = runner.session();
  const runner::StepTimeHistogram& total = runner.total();
  const double wall = runner.wall_time();
  nlohmann::ordered_json r;
  r["session"] = options.session;
  r["scene"] = session.scene().name();
  r["server_id"] = server_id;
  r["sim_time_s"] = session.time();
  r["wall_time_s"] = wall;
  r["realtime_factor"] = wall > 0.0 ? session.time() / wall : 0.0;
  r["ticks"] = session.ticks();
  r["organ_steps"] = session.organ_steps();
  r["rejected_steps"] = session.rejected_steps();
  r["step_time_us"] = {
      {"mean",
       total.count() > 0 ? runner.total_sum_us() / static_cast<double>(total.count()) : 0.0},
      {"p50", total.Quantile(0.5)},
      {"p90", total.Quantile(0.9)},
      {"p99", total.Quantile(0.99)},
      {"max", total.max()}};
  r["frames_published"] = publisher.frames_published();
  r["force_models_published"] = link.counters().force_models.load();
  r["tool_commands_received"] = link.counters().commands_received.load();
  r["tool_commands_rejected"] = link.counters().commands_rejected.load();
  r["instructor_commands_received"] = publisher.instructor_received();
  r["publish_overruns"] = publisher.publish_overruns();
  r["fell_behind_real_time"] = runner.counters().behind.load();
  nlohmann::ordered_json events = nlohmann::ordered_json::object();
  for (const auto& [name, count] : publisher.event_counts()) events[name] = count;
  r["events"] = events;
  nlohmann::ordered_json tools = nlohmann::ordered_json::array();
  for (int32_t t = 0; t < session.num_tools(); ++t) {
    const runner::ToolStats& s = runner.tool_stats()[static_cast<size_t>(t)];
    tools.push_back(
        {{"id", session.tool(t).id},
         {"contact_time_s", s.contact_time},
         {"max_force_n", s.max_force},
         {"mean_force_in_contact_n", s.contact_time > 0.0 ? s.force_sum / s.contact_time : 0.0},
         {"grasps", publisher.grasps()[static_cast<size_t>(t)]}});
  }
  r["tools"] = tools;
  nlohmann::ordered_json organs = nlohmann::ordered_json::array();
  for (int32_t k = 0; k < session.num_organs(); ++k) {
    const SessionOrgan& o = session.organ(k);
    organs.push_back({{"id", o.built.id},
                      {"topology_version", o.topology_version},
                      {"elements_cut", o.elements_cut}});
  }
  r["organs"] = organs;
  if (recorder != nullptr) {
    const RecorderStats rs = recorder->stats();
    r["recording"] = {{"file", options.record}, {"records", rs.records},   {"bytes", rs.bytes},
                      {"gaps", rs.gaps},        {"records_lost", rs.lost}, {"failed", rs.failed},
                      {"error", rs.error}};
  }
  return r;
}

}  // namespace somasim::server
