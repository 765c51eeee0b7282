"""Draw the README's global-map figure: the simulator's loop mapped with and without loop closing.

Run: ``python scripts/map_figures.py [--output docs/images/mapper_synthetic_loop.png]`` (about a
minute: the scans are ray-cast first).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import terracube as tc  # noqa: E402
from terracube import simulation as sim  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=Path("docs/images/mapper_synthetic_loop.png"))
    args = parser.parse_args()

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
    sequence = sim.generate_sequence(sim.LoopSceneParams(), trajectory, lidar, seed=3)
    scans = [sequence.scan(k).points for k in range(len(sequence))]
    runs = {
        "weighted ICP, no loop closing": tc.run_mapper(
            scans, sequence.odometry, tc.MapperParams(loop_closing=False)
        ),
        "weighted ICP + loop closing (Ceres)": tc.run_mapper(scans, sequence.odometry, tc.MapperParams()),
    }
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), constrained_layout=True)
    colours = {int(k): v for k, v in tc.TERRAIN_COLORS.items()}
    for ax, (title, mapper) in zip(axes, runs.items(), strict=True):
        dem = mapper.global_map()
        g = dem.geometry
        classes = np.nan_to_num(dem["class"], nan=0).astype(int)
        rgb = np.ones((*classes.shape, 3))
        for value, colour in colours.items():
            if value:
                rgb[classes == value] = colour
        extent = (g.origin[0], g.origin[0] + g.length[0], g.origin[1], g.origin[1] + g.length[1])
        ax.imshow(np.transpose(rgb, (1, 0, 2)), origin="lower", extent=extent, interpolation="nearest")
        keys = mapper.keyframe_scan_indices()
        truth = sequence.poses[keys]
        ate = tc.absolute_trajectory_error(mapper.keyframe_poses(), truth, "first_pose").translation
        ax.plot(truth[:, 0, 3], truth[:, 1, 3], "k-", lw=1.2, label="ground truth")
        ax.plot(*mapper.keyframe_odometry()[:, :2, 3].T, "--", color="0.5", lw=1, label="odometry")
        ax.plot(*mapper.keyframe_poses()[:, :2, 3].T, "-", color="tab:red", lw=1.2, label="estimate")
        ax.set_title(f"{title}: ATE {ate.rmse:.2f} m, {len(mapper.loop_closures)} loops", fontsize=10)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
        ax.legend(loc="lower right", fontsize=8)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=110)
    print(f"written: {args.output}")


if __name__ == "__main__":
    main()
