// The geometry of a cut (SPEC §5.3, seed 003 §3): the surface a blade sweeps between two poses,
// and which mesh edges cross it. The particle models remove the springs or constraints whose
// current segment crosses the sweep (TissueModel::Cut). Pure.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace somasim::models {

// The quadrilateral a blade segment PQ sweeps from pose 0 (p0, q0) to pose 1 (p1, q1) [m], split
// into the triangles (p0, q0, q1) and (p0, q1, p1). A blade that did not move sweeps nothing.
struct SweptQuad {
  Eigen::Vector3d p0 = Eigen::Vector3d::Zero();
  Eigen::Vector3d q0 = Eigen::Vector3d::Zero();
  Eigen::Vector3d p1 = Eigen::Vector3d::Zero();
  Eigen::Vector3d q1 = Eigen::Vector3d::Zero();
  bool AllFinite() const {
    return p0.allFinite() && q0.allFinite() && p1.allFinite() && q1.allFinite();
  }
};

// Whether the segment ab passes through the triangle (t0, t1, t2): a proper crossing, an end on
// the triangle counts, a segment lying in the triangle's plane does not (it separates nothing).
bool SegmentCrossesTriangle(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                            const Eigen::Vector3d& t0, const Eigen::Vector3d& t1,
                            const Eigen::Vector3d& t2);

// Whether the segment ab crosses the swept quad (either of its triangles).
bool SegmentCrossesSweep(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                         const SweptQuad& sweep);

}  // namespace somasim::models
