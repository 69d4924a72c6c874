// libFuzzer target for scenes (common/scene): arbitrary bytes as a text-format scene; only a
// SceneError may come out.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "common/scene/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    somasim::scene::ParseScene(std::string_view(reinterpret_cast<const char*>(data), size),
                               "fuzz.scene.txtpb");
  } catch (const somasim::scene::SceneError&) {
  }
  return 0;
}
