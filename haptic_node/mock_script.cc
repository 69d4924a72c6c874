#include "haptic_node/mock_script.h"

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <fstream>
#include <iterator>
#include <sstream>
#include <system_error>

namespace somasim::haptic {
namespace {

constexpr std::string_view kHeaderWord = "somasim-script";
constexpr std::string_view kVersion = "1";
constexpr double kMaxDistance = 10.0;  // [m] a key farther from the origin is a typo

// One line of a script, split into whitespace-separated words (comments removed).
class Words {
 public:
  explicit Words(std::string_view line) {
    const size_t hash = line.find('#');
    if (hash != std::string_view::npos) line = line.substr(0, hash);
    size_t i = 0;
    while (i < line.size()) {
      while (i < line.size() && IsSpace(line[i])) ++i;
      const size_t begin = i;
      while (i < line.size() && !IsSpace(line[i])) ++i;
      if (i > begin) words_.push_back(line.substr(begin, i - begin));
    }
  }
  size_t size() const { return words_.size(); }
  bool empty() const { return words_.empty(); }
  std::string_view operator[](size_t i) const { return words_[i]; }

 private:
  static bool IsSpace(char c) {
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
  }
  std::vector<std::string_view> words_;
};

// Parses the line's words; throws ScriptError at `line` naming the fault.
class LineParser {
 public:
  LineParser(const std::string& name, int line, const Words& words)
      : name_(name), line_(line), words_(words) {}

  [[noreturn]] void Fail(const std::string& message) const {
    throw ScriptError(name_, line_, message);
  }

  // The finite number in word i, called `what` in messages.
  double Number(size_t i, const char* what) const {
    if (i >= words_.size()) Fail(std::string(words_[0]) + ": missing " + what);
    const std::string_view w = words_[i];
    double value = 0.0;
    const auto [end, ec] = std::from_chars(w.data(), w.data() + w.size(), value);
    if (ec == std::errc::result_out_of_range) {
      Fail(std::string(words_[0]) + ": " + what + " '" + std::string(w) + "' is out of range");
    }
    if (ec != std::errc() || end != w.data() + w.size()) {
      Fail(std::string(words_[0]) + ": " + what + " '" + std::string(w) + "' is not a number");
    }
    if (!std::isfinite(value)) {
      Fail(std::string(words_[0]) + ": " + what + " '" + std::string(w) +
           "' is not a finite number");
    }
    return value;
  }

  uint32_t Unsigned(size_t i, const char* what) const {
    if (i >= words_.size()) Fail(std::string(words_[0]) + ": missing " + what);
    const std::string_view w = words_[i];
    uint32_t value = 0;
    const auto [end, ec] = std::from_chars(w.data(), w.data() + w.size(), value);
    if (ec != std::errc() || end != w.data() + w.size()) {
      Fail(std::string(words_[0]) + ": " + what + " '" + std::string(w) +
           "' is not an unsigned 32-bit integer");
    }
    return value;
  }

 private:
  const std::string& name_;
  int line_;
  const Words& words_;
};

bool IsToolId(std::string_view id) {
  return !id.empty() && std::all_of(id.begin(), id.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
           c == '-';
  });
}

std::string Str(std::string_view s) { return std::string(s); }

}  // namespace

ScriptError::ScriptError(const std::string& file, int line, const std::string& message)
    : std::runtime_error(file + ":" + std::to_string(line) + ": " + message),
      file_(file),
      line_(line) {}

MockScript MockScript::Parse(std::string_view text, const std::string& name) {
  MockScript script;
  bool have_header = false;
  int tool = -1;             // the tool of the keys that follow (index into tools_)
  int tool_line = 0;         // where it was named
  bool tool_has_key = true;  // the last tool line has been followed by a key
  ScriptKey previous;        // what a key inherits (jaw, quat, buttons)
  int line_number = 0;
  size_t pos = 0;
  while (pos <= text.size()) {
    size_t end = text.find('\n', pos);
    if (end == std::string_view::npos) end = text.size();
    const std::string_view line = text.substr(pos, end - pos);
    pos = end + 1;
    if (end == text.size() && line.empty()) break;  // after the text's final newline
    ++line_number;
    const Words words(line);
    if (words.empty()) continue;
    const LineParser p(name, line_number, words);
    const std::string_view keyword = words[0];

    if (!have_header) {
      if (keyword != kHeaderWord) {
        p.Fail("expected the header 'somasim-script 1', got '" + Str(keyword) + "'");
      }
      if (words.size() < 2) p.Fail("somasim-script: missing version (expected 1)");
      if (words[1] != kVersion) {
        p.Fail("somasim-script: unsupported version '" + Str(words[1]) + "' (expected 1)");
      }
      if (words.size() > 2) p.Fail("somasim-script: extra value '" + Str(words[2]) + "'");
      have_header = true;
      continue;
    }

    if (keyword == "tool") {
      if (words.size() < 2) p.Fail("tool: missing ID");
      if (words.size() > 2) p.Fail("tool: extra value '" + Str(words[2]) + "'");
      if (!tool_has_key) {
        throw ScriptError(
            name, tool_line,
            "tool: '" + script.tools_[static_cast<size_t>(tool)] + "' is not followed by a key");
      }
      const std::string_view id = words[1];
      if (!IsToolId(id)) {
        p.Fail("tool: ID '" + Str(id) + "' is not letters, digits, '_' or '-'");
      }
      const auto found = std::find(script.tools_.begin(), script.tools_.end(), id);
      tool = static_cast<int>(std::distance(script.tools_.begin(), found));
      if (found == script.tools_.end()) script.tools_.emplace_back(id);
      tool_line = line_number;
      tool_has_key = false;
      continue;
    }

    if (keyword == "key") {
      if (tool < 0) p.Fail("key: before any 'tool' line");
      ScriptKey key = previous;
      key.tool = tool;
      key.line = line_number;
      key.time = p.Number(1, "time T");
      // One by one, left to right: the first fault on the line is the one named.
      const double x = p.Number(2, "position X");
      const double y = p.Number(3, "position Y");
      const double z = p.Number(4, "position Z");
      key.position = Eigen::Vector3d(x, y, z);
      if (key.time < 0.0) {
        p.Fail("key: time " + Str(words[1]) + " is negative (the first key is at T >= 0)");
      }
      if (!script.keys_.empty() && !(key.time > script.keys_.back().time)) {
        p.Fail("key: time " + Str(words[1]) + " does not increase (the key on line " +
               std::to_string(script.keys_.back().line) + " is at " +
               std::to_string(script.keys_.back().time) + " s)");
      }
      if (key.position.norm() > kMaxDistance) {
        p.Fail("key: position " + Str(words[2]) + " " + Str(words[3]) + " " + Str(words[4]) +
               " is " + std::to_string(key.position.norm()) + " m from the origin (at most 10 m)");
      }
      bool have_jaw = false;
      bool have_quat = false;
      bool have_buttons = false;
      size_t i = 5;
      while (i < words.size()) {
        const std::string_view option = words[i];
        if (option == "jaw" && !have_jaw) {
          key.jaw = p.Number(i + 1, "jaw J");
          if (!(key.jaw >= 0.0 && key.jaw <= 1.0)) {
            p.Fail("key: jaw " + Str(words[i + 1]) + " is outside [0, 1]");
          }
          have_jaw = true;
          i += 2;
        } else if (option == "quat" && !have_quat) {
          const double w = p.Number(i + 1, "quat W");
          const double qx = p.Number(i + 2, "quat X");
          const double qy = p.Number(i + 3, "quat Y");
          const double qz = p.Number(i + 4, "quat Z");
          const Eigen::Quaterniond q(w, qx, qy, qz);
          const double norm = q.norm();
          if (!(norm > 1e-12) || !std::isfinite(norm)) {
            p.Fail("key: quat " + Str(words[i + 1]) + " " + Str(words[i + 2]) + " " +
                   Str(words[i + 3]) + " " + Str(words[i + 4]) + " has no direction (length " +
                   std::to_string(norm) + ")");
          }
          key.orientation = q.normalized();
          have_quat = true;
          i += 5;
        } else if (option == "buttons" && !have_buttons) {
          key.buttons = p.Unsigned(i + 1, "buttons B");
          have_buttons = true;
          i += 2;
        } else if (option == "jaw" || option == "quat" || option == "buttons") {
          p.Fail("key: " + Str(option) + " given twice");
        } else {
          p.Fail("key: extra value '" + Str(option) +
                 "' (after T X Y Z come only jaw J, quat W X Y Z, buttons B)");
        }
      }
      script.keys_.push_back(key);
      previous = key;
      tool_has_key = true;
      continue;
    }

    if (keyword == kHeaderWord) p.Fail("somasim-script: the header is repeated");
    p.Fail("unknown keyword '" + Str(keyword) + "' (expected tool or key)");
  }
  const int last_line = std::max(line_number, 1);
  if (!have_header) {
    throw ScriptError(name, last_line, "empty script: expected the header 'somasim-script 1'");
  }
  if (!tool_has_key) {
    throw ScriptError(
        name, tool_line,
        "tool: '" + script.tools_[static_cast<size_t>(tool)] + "' is not followed by a key");
  }
  if (script.keys_.empty()) throw ScriptError(name, last_line, "no key in the script");
  return script;
}

MockScript MockScript::Load(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ScriptError(path, 0, std::string("cannot open: ") + std::strerror(errno));
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) throw ScriptError(path, 0, "cannot read");
  return Parse(text.str(), path);
}

double MockScript::duration() const { return keys_.empty() ? 0.0 : keys_.back().time; }

ScriptSample MockScript::At(double t) const {
  ScriptSample s;
  if (keys_.empty()) return s;
  // The key at or before t (the first key for t before it, or NaN), and the one after.
  size_t k0 = 0;
  if (t > keys_.front().time) {
    const auto after =
        std::upper_bound(keys_.begin(), keys_.end(), t,
                         [](double time, const ScriptKey& k) { return time < k.time; });
    k0 = static_cast<size_t>(std::distance(keys_.begin(), after)) - 1;
  }
  const ScriptKey& a = keys_[k0];
  s.tool = a.tool;
  s.position = a.position;
  s.orientation = a.orientation;
  s.jaw = a.jaw;
  s.buttons = a.buttons;
  if (k0 + 1 == keys_.size() || !(t > a.time)) return s;
  const ScriptKey& b = keys_[k0 + 1];
  // Across a tool switch the old tool holds its last pose until the new tool's first key.
  if (b.tool != a.tool) return s;
  const double u = (t - a.time) / (b.time - a.time);  // in (0, 1)
  s.position = a.position + u * (b.position - a.position);
  s.jaw = a.jaw + u * (b.jaw - a.jaw);
  s.orientation = a.orientation.slerp(u, b.orientation);
  return s;
}

}  // namespace somasim::haptic
