// Structured logs for the processes (server, haptic node, demo): one JSON object per line on
// stderr, {"time": <s since the process started>, "process": ..., "level": ..., "event": ...,
// <fields>}, so a lab's log collector can parse them and a person can still read them.
// Not for real-time paths (it formats and allocates).
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <string_view>

namespace somasim::app {

enum class LogLevel { kDebug, kInfo, kWarning, kError };

// Names the process in every line (e.g. "server"); call once at start-up.
void SetLogProcess(std::string_view process);
// Lines below `level` are dropped (default kInfo).
void SetLogLevel(LogLevel level);
// Writes one line; thread-safe.
void Log(LogLevel level, std::string_view event, const nlohmann::json& fields = {});

}  // namespace somasim::app
