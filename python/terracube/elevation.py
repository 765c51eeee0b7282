"""Elevation maps (named float layers, NaN = empty) and terrain classes."""

from __future__ import annotations

import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import _core
from .classes import TERRAIN_COLORS, TerrainClass
from .collapse import (
    CollapseParams,
    CollapseResult,
    _as_directions,
    _as_points,
    _as_use_mask,
    _checked,
    _num_threads,
    _set_frame,
)

__all__ = [
    "ElevationMap",
    "MapGeometry",
    "ElevationParams",
    "TerrainClass",
    "TerrainParams",
    "build_elevation_map",
    "dem_without_overhangs",
    "classify_terrain",
    "TERRAIN_COLORS",
]

MapGeometry = _core.MapGeometry


class ElevationMap:
    """A grid geometry with named float32 layers of shape (nx, ny); NaN means no data.

    Cell (i, j) covers x in [origin_x + i*res, origin_x + (i+1)*res) and likewise j along y; its
    centre is ``geometry.position_of(i, j)``. ``map["mean"]`` is a writeable view (no copy).
    Maps pickle with their geometry and layers (a worker process returns them whole) and
    ``copy.deepcopy`` gives a map that owns its layers.
    """

    def __init__(self, core: _core.ElevationMap):
        self._core = core

    @classmethod
    def empty(cls, resolution: float, origin: Sequence[float], size: Sequence[int]) -> ElevationMap:
        return cls(_core.ElevationMap(_core.MapGeometry(float(resolution), np.asarray(origin, float), size)))

    @property
    def geometry(self) -> MapGeometry:
        return self._core.geometry

    @property
    def resolution(self) -> float:
        return self._core.geometry.resolution

    @property
    def layers(self) -> list[str]:
        return list(self._core.layers)

    def __contains__(self, name: str) -> bool:
        return self._core.exists(name)

    def __iter__(self):
        """The layer names, in the order they were added (``for name in m``, ``dict(m.items())``)."""
        return iter(self.layers)

    def __len__(self) -> int:
        """How many layers the map holds."""
        return len(self.layers)

    def items(self):
        """(name, layer view) pairs of every layer."""
        return [(name, self[name]) for name in self.layers]

    def __getitem__(self, name: str) -> np.ndarray:
        if not self._core.exists(name):
            raise KeyError(f"no layer {name!r}; layers: {', '.join(self.layers)}")
        return self._core.get(name)

    def __setitem__(self, name: str, data) -> None:
        data = np.asarray(data, dtype=np.float32)
        size = tuple(int(n) for n in self.geometry.size)
        if data.shape != size:
            raise ValueError(f"layer {name!r} has shape {data.shape}, the map is {size}")
        self._core.add(name, data)

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(nx,) x and (ny,) y coordinates of the cell centres [m]."""
        g = self.geometry
        x = g.origin[0] + (np.arange(g.size[0]) + 0.5) * g.resolution
        y = g.origin[1] + (np.arange(g.size[1]) + 0.5) * g.resolution
        return x, y

    def save(self, path: str | Path) -> Path:
        """Write geometry and every layer to a compressed .npz file."""
        from .io import atomic_path

        path = Path(path)
        g = self.geometry
        with atomic_path(path) as temporary:
            self._savez(temporary, g)
        return path

    def _savez(self, path: Path, g) -> None:
        np.savez_compressed(
            path,
            resolution=np.float64(g.resolution),
            origin=np.asarray(g.origin, dtype=np.float64),
            size=np.asarray(g.size, dtype=np.int64),
            layer_names=np.asarray(self.layers),
            **{f"layer_{name}": self[name] for name in self.layers},
        )

    @classmethod
    def load(cls, path: str | Path) -> ElevationMap:
        """Read a map written by :meth:`save`; FileNotFoundError when there is no such file,
        ValueError naming the file when it is not one."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such elevation map file")
        try:
            with np.load(path, allow_pickle=False) as archive:
                elevation_map = cls.empty(float(archive["resolution"]), archive["origin"], archive["size"])
                for name in archive["layer_names"]:
                    elevation_map[str(name)] = archive[f"layer_{name}"]
        except (KeyError, OSError, EOFError, ValueError, TypeError, zipfile.BadZipFile) as error:
            raise ValueError(f"{path}: not a terracube elevation map: {error}") from error
        return elevation_map

    def to_png(self, name: str, path: str | Path, *, title: str | None = None, cmap: str = "viridis") -> Path:
        """Render one layer as a PNG picture (x right, y up, NaN white)."""
        from .viz import plot_layer

        return plot_layer(self, name, path, title=title, cmap=cmap)

    def to_geotiff(self, name: str, path: str | Path, *, crs: str | None = None) -> Path:
        """Write one layer as a deflate-compressed GeoTIFF (needs the ``geo`` extra: rasterio).

        See :func:`terracube.io.write_geotiff`: float layers are float32 with nodata NaN, the
        ``class`` layer uint8 with its category names; ``crs`` (WKT or ``EPSG:code``) georeferences it.
        """
        from .io import write_geotiff

        return write_geotiff(self, name, path, crs=crs)

    def __repr__(self) -> str:
        g = self.geometry
        return (
            f"ElevationMap({g.size[0]}x{g.size[1]} cells at {g.resolution} m, origin=({g.origin[0]:.2f}, "
            f"{g.origin[1]:.2f}), layers={self.layers})"
        )


def _two_numbers(values):
    """`values` when it is a tuple or list of two Python or numpy real scalars, else None."""
    if isinstance(values, (tuple, list)) and len(values) == 2:
        if all(isinstance(v, (int, float, np.integer, np.floating)) for v in values):
            return values
    return None


def _fixed_extent(origin, size) -> tuple[float, float, int, int]:
    """(x0, y0, nx, ny) of a fixed map extent: two finite coordinates [m] and two whole cell counts
    in [1, 2**31). Tuples and lists of scalars (the usual case) are checked in plain Python, in
    about a microsecond; anything else goes through numpy."""
    pair = _two_numbers(origin)
    if pair is not None:
        x0, y0 = float(pair[0]), float(pair[1])
        origin_ok = math.isfinite(x0) and math.isfinite(y0)
    else:
        array = np.asarray(origin, dtype=np.float64)
        origin_ok = array.shape == (2,) and bool(np.all(np.isfinite(array)))
        x0, y0 = (float(array[0]), float(array[1])) if origin_ok else (0.0, 0.0)
    if not origin_ok:
        raise ValueError(f"origin must be two finite coordinates [m], got {origin!r}")
    pair = _two_numbers(size)
    if pair is not None:
        counts = [float(v) for v in pair]
        size_ok = all(1 <= c < 2**31 and c == round(c) for c in counts)
    else:
        array = np.asarray(size)
        size_ok = (
            array.shape == (2,)
            and not np.any(array < 1)
            and not np.any(array >= 2**31)
            and not np.any(array != np.round(array))
        )
        counts = [float(v) for v in array] if size_ok else []
    if not size_ok:
        raise ValueError(f"size must be two positive whole cell counts, got {size!r}")
    return x0, y0, int(counts[0]), int(counts[1])


@dataclass
class ElevationParams:
    """Parameters of :func:`build_elevation_map`, mirroring ``terracube::ElevationParams``.

    Attributes
    ----------
    resolution : float
        Cell edge [m].
    origin, size : (2,) or None
        Fixed extent: lower-left corner of cell (0, 0) [m] and cells along x, y. Both or neither;
        neither means the points' bounding box snapped outwards to the resolution.
    discontinuity : float
        A gap between sorted elevations longer than this [m] sets the discontinuity flag (1 m).
    transform, crop, drop_non_finite
        As in :class:`terracube.CollapseParams`.
    max_cells : int
        Memory guard on the number of cells.
    num_threads : int
        Threads: 1 runs on the calling thread alone (the default), 0 uses one per processor
        (oneTBB, in an arena made for this call). The work is cut into parts by its size alone, so
        the map is the same bit for bit whatever the number, in forked children
        (``multiprocessing`` "fork" workers) too.
    """

    resolution: float = 0.1
    origin: Sequence[float] | None = None
    size: Sequence[int] | None = None
    discontinuity: float = 1.0
    transform: np.ndarray | None = None
    crop: Sequence[Sequence[float]] | None = None
    drop_non_finite: bool = False
    max_cells: int = 1 << 26
    num_threads: int = 1

    def to_core(self) -> _core.ElevationParams:
        params = _checked(_core.ElevationParams)()
        params.resolution_m = float(self.resolution)
        if (self.origin is None) != (self.size is None):
            raise ValueError("give both origin and size for a fixed map extent, or neither")
        if self.size is not None:
            params.set_extent(*_fixed_extent(self.origin, self.size))
        params.discontinuity_m = float(self.discontinuity)
        _set_frame(params, self.transform, self.crop)
        params.drop_non_finite = bool(self.drop_non_finite)
        params.max_cells = int(self.max_cells)
        params.num_threads = _num_threads(self.num_threads)
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params


def build_elevation_map(
    points,
    resolution: float = 0.1,
    *,
    use=None,
    params: ElevationParams | None = None,
    out: ElevationMap | None = None,
    **kwargs,
):
    """Per-cell layers from a cloud in O(N): count, min, max, mean (the DEM), std_dev, discontinuity.

    Parameters
    ----------
    points : (N, 3) or wider float32 or float64 array
        x, y, z [m] in the first three columns, any row stride.
    resolution : float
        Cell edge [m]; other options as in :class:`ElevationParams` (``params`` overrides them).
    use : (N,) bool (or whole numbers 0 and 1), optional
        Only these points take part.
    out : ElevationMap, optional
        Refill this map instead of making a new one, and return it: its layers' buffers are
        reused (a loop that refills one map allocates nothing once warm), so arrays taken from
        it earlier stay valid and show the new values. The build's size must be the map's (give
        a fixed ``origin`` and ``size``); layers other than the six (``classify_terrain``'s, say)
        are reset to NaN. ValueError on a size mismatch, leaving the map unchanged.

    Returns
    -------
    ElevationMap
        Layers of shape (nx, ny), float32: ``count`` (points per cell), ``min``, ``max``, ``mean``
        and ``std_dev`` of the heights [m], ``discontinuity`` (1 where sorted heights jump by more
        than ``discontinuity`` [m]); NaN where no point falls.
    """
    if params is None:
        params = ElevationParams(resolution, **kwargs)
    use_flags = _as_use_mask(use)
    if out is not None:
        if not isinstance(out, ElevationMap):
            raise TypeError(f"out must be an ElevationMap, not {type(out).__name__}")
        _core.build_elevation_map_into(
            out._core, _as_points(points, params.resolution, "resolution"), params.to_core(), use_flags
        )
        return out
    return ElevationMap(
        _core.build_elevation_map(
            _as_points(points, params.resolution, "resolution"), params.to_core(), use_flags
        )
    )


def dem_without_overhangs(
    points,
    edge: float = 0.5,
    sigma: int = 2,
    resolution: float = 0.1,
    *,
    collapse: CollapseParams | None = None,
    elevation: ElevationParams | None = None,
    no_returns=None,
) -> tuple[ElevationMap, CollapseResult]:
    """The DEM without overhangs of [CBC] section IV-C, plus ``clearance`` and ``step`` layers.

    Runs :func:`terracube.collapse_overhangs`, then maps the points it kept in the same (leveled,
    cropped) frame.

    Parameters
    ----------
    points : (N, 3) or wider float32/float64 array
        x, y, z [m] in the first three columns.
    edge : float
        Cube edge E [m] (ignored when ``collapse`` is given).
    sigma : int
        σ [cubes] (ignored when ``collapse`` is given).
    resolution : float
        Cell edge [m] (ignored when ``elevation`` is given).
    collapse, elevation : CollapseParams, ElevationParams, optional
        All parameters of each step; the collapse's transform and crop box apply to the map too.
    no_returns : (M, 3) array or None
        The scan's beams that returned nothing, for ``method="shadow_aware"`` (see
        :func:`terracube.collapse_overhangs`).

    Returns
    -------
    (ElevationMap, CollapseResult)
        The map of the kept points with the layers of :func:`build_elevation_map` plus
        ``overhang_min`` (lowest overhang point [m]), ``clearance`` (from the top of the kept points
        to the lowest overhang above them [m], +inf where none) and ``step`` (largest height
        difference of ``max`` to the 8 neighbours [m]); and the overhang mask with its cubes.
    """
    collapse = collapse or CollapseParams(edge, sigma)
    elevation = elevation or ElevationParams(resolution)
    beams = None if no_returns is None else _as_directions(no_returns)
    finest = min((collapse.edge, "cube edge"), (elevation.resolution, "resolution"))
    result = _core.build_overhang_free_map(
        _as_points(points, *finest), collapse.to_core(), elevation.to_core(), beams
    )
    return ElevationMap(result.map), result.collapse


_REFERENCES = {
    "sensor_height": _core.GroundReference.sensor_height,
    "local_ground": _core.GroundReference.local_ground,
}


@dataclass
class TerrainParams:
    """Thresholds of [TC] Table 1 (defaults are the paper's values, section 3.2).

    The rule: a discontinuity gives an overhanging object; otherwise a large spread gives a
    vertical object at any height; a small spread gives ground when low, an obstacle when middle
    and an overhanging object when high; ground beside another known class becomes a horizontal
    edge.

    Attributes
    ----------
    ground_height : float
        "Low" cells have a relative highest elevation below this [m] (0.2).
    std_dev : float
        A "small" spread of elevations is a std-dev below this [m] (0.1).
    robot_height : float
        "High" cells are strictly higher than this [m] (0.7); "middle" lies between, both ends
        included.
    reference : {"sensor_height", "local_ground"}
        What the highest elevation is measured from: the plane ``z = -sensor_height`` of a leveled
        sensor frame (the paper), or the lowest ``min`` elevation within ``local_ground_radius``
        cells (for maps chained over slopes).
    sensor_height : float
        Sensor height above the ground [m] for ``reference="sensor_height"``.
    local_ground_radius : int
        Window half-size [cells] for ``reference="local_ground"``.
    num_threads : int
        Threads, as :class:`ElevationParams`' (1: the calling thread alone; the classes are the same
        whatever the number).
    """

    ground_height: float = 0.2
    std_dev: float = 0.1
    robot_height: float = 0.7
    reference: str = "sensor_height"
    sensor_height: float = 0.0
    local_ground_radius: int = 10
    num_threads: int = 1

    def to_core(self) -> _core.TerrainParams:
        if self.reference not in _REFERENCES:
            raise ValueError(f"reference must be one of {sorted(_REFERENCES)}, got {self.reference!r}")
        params = _checked(_core.TerrainParams)()
        params.ground_height_m = float(self.ground_height)
        params.std_dev_m = float(self.std_dev)
        params.robot_height_m = float(self.robot_height)
        params.reference = _REFERENCES[self.reference]
        params.sensor_height_m = float(self.sensor_height)
        params.local_ground_radius_cells = int(self.local_ground_radius)
        params.num_threads = _num_threads(self.num_threads)
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params


def classify_terrain(
    elevation_map: ElevationMap, params: TerrainParams | None = None, **kwargs
) -> np.ndarray:
    """Classify every cell ([TC] Table 1) and return an (nx, ny) uint8 array of :class:`TerrainClass`.

    Also adds the layers ``class`` (float, NaN for unknown), ``relative_height`` and ``ground``.
    """
    if not isinstance(elevation_map, ElevationMap):
        raise TypeError(
            f"classify_terrain needs an ElevationMap (build_elevation_map's result), "
            f"not {type(elevation_map).__name__}"
        )
    if params is None:
        params = TerrainParams(**kwargs)
    missing = [name for name in ("max", "min", "std_dev", "discontinuity") if name not in elevation_map]
    if missing:
        have = ", ".join(elevation_map.layers)
        raise KeyError(f"classify_terrain needs the layers {', '.join(missing)}; the map has {have}")
    return _core.classify_terrain(elevation_map._core, params.to_core())
