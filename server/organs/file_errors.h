// The offline tools' (somasim-solve, somasim-reduce) report of the file that stopped them — a
// scene, a mesh, a reduced model — said once for both: "PROGRAM: what" on stderr, and the exit
// code it stands for (common/app/exit_codes.h).
#pragma once

namespace somasim::organs {

// Call inside a catch block. A scene or mesh refused or unreadable (scene::ExitCodeOf,
// mesh_io::ExitCodeOf), a reduced-model file (kExitIo); another std::runtime_error gives
// `otherwise`, or is rethrown when `otherwise` < 0, as is anything else.
int ReportFileError(const char* program, int otherwise = -1);

}  // namespace somasim::organs
