"""The per-scan pipeline's stages on one thread, for two builds side by side (issue 33's judgement).

What is measured
----------------
KITTI seq 00 frames 0-5 (float32 x, y, z views of the ``.bin`` rows), one thread, each stage's
median over ``--repeat`` calls after a warm-up, the stages timed in turn:

- ``collapse``: ``collapse_overhangs`` of frame 0 (E = 0.5 m, sigma 2, the paper's rule);
- ``map + classes``: ``build_elevation_map`` of frame 0 into 400 x 200 cells at 0.1 m (origin
  (-20, -10)), then ``classify_terrain`` (sensor height 1.73 m), a fresh map per call;
- ``registration``: ``register_maps`` of the classified 400 x 200 maps of the pairs 0->1 ... 4->5
  from the ground truth (the Velodyne poses of ``poses.txt``), the defaults of the build (the
  correlative search before the ICP where the build has one), the median over the pairs;
- ``registration, ICP alone``: the same without that search (only for builds that have it);
- ``mapper per scan``: a ``Mapper`` (a keyframe every scan, no loop closing) fed frames 0-5 at their
  poses, wall time / 6.

Only the Python API that both the current core and the core before the simplification (revision
80f10ff) have is used, so ``bench/ab_python.sh`` can run this file against any revision since then,
alternating the two builds' processes:

    bash bench/ab_python.sh 80f10ff - bench/bench_stages.py --json

Nothing is asserted; the ratios are read against issue 33's bar (no stage more than 1.5x slower
than the previous main).

Reproduce
---------
    python bench/bench_stages.py              # about 20 s
    python bench/bench_stages.py --json       # the medians as one JSON object
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
import terracube as tc
from _common import default_data_dir, load_xyzi_bin, median_ms
from terracube.mapping import read_kitti_calibration, read_pose_file

RESOLUTION = 0.1
SENSOR_HEIGHT = 1.73
ORIGIN, SIZE = (-20.0, -10.0), (400, 200)
FRAMES = range(6)


def classified_map(points: np.ndarray):
    elevation_map = tc.build_elevation_map(points, RESOLUTION, origin=ORIGIN, size=SIZE)
    tc.classify_terrain(elevation_map, sensor_height=SENSOR_HEIGHT)
    return elevation_map


def measure(data_dir: Path, repeat: int) -> dict[str, float]:
    folder = data_dir / "kitti_seq00"
    scans = [load_xyzi_bin(folder / "velodyne" / f"{k:06d}.bin") for k in FRAMES]
    # KITTI's camera poses as Velodyne poses, inv(Tr) P Tr.
    poses = read_pose_file(folder / "poses.txt", "kitti", read_kitti_calibration(folder / "calib.txt"))[1][
        : len(scans)
    ]
    maps = [classified_map(scan) for scan in scans]
    truths = [np.linalg.inv(poses[k + 1]) @ poses[k] for k in range(len(scans) - 1)]

    def registration(params=None) -> float:
        per_pair = []
        for k, truth in enumerate(truths):
            if params is None:
                per_pair.append(
                    median_ms(lambda k=k, t=truth: tc.register_maps(maps[k], maps[k + 1], t), repeat)
                )
            else:
                per_pair.append(
                    median_ms(lambda k=k, t=truth: tc.register_maps(maps[k], maps[k + 1], t, params), repeat)
                )
        return statistics.median(per_pair)

    def mapper_per_scan() -> None:
        mapper = tc.Mapper(tc.MapperParams(keyframe_distance=0.01, loop_closing=False))
        for scan, pose in zip(scans, poses, strict=True):
            mapper.add_scan(scan, pose)

    times = {
        "collapse": median_ms(lambda: tc.collapse_overhangs(scans[0], 0.5, 2), repeat),
        "map + classes": median_ms(lambda: classified_map(scans[0]), repeat),
        "registration": registration(),
    }
    if "correlative_search" in getattr(tc.RegistrationParams, "__dataclass_fields__", {}):
        times["registration, ICP alone"] = registration(tc.RegistrationParams(correlative_search=False))
    times["mapper per scan"] = median_ms(mapper_per_scan, max(3, repeat // 5)) / len(scans)
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=15, help="calls per stage (default 15)")
    parser.add_argument("--json", action="store_true", help="print the medians [ms] as one JSON object")
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=default_data_dir(),
        help="the shared data folder (default $TERRACUBE_DATA_DIR, else ../shared/data)",
    )
    args = parser.parse_args(argv)
    if not (args.data_dir / "kitti_seq00" / "velodyne" / "000005.bin").is_file():
        print(f"skipped: KITTI 00 frames 0-5 not found under {args.data_dir}")
        return 0
    times = measure(args.data_dir, args.repeat)
    if args.json:
        print(json.dumps(times))
        return 0
    print("Per-scan stages, KITTI 00 frames 0-5, one thread (median ms)")
    for name, ms in times.items():
        print(f"  {name:<26} {ms:8.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
