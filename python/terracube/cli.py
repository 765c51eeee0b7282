"""The ``terracube`` command line."""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np
import typer

app = typer.Typer(
    help="Navigable 2.5D elevation maps from ground-robot 3D LiDAR scans.",
    no_args_is_help=True,
    add_completion=False,
)

_FORMATS = ("ply", "pcd", "las", "laz", "npz", "npy", "txt", "xyz")

_Crop = tuple[float, float, float, float, float, float]


def _fail(message: str) -> typer.Exit:
    """Print a red error message; the caller raises the returned Exit (code 2)."""
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    return typer.Exit(2)


@contextmanager
def _exit_on_bad_input(name: str) -> Iterator[None]:
    """Turn a ValueError or TypeError from the library into ``error: NAME: ...`` and exit code 2."""
    try:
        yield
    except (ValueError, TypeError) as error:
        raise _fail(f"{name}: {error}") from error


def _read_points(input_path: Path):
    """The points of ``input_path``; a missing or unreadable file exits with code 2."""
    from .io import read_points

    try:
        return read_points(input_path)
    except (ValueError, FileNotFoundError) as error:
        raise _fail(str(error)) from error


def _leveling(roll_deg: float, pitch_deg: float, crop: _Crop | None):
    """The leveling transform of --roll and --pitch, and the --crop box as (min, max) or None."""
    from . import leveling_transform

    transform = leveling_transform(math.radians(roll_deg), math.radians(pitch_deg))
    crop_box = None if crop is None else (crop[:3], crop[3:])
    return transform, crop_box


def _sigma(sigma: int | None, robot_height: float, edge: float) -> int:
    """--sigma, or by default ceil(robot height / edge) cubes."""
    from . import sigma_from_robot_height

    return sigma_from_robot_height(robot_height, edge) if sigma is None else sigma


def _elapsed_ms(start: float) -> float:
    return 1e3 * (time.perf_counter() - start)


def _run_collapse(
    points,
    name: str,
    output_dir: Path,
    edge: float,
    sigma: int | None,
    robot_height: float,
    roll_deg: float,
    pitch_deg: float,
    crop: _Crop | None,
    output_format: str,
    picture: bool,
) -> None:
    from . import collapse_overhangs
    from .io import write_classified

    if output_format not in _FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(_FORMATS)}")
    with _exit_on_bad_input(name):
        sigma = _sigma(sigma, robot_height, edge)
        transform, crop_box = _leveling(roll_deg, pitch_deg, crop)
        start = time.perf_counter()
        result = collapse_overhangs(points, edge, sigma, transform=transform, crop=crop_box)
    elapsed_ms = _elapsed_ms(start)
    grid = result.grid
    typer.echo(
        f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
        f"(edge {edge} m, sigma {sigma} cubes; {len(result.occupied_cubes):,} occupied cubes, "
        f"{len(result.removed_cubes):,} collapsed; grid {grid.ixmax}x{grid.iymax}x{grid.izmax}; "
        f"{elapsed_ms:.1f} ms)"
    )
    if result.num_cropped:
        typer.echo(f"  {result.num_cropped:,} points outside the crop box were left out")
    output_dir.mkdir(parents=True, exist_ok=True)
    with _exit_on_bad_input(name):
        cloud_path = write_classified(
            output_dir / f"{name}_classified.{output_format}", points, result.overhang
        )
    typer.echo(f"  classified cloud: {cloud_path}")
    if picture:
        from .viz import plot_overhangs

        leveled = points @ transform[:3, :3].T + transform[:3, 3]
        png = plot_overhangs(
            leveled,
            result.overhang,
            output_dir / f"{name}_overhangs.png",
            title=f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
            f"(collapsible cubes, E = {edge} m, sigma = {sigma})",
        )
        typer.echo(f"  picture: {png}")


_INPUT = typer.Argument(
    ..., help="Point cloud: .pcd, .ply, .las/.laz, .bin (KITTI), .npy, .npz, .txt/.xyz/.csv."
)
_OUTPUT_DIR = typer.Option(Path("terracube_out"), "--output-dir", "-o", help="Where to write.")
_EDGE = typer.Option(0.5, "--edge", "-e", help="Cube edge E, metres.")
_SIGMA = typer.Option(None, "--sigma", "-s", help="σ in cubes; default ceil(robot height / E).")
_HEIGHT = typer.Option(1.0, "--robot-height", help="Robot height in metres, gives σ when --sigma is not set.")
_ROLL = typer.Option(0.0, "--roll", help="Sensor roll in degrees, for leveling.")
_PITCH = typer.Option(0.0, "--pitch", help="Sensor pitch in degrees, for leveling.")
_CROP = typer.Option(None, "--crop", help="Crop box XMIN YMIN ZMIN XMAX YMAX ZMAX in metres, leveled frame.")
_FORMAT = typer.Option(
    "ply",
    "--format",
    "-f",
    help="Classified cloud format: ply, pcd, las, laz (overhang as LAS class 64), npz, npy, txt or xyz.",
)
_PNG = typer.Option(True, "--png/--no-png", help="Also write a picture.")


@app.command()
def collapse(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    edge: float = _EDGE,
    sigma: int | None = _SIGMA,
    robot_height: float = _HEIGHT,
    roll: float = _ROLL,
    pitch: float = _PITCH,
    crop: _Crop | None = _CROP,
    output_format: str = _FORMAT,
    png: bool = _PNG,
) -> None:
    """Remove overhangs (canopy, ceilings, bridge decks) from one scan with collapsible cubes."""
    points = _read_points(input_path)
    _run_collapse(
        points, input_path.stem, output_dir, edge, sigma, robot_height, roll, pitch, crop, output_format, png
    )


@app.command()
def demo(
    output_dir: Path = typer.Option(Path("terracube_demo"), "--output-dir", "-o", help="Where to write."),
    edge: float = _EDGE,
    sigma: int | None = _SIGMA,
    robot_height: float = typer.Option(1.5, "--robot-height", help="Robot height in metres, for σ."),
) -> None:
    """Run overhang removal on the bundled Ouster sample scan and write the cloud and a picture.

    The sample's road is near z = 0; the crop drops the few multipath returns below z = -1 m, which
    would otherwise become their column's ground and lift the real ground out as "overhang".
    """
    from .io import load_sample_scan

    crop = (-100.0, -100.0, -1.0, 100.0, 100.0, 40.0)
    _run_collapse(
        load_sample_scan(),
        "ouster128_sample",
        output_dir,
        edge,
        sigma,
        robot_height,
        0.0,
        0.0,
        crop,
        "ply",
        True,
    )


_RESOLUTION = typer.Option(0.1, "--resolution", "-r", help="Cell edge of the map, metres.")
_ORIGIN = typer.Option(
    None,
    "--origin",
    help="Corner X Y of the map with the smallest x and y, metres, leveled frame; needs --size.",
)
_SIZE = typer.Option(
    None, "--size", help="Cells NX NY of the map along x and y; needs --origin. Default: the points' extent."
)


class _Frame(NamedTuple):
    """Where a map is built: leveling transform, crop box and fixed extent (origin, size or None)."""

    transform: np.ndarray
    crop_box: tuple | None
    origin: tuple[float, float] | None
    size: tuple[int, int] | None


def _frame(
    roll_deg: float,
    pitch_deg: float,
    crop: _Crop | None,
    origin: tuple[float, float] | None,
    size: tuple[int, int] | None,
) -> _Frame:
    """The map frame from --roll, --pitch, --crop, --origin and --size (exit 2 unless both or
    neither of --origin and --size are given)."""
    if (origin is None) != (size is None):
        raise _fail("give both --origin and --size for a fixed map extent, or neither")
    return _Frame(*_leveling(roll_deg, pitch_deg, crop), origin, size)


def _raw_map(points, resolution: float, frame: _Frame):
    """The elevation map of all points in ``frame``."""
    from . import build_elevation_map

    return build_elevation_map(
        points,
        resolution,
        transform=frame.transform,
        crop=frame.crop_box,
        origin=frame.origin,
        size=frame.size,
    )


def _map_without_overhangs(points, resolution: float, edge: float, sigma: int, frame: _Frame, origin, size):
    """The DEM without overhangs (collapsible cubes in ``frame``) on the extent ``origin``, ``size``."""
    from . import CollapseParams, ElevationParams, dem_without_overhangs

    return dem_without_overhangs(
        points,
        collapse=CollapseParams(edge, sigma, transform=frame.transform, crop=frame.crop_box),
        elevation=ElevationParams(resolution, origin=origin, size=size),
    )


def _require_data(name: str, elevation_map) -> None:
    if not np.any(elevation_map["count"] > 0):
        raise _fail(f"{name}: no point falls inside the map; check --crop, --origin and --size")


def _save_map(elevation_map, output_dir: Path, file_name: str) -> None:
    """Create ``output_dir``, save the map there as ``file_name`` and print its path."""
    output_dir.mkdir(parents=True, exist_ok=True)
    typer.echo(f"  map: {elevation_map.save(output_dir / file_name)}")


@app.command()
def dem(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    resolution: float = _RESOLUTION,
    edge: float = _EDGE,
    sigma: int | None = _SIGMA,
    robot_height: float = _HEIGHT,
    roll: float = _ROLL,
    pitch: float = _PITCH,
    crop: _Crop | None = _CROP,
    origin: tuple[float, float] | None = _ORIGIN,
    size: tuple[int, int] | None = _SIZE,
) -> None:
    """Build the DEM of one scan with and without overhangs (collapsible cubes); write the map and pictures.

    Writes NAME_dem.npz (the DEM without overhangs, with clearance and step layers) and the pictures
    NAME_dem_comparison.png, NAME_clearance.png and NAME_step.png. Both DEMs share one geometry.
    """
    from .viz import plot_dem_comparison, plot_layer

    points = _read_points(input_path)
    name = input_path.stem
    frame = _frame(roll, pitch, crop, origin, size)
    with _exit_on_bad_input(name):
        sigma = _sigma(sigma, robot_height, edge)
        start = time.perf_counter()
        raw = _raw_map(points, resolution, frame)
        raw_ms = _elapsed_ms(start)
        _require_data(name, raw)
        g = raw.geometry
        start = time.perf_counter()
        clean, result = _map_without_overhangs(points, resolution, edge, sigma, frame, g.origin, g.size)
        clean_ms = _elapsed_ms(start)

    before, after = raw["max"], clean["max"]
    lower = int(np.count_nonzero(np.isfinite(before) & np.isfinite(after) & (after < before)))
    emptied = int(np.count_nonzero(np.isfinite(before) & np.isnan(after)))
    typer.echo(
        f"{name}: DEM {g.size[0]} x {g.size[1]} cells at {g.resolution:g} m, "
        f"{int(np.count_nonzero(np.isfinite(before))):,} with data; {result.num_overhang:,} of "
        f"{result.num_points:,} points are overhang (edge {edge} m, sigma {sigma}); {lower:,} cells lower, "
        f"{emptied:,} emptied; raw DEM {raw_ms:.1f} ms, DEM without overhangs {clean_ms:.1f} ms"
    )
    _save_map(clean, output_dir, f"{name}_dem.npz")
    comparison = plot_dem_comparison(
        raw,
        clean,
        output_dir / f"{name}_dem_comparison.png",
        title=f"{name}: highest elevation before and after overhang removal (E = {edge} m, σ = {sigma})",
    )
    clearance = plot_layer(
        clean,
        "clearance",
        output_dir / f"{name}_clearance.png",
        title=f"{name}: clearance from the retained points to the lowest overhang above",
        cmap="RdYlGn",
        vmin=0.0,
        vmax=max(2.0 * robot_height, sigma * edge + edge),
    )
    step = plot_layer(
        clean,
        "step",
        output_dir / f"{name}_step.png",
        title=f"{name}: largest step of the DEM without overhangs to a neighbour cell",
        cmap="plasma",
        vmin=0.0,
    )
    typer.echo(f"  pictures: {comparison}, {clearance}, {step}")


_REFERENCES = ("sensor_height", "local_ground")


@app.command()
def classify(
    input_path: Path = _INPUT,
    output_dir: Path = _OUTPUT_DIR,
    resolution: float = _RESOLUTION,
    sensor_height: float = typer.Option(
        0.0, "--sensor-height", help="Sensor height above the ground in metres: the ground is z = -height."
    ),
    reference: str = typer.Option(
        "sensor_height",
        "--reference",
        help="Ground reference: sensor_height (the plane z = -sensor height) or local_ground "
        "(the lowest point nearby).",
    ),
    ground_radius: int = typer.Option(
        10, "--ground-radius", help="Window half-size in cells for --reference local_ground."
    ),
    ground_height: float = typer.Option(
        0.2, "--ground-height", help="Cells lower than this above the ground, in metres, are low."
    ),
    std_dev: float = typer.Option(
        0.1, "--std-dev", help="A std-dev of elevations below this, in metres, is a small spread."
    ),
    robot_height: float = typer.Option(
        0.7, "--robot-height", help="Cells this high above the ground, in metres, or more are high."
    ),
    roll: float = _ROLL,
    pitch: float = _PITCH,
    crop: _Crop | None = _CROP,
    origin: tuple[float, float] | None = _ORIGIN,
    size: tuple[int, int] | None = _SIZE,
    remove_overhangs: bool = typer.Option(
        False,
        "--remove-overhangs/--keep-overhangs",
        help="Classify the DEM without overhangs instead of the raw map (the paper classifies raw maps).",
    ),
    edge: float = typer.Option(0.5, "--edge", "-e", help="Cube edge E in metres, for --remove-overhangs."),
    sigma: int | None = typer.Option(
        None, "--sigma", "-s", help="σ in cubes for --remove-overhangs; default ceil(robot height / E)."
    ),
) -> None:
    """Classify the cells of one scan's elevation map: ground, obstacle, overhanging, vertical, edge.

    Writes NAME_classes.npz (the map with class, relative_height and ground layers) and
    NAME_classes.png.
    """
    from . import TerrainClass, TerrainParams, classify_terrain
    from .viz import plot_terrain_classes

    if reference not in _REFERENCES:
        raise _fail(f"--reference must be one of {', '.join(_REFERENCES)}, got {reference!r}")
    points = _read_points(input_path)
    name = input_path.stem
    frame = _frame(roll, pitch, crop, origin, size)
    terrain = TerrainParams(
        ground_height=ground_height,
        std_dev=std_dev,
        robot_height=robot_height,
        reference=reference,
        sensor_height=sensor_height,
        local_ground_radius=ground_radius,
    )
    with _exit_on_bad_input(name):
        terrain.to_core()  # checks the thresholds before the map is built
        start = time.perf_counter()
        if remove_overhangs:
            sigma = _sigma(sigma, robot_height, edge)
            elevation_map, result = _map_without_overhangs(
                points, resolution, edge, sigma, frame, frame.origin, frame.size
            )
            source = (
                f"DEM without overhangs (edge {edge} m, sigma {sigma}; "
                f"{result.num_overhang:,} overhang points)"
            )
        else:
            elevation_map = _raw_map(points, resolution, frame)
            source = "raw map"
        map_ms = _elapsed_ms(start)
        _require_data(name, elevation_map)
        start = time.perf_counter()
        classes = classify_terrain(elevation_map, terrain)
        classify_ms = _elapsed_ms(start)

    g = elevation_map.geometry
    counts = np.bincount(classes.ravel(), minlength=len(TerrainClass))
    known = int(classes.size - counts[0])
    where = (
        f"sensor height {sensor_height:g} m"
        if reference == "sensor_height"
        else f"local ground, {ground_radius} cells"
    )
    typer.echo(
        f"{name}: {g.size[0]} x {g.size[1]} cells at {g.resolution:g} m, {known:,} with data; {source}; "
        f"reference {where}; map {map_ms:.1f} ms, classification {classify_ms:.1f} ms"
    )
    for terrain_class in TerrainClass:
        count = int(counts[int(terrain_class)])
        share = f" ({count / known:.1%} of cells with data)" if terrain_class and known else ""
        typer.echo(f"  {terrain_class.name.lower().replace('_', ' '):<20} {count:>10,}{share}")
    _save_map(elevation_map, output_dir, f"{name}_classes.npz")
    picture = plot_terrain_classes(
        elevation_map,
        classes,
        output_dir / f"{name}_classes.png",
        title=f"{name}: terrain classes ({source.split(' (')[0]}, {where})",
    )
    typer.echo(f"  picture: {picture}")


@app.command()
def version() -> None:
    """Print the terracube version."""
    from . import __version__

    typer.echo(__version__)


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
