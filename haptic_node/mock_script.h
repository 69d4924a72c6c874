// The mock haptic device's script (the mock haptic node of automated tests and the demo,
// `somasim-haptic --device mock --script FILE`): a scripted tool trajectory, sampled at 1 kHz.
// Format (documented in docs/mock_scripts.md; examples in haptic_node/scripts/):
//
//   somasim-script 1                  first non-comment line: the format and its version
//   tool ID                           the keys below drive the scene's tool ID
//   key T X Y Z [jaw J] [quat W X Y Z] [buttons B]
//
// '#' starts a comment; blank lines are ignored. T [s] strictly increases through the file (the
// first key at T >= 0); X Y Z [m] is the tool tip in the scene frame; J in [0, 1] (0 open);
// quat is the tool frame's orientation (shaft along the frame's +z; normalised when read; a
// missing quat keeps the previous key's, the first defaults to identity: shaft pointing up from
// the tip); buttons is an unsigned bit set (idl/tool.idl ToolCommand: bit 0 clutch, 1 emergency
// stop, 2 cut). A missing jaw or buttons keeps the previous key's (0 at first). A `tool` line
// switches the driven tool from its next key on; every tool line is followed by at least one key.
// Between two keys of the same tool, position and jaw are linear in time and the orientation is
// slerped; buttons hold the earlier key's value. Across a tool switch the new tool starts at its
// first key's pose (a jump: scripts retract before they switch).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace somasim::haptic {

// A script that cannot be used: what(): "FILE:LINE: message".
class ScriptError : public std::runtime_error {
 public:
  ScriptError(const std::string& file, int line, const std::string& message);
  const std::string& file() const { return file_; }
  int line() const { return line_; }

 private:
  std::string file_;
  int line_;
};

struct ScriptKey {
  double time = 0.0;                                   // [s]
  int32_t tool = 0;                                    // index into MockScript::tools()
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // [m]
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();
  double jaw = 0.0;  // [0, 1]
  uint32_t buttons = 0;
  int line = 0;  // where it was written
};

// The tool command the script gives at time t.
struct ScriptSample {
  int32_t tool = 0;  // index into tools()
  Eigen::Vector3d position = Eigen::Vector3d::Zero();
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();
  double jaw = 0.0;
  uint32_t buttons = 0;
};

class MockScript {
 public:
  // Throws ScriptError naming `name`, the line and the fault: a missing or wrong header, an
  // unknown keyword, a missing or extra value, a number that is not finite, times that do not
  // increase, jaw outside [0, 1], a zero quaternion, buttons that are not an unsigned 32-bit
  // integer, a key before any tool, a tool id that is not letters, digits, '_' or '-', a
  // position farther than 10 m from the origin, no key at all.
  static MockScript Parse(std::string_view text, const std::string& name);
  // Reads the file (ScriptError with line 0 when it cannot be read) and parses it.
  static MockScript Load(const std::string& path);

  double duration() const;  // [s] the last key's time
  const std::vector<std::string>& tools() const { return tools_; }
  const std::vector<ScriptKey>& keys() const { return keys_; }
  // The command at time t [s]: before the first key, the first key's; after the last, the
  // last's. Allocation-free, O(log keys).
  ScriptSample At(double t) const;

 private:
  std::vector<std::string> tools_;
  std::vector<ScriptKey> keys_;
};

}  // namespace somasim::haptic
