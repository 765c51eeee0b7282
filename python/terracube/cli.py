"""The ``terracube`` command line: a thin typer layer over :mod:`terracube.pipeline`.

Every shared option is defined once in :data:`OPTIONS` (with the config keys it sets) and named by
the commands that take it (:data:`STAGE_OPTIONS`); :func:`with_options` adds them to a command and
:func:`command_config` turns their values into a :class:`terracube.config.Config`. ``terracube
batch`` takes the options of every stage. Parameters come from ``--config FILE`` (see ``terracube
config``) with the options given on the command line over it. Bad input or parameters exit with
code 2 and a message naming the problem.

To give several commands a new option, add it to :data:`OPTIONS` and name it in
:data:`STAGE_OPTIONS`; a new kind of input belongs in :func:`terracube.pipeline.read_scan`, which
every command reads its scans through.
"""

from __future__ import annotations

import copy
import functools
import inspect
import json
import math
import os
import re
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import typer

from .pipeline import (
    CLOUD_FORMATS,
    ESTIMATED_GROUND_WINDOW_M,
    REGISTRATION_METHODS,
    SCAN_SUFFIXES,
    STAGE_OUTPUT_OPTIONS,
    STAGES,
    read_scan,
)

app = typer.Typer(
    help="Navigable 2.5D elevation maps from ground-robot 3D LiDAR scans.\n\n"
    "Stages: collapse (overhang removal), dem (elevation map), classify (terrain classes), "
    "fem (fuzzy elevation map), register (ICP between two scans), map (global elevation map and "
    "trajectory from a scan sequence, with odometry or LiDAR-only), stream (a robot-centric local "
    "map fused scan after scan), view (pictures, 3D); batch runs a stage over many scans in "
    "parallel; config prints every parameter as YAML; bag-info lists a ROS bag's topics.",
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,  # help texts say "[m]" and "[config collapse.edge ...]": no markup
)

TERRAIN_REFERENCES = ("sensor_height", "local_ground")


def _print_version(value: bool) -> None:
    if value:
        from . import __version__

        typer.echo(f"terracube {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(
        False,
        "--version",
        help="Print the terracube version and exit.",
        callback=_print_version,
        is_eager=True,
    ),
) -> None:
    """Navigable 2.5D elevation maps from ground-robot 3D LiDAR scans."""


# ------------------------------------------------------------------------------------------ errors


#: The progress bars shown now (:func:`progress_bar`): an error closes them so that its line starts
#: on a line of its own instead of being glued onto a bar's.
_PROGRESS_BARS: weakref.WeakSet = weakref.WeakSet()


def progress_bar(iterable, what: str, unit: str = "scan", **kwargs):
    """A tqdm bar over ``iterable`` that :func:`_fail` closes before printing its error."""
    from tqdm import tqdm

    bar = tqdm(iterable, unit=unit, desc=what, **kwargs)
    _PROGRESS_BARS.add(bar)
    return bar


def _fail(message: str) -> typer.Exit:
    """Print a red error message (closing the progress bars first); the caller raises the returned
    Exit (code 2)."""
    for bar in list(_PROGRESS_BARS):
        bar.close()
    _PROGRESS_BARS.clear()
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    return typer.Exit(2)


def _short_path(name: Any, limit: int = 80) -> str:
    text = str(name)
    return text if len(text) <= limit else f"{text[: limit // 2]}...{text[-limit // 2 :]}"


def _os_error_message(error: OSError) -> str:
    """``PATH: what went wrong`` for a failed file operation (a long path shortened)."""
    if error.strerror is None:  # raised with a message of its own
        return str(error)
    what = error.strerror.rstrip(".")
    what = what[:1].lower() + what[1:]
    if error.filename is None:
        return what
    where = _short_path(error.filename)
    return f"{where}: {what}" + (f" ({_short_path(error.filename2)})" if error.filename2 else "")


@contextmanager
def _exit_on_bad_input(name: str = "") -> Iterator[None]:
    """Turn a ValueError, TypeError, KeyError, a missing extra (ImportError) or a failed file
    operation (OSError: not a folder, no space left, name too long ...) into ``error: NAME: ...``
    and exit code 2. NAME is left out when the message already starts with it."""
    try:
        yield
    except (ValueError, TypeError, KeyError, ImportError, OSError) as error:
        if isinstance(error, KeyError) and error.args:
            text = str(error.args[0])
        elif isinstance(error, OSError) and not isinstance(error, (ValueError, ImportError)):
            text = _os_error_message(error)
        else:
            text = str(error)
        prefixed = not name or text.startswith(f"{name}:") or text.startswith(f"{name} ")
        raise _fail(text if prefixed else f"{name}: {text}") from error


def _writable_folder(folder: Path, option: str = "--output-dir") -> Path:
    """Create ``folder`` if needed; exit 2 before any work when it cannot hold the outputs."""
    if folder.exists() and not folder.is_dir():
        raise _fail(f"{option} {_short_path(folder)}: exists and is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise _fail(f"{option} {_os_error_message(error)}") from error
    if not os.access(folder, os.W_OK | os.X_OK):
        raise _fail(f"{option} {_short_path(folder)}: the folder is not writable")
    return folder


def _scan_files(scans: Path, limit: int | None) -> tuple[list[Path], int]:
    """The scan files of a folder (sorted) or a glob, at most ``limit``, and how many there are in
    all (read_odometry matches scans to poses by their count); exits when there are none.

    A folder holding files of several scan suffixes (KITTI's ``*.bin`` beside its ``calib.txt``)
    gives the files of the most common one, with a note naming what was left out; a glob pattern
    gives every scan it matches."""
    from .pipeline import expand_inputs

    if scans.is_dir():
        files = sorted(p for p in scans.iterdir() if p.is_file() and not p.name.startswith("."))
        every = _scans_of_one_suffix(scans, files)
    else:
        with _exit_on_bad_input():
            files = expand_inputs([str(scans)])
        every = [f for f in files if f.suffix.lower() in SCAN_SUFFIXES]
    files = every[:limit]
    if not files:
        raise _fail(f"{scans}: no scans found")
    return files, len(every)


def _scans_of_one_suffix(folder: Path, files: list[Path]) -> list[Path]:
    """The files of ``folder`` with its most common scan suffix (the first of SCAN_SUFFIXES on a
    tie); prints a note when other files are left out."""
    counts: dict[str, int] = {}
    for path in files:
        suffix = path.suffix.lower()
        if suffix in SCAN_SUFFIXES:
            counts[suffix] = counts.get(suffix, 0) + 1
    if not counts:
        return []
    chosen = max(counts, key=lambda suffix: (counts[suffix], -SCAN_SUFFIXES.index(suffix)))
    scans = [p for p in files if p.suffix.lower() == chosen]
    others = [p for p in files if p.suffix.lower() != chosen]
    if others:
        suffixes = sorted({p.suffix.lower() or "no suffix" for p in others})
        typer.echo(
            f"{_short_path(folder)}: {len(scans)} {chosen} scans; {len(others)} other "
            f"file{'s' if len(others) != 1 else ''} left out ({', '.join(suffixes)})"
        )
    return scans


def _existing_file(path: Path | None, option: str) -> None:
    """Exit 2 before any work when an input file given by ``option`` is missing."""
    if path is not None and not path.is_file():
        raise _fail(f"{option} {_short_path(path)}: no such file")


def _echo_odometry(odometry) -> None:
    """Print the calibration and timestamps a sequence's odometry used, and its warnings."""
    for text, warning in odometry.notes():
        if warning:
            typer.secho(text, fg=typer.colors.YELLOW, err=True)
        else:
            typer.echo(text)


#: How far from the Velodyne the KITTI car's own returns (its bonnet and mirrors) reach [m].
KITTI_CAR_REACH_M = 2.8


def _warn_of_the_kitti_car(files: list[Path], min_range: float, configured: bool) -> None:
    """A warning when KITTI ``.bin`` scans are mapped with the default range limits: the car's own
    returns then map as steps along its path (``--preset kitti`` leaves them out)."""
    if configured or min_range >= KITTI_CAR_REACH_M or any(f.suffix.lower() != ".bin" for f in files):
        return
    typer.secho(
        f"warning: KITTI .bin scans with min_range {min_range:g} m: the car's own returns (up to "
        f"{KITTI_CAR_REACH_M:g} m from the sensor) map as steps along its path; --preset kitti (or "
        "--min-range 3) leaves them out",
        fg=typer.colors.YELLOW,
        err=True,
    )


def _read_scan(path: Path) -> np.ndarray:
    """The points of one scan; a missing or unreadable file exits with code 2."""
    with _exit_on_bad_input():
        return read_scan(path)


# ------------------------------------------------------------------------------------------ options


def _preset_names() -> list[str]:
    from .config import preset_names

    return preset_names()


def _default(section: str, key: str) -> Any:
    from .config import default_config

    return getattr(default_config()[section], key)


def _help(text: str, section: str, key: str) -> str:
    """Option help ending with the configuration key it overrides and that key's default."""
    default = _default(section, key)
    return f"{text} [config {section}.{key}, default {'none' if default is None else default}]"


@dataclass(frozen=True)
class Option:
    """One command-line option: its Python type, typer declaration and the config keys it sets."""

    type: Any
    info: Any  # typer.models.OptionInfo
    sets: tuple[tuple[str, str], ...] = ()


def _option(type_, *names: str, help: str, default: Any = None, sets=(), **kwargs) -> Option:
    kwargs.setdefault("show_default", default is not None)
    return Option(type_, typer.Option(default, *names, help=help, **kwargs), tuple(sets))


_Crop = tuple[float, float, float, float, float, float]

#: Every option shared by several commands, by parameter name.
OPTIONS: dict[str, Option] = {
    "config": _option(
        Path | None,
        "--config",
        "-c",
        help="YAML parameters (`terracube config` prints them all); options win over it.",
    ),
    "preset": _option(
        str | None,
        "--preset",
        help="Sensor preset under --config and the options: "
        + ", ".join(_preset_names())
        + " (also kitti, hdl64, tls, als; `terracube config --preset NAME` prints it).",
    ),
    # frame
    "min_range": _option(
        float | None,
        "--min-range",
        help=_help("Leave out points nearer the sensor [m] (no-returns at 0).", "frame", "min_range"),
        sets=[("frame", "min_range")],
    ),
    "max_range": _option(
        float | None,
        "--max-range",
        help=_help("Leave out points farther from the sensor [m].", "frame", "max_range"),
        sets=[("frame", "max_range")],
    ),
    "roll": _option(
        float | None,
        "--roll",
        help=_help("Sensor roll [deg], for leveling.", "frame", "roll_deg"),
        sets=[("frame", "roll_deg")],
    ),
    "pitch": _option(
        float | None,
        "--pitch",
        help=_help("Sensor pitch [deg], for leveling.", "frame", "pitch_deg"),
        sets=[("frame", "pitch_deg")],
    ),
    "crop": _option(
        _Crop | None,
        "--crop",
        help=_help("Crop box XMIN YMIN ZMIN XMAX YMAX ZMAX [m], leveled frame.", "frame", "crop"),
        metavar="XMIN YMIN ZMIN XMAX YMAX ZMAX",
    ),
    # collapse
    "edge": _option(
        float | None,
        "--edge",
        "-e",
        help=_help("Cube edge E [m].", "collapse", "edge"),
        sets=[("collapse", "edge")],
    ),
    "sigma": _option(
        int | None,
        "--sigma",
        "-s",
        help=_help("σ [cubes]: gap that makes an overhang.", "collapse", "sigma"),
        sets=[("collapse", "sigma")],
    ),
    "robot_height": _option(
        float | None,
        "--robot-height",
        help="Robot height [m]: sets σ = ceil(height / E) unless --sigma is given.",
    ),
    "collapse_method": _option(
        str | None,
        "--method",
        help=_help(
            "Overhang rule: paper ([CBC] Algorithm 1) or shadow_aware (also over unseen ground).",
            "collapse",
            "method",
        ),
        sets=[("collapse", "method")],
    ),
    "sensor_origin": _option(
        tuple[float, float, float] | None,
        "--sensor-origin",
        help=_help(
            "Sensor position X Y Z [m] in the leveled frame, for --method shadow_aware "
            "(none: the scan's own origin), e.g. --sensor-origin 0 0 1.8.",
            "collapse",
            "sensor_origin",
        ),
        sets=[("collapse", "sensor_origin")],
        metavar="X Y Z",
    ),
    # elevation map
    "resolution": _option(
        float | None,
        "--resolution",
        "-r",
        help=_help("Cell edge of the map [m].", "elevation", "resolution"),
        sets=[("elevation", "resolution")],
    ),
    "origin": _option(
        tuple[float, float] | None,
        "--origin",
        help=_help(
            "Corner X Y [m] of the map with the smallest x and y, e.g. --origin -20 -20; needs --size.",
            "elevation",
            "origin",
        ),
        metavar="X Y",
    ),
    "size": _option(
        tuple[int, int] | None,
        "--size",
        help=_help(
            "Cells NX NY of the map, e.g. --size 400 400; needs --origin (else the 1st-99th "
            "percentile window of the points).",
            "elevation",
            "size",
        ),
        metavar="NX NY",
    ),
    "num_threads": _option(
        int | None,
        "--num-threads",
        "-j",
        help="Threads of the C++ passes (collapse, map, classes): 1 the calling thread, 0 one per processor; "
        "the results are the same. [default: 1]",
        sets=[("collapse", "num_threads"), ("elevation", "num_threads"), ("terrain", "num_threads")],
    ),
    # terrain classes
    "sensor_height": _option(
        float | None,
        "--sensor-height",
        help=_help(
            "Sensor height above the ground [m]: the ground is z = -height. Left at 0 with the reference "
            "at sensor_height (the defaults), the ground is estimated instead: the lowest point within "
            f"{ESTIMATED_GROUND_WINDOW_M:g} m of each cell (local_ground).",
            "terrain",
            "sensor_height",
        ),
        sets=[("terrain", "sensor_height")],
    ),
    "reference": _option(
        str | None,
        "--reference",
        help=_help(
            "Ground reference: sensor_height or local_ground (lowest point nearby); see --sensor-height "
            "for what the defaults do.",
            "terrain",
            "reference",
        ),
        sets=[("terrain", "reference")],
    ),
    "ground_radius": _option(
        int | None,
        "--ground-radius",
        help=_help(
            "Window half-size [cells] for --reference local_ground.", "terrain", "local_ground_radius"
        ),
        sets=[("terrain", "local_ground_radius")],
    ),
    "high_height": _option(
        float | None,
        "--high-height",
        help=_help("Cells higher than this above the ground [m] are high.", "terrain", "robot_height"),
        sets=[("terrain", "robot_height")],
    ),
    "ground_height": _option(
        float | None,
        "--ground-height",
        help=_help("Cells lower than this above the ground [m] are low.", "terrain", "ground_height"),
        sets=[("terrain", "ground_height")],
    ),
    "std_dev": _option(
        float | None,
        "--std-dev",
        help=_help("A std-dev of elevations below this [m] is a small spread.", "terrain", "std_dev"),
        sets=[("terrain", "std_dev")],
    ),
    # fuzzy elevation map
    "rules": _option(
        tuple[int, int] | None,
        "--rules",
        help="Membership functions NX NY along x and y [config fuzzy.rules_x, rules_y: 19 10].",
        metavar="NX NY",
    ),
    "epochs": _option(
        int | None,
        "--epochs",
        help=_help("Hybrid-learning epochs.", "fuzzy", "epochs"),
        sets=[("fuzzy", "epochs")],
    ),
    "membership": _option(
        str | None,
        "--membership",
        help=_help("triangular or gaussian.", "fuzzy", "membership"),
        sets=[("fuzzy", "membership")],
    ),
    # registration
    "max_iterations": _option(
        int | None,
        "--max-iterations",
        help=_help("ICP updates at most.", "registration", "max_iterations"),
        sets=[("registration", "max_iterations"), ("pcl_icp", "max_iterations")],
    ),
    "structure_radius": _option(
        float | None,
        "--structure-radius",
        help=_help(
            "Also report what the scene constrains (classes and all-cells): the weakest motions, "
            "from neighbourhoods of this radius [m], e.g. three cells.",
            "registration",
            "structure_radius",
        ),
        sets=[("registration", "structure_radius")],
    ),
    # outputs
    "remove_overhangs": _option(
        bool,
        "--remove-overhangs/--keep-overhangs",
        default=False,
        help="Map each scan without its overhangs first.",
    ),
    "output_format": _option(
        str,
        "--format",
        "-f",
        default="ply",
        help="Classified cloud format: ply, pcd, las, laz (overhang as LAS class 64), bin (KITTI + .label), "
        "npz, npy, txt or xyz.",
    ),
    "cloud": _option(
        bool, "--cloud/--no-cloud", default=True, help="Write the cloud with each point's cell class."
    ),
    "las_classification": _option(
        bool,
        "--las-classification/--las-extra-dimension",
        default=False,
        help="LAS/LAZ cloud: terracube's labels in 'classification' too, or only in an extra dimension "
        "(a LAS input's own classification kept).",
    ),
    "png": _option(bool, "--png/--no-png", default=True, help="Also write pictures."),
    "geotiff": _option(
        bool,
        "--geotiff/--no-geotiff",
        default=False,
        help="Also write a GeoTIFF of the main layer (rasterio).",
    ),
}

_FRAME = ("min_range", "max_range", "roll", "pitch", "crop")
_EXTENT = ("resolution", "origin", "size")
_OVERHANGS = ("edge", "sigma", "robot_height", "collapse_method", "sensor_origin")
_TERRAIN = ("sensor_height", "reference", "ground_radius", "ground_height", "high_height", "std_dev")

#: The options of each command that takes shared ones, in --help order.
STAGE_OPTIONS: dict[str, tuple[str, ...]] = {
    "collapse": (
        "config",
        "preset",
        *_OVERHANGS,
        *_FRAME,
        "num_threads",
        "output_format",
        "las_classification",
        "png",
    ),
    "dem": ("config", "preset", *_EXTENT, *_OVERHANGS, *_FRAME, "num_threads", "png", "geotiff"),
    "classify": (
        "config",
        "preset",
        *_EXTENT,
        *_TERRAIN,
        *_OVERHANGS,
        *_FRAME,
        "num_threads",
        "remove_overhangs",
        "output_format",
        "las_classification",
        "cloud",
        "png",
        "geotiff",
    ),
    "fem": (
        "config",
        "preset",
        *_EXTENT,
        "rules",
        "epochs",
        "membership",
        *_OVERHANGS,
        *_FRAME,
        "num_threads",
        "remove_overhangs",
        "png",
        "geotiff",
    ),  # fmt: skip
    "register": (
        "config",
        "preset",
        "resolution",
        "sensor_height",
        "reference",
        "max_iterations",
        "structure_radius",
        "remove_overhangs",
        *_FRAME,
    ),  # fmt: skip
    "view": ("config", "preset", "min_range", "max_range", "resolution", "sensor_height", "png"),
}
STAGE_OPTIONS["batch"] = tuple(dict.fromkeys(name for stage in STAGES for name in STAGE_OPTIONS[stage]))

#: Where a command's option differs from the shared one: (command, option) -> typer.Option fields.
_OPTION_CHANGES: dict[tuple[str, str], dict[str, Any]] = {
    ("batch", "png"): {
        "default": False,
        "help": "Also write each scan's pictures (they take most of the time: seconds per scan).",
    },
    ("classify", "remove_overhangs"): {
        "help": "Classify the DEM without overhangs instead of the raw map (the paper classifies raw maps)."
    },
    ("fem", "remove_overhangs"): {
        "default": True,
        "help": "Fit the points collapsible cubes keep (the paper) or every point.",
    },
    ("batch", "remove_overhangs"): {
        "default": None,
        "help": "classify and fem: map without overhangs first. "
        "[default: classify keeps them, fem removes them]",
    },
}


def _parameter(command: str, name: str) -> inspect.Parameter:
    option = OPTIONS[name]
    info = option.info
    changes = _OPTION_CHANGES.get((command, name))
    if changes:
        info = copy.copy(info)
        for field, value in changes.items():
            setattr(info, field, value)
        if "default" in changes and changes["default"] is None:
            return inspect.Parameter(
                name, inspect.Parameter.KEYWORD_ONLY, default=info, annotation=bool | None
            )
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=info, annotation=option.type)


def with_options(command: str):
    """Decorate a command to take the shared options of :data:`STAGE_OPTIONS` ``[command]``; it
    receives their values as one dict ``options``."""
    names = STAGE_OPTIONS[command]

    def decorate(func):
        signature = inspect.signature(func)
        own = [p for p in signature.parameters.values() if p.name != "options"]
        parameters = own + [_parameter(command, name) for name in names]

        @functools.wraps(func)
        def wrapper(**kwargs):
            options = {name: kwargs.pop(name) for name in names}
            return func(**kwargs, options=options)

        wrapper.__signature__ = signature.replace(parameters=parameters)
        wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
        del wrapper.__wrapped__  # typer reads the signature above, not the function's own
        return wrapper

    return decorate


def command_config(command: str, options: dict[str, Any]):
    """The configuration of ``--config`` (defaults when None) with the options given on the command
    line (not None) over it; exit 2 naming the problem."""
    from .config import ConfigError, load_config

    changes: dict[str, dict[str, Any]] = {}
    for name, value in options.items():
        for section, key in OPTIONS[name].sets if name in OPTIONS else ():
            changes.setdefault(section, {})[key] = value
    if options.get("crop") is not None:
        changes.setdefault("frame", {})["crop"] = [list(options["crop"][:3]), list(options["crop"][3:])]
    origin, size = options.get("origin"), options.get("size")
    if (origin is None) != (size is None):
        raise _fail("give both --origin and --size for a fixed map extent, or neither")
    if origin is not None:
        changes.setdefault("elevation", {}).update(origin=list(origin), size=list(size))
    if options.get("rules") is not None:
        changes.setdefault("fuzzy", {}).update(rules_x=options["rules"][0], rules_y=options["rules"][1])
    reference = options.get("reference")
    if reference is not None and reference not in TERRAIN_REFERENCES:
        raise _fail(f"--reference must be one of {', '.join(TERRAIN_REFERENCES)}, got {reference!r}")
    try:
        config = load_config(options.get("config"), preset=options.get("preset"))
    except ConfigError as error:
        raise _fail(str(error)) from error
    with _exit_on_bad_input("command line"):
        for section, values in changes.items():
            config = config.replace(section, **values)
        if options.get("robot_height") is not None and options.get("sigma") is None:
            from . import sigma_from_robot_height

            sigma = sigma_from_robot_height(options["robot_height"], config.collapse.edge)
            config = config.replace("collapse", sigma=sigma)
    _check_terrain_heights(config, options)
    return config


def _check_terrain_heights(config, options: dict[str, Any]) -> None:
    """Exit 2 naming --high-height and --ground-height as the user typed them when the high-cell
    threshold lies below the low-cell one (the core's message names its own fields)."""
    high, ground = options.get("high_height"), options.get("ground_height")
    if high is None and ground is None:
        return
    terrain = config["terrain"]
    if not terrain.robot_height < terrain.ground_height:
        return

    def named(option: str, given: float | None, key: str) -> str:
        if given is not None:
            return f"{option} {given:g}"
        return f"{option} {getattr(terrain, key):g} (terrain.{key} of the configuration)"

    raise _fail(
        f"{named('--high-height', high, 'robot_height')} is below "
        f"{named('--ground-height', ground, 'ground_height')}: cells above --high-height are high and "
        "cells below --ground-height low, so --high-height must be at least --ground-height"
    )


def stage_output_options(stage: str, options: dict[str, Any]) -> dict[str, Any]:
    """The output options of :func:`terracube.pipeline.run_stage` for ``stage`` from the command's."""
    output_format = options.get("output_format", "ply")
    if output_format not in CLOUD_FORMATS:
        raise _fail(f"--format must be one of {', '.join(CLOUD_FORMATS)}, got {output_format!r}")
    values = {
        "output_format": output_format,
        "cloud_format": output_format if options.get("cloud", True) else None,
        "png": options.get("png"),
        "geotiff": options.get("geotiff"),
        "remove_overhangs": options.get("remove_overhangs"),
        "las_classification": options.get("las_classification"),
    }
    return {key: values[key] for key in STAGE_OUTPUT_OPTIONS[stage] if values[key] is not None}


# ------------------------------------------------------------------------------------------ stages

_INPUT = typer.Argument(
    ...,
    help="Point cloud: .pcd, .ply, .las/.laz, .bin (KITTI), .npy, .npz, .txt/.xyz/.csv.",
    show_default=False,
)
_OUTPUT_DIR = typer.Option(Path("terracube_out"), "--output-dir", "-o", help="Where to write.")
_POSES = typer.Option(
    None,
    "--poses",
    "-p",
    help="Odometry poses: KITTI (12 numbers a line) or TUM. Scan 000123.bin takes row 123; with TUM, a "
    "scan named by its time (1622812345.123456789.pcd) the pose interpolated at it; other names one pose "
    "each, in order. Needed unless --lidar-only.",
    show_default=False,
)


def _scan_limit(value: int | None) -> int | None:
    """--limit is a count of scans: exit 2 naming it when below 1 (0 would read no scan at all)."""
    if value is not None and value < 1:
        raise _fail(f"--limit {value}: give how many scans to use, at least 1")
    return value


_LIMIT = typer.Option(
    None, "--limit", help="Use the first N scans only.", show_default=False, callback=_scan_limit
)

_STAGE_HELP = {
    "collapse": """Remove overhangs (canopy, ceilings, bridge decks) from one scan with collapsible cubes.

    Writes NAME_classified.FORMAT (per-point overhang label) and NAME_overhangs.png; with --method
    shadow_aware also NAME_reasons.png, each point coloured by why it was kept or removed.
    """,
    "dem": """Build the DEM of one scan with and without overhangs (collapsible cubes); write map, pictures.

    Writes NAME_dem.npz (the DEM without overhangs, with clearance and step layers), the pictures
    NAME_dem_comparison.png, NAME_clearance.png and NAME_step.png (with --method shadow_aware also
    NAME_reasons.png, as collapse writes), and with --geotiff NAME_dem_max.tif.
    """,
    "classify": """Classify the cells of one scan's map: ground, obstacle, overhanging, vertical, edge.

    Writes NAME_classes.npz (the map with class, relative_height and ground layers), NAME_classes.png,
    the cloud NAME_classes.FORMAT with each point's cell class (LAS: ground 2, others 65-68, the
    class itself in a 'label' field) and with --geotiff NAME_classes.tif.
    """,
    "fem": """Fit the fuzzy elevation map (ANFIS) of one scan; write it as map layers and pictures.

    Writes NAME_fem.npz (the DEM with fem and fem_confidence layers), NAME_fem.png,
    NAME_fem_confidence.png and with --geotiff NAME_fem.tif.
    """,
}


def _echo_report(report) -> None:
    for line in report.lines:
        typer.echo(line)


def _add_stage_command(stage: str) -> None:
    @with_options(stage)
    def command(input_path: Path = _INPUT, output_dir: Path = _OUTPUT_DIR, options=None) -> None:
        from .pipeline import read_stage_input, run_stage

        config = command_config(stage, options)
        outputs = stage_output_options(stage, options)
        _writable_folder(output_dir)
        with _exit_on_bad_input():
            points, no_returns = read_stage_input(input_path, config)
        with _exit_on_bad_input(input_path.stem):
            _echo_report(
                run_stage(
                    stage,
                    points,
                    input_path.stem,
                    output_dir,
                    config,
                    source=input_path,
                    no_returns=no_returns,
                    **outputs,
                )
            )

    command.__doc__ = _STAGE_HELP[stage]
    command.__name__ = stage
    app.command(stage)(command)


for _stage in STAGES:
    _add_stage_command(_stage)


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
    from .pipeline import run_stage

    config = command_config(
        "demo",
        {"edge": edge, "sigma": sigma, "robot_height": robot_height, "crop": (-100, -100, -1, 100, 100, 40)},
    )
    _writable_folder(output_dir)
    with _exit_on_bad_input("ouster128_sample"):
        _echo_report(run_stage("collapse", load_sample_scan(), "ouster128_sample", output_dir, config))


# ------------------------------------------------------------------------------------------ register


def _pose_xy_yaw(x: float, y: float, yaw_deg: float) -> np.ndarray:
    yaw = math.radians(yaw_deg)
    transform = np.eye(4)
    transform[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    transform[:2, 3] = (x, y)
    return transform


def parse_initial(text: str | None) -> np.ndarray:
    """A (4, 4) guess from ``--initial``: a text file of 4 rows of 4 numbers (or 3 x 4, KITTI style), a
    JSON file with a ``transform`` entry, or ``x,y,yaw`` [m, m, deg]. ValueError naming the problem.
    A file's rotation rounded to fewer than six digits is replaced by the nearest rotation."""
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
        from .poses import rigid_from_file

        return rigid_from_file(matrix, str(path))
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


def _print_register_record(record: dict[str, Any], elapsed_ms: float, source: Path, target: Path) -> None:
    method = record["method"]
    typer.echo(f"{source.stem} -> {target.stem} ({method}, {elapsed_ms:.1f} ms):")
    typer.echo(f"  converged: {'yes' if record['converged'] else 'no'} ({record['reason']})")
    typer.echo(f"  iterations: {record['iterations']}")
    if "ground_reference" in record:
        typer.echo(f"  ground reference: {record['ground_reference']}")
    left_out = record.get("points_left_out", [0, 0])
    if any(left_out):
        typer.echo(
            f"  range filter: {left_out[0]:,} points of {source.stem} and {left_out[1]:,} of {target.stem} "
            "left out"
        )
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
    typer.echo(f"  verdict: {record['verdict']}")
    t = np.asarray(record["transform"])
    typer.echo(
        f"  translation: x {t[0, 3]:+.4f} m, y {t[1, 3]:+.4f} m, z {t[2, 3]:+.4f} m; "
        f"yaw {record['yaw_deg']:+.3f} deg"
    )
    typer.echo("  transform:")
    for row in t:
        typer.echo("    " + " ".join(f"{v:+.8f}" for v in row))


@app.command()
@with_options("register")
def register(
    source: Path = typer.Argument(
        ..., help="Scan to move (any readable point-cloud format).", show_default=False
    ),
    target: Path = typer.Argument(..., help="Scan to move it onto.", show_default=False),
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
    options=None,
) -> None:
    """Register two scans: each becomes a classified elevation map, then ICP moves source onto target.

    Prints the transform, whether it converged and why, iterations, RMSE and the correspondences per
    terrain class, the two motions the scene holds least firmly (--structure-radius > 0) and the
    verdict; exits with code 1 when the result is not trusted (the reason on stderr).
    """
    from .pipeline import register_scans

    if method not in REGISTRATION_METHODS:
        raise _fail(f"--method must be one of {', '.join(REGISTRATION_METHODS)}, got {method!r}")
    if output is not None and output.suffix.lower() not in (".json", ".txt"):
        raise _fail(f"--output {output}: use a .json or .txt file")
    config = command_config("register", options)
    with _exit_on_bad_input():
        guess = parse_initial(initial)
    points = [_read_scan(source), _read_scan(target)]
    with _exit_on_bad_input("registration"):
        try:
            record, elapsed_ms = register_scans(
                *points,
                config,
                method=method,
                initial=guess,
                remove_overhangs=options["remove_overhangs"],
                names=(str(source), str(target)),
            )
        except RuntimeError as error:  # PCL absent from this build
            raise _fail(str(error)) from error
    _print_register_record(record, elapsed_ms, source, target)
    if output is not None:
        from .io import atomic_path

        with _exit_on_bad_input("--output"), atomic_path(output) as temporary:
            _write_register_record(temporary, output.suffix.lower(), record, source, target, method)
        typer.echo(f"  written: {output}")
    if not record["trusted"]:
        # Issue 38: an answer the verdict does not trust is a failure for scripts (exit code 1).
        why = record["verdict"].removeprefix("not trusted: ")  # the core's verdict starts with it
        typer.secho(f"registration not trusted: {why}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1)


def _write_register_record(output: Path, suffix: str, record: dict, source, target, method) -> None:
    if suffix == ".json":
        output.write_text(json.dumps(record, indent=2) + "\n")
    else:
        header = (
            f"terracube register {source} -> {target} ({method}): converged {record['converged']} "
            f"({record['reason']}), {record['iterations']} iterations"
        )
        np.savetxt(output, np.asarray(record["transform"]), fmt="%.12g", header=header)


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
@with_options("view")
def view(
    input_path: Path = typer.Argument(
        ...,
        help="A scan (any readable format) or a map .npz written by dem, classify or fem.",
        show_default=False,
    ),
    output_dir: Path = _OUTPUT_DIR,
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
    options=None,
) -> None:
    """Draw the pictures of a scan or of a saved map; --3d shows it in rerun.

    A scan gives NAME_overhangs.png, NAME_max.png and NAME_classes.png; a map .npz one NAME_LAYER.png
    per layer. --3d --save FILE.rrd writes a rerun recording instead of opening the viewer.
    """
    from . import ElevationMap, TerrainClass, build_elevation_map, classify_terrain, collapse_overhangs
    from .pipeline import (
        collapse_params,
        elevation_params,
        leveled_points,
        range_note,
        terrain_params,
    )

    if save is not None and not three_d:
        raise _fail("--save writes a 3D recording: give --3d too")
    if three_d:  # before any picture is drawn or file written
        from .viewer import require_viewer

        with _exit_on_bad_input("--3d"):
            require_viewer()
    config = command_config("view", options)
    png = options["png"]
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
            from .viz import plot_layer

            for layer in chosen:
                with _exit_on_bad_input(name):
                    written.append(plot_layer(elevation_map, layer, output_dir / f"{name}_{layer}.png"))
        points, labels, cloud_map = None, None, elevation_map
    else:
        if layers:
            raise _fail("--layer picks layers of a map .npz; a scan is drawn as overhangs, max and classes")
        every_point = _read_scan(input_path)
        keep = config.frame.in_range(every_point)
        points = np.ascontiguousarray(every_point[keep])
        note = range_note(every_point, keep, config.frame)
        with _exit_on_bad_input(name):
            result = collapse_overhangs(points, params=collapse_params(config))
            elevation_map = build_elevation_map(points, params=elevation_params(config, points))
            if not np.any(elevation_map["count"] > 0):
                raise ValueError("no point falls inside the map; check the crop box, origin and size")
            terrain, where = terrain_params(config)
            classes = classify_terrain(elevation_map, terrain)
            if png:
                from .viz import plot_layer, plot_overhangs, plot_terrain_classes

                leveled, _ = leveled_points(points, config)
                written.append(plot_overhangs(leveled, result.overhang, output_dir / f"{name}_overhangs.png"))
                written.append(plot_layer(elevation_map, "max", output_dir / f"{name}_max.png"))
                written.append(
                    plot_terrain_classes(elevation_map, classes, output_dir / f"{name}_classes.png")
                )
        labels, cloud_map = result.overhang, None
        known = int(np.count_nonzero(classes != TerrainClass.UNKNOWN))
        g = elevation_map.geometry
        typer.echo(
            f"{name}: {len(points):,} points, {result.num_overhang:,} overhang; map "
            f"{g.size[0]} x {g.size[1]} cells, {known:,} classified; ground reference: {where}"
        )
        if note is not None:
            typer.echo(note)
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


# ------------------------------------------------------------------------------------------ map


@app.command("map")
def map_command(
    scans: Path = typer.Argument(
        ...,
        help="Directory of scans (any readable format, sorted by name; the files of its most common scan "
        "suffix when it holds several) or one glob pattern (every scan it matches).",
        show_default=False,
    ),
    poses: Path | None = _POSES,
    lidar_only: bool | None = typer.Option(
        None,
        "--lidar-only/--with-odometry",
        help=_help(
            "Without odometry: every scan is registered to the newest keyframe from the previous scan's "
            "motion; --poses, if given, only levels the scans (roll and pitch, e.g. an IMU's).",
            "mapper",
            "lidar_only",
        ),
        show_default=False,
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
    times: Path | None = typer.Option(
        None,
        "--times",
        help="KITTI times.txt: the time [s] of each pose, for the TUM trajectories (default: times.txt "
        "beside KITTI --poses, if present; else the pose index).",
        show_default=False,
    ),
    output_dir: Path = _OUTPUT_DIR,
    config: Path | None = OPTIONS["config"].info,
    preset: str | None = OPTIONS["preset"].info,
    min_range: float | None = OPTIONS["min_range"].info,
    max_range: float | None = OPTIONS["max_range"].info,
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
    limit: int | None = _LIMIT,
    ground_truth: Path | None = typer.Option(
        None,
        "--ground-truth",
        help="Poses to evaluate against (same format and calibration as --poses): prints ATE.",
        show_default=False,
    ),
    png: bool = OPTIONS["png"].info,
) -> None:
    """Build a global elevation map from a sequence of scans and odometry poses.

    Every ~3 m a local classified map is registered to the previous one (class-weighted ICP, odometry
    as the guess) and fused; revisits are registered and the pose graph optimised with Ceres. Writes
    global_map.npz (layers count, min, max, mean, std_dev, discontinuity, class), global_max.png,
    global_classes.png (the trajectory drawn over them), the pose of every scan as
    trajectory_kitti.txt and trajectory_tum.txt (times from times.txt; evo reads both) and the
    keyframes' as keyframes_kitti.txt and keyframes_tum.txt (Velodyne frame when a calibration was
    used; without one KITTI's camera poses are used as they are, with a warning). Exits with code 2,
    writing no map, when no point falls in the map; a scan spanning over 10 km (coordinates in
    millimetres, say) is named then, and warned of otherwise.
    """
    from .mapping import read_odometry
    from .pipeline import build_global_map

    cfg = command_config(
        "map", {"config": config, "preset": preset, "min_range": min_range, "max_range": max_range}
    ).replace(
        "mapper",
        keyframe_distance=keyframe_distance,
        resolution=resolution,
        loop_closing=loop_closing,
        use_registration=registration,
        lidar_only=lidar_only,
    )
    files, total = _scan_files(scans, limit)
    if poses is None and not cfg.mapper.lidar_only:
        raise _fail("give the odometry as --poses FILE, or map without it: --lidar-only")
    for path, option in (
        (poses, "--poses"),
        (calib, "--calib"),
        (times, "--times"),
        (ground_truth, "--ground-truth"),
    ):
        _existing_file(path, option)
    _writable_folder(output_dir)
    with _exit_on_bad_input():  # the ground truth's format and calib.txt count when there are no poses
        odometry = read_odometry(poses, files, pose_format, calib, times, reference=ground_truth, total=total)
    truth = None
    if ground_truth is not None:
        with _exit_on_bad_input(str(ground_truth)):
            truth = odometry.read_like(ground_truth)
    _echo_odometry(odometry)
    _warn_of_the_kitti_car(
        files, cfg.frame.min_range, configured=any(v is not None for v in (config, preset, min_range))
    )
    sequence = progress_bar(list(enumerate(files)), "mapping")
    with _exit_on_bad_input("global map"):
        report = build_global_map(
            ((str(path), _read_scan(path), k) for k, path in sequence),
            odometry.poses,
            odometry.stamps,
            output_dir,
            cfg,
            png=png,
            ground_truth=truth,
        )
    _echo_report(report)


# ------------------------------------------------------------------------------------------ stream


#: The options of ``terracube stream`` that --config and --preset also set.
STREAM_CONFIG_OPTIONS = (
    "config",
    "preset",
    "min_range",
    "max_range",
    "edge",
    "sigma",
    "robot_height",
    "collapse_method",
)


def stream_params(values: dict[str, Any]):
    """The LocalMapParams of ``terracube stream``'s options (a folder of scans or a bag): the
    --config / --preset frame range limits and collapse section, the options given over them;
    exit 2 naming a bad value before any scan is read. Each scan's pose replaces the frame's
    leveling; the frame's crop box applies around the sensor (the scan leveled by its
    pose, relative to the sensor's position), as it does around a single scan's sensor."""
    import dataclasses

    from .local_map import LocalMapParams

    cfg = command_config("stream", {name: values.get(name) for name in STREAM_CONFIG_OPTIONS})
    with _exit_on_bad_input("command line"):
        max_range = cfg.frame.max_range
        params = LocalMapParams(
            length=values["length"],
            resolution=values["resolution"],
            collapse=dataclasses.replace(cfg.collapse, crop=cfg.frame.crop_box()),
            min_range=cfg.frame.min_range,
            max_range=math.inf if max_range is None else max_range,
        )
        params.to_core()
    return params


def stream_lidar_only_poses(scans, values: dict[str, Any]):
    """``scans`` posed by a LiDAR-only mapper (:class:`terracube.stream.LidarOnlyPoses`) with the
    mapper, terrain and registration sections of --config / --preset and the frame's range limits
    (``terracube stream``'s options over them)."""
    from .pipeline import mapper_params
    from .stream import LidarOnlyPoses

    cfg = command_config("stream", {name: values.get(name) for name in STREAM_CONFIG_OPTIONS})
    return LidarOnlyPoses(scans, mapper_params(cfg), keep=cfg.frame.in_range)


@app.command("stream")
def stream_command(
    scans: Path = typer.Argument(
        ...,
        help="Directory of scans (sorted by name; the files of its most common scan suffix when it holds "
        "several) or one glob pattern (every scan it matches).",
        show_default=False,
    ),
    poses: Path | None = _POSES,
    lidar_only: bool = typer.Option(
        False,
        "--lidar-only",
        help="Without odometry: each scan posed by a LiDAR-only mapper (every scan registered to its "
        "newest keyframe); --poses, if given, only levels the scans (roll and pitch, e.g. an IMU's).",
    ),
    pose_format: str = typer.Option(
        "auto", "--pose-format", help="kitti, tum or auto (by the column count)."
    ),
    calib: Path | None = typer.Option(
        None, "--calib", help="KITTI calib.txt (default: calib.txt beside KITTI --poses).", show_default=False
    ),
    times: Path | None = typer.Option(
        None,
        "--times",
        help="KITTI times.txt: the time [s] of each pose, for the map's time layer (default: times.txt "
        "beside KITTI --poses, if present; else the pose index).",
        show_default=False,
    ),
    output_dir: Path = _OUTPUT_DIR,
    length: float = typer.Option(20.0, "--length", help="Side of the square local map [m]."),
    resolution: float = typer.Option(0.1, "--resolution", help="Cell size [m]."),
    every: int = typer.Option(
        0,
        "--every",
        min=0,
        help="A PNG (or animation frame) after every N-th scan, local_elevation_NNNNNN.png with NNNNNN the "
        "scan's 0-based index (KITTI's 000005.bin gives local_elevation_000005.png); 0: none.",
    ),
    animation: Path | None = typer.Option(
        None,
        "--animation",
        help="Write a .gif (or .mp4 with ffmpeg) of the elevation: a frame every --every scans and the "
        "final map.",
        show_default=False,
    ),
    limit: int | None = _LIMIT,
    config: Path | None = OPTIONS["config"].info,
    preset: str | None = OPTIONS["preset"].info,
    min_range: float | None = OPTIONS["min_range"].info,
    max_range: float | None = OPTIONS["max_range"].info,
    edge: float | None = OPTIONS["edge"].info,
    sigma: int | None = OPTIONS["sigma"].info,
    robot_height: float | None = OPTIONS["robot_height"].info,
    collapse_method: str | None = OPTIONS["collapse_method"].info,
    png: bool = OPTIONS["png"].info,
) -> None:
    """Fuse a scan sequence into a robot-centric local map (terracube.LocalMap) and write it.

    Writes local_map.npz (elevation, variance, clearance, traversability, ... in map order),
    local_elevation.png and local_traversability.png, plus a PNG every --every scans or --animation.
    --config and --preset give the range limits (frame section: --preset kitti leaves KITTI's car
    out) and the overhang removal (collapse section); each scan's pose levels it. Exits with code 2,
    writing no map, when no point of any scan falls in the map; warns when the map knows no cell at
    the end, or when a scan spans over 10 km (coordinates in millimetres, say).
    """
    from .mapping import read_odometry
    from .pipeline import read_returns_and_beams
    from .stream import check_animation_target, run_stream

    files, total = _scan_files(scans, limit)
    if poses is None and not lidar_only:
        raise _fail("give the odometry as --poses FILE, or stream without it: --lidar-only")
    for path, option in ((poses, "--poses"), (calib, "--calib"), (times, "--times")):
        _existing_file(path, option)
    if animation is not None:  # before the output folder is made
        with _exit_on_bad_input("stream"):
            check_animation_target(animation)
    _writable_folder(output_dir)
    with _exit_on_bad_input():
        odometry = read_odometry(poses, files, pose_format, calib, times, total=total)
        options = dict(
            config=config,
            preset=preset,
            min_range=min_range,
            max_range=max_range,
            edge=edge,
            sigma=sigma,
            robot_height=robot_height,
            collapse_method=collapse_method,
            length=length,
            resolution=resolution,
        )
        params = stream_params(options)
    _echo_odometry(odometry)
    _warn_of_the_kitti_car(
        files, params.min_range, configured=any(v is not None for v in (config, preset, min_range))
    )
    sequence = progress_bar(list(enumerate(files)), "streaming")
    beams = params.collapse.method == "shadow_aware"  # the empty pixels of organised scans help it
    used_beams = []

    def scans_of_files():
        for k, path in sequence:
            if beams:
                with _exit_on_bad_input():
                    points, no_returns = read_returns_and_beams(path)
                used_beams.append(0 if no_returns is None else len(no_returns))
            else:
                points, no_returns = _read_scan(path), None
            yield str(path), points, odometry.poses[k], float(odometry.stamps[k]), no_returns

    posed = stream_lidar_only_poses(scans_of_files(), options) if lidar_only else scans_of_files()
    with _exit_on_bad_input("stream"):
        report = run_stream(posed, output_dir, params, every=every, animation=animation, png=png)
    _echo_report(report)
    if lidar_only:
        typer.echo(posed.summary())
    if sum(used_beams):
        typer.echo(f"{sum(used_beams):,} beams without a return showed free space")
    elif beams and files:
        typer.echo(f"note: shadow_aware took no empty pixels as free space: {_no_beams_reason(files[0])}")


def _no_beams_reason(path: Path) -> str:
    """Why a scan file gives no beams without a return (:func:`terracube.pipeline.no_beams_reason`)."""
    from .io import organised_shape, read_cloud
    from .pipeline import no_beams_reason

    fields = read_cloud(path)
    return no_beams_reason(fields["xyz"], fields.get("ring"), organised_shape(path)) or "none were found"


# ------------------------------------------------------------------------------------------ config, batch


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
    preset: str | None = OPTIONS["preset"].info,
) -> None:
    """Print every stage's parameters as commented YAML (the defaults, or a file merged over them).

    Edit a copy and pass it to any stage with --config FILE.
    """
    from .config import dump_config

    text = dump_config(command_config("config", {"config": config, "preset": preset}))
    if output is None:
        typer.echo(text, nl=False)
    else:
        from .io import atomic_path

        if output.is_dir():
            raise _fail(f"--output {_short_path(output)}: is a folder; give a file name (e.g. robot.yaml)")
        with _exit_on_bad_input("--output"), atomic_path(output) as temporary:
            temporary.write_text(text)
        typer.echo(f"written: {output}")


@app.command()
@with_options("batch")
def batch(
    stage: str = typer.Argument(
        ..., help=f"Stage to run on every scan: {', '.join(STAGES)}.", show_default=False
    ),
    inputs: list[str] = typer.Argument(
        ..., help="Scans, folders of scans or glob patterns.", show_default=False
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for every file's outputs.", show_default=False),
    workers: int | None = typer.Option(
        None, "--workers", "-w", help="Local worker processes (default: one per core).", show_default=False
    ),
    threads: bool = typer.Option(
        False, "--threads/--processes", help="Local workers as threads, or processes."
    ),
    backend: str = typer.Option(
        "auto",
        "--backend",
        help="pool (concurrent.futures on this machine), dask (needs terracube[batch]) or auto: Dask "
        "when installed or --scheduler is given.",
    ),
    scheduler: str | None = typer.Option(
        None,
        "--scheduler",
        help="Address of a running Dask scheduler (e.g. tcp://HOST:8786); needs terracube[batch].",
        show_default=False,
    ),
    timeout: float = typer.Option(
        600.0,
        "--timeout",
        help="Seconds one file may take; past it the file fails as timed out and its worker is "
        "replaced (0: no limit).",
    ),
    options=None,
) -> None:
    """Run one stage over many scans in parallel; print a summary table.

    Takes every option of the single-scan stage commands. A file that fails is reported with its
    error and the others go on; the exit code is 1 when any file failed. Outputs are the stage's
    own (NAME_... files in --out).
    """
    from .batch import format_summary, run_batch
    from .pipeline import expand_inputs

    if stage not in STAGES:
        raise _fail(f"unknown stage {stage!r}: batch runs {', '.join(STAGES)}")
    if workers is not None and workers < 1:
        raise _fail(f"--workers must be at least 1, got {workers}")
    if not timeout >= 0:
        raise _fail(f"--timeout must be a number of seconds >= 0 (0: no limit), got {timeout}")
    if scheduler is not None and not re.fullmatch(r"[a-z][a-z0-9+.-]*://\S+", scheduler):
        raise _fail(f"--scheduler must be an address such as tcp://HOST:8786, got {scheduler!r}")
    config = command_config(stage, options)
    outputs = stage_output_options(stage, options)
    with _exit_on_bad_input():
        files = expand_inputs(inputs)
    _writable_folder(out, "--out")
    where = scheduler or f"{workers or 'one per core'} local {'threads' if threads else 'processes'}"
    typer.echo(f"{stage}: {len(files)} scans on {where}", err=True)
    with _exit_on_bad_input():
        records = run_batch(
            stage,
            files,
            out,
            config=config,
            options=outputs,
            scheduler=scheduler,
            workers=workers,
            processes=not threads,
            progress=True,
            backend=backend,
            timeout=timeout,
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


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:  # pragma: no cover
    """Python warnings (e.g. a pose file's rounding, float32 precision) as one line, like the
    commands' own warnings."""
    typer.secho(f"warning: {message}", fg=typer.colors.YELLOW, err=True)


def main() -> None:  # pragma: no cover
    import warnings

    warnings.showwarning = _show_warning
    try:
        app()
    except OSError as error:  # a file operation no command anticipated: still an error line
        raise SystemExit(_fail(_os_error_message(error)).exit_code) from None


if __name__ == "__main__":  # pragma: no cover
    main()
