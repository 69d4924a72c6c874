#include "viewer/viewer_script.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iterator>
#include <sstream>
#include <utility>

namespace somasim::viewer {

namespace {

// GLUT's special key codes (GL/freeglut_std.h; viewer_app.cc checks them against GLUT's).
constexpr std::pair<const char*, int> kSpecialKeys[] = {
    {"left", 100}, {"up", 101}, {"right", 102}, {"down", 103}, {"pageup", 104}, {"pagedown", 105}};

std::string Trim(const std::string& s) {
  const size_t first = s.find_first_not_of(" \t\r");
  if (first == std::string::npos) return "";
  return s.substr(first, s.find_last_not_of(" \t\r") - first + 1);
}

// A finite number >= 0 from the whole of `word`; false otherwise.
bool NonNegative(const std::string& word, double* out) {
  std::istringstream in(word);
  double v = 0.0;
  if (!(in >> v) || !in.eof() || !std::isfinite(v) || v < 0.0) return false;
  *out = v;
  return true;
}

bool Integer(const std::string& word, int lo, int hi, int* out) {
  std::istringstream in(word);
  long long v = 0;
  if (!(in >> v) || !in.eof() || v < lo || v > hi) return false;
  *out = static_cast<int>(v);
  return true;
}

}  // namespace

ViewerScriptError::ViewerScriptError(const std::string& file, int line, const std::string& message)
    : std::runtime_error(file + ":" + std::to_string(line) + ": " + message) {}

std::vector<ViewerEvent> ParseViewerScript(const std::string& text, const std::string& file) {
  std::vector<ViewerEvent> events;
  std::istringstream in(text);
  std::string raw;
  int number = 0;
  bool header = false;
  while (std::getline(in, raw)) {
    ++number;
    const auto fail = [&](const std::string& message) {
      throw ViewerScriptError(file, number, message);
    };
    if (raw.find('\0') != std::string::npos) fail("a NUL byte: not a text file");
    // A comment ends the line, except inside annotate's text (handled below).
    const std::string uncommented = Trim(raw.substr(0, raw.find('#')));
    if (uncommented.empty()) continue;
    std::istringstream words(uncommented);
    std::string first;
    words >> first;
    if (!header) {
      std::string version, rest;
      words >> version >> rest;
      if (first != "somasim-viewer-script") {
        fail("the first line must be \"somasim-viewer-script 1\"");
      }
      if (version != "1" || !rest.empty()) {
        fail("format version \"" + version + "\" is not supported (this viewer reads 1)");
      }
      header = true;
      continue;
    }
    ViewerEvent e;
    e.line = number;
    std::string at, action;
    words >> at >> action;
    if (first == "frame") {
      e.when = ViewerEvent::When::kFrame;
    } else if (first == "sim") {
      e.when = ViewerEvent::When::kSim;
    } else if (first == "wall") {
      e.when = ViewerEvent::When::kWall;
    } else {
      fail("\"" + first + "\": an event starts with frame N, sim T or wall S");
    }
    if (e.when == ViewerEvent::When::kFrame) {
      int frames = 0;
      if (!Integer(at, 0, 100000000, &frames)) fail("frame \"" + at + "\": not a count >= 0");
      e.at = frames;
    } else if (!NonNegative(at, &e.at)) {
      fail(first + " \"" + at + "\": not a finite number of seconds >= 0");
    }
    std::vector<std::string> args;
    for (std::string w; words >> w;) args.push_back(w);
    const auto need = [&](size_t n) {
      if (args.size() != n) {
        fail(action + " takes " + std::to_string(n) + " argument" + (n == 1 ? "" : "s") + ", not " +
             std::to_string(args.size()));
      }
    };
    if (action == "key") {
      need(1);
      e.action = ViewerEvent::Action::kKey;
      constexpr std::pair<const char*, int> kControlKeys[] = {
          {"enter", 13}, {"escape", 27}, {"backspace", 8}, {"space", ' '}};
      if (args[0].size() == 1 && args[0][0] > ' ' && args[0][0] < 127) {
        e.key = static_cast<unsigned char>(args[0][0]);
      } else if (const auto* c = std::find_if(std::begin(kControlKeys), std::end(kControlKeys),
                                              [&](const auto& k) { return args[0] == k.first; });
                 c != std::end(kControlKeys)) {
        e.key = c->second;
      } else {
        e.action = ViewerEvent::Action::kSpecialKey;
        for (const auto& [name, code] : kSpecialKeys) {
          if (args[0] == name) e.key = code;
        }
        if (e.key == 0) {
          fail("key \"" + args[0] +
               "\": one printable character, or enter escape backspace space left right up "
               "down pageup pagedown");
        }
      }
    } else if (action == "screenshot") {
      need(1);
      e.action = ViewerEvent::Action::kScreenshot;
      e.text = args[0];
    } else if (action == "resize") {
      need(2);
      e.action = ViewerEvent::Action::kResize;
      if (!Integer(args[0], 16, 8192, &e.a) || !Integer(args[1], 16, 8192, &e.b)) {
        fail("resize " + args[0] + " " + args[1] + ": width and height are 16..8192 pixels");
      }
    } else if (action == "drag") {
      need(2);
      e.action = ViewerEvent::Action::kDrag;
      if (!Integer(args[0], -8192, 8192, &e.a) || !Integer(args[1], -8192, 8192, &e.b)) {
        fail("drag " + args[0] + " " + args[1] + ": dx and dy are -8192..8192 pixels");
      }
    } else if (action == "annotate") {
      // The note is the rest of the raw line, '#' included.
      e.action = ViewerEvent::Action::kAnnotate;
      const size_t pos = raw.find("annotate");
      e.text = Trim(raw.substr(pos + 8));
      if (e.text.empty()) fail("annotate needs the note's text");
      if (e.text.size() > 1000) fail("annotate: a note is at most 1000 characters");
    } else {
      const std::pair<const char*, ViewerEvent::Action> plain[] = {
          {"hide", ViewerEvent::Action::kHide},
          {"show", ViewerEvent::Action::kShow},
          {"iconify", ViewerEvent::Action::kIconify},
          {"recreate", ViewerEvent::Action::kRecreate},
          {"quit", ViewerEvent::Action::kQuit}};
      bool known = false;
      for (const auto& [name, kind] : plain) {
        if (action == name) {
          need(0);
          e.action = kind;
          known = true;
        }
      }
      if (!known) {
        fail("\"" + action +
             "\": not an action (key, screenshot, resize, hide, show, iconify, recreate, drag, "
             "annotate, quit)");
      }
    }
    events.push_back(std::move(e));
  }
  if (!header) throw ViewerScriptError(file, number, "empty: no \"somasim-viewer-script 1\" line");
  return events;
}

std::vector<ViewerEvent> LoadViewerScript(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ViewerScriptError(path, 0, "cannot open the file");
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) throw ViewerScriptError(path, 0, "cannot read the file");
  if (text.str().size() > (1u << 20)) throw ViewerScriptError(path, 0, "larger than 1 MiB");
  return ParseViewerScript(text.str(), path);
}

}  // namespace somasim::viewer
