// somasim-viewer: see viewer_app.h.
#include <cstdio>
#include <exception>

#include "viewer/viewer_app.h"

int main(int argc, char** argv) {
  try {
    return somasim::viewer::ViewerMain(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-viewer: internal error: %s\n", e.what());
    return somasim::viewer::kExitBug;
  }
}
