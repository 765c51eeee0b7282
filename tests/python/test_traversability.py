"""add_traversability_layers on any ElevationMap: a plain numpy least-squares fit of every window
of a real scan's DEM, the LocalMap's own planner layers, and the errors."""

import numpy as np
import pytest
import terracube as tc


def naive_planner_layers(height: np.ndarray, resolution: float, params: tc.TraversabilityParams):
    """Every cell's window fitted by np.linalg.lstsq, written plainly."""
    r = max(1, int(round(params.footprint_radius / resolution)))
    nx, ny = height.shape
    out = {name: np.full(height.shape, np.nan) for name in ("step", "slope", "roughness", "traversability")}
    for i in range(nx):
        for j in range(ny):
            if np.isnan(height[i, j]):
                continue
            window = height[max(i - r, 0) : i + r + 1, max(j - r, 0) : j + r + 1]
            a, b = np.nonzero(~np.isnan(window))
            z = window[a, b].astype(np.float64)
            out["step"][i, j] = z.max() - z.min()
            design = np.c_[a, b, np.ones_like(a)].astype(np.float64)
            if len(z) < params.min_window_cells or np.linalg.matrix_rank(design) < 3:
                continue
            plane = np.linalg.lstsq(design, z, rcond=None)[0]
            slope = np.arctan(np.hypot(plane[0], plane[1]) / resolution)
            roughness = np.sqrt(np.mean((design @ plane - z) ** 2))
            step = out["step"][i, j]
            out["slope"][i, j], out["roughness"][i, j] = slope, roughness
            blocked = slope > params.max_slope or step > params.max_step or roughness > params.max_roughness
            cost = (slope / params.max_slope + step / params.max_step + roughness / params.max_roughness) / 3
            out["traversability"][i, j] = 0.0 if blocked else 1.0 - cost
    return out


def test_the_layers_of_a_kitti_dem_match_a_numpy_fit_of_every_window(shared_data):
    points = shared_data.kitti_xyzi(0)[:, :3]
    elevation_map = tc.build_elevation_map(points, 0.2, origin=(-6.0, -6.0), size=(60, 60))
    params = tc.TraversabilityParams(footprint_radius=0.4)  # 5 x 5 windows
    assert tc.add_traversability_layers(elevation_map, params) is elevation_map
    expected = naive_planner_layers(elevation_map["mean"], 0.2, params)
    for name, want in expected.items():
        got = elevation_map[name]
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want), err_msg=name)
        np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], atol=2e-5, err_msg=name)
    traversable = elevation_map["traversability"]
    assert 0.2 < np.mean(traversable[np.isfinite(traversable)] > 0.5) < 0.95  # road, and the car beside it


def test_a_local_maps_layers_are_those_of_its_copy_and_a_clearance_layer_blocks(shared_data):
    local = tc.LocalMap(length=8.0, resolution=0.1)
    local.update(shared_data.kitti_xyzi(0), np.eye(4))
    copy = local.to_elevation_map()
    own = {name: copy[name].copy() for name in ("step", "slope", "roughness", "traversability")}
    tc.add_traversability_layers(copy, layer="elevation")
    for name, want in own.items():
        np.testing.assert_array_equal(copy[name], want, err_msg=name)
    copy["clearance"] = np.full(copy.geometry.size, 0.5, dtype=np.float32)  # under a 0.7 m robot
    tc.add_traversability_layers(copy, layer="elevation")
    assert np.all(copy["traversability"][np.isfinite(copy["traversability"])] == 0.0)


def test_bad_calls_name_the_problem():
    elevation_map = tc.build_elevation_map(np.random.default_rng(1).uniform(0, 2, (500, 3)), 0.2)
    with pytest.raises(KeyError, match="elevation"):
        tc.add_traversability_layers(elevation_map, layer="elevation")
    with pytest.raises(ValueError, match="max_step_m"):
        tc.add_traversability_layers(elevation_map, max_step=0.0)
    with pytest.raises(TypeError, match="ElevationMap"):
        tc.add_traversability_layers(np.zeros((3, 3)))
    with pytest.raises(TypeError, match="not both"):
        tc.add_traversability_layers(elevation_map, tc.TraversabilityParams(), max_step=0.1)
    with pytest.raises(ValueError, match="num_threads"):
        tc.add_traversability_layers(elevation_map, num_threads=-1)
    # A footprint of thousands of cells (two points 2.6 m apart at 0.1 mm: 1401 x 26001 cells) is
    # refused at once; its windows' extremes would take hours.
    fine = tc.build_elevation_map(np.array([[0.0, 0.0, -5.1], [0.14, 2.6, 1e9]]), 1e-4)
    with pytest.raises(ValueError, match="window of 6001 cells a side, over 511"):
        tc.add_traversability_layers(fine)


def test_a_local_map_of_kitti_is_open_on_the_road_and_blocked_at_cars_and_walls(shared_data):
    # KITTI 00 frames 0-2 fused at their poses; each cell's majority SemanticKITTI label in frame 2
    # (3 or more points) against the planner's traversability there.
    poses = shared_data.kitti_poses()
    local = tc.LocalMap(length=30.0, resolution=0.2, collapse=tc.CollapseParams(sigma=4))
    for frame in range(3):
        local.update(shared_data.kitti_xyzi(frame)[:, :3], poses[frame])
    points = shared_data.kitti_xyzi(2)[:, :3].astype(np.float64) @ poses[2][:3, :3].T + poses[2][:3, 3]
    labels = shared_data.kitti_labels(2)
    ordered = local.to_elevation_map()
    g = ordered.geometry
    i = np.floor((points[:, 0] - g.origin[0]) / g.resolution).astype(np.int64)
    j = np.floor((points[:, 1] - g.origin[1]) / g.resolution).astype(np.int64)
    inside = (i >= 0) & (i < g.size[0]) & (j >= 0) & (j < g.size[1])
    cell = (i * g.size[1] + j)[inside]
    all_points = np.bincount(cell, minlength=g.num_cells)
    traversability = ordered["traversability"].ravel()

    def traversability_of(classes):
        of_class = np.bincount(cell[np.isin(labels[inside], classes)], minlength=g.num_cells)
        values = traversability[(of_class > 0.5 * all_points) & (all_points >= 3)]
        return values[np.isfinite(values)]

    ground = traversability_of([40, 44, 48])  # road, parking, sidewalk
    obstacles = traversability_of([10, 50, 51, 71, 80])  # car, building, fence, trunk, pole
    assert len(ground) > 4000 and len(obstacles) > 400
    assert np.mean(ground > 0.5) > 0.9  # measured 0.93
    assert np.mean(obstacles == 0.0) > 0.9  # measured 0.96


def test_replacing_the_dems_own_step_layer_warns_once_and_refreshing_does_not(recwarn):
    points = np.random.default_rng(2).uniform(0, 4, (2000, 3))
    dem, _ = tc.dem_without_overhangs(points, edge=0.5, sigma=2, resolution=0.2)
    neighbours_step = dem["step"].copy()
    with pytest.warns(UserWarning, match="replaces the map's 'step' layer"):
        tc.add_traversability_layers(dem)
    assert not np.array_equal(dem["step"], neighbours_step, equal_nan=True)  # the window's now
    recwarn.clear()
    tc.add_traversability_layers(dem, max_step=0.1)  # a refresh of its own layers
    tc.add_traversability_layers(tc.build_elevation_map(points, 0.2))  # no step layer to replace
    assert not [w for w in recwarn if "step" in str(w.message)]
