// Every somasim program's exit codes, in one table (docs/running_a_lab.md lists them for the
// lab's scripts). Codes 0-4 and 70 mean the same in every program; 5-8 are a program's own
// (somasim-mesh has no DDS, so its 5 is a surface that cannot be meshed). Header only.
#pragma once

namespace somasim::app {

// Every program.
inline constexpr int kExitOk = 0;
// Ran to its end without the result: a solve that did not converge, a reduction that failed, a
// replay that diverged.
inline constexpr int kExitFailed = 1;
inline constexpr int kExitUsage = 2;  // a bad command line
// A file was refused: a scene, mesh, script, recording or reduced model.
inline constexpr int kExitBadInput = 3;
inline constexpr int kExitIo = 4;    // a file could not be read or written
inline constexpr int kExitBug = 70;  // an unexpected exception: a bug

// A program's own.
inline constexpr int kExitDds = 5;             // the networked ones: Cyclone DDS failed
inline constexpr int kExitTetrahedralize = 5;  // somasim-mesh: the surface cannot be meshed
inline constexpr int kExitNoServer = 6;        // somasim-haptic: no server within --wait-server
inline constexpr int kExitNoDisplay = 6;       // somasim-viewer: no X display to open
inline constexpr int kExitServerLost = 7;      // somasim-haptic: the server fell silent
inline constexpr int kExitTimeout = 7;         // somasim-viewer: --timeout passed
inline constexpr int kExitArmBlock = 8;        // somasim-haptic, -arm-sim: the arm's shared memory

// What a refused or unreadable file stands for is said once, next to its error type:
// mesh_io::ExitCodeOf (common/mesh_io/mesh_error.h) and scene::ExitCodeOf (common/scene/scene.h).

}  // namespace somasim::app
