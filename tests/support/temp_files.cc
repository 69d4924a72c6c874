#include "tests/support/temp_files.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <map>
#include <mutex>
#include <string_view>
#include <system_error>
#include <utility>
#include <vector>

namespace somasim::testing {
namespace {

// The registered paths with the pid that registered each, and the ProcessTempDir folders by
// (prefix, pid). A forked child inherits both; the pids keep it from using or removing the
// parent's entries.
struct Registry {
  std::mutex mutex;
  std::vector<std::pair<std::string, pid_t>> paths;
  std::map<std::pair<std::string, pid_t>, std::string> process_dirs;
};

Registry& TheRegistry() {
  static Registry registry;
  return registry;
}

// mkdtemp of <temp>/<prefix>-XXXXXX, not registered; "" (and a test failure) when it fails.
std::string CreateTempDir(const std::string& prefix) {
  const std::string pattern =
      (std::filesystem::temp_directory_path() / (prefix + "-XXXXXX")).string();
  std::vector<char> buffer(pattern.begin(), pattern.end());
  buffer.push_back('\0');
  const char* dir = mkdtemp(buffer.data());
  EXPECT_NE(dir, nullptr) << "mkdtemp failed for " << pattern;
  return dir != nullptr ? std::string(dir) : std::string();
}

// SOMASIM_KEEP_TEST_FILES set to anything but "" or "0".
bool KeepRequested() {
  const char* keep = std::getenv("SOMASIM_KEEP_TEST_FILES");
  return keep != nullptr && std::string_view(keep) != "" && std::string_view(keep) != "0";
}

// The end of this process's tests: its registered paths are removed when every test passed,
// else kept and listed on stderr. The registry is emptied either way (--gtest_repeat starts the
// next round with none).
void RemoveOrKeepTempPaths() {
  Registry& registry = TheRegistry();
  std::vector<std::string> mine;
  {
    const std::lock_guard<std::mutex> lock(registry.mutex);
    const pid_t self = getpid();
    for (const auto& [path, pid] : registry.paths) {
      if (pid == self) mine.push_back(path);
    }
    registry.paths.clear();
    registry.process_dirs.clear();
  }
  if (mine.empty()) return;
  const bool passed = ::testing::UnitTest::GetInstance()->Passed();
  if (passed && !KeepRequested()) {
    for (const std::string& path : mine) {
      std::error_code error;
      std::filesystem::remove_all(path, error);
      if (error)
        std::cerr << "cannot remove test files " << path << ": " << error.message() << "\n";
    }
    return;
  }
  std::cerr << "kept test files (" << (passed ? "SOMASIM_KEEP_TEST_FILES is set" : "a test failed")
            << "):";
  for (const std::string& path : mine) std::cerr << " " << path;
  std::cerr << "\n";
}

class TempFilesEnvironment final : public ::testing::Environment {
 public:
  void TearDown() override { RemoveOrKeepTempPaths(); }
};

// Registered before gtest_main's main runs. Every helper that makes a temp path is in this file,
// so any test executable that makes one links this registration as well.
[[maybe_unused]] ::testing::Environment* const kTempFilesEnvironment =
    ::testing::AddGlobalTestEnvironment(new TempFilesEnvironment);

}  // namespace

void RegisterTempPath(const std::string& path) {
  if (path.empty()) return;
  Registry& registry = TheRegistry();
  const std::lock_guard<std::mutex> lock(registry.mutex);
  registry.paths.emplace_back(path, getpid());
}

std::string MakeTempDir(const std::string& prefix) {
  std::string dir = CreateTempDir(prefix);
  RegisterTempPath(dir);
  return dir;
}

std::string ProcessTempDir(const std::string& prefix) {
  Registry& registry = TheRegistry();
  const pid_t self = getpid();
  const std::lock_guard<std::mutex> lock(registry.mutex);
  std::string& dir = registry.process_dirs[{prefix, self}];
  if (dir.empty()) {
    dir = CreateTempDir(prefix + "-" + std::to_string(self));
    if (!dir.empty()) registry.paths.emplace_back(dir, self);
  }
  return dir;
}

}  // namespace somasim::testing
