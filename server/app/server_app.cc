#include "server/app/server_app.h"

#include <CLI/CLI.hpp>
#include <atomic>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <exception>
#include <filesystem>
#include <fstream>
#include <memory>
#include <random>
#include <thread>

#include "common/app/log.h"
#include "common/app/scheduling.h"
#include "common/app/signals.h"
#include "common/dds/topics.h"
#include "common/mesh_io/mesh_error.h"
#include "server/app/report.h"
#include "server/net/endpoints.h"
#include "server/net/publisher.h"
#include "server/net/tool_link.h"
#include "server/recording/recorder.h"
#include "server/recording/replay.h"
#include "server/runner/physics_runner.h"
#include "server/session/session.h"

#ifndef SOMASIM_VERSION
#define SOMASIM_VERSION "0.0.0"
#endif

namespace somasim::server {
namespace {

using app::Log;
using app::LogLevel;

// Empty when `trainee` is a usable pseudonym for a recording's header, else why not.
std::string TraineeError(const std::string& trainee) {
  if (trainee.size() > 32) return "is longer than 32 characters";
  for (const char c : trainee) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') {
      return "may hold only letters, digits, - and _ (a pseudonym such as trainee-07)";
    }
  }
  return "";
}

// A running server: the physics on the calling thread (runner/physics_runner.h), the tool link's
// two threads and the publisher's (net/). Its report, and each organ's last frame in
// options.dump_final (`dumped`: false when it could not be written). Throws dds::DdsError.
nlohmann::ordered_json RunServer(const ServerOptions& options, Session& session,
                                 const std::string& dds_config, Recorder* recorder,
                                 RecordedInputs* replay, bool* dumped) {
  // Cyclone's threads, the tool link's and the publisher's (created from here on) wait on the
  // wire: a short slice wakes them promptly next to the busy physics thread, which returns to
  // the default slice.
  app::LogSchedulerSlice(app::SetSchedulerSlice(app::kWireSlice), "dds and publisher threads");
  std::random_device rd;
  const uint64_t server_id = (static_cast<uint64_t>(rd()) << 32) ^ rd();
  net::Endpoints endpoints(options.domain, dds_config, options.session, session.num_rigid() > 0);
  runner::RunnerOptions ro;
  ro.duration = options.duration;
  ro.realtime = options.realtime;
  ro.speed = options.speed;
  ro.replay_from = options.replay_from;
  ro.rt_priority = options.rt_priority;
  runner::PhysicsRunner runner(session, ro, recorder, replay);
  net::ToolLink link(runner, endpoints, server_id, /*intake=*/replay == nullptr);
  net::PublisherOptions po;
  po.session = options.session;
  po.frame_rate = options.frame_rate;
  po.keyframe_interval = options.keyframe_interval;
  po.verbose = options.verbose;
  po.record = options.record;
  po.software_version = SOMASIM_VERSION;
  net::Publisher publisher(po, runner, endpoints, link, server_id, recorder, replay);
  publisher.PublishStart();
  link.Start();
  std::atomic<bool> done{false};
  std::thread publishing([&] {
    try {
      publisher.Run(done);
    } catch (const std::exception& e) {
      // A DDS failure while publishing: stop the session cleanly rather than abort.
      Log(LogLevel::kError, "publisher_failed", {{"error", e.what()}});
      app::RequestStop();
    }
  });
  try {
    runner.Run();
  } catch (...) {
    done = true;
    publishing.join();
    link.Stop();
    throw;
  }
  done = true;
  publishing.join();
  link.Stop();
  if (recorder != nullptr) {
    recorder->Finish(runner.counters().ticks.load(),
                     app::StopRequested() ? "stopped by a signal" : "the session ended");
    publisher.ReportRecordingFailure();
  }
  publisher.PublishEnd();
  *dumped = options.dump_final.empty() || publisher.DumpFinal(options.dump_final);
  return ServerReport(options, server_id, runner, publisher, link, recorder);
}

}  // namespace

int ServerMain(int argc, char** argv) {
  app::SetLogProcess("server");
  ServerOptions options;
  CLI::App cli{
      "somasim-server: runs a session's physics and publishes it over Cyclone DDS.\n"
      "Exit codes: 0 done, 2 usage, 3 bad scene or mesh, 4 I/O, 5 DDS, 70 bug."};
  cli.set_version_flag("--version", std::string("somasim-server ") + SOMASIM_VERSION);
  cli.add_option("--scene", options.scene, "a .scene.txtpb file, or builtin:NAME")
      ->capture_default_str();
  cli.add_option("--session", options.session, "the session's name (its DDS partition)")
      ->capture_default_str();
  cli.add_flag("--headless", options.headless, "no window (the server never opens one)");
  cli.add_option("--duration", options.duration,
                 "seconds of session time to run; 0 runs until SIGINT/SIGTERM")
      ->check(CLI::NonNegativeNumber);
  cli.add_option("--domain", options.domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--dds-config", options.dds_config,
                 "Cyclone DDS XML configuration (deploy/cyclonedds-*.xml); default: "
                 "CYCLONEDDS_URI or Cyclone's defaults");
  cli.add_option("--frame-rate", options.frame_rate, "mesh frames per second")
      ->check(CLI::Range(1.0, 1000.0))
      ->capture_default_str();
  cli.add_option("--keyframe-interval", options.keyframe_interval,
                 "a full keyframe every this many frames")
      ->check(CLI::Range(1, 100000))
      ->capture_default_str();
  bool fast = false;
  cli.add_flag("--as-fast-as-possible", fast,
               "do not pace session time to the wall clock (offline runs, tests)");
  cli.add_option("--report", options.report, "write a JSON report here at the end");
  cli.add_option("--record", options.record,
                 "record the session to this new file (.somarec; never overwritten), for "
                 "somasim-replay");
  cli.add_option("--trainee", options.trainee,
                 "the trainee's pseudonym in the recording (letters, digits, - and _; at most 32; "
                 "never a person's name)");
  cli.add_option("--rt-priority", options.rt_priority,
                 "run the physics thread under SCHED_FIFO at this priority (1-99; needs "
                 "CAP_SYS_NICE; refused: says so and runs at normal priority). A physics "
                 "slower than real time then holds its core")
      ->check(CLI::Range(0, 99));
  cli.add_option("--dump-final", options.dump_final,
                 "at the end, write each organ's last published frame to DIR/<organ>.f32 "
                 "(float32 x y z per node) and DIR/<organ>.frame (for exactness checks)");
  cli.add_flag("-v,--verbose", options.verbose, "log metrics every second");
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  options.realtime = !fast;
  if (const std::string bad = dds::SessionNameError(options.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-server: --session \"%s\" %s\n", options.session.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  if (const std::string bad = TraineeError(options.trainee); !bad.empty()) {
    std::fprintf(stderr, "somasim-server: --trainee \"%s\" %s\n", options.trainee.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  app::InstallStopSignals();
  std::unique_ptr<Session> session;
  std::string scene_dir = ".";
  try {
    scene::Scene scene;
    scene::SceneLines lines(options.scene);
    if (options.scene.rfind("builtin:", 0) == 0) {
      scene = ServerDefaultScene(options.scene.substr(8));
    } else {
      scene = scene::LoadSceneFile(options.scene, &lines);
      scene_dir = std::filesystem::path(options.scene).parent_path().string();
      if (scene_dir.empty()) scene_dir = ".";
    }
    Log(LogLevel::kInfo, "building", {{"scene", options.scene}});
    session = std::make_unique<Session>(scene, lines, scene_dir);
  } catch (const scene::SceneError& e) {
    Log(LogLevel::kError, "bad_scene", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: %s\n", e.what());
    return kExitBadInput;
  } catch (const mesh_io::MeshError& e) {
    Log(LogLevel::kError, "bad_mesh", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: %s\n", e.what());
    return kExitBadInput;
  } catch (const std::invalid_argument& e) {
    Log(LogLevel::kError, "bad_scene", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: %s: %s\n", options.scene.c_str(), e.what());
    return kExitBadInput;
  }
  std::string dds_config;
  try {
    dds_config = dds::ReadDdsConfig(options.dds_config);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-server: %s\n", e.what());
    return kExitIo;
  }
  std::unique_ptr<Recorder> recorder;
  if (!options.record.empty()) {
    std::string error;
    std::unique_ptr<recording::Sink> sink = recording::CreateFileSink(options.record, &error);
    try {
      if (!sink) throw std::runtime_error(error);
      recorder =
          std::make_unique<Recorder>(std::move(sink),
                                     Recorder::MakeHeader(*session, scene_dir, options.session,
                                                          options.trainee, SOMASIM_VERSION),
                                     *session);
    } catch (const std::runtime_error& e) {
      Log(LogLevel::kError, "recording_refused", {{"file", options.record}, {"error", e.what()}});
      std::fprintf(stderr, "somasim-server: %s\n", e.what());
      return kExitIo;
    }
    Log(LogLevel::kInfo, "recording", {{"file", options.record}});
  }
  nlohmann::ordered_json report;
  try {
    Log(LogLevel::kInfo, "running",
        {{"session", options.session},
         {"domain", options.domain},
         {"organs", session->num_organs()},
         {"tools", session->num_tools()},
         {"tick_s", session->dt()},
         {"duration_s", options.duration}});
    bool dumped = true;
    report = RunServer(options, *session, dds_config, recorder.get(), nullptr, &dumped);
    if (!dumped) {
      std::fprintf(stderr, "somasim-server: cannot write %s\n", options.dump_final.c_str());
      return kExitIo;
    }
  } catch (const dds::DdsError& e) {
    Log(LogLevel::kError, "dds", {{"error", e.what()}});
    std::fprintf(stderr, "somasim-server: DDS: %s\n", e.what());
    return kExitDds;
  }
  Log(LogLevel::kInfo, "stopped",
      {{"signal", app::StopSignal()},
       {"sim_time", report["sim_time_s"]},
       {"organ_steps", report["organ_steps"]}});
  if (!options.report.empty()) {
    std::ofstream out(options.report);
    out << report.dump(2) << "\n";
    if (!out) {
      std::fprintf(stderr, "somasim-server: cannot write the report %s\n", options.report.c_str());
      return kExitIo;
    }
  }
  return kExitOk;
}

int ReplayServerMain(const ServerOptions& given, const std::string& file) {
  app::SetLogProcess("replay");
  ServerOptions options = given;
  if (const std::string bad = dds::SessionNameError(options.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-replay: --session \"%s\" %s\n", options.session.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  app::InstallStopSignals();
  std::unique_ptr<RecordedInputs> inputs;
  std::unique_ptr<Session> session;
  try {
    inputs = std::make_unique<RecordedInputs>(file);
    session = inputs->MakeSession();
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return kExitBadInput;
  }
  // The checkpoint nearest to --from.
  const double every = static_cast<double>(inputs->header().checkpoint_interval()) * session->dt();
  if (options.replay_from > 0.0 && every > 0.0) {
    options.replay_from = std::round(options.replay_from / every) * every;
  }
  std::string dds_config;
  try {
    dds_config = dds::ReadDdsConfig(options.dds_config);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return kExitIo;
  }
  nlohmann::ordered_json report;
  try {
    Log(LogLevel::kInfo, "replaying",
        {{"file", file},
         {"session", options.session},
         {"domain", options.domain},
         {"speed", options.speed},
         {"from_s", options.replay_from}});
    bool dumped = true;
    report = RunServer(options, *session, dds_config, nullptr, inputs.get(), &dumped);
  } catch (const dds::DdsError& e) {
    std::fprintf(stderr, "somasim-replay: DDS: %s\n", e.what());
    return kExitDds;
  } catch (const std::exception& e) {  // a corrupt record met while publishing
    std::fprintf(stderr, "somasim-replay: %s\n", e.what());
    return kExitBadInput;
  }
  const ReplayResult& r = inputs->result();
  report["replay"] = {{"file", file},
                      {"checkpoints_matched", r.checkpoints_matched},
                      {"diverged", r.diverged},
                      {"divergence", r.divergence},
                      {"gap", r.gap},
                      {"truncated", r.truncated},
                      {"ended_cleanly", r.ended_cleanly},
                      {"finished", inputs->finished()}};
  std::printf(
      "published the replay of %s in session %s: %.3f s of session time, %llu "
      "checkpoints reproduced bit for bit%s\n",
      file.c_str(), options.session.c_str(), session->time(),
      static_cast<unsigned long long>(r.checkpoints_matched),
      r.diverged ? (", then DIVERGED: " + r.divergence).c_str() : "");
  if (!options.report.empty()) {
    std::ofstream out(options.report);
    out << report.dump(2) << "\n";
    if (!out) return kExitIo;
  }
  return r.diverged ? 1 : kExitOk;
}

}  // namespace somasim::server
