"""Pictures of overhang removal (matplotlib, imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_overhangs"]


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as error:  # pragma: no cover - matplotlib is a core dependency
        raise ImportError("pictures need matplotlib: pip install matplotlib") from error
    return plt


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
    index = np.arange(points.shape[0])
    if index.size > max_points:
        index = np.sort(np.random.default_rng(seed).choice(index, max_points, replace=False))
    xyz = points[index, :3].astype(np.float64)
    removed = overhang[index]
    kept = ~removed

    fig, (top, side) = plt.subplots(
        1, 2, figsize=(14, 6.5), gridspec_kw={"width_ratios": [1.0, 1.4]}, constrained_layout=True
    )
    low, high = np.percentile(xyz[kept, 2], [2, 98]) if kept.any() else (0.0, 1.0)
    scatter = dict(s=0.6, linewidths=0, rasterized=True)
    top.scatter(xyz[kept, 0], xyz[kept, 1], c=xyz[kept, 2], cmap="viridis", vmin=low, vmax=high, **scatter)
    top.scatter(xyz[removed, 0], xyz[removed, 1], c="red", s=1.5, linewidths=0, rasterized=True)
    top.set_aspect("equal")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("top view")
    side.scatter(xyz[kept, 0], xyz[kept, 2], c=xyz[kept, 2], cmap="viridis", vmin=low, vmax=high, **scatter)
    side.scatter(xyz[removed, 0], xyz[removed, 2], c="red", s=1.5, linewidths=0, rasterized=True)
    side.set_xlabel("x [m]")
    side.set_ylabel("z [m]")
    side.set_title("side view (vertical exaggeration)")
    handles = [
        plt.Line2D(
            [],
            [],
            marker="o",
            ls="",
            color=plt.get_cmap("viridis")(0.6),
            label=f"retained ({int((~overhang).sum()):,})",
        ),
        plt.Line2D(
            [], [], marker="o", ls="", color="red", label=f"overhang, removed ({int(overhang.sum()):,})"
        ),
    ]
    side.legend(handles=handles, loc="upper right", markerscale=1.5)
    n_all = points.shape[0]
    fig.suptitle(title or f"collapsible cubes: {int(overhang.sum()):,} of {n_all:,} points are overhang")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
