"""collapse_overhangs against a loop-by-loop Algorithm 1 (Reina et al., IEEE AIM 2014).

The reference below is written from the paper's definition only, in plain Python: a set for the
occupancy bit vector V, a list for L, a dict for the ground matrix M. It shares no code with the
C++ library; the quantisation is computed with Python floats, which are IEEE doubles, exactly as
the definition states: ix = floor((x - xmin) * (1.0 / E) + 0.5).
"""

from __future__ import annotations

import gc
import math
import sys
import threading
import time
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import pytest
import terracube as tc
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

STORAGES = ("auto", "dense", "sparse")

HYPOTHESIS = settings(
    max_examples=50,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


# --------------------------------------------------------------------------------------------
# The independent reference: Algorithm 1 loop by loop.
# --------------------------------------------------------------------------------------------


@dataclass
class NaiveResult:
    overhang: np.ndarray  # (N,) bool
    occupied: np.ndarray  # sorted L, int64
    removed: np.ndarray  # sorted R, int64
    counts: tuple | None  # (ixmax, iymax, izmax), None for an empty cloud
    min_corner: tuple | None
    cube_of_point: list  # I of every point


def naive_algorithm1(points, edge: float, sigma: int) -> NaiveResult:
    """Algorithm 1 as the paper states it, with Python containers."""
    rows = np.asarray(points, dtype=np.float64).reshape(-1, 3).tolist()
    if not rows:
        empty = np.zeros(0, dtype=np.int64)
        return NaiveResult(np.zeros(0, dtype=bool), empty, empty, None, None, [])
    xmin = min(r[0] for r in rows)
    ymin = min(r[1] for r in rows)
    zmin = min(r[2] for r in rows)
    xmax = max(r[0] for r in rows)
    ymax = max(r[1] for r in rows)
    zmax = max(r[2] for r in rows)
    inverse_edge = 1.0 / edge

    def cube(value: float, minimum: float) -> int:
        return math.floor((value - minimum) * inverse_edge + 0.5)

    ixmax = cube(xmax, xmin) + 1
    iymax = cube(ymax, ymin) + 1
    izmax = cube(zmax, zmin) + 1
    columns = ixmax * iymax

    # Lines 1-4: one pass builds V and the unsorted list L.
    V = set()
    L = []
    cube_of_point = []
    for x, y, z in rows:
        index = cube(x, xmin) + cube(y, ymin) * ixmax + cube(z, zmin) * columns
        cube_of_point.append(index)
        if index not in V:
            V.add(index)
            L.append(index)
    L.sort()

    # Lines 5-15: sweep L ascending; M holds the index of each column's ground cube.
    M = {}
    R = []
    for index in L:
        column = index % columns
        ground = M.get(column, -1)
        if ground == -1:
            M[column] = index
        else:
            empty_cubes = (index - ground) // columns - 1
            if empty_cubes < sigma:
                M[column] = index
            else:
                R.append(index)  # collapsed; the ground does not move
    removed = set(R)
    overhang = np.array([index in removed for index in cube_of_point], dtype=bool)
    return NaiveResult(
        overhang,
        np.array(L, dtype=np.int64),
        np.array(R, dtype=np.int64),
        (ixmax, iymax, izmax),
        (xmin, ymin, zmin),
        cube_of_point,
    )


def assert_same_as_naive(result, reference: NaiveResult) -> None:
    np.testing.assert_array_equal(result.overhang, reference.overhang)
    np.testing.assert_array_equal(result.occupied_cubes, reference.occupied)
    np.testing.assert_array_equal(result.removed_cubes, reference.removed)
    assert result.num_overhang == int(reference.overhang.sum())
    if reference.counts is not None:
        assert (result.grid.ixmax, result.grid.iymax, result.grid.izmax) == reference.counts
        assert tuple(result.grid.min_corner) == reference.min_corner


def assert_all_storages_match_naive(points, edge: float, sigma: int) -> NaiveResult:
    reference = naive_algorithm1(points, edge, sigma)
    for storage in STORAGES:
        result = tc.collapse_overhangs(points, edge, sigma, storage=storage)
        assert_same_as_naive(result, reference)
        if storage != "auto" and result.num_used > 0:
            assert result.storage_used == storage
    return reference


# --------------------------------------------------------------------------------------------
# Scenes.
# --------------------------------------------------------------------------------------------


def make_scene(seed: int, size: float = 20.0) -> np.ndarray:
    """Ground with trees (continuous trunks, crowns over open ground), a wall, a balcony slab and
    a few floating points, as float64 (N, 3). Coordinates are uniform random, so no point sits on
    a cube boundary."""
    rng = np.random.default_rng(seed)

    def terrain(x, y):
        return 0.3 * np.sin(x / 3.0) + 0.2 * np.cos(y / 4.0)

    parts = []
    xy = rng.uniform(0.0, size, (6000, 2))
    parts.append(np.column_stack([xy, terrain(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.02, len(xy))]))
    for _ in range(4):  # trees
        cx, cy = rng.uniform(3.0, size - 3.0, 2)
        base = terrain(cx, cy)
        h = rng.uniform(0.0, 2.5, 400)
        a = rng.uniform(0, 2 * np.pi, 400)
        parts.append(np.column_stack([cx + 0.15 * np.cos(a), cy + 0.15 * np.sin(a), base + h]))
        d = rng.normal(size=(1200, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        crown = np.array([cx, cy, base + 4.5]) + d * np.array([2.2, 2.2, 1.5])
        parts.append(crown)
    # A wall: continuous from the ground up, never removed.
    wy = rng.uniform(2.0, 8.0, 1500)
    wz = rng.uniform(0.0, 3.0, 1500)
    parts.append(np.column_stack([np.full(1500, size * 0.75) + rng.normal(0, 0.01, 1500), wy, wz]))
    # A balcony slab 3 m over the ground.
    bx = rng.uniform(size * 0.25, size * 0.4, 800)
    by = rng.uniform(size * 0.6, size * 0.8, 800)
    parts.append(np.column_stack([bx, by, 3.0 + rng.normal(0, 0.03, 800)]))
    # Floating points.
    parts.append(np.column_stack([rng.uniform(0, size, (40, 2)), rng.uniform(1.0, 6.0, 40)]))
    cloud = np.concatenate(parts)
    return cloud[rng.permutation(len(cloud))]


def column_cloud(z_values, x: float = 0.0, y: float = 0.0) -> np.ndarray:
    return np.array([[x, y, float(z)] for z in z_values], dtype=np.float64)


# --------------------------------------------------------------------------------------------
# Agreement with the reference.
# --------------------------------------------------------------------------------------------


@st.composite
def small_clouds(draw):
    """Up to ~300 points within a few metres: lattice values (exact ties at half an edge when the
    edge is a multiple of the step), free floats and duplicated rows; float32 or float64."""
    step = draw(st.sampled_from([0.25, 0.5, 0.1, 1.0 / 3.0, 1.0]))
    lattice_xy = st.integers(-3, 3).map(lambda k: k * step)
    lattice_z = st.integers(-15, 15).map(lambda k: k * step)
    free_xy = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
    free_z = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)
    xy = st.one_of(lattice_xy, free_xy)
    z = st.one_of(lattice_z, free_z)
    pool_size = draw(st.integers(1, 150))
    pool = draw(st.lists(st.tuples(xy, xy, z), min_size=pool_size, max_size=pool_size))
    n = draw(st.integers(0, 300))
    picks = draw(st.lists(st.integers(0, len(pool) - 1), min_size=n, max_size=n))
    cloud = np.array([pool[i] for i in picks], dtype=np.float64).reshape(-1, 3)
    if draw(st.booleans()):
        cloud = cloud.astype(np.float32)
    return cloud


@HYPOTHESIS
@given(
    cloud=small_clouds(),
    edge=st.sampled_from([0.1, 0.25, 0.3, 0.5, 1.0, 0.7]),
    sigma=st.integers(1, 6),
)
def test_hypothesis_clouds_match_naive_algorithm1_for_every_storage(cloud, edge, sigma):
    assert_all_storages_match_naive(cloud, edge, sigma)


@pytest.mark.parametrize(
    ("seed", "edge", "sigma"), [(0, 0.5, 2), (1, 0.25, 4), (2, 0.2, 1), (3, 0.5, 5), (4, 1.0, 1)]
)
def test_random_scenes_match_naive_algorithm1_for_every_storage(seed, edge, sigma):
    cloud = make_scene(seed)
    reference = assert_all_storages_match_naive(cloud, edge, sigma)
    # The scene must exercise both outcomes, or the comparison proves little.
    assert 0 < len(reference.removed) < len(reference.occupied)
    assert 0 < reference.overhang.sum() < len(cloud)


@pytest.mark.parametrize(("edge", "sigma"), [(0.5, 2), (0.2, 5)])
def test_kitti_frame0_matches_naive_algorithm1_for_every_storage(shared_data, edge, sigma):
    xyzi = shared_data.kitti_xyzi(0)
    xyz = xyzi[:, :3]  # strided float32 view, no copy
    assert not xyz.flags.c_contiguous
    reference = assert_all_storages_match_naive(xyz, edge, sigma)
    assert len(reference.removed) > 0


def test_ouster_scan_matches_naive_algorithm1_for_every_storage(shared_data):
    xyzi = shared_data.ouster_xyzi()
    reference = assert_all_storages_match_naive(xyzi[:, :3], 0.5, 2)
    assert len(reference.removed) > 0


@pytest.mark.parametrize("num_threads", [2, 0])
def test_kitti_and_ouster_scans_on_several_threads_match_naive_algorithm1(shared_data, num_threads):
    for xyz in (shared_data.kitti_xyzi(0)[:, :3], shared_data.ouster_xyzi()[:, :3].astype(np.float64)):
        reference = naive_algorithm1(xyz, 0.5, 2)
        result = tc.collapse_overhangs(xyz, 0.5, 2, num_threads=num_threads)
        assert_same_as_naive(result, reference)
        assert result.num_overhang == int(result.overhang.sum()) > 0


@pytest.mark.parametrize("num_threads", [-1, 2.5, False])
def test_num_threads_that_is_not_a_whole_number_at_least_zero_raises_value_error(num_threads):
    with pytest.raises(ValueError, match="num_threads"):
        tc.collapse_overhangs(np.zeros((4, 3)), num_threads=num_threads)


# --------------------------------------------------------------------------------------------
# Hand-made columns (edge 1, points at integer heights).
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sigma", [1, 2, 3, 5])
def test_gap_of_sigma_minus_one_empty_cubes_keeps_the_cube_as_ground(sigma):
    # Cubes 0 and sigma: the cubes 1..sigma-1 between them are empty, sigma - 1 of them.
    for storage in STORAGES:
        result = tc.collapse_overhangs(column_cloud([0, sigma]), 1.0, sigma, storage=storage)
        assert not result.overhang.any()
        assert len(result.removed_cubes) == 0


@pytest.mark.parametrize("sigma", [1, 2, 3, 5])
@pytest.mark.parametrize("extra", [0, 1])
def test_gap_of_sigma_or_sigma_plus_one_empty_cubes_collapses_the_cube(sigma, extra):
    top = sigma + 1 + extra  # sigma + extra empty cubes between 0 and top
    for storage in STORAGES:
        result = tc.collapse_overhangs(column_cloud([0, top]), 1.0, sigma, storage=storage)
        np.testing.assert_array_equal(result.overhang, [False, True])
        # One column (ixmax = iymax = 1): I = iz.
        np.testing.assert_array_equal(result.removed_cubes, [top])


def test_several_overhang_layers_in_one_column_all_collapse_measured_from_the_ground():
    # sigma 2, ground at 0. Cube 3 collapses (2 empty). Cube 4 sits right on the collapsed cube 3
    # but the ground did not move, so it is 3 empty cubes above the ground and collapses too;
    # likewise 5 and 9.
    z = [0, 3, 4, 5, 9]
    for storage in STORAGES:
        result = tc.collapse_overhangs(column_cloud(z), 1.0, 2, storage=storage)
        np.testing.assert_array_equal(result.overhang, [False, True, True, True, True])
        np.testing.assert_array_equal(result.removed_cubes, [3, 4, 5, 9])


def test_staircase_ground_climbs_through_gaps_smaller_than_sigma():
    # sigma 2: gaps of one empty cube keep moving the ground up 0 -> 2 -> 4 -> 6 -> 8; cube 11
    # is 2 empty cubes over the ground at 8 and collapses.
    z = [0, 2, 4, 6, 8, 11]
    for storage in STORAGES:
        result = tc.collapse_overhangs(column_cloud(z), 1.0, 2, storage=storage)
        np.testing.assert_array_equal(result.overhang, [False] * 5 + [True])
        np.testing.assert_array_equal(result.removed_cubes, [11])


def test_single_cube_columns_are_ground_at_any_height():
    # Four columns with one cube each, at very different heights: each is its column's ground.
    cloud = np.array([[0, 0, 0], [1, 0, 10], [0, 1, 25], [1, 1, 7]], dtype=np.float64)
    for storage in STORAGES:
        result = tc.collapse_overhangs(cloud, 1.0, 1, storage=storage)
        assert not result.overhang.any()
        assert len(result.removed_cubes) == 0
        assert len(result.occupied_cubes) == 4


def test_two_by_two_columns_remove_the_hand_computed_cube_indices():
    # edge 1, sigma 2, ixmax = iymax = 2, izmax = 8: I = ix + 2 iy + 4 iz.
    #   column (0,0): z 0, 3        -> 3 has 2 empty cubes over 0: R gets I = 0 + 0 + 12 = 12
    #   column (1,0): z 1, 2, 5     -> 2 is ground, 5 has 2 empty over 2: I = 1 + 0 + 20 = 21
    #   column (0,1): z 4           -> ground only
    #   column (1,1): z 0, 2, 4, 7  -> 2 and 4 climb, 7 has 2 empty over 4: I = 1 + 2 + 28 = 31
    cloud = np.array(
        [
            [0, 0, 0], [0, 0, 3],
            [1, 0, 1], [1, 0, 2], [1, 0, 5],
            [0, 1, 4],
            [1, 1, 0], [1, 1, 2], [1, 1, 4], [1, 1, 7],
        ],
        dtype=np.float64,
    )  # fmt: skip
    expected_mask = [False, True, False, False, True, False, False, False, False, True]
    expected_occupied = [0, 3, 5, 9, 11, 12, 18, 19, 21, 31]
    for storage in STORAGES:
        result = tc.collapse_overhangs(cloud, 1.0, 2, storage=storage)
        assert (result.grid.ixmax, result.grid.iymax, result.grid.izmax) == (2, 2, 8)
        np.testing.assert_array_equal(result.removed_cubes, [12, 21, 31])
        np.testing.assert_array_equal(result.occupied_cubes, expected_occupied)
        np.testing.assert_array_equal(result.overhang, expected_mask)
        assert result.num_overhang == 3


def test_points_sharing_a_cube_share_its_fate_and_ties_round_half_up():
    # edge 1, xmin = 0: z = 2.5 lies exactly on a half and rounds up into cube 3, joining the
    # point at z = 3.2; z = 2.4999 rounds down into cube 2 and stays next to the ground.
    cloud = column_cloud([0.0, 2.5, 3.2, 0.4])
    result = tc.collapse_overhangs(cloud, 1.0, 2)
    np.testing.assert_array_equal(result.overhang, [False, True, True, False])
    np.testing.assert_array_equal(result.removed_cubes, [3])
    cloud = column_cloud([0.0, 2.4999])
    result = tc.collapse_overhangs(cloud, 1.0, 2)
    assert not result.overhang.any()


# --------------------------------------------------------------------------------------------
# Input types and layouts.
# --------------------------------------------------------------------------------------------


def test_float32_and_float64_inputs_of_the_same_values_give_identical_results():
    cloud32 = make_scene(5).astype(np.float32)
    a = tc.collapse_overhangs(cloud32, 0.5, 2)
    b = tc.collapse_overhangs(cloud32.astype(np.float64), 0.5, 2)
    np.testing.assert_array_equal(a.overhang, b.overhang)
    np.testing.assert_array_equal(a.occupied_cubes, b.occupied_cubes)
    np.testing.assert_array_equal(a.removed_cubes, b.removed_cubes)
    np.testing.assert_array_equal(a.grid.min_corner, b.grid.min_corner)
    assert a.num_overhang > 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_contiguous_fortran_strided_and_reversed_layouts_give_identical_results(dtype):
    cloud = make_scene(6).astype(dtype)
    expected = tc.collapse_overhangs(np.ascontiguousarray(cloud), 0.5, 2)
    assert expected.num_overhang > 0

    fortran = np.asfortranarray(cloud)
    assert fortran.flags.f_contiguous and not fortran.flags.c_contiguous
    np.testing.assert_array_equal(tc.collapse_overhangs(fortran, 0.5, 2).overhang, expected.overhang)

    xyzi = np.column_stack([cloud, np.arange(len(cloud), dtype=dtype)])
    strided = xyzi[:, :3]
    assert not strided.flags.c_contiguous
    np.testing.assert_array_equal(tc.collapse_overhangs(strided, 0.5, 2).overhang, expected.overhang)

    reversed_rows = cloud[::-1]
    np.testing.assert_array_equal(
        tc.collapse_overhangs(reversed_rows, 0.5, 2).overhang[::-1], expected.overhang
    )

    every_other = cloud[::2]
    np.testing.assert_array_equal(
        tc.collapse_overhangs(every_other, 0.5, 2).overhang,
        tc.collapse_overhangs(every_other.copy(), 0.5, 2).overhang,
    )
    np.testing.assert_array_equal(
        tc.collapse_overhangs(every_other, 0.5, 2).overhang,
        naive_algorithm1(every_other, 0.5, 2).overhang,
    )


def test_misaligned_packed_structured_field_gives_identical_results():
    cloud = make_scene(7)
    packed = np.zeros(len(cloud), dtype=np.dtype([("flag", "u1"), ("xyz", "<f8", (3,))], align=False))
    packed["xyz"] = cloud
    view = packed["xyz"]
    assert view.strides[0] % 8 != 0  # the bindings must copy this one
    np.testing.assert_array_equal(
        tc.collapse_overhangs(view, 0.5, 2).overhang, tc.collapse_overhangs(cloud, 0.5, 2).overhang
    )


def test_python_list_input_is_accepted_as_float64():
    cloud = make_scene(8)[:500]
    from_list = tc.collapse_overhangs(cloud.tolist(), 0.5, 2)
    from_array = tc.collapse_overhangs(cloud, 0.5, 2)
    np.testing.assert_array_equal(from_list.overhang, from_array.overhang)
    np.testing.assert_array_equal(from_list.removed_cubes, from_array.removed_cubes)
    hand = tc.collapse_overhangs([[0, 0, 0], [0, 0, 3]], 1.0, 2)  # integers in a list are fine
    np.testing.assert_array_equal(hand.overhang, [False, True])


def test_params_dataclass_overrides_the_keyword_arguments():
    cloud = make_scene(9)
    params = tc.CollapseParams(edge=0.25, sigma=3, storage="sparse")
    via_params = tc.collapse_overhangs(cloud, 5.0, 1, params=params)
    via_kwargs = tc.collapse_overhangs(cloud, 0.25, 3, storage="sparse")
    np.testing.assert_array_equal(via_params.overhang, via_kwargs.overhang)
    assert via_params.storage_used == "sparse"
    assert via_params.grid.edge == 0.25


# --------------------------------------------------------------------------------------------
# Leveling and crop.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("roll", "pitch"), [(0.15, -0.1), (-0.05, 0.2), (0.3, 0.0)])
def test_tilted_scene_with_leveling_transform_gives_the_level_scene_mask(roll, pitch):
    level = make_scene(10)
    rotation = tc.leveling_transform(roll, pitch)[:3, :3]
    tilted = level @ rotation  # rows of R^T p: what a sensor with this attitude sees
    expected = tc.collapse_overhangs(level, 0.5, 2)
    assert expected.num_overhang > 0
    for storage in STORAGES:
        leveled = tc.collapse_overhangs(
            tilted, 0.5, 2, transform=tc.leveling_transform(roll, pitch), storage=storage
        )
        np.testing.assert_array_equal(leveled.overhang, expected.overhang)
        np.testing.assert_array_equal(leveled.removed_cubes, expected.removed_cubes)
    # Without leveling, the tilt changes the answer: the transform is really applied.
    unleveled = tc.collapse_overhangs(tilted, 0.5, 2)
    assert not np.array_equal(unleveled.overhang, expected.overhang)


def test_leveling_transform_is_ry_pitch_times_rx_roll():
    for roll, pitch in [(0.0, 0.0), (0.1, -0.2), (-1.0, 0.7), (np.pi / 2, 0.3)]:
        cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
        rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        expected = np.eye(4)
        expected[:3, :3] = ry @ rx
        np.testing.assert_allclose(tc.leveling_transform(roll, pitch), expected, atol=1e-15)


def test_attitude_from_gravity_levels_an_accelerometer_reading():
    """A reading at rest is g along the sensor frame's up: the attitude found levels it onto +z
    and is the one the sensor was given (any heading, any length of the reading)."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        roll, pitch, yaw = rng.uniform(-1.4, 1.4, 3)
        turn = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        world_sensor = turn @ tc.leveling_transform(roll, pitch)[:3, :3]
        reading = rng.uniform(0.5, 20.0) * world_sensor.T @ [0.0, 0.0, 1.0]
        got = tc.attitude_from_gravity(reading)
        np.testing.assert_allclose(got, (roll, pitch), atol=1e-12)
        leveled = tc.leveling_transform(*got)[:3, :3] @ reading
        np.testing.assert_allclose(leveled / np.linalg.norm(leveled), [0.0, 0.0, 1.0], atol=1e-12)
    for bad in ([0.0, 0.0, 0.0], [np.nan, 0.0, 9.8], [np.inf, 0.0, 9.8]):
        with pytest.raises(ValueError, match="finite and not zero"):
            tc.attitude_from_gravity(bad)
    with pytest.raises(ValueError, match=r"\(3,\) vector"):
        tc.attitude_from_gravity([0.0, 9.8])


def test_rigid_transform_with_translation_gives_the_untransformed_mask():
    cloud = make_scene(11)
    transform = np.eye(4)
    transform[:3, 3] = [3.25, -7.5, 1.0]
    moved = tc.collapse_overhangs(cloud, 0.5, 2, transform=transform)
    np.testing.assert_array_equal(moved.overhang, tc.collapse_overhangs(cloud, 0.5, 2).overhang)
    np.testing.assert_allclose(moved.grid.min_corner, cloud.min(axis=0) + [3.25, -7.5, 1.0], atol=1e-12)


def inside_box(points: np.ndarray, lo, hi) -> np.ndarray:
    return np.all((points >= np.asarray(lo)) & (points <= np.asarray(hi)), axis=1)


def test_crop_excludes_points_which_are_never_overhang_and_are_counted():
    cloud = make_scene(12)
    lo, hi = (2.0, 3.0, -1.0), (15.0, 18.0, 5.0)
    inside = inside_box(cloud, lo, hi)
    assert 0 < inside.sum() < len(cloud)
    reference = naive_algorithm1(cloud[inside], 0.5, 2)
    assert reference.overhang.any()
    for storage in STORAGES:
        result = tc.collapse_overhangs(cloud, 0.5, 2, crop=(lo, hi), storage=storage)
        assert result.num_points == len(cloud)
        assert result.num_cropped == int((~inside).sum())
        assert result.num_used == int(inside.sum())
        assert not result.overhang[~inside].any()
        np.testing.assert_array_equal(result.overhang[inside], reference.overhang)
        np.testing.assert_array_equal(result.removed_cubes, reference.removed)
        assert tuple(result.grid.min_corner) == reference.min_corner


def test_crop_below_the_canopy_base_turns_the_canopy_into_ground():
    # A slab 3 m over a ground plane collapses; cropping the ground away leaves the slab as the
    # lowest cube of every column, so nothing collapses and the ground rows count as cropped.
    rng = np.random.default_rng(13)
    ground = np.column_stack([rng.uniform(0, 5, (400, 2)), rng.normal(0, 0.02, 400)])
    slab = np.column_stack([rng.uniform(0, 5, (400, 2)), 3.0 + rng.normal(0, 0.02, 400)])
    cloud = np.concatenate([ground, slab])
    full = tc.collapse_overhangs(cloud, 0.5, 2)
    assert full.overhang[400:].mean() > 0.9 and not full.overhang[:400].any()
    cropped = tc.collapse_overhangs(cloud, 0.5, 2, crop=((-1, -1, 1.0), (6, 6, 10)))
    assert cropped.num_cropped == 400
    assert not cropped.overhang.any()


def test_crop_is_applied_in_the_leveled_frame():
    level = make_scene(14)
    roll, pitch = 0.1, -0.12
    tilted = level @ tc.leveling_transform(roll, pitch)[:3, :3]
    lo, hi = (1.0, 1.0, -0.5), (17.0, 19.0, 4.0)
    inside = inside_box(level, lo, hi)
    expected = tc.collapse_overhangs(level, 0.5, 2, crop=(lo, hi))
    got = tc.collapse_overhangs(tilted, 0.5, 2, crop=(lo, hi), transform=tc.leveling_transform(roll, pitch))
    assert got.num_cropped == expected.num_cropped == int((~inside).sum())
    np.testing.assert_array_equal(got.overhang, expected.overhang)
    assert expected.num_overhang > 0


# --------------------------------------------------------------------------------------------
# Grid geometry (eqs. 1-9).
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("seed", "edge"), [(15, 0.5), (16, 0.3), (17, 1.0)])
def test_grid_counts_and_min_corner_follow_the_definition(seed, edge):
    cloud = make_scene(seed) + np.array([-40.0, 12.5, 100.0])
    result = tc.collapse_overhangs(cloud, edge, 2)
    grid = result.grid
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    np.testing.assert_array_equal(grid.min_corner, lo)
    counts = [math.floor((hi[a] - lo[a]) * (1.0 / edge) + 0.5) + 1 for a in range(3)]
    assert [grid.ixmax, grid.iymax, grid.izmax] == counts
    assert grid.edge == edge
    assert grid.num_cubes == counts[0] * counts[1] * counts[2]
    assert grid.num_columns == counts[0] * counts[1]


def test_grid_coordinates_and_centers_invert_the_cube_index():
    cloud = make_scene(18)
    edge = 0.4
    result = tc.collapse_overhangs(cloud, edge, 2)
    grid = result.grid
    reference = naive_algorithm1(cloud, edge, 2)
    coordinates = grid.coordinates(result.occupied_cubes)
    assert coordinates.shape == (len(result.occupied_cubes), 3)
    ix, iy, iz = coordinates.T
    assert ix.min() >= 0 and iy.min() >= 0 and iz.min() >= 0
    assert ix.max() < grid.ixmax and iy.max() < grid.iymax and iz.max() < grid.izmax
    np.testing.assert_array_equal(ix + iy * grid.ixmax + iz * grid.ixmax * grid.iymax, result.occupied_cubes)

    # Every point's cube: its coordinates are the point's quantised coordinates and the point
    # lies within half an edge of the cube's centre.
    per_point = np.array(reference.cube_of_point, dtype=np.int64)
    quantised = np.floor((cloud - cloud.min(axis=0)) * (1.0 / edge) + 0.5).astype(np.int64)
    np.testing.assert_array_equal(grid.coordinates(per_point), quantised)
    centers = grid.centers(per_point)
    np.testing.assert_allclose(centers, cloud.min(axis=0) + edge * quantised, rtol=0, atol=1e-12)
    assert np.all(np.abs(cloud - centers) <= edge / 2 + 1e-9)

    with pytest.raises(IndexError, match="out of the grid"):
        grid.coordinates(np.array([grid.num_cubes], dtype=np.int64))
    with pytest.raises(IndexError, match="out of the grid"):
        grid.centers(np.array([-1], dtype=np.int64))


def test_result_counters_and_repr_describe_the_run():
    cloud = make_scene(19)
    result = tc.collapse_overhangs(cloud, 0.5, 2)
    assert result.num_points == result.num_used == len(cloud)
    assert result.num_cropped == 0 and result.num_dropped_non_finite == 0
    assert result.num_overhang == int(result.overhang.sum()) > 0
    text = repr(result)
    assert f"points={len(cloud)}" in text
    assert f"overhang={result.num_overhang}" in text
    assert f"removed_cubes={len(result.removed_cubes)}" in text
    assert "CubeGrid(" in repr(result.grid)


def test_sigma_from_robot_height_is_ceil_of_height_over_edge_and_at_least_one():
    assert tc.sigma_from_robot_height(2.5, 0.5) == 5
    assert tc.sigma_from_robot_height(2.6, 0.5) == 6
    assert tc.sigma_from_robot_height(1.0, 0.3) == 4
    assert tc.sigma_from_robot_height(0.1, 0.5) == 1
    for bad in [(0.0, 0.5), (-1.0, 0.5), (1.0, 0.0), (float("nan"), 0.5), (1.0, float("inf"))]:
        with pytest.raises(ValueError):
            tc.sigma_from_robot_height(*bad)


@HYPOTHESIS
@given(
    height=st.floats(0.01, 50.0, allow_nan=False),
    edge=st.floats(0.01, 5.0, allow_nan=False),
)
def test_sigma_from_robot_height_is_the_ceil_of_the_decimal_ratio(height, edge):
    # The reference divides the decimal lengths exactly (fractions); a ratio within 1e-9 of a
    # whole number counts as that number (documented tolerance: 2.1 / 0.3 is 7).
    ratio = Fraction(repr(height)) / Fraction(repr(edge))
    nearest = round(ratio)
    expected = nearest if abs(ratio - nearest) <= Fraction(1, 10**9) * max(1, nearest) else math.ceil(ratio)
    assert tc.sigma_from_robot_height(height, edge) == max(1, expected)


def test_sigma_from_robot_height_is_exact_for_decimal_lengths():
    # Binary floating point gives 2.1 / 0.3 = 7.000000000000001 (a plain ceil: 8).
    assert tc.sigma_from_robot_height(2.1, 0.3) == 7
    assert tc.sigma_from_robot_height(2.1, 0.7) == 3
    assert tc.sigma_from_robot_height(2.7, 0.3) == 9
    assert tc.sigma_from_robot_height(0.9, 0.5) == 2  # [CBC] section IV-B


# --------------------------------------------------------------------------------------------
# Storage.
# --------------------------------------------------------------------------------------------


def two_far_clusters():
    """Two scenes 10 km apart, each shifted so that its own minimum is an exact anchor; the
    halves' grids are then aligned and each half alone must give the same mask."""
    a = make_scene(20, size=6.0)
    a = a - a.min(axis=0)
    b = make_scene(21, size=6.0)
    b = b - b.min(axis=0) + np.array([10000.0, 10000.0, 0.0])
    return a, b


def test_ten_km_cloud_at_5cm_uses_sparse_storage_and_each_half_is_unchanged():
    a, b = two_far_clusters()
    both = np.concatenate([a, b])
    result = tc.collapse_overhangs(both, 0.05, 4)
    assert result.storage_used == "sparse"
    assert result.grid.ixmax > 200_000 and result.grid.iymax > 200_000
    alone_a = tc.collapse_overhangs(a, 0.05, 4)
    alone_b = tc.collapse_overhangs(b, 0.05, 4)
    assert alone_a.num_overhang > 0 and alone_b.num_overhang > 0
    np.testing.assert_array_equal(result.overhang[: len(a)], alone_a.overhang)
    np.testing.assert_array_equal(result.overhang[len(a) :], alone_b.overhang)
    assert len(result.removed_cubes) == len(alone_a.removed_cubes) + len(alone_b.removed_cubes)
    assert_same_as_naive(result, naive_algorithm1(both, 0.05, 4))
    explicit = tc.collapse_overhangs(both, 0.05, 4, storage="sparse")
    np.testing.assert_array_equal(explicit.overhang, result.overhang)


def test_dense_storage_refuses_a_ten_km_cloud_at_5cm():
    a, b = two_far_clusters()
    with pytest.raises(ValueError, match="dense"):
        tc.collapse_overhangs(np.concatenate([a, b]), 0.05, 4, storage="dense")


def test_small_cloud_uses_dense_storage_on_auto():
    assert tc.collapse_overhangs(make_scene(22), 0.5, 2).storage_used == "dense"


# --------------------------------------------------------------------------------------------
# Bad inputs.
# --------------------------------------------------------------------------------------------


def test_nan_and_inf_rows_raise_value_error_naming_count_and_first_row():
    cloud = np.array([[0, 0, 0], [np.nan, 0, 0], [0, 0, 1], [0, np.inf, 0]], dtype=np.float64)
    with pytest.raises(ValueError, match=r"2 of 4 point rows contain NaN or Inf \(first at row 1\)"):
        tc.collapse_overhangs(cloud)
    with pytest.raises(ValueError, match=r"1 of 3 point rows contain NaN or Inf \(first at row 2\)"):
        tc.collapse_overhangs(np.array([[0, 0, 0], [1, 1, 1], [0, 0, -np.inf]], dtype=np.float32))


def test_drop_non_finite_drops_rows_as_never_overhang_and_counts_them():
    cloud = column_cloud([0, 3, 1, 4])
    cloud[2] = [np.nan, 0, 0]
    cloud = np.insert(cloud, 1, [0, -np.inf, 5], axis=0)  # rows: 0, inf, 3, nan, 4
    for storage in STORAGES:
        result = tc.collapse_overhangs(cloud, 1.0, 2, drop_non_finite=True, storage=storage)
        assert result.num_dropped_non_finite == 2
        assert result.num_used == 3
        np.testing.assert_array_equal(result.overhang, [False, False, True, False, True])
        finite = np.isfinite(cloud).all(axis=1)
        assert_same_as_naive(result, _naive_on_subset(cloud, finite, 1.0, 2))


def _naive_on_subset(cloud, keep, edge, sigma):
    reference = naive_algorithm1(cloud[keep], edge, sigma)
    full = np.zeros(len(cloud), dtype=bool)
    full[keep] = reference.overhang
    reference.overhang = full
    return reference


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_empty_cloud_gives_a_valid_empty_result(dtype):
    result = tc.collapse_overhangs(np.zeros((0, 3), dtype=dtype))
    assert result.overhang.shape == (0,) and result.overhang.dtype == bool
    assert result.occupied_cubes.shape == (0,) and result.occupied_cubes.dtype == np.int64
    assert result.removed_cubes.shape == (0,)
    assert result.num_points == result.num_used == result.num_overhang == 0


def test_all_rows_cropped_or_dropped_gives_an_empty_grid():
    cloud = np.array([[0, 0, 0], [np.nan, 0, 0], [5, 5, 5]], dtype=np.float64)
    result = tc.collapse_overhangs(cloud, crop=((10, 10, 10), (20, 20, 20)), drop_non_finite=True)
    assert result.num_used == 0 and result.num_cropped == 2 and result.num_dropped_non_finite == 1
    assert not result.overhang.any() and len(result.occupied_cubes) == 0


@pytest.mark.parametrize("shape", [(5, 2), (5, 17), (3,), (2, 3, 3), (0,)])
def test_wrong_shape_raises_value_error_naming_the_expected_shape(shape):
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        tc.collapse_overhangs(np.zeros(shape, dtype=np.float64))


def test_a_cloud_stored_by_columns_is_refused_with_the_hint_to_transpose_it():
    with pytest.raises(
        ValueError, match=r"got shape \(4, 100\): a cloud stored by columns\? pass its transpose"
    ):
        tc.collapse_overhangs(np.zeros((4, 100), dtype=np.float32))


def assert_maps_agree(points, reference) -> None:
    """Every map entry point (build_elevation_map, dem_without_overhangs, LocalMap.update,
    Mapper.add_scan) gives `points` what it gives `reference`, bit for bit."""
    for build in (tc.build_elevation_map, lambda cloud: tc.dem_without_overhangs(cloud)[0]):
        got, expected = build(points), build(reference)
        for layer in expected.layers:
            np.testing.assert_array_equal(got[layer], expected[layer], err_msg=layer)
    local = [tc.LocalMap(length=10.0, resolution=0.2) for _ in range(2)]
    for local_map, cloud in zip(local, (points, reference), strict=True):
        local_map.update(cloud, np.eye(4))
    np.testing.assert_array_equal(local[0]["elevation"], local[1]["elevation"])
    mappers = [tc.Mapper(), tc.Mapper()]
    for mapper, cloud in zip(mappers, (points, reference), strict=True):
        mapper.add_scan(cloud, np.eye(4))
    np.testing.assert_array_equal(mappers[0].global_map()["max"], mappers[1].global_map()["max"])


def test_wider_rows_give_what_their_x_y_z_give_everywhere(shared_data):
    """KITTI's (N, 4) rows (x, y, z, intensity), read in place, give every entry point the result
    of a separate (N, 3) copy of their x, y, z."""
    rows = shared_data.kitti_xyzi(0)
    xyz = np.ascontiguousarray(rows[:, :3])
    assert rows.shape[1] == 4 and rows.flags.c_contiguous
    np.testing.assert_array_equal(tc.collapse_overhangs(rows).overhang, tc.collapse_overhangs(xyz).overhang)
    np.testing.assert_array_equal(
        tc.collapse_overhangs(rows, 0.5, 4, method="shadow_aware").overhang,
        tc.collapse_overhangs(xyz, 0.5, 4, method="shadow_aware").overhang,
    )
    assert_maps_agree(rows, xyz)


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.float16, np.complex128, np.uint8])
def test_other_dtypes_raise_type_error_naming_float32_and_float64(dtype):
    with pytest.raises(TypeError, match="float32 or float64"):
        tc.collapse_overhangs(np.zeros((4, 3), dtype=dtype))


@pytest.mark.parametrize("edge", [0.0, -0.5, float("nan"), float("inf")])
def test_non_positive_or_non_finite_edge_raises_value_error(edge):
    with pytest.raises(ValueError, match="edge"):
        tc.collapse_overhangs(make_scene(23)[:100], edge, 2)


@pytest.mark.parametrize("sigma", [0, -1, -100])
def test_sigma_below_one_raises_value_error(sigma):
    with pytest.raises(ValueError, match="sigma"):
        tc.collapse_overhangs(make_scene(23)[:100], 0.5, sigma)


@pytest.mark.parametrize("sigma", [2**31, 2**40])
def test_sigma_beyond_32_bits_raises_value_error(sigma):
    with pytest.raises(ValueError, match="sigma"):
        tc.collapse_overhangs(make_scene(23)[:100], 0.5, sigma)


def test_subnormal_edge_raises_value_error_saying_it_is_too_small():
    with pytest.raises(ValueError, match=r"edge \S+e-32\d m is too small"):
        tc.collapse_overhangs(np.zeros((1, 3)), 1e-320, 2)


@pytest.mark.parametrize(
    ("call", "text"),
    [
        (lambda: tc.collapse_overhangs(np.zeros((1, 3)), -0.25, 2), "edge must be .*, got -0.25$"),
        (lambda: tc.point_based_overhangs(np.zeros((1, 3)), edge=0.0), "edge must be .*, got 0$"),
        (
            lambda: tc.point_based_overhangs(np.zeros((1, 3)), variance_threshold=np.inf),
            "variance threshold must be .*, got inf$",
        ),
        (lambda: tc.build_elevation_map(np.zeros((1, 3)), 1e-400), "resolution must be .*, got 0$"),
        (lambda: tc.build_elevation_map(np.zeros((1, 3)), -3e-9), "resolution must be .*, got -3e-09$"),
    ],
)
def test_rejected_lengths_are_named_as_given(call, text):
    with pytest.raises(ValueError, match=text):
        call()


@pytest.mark.parametrize("storage", ["dense", "sparse"])
def test_empty_cloud_reports_the_requested_storage(storage):
    assert tc.collapse_overhangs(np.zeros((0, 3)), storage=storage).storage_used == storage


def test_fractional_sigma_raises_value_error():
    with pytest.raises(ValueError, match="sigma"):
        tc.collapse_overhangs(make_scene(23)[:100], 0.5, 2.5)


def test_extent_overflowing_a_64_bit_cube_index_raises_value_error():
    cloud = np.array([[0, 0, 0], [1e7, 1e7, 1e7]], dtype=np.float64)
    for storage in STORAGES:
        with pytest.raises(ValueError, match="overflows a 64-bit cube index"):
            tc.collapse_overhangs(cloud, 1e-3, 2, storage=storage)
    # One huge axis alone overflows too.
    with pytest.raises(ValueError, match="overflows a 64-bit cube index"):
        tc.collapse_overhangs(np.array([[0, 0, 0], [1e300, 0, 0]]), 0.5, 2)


def _non_rigid_transforms():
    scale = np.eye(4)
    scale[:3, :3] *= 2.0
    shear = np.eye(4)
    shear[0, 1] = 0.3
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    projective = np.eye(4)
    projective[3, 0] = 0.1
    nan = np.eye(4)
    nan[0, 3] = np.nan
    return {"scale": scale, "shear": shear, "mirror": mirror, "projective": projective, "nan": nan}


@pytest.mark.parametrize("name", sorted(_non_rigid_transforms()))
def test_non_rigid_transform_raises_value_error(name):
    transform = _non_rigid_transforms()[name]
    with pytest.raises(ValueError, match="rigid|NaN"):
        tc.collapse_overhangs(make_scene(24)[:100], 0.5, 2, transform=transform)


def test_malformed_transform_crop_and_storage_raise_value_error():
    cloud = make_scene(25)[:100]
    with pytest.raises(ValueError, match="4x4"):
        tc.collapse_overhangs(cloud, transform=np.eye(3))
    with pytest.raises(ValueError, match="crop"):
        tc.collapse_overhangs(cloud, crop=(0, 0, 0))
    with pytest.raises(ValueError, match="crop"):
        tc.collapse_overhangs(cloud, crop=((1, 1, 1), (0, 2, 2)))  # min > max on x
    with pytest.raises(ValueError, match="storage"):
        tc.collapse_overhangs(cloud, storage="bitmap")


# --------------------------------------------------------------------------------------------
# Memory ownership and the GIL.
# --------------------------------------------------------------------------------------------


def test_returned_arrays_stay_valid_after_the_result_object_is_gone():
    cloud = make_scene(26)
    expected = naive_algorithm1(cloud, 0.5, 2)
    mask = tc.collapse_overhangs(cloud, 0.5, 2).overhang
    occupied = tc.collapse_overhangs(cloud, 0.5, 2, storage="sparse").occupied_cubes
    removed = tc.collapse_overhangs(cloud, 0.5, 2, storage="dense").removed_cubes
    gc.collect()
    # Churn the allocator so that freed memory would be reused and overwritten.
    junk = [np.full(len(cloud), 7, dtype=np.int64) for _ in range(20)]
    del junk
    gc.collect()
    np.testing.assert_array_equal(mask, expected.overhang)
    np.testing.assert_array_equal(occupied, expected.occupied)
    np.testing.assert_array_equal(removed, expected.removed)
    assert mask.sum() == expected.overhang.sum() > 0


def test_result_arrays_are_views_into_the_result_object():
    result = tc.collapse_overhangs(make_scene(27), 0.5, 2)
    mask = result.overhang
    assert not mask.flags.owndata
    # Shared views of the result are read-only, so one cannot corrupt another.
    assert not mask.flags.writeable and not result.removed_cubes.flags.writeable
    with pytest.raises(ValueError):
        mask[0] = True
    # Two reads view the same memory: no per-access copy.
    assert mask.__array_interface__["data"][0] == result.overhang.__array_interface__["data"][0]


def _main_thread_increments_during_call(call) -> tuple:
    """Runs `call` in a worker that snapshots a counter right before and right after it, while
    the main thread increments the counter. Returns (increments seen by the worker, seconds)."""
    counter = [0]
    snapshots = {}
    done = threading.Event()

    def worker():
        snapshots["before"] = counter[0]
        start = time.perf_counter()
        try:
            snapshots["result"] = call()
        finally:
            snapshots["elapsed"] = time.perf_counter() - start
            snapshots["after"] = counter[0]
            done.set()

    old_interval = sys.getswitchinterval()
    # A long switch interval stops the interpreter from forcing a GIL hand-over while the worker
    # is inside the call: the main thread can then only run if the call released the GIL.
    sys.setswitchinterval(5.0)
    try:
        thread = threading.Thread(target=worker, daemon=True)
        thread.start()
        while not done.is_set():
            counter[0] += 1
            if counter[0] % 256 == 0:
                time.sleep(1e-4)  # lets the worker take the GIL back promptly once it is done
        thread.join(timeout=60)
    finally:
        sys.setswitchinterval(old_interval)
    assert "result" in snapshots, "the call raised in the worker thread"
    return snapshots["after"] - snapshots["before"], snapshots["elapsed"]


@pytest.mark.parametrize(
    "function",
    [
        lambda cloud: tc.collapse_overhangs(cloud, 0.5, 2),
        lambda cloud: tc.collapse_overhangs(cloud, 0.5, 2, storage="sparse"),
        lambda cloud: tc.octomap_column_overhangs(cloud, 5.0, 2),
        lambda cloud: tc.point_based_overhangs(cloud, 0.5, 2),
    ],
    ids=["collapse_dense", "collapse_sparse", "octomap", "point_based"],
)
def test_calls_release_the_gil_while_they_run(function):
    """The main thread keeps running Python while the call works in another thread. Up to three
    attempts absorb a loaded machine; a call holding the GIL never shows a single increment."""
    cloud = np.random.default_rng(28).uniform(0.0, 200.0, (300_000, 3))
    elapsed = []
    for _ in range(3):
        increments, seconds = _main_thread_increments_during_call(lambda: function(cloud))
        elapsed.append(seconds)
        if increments > 0:
            return
    if max(elapsed) < 0.005:
        pytest.skip(f"the calls took {max(elapsed) * 1e3:.2f} ms at most, too fast to observe")
    pytest.fail(f"the main thread never ran during calls of {[round(s, 3) for s in elapsed]} s")


@pytest.mark.parametrize("native", [np.float32, np.float64])
def test_points_in_the_other_byte_order_give_the_native_result_everywhere(native):
    """Big-endian rows (a file read with ``dtype=">f4"``, x, y, z, intensity) are converted once,
    at the entry point, and give what the native array gives; the caller's array is left as it is."""
    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(-4, 4, (3000, 2)), rng.normal(0.0, 0.02, 3000)])
    roof = np.column_stack([rng.uniform(-1, 1, (500, 2)), np.full(500, 2.5)])
    rows = np.column_stack([np.vstack([ground, roof]), rng.uniform(0, 1, 3500)]).astype(native)
    swapped = rows.astype(rows.dtype.newbyteorder())
    assert not swapped.dtype.isnative and swapped.dtype.byteorder != rows.dtype.byteorder
    before = swapped.copy()
    np.testing.assert_array_equal(
        tc.collapse_overhangs(swapped, 0.5, 2).overhang, tc.collapse_overhangs(rows, 0.5, 2).overhang
    )
    assert_maps_agree(swapped, rows)
    shifted = rows[:, :3].astype(np.float64) + (0.05, 0.0, 0.0)
    got = tc.register_points(shifted.astype(">f8"), swapped[:, :3])
    np.testing.assert_array_equal(got.transform, tc.register_points(shifted, rows[:, :3]).transform)
    assert swapped.dtype == before.dtype
    np.testing.assert_array_equal(swapped, before)
    if native is np.float32:  # float32 at a UTM northing is still flagged
        far = (rows + np.float32(4_500_000.0)).astype(">f4")
        with pytest.warns(UserWarning, match="float32 points reach"):
            tc.build_elevation_map(far, 0.1)
