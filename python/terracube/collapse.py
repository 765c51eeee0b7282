"""Overhang removal with collapsible cubes ([CBC]) and its baselines."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from . import _core

__all__ = [
    "CollapseParams",
    "CubeReason",
    "COLLAPSE_METHODS",
    "PointBasedParams",
    "collapse_overhangs",
    "no_return_directions",
    "point_based_overhangs",
    "point_reasons",
    "octomap_column_overhangs",
    "sigma_from_robot_height",
    "attitude_from_gravity",
    "leveling_transform",
]

CubeGrid = _core.CubeGrid
CollapseResult = _core.CollapseResult
#: Why the shadow-aware rule kept or removed a cube: ``CollapseResult.cube_reasons`` holds these
#: values (uint8), one per cube of ``occupied_cubes``. supported (0), below_ground (1),
#: no_ground_estimate (2), shadowed (3) and thin (6) are kept; removed_above_kept (4),
#: removed_free_below (5) and removed_rim (7) are removed. See ``terracube/shadow_aware.hpp``.
#: :func:`point_reasons` gives them per point, and not_used (255) for a point that took no part.
CubeReason = _core.CubeReason

#: ``method`` of :func:`collapse_overhangs`: "paper" is [CBC] Algorithm 1 bit for bit (the default);
#: "shadow_aware" also removes overhangs over ground the sensor cannot see (recommended for mapping).
COLLAPSE_METHODS = {"paper": _core.CollapseMethod.paper, "shadow_aware": _core.CollapseMethod.shadow_aware}

_STORAGE = {
    "auto": _core.CubeStorage.auto,
    "dense": _core.CubeStorage.dense,
    "sparse": _core.CubeStorage.sparse,
}


#: A float32 cloud is flagged when the float32 step at its largest |coordinate| exceeds this share
#: of the length the call resolves (cell or cube edge) ...
FLOAT32_STEP_SHARE = 0.1
#: ... or, for a call without such a length, this step [m].
FLOAT32_STEP_M = 0.01
#: Rows float32_step_warning reads at most (evenly spaced).
FLOAT32_SAMPLE_ROWS = 1024


def _as_points(points, length: float | None = None, length_name: str = "") -> np.ndarray:
    """Numpy arrays pass through untouched (float32/float64 of any strides); sequences become float64.

    float32/float64 in the other byte order (a big-endian file read with ``dtype=">f4"``) take one
    copy in the native order; the core reads native numbers only. A float32 array warns
    (:func:`float32_step_warning`) when its coordinates are too large for float32 to hold them to a
    tenth of ``length`` [m], the cell or cube edge named ``length_name``."""
    if isinstance(points, np.ndarray):
        points = _native_byte_order(points)
        message = float32_step_warning(points, length, length_name)
        if message is not None:
            warnings.warn(message, UserWarning, stacklevel=3)
        return points
    return np.asarray(points, dtype=np.float64)


def _native_byte_order(points):
    """A float32/float64 array in the other byte order as one native copy; anything else as it is."""
    if isinstance(points, np.ndarray) and not points.dtype.isnative and points.dtype.kind == "f":
        if points.dtype.itemsize in (4, 8):
            return points.astype(points.dtype.newbyteorder("="))
    return points


def float32_step_warning(
    points: np.ndarray, length: float | None = None, length_name: str = ""
) -> str | None:
    """Why a float32 cloud is too coarse for a call resolving ``length`` [m] (named ``length_name``),
    or None: float32 steps by 0.5 m at 4,500,000 m (a UTM northing), so its points pile into every
    fifth 0.1 m row. Flagged when the step at the largest finite |x|, |y| or |z| exceeds
    :data:`FLOAT32_STEP_SHARE` of ``length``, or :data:`FLOAT32_STEP_M` without one. Read on at
    most :data:`FLOAT32_SAMPLE_ROWS` evenly spaced rows (a strided view, no copy): an offset such as
    a UTM origin moves every row, and the check stays far below the cost of the call it guards."""
    if points.dtype != np.float32 or points.ndim != 2 or points.shape[1] < 3 or points.shape[0] == 0:
        return None
    xyz = points[:: max(1, points.shape[0] // FLOAT32_SAMPLE_ROWS), :3]
    largest = max(float(np.fmax.reduce(xyz, axis=None)), -float(np.fmin.reduce(xyz, axis=None)))
    if not np.isfinite(largest):  # NaN everywhere, or Inf rows: the call reports those
        return None
    step = float(np.spacing(np.float32(largest)))
    try:
        length = None if length is None else float(length)
    except (TypeError, ValueError):  # a bad length is the parameters' check to report
        length = None
    if length is not None and length > 0:
        allowed, what = FLOAT32_STEP_SHARE * length, f"a tenth of the {length_name} {length:g} m"
    else:
        allowed, what = FLOAT32_STEP_M, f"{FLOAT32_STEP_M * 100:g} cm"
    if step <= allowed:
        return None
    return (
        f"float32 points reach |coordinate| {largest:,.0f} m, where float32 steps by {step:g} m, more "
        f"than {what}: the points are rounded to that step; pass float64 points, or subtract an offset "
        "(e.g. the first point) so the coordinates stay small"
    )


def _as_transform(transform) -> np.ndarray:
    matrix = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f"transform must be a 4x4 matrix, got shape {matrix.shape}")
    return matrix


def _num_threads(num_threads) -> int:
    """A thread count for the C++ parameters: a whole number >= 0 (0 = one per processor)."""
    if isinstance(num_threads, bool) or not isinstance(num_threads, (int, np.integer)) or num_threads < 0:
        raise ValueError(
            f"num_threads must be a whole number >= 0 (0 = one per processor), got {num_threads!r}"
        )
    return int(num_threads)


def _as_use_mask(use, name: str = "use") -> np.ndarray | None:
    """A point mask for the core: a bool array, or whole numbers that are all 0 or 1. Anything
    else (floats, NaN, strings, other numbers) is a ValueError, as ``astype(bool)`` would make it
    all True."""
    if use is None:
        return None
    mask = np.asarray(use)
    if mask.dtype == bool:
        return mask
    if mask.dtype.kind in "iu" and not np.any((mask != 0) & (mask != 1)):
        return mask.astype(bool)
    detail = f"dtype {mask.dtype}" if mask.dtype.kind not in "iu" else "values other than 0 and 1"
    raise ValueError(f"{name} must be a bool mask (or whole numbers 0 and 1), got {detail}")


def _as_classes(classes, name: str) -> np.ndarray | None:
    """Terrain classes for the core: whole numbers 0..255 as uint8 (a bigger one is a ValueError,
    not wrapped around as uint8 would)."""
    if classes is None:
        return None
    values = np.asarray(classes)
    if values.dtype == np.uint8:
        return values
    if values.dtype.kind not in "iu" and not (values.dtype.kind == "b" and values.size == 0):
        raise ValueError(f"{name} must be whole numbers 0..255 (terrain classes), got dtype {values.dtype}")
    if values.size and (values.min() < 0 or values.max() > 255):
        raise ValueError(f"{name} must lie in 0..255 (terrain classes), got {values.min()}..{values.max()}")
    return values.astype(np.uint8)


_INT_LIMITS = (-(2**63), -(2**31), 0, 2**31 - 1, 2**32 - 1, 2**63 - 1, 2**64 - 1)


def _core_int_range(core_type: type, name: str) -> tuple[int, int]:
    """The whole numbers the C++ field ``name`` holds, found by trying the usual limits."""
    accepted = []
    for limit in _INT_LIMITS:
        try:
            setattr(core_type(), name, limit)
            accepted.append(limit)
        except (TypeError, OverflowError):
            pass
    return (min(accepted), max(accepted)) if accepted else (0, 0)


@functools.cache
def _checked(core_type: type) -> type:
    """``core_type`` (a pybind11 parameter struct) whose fields refuse an out-of-range whole number
    with a ValueError naming the field and its range, where pybind11 says only "incompatible
    function arguments". Instances are ``core_type`` instances for every C++ function."""

    def __setattr__(self, name: str, value) -> None:
        try:
            core_type.__setattr__(self, name, value)
        except TypeError:
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise
            low, high = _core_int_range(core_type, name)
            raise ValueError(f"{name} must be a whole number in {low}..{high}, got {value}") from None

    return type(core_type.__name__, (core_type,), {"__setattr__": __setattr__, "__slots__": ()})


def _set_frame(params, transform, crop) -> None:
    """Sets a fresh core parameter struct's transform and crop, leaving its defaults (identity, no
    crop) in place for None: a parameter conversion stays a few microseconds, which matters to a
    loop over scans that takes well under a millisecond per call."""
    if transform is not None:
        params.transform = _as_transform(transform)
    if crop is not None:
        params.crop = _as_crop(crop)


def _as_crop(crop) -> _core.CropBox | None:
    if crop is None:
        return None
    box = np.asarray(crop, dtype=np.float64)
    if box.shape != (2, 3):
        raise ValueError(f"crop must be ((xmin, ymin, zmin), (xmax, ymax, zmax)), got shape {box.shape}")
    return _core.CropBox(box[0], box[1])


@dataclass
class CollapseParams:
    """Parameters of :func:`collapse_overhangs`, mirroring ``terracube::CollapseParams``.

    Attributes
    ----------
    edge : float
        Cube edge E [m], > 0.
    sigma : int
        σ [cubes], >= 1: a cube separated from its column's ground by σ or more empty cubes is
        collapsed. ``sigma_from_robot_height(h, edge)`` gives ceil(h / E).
    transform : (4, 4) array or None
        Rigid transform applied before CBC, e.g. ``leveling_transform(roll, pitch)``.
    crop : ((3,), (3,)) or None
        Axis-aligned box (min corner, max corner) [m] in the leveled frame.
    drop_non_finite : bool
        Drop NaN/Inf rows (never overhang) instead of raising ValueError.
    storage : {"auto", "dense", "sparse"}
        Storage of V and M; all give identical results.
    dense_budget_bytes : int
        Largest V + M allowed for the dense storage [bytes].
    num_threads : int
        Threads for the passes over the points on the dense storage: 1 runs on the calling
        thread alone, 0 uses one per processor; the result is the same whatever the number (as
        :class:`terracube.ElevationParams`').
    method : {"paper", "shadow_aware"}
        "paper" ([CBC] Algorithm 1, exactly) or "shadow_aware": the ground under columns without
        one is estimated from the neighbourhood, and a chain of cubes (gaps < σ) floating σ or more
        above it is removed when a ray from the sensor crossed the column under it or a kept chain
        lies below it; isolated returns below the ground never become ground. Fills
        ``CollapseResult.cube_reasons`` (:data:`CubeReason`).
    sensor_origin : (3,) floats or None
        shadow_aware: the sensor position [m] in the leveled frame; None: the transform's
        translation (the origin of a single scan's own frame). A position more than 10 m below
        every point (a survey in its own coordinates, with None) is refused with a ValueError.
    ground_radius : float
        shadow_aware: ground is looked for within this distance [m] (a square window), >= 0.
    ground_support : int
        shadow_aware: a column's lowest cube is reliable ground when this many columns of its 3x3
        neighbourhood (itself included) have their lowest cube within one layer of it, and more
        of them than have theirs σ or more layers above it (not a patch of multipath returns
        under the road; 4, the default, needs a 2 x 2 block, not an L of three columns), 1..9.
    hidden_ground_margin : float
        shadow_aware: reliable ground lying more than this far [m] under the line of sight over
        reliable ground nearer the sensor (and below it) is no ground: the sensor cannot have seen
        it through the road (multipath, reflections), >= 0.
    free_margin : float
        shadow_aware: a ray proves the space under a chain empty only when it passes at least this
        far [m] below the chain's bottom face (not through a car's windows), >= 0.
    min_bottom_neighbours : int
        shadow_aware: a floating chain goes only when its bottom is wide (a crown's or a ceiling's
        is, a trunk's over a car is not): this many of the 8 columns around it hold a cube within
        one layer of its bottom, or, when none of those 8 holds a grounded chain there, this many
        columns of the ``bottom_window`` square hold a floating chain there.
    bottom_window : int
        shadow_aware: half-width in columns of the square whose floating chains can make a bottom
        wide (1: the 8 neighbours only, 2: 24 columns, which finds the sparse scan rings under a
        ceiling), 1..8.
    remove_rims : bool
        shadow_aware: a thin chain is the rim of an overhang (a crown's edge, a deck's border, a
        scan ring under a ceiling) when one of the 8 columns around it holds a cube of a removed
        wide chain or rim (``removed_free_below``, ``removed_rim``; not ``removed_above_kept``, which
        was never judged wide) within one layer of its bottom and no more of them hold a grounded
        (supported) cube there than such a removed one (a pole's top beside a sign has its own
        grounded column beside it); a rim goes (``removed_rim``) when a ray crossed the column under
        it. False: thin chains stay.
    azimuth_bins : int
        shadow_aware: azimuth sectors of the free-space floor around the sensor, >= 1.
    no_return_range : float
        shadow_aware: how far [m] a beam that returned nothing (``no_returns`` of
        :func:`collapse_overhangs`) shows the space empty, > 0: a range within which the sensor
        sees every surface that matters (dark cars, foliage).
    """

    edge: float = 0.5
    sigma: int = 2
    transform: np.ndarray | None = None
    crop: Sequence[Sequence[float]] | None = None
    drop_non_finite: bool = False
    storage: str = "auto"
    dense_budget_bytes: int = field(default=256 << 20)
    num_threads: int = 1
    method: str = "paper"
    sensor_origin: tuple[float, float, float] | None = None
    ground_radius: float = 5.0
    ground_support: int = 4
    hidden_ground_margin: float = 2.0
    free_margin: float = 0.25
    min_bottom_neighbours: int = 4
    bottom_window: int = 2
    remove_rims: bool = True
    azimuth_bins: int = 512
    no_return_range: float = 30.0

    def to_core(self) -> _core.CollapseParams:
        if self.storage not in _STORAGE:
            raise ValueError(f"storage must be one of {sorted(_STORAGE)}, got {self.storage!r}")
        if isinstance(self.sigma, bool) or int(self.sigma) != self.sigma:
            raise ValueError(f"sigma must be a whole number of cubes, got {self.sigma!r}")
        if not 1 <= int(self.sigma) < 2**31:
            raise ValueError(f"sigma must be between 1 and 2**31 - 1 cubes, got {self.sigma!r}")
        params = _checked(_core.CollapseParams)()
        params.edge_m = float(self.edge)
        params.sigma = int(self.sigma)
        _set_frame(params, self.transform, self.crop)
        params.drop_non_finite = bool(self.drop_non_finite)
        params.storage = _STORAGE[self.storage]
        params.dense_budget_bytes = int(self.dense_budget_bytes)
        params.num_threads = _num_threads(self.num_threads)
        if self.method not in COLLAPSE_METHODS:
            raise ValueError(f"method must be one of {sorted(COLLAPSE_METHODS)}, got {self.method!r}")
        params.method = COLLAPSE_METHODS[self.method]
        params.shadow_aware = self._shadow_aware_core()
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params

    def _shadow_aware_core(self) -> _core.ShadowAwareParams:
        core = _checked(_core.ShadowAwareParams)()
        if self.sensor_origin is not None:
            origin = np.asarray(self.sensor_origin, dtype=np.float64)
            if origin.shape != (3,) or not np.isfinite(origin).all():
                raise ValueError(f"sensor_origin must be 3 finite numbers [m], got {self.sensor_origin!r}")
            core.sensor_origin = origin
        core.ground_radius_m = float(self.ground_radius)
        core.hidden_ground_margin_m = float(self.hidden_ground_margin)
        core.free_margin_m = float(self.free_margin)
        core.no_return_range_m = float(self.no_return_range)
        core.remove_rims = bool(self.remove_rims)
        for name in ("ground_support", "min_bottom_neighbours", "bottom_window", "azimuth_bins"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value:
                raise ValueError(f"{name} must be a whole number, got {value!r}")
            setattr(core, name, int(value))
        return core


@dataclass
class PointBasedParams:
    """Parameters of :func:`point_based_overhangs`, mirroring ``terracube::PointBasedParams``.

    Attributes
    ----------
    edge : float
        Cell edge and height step E [m], > 0: the same grid as the CBC cubes.
    sigma : int
        The gap: ``sigma`` or more empty steps of E between consecutive points of a cell, >= 1.
    variance_threshold : float
        Cells whose height variance is at most this [m^2] are not searched (refs. [3], [7] of
        [CBC]; the value is ours: a 10 cm standard deviation).
    transform, crop, drop_non_finite
        As in :class:`CollapseParams`.
    """

    edge: float = 0.5
    sigma: int = 2
    variance_threshold: float = 0.01
    transform: np.ndarray | None = None
    crop: Sequence[Sequence[float]] | None = None
    drop_non_finite: bool = False

    def to_core(self) -> _core.PointBasedParams:
        params = _checked(_core.PointBasedParams)()
        params.edge_m = float(self.edge)
        params.sigma = int(self.sigma)
        params.variance_threshold_m2 = float(self.variance_threshold)
        _set_frame(params, self.transform, self.crop)
        params.drop_non_finite = bool(self.drop_non_finite)
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params


def collapse_overhangs(
    points,
    edge: float = 0.5,
    sigma: int = 2,
    *,
    transform=None,
    crop=None,
    drop_non_finite: bool = False,
    storage: str = "auto",
    num_threads: int = 1,
    method: str = "paper",
    sensor_origin=None,
    no_returns=None,
    params: CollapseParams | None = None,
) -> CollapseResult:
    """Remove overhangs with collapsible cubes ([CBC] Algorithm 1, or its shadow-aware extension).

    Parameters
    ----------
    points : (N, 3) float32 or float64 array
        x, y, z [m]; any strides, not copied. Wider rows (up to 16 values, x, y, z first: KITTI's
        x, y, z, intensity) are read in place. Other sequences are converted to float64, and an
        array in the other byte order (``dtype=">f4"``) to one native copy, as every entry point does.
    edge, sigma, transform, crop, drop_non_finite, storage, num_threads, method, sensor_origin
        See :class:`CollapseParams`; ``params`` overrides them all when given. ``method="paper"``
        (the default) reproduces the paper; ``method="shadow_aware"`` is recommended for mapping.
    no_returns : (M, 3) array or None
        shadow_aware: directions of the beams of this scan that returned nothing, in the points'
        frame (the empty pixels of an organised scan: :func:`terracube.no_return_directions`). A
        beam level with or above the horizon crossed free space out to ``no_return_range``, so it
        shows the space under a crown or a deck empty as a ray to a point does; lower beams are not
        used (a dark or wet road returns nothing too). Ignored by the paper's method.

    Returns
    -------
    CollapseResult
        ``.overhang`` (N,) bool in input order, ``.removed_cubes`` (R,) int64 (sorted R),
        ``.occupied_cubes`` (K,) int64 (sorted L), ``.grid`` (min corner, ixmax, iymax, izmax) and,
        for shadow_aware, ``.cube_reasons`` (K,) uint8 (:data:`CubeReason`).

    Raises
    ------
    ValueError
        Wrong shape, NaN/Inf rows (unless dropped), edge <= 0, sigma < 1, a non-rigid transform,
        or an extent whose cube count would overflow a 64-bit index.
    TypeError
        A dtype other than float32 or float64.
    """
    if params is None:
        params = CollapseParams(
            edge,
            sigma,
            transform,
            crop,
            drop_non_finite,
            storage,
            num_threads=num_threads,
            method=method,
            sensor_origin=sensor_origin,
        )
    beams = None if no_returns is None else _as_directions(no_returns)
    return _core.collapse_overhangs(_as_points(points, params.edge, "cube edge"), params.to_core(), beams)


def point_reasons(
    points, result: CollapseResult, *, transform=None, crop=None, params: CollapseParams | None = None
) -> np.ndarray:
    """Why each point was kept or removed by a shadow-aware :func:`collapse_overhangs` call.

    Parameters
    ----------
    points : (N, 3) or wider float32 or float64 array
        The points of that call.
    result : CollapseResult
        Its result (``method="shadow_aware"``).
    transform, crop, params
        The call's transform and crop, or its :class:`CollapseParams`: each point's cube is found
        again with the call's own arithmetic.

    Returns
    -------
    (N,) uint8
        The :data:`CubeReason` of the cube holding each point, ``CubeReason.not_used`` (255) for a
        point that took no part (NaN/Inf dropped, outside the crop). Colour a cloud by it to see
        why a crown stayed (shadowed, thin, supported by its trunk) or a wall went.

    Raises
    ------
    ValueError
        A result without cube reasons (the paper's method), or one of other points or parameters.
    """
    if params is None:
        params = CollapseParams(transform=transform, crop=crop, method="shadow_aware")
    return _core.point_reasons(_as_points(points, params.edge, "cube edge"), params.to_core(), result)


def _as_directions(directions) -> np.ndarray:
    """An (M, 3) float64 array of directions (not copied when it is one); ValueError otherwise."""
    array = np.asarray(directions, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"no_returns must be an (M, 3) array of directions, got shape {array.shape}")
    return array


def _unit(values: np.ndarray) -> np.ndarray:
    """Complex numbers scaled to length 1 (0 stays 0): the direction of a sum of headings."""
    length = np.abs(values)
    return np.where(length > 0, values / np.where(length > 0, length, 1.0), 0)


def _filled(values: np.ndarray, *, periodic: bool) -> np.ndarray:
    """NaN entries of a per-row or per-column table filled by a straight line through the others
    (index -> value; angles unwrapped first when `periodic`)."""
    known = np.flatnonzero(np.isfinite(values))
    if known.size == len(values):
        return values
    samples = np.unwrap(values[known]) if periodic else values[known]
    if known.size == 1:
        line = np.full(len(values), samples[0])
    else:
        line = np.polyval(np.polyfit(known, samples, 1), np.arange(len(values)))
    return np.where(np.isfinite(values), values, line)


def _organised_image(points, ring) -> np.ndarray:
    """(H, W, 3) float64 from an (H, W, 3) array, or from (N, 3) rows and their beam numbers."""
    xyz = np.asarray(points, dtype=np.float64)
    if ring is None:
        if xyz.ndim != 3 or xyz.shape[2] != 3:
            raise ValueError(
                "organised must be an (H, W, 3) array (rows = beams), or (N, 3) with ring, "
                f"got shape {xyz.shape}"
            )
        return xyz
    beam = np.asarray(ring)
    if xyz.ndim != 2 or xyz.shape[1] < 3 or beam.shape != (len(xyz),):
        raise ValueError(
            f"with ring, organised must be (N, 3) and ring (N,), got {xyz.shape} and {beam.shape}"
        )
    if len(beam) == 0 or not np.issubdtype(beam.dtype, np.integer):
        raise ValueError("ring must be a non-empty array of whole beam numbers")
    beams, counts = np.unique(beam, return_counts=True)
    if (counts != counts[0]).any():
        raise ValueError(
            f"each beam needs the same number of pixels; ring counts range {counts.min()}..{counts.max()}"
        )
    order = np.argsort(beam, kind="stable")  # each beam's pixels in firing order
    return xyz[order, :3].reshape(len(beams), counts[0], 3)


def is_return(xyz: np.ndarray) -> np.ndarray:
    """Which pixels or rows of x, y, z (last axis) are returns: finite and not (0, 0, 0), the two
    ways drivers store a beam that returned nothing."""
    return np.isfinite(xyz).all(axis=-1) & (xyz != 0).any(axis=-1)


def no_return_directions(organised, ring=None, origin=None) -> np.ndarray:
    """The directions of the empty pixels of an organised scan, for ``collapse_overhangs(no_returns=)``.

    ``organised`` is an (H, W, 3) array of x, y, z [m]: a row per beam, a column per firing, as an
    organised PCD or ROS PointCloud2 stores a spinning lidar's scan (e.g. Ouster's, staggered or
    not); or the (N, 3) rows of such a cloud with ``ring`` (N,), each row's beam number (the PCD
    or PointCloud2 ``ring`` field): the beams interleaved in any way (row or column first), each
    beam's rows in firing order, as many for every beam. A pixel without a return holds NaN or
    (0, 0, 0). ``origin``: the sensor's
    position in the points' frame (default (0, 0, 0), the sensor frame). Each beam's elevation is
    the median over its returns, and each pixel's azimuth that of its column plus its beam's offset
    (both circular means over the returns, a straight line through the others for a column or beam
    without any), so no sensor metadata is needed. Returns (M, 3) float64 unit vectors, one per
    empty pixel (row-major in the image). Raises ValueError for other shapes or an image without a
    return to measure the beams by.
    """
    image = _organised_image(organised, ring)
    sensor = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    if sensor.shape != (3,) or not np.isfinite(sensor).all():
        raise ValueError(f"origin must be 3 finite numbers [m], got {origin!r}")
    valid = is_return(image)
    if not valid.any():
        raise ValueError("organised has no return to measure the beams' directions by")
    if valid.all():
        return np.zeros((0, 3))
    xyz = np.where(valid[..., None], image - sensor, 0.0)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    horizontal = np.hypot(x, y)
    elevation = np.arctan2(z, horizontal)
    beam_elevation = np.array(
        [np.median(row[ok]) if ok.any() else np.nan for row, ok in zip(elevation, valid, strict=True)]
    )
    # Each return's azimuth as a unit complex number (0 without one): a circular mean is the
    # direction of a sum, and the sums over columns and over beams are matrix products.
    heading = _unit(np.where(valid, x + 1j * y, 0))
    offset = np.ones(xyz.shape[0], dtype=complex)  # each beam's azimuth offset, as e^(i offset)
    for _ in range(3):  # column azimuths and beam offsets, each from the other
        column_sum = heading.T @ np.conj(offset)
        offset_sum = heading @ np.conj(_unit(column_sum))
        offset = _unit(offset_sum)
    column = np.where(column_sum != 0, np.angle(column_sum), np.nan)
    offset = np.where(offset_sum != 0, np.angle(offset_sum), np.nan)
    column = _filled(column, periodic=True)
    offset = _filled(offset, periodic=True)
    beam_elevation = _filled(beam_elevation, periodic=False)
    rows, columns = np.nonzero(~valid)
    a = column[columns] + offset[rows]
    e = beam_elevation[rows]
    return np.column_stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def point_based_overhangs(
    points,
    edge: float = 0.5,
    sigma: int = 2,
    *,
    variance_threshold: float = 0.01,
    params: PointBasedParams | None = None,
    **kwargs,
) -> np.ndarray:
    """The point-based method [CBC] compares collapsible cubes with (its refs. [3], [7]).

    Per 2D cell of the CBC grid, cells whose height variance exceeds ``variance_threshold`` [m^2]
    are searched bottom-up for a gap of ``sigma`` or more empty steps of ``edge`` between
    consecutive points; everything above the first such gap is overhang. It agrees with
    :func:`collapse_overhangs` except in cells that hold a gap but a small variance.

    Returns
    -------
    (N,) bool array
        True for overhang points, in input order.
    """
    if params is None:
        params = PointBasedParams(edge, sigma, variance_threshold, **kwargs)
    return _core.point_based_overhangs(_as_points(points, params.edge, "cube edge"), params.to_core())


def octomap_column_overhangs(
    points, edge: float = 0.5, sigma: int = 2, *, params: CollapseParams | None = None, **kwargs
) -> np.ndarray:
    """Algorithm 1's column rule evaluated on an OctoMap OcTree aligned to the CBC grid.

    An independent reference that agrees with :func:`collapse_overhangs` point for point; OctoMap's
    16-bit keys limit it to 65536 cubes per axis.

    Parameters
    ----------
    points : (N, 3) or wider float32/float64 array
        x, y, z [m] in the first three columns.
    edge : float
        Cube edge E [m].
    sigma : int
        σ [cubes].
    params : CollapseParams, optional
        Everything at once (transform, crop ...); ``edge``, ``sigma`` and ``kwargs`` are then ignored.

    Returns
    -------
    (N,) bool array
        True for an overhang point, in input order.
    """
    if params is None:
        params = CollapseParams(edge, sigma, **kwargs)
    return _core.octomap_column_overhangs(_as_points(points, params.edge, "cube edge"), params.to_core())


def sigma_from_robot_height(robot_height: float, edge: float) -> int:
    """σ = ceil(robot_height / edge) [cubes], at least 1."""
    return _core.sigma_from_robot_height(float(robot_height), float(edge))


def attitude_from_gravity(up) -> tuple[float, float]:
    """A sensor's (roll, pitch) [rad] from the direction of gravity's reaction in its frame.

    Parameters
    ----------
    up : (3,) array_like
        An accelerometer's reading at rest (+g along up) or the world's up in the sensor frame;
        only the direction counts.

    Returns
    -------
    (roll, pitch) : tuple of float
        The attitude whose :func:`leveling_transform` turns ``up`` onto +z ([CBC] section IV-B).
        Raises ValueError when ``up`` is zero or not finite.
    """
    vector = np.asarray(up, dtype=np.float64)
    if vector.shape != (3,):
        raise ValueError(f"up must be a (3,) vector, got shape {vector.shape}")
    return _core.attitude_from_gravity(vector)


def leveling_transform(roll: float, pitch: float) -> np.ndarray:
    """The rigid transform R = Ry(pitch) Rx(roll) that levels a sensor with attitude (roll, pitch).

    Parameters
    ----------
    roll, pitch : float
        Sensor attitude [rad].

    Returns
    -------
    (4, 4) float64 array
        Rotation only (zero translation), for ``CollapseParams.transform`` or
        ``ElevationParams.transform``.
    """
    return _core.leveling_transform(float(roll), float(pitch))
