// Private: allocation of map layers. Not installed.
#pragma once

#include <cstddef>

#include "terracube/elevation_map.hpp"

namespace terracube::detail {

/// Asks the kernel to back [data, data + bytes) with transparent huge pages where it covers whole
/// 2 MB pages, before the memory is first touched. A fresh layer of a large map otherwise costs a
/// page fault per 4 kB: about 2.5 us each on the VMs this project is measured on, 40 ms for the
/// ten 6 MB layers of a 1,561 x 1,007-cell DEM. A hint only (Linux, THP "always" or "madvise");
/// elsewhere, or when refused, nothing changes.
void advise_huge_pages(void* data, std::size_t bytes);

/// A rows x cols layer, not initialised: a buffer of the same size that a dropped map left to
/// this thread when there is one (no page is touched for the first time), else a fresh one,
/// advised as above.
Layer uninitialised_layer(Eigen::Index rows, Eigen::Index cols);

/// Keeps a layer's buffer for uninitialised_layer on this thread: up to 64 MB of the most
/// recently dropped layers (the oldest go first). A fresh 320 kB layer costs 80 page faults on
/// first touch, about 0.2-0.6 ms on the VMs this project is measured on: a loop that builds and
/// drops a map per scan would otherwise pay them for every layer of every map.
void recycle_layer(Layer&& layer);

/// A rows x cols layer filled with `value`, advised as above.
Layer filled_layer(Eigen::Index rows, Eigen::Index cols, float value);

}  // namespace terracube::detail
