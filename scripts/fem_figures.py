"""Pictures of the fuzzy elevation map (FEM) beside the DEM, before and after overhang removal.

As Figs. 7-10 of Reina et al. (IEEE AIM 2014): for a real scan, the DEM ("mean" layer) and the FEM
(19 x 10 rules per 20 x 10 m, hybrid learning) from every point and from the points collapsible
cubes kept, on one colour scale; plus a synthetic scene with a known height function where the
FEM's noise filtering and hole filling can be measured. Writes docs/images/fem_*.png.

    PYTHONPATH=python python scripts/fem_figures.py [--data-dir DIR] [--out docs/images]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import terracube as tc

REPO = Path(__file__).resolve().parents[1]


def find_data_dir(explicit: str | None) -> Path:
    for candidate in (
        explicit,
        os.environ.get("TERRACUBE_DATA_DIR"),
        REPO.parent / "shared/data",
        "/work/shared/data",
    ):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    raise SystemExit("real data folder not found; pass --data-dir")


def four_panels(path, title, extent_m, panels, label="elevation [m]"):
    """A 2 x 2 figure: rows before/after overhang removal, columns DEM/FEM, one colour scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = np.concatenate([np.ravel(p[1]) for p in panels])
    low, high = np.nanpercentile(values, [1, 99])
    (x0, y0), (x1, y1) = extent_m
    aspect = (x1 - x0) / (y1 - y0)
    fig, axes = plt.subplots(
        2, 2, figsize=(2 * 4.2 * min(aspect, 1.6) + 1.5, 2 * 4.2 + 0.8), layout="compressed"
    )
    cmap = plt.get_cmap("viridis").with_extremes(bad="white")
    for ax, (name, layer) in zip(axes.ravel(), panels, strict=True):
        image = ax.imshow(
            np.asarray(layer).T,
            origin="lower",
            extent=(x0, x1, y0, y1),
            cmap=cmap,
            vmin=low,
            vmax=high,
            interpolation="nearest",
        )
        ax.set_title(name, fontsize="medium")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_facecolor("white")
    fig.colorbar(image, ax=list(axes.ravel()), shrink=0.8, label=label)
    fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90, facecolor="white", bbox_inches="tight")
    plt.close(fig)
    print(f"wrote {path} ({path.stat().st_size / 1024:.0f} KB)")


def real_scene(path, title, xyz, window, resolution, rules, edge, sigma):
    origin = window[0]
    size = [round((window[1][a] - window[0][a]) / resolution) for a in range(2)]
    elevation = tc.ElevationParams(resolution, origin=origin, size=size)
    raw = tc.build_elevation_map(xyz, params=elevation)
    clean, collapse = tc.dem_without_overhangs(
        xyz, collapse=tc.CollapseParams(edge, sigma), elevation=elevation
    )
    kept = ~np.asarray(collapse.overhang)
    params = tc.FuzzyParams(*rules, extent=window)
    fem_raw = tc.FuzzyElevationMap.fit(xyz, params)
    fem_clean = tc.FuzzyElevationMap.fit(xyz, params, use=kept)
    fem_raw.to_layer(raw)
    fem_clean.to_layer(clean)

    def cells(layer):
        return int(np.isfinite(layer).sum())

    holes = np.isnan(clean["mean"])
    filled = int(np.isfinite(clean["fem"][holes]).sum())
    panels = [
        (f"DEM, every point ({cells(raw['mean']):,} cells)", raw["mean"]),
        (f"FEM, every point (RMSE {fem_raw.rmse_history[-1]:.3f} m)", raw["fem"]),
        (f"DEM without overhangs ({cells(clean['mean']):,} cells)", clean["mean"]),
        (f"FEM without overhangs ({filled:,} of {int(holes.sum()):,} empty cells filled)", clean["fem"]),
    ]
    four_panels(path, title, window, panels)
    return fem_clean


def synthetic_scene(path):
    rng = np.random.default_rng(0)
    xy = rng.uniform((0, 0), (20, 10), (60_000, 2))
    shadowed = np.zeros(len(xy), bool)
    for cx, cy, r in ((5, 5, 0.6), (12, 3, 0.5), (15, 7, 0.7), (8, 2, 0.4)):
        shadowed |= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) < r
    xy = xy[~shadowed]

    def height(x, y):
        return 0.3 * np.sin(0.4 * x) + 0.2 * np.cos(0.6 * y) + 0.02 * x

    points = np.c_[xy, height(xy[:, 0], xy[:, 1]) + rng.normal(0, 0.05, len(xy))]
    dem = tc.build_elevation_map(points, 0.1, origin=(0, 0), size=(200, 100))
    fem = tc.FuzzyElevationMap.fit(points, extent=((0, 0), (20, 10)))
    fem.to_layer(dem)
    x, y = dem.cell_centers()
    truth = height(*np.meshgrid(x, y, indexing="ij"))
    observed = np.isfinite(dem["mean"])
    dem_rmse = np.sqrt(np.mean((dem["mean"] - truth)[observed] ** 2))
    fem_rmse = np.sqrt(np.mean((dem["fem"] - truth)[observed] ** 2))
    filled = np.isfinite(dem["fem"][~observed]).mean()
    panels = [
        ("true height", truth),
        ("FEM error x 10 (+ mean)", 10 * (dem["fem"] - truth) + truth.mean()),
        (f"DEM, 5 cm noise + shadows (RMSE {dem_rmse * 100:.1f} cm)", dem["mean"]),
        (f"FEM 19x10 rules (RMSE {fem_rmse * 100:.2f} cm, {filled:.0%} of holes filled)", dem["fem"]),
    ]
    four_panels(path, "Synthetic terrain: DEM vs FEM against the true height", ((0, 0), (20, 10)), panels)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data-dir")
    parser.add_argument("--out", default=str(REPO / "docs/images"))
    args = parser.parse_args()
    data = find_data_dir(args.data_dir)
    out = Path(args.out)
    synthetic_scene(out / "fem_synthetic.png")
    kitti = np.fromfile(data / "kitti_seq00/velodyne/000000.bin", dtype=np.float32).reshape(-1, 4)[:, :3]
    real_scene(
        out / "fem_kitti.png",
        "KITTI 00/000000, 20 x 10 m beside the road (trees): DEM and FEM before/after overhang removal",
        kitti,
        ((-30.0, 8.0), (-10.0, 18.0)),
        0.1,
        (19, 10),
        0.5,
        2,
    )
    forest = np.load(data / "forest_tls/TreeLS_pine_plot.npz")["xyz"]
    real_scene(
        out / "fem_forest.png",
        "TreeLS pine plot (TLS), 10 x 10 m: DEM and FEM before/after overhang removal",
        forest,
        ((0.0, 0.0), (10.0, 10.0)),
        0.1,
        (10, 10),
        0.5,
        4,
    )


if __name__ == "__main__":
    main()
