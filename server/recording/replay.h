// Deterministic replay of a session recording (issue 11; docs/recording.md): the session is
// rebuilt from the recording's scene, the recorded tool commands and resets are applied before
// the same steps as in the server, and every checkpoint must come out bit for bit.
#pragma once

#include <cstdint>
#include <functional>
#include <string>

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

// Replays the recording at `path`. Throws recording::RecordingError for a file that is not a
// recording, is newer than this reader, or has a corrupt record (naming its offset), and
// scene::SceneError / std::runtime_error for a scene that no longer builds or a record that
// does not fit the scene (a tool index out of range, a checkpoint of another size).
ReplayResult Replay(const std::string& path, const ReplayOptions& options = {});

}  // namespace somasim::server
