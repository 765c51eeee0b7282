"""The work behind the ``terracube`` command line and ``terracube batch``, without the printing.

Each per-scan stage (collapse, dem, classify, fem) reads nothing and prints nothing:
:func:`run_stage` takes the points, runs the stage with a :class:`terracube.config.Config`, writes
the outputs as ``NAME_...`` files and returns a :class:`StageReport` (summary lines, written files).
What a real sensor needs is decided here, once for every stage: the points outside the frame's
range limits are left out (:func:`range_note`), a map without a fixed extent covers
:func:`auto_extent`, the ground reference is estimated when none is given (:func:`terrain_params`)
and a mostly empty map is flagged (:func:`fill_note`).
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
import functools
import glob
import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "CLOUD_FORMATS",
    "MapperRun",
    "REGISTRATION_METHODS",
    "SCAN_SUFFIXES",
    "STAGES",
    "ScanOutput",
    "StageReport",
    "auto_extent",
    "build_global_map",
    "collapse_params",
    "elevation_params",
    "empty_beams",
    "no_beams_reason",
    "expand_inputs",
    "fill_note",
    "ground_reference_given",
    "leveled_points",
    "looks_airborne",
    "map_scans",
    "mapper_params",
    "point_classes",
    "range_note",
    "read_returns_and_beams",
    "read_scan",
    "read_scan_and_beams",
    "read_stage_input",
    "register_scans",
    "registration_record",
    "returns_and_beams",
    "run_stage",
    "scan_span",
    "scan_span_warning",
    "scan_trajectory",
    "terrain_params",
    "write_global_map",
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


def _read_scan_fields(path: str | Path) -> dict[str, np.ndarray]:
    """:func:`terracube.io.read_cloud` of a scan file; ValueError naming it when it holds no points
    (every reader of a scan goes through here, so every command refuses such a file alike)."""
    from .io import read_cloud

    fields = read_cloud(path)
    if len(fields["xyz"]) == 0:
        raise ValueError(f"{path}: the file holds no points")
    return fields


def read_scan(path: str | Path) -> np.ndarray:
    """The (N, 3) array of points [m] of one scan file (any format of :mod:`terracube.io`).

    Raises FileNotFoundError for a missing file and ValueError naming the file for a malformed one
    or one that holds no points.
    """
    return _read_scan_fields(path)["xyz"]


def read_scan_and_beams(path: str | Path, origin=None) -> tuple[np.ndarray, np.ndarray | None]:
    """The points of one scan file (as :func:`read_scan`) and the directions of its beams that
    returned nothing, seen from ``origin`` (the file's origin when None; :func:`empty_beams` of its
    image layout and ``ring`` field), for ``method="shadow_aware"``; None when the file does not lay
    the scan out (:func:`no_beams_reason` says why)."""
    from .io import organised_shape

    fields = _read_scan_fields(path)
    return fields["xyz"], empty_beams(fields["xyz"], fields.get("ring"), origin, organised_shape(path))


def read_returns_and_beams(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`returns_and_beams` of one scan file (ValueError as :func:`read_scan`)."""
    from .io import organised_shape

    fields = _read_scan_fields(path)
    return returns_and_beams(fields["xyz"], fields.get("ring"), organised_shape(path))


def returns_and_beams(
    xyz: np.ndarray, ring: np.ndarray | None, image_shape: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The returns of a scan (its rows without NaN/Inf or (0, 0, 0) no-returns) and the directions
    of its beams that returned nothing (:func:`empty_beams`, None when neither ``image_shape`` nor
    ``ring`` lays the scan out): what ``LocalMap.update`` takes as ``points`` and ``no_returns``."""
    from .collapse import is_return

    returns = is_return(xyz)
    beams = empty_beams(xyz, ring, image_shape=image_shape)
    return (xyz if returns.all() else np.ascontiguousarray(xyz[returns])), beams


def read_stage_input(path: str | Path, config) -> tuple[np.ndarray, np.ndarray | None]:
    """What a per-scan stage reads of a scan file under ``config``: its points, and its beams
    without a return when the overhang removal is ``shadow_aware`` (:func:`read_scan_and_beams`,
    from the collapse's ``sensor_origin`` when set, else the file's origin)."""
    if config is None or config.collapse.method != "shadow_aware":
        return read_scan(path), None
    origin = config.collapse.sensor_origin
    if origin is not None:  # given in the leveled frame: back into the file's
        transform = config.frame.transform()
        origin = transform[:3, :3].T @ (np.asarray(origin, dtype=np.float64) - transform[:3, 3])
    return read_scan_and_beams(path, origin)


def _is_image_shape(image_shape, count: int) -> bool:
    return image_shape is not None and image_shape[0] > 1 and image_shape[0] * image_shape[1] == count


def no_beams_reason(
    xyz: np.ndarray, ring: np.ndarray | None, image_shape: tuple[int, int] | None = None
) -> str | None:
    """Why :func:`empty_beams` finds no beams without a return in a scan (a phrase), or None when it
    finds some."""
    from .collapse import is_return

    if not _is_image_shape(image_shape, len(xyz)):
        layout = "the cloud is not organised (no HEIGHT > 1 with WIDTH x HEIGHT = its points)"
        if ring is None:
            return f"{layout} and has no ring field"
        if ring.ndim != 1 or not np.issubdtype(ring.dtype, np.integer) or len(ring) != len(xyz):
            return f"{layout} and its ring field is not one integer per point"
        _, counts = np.unique(ring, return_counts=True)
        if not (counts == counts[0]).all():
            return (
                f"{layout} and its ring field gives the beams unequal pixel counts "
                f"({counts.min():,}..{counts.max():,}: a driver that drops or mislabels the empty pixels)"
            )
    returned = np.count_nonzero(is_return(xyz))
    if returned == len(xyz):
        return "every pixel of the scan holds a return"
    if returned == 0:
        return "the scan holds no return to measure its beams by"
    return None


def empty_beams(
    xyz: np.ndarray, ring: np.ndarray | None, origin=None, image_shape: tuple[int, int] | None = None
) -> np.ndarray | None:
    """The directions of the empty pixels (NaN or (0, 0, 0)) of an organised scan, seen from
    ``origin`` (the points' origin when None), from :func:`terracube.no_return_directions`.

    The scan's layout comes from ``image_shape`` (HEIGHT, WIDTH) when HEIGHT > 1 and it holds every
    point (an organised PCD's header, :func:`terracube.io.organised_shape`; the rows are then the
    image row-major), else from an integer ``ring`` field with as many pixels per beam (as Ouster
    drivers write them). None when neither lays the scan out or none is empty
    (:func:`no_beams_reason` says which)."""
    from .collapse import no_return_directions

    if no_beams_reason(xyz, ring, image_shape) is not None:
        return None
    if _is_image_shape(image_shape, len(xyz)):
        return no_return_directions(np.asarray(xyz).reshape(*image_shape, 3), origin=origin)
    return no_return_directions(xyz, ring=ring, origin=origin)


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


#: The automatic map window spans the 1st..99th percentile of the points' x and y, widened by this
#: share of its span on each side (and never beyond the points): a few far returns (an Ouster scan
#: reaches 240 m) no longer blow the map up to millions of empty cells.
AUTO_EXTENT_PERCENTILES = (1.0, 99.0)
AUTO_EXTENT_MARGIN = 0.1
#: Below this share of cells with data a stage notes that the map is mostly empty.
LOW_FILL_RATIO = 0.02


def checked_resolution(config) -> float:
    """The config's map resolution [m]; a ValueError naming it unless positive and finite (checked
    before anything divides by it)."""
    resolution = float(config.elevation.resolution)
    if not (resolution > 0 and math.isfinite(resolution)):
        raise ValueError(f"resolution must be a positive finite length in metres, got {resolution:g}")
    return resolution


def auto_extent(points: np.ndarray, config) -> tuple[list[float], list[int]] | None:
    """(origin [m], size [cells]) of the automatic map window of ``points`` in the config's frame, or
    None when no point is inside the crop box. See :data:`AUTO_EXTENT_PERCENTILES`."""
    resolution = checked_resolution(config)  # the window divides by it
    leveled, inside = leveled_points(points, config)
    if not inside.any():
        return None
    # Column by column: numpy's reductions along the rows of an (N, 2) array are many times slower.
    x, y = leveled[inside, 0], leveled[inside, 1]
    low, high = np.array([np.percentile(values, AUTO_EXTENT_PERCENTILES) for values in (x, y)]).T
    margin = np.maximum(AUTO_EXTENT_MARGIN * (high - low), 2.0 * resolution)
    low = np.maximum(low - margin, [x.min(), y.min()])
    high = np.minimum(high + margin, [x.max(), y.max()])
    origin = np.floor(low / resolution) * resolution
    size = np.maximum(np.floor((high - origin) / resolution).astype(np.int64) + 1, 1)
    return [float(v) for v in origin], [int(v) for v in size]


def elevation_params(config, points: np.ndarray | None = None, **changes):
    """The config's elevation section in the config's frame, with ``changes`` applied.

    With ``points`` and no fixed extent (origin and size) the map covers :func:`auto_extent`.
    """
    frame = config.frame
    if points is not None and config.elevation.origin is None and "origin" not in changes:
        window = auto_extent(points, config)
        if window is not None:
            changes = {**changes, "origin": window[0], "size": window[1]}
    return dataclasses.replace(
        config.elevation, transform=frame.transform(), crop=frame.crop_box(), **changes
    )


#: Window half-size [m] of the estimated local-ground reference: 5 cells at 0.1 m (all ground on an
#: 11 deg slope, where the 10-cell window finds 15 %), never under 3 cells.
ESTIMATED_GROUND_WINDOW_M = 0.5


def ground_reference_given(terrain) -> bool:
    """Whether ``terrain`` names a ground reference: anything but the sensor-height reference at the
    default height 0 (no real sensor sits on the ground), which means "estimate it"."""
    return not (terrain.reference == "sensor_height" and float(terrain.sensor_height) == 0.0)


def terrain_params(config):
    """(TerrainParams, description) of the ground reference the classes are measured from.

    The terrain section as given when it names a reference (:func:`ground_reference_given`);
    otherwise the ground is estimated as the lowest point within :data:`ESTIMATED_GROUND_WINDOW_M`
    of each cell (the local-ground reference), which holds on slopes and needs no sensor height.
    """
    terrain = config.terrain
    if ground_reference_given(terrain):
        if terrain.reference == "sensor_height":
            return terrain, f"sensor height {terrain.sensor_height:g} m"
        return terrain, f"local ground, {terrain.local_ground_radius} cells"
    radius = max(3, round(ESTIMATED_GROUND_WINDOW_M / checked_resolution(config)))
    estimated = dataclasses.replace(terrain, reference="local_ground", local_ground_radius=radius)
    return estimated, (
        f"local ground, {radius} cells (estimated: no sensor height given; "
        "--sensor-height H or --reference local_ground to choose)"
    )


def mapper_params(config):
    """MapperParams of the config: the mapper section plus the terrain and registration sections.

    A terrain section that names no ground reference (:func:`ground_reference_given`) gives way to
    the mapper's terrain defaults (local ground, 5-cell window) for maps chained over slopes.
    """
    from .config import default_config
    from .mapping import MapperParams

    terrain = config.terrain
    if terrain == default_config().terrain or not ground_reference_given(terrain):
        terrain = MapperParams().terrain
    return dataclasses.replace(config.mapper, terrain=terrain, registration=config.registration)


def range_note(points: np.ndarray, keep: np.ndarray, frame) -> str | None:
    """A summary line of the points the frame's range limits left out, or None when none were."""
    dropped = int(len(keep) - np.count_nonzero(keep))
    if dropped == 0:
        return None
    xyz = np.asarray(points)[~keep, :3]
    zeros = int(np.count_nonzero(np.all(xyz == 0, axis=1)))
    squared = np.einsum("ij,ij->i", xyz, xyz, dtype=np.float64)
    farthest = float(frame.max_range) if frame.max_range is not None else math.inf
    far = int(np.count_nonzero(squared > farthest * farthest))  # x * x: inf for 1e300, where ** 2 raises
    parts = [f"{zeros:,} no-returns at (0, 0, 0)"] if zeros else []
    near = dropped - zeros - far
    if near:
        parts.append(f"{near:,} nearer than {frame.min_range:g} m or not finite")
    if far:
        parts.append(f"{far:,} beyond {frame.max_range:g} m")
    return f"  range filter: {dropped:,} of {len(keep):,} points left out ({', '.join(parts)})"


#: A single scan in metres spans at most a few kilometres (a ground robot's LiDAR a few hundred
#: metres, an airborne tile a few km): wider, its coordinates are taken to be in another unit.
IMPLAUSIBLE_SCAN_SPAN_M = 10_000.0
#: :func:`scan_span` measures the 1st..99th percentile of the coordinates (a few stray far returns
#: do not count) over at most this many points of the scan.
_SPAN_SAMPLE = 20_000


def scan_span(points: np.ndarray) -> float:
    """The largest extent [m] along x, y or z of a scan's finite points, from the 1st to the 99th
    percentile (of every k-th point, at most :data:`_SPAN_SAMPLE`); 0 without a finite point."""
    xyz = np.asarray(points)[:: max(1, len(points) // _SPAN_SAMPLE), :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) == 0:
        return 0.0
    low, high = np.percentile(xyz, [1.0, 99.0], axis=0)
    return float(np.max(high - low))


def _span_text(span: float) -> str:
    return f"{span / 1000:,.0f} km"


def scan_span_warning(spans: Iterable[float], what: str = "scans") -> str | None:
    """A warning when a scan spans more than :data:`IMPLAUSIBLE_SCAN_SPAN_M` (:func:`scan_span`):
    its coordinates are most likely millimetres (1000 times a scan in metres), and every length of
    the settings (cells, cube edge, ranges, the local map) is then 1000 times too small. ``spans``:
    each scan's span [m]; ``what`` names them when there are several."""
    spans = [s for s in spans if math.isfinite(s)]
    wide = [s for s in spans if s > IMPLAUSIBLE_SCAN_SPAN_M]
    if not wide:
        return None
    where = (
        f"the scan spans {_span_text(wide[0])}"
        if len(spans) == 1
        else f"{len(wide)} of {len(spans)} {what} span over {_span_text(IMPLAUSIBLE_SCAN_SPAN_M)} "
        f"(the widest {_span_text(max(wide))})"
    )
    return (
        f"warning: {where}, more than a LiDAR scan in metres: are the coordinates in millimetres? "
        "terracube expects metres (divide millimetres by 1000)"
    )


#: Below this many points per cell with data the cells are finer than the point spacing.
SPARSE_POINTS_PER_CELL = 1.5


@functools.cache
def _airborne_resolution() -> float:
    """The cell size [m] of the airborne_las preset."""
    from .config import load_config

    return float(load_config(None, preset="airborne_las").elevation.resolution)


def _scan_length_unit(scan: ScanOutput) -> tuple[str, float | None] | None:
    """The unit of length of the scan's CRS (:func:`terracube.io.crs_length_unit`) when it is not
    the metre; None for metres, without a CRS, or when it cannot be read."""
    from .io import crs_length_unit

    try:
        crs = scan.crs
    except Exception:  # noqa: BLE001 - advisory lines: a CRS that cannot be read says nothing
        return None
    unit = crs_length_unit(crs)
    return None if unit is None or unit[1] == 1.0 else unit


#: Short symbols of the units of length other than the metre that LAS files' CRSs name.
_UNIT_SYMBOLS = {"foot": "ft", "US survey foot": "ftUS"}


def length_text(value: float, unit: tuple[str, float | None] | None = None, spec: str = "g") -> str:
    """``value`` formatted by ``spec`` with the unit of length it is in: ``unit`` as
    :func:`_scan_length_unit` gives it, None for metres ("0.5 m"); a foot CRS gives "0.5 ft" or
    "0.5 ftUS", another unit (or a geographic CRS's degrees) "0.5 (file units, NAME)"."""
    number = format(value, spec)
    if unit is None:
        return f"{number} m"
    name = unit[0]
    symbol = _UNIT_SYMBOLS.get(name)
    return f"{number} {symbol}" if symbol is not None else f"{number} (file units, {name})"


def unit_note(scan: ScanOutput, config) -> str | None:
    """A warning line when the CRS of the scan's LAS/LAZ source does not measure in metres: terracube
    takes the coordinates as they are, so every length of the settings acts in the file's unit (a
    foot file's 0.5 m cells are 0.15 m), or, for a geographic CRS, x and y are degrees."""
    unit = _scan_length_unit(scan)
    if unit is None:
        return None
    name, factor = unit
    if factor is None:
        return (
            f"  warning: the CRS of {scan.source.name} is geographic: x and y are degrees of longitude and "
            "latitude, not metres; reproject the cloud to a projected CRS (e.g. its UTM zone) first"
        )
    resolution = float(config.elevation.resolution)
    return (
        f"  warning: the CRS of {scan.source.name} measures in {name} (1 {name} = {factor:.7g} m) and "
        "terracube takes the coordinates as they are: every length set (cells, cube edge, robot height, "
        f"ranges) acts in {name} here, e.g. the cells of {resolution:g} are {resolution * factor:.3g} m; for "
        f"metric settings divide the lengths by {factor:.7g} (--resolution {resolution / factor:.3g})"
    )


def fill_note(elevation_map, unit: str | None = None, airborne: bool = True) -> str | None:
    """A warning line when fewer than :data:`LOW_FILL_RATIO` of the map's cells hold data, or a note
    when the cells with data hold fewer than :data:`SPARSE_POINTS_PER_CELL` points on average (an
    airborne tile at 0.1 m: a speckle of single points), with the cell size that holds about four.
    ``unit`` names the unit of length of the map's coordinates when it is not the metre (a LAS file
    in feet: the density is then per square foot). ``airborne`` allows the hint that a speckle of
    single points may be an airborne tile (``--preset airborne_las``); a ground sensor's far field
    looks the same and is better cut by ``--max-range``."""
    count = np.asarray(elevation_map["count"])
    filled = int(np.count_nonzero(count > 0))
    if count.size == 0 or filled == 0:
        return None
    points = float(count.sum())
    resolution = float(elevation_map.geometry.resolution)
    density = points / (count.size * resolution * resolution)  # per unit squared over the map (0 at 1e300)
    suggested = max(resolution, math.ceil(10 * math.sqrt(4.0 / density)) / 10) if density > 0 else resolution
    sparse = points / filled < SPARSE_POINTS_PER_CELL
    # The airborne preset helps only a map finer than its cells (not one already made with it).
    hint = (
        " (an airborne tile: --preset airborne_las)"
        if airborne and sparse and resolution < _airborne_resolution()
        else ""
    )
    if filled < LOW_FILL_RATIO * count.size:
        return (
            f"  warning: only {filled / count.size:.1%} of the {count.size:,} cells hold data; a smaller "
            "window (--max-range, --crop, or --origin with --size) or a coarser --resolution "
            f"(--resolution {suggested:g}: about four points a cell) gives a readable map{hint}"
        )
    if not sparse:
        return None
    return (
        f"  note: the cells with data hold {points / filled:.1f} points on average ({density:.1f} points "
        f"per {'m2' if unit is None else 'square ' + unit}): --resolution {suggested:g} gives cells of about "
        f"four points{hint}"
    )


def leveled_points(points: np.ndarray, config) -> tuple[np.ndarray, np.ndarray]:
    """The (N, 3) float64 points [m] in the leveled frame (``points`` itself when it is float64 and
    the frame is not leveled: read only), and the (N,) bool mask of the finite ones inside the crop
    box."""
    transform = config.frame.transform()
    leveled = np.asarray(points[:, :3], dtype=np.float64)
    if not np.array_equal(transform, np.eye(4)):
        with np.errstate(invalid="ignore"):  # NaN/Inf rows stay non-finite, and are left out below
            leveled = leveled @ transform[:3, :3].T + transform[:3, 3]
    # Column by column: numpy's reductions along the rows of an (N, 3) array are many times slower.
    inside = np.isfinite(leveled[:, 0]) & np.isfinite(leveled[:, 1]) & np.isfinite(leveled[:, 2])
    box = config.frame.crop_box()
    if box is not None:
        for axis in range(3):
            inside &= (leveled[:, axis] >= box[0][axis]) & (leveled[:, axis] <= box[1][axis])
    return leveled, inside


def points_cropped(points: np.ndarray, config) -> int:
    """How many finite points of ``points`` the config's crop box leaves out (0 without one)."""
    if config.frame.crop_box() is None:
        return 0
    leveled, inside = leveled_points(points, config)
    finite = np.isfinite(leveled[:, 0]) & np.isfinite(leveled[:, 1]) & np.isfinite(leveled[:, 2])
    return int(np.count_nonzero(finite & ~inside))


def _add_crop_line(report: StageReport, cropped: int) -> None:
    if cropped:
        report.lines.append(f"  {cropped:,} points outside the crop box were left out")


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
        """Record written files and a summary line ``  label: path, path`` (none without files)."""
        if not paths:
            return
        self.outputs.extend(paths)
        self.lines.append(f"  {label}: {', '.join(map(str, paths))}")


@dataclass
class ScanOutput:
    """Every point of one input scan, which of them the stage used (in range), the file it came
    from and its beams without a return (``no_returns``, or None): the classified cloud a stage
    writes holds every input point (the unused ones labelled 0) and, written as LAS/LAZ from a
    LAS/LAZ input, every dimension and VLR of the input."""

    points: np.ndarray
    keep: np.ndarray
    source: Path | None = None
    no_returns: np.ndarray | None = None

    @functools.cached_property
    def crs(self) -> str | None:
        """The source file's CRS (:func:`terracube.io.read_crs`), read once; None without one."""
        from .io import read_crs

        return read_crs(self.source) if self.source is not None else None

    @functools.cached_property
    def source_fields(self) -> dict[str, np.ndarray]:
        """The source file's per-point fields (:func:`terracube.io.read_cloud`), read once, with
        ``xyz``; empty without a source or when it holds other points than ``points``."""
        from .io import read_cloud

        if self.source is None:
            return {}
        fields = read_cloud(self.source)
        return fields if len(fields["xyz"]) == len(self.points) else {}

    @functools.cached_property
    def image_shape(self) -> tuple[int, int] | None:
        """(HEIGHT, WIDTH) of an organised PCD source (:func:`terracube.io.organised_shape`), or None."""
        from .io import organised_shape

        return None if self.source is None else organised_shape(self.source)

    def no_beams_reason(self) -> str:
        """Why the scan has no beams without a return (``no_returns`` is None)."""
        if not self.source_fields:
            return "none were given with the points"
        fields = self.source_fields
        return no_beams_reason(fields["xyz"], fields.get("ring"), self.image_shape) or "none were given"

    @functools.cached_property
    def length_unit(self) -> tuple[str, float | None] | None:
        """The unit of length of the source's CRS when it is not the metre (:func:`_scan_length_unit`)."""
        return _scan_length_unit(self)

    def length(self, value: float, spec: str = "g") -> str:
        """``value`` with the unit of length of the scan's coordinates (:func:`length_text`)."""
        return length_text(value, self.length_unit, spec)

    def labels(self, kept_labels: np.ndarray) -> np.ndarray:
        """(N,) labels of every input point from those of the kept ones (0 / False elsewhere)."""
        kept_labels = np.asarray(kept_labels)
        if len(kept_labels) == len(self.points):
            return kept_labels
        labels = np.zeros(len(self.points), dtype=kept_labels.dtype)
        labels[self.keep] = kept_labels
        return labels

    def write(self, path: Path, kept_labels: np.ndarray, **kwargs) -> Path:
        from .io import write_classified

        if path.suffix.lower() in (".las", ".laz"):
            return write_classified(path, self.points, self.labels(kept_labels), source=self.source, **kwargs)
        fields = dict(self.source_fields)
        # read_cloud's "label" naming another field's values is no field of the file: not written twice
        if "label" in fields and any(
            name in fields and np.array_equal(fields[name], fields["label"])
            for name in ("overhang", "terracube_class", "classification")
        ):
            del fields["label"]
        image_shape = self.image_shape if fields else None
        return write_classified(
            path, self.points, self.labels(kept_labels), fields=fields, image_shape=image_shape, **kwargs
        )


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


def reason_counts(cube_reasons) -> str:
    """The shadow-aware rule's cubes counted by CubeReason, removed ones first: "removed_above_kept
    1,090, removed_free_below 1,995; kept: supported 15,803, ..."."""
    from .collapse import CubeReason

    counts = np.bincount(np.asarray(cube_reasons, dtype=np.uint8), minlength=256)
    # not_used marks points that took no part (point_reasons), never a cube
    members = {name: value for name, value in CubeReason.__members__.items() if name != "not_used"}
    text = {name: f"{name} {counts[int(value)]:,}" for name, value in members.items()}
    removed = [line for name, line in text.items() if name.startswith("removed")]
    kept = [line for name, line in text.items() if not name.startswith("removed")]
    return ", ".join(removed) + "; kept: " + ", ".join(kept)


def _run_collapse(
    points,
    name,
    output_dir: Path,
    config,
    *,
    scan: ScanOutput,
    output_format="ply",
    png=True,
    las_classification=False,
) -> StageReport:
    from . import collapse_overhangs

    _check_cloud_format(output_format)
    params = collapse_params(config)
    start = time.perf_counter()
    result = collapse_overhangs(points, params=params, no_returns=scan.no_returns)
    elapsed_ms = _elapsed_ms(start)
    grid = result.grid
    report = StageReport(name, int(result.num_points))
    report.lines.append(
        f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
        f"(edge {scan.length(params.edge)}, sigma {params.sigma} cubes; "
        f"{len(result.occupied_cubes):,} occupied cubes, {len(result.removed_cubes):,} collapsed; "
        f"grid {grid.ixmax}x{grid.iymax}x{grid.izmax}; "
        f"{elapsed_ms:.1f} ms)"
    )
    _add_crop_line(report, result.num_cropped)
    if len(result.cube_reasons):
        report.lines.append("  cubes by reason (shadow_aware): " + reason_counts(result.cube_reasons))
    _add_beams_note(report, params, scan)
    cloud = output_dir / f"{name}_classified.{output_format}"
    report.add("classified cloud", scan.write(cloud, result.overhang, as_classification=las_classification))
    if png:
        from .viz import plot_overhangs

        leveled, _ = leveled_points(points, config)
        title = (
            f"{name}: {result.num_overhang:,} of {result.num_points:,} points are overhang "
            f"(collapsible cubes, E = {scan.length(params.edge)}, sigma = {params.sigma})"
        )
        path = output_dir / f"{name}_overhangs.png"
        report.add("picture", *_pictures(lambda: plot_overhangs(leveled, result.overhang, path, title=title)))
        report.add("picture", *_reasons_picture(points, result, params, config, output_dir, name, leveled))
    return report


def _reasons_picture(points, result, params, config, output_dir: Path, name: str, leveled=None) -> list[Path]:
    """NAME_reasons.png of a shadow-aware removal (the points coloured by why they were kept or
    removed, :func:`terracube.point_reasons`); nothing for the paper's rule, which has no reasons.
    ``leveled``: the points in the leveled frame when the caller has them (else leveled here)."""
    if not len(result.cube_reasons):
        return []
    from .collapse import point_reasons
    from .viz import plot_reasons

    if leveled is None:
        leveled, _ = leveled_points(points, config)
    reasons = point_reasons(points, result, params=params)
    path = output_dir / f"{name}_reasons.png"
    title = (
        f"{name}: why shadow_aware kept or removed each point (E = {params.edge} m, sigma = {params.sigma})"
    )
    return _pictures(lambda: plot_reasons(leveled, reasons, path, title=title))


def _run_dem(
    points, name, output_dir: Path, config, *, scan: ScanOutput, png=True, geotiff=False
) -> StageReport:
    from . import build_elevation_map, dem_without_overhangs

    collapse = collapse_params(config)
    params = elevation_params(config, points)  # the automatic window is not the map's time
    start = time.perf_counter()
    raw = build_elevation_map(points, params=params)
    raw_ms = _elapsed_ms(start)
    _require_data(name, raw)
    g = raw.geometry
    start = time.perf_counter()
    clean, result = dem_without_overhangs(
        points,
        collapse=collapse,
        elevation=elevation_params(config, origin=g.origin, size=g.size),
        no_returns=scan.no_returns,
    )
    clean_ms = _elapsed_ms(start)
    before, after = raw["max"], clean["max"]
    lower = int(np.count_nonzero(np.isfinite(before) & np.isfinite(after) & (after < before)))
    emptied = int(np.count_nonzero(np.isfinite(before) & np.isnan(after)))
    report = StageReport(name, int(result.num_points))
    report.lines.append(
        f"{name}: DEM {g.size[0]} x {g.size[1]} cells at {scan.length(g.resolution)}, "
        f"{int(np.count_nonzero(np.isfinite(before))):,} with data; {result.num_overhang:,} of "
        f"{result.num_points:,} points are overhang (edge {scan.length(collapse.edge)}, sigma "
        f"{collapse.sigma}); "
        f"{lower:,} cells lower, {emptied:,} emptied; raw DEM {raw_ms:.1f} ms, DEM without overhangs "
        f"{clean_ms:.1f} ms"
    )
    _add_crop_line(report, result.num_cropped)  # the raw map's crop box is the removal's
    _add_beams_note(report, collapse, scan)
    _add_notes(report, raw, scan)
    report.add("map", clean.save(output_dir / f"{name}_dem.npz"))
    if geotiff:
        report.add("GeoTIFF", _geotiff(clean, "max", output_dir / f"{name}_dem_max.tif", scan))
    if png:
        from .viz import plot_dem_comparison, plot_layer

        robot_height = collapse.sigma * collapse.edge
        pictures = _pictures(
            lambda: plot_dem_comparison(
                raw,
                clean,
                output_dir / f"{name}_dem_comparison.png",
                title=f"{name}: highest elevation before and after overhang removal "
                f"(E = {scan.length(collapse.edge)}, σ = {collapse.sigma})",
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
        pictures += _reasons_picture(points, result, collapse, config, output_dir, name)
        report.add("pictures", *pictures)
    return report


def map_of_scan(
    points, name, config, remove_overhangs: bool, elevation=None, no_returns=None, length=length_text
):
    """The elevation map of one scan (raw, or without overhangs), a description of it, and the
    :class:`terracube.CollapseResult` (None for the raw map). ``elevation``: the map's
    :class:`terracube.ElevationParams` (default :func:`elevation_params`, with the automatic window
    from the points); ``no_returns``: the scan's beams without a return, for the shadow-aware
    removal; ``length`` formats a length for the description (:meth:`ScanOutput.length`: the
    file's unit). ValueError when no point is in the map."""
    from . import build_elevation_map, dem_without_overhangs

    elevation = elevation_params(config, points) if elevation is None else elevation
    if remove_overhangs:
        collapse = collapse_params(config)
        elevation_map, result = dem_without_overhangs(
            points, collapse=collapse, elevation=elevation, no_returns=no_returns
        )
        source = (
            f"DEM without overhangs (edge {length(collapse.edge)}, sigma {collapse.sigma}; "
            f"{result.num_overhang:,} overhang points)"
        )
    else:
        elevation_map, result = build_elevation_map(points, params=elevation), None
        source = "raw map"
    _require_data(name, elevation_map)
    return elevation_map, source, result


def classified_map(points, name, config, remove_overhangs: bool, no_returns=None, length=length_text):
    """(elevation map, (nx, ny) uint8 classes, description, map ms, classification ms) of one scan.

    The classes are measured from :func:`terrain_params`' ground reference; ``no_returns`` and
    ``length`` as :func:`map_of_scan`'s.
    """
    from . import classify_terrain

    terrain, _ = terrain_params(config)
    terrain.to_core()  # checks the thresholds before the map is built
    elevation = elevation_params(config, points)  # the automatic window is not the map's time
    start = time.perf_counter()
    elevation_map, source, _ = map_of_scan(
        points, name, config, remove_overhangs, elevation, no_returns, length
    )
    map_ms = _elapsed_ms(start)
    start = time.perf_counter()
    classes = classify_terrain(elevation_map, terrain)
    return elevation_map, classes, source, map_ms, _elapsed_ms(start)


def _add_beams_note(report: StageReport, collapse, scan: ScanOutput) -> None:
    if collapse.method != "shadow_aware":
        return
    if scan.no_returns is not None:
        report.lines.append(f"  {len(scan.no_returns):,} beams without a return showed free space")
    else:
        report.lines.append(
            f"  note: shadow_aware took no empty pixels as free space: {scan.no_beams_reason()}"
        )


def looks_airborne(points: np.ndarray) -> bool:
    """Whether a cloud looks like an airborne tile rather than a ground sensor's scan: its height
    (1st to 99th percentile) is less than half its width, and it is seen from above: either the
    origin lies farther from the cloud's footprint than the footprint is wide (georeferenced
    coordinates: the sensor is not at the origin) or the origin is a sensor higher above the
    cloud's top than the cloud is deep. A car's LiDAR sits amid its returns, some of them above it."""
    xyz = np.asarray(points)[:, :3]
    xyz = xyz[:: max(1, len(xyz) // 100_000)]  # the percentiles of 100,000 points are enough
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if len(xyz) < 3:
        return False
    low, high = np.percentile(xyz, [1.0, 99.0], axis=0)
    width = float(np.hypot(*(high[:2] - low[:2])))
    depth = float(high[2] - low[2])
    if not depth < 0.5 * width:
        return False
    outside = np.maximum(np.maximum(low[:2], -high[:2]), 0.0)  # the origin's xy distance to the footprint
    georeferenced = float(np.hypot(*outside)) > width
    from_above = float(-high[2]) > depth
    return georeferenced or from_above


def _add_notes(report: StageReport, elevation_map, scan: ScanOutput) -> None:
    unit = _scan_length_unit(scan)
    # Airborne tiles come as LAS/LAZ; a KITTI .bin or a PCD is a ground sensor's; other sources (a
    # bag's clouds, arrays, .npz) by their geometry.
    suffix = "" if scan.source is None else scan.source.suffix.lower()
    if suffix in (".las", ".laz"):
        airborne = True
    elif suffix in (".bin", ".pcd"):
        airborne = False
    else:
        airborne = looks_airborne(scan.points[scan.keep] if not scan.keep.all() else scan.points)
    note = fill_note(elevation_map, None if unit is None else unit[0], airborne)
    if note is not None:
        report.lines.append(note)


def _geotiff(elevation_map, layer: str, path: Path, scan: ScanOutput) -> Path:
    from .io import write_geotiff

    return write_geotiff(elevation_map, layer, path, crs=scan.crs)


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
    scan: ScanOutput,
    las_classification=False,
    cloud_format="ply",
    png=True,
    geotiff=False,
) -> StageReport:
    from . import TerrainClass
    from .io import TERRAIN_LAS_CLASSES

    _check_cloud_format(cloud_format)
    elevation_map, classes, source, map_ms, classify_ms = classified_map(
        points, name, config, remove_overhangs, scan.no_returns, scan.length
    )
    g = elevation_map.geometry
    counts = np.bincount(classes.ravel(), minlength=len(TerrainClass))
    known = int(classes.size - counts[0])
    terrain, where = terrain_params(config)
    report = StageReport(name, len(points))
    report.lines.append(
        f"{name}: {g.size[0]} x {g.size[1]} cells at {scan.length(g.resolution)}, {known:,} with data; "
        f"{source}; "
        f"map {map_ms:.1f} ms, classification {classify_ms:.1f} ms"
    )
    _add_crop_line(report, points_cropped(points, config))
    report.lines.append(f"  ground reference: {where}")
    if remove_overhangs:
        _add_beams_note(report, config.collapse, scan)
    for terrain_class in TerrainClass:
        count = int(counts[int(terrain_class)])
        share = f" ({count / known:.1%} of cells with data)" if terrain_class and known else ""
        report.lines.append(f"  {terrain_class.name.lower().replace('_', ' '):<20} {count:>10,}{share}")
    hint = _ground_plane_hint(elevation_map, terrain)
    if hint is not None:
        report.lines.append(hint)
    _add_notes(report, elevation_map, scan)
    report.add("map", elevation_map.save(output_dir / f"{name}_classes.npz"))
    if cloud_format is not None:
        labels = point_classes(*leveled_points(points, config), elevation_map, classes)
        cloud = output_dir / f"{name}_classes.{cloud_format}"
        cloud = scan.write(
            cloud, labels, las_classes=TERRAIN_LAS_CLASSES, as_classification=las_classification
        )
        report.add("classified cloud (per-point terrain class)", cloud)
    if geotiff:
        report.add("GeoTIFF", _geotiff(elevation_map, "class", output_dir / f"{name}_classes.tif", scan))
    if png:
        from .viz import plot_terrain_classes

        title = f"{name}: terrain classes ({source.split(' (')[0]}, {where.split(' (')[0]})"
        path = output_dir / f"{name}_classes.png"
        report.add(
            "picture", *_pictures(lambda: plot_terrain_classes(elevation_map, classes, path, title=title))
        )
    return report


def _run_fem(
    points,
    name,
    output_dir: Path,
    config,
    *,
    scan: ScanOutput,
    remove_overhangs=True,
    png=True,
    geotiff=False,
) -> StageReport:
    from . import fit_fuzzy_elevation_map

    start = time.perf_counter()
    elevation_map, source, collapse = map_of_scan(
        points, name, config, remove_overhangs, no_returns=scan.no_returns, length=scan.length
    )
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
        f"{scan.length(history[-1], '.3f')} after {len(history) - 1} epochs; "
        f"{int(np.isfinite(fitted).sum()):,} of {g.size[0] * g.size[1]:,} cells "
        f"({scan.length(g.resolution)}) filled, RMSE to the mean DEM {scan.length(rmse, '.3f')}; "
        f"{elapsed_ms:.1f} ms"
    )
    _add_crop_line(report, points_cropped(points, config))
    if remove_overhangs:
        _add_beams_note(report, config.collapse, scan)
    _add_notes(report, elevation_map, scan)
    report.add(
        "map (layers fem, fem_confidence and the DEM's)", elevation_map.save(output_dir / f"{name}_fem.npz")
    )
    if geotiff:
        report.add("GeoTIFF", _geotiff(elevation_map, "fem", output_dir / f"{name}_fem.tif", scan))
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
    "collapse": {"output_format": "ply", "png": True, "las_classification": False},
    "dem": {"png": True, "geotiff": False},
    "classify": {
        "remove_overhangs": False,
        "cloud_format": "ply",
        "png": True,
        "geotiff": False,
        "las_classification": False,
    },
    "fem": {"remove_overhangs": True, "png": True, "geotiff": False},
}


def run_stage(
    stage: str,
    points: np.ndarray,
    name: str,
    output_dir: str | Path,
    config=None,
    *,
    source: str | Path | None = None,
    no_returns=None,
    **options,
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
        A :class:`terracube.config.Config` (the defaults when None). Points outside its frame's
        ``min_range`` .. ``max_range`` take no part (reported); a map without a fixed extent covers
        :func:`auto_extent`; classes use :func:`terrain_params`' ground reference (reported).
    source
        The file the points were read from: its CRS goes into GeoTIFFs, and a LAS/LAZ source's
        dimensions and VLRs into a LAS/LAZ classified cloud.
    no_returns
        (M, 3) directions of the scan's beams that returned nothing, in the points' frame
        (:func:`read_scan_and_beams`), or None: the shadow-aware removal (``collapse.method``)
        takes them as free space; the paper's rule ignores them.
    **options
        The stage's output options, :data:`STAGE_OUTPUT_OPTIONS` (collapse: ``output_format``,
        ``png``, ``las_classification``; dem: ``png``, ``geotiff``; classify: ``remove_overhangs``,
        ``cloud_format``, ``png``, ``geotiff``, ``las_classification``; fem: ``remove_overhangs``,
        ``png``, ``geotiff``). ``las_classification`` writes terracube's labels into a LAS/LAZ
        cloud's ``classification`` too (by default they go in an extra dimension only).

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
    config = config or default_config()
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"{name}: need an (N, 3) or wider array of points, got shape {points.shape}")
    keep = config.frame.in_range(points)
    scan = ScanOutput(points, keep, None if source is None else Path(source), no_returns)
    kept = points if keep.all() else np.ascontiguousarray(points[keep])
    span = scan_span_warning([scan_span(kept)])
    try:
        report = _RUNNERS[stage](kept, name, output_dir, config, scan=scan, **options)
    except ValueError as error:  # a map of millions of cells, say: the unit is the likely cause
        if span is None:
            raise
        raise ValueError(f"{error}; {span.removeprefix('warning: ')}") from error
    for note in (range_note(points, keep, config.frame), unit_note(scan, config), span and f"  {span}"):
        if note is not None:
            report.lines.insert(1, note)
    return report


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
        :func:`registration_record` of the result (plus ``ground_reference``, the classes'
        reference, and ``points_left_out``, per scan the points outside the frame's range limits),
        and the registration's time [ms].
    """
    from .config import default_config
    from .registration import pcl_icp, points_of_map, register_maps, register_maps_all_cells

    if method not in REGISTRATION_METHODS:
        raise ValueError(f"the method must be one of {', '.join(REGISTRATION_METHODS)}, got {method!r}")
    config = config or default_config()
    guess = np.eye(4) if initial is None else np.asarray(initial, dtype=np.float64)
    scans = [np.asarray(points) for points in (source, target)]
    kept = [config.frame.in_range(points) for points in scans]
    maps = [
        classified_map(points[keep] if not keep.all() else points, name, config, remove_overhangs)[0]
        for points, keep, name in zip(scans, kept, names, strict=True)
    ]
    start = time.perf_counter()
    if method == "classes":
        result = register_maps(maps[0], maps[1], guess, config.registration)
    elif method == "all-cells":
        result = register_maps_all_cells(maps[0], maps[1], guess, config.registration)
    else:
        result = pcl_icp(points_of_map(maps[0])[0], points_of_map(maps[1])[0], guess, config.pcl_icp)
    record = registration_record(method, names[0], names[1], result)
    record["ground_reference"] = terrain_params(config)[1]
    record["points_left_out"] = [int(len(keep) - np.count_nonzero(keep)) for keep in kept]
    return record, _elapsed_ms(start)


# ------------------------------------------------------------------------------------------ map


def _mapper_reference(terrain, config) -> str:
    if terrain.reference == "sensor_height":
        return f"sensor height {terrain.sensor_height:g} m"
    given = "" if ground_reference_given(config.terrain) and terrain == config.terrain else " (the mapper's)"
    return f"local ground, {terrain.local_ground_radius} cells{given}"


def scan_trajectory(
    keyframe_poses: np.ndarray,
    keyframe_odometry: np.ndarray,
    keyframe_scans: np.ndarray,
    odometry: np.ndarray,
) -> np.ndarray:
    """(S, 4, 4) pose of every scan: scan i after keyframe k (the last one at or before it) is
    ``K_k inv(O_k) O_i``, the keyframe's estimate moved by the odometry since that keyframe.

    ``keyframe_scans`` are the keyframes' positions in ``odometry`` (the scans' odometry, in order).
    """
    odometry = np.asarray(odometry, dtype=np.float64)
    keyframe_scans = np.asarray(keyframe_scans, dtype=np.int64)
    owner = np.searchsorted(keyframe_scans, np.arange(len(odometry)), side="right") - 1
    owner = np.maximum(owner, 0)  # scans before the first keyframe (none in practice) follow it
    corrections = np.asarray(keyframe_poses) @ np.linalg.inv(np.asarray(keyframe_odometry))
    return corrections[owner] @ odometry


def mapper_steps_line(mapper, odometry_steps: int, params) -> str:
    """The summary line of how the mapper's steps were made."""
    if params.lidar_only:
        t = mapper.timings
        return (
            f"LiDAR-only: {t.registered_steps} of {t.registered_steps + t.untrusted_steps} scans registered "
            f"to the newest keyframe, {t.untrusted_steps} untrusted kept the constant-velocity prediction"
        )
    if not params.use_registration:
        return "odometry only: no step was scan-matched (--odometry-only)"
    return (
        f"odometry fallbacks: {odometry_steps} of {max(len(mapper) - 1, 0)} keyframe steps kept the "
        "odometry (registration failed or its correction was refused)"
    )


def median_horizontal_range(points: np.ndarray) -> float:
    """The median horizontal distance [m] of a scan's points from its sensor (every 16th point; NaN
    for an empty scan): how far the returns typically lie, against the mapper's local map."""
    sample = np.asarray(points)[::16, :2].astype(np.float64)
    return float(np.median(np.hypot(sample[:, 0], sample[:, 1]))) if len(sample) else math.nan


def local_map_reach_warning(median_ranges, params) -> str | None:
    """A warning when the typical return lies beyond the mapper's local map, the square of side
    ``local_map_size`` round each keyframe's sensor that registration matches: a long-range sensor
    (a truck's forward-looking LiDAR sees nothing within 13 m) then has too little of each scan in
    it. Suggests a side of twice the median range at cells of at most 600 a side."""
    ranges = [r for r in median_ranges if math.isfinite(r)]
    if not ranges or np.median(ranges) <= params.local_map_size / 2:
        return None
    reach = float(np.median(ranges))
    size = 10.0 * math.ceil(reach / 5.0)  # twice the reach, in whole tens of metres
    resolution = max(params.resolution, math.ceil(size / 600.0 / 0.05) * 0.05)
    return (
        f"warning: the median return lies {reach:.0f} m from the sensor, beyond the mapper's local map "
        f"(+-{params.local_map_size / 2:g} m), the area registration matches; for a long-range sensor "
        f"set mapper.local_map_size {size:g} and mapper.resolution {resolution:g} (--config)"
    )


@dataclass
class MapperRun:
    """A scan sequence fed to a :class:`terracube.Mapper` by :func:`map_scans`."""

    mapper: Any
    poses: np.ndarray  #: (S, 4, 4) the pose given with each scan: odometry, or LiDAR-only a leveling
    stamps: np.ndarray  #: (S,) the scans' times [s]
    estimates: np.ndarray  #: (S, 4, 4) each scan's pose as the mapper reported it
    seconds: float  #: the mapper's time, reading the scans included
    odometry_steps: int  #: keyframe steps that kept odometry: registration failed or was refused
    left_out: int  #: points outside the frame's range limits
    reaches: list[float]  #: each scan's median horizontal range [m]
    spans: list[float] = field(default_factory=list)  #: each scan's :func:`scan_span` [m]

    @functools.cached_property
    def global_map(self):
        """The mapper's global elevation map (:meth:`terracube.Mapper.global_map`, built once)."""
        return self.mapper.global_map()

    def trajectory(self) -> np.ndarray:
        """(S, 4, 4) every scan's pose: its keyframe's final estimate moved by the odometry since
        (LiDAR-only: by the scan's own registration, the pose the mapper reported at its time)."""
        moved = self.estimates if self.mapper.params.lidar_only else self.poses
        key_scans = np.asarray(self.mapper.keyframe_scan_indices())
        return scan_trajectory(self.mapper.keyframe_poses(), moved[key_scans], key_scans, moved)


def map_scans(scans: Iterable[tuple[str, np.ndarray, np.ndarray, float]], config=None) -> MapperRun:
    """Feed ``(name, points, pose, stamp)`` per scan, in order, to a :class:`terracube.Mapper` with
    ``config``'s mapper, terrain and registration sections, leaving out the points beyond the
    frame's range limits, then close the loops still pending. ``points``: (N, 3) or wider [m] in
    the sensor frame; ``pose``: its (4, 4) odometry world <- sensor (LiDAR-only: its leveling).
    Read lazily: a generator that reads files keeps one scan in memory. ValueError naming the scan."""
    from .config import default_config
    from .mapping import Mapper

    config = config or default_config()
    mapper = Mapper(mapper_params(config))
    poses, stamps, estimates, reaches, spans = [], [], [], [], []
    odometry_steps = left_out = 0
    start = time.perf_counter()
    for name, points, pose, stamp in scans:
        points = np.asarray(points)
        keep = config.frame.in_range(points)
        left_out += int(len(keep) - np.count_nonzero(keep))
        try:
            step = mapper.add_scan(points if keep.all() else np.ascontiguousarray(points[keep]), pose)
        except (ValueError, TypeError) as error:
            raise ValueError(f"{name}: {error}") from error
        reaches.append(median_horizontal_range(points[keep]))
        spans.append(scan_span(points[keep]))
        if step.keyframe and step.index > 0 and config.mapper.use_registration and not step.registered:
            odometry_steps += 1
        poses.append(np.asarray(pose, dtype=np.float64))
        stamps.append(float(stamp))
        estimates.append(step.pose)
    if not poses:
        raise ValueError("no scan to map")
    if mapper.pending_loops:
        mapper.optimize()
    seconds = time.perf_counter() - start
    return MapperRun(
        mapper,
        np.asarray(poses),
        np.asarray(stamps),
        np.asarray(estimates),
        seconds,
        odometry_steps,
        left_out,
        reaches,
        spans,
    )


def write_global_map(
    run: MapperRun, output_dir: str | Path, config=None, *, png: bool = True, what: str = "scans"
) -> StageReport:
    """Write a :func:`map_scans` run: ``global_map.npz``, ``trajectory_kitti.txt`` and
    ``trajectory_tum.txt`` (every scan's pose, :meth:`MapperRun.trajectory`, with its time),
    ``keyframes_kitti.txt`` and ``keyframes_tum.txt`` and, with ``png``, ``global_max.png`` and
    ``global_classes.png`` with the trajectory drawn on them. Returns a :class:`StageReport` whose
    lines sum the run up (``what`` names its scans: "scans", "clouds of /points")."""
    from .config import default_config

    config = config or default_config()
    mapper, output_dir, dem = run.mapper, Path(output_dir), run.global_map
    if dem.geometry.num_cells == 0 or not np.isfinite(dem["max"]).any():  # nothing worth writing
        raise ValueError(_empty_global_map_message(run, what))
    output_dir.mkdir(parents=True, exist_ok=True)
    report = StageReport("global map", len(run.poses))
    report.outputs.append(dem.save(output_dir / "global_map.npz"))
    trajectory, keyframes = run.trajectory(), mapper.keyframe_poses()
    key_stamps = run.stamps[np.asarray(mapper.keyframe_scan_indices(), dtype=np.int64)]
    report.outputs += _write_poses(output_dir / "trajectory", run.stamps, trajectory)
    report.outputs += _write_poses(output_dir / "keyframes", key_stamps, keyframes)
    if png and dem.geometry.num_cells > 0:
        from .viz import plot_layer, plot_terrain_classes

        classes = np.nan_to_num(dem["class"], nan=0).astype(np.uint8)
        path_xy = trajectory[:, :2, 3]
        report.outputs += _pictures(
            lambda: plot_layer(
                dem, "max", output_dir / "global_max.png", title="highest elevation [m]", trajectory=path_xy
            ),
            lambda: plot_terrain_classes(
                dem, classes, output_dir / "global_classes.png", title="terrain classes", trajectory=path_xy
            ),
        )
    report.lines += _mapping_lines(run, dem, config, what)
    return report


def _empty_global_map_message(run: MapperRun, what: str) -> str:
    """Why a mapper run left the global map empty, for the error that stops it being written."""
    params = run.mapper.params
    span = scan_span_warning(run.spans, what)
    farthest = "" if params.max_range is None else f" and nearer than {params.max_range:g} m"
    cause = (
        span.removeprefix("warning: ")
        if span is not None
        else f"the mapper keeps the returns within +-{params.local_map_size / 2:g} m of each keyframe's "
        f"sensor, from {params.min_range:g} m{farthest} (mapper.local_map_size, min_range, max_range)"
    )
    return f"no point of the {len(run.poses)} {what} fell in the global map: {cause}"


def _write_poses(stem: Path, stamps: np.ndarray, poses: np.ndarray) -> list[Path]:
    """STEM_kitti.txt and STEM_tum.txt of (S, 4, 4) poses at their (S,) times, each atomically."""
    from .io import atomic_path
    from .poses import write_kitti_poses, write_tum_poses

    kitti, tum = stem.with_name(f"{stem.name}_kitti.txt"), stem.with_name(f"{stem.name}_tum.txt")
    with atomic_path(kitti) as temporary:
        write_kitti_poses(temporary, poses)
    with atomic_path(tum) as temporary:
        write_tum_poses(temporary, stamps, poses)
    return [kitti, tum]


def _mapping_lines(run: MapperRun, dem, config, what: str) -> list[str]:
    """The summary of a mapper run: scans, keyframes and loops, time per step, the map, the ground
    reference, how the steps were made, and the warnings (local map reach, range filter)."""
    mapper, t, g = run.mapper, run.mapper.timings, dem.geometry
    scans = len(run.poses)
    lines = [
        f"{scans} {what}, {len(mapper)} keyframes, {len(mapper.loop_closures)} loop closures "
        f"in {run.seconds:.2f} s ({scans / run.seconds:.1f} scans/s incl. reading)",
        f"time [ms]: map building {t.map_building_ms:.0f}, classification {t.classification_ms:.0f}, "
        f"registration {t.registration_ms:.0f}, fusion {t.fusion_ms:.0f}, "
        f"loop closing {t.loop_closing_ms:.0f}",
        f"global map: {int(g.size[0])} x {int(g.size[1])} cells at {g.resolution} m, "
        f"{int(np.isfinite(dem['max']).sum())} with data, "
        f"{mapper.global_memory_bytes / 2**20:.1f} MiB of tiles",
        f"ground reference: {_mapper_reference(mapper.params.terrain, config)}",
        mapper_steps_line(mapper, run.odometry_steps, config.mapper),
    ]
    span = scan_span_warning(run.spans, what)
    # Scans in millimetres reach 1000 times too far: the unit, not the local map, is to change.
    reach = None if span else local_map_reach_warning(run.reaches, config.mapper)
    lines += [warning for warning in (span, reach) if warning]
    left_out = run.left_out + mapper.points_out_of_range
    if left_out:
        frame, params = config.frame, mapper.params
        limits = [f"nearer than {max(frame.min_range, params.min_range):g} m"]
        farthest = [r for r in (frame.max_range, params.max_range) if r is not None]
        limits += [f"beyond {min(farthest):g} m"] if farthest else []
        lines.append(f"range filter: {left_out:,} points left out ({' or '.join(limits)})")
    return lines


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
    """Chain a scan sequence into a global elevation map with :class:`terracube.Mapper` and write it
    (:func:`map_scans`, then :func:`write_global_map`).

    Parameters
    ----------
    scans
        ``(name, points, pose index)`` per scan, in order: (N, 3) or wider points [m] in the sensor
        frame and the row of ``odometry`` taken when it was recorded. Read lazily.
    odometry : (P, 4, 4) array
        Odometry poses world <- sensor [m]. With the mapper section's ``lidar_only`` only their roll
        and pitch are used (identities for a level sensor): the motion comes from the scans.
    stamps : (P,) array
        Their times [s], for the TUM trajectories.
    output_dir
        Where :func:`write_global_map` writes.
    config
        A :class:`terracube.config.Config`: the frame's range limits and the mapper, terrain and
        registration sections.
    ground_truth : (P, 4, 4) array, optional
        True poses: the report adds the ATE of the estimate and of the odometry (first pose aligned).

    Returns
    -------
    StageReport
        Summary lines (scans, keyframes, loops, time per step, the map) and the written files.
    """
    from .config import default_config

    config = config or default_config()
    indices: list[int] = []

    def posed():
        for name, points, index in scans:
            indices.append(index)
            yield name, points, odometry[index], float(stamps[index])

    run = map_scans(posed(), config)
    report = write_global_map(run, output_dir, config, png=png)
    if ground_truth is not None:
        from .evaluation import absolute_trajectory_error

        truth = np.asarray(ground_truth)[indices]
        estimate = absolute_trajectory_error(run.trajectory(), truth, "first_pose").translation
        line = f"ATE over {len(indices)} scans (first pose aligned): mapper RMSE {estimate.rmse:.3f} m"
        if not config.mapper.lidar_only:
            odom = absolute_trajectory_error(run.poses, truth, "first_pose").translation
            line += f", odometry RMSE {odom.rmse:.3f} m"
        report.lines.append(line)
    report.lines += [f"written: {path}" for path in report.outputs]
    return report
