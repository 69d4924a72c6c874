// What the server publishes besides force models (SPEC §1, §3; docs/topics.md), from a thread of
// its own that takes the physics runner's hand-offs: at start the session description and each
// organ's topology (transient-local, for late joiners); then mesh frames at the frame rate as
// keyframes and deltas (a keyframe at once for a new subscriber), topologies after a cut or a
// reset (the surface extracted with the cut's inner faces marked, then a keyframe), rigid
// bodies, the heartbeat (10 Hz), metrics (1 Hz), the session's events, and the instructors'
// commands (pause, resume, reset, notes), each recorded when the session is.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "common/wire/frame_codec.h"
#include "server/cutting/cut_surface.h"
#include "server/net/endpoints.h"
#include "server/net/tool_link.h"
#include "server/runner/physics_runner.h"

namespace somasim::net {

struct PublisherOptions {
  std::string session;
  double frame_rate = 60.0;         // [Hz]
  uint32_t keyframe_interval = 30;  // a keyframe every this many frames
  bool verbose = false;             // log the metrics every second
  std::string record;               // the recording's file, for its failure's message
  std::string software_version;     // in the session description
};

class Publisher {
 public:
  // Everything given outlives the publisher. `recorder` (or null) records instructor commands;
  // `replay` (or null): a replay, which instructors cannot reset.
  Publisher(const PublisherOptions& options, runner::PhysicsRunner& runner, Endpoints& endpoints,
            const ToolLink& link, uint64_t server_id, runner::Recorder* recorder,
            runner::RecordedInputs* replay);

  // The session description, every topology, the heartbeat "running" and the event "session
  // starts". Throws dds::DdsError.
  void PublishStart();
  // The loop, until `done` (or a stop signal); then the last events, topologies and a keyframe
  // of the final shape. Throws dds::DdsError.
  void Run(const std::atomic<bool>& done);
  // The heartbeat "stopping" and the event "session ends".
  void PublishEnd();
  // Writes each organ's last published frame (ServerOptions::dump_final). False on I/O errors.
  bool DumpFinal(const std::string& dir) const;
  // A recording that stopped (a full disk, an fsync error) is said loudly, once: an error event
  // to every subscriber and an error in the log.
  void ReportRecordingFailure();

  uint64_t frames_published() const { return frames_published_; }
  uint64_t publish_overruns() const { return publish_overruns_; }
  uint64_t instructor_received() const { return instructor_received_; }
  const std::map<std::string, uint64_t>& event_counts() const { return event_counts_; }
  const std::vector<uint64_t>& grasps() const { return grasps_; }  // per tool

 private:
  void PublishTopology(int32_t k, uint32_t version, std::span<const double> rest,
                       const mesh::Triangles& surface, std::span<const uint8_t> inner);
  void PublishTopologies();
  void PublishFrames();
  void PublishRigidBodies();
  void Heartbeat(uint32_t state);
  void PublishMetrics();
  void PublishEvent(uint32_t kind, const std::string& subject, const std::string& text);
  void PublishSessionEvent(const runner::SessionEventRecord& e);
  void TakeInstructorCommands();
  void ReportRunnerNotices();

  PublisherOptions options_;
  runner::PhysicsRunner& runner_;
  const runner::Session& session_;
  Endpoints& endpoints_;
  const ToolLink& link_;
  uint64_t server_id_;
  runner::Recorder* recorder_;
  runner::RecordedInputs* replay_;
  std::vector<std::string> organ_ids_;
  std::vector<std::unique_ptr<wire::FrameEncoder>> encoders_;
  std::vector<uint32_t> published_version_;  // per organ
  // Per organ that can be cut, its cut surface (the physics's cutter has its own: a reset
  // replaces that one while this thread may be extracting).
  std::vector<std::unique_ptr<cutting::CutSurface>> cut_surfaces_;
  std::vector<std::string> rigid_ids_;
  std::vector<uint64_t> grasps_;
  std::map<std::string, uint64_t> event_counts_;
  uint64_t heartbeat_seq_ = 0;
  uint64_t event_seq_ = 0;
  uint64_t frames_published_ = 0;
  uint64_t publish_overruns_ = 0;
  uint64_t instructor_received_ = 0;
  bool behind_reported_ = false;
  bool divergence_reported_ = false;
  bool fast_forward_reported_ = false;
  bool recording_failure_reported_ = false;
  std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
};

}  // namespace somasim::net
