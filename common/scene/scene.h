// Scenes (idl/scene.proto, SPEC §6): parsing the text format and checking every value before
// anything is built, so that a bad scene is refused with the file, the line and the field —
// e.g. "liver.scene.txtpb:14: organ[0].material.density: must be a finite value > 0" — and
// never half-loaded. What can only be checked against a mesh (node ids in range, regions that
// select no node) is checked when the scene is built.
#pragma once

#include <map>
#include <stdexcept>
#include <string>
#include <string_view>

#include "common/app/exit_codes.h"
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

// The exit code a program ends with on this error (common/app/exit_codes.h): kExitIo when the
// file could not be read (no line and no field), kExitBadInput when it was refused.
inline int ExitCodeOf(const SceneError& e) {
  return e.line() == 0 && e.field().empty() ? app::kExitIo : app::kExitBadInput;
}

// True for the finite-element kinds (fem_linear, fem_corotational, fem_hyperelastic).
bool IsFemModel(const Model& model);

// Where a scene's messages were written, so that faults found later (when the scene is built on
// its meshes) still name the file, the line and the field.
class SceneLines {
 public:
  SceneLines() = default;
  explicit SceneLines(std::string file) : file_(std::move(file)) {}
  const std::string& file() const { return file_; }
  void Record(const std::string& field, int line) { lines_.emplace(field, line); }
  // The line of `field` (e.g. "organ[0].fixed[1].box"), or of its nearest recorded parent; 0
  // when none is known.
  int LineOf(const std::string& field) const;
  SceneError Error(const std::string& field, const std::string& message) const;

 private:
  std::string file_;
  std::map<std::string, int> lines_;
};

// Parses and checks a scene in protobuf text format; `file_name` names it in errors. `lines`,
// when given, receives where each message was written.
Scene ParseScene(std::string_view text, const std::string& file_name, SceneLines* lines = nullptr);
// Reads and parses the file at `path`.
Scene LoadSceneFile(const std::string& path, SceneLines* lines = nullptr);

// The default scene of a built-in organ (`builtin:NAME` on the command line): volume organs and
// closed surfaces as a corotational FEM (ρ = 1000 kg/m³, ν = 0.45, E = max(5 kPa, 20 ρ g L), L
// the longest side, so that the weight strains the body by a few per cent: the corotational
// model's range) resting on a table (the lowest 10 % of their height held) under gravity (-z),
// in a static solve of two load steps; the open patch as an implicit mass-spring sheet held along
// its lowest-x edge, 1 s of dynamics. Throws std::invalid_argument for an unknown organ.
Scene DefaultScene(std::string_view organ);

}  // namespace somasim::scene
