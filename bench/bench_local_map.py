"""Benchmark one LocalMap update against build_elevation_map of the same scan over the same area.

What is measured
----------------
KITTI seq 00 frames 0-5 (float32 strided views of x, y, z, intensity rows, about 124,000 points
each) at their poses (``poses.txt`` turned into Velodyne poses with ``calib.txt``). A
``terracube.LocalMap`` of 20 x 20 m at 0.1 m (200 x 200 cells, the defaults) is first fed frames
0-4, then every timed call fuses frame 5 again (the steady state of a robot's loop: the map full,
the same amount of work every call). Timed side by side, in turn, on one thread:

- ``build_elevation_map``: the six layers of frame 5, moved by its pose, over the same 200 x 200
  cells (the baseline the issue names: one scan, no fusion, no overhang removal);
- ``LocalMap.update``: overhang removal ([CBC], edge 0.5 m, sigma 2), the see-through test, the
  Kalman fusion and the planner layers (step, slope, roughness, traversability over 7 x 7 windows);
- the same update without the planner layers (``compute_planner_layers=False``), and without the
  see-through test too, to show where the time goes;
- ``update_planner_layers`` alone: the step, slope, roughness and traversability of the fused map,
  the stage the first two rows differ by;
- ``dem_without_overhangs`` over the same area (collapse, then the map), for information.

Before timing, the fused map of frames 0-5 is checked against ``build_elevation_map``: of the cells
frame 5 alone has below 0.5 m, the fused map holds more than 99.5 % (all but a few of one point on a
cell border, which the two bin by different roundings).

Ratios are *LocalMap time / build_elevation_map time* (lower is better); the target is at most 2x,
reported as MET / NOT MET, never asserted.

Reproduce
---------
    python bench/bench_local_map.py             # a few seconds
    python bench/bench_local_map.py --quick     # every 4th point, 3 repeats
    python bench/bench_local_map.py --markdown  # also print a Markdown table
    bash bench/ab_python.sh BASE - bench/bench_local_map.py --json   # two builds, alternating
"""

from __future__ import annotations

import json
import sys

import numpy as np
import terracube as tc
from _common import (
    QUICK_STRIDE,
    describe_points,
    interleaved_median_ms,
    load_xyzi_bin,
    markdown_row,
    markdown_rule,
    parse_benchmark_args,
    print_header,
    print_target,
    require,
)

FRAMES = [f"{k:06d}.bin" for k in range(6)]


def main(argv: list[str] | None = None) -> int:
    args = parse_benchmark_args(
        __doc__.splitlines()[0],
        argv,
        repeat_unit="method",
        quick_help=f"every {QUICK_STRIDE}th point, 3 repeats",
        add_arguments=lambda parser: parser.add_argument(
            "--json", action="store_true", help="also print the medians [ms] as one JSON object, last"
        ),
    )
    folder = args.data_dir / "kitti_seq00" / "velodyne"
    paths = [folder / name for name in FRAMES]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        print(f"skipped: {missing[0]} is missing")
        return 0
    scans = [load_xyzi_bin(p) for p in paths]
    if args.quick:
        scans = [s[::QUICK_STRIDE] for s in scans]
    print_header(
        "LocalMap update vs build_elevation_map (KITTI 00, 20 x 20 m at 0.1 m)",
        [describe_points(scans[-1])],
        "LocalMap / build_elevation_map (lower is better)",
        args,
        f"every {QUICK_STRIDE}th point",
    )
    from terracube.mapping import read_kitti_calibration, read_pose_file

    kitti = args.data_dir / "kitti_seq00"
    poses = read_pose_file(kitti / "poses.txt", "kitti", read_kitti_calibration(kitti / "calib.txt"))[1]
    pose = poses[5]

    def local_map(**changes) -> tc.LocalMap:
        m = tc.LocalMap(length=20.0, resolution=0.1, **changes)
        for scan, scan_pose in zip(scans[:-1], poses[:5], strict=True):
            m.update(scan, scan_pose)
        return m

    full = local_map()
    no_planner = local_map(compute_planner_layers=False)
    fusion_only = local_map(compute_planner_layers=False, clear_seen_through=False)
    last = scans[-1]
    full.update(last, pose)
    origin, size = tuple(full.geometry.origin), (200, 200)

    def single_map():
        return tc.build_elevation_map(last, 0.1, origin=origin, size=size, transform=pose)

    single = single_map()
    fused = full.to_elevation_map()["elevation"]
    # Cells are floor((x - origin) / res) there and floor(x / res) - origin / res here: a point on a
    # cell border may fall on either side, so a few cells of one point can differ.
    low = np.isfinite(single["mean"]) & (single["max"] < 0.5)
    kept = np.count_nonzero(low & np.isfinite(fused)) / max(np.count_nonzero(low), 1)
    print(f"  low cells of frame 5 alone that the fused map holds: {100 * kept:.2f} %")
    require(kept > 0.995, "low cells of the last scan are missing from the fused map")
    times = interleaved_median_ms(
        {
            "build_elevation_map": single_map,
            "LocalMap.update": lambda: full.update(last, pose),
            "update, no planner layers": lambda: no_planner.update(last, pose),
            "update, fusion only": lambda: fusion_only.update(last, pose),
            "update_planner_layers": full.update_planner_layers,
            "dem_without_overhangs": lambda: tc.dem_without_overhangs(
                last,
                collapse=tc.CollapseParams(transform=pose),
                elevation=tc.ElevationParams(0.1, origin=origin, size=size),
            ),
        },
        args.repeat,
        run=3,
    )
    base = times["build_elevation_map"]
    print(f"  {'step':<28} {'ms':>8} {'/ baseline':>11}")
    for name, ms in times.items():
        print(f"  {name:<28} {ms:8.2f} {ms / base:10.2f}x")
    print_target(
        "LocalMap.update <= 2x build_elevation_map",
        [times["LocalMap.update"] / base],
        lambda r: r <= 2.0,
        "x",
    )
    if args.markdown:
        print()
        print(markdown_row(["step", "ms", "/ build_elevation_map"]))
        print(markdown_rule(2))
        for name, ms in times.items():
            print(markdown_row([name, f"{ms:.2f}", f"{ms / base:.2f}×"]))
    if args.json:
        print(json.dumps(times))
    return 0


if __name__ == "__main__":
    sys.exit(main())
