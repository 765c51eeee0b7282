"""What each of terracube's departures from the papers changes, measured side by side.

Every row of the departures table in docs/algorithms.md is run here twice: with terracube's default
and with the setting that restores the paper, on the same inputs in the same process.

- Weighted ICP ([TC] section 2.2 and eq. (4)) on KITTI seq 00 pairs 0->1 ... 4->5 and 0->5 and on
  simulated pairs with an exact truth (bench_icp.py's inputs: 60 x 40 m maps at 0.1 m, guesses
  the truth moved by up to 0.3 m / 3 deg): median translation error, iterations and time, for the
  default, each departure reverted alone, and all of them reverted ("paper").
- The Mapper ([TC] section 3.3) on the simulated loop with drifting odometry: keyframe ATE for the
  default and with 0.2 m cells, the sensor-height reference and 6-DOF steps.
- The fuzzy elevation map ([CBC] section IV-C) on a 20 x 10 m window of KITTI frame 0 after
  collapse_overhangs: training RMSE, RMSE on held-out points (every 5th) and the share of 0.2 m
  cells the map fills, with terracube's regularised, guarded learning and with plain ANFIS.
- The DEM cell ([CBC] section IV-C: 0.5 m) against terracube's 0.1 m on KITTI frame 0: the mean
  absolute height difference between each kept point and its cell's mean.

Reproduce
---------
    python bench/bench_departures.py            # about two minutes
    python bench/bench_departures.py --quick    # fewer pairs and scans
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np
import terracube as tc
from _common import load_xyzi_bin, parse_benchmark_args, print_header
from bench_icp import (
    KITTI_PAIRS,
    SENSOR_HEIGHT,
    classified_map,
    errors,
    kitti_world_velo,
    perturbation,
)
from bench_mapper import simulated_loop
from terracube import simulation as sim
from terracube.mapping import Mapper, MapperParams

ACCURACY_EXTENT = ((-30.0, -20.0), (60.0, 40.0))  # 60 x 40 m at 0.1 m, centred on the sensor

PAPER_ICP = {
    "pairing": "target_to_source",
    "extrapolate": False,
    "coarse_subsample": 1,
    "max_correspondence_distance": 1e9,
    "correspondence_distance_decay": 1.0,
}
ICP_VARIANTS = {
    "default": {},
    "no extrapolation": {"extrapolate": False},
    "no subsampling": {"coarse_subsample": 1},
    "no distance limit": {"max_correspondence_distance": 1e9, "correspondence_distance_decay": 1.0},
    "error threshold 0.1 m": {"error_threshold": 0.1},
    "pairing from the target": {"pairing": "target_to_source"},
    "paper (all reverted)": PAPER_ICP,
}


def icp_pairs(data_dir, quick: bool) -> list[tuple[str, tc.ElevationMap, tc.ElevationMap, np.ndarray]]:
    pairs = []
    velodyne = data_dir / "kitti_seq00" / "velodyne"
    if velodyne.is_dir():
        world_velo = kitti_world_velo(data_dir)
        frames = sorted({f for pair in KITTI_PAIRS for f in pair})
        maps = {f: classified_map(load_xyzi_bin(velodyne / f"{f:06d}.bin"), ACCURACY_EXTENT) for f in frames}
        for s, t in KITTI_PAIRS:
            pairs.append((f"KITTI {s}->{t}", maps[s], maps[t], np.linalg.inv(world_velo[t]) @ world_velo[s]))
    trajectory = sim.TrajectoryParams.exact(scan_spacing=2.963, mount_height=SENSOR_HEIGHT)
    sequence = sim.generate_sequence(trajectory=trajectory)
    for k in range(0, len(sequence) - 1, 20 if quick else 10):
        pairs.append(
            (
                f"sim {k}->{k + 1}",
                classified_map(sequence.scan(k).points, ACCURACY_EXTENT),
                classified_map(sequence.scan(k + 1).points, ACCURACY_EXTENT),
                np.linalg.inv(sequence.poses[k + 1]) @ sequence.poses[k],
            )
        )
    return pairs


def icp_part(data_dir, quick: bool) -> None:
    pairs = icp_pairs(data_dir, quick)
    rng = np.random.default_rng(5)
    guesses = {name: [perturbation(rng) @ truth for _ in range(2)] for name, _, _, truth in pairs}
    print(
        "\nWeighted ICP: median translation error [mm] over pairs and guesses, "
        "median iterations, mean time [ms]"
    )
    print(f"  {'variant':24s} {'KITTI err':>10s} {'sim err':>9s} {'iters':>6s} {'ms':>7s} {'converged':>10s}")
    for label, overrides in ICP_VARIANTS.items():
        params = replace(tc.RegistrationParams(), **overrides)
        kitti, simulated, iterations, times, converged, runs = [], [], [], [], 0, 0
        for name, source, target, truth in pairs:
            for guess in guesses[name]:
                start = time.perf_counter()
                result = tc.register_maps(source, target, guess, params)
                times.append(time.perf_counter() - start)
                translation = errors(result.transform, truth)[0]
                (kitti if name.startswith("KITTI") else simulated).append(translation)
                iterations.append(result.iterations)
                converged += int(result.converged)
                runs += 1
        print(
            f"  {label:24s} {1e3 * np.median(kitti) if kitti else float('nan'):10.1f} "
            f"{1e3 * np.median(simulated):9.1f} {np.median(iterations):6.0f} {1e3 * np.mean(times):7.1f} "
            f"{converged:>5d}/{runs}"
        )


def mapper_part(quick: bool) -> None:
    sequence = simulated_loop()
    count = min(len(sequence), 120) if quick else len(sequence)
    scans = [sequence.scan(k).points for k in range(count)]
    truth, odometry = sequence.poses[:count], sequence.odometry[:count]
    print(f"\nMapper on the simulated loop ({count} scans 1 m apart, drifting odometry): keyframe ATE [m]")
    default = MapperParams(loop_closing=False)
    for label, params in (
        ("default (0.1 m, local ground, yaw-only)", default),
        ("0.2 m cells (faster)", replace(default, resolution=0.2)),
        ("sensor-height reference", replace(default, terrain=tc.TerrainParams(sensor_height=1.73))),
        ("6-DOF steps", replace(default, yaw_only_registration=False)),
        (
            "the paper (sensor height, 6-DOF)",
            replace(default, terrain=tc.TerrainParams(sensor_height=1.73), yaw_only_registration=False),
        ),
    ):
        mapper = Mapper(params)
        start = time.perf_counter()
        for points, pose in zip(scans, odometry, strict=True):
            mapper.add_scan(points, pose)
        seconds = time.perf_counter() - start
        keys = mapper.keyframe_scan_indices()
        ate = tc.absolute_trajectory_error(mapper.keyframe_poses(), truth[keys], "first_pose").translation
        print(f"  {label:42s} ATE {ate.rmse:5.2f} m, {1e3 * seconds / count:6.1f} ms per scan")


def fem_part(data_dir) -> None:
    xyz = load_xyzi_bin(data_dir / "kitti_seq00" / "velodyne" / "000000.bin")[:, :3].astype(np.float64)
    _, collapse = tc.dem_without_overhangs(xyz, sigma=5)
    window = ((0.0, -5.0), (20.0, 5.0))
    kept = xyz[~np.asarray(collapse.overhang)]
    inside = np.all((kept[:, :2] >= window[0]) & (kept[:, :2] <= window[1]), axis=1)
    kept = kept[inside]
    held = np.zeros(len(kept), dtype=bool)
    held[::5] = True
    print(f"\nFEM, 19 x 10 rules on KITTI 000000's kept points in a 20 x 10 m window ({len(kept)} points)")
    for label, overrides in (
        ("default (ridge, smoothness, guarded)", {}),
        ("plain ANFIS (no regularisation, Jang)", {"ridge": 0.0, "smoothness": 0.0, "step_rule": "jang"}),
    ):
        try:
            fem = tc.FuzzyElevationMap.fit(kept[~held], extent=window, **overrides)
        except ValueError as error:
            print(f"  {label:40s} fails: {error}")
            continue
        holdout = np.sqrt(np.mean((fem.evaluate(kept[held, :2]) - kept[held, 2]) ** 2))
        dem = tc.build_elevation_map(kept[~held], 0.2, origin=window[0], size=(100, 50))
        fem.to_layer(dem)
        gx, gy = np.meshgrid(np.arange(0.1, 20.0, 0.2), np.arange(-4.9, 5.0, 0.2), indexing="ij")
        surface = fem.evaluate(np.column_stack([gx.ravel(), gy.ravel()]))
        extreme = float(np.max(np.abs(surface - np.median(kept[:, 2]))))
        print(
            f"  {label:40s} training RMSE {fem.rmse_history[-1]:.3f} m, held-out RMSE {holdout:.3f} m, "
            f"cells filled {np.isfinite(dem['fem']).mean():.1%}, largest |f - median z| {extreme:.2f} m"
        )


def dem_part(data_dir) -> None:
    xyz = load_xyzi_bin(data_dir / "kitti_seq00" / "velodyne" / "000000.bin")[:, :3].astype(np.float64)
    kept = xyz[~np.asarray(tc.collapse_overhangs(xyz, 0.5, 5).overhang)]
    print("\nDEM cell size on KITTI 000000 (kept points within 20 m)")
    near = kept[np.hypot(kept[:, 0], kept[:, 1]) < 20.0]
    for resolution in (0.1, 0.5):
        dem = tc.build_elevation_map(near, resolution)
        g = dem.geometry
        i = np.floor((near[:, 0] - g.origin[0]) / resolution).astype(int)
        j = np.floor((near[:, 1] - g.origin[1]) / resolution).astype(int)
        i, j = np.clip(i, 0, g.size[0] - 1), np.clip(j, 0, g.size[1] - 1)
        deviation = np.abs(near[:, 2] - dem["mean"][i, j])
        print(
            f"  {resolution:.1f} m cells: mean |z - cell mean| {1e3 * np.mean(deviation):5.1f} mm, "
            f"95th percentile {1e3 * np.percentile(deviation, 95):6.1f} mm"
        )


def main(argv: list[str] | None = None) -> int:
    args = parse_benchmark_args(
        __doc__, argv, repeat_unit="variant", quick_help="fewer simulated pairs and a shorter loop"
    )
    print_header(
        "terracube departures from the papers, default vs the paper's setting",
        [],
        "none (times are of one call each)",
        args,
        "every 20th simulated pair, 120 loop scans",
    )
    icp_part(args.data_dir, args.quick)
    fem_part(args.data_dir)
    dem_part(args.data_dir)
    mapper_part(args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
