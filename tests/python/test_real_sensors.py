"""Issue 37 through the Python API: range limits, the automatic map window, the estimated ground
reference, the sensor presets, GeoTIFF metadata and the classified LAS that keeps its input."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import terracube as tc
from terracube.config import ConfigError, FrameParams, default_config, load_config, preset_names
from terracube.io import read_crs, read_points, write_geotiff
from terracube.pipeline import auto_extent, run_stage, scan_trajectory, terrain_params


def _ground_scene(seed: int = 0, slope_deg: float = 0.0, n: int = 20_000) -> np.ndarray:
    """A 20 x 20 m ground patch around a sensor 1.5 m above it, tilted by ``slope_deg`` along x."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-10, 10, (n, 2))
    z = -1.5 + np.tan(np.radians(slope_deg)) * xy[:, 0] + rng.normal(0, 0.01, n)
    return np.c_[xy, z]


# ------------------------------------------------------------------------------------------ range


def test_the_default_min_range_drops_exactly_the_no_returns_and_the_report_counts_them(tmp_path):
    points = np.vstack([_ground_scene(), np.zeros((777, 3))])
    report = run_stage("dem", points, "scan", tmp_path, png=False)
    assert report.lines[1] == "  range filter: 777 of 20,777 points left out (777 no-returns at (0, 0, 0))"
    saved = tc.ElevationMap.load(tmp_path / "scan_dem.npz")
    assert int(np.nansum(saved["count"])) == 20_000  # no cell holds a no-return


def test_max_range_leaves_out_the_far_points_and_the_cloud_keeps_every_point_labelled_0(tmp_path):
    near = _ground_scene()
    far = np.array([[60.0, 0.0, -1.5], [0.0, -80.0, -1.5], [45.0, 45.0, 0.0]])
    points = np.vstack([near, far, np.zeros((3, 3))])
    config = default_config().replace("frame", max_range=50.0)
    report = run_stage("classify", points, "s", tmp_path, config, cloud_format="npz", png=False)
    assert "3 no-returns at (0, 0, 0), 3 beyond 50 m" in report.lines[1]
    labels = np.load(tmp_path / "s_classes.npz")["label"]
    assert labels.shape == (len(points),)
    assert np.all(labels[-6:] == 0) and np.all(labels[: len(near)] > 0)


def test_range_limits_are_checked_with_a_message_naming_them():
    with pytest.raises(ValueError, match="min_range must be a distance >= 0"):
        FrameParams(min_range=-1.0)
    with pytest.raises(ValueError, match="max_range must be a distance"):
        FrameParams(min_range=2.0, max_range=1.0)
    keep = FrameParams(min_range=1.0, max_range=2.0).in_range(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1.5, 0], [0, 0, 2.0], [3, 0, 0], [np.nan, 0, 0]])
    )
    assert keep.tolist() == [False, True, True, True, False, False]


def test_the_mapper_leaves_out_the_frame_range_too(tmp_path, shared_data):
    from terracube.pipeline import build_global_map

    points = np.vstack([_ground_scene(), np.zeros((50, 3)), [[90.0, 0.0, -1.5]]])
    config = default_config().replace("frame", max_range=60.0)
    report = build_global_map([("a", points, 0)], np.eye(4)[None], np.zeros(1), tmp_path, config, png=False)
    assert "range filter: 51 points left out (nearer than 0.5 m or beyond 60 m)" in report.lines


def test_the_mapper_api_takes_a_max_range_and_counts_what_it_left_out():
    from terracube.mapping import Mapper, MapperParams

    points = np.vstack([_ground_scene(), np.zeros((7, 3)), [[90.0, 0.0, -1.5], [0.0, 95.0, -1.5]]])
    mapper = Mapper(MapperParams(max_range=60.0))
    report = mapper.add_scan(points, np.eye(4))
    assert report.num_out_of_range == 9
    assert repr(report).endswith(", num_out_of_range=9)")
    reference = Mapper(MapperParams())
    reference.add_scan(_ground_scene(), np.eye(4))
    np.testing.assert_array_equal(mapper.global_map()["count"], reference.global_map()["count"])
    assert mapper.add_scan(points[::-1].astype(np.float32), np.eye(4)).num_out_of_range == 9
    assert mapper.points_out_of_range == 18
    for max_range in (0.5, 1.0, float("nan")):
        with pytest.raises(ValueError, match="max_range_m must exceed min_range_m"):
            Mapper(MapperParams(min_range=1.0, max_range=max_range))
    # A huge range limit leaves everything out (OverflowError from ``1e300 ** 2`` before).
    everything_out = Mapper(MapperParams(min_range=1e300))
    everything_out.add_scan(points, np.eye(4))
    assert everything_out.points_out_of_range == len(points)


def test_register_leaves_out_each_scans_no_returns_and_names_the_ground_reference():
    from terracube.pipeline import register_scans

    source = np.vstack([_ground_scene(seed=1), np.zeros((11, 3))])
    target = np.vstack([_ground_scene(seed=2), np.zeros((4, 3))])
    record, _ = register_scans(source, target)
    assert record["points_left_out"] == [11, 4]
    assert record["ground_reference"].startswith("local ground, 5 cells (estimated")


# ------------------------------------------------------------------------------------------ window


def test_a_few_far_returns_no_longer_blow_up_the_automatic_map_window(tmp_path):
    points = np.vstack([_ground_scene(), [[230.0, 170.0, 5.0], [-237.0, -110.0, 0.0]]])
    origin, size = auto_extent(points, default_config())
    # the 20 x 20 m patch, widened by at most 10 % of its span per side: no more than 240 x 240 cells
    assert -12.1 <= origin[0] <= -9.9 and -12.1 <= origin[1] <= -9.9
    assert 200 <= size[0] <= 241 and 200 <= size[1] <= 241
    # an extent that holds the whole patch and no more than the points' own extent
    dense = _ground_scene()
    origin, size = auto_extent(dense, default_config())
    lo, hi = dense[:, :2].min(axis=0), dense[:, :2].max(axis=0)
    assert np.all(np.array(origin) <= lo) and np.all(np.array(origin) + 0.1 * np.array(size) >= hi)


def test_the_window_and_the_leveled_points_match_a_plain_computation():
    """auto_extent and leveled_points (column by column, no copy without leveling) against the
    formula written plainly: leveled rows, finite and inside the crop box, their 1st..99th
    percentiles widened by 10 % (at least two cells), clipped to their extent, snapped to cells."""
    from terracube.pipeline import leveled_points

    rng = np.random.default_rng(8)
    points = np.vstack(
        [_ground_scene(n=5000), rng.uniform(-60, 60, (50, 3)), [[np.nan, 1, 1], [1, np.inf, 1]]]
    )
    flat = default_config()
    config = flat.replace("frame", roll_deg=3.0, pitch_deg=-2.0, crop=[[-30, -40, -5], [50, 30, 5]])
    for cfg in (flat, config):
        transform = cfg.frame.transform()
        with np.errstate(invalid="ignore"):
            expected = np.array([transform[:3, :3] @ p + transform[:3, 3] for p in points])
        box = cfg.frame.crop_box()
        keep = np.array(
            [
                np.isfinite(q).all()
                and (box is None or all(box[0][k] <= q[k] <= box[1][k] for k in range(3)))
                for q in expected
            ]
        )
        leveled, inside = leveled_points(points, cfg)
        np.testing.assert_allclose(leveled[keep], expected[keep], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(inside, keep)
        xy = expected[keep, :2]
        low, high = np.percentile(xy[:, 0], [1, 99]), np.percentile(xy[:, 1], [1, 99])
        low, high = np.array([low[0], high[0]]), np.array([low[1], high[1]])
        margin = np.maximum(0.1 * (high - low), 0.2)
        low, high = np.maximum(low - margin, xy.min(axis=0)), np.minimum(high + margin, xy.max(axis=0))
        origin = np.floor(low / 0.1) * 0.1
        size = np.maximum(np.floor((high - origin) / 0.1).astype(int) + 1, 1)
        window = auto_extent(points, cfg)
        np.testing.assert_allclose(window[0], origin, rtol=0, atol=1e-9)
        assert window[1] == list(size)
    assert np.shares_memory(leveled_points(points, flat)[0], points)  # not leveled: no copy


def test_a_map_with_almost_no_filled_cell_gets_a_warning(tmp_path):
    config = default_config().replace("elevation", origin=[-50.0, -50.0], size=[1000, 1000])
    report = run_stage("dem", _ground_scene(n=2000), "sparse", tmp_path, config, png=False)
    warning = [line for line in report.lines if "warning:" in line]
    assert len(warning) == 1 and "of the 1,000,000 cells hold data" in warning[0]
    counts = np.load(tmp_path / "sparse_dem.npz")["layer_count"]
    sparse = counts.sum() / np.count_nonzero(counts) < 1.5  # the cells with data hold single points
    assert ("--preset airborne_las" in warning[0]) == sparse
    report = run_stage("dem", _ground_scene(n=2000), "dense", tmp_path, png=False)
    assert not any("warning:" in line for line in report.lines)


def test_cells_finer_than_the_point_spacing_get_a_note_with_a_cell_size_that_fits(tmp_path):
    # an airborne-like tile: 10 points per m2 at 0.1 m cells holds about one point per cell with data
    report = run_stage("dem", _ground_scene(n=4000), "tile", tmp_path, png=False)
    note = [line for line in report.lines if "note:" in line]
    assert len(note) == 1 and "--resolution 0.7 gives cells of about four points" in note[0], report.lines
    assert "--preset airborne_las" in note[0]
    # a map already as coarse as the preset's cells is not sent to the preset
    airborne = load_config(None, preset="airborne_las")
    for resolution, hinted in ((0.1, True), (0.5, False), (0.7, False)):
        config = airborne.replace("elevation", resolution=resolution)
        report = run_stage("dem", _ground_scene(n=300), f"r{resolution}", tmp_path, config, png=False)
        lines = [line for line in report.lines if "note:" in line or "warning:" in line]
        assert any("--preset airborne_las" in line for line in lines) == hinted, (resolution, lines)
    # a ground sensor's far field (a bag, a KITTI .bin, a PCD) is not sent to the airborne preset
    sparse = _ground_scene(n=4000)
    for suffix, hinted in ((".bin", False), (".pcd", False), (".laz", True)):
        source = tmp_path / f"scan{suffix}"
        source.touch()  # run_stage reads the points given; the source only names their file
        report = run_stage("dem", sparse, f"s{suffix[1:]}", tmp_path, source=source, png=False)
        note = [line for line in report.lines if "note:" in line]
        assert len(note) == 1 and ("--preset airborne_las" in note[0]) == hinted, (suffix, note)
    config = default_config().replace("elevation", resolution=0.7)
    report = run_stage("dem", _ground_scene(n=4000), "coarse", tmp_path, config, png=False)
    assert not any("note:" in line or "warning:" in line for line in report.lines), report.lines


# ------------------------------------------------------------------------------------------ ground


def test_without_a_sensor_height_the_ground_is_estimated_and_holds_on_an_11_degree_slope(tmp_path):
    slope = _ground_scene(slope_deg=11.0, n=40_000)
    report = run_stage("classify", slope, "slope", tmp_path, cloud_format=None, png=False)
    assert report.lines[1].startswith("  ground reference: local ground, 5 cells (estimated")
    classes = np.nan_to_num(tc.ElevationMap.load(tmp_path / "slope_classes.npz")["class"]).astype(int)
    known = classes[classes > 0]
    ground = np.isin(known, [tc.TerrainClass.GROUND, tc.TerrainClass.HORIZONTAL_EDGE])
    assert ground.mean() > 0.98, np.bincount(known)
    # the paper's plane z = -1.5 on the same slope: the upper half of the slope is no longer ground
    given = default_config().replace("terrain", sensor_height=1.5)
    assert terrain_params(given)[1] == "sensor height 1.5 m"
    report = run_stage("classify", slope, "plane", tmp_path, given, cloud_format=None, png=False)
    plane = np.nan_to_num(tc.ElevationMap.load(tmp_path / "plane_classes.npz")["class"]).astype(int)
    assert (plane[plane > 0] == tc.TerrainClass.GROUND).mean() < ground.mean() - 0.3


# ------------------------------------------------------------------------------------------ presets


def test_every_preset_loads_and_sets_what_its_sensor_needs():
    assert set(preset_names()) >= {"ouster128", "kitti_hdl64", "tls_plot", "airborne_las"}
    kitti = load_config(None, preset="kitti_hdl64")
    assert kitti.terrain.sensor_height == 1.73 and kitti.frame.min_range == 3.0
    ouster = load_config(None, preset="ouster128")
    assert ouster.frame.min_range > 0 and ouster.frame.max_range == 40.0
    for name in preset_names():
        assert load_config(None, preset=name) != default_config(), name
    with pytest.raises(ConfigError, match="unknown preset 'oustr128'; did you mean 'ouster128'"):
        load_config(None, preset="oustr128")
    assert load_config(None, preset="kitti") == load_config(None, preset="hdl64") == kitti


def test_the_kitti_preset_leaves_out_the_car_and_nothing_else(shared_data):
    """By SemanticKITTI's labels (frames 0-2): every return nearer than the preset's min_range is
    the car (unlabelled, or 'outlier' for the hood's front edge at 2.7-2.8 m), and no such return of
    the car lies beyond it: the nearest labelled world returns (road, sidewalk) start near 4 m."""
    min_range = load_config(None, preset="kitti_hdl64").frame.min_range
    for frame in range(3):
        xyz = shared_data.kitti_xyzi(frame)[:, :3]
        labels = shared_data.kitti_labels(frame)
        distance = np.linalg.norm(xyz, axis=1)
        near = distance < min_range
        assert set(np.unique(labels[near])) <= {0, 1}, frame  # unlabelled, outlier
        assert (labels[near] == 1).sum() > 0, frame  # the hood's edge (2.5 m left it in)
        assert distance[near & (labels == 1)].max() > 2.5, frame
        assert not np.any((labels == 1) & ~near & (distance < 6.0)), frame
        assert set(np.unique(labels[~near & (distance < 6.0)])) - {0} <= {40, 44, 48, 60, 70, 80}, frame


def test_a_config_file_wins_over_the_preset(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("terrain:\n  sensor_height: 2.0\n")
    config = load_config(path, preset="kitti_hdl64")
    assert config.terrain.sensor_height == 2.0 and config.frame.min_range == 3.0


def test_the_presets_ship_inside_the_package():
    import terracube

    folder = Path(terracube.__file__).parent / "presets"
    assert sorted(p.stem for p in folder.glob("*.yaml")) == preset_names()
    pyproject = (Path(__file__).parents[2] / "pyproject.toml").read_text()
    assert 'wheel.packages = ["python/terracube"]' in pyproject  # the whole folder, YAML included


# ------------------------------------------------------------------------------------------ GIS


def _georeferenced_las(
    path: Path, points: np.ndarray, wkt: str | None, epsg: int | None, point_format: int = 6
):
    import laspy

    header = laspy.LasHeader(point_format=point_format, version="1.4" if point_format >= 6 else "1.2")
    header.offsets = points.min(axis=0)
    header.scales = [0.001, 0.001, 0.001]
    if wkt is not None:
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(wkt))
    if epsg is not None:
        directory = laspy.vlrs.known.GeoKeyDirectoryVlr()
        directory.geo_keys_header.number_of_keys = 1
        key = directory.geo_keys[0]
        key.id, key.tiff_tag_location, key.count, key.value_offset = 3072, 0, 1, epsg
        header.vlrs.append(directory)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    rng = np.random.default_rng(5)
    las.intensity = rng.integers(0, 65535, len(points), dtype=np.uint16)
    if "gps_time" in las.point_format.dimension_names:
        las.gps_time = np.arange(len(points)) * 1e-5 + 3.0e5
    las.return_number = rng.integers(1, 3, len(points))
    las.number_of_returns = np.full(len(points), 2)
    las.classification = rng.choice([2, 5, 6], len(points)).astype(np.uint8)
    las.write(str(path))
    return laspy.read(str(path))


def test_geotiffs_carry_the_input_crs_are_deflated_and_the_classes_are_uint8_with_names(tmp_path):
    pytest.importorskip("laspy")
    rasterio = pytest.importorskip("rasterio")
    from rasterio.crs import CRS

    points = _ground_scene() + [500_000.0, 5_400_000.0, 300.0]
    source = tmp_path / "utm.las"
    _georeferenced_las(source, points, None, 32632)
    assert read_crs(source) == "EPSG:32632"
    run_stage("classify", points, "utm", tmp_path, source=source, cloud_format=None, png=False, geotiff=True)
    run_stage("dem", points, "utm", tmp_path, source=source, png=False, geotiff=True)
    with rasterio.open(tmp_path / "utm_classes.tif") as classes:
        assert classes.crs == CRS.from_epsg(32632)
        assert classes.dtypes == ("uint8",) and classes.nodata == 0
        assert classes.compression.name == "deflate"
        names = classes.tags(1)["CATEGORY_NAMES"].split(",")
        assert names == [c.name.lower() for c in tc.TerrainClass]
        values = classes.read(1)
    import xml.etree.ElementTree as ElementTree

    pam = ElementTree.parse(tmp_path / "utm_classes.tif.aux.xml").getroot()  # GDAL's category names
    assert [c.text for c in pam.iter("Category")] == [c.name.lower() for c in tc.TerrainClass]
    saved = np.nan_to_num(tc.ElevationMap.load(tmp_path / "utm_classes.npz")["class"]).astype(np.uint8)
    np.testing.assert_array_equal(values, saved.T[::-1, :])
    with rasterio.open(tmp_path / "utm_dem_max.tif") as dem:
        assert dem.crs == CRS.from_epsg(32632) and dem.dtypes == ("float32",)
        assert np.isnan(dem.nodata) and dem.compression.name == "deflate"
        # the raster's corner is the map's: georeferenced, not in the sensor frame
        g = tc.ElevationMap.load(tmp_path / "utm_dem.npz").geometry
        assert dem.transform.c == pytest.approx(g.origin[0]) and dem.transform.c > 499_980


def test_the_crs_of_the_bundled_airborne_las_reaches_the_geotiff(tmp_path, shared_data):
    rasterio = pytest.importorskip("rasterio")
    path = shared_data.path("als_classified/laspy_wkt_geotiff_ground_veg_building.las")
    wkt = read_crs(path)
    assert wkt.startswith('PROJCS["NAD83_2011_Nebraska_ft"')
    elevation_map = tc.build_elevation_map(read_points(path)[:, :3], 1.0)
    with rasterio.open(write_geotiff(elevation_map, "max", tmp_path / "a.tif", crs=wkt)) as dataset:
        assert dataset.crs is not None and "Nebraska" in dataset.crs.to_wkt()
        assert dataset.units == ("US survey foot",)  # the file's heights are in its CRS's feet


def test_the_length_unit_of_a_crs_is_read_and_a_file_not_in_metres_gets_a_warning(tmp_path, shared_data):
    """Two of the bundled airborne tiles measure in feet: their coordinates are used as they are, so
    a run says that every length of the settings acts in feet there (and a geographic CRS in
    degrees); a metric tile gets no such line."""
    pytest.importorskip("rasterio")
    pytest.importorskip("laspy")
    from terracube.io import crs_length_unit

    folder = "als_classified/"
    units = {
        "laspy_autzen_trim.laz": ("foot", 0.3048),
        "laspy_wkt_geotiff_ground_veg_building.las": ("US survey foot", 1200 / 3937),
        "lidR_Topography.laz": ("metre", 1.0),
    }
    for name, (unit, factor) in units.items():
        found = crs_length_unit(read_crs(shared_data.path(folder + name)))
        assert found is not None and found[0] == unit and found[1] == pytest.approx(factor, rel=1e-12), found
    assert crs_length_unit("EPSG:4326") == ("degree", None)
    assert crs_length_unit(None) is None and crs_length_unit("not a crs") is None

    points = _ground_scene(n=1200) + [500_000.0, 4_000_000.0, 100.0]
    config = default_config().replace("elevation", resolution=0.5)
    lines = {}
    for label, epsg in (("feet", 2229), ("metres", 32611), ("degrees", 4326)):  # ftUS, UTM 11N, lon/lat
        source = tmp_path / f"{label}.las"
        _georeferenced_las(source, points, None, epsg)
        report = run_stage("dem", read_points(source), label, tmp_path, config, source=source, png=False)
        lines[label] = [line for line in report.lines if "CRS of" in line]
        density = [line for line in report.lines if "points per" in line]  # about 1.1 points a cell
        unit = {"feet": "square US survey foot", "metres": "m2", "degrees": "square degree"}[label]
        assert len(density) == 1 and f"points per {unit})" in density[0], report.lines
    assert len(lines["feet"]) == 1 and "US survey foot" in lines["feet"][0], lines
    assert "the cells of 0.5 are 0.152 m" in lines["feet"][0] and "--resolution 1.64" in lines["feet"][0]
    assert lines["metres"] == []
    assert len(lines["degrees"]) == 1 and "geographic" in lines["degrees"][0]


def test_a_classified_las_keeps_every_input_dimension_and_vlr_with_the_labels_added(tmp_path):
    laspy = pytest.importorskip("laspy")
    from terracube.io import TERRAIN_LAS_CLASSES

    points = _ground_scene(n=5000) + [500_000.0, 5_400_000.0, 300.0]
    wkt = 'PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984"]],AUTHORITY["EPSG","32632"]]'
    source = tmp_path / "in.laz"
    original = _georeferenced_las(source, points, wkt, 32632)
    xyz = read_points(source)
    for las_classification in (False, True):
        out = tmp_path / f"out_{las_classification}"
        run_stage(
            "classify",
            xyz,
            "in",
            out,
            source=source,
            cloud_format="laz",
            png=False,
            las_classification=las_classification,
        )
        written = laspy.read(str(out / "in_classes.laz"))
        dimensions = list(original.point_format.dimension_names)
        assert list(written.point_format.dimension_names) == [*dimensions, "terracube_class"]
        for name in dimensions:
            if name != "classification":
                np.testing.assert_array_equal(written[name], original[name], err_msg=name)
        assert [v.record_id for v in written.header.vlrs][:2] == [v.record_id for v in original.header.vlrs]
        assert written.header.vlrs[0].string.rstrip("\0") == wkt
        saved = tc.ElevationMap.load(out / "in_classes.npz")
        g = saved.geometry
        i = np.floor((xyz[:, 0] - g.origin[0]) / g.resolution).astype(int)
        j = np.floor((xyz[:, 1] - g.origin[1]) / g.resolution).astype(int)
        expected = np.nan_to_num(saved["class"]).astype(np.uint8)[i, j]
        np.testing.assert_array_equal(written.terracube_class, expected)
        if las_classification:
            codes = np.array([TERRAIN_LAS_CLASSES[int(c)] for c in expected], dtype=np.uint8)
            np.testing.assert_array_equal(written.classification, codes)
        else:
            np.testing.assert_array_equal(written.classification, original.classification)


def test_classes_in_the_classification_of_an_old_point_format_move_it_to_las_1_4(tmp_path):
    laspy = pytest.importorskip("laspy")
    from terracube.io import TERRAIN_LAS_CLASSES

    rng = np.random.default_rng(4)
    wall = np.c_[np.full(600, 5.0), rng.uniform(-5, 5, 600), rng.uniform(-1.5, 0.5, 600)]  # not ground
    points = np.vstack([_ground_scene(n=3000), wall]) + [500_000.0, 5_400_000.0, 300.0]
    source = tmp_path / "old.las"
    original = _georeferenced_las(source, points, None, 32632, point_format=1)
    run_stage("classify", read_points(source), "old", tmp_path, source=source, cloud_format="las",
              png=False, las_classification=True)  # fmt: skip
    written = laspy.read(str(tmp_path / "old_classes.las"))
    assert written.classification.max() > 31  # e.g. 67, vertical object: format 1 cannot hold it
    assert written.point_format.id == 6 and str(written.header.version) == "1.4"
    for name in ("X", "Y", "Z", "intensity", "return_number", "gps_time"):
        np.testing.assert_array_equal(written[name], original[name], err_msg=name)
    assert read_crs(tmp_path / "old_classes.las") == "EPSG:32632"
    codes = {TERRAIN_LAS_CLASSES[int(c)]: int(c) for c in tc.TerrainClass}
    np.testing.assert_array_equal([codes[c] for c in written.classification], written.terracube_class)


def test_a_collapse_las_keeps_the_asprs_classes_and_adds_the_overhang_dimension(tmp_path):
    laspy = pytest.importorskip("laspy")
    rng = np.random.default_rng(2)
    ground = np.c_[rng.uniform(0, 6, (3000, 2)), rng.normal(0, 0.02, 3000)]
    canopy = np.c_[rng.uniform(2, 4, (400, 2)), rng.uniform(3.0, 3.3, 400)]
    source = tmp_path / "forest.las"
    original = _georeferenced_las(source, np.vstack([ground, canopy]) + 100.0, None, None)
    xyz = read_points(source)
    run_stage("collapse", xyz, "forest", tmp_path, source=source, output_format="las", png=False)
    written = laspy.read(str(tmp_path / "forest_classified.las"))
    np.testing.assert_array_equal(written.classification, original.classification)
    np.testing.assert_array_equal(written.gps_time, original.gps_time)
    np.testing.assert_array_equal(written.overhang, tc.collapse_overhangs(xyz, 0.5, 2).overhang)
    assert written.overhang[3000:].mean() > 0.9 and written.overhang[:3000].max() == 0


# ------------------------------------------------------------------------------------------ map


def test_every_scan_gets_its_keyframe_estimate_moved_by_the_odometry_since():
    rng = np.random.default_rng(3)
    odometry = np.repeat(np.eye(4)[None], 6, axis=0)
    odometry[:, 0, 3] = np.arange(6) * 1.0
    keyframes = np.array([0, 3])
    corrected = odometry[keyframes].copy()
    corrected[1, :3, 3] += rng.normal(0, 0.1, 3)
    trajectory = scan_trajectory(corrected, odometry[keyframes], keyframes, odometry)
    np.testing.assert_allclose(trajectory[:3], odometry[:3])
    shift = corrected[1, :3, 3] - odometry[3, :3, 3]
    np.testing.assert_allclose(trajectory[3:, :3, 3], odometry[3:, :3, 3] + shift)


def test_the_trajectory_is_drawn_over_the_map_pictures(tmp_path):
    pytest.importorskip("matplotlib")
    from matplotlib.image import imread
    from terracube.viz import plot_layer

    elevation_map = tc.build_elevation_map(_ground_scene(), 0.2)
    path = np.c_[np.linspace(-8, 8, 20), np.zeros(20)]
    plain = imread(plot_layer(elevation_map, "max", tmp_path / "plain.png", title="t"))
    drawn = imread(plot_layer(elevation_map, "max", tmp_path / "path.png", title="t", trajectory=path))
    assert plain.shape == drawn.shape
    changed = np.any(np.abs(plain - drawn) > 0.1, axis=-1)
    rows = np.nonzero(changed.any(axis=1))[0]
    # a horizontal line across the map: the change is a thin band of rows, not the whole picture
    assert 0 < rows.size < 0.1 * plain.shape[0] and changed.sum() > 100


def test_the_configs_stay_equal_after_a_dataclass_round_trip():
    frame = dataclasses.replace(default_config().frame, max_range=30.0)
    assert frame.max_range == 30.0 and frame.min_range == 0.1


def test_the_lengths_of_a_stage_report_carry_the_unit_of_a_foot_crs(tmp_path, shared_data):
    """The bundled tile measures in US survey feet: its reports give the cube edge, the cell size
    and the RMSEs in ftUS, not in metres they are not."""
    pytest.importorskip("rasterio")
    pytest.importorskip("laspy")
    path = shared_data.path("als_classified/laspy_wkt_geotiff_ground_veg_building.las")
    points = read_points(path)[:, :3]
    first = {
        stage: run_stage(stage, points, stage, tmp_path, source=path, png=False).lines[0]
        for stage in ("collapse", "dem", "classify", "fem")
    }
    assert "(edge 0.5 ftUS, sigma 2 cubes;" in first["collapse"], first
    assert "cells at 0.1 ftUS," in first["dem"] and "(edge 0.5 ftUS, sigma 2)" in first["dem"], first
    assert "cells at 0.1 ftUS," in first["classify"], first
    assert "(edge 0.5 ftUS, sigma 2;" in first["fem"] and "cells (0.1 ftUS) filled" in first["fem"], first
    assert re.search(r"training RMSE \d+\.\d{3} ftUS .* mean DEM \d+\.\d{3} ftUS;", first["fem"]), first
    assert not any(re.search(r"\d m\b", line) for line in first.values()), first


def test_length_text_names_the_unit_or_says_file_units():
    from terracube.pipeline import length_text

    assert length_text(0.5) == "0.5 m"
    assert length_text(3.28084, ("US survey foot", 1200 / 3937)) == "3.28084 ftUS"
    assert length_text(0.1234, ("foot", 0.3048), ".2f") == "0.12 ft"
    assert length_text(0.5, ("degree", None)) == "0.5 (file units, degree)"


def test_looks_airborne_tells_a_tile_seen_from_above_from_a_ground_sensors_scan():
    from terracube.pipeline import looks_airborne

    rng = np.random.default_rng(3)
    n = 20_000
    angle, reach = rng.uniform(0, 2 * np.pi, n), rng.uniform(2.0, 60.0, n)
    ground_scan = np.column_stack([reach * np.cos(angle), reach * np.sin(angle), rng.uniform(-1.7, 3.0, n)])
    forward = ground_scan[ground_scan[:, 1] > 5.0]  # a car's forward-looking LiDAR: none behind it
    tile = np.column_stack([rng.uniform(0, 300, n), rng.uniform(0, 300, n), rng.uniform(0, 25, n)])
    column = np.column_stack([rng.uniform(0, 8, n), rng.uniform(0, 8, n), rng.uniform(0, 30, n)])  # a tree
    assert not looks_airborne(ground_scan) and not looks_airborne(forward)
    assert looks_airborne(tile + [500_000.0, 4_000_000.0, 100.0])  # georeferenced
    assert looks_airborne(tile - [150.0, 150.0, 600.0])  # the scanner's own frame, 575 m above the top
    assert not looks_airborne(tile - [150.0, 150.0, 0.0])  # a sensor amid the points
    assert not looks_airborne(column + [500_000.0, 4_000_000.0, 100.0])  # taller than wide
    assert not looks_airborne(np.zeros((2, 3))) and not looks_airborne(np.full((10, 3), np.nan))


def test_the_airborne_hint_follows_the_clouds_geometry_when_the_source_does_not_tell(tmp_path):
    rng = np.random.default_rng(4)
    n = 5000
    tile = np.column_stack([rng.uniform(0, 200, n), rng.uniform(0, 200, n), rng.uniform(0, 20, n)])
    hints = {}
    for label, points in (
        ("georeferenced", tile + [500_000.0, 4_000_000.0, 100.0]),
        ("amid", tile - [100, 100, 0]),
    ):
        report = run_stage("dem", points, label, tmp_path, png=False)
        fill = [line for line in report.lines if "cells hold data" in line]
        assert len(fill) == 1, report.lines
        hints[label] = "--preset airborne_las" in fill[0]
    assert hints == {"georeferenced": True, "amid": False}


def test_every_stage_reports_the_points_the_kitti_crop_box_leaves_out(tmp_path, shared_data):
    """--preset kitti crops 40 m around the car: collapse, dem, classify and fem all say how many
    points it left out, and agree (a count independent of each stage's own removal)."""
    from terracube.pipeline import leveled_points

    config = load_config(None, preset="kitti")
    points = shared_data.kitti_xyzi(0)[:, :3]
    kept = points[config.frame.in_range(points)]
    leveled, inside = leveled_points(kept, config)
    expected = int(np.count_nonzero(np.isfinite(leveled).all(axis=1) & ~inside))
    assert expected > 1000  # the KITTI scan reaches 80 m
    line = f"  {expected:,} points outside the crop box were left out"
    for stage in ("collapse", "dem", "classify", "fem"):
        report = run_stage(stage, points, stage, tmp_path, config, png=False)
        assert line in report.lines, (stage, report.lines)
