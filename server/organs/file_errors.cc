#include "server/organs/file_errors.h"

#include <iostream>
#include <stdexcept>

#include "common/app/exit_codes.h"
#include "common/mesh_io/mesh_error.h"
#include "common/scene/scene.h"
#include "server/organs/reduced_file.h"

namespace somasim::organs {

int ReportFileError(const char* program, int otherwise) {
  try {
    throw;
  } catch (const scene::SceneError& e) {
    std::cerr << program << ": " << e.what() << "\n";
    return scene::ExitCodeOf(e);
  } catch (const mesh_io::MeshError& e) {
    std::cerr << program << ": " << e.what() << "\n";
    return mesh_io::ExitCodeOf(e);
  } catch (const ReducedFileError& e) {
    std::cerr << program << ": " << e.what() << "\n";
    return app::kExitIo;
  } catch (const std::runtime_error& e) {
    if (otherwise < 0) throw;
    std::cerr << program << ": " << e.what() << "\n";
    return otherwise;
  }
}

}  // namespace somasim::organs
