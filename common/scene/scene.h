// Scenes (idl/scene.proto, SPEC §6): parsing the text format and checking every value before
// anything is built, so that a bad scene is refused with the file, the line and the field —
// e.g. "liver.scene.txtpb:14: organ[0].material.density: must be a finite value > 0" — and
// never half-loaded. What can only be checked against a mesh (node ids in range, regions that
// select no node) is checked when the scene is built.
#pragma once

#include <stdexcept>
#include <string>
#include <string_view>

#include "idl/scene.pb.h"

namespace somasim::scene {

inline constexpr uint32_t kSceneFormatVersion = 1;

class SceneError : public std::runtime_error {
 public:
  // line: 1-based, 0 when the fault has no line (an unreadable file, a missing field).
  SceneError(const std::string& file, int line, const std::string& field,
             const std::string& message);
  const std::string& file() const { return file_; }
  int line() const { return line_; }
  const std::string& field() const { return field_; }  // e.g. "organ[1].material.density"

 private:
  std::string file_;
  int line_;
  std::string field_;
};

// Parses and checks a scene in protobuf text format; `file_name` names it in errors.
Scene ParseScene(std::string_view text, const std::string& file_name);
// Reads and parses the file at `path`.
Scene LoadSceneFile(const std::string& path);

}  // namespace somasim::scene
