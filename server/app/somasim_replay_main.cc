// somasim-replay FILE: re-runs a recorded session headless from its scene and its recorded
// inputs and checks that every checkpoint comes out bit for bit (docs/recording.md). With
// --publish --session NAME it re-publishes the session on DDS in real time (--speed, --from)
// for viewers and instructors, as a server would.
// Exit codes: 0 every checkpoint reproduced (a file that ends early replays up to its last
// good record and says so), 1 a checkpoint differs (the first divergence is printed), 2 a bad
// command line, 3 a file refused (not a recording, a newer format, a corrupt record: the
// offset is named) or a scene that no longer builds.
#include <CLI/CLI.hpp>
#include <cstdio>
#include <exception>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "common/recording/recording_file.h"
#include "server/app/server_app.h"
#include "server/recording/replay.h"

namespace {

int Run(int argc, char** argv) {
  std::string file;
  std::string report;
  CLI::App cli{"somasim-replay: replay a session recording and check it bit for bit"};
  cli.add_option("file", file, "the recording (.somarec)")->required();
  cli.add_option("--report", report, "write the result as JSON here");
  bool publish = false;
  somasim::server::ServerOptions options;
  options.session = "";
  cli.add_flag("--publish", publish,
               "re-publish the session on DDS as a server would, so that viewers and instructors "
               "can watch it (needs --session)");
  cli.add_option("--session", options.session, "the session (DDS partition) to publish in");
  cli.add_option("--domain", options.domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--dds-config", options.dds_config,
                 "Cyclone DDS XML configuration (deploy/cyclonedds-*.xml)");
  cli.add_option("--speed", options.speed, "session time per wall-clock time (--publish)")
      ->check(CLI::Range(0.01, 100.0))
      ->capture_default_str();
  cli.add_option("--from", options.replay_from,
                 "start publishing at the checkpoint nearest to this session time [s] "
                 "(fast-forwarded to it)")
      ->check(CLI::Range(0.0, 1e6));
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? 0 : 2;
  }
  if (publish) {
    if (options.session.empty()) {
      std::fprintf(stderr, "somasim-replay: --publish needs --session NAME\n");
      return 2;
    }
    options.report = report;
    return somasim::server::ReplayServerMain(options, file);
  }
  if (!options.session.empty() || options.replay_from > 0.0) {
    std::fprintf(stderr, "somasim-replay: --session and --from go with --publish\n");
    return 2;
  }
  somasim::server::ReplayResult r;
  try {
    r = somasim::server::Replay(file);
  } catch (const somasim::recording::RecordingError& e) {
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return 3;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return 3;
  }
  std::printf(
      "replayed %llu steps (%.3f s of session time) from %llu records, recorded by "
      "somasim %s\n",
      static_cast<unsigned long long>(r.steps), r.sim_time,
      static_cast<unsigned long long>(r.records), r.software_version.c_str());
  std::printf("checkpoints      %llu reproduced bit for bit\n",
              static_cast<unsigned long long>(r.checkpoints_matched));
  if (r.gap) {
    std::printf(
        "gap              the recorder lost records at step %llu: checkpoints after it "
        "were not compared\n",
        static_cast<unsigned long long>(r.gap_step));
  }
  if (r.truncated) {
    std::printf(
        "truncated        the file ends inside a record: replayed up to its last good "
        "record, which ends at byte %llu\n",
        static_cast<unsigned long long>(r.end_offset));
  } else if (!r.ended_cleanly && !r.diverged) {
    std::printf(
        "unfinished       no End record: the server stopped without closing it (the "
        "replay went to its last record)\n");
  }
  if (r.diverged) std::printf("DIVERGED         %s\n", r.divergence.c_str());
  if (!report.empty()) {
    nlohmann::ordered_json j;
    j["file"] = file;
    j["steps"] = r.steps;
    j["sim_time_s"] = r.sim_time;
    j["records"] = r.records;
    j["checkpoints_matched"] = r.checkpoints_matched;
    j["diverged"] = r.diverged;
    j["divergence"] = r.divergence;
    j["gap"] = r.gap;
    j["truncated"] = r.truncated;
    j["end_offset"] = r.end_offset;
    j["ended_cleanly"] = r.ended_cleanly;
    j["software_version"] = r.software_version;
    std::ofstream(report) << j.dump(2) << "\n";
  }
  return r.diverged ? 1 : 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Run(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-replay: internal error: %s\n", e.what());
    return 70;
  } catch (...) {
    return 70;
  }
}
