#include "common/wire/frame_dump.h"

#include <filesystem>
#include <fstream>

namespace somasim::wire {

bool WriteFrameDump(const std::string& dir, const std::string& organ,
                    std::span<const float> positions, uint64_t frame) {
  std::error_code error;
  std::filesystem::create_directories(dir, error);
  std::ofstream data(dir + "/" + organ + ".f32", std::ios::binary);
  data.write(reinterpret_cast<const char*>(positions.data()),
             static_cast<std::streamsize>(positions.size() * sizeof(float)));
  std::ofstream text(dir + "/" + organ + ".frame");
  text << frame << "\n";
  return static_cast<bool>(data) && static_cast<bool>(text);
}

}  // namespace somasim::wire
