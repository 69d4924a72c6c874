#include "common/app/log.h"

#include <chrono>
#include <cstdio>
#include <mutex>

namespace somasim::app {
namespace {

struct LogState {
  std::mutex mutex;
  std::string process = "somasim";
  LogLevel level = LogLevel::kInfo;
  std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now();
};

LogState& State() {
  static LogState state;
  return state;
}

const char* LevelName(LogLevel level) {
  switch (level) {
    case LogLevel::kDebug:
      return "debug";
    case LogLevel::kInfo:
      return "info";
    case LogLevel::kWarning:
      return "warning";
    case LogLevel::kError:
      return "error";
  }
  return "info";
}

}  // namespace

void SetLogProcess(std::string_view process) {
  LogState& s = State();
  const std::lock_guard<std::mutex> lock(s.mutex);
  s.process = std::string(process);
}

void SetLogLevel(LogLevel level) {
  LogState& s = State();
  const std::lock_guard<std::mutex> lock(s.mutex);
  s.level = level;
}

void Log(LogLevel level, std::string_view event, const nlohmann::json& fields) {
  LogState& s = State();
  const std::lock_guard<std::mutex> lock(s.mutex);
  if (level < s.level) return;
  nlohmann::ordered_json line;
  line["time"] = std::chrono::duration<double>(std::chrono::steady_clock::now() - s.start).count();
  line["process"] = s.process;
  line["level"] = LevelName(level);
  line["event"] = std::string(event);
  if (fields.is_object()) {
    for (const auto& [key, value] : fields.items()) line[key] = value;
  }
  const std::string text = line.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
  std::fprintf(stderr, "%s\n", text.c_str());
  std::fflush(stderr);
}

}  // namespace somasim::app
