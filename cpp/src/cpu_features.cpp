#include "cpu_features.hpp"

#include <cstdlib>

namespace terracube::detail {

bool has_avx2() {
#if defined(__x86_64__) && defined(__GNUC__)
  static const bool supported = __builtin_cpu_supports("avx2") && std::getenv("TERRACUBE_DISABLE_AVX2") == nullptr;
  return supported;
#else
  return false;
#endif
}

}  // namespace terracube::detail
