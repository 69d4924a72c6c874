// The parameter checks every layer writes (SPEC §7: bad input is refused by name): whether a
// value is a finite number above (or at least) zero, NaN-safe, in one place instead of
// `!std::isfinite(x) || x <= 0` by hand in every model, tool and reader. Header only, pure.
#pragma once

#include <limits>
#include <stdexcept>
#include <string>
#include <string_view>

namespace somasim::checks {

// x is finite and > 0 (false for NaN and ±inf).
constexpr bool FinitePositive(double x) {
  return x > 0.0 && x <= std::numeric_limits<double>::max();
}
// x is finite and >= 0 (false for NaN and ±inf).
constexpr bool FiniteNonNegative(double x) {
  return x >= 0.0 && x <= std::numeric_limits<double>::max();
}

// Throws std::invalid_argument("<what>: <name> must be finite and > 0[ <unit>]") unless
// FinitePositive(value).
inline void RequireFinitePositive(std::string_view what, std::string_view name, double value,
                                  std::string_view unit = {}) {
  if (FinitePositive(value)) return;
  std::string message = std::string(what) + ": " + std::string(name) + " must be finite and > 0";
  if (!unit.empty()) message += " " + std::string(unit);
  throw std::invalid_argument(message);
}

// Throws std::invalid_argument("<what>: <name> must be finite and >= 0[ <unit>]") unless
// FiniteNonNegative(value).
inline void RequireFiniteNonNegative(std::string_view what, std::string_view name, double value,
                                     std::string_view unit = {}) {
  if (FiniteNonNegative(value)) return;
  std::string message = std::string(what) + ": " + std::string(name) + " must be finite and >= 0";
  if (!unit.empty()) message += " " + std::string(unit);
  throw std::invalid_argument(message);
}

}  // namespace somasim::checks
