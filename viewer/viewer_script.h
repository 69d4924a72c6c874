// A viewer script (`somasim-viewer --script FILE`): what a person at the viewer would do, at
// stated moments, for tests, demonstrations and bug reports that must happen the same way each
// time (keys, window resizes, minimising, losing the GL context, annotations, screenshots).
// Format (docs/viewer.md):
//
//   somasim-viewer-script 1        first non-comment line: the format and its version
//   WHEN ACTION [ARGUMENTS]        one event per line, run in file order
//
// WHEN is `frame N` (N >= 0 frames drawn with the whole scene), `sim T` (the session time shown,
// T >= 0 s) or `wall S` (S >= 0 wall-clock seconds since the whole scene was first shown). An
// event waits for the ones before it, so the moments need not increase. ACTION:
//   key K            a key press: one printable character, or enter escape backspace space, or
//                    left right up down pageup pagedown
//   screenshot FILE  a PNG of the next frame drawn (relative to the working directory)
//   resize W H       the window to W × H pixels (16..8192)
//   hide / show      unmaps / maps the window (what minimising does to it)
//   iconify          asks the window manager to minimise it; freeglut stops drawing until the
//                    window is mapped again (without a window manager, as on Xvfb: hide, show)
//   recreate         destroys the window and its GL context and makes new ones (a context lost)
//   drag DX DY       the driven tool moves as by a Shift + left mouse drag of DX, DY pixels
//   annotate TEXT    an instructor's note (observe-only), the rest of the line
//   quit             stops the viewer (exit 0)
// '#' starts a comment (not inside annotate's text); blank lines are ignored.
#pragma once

#include <stdexcept>
#include <string>
#include <vector>

namespace somasim::viewer {

// A script that cannot be used: what() is "FILE:LINE: message".
class ViewerScriptError : public std::runtime_error {
 public:
  ViewerScriptError(const std::string& file, int line, const std::string& message);
};

struct ViewerEvent {
  enum class When { kFrame, kSim, kWall };
  enum class Action {
    kKey,
    kSpecialKey,
    kScreenshot,
    kResize,
    kHide,
    kShow,
    kIconify,
    kRecreate,
    kDrag,
    kAnnotate,
    kQuit
  };
  When when = When::kFrame;
  double at = 0.0;  // frames, or seconds (sim or wall)
  Action action = Action::kQuit;
  int key = 0;       // kKey: the character; kSpecialKey: a GLUT_KEY_* code
  int a = 0, b = 0;  // kResize: width, height [pixels]; kDrag: dx, dy [pixels]
  std::string text;  // kScreenshot: the file; kAnnotate: the note
  int line = 0;
};

// Parses a script's text; throws ViewerScriptError naming the line and what is wrong.
std::vector<ViewerEvent> ParseViewerScript(const std::string& text, const std::string& file);
// Reads and parses a file; throws ViewerScriptError (line 0 when it cannot be read).
std::vector<ViewerEvent> LoadViewerScript(const std::string& path);

}  // namespace somasim::viewer
