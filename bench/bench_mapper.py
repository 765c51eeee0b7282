"""Benchmark the Mapper: scans per second for the whole pipeline, the time split, and accuracy.

What is measured
----------------
- KITTI-size scans: KITTI odometry seq 00 frames 0-5 (~124k points each, real) with the ground
  truth (T_wv = inv(Tr) P Tr) as odometry, fed to a new Mapper ``--repeat`` times. Two settings:
  every scan a keyframe (``keyframe_distance = 0.01`` m: the whole pipeline -- leveling, map layers,
  classes, weighted ICP, fusion -- on every scan, the worst case) and the paper's ~3 m keyframes.
  Scans per second = scans / wall time of the add_scan calls (scans already in memory).
  Baseline side by side: PCL's ICP (``pcl::IterativeClosestPoint``, SVD) on the same consecutive
  local-map point sets, odometry as the guess, against the mapper's own registration step. Then
  without odometry: the distance the six frames span by the LiDAR-only Mapper and by KISS-ICP.
- A synthetic loop (``terracube.simulation``): an HDL-64-like rotating LiDAR (64 channels,
  2048 steps, ~KITTI-size scans) driving one lap of the loop scene (tunnel, bridge, ramp, trees,
  buildings), a scan every metre, odometry with drift (yaw bias and random walk, 1 % scale error).
  Scans are cast before timing. Three runs: odometry chaining only, chaining by weighted ICP, and
  chaining plus loop closing (Ceres). Reported: scans per second, the time split, and the keyframe
  ATE (first pose aligned) and RPE against the ground truth.
- The same scans without odometry: the LiDAR-only Mapper (every scan registered to its newest
  keyframe; the pose it reports for each scan) beside KISS-ICP (``pip install kiss-icp``; skipped
  when absent), a LiDAR odometry: time per scan, ATE and RPE of every scan's pose.

Targets (reported, not asserted): at least 20 scans per second on one core for KITTI-size scans.

Reproduce
---------
    python bench/bench_mapper.py              # full run, about two minutes
    python bench/bench_mapper.py --quick      # fewer repeats, a shorter synthetic run
    python bench/bench_mapper.py --markdown   # also print Markdown tables
"""

from __future__ import annotations

import sys
import time

import numpy as np
import terracube as tc
from _common import (
    load_xyzi_bin,
    markdown_row,
    parse_benchmark_args,
    print_header,
    print_target,
    require,
)
from terracube import simulation as sim
from terracube.mapping import Mapper, MapperParams


def kitti_world_velo(data_dir) -> np.ndarray:
    """KITTI seq 00 ground truth as Velodyne poses, inv(Tr) P Tr (the library's pose-file reader)."""
    from terracube.mapping import read_kitti_calibration, read_pose_file

    folder = data_dir / "kitti_seq00"
    return read_pose_file(folder / "poses.txt", "kitti", read_kitti_calibration(folder / "calib.txt"))[1]


def run(scans, poses, params: MapperParams) -> tuple[Mapper, float]:
    """Feeds every scan (then applies pending loops); returns the mapper and the wall time [s]."""
    mapper = Mapper(params)
    start = time.perf_counter()
    for points, pose in zip(scans, poses, strict=True):
        mapper.add_scan(points, pose)
    if mapper.pending_loops:
        mapper.optimize()
    return mapper, time.perf_counter() - start


def split(mapper: Mapper) -> str:
    t = mapper.timings
    k = max(t.keyframes, 1)
    return (
        f"per keyframe: map {t.map_building_ms / k:.1f}, classes {t.classification_ms / k:.1f}, "
        f"ICP {t.registration_ms / k:.1f}, fusion {t.fusion_ms / k:.1f}, loops {t.loop_closing_ms / k:.1f} ms"
    )


def kitti_part(args, rows) -> list[float]:
    frames = [
        load_xyzi_bin(args.data_dir / "kitti_seq00" / "velodyne" / f"{k:06d}.bin")[:, :3] for k in range(6)
    ]
    truth = kitti_world_velo(args.data_dir)[:6]
    print(f"\nKITTI seq 00 frames 0-5 ({np.mean([len(f) for f in frames]):.0f} points per scan, real)")
    rates = []
    for label, distance in (("every scan a keyframe", 0.01), ("keyframes every 3 m", 3.0)):
        params = MapperParams(keyframe_distance=distance, loop_closing=False)
        run(frames, truth, params)  # warm-up
        timed = [run(frames, truth, params) for _ in range(args.repeat)]
        seconds = sorted(s for _, s in timed)[len(timed) // 2]
        mapper = timed[0][0]
        rate = len(frames) / seconds
        if distance < 1:
            rates.append(rate)
        print(
            f"  {label:24s}: {rate:6.1f} scans/s ({1e3 * seconds / len(frames):.1f} ms per scan, "
            f"{len(mapper)} keyframes); {split(mapper)}"
        )
        rows.append(["KITTI 0-5", label, f"{rate:.1f}", f"{1e3 * seconds / len(frames):.1f}", split(mapper)])

    # Registration side by side with PCL's ICP on the same consecutive local maps.
    params = MapperParams(keyframe_distance=0.01, loop_closing=False, keep_local_maps=True)
    mapper, _ = run(frames, truth, params)
    if tc.has_pcl():
        ours, pcl = [], []
        for k in range(1, len(frames)):
            source, target = (tc.points_of_map(mapper.local_map(i)) for i in (k, k - 1))
            guess = np.linalg.inv(mapper.keyframe_odometry()[k - 1]) @ mapper.keyframe_odometry()[k]
            start = time.perf_counter()
            tc.registration._core.register_points(
                source[0], source[1], target[0], target[1], guess, params.registration.to_core()
            )
            ours.append(time.perf_counter() - start)
            start = time.perf_counter()
            tc.pcl_icp(source[0], target[0], guess)
            pcl.append(time.perf_counter() - start)
        o, p = 1e3 * np.median(ours), 1e3 * np.median(pcl)
        print(
            f"  registration step (median of {len(ours)}): weighted ICP {o:.1f} ms, PCL ICP {p:.1f} ms "
            f"-> PCL / terracube = {p / o:.1f}x"
        )
    kitti_lidar_only(args, frames, truth)
    return rates


def kitti_lidar_only(args, frames: list[np.ndarray], truth: np.ndarray) -> None:
    """The distance frames 0-5 span without odometry: the LiDAR-only Mapper against KISS-ICP and the
    ground truth (KITTI's scans and truth disagree by about 0.17 m a frame: bench_icp.py --scan-floor)."""
    from bench_icp import kiss_icp_steps

    mapper = Mapper(MapperParams(lidar_only=True, loop_closing=False, min_range=3.0))
    poses = [mapper.add_scan(points, np.eye(4)).pose for points in frames]
    ours = np.linalg.norm((np.linalg.inv(poses[0]) @ poses[-1])[:3, 3])
    line = f"  LiDAR-only, frames 0-5 span: mapper {ours:.3f} m"
    kiss = kiss_icp_steps(args.data_dir)
    if kiss is not None:
        line += f", KISS-ICP {np.linalg.norm(kiss['KITTI 0->5'][:3, 3]):.3f} m"
    true = np.linalg.norm((np.linalg.inv(truth[0]) @ truth[-1])[:3, 3])
    print(line + f", ground truth {true:.3f} m")


def simulated_loop() -> sim.SyntheticSequence:
    """One lap of the loop scene with an HDL-64-like LiDAR, a scan every metre, drifting odometry."""
    lidar = sim.RotatingLidar(
        channels=64, steps_per_revolution=2048, vertical_fov_min=-24.8, vertical_fov_max=2.0, max_range=80.0
    )
    trajectory = sim.TrajectoryParams(
        scan_spacing=1.0,
        mount_height=1.73,
        yaw_bias=1e-3,
        yaw_random_walk=1e-3,
        translation_scale_error=0.01,
        seed=7,
    )
    return sim.generate_sequence(sim.LoopSceneParams(), trajectory, lidar, seed=3)


def synthetic_part(args, rows) -> list[float]:
    sequence = simulated_loop()
    count = len(sequence) if not args.quick else min(len(sequence), 120)
    start = time.perf_counter()
    scans = [sequence.scan(k).points for k in range(count)]
    cast = time.perf_counter() - start
    truth, odometry = sequence.poses[:count], sequence.odometry[:count]
    print(
        f"\nSynthetic loop: {count} scans 1 m apart, {np.mean([len(s) for s in scans]):.0f} points per scan "
        f"(64 x 2048 rays; cast in {cast:.1f} s, not timed)"
    )
    rates = []
    for label, params in (
        ("odometry chaining", MapperParams(use_registration=False, loop_closing=False)),
        ("weighted ICP chaining", MapperParams(loop_closing=False)),
        ("ICP + loop closing", MapperParams()),
    ):
        mapper, seconds = run(scans, odometry, params)
        keys = mapper.keyframe_scan_indices()
        ate = tc.absolute_trajectory_error(mapper.keyframe_poses(), truth[keys], "first_pose").translation
        odo = tc.absolute_trajectory_error(mapper.keyframe_odometry(), truth[keys], "first_pose").translation
        rpe = tc.relative_pose_error(mapper.keyframe_poses(), truth[keys], lengths=[20.0, 50.0])
        rate = count / seconds
        rates.append(rate)
        print(
            f"  {label:22s}: {rate:6.1f} scans/s, {len(mapper)} keyframes, "
            f"{len(mapper.loop_closures)} loops, "
            f"ATE {ate.rmse:.2f} m (odometry {odo.rmse:.2f} m), RPE {rpe.translation_percent:.2f} % "
            f"{rpe.rotation_deg_per_100m:.2f} deg/100 m; {split(mapper)}"
        )
        rows.append(
            [
                "synthetic loop",
                label,
                f"{rate:.1f}",
                f"{1e3 * seconds / count:.1f}",
                f"ATE {ate.rmse:.2f} m (odometry {odo.rmse:.2f} m)",
            ]
        )
    lidar_only_part(scans, truth, rows)
    return rates


def kiss_icp_poses(scans: list[np.ndarray], max_range: float) -> tuple[np.ndarray, float] | None:
    """KISS-ICP (Vizzo et al. 2023, ``pip install kiss-icp``) over the scans: its pose of each and the
    time [s]; None when it is not installed. Its defaults but the range (its voxel rule: range / 100)
    and no de-skewing (the simulated scans are instantaneous)."""
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        return None
    config = KISSConfig()
    config.data.max_range, config.data.deskew = max_range, False
    config.mapping.voxel_size = config.data.max_range / 100.0
    odometry = KissICP(config)
    poses = []
    start = time.perf_counter()
    for points in scans:
        odometry.register_frame(points.astype(np.float64), np.zeros(len(points)))
        poses.append(np.array(odometry.last_pose))
    return np.asarray(poses), time.perf_counter() - start


def lidar_only_part(scans: list[np.ndarray], truth: np.ndarray, rows) -> None:
    """Without odometry: the LiDAR-only Mapper (every scan registered to its newest keyframe, the
    poses it reports per scan) beside KISS-ICP, a LiDAR odometry, on the same scans."""
    mapper = Mapper(MapperParams(lidar_only=True, loop_closing=False))
    start = time.perf_counter()
    poses = np.array([mapper.add_scan(points, np.eye(4)).pose for points in scans])
    runs = {"LiDAR-only mapper": (poses, time.perf_counter() - start)}
    kiss = kiss_icp_poses(scans, 80.0)
    if kiss is None:
        print("  KISS-ICP: not installed (pip install kiss-icp for the side-by-side LiDAR-only row)")
    else:
        runs["KISS-ICP"] = kiss
    for label, (poses, seconds) in runs.items():
        ate = tc.absolute_trajectory_error(poses, truth, "first_pose").translation
        rpe = tc.relative_pose_error(poses, truth, lengths=[20.0, 50.0])
        height = np.abs((poses[:, 2, 3] - poses[0, 2, 3]) - (truth[:, 2, 3] - truth[0, 2, 3])).max()
        ms = 1e3 * seconds / len(scans)
        print(
            f"  {label:26s}: {ms:6.1f} ms per scan, every scan's pose: ATE {ate.rmse:.2f} m, RPE "
            f"{rpe.translation_percent:.2f} % {rpe.rotation_deg_per_100m:.2f} deg/100 m, height error "
            f"up to {height:.2f} m"
        )
        rows.append(
            ["synthetic loop", label, f"{1e3 / ms:.1f}", f"{ms:.1f}", f"ATE {ate.rmse:.2f} m (no odometry)"]
        )


def main(argv: list[str] | None = None) -> int:
    args = parse_benchmark_args(
        __doc__.splitlines()[0], argv, repeat_unit="setting", quick_help="3 repeats, 120 synthetic scans"
    )
    require((args.data_dir / "kitti_seq00").is_dir(), f"no KITTI frames under {args.data_dir}")
    print_header(
        "terracube Mapper benchmark",
        ["  pipeline: leveling, layers, classes, weighted ICP, fusion (+ loops), 0.1 m cells, 40 m maps"],
        "PCL ICP time / terracube weighted ICP time on the same local maps",
        args,
        "fewer repeats, shorter synthetic run",
    )
    rows: list[list[str]] = []
    kitti = kitti_part(args, rows)
    synthetic = synthetic_part(args, rows)
    print()
    print_target(
        "KITTI-size scans per second, every scan a keyframe (target >= 20)",
        kitti,
        lambda v: v >= 20,
        " scans/s",
    )
    print_target(
        "synthetic KITTI-size scans per second (target >= 20)", synthetic, lambda v: v >= 20, " scans/s"
    )
    if args.markdown:
        print()
        print(markdown_row(["data", "setting", "scans/s", "ms/scan", "notes"]))
        print("|---|---|---:|---:|---|")
        for row in rows:
            print(markdown_row(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
