"""An interactive 3D view of scans and elevation maps with rerun (the optional ``viewer`` extra).

rerun is imported only when a view is asked for; without it the functions raise ImportError with
the command that installs it. ``save=PATH`` writes a recording (``.rrd``, opened later with
``rerun PATH``) instead of spawning the viewer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["require_viewer", "show_cloud", "show_map", "VIEWER_INSTALL_HINT"]

VIEWER_INSTALL_HINT = 'the 3D view needs rerun: pip install "terracube[viewer]"'

_RETAINED = np.array([150, 150, 150], dtype=np.uint8)
_OVERHANG = np.array([230, 30, 30], dtype=np.uint8)


def _rerun():
    """The rerun module, or ImportError naming the extra to install."""
    try:
        import rerun
    except ImportError as error:
        raise ImportError(VIEWER_INSTALL_HINT) from error
    return rerun


def require_viewer() -> None:
    """ImportError naming the ``viewer`` extra when rerun or matplotlib (its colours) is missing; a
    command calls it before it writes anything."""
    _rerun()
    try:
        import matplotlib  # noqa: F401
    except ImportError as error:
        raise ImportError(VIEWER_INSTALL_HINT) from error


def _height_colours(z: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 viridis colours of heights between their 2nd and 98th percentiles."""
    from matplotlib import colormaps

    finite = z[np.isfinite(z)]
    low, high = np.percentile(finite, [2, 98]) if finite.size else (0.0, 1.0)
    scaled = np.clip((z - low) / max(high - low, 1e-9), 0.0, 1.0)
    return (255 * colormaps["viridis"](np.nan_to_num(scaled))[:, :3]).astype(np.uint8)


def _record(rr, name: str, save: str | Path | None, log) -> Path | None:
    """Runs ``log()`` into a spawned viewer, or with ``save`` into a recording written under a
    temporary name and renamed to ``save`` once rerun has flushed it (nothing half-written)."""
    from .io import atomic_path

    rr.init(f"terracube_{name}", spawn=False)
    if save is None:
        rr.spawn()
        log()
        return None
    path = Path(save)
    with atomic_path(path) as temporary:
        rr.save(str(temporary))
        log()
        if hasattr(rr, "disconnect"):
            rr.disconnect()  # flushes and closes the recording file
    return path


def show_cloud(
    points: np.ndarray,
    *,
    overhang: np.ndarray | None = None,
    name: str = "scan",
    save: str | Path | None = None,
    radius: float = 0.03,
) -> Path | None:
    """Log an (N, 3) cloud as ``NAME/points``: overhang points red and the rest grey when an (N,) mask
    is given, else coloured by height. Returns the recording path when ``save`` is given."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {points.shape}")
    rr = _rerun()
    xyz = np.asarray(points[:, :3], dtype=np.float32)
    keep = np.all(np.isfinite(xyz), axis=1)
    if overhang is not None:
        mask = np.asarray(overhang, dtype=bool)
        if mask.shape != (len(xyz),):
            raise ValueError(f"overhang must be an ({len(xyz)},) mask, got shape {mask.shape}")
        colours = np.where(mask[:, None], _OVERHANG, _RETAINED).astype(np.uint8)
    else:
        colours = _height_colours(xyz[:, 2])
    return _record(
        rr,
        name,
        save,
        lambda: rr.log(f"{name}/points", rr.Points3D(xyz[keep], colors=colours[keep], radii=radius)),
    )


def show_map(elevation_map, *, name: str = "map", save: str | Path | None = None) -> Path | None:
    """Log an elevation map as one point per cell with data at (x, y, max), coloured by terrain class
    when the map has a ``class`` layer, else by height. Returns the recording path when ``save`` is given."""
    from .classes import TERRAIN_COLORS, TerrainClass

    rr = _rerun()
    layer = "max" if "max" in elevation_map else elevation_map.layers[0]
    heights = np.asarray(elevation_map[layer], dtype=np.float64)
    x, y = elevation_map.cell_centers()
    gx, gy = np.meshgrid(x, y, indexing="ij")
    known = np.isfinite(heights)
    xyz = np.column_stack([gx[known], gy[known], heights[known]]).astype(np.float32)
    if "class" in elevation_map:
        classes = np.nan_to_num(np.asarray(elevation_map["class"])[known], nan=0.0).astype(np.uint8)
        palette = np.array([TERRAIN_COLORS[c] for c in TerrainClass]) * 255
        colours = palette[np.minimum(classes, len(palette) - 1)].astype(np.uint8)
    else:
        colours = _height_colours(xyz[:, 2])
    radius = 0.4 * elevation_map.resolution
    return _record(
        rr, name, save, lambda: rr.log(f"{name}/cells", rr.Points3D(xyz, colors=colours, radii=radius))
    )
