"""Map + classify at the cadences a caller really has, on one thread and on every processor.

What is measured
----------------
The map + classify of ``bench_elevation.py`` (KITTI 00/000000 into 400 x 200 cells at 0.1 m, all six
layers, then the Table 1 classes; a fresh map per call), called

- back to back (a dataset processed offline),
- straight after a numpy map + classify of the same scan (about 6 ms of other work on the calling
  thread, as in ``bench_elevation.py``'s interleaved timing),
- once every 10 ms and once every 100 ms (a 10 Hz LiDAR's scans), the thread asleep in between,

each on one thread (``num_threads=1``) and on every processor (``num_threads=0``); the same for a DEM
without overhangs (collapse, then the map; edge 0.5 m, sigma 5, crop as in ``bench_elevation.py``)
followed by its classes: three calls that take threads per scan. Between paced calls the worker
threads (a TBB arena per call), the caches and the (virtual) processors go idle, which back-to-back
timing never shows (the host decides how long a sleeping processor takes to wake). Each line is
the median of ``--repeat`` calls (at most 25 at 100 ms) after 0.1 s of calls back to back;
``--json`` prints the medians as one JSON object instead (for ``bench/ab_python.sh``, which
alternates two builds' processes).

Reproduce
---------
    python bench/bench_threads.py                   # about 20 s
    python bench/bench_threads.py --quick           # every 4th point, fewer calls
    bash bench/ab_python.sh BASE [NEW] bench/bench_threads.py --json   # two builds, alternating
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import terracube as tc
from _common import parse_benchmark_args, print_header, processors
from bench_elevation import (
    DEM_CROP,
    DEM_EDGE,
    DEM_SIGMA,
    SENSOR_HEIGHT,
    cpp_classify,
    cpp_map,
    elevation_params,
    load_scan,
    numpy_classify,
    numpy_elevation_map,
)

CADENCES = ("back to back", "after numpy", "every 10 ms", "every 100 ms")
# Before each cadence, calls back to back for this long: caches and worker threads warm.
WARM_UP_S = 0.1


def timed_calls(call, cadence: str, calls: int, before) -> float:
    """Median ms of ``call`` at ``cadence``; ``before`` is the numpy work of "after numpy"."""
    period = {"every 10 ms": 0.01, "every 100 ms": 0.1}.get(cadence, 0.0)
    warm_until = time.perf_counter() + WARM_UP_S  # calls back to back: the steady state
    while time.perf_counter() < warm_until:
        call()
    times = []
    next_start = time.perf_counter()
    for _ in range(calls):
        if cadence == "after numpy":
            before()
        elif period:
            next_start += period
            time.sleep(max(0.0, next_start - time.perf_counter()))
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


def workloads(points, threads: int) -> dict:
    """The calls timed, on ``threads`` threads: map + classify (two calls that take threads), and
    a DEM without overhangs + classify (three: collapse, map, classes), as a robot would per scan."""
    params = elevation_params(num_threads=threads)
    terrain = tc.TerrainParams(sensor_height=SENSOR_HEIGHT, num_threads=threads)
    collapse = tc.CollapseParams(DEM_EDGE, DEM_SIGMA, crop=DEM_CROP, num_threads=threads)
    return {
        "map + classify": lambda: cpp_classify(cpp_map(points, params), terrain),
        "DEM without overhangs + classify": lambda: cpp_classify(
            tc.dem_without_overhangs(points, collapse=collapse, elevation=params)[0], terrain
        ),
    }


def measure(points, repeat: int) -> dict[str, float]:
    results = {}
    for threads in (1, 0):
        label = "1 thread" if threads == 1 else f"{processors()} threads"
        for workload, call in workloads(points, threads).items():
            for cadence in CADENCES:
                calls = min(repeat, 25) if cadence == "every 100 ms" else repeat
                results[f"{workload}, {cadence}, {label}"] = timed_calls(
                    call, cadence, calls, lambda: numpy_classify(numpy_elevation_map(points))
                )
    return results


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    def add(parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--json", action="store_true", help="print the medians as one JSON object")

    args = parse_benchmark_args(
        __doc__.split("\n\n")[0],
        argv,
        repeat_unit="cadence",
        quick_help="every 4th point, 10 calls per cadence",
        add_arguments=add,
        default_repeat=(60, 10),
    )
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    scan = load_scan(args.data_dir, args.quick)
    results = measure(scan.points, args.repeat)
    if args.json:
        print(json.dumps(results))
        return 0
    print_header(
        "terracube map + classify at a caller's cadences (bench/bench_threads.py)",
        [],
        "none (absolute times; compare builds with bench/ab_python.sh)",
        args,
        "every 4th point",
        threads=f"1 thread and {processors()} (num_threads=0), at most 25 calls every 100 ms",
    )
    print(f"\n{scan.name}: {len(scan.points):,} points, a fresh map per call, median ms")
    width = max(len(name) for name in results)
    for name, ms in results.items():
        print(f"  {name:<{width}} {ms:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
