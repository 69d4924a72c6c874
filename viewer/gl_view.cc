#include "viewer/gl_view.h"

#include <GL/freeglut.h>
#include <GL/gl.h>
#include <GL/glu.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

namespace somasim::viewer {

namespace {

// Organ colours (sRGB), by the organ's place in the session; the inner faces of cuts are pale.
constexpr float kPalette[][3] = {{0.72F, 0.25F, 0.22F},  // liver red
                                 {0.80F, 0.55F, 0.45F},
                                 {0.45F, 0.60F, 0.30F},
                                 {0.55F, 0.35F, 0.55F}};
constexpr float kInnerFace[3] = {0.95F, 0.85F, 0.55F};
constexpr float kBackground[3] = {0.10F, 0.11F, 0.13F};
constexpr float kMetal[3] = {0.70F, 0.72F, 0.78F};    // tools
constexpr float kContact[3] = {1.00F, 0.85F, 0.10F};  // contact point and normal
constexpr float kGrasp[3] = {0.20F, 0.85F, 0.30F};    // grasp anchor and grasped points
constexpr float kForce[3] = {1.00F, 0.50F, 0.10F};    // the rendered force
constexpr float kStone[3] = {0.85F, 0.78F, 0.55F};    // rigid bodies (calculi: pale sand)
constexpr double kForceScale = 0.01;                  // [m/N] the arrow's length per newton

void Colour(const float* c) {
  const GLfloat diffuse[4] = {c[0], c[1], c[2], 1.0F};
  const GLfloat ambient[4] = {0.25F * c[0], 0.25F * c[1], 0.25F * c[2], 1.0F};
  glMaterialfv(GL_FRONT_AND_BACK, GL_DIFFUSE, diffuse);
  glMaterialfv(GL_FRONT_AND_BACK, GL_AMBIENT, ambient);
}

}  // namespace

Eigen::Vector3d OrbitCamera::Eye() const {
  const Eigen::Vector3d dir(std::cos(pitch) * std::cos(yaw), std::cos(pitch) * std::sin(yaw),
                            std::sin(pitch));
  return target + distance * dir;
}

void OrbitCamera::Fit(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) {
  target = 0.5 * (lo + hi);
  const double radius = std::max(0.5 * (hi - lo).norm(), 1e-3);
  distance = radius / std::sin(0.5 * fov_deg * std::numbers::pi / 180.0) * 1.05;
  fitted = true;
}

void OrbitCamera::Orbit(double d_yaw, double d_pitch) {
  yaw += d_yaw;
  pitch = std::clamp(pitch + d_pitch, -1.5, 1.5);
}

void OrbitCamera::Zoom(double factor) {
  if (factor > 0.0 && std::isfinite(factor)) distance = std::clamp(distance * factor, 1e-3, 1e3);
}

void OrbitCamera::Pan(double dx, double dy) {
  const Eigen::Vector3d forward = (target - Eye()).normalized();
  Eigen::Vector3d right = forward.cross(Eigen::Vector3d::UnitZ());
  if (right.norm() < 1e-9) right = Eigen::Vector3d::UnitX();
  right.normalize();
  const Eigen::Vector3d up = right.cross(forward);
  target += distance * (dx * right + dy * up);
}

ViewPose ViewPose::Of(const OrbitCamera& camera) {
  ViewPose pose;
  pose.eye = camera.Eye();
  pose.center = camera.target;
  pose.up = Eigen::Vector3d::UnitZ();
  pose.fov_deg = camera.fov_deg;
  pose.near = std::max(camera.distance * 0.01, 1e-4);
  pose.far = camera.distance * 20.0;
  return pose;
}

ViewPose ViewPose::Laparoscope(const ToolScene& camera_tool) {
  const Eigen::Quaterniond q(camera_tool.orientation[0], camera_tool.orientation[1],
                             camera_tool.orientation[2], camera_tool.orientation[3]);
  const Eigen::Matrix3d r =
      q.norm() > 1e-9 ? q.normalized().toRotationMatrix() : Eigen::Matrix3d::Identity();
  ViewPose pose;
  pose.eye =
      Eigen::Vector3d(camera_tool.position[0], camera_tool.position[1], camera_tool.position[2]);
  pose.center = pose.eye - 0.1 * r.col(2);  // looking out of the tip, away from the handle
  pose.up = r.col(1);
  pose.fov_deg = 70.0;
  pose.near = 1e-3;
  pose.far = 2.0;
  return pose;
}

bool GlView::Bounds(const SceneReceiver& scene, Eigen::Vector3d* lo, Eigen::Vector3d* hi,
                    bool rest) {
  *lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::infinity());
  *hi = -*lo;
  bool any = false;
  for (const auto& [id, organ] : scene.organs()) {
    if (rest && organ.rest.size() != 3 * static_cast<size_t>(organ.num_nodes)) continue;
    const float* x = rest ? organ.rest.data() : organ.positions();
    for (uint32_t i = 0; i < organ.num_nodes; ++i) {
      const Eigen::Vector3d p =
          Eigen::Vector3f(x[3 * i], x[3 * i + 1], x[3 * i + 2]).cast<double>();
      *lo = lo->cwiseMin(p);
      *hi = hi->cwiseMax(p);
      any = true;
    }
  }
  return any;
}

void GlView::Draw(const SceneReceiver& scene, const ViewPose& pose, const Hud& hud, int width,
                  int height) {
  width = std::max(width, 1);
  height = std::max(height, 1);
  glViewport(0, 0, width, height);
  glClearColor(kBackground[0], kBackground[1], kBackground[2], 1.0F);
  glClear(GL_COLOR_BUFFER_BIT | GL_DEPTH_BUFFER_BIT);
  glMatrixMode(GL_PROJECTION);
  glLoadIdentity();
  gluPerspective(pose.fov_deg, static_cast<double>(width) / height, pose.near, pose.far);
  glMatrixMode(GL_MODELVIEW);
  glLoadIdentity();
  // A headlight: the light sits at the eye (set before the view transform).
  const GLfloat light_position[4] = {0.0F, 0.0F, 0.0F, 1.0F};
  const GLfloat white[4] = {0.9F, 0.9F, 0.9F, 1.0F};
  const GLfloat specular[4] = {0.25F, 0.25F, 0.25F, 1.0F};
  glLightfv(GL_LIGHT0, GL_POSITION, light_position);
  glLightfv(GL_LIGHT0, GL_DIFFUSE, white);
  glLightfv(GL_LIGHT0, GL_SPECULAR, specular);
  gluLookAt(pose.eye.x(), pose.eye.y(), pose.eye.z(), pose.center.x(), pose.center.y(),
            pose.center.z(), pose.up.x(), pose.up.y(), pose.up.z());
  glEnable(GL_DEPTH_TEST);
  glEnable(GL_LIGHTING);
  glEnable(GL_LIGHT0);
  glEnable(GL_NORMALIZE);
  glLightModeli(GL_LIGHT_MODEL_TWO_SIDE, GL_TRUE);
  glShadeModel(GL_SMOOTH);
  const GLfloat shine_specular[4] = {0.3F, 0.3F, 0.3F, 1.0F};
  glMaterialfv(GL_FRONT_AND_BACK, GL_SPECULAR, shine_specular);
  glMaterialf(GL_FRONT_AND_BACK, GL_SHININESS, 30.0F);
  glEnableClientState(GL_VERTEX_ARRAY);
  glEnableClientState(GL_NORMAL_ARRAY);
  size_t index = 0;
  for (const auto& [id, organ] : scene.organs()) {
    OrganBuffers& b = buffers_[id];
    if (b.topology_version != organ.topology_version || b.normals.size() != 3 * organ.num_nodes) {
      b.topology_version = organ.topology_version;
      b.outer.clear();
      b.inner.clear();
      for (size_t t = 0; 3 * t + 2 < organ.triangles.size(); ++t) {
        std::vector<uint32_t>& to = organ.inner_face[t] != 0 ? b.inner : b.outer;
        to.insert(to.end(), organ.triangles.begin() + static_cast<std::ptrdiff_t>(3 * t),
                  organ.triangles.begin() + static_cast<std::ptrdiff_t>(3 * t + 3));
      }
      b.normals.assign(3 * static_cast<size_t>(organ.num_nodes), 0.0F);
    }
    // Area-weighted vertex normals from the positions shown (the cross product's length is
    // twice the area).
    const float* x = organ.positions();
    std::fill(b.normals.begin(), b.normals.end(), 0.0F);
    for (size_t t = 0; 3 * t + 2 < organ.triangles.size(); ++t) {
      const uint32_t* v = organ.triangles.data() + 3 * t;
      const Eigen::Vector3f a(x[3 * v[0]], x[3 * v[0] + 1], x[3 * v[0] + 2]);
      const Eigen::Vector3f e1 = Eigen::Vector3f(x[3 * v[1]], x[3 * v[1] + 1], x[3 * v[1] + 2]) - a;
      const Eigen::Vector3f e2 = Eigen::Vector3f(x[3 * v[2]], x[3 * v[2] + 1], x[3 * v[2] + 2]) - a;
      const Eigen::Vector3f n = e1.cross(e2);
      for (int k = 0; k < 3; ++k) {
        float* out = b.normals.data() + 3 * static_cast<size_t>(v[k]);
        out[0] += n.x();
        out[1] += n.y();
        out[2] += n.z();
      }
    }
    glVertexPointer(3, GL_FLOAT, 0, x);
    glNormalPointer(GL_FLOAT, 0, b.normals.data());
    Colour(kPalette[index % std::size(kPalette)]);
    if (!b.outer.empty()) {
      glDrawElements(GL_TRIANGLES, static_cast<GLsizei>(b.outer.size()), GL_UNSIGNED_INT,
                     b.outer.data());
    }
    if (!b.inner.empty()) {
      Colour(kInnerFace);
      glDrawElements(GL_TRIANGLES, static_cast<GLsizei>(b.inner.size()), GL_UNSIGNED_INT,
                     b.inner.data());
    }
    ++index;
  }
  glDisableClientState(GL_NORMAL_ARRAY);
  glDisableClientState(GL_VERTEX_ARRAY);
  DrawTools(scene);
  // The heads-up display in pixel coordinates.
  glDisable(GL_LIGHTING);
  glDisable(GL_DEPTH_TEST);
  glMatrixMode(GL_PROJECTION);
  glLoadIdentity();
  gluOrtho2D(0.0, width, 0.0, height);
  glMatrixMode(GL_MODELVIEW);
  glLoadIdentity();
  if (hud.server_gone) {  // dim the last image and say so
    glEnable(GL_BLEND);
    glBlendFunc(GL_SRC_ALPHA, GL_ONE_MINUS_SRC_ALPHA);
    glColor4f(0.0F, 0.0F, 0.0F, 0.6F);
    glRectf(0.0F, 0.0F, static_cast<float>(width), static_cast<float>(height));
    glDisable(GL_BLEND);
    glColor3f(1.0F, 0.35F, 0.3F);
    glRasterPos2i(width / 2 - 120, height / 2);
    glutBitmapString(GLUT_BITMAP_HELVETICA_18,
                     reinterpret_cast<const unsigned char*>("SERVER GONE: no heartbeat"));
  }
  glColor3f(0.9F, 0.9F, 0.9F);
  int y = height - 18;
  for (const std::string& line : hud.lines) {
    glRasterPos2i(8, y);
    glutBitmapString(GLUT_BITMAP_8_BY_13, reinterpret_cast<const unsigned char*>(line.c_str()));
    y -= 15;
  }
}

void GlView::DrawTools(const SceneReceiver& scene) {
  if (quadric_ == nullptr) quadric_ = gluNewQuadric();
  GLUquadric* q = quadric_;
  const auto sphere = [q](const double* at, double radius, const float* colour) {
    Colour(colour);
    glPushMatrix();
    glTranslated(at[0], at[1], at[2]);
    gluSphere(q, radius, 16, 12);
    glPopMatrix();
  };
  for (const auto& [id, body] : scene.rigid_bodies()) {
    sphere(body.position, body.radius, body.grasped ? kGrasp : kStone);
  }
  for (const auto& [id, tool] : scene.tools()) {
    if (!tool.has_pose || tool.kind == "camera") continue;
    // The tool frame: the tip at the origin, the shaft along +z (column-major for GL).
    const Eigen::Quaterniond rotation(tool.orientation[0], tool.orientation[1], tool.orientation[2],
                                      tool.orientation[3]);
    const Eigen::Matrix3d r = rotation.norm() > 1e-9 ? rotation.normalized().toRotationMatrix()
                                                     : Eigen::Matrix3d::Identity();
    double frame[16] = {};
    for (int c = 0; c < 3; ++c) {
      for (int k = 0; k < 3; ++k) frame[4 * c + k] = r(k, c);
      frame[12 + c] = tool.position[c];
    }
    frame[15] = 1.0;
    const double radius = std::max(tool.shaft_radius, 0.001);  // [m] at least 1 mm on screen
    const double length = tool.shaft_length > 0.0 ? tool.shaft_length : 0.1;
    glPushMatrix();
    glMultMatrixd(frame);
    Colour(kMetal);
    gluCylinder(q, radius, radius, length, 16, 1);
    gluSphere(q, radius * 1.2, 16, 12);
    glPopMatrix();
    if (tool.in_contact) {
      sphere(tool.contact_point, radius * 1.1, kContact);
      // The contact normal, 1 cm, as a line.
      glDisable(GL_LIGHTING);
      glColor3fv(kContact);
      glBegin(GL_LINES);
      glVertex3dv(tool.contact_point);
      glVertex3d(tool.contact_point[0] + 0.01 * tool.normal[0],
                 tool.contact_point[1] + 0.01 * tool.normal[1],
                 tool.contact_point[2] + 0.01 * tool.normal[2]);
      glEnd();
      glEnable(GL_LIGHTING);
    }
    if (tool.grasping) sphere(tool.grasp_anchor, radius * 1.1, kGrasp);
    // The grasped points and the force are drawn over everything: a force pulling the tool
    // into the organ would otherwise be hidden inside it.
    glDisable(GL_LIGHTING);
    glDisable(GL_DEPTH_TEST);
    const auto held = scene.organs().find(tool.held_organ);
    if (!tool.held_nodes.empty() && held != scene.organs().end()) {
      const float* x = held->second.positions();
      glPointSize(5.0F);
      glColor3fv(kGrasp);
      glBegin(GL_POINTS);
      for (const uint32_t node : tool.held_nodes) {
        if (node < held->second.num_nodes) glVertex3fv(x + 3 * static_cast<size_t>(node));
      }
      glEnd();
    }
    // The force at the tip: a line and an arrowhead (two strokes in the plane of the view's
    // up direction, which is enough to tell its sense).
    const Eigen::Vector3d f = tool.Force();
    if (f.norm() > 1e-3) {
      const Eigen::Vector3d a(tool.position[0], tool.position[1], tool.position[2]);
      const Eigen::Vector3d b = a + kForceScale * f;
      const Eigen::Vector3d dir = f.normalized();
      Eigen::Vector3d side = dir.cross(Eigen::Vector3d::UnitZ());
      if (side.norm() < 1e-6) side = dir.cross(Eigen::Vector3d::UnitX());
      side = 0.25 * (b - a).norm() * side.normalized();
      const Eigen::Vector3d back = b - 0.3 * (b - a);
      glLineWidth(3.0F);
      glColor3fv(kForce);
      glBegin(GL_LINES);
      glVertex3dv(a.data());
      glVertex3dv(b.data());
      const Eigen::Vector3d h1 = back + side, h2 = back - side;
      glVertex3dv(b.data());
      glVertex3dv(h1.data());
      glVertex3dv(b.data());
      glVertex3dv(h2.data());
      glEnd();
      glLineWidth(1.0F);
    }
    glEnable(GL_DEPTH_TEST);
    glEnable(GL_LIGHTING);
  }
}

GlView::~GlView() {
  if (quadric_ != nullptr) gluDeleteQuadric(quadric_);
}

render::Image GlView::ReadPixels(int width, int height) {
  render::Image image;
  image.width = width;
  image.height = height;
  image.rgb.resize(3 * static_cast<size_t>(width) * static_cast<size_t>(height));
  glPixelStorei(GL_PACK_ALIGNMENT, 1);
  glReadBuffer(GL_BACK);
  std::vector<uint8_t> bottom_up(image.rgb.size());
  glReadPixels(0, 0, width, height, GL_RGB, GL_UNSIGNED_BYTE, bottom_up.data());
  const size_t row = 3 * static_cast<size_t>(width);
  for (int r = 0; r < height; ++r) {
    std::copy_n(bottom_up.data() + row * static_cast<size_t>(height - 1 - r), row,
                image.rgb.data() + row * static_cast<size_t>(r));
  }
  return image;
}

}  // namespace somasim::viewer
