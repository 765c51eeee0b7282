"""A robot-centric local elevation map fused over time (``terracube::LocalMap``, issue 35)."""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from . import _core
from .collapse import CollapseParams, _as_directions, _as_points, _checked, _num_threads
from .elevation import ElevationMap, MapGeometry
from .traversability import TraversabilityParams

__all__ = ["LocalMap", "LocalMapParams", "TraversabilityParams"]


@dataclass
class LocalMapParams:
    """Parameters of :class:`LocalMap`, mirroring ``terracube::LocalMapParams``.

    Attributes
    ----------
    length, resolution : float
        Side of the square map and cell edge [m]; ``round(length / resolution)`` cells a side.
    max_cells : int
        Memory guard: a map keeps about 72 bytes a cell, so the default 16 M cells (4096 x 4096,
        409.6 m at 0.1 m) is about 1.2 GB; a larger map is refused with its size named.
    collapse : CollapseParams
        Overhang removal of each scan ([CBC]); its transform is each scan's pose, its other fields
        are used as given. Its ``crop``, when set, is a box around the sensor: the scan leveled by
        the pose, relative to the sensor's position (``((-40, -40, -3), (40, 40, 20))`` leaves out
        multipath returns under the road seen from 1.7 m up); returns outside it take no part
        (``LocalMapUpdate.num_cropped``).
    min_range, max_range : float
        Returns nearer the sensor than ``min_range`` (the robot's own body; no-returns stored as
        (0, 0, 0)) or farther than ``max_range`` take no part [m]; ``max_range=inf``: no limit.
        KITTI's HDL-64 sees its car within 3 m (the hood's front edge at 2.7-2.8 m).
    range_sigma, angle_sigma : float
        Measurement noise: a return at range r and elevation angle phi has the height variance
        ``range_sigma**2 sin(phi)**2 + (r angle_sigma)**2 cos(phi)**2`` [m], [rad].
    cell_sigma : float
        Height error per cell and scan that does not average out over its points [m]; a scan's
        measurement of a cell (mean of n heights) has the variance
        ``(mean var_z + spread**2) / n + cell_sigma**2``. The defaults suit a Velodyne HDL-64E-class
        sensor on a vehicle; the simulator's exact noise is ``range_sigma=0.02, angle_sigma=0,
        cell_sigma=0.004, drift=0``.
    drift : float
        Odometry height drift [m / sqrt(m)]: before each update every known variance grows by
        ``drift**2`` times the distance travelled since the last one.
    gate_sigmas : float
        A measurement further than this many standard deviations of the innovation replaces the
        cell instead of being fused (something came or went).
    clear_seen_through, clearing_margin, clearing_depth, clearing_beyond
        Clear a cell whose column this scan's rays passed through, on their way to returns at least
        ``clearing_beyond`` [m] further (more than motion distortion moves a surface), between its
        lowest fused point (or ``clearing_depth`` [m] below its height, if lower) and
        ``clearing_margin`` [m] below its height (a person or car that left); rays below all its
        points (under a car's body) say nothing.
    visibility_bin : float
        Angular bin of the see-through test [rad], 0.001 to 0.5.
    discontinuity : float
        Gap [m] between one scan's sorted heights in a cell that makes it discontinuous; the points
        above the gap count as an overhang.
    compute_planner_layers : bool
        Refresh step, slope, roughness and traversability after every update (False: only when
        :meth:`LocalMap.update_planner_layers` is called, e.g. at a planner's slower rate).
    traversability : TraversabilityParams
    num_threads : int
        1 (default) the calling thread, 0 one per processor; the map is the same bit for bit.
    """

    length: float = 20.0
    resolution: float = 0.1
    max_cells: int = 1 << 24
    collapse: CollapseParams = field(default_factory=CollapseParams)
    min_range: float = 0.1
    max_range: float = math.inf
    range_sigma: float = 0.02
    angle_sigma: float = 0.0015
    cell_sigma: float = 0.02
    drift: float = 0.01
    gate_sigmas: float = 3.0
    clear_seen_through: bool = True
    clearing_margin: float = 0.1
    clearing_depth: float = 0.5
    clearing_beyond: float = 0.5
    visibility_bin: float = 0.0087
    discontinuity: float = 1.0
    compute_planner_layers: bool = True
    traversability: TraversabilityParams = field(default_factory=TraversabilityParams)
    num_threads: int = 1

    def to_core(self) -> _core.LocalMapParams:
        params = _checked(_core.LocalMapParams)()
        params.length_m = float(self.length)
        params.resolution_m = float(self.resolution)
        params.max_cells = _max_cells(self.max_cells)
        params.collapse = self.collapse.to_core()
        params.min_range_m = float(self.min_range)
        params.max_range_m = float(self.max_range)
        params.range_sigma_m = float(self.range_sigma)
        params.angle_sigma_rad = float(self.angle_sigma)
        params.cell_sigma_m = float(self.cell_sigma)
        params.drift_m_per_sqrt_m = float(self.drift)
        params.gate_sigmas = float(self.gate_sigmas)
        params.clear_seen_through = bool(self.clear_seen_through)
        params.clearing_margin_m = float(self.clearing_margin)
        params.clearing_depth_m = float(self.clearing_depth)
        params.clearing_beyond_m = float(self.clearing_beyond)
        params.visibility_bin_rad = float(self.visibility_bin)
        params.discontinuity_m = float(self.discontinuity)
        params.compute_planner_layers = bool(self.compute_planner_layers)
        params.traversability = self.traversability.to_core()
        params.num_threads = _num_threads(self.num_threads)
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params


def _max_cells(value) -> int:
    cells = operator.index(value)
    if cells < 1:
        raise ValueError(f"LocalMapParams.max_cells must be a positive number of cells, got {cells}")
    return cells


def _cell_index(index) -> tuple[int, int]:
    """``(i, j)`` as two Python ints: integers (numpy's too), not floats, bools or strings."""
    values = list(index)
    if len(values) != 2:
        raise ValueError(f"index must be two whole cell numbers (i, j), got {len(values)} values")
    try:
        if any(isinstance(v, (bool, np.bool_)) for v in values):
            raise TypeError
        return operator.index(values[0]), operator.index(values[1])
    except TypeError:
        raise TypeError(
            f"index must be two whole cell numbers (i, j), got {tuple(values)!r} (index_of gives the "
            "cell holding a position [m])"
        ) from None


def _as_pose(pose) -> np.ndarray:
    matrix = np.asarray(pose, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 matrix (odometry <- sensor), got shape {matrix.shape}")
    return matrix


class LocalMap:
    """A square robot-centric elevation map in the odometry frame, fused scan after scan.

    ``update(points, pose)`` takes a scan in the sensor frame and its 4x4 pose (odometry <- sensor):
    the map re-centres on the sensor (a circular-buffer shift: cells that leave are dropped, cells
    that enter are empty, nothing else is copied; a jump by the map's length or more drops every
    cell), removes overhangs ([CBC]), clears heights the scan saw through, fuses each cell's mean
    height by a 1-D Kalman update and refreshes the planner layers.

    Layers (``m["elevation"]``, read-only float32 views without a copy that follow the map's
    updates) are in *storage order*: index them with :meth:`index_of`, as in grid_map. Layers:
    ``elevation`` [m], ``variance`` [m^2], ``count``, ``time``, ``min``, ``max``, ``std_dev``,
    ``discontinuity`` ([TC] Table 1 inputs), ``overhang_min``, ``clearance`` (free height under the
    lowest overhang, +inf without one; 0 when that point lies at or below the elevation, which
    blocks rather than guesses), ``step``, ``slope`` [rad], ``roughness``, ``traversability`` in
    [0, 1] (:class:`TraversabilityParams`); NaN where unknown (``count`` 0).
    :meth:`to_elevation_map` gives a copy in map order for ``classify_terrain``, the writers and
    plots.

    Parameters
    ----------
    length, resolution : float
        Map side and cell edge [m].
    params : LocalMapParams, optional
        All parameters (``length``, ``resolution`` and ``kwargs`` are ignored then).
    **kwargs
        Other :class:`LocalMapParams` fields.
    """

    def __init__(
        self, length: float = 20.0, resolution: float = 0.1, *, params: LocalMapParams | None = None, **kwargs
    ):
        if params is None:
            params = LocalMapParams(length=length, resolution=resolution, **kwargs)
        self.params = params
        self._core = _core.LocalMap(params.to_core())

    @property
    def geometry(self) -> MapGeometry:
        """The map's area: ``origin`` its lower-left corner [m], ``size`` its cells (map order)."""
        return self._core.geometry

    @property
    def resolution(self) -> float:
        return self._core.geometry.resolution

    @property
    def start_index(self) -> tuple[int, int]:
        """Storage index of the map's lower-left cell."""
        return self._core.start_index

    @property
    def layers(self) -> list[str]:
        return list(self._core.layers)

    @property
    def num_updates(self) -> int:
        return self._core.num_updates

    @property
    def time_origin(self) -> float:
        """The first update's stamp [s]: the ``time`` layer is relative to it (float32 keeps ms)."""
        return self._core.time_origin

    def __contains__(self, name: str) -> bool:
        return name in self._core.layers

    def __iter__(self):
        """The layer names (``for name in m``), as :attr:`layers`."""
        return iter(self.layers)

    def __len__(self) -> int:
        """How many layers the map holds."""
        return len(self.layers)

    def __reduce__(self):
        raise TypeError(
            "a LocalMap holds a robot's live state (a circular buffer and its fused sums) and does not "
            "pickle; pickle m.to_elevation_map(), its layers in map order, instead"
        )

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self:
            raise KeyError(f"no layer {name!r}; layers: {', '.join(self.layers)}")
        return self._core.get(name)

    def index_of(self, position: Sequence[float]) -> tuple[int, int] | None:
        """Storage index (i, j) of the cell holding ``(x, y)`` [m], or None outside the map."""
        x, y = (float(v) for v in position)
        return self._core.index_of(x, y)

    def position_of(self, index: Sequence[int]) -> np.ndarray:
        """Centre (x, y) [m] of the cell at storage index ``(i, j)``. TypeError for an index that is
        not two whole numbers (``(1.5, 2.0)`` names no cell; no rounding)."""
        i, j = _cell_index(index)
        return self._core.position_of(i, j)

    def update(self, points, pose, stamp: float = math.nan, *, no_returns=None) -> _core.LocalMapUpdate:
        """Fuse one scan ((N, 3) or wider float32/float64, x, y, z first, sensor frame) taken at
        ``pose`` (4x4).

        ``stamp`` [s] goes into the ``time`` layer, relative to the first update's (NaN: the number of
        the update; every update gives a stamp, or none). ``no_returns``: (M, 3) directions of the
        scan's beams that returned nothing, in the sensor frame (:func:`terracube.no_return_directions`),
        for the shadow-aware overhang removal (``collapse.method="shadow_aware"``; ignored by the
        paper's). An empty scan only
        moves the map. ValueError for a non-finite or non-rigid pose, NaN/Inf rows (unless
        ``collapse.drop_non_finite``), a zero or non-finite beam, an infinite stamp, a NaN stamp
        after stamped updates (or the reverse) or one over 1e30 s from the first, before anything
        changes. Releases the GIL.
        """
        points = _as_points(points, self.resolution, "resolution")
        beams = None if no_returns is None else _as_directions(no_returns)
        return self._core.update(points, _as_pose(pose), float(stamp), beams)

    def update_planner_layers(self) -> None:
        """Refresh ``step``, ``slope``, ``roughness`` and ``traversability`` from ``elevation`` and
        ``clearance`` (:func:`terracube.add_traversability_layers` on the circular buffer). With
        ``compute_planner_layers=False`` a planner that runs slower than the sensor calls this when
        it plans, instead of after every scan. Releases the GIL."""
        self._core.update_planner_layers()

    def move_to(self, position: Sequence[float]) -> bool:
        """Centre the map on ``(x, y)``; True when the move dropped every cell. With
        ``compute_planner_layers`` the planner layers are refreshed after a move. Releases the GIL."""
        x, y = (float(v) for v in position)
        return self._core.move_to(x, y)

    def clear(self) -> None:
        self._core.clear()

    def to_elevation_map(self) -> ElevationMap:
        """A copy of every layer in map order, with :attr:`geometry`: cell (i, j) is centred on
        ``geometry.position_of(i, j)``. The copy's ``geometry.index_of`` rounds ``(x - origin) /
        resolution`` where :meth:`index_of` rounds ``x / resolution``: a position on a cell's
        border (a round number) may fall in the neighbouring cell of the copy; use
        :meth:`index_of` for the cell a point was fused into."""
        return ElevationMap(self._core.to_elevation_map())

    def __repr__(self) -> str:
        g = self.geometry
        known = int(np.count_nonzero(~np.isnan(self["elevation"])))
        return (
            f"LocalMap(length={self.params.length}, resolution={g.resolution}, origin=({g.origin[0]:.2f}, "
            f"{g.origin[1]:.2f}), known_cells={known}, num_updates={self.num_updates})"
        )
