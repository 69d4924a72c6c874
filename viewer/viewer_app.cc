#include "viewer/viewer_app.h"

#include <GL/freeglut.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "common/app/log.h"
#include "common/app/signals.h"
#include "common/dds/topics.h"
#include "common/render/png_encoder.h"
#include "common/wire/frame_dump.h"
#include "viewer/gl_view.h"
#include "viewer/scene_receiver.h"
#include "viewer/viewer_script.h"

namespace somasim::viewer {

namespace {

using app::Log;
using app::LogLevel;
using Clock = std::chrono::steady_clock;

struct ViewerOptions {
  std::string session = "default";
  uint32_t domain = 0;
  std::string dds_config;
  std::string screenshot;
  int after_frames = 30;
  std::string dump_positions;
  int width = 960;
  int height = 720;
  double timeout = 0.0;            // [s]; 0 = none
  bool observe = false;            // observe-only: never publishes tool commands
  std::string drive;               // station: drive this tool from the start ("" = on 't')
  std::string station = "viewer";  // the station name in tool commands and logs
  bool list_sessions = false;      // print the running sessions and exit
  int frames = 0;                  // stop after this many frames of the complete scene; 0 = never
  std::string report;              // JSON written when stopping ("" = none)
  std::string script;              // a viewer script (viewer/viewer_script.h; "" = none)
};

// viewer_script.cc names GLUT's special keys by their codes.
static_assert(GLUT_KEY_LEFT == 100 && GLUT_KEY_UP == 101 && GLUT_KEY_RIGHT == 102 &&
              GLUT_KEY_DOWN == 103 && GLUT_KEY_PAGE_UP == 104 && GLUT_KEY_PAGE_DOWN == 105);

// The last kCapacity samples of a quantity [ms], for the display and the report.
class Recent {
 public:
  static constexpr size_t kCapacity = 4096;
  void Add(double value) {
    if (values_.size() < kCapacity) {
      values_.push_back(value);
    } else {
      values_[next_] = value;
    }
    next_ = (next_ + 1) % kCapacity;
    ++count_;
  }
  // The q-quantile (0..1) of the last `window` samples (all when 0); NaN when there are none.
  double Quantile(double q, size_t window = 0) const {
    const size_t n = window == 0 ? values_.size() : std::min(window, values_.size());
    if (n == 0) return std::nan("");
    std::vector<double> v;
    v.reserve(n);
    for (size_t k = 0; k < n; ++k) {
      v.push_back(values_[(next_ + values_.size() - 1 - k) % values_.size()]);
    }
    const auto at = v.begin() + static_cast<std::ptrdiff_t>(q * static_cast<double>(n - 1));
    std::nth_element(v.begin(), at, v.end());
    return *at;
  }
  uint64_t count() const { return count_; }

 private:
  std::vector<double> values_;
  size_t next_ = 0;
  uint64_t count_ = 0;
};

// The one viewer of this process: GLUT's callbacks are plain functions.
struct Viewer {
  ViewerOptions options;
  std::unique_ptr<dds::Domain> domain;
  std::unique_ptr<dds::Participant> participant;
  std::unique_ptr<dds::Topics> topics;
  std::unique_ptr<SceneReceiver> receiver;
  // Station mode only: the tool command writer (made when driving starts). Observe-only mode:
  // only the instructor command writer. Neither exists until it is used.
  std::unique_ptr<dds::Writer<somasim_wire_ToolCommand>> tool_writer;
  std::unique_ptr<dds::Writer<somasim_wire_InstructorCommand>> instructor_writer;
  std::string driving;                            // the tool the keyboard drives ("" = none)
  Eigen::Vector3d tip = Eigen::Vector3d::Zero();  // [m]
  double jaw_closure = 0.0;
  uint64_t tool_seq = 0, instructor_seq = 0;
  Clock::time_point last_command{};
  // Observe-only: the sessions running on the domain, refreshed every 2 s (n switches).
  std::vector<std::string> sessions;
  Clock::time_point last_listing{};
  std::unique_ptr<GlView> view;  // remade with the window (a lost GL context)
  int window = 0;                // GLUT's window id
  OrbitCamera camera;
  bool laparoscope = false;  // drawing from the scene's camera tool (l toggles)
  // Observe-only: an annotation being typed (a starts it, Enter sends, Esc drops it).
  bool typing = false;
  std::string note;
  // The script's events, the next to run, and when the whole scene was first shown.
  std::vector<ViewerEvent> script;
  size_t next_event = 0;
  Clock::time_point complete_at{};
  std::string pending_screenshot;  // written after the next draw
  int width = 0, height = 0;
  int frames_with_scene = 0;  // frames drawn since every organ had a shape
  Clock::time_point started = Clock::now();
  int exit_code = kExitOk;
  bool finished = false;
  bool logged_complete = false;  // "scene_complete" is logged once every organ has a shape
  bool shown_gone = false;       // the server was shown as gone (logged when it changes)
  uint64_t restarts_seen = 0;    // server restarts logged
  // Frame time (between draws of the complete scene) and frame latency (a server frame's write
  // to the end of the draw that first shows it; both clocks are the host's steady clock, so
  // only meaningful when the server runs on the same host) [ms].
  Recent frame_ms, latency_ms;
  Clock::time_point last_draw{};
  std::map<std::string, uint64_t> drawn_frame;      // per organ, the frame last drawn
  std::map<std::string, uint32_t> logged_topology;  // per organ, the topology version logged
  // Mouse state: the button held, where it was, and whether it drags the driven tool (Shift
  // held when it was pressed).
  int button = -1, last_x = 0, last_y = 0;
  bool drag_tool = false;
};

Viewer* g_viewer = nullptr;

// wire::WriteFrameDump of every organ with a shape; false on an I/O error.
bool DumpPositions(const SceneReceiver& r, const std::string& dir) {
  for (const auto& [id, organ] : r.organs()) {
    if (organ.has_shape() &&
        !wire::WriteFrameDump(dir, id, organ.decoder->positions(), organ.decoder->frame())) {
      return false;
    }
  }
  return true;
}

void Finish(int code) {
  Viewer& v = *g_viewer;
  if (v.finished) return;
  v.finished = true;
  v.exit_code = code;
  if (!v.options.dump_positions.empty()) {
    if (DumpPositions(*v.receiver, v.options.dump_positions)) {
      Log(LogLevel::kInfo, "dumped_positions", {{"dir", v.options.dump_positions}});
    } else {
      std::fprintf(stderr, "somasim-viewer: cannot write %s\n", v.options.dump_positions.c_str());
      v.exit_code = kExitIo;
    }
  }
  if (!v.options.report.empty()) {
    const ReceiverCounters& c = v.receiver->counters();
    nlohmann::ordered_json report = {{"session", v.options.session},
                                     {"scene", v.receiver->scene_name()},
                                     {"frames_drawn_with_scene", v.frames_with_scene},
                                     {"frame_ms",
                                      {{"samples", v.frame_ms.count()},
                                       {"p50", v.frame_ms.Quantile(0.5)},
                                       {"p99", v.frame_ms.Quantile(0.99)}}},
                                     {"latency_ms",
                                      {{"samples", v.latency_ms.count()},
                                       {"p50", v.latency_ms.Quantile(0.5)},
                                       {"p99", v.latency_ms.Quantile(0.99)}}},
                                     {"bad_frames", c.bad_frames},
                                     {"bad_topologies", c.bad_topologies},
                                     {"wrong_format_version", c.wrong_format_version},
                                     {"frames_waiting_for_topology", c.frames_waiting_for_topology},
                                     {"server_restarts", c.server_restarts}};
    std::ofstream out(v.options.report);
    out << report.dump(2) << "\n";
    if (!out) {
      std::fprintf(stderr, "somasim-viewer: cannot write %s\n", v.options.report.c_str());
      v.exit_code = kExitIo;
    }
  }
  glutLeaveMainLoop();
}

// Station mode: the keyboard drives `tool` (a tool of the session), its tip starting 2 cm above
// the organs' top centre, shaft up.
void StartDriving(Viewer& v, const std::string& tool) {
  if (v.options.observe || !v.driving.empty()) return;
  const auto it = v.receiver->tools().find(tool);
  if (it == v.receiver->tools().end() || it->second.kind == "camera") {
    Log(LogLevel::kWarning, "no_such_tool", {{"tool", tool}});
    return;
  }
  Eigen::Vector3d lo, hi;
  if (!GlView::Bounds(*v.receiver, &lo, &hi)) return;  // no organ yet: the next tick retries
  v.tip = Eigen::Vector3d(0.5 * (lo.x() + hi.x()), 0.5 * (lo.y() + hi.y()), hi.z() + 0.02);
  if (!v.tool_writer) {
    v.tool_writer = std::make_unique<dds::Writer<somasim_wire_ToolCommand>>(
        *v.participant, v.topics->tool_command, dds::ToolCommandQos(v.options.session));
  }
  v.driving = tool;
  Log(LogLevel::kInfo, "driving", {{"tool", tool}, {"station", v.options.station}});
}

// The driven tool's command, at most every 10 ms (the tool command's lease is 500 ms).
void PublishTool(Viewer& v) {
  if (v.driving.empty()) return;
  const Clock::time_point now = Clock::now();
  if (now - v.last_command < std::chrono::milliseconds(10)) return;
  v.last_command = now;
  somasim_wire_ToolCommand c{};
  c.tool = dds::CString(v.driving);
  c.format_version = dds::kWireFormatVersion;
  c.station = dds::CString(v.options.station);
  c.seq = ++v.tool_seq;
  c.sender_time_ns =
      std::chrono::duration_cast<std::chrono::nanoseconds>(now.time_since_epoch()).count();
  for (int k = 0; k < 3; ++k) c.position[k] = v.tip[k];
  c.orientation[0] = 1.0;  // shaft along +z
  c.jaw_closure = v.jaw_closure;
  v.tool_writer->Write(c);
}

// Observe-only mode: an instructor command (1 pause, 2 resume, 4 annotate with `text`).
void Instruct(Viewer& v, uint32_t kind, const std::string& text = std::string()) {
  if (!v.options.observe) return;
  if (!v.instructor_writer) {
    v.instructor_writer = std::make_unique<dds::Writer<somasim_wire_InstructorCommand>>(
        *v.participant, v.topics->instructor, dds::InstructorQos(v.options.session));
  }
  somasim_wire_InstructorCommand c{};
  c.format_version = dds::kWireFormatVersion;
  c.seq = ++v.instructor_seq;
  c.instructor = dds::CString(v.options.station);
  c.kind = kind;
  c.text = dds::CString(text);
  v.instructor_writer->Write(c);
  Log(LogLevel::kInfo, "instructor_command", {{"kind", kind}, {"text", text}});
}

// Observe-only: joins the next running session (in name order) instead of this one.
void NextSession(Viewer& v) {
  if (!v.options.observe) return;
  v.sessions = dds::RunningSessions(*v.participant, std::chrono::milliseconds(0));
  if (v.sessions.empty()) return;
  const auto after = std::upper_bound(v.sessions.begin(), v.sessions.end(), v.options.session);
  const std::string next = after != v.sessions.end() ? *after : v.sessions.front();
  if (next == v.options.session) return;
  v.options.session = next;
  v.receiver = std::make_unique<SceneReceiver>(*v.participant, *v.topics, next);
  v.instructor_writer.reset();  // bound to the old session's partition
  v.camera.fitted = false;
  v.laparoscope = false;
  v.logged_complete = false;
  v.drawn_frame.clear();
  v.last_draw = Clock::time_point{};
  glutSetWindowTitle(("somasim-viewer: " + next).c_str());
  Log(LogLevel::kInfo, "switched_session", {{"session", next}});
}

// The scene's laparoscope: its first camera tool with a pose (nullptr: none).
const ToolScene* Laparoscope(const SceneReceiver& r) {
  for (const auto& [id, tool] : r.tools()) {
    if (tool.kind == "camera" && tool.has_pose) return &tool;
  }
  return nullptr;
}

Hud MakeHud(const Viewer& v) {
  Hud hud;
  const SceneReceiver& r = *v.receiver;
  char line[256];
  std::snprintf(line, sizeof line, "session %s  scene %s  t = %.2f s", v.options.session.c_str(),
                r.scene_name().c_str(), r.sim_time());
  hud.lines.emplace_back(line);
  if (r.has_metrics()) {
    const somasim_wire_ServerMetrics& m = r.metrics();
    std::snprintf(line, sizeof line, "physics %.0f Hz  step p50 %.0f us  p99 %.0f us",
                  m.physics_rate_hz, m.step_p50_us, m.step_p99_us);
    hud.lines.emplace_back(line);
  }
  if (v.frame_ms.count() > 0) {
    std::snprintf(line, sizeof line, "frame %.1f ms (p99 %.1f)  frame latency %.1f ms",
                  v.frame_ms.Quantile(0.5, 120), v.frame_ms.Quantile(0.99, 120),
                  v.latency_ms.count() > 0 ? v.latency_ms.Quantile(0.5, 120) : 0.0);
    hud.lines.emplace_back(line);
  }
  const ReceiverCounters& c = r.counters();
  if (c.bad_frames + c.bad_topologies + c.wrong_format_version + c.bad_tool_samples > 0) {
    std::snprintf(line, sizeof line,
                  "dropped: %llu bad frames, %llu bad topologies, %llu versions, %llu tool",
                  static_cast<unsigned long long>(c.bad_frames),
                  static_cast<unsigned long long>(c.bad_topologies),
                  static_cast<unsigned long long>(c.wrong_format_version),
                  static_cast<unsigned long long>(c.bad_tool_samples));
    hud.lines.emplace_back(line);
  }
  const Clock::time_point now = Clock::now();
  for (const auto& [id, tool] : r.tools()) {
    // Haptic rates: the stations driving a tool now (commands within the lease).
    if (tool.has_pose && now - tool.last_command < dds::kLease && tool.command_rate_hz > 0.0) {
      std::snprintf(line, sizeof line, "haptic %s: %.0f Hz from %s", id.c_str(),
                    tool.command_rate_hz, tool.station.c_str());
      hud.lines.emplace_back(line);
    }
  }
  for (const auto& [id, tool] : r.tools()) {
    const Eigen::Vector3d f = tool.Force();
    if (!tool.in_contact && !tool.grasping && f.norm() < 0.01) continue;
    std::snprintf(line, sizeof line, "%s: %s %s  force %.2f N", id.c_str(),
                  tool.grasping ? "holds" : "touches", tool.organ.c_str(), f.norm());
    hud.lines.emplace_back(line);
  }
  if (v.laparoscope) {
    hud.lines.emplace_back(Laparoscope(r) != nullptr
                               ? "laparoscope view (l: orbit camera)"
                               : "laparoscope: no camera pose yet (l: orbit camera)");
  }
  if (v.options.observe) {
    if (v.typing) {
      hud.lines.push_back("note: " + v.note + "_  (Enter sends, Esc drops)");
    } else {
      std::snprintf(line, sizeof line,
                    "observe-only: p pause, r resume, a annotate, n next session (%zu running)",
                    v.sessions.size());
      hud.lines.emplace_back(line);
    }
  } else if (v.driving.empty()) {
    hud.lines.emplace_back("station: t drives a tool with the keys and Shift + mouse");
  } else {
    std::snprintf(line, sizeof line,
                  "driving %s at (%.0f, %.0f, %.0f) mm: arrows, PgUp/PgDn, Shift+drag, c jaws",
                  v.driving.c_str(), 1e3 * v.tip.x(), 1e3 * v.tip.y(), 1e3 * v.tip.z());
    hud.lines.emplace_back(line);
  }
  if (!r.has_session()) hud.lines.emplace_back("waiting for the session...");
  for (const std::string& message : r.messages()) hud.lines.push_back(message);
  hud.server_gone = r.has_session() && r.server_gone(Clock::now());
  return hud;
}

// Writes the back buffer's pixels (after a draw, before the swap) to `file` as PNG.
bool WriteScreenshot(const Viewer& v, const std::string& file) {
  glFinish();
  const render::Image image = GlView::ReadPixels(v.width, v.height);
  std::ofstream out(file, std::ios::binary);
  const std::string png = render::EncodePng(image);
  out.write(png.data(), static_cast<std::streamsize>(png.size()));
  if (!out) {
    std::fprintf(stderr, "somasim-viewer: cannot write %s\n", file.c_str());
    return false;
  }
  Log(LogLevel::kInfo, "screenshot",
      {{"file", file}, {"frames", v.frames_with_scene}, {"width", v.width}, {"height", v.height}});
  return true;
}

void Display() {
  Viewer& v = *g_viewer;
  if (v.finished) return;
  if (!v.logged_complete && v.receiver->complete()) {
    v.logged_complete = true;
    v.complete_at = Clock::now();
    Log(LogLevel::kInfo, "scene_complete",
        {{"organs", v.receiver->organs().size()}, {"scene", v.receiver->scene_name()}});
  }
  if (v.receiver->complete()) {  // each organ's topology as first shown (after a cut: its faces)
    for (const auto& [id, organ] : v.receiver->organs()) {
      uint32_t& logged = v.logged_topology[id];
      if (logged == organ.topology_version) continue;
      logged = organ.topology_version;
      Log(LogLevel::kInfo, "topology_shown",
          {{"organ", id},
           {"version", organ.topology_version},
           {"triangles", organ.triangles.size() / 3},
           {"inner_faces", std::count(organ.inner_face.begin(), organ.inner_face.end(), 1)}});
    }
  }
  if (!v.camera.fitted) {
    // Framed on the rest shapes: every viewer of the session frames it alike, however late it
    // joined and whatever the tools were doing then.
    Eigen::Vector3d lo, hi;
    if (v.receiver->complete() && GlView::Bounds(*v.receiver, &lo, &hi, /*rest=*/true)) {
      v.camera.Fit(lo, hi);
    }
  }
  const ToolScene* scope = v.laparoscope ? Laparoscope(*v.receiver) : nullptr;
  v.view->Draw(*v.receiver,
               scope != nullptr ? ViewPose::Laparoscope(*scope) : ViewPose::Of(v.camera),
               MakeHud(v), v.width, v.height);
  if (v.receiver->complete()) ++v.frames_with_scene;
  if (!v.pending_screenshot.empty() && v.receiver->complete()) {
    const bool ok = WriteScreenshot(v, v.pending_screenshot);
    v.pending_screenshot.clear();
    if (!ok) {
      Finish(kExitIo);
      return;
    }
  }
  if (!v.options.screenshot.empty() && v.frames_with_scene >= v.options.after_frames) {
    Finish(WriteScreenshot(v, v.options.screenshot) ? kExitOk : kExitIo);
    return;
  }
  glutSwapBuffers();
  if (v.receiver->complete()) {
    glFinish();  // the frame is on screen (in Xvfb's framebuffer) before it is timed
    const Clock::time_point now = Clock::now();
    if (v.last_draw != Clock::time_point{}) {
      v.frame_ms.Add(std::chrono::duration<double, std::milli>(now - v.last_draw).count());
    }
    v.last_draw = now;
    const int64_t now_ns =
        std::chrono::duration_cast<std::chrono::nanoseconds>(now.time_since_epoch()).count();
    for (const auto& [id, organ] : v.receiver->organs()) {
      if (!organ.has_shape()) continue;
      uint64_t& drawn = v.drawn_frame[id];
      if (organ.decoder->frame() == drawn) continue;
      drawn = organ.decoder->frame();
      const double latency = static_cast<double>(now_ns - organ.sender_time_ns) * 1e-6;
      if (latency >= 0.0 && latency < 10000.0) v.latency_ms.Add(latency);  // same host only
    }
    if (v.options.frames > 0 && v.frames_with_scene >= v.options.frames) Finish(kExitOk);
  }
}

void Reshape(int width, int height) {
  g_viewer->width = std::max(width, 1);  // minimised: 0 × 0, drawn as 1 × 1
  g_viewer->height = std::max(height, 1);
}

// The view's right and up directions and its forward one (into the screen), for moving the
// driven tool as the user sees it.
void ViewAxes(const Viewer& v, Eigen::Vector3d* right, Eigen::Vector3d* up,
              Eigen::Vector3d* forward) {
  *forward = (v.camera.target - v.camera.Eye()).normalized();
  *right = forward->cross(Eigen::Vector3d::UnitZ());
  if (right->norm() < 1e-9) *right = Eigen::Vector3d::UnitX();
  right->normalize();
  *up = right->cross(*forward);
}

// Station driving by mouse: the tip follows a drag of (dx, dy) pixels in the view plane, so that
// at the camera's target it stays under the pointer.
void DragTool(Viewer& v, int dx, int dy) {
  if (v.driving.empty()) return;
  Eigen::Vector3d right, up, forward;
  ViewAxes(v, &right, &up, &forward);
  const double per_pixel = 2.0 * v.camera.distance *
                           std::tan(0.5 * v.camera.fov_deg * std::numbers::pi / 180.0) /
                           std::max(v.height, 1);  // [m]
  v.tip += per_pixel * (dx * right - dy * up);
}

void Mouse(int button, int state, int x, int y) {
  Viewer& v = *g_viewer;
  const bool shift = (glutGetModifiers() & GLUT_ACTIVE_SHIFT) != 0;
  if (button == 3 || button == 4) {  // wheel: zoom, or with Shift move the tool along the view
    if (state != GLUT_DOWN) return;
    if (shift && !v.driving.empty()) {
      Eigen::Vector3d right, up, forward;
      ViewAxes(v, &right, &up, &forward);
      v.tip += (button == 3 ? 0.002 : -0.002) * forward;
    } else {
      v.camera.Zoom(button == 3 ? 0.9 : 1.0 / 0.9);
    }
    return;
  }
  v.button = state == GLUT_DOWN ? button : -1;
  v.drag_tool = state == GLUT_DOWN && button == GLUT_LEFT_BUTTON && shift && !v.driving.empty();
  v.last_x = x;
  v.last_y = y;
}

void Motion(int x, int y) {
  Viewer& v = *g_viewer;
  const int px = x - v.last_x, py = y - v.last_y;
  const double dx = static_cast<double>(px) / v.height;
  const double dy = static_cast<double>(py) / v.height;
  v.last_x = x;
  v.last_y = y;
  if (v.drag_tool) {
    DragTool(v, px, py);
    return;
  }
  if (v.button == GLUT_LEFT_BUTTON) v.camera.Orbit(-3.0 * dx, 3.0 * dy);
  if (v.button == GLUT_RIGHT_BUTTON) v.camera.Pan(-dx, dy);
  if (v.button == GLUT_MIDDLE_BUTTON) v.camera.Zoom(std::exp(2.0 * dy));
}

void Key(Viewer& v, unsigned char key) {
  if (v.typing) {  // an annotation: every key is text until Enter or Esc
    if (key == 13 || key == 10) {
      if (!v.note.empty()) Instruct(v, 4, v.note);
      v.typing = false;
      v.note.clear();
    } else if (key == 27) {
      v.typing = false;
      v.note.clear();
    } else if ((key == 8 || key == 127) && !v.note.empty()) {
      v.note.pop_back();
    } else if (key >= ' ' && key < 127 && v.note.size() < 200) {
      v.note.push_back(static_cast<char>(key));
    }
    return;
  }
  if (key == 'q' || key == 27) Finish(kExitOk);
  if (key == 'f') v.camera.fitted = false;
  if (key == 'l') v.laparoscope = !v.laparoscope;
  if (key == 'p') Instruct(v, 1);
  if (key == 'r') Instruct(v, 2);
  if (key == 'a' && v.options.observe) v.typing = true;
  if (key == 'n') NextSession(v);
  if (key == 'c' && !v.driving.empty()) v.jaw_closure = v.jaw_closure > 0.5 ? 0.0 : 1.0;
  if (key == 't' && v.driving.empty()) {
    for (const auto& [id, tool] : v.receiver->tools()) {
      if (tool.kind != "camera") {
        StartDriving(v, id);
        break;
      }
    }
  }
}

void Keyboard(unsigned char key, int, int) { Key(*g_viewer, key); }

// Station driving: arrows move the tip in the view plane, Page Up / Down along the view, 1 mm
// a press (5 mm with Shift).
void SpecialKey(Viewer& v, int key, bool shift) {
  if (v.driving.empty()) return;
  const double step = shift ? 0.005 : 0.001;  // [m]
  Eigen::Vector3d right, up, forward;
  ViewAxes(v, &right, &up, &forward);
  if (key == GLUT_KEY_LEFT) v.tip -= step * right;
  if (key == GLUT_KEY_RIGHT) v.tip += step * right;
  if (key == GLUT_KEY_UP) v.tip += step * up;
  if (key == GLUT_KEY_DOWN) v.tip -= step * up;
  if (key == GLUT_KEY_PAGE_UP) v.tip += step * forward;
  if (key == GLUT_KEY_PAGE_DOWN) v.tip -= step * forward;
}

void Special(int key, int, int) {
  SpecialKey(*g_viewer, key, (glutGetModifiers() & GLUT_ACTIVE_SHIFT) != 0);
}

void Idle();

// The window and its GL context, with every callback; the view's GL objects are made anew.
void CreateViewerWindow(Viewer& v) {
  glutInitWindowSize(v.width, v.height);
  v.window = glutCreateWindow(("somasim-viewer: " + v.options.session).c_str());
  v.view = std::make_unique<GlView>();
  glutDisplayFunc(Display);
  glutIdleFunc(Idle);
  glutReshapeFunc(Reshape);
  glutMouseFunc(Mouse);
  glutMotionFunc(Motion);
  glutKeyboardFunc(Keyboard);
  glutSpecialFunc(Special);
}

// Runs the script's events whose moment has come, in order.
void RunScript(Viewer& v) {
  while (v.next_event < v.script.size() && !v.finished) {
    const ViewerEvent& e = v.script[v.next_event];
    if (!v.receiver->complete() && v.complete_at == Clock::time_point{}) return;
    bool due = false;
    switch (e.when) {
      case ViewerEvent::When::kFrame:
        due = v.frames_with_scene >= static_cast<int>(e.at);
        break;
      case ViewerEvent::When::kSim:
        due = v.receiver->sim_time() >= e.at;
        break;
      case ViewerEvent::When::kWall:
        due = v.complete_at != Clock::time_point{} &&
              std::chrono::duration<double>(Clock::now() - v.complete_at).count() >= e.at;
        break;
    }
    if (!due) return;
    // A screenshot is taken after the next draw; the events after it wait for it.
    if (!v.pending_screenshot.empty()) return;
    ++v.next_event;
    Log(LogLevel::kInfo, "script_event", {{"line", e.line}, {"frames", v.frames_with_scene}});
    switch (e.action) {
      case ViewerEvent::Action::kKey:
        Key(v, static_cast<unsigned char>(e.key));
        break;
      case ViewerEvent::Action::kSpecialKey:
        SpecialKey(v, e.key, false);
        break;
      case ViewerEvent::Action::kScreenshot:
        v.pending_screenshot = e.text;
        return;
      case ViewerEvent::Action::kResize:
        glutReshapeWindow(e.a, e.b);
        break;
      case ViewerEvent::Action::kHide:
        glutHideWindow();
        break;
      case ViewerEvent::Action::kShow:
        glutShowWindow();
        break;
      case ViewerEvent::Action::kIconify:
        glutIconifyWindow();
        break;
      case ViewerEvent::Action::kRecreate:
        // What a lost GL context leaves: nothing of the old one is used again.
        v.view.reset();
        glutDestroyWindow(v.window);
        CreateViewerWindow(v);
        Log(LogLevel::kInfo, "window_recreated", {{"window", v.window}});
        return;  // the new window's callbacks run from the next loop
      case ViewerEvent::Action::kDrag:
        DragTool(v, e.a, e.b);
        break;
      case ViewerEvent::Action::kAnnotate:
        Instruct(v, 4, e.text);
        break;
      case ViewerEvent::Action::kQuit:
        Finish(kExitOk);
        return;
    }
  }
}

void Idle() {
  Viewer& v = *g_viewer;
  if (v.finished) return;
  if (app::StopRequested()) {
    Finish(kExitOk);
    return;
  }
  if (v.options.timeout > 0.0 && !v.receiver->complete() && !v.logged_complete &&
      std::chrono::duration<double>(Clock::now() - v.started).count() > v.options.timeout) {
    std::fprintf(stderr, "somasim-viewer: no complete scene of session \"%s\" within %.0f s\n",
                 v.options.session.c_str(), v.options.timeout);
    Finish(kExitTimeout);
    return;
  }
  v.receiver->Poll();
  // What the display shows of the server, in the log too: gone (no heartbeat for the lease),
  // back, restarted (a new server id: its shapes are awaited anew).
  if (v.receiver->counters().server_restarts != v.restarts_seen) {
    v.restarts_seen = v.receiver->counters().server_restarts;
    v.logged_complete = false;
    v.drawn_frame.clear();
    Log(LogLevel::kInfo, "server_restarted", {{"server_id", v.receiver->server_id()}});
  }
  const bool gone = v.receiver->has_session() && v.receiver->server_gone(Clock::now());
  if (gone != v.shown_gone && (gone || v.receiver->has_session())) {
    v.shown_gone = gone;
    Log(gone ? LogLevel::kWarning : LogLevel::kInfo, gone ? "server_gone" : "server_back",
        {{"server_id", v.receiver->server_id()}});
  }
  if (!v.options.drive.empty() && v.driving.empty() && v.receiver->complete()) {
    StartDriving(v, v.options.drive);
  }
  RunScript(v);
  if (v.finished) return;
  PublishTool(v);
  if (v.options.observe && Clock::now() - v.last_listing > std::chrono::seconds(2)) {
    v.last_listing = Clock::now();
    v.sessions = dds::RunningSessions(*v.participant, std::chrono::milliseconds(0));
  }
  glutPostRedisplay();
  // The display rate is the frames' rate at most (60 Hz from the server); a short sleep keeps the
  // loop from spinning on a core the station's haptic node may need.
  std::this_thread::sleep_for(std::chrono::milliseconds(4));
}

// GLUT's fatal errors (no display, no visual): a clear message and our exit code.
[[noreturn]] __attribute__((format(printf, 1, 0))) void GlutError(const char* format,
                                                                  va_list args) {
  std::fprintf(stderr, "somasim-viewer: OpenGL/GLUT: ");
  std::vfprintf(stderr, format, args);
  std::fprintf(stderr, "\n");
  std::exit(kExitNoDisplay);
}

}  // namespace

int ViewerMain(int argc, char** argv) {
  app::SetLogProcess("viewer");
  ViewerOptions options;
  CLI::App cli{
      "somasim-viewer: shows a somasim session from Cyclone DDS (OpenGL/freeglut).\n"
      "Exit codes: 0 done, 2 usage, 4 I/O, 5 DDS, 6 no display, 7 timeout, 70 bug."};
  cli.set_version_flag("--version", std::string("somasim-viewer ") + SOMASIM_VERSION);
  cli.add_option("--session", options.session, "the session to join (its DDS partition)")
      ->capture_default_str();
  cli.add_option("--domain", options.domain, "DDS domain id")->check(CLI::Range(0, 232));
  cli.add_option("--dds-config", options.dds_config,
                 "Cyclone DDS XML configuration (deploy/cyclonedds-*.xml); default: "
                 "CYCLONEDDS_URI or Cyclone's defaults");
  cli.add_option("--screenshot", options.screenshot,
                 "write a PNG of the view after --after-frames frames, then exit");
  cli.add_option("--after-frames", options.after_frames,
                 "frames drawn with every organ's shape before the screenshot")
      ->check(CLI::Range(1, 1000000))
      ->capture_default_str();
  cli.add_option("--dump-positions", options.dump_positions,
                 "when stopping, write each shown organ's positions to DIR/<organ>.f32 and its "
                 "frame number to DIR/<organ>.frame");
  cli.add_option("--width", options.width, "window width [pixels]")
      ->check(CLI::Range(16, 8192))
      ->capture_default_str();
  cli.add_option("--height", options.height, "window height [pixels]")
      ->check(CLI::Range(16, 8192))
      ->capture_default_str();
  cli.add_option("--timeout", options.timeout,
                 "give up (exit 7) when no complete scene has been seen after this many "
                 "seconds; 0 waits for ever")
      ->check(CLI::Range(0.0, 86400.0));
  cli.add_flag("--observe", options.observe,
               "observe-only (instructors): never publishes tool commands; p pauses and r "
               "resumes the session");
  cli.add_flag("--list-sessions", options.list_sessions,
               "print the sessions running on the domain (one per line, after 2 s of "
               "discovery) and exit; needs no display");
  cli.add_option("--drive", options.drive,
                 "station: drive this tool with the keyboard from the start (else t starts "
                 "driving the first tool)");
  cli.add_option("--station", options.station,
                 "this station's name (a pseudonym) in tool and instructor commands")
      ->capture_default_str();
  cli.add_option("--frames", options.frames,
                 "stop after drawing this many frames of the complete scene (0: run until "
                 "stopped)")
      ->check(CLI::Range(0, 100000000));
  cli.add_option("--report", options.report,
                 "when stopping, write a JSON report here: frame time and frame latency "
                 "percentiles [ms], dropped samples");
  cli.add_option("--script", options.script,
                 "a viewer script: keys, resizes, screenshots, ... at stated frames or times "
                 "(docs/viewer.md)");
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli.exit(e) == 0 ? kExitOk : kExitUsage;
  }
  if (options.observe && !options.drive.empty()) {
    std::fprintf(stderr, "somasim-viewer: --drive and --observe exclude each other\n");
    return kExitUsage;
  }
  if (const std::string bad = dds::SessionNameError(options.session); !bad.empty()) {
    std::fprintf(stderr, "somasim-viewer: --session \"%s\" %s\n", options.session.c_str(),
                 bad.c_str());
    return kExitUsage;
  }
  app::InstallStopSignals();
  Viewer viewer;
  viewer.options = options;
  if (!options.script.empty()) {
    try {
      viewer.script = LoadViewerScript(options.script);
    } catch (const ViewerScriptError& e) {
      std::fprintf(stderr, "somasim-viewer: --script %s\n", e.what());
      return kExitUsage;
    }
  }
  try {
    const std::string config = dds::ReadDdsConfig(options.dds_config);
    if (!config.empty()) viewer.domain = std::make_unique<dds::Domain>(options.domain, config);
    viewer.participant = std::make_unique<dds::Participant>(options.domain);
    viewer.topics = std::make_unique<dds::Topics>(*viewer.participant);
    viewer.receiver =
        std::make_unique<SceneReceiver>(*viewer.participant, *viewer.topics, options.session);
  } catch (const std::runtime_error& e) {
    std::fprintf(stderr, "somasim-viewer: DDS: %s\n", e.what());
    return kExitDds;
  }
  if (options.list_sessions) {
    try {
      for (const std::string& name :
           dds::RunningSessions(*viewer.participant, std::chrono::milliseconds(2000))) {
        std::printf("%s\n", name.c_str());
      }
    } catch (const std::runtime_error& e) {
      std::fprintf(stderr, "somasim-viewer: DDS: %s\n", e.what());
      return kExitDds;
    }
    return kExitOk;
  }
  const char* display = std::getenv("DISPLAY");
  if (display == nullptr || *display == '\0') {
    std::fprintf(stderr,
                 "somasim-viewer: no display (DISPLAY is unset); for off-screen rendering run "
                 "it under Xvfb, e.g. xvfb-run -s '-screen 0 1280x1024x24' somasim-viewer ...\n");
    return kExitNoDisplay;
  }
  g_viewer = &viewer;
  Log(LogLevel::kInfo, "joining", {{"session", options.session}, {"domain", options.domain}});
  // GLUT sees only the program's name: the options above are ours.
  int glut_argc = 1;
  char* glut_argv[] = {argv[0], nullptr};
  glutInitErrorFunc(GlutError);
  glutInit(&glut_argc, glut_argv);
  glutInitDisplayMode(GLUT_RGB | GLUT_DOUBLE | GLUT_DEPTH);
  glutInitWindowSize(options.width, options.height);
  glutSetOption(GLUT_ACTION_ON_WINDOW_CLOSE, GLUT_ACTION_GLUTMAINLOOP_RETURNS);
  viewer.width = options.width;
  viewer.height = options.height;
  CreateViewerWindow(viewer);
  glutMainLoop();
  // The window was closed (or Finish left the loop): stop as on a signal.
  if (!viewer.finished) Finish(kExitOk);
  viewer.view.reset();
  if (glutGetWindow() == viewer.window) glutDestroyWindow(viewer.window);
  glutExit();  // frees GLUT's state and the GL context
  const ReceiverCounters& c = viewer.receiver->counters();
  Log(LogLevel::kInfo, "stopped",
      {{"frames_drawn_with_scene", viewer.frames_with_scene},
       {"bad_frames", c.bad_frames},
       {"bad_topologies", c.bad_topologies},
       {"wrong_format_version", c.wrong_format_version},
       {"frames_waiting_for_topology", c.frames_waiting_for_topology},
       {"server_restarts", c.server_restarts}});
  g_viewer = nullptr;
  return viewer.exit_code;
}

}  // namespace somasim::viewer
