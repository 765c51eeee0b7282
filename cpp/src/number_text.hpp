// Private: numbers in error messages, and the range checks that quote them. Not installed.
#pragma once

#include <cmath>
#include <cstdio>
#include <stdexcept>
#include <string>

namespace terracube::detail {

/// A double as printf's %g writes it (0, 0.05, 1e-320, inf, nan). std::to_string writes six fixed
/// decimals, so an edge of 1e-320 m would read "0.000000" in the message that rejects it.
inline std::string number_text(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%g", value);
  return text;
}

/// Throws std::invalid_argument "<name> must be a finite value >= 0, got <value>" unless it is.
inline void check_non_negative(double value, const char* name) {
  if (!(value >= 0.0) || !std::isfinite(value)) {
    throw std::invalid_argument(std::string(name) + " must be a finite value >= 0, got " + number_text(value));
  }
}

/// Throws std::invalid_argument "<name> must be a positive finite value, got <value>" unless it is.
inline void check_positive(double value, const char* name) {
  if (!(value > 0.0) || !std::isfinite(value)) {
    throw std::invalid_argument(std::string(name) + " must be a positive finite value, got " + number_text(value));
  }
}

}  // namespace terracube::detail
