"""The work behind the ``terracube`` command line and ``terracube batch``, without the printing.

Each per-scan stage (collapse, dem, classify, fem) reads nothing and prints nothing:
:func:`run_stage` takes the points, runs the stage with a :class:`terracube.config.Config`, writes
the outputs as ``NAME_...`` files and returns a :class:`StageReport` (summary lines, written files).
The command line prints the report; batch workers collect it. :func:`register_scans` and
:func:`build_global_map` do the same for ``terracube register`` and ``terracube map``. Scans are found
with :func:`read_scan` and :func:`expand_inputs`, so a new input source (a ROS bag topic, say) is
added in one place.

Example
-------
>>> from terracube.pipeline import read_scan, run_stage
>>> report = run_stage("dem", read_scan("scan.pcd"), "scan", "out")
>>> print("\\n".join(report.lines))
"""

from __future__ import annotations

import dataclasses
import glob
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "CLOUD_FORMATS",
    "REGISTRATION_METHODS",
    "SCAN_SUFFIXES",
    "STAGES",
    "StageReport",
    "build_global_map",
    "collapse_params",
    "elevation_params",
    "expand_inputs",
    "leveled_points",
    "mapper_params",
    "point_classes",
    "read_scan",
    "register_scans",
    "registration_record",
    "run_stage",
]

#: Formats of the classified clouds the stages write.
CLOUD_FORMATS = ("ply", "pcd", "las", "laz", "bin", "npz", "npy", "txt", "xyz")
#: Stages :func:`run_stage` (and so ``terracube batch``) can run on one scan.
STAGES = ("collapse", "dem", "classify", "fem")
#: Suffixes of the scans a folder contributes (the readable point-cloud formats).
SCAN_SUFFIXES = (".pcd", ".ply", ".las", ".laz", ".bin", ".npy", ".npz", ".txt", ".xyz", ".csv", ".asc")

# pyplot keeps global state: batch workers running in threads draw one picture at a time.
_PLOT_LOCK = threading.Lock()


# ------------------------------------------------------------------------------------------ inputs


def read_scan(path: str | Path) -> np.ndarray:
    """The (N, 3) or wider array of points [m] of one scan file (any format of :mod:`terracube.io`).

    Raises FileNotFoundError for a missing file and ValueError naming the file for a malformed one.
    """
    from .io import read_points

    return read_points(path)


def expand_inputs(inputs: Iterable[str | Path]) -> list[Path]:
    """The scans named by ``inputs``: files as given, folders' scans (by suffix, sorted), glob matches.

    Duplicates are dropped, order kept. ValueError when an input matches nothing or no scan at all.
    """
    files: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES)
            if not found:
                raise ValueError(f"{path}: the folder holds no scan ({', '.join(SCAN_SUFFIXES)})")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        elif glob.has_magic(str(item)):
            found = sorted(Path(p) for p in glob.glob(str(item), recursive=True) if Path(p).is_file())
            if not found:
                raise ValueError(f"{item}: the pattern matches no file")
            files.extend(found)
        else:
            raise ValueError(f"{path}: no such file or folder")
    unique = list(dict.fromkeys(files))
    if not unique:
        raise ValueError("no scan to process")
    return unique


# ------------------------------------------------------------------------------------------ parameters


def collapse_params(config):
    """The config's collapse section in the config's frame (leveling transform and crop box)."""
    frame = config.frame
    return dataclasses.replace(config.collapse, transform=frame.transform(), crop=frame.crop_box())


def elevation_params(config, **changes):
    """The config's elevation section in the config's frame, with ``changes`` applied."""
    frame = config.frame
    return dataclasses.replace(
        config.elevation, transform=frame.transform(), crop=frame.crop_box(), **changes
    )


def mapper_params(config):
    """MapperParams of the config: the mapper section plus the terrain and registration sections.

    An untouched terrain section (the paper's sensor-height reference) gives way to the mapper's
    terrain defaults (local ground, 1 m window) for maps chained over slopes.
    """
    from .config import default_config
    from .mapping import MapperParams

    terrain = config.terrain
    if terrain == default_config().terrain:
        terrain = MapperParams().terrain
    return dataclasses.replace(config.mapper, terrain=terrain, registration=config.registration)


def leveled_points(points: np.ndarray, config) -> tuple[np.ndarray, np.ndarray]:
    """The (N, 3) float64 points [m] in the leveled frame, and the (N,) bool mask of the finite ones
    inside the crop box."""
    transform = config.frame.transform()
    leveled = np.asarray(points[:, :3], dtype=np.float64) @ transform[:3, :3].T + transform[:3, 3]
    inside = np.all(np.isfinite(leveled), axis=1)
    box = config.frame.crop_box()
    if box is not None:
        inside &= np.all((leveled >= box[0]) & (leveled <= box[1]), axis=1)
    return leveled, inside


def point_classes(leveled: np.ndarray, inside: np.ndarray, elevation_map, classes: np.ndarray) -> np.ndarray:
    """(N,) uint8 class of each point: the class of the map cell holding it (leveled x, y), 0 outside.

    ``leveled`` and ``inside`` come from :func:`leveled_points`, ``classes`` is the (nx, ny) uint8
    output of :func:`terracube.classify_terrain` on ``elevation_map``.
    """
    g = elevation_map.geometry
    nx, ny = (int(v) for v in g.size)
    with np.errstate(invalid="ignore"):
        i = np.floor((leveled[:, 0] - g.origin[0]) / g.resolution)
        j = np.floor((leveled[:, 1] - g.origin[1]) / g.resolution)
    ok = inside & (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    labels = np.zeros(len(leveled), dtype=np.uint8)
    labels[ok] = classes[i[ok].astype(np.int64), j[ok].astype(np.int64)]
    return labels


# ------------------------------------------------------------------------------------------ stages


@dataclass
class StageReport:
    """What one stage did to one scan: its name, point count, summary lines and written files."""

    name: str
    points: int
    lines: list[str] = field(default_factory=list)
    outputs: list[Path] = field(default_factory=list)

    def add(self, label: str, *paths: Path) -> None:
        """Record written files and a summary line ``  label: path, path``."""
        self.outputs.extend(paths)
        self.lines.append(f"  {label}: {', '.join(map(str, paths))}")


def _elapsed_ms(start: float) -> float:
    return 1e3 * (time.perf_counter() - start)


def _check_cloud_format(cloud_format: str | None) -> None:
    if cloud_format is not None and cloud_format not in CLOUD_FORMATS:
        raise ValueError(f"the cloud format must be one of {', '.join(CLOUD_FORMATS)}, got {cloud_format!r}")


def _require_data(name: str, elevation_map) -> None:
    if not np.any(elevation_map["count"] > 0):
        raise ValueError(f"{name}: no point falls inside the map; check the crop box, origin and size")


def _pictures(*draw: Callable[[], Path]) -> list[Path]:
    with _PLOT_LOCK:
        return [picture() for picture in draw]


def _run_collapse(points, name, output_dir: Path, config, *, output_format="ply", png=True) -> StageReport:
    from . import collapse_overhangs
    from .io import write_classified

    _check_cloud_format(output_format)
    params = collapse_params(config)
    start = time.perf_counter()
    result = collapse_overhangs(points, params=params)
    elapsed_ms = _elapsed_ms(start)
    grid = result.grid
    report = StageReport(name, int(result.num_points))
    report.lines.append(
        f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
        f"(edge {params.edge} m, sigma {params.sigma} cubes; {len(result.occupied_cubes):,} occupied cubes, "
        f"{len(result.removed_cubes):,} collapsed; grid {grid.ixmax}x{grid.iymax}x{grid.izmax}; "
        f"{elapsed_ms:.1f} ms)"
    )
    if result.num_cropped:
        report.lines.append(f"  {result.num_cropped:,} points outside the crop box were left out")
    cloud = output_dir / f"{name}_classified.{output_format}"
    report.add("classified cloud", write_classified(cloud, points, result.overhang))
    if png:
        from .viz import plot_overhangs

        leveled, _ = leveled_points(points, config)
        title = (
            f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
            f"(collapsible cubes, E = {params.edge} m, sigma = {params.sigma})"
        )
        path = output_dir / f"{name}_overhangs.png"
        report.add("picture", *_pictures(lambda: plot_overhangs(leveled, result.overhang, path, title=title)))
    return report


def _run_dem(points, name, output_dir: Path, config, *, png=True, geotiff=False) -> StageReport:
    from . import build_elevation_map, dem_without_overhangs

    collapse = collapse_params(config)
    start = time.perf_counter()
    raw = build_elevation_map(points, params=elevation_params(config))
    raw_ms = _elapsed_ms(start)
    _require_data(name, raw)
    g = raw.geometry
    start = time.perf_counter()
    clean, result = dem_without_overhangs(
        points, collapse=collapse, elevation=elevation_params(config, origin=g.origin, size=g.size)
    )
    clean_ms = _elapsed_ms(start)
    before, after = raw["max"], clean["max"]
    lower = int(np.count_nonzero(np.isfinite(before) & np.isfinite(after) & (after < before)))
    emptied = int(np.count_nonzero(np.isfinite(before) & np.isnan(after)))
    report = StageReport(name, int(result.num_points))
    report.lines.append(
        f"{name}: DEM {g.size[0]} x {g.size[1]} cells at {g.resolution:g} m, "
        f"{int(np.count_nonzero(np.isfinite(before))):,} with data; {result.num_overhang:,} of "
        f"{result.num_points:,} points are overhang (edge {collapse.edge} m, sigma {collapse.sigma}); "
        f"{lower:,} cells lower, {emptied:,} emptied; raw DEM {raw_ms:.1f} ms, DEM without overhangs "
        f"{clean_ms:.1f} ms"
    )
    report.add("map", clean.save(output_dir / f"{name}_dem.npz"))
    if geotiff:
        report.add("GeoTIFF", clean.to_geotiff("max", output_dir / f"{name}_dem_max.tif"))
    if png:
        from .viz import plot_dem_comparison, plot_layer

        robot_height = collapse.sigma * collapse.edge
        pictures = _pictures(
            lambda: plot_dem_comparison(
                raw,
                clean,
                output_dir / f"{name}_dem_comparison.png",
                title=f"{name}: highest elevation before and after overhang removal "
                f"(E = {collapse.edge} m, σ = {collapse.sigma})",
            ),
            lambda: plot_layer(
                clean,
                "clearance",
                output_dir / f"{name}_clearance.png",
                title=f"{name}: clearance from the retained points to the lowest overhang above",
                cmap="RdYlGn",
                vmin=0.0,
                vmax=2.0 * robot_height + collapse.edge,
            ),
            lambda: plot_layer(
                clean,
                "step",
                output_dir / f"{name}_step.png",
                title=f"{name}: largest step of the DEM without overhangs to a neighbour cell",
                cmap="plasma",
                vmin=0.0,
            ),
        )
        report.add("pictures", *pictures)
    return report


def map_of_scan(points, name, config, remove_overhangs: bool):
    """The elevation map of one scan (raw, or without overhangs), a description of it, and the
    :class:`terracube.CollapseResult` (None for the raw map). ValueError when no point is in the map."""
    from . import build_elevation_map, dem_without_overhangs

    if remove_overhangs:
        collapse = collapse_params(config)
        elevation_map, result = dem_without_overhangs(
            points, collapse=collapse, elevation=elevation_params(config)
        )
        source = (
            f"DEM without overhangs (edge {collapse.edge} m, sigma {collapse.sigma}; "
            f"{result.num_overhang:,} overhang points)"
        )
    else:
        elevation_map, result = build_elevation_map(points, params=elevation_params(config)), None
        source = "raw map"
    _require_data(name, elevation_map)
    return elevation_map, source, result


def classified_map(points, name, config, remove_overhangs: bool):
    """(elevation map, (nx, ny) uint8 classes, description, map ms, classification ms) of one scan."""
    from . import classify_terrain

    config.terrain.to_core()  # checks the thresholds before the map is built
    start = time.perf_counter()
    elevation_map, source, _ = map_of_scan(points, name, config, remove_overhangs)
    map_ms = _elapsed_ms(start)
    start = time.perf_counter()
    classes = classify_terrain(elevation_map, config.terrain)
    return elevation_map, classes, source, map_ms, _elapsed_ms(start)


def _reference_text(terrain) -> str:
    if terrain.reference == "sensor_height":
        return f"sensor height {terrain.sensor_height:g} m"
    return f"local ground, {terrain.local_ground_radius} cells"


#: How far [m] the cells' typical lowest point may lie from the sensor-height ground plane before
#: ``classify`` suggests another sensor height (a KITTI scan classified with the default 0 m).
_GROUND_PLANE_HINT_M = 0.5


def _ground_plane_hint(elevation_map, terrain) -> str | None:
    """A note when the sensor-height reference looks wrong for the scan: the median of the cells'
    lowest elevations (mostly ground cells on a ground robot's scan) lies more than
    :data:`_GROUND_PLANE_HINT_M` from the plane z = -sensor_height that [TC] Table 1 measures from."""
    if terrain.reference != "sensor_height":
        return None
    lowest = elevation_map["min"]
    lowest = lowest[~np.isnan(lowest)]
    if lowest.size == 0:
        return None
    typical = float(np.median(lowest))
    plane = -float(terrain.sensor_height)
    if abs(typical - plane) <= _GROUND_PLANE_HINT_M:
        return None
    return (
        f"  note: half the cells' lowest points lie at or below z = {typical:.2f} m, "
        f"{abs(typical - plane):.2f} m from the ground plane z = {plane + 0.0:g} m of the sensor height; "
        f"if that is the ground, pass --sensor-height {-typical:.2f}, or --reference local_ground"
    )


def _run_classify(
    points,
    name,
    output_dir: Path,
    config,
    *,
    remove_overhangs=False,
    cloud_format="ply",
    png=True,
    geotiff=False,
) -> StageReport:
    from . import TerrainClass
    from .io import TERRAIN_LAS_CLASSES, write_classified

    _check_cloud_format(cloud_format)
    elevation_map, classes, source, map_ms, classify_ms = classified_map(
        points, name, config, remove_overhangs
    )
    g = elevation_map.geometry
    counts = np.bincount(classes.ravel(), minlength=len(TerrainClass))
    known = int(classes.size - counts[0])
    where = _reference_text(config.terrain)
    report = StageReport(name, len(points))
    report.lines.append(
        f"{name}: {g.size[0]} x {g.size[1]} cells at {g.resolution:g} m, {known:,} with data; {source}; "
        f"reference {where}; map {map_ms:.1f} ms, classification {classify_ms:.1f} ms"
    )
    for terrain_class in TerrainClass:
        count = int(counts[int(terrain_class)])
        share = f" ({count / known:.1%} of cells with data)" if terrain_class and known else ""
        report.lines.append(f"  {terrain_class.name.lower().replace('_', ' '):<20} {count:>10,}{share}")
    hint = _ground_plane_hint(elevation_map, config.terrain)
    if hint is not None:
        report.lines.append(hint)
    report.add("map", elevation_map.save(output_dir / f"{name}_classes.npz"))
    if cloud_format is not None:
        labels = point_classes(*leveled_points(points, config), elevation_map, classes)
        cloud = output_dir / f"{name}_classes.{cloud_format}"
        cloud = write_classified(cloud, points, labels, las_classes=TERRAIN_LAS_CLASSES)
        report.add("classified cloud (per-point terrain class)", cloud)
    if geotiff:
        report.add("GeoTIFF", elevation_map.to_geotiff("class", output_dir / f"{name}_classes.tif"))
    if png:
        from .viz import plot_terrain_classes

        title = f"{name}: terrain classes ({source.split(' (')[0]}, {where})"
        path = output_dir / f"{name}_classes.png"
        report.add(
            "picture", *_pictures(lambda: plot_terrain_classes(elevation_map, classes, path, title=title))
        )
    return report


def _run_fem(
    points, name, output_dir: Path, config, *, remove_overhangs=True, png=True, geotiff=False
) -> StageReport:
    from . import fit_fuzzy_elevation_map

    start = time.perf_counter()
    elevation_map, source, collapse = map_of_scan(points, name, config, remove_overhangs)
    leveled, use = leveled_points(points, config)
    if collapse is not None:
        use &= ~collapse.overhang
    fem = fit_fuzzy_elevation_map(np.ascontiguousarray(leveled), config.fuzzy, use=use)
    fem.to_layer(elevation_map, config.fuzzy.min_confidence)
    elapsed_ms = _elapsed_ms(start)
    fitted, dem = elevation_map["fem"], elevation_map["mean"]
    both = np.isfinite(fitted) & np.isfinite(dem)
    rmse = float(np.sqrt(np.mean((fitted[both] - dem[both]) ** 2))) if both.any() else float("nan")
    g = elevation_map.geometry
    report = StageReport(name, len(points))
    history = fem.rmse_history
    report.lines.append(
        f"{name}: fuzzy elevation map of {fem.num_rules} rules ({fem.num_parameters} parameters) from "
        f"{fem.num_training_points:,} points of the {source}; training RMSE "
        f"{history[-1]:.3f} m after {len(history) - 1} epochs; {int(np.isfinite(fitted).sum()):,} of "
        f"{g.size[0] * g.size[1]:,} cells ({g.resolution:g} m) filled, RMSE to the mean DEM {rmse:.3f} m; "
        f"{elapsed_ms:.1f} ms"
    )
    report.add(
        "map (layers fem, fem_confidence and the DEM's)", elevation_map.save(output_dir / f"{name}_fem.npz")
    )
    if geotiff:
        report.add("GeoTIFF", elevation_map.to_geotiff("fem", output_dir / f"{name}_fem.tif"))
    if png:
        from .viz import plot_layer

        pictures = _pictures(
            lambda: plot_layer(
                elevation_map,
                "fem",
                output_dir / f"{name}_fem.png",
                title=f"{name}: fuzzy elevation map ({len(fem.centers_x)} x {len(fem.centers_y)} rules)",
            ),
            lambda: plot_layer(
                elevation_map,
                "fem_confidence",
                output_dir / f"{name}_fem_confidence.png",
                title=f"{name}: rule support of the fuzzy elevation map [points]",
                cmap="magma",
                vmin=0.0,
            ),
        )
        report.add("pictures", *pictures)
    return report


_RUNNERS: dict[str, Callable[..., StageReport]] = {
    "collapse": _run_collapse,
    "dem": _run_dem,
    "classify": _run_classify,
    "fem": _run_fem,
}

#: The output options each stage takes, with their defaults.
STAGE_OUTPUT_OPTIONS: dict[str, dict[str, object]] = {
    "collapse": {"output_format": "ply", "png": True},
    "dem": {"png": True, "geotiff": False},
    "classify": {"remove_overhangs": False, "cloud_format": "ply", "png": True, "geotiff": False},
    "fem": {"remove_overhangs": True, "png": True, "geotiff": False},
}


def run_stage(
    stage: str, points: np.ndarray, name: str, output_dir: str | Path, config=None, **options
) -> StageReport:
    """Run one stage on one scan and write its outputs to ``output_dir`` as ``NAME_...`` files.

    Parameters
    ----------
    stage
        One of :data:`STAGES`: collapse, dem, classify, fem.
    points
        (N, 3) or wider float32/float64 array of points [m] in the sensor frame.
    name
        Prefix of the written files, usually the scan file's stem.
    output_dir
        Folder for the outputs; created when missing.
    config
        A :class:`terracube.config.Config` (the defaults when None).
    **options
        The stage's output options, :data:`STAGE_OUTPUT_OPTIONS` (collapse: ``output_format``,
        ``png``; dem: ``png``, ``geotiff``; classify: ``remove_overhangs``, ``cloud_format``,
        ``png``, ``geotiff``; fem: ``remove_overhangs``, ``png``, ``geotiff``).

    Returns
    -------
    StageReport
        Summary lines and written files; nothing is printed.

    Raises ValueError for bad input or parameters.
    """
    from .config import default_config

    if stage not in _RUNNERS:
        raise ValueError(f"unknown stage {stage!r} (one of {', '.join(STAGES)})")
    unknown = set(options) - set(STAGE_OUTPUT_OPTIONS[stage])
    if unknown:
        raise TypeError(f"stage {stage!r} takes no option {', '.join(sorted(unknown))}")
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    return _RUNNERS[stage](points, name, output_dir, config or default_config(), **options)


# ------------------------------------------------------------------------------------------ register

#: Registration methods of :func:`register_scans`.
REGISTRATION_METHODS = ("classes", "all-cells", "pcl")


def registration_record(method: str, source: str, target: str, result) -> dict:
    """A JSON-ready summary of one registration: transform (4, 4), yaw [deg], convergence and why,
    iterations, RMSE [m] or PCL's fitness [m^2], correspondences per terrain class, constraints."""
    from . import TerrainClass

    transform = np.asarray(result.transform)
    record: dict = {
        "source": str(source),
        "target": str(target),
        "method": method,
        "transform": transform.tolist(),
        "yaw_deg": float(np.degrees(np.arctan2(transform[1, 0], transform[0, 0]))),
        "converged": bool(result.converged),
        "iterations": int(result.iterations),
    }
    if method == "pcl":
        record["reason"] = "converged" if result.converged else "not converged"
        record["fitness"] = float(result.fitness)
        # PCL gives no verdict of its own: its convergence stands in for it.
        record["trusted"] = bool(result.converged)
        record["verdict"] = "PCL's ICP " + (
            "converged (no overlap or constraint test)" if result.converged else "did not converge"
        )
        return record
    counts = list(result.correspondences_per_class)
    record.update(
        reason=result.reason.name,
        rmse=float(result.rmse),
        num_correspondences=int(result.num_correspondences),
        correspondences_per_class={c.name.lower(): int(counts[int(c)]) for c in TerrainClass},
        overlap=float(result.overlap),
        inlier_share_per_class={
            c.name.lower(): float(result.inlier_share_per_class[int(c)]) for c in TerrainClass
        },
        trusted=bool(result.trusted),
        verdict=str(result.verdict),
    )
    if np.any(np.asarray(result.constraint_matrix)):
        from .registration import constrained_directions

        record["constraints"] = [
            {"along": along, "held": held} for along, held, _ in constrained_directions(result)
        ]
    return record


def register_scans(
    source: np.ndarray,
    target: np.ndarray,
    config=None,
    *,
    method: str = "classes",
    initial: np.ndarray | None = None,
    remove_overhangs: bool = False,
    names: tuple[str, str] = ("source", "target"),
) -> tuple[dict, float]:
    """Map and classify two scans, then move ``source`` onto ``target``.

    Parameters
    ----------
    source, target : (N, 3) and (M, 3) or wider float arrays
        The scans' points [m], each in its sensor frame.
    config
        A :class:`terracube.config.Config` (defaults when None): frame, elevation, terrain,
        registration and pcl_icp sections.
    method
        ``classes`` (the paper's class-weighted ICP), ``all-cells`` (every cell, unit weight) or
        ``pcl`` (PCL's point-to-point ICP on the same cell points; RuntimeError without PCL).
    initial : (4, 4) array, optional
        Guess of the source -> target transform (identity when None).
    remove_overhangs
        Map each scan without its overhangs first.
    names
        The scans' names in the record and in error messages.

    Returns
    -------
    (dict, float)
        :func:`registration_record` of the result, and the registration's time [ms].
    """
    from .config import default_config
    from .registration import pcl_icp, points_of_map, register_maps, register_maps_all_cells

    if method not in REGISTRATION_METHODS:
        raise ValueError(f"the method must be one of {', '.join(REGISTRATION_METHODS)}, got {method!r}")
    config = config or default_config()
    guess = np.eye(4) if initial is None else np.asarray(initial, dtype=np.float64)
    maps = [
        classified_map(points, name, config, remove_overhangs)[0]
        for points, name in zip((source, target), names, strict=True)
    ]
    start = time.perf_counter()
    if method == "classes":
        result = register_maps(maps[0], maps[1], guess, config.registration)
    elif method == "all-cells":
        result = register_maps_all_cells(maps[0], maps[1], guess, config.registration)
    else:
        result = pcl_icp(points_of_map(maps[0])[0], points_of_map(maps[1])[0], guess, config.pcl_icp)
    return registration_record(method, names[0], names[1], result), _elapsed_ms(start)


# ------------------------------------------------------------------------------------------ map


def build_global_map(
    scans: Iterable[tuple[str, np.ndarray, int]],
    odometry: np.ndarray,
    stamps: np.ndarray,
    output_dir: str | Path,
    config=None,
    *,
    png: bool = True,
    ground_truth: np.ndarray | None = None,
) -> StageReport:
    """Chain a scan sequence into a global elevation map with :class:`terracube.Mapper` and write it.

    Parameters
    ----------
    scans
        ``(name, points, pose index)`` per scan, in order: (N, 3) or wider points [m] in the sensor
        frame and the row of ``odometry`` taken when it was recorded. Read lazily, so a generator
        that reads files keeps one scan in memory.
    odometry : (P, 4, 4) array
        Odometry poses world <- sensor [m].
    stamps : (P,) array
        Their times [s], for the TUM trajectory.
    output_dir
        Writes ``global_map.npz``, ``trajectory_kitti.txt``, ``trajectory_tum.txt`` (keyframes) and,
        with ``png``, ``global_max.png`` and ``global_classes.png``.
    config
        A :class:`terracube.config.Config`: the mapper, terrain and registration sections.
    ground_truth : (P, 4, 4) array, optional
        True poses: the report adds the ATE of the estimate and of the odometry (first pose aligned).

    Returns
    -------
    StageReport
        Summary lines (scans, keyframes, loops, time per step, the map) and the written files.
    """
    from .config import default_config
    from .mapping import Mapper
    from .poses import write_kitti_poses, write_tum_poses

    mapper = Mapper(mapper_params(config or default_config()))
    indices: list[int] = []
    start = time.perf_counter()
    for name, points, index in scans:
        try:
            mapper.add_scan(points, odometry[index])
        except (ValueError, TypeError) as error:
            raise ValueError(f"{name}: {error}") from error
        indices.append(index)
    if mapper.pending_loops:
        mapper.optimize()
    seconds = time.perf_counter() - start
    if not indices:
        raise ValueError("no scan to map")
    dem = mapper.global_map()
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    report = StageReport("global map", len(indices))
    report.outputs.append(dem.save(output_dir / "global_map.npz"))
    keyframes = mapper.keyframe_poses()
    key_scans = [indices[k] for k in mapper.keyframe_scan_indices()]
    write_kitti_poses(output_dir / "trajectory_kitti.txt", keyframes)
    write_tum_poses(output_dir / "trajectory_tum.txt", stamps[key_scans], keyframes)
    report.outputs += [output_dir / "trajectory_kitti.txt", output_dir / "trajectory_tum.txt"]
    if png and dem.geometry.num_cells > 0:
        from .viz import plot_layer, plot_terrain_classes

        classes = np.nan_to_num(dem["class"], nan=0).astype(np.uint8)
        report.outputs += _pictures(
            lambda: plot_layer(dem, "max", output_dir / "global_max.png", title="highest elevation [m]"),
            lambda: plot_terrain_classes(
                dem, classes, output_dir / "global_classes.png", title="terrain classes"
            ),
        )
    t = mapper.timings
    g = dem.geometry
    report.lines += [
        f"{len(indices)} scans, {len(mapper)} keyframes, {len(mapper.loop_closures)} loop closures "
        f"in {seconds:.2f} s ({len(indices) / seconds:.1f} scans/s incl. reading)",
        f"time [ms]: map building {t.map_building_ms:.0f}, classification {t.classification_ms:.0f}, "
        f"registration {t.registration_ms:.0f}, fusion {t.fusion_ms:.0f}, "
        f"loop closing {t.loop_closing_ms:.0f}",
        f"global map: {int(g.size[0])} x {int(g.size[1])} cells at {g.resolution} m, "
        f"{int(np.isfinite(dem['max']).sum())} with data, "
        f"{mapper.global_memory_bytes / 2**20:.1f} MiB of tiles",
    ]
    if ground_truth is not None:
        from .evaluation import absolute_trajectory_error

        truth = np.asarray(ground_truth)[key_scans]
        estimate = absolute_trajectory_error(keyframes, truth, "first_pose").translation
        odom = absolute_trajectory_error(mapper.keyframe_odometry(), truth, "first_pose").translation
        report.lines.append(
            f"ATE (first pose aligned): mapper RMSE {estimate.rmse:.3f} m, odometry RMSE {odom.rmse:.3f} m"
        )
    report.lines += [f"written: {path}" for path in report.outputs]
    return report
