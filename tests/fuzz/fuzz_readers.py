"""Seeded mutation fuzzing of terracube's Python readers (issue 39).

Every reader must answer a mutated file with points or a ``ValueError`` naming it (``ConfigError``,
a ValueError, for YAML), in bounded time and memory: never another exception type, a crash, a hang
or gigabytes. The seed corpus is small files of every format (written here from a synthetic cloud,
plus the bundled sample and a few small shared scans when present); the mutator flips bits, writes
boundary integers (0, -1, 2^31 - 1 ...) over header fields, truncates, repeats and splices, and
rewrites numbers in text formats.

Cases run in a worker subprocess under a memory limit (RLIMIT_AS) and a per-case alarm; the parent
restarts the worker when it crashes or stops answering, and records the case. atheris has no wheel
for this interpreter, hence the seeded mutator: a failure replays from its seed alone.

Used by ``tests/fuzz/run.py`` (a bounded run for CI) and ``tests/python/test_fuzz_quick.py``.
"""

from __future__ import annotations

import json
import os
import random
import resource
import select
import signal
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
MEMORY_LIMIT_BYTES = 3 << 30  # address space of the worker: the interpreter and libraries take ~1 GB
CASE_SECONDS = 10.0  # alarm per case; the parent waits a little longer before killing the worker
READ_SUFFIXES = (".las", ".laz", ".pcd", ".ply", ".bin", ".npz", ".npy", ".txt", ".yaml")
SHARED_SEEDS = ("forest_tls/TreeLS_pine.laz", "ouster128/ouster128_000000.pcd")


# ----------------------------------------------------------------------------------------- corpus


def package_root() -> Path:
    """The folder whose ``terracube`` package imports with its compiled core: the installed one
    (as scripts/setup.sh leaves it), else the source tree's ``python/`` (a developer's build)."""
    try:
        import terracube
    except ImportError:
        sys.path.insert(0, str(REPO / "python"))
        import terracube
    return Path(terracube.__file__).resolve().parents[1]


def build_corpus(folder: Path) -> list[Path]:
    """Small seed files of every readable format in ``folder``; returns their paths."""
    package_root()
    from terracube.config import dump_config
    from terracube.io import sample_scan_path, write_classified, write_pcd

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(39)
    xyz = np.c_[rng.uniform(0, 4, (300, 2)), rng.normal(0, 0.1, 300)]
    labels = rng.integers(0, 6, 300).astype(np.uint8)
    seeds = []
    for suffix in (".las", ".laz", ".ply", ".bin", ".npz", ".npy", ".txt"):
        seeds.append(write_classified(folder / f"synthetic{suffix}", xyz, labels))
    for encoding in ("ascii", "binary", "binary_compressed"):
        fields = {"xyz": xyz.astype(np.float32), "ring": labels.astype(np.uint16)}
        seeds.append(write_pcd(folder / f"synthetic_{encoding}.pcd", fields, encoding=encoding))
    (folder / "config.yaml").write_text(dump_config())
    seeds.append(folder / "config.yaml")
    sample = folder / "ouster128_sample.npz"
    sample.write_bytes(sample_scan_path().read_bytes())
    seeds.append(sample)
    data = _shared_data()
    if data is not None:
        for relative in SHARED_SEEDS:
            if (data / relative).is_file():
                seeds.append(folder / Path(relative).name)
                seeds[-1].write_bytes((data / relative).read_bytes())
        velodyne = data / "kitti_seq00" / "velodyne"
        scans = sorted(velodyne.glob("*.bin")) if velodyne.is_dir() else []
        if scans:  # the first 2,000 rows of a KITTI scan
            seeds.append(folder / "kitti.bin")
            seeds[-1].write_bytes(scans[0].read_bytes()[: 2000 * 16])
    return seeds


def _shared_data() -> Path | None:
    for candidate in (
        os.environ.get("TERRACUBE_DATA_DIR"),
        REPO.parent / "shared" / "data",
        "/work/shared/data",
    ):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


# ---------------------------------------------------------------------------------------- mutator

_BOUNDARY_INTS = (0, 1, 2, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF)
_TEXT_VALUES = (b"nan", b"inf", b"-1", b"1e308", b"99999999999999999999", b"", b"0x10", b"-0", b"1.5")


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One to four random edits of ``data``."""
    out = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        kind = rng.randrange(8)
        if not out:
            out += bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
        elif kind == 0:  # bit flip
            i = rng.randrange(len(out))
            out[i] ^= 1 << rng.randrange(8)
        elif kind == 1:  # a boundary integer over a (header) field
            width = rng.choice((1, 2, 4, 8))
            value = rng.choice(_BOUNDARY_INTS) & ((1 << (8 * width)) - 1)
            i = rng.randrange(min(len(out), 400)) if rng.random() < 0.7 else rng.randrange(len(out))
            out[i : i + width] = value.to_bytes(width, "little")
        elif kind == 2:  # truncate
            del out[rng.randrange(len(out)) :]
        elif kind == 3:  # random bytes
            i = rng.randrange(len(out))
            out[i : i + rng.randint(1, 16)] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        elif kind == 4:  # repeat a block
            i = rng.randrange(len(out))
            block = out[i : i + rng.randint(1, 256)]
            out[i:i] = block * rng.randint(1, 8)
        elif kind == 5:  # a double over a field
            i = rng.randrange(len(out))
            out[i : i + 8] = struct.pack("<d", rng.choice((float("nan"), float("inf"), -1e308, 1e-320, 0.0)))
        elif kind == 6:  # text: a number token replaced
            tokens = [t for t in out.split() if t[:1].isdigit() or t[:1] in b"-."]
            if tokens:
                token = rng.choice(tokens)
                at = out.find(token)
                out[at : at + len(token)] = rng.choice(_TEXT_VALUES)
        else:  # delete a range
            i = rng.randrange(len(out))
            del out[i : i + rng.randint(1, 64)]
    return bytes(out)


# ----------------------------------------------------------------------------------------- worker

REFUSALS = (ValueError, FileNotFoundError)  # what a reader may answer a bad file with


def answer_case(path: str) -> None:
    """One reader case: the file at `path` read as a cloud, or as a config when it is YAML."""
    from terracube.config import load_config
    from terracube.io import read_cloud

    if path.endswith(".yaml"):
        load_config(path)
    else:
        read_cloud(path)


# A fuzzer's worker: `module` (this one or fuzz_api) answers one case a line with answer_case();
# its REFUSALS are "rejected", anything else a failure.
WORKER = """
import json, signal, sys
sys.path.insert(0, {python!r})
sys.path.insert(0, {fuzz!r})
from {module} import REFUSALS, answer_case

class Alarm(Exception):
    pass

def on_alarm(*_):
    raise Alarm()

signal.signal(signal.SIGALRM, on_alarm)
print(json.dumps({{"ready": True}}), flush=True)
for line in sys.stdin:
    signal.alarm({alarm})
    try:
        answer_case(line.strip())
        outcome = {{"outcome": "read"}}
    except REFUSALS:
        outcome = {{"outcome": "rejected"}}
    except Alarm:
        outcome = {{"outcome": "failure", "error": "alarm: no answer within {alarm} s"}}
    except BaseException as error:
        outcome = {{"outcome": "failure", "error": f"{{type(error).__name__}}: {{str(error)[:300]}}"}}
    finally:
        signal.alarm(0)
    print(json.dumps(outcome), flush=True)
"""


class Worker:
    """A subprocess that answers one case per line it is sent with `module`'s answer_case() (this
    module's file reader, or fuzz_api's calls), under a memory limit and a per-case alarm."""

    def __init__(
        self,
        stderr: Path,
        module: str = "fuzz_readers",
        memory_limit: int = MEMORY_LIMIT_BYTES,
        case_seconds: float = CASE_SECONDS,
    ):
        code = WORKER.format(
            python=str(package_root()),
            fuzz=str(Path(__file__).resolve().parent),
            module=module,
            alarm=int(case_seconds),
        )
        self.stderr_path = stderr
        self.case_seconds = case_seconds

        def limit_memory() -> None:
            resource.setrlimit(resource.RLIMIT_AS, (memory_limit, memory_limit))

        with stderr.open("w") as sink:  # a file, not a pipe nobody reads (which could fill and block)
            self.process = subprocess.Popen(
                [sys.executable, "-c", code],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=sink,
                text=True,
                preexec_fn=limit_memory,
            )
        if self._answer(120.0) != {"ready": True}:
            raise RuntimeError(f"the fuzz worker did not start: {self.stop()}")

    def _answer(self, seconds: float) -> dict | None:
        ready, _, _ = select.select([self.process.stdout], [], [], seconds)
        line = self.process.stdout.readline() if ready else ""
        return json.loads(line) if line else None

    def run(self, case: Path | str) -> dict:
        """{"outcome": "read" | "rejected" | "failure", "error": ...} for one case (a file's path,
        or the API fuzzer's case seed); after a failure that is not an exception (crash, hang) the
        worker is gone and a new one must be made."""
        self.process.stdin.write(f"{case}\n")
        self.process.stdin.flush()
        answer = self._answer(self.case_seconds + 20.0)
        if answer is not None:
            return answer
        return {"outcome": "failure", "error": self.stop(), "worker_lost": True}

    def stop(self) -> str:
        """Ends the worker; says how it ended."""
        try:
            code = self.process.wait(timeout=5)
            how = f"died of {signal.Signals(-code).name}" if code < 0 else f"exited with code {code}"
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            how = "hang: no answer, killed"
        lines = self.stderr_path.read_text(errors="replace").strip().splitlines()
        return how + (f"; stderr starts: {' | '.join(lines[:3])[:300]}" if lines else "")

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.stdin.close()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.stop()


@dataclass
class Finding:
    seed_file: str
    case_seed: int
    path: str
    error: str


def fuzz(
    seeds: list[Path], work: Path, *, seed: int, cases: int | None, seconds: float | None
) -> tuple[int, list[Finding]]:
    """Run mutated cases until ``cases`` are done or ``seconds`` have passed; keeps each failing
    case as ``work/findings/<seed file>-<case seed><suffix>``. Returns (cases run, findings)."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "findings").mkdir(exist_ok=True)
    originals = {path: path.read_bytes() for path in seeds}
    master = random.Random(seed)
    worker = Worker(work / "worker-stderr.txt")
    findings: list[Finding] = []
    start, done = time.monotonic(), 0
    try:
        while (cases is None or done < cases) and (seconds is None or time.monotonic() - start < seconds):
            source = seeds[done % len(seeds)]
            case_seed = master.randrange(2**32)
            case = work / f"case{source.suffix}"
            case.write_bytes(mutate(originals[source], random.Random(case_seed)))
            answer = worker.run(case)
            done += 1
            if answer["outcome"] == "failure":
                kept = work / "findings" / f"{source.stem}-{case_seed}{source.suffix}"
                kept.write_bytes(case.read_bytes())
                findings.append(Finding(source.name, case_seed, str(kept), answer["error"]))
                if answer.get("worker_lost"):
                    worker = Worker(work / "worker-stderr.txt")
    finally:
        worker.close()
    return done, findings


def replay(seed_file: Path, case_seed: int) -> bytes:
    """The mutated bytes of one case, from its seed file and case seed."""
    return replay_bytes(seed_file.read_bytes(), case_seed)


def replay_bytes(data: bytes, case_seed: int) -> bytes:
    return mutate(data, random.Random(case_seed))
