// Drawing a session with OpenGL (fixed-function, GL 1.5 vertex arrays: what Mesa's software
// renderer under Xvfb and any station GPU both run): each organ's surface from its current
// positions with smooth shading (per-vertex normals from those positions, area-weighted), a
// colour per organ, the inner faces of cuts in a distinct colour; an orbit/pan/zoom camera; a
// heads-up display. Needs a current GL context (GLUT's window); no DDS, no physics.
#pragma once

#include <GL/glu.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <map>
#include <string>
#include <vector>

#include "common/render/image.h"
#include "viewer/scene_receiver.h"

namespace somasim::viewer {

// An orbit camera around `target`: yaw about the world z axis (up), pitch above the horizon.
struct OrbitCamera {
  Eigen::Vector3d target = Eigen::Vector3d::Zero();  // [m]
  double distance = 0.5;                             // [m], > 0
  double yaw = 0.6;                                  // [rad]
  double pitch = 0.5;                                // [rad], within ±1.5
  double fov_deg = 40.0;                             // vertical field of view
  bool fitted = false;                               // set by Fit

  Eigen::Vector3d Eye() const;
  // Frames the box [lo, hi] [m]: target at its centre, distance so that it fills the view.
  void Fit(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi);
  void Orbit(double d_yaw, double d_pitch);
  void Zoom(double factor);        // distance × factor (factor > 0)
  void Pan(double dx, double dy);  // in view-plane units of the distance
};

// Where a frame is drawn from: the orbit camera's view, or the laparoscope's (a camera tool's
// pose: the eye at its tip looking down its shaft, -z of the tool frame, with the frame's +y
// up, 70° wide).
struct ViewPose {
  Eigen::Vector3d eye = Eigen::Vector3d::UnitX();  // [m]
  Eigen::Vector3d center = Eigen::Vector3d::Zero();
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  double fov_deg = 40.0;  // vertical
  double near = 1e-3;     // [m] clip planes
  double far = 10.0;

  static ViewPose Of(const OrbitCamera& camera);
  static ViewPose Laparoscope(const ToolScene& camera_tool);
};

// The heads-up display's lines, drawn top left.
struct Hud {
  std::vector<std::string> lines;
  bool server_gone = false;  // drawn as a banner over a dimmed scene, not as a frozen image
};

class GlView {
 public:
  GlView() = default;
  ~GlView();
  GlView(const GlView&) = delete;
  GlView& operator=(const GlView&) = delete;
  // The box of every organ's shown positions (or, with `rest`, their rest positions, the same
  // for every viewer whenever it joins); false when there is none.
  static bool Bounds(const SceneReceiver& scene, Eigen::Vector3d* lo, Eigen::Vector3d* hi,
                     bool rest = false);
  // Draws the scene into the current context's back buffer, width × height pixels.
  void Draw(const SceneReceiver& scene, const ViewPose& pose, const Hud& hud, int width,
            int height);
  // The back buffer's pixels (after Draw, before the swap), top row first.
  static render::Image ReadPixels(int width, int height);

 private:
  struct OrganBuffers {
    uint32_t topology_version = 0;
    std::vector<uint32_t> outer, inner;  // triangle corner indices by face kind
    std::vector<float> normals;          // 3 × num_nodes
  };
  // The rigid bodies (pale sand spheres, green while grasped); each tool with a pose: its shaft
  // and tip (metal), its contact point and normal (yellow), its
  // grasp anchor (green sphere) and grasped points (green dots), and the force its local force
  // model gives at the tip (an orange arrow from the tip, 1 cm per newton).
  void DrawTools(const SceneReceiver& scene);

  std::map<std::string, OrganBuffers> buffers_;
  GLUquadric* quadric_ = nullptr;  // made on the first draw (needs the GL context)
};

}  // namespace somasim::viewer
