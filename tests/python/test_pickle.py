"""Maps, overhang masks, fuzzy surfaces and every result object survive pickling: what
multiprocessing, Dask and joblib do to a result a worker returns, and what copy.deepcopy does.
Each round trip is compared field by field with the object it came from."""

from __future__ import annotations

import copy
import multiprocessing
import pickle

import numpy as np
import pytest
import terracube as tc


def scene(seed: int = 0) -> np.ndarray:
    """A 20 x 20 m slope with a box and a canopy slab over part of it (float32)."""
    rng = np.random.default_rng(seed)
    xy = rng.random((6000, 2)) * 20.0
    ground = np.c_[xy, 0.05 * xy[:, 0] + 0.02 * rng.standard_normal(len(xy))]
    box = np.c_[rng.random((800, 2)) * 2.0 + 4.0, rng.random(800) * 1.5]
    canopy = np.c_[rng.random((1500, 2)) * 6.0 + 10.0, 4.0 + 0.3 * rng.random(1500)]
    return np.vstack([ground, box, canopy]).astype(np.float32)


def assert_same_map(a: tc.ElevationMap, b: tc.ElevationMap) -> None:
    assert b.layers == a.layers  # the same layers in the same order
    assert b.resolution == a.resolution
    np.testing.assert_array_equal(b.geometry.origin, a.geometry.origin)
    np.testing.assert_array_equal(b.geometry.size, a.geometry.size)
    for name in a.layers:
        assert b[name].dtype == np.float32
        np.testing.assert_array_equal(b[name], a[name])  # NaN where NaN


def assert_same_collapse(a: tc.CollapseResult, b: tc.CollapseResult) -> None:
    for field in ("overhang", "occupied_cubes", "removed_cubes", "cube_reasons"):
        assert getattr(b, field).dtype == getattr(a, field).dtype
        np.testing.assert_array_equal(getattr(b, field), getattr(a, field))
    for field in (
        "num_points",
        "num_used",
        "num_cropped",
        "num_dropped_non_finite",
        "num_overhang",
        "storage_used",
    ):
        assert getattr(b, field) == getattr(a, field), field
    for field in ("edge", "ixmax", "iymax", "izmax"):
        assert getattr(b.grid, field) == getattr(a.grid, field), field
    np.testing.assert_array_equal(b.grid.min_corner, a.grid.min_corner)


@pytest.mark.parametrize("method", ["paper", "shadow_aware"])
@pytest.mark.parametrize("storage", ["dense", "sparse"])
def test_a_collapse_result_round_trips(method, storage):
    points = scene()
    params = tc.CollapseParams(0.5, 2, method=method, storage=storage)
    result = tc.collapse_overhangs(points, params=params)
    assert result.num_overhang > 0 and result.storage_used == storage
    back = pickle.loads(pickle.dumps(result))
    assert_same_collapse(result, back)
    assert (len(back.cube_reasons) > 0) == (method == "shadow_aware")
    if method == "shadow_aware":  # the restored result answers as the original does
        np.testing.assert_array_equal(
            tc.point_reasons(points, back, params=params), tc.point_reasons(points, result, params=params)
        )


def test_an_elevation_map_round_trips_and_deep_copies_apart():
    elevation = tc.build_elevation_map(scene(), 0.25)
    tc.classify_terrain(elevation)
    elevation["extra"] = np.full(tuple(elevation.geometry.size), 2.5, np.float32)
    assert np.isnan(elevation["max"]).any()  # empty cells travel as NaN
    assert_same_map(elevation, pickle.loads(pickle.dumps(elevation)))
    twin = copy.deepcopy(elevation)
    assert_same_map(elevation, twin)
    twin["max"][:] = 7.0  # a deep copy owns its layers
    assert not np.any(elevation["max"] == 7.0)
    geometry = pickle.loads(pickle.dumps(elevation.geometry))
    assert repr(geometry) == repr(elevation.geometry)


def test_an_overhang_free_map_round_trips():
    elevation, collapse = tc.dem_without_overhangs(scene())
    back_map, back_collapse = pickle.loads(pickle.dumps((elevation, collapse)))
    assert_same_map(elevation, back_map)
    assert_same_collapse(collapse, back_collapse)


def test_a_registration_result_round_trips_with_every_field():
    points = scene()
    target = tc.build_elevation_map(points, 0.25)
    tc.classify_terrain(target)
    turn = np.eye(4)
    turn[:2, :2] = [[np.cos(0.02), -np.sin(0.02)], [np.sin(0.02), np.cos(0.02)]]
    turn[:3, 3] = [0.2, -0.1, 0.0]
    result = tc.register_maps(target, target, turn)
    back = pickle.loads(pickle.dumps(result))
    fields = [name for name in dir(result) if not name.startswith("_")]
    assert len(fields) >= 23  # every field of RegistrationResult, none left behind
    for name in fields:
        a, b = getattr(result, name), getattr(back, name)
        if isinstance(a, np.ndarray) or isinstance(a, list):
            np.testing.assert_array_equal(np.asarray(b), np.asarray(a), err_msg=name)
        else:
            assert b == a or (a != a and b != b), name  # NaN RMSE stays NaN
    # A result worth carrying: it moved from the start back onto the map itself, and was analysed.
    assert np.allclose(result.transform, np.eye(4), atol=1e-3) and not np.allclose(
        result.icp_start, np.eye(4)
    )
    assert result.verdict and np.any(result.held != 0.0) and result.num_correspondences > 0


def same_value(a, b) -> bool:
    """Equal, NaN equal to NaN, arrays element by element, bound result objects field by field."""
    if isinstance(a, (list, tuple)) and not isinstance(a, str):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(map(same_value, a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    if (
        type(a).__module__ == "terracube._core"
        and hasattr(a, "__getstate__")
        and not hasattr(a, "__members__")
    ):
        return type(b) is type(a) and all(same_value(getattr(a, n), getattr(b, n)) for n in public_fields(a))
    return a == b or (isinstance(a, float) and a != a and b != b)


def public_fields(obj) -> list[str]:
    return [n for n in dir(obj) if not n.startswith("_") and not callable(getattr(obj, n))]


def trajectory(count: int, drift: float) -> np.ndarray:
    """A curved drive, 1 m a pose; `drift` bends it a little more every pose."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    yaw = (0.02 + drift) * np.arange(count)
    poses[:, 0, 0], poses[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    poses[:, 1, 0], poses[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    poses[:, 0, 3], poses[:, 1, 3] = np.cumsum(np.cos(yaw)), np.cumsum(np.sin(yaw))
    return poses


def result_objects() -> dict[str, object]:
    """One real result of every other kind the API returns, with fields away from their defaults."""
    truth, estimate = trajectory(40, 0.0), trajectory(40, 0.001)
    points = scene()
    obstacles = np.full(len(points), int(tc.TerrainClass.OBSTACLE), np.uint8)
    local = tc.LocalMap(length=10.0)
    mapper = tc.Mapper(tc.MapperParams(lidar_only=True))
    mapper.add_scan(points, np.eye(4))
    results = {
        "AbsoluteTrajectoryError": tc.absolute_trajectory_error(estimate, truth),
        "RelativePoseError": tc.relative_pose_error(estimate, truth, lengths=[5.0, 10.0], step_frames=3),
        "RegionLayoutComparison": tc.compare_region_layouts(
            np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 9.0]]),
            np.array([[0.1, 0.0], [10.0, 0.2], [9.8, 8.0], [0.0, 9.1]]),
        ),
        "PoseGraphResult": tc.optimize_pose_graph(
            estimate[:5],
            [tc.PoseGraphEdge(k, k + 1, np.linalg.inv(truth[k]) @ truth[k + 1]) for k in range(4)],
        ),
        "LocalMapUpdate": local.update(points, np.eye(4)),
        "ScanReport": mapper.add_scan(points, np.eye(4)),
        "MapperTimings": mapper.timings,
        "CorrelativeSearchResult": tc._core.correlative_search(
            points,
            obstacles,
            points + np.float32(0.2),
            obstacles,
            np.eye(4),
            tc._core.CorrelativeSearchParams(),
        ),
    }
    if tc.has_pcl():
        results["PclIcpResult"] = tc.pcl_icp(points[::10], points[::10] + np.float32(0.05))
    return results


@pytest.mark.parametrize("name", sorted(result_objects()))
def test_every_result_round_trips_field_by_field(name):
    result = result_objects()[name]
    assert type(result).__name__ == name
    back = pickle.loads(pickle.dumps(result))
    fields = public_fields(result)
    assert fields and same_value(result, back), name
    assert any(  # a result worth the test: some field holds more than a default
        isinstance(getattr(result, f), (list, np.ndarray))
        and len(getattr(result, f))
        or getattr(result, f) not in (0, 0.0, False, "", None)
        for f in fields
    ), name


@pytest.mark.parametrize("membership", ["triangular", "gaussian"])
def test_a_fuzzy_elevation_map_round_trips_with_its_training_record(membership):
    fitted = tc.fit_fuzzy_elevation_map(scene(), membership=membership, epochs=3)
    back = pickle.loads(pickle.dumps(fitted))
    assert back.params == fitted.params
    for name in ("centers_x", "centers_y", "consequents", "rule_support", "rmse_history"):
        np.testing.assert_array_equal(getattr(back, name), getattr(fitted, name), err_msg=name)
    assert back.num_training_points == fitted.num_training_points == len(scene())
    xy = np.random.default_rng(3).random((500, 2)) * 24.0 - 2.0  # inside and beyond the extent
    np.testing.assert_array_equal(back.evaluate(xy), fitted.evaluate(xy))
    np.testing.assert_array_equal(back.confidence(xy), fitted.confidence(xy))
    assert repr(copy.deepcopy(fitted)) == repr(fitted)


def test_a_loop_closure_state_maps_onto_its_fields():
    """Loop closures come from long drives; their state is checked against its own fields."""
    relative = np.eye(4)
    relative[:3, 3] = [1.0, 2.0, 3.0]
    state = {"source": 7, "target": 2, "relative": relative, "rmse": 0.05, "overlap": 0.8}
    loop = tc.LoopClosure.__new__(tc.LoopClosure)
    loop.__setstate__(state)
    assert (loop.source, loop.target, loop.rmse, loop.overlap) == (7, 2, 0.05, 0.8)
    np.testing.assert_array_equal(loop.relative, relative)
    assert same_value(pickle.loads(pickle.dumps(loop)), loop)


def build_in_worker(seed: int) -> tuple[tc.ElevationMap, tc.CollapseResult]:
    return tc.dem_without_overhangs(scene(seed))


def test_maps_come_back_from_worker_processes():
    """The reason pickling matters: a pool of processes returns its maps to the parent."""
    context = multiprocessing.get_context("spawn")  # a fresh interpreter, as Dask's and joblib's workers
    with context.Pool(2) as pool:
        results = pool.map(build_in_worker, [1, 2])
    for seed, (elevation, collapse) in zip([1, 2], results, strict=True):
        here_map, here_collapse = build_in_worker(seed)
        assert_same_map(here_map, elevation)
        assert_same_collapse(here_collapse, collapse)


def test_bad_pickled_states_are_refused_by_name():
    result = tc.collapse_overhangs(scene(), params=tc.CollapseParams(0.5, 2, method="shadow_aware"))
    state = result.__getstate__()
    fresh = tc.CollapseResult.__new__(tc.CollapseResult)
    with pytest.raises(ValueError, match="CollapseResult: a pickled state has 11 items"):
        fresh.__setstate__(state[:5])
    fresh = tc.CollapseResult.__new__(tc.CollapseResult)
    with pytest.raises(ValueError, match="do not belong together"):  # a mask of another cloud
        fresh.__setstate__((state[0], state[1][:10], *state[2:]))
    reasons = state[4].copy()
    reasons[0] = 200
    fresh = tc.CollapseResult.__new__(tc.CollapseResult)
    with pytest.raises(ValueError, match="unknown cube reason 200"):
        fresh.__setstate__((*state[:4], reasons, *state[5:]))

    elevation = tc.build_elevation_map(scene(), 0.5)
    tc.classify_terrain(elevation)
    geometry, layers = elevation._core.__getstate__()
    fresh = tc._core.ElevationMap.__new__(tc._core.ElevationMap)
    with pytest.raises(ValueError, match="layer max does not have the map's"):
        fresh.__setstate__((geometry, [("max", np.zeros((3, 3), np.float32))]))

    registration = tc.register_maps(elevation, elevation)
    state = registration.__getstate__()
    del state["verdict"]
    fresh = tc.RegistrationResult.__new__(tc.RegistrationResult)
    with pytest.raises(ValueError, match="has no verdict"):
        fresh.__setstate__(state)


def test_a_live_local_map_or_mapper_refuses_to_pickle_and_names_what_does():
    local_map = tc.LocalMap(length=4.0, resolution=0.5)
    local_map.update(scene(), np.eye(4))
    with pytest.raises(TypeError, match=r"LocalMap .*does not pickle; pickle m.to_elevation_map\(\)"):
        pickle.dumps(local_map)
    assert_same_map(local_map.to_elevation_map(), pickle.loads(pickle.dumps(local_map.to_elevation_map())))
    with pytest.raises(TypeError, match=r"Mapper .*does not pickle; .*mapper.global_map\(\)"):
        pickle.dumps(tc.Mapper(tc.MapperParams()))


def test_maps_iterate_over_their_layer_names_like_a_mapping():
    elevation = tc.build_elevation_map(scene(), 0.5)
    assert list(elevation) == elevation.layers and len(elevation) == len(elevation.layers) == 6
    assert dict(elevation.items()).keys() == set(elevation.layers)
    np.testing.assert_array_equal(dict(elevation.items())["max"], elevation["max"])
    local_map = tc.LocalMap(length=4.0, resolution=0.5)
    assert list(local_map) == local_map.layers and len(local_map) == len(local_map.layers)


def test_geometries_compare_by_resolution_origin_and_size():
    local_map = tc.LocalMap(length=4.0, resolution=0.5)
    local_map.update(scene(), np.eye(4))
    geometry = local_map.geometry
    assert geometry == local_map.to_elevation_map().geometry == pickle.loads(pickle.dumps(geometry))
    assert geometry != tc.MapGeometry(0.25, geometry.origin, geometry.size)
    assert geometry != tc.MapGeometry(0.5, geometry.origin + [0.5, 0.0], geometry.size)
    assert geometry != tc.MapGeometry(0.5, geometry.origin, geometry.size + [1, 0])
