"""Run one stage over many scans in parallel with Dask distributed.

Each scan is one task: read it, run the stage (:func:`terracube.cli.run_stage`), write the outputs
to one folder, and return a :class:`FileRecord`. A task never raises: a file that fails comes back
with ``status == "failed"`` and its error, and the others go on. The tasks run on a
``LocalCluster`` (processes by default; ``workers`` of them) or on a running cluster given by its
scheduler address.

Example
-------
>>> from terracube.batch import run_batch, format_summary
>>> records = run_batch("dem", ["scans/"], "out", workers=2)
>>> print(format_summary(records))
"""

from __future__ import annotations

import glob
import time
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["FileRecord", "expand_inputs", "process_file", "run_batch", "format_summary", "SCAN_SUFFIXES"]

#: Suffixes of the scans a folder contributes (the readable point-cloud formats).
SCAN_SUFFIXES = (".pcd", ".ply", ".las", ".laz", ".bin", ".npy", ".npz", ".txt", ".xyz", ".csv", ".asc")


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


def expand_inputs(inputs: Iterable[str | Path]) -> list[Path]:
    """The scans named by ``inputs``: files as given, folders' scans (by suffix, sorted), glob matches.

    Duplicates are dropped, order kept. ValueError when an input matches nothing or no scan at all.
    """
    files: list[Path] = []
    for item in inputs:
        path = Path(item)
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES)
            if not found:
                raise ValueError(f"{path}: the folder holds no scan ({', '.join(SCAN_SUFFIXES)})")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        elif glob.has_magic(str(item)):
            found = sorted(Path(p) for p in glob.glob(str(item), recursive=True) if Path(p).is_file())
            if not found:
                raise ValueError(f"{item}: the pattern matches no file")
            files.extend(found)
        else:
            raise ValueError(f"{path}: no such file or folder")
    unique = list(dict.fromkeys(files))
    if not unique:
        raise ValueError("no scan to process")
    return unique


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
        from .cli import run_stage
        from .io import read_points

        points = read_points(path)
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


def _client(scheduler: str | None, workers: int | None, processes: bool):
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as error:  # pragma: no cover - dask[distributed] is a dependency
        raise ImportError("batch processing needs Dask: pip install 'dask[distributed]'") from error
    if scheduler is not None:
        return Client(scheduler), None
    # Worker processes talk over TCP on the loopback interface only; threads use in-process transport.
    where = {"host": "127.0.0.1"} if processes else {}
    cluster = LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=processes, dashboard_address=None, **where
    )
    return Client(cluster), cluster


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
) -> list[FileRecord]:
    """Run ``stage`` (collapse, dem, classify or fem) on every scan of ``inputs`` with Dask.

    Parameters
    ----------
    inputs
        Files, folders (their scans) and glob patterns; see :func:`expand_inputs`.
    output_dir
        Every file's outputs go here, named after the file (``NAME_dem.npz`` ...).
    config
        A :class:`terracube.config.Config`; the defaults when None.
    options
        The stage's output options (see :func:`terracube.cli.run_stage`).
    scheduler
        Address of a running Dask scheduler; None starts a ``LocalCluster`` on 127.0.0.1.
    workers, processes
        Workers of the local cluster (None: Dask's default, one per core) and whether they are
        processes (default) or threads of this process.
    progress
        Show a tqdm bar on stderr as files finish.

    Returns
    -------
    list of FileRecord
        One per scan, in input order; failed files have ``status == "failed"`` and ``error``.
    """
    from .cli import BATCH_STAGES

    if stage not in BATCH_STAGES:
        raise ValueError(f"unknown stage {stage!r}: batch runs {', '.join(BATCH_STAGES)}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    files = expand_inputs(inputs)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    names: dict[str, int] = {}
    jobs = [(path, _output_name(path, names)) for path in files]

    from dask.distributed import as_completed
    from tqdm import tqdm

    client, cluster = _client(scheduler, workers, processes)
    records: dict[int, FileRecord] = {}
    try:
        futures = {
            client.submit(
                process_file,
                stage,
                str(path.resolve()),
                str(output_dir.resolve()),
                config,
                options,
                name,
                key=f"terracube-{stage}-{index}-{name}",
                pure=False,
            ): index
            for index, (path, name) in enumerate(jobs)
        }
        bar = tqdm(total=len(futures), desc=stage, unit="scan", disable=not progress)
        failed = 0
        for future in as_completed(futures):
            index = futures[future]
            if future.status == "finished":
                record = future.result()
                record.path = str(jobs[index][0])
            else:  # the task itself died (worker lost, unpicklable result ...)
                error = future.exception()
                record = FileRecord(
                    str(jobs[index][0]), stage, "failed", error=f"{jobs[index][0]}: {error!r}"
                )
            records[index] = record
            failed += not record.ok
            bar.set_postfix(failed=failed, refresh=False)
            bar.update(1)
        bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return [records[index] for index in range(len(jobs))]


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
