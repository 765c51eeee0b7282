"""Run one stage over many scans in parallel: a local process pool, or Dask.

Each scan is one task: read it, run the stage (:func:`terracube.pipeline.run_stage`), write the
outputs to one folder, and return a :class:`FileRecord`. A task never raises: a file that fails
comes back with ``status == "failed"`` and its error, and the others go on. The tasks run on a
``concurrent.futures`` pool of this machine (processes by default) or, with the ``batch`` extra
(``dask[distributed]``), on a Dask ``LocalCluster`` or a running cluster given by its scheduler
address.

Example
-------
>>> from terracube.batch import run_batch, format_summary
>>> records = run_batch("dem", ["scans/"], "out", workers=2)
>>> print(format_summary(records))
"""

from __future__ import annotations

import multiprocessing
import time
import traceback
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures import as_completed as as_completed_futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .pipeline import SCAN_SUFFIXES, STAGES, expand_inputs, read_scan, run_stage

__all__ = ["FileRecord", "expand_inputs", "process_file", "run_batch", "format_summary", "SCAN_SUFFIXES"]


@dataclass
class FileRecord:
    """The outcome of one scan: ``status`` is ``"ok"`` or ``"failed"`` (then ``error`` says why)."""

    path: str
    stage: str
    status: str
    points: int | None = None
    seconds: float = 0.0
    outputs: list[str] = field(default_factory=list)
    error: str | None = None
    lines: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _output_name(path: Path, names: dict[str, int]) -> str:
    """The file's stem, made unique when two scans share it (a_1, a_2 ...)."""
    stem = path.stem
    count = names.get(stem, 0)
    names[stem] = count + 1
    return stem if count == 0 else f"{stem}_{count}"


def process_file(
    stage: str,
    path: str | Path,
    output_dir: str | Path,
    config=None,
    options: dict[str, Any] | None = None,
    name: str | None = None,
) -> FileRecord:
    """Run ``stage`` on one scan; never raises (a failure is a record with its error)."""
    path = Path(path)
    start = time.perf_counter()
    record = FileRecord(str(path), stage, "failed")
    try:
        points = read_scan(path)
        record.points = int(len(points))
        report = run_stage(stage, points, name or path.stem, Path(output_dir), config, **(options or {}))
        record.outputs = [str(p) for p in report.outputs]
        record.lines = list(report.lines)
        record.status = "ok"
    except (ValueError, FileNotFoundError, KeyError, TypeError, OSError) as error:
        record.error = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)
        if str(path) not in record.error:
            record.error = f"{path}: {record.error}"
    except Exception as error:  # anything else: still a record, with where it came from
        last = traceback.extract_tb(error.__traceback__)[-1]
        record.error = f"{path}: {type(error).__name__}: {error} ({Path(last.filename).name}:{last.lineno})"
    record.seconds = time.perf_counter() - start
    return record


BACKENDS = ("auto", "dask", "pool")


def _dask_available() -> bool:
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        return False
    return True


def _dask_jobs(submit_args, scheduler, workers, processes):
    """Yield (index, record or exception) as the Dask tasks finish."""
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as error:
        raise ImportError("batch on Dask needs the batch extra: pip install 'terracube[batch]'") from error
    if scheduler is not None:
        client, cluster = Client(scheduler), None
    else:  # worker processes talk over TCP on the loopback interface only
        where = {"host": "127.0.0.1"} if processes else {}
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=None, **where
        )
        client = Client(cluster)
    try:
        futures = {
            client.submit(
                process_file, *args, key=f"terracube-{args[0]}-{index}-{args[-1]}", pure=False
            ): index
            for index, args in enumerate(submit_args)
        }
        for future in as_completed(futures):
            outcome = future.result() if future.status == "finished" else future.exception()
            yield futures[future], outcome
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _pool_jobs(submit_args, workers, processes):
    """Yield (index, record or exception) as the local pool's tasks finish."""
    if processes:  # spawn: a fork would copy this process's threads' state into the workers
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))
    else:
        pool = ThreadPoolExecutor(max_workers=workers)
    with pool:
        futures = {pool.submit(process_file, *args): index for index, args in enumerate(submit_args)}
        for future in as_completed_futures(futures):
            error = future.exception()
            yield futures[future], error if error is not None else future.result()


def run_batch(
    stage: str,
    inputs: Sequence[str | Path],
    output_dir: str | Path,
    *,
    config=None,
    options: dict[str, Any] | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    progress: bool = True,
    backend: str = "auto",
) -> list[FileRecord]:
    """Run ``stage`` (collapse, dem, classify or fem) on every scan of ``inputs`` in parallel.

    Parameters
    ----------
    stage
        One of :data:`terracube.pipeline.STAGES`.
    inputs
        Files, folders (their scans) and glob patterns; see :func:`terracube.pipeline.expand_inputs`.
    output_dir
        Every file's outputs go here, named after the file (``NAME_dem.npz`` ...).
    config
        A :class:`terracube.config.Config`; the defaults when None.
    options
        The stage's output options (see :func:`terracube.pipeline.run_stage`).
    scheduler
        Address of a running Dask scheduler (needs the ``batch`` extra); None runs on this machine.
    workers, processes
        Local workers (None: one per core) and whether they are processes (default) or threads of
        this process.
    progress
        Show a tqdm bar on stderr as files finish.
    backend
        ``"dask"`` (a Dask ``LocalCluster`` or ``scheduler``), ``"pool"`` (a ``concurrent.futures``
        pool) or ``"auto"``: Dask when a scheduler is given or Dask is installed, else the pool.

    Returns
    -------
    list of FileRecord
        One per scan, in input order; failed files have ``status == "failed"`` and ``error``.
    """
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}: batch runs {', '.join(STAGES)}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "pool" and scheduler is not None:
        raise ValueError("a Dask scheduler needs the dask backend")
    files = expand_inputs(inputs)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    names: dict[str, int] = {}
    submit_args = [
        (stage, str(path.resolve()), str(output_dir.resolve()), config, options, _output_name(path, names))
        for path in files
    ]
    if backend == "auto":
        backend = "dask" if scheduler is not None or _dask_available() else "pool"
    if backend == "dask":
        jobs = _dask_jobs(submit_args, scheduler, workers, processes)
    else:
        jobs = _pool_jobs(submit_args, workers, processes)

    from tqdm import tqdm

    records: dict[int, FileRecord] = {}
    with tqdm(total=len(files), desc=stage, unit="scan", disable=not progress) as bar:
        for index, outcome in jobs:
            path = files[index]
            if isinstance(outcome, FileRecord):
                outcome.path = str(path)
                records[index] = outcome
            else:  # the task itself died (worker lost, unpicklable result ...)
                records[index] = FileRecord(str(path), stage, "failed", error=f"{path}: {outcome!r}")
            bar.set_postfix(failed=sum(not r.ok for r in records.values()), refresh=False)
            bar.update(1)
    return [records[index] for index in range(len(files))]


def format_summary(records: Sequence[FileRecord], *, width: int = 70) -> str:
    """A plain-text table: file, points, status, seconds, outputs (or the error), and a total line."""
    header = ("file", "points", "status", "seconds", "outputs")
    rows = []
    for r in records:
        detail = ", ".join(Path(p).name for p in r.outputs) if r.ok else (r.error or "")
        if len(detail) > width:
            detail = detail[: width - 3] + "..."
        rows.append(
            (
                Path(r.path).name,
                "-" if r.points is None else f"{r.points:,}",
                r.status,
                f"{r.seconds:.2f}",
                detail,
            )
        )
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(header)]
    align = ["<", ">", "<", ">", "<"]

    def line(cells) -> str:
        return "  ".join(f"{c:{a}{w}}" for c, a, w in zip(cells, align, widths, strict=True)).rstrip()

    out = [line(header), line(["-" * w for w in widths])]
    out += [line(row) for row in rows]
    ok = sum(r.ok for r in records)
    total_points = sum(r.points or 0 for r in records if r.ok)
    for r in records:
        if not r.ok:
            out.append(f"failed: {r.error}")
    out.append(
        f"{ok} of {len(records)} files ok, {len(records) - ok} failed; {total_points:,} points; "
        f"{sum(r.seconds for r in records):.2f} s of work"
    )
    return "\n".join(out)
