// Private: run-time CPU dispatch of the kernels compiled twice (baseline x86-64 and AVX2).
#pragma once

namespace terracube::detail {

/// Whether the AVX2 builds of the kernels may run: the CPU has AVX2 and TERRACUBE_DISABLE_AVX2
/// is not set. With that variable (any value) the baseline x86-64 kernels run instead: the tests
/// run once with it, so both builds of every kernel are checked on an AVX2 machine. Always false
/// off x86-64 or without GCC/Clang.
bool has_avx2();

}  // namespace terracube::detail
