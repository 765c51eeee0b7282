"""The ``terracube`` command line: one subcommand per stage, parameters from flags or a YAML file.

Every stage subcommand takes ``--config FILE`` (see ``terracube config``); an option given on the
command line wins over the file, the file over the defaults. The per-file work of the stages that
``terracube batch`` can run (collapse, dem, classify, fem) lives in :func:`run_stage`, which returns
what it did (summary lines, written files) and prints nothing, so batch workers share it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import typer

app = typer.Typer(
    help="Navigable 2.5D elevation maps from ground-robot 3D LiDAR scans.\n\n"
    "Stages: collapse (overhang removal), dem (elevation map), classify (terrain classes), "
    "fem (fuzzy elevation map), register (ICP between two scans), map (global elevation map and "
    "trajectory from a scan sequence with odometry), view (pictures, 3D); batch runs a stage over "
    "many scans with Dask; config prints every parameter as YAML.",
    no_args_is_help=True,
    add_completion=False,
)

#: Formats of the classified clouds the stages write.
CLOUD_FORMATS = ("ply", "pcd", "las", "laz", "bin", "npz", "npy", "txt", "xyz")
#: Stages ``run_stage`` (and so ``terracube batch``) can run on one scan.
BATCH_STAGES = ("collapse", "dem", "classify", "fem")
REGISTRATION_METHODS = ("classes", "all-cells", "pcl")

_Crop = tuple[float, float, float, float, float, float]

# pyplot keeps global state: batch workers running in threads draw one picture at a time.
_PLOT_LOCK = threading.Lock()


# ------------------------------------------------------------------------------------------ helpers


def _fail(message: str) -> typer.Exit:
    """Print a red error message; the caller raises the returned Exit (code 2)."""
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    return typer.Exit(2)


@contextmanager
def _exit_on_bad_input(name: str = "") -> Iterator[None]:
    """Turn a ValueError, TypeError or KeyError into ``error: NAME: ...`` and exit code 2."""
    try:
        yield
    except (ValueError, TypeError, KeyError) as error:
        text = error.args[0] if isinstance(error, KeyError) and error.args else error
        raise _fail(f"{name}: {text}" if name else str(text)) from error


def _read_points(input_path: Path) -> np.ndarray:
    """The points of ``input_path``; a missing or unreadable file exits with code 2."""
    from .io import read_points

    try:
        return read_points(input_path)
    except (ValueError, FileNotFoundError) as error:
        raise _fail(str(error)) from error


def _elapsed_ms(start: float) -> float:
    return 1e3 * (time.perf_counter() - start)


def _default(section: str, key: str) -> Any:
    from .config import default_config

    return getattr(default_config()[section], key)


def _config(path: Path | None, **sections: dict[str, Any]) -> Any:
    """The configuration of ``--config`` (defaults when None) with the options given on the command
    line (not None) over it, one keyword per section; exit 2 naming the problem."""
    from .config import ConfigError, load_config

    try:
        config = load_config(path)
    except ConfigError as error:
        raise _fail(str(error)) from error
    with _exit_on_bad_input("command line"):
        for name, values in sections.items():
            config = config.replace(name, **values)
    return config


def _frame_options(roll: float | None, pitch: float | None, crop: _Crop | None) -> dict[str, Any]:
    return {
        "roll_deg": roll,
        "pitch_deg": pitch,
        "crop": None if crop is None else [list(crop[:3]), list(crop[3:])],
    }


def _sigma_option(
    sigma: int | None, robot_height: float | None, edge: float | None, config_path
) -> int | None:
    """--sigma, else ceil(--robot-height / edge) when --robot-height is given, else None (config)."""
    if sigma is not None or robot_height is None:
        return sigma
    from . import sigma_from_robot_height

    edge = edge if edge is not None else _config(config_path).collapse.edge
    with _exit_on_bad_input("--robot-height"):
        return sigma_from_robot_height(robot_height, edge)


def _extent_options(origin, size) -> dict[str, Any]:
    if (origin is None) != (size is None):
        raise _fail("give both --origin and --size for a fixed map extent, or neither")
    return {"origin": None if origin is None else list(origin), "size": None if size is None else list(size)}


# ------------------------------------------------------------------------------------------ stages


@dataclass
class StageReport:
    """What one stage did to one scan: its name, point count, summary lines and written files."""

    name: str
    points: int
    lines: list[str] = field(default_factory=list)
    outputs: list[Path] = field(default_factory=list)


def _collapse_params(config):
    frame = config.frame
    return dataclasses.replace(config.collapse, transform=frame.transform(), crop=frame.crop_box())


def _elevation_params(config, **changes):
    frame = config.frame
    return dataclasses.replace(
        config.elevation, transform=frame.transform(), crop=frame.crop_box(), **changes
    )


def _leveled(points: np.ndarray, config) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 points in the leveled frame, and the (N,) mask of finite ones inside the crop box."""
    transform = config.frame.transform()
    leveled = np.asarray(points[:, :3], dtype=np.float64) @ transform[:3, :3].T + transform[:3, 3]
    inside = np.all(np.isfinite(leveled), axis=1)
    box = config.frame.crop_box()
    if box is not None:
        inside &= np.all((leveled >= box[0]) & (leveled <= box[1]), axis=1)
    return leveled, inside


def point_classes(leveled: np.ndarray, inside: np.ndarray, elevation_map, classes: np.ndarray) -> np.ndarray:
    """(N,) uint8 class of each point: the class of the map cell holding it (leveled x, y), 0 outside."""
    g = elevation_map.geometry
    nx, ny = (int(v) for v in g.size)
    with np.errstate(invalid="ignore"):
        i = np.floor((leveled[:, 0] - g.origin[0]) / g.resolution)
        j = np.floor((leveled[:, 1] - g.origin[1]) / g.resolution)
    ok = inside & (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    labels = np.zeros(len(leveled), dtype=np.uint8)
    labels[ok] = classes[i[ok].astype(np.int64), j[ok].astype(np.int64)]
    return labels


def _require_data(name: str, elevation_map) -> None:
    if not np.any(elevation_map["count"] > 0):
        raise ValueError(f"{name}: no point falls inside the map; check the crop box, origin and size")


def _geotiff(elevation_map, layer: str, path: Path, report: StageReport) -> None:
    report.outputs.append(elevation_map.to_geotiff(layer, path))


def _run_collapse(points, name, output_dir: Path, config, *, output_format="ply", png=True) -> StageReport:
    from . import collapse_overhangs
    from .io import write_classified

    if output_format not in CLOUD_FORMATS:
        raise ValueError(f"the cloud format must be one of {', '.join(CLOUD_FORMATS)}, got {output_format!r}")
    params = _collapse_params(config)
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
    cloud = write_classified(output_dir / f"{name}_classified.{output_format}", points, result.overhang)
    report.outputs.append(cloud)
    report.lines.append(f"  classified cloud: {cloud}")
    if png:
        from .viz import plot_overhangs

        leveled, _ = _leveled(points, config)
        with _PLOT_LOCK:
            picture = plot_overhangs(
                leveled,
                result.overhang,
                output_dir / f"{name}_overhangs.png",
                title=f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
                f"(collapsible cubes, E = {params.edge} m, sigma = {params.sigma})",
            )
        report.outputs.append(picture)
        report.lines.append(f"  picture: {picture}")
    return report


def _run_dem(points, name, output_dir: Path, config, *, png=True, geotiff=False) -> StageReport:
    from . import build_elevation_map, dem_without_overhangs

    collapse = _collapse_params(config)
    start = time.perf_counter()
    raw = build_elevation_map(points, params=_elevation_params(config))
    raw_ms = _elapsed_ms(start)
    _require_data(name, raw)
    g = raw.geometry
    start = time.perf_counter()
    clean, result = dem_without_overhangs(
        points, collapse=collapse, elevation=_elevation_params(config, origin=g.origin, size=g.size)
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
    report.outputs.append(clean.save(output_dir / f"{name}_dem.npz"))
    report.lines.append(f"  map: {report.outputs[-1]}")
    if geotiff:
        _geotiff(clean, "max", output_dir / f"{name}_dem_max.tif", report)
        report.lines.append(f"  GeoTIFF: {report.outputs[-1]}")
    if png:
        from .viz import plot_dem_comparison, plot_layer

        robot_height = collapse.sigma * collapse.edge
        with _PLOT_LOCK:
            pictures = [
                plot_dem_comparison(
                    raw,
                    clean,
                    output_dir / f"{name}_dem_comparison.png",
                    title=f"{name}: highest elevation before and after overhang removal "
                    f"(E = {collapse.edge} m, σ = {collapse.sigma})",
                ),
                plot_layer(
                    clean,
                    "clearance",
                    output_dir / f"{name}_clearance.png",
                    title=f"{name}: clearance from the retained points to the lowest overhang above",
                    cmap="RdYlGn",
                    vmin=0.0,
                    vmax=2.0 * robot_height + collapse.edge,
                ),
                plot_layer(
                    clean,
                    "step",
                    output_dir / f"{name}_step.png",
                    title=f"{name}: largest step of the DEM without overhangs to a neighbour cell",
                    cmap="plasma",
                    vmin=0.0,
                ),
            ]
        report.outputs.extend(pictures)
        report.lines.append(f"  pictures: {', '.join(map(str, pictures))}")
    return report


def _map_of(points, name, config, remove_overhangs: bool):
    """The elevation map of one scan (raw, or without overhangs), a description and the collapse result."""
    from . import build_elevation_map, dem_without_overhangs

    if remove_overhangs:
        collapse = _collapse_params(config)
        elevation_map, result = dem_without_overhangs(
            points, collapse=collapse, elevation=_elevation_params(config)
        )
        source = (
            f"DEM without overhangs (edge {collapse.edge} m, sigma {collapse.sigma}; "
            f"{result.num_overhang:,} overhang points)"
        )
    else:
        elevation_map, result = build_elevation_map(points, params=_elevation_params(config)), None
        source = "raw map"
    _require_data(name, elevation_map)
    return elevation_map, source, result


def _classified_map(points, name, config, remove_overhangs: bool):
    from . import classify_terrain

    config.terrain.to_core()  # checks the thresholds before the map is built
    start = time.perf_counter()
    elevation_map, source, _ = _map_of(points, name, config, remove_overhangs)
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
    :data:`_GROUND_PLANE_HINT_M` from the plane z = -sensor_height that Table 1 measures from."""
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

    if cloud_format is not None and cloud_format not in CLOUD_FORMATS:
        raise ValueError(f"the cloud format must be one of {', '.join(CLOUD_FORMATS)}, got {cloud_format!r}")
    elevation_map, classes, source, map_ms, classify_ms = _classified_map(
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
    report.outputs.append(elevation_map.save(output_dir / f"{name}_classes.npz"))
    report.lines.append(f"  map: {report.outputs[-1]}")
    if cloud_format is not None:
        leveled, inside = _leveled(points, config)
        labels = point_classes(leveled, inside, elevation_map, classes)
        cloud = write_classified(
            output_dir / f"{name}_classes.{cloud_format}", points, labels, las_classes=TERRAIN_LAS_CLASSES
        )
        report.outputs.append(cloud)
        report.lines.append(f"  classified cloud (per-point terrain class): {cloud}")
    if geotiff:
        _geotiff(elevation_map, "class", output_dir / f"{name}_classes.tif", report)
        report.lines.append(f"  GeoTIFF: {report.outputs[-1]}")
    if png:
        from .viz import plot_terrain_classes

        with _PLOT_LOCK:
            picture = plot_terrain_classes(
                elevation_map,
                classes,
                output_dir / f"{name}_classes.png",
                title=f"{name}: terrain classes ({source.split(' (')[0]}, {where})",
            )
        report.outputs.append(picture)
        report.lines.append(f"  picture: {picture}")
    return report


def _run_fem(
    points, name, output_dir: Path, config, *, remove_overhangs=True, png=True, geotiff=False
) -> StageReport:
    from . import fit_fuzzy_elevation_map

    start = time.perf_counter()
    elevation_map, source, collapse = _map_of(points, name, config, remove_overhangs)
    leveled, use = _leveled(points, config)
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
    report.outputs.append(elevation_map.save(output_dir / f"{name}_fem.npz"))
    report.lines.append(f"  map (layers fem, fem_confidence and the DEM's): {report.outputs[-1]}")
    if geotiff:
        _geotiff(elevation_map, "fem", output_dir / f"{name}_fem.tif", report)
        report.lines.append(f"  GeoTIFF: {report.outputs[-1]}")
    if png:
        from .viz import plot_layer

        with _PLOT_LOCK:
            pictures = [
                plot_layer(
                    elevation_map,
                    "fem",
                    output_dir / f"{name}_fem.png",
                    title=f"{name}: fuzzy elevation map ({len(fem.centers_x)} x {len(fem.centers_y)} rules)",
                ),
                plot_layer(
                    elevation_map,
                    "fem_confidence",
                    output_dir / f"{name}_fem_confidence.png",
                    title=f"{name}: rule support of the fuzzy elevation map [points]",
                    cmap="magma",
                    vmin=0.0,
                ),
            ]
        report.outputs.extend(pictures)
        report.lines.append(f"  pictures: {', '.join(map(str, pictures))}")
    return report


_RUNNERS: dict[str, Callable[..., StageReport]] = {
    "collapse": _run_collapse,
    "dem": _run_dem,
    "classify": _run_classify,
    "fem": _run_fem,
}


def run_stage(
    stage: str, points: np.ndarray, name: str, output_dir: Path, config=None, **options
) -> StageReport:
    """Run one stage on one scan and write its outputs to ``output_dir`` as ``NAME_...`` files.

    ``stage`` is one of :data:`BATCH_STAGES`; ``config`` a :class:`terracube.config.Config` (defaults
    when None); ``options`` the stage's output options (collapse: ``output_format``, ``png``; dem:
    ``png``, ``geotiff``; classify: ``remove_overhangs``, ``cloud_format``, ``png``, ``geotiff``; fem:
    ``remove_overhangs``, ``png``, ``geotiff``). Raises ValueError for bad input or parameters.
    """
    from .config import default_config

    if stage not in _RUNNERS:
        raise ValueError(f"unknown stage {stage!r} (one of {', '.join(BATCH_STAGES)})")
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    return _RUNNERS[stage](points, name, output_dir, config or default_config(), **options)


def _run_and_print(stage: str, input_path: Path, output_dir: Path, config, **options) -> None:
    points = _read_points(input_path)
    with _exit_on_bad_input(input_path.stem):
        report = run_stage(stage, points, input_path.stem, output_dir, config, **options)
    for line in report.lines:
        typer.echo(line)


# ------------------------------------------------------------------------------------------ options


def _help(text: str, section: str | None = None, key: str | None = None) -> str:
    """Option help ending with the configuration key it overrides and that key's default."""
    if section is None:
        return text
    default = _default(section, key)
    shown = "none" if default is None else default
    return f"{text} [config {section}.{key}, default {shown}]"


_INPUT = typer.Argument(
    ...,
    help="Point cloud: .pcd, .ply, .las/.laz, .bin (KITTI), .npy, .npz, .txt/.xyz/.csv.",
    show_default=False,
)
_OUTPUT_DIR = typer.Option(Path("terracube_out"), "--output-dir", "-o", help="Where to write.")
_CONFIG = typer.Option(
    None, "--config", "-c", help="YAML parameters (`terracube config` prints them all); options win over it."
)
_EDGE = typer.Option(
    None, "--edge", "-e", help=_help("Cube edge E [m].", "collapse", "edge"), show_default=False
)
_SIGMA = typer.Option(
    None,
    "--sigma",
    "-s",
    help=_help("σ [cubes]: gap that makes an overhang.", "collapse", "sigma"),
    show_default=False,
)
_CUBE_HEIGHT = typer.Option(
    None,
    "--robot-height",
    help="Robot height [m]: sets σ = ceil(height / E) unless --sigma is given.",
    show_default=False,
)
_ROLL = typer.Option(
    None, "--roll", help=_help("Sensor roll [deg], for leveling.", "frame", "roll_deg"), show_default=False
)
_PITCH = typer.Option(
    None, "--pitch", help=_help("Sensor pitch [deg], for leveling.", "frame", "pitch_deg"), show_default=False
)
_CROP = typer.Option(
    None,
    "--crop",
    help=_help("Crop box XMIN YMIN ZMIN XMAX YMAX ZMAX [m], leveled frame.", "frame", "crop"),
    show_default=False,
)
_FORMAT = typer.Option(
    "ply",
    "--format",
    "-f",
    help="Classified cloud format: ply, pcd, las, laz (overhang as LAS class 64), bin (KITTI + .label), "
    "npz, npy, txt or xyz.",
)
_PNG = typer.Option(True, "--png/--no-png", help="Also write pictures.")
_GEOTIFF = typer.Option(
    False, "--geotiff/--no-geotiff", help="Also write a GeoTIFF of the main layer (rasterio)."
)
_RESOLUTION = typer.Option(
    None,
    "--resolution",
    "-r",
    help=_help("Cell edge of the map [m].", "elevation", "resolution"),
    show_default=False,
)
_ORIGIN = typer.Option(
    None,
    "--origin",
    help=_help("Corner X Y [m] of the map with the smallest x and y; needs --size.", "elevation", "origin"),
    show_default=False,
)
_SIZE = typer.Option(
    None,
    "--size",
    help=_help("Cells NX NY of the map; needs --origin (else the points' extent).", "elevation", "size"),
    show_default=False,
)
_SENSOR_HEIGHT = typer.Option(
    None,
    "--sensor-height",
    help=_help("Sensor height above the ground [m]: the ground is z = -height.", "terrain", "sensor_height"),
    show_default=False,
)
_NUM_THREADS = typer.Option(
    None,
    "--num-threads",
    "-j",
    help="Threads of the C++ passes (collapse, map, classes): 1 the calling thread, 0 one per processor; "
    "the results are the same. [default: 1]",
    show_default=False,
)
_REFERENCE = typer.Option(
    None,
    "--reference",
    help=_help(
        "Ground reference: sensor_height or local_ground (lowest point nearby).", "terrain", "reference"
    ),
    show_default=False,
)


def _terrain_options(**values) -> dict[str, Any]:
    reference = values.get("reference")
    if reference is not None and reference not in ("sensor_height", "local_ground"):
        raise _fail(f"--reference must be one of sensor_height, local_ground, got {reference!r}")
    return values


# ------------------------------------------------------------------------------------------ commands


@app.command()
def collapse(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = _CONFIG,
    edge: float | None = _EDGE,
    sigma: int | None = _SIGMA,
    robot_height: float | None = _CUBE_HEIGHT,
    roll: float | None = _ROLL,
    pitch: float | None = _PITCH,
    crop: _Crop | None = _CROP,
    output_format: str = _FORMAT,
    png: bool = _PNG,
    num_threads: int | None = _NUM_THREADS,
) -> None:
    """Remove overhangs (canopy, ceilings, bridge decks) from one scan with collapsible cubes.

    Writes NAME_classified.FORMAT (per-point overhang label) and NAME_overhangs.png.
    """
    if output_format not in CLOUD_FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(CLOUD_FORMATS)}")
    cfg = _config(
        config,
        frame=_frame_options(roll, pitch, crop),
        collapse={
            "edge": edge,
            "sigma": _sigma_option(sigma, robot_height, edge, config),
            "num_threads": num_threads,
        },
    )
    _run_and_print("collapse", input_path, output_dir, cfg, output_format=output_format, png=png)


@app.command()
def demo(
    output_dir: Path = typer.Option(Path("terracube_demo"), "--output-dir", "-o", help="Where to write."),
    edge: float = typer.Option(0.5, "--edge", "-e", help="Cube edge E [m]."),
    sigma: int | None = typer.Option(
        None, "--sigma", "-s", help="σ in cubes; default ceil(robot height / E)."
    ),
    robot_height: float = typer.Option(1.5, "--robot-height", help="Robot height in metres, for σ."),
) -> None:
    """Run overhang removal on the bundled Ouster sample scan and write the cloud and a picture.

    The sample's road is near z = 0; the crop drops the few multipath returns below z = -1 m, which
    would otherwise become their column's ground and lift the real ground out as "overhang".
    """
    from .io import load_sample_scan

    sigma = _sigma_option(sigma, robot_height, edge, None)
    cfg = _config(
        None,
        frame={"crop": [[-100.0, -100.0, -1.0], [100.0, 100.0, 40.0]]},
        collapse={"edge": edge, "sigma": sigma},
    )
    with _exit_on_bad_input("ouster128_sample"):
        report = run_stage("collapse", load_sample_scan(), "ouster128_sample", output_dir, cfg)
    for line in report.lines:
        typer.echo(line)


@app.command()
def dem(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = _CONFIG,
    resolution: float | None = _RESOLUTION,
    edge: float | None = _EDGE,
    sigma: int | None = _SIGMA,
    robot_height: float | None = _CUBE_HEIGHT,
    roll: float | None = _ROLL,
    pitch: float | None = _PITCH,
    crop: _Crop | None = _CROP,
    origin: tuple[float, float] | None = _ORIGIN,
    size: tuple[int, int] | None = _SIZE,
    png: bool = _PNG,
    geotiff: bool = _GEOTIFF,
    num_threads: int | None = _NUM_THREADS,
) -> None:
    """Build the DEM of one scan with and without overhangs (collapsible cubes); write the map and pictures.

    Writes NAME_dem.npz (the DEM without overhangs, with clearance and step layers), the pictures
    NAME_dem_comparison.png, NAME_clearance.png and NAME_step.png, and with --geotiff NAME_dem_max.tif.
    """
    cfg = _config(
        config,
        frame=_frame_options(roll, pitch, crop),
        collapse={
            "edge": edge,
            "sigma": _sigma_option(sigma, robot_height, edge, config),
            "num_threads": num_threads,
        },
        elevation={"resolution": resolution, **_extent_options(origin, size), "num_threads": num_threads},
    )
    _run_and_print("dem", input_path, output_dir, cfg, png=png, geotiff=geotiff)


@app.command()
def classify(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = _CONFIG,
    resolution: float | None = _RESOLUTION,
    sensor_height: float | None = _SENSOR_HEIGHT,
    reference: str | None = _REFERENCE,
    ground_radius: int | None = typer.Option(
        None,
        "--ground-radius",
        help=_help(
            "Window half-size [cells] for --reference local_ground.", "terrain", "local_ground_radius"
        ),
        show_default=False,
    ),
    ground_height: float | None = typer.Option(
        None,
        "--ground-height",
        help=_help("Cells lower than this above the ground [m] are low.", "terrain", "ground_height"),
        show_default=False,
    ),
    std_dev: float | None = typer.Option(
        None,
        "--std-dev",
        help=_help("A std-dev of elevations below this [m] is a small spread.", "terrain", "std_dev"),
        show_default=False,
    ),
    robot_height: float | None = typer.Option(
        None,
        "--robot-height",
        help=_help("Cells higher than this above the ground [m] are high.", "terrain", "robot_height"),
        show_default=False,
    ),
    roll: float | None = _ROLL,
    pitch: float | None = _PITCH,
    crop: _Crop | None = _CROP,
    origin: tuple[float, float] | None = _ORIGIN,
    size: tuple[int, int] | None = _SIZE,
    remove_overhangs: bool = typer.Option(
        False,
        "--remove-overhangs/--keep-overhangs",
        help="Classify the DEM without overhangs instead of the raw map (the paper classifies raw maps).",
    ),
    edge: float | None = _EDGE,
    sigma: int | None = _SIGMA,
    cloud_format: str = _FORMAT,
    cloud: bool = typer.Option(
        True, "--cloud/--no-cloud", help="Write the cloud with each point's cell class."
    ),
    png: bool = _PNG,
    geotiff: bool = _GEOTIFF,
    num_threads: int | None = _NUM_THREADS,
) -> None:
    """Classify the cells of one scan's elevation map: ground, obstacle, overhanging, vertical, edge.

    Writes NAME_classes.npz (the map with class, relative_height and ground layers), NAME_classes.png,
    the cloud NAME_classes.FORMAT with each point's cell class (LAS: ground 2, others 65-68, the
    class itself in a 'label' field) and with --geotiff NAME_classes.tif.
    """
    if cloud_format not in CLOUD_FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(CLOUD_FORMATS)}")
    cfg = _config(
        config,
        frame=_frame_options(roll, pitch, crop),
        collapse={"edge": edge, "sigma": sigma, "num_threads": num_threads},
        elevation={"resolution": resolution, **_extent_options(origin, size), "num_threads": num_threads},
        terrain=_terrain_options(
            ground_height=ground_height,
            std_dev=std_dev,
            robot_height=robot_height,
            reference=reference,
            sensor_height=sensor_height,
            local_ground_radius=ground_radius,
            num_threads=num_threads,
        ),
    )
    _run_and_print(
        "classify",
        input_path,
        output_dir,
        cfg,
        remove_overhangs=remove_overhangs,
        cloud_format=cloud_format if cloud else None,
        png=png,
        geotiff=geotiff,
    )


@app.command()
def fem(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = _CONFIG,
    resolution: float | None = _RESOLUTION,
    rules: tuple[int, int] | None = typer.Option(
        None,
        "--rules",
        help="Membership functions NX NY along x and y [config fuzzy.rules_x, rules_y: 19 10].",
        show_default=False,
    ),
    epochs: int | None = typer.Option(
        None, "--epochs", help=_help("Hybrid-learning epochs.", "fuzzy", "epochs"), show_default=False
    ),
    membership: str | None = typer.Option(
        None, "--membership", help=_help("triangular or gaussian.", "fuzzy", "membership"), show_default=False
    ),
    remove_overhangs: bool = typer.Option(
        True,
        "--remove-overhangs/--keep-overhangs",
        help="Fit the points collapsible cubes keep (the paper) or every point.",
    ),
    edge: float | None = _EDGE,
    sigma: int | None = _SIGMA,
    roll: float | None = _ROLL,
    pitch: float | None = _PITCH,
    crop: _Crop | None = _CROP,
    origin: tuple[float, float] | None = _ORIGIN,
    size: tuple[int, int] | None = _SIZE,
    png: bool = _PNG,
    geotiff: bool = _GEOTIFF,
) -> None:
    """Fit the fuzzy elevation map (ANFIS) of one scan; write it as map layers and pictures.

    Writes NAME_fem.npz (the DEM with fem and fem_confidence layers), NAME_fem.png,
    NAME_fem_confidence.png and with --geotiff NAME_fem.tif.
    """
    rules_x, rules_y = rules if rules is not None else (None, None)
    cfg = _config(
        config,
        frame=_frame_options(roll, pitch, crop),
        collapse={"edge": edge, "sigma": sigma},
        elevation={"resolution": resolution, **_extent_options(origin, size)},
        fuzzy={"rules_x": rules_x, "rules_y": rules_y, "epochs": epochs, "membership": membership},
    )
    _run_and_print(
        "fem", input_path, output_dir, cfg, remove_overhangs=remove_overhangs, png=png, geotiff=geotiff
    )


# ------------------------------------------------------------------------------------------ register


def _pose_xy_yaw(x: float, y: float, yaw_deg: float) -> np.ndarray:
    yaw = math.radians(yaw_deg)
    transform = np.eye(4)
    transform[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    transform[:2, 3] = (x, y)
    return transform


def parse_initial(text: str | None) -> np.ndarray:
    """A 4x4 guess from ``--initial``: a text file of 4 rows of 4 numbers (or 3 x 4, KITTI style), a
    JSON file with a ``transform`` entry, or ``x,y,yaw`` [m, m, deg]. ValueError naming the problem."""
    if text is None:
        return np.eye(4)
    path = Path(text)
    if path.is_file():
        try:
            if path.suffix.lower() == ".json":
                matrix = np.asarray(json.loads(path.read_text())["transform"], dtype=np.float64)
            else:
                matrix = np.loadtxt(path, ndmin=2)
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{path}: not a 4x4 transform ({type(error).__name__}: {error})") from error
        if matrix.size in (12, 16):
            matrix = matrix.reshape(-1, 4)
        if matrix.shape == (3, 4):
            matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"{path}: expected a finite 4x4 (or 3x4) transform, got shape {matrix.shape}")
        return matrix
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(
            f"--initial {text!r} is neither a file nor x,y,yaw (metres, metres, degrees), e.g. 1.5,0,10"
        )
    return _pose_xy_yaw(*values)


def _class_counts(result) -> dict[str, int]:
    from . import TerrainClass

    counts = list(result.correspondences_per_class)
    return {c.name.lower(): int(counts[int(c)]) for c in TerrainClass}


def _register_record(method: str, source: Path, target: Path, result) -> dict[str, Any]:
    transform = np.asarray(result.transform)
    yaw = math.degrees(math.atan2(transform[1, 0], transform[0, 0]))
    record: dict[str, Any] = {
        "source": str(source),
        "target": str(target),
        "method": method,
        "transform": transform.tolist(),
        "yaw_deg": yaw,
        "converged": bool(result.converged),
        "iterations": int(result.iterations),
    }
    if method == "pcl":
        record["reason"] = "converged" if result.converged else "not converged"
        record["fitness"] = float(result.fitness)
    else:
        record.update(
            reason=result.reason.name,
            rmse=float(result.rmse),
            num_correspondences=int(result.num_correspondences),
            correspondences_per_class=_class_counts(result),
        )
        if np.any(np.asarray(result.constraint_matrix)):
            from .registration import constrained_directions

            record["constraints"] = [
                {"along": along, "held": held} for along, held, _ in constrained_directions(result)
            ]
    return record


@app.command()
def register(
    source: Path = typer.Argument(
        ..., help="Scan to move (any readable point-cloud format).", show_default=False
    ),
    target: Path = typer.Argument(..., help="Scan to move it onto.", show_default=False),
    config: Path | None = _CONFIG,
    method: str = typer.Option(
        "classes",
        "--method",
        "-m",
        help="classes: class-weighted ICP (the paper); all-cells: every cell, unit weight; "
        "pcl: PCL's point-to-point ICP on the same cell points.",
    ),
    initial: str | None = typer.Option(
        None,
        "--initial",
        "-i",
        help="Guess of the source -> target transform: a text file of a 4x4 (or 3x4) matrix, a JSON "
        "file with 'transform', or x,y,yaw [m, m, deg]. Default: identity.",
        show_default=False,
    ),
    output: Path | None = typer.Option(
        None,
        "--output",
        help="Write the result: .json (everything) or .txt (the 4x4 matrix).",
        show_default=False,
    ),
    resolution: float | None = _RESOLUTION,
    sensor_height: float | None = _SENSOR_HEIGHT,
    reference: str | None = _REFERENCE,
    max_iterations: int | None = typer.Option(
        None,
        "--max-iterations",
        help=_help("ICP updates at most.", "registration", "max_iterations"),
        show_default=False,
    ),
    remove_overhangs: bool = typer.Option(
        False, "--remove-overhangs/--keep-overhangs", help="Map each scan without its overhangs first."
    ),
    structure_radius: float | None = typer.Option(
        None,
        "--structure-radius",
        help=_help(
            "Also report what the scene constrains (classes and all-cells): the weakest motions, "
            "from neighbourhoods of this radius [m], e.g. three cells.",
            "registration",
            "structure_radius",
        ),
        show_default=False,
    ),
    roll: float | None = _ROLL,
    pitch: float | None = _PITCH,
    crop: _Crop | None = _CROP,
) -> None:
    """Register two scans: each becomes a classified elevation map, then ICP moves source onto target.

    Prints the transform, whether it converged and why, iterations, RMSE and the correspondences per
    terrain class; with --structure-radius also the two motions the scene holds least firmly.
    """
    from tqdm import tqdm

    from .registration import pcl_icp, points_of_map, register_maps, register_maps_all_cells

    if method not in REGISTRATION_METHODS:
        raise _fail(f"--method must be one of {', '.join(REGISTRATION_METHODS)}, got {method!r}")
    if output is not None and output.suffix.lower() not in (".json", ".txt"):
        raise _fail(f"--output {output}: use a .json or .txt file")
    cfg = _config(
        config,
        frame=_frame_options(roll, pitch, crop),
        elevation={"resolution": resolution},
        terrain=_terrain_options(sensor_height=sensor_height, reference=reference),
        registration={"max_iterations": max_iterations, "structure_radius": structure_radius},
        pcl_icp={"max_iterations": max_iterations},
    )
    with _exit_on_bad_input():
        guess = parse_initial(initial)
    maps = []
    for path in tqdm([source, target], desc="mapping scans", unit="scan", leave=False):
        points = _read_points(path)
        with _exit_on_bad_input(path.stem):
            maps.append(_classified_map(points, path.stem, cfg, remove_overhangs)[0])
    with _exit_on_bad_input("registration"):
        start = time.perf_counter()
        if method == "classes":
            result = register_maps(maps[0], maps[1], guess, cfg.registration)
        elif method == "all-cells":
            result = register_maps_all_cells(maps[0], maps[1], guess, cfg.registration)
        else:
            try:
                result = pcl_icp(points_of_map(maps[0])[0], points_of_map(maps[1])[0], guess, cfg.pcl_icp)
            except RuntimeError as error:
                raise _fail(str(error)) from error
        elapsed_ms = _elapsed_ms(start)
    record = _register_record(method, source, target, result)
    typer.echo(f"{source.stem} -> {target.stem} ({method}, {elapsed_ms:.1f} ms):")
    typer.echo(f"  converged: {'yes' if record['converged'] else 'no'} ({record['reason']})")
    typer.echo(f"  iterations: {record['iterations']}")
    if method == "pcl":
        typer.echo(f"  fitness: {record['fitness']:.6f} m^2 (mean squared pair distance)")
    else:
        typer.echo(f"  RMSE: {record['rmse']:.4f} m over {record['num_correspondences']:,} correspondences")
        per_class = ", ".join(
            f"{k.replace('_', ' ')} {v:,}" for k, v in record["correspondences_per_class"].items()
        )
        typer.echo(f"  correspondences per class: {per_class}")
        if "constraints" in record:
            weakest = ", ".join(f"{c['along']} {c['held']:.3f}" for c in record["constraints"][:2])
            typer.echo(f"  least held (share of the pairs' weight holding it, 1 = all): {weakest}")
    t = np.asarray(record["transform"])
    typer.echo(
        f"  translation: x {t[0, 3]:+.4f} m, y {t[1, 3]:+.4f} m, z {t[2, 3]:+.4f} m; "
        f"yaw {record['yaw_deg']:+.3f} deg"
    )
    typer.echo("  transform:")
    for row in t:
        typer.echo("    " + " ".join(f"{v:+.8f}" for v in row))
    if output is not None:
        output.parent.mkdir(parents=True, exist_ok=True)
        if output.suffix.lower() == ".json":
            output.write_text(json.dumps(record, indent=2) + "\n")
        else:
            header = (
                f"terracube register {source} -> {target} ({method}): converged {record['converged']} "
                f"({record['reason']}), {record['iterations']} iterations"
            )
            np.savetxt(output, t, fmt="%.12g", header=header)
        typer.echo(f"  written: {output}")


# ------------------------------------------------------------------------------------------ view


def _is_map_file(path: Path) -> bool:
    if path.suffix.lower() != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as archive:
            return "layer_names" in archive.files
    except Exception:  # not a zip: the point-cloud reader names the problem
        return False


@app.command()
def view(
    input_path: Path = typer.Argument(
        ...,
        help="A scan (any readable format) or a map .npz written by dem, classify or fem.",
        show_default=False,
    ),
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = _CONFIG,
    layers: list[str] | None = typer.Option(
        None,
        "--layer",
        "-l",
        help="Map layers to draw (repeatable); default every layer.",
        show_default=False,
    ),
    three_d: bool = typer.Option(
        False, "--3d", help='Open an interactive 3D view (rerun; pip install "terracube[viewer]").'
    ),
    save: Path | None = typer.Option(
        None,
        "--save",
        help="With --3d: write a rerun recording (.rrd) instead of opening a viewer.",
        show_default=False,
    ),
    resolution: float | None = _RESOLUTION,
    sensor_height: float | None = _SENSOR_HEIGHT,
    png: bool = _PNG,
) -> None:
    """Draw the pictures of a scan or of a saved map; --3d shows it in rerun.

    A scan gives NAME_overhangs.png, NAME_max.png and NAME_classes.png; a map .npz one NAME_LAYER.png
    per layer. --3d --save FILE.rrd writes a rerun recording instead of opening the viewer.
    """
    from . import ElevationMap, TerrainClass, classify_terrain, collapse_overhangs
    from .viz import plot_layer, plot_overhangs, plot_terrain_classes

    if save is not None and not three_d:
        raise _fail("--save writes a 3D recording: give --3d too")
    cfg = _config(config, elevation={"resolution": resolution}, terrain={"sensor_height": sensor_height})
    name = input_path.stem
    written: list[Path] = []
    if _is_map_file(input_path):
        with _exit_on_bad_input():
            elevation_map = ElevationMap.load(input_path)
        chosen = layers or elevation_map.layers
        unknown = [layer for layer in chosen if layer not in elevation_map]
        if unknown:
            raise _fail(
                f"{input_path}: no layer {', '.join(unknown)}; layers: {', '.join(elevation_map.layers)}"
            )
        if png:
            for layer in chosen:
                with _exit_on_bad_input(name):
                    written.append(plot_layer(elevation_map, layer, output_dir / f"{name}_{layer}.png"))
        points, labels, cloud_map = None, None, elevation_map
    else:
        if layers:
            raise _fail("--layer picks layers of a map .npz; a scan is drawn as overhangs, max and classes")
        points = _read_points(input_path)
        with _exit_on_bad_input(name):
            result = collapse_overhangs(points, params=_collapse_params(cfg))
            from . import build_elevation_map

            elevation_map = build_elevation_map(points, params=_elevation_params(cfg))
            _require_data(name, elevation_map)
            classes = classify_terrain(elevation_map, cfg.terrain)
            if png:
                leveled, _ = _leveled(points, cfg)
                written.append(plot_overhangs(leveled, result.overhang, output_dir / f"{name}_overhangs.png"))
                written.append(plot_layer(elevation_map, "max", output_dir / f"{name}_max.png"))
                written.append(
                    plot_terrain_classes(elevation_map, classes, output_dir / f"{name}_classes.png")
                )
        labels, cloud_map = result.overhang, None
        known = int(np.count_nonzero(classes != TerrainClass.UNKNOWN))
        typer.echo(
            f"{name}: {len(points):,} points, {result.num_overhang:,} overhang; map "
            f"{elevation_map.geometry.size[0]} x {elevation_map.geometry.size[1]} cells, {known:,} classified"
        )
    for path in written:
        typer.echo(f"  picture: {path}")
    if three_d:
        from .viewer import show_cloud, show_map

        try:
            if cloud_map is not None:
                recording = show_map(cloud_map, name=name, save=save)
            else:
                recording = show_cloud(points, overhang=labels, name=name, save=save)
        except ImportError as error:
            raise _fail(str(error)) from error
        typer.echo(f"  3D recording: {recording}" if save is not None else "  3D view: opened in rerun")


# ------------------------------------------------------------------------------------------ config, batch


# ------------------------------------------------------------------------------------------ map


def _mapper_params(cfg):
    """MapperParams of the config: the mapper section plus the terrain and registration sections. An
    untouched terrain section (the paper's sensor-height reference) gives way to the mapper's terrain
    defaults (local ground, 1 m window) for maps chained over slopes."""
    import dataclasses

    from .config import default_config
    from .mapping import MapperParams

    terrain = cfg.terrain
    if terrain == default_config().terrain:  # untouched: the mapper's own terrain defaults
        terrain = MapperParams().terrain
    return dataclasses.replace(cfg.mapper, terrain=terrain, registration=cfg.registration)


@app.command("map")
def map_command(
    scans: Path = typer.Argument(
        ...,
        help="Directory of scans (any readable format, sorted by name) or one glob pattern.",
        show_default=False,
    ),
    poses: Path = typer.Option(
        ..., "--poses", "-p", help="Odometry poses: KITTI (12 numbers a line) or TUM.", show_default=False
    ),
    pose_format: str = typer.Option(
        "auto", "--pose-format", help="kitti, tum or auto (by the column count)."
    ),
    calib: Path | None = typer.Option(
        None,
        "--calib",
        help="KITTI calib.txt: turns camera poses into Velodyne poses (default: calib.txt beside --poses "
        "for KITTI poses, if present).",
        show_default=False,
    ),
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = _CONFIG,
    keyframe_distance: float | None = typer.Option(
        None,
        "--keyframe-distance",
        help=_help("Travel between local maps [m].", "mapper", "keyframe_distance"),
        show_default=False,
    ),
    resolution: float | None = typer.Option(
        None, "--resolution", help=_help("Cell size [m].", "mapper", "resolution"), show_default=False
    ),
    loop_closing: bool | None = typer.Option(
        None,
        "--loop-closing/--no-loop-closing",
        help="Close loops with Ceres [config mapper.loop_closing].",
        show_default=False,
    ),
    registration: bool | None = typer.Option(
        None,
        "--registration/--odometry-only",
        help="Scan-match every step, or chain by odometry alone [config mapper.use_registration].",
        show_default=False,
    ),
    limit: int | None = typer.Option(None, "--limit", help="Use the first N scans only.", show_default=False),
    ground_truth: Path | None = typer.Option(
        None,
        "--ground-truth",
        help="Poses to evaluate against (same format and calibration as --poses): prints ATE.",
        show_default=False,
    ),
    png: bool = _PNG,
) -> None:
    """Build a global elevation map from a sequence of scans and odometry poses.

    Every ~3 m a local classified map is registered to the previous one (class-weighted ICP, odometry
    as the guess) and fused; revisits are registered and the pose graph optimised with Ceres. Writes
    global_map.npz (layers count, min, max, mean, std_dev, discontinuity, class), global_max.png,
    global_classes.png, and the keyframe trajectory as trajectory_kitti.txt and trajectory_tum.txt
    (Velodyne frame when a calibration was used).
    """
    from tqdm import tqdm

    from .mapping import (
        Mapper,
        detect_pose_format,
        match_scans_to_poses,
        read_kitti_calibration,
        read_pose_file,
    )
    from .poses import write_kitti_poses, write_tum_poses

    cfg = _config(
        config,
        mapper={
            "keyframe_distance": keyframe_distance,
            "resolution": resolution,
            "loop_closing": loop_closing,
            "use_registration": registration,
        },
    )
    if scans.is_dir():
        files = sorted(p for p in scans.iterdir() if p.is_file() and not p.name.startswith("."))
    else:
        from .batch import expand_inputs

        try:
            files = expand_inputs([str(scans)])
        except (ValueError, FileNotFoundError) as error:
            raise _fail(str(error)) from error
    from .io import _READ_SUFFIXES

    files = [f for f in files if f.suffix.lower() in _READ_SUFFIXES]
    if limit is not None:
        files = files[: max(limit, 0)]
    if not files:
        raise _fail(f"{scans}: no scans found")
    if not poses.is_file():
        raise _fail(f"{poses}: no such pose file")
    with _exit_on_bad_input():
        if pose_format == "auto":
            pose_format = detect_pose_format(poses)
        if calib is None and pose_format == "kitti" and (poses.parent / "calib.txt").is_file():
            calib = poses.parent / "calib.txt"
        calibration = read_kitti_calibration(calib) if calib is not None else None
        stamps, odometry = read_pose_file(poses, pose_format, calibration)
        indices = match_scans_to_poses(files, len(odometry))
        mapper = Mapper(_mapper_params(cfg))
    if calibration is not None:
        typer.echo(f"calibration: {calib} (camera poses -> Velodyne)")
    start = time.perf_counter()
    for path, index in tqdm(list(zip(files, indices, strict=True)), unit="scan", desc="mapping"):
        points = _read_points(path)
        with _exit_on_bad_input(str(path)):
            mapper.add_scan(points, odometry[index])
    if mapper.pending_loops:
        mapper.optimize()
    seconds = time.perf_counter() - start
    with _exit_on_bad_input("global map"):
        dem = mapper.global_map()
    output_dir.mkdir(parents=True, exist_ok=True)
    written = [dem.save(output_dir / "global_map.npz")]
    keyframes = mapper.keyframe_poses()
    key_scans = [indices[k] for k in mapper.keyframe_scan_indices()]
    write_kitti_poses(output_dir / "trajectory_kitti.txt", keyframes)
    write_tum_poses(output_dir / "trajectory_tum.txt", stamps[key_scans], keyframes)
    written += [output_dir / "trajectory_kitti.txt", output_dir / "trajectory_tum.txt"]
    if png and dem.geometry.num_cells > 0:
        from .viz import plot_layer, plot_terrain_classes

        written.append(plot_layer(dem, "max", output_dir / "global_max.png", title="highest elevation [m]"))
        classes = np.nan_to_num(dem["class"], nan=0).astype(np.uint8)
        written.append(
            plot_terrain_classes(dem, classes, output_dir / "global_classes.png", title="terrain classes")
        )
    t = mapper.timings
    typer.echo(
        f"{len(files)} scans, {len(mapper)} keyframes, {len(mapper.loop_closures)} loop closures "
        f"in {seconds:.2f} s ({len(files) / seconds:.1f} scans/s incl. reading)"
    )
    typer.echo(
        f"time [ms]: map building {t.map_building_ms:.0f}, classification {t.classification_ms:.0f}, "
        f"registration {t.registration_ms:.0f}, fusion {t.fusion_ms:.0f}, "
        f"loop closing {t.loop_closing_ms:.0f}"
    )
    g = dem.geometry
    typer.echo(
        f"global map: {int(g.size[0])} x {int(g.size[1])} cells at {g.resolution} m, "
        f"{int(np.isfinite(dem['max']).sum())} with data, "
        f"{mapper.global_memory_bytes / 2**20:.1f} MiB of tiles"
    )
    if ground_truth is not None:
        from .evaluation import absolute_trajectory_error

        with _exit_on_bad_input(str(ground_truth)):
            _, truth = read_pose_file(ground_truth, pose_format, calibration)
            key_truth = truth[key_scans]
            estimate = absolute_trajectory_error(keyframes, key_truth, "first_pose").translation
            odom = absolute_trajectory_error(mapper.keyframe_odometry(), key_truth, "first_pose").translation
        typer.echo(
            f"ATE (first pose aligned): mapper RMSE {estimate.rmse:.3f} m, odometry RMSE {odom.rmse:.3f} m"
        )
    for path in written:
        typer.echo(f"written: {path}")


@app.command("config")
def config_command(
    output: Path | None = typer.Option(
        None, "--output", "-o", help="Write the YAML to this file instead of printing it.", show_default=False
    ),
    config: Path | None = typer.Option(
        None,
        "--config",
        "-c",
        help="Print this file merged over the defaults (checks it, too).",
        show_default=False,
    ),
) -> None:
    """Print every stage's parameters as commented YAML (the defaults, or a file merged over them).

    Edit a copy and pass it to any stage with --config FILE.
    """
    from .config import dump_config

    text = dump_config(_config(config))
    if output is None:
        typer.echo(text, nl=False)
    else:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(text)
        typer.echo(f"written: {output}")


@app.command()
def batch(
    stage: str = typer.Argument(
        ..., help=f"Stage to run on every scan: {', '.join(BATCH_STAGES)}.", show_default=False
    ),
    inputs: list[str] = typer.Argument(
        ..., help="Scans, folders of scans or glob patterns.", show_default=False
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for every file's outputs.", show_default=False),
    scheduler: str | None = typer.Option(
        None,
        "--scheduler",
        help="Address of a running Dask scheduler (e.g. tcp://HOST:8786); default: a local cluster.",
        show_default=False,
    ),
    workers: int | None = typer.Option(
        None,
        "--workers",
        "-w",
        help="Worker processes of the local cluster (default: one per core).",
        show_default=False,
    ),
    threads: bool = typer.Option(
        False, "--threads/--processes", help="Local cluster workers as threads of this process, or processes."
    ),
    config: Path | None = _CONFIG,
    output_format: str = _FORMAT,
    png: bool = _PNG,
    geotiff: bool = _GEOTIFF,
) -> None:
    """Run one stage over many scans in parallel with Dask; print a summary table.

    A file that fails is reported with its error and the others go on; the exit code is 1 when any
    file failed. Outputs are the stage's own (NAME_... files in --out).
    """
    from .batch import expand_inputs, format_summary, run_batch

    if stage not in BATCH_STAGES:
        raise _fail(f"unknown stage {stage!r}: batch runs {', '.join(BATCH_STAGES)}")
    if output_format not in CLOUD_FORMATS:
        raise _fail(f"--format must be one of {', '.join(CLOUD_FORMATS)}")
    if workers is not None and workers < 1:
        raise _fail(f"--workers must be at least 1, got {workers}")
    cfg = _config(config)
    with _exit_on_bad_input():
        files = expand_inputs(inputs)
    options: dict[str, Any] = {"png": png}
    if stage == "collapse":
        options["output_format"] = output_format
    elif stage == "classify":
        options["cloud_format"] = output_format
    if stage in ("dem", "classify", "fem"):
        options["geotiff"] = geotiff
    where = (
        scheduler or f"a local cluster of {workers or 'one per core'} {'threads' if threads else 'processes'}"
    )
    typer.echo(f"{stage}: {len(files)} scans on {where}", err=True)
    records = run_batch(
        stage,
        files,
        out,
        config=cfg,
        options=options,
        scheduler=scheduler,
        workers=workers,
        processes=not threads,
        progress=True,
    )
    typer.echo(format_summary(records))
    failed = [r for r in records if r.status != "ok"]
    if failed:
        typer.secho(f"{len(failed)} of {len(records)} files failed", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)


@app.command()
def version() -> None:
    """Print the terracube version."""
    from . import __version__

    typer.echo(__version__)


from .cli_bag import register as _register_bag_commands  # noqa: E402 - after every command

_register_bag_commands(app)  # bag-info, and ROS bags as the input of map, collapse, dem, classify, fem


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
