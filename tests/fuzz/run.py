#!/usr/bin/env python3
"""Fuzz terracube for a bounded time: ``python tests/fuzz/run.py --seconds 60 [--target api]``.

``--target readers`` (the default) mutates files of every format: exits 1 when one gave anything but
points or a ValueError (another exception, a crash, a hang, memory beyond the limit); the failing
files are kept in ``--work``/findings with the seed to replay them (``fuzz_readers.replay``).
``--target api`` calls the Python API with hostile clouds, poses and parameters (``fuzz_api``):
exits 1 when a call gave anything but a result or a ValueError/TypeError/KeyError; a failing case
replays with ``fuzz_api.run_case(case_seed)``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import fuzz_api  # noqa: E402
from fuzz_readers import build_corpus, fuzz  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="how long to fuzz [s] (default 60)")
    parser.add_argument("--cases", type=int, default=None, help="stop after this many cases")
    parser.add_argument("--seed", type=int, default=0, help="seed of the whole run (default 0)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the corpus and findings")
    parser.add_argument("--target", choices=("readers", "api"), default="readers", help="what to fuzz")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="terracube-fuzz-"))
    if args.target == "api":
        done, failures = fuzz_api.fuzz(work, seed=args.seed, cases=args.cases, seconds=args.seconds)
        print(f"fuzz api: {done} cases from seed {args.seed}, {len(failures)} failures")
        for case_seed, error in failures:
            print(f"  case seed {case_seed}: {error}")
        return 1 if failures else 0
    seeds = build_corpus(work / "corpus")
    done, findings = fuzz(seeds, work, seed=args.seed, cases=args.cases, seconds=args.seconds)
    print(f"fuzz: {done} cases over {len(seeds)} seed files (seed {args.seed}), {len(findings)} failures")
    for finding in findings:
        print(
            f"  {finding.seed_file} case seed {finding.case_seed}: {finding.error}\n    kept: {finding.path}"
        )
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
