// somasim-viewer: joins a session (`--session NAME`) over Cyclone DDS and shows it in a
// freeglut window (SPEC §1, issue 8). Off-screen under Xvfb: `--screenshot OUT.png
// --after-frames N` writes what it shows once every organ has a shape and N frames have been
// drawn, then exits; `--dump-positions DIR` writes, when it stops (SIGINT/SIGTERM, or after the
// screenshot), the positions it shows: DIR/<organ>.f32 (float32 x y z per node) and
// DIR/<organ>.frame (the frame number), the format of somasim-server --dump-final, so the two
// compare byte for byte. Mouse: left drag orbits, right drag pans, wheel / middle drag zooms;
// keys: f fits the view, q or Esc quits.
#pragma once

#include "common/app/exit_codes.h"

namespace somasim::viewer {

// Exit codes (common/app/exit_codes.h; also in --help).
using app::kExitBug;
using app::kExitDds;
using app::kExitIo;
using app::kExitNoDisplay;
using app::kExitOk;
using app::kExitTimeout;
using app::kExitUsage;

int ViewerMain(int argc, char** argv);

}  // namespace somasim::viewer
