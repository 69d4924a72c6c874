// What the end-to-end benchmarks (wire, viewer) share to run the project's programs: where they
// are, a scratch folder, reading what they wrote.
#pragma once

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

namespace somasim::bench {

// The programs live beside this benchmark (build/bin).
inline std::string BinPath(const std::string& program) {
  return (std::filesystem::read_symlink("/proc/self/exe").parent_path() / program).string();
}

// A fresh folder for this process's files.
inline std::string TempDir(const std::string& name) {
  const std::filesystem::path dir =
      std::filesystem::temp_directory_path() / ("somasim-bench-" + std::to_string(getpid())) / name;
  std::filesystem::create_directories(dir);
  return dir.string();
}

// The file's text ("" if unreadable).
inline std::string ReadText(const std::string& path) {
  std::ifstream in(path);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

}  // namespace somasim::bench
