// Deterministic replay of a session recording (issue 11; docs/recording.md): the session is
// rebuilt from the recording's scene, the recorded tool commands and resets are applied before
// the same steps as in the server, and every checkpoint must come out bit for bit.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "common/recording/recording_file.h"
#include "server/session/session.h"

namespace somasim::server {

struct ReplayOptions {
  // Called after every replayed step (the session as it stands, the steps taken); return false
  // to stop. For re-publishing and for tests. May be empty.
  std::function<bool(const Session&, uint64_t)> on_step;
};

struct ReplayResult {
  uint64_t steps = 0;                // steps replayed
  double sim_time = 0.0;             // [s] the session's time at the end
  uint64_t records = 0;              // records read
  uint64_t checkpoints_matched = 0;  // bit for bit
  bool diverged = false;             // a checkpoint differed: divergence says where
  std::string divergence;
  bool gap = false;  // the recording has a Gap: checks stopped there
  uint64_t gap_step = 0;
  bool ended_cleanly = false;    // an End record closed it
  bool truncated = false;        // the file ends inside a record ...
  uint64_t end_offset = 0;       // ... and its last good record ends here [bytes]
  std::string software_version;  // of the server that recorded it
};

// A recording's inputs applied to a session step by step: what Replay and the server's replay
// mode (somasim-replay --publish) share. Opening checks the header (as recording::Reader, and
// the scene against its hash).
class RecordedInputs {
 public:
  explicit RecordedInputs(const std::string& path);
  ~RecordedInputs();
  RecordedInputs(const RecordedInputs&) = delete;
  RecordedInputs& operator=(const RecordedInputs&) = delete;

  const recording::RecordingHeader& header() const;
  // The recording's session, built from its scene (throws as Replay does).
  std::unique_ptr<Session> MakeSession() const;
  // Applies the records of `steps` steps taken and before: tool commands and resets (a reset's
  // events stay in the session for the caller to take), checkpoints compared bit for bit (the
  // first difference makes result().diverged). Throws as Replay does for a corrupt record.
  void ApplyUpTo(uint64_t steps, Session* session);
  // No record remains (an End record, the end of the file, or a divergence).
  bool finished() const { return finished_; }
  // The steps of the last record applied (where a replay ends).
  uint64_t last_step() const { return last_step_; }
  ReplayResult& result() { return result_; }

 private:
  std::string path_;
  std::unique_ptr<recording::Reader> reader_;
  std::unique_ptr<recording::Record> next_;  // read ahead, not yet applied
  bool has_next_ = false;
  bool finished_ = false;
  uint64_t last_step_ = 0;
  ReplayResult result_;
};

// Replays the recording at `path`. Throws recording::RecordingError for a file that is not a
// recording, is newer than this reader, or has a corrupt record (naming its offset), and
// scene::SceneError / std::runtime_error for a scene that no longer builds or a record that
// does not fit the scene (a tool index out of range, a checkpoint of another size).
ReplayResult Replay(const std::string& path, const ReplayOptions& options = {});

}  // namespace somasim::server
