// What the end-to-end benchmarks (wire, viewer) share to run the project's programs: where they
// are, a scratch folder (removed at exit), reading what they wrote.
#pragma once

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <system_error>

namespace somasim::bench {

// The programs live beside this benchmark (build/bin).
inline std::string BinPath(const std::string& program) {
  return (std::filesystem::read_symlink("/proc/self/exe").parent_path() / program).string();
}

// This process's scratch folder <temp>/somasim-bench-<pid>, removed with everything in it when
// the process exits (static destruction), unless SOMASIM_KEEP_TEST_FILES=1. Only the process
// that named it removes it, never a forked child.
class BenchScratch {
 public:
  BenchScratch()
      : pid_(getpid()),
        path_(std::filesystem::temp_directory_path() / ("somasim-bench-" + std::to_string(pid_))) {}
  ~BenchScratch() {
    const char* keep = std::getenv("SOMASIM_KEEP_TEST_FILES");
    if (getpid() != pid_ ||
        (keep != nullptr && std::string(keep) != "" && std::string(keep) != "0")) {
      return;
    }
    std::error_code error;  // at exit: nothing to report a failure to
    std::filesystem::remove_all(path_, error);
  }
  BenchScratch(const BenchScratch&) = delete;
  BenchScratch& operator=(const BenchScratch&) = delete;
  const std::filesystem::path& path() const { return path_; }

 private:
  pid_t pid_;
  std::filesystem::path path_;
};

// The folder `name` in this process's scratch folder (made on first use).
inline std::string TempDir(const std::string& name) {
  static const BenchScratch scratch;  // one for the whole executable (an inline function's static)
  const std::filesystem::path dir = scratch.path() / name;
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
