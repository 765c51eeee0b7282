"""Benchmark fitting the fuzzy elevation map (FEM): ANFIS hybrid learning vs least squares only.

What is measured
----------------
``terracube.fit_fuzzy_elevation_map`` with the paper's model size -- 19 x 10 zero-order rules with
triangular membership functions over a 20 x 10 m area, 190 consequents + 29 centres = 219
parameters (Reina et al., IEEE AIM 2014) -- in three scenes:

* ``kitti window``: KITTI seq 00 frame 0, the points collapsible cubes kept (edge 0.5 m, sigma 5)
  inside x in [0, 20], y in [-5, 5] m in front of the car;
* ``kitti whole scan``: every kept point of the same scan (about 120k), the grid grown in
  proportion to the scan's extent (the paper's rule density: 19 rules per 20 m along x, 10 per
  10 m along y);
* ``synthetic 124k``: 124,000 noisy samples (sigma 5 cm) of a smooth known surface on 20 x 10 m,
  the KITTI point count on the paper's area; its RMSE against the true height is reported too.

Each scene is fitted twice: ``hybrid`` (10 epochs of gradient steps on the centres alternating
with the least-squares consequents, the default) and ``LS only`` (epochs = 0: least squares on
uniform centres). Times are ``time.perf_counter`` wall-clock in milliseconds: one warm-up fit, then
the median of ``--repeat`` fits, single-threaded. "train RMSE" is the RMSE of the fitted surface
at the training points; "truth RMSE" (synthetic only) against the noise-free height on a grid.
Nothing is asserted; the ratio hybrid / LS-only is printed.

Reproduce
---------
    PYTHONPATH=python python bench/bench_fuzzy.py              # a few seconds
    PYTHONPATH=python python bench/bench_fuzzy.py --repeat 3   # quicker

The data directory is ``--data-dir``, else ``$TERRACUBE_DATA_DIR``, else ``<repo>/../shared/data``,
else ``/work/shared/data``; without the KITTI file only the synthetic scene runs (and says so).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import terracube as tc
from _common import core_build

PAPER_RULES = (19, 10)
PAPER_AREA_M = (20.0, 10.0)
WINDOW = ((0.0, -5.0), (20.0, 5.0))
COLLAPSE_EDGE = 0.5
COLLAPSE_SIGMA = 5
SYNTHETIC_POINTS = 124_000
SYNTHETIC_NOISE_M = 0.05
SEED = 0


def height(x, y):
    """The synthetic terrain [m]: gentle waves and a slope."""
    return 0.3 * np.sin(0.4 * x) + 0.2 * np.cos(0.6 * y) + 0.02 * x


def find_data_dir(explicit: str | None) -> Path | None:
    candidates = [explicit, os.environ.get("TERRACUBE_DATA_DIR")]
    candidates += [Path(__file__).resolve().parents[2] / "shared" / "data", "/work/shared/data"]
    for candidate in candidates:
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


def machine_info() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"{cpu}, {os.cpu_count()} logical CPUs; Python {platform.python_version()}, numpy {np.__version__}, "
        f"terracube {tc.__version__}"
    )


def median_ms(call, repeat: int) -> tuple[float, object]:
    result = call()  # warm-up
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        result = call()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), result


def scenes(data_dir: Path | None):
    """(name, points, use, FuzzyParams, truth function or None)."""
    rng = np.random.default_rng(SEED)
    xy = rng.uniform((0, 0), PAPER_AREA_M, (SYNTHETIC_POINTS, 2))
    synthetic = np.c_[xy, height(xy[:, 0], xy[:, 1]) + rng.normal(0, SYNTHETIC_NOISE_M, len(xy))]
    paper = tc.FuzzyParams(*PAPER_RULES, extent=((0.0, 0.0), PAPER_AREA_M))
    found = []
    path = None if data_dir is None else data_dir / "kitti_seq00/velodyne/000000.bin"
    if path is not None and path.is_file():
        xyz = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3]
        _, collapse = tc.dem_without_overhangs(xyz, COLLAPSE_EDGE, COLLAPSE_SIGMA)
        kept = ~np.asarray(collapse.overhang)
        found.append(("kitti window", xyz, kept, tc.FuzzyParams(*PAPER_RULES, extent=WINDOW), None))
        lo = xyz[kept, :2].min(axis=0)
        hi = xyz[kept, :2].max(axis=0)
        rules = [max(2, round(PAPER_RULES[a] * (hi[a] - lo[a]) / PAPER_AREA_M[a])) for a in range(2)]
        found.append(("kitti whole scan", xyz, kept, tc.FuzzyParams(*rules), None))
    else:
        print(f"KITTI frame not found ({path}); running the synthetic scene only")
    found.append(("synthetic 124k", synthetic, None, paper, height))
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed fits per case (median)")
    parser.add_argument("--data-dir", default=None)
    args = parser.parse_args()
    print(f"machine: {machine_info()}")
    print(f"core: {core_build()}")
    print(
        f"{'scene':<18} {'points':>8} {'rules':>9} {'params':>6} {'fit':>8} {'time [ms]':>10} "
        f"{'train RMSE':>11} {'truth RMSE':>11}"
    )
    for name, points, use, params, truth in scenes(find_data_dir(args.data_dir)):
        times = {}
        for label, epochs in (("LS only", 0), ("hybrid", params.epochs)):
            case = tc.FuzzyParams(**{**params.__dict__, "epochs": epochs})
            ms, model = median_ms(
                lambda case=case, points=points, use=use: tc.fit_fuzzy_elevation_map(points, case, use=use),
                args.repeat,
            )
            times[label] = ms
            truth_rmse = ""
            if truth is not None:
                gx, gy = np.meshgrid(
                    np.linspace(0.05, 19.95, 200), np.linspace(0.05, 9.95, 100), indexing="ij"
                )
                grid = np.c_[gx.ravel(), gy.ravel()]
                error = model.evaluate(grid) - truth(grid[:, 0], grid[:, 1])
                truth_rmse = f"{np.sqrt(np.mean(error**2)):.4f} m"
            rules = f"{len(model.centers_x)}x{len(model.centers_y)}"
            print(
                f"{name:<18} {model.num_training_points:>8,} {rules:>9} {model.num_parameters:>6} {label:>8} "
                f"{ms:>10.1f} {model.rmse_history[-1]:>9.4f} m {truth_rmse:>11}"
            )
        print(f"{'':<18} hybrid / LS-only time: {times['hybrid'] / times['LS only']:.1f}x")


if __name__ == "__main__":
    main()
