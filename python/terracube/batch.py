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
>>> records = run_batch("dem", ["scans/"], "out", workers=2)  # in a script: under if __name__ == "__main__":
>>> print(format_summary(records))
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
import traceback
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .pipeline import SCAN_SUFFIXES, STAGES, expand_inputs, read_stage_input, run_stage

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
        points, no_returns = read_stage_input(path, config)
        record.points = int(len(points))
        report = run_stage(
            stage,
            points,
            name or path.stem,
            Path(output_dir),
            config,
            source=path,
            no_returns=no_returns,
            **(options or {}),
        )
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

#: Seconds one file may take before its worker is stopped and the file reported as timed out.
DEFAULT_TIMEOUT_S = 600.0


def _timed_out(timeout: float, stopped: bool = True) -> str:
    worker = (
        "its worker was stopped" if stopped else "its worker thread, which cannot be stopped, was given up"
    )
    return f"timed out after {timeout:g} s ({worker}; raise --timeout for bigger scans)"


def _died(exitcode: int | None) -> str:
    """Why a worker process ended without a result: its signal or exit code."""
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        cause = {"SIGKILL": "killed, e.g. out of memory", "SIGSEGV": "a crash", "SIGABRT": "an abort"}
        return f"its worker process died of {name} ({cause.get(name, 'a signal')}) while running it"
    return f"its worker process exited with code {exitcode} while running it"


def _dask_available() -> bool:
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        return False
    return True


def _dask_jobs(submit_args, scheduler, workers, processes, timeout) -> Iterator[tuple[int, Any, float]]:
    """Yield (index, record, or the task's exception or failure text, seconds since the task was
    submitted) as the Dask tasks finish. Dask's own log lines below ERROR (a nanny restarting a
    worker after a timeout ...) are kept off the console while it runs.

    At most one task per worker thread is submitted at a time, so a task's clock starts when it
    starts. A task past ``timeout`` is reported and its worker restarted (a thread cannot be
    stopped: then that worker thread is given up, and the files left fail once none is left)."""
    try:
        import dask.distributed  # noqa: F401
        from distributed.utils import silence_logging_cmgr
    except ImportError as error:
        raise ImportError("batch on Dask needs the batch extra: pip install 'terracube[batch]'") from error
    with silence_logging_cmgr(logging.ERROR):  # this process's Dask log handlers, restored on exit
        yield from _dask_tasks(submit_args, scheduler, workers, processes, timeout)


def _dask_tasks(submit_args, scheduler, workers, processes, timeout) -> Iterator[tuple[int, Any, float]]:
    """:func:`_dask_jobs` once Dask is imported and its logs quieted."""
    from dask.distributed import Client, LocalCluster, wait

    slots = initial_slots = 0
    if scheduler is not None:
        client, cluster = Client(scheduler), None
    else:  # worker processes talk over TCP on the loopback interface only
        where = {"host": "127.0.0.1"} if processes else {}
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=processes,
            dashboard_address=None,
            silence_logs=logging.ERROR,  # the same in the workers and their nannies
            **where,
        )
        client = Client(cluster)
    try:
        slots = initial_slots = max(sum(client.nthreads().values()), 1)
        pending = list(enumerate(submit_args))[::-1]
        running: dict[Any, tuple[int, float, float]] = {}
        while pending or running:
            while pending and len(running) < slots:
                index, args = pending.pop()
                future = client.submit(
                    process_file, *args, key=f"terracube-{args[0]}-{index}-{args[-1]}", pure=False
                )
                start = time.monotonic()
                running[future] = (index, start + timeout if timeout else math.inf, start)
            if not running:  # every worker thread is stuck on a file that timed out
                for index, _ in pending[::-1]:
                    yield index, "not run: every worker was stuck on a file that timed out", 0.0
                return
            first = min(deadline for _, deadline, _ in running.values())
            try:
                done, _ = wait(
                    list(running),
                    timeout=None if first == math.inf else max(first - time.monotonic(), 0.01),
                    return_when="FIRST_COMPLETED",
                )
            except TimeoutError:
                done = set()
            for future in done:
                index, _, start = running.pop(future)
                outcome = future.result() if future.status == "finished" else future.exception()
                yield index, outcome, time.monotonic() - start
            now = time.monotonic()
            for future, (index, deadline, start) in list(running.items()):
                if now < deadline:
                    continue
                del running[future]
                holders = [w for w, keys in client.processing().items() if future.key in keys]
                future.cancel()
                try:
                    if not processes or not holders:
                        raise RuntimeError("a thread cannot be stopped")
                    client.restart_workers(holders, timeout=60)
                    stopped = True
                except Exception:  # noqa: BLE001 - any failure to restart: give that thread up
                    slots, stopped = slots - 1, False
                yield index, _timed_out(timeout, stopped), now - start
    finally:
        client.close()
        if cluster is not None:
            try:  # a worker thread given up would hold a plain close() for 30 s
                cluster.close(timeout=5 if slots < initial_slots else None)
            except Exception:  # noqa: BLE001 - closing a cluster with a stuck thread
                pass


_STARTUP_S = 120.0  # time a new worker process may take to import terracube, on top of the timeout
_READY = "ready"  # a new worker process's first message: its files' clocks start then, not at spawn


def _worker_loop(connection) -> None:
    """A local worker process: run the tasks sent on ``connection`` and send back their records."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    connection.send(_READY)
    while True:
        try:
            args = connection.recv()
        except EOFError:
            return
        if args is None:
            return
        connection.send(process_file(*args))


def _thread_task(connection, args: tuple) -> None:
    record = process_file(*args)
    try:
        connection.send(record)
    except OSError:  # timed out meanwhile: nobody listens any more
        pass


class _Slot:
    """One local worker: a process that a timeout can kill (and replace), or a daemon thread per
    task that a timeout abandons (threads cannot be stopped)."""

    def __init__(self, processes: bool):
        self.processes = processes
        self.process = None
        self.connection = None
        self.index: int | None = None
        self.deadline = math.inf
        self.clock = 0.0  # when the task's clock (the one its timeout counts on) started
        self.ready = False  # a worker process has imported terracube

    def start(self, index: int, args: tuple, timeout: float | None) -> None:
        if self.processes:
            if self.process is not None and not self.process.is_alive():  # died while idle
                self.process.join()
                self._forget_process()
            if self.process is None:
                context = multiprocessing.get_context("spawn")  # a fork would copy our threads' state
                self.connection, child = context.Pipe()
                self.process = context.Process(target=_worker_loop, args=(child,), daemon=True)
                self.process.start()
                child.close()
            self.connection.send(args)
        else:
            self.connection, child = multiprocessing.Pipe(duplex=False)
            threading.Thread(target=_thread_task, args=(child, args), daemon=True).start()
        self.index = index
        self.ready = self.processes is False or self.ready
        # a new worker's clock starts when it has imported terracube (then _READY resets it), but
        # a worker that never gets there is stopped too
        startup = 0.0 if self.ready else _STARTUP_S
        self.clock = time.monotonic()
        self.deadline = self.clock + timeout + startup if timeout else math.inf

    def waitables(self) -> list:
        return [self.connection] + ([self.process.sentinel] if self.process is not None else [])

    def outcome(self, timeout: float | None) -> Any:
        """The task's record or failure text once it has one, else None."""
        if self.connection.poll():
            try:
                message = self.connection.recv()
                if not (isinstance(message, str) and message == _READY):
                    return message
                self.ready = True
                self.clock = time.monotonic()
                self.deadline = self.clock + timeout if timeout else math.inf
                return None
            except EOFError:
                pass
            except Exception as error:  # noqa: BLE001 - e.g. an unpicklable result
                return error
        if self.process is not None and not self.process.is_alive():
            self.process.join()
            text = _died(self.process.exitcode)
            self._forget_process()
            return text
        if time.monotonic() >= self.deadline:
            self.stop()
            return _timed_out(timeout, stopped=self.processes)
        return None

    def stop(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.join()
            self._forget_process()

    def close(self) -> None:
        if self.process is not None:
            try:
                self.connection.send(None)
            except OSError:
                pass
            self.process.join(timeout=5)
            self.stop()

    def _forget_process(self) -> None:
        self.connection.close()
        self.process, self.connection, self.ready = None, None, False


def _pool_jobs(submit_args, workers, processes, timeout) -> Iterator[tuple[int, Any, float]]:
    """Yield (index, record or failure text, seconds on the file's clock) as the local workers
    finish their files."""
    workers = max(min(workers or os.cpu_count() or 1, len(submit_args)), 1)
    slots = [_Slot(processes) for _ in range(workers)]
    pending = list(enumerate(submit_args))[::-1]
    try:
        while True:
            for slot in slots:
                if slot.index is None and pending:
                    slot.start(*pending.pop(), timeout)
            busy = [slot for slot in slots if slot.index is not None]
            if not busy:
                return
            first = min(slot.deadline for slot in busy)
            wait_s = None if first == math.inf else max(first - time.monotonic(), 0.0)
            multiprocessing.connection.wait([w for slot in busy for w in slot.waitables()], timeout=wait_s)
            for slot in busy:
                outcome = slot.outcome(timeout)
                if outcome is not None:
                    index, slot.index = slot.index, None
                    yield index, outcome, time.monotonic() - slot.clock
    finally:
        for slot in slots:
            slot.close()


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
    timeout: float | None = DEFAULT_TIMEOUT_S,
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
        The stage's output options (see :func:`terracube.pipeline.run_stage`). Like ``terracube
        batch``, no pictures unless ``{"png": True}`` (they take most of the time).
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
    timeout
        Seconds one file may take [s]; past it the file fails as timed out and its worker process
        is stopped and replaced (a worker thread cannot be stopped: it is given up). None or 0: no
        limit.

    Returns
    -------
    list of FileRecord
        One per scan, in input order; failed files have ``status == "failed"`` and ``error``.

    Notes
    -----
    Worker processes are spawned: each imports the calling script again, so a script must call
    ``run_batch`` under ``if __name__ == "__main__":`` (a call while a worker imports it raises
    RuntimeError saying so).
    """
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise RuntimeError(
            "run_batch was called while a spawned worker process imported the calling script: "
            'put the call under `if __name__ == "__main__":`'
        )
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}: batch runs {', '.join(STAGES)}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if timeout is not None and not timeout >= 0:
        raise ValueError(f"timeout must be a number of seconds >= 0 (0: no limit), got {timeout}")
    if backend == "pool" and scheduler is not None:
        raise ValueError("a Dask scheduler needs the dask backend")
    options = {"png": False, **(options or {})}
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
        jobs = _dask_jobs(submit_args, scheduler, workers, processes, timeout or None)
    else:
        jobs = _pool_jobs(submit_args, workers, processes, timeout or None)

    from tqdm import tqdm

    records: dict[int, FileRecord] = {}
    with tqdm(total=len(files), desc=stage, unit="scan", disable=not progress) as bar:
        for index, outcome, seconds in jobs:
            path = files[index]
            if isinstance(outcome, FileRecord):
                outcome.path = str(path)
                records[index] = outcome
            else:  # no record: timed out, its worker died (text), or Dask's exception for the task
                records[index] = FileRecord(
                    str(path), stage, "failed", seconds=seconds, error=f"{path}: {_cause(outcome)}"
                )
            bar.set_postfix(failed=sum(not r.ok for r in records.values()), refresh=False)
            bar.update(1)
    return [records[index] for index in range(len(files))]


def _cause(outcome: Any) -> str:
    if isinstance(outcome, str):
        return outcome
    if type(outcome).__name__ == "KilledWorker":  # Dask: every worker that tried it died
        return (
            "every Dask worker that ran it died (out of memory or a crash; run the file alone with "
            f"'terracube STAGE FILE' to see why): {outcome}"
        )
    return f"{type(outcome).__name__}: {outcome}"


#: Report lines :func:`format_summary` repeats under the table, per file.
_NOTE_PREFIXES = ("note:", "warning:", "range filter:", "ground reference:")


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
    for r in records:  # what each file's report flags: points left out, the ground reference, warnings
        for note in r.lines:
            text = note.strip()
            if text.startswith(_NOTE_PREFIXES):
                out.append(f"{Path(r.path).name}: {text}")
    out.append(
        f"{ok} of {len(records)} files ok, {len(records) - ok} failed; {total_points:,} points; "
        f"{sum(r.seconds for r in records):.2f} s of work"
    )
    return "\n".join(out)
