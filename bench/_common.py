"""Pieces shared by the benchmark scripts in this folder.

The scripts run as ``python bench/<script>.py``; Python then puts this folder first on ``sys.path``,
so they import this module as plain ``_common``.

- the command line every benchmark has (:func:`parse_benchmark_args`: ``--repeat``, ``--quick``,
  ``--data-dir``, ``--markdown``) and the data folder it defaults to (:func:`default_data_dir`);
- input helpers (:func:`load_xyzi_bin`, :data:`QUICK_STRIDE`, :data:`SYNTHETIC_SEED`);
- timing (:func:`median_ms`; :func:`interleaved_median_ms` for calls compared by their ratio) and
  checks that survive ``python -O`` (:func:`require`);
- the report: the machine/software header (:func:`print_header`), a cloud's size line
  (:func:`describe_points`), MET / NOT MET target lines (:func:`print_target`) and Markdown table
  rows (:func:`markdown_row`, :func:`markdown_rule`).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import terracube as tc

REPO_ROOT = Path(__file__).resolve().parent.parent
SYNTHETIC_SEED = 20140708
QUICK_STRIDE = 4  # --quick keeps every 4th point of the files


# --------------------------------------------------------------------------------------------
# Command line and inputs
# --------------------------------------------------------------------------------------------


def default_data_dir() -> Path:
    """$TERRACUBE_DATA_DIR, else <repo>/../shared/data, else /work/shared/data."""
    env = os.environ.get("TERRACUBE_DATA_DIR")
    if env:
        return Path(env)
    sibling = REPO_ROOT.parent / "shared" / "data"
    return sibling if sibling.is_dir() else Path("/work/shared/data")


def parse_benchmark_args(
    description: str,
    argv: list[str] | None,
    *,
    repeat_unit: str,
    quick_help: str,
    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
    default_repeat: tuple[int, int] = (7, 3),
) -> argparse.Namespace:
    """Parse ``--repeat``, ``--quick``, ``--data-dir``, the script's own options, then ``--markdown``.

    ``repeat_unit`` names what ``--repeat`` counts runs of ("method", "step"); ``add_arguments``
    adds the script's own options (between ``--data-dir`` and ``--markdown`` in ``--help``).
    ``args.repeat`` defaults to ``default_repeat`` (7, and 3 with ``--quick``) and must be at least
    1; ``args.data_dir`` defaults to :func:`default_data_dir`.
    """
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument(
        "--repeat",
        type=int,
        default=None,
        help=f"timed runs per {repeat_unit} (default {default_repeat[0]}, {default_repeat[1]} with --quick)",
    )
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=None,
        help="data folder (default $TERRACUBE_DATA_DIR, <repo>/../shared/data, /work/shared/data)",
    )
    if add_arguments is not None:
        add_arguments(parser)
    parser.add_argument("--markdown", action="store_true", help="also print a Markdown table")
    args = parser.parse_args(argv)
    if args.repeat is None:
        args.repeat = default_repeat[1] if args.quick else default_repeat[0]
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    if args.data_dir is None:
        args.data_dir = default_data_dir()
    return args


def load_xyzi_bin(path: Path) -> np.ndarray:
    """A float32 x, y, z, intensity file as a strided (N, 3) view (no copy)."""
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3]


# --------------------------------------------------------------------------------------------
# Timing and checks
# --------------------------------------------------------------------------------------------


def median_ms(fn: Callable[[], object], repeat: int) -> float:
    """One warm-up call of ``fn``, then the median of ``repeat`` timed calls, in milliseconds."""
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3


def interleaved_median_ms(
    calls: dict[str, Callable[[], object]], repeat: int, run: int = 1
) -> dict[str, float]:
    """One warm-up call of each, then rounds timing every call ``run`` times in a row, in turn,
    until each has at least ``repeat`` timed calls: the median per call, in milliseconds.

    Calls timed in turn see the same stretch of a shared machine, whose speed drifts by tens of
    percent within seconds; their ratios then hold far better than those of back-to-back blocks.
    ``run`` > 1 keeps most calls after one of their own kind (a call that follows another kind can
    find the allocator in another state, e.g. memory just returned to the system).
    """
    for fn in calls.values():
        fn()  # warm-up
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(-(-repeat // run)):
        for name, fn in calls.items():
            for _ in range(run):
                start = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) * 1e3 for name, values in times.items()}


def require(condition: bool, message: str) -> None:
    """An assertion that survives ``python -O``."""
    if not condition:
        raise AssertionError(message)


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def cpu_model() -> str:
    """The CPU's model name from ``lscpu``, else what :mod:`platform` knows."""
    try:
        output = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=5, check=False).stdout
    except (OSError, subprocess.SubprocessError):
        output = ""
    for line in output.splitlines():
        if line.lower().startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown"


def header_line(field: str, text: str) -> str:
    """One ``  field   : text`` line of the header (the field padded to 8 characters)."""
    return f"  {field:<8}: {text}"


def core_build() -> str:
    """Where the timed C++ module comes from and when it was built: a bench times the installed
    ``terracube``, which a change to the C++ core does not update until it is installed again."""
    from terracube import _core

    path = Path(_core.__file__)
    built = datetime.datetime.fromtimestamp(path.stat().st_mtime).isoformat(timespec="minutes")
    return f"{path} (built {built})"


def print_header(
    title: str,
    details: Iterable[str],
    ratio: str,
    args: argparse.Namespace,
    quick_note: str,
    threads: str = "single-threaded",
) -> None:
    """The report's header: title, machine, software and date, the script's ``details`` lines
    (see :func:`header_line`), the timing rule with ``ratio = <ratio>``, and the data folder
    (followed by ``  (--quick: <quick_note>)`` with ``--quick``). ``threads`` says how the methods
    use threads."""
    print(title)
    print(
        header_line(
            "machine",
            f"{cpu_model()}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}",
        )
    )
    print(
        header_line(
            "software",
            f"python {platform.python_version()}, numpy {np.__version__}, terracube {tc.__version__}",
        )
    )
    print(header_line("core", core_build()))
    print(header_line("date", datetime.datetime.now().isoformat(timespec="seconds")))
    for line in details:
        print(line)
    print(header_line("timing", f"{threads}, median of {args.repeat} runs after 1 warm-up, milliseconds;"))
    print(f"            ratio = {ratio}")
    print(header_line("data", f"{args.data_dir}{f'  (--quick: {quick_note})' if args.quick else ''}"))


def processors() -> int:
    """The processors this process may run on (what ``num_threads=0`` uses)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def describe_points(points: np.ndarray) -> str:
    """``N = <count> points (<dtype>, contiguous|strided)``."""
    layout = "contiguous" if points.flags.c_contiguous else "strided"
    return f"N = {len(points):,} points ({points.dtype}, {layout})"


def print_target(
    label: str, values: list[float], ok: Callable[[float], bool], unit: str, suffix: str = ""
) -> None:
    """``  label: MET (v1, v2, ...)`` when ``ok`` holds for every value, else ``NOT MET``; ``n/a``
    without values. Values are shown with one decimal and ``unit``, then ``suffix``."""
    if not values:
        print(f"  {label}: n/a")
        return
    verdict = "MET" if all(ok(v) for v in values) else "NOT MET"
    shown = ", ".join(f"{v:.1f}{unit}" for v in values)
    print(f"  {label}: {verdict} ({shown}){suffix}")


def markdown_row(cells: Iterable[str]) -> str:
    """``| a | b | c |``; an empty cell is written as ``| |``."""
    return "|" + "|".join(f" {cell} " if cell else " " for cell in cells) + "|"


def markdown_rule(num_numeric: int) -> str:
    """The rule under a Markdown header: a left-aligned column, then ``num_numeric`` right-aligned."""
    return "|---|" + "---:|" * num_numeric
