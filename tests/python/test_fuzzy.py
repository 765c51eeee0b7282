"""FuzzyElevationMap: evaluation against a naive formula, identification, hole filling, bad input.

The naive reference below sums every membership function as documented in fuzzy.hpp (triangles
reaching zero at the neighbouring centres and held at one beyond the outer centres, or Gaussians
of width s), normalises, and shares no code with the C++ library.
"""

from __future__ import annotations

import numpy as np
import pytest
import terracube as tc

EXTENT = ((0.0, 0.0), (10.0, 5.0))


def naive_degrees(centers, u, family, sigma):
    """(N, M) normalised degrees of the M membership functions at the N coordinates u."""
    c = np.asarray(centers)[None, :]
    u = np.asarray(u)[:, None]
    if family == "gaussian":
        degree = np.exp(-((u - c) ** 2) / (2 * sigma**2))
    else:
        left = np.r_[-np.inf, centers[:-1]][None, :]
        right = np.r_[centers[1:], np.inf][None, :]
        with np.errstate(invalid="ignore"):  # inf / inf beyond the outer centres, replaced by 1
            rising = np.where(np.isinf(left), 1.0, (u - left) / (c - left))
            falling = np.where(np.isinf(right), 1.0, (right - u) / (right - c))
        degree = np.clip(np.where(u <= c, rising, falling), 0.0, 1.0)
    return degree / degree.sum(axis=1, keepdims=True)


def naive_surface(model, xy, family):
    a = naive_degrees(model.centers_x, xy[:, 0], family, model._core.gaussian_sigma[0])
    b = naive_degrees(model.centers_y, xy[:, 1], family, model._core.gaussian_sigma[1])
    return np.einsum("ni,ij,nj->n", a, model.consequents, b)


def known_surface(family="triangular", seed=7):
    rng = np.random.default_rng(seed)
    return tc.FuzzyElevationMap.from_parameters(
        [0.0, 1.5, 4.5, 5.5, 8.0, 10.0],
        [0.0, 2.0, 3.0, 5.0],
        rng.uniform(-1, 1, (6, 4)),
        EXTENT,
        membership=family,
    )


def samples(model, n, seed, noise=0.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform((0, 0), (10, 5), (n, 2))
    return np.c_[xy, model.evaluate(xy) + rng.normal(0.0, noise, n) * (noise > 0)]


def height(x, y):
    """The synthetic terrain: gentle waves and a slope [m]."""
    return 0.3 * np.sin(0.4 * x) + 0.2 * np.cos(0.6 * y) + 0.02 * x


# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("family", ["triangular", "gaussian"])
def test_evaluate_matches_the_naive_formula(family):
    model = known_surface(family)
    xy = np.random.default_rng(1).uniform((-1, -1), (11, 6), (400, 2))
    tolerance = 1e-4 if family == "gaussian" else 1e-12  # Gaussians: the 5 nearest MFs only
    np.testing.assert_allclose(model.evaluate(xy), naive_surface(model, xy, family), atol=tolerance)
    # (N, 3) float32 rows work as well; z is ignored.
    xyz = np.c_[xy, np.full(len(xy), 99.0)].astype(np.float32)
    np.testing.assert_allclose(
        model.evaluate(xyz), naive_surface(model, xyz[:, :2].astype(float), family), atol=1e-4
    )


def test_paper_model_has_219_parameters():
    assert (tc.FuzzyParams().rules_x, tc.FuzzyParams().rules_y) == (19, 10)
    points = samples(known_surface(), 2000, 3)
    model = tc.FuzzyElevationMap.fit(points, tc.FuzzyParams(rules_x=19, rules_y=10, epochs=1, extent=EXTENT))
    assert model.num_rules == 190
    assert model.num_parameters == 219
    assert model.consequents.shape == model.rule_support.shape == (19, 10)
    assert "19x10 triangular rules, 219 parameters" in repr(model)


def test_least_squares_recovers_a_known_surface_on_its_own_centres():
    truth = tc.FuzzyElevationMap.from_parameters(
        np.linspace(0, 10, 6), np.linspace(0, 5, 4), known_surface().consequents, EXTENT
    )
    fitted = tc.fit_fuzzy_elevation_map(
        samples(truth, 3000, 2), rules_x=6, rules_y=4, epochs=0, ridge=1e-12, smoothness=0, extent=EXTENT
    )
    np.testing.assert_allclose(fitted.consequents, truth.consequents, atol=1e-6)
    assert fitted.rmse_history[-1] < 1e-8


@pytest.mark.parametrize("family", ["triangular", "gaussian"])
def test_hybrid_learning_recovers_a_known_surface_with_uneven_centres(family):
    truth = known_surface(family)
    params = tc.FuzzyParams(
        rules_x=6, rules_y=4, membership=family, epochs=40, ridge=1e-9, smoothness=0, extent=EXTENT
    )
    fitted = tc.FuzzyElevationMap.fit(samples(truth, 4000, 5), params)
    rmse = fitted.rmse_history
    assert len(rmse) == 41
    assert rmse[-1] < 0.5 * rmse[0]
    check = np.random.default_rng(9).uniform((0, 0), (10, 5), (500, 2))
    assert np.sqrt(np.mean((fitted.evaluate(check) - truth.evaluate(check)) ** 2)) < 2 * rmse[-1] + 1e-3


@pytest.mark.parametrize("family", ["triangular", "gaussian"])
def test_training_error_does_not_increase_across_epochs(family):
    points = samples(known_surface(family), 2000, 21, noise=0.05)
    model = tc.fit_fuzzy_elevation_map(
        points, rules_x=8, rules_y=5, membership=family, epochs=25, learning_rate=0.5, extent=EXTENT
    )
    assert len(model.rmse_history) == 26
    assert np.all(np.diff(model.rmse_history) <= 0)
    assert np.all(np.diff(model.centers_x) > 0) and np.all(np.diff(model.centers_y) > 0)
    assert model.centers_x[0] >= 0 and model.centers_x[-1] <= 10


def test_plain_anfis_with_jangs_step_rule_learns_a_known_surface():
    truth = known_surface("triangular")
    plain = {"ridge": 0.0, "smoothness": 0.0, "step_rule": "jang", "extent": EXTENT}
    fitted = tc.FuzzyElevationMap.fit(samples(truth, 4000, 5), rules_x=6, rules_y=4, epochs=40, **plain)
    assert fitted.rmse_history[-1] < 0.5 * fitted.rmse_history[0]
    assert fitted.params.step_rule == "jang"


def test_fit_is_reproducible():
    points = samples(known_surface(), 3000, 4, noise=0.05)
    a = tc.fit_fuzzy_elevation_map(points, rules_x=8, rules_y=5, epochs=5)
    b = tc.fit_fuzzy_elevation_map(points.copy(), rules_x=8, rules_y=5, epochs=5)
    np.testing.assert_array_equal(a.consequents, b.consequents)
    np.testing.assert_array_equal(a.centers_x, b.centers_x)
    np.testing.assert_array_equal(a.rmse_history, b.rmse_history)


def test_fem_beats_the_dem_under_noise_and_fills_its_holes():
    """Synthetic terrain with shadowed holes: RMSE against the true height, DEM vs FEM."""
    rng = np.random.default_rng(0)
    n = 60_000
    xy = rng.uniform((0, 0), (20, 10), (n, 2))
    shadowed = np.zeros(n, bool)
    for cx, cy, r in ((5, 5, 0.6), (12, 3, 0.5), (15, 7, 0.7), (8, 2, 0.4)):
        shadowed |= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) < r
    xy = xy[~shadowed]
    points = np.c_[xy, height(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.05, len(xy))]
    dem = tc.build_elevation_map(points, 0.1, origin=(0, 0), size=(200, 100))
    fem = tc.FuzzyElevationMap.fit(points, extent=((0, 0), (20, 10)))
    fem.to_layer(dem)
    x, y = dem.cell_centers()
    truth = height(*np.meshgrid(x, y, indexing="ij"))
    observed = np.isfinite(dem["mean"])
    holes = ~observed
    dem_rmse = np.sqrt(np.mean((dem["mean"] - truth)[observed] ** 2))
    fem_rmse = np.sqrt(np.mean((dem["fem"] - truth)[observed] ** 2))
    filled = np.isfinite(dem["fem"][holes]).mean()
    hole_rmse = np.sqrt(np.nanmean((dem["fem"] - truth)[holes] ** 2))
    print(f"DEM RMSE {dem_rmse:.4f} m, FEM RMSE {fem_rmse:.4f} m, {holes.sum()} holes, {filled:.1%} filled")
    assert holes.sum() > 300
    assert fem_rmse < 0.5 * dem_rmse
    assert filled > 0.95
    assert hole_rmse < 0.03
    assert np.all(dem["fem_confidence"] >= 0)


def test_to_layer_leaves_far_extrapolation_empty():
    points = samples(known_surface(), 3000, 6)
    fem = tc.fit_fuzzy_elevation_map(points, rules_x=6, rules_y=4, extent=EXTENT)
    grid = tc.ElevationMap.empty(0.5, (-5.0, 0.0), (30, 10))  # x from -5 to 10: 10 columns outside
    fem.to_layer(grid, min_confidence=1.0, name="surface")
    assert {"surface", "surface_confidence"} <= set(grid.layers)
    assert np.all(np.isnan(grid["surface"][:10])) and np.all(grid["surface_confidence"][:10] == 0)
    assert np.all(np.isfinite(grid["surface"][10:]))
    with pytest.raises(ValueError, match="min_confidence"):
        fem.to_layer(grid, min_confidence=-1)


def test_use_flags_select_the_training_points():
    points = samples(known_surface(), 2000, 8)
    polluted = np.r_[points, [[5.0, 2.0, 100.0]]]
    use = np.r_[np.ones(2000, bool), False]
    a = tc.fit_fuzzy_elevation_map(points, rules_x=6, rules_y=4, epochs=2)
    b = tc.fit_fuzzy_elevation_map(polluted, rules_x=6, rules_y=4, epochs=2, use=use)
    np.testing.assert_array_equal(a.consequents, b.consequents)
    assert b.num_training_points == 2000


def test_bad_input_gives_clear_errors():
    points = samples(known_surface(), 300, 1)
    with pytest.raises(
        ValueError, match=r"too few points for the rule grid: 300 points .* 190 rules; need at least 380"
    ):
        tc.fit_fuzzy_elevation_map(points)
    bad = points.copy()
    bad[5, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        tc.fit_fuzzy_elevation_map(bad, rules_x=4, rules_y=4)
    with pytest.raises(ValueError, match="membership"):
        tc.fit_fuzzy_elevation_map(points, membership="trapezoid")
    with pytest.raises(ValueError, match="step_rule must be one of"):
        tc.fit_fuzzy_elevation_map(points, rules_x=4, rules_y=4, step_rule="adam")
    with pytest.raises(ValueError, match="at least 2 x 2 rules"):
        tc.fit_fuzzy_elevation_map(points, rules_x=1)
    with pytest.raises(ValueError, match="extent"):
        tc.fit_fuzzy_elevation_map(points, extent=((0, 0), (0, 5)))
    with pytest.raises(ValueError, match="one flag per point"):
        tc.fit_fuzzy_elevation_map(points, rules_x=4, rules_y=4, use=np.ones(3, bool))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        tc.fit_fuzzy_elevation_map(points[:, :2], rules_x=4, rules_y=4)


def test_kitti_window_of_kept_points(shared_data):
    xyzi = shared_data.kitti_xyzi(0)
    xyz = xyzi[:, :3]
    _, collapse = tc.dem_without_overhangs(xyz, sigma=5)
    window = ((0.0, -5.0), (20.0, 5.0))
    fem = tc.FuzzyElevationMap.fit(xyz, use=~np.asarray(collapse.overhang), extent=window)
    assert fem.num_parameters == 219
    assert fem.num_training_points > 5000
    assert fem.rmse_history[-1] <= fem.rmse_history[0] < 0.5
    dem = tc.build_elevation_map(xyz, 0.2, origin=window[0], size=(100, 50))
    fem.to_layer(dem)
    assert np.isfinite(dem["fem"]).mean() > np.isfinite(dem["mean"]).mean()


def test_params_mirror_the_core_struct():
    core = tc.FuzzyParams().to_core()
    assert (core.rules_x, core.rules_y, core.epochs) == (19, 10, 10)
    assert core.membership == tc.fuzzy._FAMILIES["triangular"] and not core.has_extent
    params = tc.FuzzyParams(
        rules_x=6, rules_y=4, membership="gaussian", epochs=3, smoothness=0.1, extent=EXTENT
    )
    model = tc.fit_fuzzy_elevation_map(samples(known_surface(), 2000, 3), params)
    assert model.params == params
