"""The ``terracube`` command line."""

from __future__ import annotations

import math
import time
from pathlib import Path

import typer

app = typer.Typer(
    help="Navigable 2.5D elevation maps from ground-robot 3D LiDAR scans.",
    no_args_is_help=True,
    add_completion=False,
)

_FORMATS = ("ply", "npz", "txt")


def _run_collapse(
    points,
    name: str,
    output_dir: Path,
    edge: float,
    sigma: int | None,
    robot_height: float,
    roll_deg: float,
    pitch_deg: float,
    crop: tuple[float, float, float, float, float, float] | None,
    output_format: str,
    picture: bool,
) -> None:
    from . import collapse_overhangs, leveling_transform, sigma_from_robot_height
    from .io import write_classified

    if output_format not in _FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(_FORMATS)}")
    if sigma is None:
        sigma = sigma_from_robot_height(robot_height, edge)
    transform = leveling_transform(math.radians(roll_deg), math.radians(pitch_deg))
    crop_box = None if crop is None else (crop[:3], crop[3:])
    start = time.perf_counter()
    try:
        result = collapse_overhangs(points, edge, sigma, transform=transform, crop=crop_box)
    except (ValueError, TypeError) as error:
        typer.secho(f"error: {name}: {error}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from error
    elapsed_ms = 1e3 * (time.perf_counter() - start)
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
    cloud_path = write_classified(output_dir / f"{name}_classified.{output_format}", points, result.overhang)
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


_EDGE = typer.Option(0.5, "--edge", "-e", help="Cube edge E, metres.")
_SIGMA = typer.Option(None, "--sigma", "-s", help="σ in cubes; default ceil(robot height / E).")
_HEIGHT = typer.Option(1.0, "--robot-height", help="Robot height in metres, gives σ when --sigma is not set.")
_ROLL = typer.Option(0.0, "--roll", help="Sensor roll in degrees, for leveling.")
_PITCH = typer.Option(0.0, "--pitch", help="Sensor pitch in degrees, for leveling.")
_CROP = typer.Option(None, "--crop", help="Crop box XMIN YMIN ZMIN XMAX YMAX ZMAX in metres, leveled frame.")
_FORMAT = typer.Option("ply", "--format", "-f", help="Classified cloud format: ply, npz or txt.")
_PNG = typer.Option(True, "--png/--no-png", help="Also write a picture.")


@app.command()
def collapse(
    input_path: Path = typer.Argument(..., help="Point cloud: .bin (KITTI), .npy, .npz, .txt/.xyz/.csv."),
    output_dir: Path = typer.Option(Path("terracube_out"), "--output-dir", "-o", help="Where to write."),
    edge: float = _EDGE,
    sigma: int | None = _SIGMA,
    robot_height: float = _HEIGHT,
    roll: float = _ROLL,
    pitch: float = _PITCH,
    crop: tuple[float, float, float, float, float, float] | None = _CROP,
    output_format: str = _FORMAT,
    png: bool = _PNG,
) -> None:
    """Remove overhangs (canopy, ceilings, bridge decks) from one scan with collapsible cubes."""
    from .io import read_points

    try:
        points = read_points(input_path)
    except (ValueError, FileNotFoundError) as error:
        typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from error
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


@app.command()
def version() -> None:
    """Print the terracube version."""
    from . import __version__

    typer.echo(__version__)


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
