// The server's session recorder (issue 11; docs/recording.md): every tool command the physics
// applied, every session event, every instructor command and a checkpoint of every organ's
// state at a fixed interval, written to an append-only recording (common/recording/) by a
// thread of its own. The physics thread only copies into buffers sized at start-up (no
// allocation, no lock, no I/O); the writer flushes and fsyncs at least every second, so a crash
// loses at most the last second. A full queue becomes an explicit Gap record, never a silent
// hole; a write or fsync error (a full disk) stops the recording, and failed() says why.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "common/recording/recording_file.h"
#include "server/session/session.h"

namespace somasim::server {

struct RecorderStats {
  uint64_t records = 0;  // written
  uint64_t bytes = 0;
  uint64_t gaps = 0;  // Gap records written
  uint64_t lost = 0;  // records the gaps stand for
  bool failed = false;
  std::string error;  // why the recording stopped, when it failed
};

class Recorder {
 public:
  // Steps between checkpoints for a session ticking at dt [s]: one a second of session time.
  static uint64_t CheckpointInterval(double dt);
  // The header for `session`: scene text and hash, the scene folder made absolute, the session
  // name, the trainee's pseudonym, the tick and the checkpoint interval.
  static recording::RecordingHeader MakeHeader(const Session& session, const std::string& scene_dir,
                                               const std::string& session_name,
                                               const std::string& trainee,
                                               const std::string& software_version);

  // Writes the header to `sink` and starts the writer thread. `queue` records fit in the
  // physics thread's queue. Throws std::runtime_error when the header cannot be written.
  Recorder(std::unique_ptr<recording::Sink> sink, const recording::RecordingHeader& header,
           const Session& session, size_t queue = 1U << 14);
  ~Recorder();
  Recorder(const Recorder&) = delete;
  Recorder& operator=(const Recorder&) = delete;

  // Physics thread; allocation-free, lock-free. `step`: steps taken so far.
  void ToolCommand(uint64_t step, double time, int32_t tool, const ToolCommandInput& command);
  void Event(uint64_t step, double time, const SessionEventRecord& event);
  // Copies every organ's positions, velocities and topology into a free checkpoint buffer (two
  // exist; when the writer holds both, the checkpoint is lost and counted in a Gap).
  void Checkpoint(uint64_t step, double time, const Session& session);
  // Another thread's (allocates): an instructor command as received.
  void Instructor(uint64_t step, double time, uint32_t kind, const std::string& instructor,
                  const std::string& text);
  // The End record and a last fsync; stops the writer. Idempotent.
  void Finish(uint64_t steps, const std::string& reason);

  bool failed() const { return failed_.load(); }
  RecorderStats stats() const;

 private:
  struct Item {
    enum class Type : uint8_t { kToolCommand, kEvent, kCheckpoint };
    Type type = Type::kEvent;
    uint64_t step = 0;
    double time = 0.0;
    int32_t tool = -1;
    int32_t buffer = -1;  // kCheckpoint: which buffer
    ToolCommandInput command;
    SessionEventRecord event;
  };
  bool Push(const Item& item);  // false: the queue is full
  void WriterLoop();
  // Writes what is queued; true when anything was.
  bool Drain();
  void Write(const recording::Record& record);
  void WriteGapIfAny(uint64_t step, double time);

  recording::Writer writer_;
  std::vector<std::string> organ_ids_;
  std::vector<std::string> tool_ids_;
  std::vector<size_t> organ_offsets_;  // into a checkpoint buffer: 6 × num_nodes per organ
  // The single-producer single-consumer queue (physics → writer).
  std::vector<Item> ring_;
  std::atomic<uint64_t> head_{0};  // next to write (producer)
  std::atomic<uint64_t> tail_{0};  // next to read (consumer)
  // Checkpoint buffers: positions and velocities, then per organ topology version and
  // elements cut; state 0 free, 1 filled (owned by the writer until it frees it).
  static constexpr int kCheckpointBuffers = 2;
  std::vector<double> checkpoint_[kCheckpointBuffers];
  std::atomic<int> checkpoint_state_[kCheckpointBuffers] = {};
  std::atomic<uint64_t> lost_commands_{0}, lost_events_{0}, lost_checkpoints_{0};
  uint64_t gap_commands_ = 0, gap_events_ = 0, gap_checkpoints_ = 0;  // already in Gap records
  std::mutex instructor_mutex_;
  std::deque<recording::Record> instructor_;
  std::atomic<bool> stop_{false};
  std::atomic<bool> failed_{false};
  bool finished_ = false;
  std::mutex finish_mutex_;
  mutable std::mutex stats_mutex_;
  RecorderStats stats_;
  recording::Record scratch_;  // the writer thread's
  std::thread thread_;
};

}  // namespace somasim::server
