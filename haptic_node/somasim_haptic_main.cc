// somasim-haptic: see haptic_node.h.
#include <cstdio>
#include <exception>

#include "haptic_node/haptic_node.h"

int main(int argc, char** argv) {
  try {
    return somasim::haptic::HapticMain(argc, argv);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "somasim-haptic: internal error: %s\n", e.what());
    return somasim::app::kExitBug;
  }
}
