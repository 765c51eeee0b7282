"""build_elevation_map, ElevationMap and dem_without_overhangs against an independent numpy reference.

The reference below is written from the documented rules only (elevation_map.hpp): cell
i = floor((x - origin_x) / res), j likewise along y, points outside the map ignored; per cell the
point count, the lowest and highest elevation, the mean and the population std-dev, and a
discontinuity flag set when the sorted elevations contain a gap strictly longer than the
threshold. It works in float64 (two-pass variance) and shares no code with the C++ library.
Layers are float32: count/min/max/discontinuity are compared exactly (min and max against the
float32 cast of the reference), mean and std-dev with rtol 1e-6 / atol 1e-5.
"""

from __future__ import annotations

import gc
import sys
from dataclasses import dataclass

import numpy as np
import pytest
import terracube as tc

LAYERS = ("count", "min", "max", "mean", "std_dev", "discontinuity")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------
# The independent reference.
# --------------------------------------------------------------------------------------------


@dataclass
class ReferenceLayers:
    count: np.ndarray  # (nx, ny) int64
    min: np.ndarray  # (nx, ny) float64, NaN where empty
    max: np.ndarray
    mean: np.ndarray
    std_dev: np.ndarray
    discontinuity: np.ndarray  # (nx, ny) float64 0/1, NaN where empty


def reference_layers(points, resolution, origin, size, discontinuity=1.0, use=None) -> ReferenceLayers:
    """The documented layers, vectorised numpy in float64."""
    xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if use is not None:
        xyz = xyz[np.asarray(use, dtype=bool)]
    nx, ny = int(size[0]), int(size[1])
    i = np.floor((xyz[:, 0] - origin[0]) / resolution)
    j = np.floor((xyz[:, 1] - origin[1]) / resolution)
    inside = (i >= 0) & (j >= 0) & (i < nx) & (j < ny)
    cell = i[inside].astype(np.int64) * ny + j[inside].astype(np.int64)
    z = xyz[inside, 2]
    cells = nx * ny

    count = np.bincount(cell, minlength=cells)
    occupied = count > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(cell, weights=z, minlength=cells) / count
        variance = np.bincount(cell, weights=(z - mean[cell]) ** 2, minlength=cells) / count

    order = np.lexsort((z, cell))
    sorted_cell = cell[order]
    sorted_z = z[order]
    lowest = np.full(cells, np.nan)
    highest = np.full(cells, np.nan)
    if sorted_cell.size:
        first = np.r_[True, sorted_cell[1:] != sorted_cell[:-1]]
        last = np.r_[sorted_cell[1:] != sorted_cell[:-1], True]
        lowest[sorted_cell[first]] = sorted_z[first]
        highest[sorted_cell[last]] = sorted_z[last]
    gap = (np.diff(sorted_z) > discontinuity) & (sorted_cell[1:] == sorted_cell[:-1])
    flag = np.where(occupied, 0.0, np.nan)
    flag[sorted_cell[1:][gap]] = 1.0

    def grid(values):
        return np.where(occupied, values, np.nan).reshape(nx, ny)

    return ReferenceLayers(
        count=count.reshape(nx, ny),
        min=grid(lowest),
        max=grid(highest),
        mean=grid(mean),
        std_dev=grid(np.sqrt(variance)),
        discontinuity=flag.reshape(nx, ny),
    )


def reference_auto_extent(points, resolution):
    """Bounding box in x and y snapped outwards to whole cells: (origin, size)."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    origin = np.floor(xy.min(axis=0) / resolution) * resolution
    size = (np.floor((xy.max(axis=0) - origin) / resolution) + 1).astype(np.int64)
    return origin, size


def assert_layers_match(elevation_map: tc.ElevationMap, reference: ReferenceLayers) -> None:
    size = tuple(elevation_map.geometry.size)
    assert elevation_map.layers[: len(LAYERS)] == list(LAYERS)
    for name in LAYERS:
        layer = elevation_map[name]
        assert layer.dtype == np.float32 and layer.shape == size, name
    np.testing.assert_array_equal(elevation_map["count"], reference.count.astype(np.float32))
    empty = reference.count == 0
    for name in ("min", "max", "mean", "std_dev", "discontinuity"):
        np.testing.assert_array_equal(np.isnan(elevation_map[name]), empty, err_msg=f"NaN cells of {name}")
    np.testing.assert_array_equal(elevation_map["min"], reference.min.astype(np.float32))
    np.testing.assert_array_equal(elevation_map["max"], reference.max.astype(np.float32))
    np.testing.assert_allclose(elevation_map["mean"], reference.mean, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(elevation_map["std_dev"], reference.std_dev, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(elevation_map["discontinuity"], reference.discontinuity.astype(np.float32))


def random_cloud(seed: int, n: int = 20_000) -> np.ndarray:
    """(N, 3) float64: ground in x [-3, 5), y [-2, 4) with an empty disc, a few raised
    patches (so some cells have a gap in z), and points outside any fixed extent used below."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform((-3.0, -2.0), (5.0, 4.0), (n, 2))
    xy = xy[np.hypot(xy[:, 0] - 1.0, xy[:, 1] - 1.0) > 0.6]  # an empty hole
    z = 0.2 * np.sin(xy[:, 0]) + rng.normal(0.0, 0.05, len(xy))
    raised = rng.random(len(xy)) < 0.08
    z[raised] += rng.uniform(0.2, 1.5, raised.sum())
    return np.column_stack([xy, z])


def layout(xyz: np.ndarray, kind: str) -> np.ndarray:
    """The same points as a C array, an xyzi[:, :3] view, a Fortran array or reversed rows."""
    if kind == "c":
        return np.ascontiguousarray(xyz)
    if kind == "xyzi":
        xyzi = np.column_stack([xyz, np.zeros(len(xyz), dtype=xyz.dtype)])
        view = xyzi[:, :3]
        assert not view.flags.c_contiguous
        return view
    if kind == "fortran":
        return np.asfortranarray(xyz)
    if kind == "reversed":
        return xyz[::-1]
    raise AssertionError(kind)


# --------------------------------------------------------------------------------------------
# Layers against the reference.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("kind", ["c", "xyzi", "fortran", "reversed"])
@pytest.mark.parametrize("seed", [0, 1])
def test_random_cloud_layers_match_numpy_reference_on_a_fixed_extent(seed, kind, dtype):
    cloud = layout(random_cloud(seed).astype(dtype), kind)
    origin, size, resolution, gap = (-2.0, -1.0), (50, 40), 0.1, 0.3
    elevation_map = tc.build_elevation_map(cloud, resolution, origin=origin, size=size, discontinuity=gap)
    reference = reference_layers(cloud, resolution, origin, size, gap)
    assert_layers_match(elevation_map, reference)
    # The scene exercises empty cells, points outside the map, and both discontinuity outcomes.
    assert (reference.count == 0).any()
    assert reference.count.sum() < len(cloud)
    assert {0.0, 1.0} <= set(np.unique(reference.discontinuity[reference.count > 0]).tolist())


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_random_cloud_layers_match_numpy_reference_on_the_auto_extent(dtype):
    cloud = random_cloud(2).astype(dtype)
    resolution = 0.25
    elevation_map = tc.build_elevation_map(cloud, resolution)
    origin, size = reference_auto_extent(cloud, resolution)
    np.testing.assert_array_equal(elevation_map.geometry.origin, origin)
    np.testing.assert_array_equal(elevation_map.geometry.size, size)
    reference = reference_layers(cloud, resolution, origin, size)
    assert_layers_match(elevation_map, reference)
    assert reference.count.sum() == len(cloud)


def test_use_selects_the_points_that_take_part():
    cloud = random_cloud(3)
    use = np.random.default_rng(3).random(len(cloud)) < 0.4
    origin, size = (-3.0, -2.0), (80, 60)
    elevation_map = tc.build_elevation_map(cloud, 0.1, use=use, origin=origin, size=size, discontinuity=0.3)
    assert_layers_match(elevation_map, reference_layers(cloud, 0.1, origin, size, 0.3, use=use))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_out_refills_the_map_in_place_with_the_fresh_builds_layers(dtype):
    origin, size, resolution, gap = (-2.0, -1.0), (50, 40), 0.1, 0.3
    elevation_map = tc.build_elevation_map(
        random_cloud(5), resolution, origin=origin, size=size, discontinuity=gap
    )
    tc.classify_terrain(elevation_map, sensor_height=1.0)
    views = {name: elevation_map[name] for name in elevation_map.layers}
    layers = elevation_map.layers
    for seed, use in ((6, None), (7, np.random.default_rng(7).random(18_000) < 0.5)):
        cloud = layout(random_cloud(seed, 18_000).astype(dtype), "xyzi")
        use = None if use is None else use[: len(cloud)]
        returned = tc.build_elevation_map(
            cloud, resolution, origin=origin, size=size, discontinuity=gap, use=use, out=elevation_map
        )
        assert returned is elevation_map
        assert elevation_map.layers == layers
        assert_layers_match(elevation_map, reference_layers(cloud, resolution, origin, size, gap, use=use))
        # Arrays taken before the refill share the buffers: they show the new values.
        for name in ("count", "mean", "discontinuity"):
            np.testing.assert_array_equal(views[name], elevation_map[name])
        # classify_terrain's layers hold no data until the map is classified again.
        for name in ("class", "relative_height", "ground"):
            assert np.isnan(views[name]).all(), name
        fresh = tc.build_elevation_map(
            cloud, resolution, origin=origin, size=size, discontinuity=gap, use=use
        )
        np.testing.assert_array_equal(
            tc.classify_terrain(elevation_map, sensor_height=1.0),
            tc.classify_terrain(fresh, sensor_height=1.0),
        )
        np.testing.assert_array_equal(views["class"], fresh["class"])


def test_out_of_another_size_raises_value_error_and_leaves_the_map_unchanged():
    cloud = random_cloud(8)
    elevation_map = tc.build_elevation_map(cloud, 0.1, origin=(-2.0, -1.0), size=(50, 40))
    before = {name: elevation_map[name].copy() for name in elevation_map.layers}
    with pytest.raises(
        ValueError, match="cannot refill a map of 50 x 40 cells with a build of 51 x 40 cells"
    ):
        tc.build_elevation_map(cloud, 0.1, origin=(-2.0, -1.0), size=(51, 40), out=elevation_map)
    with pytest.raises(ValueError, match="cannot refill"):
        tc.build_elevation_map(cloud, 0.1, out=elevation_map)  # the auto extent is another size
    with pytest.raises(ValueError, match="NaN or Inf"):
        tc.build_elevation_map(
            np.vstack([cloud, [np.nan, 0.0, 0.0]]), 0.1, origin=(-2.0, -1.0), size=(50, 40), out=elevation_map
        )
    with pytest.raises(TypeError, match="out must be an ElevationMap"):
        tc.build_elevation_map(cloud, 0.1, origin=(-2.0, -1.0), size=(50, 40), out=np.zeros((50, 40)))
    np.testing.assert_array_equal(elevation_map.geometry.size, (50, 40))
    for name, values in before.items():
        np.testing.assert_array_equal(elevation_map[name], values)
    # The same size at another origin moves the map.
    moved = tc.build_elevation_map(cloud, 0.1, origin=(-3.0, -2.0), size=(50, 40), out=elevation_map)
    np.testing.assert_array_equal(moved.geometry.origin, (-3.0, -2.0))
    assert_layers_match(moved, reference_layers(cloud, 0.1, (-3.0, -2.0), (50, 40)))


def test_large_absolute_heights_keep_a_small_std_dev_accurate():
    # UTM-like heights: 6.4e6 m plus centimetre noise. A naive sum-of-squares in float64 would
    # lose the variance entirely (6.4e6**2 = 4e13, the variance is 1e-4).
    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, 2.0, (20_000, 2))
    z = 6.4e6 + rng.normal(0.0, 0.01, len(xy))
    cloud = np.column_stack([xy, z])
    origin, size = (0.0, 0.0), (8, 8)
    elevation_map = tc.build_elevation_map(cloud, 0.25, origin=origin, size=size)
    reference = reference_layers(cloud, 0.25, origin, size)
    assert_layers_match(elevation_map, reference)
    np.testing.assert_allclose(elevation_map["std_dev"], reference.std_dev, rtol=1e-6, atol=0.0)
    assert np.all(elevation_map["std_dev"] > 0.005)


def test_kitti_frame0_layers_match_numpy_reference(shared_data):
    xyzi = shared_data.kitti_xyzi(0)
    xyz = xyzi[:, :3]  # strided float32 view
    origin, size = (-20.0, -10.0), (400, 200)
    elevation_map = tc.build_elevation_map(xyz, 0.1, origin=origin, size=size)
    reference = reference_layers(xyz, 0.1, origin, size)
    assert_layers_match(elevation_map, reference)
    assert 0 < reference.count.sum() < len(xyz)
    assert (reference.discontinuity == 1.0).sum() > 0 and (reference.discontinuity == 0.0).sum() > 0


def test_forest_plot_layers_match_numpy_reference_on_the_auto_extent(shared_data):
    # z is 49-69 m: per-cell variances are small next to z**2, which stresses the std-dev.
    with np.load(shared_data.path("forest_tls/TreeLS_pine_plot.npz")) as archive:
        xyz = archive["xyz"]
    assert xyz[:, 2].min() > 40.0
    resolution = 0.1
    elevation_map = tc.build_elevation_map(xyz, resolution)
    origin, size = reference_auto_extent(xyz, resolution)
    np.testing.assert_array_equal(elevation_map.geometry.origin, origin)
    np.testing.assert_array_equal(elevation_map.geometry.size, size)
    reference = reference_layers(xyz, resolution, origin, size)
    assert_layers_match(elevation_map, reference)
    assert reference.count.sum() == len(xyz)
    assert (reference.discontinuity == 1.0).sum() > 0


def test_discontinuity_needs_a_gap_strictly_longer_than_the_threshold():
    # Gaps of exactly 0.5 (exact in binary) do not count; 0.5 + 2**-20 does.
    cloud = np.array(
        [
            [0.5, 0.5, 0.0], [0.5, 0.5, 0.5], [0.5, 0.5, 1.0],  # cell (0, 0): gaps of exactly 0.5
            [1.5, 0.5, 0.0], [1.5, 0.5, 0.5 + 2.0**-20],  # cell (1, 0): a longer gap
            [0.5, 1.5, 2.0], [0.5, 1.5, 0.0], [0.5, 1.5, 1.0],  # cell (0, 1): unsorted, gaps 1.0
        ],
        dtype=np.float64,
    )  # fmt: skip
    elevation_map = tc.build_elevation_map(cloud, 1.0, origin=(0.0, 0.0), size=(2, 2), discontinuity=0.5)
    np.testing.assert_array_equal(elevation_map["discontinuity"], [[0.0, 1.0], [1.0, np.nan]])
    np.testing.assert_array_equal(elevation_map["count"], [[3, 3], [2, 0]])
    np.testing.assert_array_equal(elevation_map["min"], [[0.0, 0.0], [0.0, np.nan]])
    np.testing.assert_array_equal(elevation_map["max"], [[1.0, 2.0], [np.float32(0.5 + 2.0**-20), np.nan]])
    np.testing.assert_array_equal(elevation_map["mean"], [[0.5, 1.0], [np.float32(0.25 + 2.0**-21), np.nan]])
    np.testing.assert_allclose(
        elevation_map["std_dev"], [[np.sqrt(1 / 6), np.sqrt(2 / 3)], [0.25 + 2.0**-21, np.nan]], rtol=1e-6
    )


def test_an_empty_cloud_gives_an_all_empty_fixed_map_and_a_zero_sized_auto_map():
    fixed = tc.build_elevation_map(np.zeros((0, 3)), 0.1, origin=(0.0, 0.0), size=(3, 2))
    np.testing.assert_array_equal(fixed["count"], np.zeros((3, 2)))
    for name in ("min", "max", "mean", "std_dev", "discontinuity"):
        assert np.isnan(fixed[name]).all()
    auto = tc.build_elevation_map(np.zeros((0, 3)), 0.1)
    assert tuple(auto.geometry.size) == (0, 0)
    assert auto["count"].shape == (0, 0)


# --------------------------------------------------------------------------------------------
# Geometry convention.
# --------------------------------------------------------------------------------------------


def test_geometry_reports_resolution_origin_size_and_length():
    g = tc.ElevationMap.empty(0.25, (-1.0, 2.0), (8, 5)).geometry
    assert g.resolution == 0.25
    np.testing.assert_array_equal(g.origin, [-1.0, 2.0])
    np.testing.assert_array_equal(g.size, [8, 5])
    np.testing.assert_array_equal(g.length, [2.0, 1.25])
    assert g.num_cells == 40


def test_position_of_is_the_cell_centre():
    g = tc.ElevationMap.empty(0.25, (-1.0, 2.0), (8, 5)).geometry
    np.testing.assert_array_equal(g.position_of(0, 0), [-0.875, 2.125])
    np.testing.assert_array_equal(g.position_of(7, 4), [0.875, 3.125])
    np.testing.assert_array_equal(g.position_of(3, 1), [-0.125, 2.375])


def test_index_of_uses_half_open_cells_with_the_origin_at_the_lower_left_corner():
    g = tc.ElevationMap.empty(0.25, (-1.0, 2.0), (8, 5)).geometry
    eps = 2.0**-40  # x - origin stays exact in double for these offsets
    assert g.index_of(-1.0, 2.0) == (0, 0)  # the origin itself belongs to cell (0, 0)
    assert g.index_of(-0.75, 2.25) == (1, 1)  # a lower boundary belongs to the cell above it
    assert g.index_of(-0.75 - eps, 2.25 - eps) == (0, 0)
    assert g.index_of(0.9, 3.2) == (7, 4)
    assert g.index_of(1.0 - eps, 3.25 - eps) == (7, 4)
    assert g.index_of(1.0, 2.5) is None  # the upper x boundary is outside
    assert g.index_of(0.0, 3.25) is None  # the upper y boundary is outside
    assert g.index_of(-1.0 - eps, 2.5) is None
    assert g.index_of(0.0, 2.0 - eps) is None
    assert g.index_of(np.nan, 2.5) is None


def test_index_of_inverts_position_of_for_every_cell():
    elevation_map = tc.ElevationMap.empty(0.1, (-20.0, -10.0), (40, 20))
    g = elevation_map.geometry
    x, y = elevation_map.cell_centers()
    for i in range(40):
        for j in range(20):
            position = g.position_of(i, j)
            assert g.index_of(*position) == (i, j)
            assert (position[0], position[1]) == (x[i], y[j])


def test_build_bins_points_on_decimal_cell_boundaries_into_the_cell_index_of_reports():
    # x = k / 10 at resolution 0.1: index_of (and floor(x / res)) is the documented convention.
    xs = [k / 10 for k in range(10)]
    cloud = np.array([[x, 0.05, float(k)] for k, x in enumerate(xs)])
    elevation_map = tc.build_elevation_map(cloud, 0.1, origin=(0.0, 0.0), size=(10, 1))
    expected = np.zeros(10)
    for x in xs:
        expected[elevation_map.geometry.index_of(x, 0.05)[0]] += 1
    np.testing.assert_array_equal(elevation_map["count"][:, 0], expected)


@pytest.mark.parametrize(
    ("resolution", "min_x"), [(0.25, -1.23), (0.1, 0.05), (0.1, -0.9), (0.1, 1.7), (0.1, 3.4), (0.2, 3.4)]
)
def test_auto_extent_snaps_the_origin_down_to_a_multiple_of_the_resolution(resolution, min_x):
    cloud = np.array([[min_x, 0.3, 0.0], [min_x + 1.01, 1.37, 1.0], [min_x + 0.5, 0.81, 2.0]])
    elevation_map = tc.build_elevation_map(cloud, resolution)
    g = elevation_map.geometry
    for axis in range(2):
        lowest = cloud[:, axis].min()
        multiple = round(g.origin[axis] / resolution)
        assert g.origin[axis] == multiple * resolution
        assert g.origin[axis] <= lowest < g.origin[axis] + resolution
        assert cloud[:, axis].max() < g.origin[axis] + g.size[axis] * resolution
    assert elevation_map["count"].sum() == len(cloud), "every point of an auto-extent map falls inside"


def test_layers_are_nx_by_ny_float32_writeable_views():
    elevation_map = tc.build_elevation_map(random_cloud(4), 0.1, origin=(-2.0, -1.0), size=(30, 20))
    mean = elevation_map["mean"]
    assert mean.shape == (30, 20) and mean.dtype == np.float32
    assert mean.flags.writeable
    mean[3, 4] = 123.5
    mean[:, 0] = -7.0
    again = elevation_map["mean"]
    assert again[3, 4] == np.float32(123.5)
    np.testing.assert_array_equal(again[:, 0], np.full(30, -7.0, dtype=np.float32))


def test_setitem_adds_a_float32_layer_and_reports_it_in_order():
    elevation_map = tc.ElevationMap.empty(0.5, (0.0, 0.0), (3, 2))
    assert elevation_map.layers == []
    elevation_map["a"] = np.arange(6, dtype=np.float64).reshape(3, 2)
    elevation_map["b"] = np.ones((3, 2), dtype=np.int32)
    assert elevation_map.layers == ["a", "b"]
    assert "a" in elevation_map and "c" not in elevation_map
    assert elevation_map["a"].dtype == np.float32
    np.testing.assert_array_equal(elevation_map["a"], np.arange(6).reshape(3, 2))


def test_missing_layer_raises_key_error_naming_it():
    elevation_map = tc.ElevationMap.empty(0.5, (0.0, 0.0), (3, 2))
    elevation_map["max"] = np.zeros((3, 2))
    with pytest.raises(KeyError, match="clearance"):
        elevation_map["clearance"]


@pytest.mark.parametrize("shape", [(2, 3), (3, 3), (6,), (3, 2, 1)])
def test_setitem_with_the_wrong_shape_raises_value_error(shape):
    elevation_map = tc.ElevationMap.empty(0.5, (0.0, 0.0), (3, 2))
    with pytest.raises(ValueError, match="shape"):
        elevation_map["max"] = np.zeros(shape)
    assert "max" not in elevation_map


# --------------------------------------------------------------------------------------------
# Files.
# --------------------------------------------------------------------------------------------


def special_map() -> tc.ElevationMap:
    elevation_map = tc.build_elevation_map(random_cloud(6), 0.1, origin=(-2.05, -1.15), size=(37, 23))
    special = elevation_map["mean"].copy()
    special[0, 0] = np.inf
    special[0, 1] = -np.inf
    special[0, 2] = -0.0
    special[0, 3] = np.nan
    elevation_map["special"] = special
    return elevation_map


def test_save_and_load_round_trip_geometry_and_every_layer_bit_identically(tmp_path):
    elevation_map = special_map()
    path = elevation_map.save(tmp_path / "sub" / "map.npz")
    assert path.is_file()
    loaded = tc.ElevationMap.load(path)
    assert loaded.geometry.resolution == elevation_map.geometry.resolution
    np.testing.assert_array_equal(loaded.geometry.origin, elevation_map.geometry.origin)
    np.testing.assert_array_equal(loaded.geometry.size, elevation_map.geometry.size)
    assert loaded.layers == elevation_map.layers
    for name in elevation_map.layers:
        assert loaded[name].dtype == np.float32
        np.testing.assert_array_equal(loaded[name].view(np.uint32), elevation_map[name].view(np.uint32))
    special = loaded["special"]
    assert special[0, 0] == np.inf and special[0, 1] == -np.inf and np.isnan(special[0, 3])
    assert np.isnan(loaded["max"]).any()


def test_load_of_an_npz_that_is_not_a_map_raises_value_error_naming_the_file(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, xyz=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="other.npz"):
        tc.ElevationMap.load(path)


def test_a_layer_view_keeps_its_values_while_later_maps_of_its_size_are_built():
    # Dropped maps leave their buffers to the next maps of the thread; a view keeps its map (and
    # so its buffer) alive, so later builds must not write into it.
    params = tc.ElevationParams(0.5, origin=(0.0, 0.0), size=(40, 40))
    first = tc.build_elevation_map(random_cloud(5, 4000), params=params)
    view = first["mean"]
    expected = view.copy()
    del first
    gc.collect()
    for seed in range(6, 10):
        later = tc.build_elevation_map(random_cloud(seed, 4000), params=params)
        assert not np.array_equal(later["mean"], expected, equal_nan=True)
        del later
    np.testing.assert_array_equal(view, expected)


def test_load_of_a_missing_file_raises_file_not_found_error_naming_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        tc.ElevationMap.load(tmp_path / "missing.npz")


@pytest.mark.parametrize("kind", ["npy", "text"])
def test_load_of_a_file_that_is_not_an_npz_raises_value_error_naming_the_file(tmp_path, kind):
    path = tmp_path / "not_a_map.npz"
    if kind == "npy":
        with path.open("wb") as stream:
            np.save(stream, np.zeros((4, 3)))
    else:
        path.write_text("resolution = 0.1\n")
    with pytest.raises(ValueError, match="not_a_map.npz"):
        tc.ElevationMap.load(path)


@pytest.mark.parametrize("keep", [0.0, 0.01, 0.5, 0.95])
def test_load_of_a_truncated_file_raises_value_error_naming_the_file(tmp_path, keep):
    data = special_map().save(tmp_path / "map.npz").read_bytes()
    path = tmp_path / "truncated.npz"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError, match="truncated.npz"):
        tc.ElevationMap.load(path)


def test_to_png_writes_a_png_file(tmp_path):
    path = special_map().to_png("mean", tmp_path / "mean.png", title="mean")
    data = path.read_bytes()
    assert len(data) > len(PNG_MAGIC) and data.startswith(PNG_MAGIC)


def test_wide_maps_are_drawn_in_blocks_that_keep_every_cell_with_data(tmp_path):
    """A map wider than a picture's pixels is drawn in k x k blocks, each its largest finite value
    (else +-inf, else empty; the smallest for clearance and traversability), against a plain
    loop; the classes' blocks show their most notable class; the pictures of such a map are
    written."""
    from terracube.viz import _DRAWN_CELLS, _LOW_IS_NOTABLE, _block_factor, _drawn_classes, _drawn_values

    rng = np.random.default_rng(5)
    values = np.where(rng.random((7, 5)) < 0.4, rng.normal(size=(7, 5)), np.nan).astype(np.float32)
    values[6, 4], values[0, 4], values[3, 3] = np.inf, -np.inf, np.inf
    values[1, 1] = -np.inf  # a block with both infinities: +inf drawn, or -inf for the lowest
    values[0:3, 0:3][np.isfinite(values[0:3, 0:3])] = np.nan
    values[0, 0] = np.inf
    for lowest in (False, True):
        drawn = _drawn_values(values, 3, lowest=lowest)
        assert drawn.shape == (3, 2)
        first, second = (-np.inf, np.inf) if lowest else (np.inf, -np.inf)
        for bi in range(3):
            for bj in range(2):
                block = values[3 * bi : 3 * bi + 3, 3 * bj : 3 * bj + 3]
                finite = block[np.isfinite(block)]
                if finite.size:
                    expected = finite.min() if lowest else finite.max()
                elif (block == first).any():
                    expected = first
                elif (block == second).any():
                    expected = second
                else:
                    expected = np.nan
                np.testing.assert_array_equal(drawn[bi, bj], expected)
    assert _drawn_values(values, 3, lowest=True)[0, 0] == -np.inf  # the block holding both
    assert {"clearance", "traversability"} <= _LOW_IS_NOTABLE and "max" not in _LOW_IS_NOTABLE
    assert _drawn_values(values, 1) is values
    classes = rng.integers(0, 6, (7, 5)).astype(np.int16)
    shown = _drawn_classes(classes, 3)
    order = [0, 1, 5, 3, 2, 4]  # unknown, ground, edge, overhanging, obstacle = vertical
    for bi in range(3):
        for bj in range(2):
            block = classes[3 * bi : 3 * bi + 3, 3 * bj : 3 * bj + 3]
            best = max(block.ravel(), key=lambda c: min(order.index(c), 4))
            assert min(order.index(shown[bi, bj]), 4) == min(order.index(best), 4)

    wide = tc.ElevationMap.empty(0.1, (0.0, 0.0), (2 * _DRAWN_CELLS + 1, 30))
    assert _block_factor(wide.geometry) == 3 and _block_factor(special_map().geometry) == 1
    heights = np.full(tuple(wide.geometry.size), np.nan, np.float32)
    heights[::97, ::7] = 1.0  # sparse: most cells would fall between the pixels
    for name in ("max", "mean", "min", "std_dev", "discontinuity"):
        wide[name] = heights if name != "std_dev" else np.where(np.isnan(heights), np.nan, 0.0)
    wide["discontinuity"] = np.where(np.isnan(heights), np.nan, 0.0)
    classes = tc.classify_terrain(wide)
    for path in (
        wide.to_png("max", tmp_path / "max.png"),
        tc.viz.plot_terrain_classes(wide, classes, tmp_path / "classes.png"),
        tc.viz.plot_dem_comparison(wide, wide, tmp_path / "comparison.png"),
    ):
        assert path.read_bytes().startswith(PNG_MAGIC)


def test_every_layer_the_library_writes_has_its_own_colour_bar_label():
    """The label names the layer's unit; only a user's own layers fall back to '<name> [m]'
    (a LocalMap's traversability, a fraction, once read 'traversability [m]')."""
    from terracube.viz import _LAYER_LABELS

    points = np.c_[np.random.default_rng(0).uniform(-5, 5, (2000, 2)), np.zeros(2000)]
    dem, _ = tc.dem_without_overhangs(points, resolution=0.5)
    tc.fit_fuzzy_elevation_map(points, tc.FuzzyParams(epochs=1)).to_layer(dem)
    with pytest.warns(UserWarning, match="replaces the map's 'step' layer"):
        tc.add_traversability_layers(dem)
    local = tc.LocalMap(length=4.0)
    local.update(points, np.eye(4))
    written = set(dem.layers) | set(local.to_elevation_map().layers)
    assert written - set(_LAYER_LABELS) == set()
    assert "[m]" not in _LAYER_LABELS["traversability"] and "[rad]" in _LAYER_LABELS["slope"]


def test_to_geotiff_round_trips_values_orientation_and_transform(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    elevation_map = tc.ElevationMap.empty(0.5, (10.0, 20.0), (3, 4))
    values = np.arange(12, dtype=np.float32).reshape(3, 4)  # value = 4 i + j
    values[1, 2] = np.nan
    elevation_map["max"] = values
    path = elevation_map.to_geotiff("max", tmp_path / "max.tif", crs="EPSG:32633")
    with rasterio.open(path) as dataset:
        raster = dataset.read(1)
        transform = dataset.transform
        assert dataset.count == 1 and dataset.dtypes[0] == "float32"
        assert dataset.crs.to_epsg() == 32633 and np.isnan(dataset.nodata)
        assert dataset.compression is not None and dataset.compression.value == "DEFLATE"
        assert dataset.units == ("metre",)
    assert raster.shape == (4, 3)  # rows along y, columns along x
    # each band names the unit of its values: the CRS's length unit (metre without one)
    elevation_map["variance"], elevation_map["slope"], elevation_map["count"] = values, values, values
    for layer, crs, unit in (
        ("max", "EPSG:2229", "US survey foot"),
        ("max", None, "metre"),
        ("max", "EPSG:4326", "metre"),  # degrees measure x and y only
        ("variance", None, "metre^2"),
        ("slope", "EPSG:2229", "radian"),
        ("count", None, None),
    ):
        with rasterio.open(elevation_map.to_geotiff(layer, tmp_path / "u.tif", crs=crs)) as dataset:
            assert dataset.units == (unit,), (layer, crs, dataset.units)
    for i in range(3):
        for j in range(4):
            row = 3 - j  # row 0 is the largest y
            np.testing.assert_array_equal(raster[row, i], values[i, j])
    assert (transform.a, transform.b, transform.c) == (0.5, 0.0, 10.0)
    assert (transform.d, transform.e, transform.f) == (0.0, -0.5, 22.0)
    # The centre of cell (i, j) maps to pixel (row 3 - j, column i).
    for i, j in [(0, 0), (2, 3), (1, 2)]:
        x, y = elevation_map.geometry.position_of(i, j)
        column = (x - transform.c) / transform.a
        row = (y - transform.f) / transform.e
        assert (int(np.floor(row)), int(np.floor(column))) == (3 - j, i)


def test_to_geotiff_without_rasterio_raises_import_error_naming_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rasterio", None)
    monkeypatch.setitem(sys.modules, "rasterio.transform", None)
    elevation_map = tc.ElevationMap.empty(0.5, (0.0, 0.0), (2, 2))
    elevation_map["max"] = np.zeros((2, 2))
    with pytest.raises(ImportError, match="rasterio"):
        elevation_map.to_geotiff("max", tmp_path / "max.tif")


# --------------------------------------------------------------------------------------------
# DEM without overhangs.
# --------------------------------------------------------------------------------------------


def canopy_scene(seed: int) -> np.ndarray:
    """Ground over 10 x 10 m, a canopy slab 3-4 m up over part of it, and a wall."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0.0, 10.0, (6000, 2)), rng.normal(0.0, 0.03, 6000)])
    canopy = np.column_stack([rng.uniform(3.0, 7.0, (2000, 2)), rng.uniform(3.0, 4.0, 2000)])
    wall = np.column_stack(
        [rng.uniform(8.5, 8.6, 800), rng.uniform(1.0, 4.0, 800), rng.uniform(0.0, 2.5, 800)]
    )
    cloud = np.concatenate([ground, canopy, wall])
    return cloud[rng.permutation(len(cloud))]


def reference_step(height: np.ndarray) -> np.ndarray:
    """max over the 8 neighbours of |h - neighbour|, NaN neighbours ignored, 0 when none,
    NaN where h is NaN; in float32 like the layer."""
    height = np.asarray(height, dtype=np.float32)
    nx, ny = height.shape
    padded = np.full((nx + 2, ny + 2), np.nan, dtype=np.float32)
    padded[1:-1, 1:-1] = height
    differences = [
        np.abs(padded[1 + di : 1 + di + nx, 1 + dj : 1 + dj + ny] - height)
        for di in (-1, 0, 1)
        for dj in (-1, 0, 1)
        if (di, dj) != (0, 0)
    ]
    stacked = np.stack(differences)
    largest = np.where(np.isnan(stacked), np.float32(0.0), stacked).max(axis=0)
    return np.where(np.isnan(height), np.float32(np.nan), largest).astype(np.float32)


def assert_clearance_and_step(elevation_map: tc.ElevationMap, overhang_min: np.ndarray, kept_xyz) -> None:
    """clearance = lowest overhang point - highest kept point below it (NaN when none is below),
    +inf where a cell with kept points has no overhang, NaN where it has no kept point."""
    top = elevation_map["max"]
    np.testing.assert_array_equal(elevation_map["overhang_min"], overhang_min)
    g = elevation_map.geometry
    kept_xyz = np.asarray(kept_xyz, dtype=np.float64)
    i = np.floor((kept_xyz[:, 0] - g.origin[0]) / g.resolution).astype(np.int64)
    j = np.floor((kept_xyz[:, 1] - g.origin[1]) / g.resolution).astype(np.int64)
    inside = (i >= 0) & (j >= 0) & (i < g.size[0]) & (j < g.size[1])
    i, j, z = i[inside], j[inside], kept_xyz[inside, 2]
    below = z < overhang_min[i, j]  # False where there is no overhang (NaN)
    under = np.full(top.shape, -np.inf)
    np.maximum.at(under, (i[below], j[below]), z[below])
    kept = ~np.isnan(top)
    expected = np.full(top.shape, np.nan, dtype=np.float32)
    expected[kept & np.isnan(overhang_min)] = np.inf
    has_under = kept & ~np.isnan(overhang_min) & np.isfinite(under)
    expected[has_under] = overhang_min[has_under] - under[has_under].astype(np.float32)
    assert np.all(expected[has_under] > 0)
    np.testing.assert_array_equal(elevation_map["clearance"], expected)
    np.testing.assert_array_equal(elevation_map["step"], reference_step(top))


def test_dem_without_overhangs_is_the_map_of_the_kept_points_on_the_geometry_of_all_points():
    cloud = canopy_scene(0)
    elevation_map, result = tc.dem_without_overhangs(cloud, 0.5, 2, 0.25)
    assert 1500 < result.num_overhang < 2500  # the canopy goes, the wall and ground stay
    everything = tc.build_elevation_map(cloud, 0.25)
    g = elevation_map.geometry
    np.testing.assert_array_equal(g.origin, everything.geometry.origin)
    np.testing.assert_array_equal(g.size, everything.geometry.size)
    kept = tc.build_elevation_map(cloud, 0.25, use=~result.overhang, origin=g.origin, size=g.size)
    for name in LAYERS:
        np.testing.assert_array_equal(elevation_map[name], kept[name], err_msg=name)
    reference = reference_layers(cloud, 0.25, g.origin, g.size, use=~result.overhang)
    assert_layers_match(elevation_map, reference)
    overhangs = reference_layers(cloud, 0.25, g.origin, g.size, use=result.overhang)
    assert_clearance_and_step(elevation_map, overhangs.min.astype(np.float32), cloud[~result.overhang])
    clearance = elevation_map["clearance"]
    assert np.isfinite(clearance).any() and np.isposinf(clearance).any()


def test_dem_without_overhangs_uses_the_collapse_transform_and_crop():
    cloud = canopy_scene(1)
    transform = tc.leveling_transform(0.05, -0.03)
    crop = ((1.0, 1.0, -1.0), (9.0, 8.0, 5.0))
    collapse = tc.CollapseParams(0.5, 2, transform=transform, crop=crop)
    elevation_map, result = tc.dem_without_overhangs(
        cloud, collapse=collapse, elevation=tc.ElevationParams(0.25, discontinuity=0.4)
    )
    assert result.num_overhang > 1000
    everything = tc.build_elevation_map(cloud, 0.25, transform=transform, crop=crop)
    g = elevation_map.geometry
    np.testing.assert_array_equal(g.origin, everything.geometry.origin)
    np.testing.assert_array_equal(g.size, everything.geometry.size)

    def same_frame(use):
        return tc.build_elevation_map(
            cloud,
            0.25,
            use=use,
            origin=g.origin,
            size=g.size,
            transform=transform,
            crop=crop,
            discontinuity=0.4,
        )

    kept = same_frame(~result.overhang)
    for name in LAYERS:
        np.testing.assert_array_equal(elevation_map[name], kept[name], err_msg=name)
    leveled = cloud[~result.overhang] @ np.asarray(transform)[:3, :3].T + np.asarray(transform)[:3, 3]
    box = np.asarray(crop, dtype=np.float64)
    leveled = leveled[np.all((leveled >= box[0]) & (leveled <= box[1]), axis=1)]
    assert_clearance_and_step(elevation_map, same_frame(result.overhang)["min"], leveled)


def test_dem_without_overhangs_keeps_a_fixed_extent():
    cloud = canopy_scene(2)
    elevation = tc.ElevationParams(0.5, origin=(2.0, 2.0), size=(10, 6))
    elevation_map, result = tc.dem_without_overhangs(cloud, 0.5, 2, elevation=elevation)
    np.testing.assert_array_equal(elevation_map.geometry.origin, [2.0, 2.0])
    np.testing.assert_array_equal(elevation_map.geometry.size, [10, 6])
    reference = reference_layers(cloud, 0.5, (2.0, 2.0), (10, 6), use=~result.overhang)
    assert_layers_match(elevation_map, reference)
    overhangs = reference_layers(cloud, 0.5, (2.0, 2.0), (10, 6), use=result.overhang)
    assert_clearance_and_step(elevation_map, overhangs.min.astype(np.float32), cloud[~result.overhang])


def test_dem_without_overhangs_hand_built_clearance_is_exact():
    # Edge 1, sigma 2, cells of 1 m centred on whole metres (origin -0.5). Cube columns and map
    # cells coincide; every height is exact in binary.
    #   cell (0, 0): kept 0.0, 0.25; overhang 3.0, 3.5 (two empty cubes)  -> clearance 2.75
    #   cell (1, 0): kept 0.5 only                                       -> +inf
    #   cell (0, 1): kept 0.0, 1.0, 2.0 (no gap)                         -> +inf, step vs (0, 0)
    #   cell (1, 1): no point                                            -> NaN
    #   cell (2, 0): kept -0.5; overhang 4.0 (4 empty cubes between)      -> 4.5
    cloud = np.array(
        [
            [0, 0, 0.0], [0, 0, 0.25], [0, 0, 3.0], [0, 0, 3.5],
            [1, 0, 0.5],
            [0, 1, 0.0], [0, 1, 1.0], [0, 1, 2.0],
            [2, 0, -0.5], [2, 0, 4.0],
        ],
        dtype=np.float64,
    )  # fmt: skip
    elevation = tc.ElevationParams(1.0, origin=(-0.5, -0.5), size=(3, 2))
    elevation_map, result = tc.dem_without_overhangs(cloud, 1.0, 2, elevation=elevation)
    np.testing.assert_array_equal(result.overhang, [0, 0, 1, 1, 0, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(elevation_map["max"], [[0.25, 2.0], [0.5, np.nan], [-0.5, np.nan]])
    np.testing.assert_array_equal(
        elevation_map["overhang_min"], [[3.0, np.nan], [np.nan, np.nan], [4.0, np.nan]]
    )
    np.testing.assert_array_equal(
        elevation_map["clearance"], [[2.75, np.inf], [np.inf, np.nan], [4.5, np.nan]]
    )
    np.testing.assert_array_equal(elevation_map["count"], [[2, 3], [1, 0], [1, 0]])
    # step: (0,0) neighbours 2.0, 0.5, -0.5 -> 1.75; (1,0): 0.25, 2.0, -0.5 -> 1.5;
    # (0,1): 0.25, 0.5 -> 1.75; (2,0): 0.5 -> 1.0 (its other neighbours are empty).
    np.testing.assert_array_equal(elevation_map["step"], [[1.75, 1.75], [1.5, np.nan], [1.0, np.nan]])


def test_step_of_an_isolated_cell_is_zero():
    cloud = np.array([[0.5, 0.5, 3.0], [2.5, 2.5, 7.0]])
    elevation = tc.ElevationParams(1.0, origin=(0.0, 0.0), size=(3, 3))
    elevation_map, _ = tc.dem_without_overhangs(cloud, 1.0, 2, elevation=elevation)
    expected = np.full((3, 3), np.nan, dtype=np.float32)
    expected[0, 0] = expected[2, 2] = 0.0
    np.testing.assert_array_equal(elevation_map["step"], expected)


def test_dem_without_overhangs_on_kitti_frame0_matches_the_map_of_kept_points(shared_data):
    xyz = shared_data.kitti_xyzi(0)[:, :3]
    crop = ((-30.0, -30.0, -3.0), (30.0, 30.0, 30.0))
    collapse = tc.CollapseParams(0.5, 5, crop=crop)
    elevation = tc.ElevationParams(0.2, origin=(-30.0, -30.0), size=(300, 300))
    elevation_map, result = tc.dem_without_overhangs(xyz, collapse=collapse, elevation=elevation)
    assert result.num_overhang > 0
    keep = ~result.overhang
    kept = tc.build_elevation_map(xyz, 0.2, use=keep, origin=(-30.0, -30.0), size=(300, 300), crop=crop)
    for name in LAYERS:
        np.testing.assert_array_equal(elevation_map[name], kept[name], err_msg=name)
    in_crop = np.all((xyz >= np.float32(-30.0)) & (xyz <= np.float32(30.0)), axis=1) & (xyz[:, 2] >= -3.0)
    reference = reference_layers(xyz, 0.2, (-30.0, -30.0), (300, 300), use=keep & in_crop)
    assert_layers_match(elevation_map, reference)
    overhangs = reference_layers(xyz, 0.2, (-30.0, -30.0), (300, 300), use=result.overhang & in_crop)
    assert_clearance_and_step(elevation_map, overhangs.min.astype(np.float32), xyz[keep & in_crop])


# --------------------------------------------------------------------------------------------
# Bad input.
# --------------------------------------------------------------------------------------------


def test_nan_and_inf_rows_raise_value_error_with_their_count():
    cloud = random_cloud(7)[:100].copy()
    cloud[[3, 50], 0] = np.nan
    cloud[70, 2] = np.inf
    with pytest.raises(ValueError, match=r"3 of 100 point rows .*first at row 3"):
        tc.build_elevation_map(cloud, 0.1)


def test_drop_non_finite_maps_the_finite_rows_only():
    cloud = random_cloud(7)[:2000].copy()
    cloud[[3, 50], 0] = np.nan
    cloud[70, 2] = -np.inf
    finite = np.isfinite(cloud).all(axis=1)
    dropped = tc.build_elevation_map(cloud, 0.1, drop_non_finite=True)
    clean = tc.build_elevation_map(cloud[finite], 0.1)
    np.testing.assert_array_equal(dropped.geometry.origin, clean.geometry.origin)
    np.testing.assert_array_equal(dropped.geometry.size, clean.geometry.size)
    for name in LAYERS:
        np.testing.assert_array_equal(dropped[name], clean[name], err_msg=name)
    origin, size = reference_auto_extent(cloud[finite], 0.1)
    assert_layers_match(dropped, reference_layers(cloud[finite], 0.1, origin, size))


@pytest.mark.parametrize("shape", [(10, 2), (10, 17), (30,), (10, 3, 1)])
def test_points_of_the_wrong_shape_raise_value_error(shape):
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        tc.build_elevation_map(np.zeros(shape), 0.1)


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.float16, np.complex128])
def test_points_of_the_wrong_dtype_raise_type_error(dtype):
    with pytest.raises(TypeError, match="float32 or float64"):
        tc.build_elevation_map(np.zeros((10, 3), dtype=dtype), 0.1)


@pytest.mark.parametrize("resolution", [0.0, -0.1, np.nan, np.inf])
def test_resolution_that_is_not_positive_and_finite_raises_value_error(resolution):
    with pytest.raises(ValueError, match="resolution"):
        tc.build_elevation_map(np.zeros((3, 3)), resolution)


def test_bad_resolutions_end_in_errors_not_endless_loops():
    # issue 39, item 5: both calls used to loop for ever.
    cloud = np.array([[5.0, 5.0, 0.0], [7.0, 6.0, 1.0]])
    with pytest.raises(ValueError, match="resolution"):
        tc.dem_without_overhangs(cloud, resolution=-0.5)
    with pytest.raises(ValueError, match="max_cells"):
        tc.build_elevation_map(cloud, 1e-20)


@pytest.mark.parametrize("extent", [{"origin": (0.0, 0.0)}, {"size": (4, 4)}])
def test_origin_without_size_or_size_without_origin_raises_value_error(extent):
    with pytest.raises(ValueError, match="both origin and size"):
        tc.build_elevation_map(np.zeros((3, 3)), 0.1, **extent)


_BAD_SIZES = [
    (0, 4),
    (4, 0),
    (0, 0),
    (-1, 4),
    (2.5, 4),
    (np.nan, 4),
    (4, np.inf),
    (2**31, 4),
    (4,),
    (4, 4, 4),
]


@pytest.mark.parametrize("as_array", [False, True], ids=["tuple", "array"])
@pytest.mark.parametrize("size", _BAD_SIZES)
def test_size_with_zero_negative_or_fractional_cells_raises_value_error(size, as_array):
    # Tuples of scalars are checked in plain Python, arrays by numpy: both reject the same sizes.
    size = np.array(size) if as_array else size
    with pytest.raises(ValueError, match="size must be two positive whole cell counts"):
        tc.build_elevation_map(np.zeros((3, 3)), 0.1, origin=(0.0, 0.0), size=size)


@pytest.mark.parametrize("as_array", [False, True], ids=["tuple", "array"])
@pytest.mark.parametrize("origin", [(0.0, np.nan), (np.inf, 0.0), (-np.inf, 1.0), (0.0,), (0.0, 0.0, 0.0)])
def test_origin_that_is_not_two_finite_coordinates_raises_value_error(origin, as_array):
    origin = np.array(origin) if as_array else origin
    with pytest.raises(ValueError, match="origin must be two finite coordinates"):
        tc.build_elevation_map(np.zeros((3, 3)), 0.1, origin=origin, size=(4, 4))


@pytest.mark.parametrize(
    "origin, size",
    [
        ((-1, 2), (3, 4)),
        ((-1.0, 2.0), (3.0, 4.0)),
        ([np.float32(-1.0), np.int64(2)], [np.int32(3), np.float64(4.0)]),
        (np.array([-1.0, 2.0]), np.array([3, 4])),
        (np.array([-1, 2], dtype=np.int16), np.array([3.0, 4.0])),
    ],
)
def test_fixed_extent_of_python_or_numpy_numbers_gives_the_same_geometry(origin, size):
    geometry = tc.build_elevation_map(np.zeros((3, 3)), 0.5, origin=origin, size=size).geometry
    assert geometry.origin.tolist() == [-1.0, 2.0]
    assert geometry.size.tolist() == [3, 4]


def test_auto_extent_over_max_cells_raises_value_error_naming_max_cells():
    cloud = np.array([[0.0, 0.0, 0.0], [1000.0, 1000.0, 0.0]])
    with pytest.raises(ValueError, match=r"need \d+ x \d+ cells, over max_cells = 1000000;"):
        tc.build_elevation_map(cloud, 0.01, max_cells=1_000_000)
    # Just under the limit it builds: 11 x 11 cells.
    assert tc.build_elevation_map(cloud, 100.0, max_cells=121)["count"].sum() == 2


def test_fixed_extent_over_max_cells_raises_value_error_naming_max_cells():
    with pytest.raises(ValueError, match="max_cells"):
        tc.build_elevation_map(
            np.zeros((3, 3)), 0.1, origin=(0.0, 0.0), size=(1000, 1001), max_cells=1_000_000
        )


@pytest.mark.parametrize("length", [0, 9, 11])
def test_use_of_the_wrong_length_raises_value_error(length):
    with pytest.raises(ValueError, match="use"):
        tc.build_elevation_map(np.zeros((10, 3)), 0.1, use=np.ones(length, dtype=bool))


def test_discontinuity_that_is_not_positive_raises_value_error():
    with pytest.raises(ValueError, match="discontinuity"):
        tc.build_elevation_map(np.zeros((3, 3)), 0.1, discontinuity=0.0)


@pytest.mark.parametrize("num_threads", [2, 3, 0])
def test_kitti_frame0_map_and_classes_on_several_threads_equal_the_one_thread_results(
    shared_data, num_threads
):
    xyz = shared_data.kitti_xyzi(0)[:, :3]
    extent = {"origin": (-20.0, -10.0), "size": (400, 200)}
    one = tc.build_elevation_map(xyz, 0.1, **extent)
    assert_layers_match(one, reference_layers(xyz, 0.1, extent["origin"], extent["size"]))
    classes_one = tc.classify_terrain(one, sensor_height=1.73)
    several = tc.build_elevation_map(xyz, 0.1, num_threads=num_threads, **extent)
    classes_several = tc.classify_terrain(several, sensor_height=1.73, num_threads=num_threads)
    assert several.layers == one.layers
    for name in one.layers:
        np.testing.assert_array_equal(several[name], one[name], err_msg=name)  # NaN where NaN, else equal
    np.testing.assert_array_equal(classes_several, classes_one)


def test_python_threads_mapping_at_once_get_the_one_thread_results(shared_data):
    # The calls release the GIL, so four Python threads use the library at once with num_threads=0:
    # each call runs its parts in its own task arena.
    from concurrent.futures import ThreadPoolExecutor

    xyz = shared_data.kitti_xyzi(0)[:, :3]
    extent = {"origin": (-20.0, -10.0), "size": (400, 200)}
    one = tc.build_elevation_map(xyz, 0.1, **extent)
    classes_one = tc.classify_terrain(one, sensor_height=1.73)

    def map_and_classify(_):
        runs = []
        for _ in range(5):
            elevation_map = tc.build_elevation_map(xyz, 0.1, num_threads=0, **extent)
            runs.append(
                (elevation_map, tc.classify_terrain(elevation_map, sensor_height=1.73, num_threads=0))
            )
        return runs

    with ThreadPoolExecutor(4) as executor:
        results = [run for runs in executor.map(map_and_classify, range(4)) for run in runs]
    assert len(results) == 20
    for elevation_map, classes in results:
        for name in one.layers:
            np.testing.assert_array_equal(elevation_map[name], one[name], err_msg=name)
        np.testing.assert_array_equal(classes, classes_one)


@pytest.mark.parametrize("num_threads", [-1, 1.5, True, "2"])
def test_num_threads_that_is_not_a_whole_number_at_least_zero_raises_value_error(num_threads):
    points = np.zeros((10, 3))
    with pytest.raises(ValueError, match="num_threads"):
        tc.build_elevation_map(points, 0.5, num_threads=num_threads)
    elevation_map = tc.build_elevation_map(points, 0.5)
    with pytest.raises(ValueError, match="num_threads"):
        tc.classify_terrain(elevation_map, num_threads=num_threads)


def _threaded_counts_in_child(points, queue):
    elevation_map = tc.build_elevation_map(points, 0.5, num_threads=2)
    collapsed = tc.collapse_overhangs(points, 0.5, 2, num_threads=2)
    queue.put((float(elevation_map["count"].sum()), int(collapsed.num_overhang)))


@pytest.mark.skipif(sys.platform != "linux", reason="fork() start method")
def test_a_forked_child_of_a_process_that_used_threads_still_builds_instead_of_hanging():
    # A thread runtime's workers do not exist in a forked child of a process that had started them
    # (with GCC's libgomp, which the library once used, the child hung); oneTBB starts new ones.
    import multiprocessing

    points = np.random.default_rng(5).random((150_000, 3)) * [60.0, 60.0, 8.0]
    expected_map = tc.build_elevation_map(points, 0.5, num_threads=2)  # starts TBB's workers here
    expected = (float(expected_map["count"].sum()), int(tc.collapse_overhangs(points, 0.5, 2).num_overhang))
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_threaded_counts_in_child, args=(points, queue))
    child.start()
    child.join(60)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked child hung in its first threaded call")
    assert child.exitcode == 0
    assert queue.get(timeout=5) == expected


# --------------------------------------------------------------------------------------------
# float32 clouds at large coordinates.
# --------------------------------------------------------------------------------------------


def _utm_grid(dtype) -> np.ndarray:
    """A 2 m square of points 0.1 m apart at UTM-like (500000, 4500000), where float32 steps by 0.5 m
    along y: as float32 its 20 rows collapse onto 4."""
    i, j = np.meshgrid(np.arange(20), np.arange(20), indexing="ij")
    xy = np.column_stack([i.ravel() * 0.1 + 0.05, j.ravel() * 0.1 + 0.05]) + [500000.0, 4500000.0]
    return np.column_stack([xy, np.zeros(len(xy))]).astype(dtype)


FLOAT32_CALLS = {
    "build_elevation_map": lambda points: tc.build_elevation_map(points, 0.1),
    "dem_without_overhangs": lambda points: tc.dem_without_overhangs(points),
    "collapse_overhangs": lambda points: tc.collapse_overhangs(points),
    "LocalMap.update": lambda points: tc.LocalMap(20.0, 0.1).update(points, np.eye(4)),
    "Mapper.add_scan": lambda points: tc.Mapper().add_scan(points, np.eye(4)),
}


@pytest.mark.parametrize("call", FLOAT32_CALLS.values(), ids=FLOAT32_CALLS.keys())
def test_float32_points_at_utm_coordinates_warn_with_the_float32_step(call):
    with pytest.warns(UserWarning, match=r"4,500,002 m, where float32 steps by 0.5 m.*pass float64 points"):
        call(_utm_grid(np.float32))


@pytest.mark.parametrize("call", FLOAT32_CALLS.values(), ids=FLOAT32_CALLS.keys())
def test_float64_or_small_float32_points_do_not_warn(call, recwarn):
    call(_utm_grid(np.float64))
    call(np.ascontiguousarray(_utm_grid(np.float32)[:, :3] - np.float32([500000.0, 4500000.0, 0.0])))
    assert not [w for w in recwarn if "float32" in str(w.message)]


def test_float32_rows_collapse_at_utm_coordinates_as_the_warning_says():
    with pytest.warns(UserWarning, match="float32"):
        coarse = tc.build_elevation_map(_utm_grid(np.float32), 0.1)
    fine = tc.build_elevation_map(_utm_grid(np.float64), 0.1)
    assert int(np.count_nonzero(fine["count"])) == 400
    assert int(np.count_nonzero(coarse["count"])) < 400


def test_float32_step_without_a_length_is_held_to_one_centimetre():
    from terracube.collapse import float32_step_warning

    at_100_km = np.full((1, 3), 100_000.0, dtype=np.float32)  # float32 steps by 7.8 mm
    at_200_km = np.full((1, 3), 200_000.0, dtype=np.float32)  # by 15.6 mm
    assert float32_step_warning(at_100_km) is None
    assert "more than 1 cm" in float32_step_warning(at_200_km)
    assert float32_step_warning(at_200_km, 0.5, "cube edge") is None  # 15.6 mm < 50 mm
    assert float32_step_warning(np.full((1, 3), np.nan, dtype=np.float32)) is None
    assert float32_step_warning(np.empty((0, 3), dtype=np.float32)) is None
