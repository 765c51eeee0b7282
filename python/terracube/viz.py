"""Pictures of overhang removal, elevation-map layers and terrain classes (matplotlib, imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .io import atomic_path

__all__ = ["plot_overhangs", "plot_reasons", "plot_layer", "plot_dem_comparison", "plot_terrain_classes"]


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as error:
        raise ImportError("pictures need the plot extra: pip install 'terracube[plot]'") from error
    return plt


def _drawn_rows(rows: np.ndarray, max_points: int, seed: int) -> np.ndarray:
    """At most ``max_points`` of ``rows`` (a seeded random subset, in order): quick pictures."""
    if rows.size > max_points:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_points, replace=False))
    return rows


def _cloud_views(plt):
    """A figure with a labelled top view and side view of a cloud: (fig, top, side)."""
    fig, (top, side) = plt.subplots(
        1, 2, figsize=(14, 6.5), gridspec_kw={"width_ratios": [1.0, 1.4]}, constrained_layout=True
    )
    top.set_aspect("equal")
    top.set(xlabel="x [m]", ylabel="y [m]", title="top view")
    side.set(xlabel="x [m]", ylabel="z [m]", title="side view (vertical exaggeration)")
    return fig, top, side


def _save_cloud_views(plt, fig, path: str | Path, handles: list, title: str) -> Path:
    """The legend, the title, then the PNG written atomically; the figure is closed."""
    fig.axes[1].legend(handles=handles, loc="upper right", markerscale=1.5)
    fig.suptitle(title)
    path = Path(path)
    try:
        with atomic_path(path) as temporary:
            fig.savefig(temporary, dpi=110)
    finally:
        plt.close(fig)
    return path


def _marker(plt, color, label: str):
    return plt.Line2D([], [], marker="o", ls="", color=color, label=label)


def plot_overhangs(
    points: np.ndarray,
    overhang: np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    max_points: int = 150_000,
    seed: int = 0,
) -> Path:
    """Save a PNG of a cloud coloured retained (by height) / removed (red): top and side views.

    Parameters
    ----------
    points : (N, 3) array
        x, y, z [m], in the frame the overhangs were computed in.
    overhang : (N,) bool
        The mask from :func:`terracube.collapse_overhangs` (or a baseline).
    path : str or Path
        Output PNG file.
    max_points : int
        At most this many points are drawn (a seeded random subset), to keep the file quick to make.
    """
    plt = _pyplot()
    points = np.asarray(points)
    overhang = np.asarray(overhang, dtype=bool)
    if points.ndim != 2 or points.shape[1] < 3 or overhang.shape != (points.shape[0],):
        raise ValueError("plot_overhangs needs (N, 3) points and an (N,) mask")
    index = _drawn_rows(np.arange(points.shape[0]), max_points, seed)
    xyz = points[index, :3].astype(np.float64)
    removed = overhang[index]
    kept = ~removed

    fig, top, side = _cloud_views(plt)
    low, high = np.percentile(xyz[kept, 2], [2, 98]) if kept.any() else (0.0, 1.0)
    scatter = dict(s=0.6, linewidths=0, rasterized=True)
    top.scatter(xyz[kept, 0], xyz[kept, 1], c=xyz[kept, 2], cmap="viridis", vmin=low, vmax=high, **scatter)
    top.scatter(xyz[removed, 0], xyz[removed, 1], c="red", s=1.5, linewidths=0, rasterized=True)
    side.scatter(xyz[kept, 0], xyz[kept, 2], c=xyz[kept, 2], cmap="viridis", vmin=low, vmax=high, **scatter)
    side.scatter(xyz[removed, 0], xyz[removed, 2], c="red", s=1.5, linewidths=0, rasterized=True)
    handles = [
        _marker(plt, plt.get_cmap("viridis")(0.6), f"retained ({int((~overhang).sum()):,})"),
        _marker(plt, "red", f"overhang, removed ({int(overhang.sum()):,})"),
    ]
    n_all = points.shape[0]
    default = f"collapsible cubes: {int(overhang.sum()):,} of {n_all:,} points are overhang"
    return _save_cloud_views(plt, fig, path, handles, title or default)


#: Colours of the shadow-aware rule's reasons (CubeReason names), in drawing order: kept ones in
#: greys and blues, then the removed ones in red and orange, on top.
REASON_COLORS = {
    "supported": "#c7c7c7",
    "below_ground": "#8c564b",
    "no_ground_estimate": "#9467bd",
    "shadowed": "#1f77b4",
    "thin": "#17becf",
    "removed_above_kept": "#ff7f0e",
    "removed_free_below": "#d62728",
    "removed_rim": "#e377c2",
}


def plot_reasons(
    points: np.ndarray,
    reasons: np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    max_points: int = 150_000,
    seed: int = 0,
) -> Path:
    """Save a PNG of a cloud coloured by why the shadow-aware rule kept or removed each point
    (:func:`terracube.point_reasons`): top and side views, a legend with the count of each reason.
    Points that took no part are not drawn.

    Parameters
    ----------
    points : (N, 3) array
        x, y, z [m], in the frame the overhangs were computed in (leveled).
    reasons : (N,) uint8
        :data:`terracube.CubeReason` per point.
    path, title, max_points, seed
        As :func:`plot_overhangs`.
    """
    from .collapse import CubeReason

    plt = _pyplot()
    points = np.asarray(points)
    reasons = np.asarray(reasons)
    if points.ndim != 2 or points.shape[1] < 3 or reasons.shape != (points.shape[0],):
        raise ValueError("plot_reasons needs (N, 3) points and (N,) reasons")
    index = _drawn_rows(np.flatnonzero(reasons != int(CubeReason.not_used)), max_points, seed)
    xyz = points[index, :3].astype(np.float64)
    drawn = reasons[index]
    fig, top, side = _cloud_views(plt)
    handles = []
    for name, color in REASON_COLORS.items():
        code = int(CubeReason.__members__[name])
        mine = drawn == code
        size = 0.6 if name == "supported" else 1.5
        top.scatter(xyz[mine, 0], xyz[mine, 1], c=color, s=size, linewidths=0, rasterized=True)
        side.scatter(xyz[mine, 0], xyz[mine, 2], c=color, s=size, linewidths=0, rasterized=True)
        handles.append(_marker(plt, color, f"{name} ({int((reasons == code).sum()):,})"))
    return _save_cloud_views(
        plt, fig, path, handles, title or "shadow_aware: why each point was kept or removed"
    )


# --------------------------------------------------------------------------------------------
# Elevation-map layers
# --------------------------------------------------------------------------------------------

#: Colour-bar labels of the layers the library writes; other layers are taken to be in metres.
_LAYER_LABELS = {
    "count": "points per cell",
    "min": "lowest elevation z [m]",
    "max": "highest elevation z [m]",
    "mean": "mean elevation z [m]",
    "std_dev": "std-dev of elevations [m]",
    "discontinuity": "vertical gap in the cell (1) or not (0)",
    "overhang_min": "lowest overhang point z [m]",
    "clearance": "clearance under the lowest overhang [m]",
    "step": "height step to the neighbours (planner layers: in the footprint) [m]",
    "relative_height": "height above the ground reference [m]",
    "ground": "ground reference z [m]",
    "elevation": "fused elevation z [m]",
    "variance": "variance of the elevation [m²]",
    "time": "time of the last measurement [s]",
    "slope": "slope of the footprint's plane [rad]",
    "roughness": "roughness about the footprint's plane [m]",
    "traversability": "traversability (0 blocked .. 1 open ground)",
    "fem": "fuzzy elevation z [m]",
    "fem_confidence": "rule support of the fuzzy elevation [points]",
}

_CLASS_NAMES = {
    0: "unknown (no data)",
    1: "ground",
    2: "obstacle",
    3: "overhanging object",
    4: "vertical object",
    5: "horizontal edge",
}

_INFINITE_COLOR = (0.82, 0.82, 0.82)


def _extent(geometry, drawn: tuple[int, int] | None = None, k: int = 1) -> tuple[float, float, float, float]:
    """(left, right, bottom, top) of the map [m], for imshow(..., origin="lower"); of a ``drawn``
    array of k x k blocks (see _block_factor) when given."""
    x0, y0 = (float(v) for v in geometry.origin)
    nx, ny = drawn if drawn is not None else (int(v) for v in geometry.size)
    return (x0, x0 + nx * k * geometry.resolution, y0, y0 + ny * k * geometry.resolution)


#: A map more cells wide than this (about a panel's pixels) is drawn in square blocks of cells:
#: resampled cell by cell, most of a sparse map's cells would fall between the pixels, and drawing
#: millions of cells takes seconds.
_DRAWN_CELLS = 1200


def _block_factor(geometry) -> int:
    """k: a map is drawn in k x k blocks of cells (1: cell by cell)."""
    return max(1, -(-max(int(v) for v in geometry.size) // _DRAWN_CELLS))


def _blocks(values: np.ndarray, k: int, fill) -> np.ndarray:
    """(ceil(nx / k), ceil(ny / k), k * k): the cells of each k x k block of an (nx, ny) array, the
    blocks at the far edges padded with ``fill``."""
    nx, ny = values.shape
    bx, by = -(-nx // k), -(-ny // k)
    padded = np.full((bx * k, by * k), fill, dtype=values.dtype)
    padded[:nx, :ny] = values
    return padded.reshape(bx, k, by, k).swapaxes(1, 2).reshape(bx, by, k * k)


#: Layers whose low values are the ones a planner must not miss (a low overhang, a blocked cell):
#: their blocks show the smallest value. Every other layer's blocks show the largest (the highest
#: point, the steepest slope, the biggest step).
_LOW_IS_NOTABLE = frozenset({"clearance", "traversability"})


def _drawn_values(values: np.ndarray, k: int, lowest: bool = False) -> np.ndarray:
    """A layer as drawn in k x k blocks: each block's largest finite value (smallest with
    ``lowest``), else +-inf when it holds an infinite one (+inf first; -inf first with ``lowest``),
    else NaN (empty)."""
    if k == 1:
        return values
    if lowest:
        return -_drawn_values(-values, k)
    blocks = _blocks(values.astype(np.result_type(values.dtype, np.float32), copy=False), k, np.nan)
    finite = np.isfinite(blocks)
    largest = np.where(finite, blocks, -np.inf).max(axis=2)
    infinite = np.where(
        (blocks == np.inf).any(axis=2), np.inf, np.where((blocks == -np.inf).any(axis=2), -np.inf, np.nan)
    )
    return np.where(finite.any(axis=2), largest, infinite)


def _require_cells(geometry) -> None:
    if int(geometry.size[0]) * int(geometry.size[1]) == 0:
        raise ValueError("the map has no cells to draw")


def _map_aspect(geometry) -> float:
    """Width over height of the map."""
    nx, ny = (int(v) for v in geometry.size)
    return max(nx, 1) / max(ny, 1)


def _panel_size(geometry, width: float) -> tuple[float, float]:
    """(width, height) in inches of a panel showing the map at ``width`` inches, clamped."""
    height = width / _map_aspect(geometry)
    return width, float(np.clip(height, 2.5, 1.6 * width))


def _colour_limits(values: np.ndarray, name: str) -> tuple[float, float]:
    """Robust limits of the finite values: the 1st and 99th percentiles (0..1 for flags)."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    if name == "discontinuity":
        return 0.0, 1.0
    if name == "count":
        return 1.0, float(max(np.percentile(finite, 99), 2.0))
    low, high = (float(v) for v in np.percentile(finite, [1, 99]))
    if high <= low:
        low, high = low - 0.5, high + 0.5
    return low, high


def _extend(values: np.ndarray, vmin: float, vmax: float) -> str:
    finite = values[np.isfinite(values)]
    below = bool(finite.size and finite.min() < vmin)
    above = bool(finite.size and finite.max() > vmax)
    return {(False, False): "neither", (True, False): "min", (False, True): "max"}.get((below, above), "both")


def _style_axes(ax, geometry) -> None:
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.set_facecolor("white")
    left, right, bottom, top = _extent(geometry)
    ax.set_xlim(left, right)
    ax.set_ylim(bottom, top)
    ax.ticklabel_format(useOffset=False, style="plain")  # projected coordinates read as written


#: How notable each TerrainClass (by value) is when a block of cells shows one class: obstacles,
#: overhanging and vertical objects first, then edges, ground and unknown.
_CLASS_RANK = np.array([0, 1, 4, 3, 4, 2], dtype=np.int16)


def _drawn_classes(classes: np.ndarray, k: int) -> np.ndarray:
    """Classes as drawn in k x k blocks: each block's most notable class (_CLASS_RANK; the first
    such cell in the block on a tie)."""
    if k == 1:
        return classes
    blocks = _blocks(classes, k, 0)
    notable = _CLASS_RANK[np.clip(blocks, 0, len(_CLASS_RANK) - 1)].argmax(axis=2)  # other codes: as edges
    return np.take_along_axis(blocks, notable[..., None], axis=2)[..., 0]


def _draw_layer(ax, values: np.ndarray, geometry, cmap_name: str, vmin: float, vmax: float, name: str = ""):
    """imshow of an (nx, ny) layer ``name``, x right and y up; NaN transparent, +-inf in light grey.
    A map wider than _DRAWN_CELLS is drawn in blocks (_drawn_values, _LOW_IS_NOTABLE)."""
    plt = _pyplot()
    cmap = plt.get_cmap(cmap_name).with_extremes(bad=(1.0, 1.0, 1.0, 0.0))
    k = _block_factor(geometry)
    values = _drawn_values(values, k, lowest=name in _LOW_IS_NOTABLE)
    extent = _extent(geometry, values.shape, k)
    finite = np.where(np.isfinite(values), values, np.nan)
    image = ax.imshow(
        finite.T, origin="lower", extent=extent, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest"
    )
    infinite = np.isinf(values)
    if infinite.any():
        overlay = np.zeros((*values.T.shape, 4))
        overlay[infinite.T] = (*_INFINITE_COLOR, 1.0)
        ax.imshow(overlay, origin="lower", extent=extent, interpolation="nearest")
    return image


def _layout() -> dict:
    """Matplotlib >= 3.6 packs fixed-aspect map panels tightly with the "compressed" layout."""
    import matplotlib

    major, minor = (int(part) for part in matplotlib.__version__.split(".")[:2])
    return {"layout": "compressed"} if (major, minor) >= (3, 6) else {"constrained_layout": True}


def _save(fig, path: str | Path, dpi: int = 130) -> Path:
    plt = _pyplot()
    path = Path(path)
    try:
        with atomic_path(path) as temporary:
            fig.savefig(temporary, dpi=dpi, facecolor="white", bbox_inches="tight", pad_inches=0.15)
    finally:
        plt.close(fig)
    return path


def _infinite_legend(ax, values: np.ndarray, name: str) -> None:
    plt = _pyplot()
    count = int(np.isinf(values).sum())
    if not count:
        return
    label = "no overhang above" if name == "clearance" else "infinite"
    patch = plt.Rectangle((0, 0), 1, 1, facecolor=_INFINITE_COLOR, edgecolor="0.4", linewidth=0.5)
    ax.legend([patch], [f"{label} ({count:,} cells)"], loc="upper right", fontsize="small", framealpha=0.9)


def _draw_trajectory(ax, trajectory: np.ndarray | None) -> None:
    """The robot's path over a map: a black-edged white line and a dot at the start."""
    if trajectory is None:
        return
    xy = np.asarray(trajectory, dtype=np.float64).reshape(-1, 2)
    if len(xy) == 0:
        return
    limits = ax.get_xlim(), ax.get_ylim()
    ax.plot(xy[:, 0], xy[:, 1], color="black", linewidth=3.0, zorder=5)
    ax.plot(xy[:, 0], xy[:, 1], color="white", linewidth=1.5, zorder=6, label="trajectory")
    ax.plot(xy[0, 0], xy[0, 1], "o", color="white", markeredgecolor="black", markersize=6, zorder=7)
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])


def plot_layer(
    elevation_map,
    name: str,
    path: str | Path,
    *,
    title: str | None = None,
    cmap: str = "viridis",
    vmin: float | None = None,
    vmax: float | None = None,
    trajectory: np.ndarray | None = None,
) -> Path:
    """Save a PNG of one layer of an :class:`terracube.ElevationMap`, x to the right and y up.

    ``trajectory`` ((S, 2) x, y [m] in the map's frame, e.g. ``terracube map``'s scan poses) is drawn
    over the map as a line from a start dot.

    Empty cells (NaN) stay white, infinite values (``clearance`` where no overhang lies above) are
    light grey; the colour scale runs between the 1st and 99th percentiles of the finite values
    unless ``vmin``/``vmax`` are given. A map more than 1200 cells wide is drawn in square blocks of
    cells, each showing its largest value (its smallest for ``clearance`` and ``traversability``,
    where low values are the ones that block a robot), so that no cell with data disappears. The
    ``class`` layer is drawn with :func:`plot_terrain_classes`. Returns the path.
    """
    values = np.asarray(elevation_map[name])
    geometry = elevation_map.geometry
    _require_cells(geometry)
    if name == "class":
        classes = np.nan_to_num(values, nan=0.0).astype(np.uint8)
        return plot_terrain_classes(elevation_map, classes, path, title=title, trajectory=trajectory)
    if name == "count":  # empty cells hold 0, not NaN: show them as empty too
        values = np.where(values > 0, values, np.nan)
    plt = _pyplot()
    low, high = _colour_limits(values, name)
    low = low if vmin is None else float(vmin)
    high = high if vmax is None else float(vmax)
    width, height = _panel_size(geometry, 9.0)
    fig, ax = plt.subplots(figsize=(width + 1.6, height + 1.0), **_layout())
    image = _draw_layer(ax, values, geometry, cmap, low, high, name)
    _style_axes(ax, geometry)
    bar = fig.colorbar(image, ax=ax, extend=_extend(values, low, high), shrink=0.9, pad=0.02)
    bar.set_label(_LAYER_LABELS.get(name, f"{name} [m]"))
    _infinite_legend(ax, values, name)
    _draw_trajectory(ax, trajectory)
    known = int(np.count_nonzero(~np.isnan(values)))
    g = geometry
    ax.set_title(
        title or f"{name}: {known:,} of {g.size[0] * g.size[1]:,} cells with data ({g.resolution:g} m cells)"
    )
    return _save(fig, path)


def plot_dem_comparison(
    raw_map,
    clean_map,
    path: str | Path,
    *,
    layer: str = "max",
    title: str | None = None,
) -> Path:
    """Save a PNG of a DEM before and after overhang removal, on one shared colour scale.

    ``raw_map`` is built from every point (:func:`terracube.build_elevation_map`), ``clean_map``
    from the points collapsible cubes kept (:func:`terracube.dem_without_overhangs`); both need
    the same geometry. The panels sit side by side, or one above the other for wide maps.
    """
    plt = _pyplot()
    g = raw_map.geometry
    h = clean_map.geometry
    if (
        tuple(g.size) != tuple(h.size)
        or not np.allclose(g.origin, h.origin)
        or not np.isclose(g.resolution, h.resolution)
    ):
        raise ValueError(f"the maps differ in geometry: {g!r} vs {h!r}; build both on the same extent")
    _require_cells(g)
    before = np.asarray(raw_map[layer])
    after = np.asarray(clean_map[layer])
    low, high = _colour_limits(np.concatenate([before.ravel(), after.ravel()]), layer)
    stacked = _map_aspect(g) >= 1.3
    width, height = _panel_size(g, 9.5 if stacked else 6.5)
    if stacked:
        fig, axes = plt.subplots(2, 1, figsize=(width + 1.8, 2 * height + 1.4), **_layout())
    else:
        fig, axes = plt.subplots(1, 2, figsize=(2 * width + 1.2, height + 1.2), **_layout())
    both = np.isfinite(before) & np.isfinite(after)
    lower = both & (after < before - 1e-6)
    emptied = np.isfinite(before) & ~np.isfinite(after)
    panels = (
        (axes[0], before, f"before: every point ({int(np.isfinite(before).sum()):,} cells with data)"),
        (
            axes[1],
            after,
            f"after overhang removal ({int(lower.sum()):,} cells lower, {int(emptied.sum()):,} emptied)",
        ),
    )
    for ax, values, label in panels:
        image = _draw_layer(ax, values, g, "viridis", low, high, layer)
        _style_axes(ax, g)
        ax.set_title(label, fontsize="medium")
    changed = lower | emptied
    if changed.any():
        # Outline the cells (or blocks, as drawn) overhang removal changed, in the "before" panel.
        k = _block_factor(g)
        drawn = _blocks(changed, k, False).any(axis=2) if k > 1 else changed
        padded = np.pad(drawn, 1).astype(float)
        left, right, bottom, top = _extent(g, drawn.shape, k)
        step = k * g.resolution
        xs = np.linspace(left - step / 2, right + step / 2, padded.shape[0])
        ys = np.linspace(bottom - step / 2, top + step / 2, padded.shape[1])
        axes[0].contour(xs, ys, padded.T, levels=[0.5], colors="red", linewidths=0.9)
        axes[0].legend(
            [plt.Line2D([], [], color="red", linewidth=1.2)],
            [f"changed by overhang removal ({int(changed.sum()):,} cells)"],
            loc="upper right",
            fontsize="small",
            framealpha=0.9,
        )
    extend = _extend(np.concatenate([before.ravel(), after.ravel()]), low, high)
    bar = fig.colorbar(image, ax=list(axes), extend=extend, shrink=0.8, aspect=30, pad=0.015)
    bar.set_label(_LAYER_LABELS.get(layer, f"{layer} [m]"))
    fig.suptitle(title or f"DEM ({layer} layer) before and after overhang removal")
    return _save(fig, path)


def plot_terrain_classes(
    elevation_map,
    classes: np.ndarray,
    path: str | Path,
    *,
    title: str | None = None,
    trajectory: np.ndarray | None = None,
) -> Path:
    """Save a PNG of an (nx, ny) class map (:func:`terracube.classify_terrain`), x right and y up,
    in :data:`terracube.TERRAIN_COLORS`, with a legend naming every class and its cell count, and
    ``trajectory`` ((S, 2) x, y [m]) over it as :func:`plot_layer` draws it."""
    from .classes import TERRAIN_COLORS, TerrainClass

    plt = _pyplot()
    from matplotlib.colors import BoundaryNorm, ListedColormap

    geometry = elevation_map.geometry
    _require_cells(geometry)
    classes = np.asarray(classes)
    size = tuple(int(v) for v in geometry.size)
    if classes.shape != size:
        raise ValueError(f"classes have shape {classes.shape}, the map is {size}")
    order = list(TerrainClass)
    cmap = ListedColormap([TERRAIN_COLORS[c] for c in order])
    norm = BoundaryNorm(np.arange(len(order) + 1) - 0.5, len(order))
    wide = _map_aspect(geometry) >= 1.3
    width, height = _panel_size(geometry, 9.5 if wide else 7.0)
    if wide:
        figsize = (width + 0.8, height + 2.0)
    else:
        figsize = (width + 3.2, height + 1.0)
    fig, ax = plt.subplots(figsize=figsize, **_layout())
    k = _block_factor(geometry)
    drawn = _drawn_classes(classes.astype(np.int16), k)
    ax.imshow(
        drawn.T,
        origin="lower",
        extent=_extent(geometry, drawn.shape, k),
        cmap=cmap,
        norm=norm,
        interpolation="nearest",
    )
    _style_axes(ax, geometry)
    _draw_trajectory(ax, trajectory)
    counts = np.bincount(classes.ravel(), minlength=len(order))
    handles = [
        plt.Rectangle((0, 0), 1, 1, facecolor=TERRAIN_COLORS[c], edgecolor="0.3", linewidth=0.6)
        for c in order
    ]
    labels = [f"{_CLASS_NAMES.get(int(c), c.name.lower())} ({counts[int(c)]:,})" for c in order]
    if wide:
        ax.legend(
            handles,
            labels,
            loc="upper center",
            bbox_to_anchor=(0.5, -0.13),
            ncol=3,
            frameon=False,
            title="class (cells)",
        )
    else:
        ax.legend(
            handles,
            labels,
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
            frameon=False,
            title="class (cells)",
        )
    known = int(classes.size - counts[0])
    ax.set_title(title or f"terrain classes of {known:,} cells with data ({geometry.resolution:g} m cells)")
    return _save(fig, path)
