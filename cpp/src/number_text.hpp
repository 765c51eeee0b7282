// Private: numbers in error messages. Not installed.
#pragma once

#include <cstdio>
#include <string>

namespace terracube::detail {

/// A double as printf's %g writes it (0, 0.05, 1e-320, inf, nan). std::to_string writes six fixed
/// decimals, so an edge of 1e-320 m would read "0.000000" in the message that rejects it.
inline std::string number_text(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%g", value);
  return text;
}

}  // namespace terracube::detail
