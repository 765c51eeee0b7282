"""Benchmark class-weighted ICP between elevation maps against the all-cells ICP and PCL's ICP.

What is measured
----------------
Three registrations of the same pair of classified 2.5D maps (0.1 m cells, Table 1 classes with
``sensor_height = 1.73`` m; every cell with data is the point (x centre, y centre, max)):

- ``weighted``: ``terracube.register_maps`` with its defaults -- pairs only within a terrain class,
  Table 2 weights (obstacle 0.8, overhanging 0.5, vertical 0.5, horizontal edge 0.8), ground takes
  no part; nearest neighbours from per-class 2D bucket grids, re-searched only where a cached
  certificate cannot prove the last partner still nearest; guarded Besl-McKay extrapolation and
  coarse-to-fine first iterations (every 4th source point) -- the two departures from the paper;
- ``weighted plain``: ``RegistrationParams.paper_icp()``: the paper's plain iteration from the
  guess (no correlative search, ``extrapolate=False, coarse_subsample=1``; same nearest
  neighbours); ``weighted`` starts with the correlative search (issue 38; its basin is measured
  by bench_basin.py);
- ``weighted + ground``: the same with ``ground_weight=4`` (not in the paper): ground cells as
  planes of 0.5 m cells, point-to-plane, paired by lookup (no search);
- ``all cells``: ``terracube.register_maps_all_cells`` -- the paper's conventional ICP, every cell,
  unit weight (same distance schedule: 1.5 m shrinking by 0.85 per iteration to 0.3 m);
- ``PCL``: ``pcl::IterativeClosestPoint<PointXYZ>`` (SVD) on the all-cells points, max
  correspondence distance 1.0 m, 30 iterations, transformation epsilon 1e-8 m^2.

``--scan-floor`` adds, per KITTI pair, PCL's ICP and PCL's GICP (plane-to-plane) on the raw 3D scans
(0.2 m voxel means, 3-30 m range): how close dense scan matchers get to the ground truth on these
scans, i.e. the floor that the data sets for every method (see the README's note on KITTI). It
also takes GICP started at the ground truth as the *scan reference* (the motion the raw scans
support), prints how far it lies from the truth and its spread (the largest translation of
GICP's runs from the perturbed guesses from it), and repeats the accuracy table with the errors
of the same runs taken against that reference. A check without any ICP comes with it: on the
labelled pairs (0->1, 1->2) the static thin objects (SemanticKITTI pole, trunk, traffic sign)
are moved by the truth's rotation and its translation scaled, and the step that aligns them best
is printed beside the truth's.

Pairs: KITTI odometry seq 00 frames 0->1, 1->2, 2->3, 3->4, 4->5 and 0->5 (about 4.3 m), with
the ground truth T_wv(i) = inv(Tr) P_i Tr and truth = inv(T_wv(target)) T_wv(source); a
synthetic street seen from two poses 3 m and 20 degrees apart (as in the paper); and, for
accuracy only, simulated pairs with an exact truth: terracube's ray-casting simulator, a 64-beam
LiDAR 1.73 m above the road of its loop scene, keyframes about 3 m apart (the paper's local-map
spacing), every 10th keyframe with the next, in three sets: steps of exactly 3 m (30 cells: on
straight stretches the cells of the two maps coincide at the truth, which favours point-to-point
pairs on the flat ground) and of 2.963 and 3.037 m (unaligned, as keyframes taken at arbitrary
distances are); 8-9 pairs per set, the first two sets at every 20th keyframe with ``--quick``. Every pair is
started from the truth perturbed by seeded random offsets of up to 0.3 m and 3 degrees
(``--trials`` draws per pair). Accuracy maps are 60 x 40 m centred on the sensor; the speed
target is timed on 40 x 20 m maps (origin (-20, -10) m, 400 x 200 cells).

Timing: ``time.perf_counter`` around one call (one warm-up, median of ``--repeat``), single
thread, maps prebuilt (map building is benchmarked in bench_elevation.py). Per-iteration time is
total / iterations (an iteration = one update; ``passes`` counts the correspondence sweeps, one
more than the iterations plus one per extrapolation tried). Targets (reported, not asserted, one
verdict per pair): a weighted registration of a 40 x 20 m map at 0.1 m within 10 ms (the paper:
260-330 ms per iteration, 5-10 iterations); the weighted ICP the most accurate of the three on
the KITTI pairs and on the simulated pairs (median translation error), printed for the weighted
ICP alone and with ground planes; and per data set (each simulated set, the synthetic street,
with ``--scan-floor`` KITTI against the scan reference) the median over its pairs, the number of
pairs on which the weighted ICP is closer than each rival, and whether its median is the lowest
of the three.

Reproduce
---------
    python bench/bench_icp.py               # full run, well under a minute
    python bench/bench_icp.py --quick       # fewer trials and repeats
    python bench/bench_icp.py --markdown    # also print Markdown tables
    python bench/bench_icp.py --scan-floor  # also the raw-scan floor and scan reference (~2 min more)
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import terracube as tc
from _common import (
    SYNTHETIC_SEED,
    header_line,
    load_xyzi_bin,
    markdown_row,
    markdown_rule,
    median_ms,
    parse_benchmark_args,
    print_header,
    print_target,
    require,
)

RESOLUTION = 0.1
SENSOR_HEIGHT = 1.73
ACCURACY_EXTENT = ((-30.0, -20.0), (60.0, 40.0))  # origin, length [m]
SPEED_EXTENT = ((-20.0, -10.0), (40.0, 20.0))
KITTI_PAIRS = ((0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5))
MAX_OFFSET_M = 0.3
MAX_ANGLE_DEG = 3.0
TARGET_MS = 10.0
PCL = tc.PclIcpParams(max_correspondence_distance=1.0, max_iterations=30, transformation_epsilon=1e-8)
METHODS = ("weighted", "weighted plain", "weighted + ground", "all cells", "PCL")
PLAIN = tc.RegistrationParams.paper_icp()
GROUND_WEIGHT = 4.0
GROUND = tc.RegistrationParams(ground_weight=GROUND_WEIGHT)
#: The weighted ICP with the constraint analysis (RegistrationResult.constraint_matrix) on.
STRUCTURE_RADIUS_M = 0.3
ANALYSED = tc.RegistrationParams(structure_radius=STRUCTURE_RADIUS_M)
#: The three methods the issue ranks (the paper's weighted ICP, all cells, PCL).
ISSUE_METHODS = ("weighted", "all cells", "PCL")
#: Simulated pairs: keyframes about 3 m apart (the paper's local-map spacing) along the loop scene.
#: At exactly 3 m (30 cells) with no turn the two maps' cells coincide at the truth, which favours
#: point-to-point pairs on the flat ground (the all-cells ICP snaps to the lattice); keyframes taken
#: at arbitrary distances do not line up, as with 2.963 and 3.037 m. All three sets are run.
SIM_STEPS_M = (3.0, 2.963, 3.037)
#: The sets with unaligned steps (those a robot taking keyframes "every ~3 m" meets).
UNALIGNED_PREFIXES = tuple(f"sim {step:.3f} " for step in SIM_STEPS_M[1:])


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------


def rotation_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def pose(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation_matrix(np.array([0.0, 0.0, 1.0]), np.radians(yaw_deg))
    t[:3, 3] = (x, y, z)
    return t


def perturbation(rng: np.random.Generator) -> np.ndarray:
    """A random rigid offset: translation up to MAX_OFFSET_M, rotation up to MAX_ANGLE_DEG."""
    t = np.eye(4)
    direction = rng.normal(size=3)
    t[:3, 3] = direction / np.linalg.norm(direction) * rng.uniform(0.5, 1.0) * MAX_OFFSET_M
    t[:3, :3] = rotation_matrix(rng.normal(size=3), np.radians(rng.uniform(0.5, 1.0) * MAX_ANGLE_DEG))
    return t


def errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation error [m], rotation error [deg])."""
    delta = estimate[:3, :3].T @ truth[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(delta) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3])), float(angle)


def classified_map(points: np.ndarray, extent) -> tc.ElevationMap:
    (ox, oy), (lx, ly) = extent
    size = (round(lx / RESOLUTION), round(ly / RESOLUTION))
    elevation_map = tc.build_elevation_map(points, RESOLUTION, origin=(ox, oy), size=size)
    tc.classify_terrain(elevation_map, sensor_height=SENSOR_HEIGHT)
    return elevation_map


def kitti_world_velo(root: Path) -> list[np.ndarray]:
    calib = {}
    for line in (root / "kitti_seq00" / "calib.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        calib[key.strip()] = np.array(values.split(), dtype=float)
    tr = np.vstack([calib["Tr"].reshape(3, 4), [0, 0, 0, 1]])
    poses = np.loadtxt(root / "kitti_seq00" / "poses.txt").reshape(-1, 3, 4)
    return [np.linalg.inv(tr) @ np.vstack([p, [0, 0, 0, 1]]) @ tr for p in poses]


def street(step: float = 0.05) -> np.ndarray:
    """A synthetic street (ground z = 0): road, house fronts with gaps, poles, kerb, boxes, canopy."""
    rng = np.random.default_rng(SYNTHETIC_SEED)
    parts = []
    gx, gy = np.meshgrid(np.arange(-40, 40, step), np.arange(-25, 25, step), indexing="ij")
    parts.append(np.column_stack([gx.ravel(), gy.ravel(), rng.normal(0, 0.01, gx.size)]))
    for y_wall in (9.0, -10.0):
        wx, wz = np.meshgrid(np.arange(-40, 40, step), np.arange(0, 4.5, step), indexing="ij")
        keep = (np.mod(wx + 40.0, 12.0) <= 9.0) & (wz < 4.0 + 0.5 * np.sin(wx))
        parts.append(
            np.column_stack([wx[keep], np.full(keep.sum(), y_wall) + 0.1 * np.sin(0.7 * wx[keep]), wz[keep]])
        )
    angles = np.arange(16) * np.pi / 8
    for px in (-22.0, -9.0, 3.0, 14.5, 26.0):
        for z in np.arange(0, 3.0, step):
            parts.append(
                np.column_stack([px + 0.15 * np.cos(angles), 6.0 + 0.15 * np.sin(angles), np.full(16, z)])
            )
    kx = np.arange(-30, 30, step)
    kx = kx[np.mod(kx + 30.0, 10.0) < 7.0]
    parts.append(np.column_stack([kx, np.full(kx.size, -4.5), np.full(kx.size, 0.3)]))
    for cx in (-15.0, 7.0, 20.0):
        bx, by = np.meshgrid(np.arange(cx, cx + 4.0, step), np.arange(-7.0, -5.2, step), indexing="ij")
        parts.append(np.column_stack([bx.ravel(), by.ravel(), 1.5 + 0.05 * (bx.ravel() - cx)]))
    cx, cy = np.meshgrid(np.arange(-4, 0, step), np.arange(-5, -1, step), indexing="ij")
    parts.append(np.column_stack([cx.ravel(), cy.ravel(), 3.5 + 0.2 * np.cos(cx.ravel() + cy.ravel())]))
    return np.vstack(parts)


@dataclass
class Pair:
    name: str
    source: tc.ElevationMap
    target: tc.ElevationMap
    truth: np.ndarray


def load_pairs(data_dir: Path, extent, quick: bool) -> list[Pair]:
    pairs = []
    world = street(0.1 if quick else 0.05)
    source_pose = pose(-1.0, 0.0, SENSOR_HEIGHT, -10.0)
    target_pose = pose(1.95, 0.5, SENSOR_HEIGHT, 10.0)

    def sensor_view(p: np.ndarray) -> np.ndarray:
        inverse = np.linalg.inv(p)
        return world @ inverse[:3, :3].T + inverse[:3, 3]

    pairs.append(
        Pair(
            "synthetic 3 m / 20 deg",
            classified_map(sensor_view(source_pose), extent),
            classified_map(sensor_view(target_pose), extent),
            np.linalg.inv(target_pose) @ source_pose,
        )
    )
    velodyne = data_dir / "kitti_seq00" / "velodyne"
    if not velodyne.is_dir():
        print(f"  (no KITTI data under {data_dir}: synthetic pair only)")
        return pairs
    world_velo = kitti_world_velo(data_dir)
    maps = {}
    for frame in sorted({f for pair in KITTI_PAIRS for f in pair}):
        maps[frame] = classified_map(load_xyzi_bin(velodyne / f"{frame:06d}.bin"), extent)
    for s, t in KITTI_PAIRS:
        pairs.append(Pair(f"KITTI {s}->{t}", maps[s], maps[t], np.linalg.inv(world_velo[t]) @ world_velo[s]))
    return pairs


def load_sim_pairs(extent, quick: bool) -> list[Pair]:
    """Ray-cast pairs with an exact truth: terracube's simulator, a 64-beam LiDAR 1.73 m above the
    road of the loop scene (buildings, walls, trees, a ramp, a tunnel, a bridge), keyframes every
    step of SIM_STEPS_M along it (the first two with ``quick``); every 10th keyframe (every 20th
    with ``quick``) and the next. Pairs are named "sim <step> <k>-><k+1>"."""
    pairs = []
    for step in SIM_STEPS_M[:2] if quick else SIM_STEPS_M:
        sequence = tc.simulation.generate_sequence(
            trajectory=tc.simulation.TrajectoryParams.exact(scan_spacing=step, mount_height=SENSOR_HEIGHT)
        )
        for k in range(0, len(sequence) - 1, 20 if quick else 10):
            pairs.append(
                Pair(
                    f"sim {step:.3f} {k}->{k + 1}",
                    classified_map(sequence.scan(k).points, extent),
                    classified_map(sequence.scan(k + 1).points, extent),
                    np.linalg.inv(sequence.poses[k + 1]) @ sequence.poses[k],
                )
            )
    return pairs


# --------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------


def run(method: str, pair: Pair, guess: np.ndarray, points=None):
    """(transform, iterations, converged, passes) of one registration."""
    if method == "weighted":
        r = tc.register_maps(pair.source, pair.target, guess)
    elif method == "weighted plain":
        r = tc.register_maps(pair.source, pair.target, guess, PLAIN)
    elif method == "weighted + ground":
        r = tc.register_maps(pair.source, pair.target, guess, GROUND)
    elif method == "all cells":
        r = tc.register_maps_all_cells(pair.source, pair.target, guess)
    else:
        r = tc.pcl_icp(points[0], points[1], guess, PCL)
        return r.transform, r.iterations, r.converged, r.iterations
    return r.transform, r.iterations, r.converged, r.passes


def accuracy(pairs: list[Pair], trials: int) -> dict:
    """errors[pair name][method] -> list of (translation m, rotation deg, converged, transform)."""
    rng = np.random.default_rng(SYNTHETIC_SEED)
    table = {}
    for pair in pairs:
        points = (tc.points_of_map(pair.source)[0], tc.points_of_map(pair.target)[0])
        table[pair.name] = {m: [] for m in METHODS if m != "PCL" or tc.has_pcl()}
        for _ in range(trials):
            guess = perturbation(rng) @ pair.truth
            for method in table[pair.name]:
                transform, _, converged, _ = run(method, pair, guess, points)
                table[pair.name][method].append((*errors(transform, pair.truth), converged, transform))
    return table


def against(table: dict, references: dict) -> dict:
    """The accuracy table's runs of the pairs in `references`, their errors taken against those."""
    return {
        name: {
            method: [(*errors(v[3], references[name]), v[2], v[3]) for v in values]
            for method, values in table[name].items()
        }
        for name in references
        if name in table
    }


def speed(pairs: list[Pair], repeat: int) -> dict:
    """timing[pair name][method] -> (median ms, iterations, passes)."""
    rng = np.random.default_rng(SYNTHETIC_SEED + 1)
    timing = {}
    for pair in pairs:
        points = (tc.points_of_map(pair.source)[0], tc.points_of_map(pair.target)[0])
        guess = perturbation(rng) @ pair.truth
        timing[pair.name] = {}
        for method in METHODS:
            if method == "PCL" and not tc.has_pcl():
                continue
            _, iterations, _, passes = run(method, pair, guess, points)
            ms = median_ms(lambda m=method, p=pair, g=guess, q=points: run(m, p, g, q), repeat)
            timing[pair.name][method] = (ms, iterations, passes)
    return timing


def constraints(pairs: list[Pair], repeat: int | None = None) -> dict:
    """Per pair, the weighted ICP from the truth with the constraint analysis, normalised: (the
    weakest eigenvalue, the unknown that dominates its direction, the second weakest, the weakest of
    the normalised point-to-point normal matrix, and with ``repeat`` the median ms with and without
    the analysis)."""
    out = {}
    for pair in pairs:
        r = tc.register_maps(pair.source, pair.target, pair.truth, ANALYSED)
        directions = tc.constrained_directions(r)
        # The point-to-point normal matrix taken alike (its translations are 1 by construction).
        weight = np.trace(r.normal_matrix[3:, 3:]) / 3.0
        scale = np.diag(
            1.0 / np.array([np.sqrt(np.trace(r.normal_matrix[:3, :3]) / (2.0 * weight))] * 3 + [1.0] * 3)
        )
        plain = np.linalg.eigvalsh(scale @ r.normal_matrix @ scale / weight)[0]
        row = [directions[0][1], directions[0][0], directions[1][1], plain]
        if repeat:
            row.append(
                median_ms(lambda p=pair: tc.register_maps(p.source, p.target, p.truth, ANALYSED), repeat)
            )
            row.append(median_ms(lambda p=pair: tc.register_maps(p.source, p.target, p.truth), repeat))
        out[pair.name] = row
    return out


def print_constraints(found: dict, markdown: bool) -> None:
    print(
        "\nWhat the geometry constrains (weighted ICP from the truth,"
        f" structure_radius={STRUCTURE_RADIUS_M} m):"
        " the weakest and second weakest eigenvalue of the constraint matrix per unit of pair weight"
        " (rotations times the pairs' rms radius; 1: every pair holds that direction fully), the"
        " unknown the weakest direction moves most, and the weakest of the point-to-point normal"
        " matrix alike, which cannot show sliding"
    )
    timed = any(len(row) > 4 for row in found.values())
    header = f"  {'pair':<24}{'weakest':>10}{'along':>7}{'second':>10}{'H weakest':>10}"
    print(header + (f"{'ms with':>9}{'without':>9}" if timed else ""))
    for name, row in found.items():
        line = f"  {name:<24}{row[0]:>10.3f}{row[1]:>7}{row[2]:>10.3f}{row[3]:>10.3f}"
        print(line + (f"{row[4]:>9.2f}{row[5]:>9.2f}" if len(row) > 4 else ""))
    if markdown:
        print()
        columns = ["pair", "weakest", "along", "second weakest", "point-to-point H: weakest"]
        print(markdown_row(columns + (["ms with", "ms without"] if timed else [])))
        print(markdown_rule(len(columns) - 1 + (2 if timed else 0)))
        for name, row in found.items():
            cells = [name, f"{row[0]:.3f}", row[1], f"{row[2]:.3f}", f"{row[3]:.3f}"]
            print(markdown_row(cells + ([f"{row[4]:.2f}", f"{row[5]:.2f}"] if len(row) > 4 else [])))


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def print_accuracy(table: dict, markdown: bool, title: str = "") -> dict:
    """Prints the table; returns the median translation error per pair and method."""
    print(
        "\nAccuracy: median over trials of translation error [m] / rotation error [deg] (converged runs)"
        + (f", {title}" if title else "")
    )
    methods = [m for m in METHODS if any(m in row for row in table.values())]
    print(f"  {'pair':<24}" + "".join(f"{m:>22}" for m in methods))
    all_medians = {}
    for name, row in table.items():
        cells = []
        medians = {}
        for method in methods:
            values = row.get(method, [])
            t = statistics.median(v[0] for v in values)
            r = statistics.median(v[1] for v in values)
            ok = sum(v[2] for v in values)
            medians[method] = t
            cells.append(f"{t:.3f} / {r:.2f} ({ok}/{len(values)})")
        print(f"  {name:<24}" + "".join(f"{c:>22}" for c in cells))
        all_medians[name] = medians
    if markdown:
        print()
        print(markdown_row(["pair", *[f"{m} t [m] / r [deg]" for m in methods]]))
        print(markdown_rule(len(methods)))
        for name, row in table.items():
            cells = []
            for m in methods:
                t = statistics.median(v[0] for v in row[m])
                cells.append(f"{t:.3f} / {statistics.median(v[1] for v in row[m]):.2f}")
            print(markdown_row([name, *cells]))
    return all_medians


def best_of(medians: dict, prefix: str, weighted: str = "weighted") -> list[str]:
    """Per pair whose name starts with `prefix`: the most accurate of the issue's three methods,
    with `weighted` standing for the weighted ICP."""
    winners = []
    for name, row in medians.items():
        if name.startswith(prefix):
            rivals = {m: row[m] for m in (weighted, *ISSUE_METHODS[1:]) if m in row}
            winners.append(min(rivals, key=rivals.get))
    return winners


def print_verdicts(medians: dict, what: str, prefix: str) -> None:
    """Whether the weighted ICP (alone, and with ground planes) is the most accurate on every pair."""
    for weighted in ("weighted", "weighted + ground"):
        winners = best_of(medians, prefix, weighted)
        if not winners:
            continue
        verdict = "MET" if all(w == weighted for w in winners) else "NOT MET"
        print(
            f"  {weighted} the most accurate of it, all cells and PCL (median translation) on every {what}:"
            f" {verdict} ({winners.count(weighted)} of {len(winners)}; best: {', '.join(winners)})"
        )


def print_typical(medians: dict, what: str, prefixes: tuple[str, ...]) -> None:
    """The median over the pairs of their median translation errors, per method, and on how many
    pairs the weighted ICP is closer than each rival."""
    rows = [row for name, row in medians.items() if name.startswith(prefixes)]
    if not rows:
        return
    typical = {m: statistics.median(row[m] for row in rows) for m in rows[0]}
    wins = {m: sum(row["weighted"] < row[m] for row in rows) for m in rows[0] if m != "weighted"}
    print(
        f"  {what}, median of the pairs' median translation errors: "
        + ", ".join(f"{m} {1000 * t:.1f} mm" for m, t in typical.items())
        + "; weighted closer than: "
        + ", ".join(f"{m} on {n} of {len(rows)}" for m, n in wins.items())
    )
    rivals = {m: typical[m] for m in ISSUE_METHODS if m in typical}
    lowest = min(rivals, key=rivals.get)
    print(
        f"  {what}: weighted the lowest median of it, all cells and PCL:"
        f" {'MET' if lowest == 'weighted' else 'NOT MET'} (lowest: {lowest})"
    )


def print_speed(timing: dict, markdown: bool) -> list[float]:
    print(
        "\nSpeed on 40 x 20 m maps at 0.1 m: total ms (iterations/passes, ms per iteration); "
        "ratios = PCL / weighted, total and per iteration; target: weighted <= "
        f"{TARGET_MS:g} ms"
    )
    print(f"  {'pair':<24}" + "".join(f"{m:>25}" for m in METHODS) + f"{'total':>8}{'per it':>8}  target")
    weighted_ms = []

    def cell(row, m):
        if m not in row:
            return "n/a"
        ms, iterations, passes = row[m]
        return f"{ms:.2f} ({iterations}/{passes}, {ms / max(iterations, 1):.2f})"

    for name, row in timing.items():
        total, per_iteration = "n/a", "n/a"
        if "PCL" in row:
            w, p = row["weighted"], row["PCL"]
            total = f"{p[0] / w[0]:.0f}x"
            per_iteration = f"{(p[0] / max(p[1], 1)) / (w[0] / max(w[1], 1)):.0f}x"
        verdict = "MET" if row["weighted"][0] <= TARGET_MS else "NOT MET"
        print(
            f"  {name:<24}"
            + "".join(f"{cell(row, m):>25}" for m in METHODS)
            + f"{total:>8}{per_iteration:>8}  {verdict}"
        )
        weighted_ms.append(row["weighted"][0])
    if markdown:
        print()
        print(
            markdown_row(
                ["pair", *[f"{m} ms (iterations/passes)" for m in METHODS], "PCL / weighted", "10 ms target"]
            )
        )
        print(markdown_rule(len(METHODS) + 2))
        for name, row in timing.items():
            ratio = f"{row['PCL'][0] / row['weighted'][0]:.0f}x" if "PCL" in row else ""
            cells = [f"{row[m][0]:.2f} ({row[m][1]}/{row[m][2]})" if m in row else "" for m in METHODS]
            verdict = "MET" if row["weighted"][0] <= TARGET_MS else "NOT MET"
            print(markdown_row([name, *cells, ratio, verdict]))
    return weighted_ms


@dataclass
class ScanFloor:
    """What dense matchers on the raw 3D scans make of each KITTI pair."""

    floor: dict  # pair name -> ((ICP t, r), (GICP t, r)): medians against the ground truth
    reference: dict  # pair name -> GICP's transform started at the ground truth
    spread: dict  # pair name -> largest translation [m] of GICP's perturbed runs from the reference


def scan_floor(data_dir: Path, trials: int) -> ScanFloor:
    """PCL's ICP and GICP on the raw 3D KITTI scans, from the perturbed guesses and from the truth."""
    result = ScanFloor({}, {}, {})
    velodyne = data_dir / "kitti_seq00" / "velodyne"
    if not velodyne.is_dir() or not tc.has_pcl():
        return result
    world_velo = kitti_world_velo(data_dir)

    def voxel_means(points: np.ndarray, size: float = 0.2) -> np.ndarray:
        keep = (np.hypot(points[:, 0], points[:, 1]) > 3.0) & (np.hypot(points[:, 0], points[:, 1]) < 30.0)
        points = points[keep].astype(np.float64)
        _, inverse = np.unique(np.floor(points / size).astype(np.int64), axis=0, return_inverse=True)
        inverse = inverse.ravel()
        sums = np.zeros((inverse.max() + 1, 3))
        np.add.at(sums, inverse, points)
        return sums / np.bincount(inverse)[:, None]

    rng = np.random.default_rng(SYNTHETIC_SEED)
    params = tc.PclIcpParams(max_correspondence_distance=0.5, max_iterations=60, transformation_epsilon=1e-10)
    for s, t in KITTI_PAIRS:
        name = f"KITTI {s}->{t}"
        source = voxel_means(load_xyzi_bin(velodyne / f"{s:06d}.bin"))
        target = voxel_means(load_xyzi_bin(velodyne / f"{t:06d}.bin"))
        truth = np.linalg.inv(world_velo[t]) @ world_velo[s]
        guesses = [perturbation(rng) @ truth for _ in range(trials)]
        row = []
        for method in (tc.pcl_icp, tc.pcl_gicp):
            found = [method(source, target, guess, params).transform for guess in guesses]
            found_errors = [errors(transform, truth) for transform in found]
            row.append(
                (statistics.median(e[0] for e in found_errors), statistics.median(e[1] for e in found_errors))
            )
        result.floor[name] = row
        # The motion the scans support: GICP from the truth; its spread: how far GICP from the
        # perturbed guesses (`found`, the last method's) lands from it.
        reference = tc.pcl_gicp(source, target, truth, params).transform
        result.reference[name] = reference
        result.spread[name] = max(errors(transform, reference)[0] for transform in found)
    return result


def kiss_icp_steps(data_dir: Path) -> dict | None:
    """KISS-ICP (Vizzo et al. 2023, ``pip install kiss-icp``) over KITTI frames 0-5, if installed.

    A third-party odometry pipeline, independent of terracube and PCL, as a check of what the
    scans support: per consecutive pair, its relative pose (Velodyne frame). Its defaults, except
    the range (5-100 m, so 1 m voxels) and no de-skewing (the odometry scans carry no point times). None when
    kiss-icp is not installed.
    """
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        return None
    config = KISSConfig()
    config.data.max_range, config.data.min_range, config.data.deskew = 100.0, 5.0, False
    config.mapping.voxel_size = config.data.max_range / 100.0  # kiss-icp's own default rule
    odometry = KissICP(config)
    poses = []
    for frame in range(6):
        points = load_xyzi_bin(data_dir / "kitti_seq00" / "velodyne" / f"{frame:06d}.bin")[:, :3]
        odometry.register_frame(points.astype(np.float64), np.zeros(len(points)))
        poses.append(np.array(odometry.last_pose))
    # Source -> target as everywhere here: inv(T_w(target)) @ T_w(source).
    return {f"KITTI {s}->{t}": np.linalg.inv(poses[t]) @ poses[s] for s, t in KITTI_PAIRS}


#: SemanticKITTI classes of static, thin, vertical objects: pole, trunk, traffic sign.
STATIC_OBJECT_LABELS = (80, 71, 81)


def _object_misfit(rotated: np.ndarray, translation: np.ndarray, target: np.ndarray, scale: float) -> float:
    """Median squared (x, y) distance from the moved objects to their nearest target object point."""
    moved = (rotated + scale * translation).astype(np.float32)
    return float(np.median(((moved[:, None, :] - target[None, :, :]) ** 2).sum(-1).min(axis=1)))


def labelled_object_steps(data_dir: Path) -> dict:
    """Per labelled KITTI pair: (truth step [m], step [m] that best aligns the labelled objects).

    An ICP-free check of the ground truth: the points SemanticKITTI labels pole, trunk or traffic
    sign (within 30 m) are moved by the truth's rotation and its translation scaled by 0.5 ... 1.2,
    and the scale whose median nearest-neighbour distance (x, y) to the next frame's objects is
    smallest gives the step the scans show.
    """
    steps = {}
    root = data_dir / "kitti_seq00"
    world_velo = kitti_world_velo(data_dir)

    def objects(frame: int) -> np.ndarray | None:
        labels = root / "labels" / f"{frame:06d}.label"
        if not labels.is_file():
            return None
        points = load_xyzi_bin(root / "velodyne" / f"{frame:06d}.bin").astype(np.float64)
        semantic = np.fromfile(labels, dtype=np.uint32) & 0xFFFF
        keep = np.isin(semantic, STATIC_OBJECT_LABELS) & (np.hypot(points[:, 0], points[:, 1]) < 30.0)
        return points[keep, :2]

    for s, t in KITTI_PAIRS:
        source, target = objects(s), objects(t)
        if source is None or target is None or len(source) == 0 or len(target) == 0:
            continue
        truth = np.linalg.inv(world_velo[t]) @ world_velo[s]
        rotated = source @ truth[:2, :2].T
        cost = functools.partial(_object_misfit, rotated, truth[:2, 3], target.astype(np.float32))
        # Coarse (0.05) then fine (0.005) steps of the scale.
        best = min(np.arange(0.5, 1.2001, 0.05), key=cost)
        best = min(np.arange(best - 0.05, best + 0.0501, 0.005), key=cost)
        step = float(np.linalg.norm(truth[:3, 3]))
        steps[f"KITTI {s}->{t}"] = (step, float(best) * step)
    return steps


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    def add(parser: argparse.ArgumentParser) -> None:
        parser.add_argument(
            "--trials", type=int, default=None, help="perturbed guesses per pair (default 5, 2 with --quick)"
        )
        parser.add_argument(
            "--scan-floor", action="store_true", help="also run PCL's ICP on the raw 3D KITTI scans (slow)"
        )

    args = parse_benchmark_args(
        __doc__.split("\n\n")[0],
        argv,
        repeat_unit="registration",
        quick_help="fewer trials",
        add_arguments=add,
    )
    if args.trials is None:
        args.trials = 2 if args.quick else 5
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    details = [
        header_line(
            "maps", f"{RESOLUTION} m cells; accuracy on 60 x 40 m, speed on 40 x 20 m (400 x 200 cells)"
        ),
        header_line(
            "guess", f"truth perturbed by up to {MAX_OFFSET_M} m and {MAX_ANGLE_DEG} deg, {args.trials} draws"
        ),
        header_line("pcl", "available" if tc.has_pcl() else "not built (PCL columns n/a)"),
        header_line("ground", f"weighted + ground: ground_weight={GROUND_WEIGHT:g}, ground_cell=0.5 m"),
    ]
    print_header(
        "terracube class-weighted ICP benchmark", details, "PCL time / weighted time", args, "fewer trials"
    )
    accuracy_pairs = load_pairs(args.data_dir, ACCURACY_EXTENT, args.quick) + load_sim_pairs(
        ACCURACY_EXTENT, args.quick
    )
    table = accuracy(accuracy_pairs, args.trials)
    for name, row in table.items():
        require(
            all(np.isfinite(v[0]) for values in row.values() for v in values), f"{name}: non-finite result"
        )
    medians = print_accuracy(table, args.markdown)
    scan_medians = {}
    if args.scan_floor:
        floor = scan_floor(args.data_dir, args.trials)
        print(
            "\nFloor: PCL's ICP and GICP on the raw 3D scans (0.2 m voxels),"
            " median translation [m] / rotation [deg] against the ground truth; GICP from the truth"
            " (the scan reference) and its spread (largest translation of GICP's perturbed runs from it)"
        )
        print(f"  {'pair':<24}{'PCL ICP':>16}{'PCL GICP':>18}{'reference - truth':>20}{'spread':>9}")
        for name, ((t, r), (gt, gr)) in floor.floor.items():
            truth = next(pair.truth for pair in accuracy_pairs if pair.name == name)
            off = errors(floor.reference[name], truth)[0]
            print(
                f"  {name:<24}{t:>10.3f} / {r:.2f}{gt:>12.3f} / {gr:.2f}"
                f"{off:>16.3f} m{floor.spread[name]:>7.3f} m"
            )
        steps = labelled_object_steps(args.data_dir)
        if steps:
            print(
                "  labelled poles, trunks and signs (SemanticKITTI, < 30 m) align best when moved by"
                " the truth's rotation and this step (no ICP involved):"
            )
            for name, (truth_step, object_step) in steps.items():
                print(
                    f"    {name}: truth step {truth_step:.3f} m, objects' step {object_step:.3f} m"
                    f" ({object_step / truth_step:.0%} of it)"
                )
        kiss = kiss_icp_steps(args.data_dir)
        if kiss is None:
            print("  KISS-ICP: not installed (pip install kiss-icp for a third-party check)")
        else:
            print(
                "  KISS-ICP (third-party odometry on the raw scans, frames 0-5 in turn):"
                " its step, and its translation / rotation from the truth and from the scan reference"
            )
            for name, found in kiss.items():
                truth = next(pair.truth for pair in accuracy_pairs if pair.name == name)
                t_truth, r_truth = errors(found, truth)
                line = (
                    f"    {name}: step {np.linalg.norm(found[:3, 3]):.3f} m (truth"
                    f" {np.linalg.norm(truth[:3, 3]):.3f} m);"
                    f" from the truth {t_truth:.3f} m / {r_truth:.2f} deg"
                )
                if name in floor.reference:
                    t_ref, r_ref = errors(found, floor.reference[name])
                    line += f", from the reference {t_ref:.3f} m / {r_ref:.2f} deg"
                print(line)
        if floor.reference:
            scan_medians = print_accuracy(
                against(table, floor.reference),
                args.markdown,
                "against the scan reference instead of the truth",
            )
    speed_pairs = load_pairs(args.data_dir, SPEED_EXTENT, args.quick)
    timing = speed(speed_pairs, args.repeat)
    weighted_ms = print_speed(timing, args.markdown)
    print_constraints(
        constraints(speed_pairs, args.repeat)
        | constraints([p for p in accuracy_pairs if p.name.startswith(UNALIGNED_PREFIXES)]),
        args.markdown,
    )

    print("\nTargets (reported, not asserted):")
    print_target(
        f"weighted registration of a 40 x 20 m map at 0.1 m within {TARGET_MS:g} ms",
        weighted_ms,
        lambda ms: ms <= TARGET_MS,
        " ms",
    )
    print_verdicts(medians, "KITTI pair (against the ground truth)", "KITTI")
    print_verdicts(scan_medians, "KITTI pair (against the scan reference)", "KITTI")
    print_typical(scan_medians, "KITTI pairs against the scan reference", ("KITTI",))
    for step in SIM_STEPS_M:
        prefix = f"sim {step:.3f} "
        aligned = (
            "cells coincide at the truth on straight stretches" if step == SIM_STEPS_M[0] else "unaligned"
        )
        print_verdicts(medians, f"simulated pair, step {step:.3f} m (exact truth; {aligned})", prefix)
        print_typical(medians, f"simulated pairs, step {step:.3f} m", (prefix,))
    print_typical(medians, "simulated pairs with unaligned steps", UNALIGNED_PREFIXES)
    print_typical(medians, "synthetic street", ("synthetic",))
    return 0


if __name__ == "__main__":
    sys.exit(main())
