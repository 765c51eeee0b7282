"""Basin of convergence of the registration, side by side with small_gicp's GICP (issue 38).

What is measured
----------------
Per pair, 14 starts: the ground truth moved by 1 m along +x, -x, +y, -y (4 "1 m" starts), the
same four each turned by +10 and -10 degrees of yaw about the source sensor (8 "1 m + 10 deg"
starts) and the truth turned by +-10 degrees alone (2 "10 deg" starts). A start *converges* when
its answer lies within 0.1 m and 0.5 deg of the same method's answer started from the truth.

Methods:

- ``terracube``: ``terracube.register_maps`` with its defaults (correlative yaw x translation
  search on the classified maps, then the class-weighted ICP);
- ``terracube ICP alone``: the defaults with ``correlative_search=False`` (the defaults before
  issue 38: extrapolation and coarse-to-fine, no search);
- ``terracube paper ICP``: ``RegistrationParams.paper_icp()``: the paper's plain weighted ICP from
  the start alone (no search, no extrapolation, no coarse-to-fine);
- ``small_gicp GICP``: ``small_gicp.align(..., registration_type="GICP")`` on the raw scans,
  0.25 m voxel downsampling, 1 m correspondence distance, single thread (its defaults otherwise).

Pairs: KITTI odometry seq 00 frames 0->1, 1->2, 2->3, 3->4, 4->5 and 0->5, 60 x 40 m maps at
0.1 m centred on the sensor (as bench_icp.py builds them); simulated pairs from terracube's
ray-casting simulator (64-beam LiDAR 1.73 m above the road of the loop scene, keyframes 3 m apart
with the heading turned by up to 20 deg between them, as [TC] Fig. 10), every 10th keyframe with
the next.

Timing (end to end, single thread, median of ``--repeat`` after one warm-up, from the truth moved
by 1 m + 10 deg): terracube = two elevation maps built and classified from the raw scans plus the
registration; small_gicp = ``align`` on the raw scans (its downsampling, covariances, k-d trees
and registration). Ratio = small_gicp ms / terracube ms (> 1: terracube faster). Run on a shared,
loaded 2-vCPU VM: compare ratios, not absolute times.

Reproduce
---------
    python bench/bench_basin.py             # KITTI + simulated pairs
    python bench/bench_basin.py --quick     # KITTI only, 3 timing runs
    python bench/bench_basin.py --markdown  # also a Markdown table
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import terracube as tc
from _common import (
    interleaved_median_ms,
    load_xyzi_bin,
    markdown_row,
    markdown_rule,
    parse_benchmark_args,
    print_header,
)

RESOLUTION = 0.1
SENSOR_HEIGHT = 1.73
EXTENT = ((-30.0, -20.0), (60.0, 40.0))  # origin, length [m]
KITTI_PAIRS = ((0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5))
OFFSET_M = 1.0
YAW_DEG = 10.0
SAME_M = 0.1
SAME_DEG = 0.5
GROUPS = ("1 m", "1 m + 10 deg", "10 deg")


def rotation_z(yaw_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    t = np.eye(4)
    t[:2, :2] = ((c, -s), (s, c))
    return t


def translation(x: float, y: float) -> np.ndarray:
    t = np.eye(4)
    t[:2, 3] = (x, y)
    return t


def starts(truth: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The 14 (group, initial guess) starts of one pair."""
    moves = [translation(*d) for d in ((OFFSET_M, 0), (-OFFSET_M, 0), (0, OFFSET_M), (0, -OFFSET_M))]
    out = [("1 m", m @ truth) for m in moves]
    out += [("1 m + 10 deg", m @ truth @ rotation_z(s * YAW_DEG)) for m in moves for s in (1, -1)]
    out += [("10 deg", truth @ rotation_z(s * YAW_DEG)) for s in (1, -1)]
    return out


def same(a: np.ndarray, b: np.ndarray) -> bool:
    delta = a[:3, :3].T @ b[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(delta) - 1.0) / 2.0, -1.0, 1.0)))
    return bool(np.linalg.norm(a[:3, 3] - b[:3, 3]) <= SAME_M and angle <= SAME_DEG)


def classified_map(points: np.ndarray) -> tc.ElevationMap:
    (ox, oy), (lx, ly) = EXTENT
    size = (round(lx / RESOLUTION), round(ly / RESOLUTION))
    elevation_map = tc.build_elevation_map(points, RESOLUTION, origin=(ox, oy), size=size)
    tc.classify_terrain(elevation_map, sensor_height=SENSOR_HEIGHT)
    return elevation_map


@dataclass
class Pair:
    name: str
    source_points: np.ndarray  # (N, 3) float64, sensor frame
    target_points: np.ndarray
    truth: np.ndarray  # target <- source
    source: tc.ElevationMap | None = None
    target: tc.ElevationMap | None = None

    def build(self) -> None:
        self.source = classified_map(self.source_points)
        self.target = classified_map(self.target_points)


def kitti_pairs(data_dir: Path) -> list[Pair]:
    root = data_dir / "kitti_seq00"
    calib = {}
    for line in (root / "calib.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        calib[key.strip()] = np.array(values.split(), dtype=float)
    tr = np.vstack([calib["Tr"].reshape(3, 4), [0, 0, 0, 1]])
    poses = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    world = [np.linalg.inv(tr) @ np.vstack([p, [0, 0, 0, 1]]) @ tr for p in poses[:6]]
    scans = {
        f: np.ascontiguousarray(load_xyzi_bin(root / "velodyne" / f"{f:06d}.bin"), dtype=np.float64)
        for f in range(6)
    }
    return [
        Pair(f"KITTI {s}->{t}", scans[s], scans[t], np.linalg.inv(world[t]) @ world[s])
        for s, t in KITTI_PAIRS
    ]


def simulated_pairs(every: int = 10) -> list[Pair]:
    """Keyframes 3 m apart along the simulator's loop, every `every`-th with the next, each pair's
    source turned by 20 deg about its sensor (the paper's Fig. 10 steps: 3 m and 20 deg)."""
    sequence = tc.simulation.generate_sequence(
        trajectory=tc.simulation.TrajectoryParams.exact(scan_spacing=3.0, mount_height=SENSOR_HEIGHT)
    )
    pairs = []
    turn = rotation_z(20.0)
    for k in range(0, len(sequence) - 1, every):
        # The source scan seen from a sensor turned by 20 deg: points p -> turn^-1 p.
        source = sequence.scan(k).points @ turn[:3, :3]
        truth = np.linalg.inv(sequence.poses[k + 1]) @ sequence.poses[k] @ turn
        pairs.append(
            Pair(f"sim {k}->{k + 1}", np.ascontiguousarray(source), sequence.scan(k + 1).points, truth)
        )
    return pairs


# --------------------------------------------------------------------------------------------
# Methods: (pair, guess) -> transform target <- source
# --------------------------------------------------------------------------------------------


def terracube_method(params: tc.RegistrationParams | None) -> Callable[[Pair, np.ndarray], np.ndarray]:
    def run(pair: Pair, guess: np.ndarray) -> np.ndarray:
        return tc.register_maps(pair.source, pair.target, guess, params).transform

    return run


def small_gicp_align(pair: Pair, guess: np.ndarray):
    import small_gicp

    return small_gicp.align(
        pair.target_points,
        pair.source_points,
        guess,
        registration_type="GICP",
        downsampling_resolution=0.25,
        max_correspondence_distance=1.0,
        num_threads=1,
    ).T_target_source


def methods() -> dict[str, Callable[[Pair, np.ndarray], np.ndarray]]:
    out = {
        "terracube": terracube_method(None),
        "terracube ICP alone": terracube_method(tc.RegistrationParams(correlative_search=False)),
        "terracube paper ICP": terracube_method(tc.RegistrationParams.paper_icp()),
    }
    try:
        import small_gicp  # noqa: F401

        out["small_gicp GICP"] = small_gicp_align
    except ImportError:
        print("  (small_gicp not installed: pip install small_gicp for the side-by-side rows)")
    return out


def basin(pairs: list[Pair], method: Callable[[Pair, np.ndarray], np.ndarray]) -> dict[str, tuple[int, int]]:
    """group -> (converged starts, starts)."""
    counts = {g: [0, 0] for g in GROUPS}
    for pair in pairs:
        reference = method(pair, pair.truth)
        for group, guess in starts(pair.truth):
            counts[group][0] += same(method(pair, guess), reference)
            counts[group][1] += 1
    return {g: (c[0], c[1]) for g, c in counts.items()}


def end_to_end(pairs: list[Pair], repeat: int) -> dict[str, float]:
    """Median ms per pair of each method from raw scans, summed over the pairs."""
    totals: dict[str, float] = {}
    for pair in pairs:
        guess = translation(OFFSET_M, 0) @ pair.truth @ rotation_z(YAW_DEG)

        def terracube_once(p=pair, g=guess):
            source, target = classified_map(p.source_points), classified_map(p.target_points)
            return tc.register_maps(source, target, g).transform

        calls = {"terracube": terracube_once}
        if "small_gicp GICP" in METHODS:
            calls["small_gicp GICP"] = lambda p=pair, g=guess: small_gicp_align(p, g)
        for name, ms in interleaved_median_ms(calls, repeat).items():
            totals[name] = totals.get(name, 0.0) + ms
    return totals


METHODS: dict[str, Callable[[Pair, np.ndarray], np.ndarray]] = {}


def main(argv: list[str] | None = None) -> int:
    args = parse_benchmark_args(
        __doc__.splitlines()[0],
        argv,
        repeat_unit="pair",
        quick_help="KITTI pairs only",
        default_repeat=(5, 3),
    )
    METHODS.update(methods())
    print_header(
        "bench_basin: basin of convergence and end-to-end time vs small_gicp GICP",
        [
            "  starts  : 14 per pair (1 m x4, 1 m + 10 deg x8, 10 deg x2);"
            f" same = within {SAME_M} m, {SAME_DEG} deg"
        ],
        "small_gicp ms / terracube ms (end to end from raw scans)",
        args,
        "KITTI pairs only",
    )
    sets = {"KITTI 00": kitti_pairs(args.data_dir)}
    if not args.quick:
        sets["simulated 3 m / 20 deg"] = simulated_pairs()
    rows = []
    for set_name, pairs in sets.items():
        for pair in pairs:
            pair.build()
        for name, method in METHODS.items():
            counts = basin(pairs, method)
            rows.append((set_name, name, counts))
            cells = "  ".join(f"{g}: {c}/{n}" for g, (c, n) in counts.items())
            print(f"  {set_name:<24} {name:<22} {cells}", flush=True)
    timing = end_to_end(sets["KITTI 00"], args.repeat)
    print("  end to end over the KITTI pairs (sum of per-pair medians):")
    for name, ms in timing.items():
        print(f"    {name:<22} {ms:8.1f} ms")
    if "small_gicp GICP" in timing:
        print(f"  ratio small_gicp GICP / terracube: {timing['small_gicp GICP'] / timing['terracube']:.1f}x")
    if args.markdown:
        print()
        print(markdown_row(["pairs", "method", *(f"{g} (/n)" for g in GROUPS)]))
        print(markdown_rule(4))
        for set_name, name, counts in rows:
            print(markdown_row([set_name, name, *(f"{c}/{n}" for c, n in counts.values())]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
