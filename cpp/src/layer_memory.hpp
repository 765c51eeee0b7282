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

/// A rows x cols layer, not initialised, advised as above.
Layer uninitialised_layer(Eigen::Index rows, Eigen::Index cols);

/// A rows x cols layer filled with `value`, advised as above.
Layer filled_layer(Eigen::Index rows, Eigen::Index cols, float value);

}  // namespace terracube::detail
