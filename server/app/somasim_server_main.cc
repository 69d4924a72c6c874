// somasim-server: see server_app.h.
#include <cstdio>
#include <exception>

#include "server/app/server_app.h"

int main(int argc, char** argv) {
  try {
    return somasim::server::ServerMain(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-server: internal error: %s\n", e.what());
    return somasim::server::kExitBug;
  }
}
