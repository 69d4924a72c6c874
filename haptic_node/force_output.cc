#include "haptic_node/force_output.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace somasim::haptic {

namespace {

bool Finite(const Eigen::Vector3d& v) { return v.allFinite(); }

// `f` scaled down to at most `limit` in magnitude, keeping its direction.
Eigen::Vector3d Clamp(const Eigen::Vector3d& f, double limit, bool* clamped) {
  const double n = f.norm();
  *clamped = n > limit;
  return *clamped ? (limit / n) * f : f;
}

}  // namespace

ForceOutput::ForceOutput(const ForceOutputSettings& settings) : s_(settings) {
  const std::pair<const char*, double> positive[] = {{"dt", s_.dt},
                                                     {"max_force", s_.max_force},
                                                     {"max_step", s_.max_step},
                                                     {"fresh", s_.fresh},
                                                     {"ramp", s_.ramp},
                                                     {"engage_below", s_.engage_below},
                                                     {"engage_ramp", s_.engage_ramp},
                                                     {"passivity_epsilon", s_.passivity_epsilon},
                                                     {"max_damping", s_.max_damping}};
  for (const auto& [name, value] : positive) {
    if (!std::isfinite(value) || value <= 0.0) {
      throw std::invalid_argument(std::string("force output: ") + name + " must be finite and > 0");
    }
  }
  if (s_.engage_ticks < 1) throw std::invalid_argument("force output: engage_ticks must be >= 1");
}

void ForceOutput::Latch(const char* reason) {
  if (!fault_) ++counters_.faults;
  fault_ = true;
  fault_reason_ = reason;
  Disengage();
}

void ForceOutput::Disengage() {
  engaged_ = false;
  quiet_ticks_ = 0;
  authority_ = 0.0;
  energy_ = 0.0;
  last_ = Eigen::Vector3d::Zero();
}

void ForceOutput::ClearFault() {
  fault_ = false;
  fault_reason_ = "";
  Disengage();
}

Eigen::Vector3d ForceOutput::Tick(const ForceInput& in) {
  ++counters_.ticks;
  last_damping_ = 0.0;
  // 1. Faults latch; 2. the emergency stop zeroes at once.
  if (!in.device_ok) Latch("the arm is not usable (heartbeat, header or state)");
  if (!Finite(in.desired) || !std::isfinite(in.model_age)) Latch("a non-finite desired force");
  if (!Finite(in.velocity)) Latch("a non-finite device velocity");
  if (fault_ || in.emergency_stop) {
    if (in.emergency_stop) Disengage();
    last_ = Eigen::Vector3d::Zero();
    return last_;
  }
  // 3. Staleness.
  double scale = 0.0;
  if (in.model_age >= 0.0) {
    if (in.model_age <= s_.fresh) {
      scale = 1.0;
    } else {
      // Exactly zero from fresh + ramp on (1e-9 absorbs the rounding of a sum of ages).
      const double left = 1.0 - (in.model_age - s_.fresh) / s_.ramp;
      scale = left > 1e-9 ? left : 0.0;
    }
  }
  if (scale < 1.0 && engaged_) ++counters_.stale_ticks;
  Eigen::Vector3d target = scale * in.desired;
  // 4. Engagement.
  if (!engaged_) {
    quiet_ticks_ = target.norm() < s_.engage_below ? quiet_ticks_ + 1 : 0;
    if (quiet_ticks_ >= s_.engage_ticks) {
      engaged_ = true;
      authority_ = 0.0;
      energy_ = 0.0;  // a new coupling: the observer's balance starts again
    }
  }
  // Nothing is rendered while disengaged or once the stale ramp has reached zero (none yet, or
  // stale to zero): not the model's force and not the passivity controller's damping, whatever
  // the energy balance (SPEC §7: zero 60 ms after the last good model). The authority rests at
  // zero, so force comes back gradually when models resume (a server paused and continued: no
  // jump), and the balance restarts with it.
  if (!engaged_ || scale == 0.0) {
    authority_ = 0.0;
    energy_ = 0.0;
    last_ = Eigen::Vector3d::Zero();
    return last_;
  }
  authority_ = std::min(1.0, authority_ + s_.dt / s_.engage_ramp);
  target *= authority_;
  // 5. The arm's limit (and, from a stale model, never more than last tick's: the hand may push
  // deeper into a model that no longer knows where the tissue is); 6. the change per tick.
  const double limit = scale < 1.0 ? std::min(s_.max_force, last_.norm()) : s_.max_force;
  bool clamped = false;
  target = Clamp(target, s_.max_force, &clamped);
  if (scale < 1.0) {
    bool held = false;
    target = Clamp(target, limit, &held);
  }
  const Eigen::Vector3d step = target - last_;
  bool limited = false;
  Eigen::Vector3d out = last_ + Clamp(step, s_.max_step, &limited);
  // 7. The passivity observer and controller.
  const double v2 = in.velocity.squaredNorm();
  const double w = energy_ - out.dot(in.velocity) * s_.dt;
  if (w < -s_.passivity_epsilon && v2 > 1e-12) {
    last_damping_ = std::min(s_.max_damping, (-s_.passivity_epsilon - w) / (v2 * s_.dt));
    out -= last_damping_ * in.velocity;
    ++counters_.damped_ticks;
    // The damping too stays within the arm's limit and, while stale, within last tick's force.
    bool again = false;
    out = Clamp(out, limit, &again);
    clamped = clamped || (again && limit == s_.max_force);
  }
  energy_ -= out.dot(in.velocity) * s_.dt;
  counters_.clamped_ticks += clamped ? 1 : 0;
  counters_.rate_limited_ticks += limited ? 1 : 0;
  if (!Finite(out)) {  // cannot happen with finite inputs; the last guard all the same
    Latch("a non-finite output force");
    out = Eigen::Vector3d::Zero();
  }
  last_ = out;
  return out;
}

}  // namespace somasim::haptic
