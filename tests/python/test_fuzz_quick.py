"""A short, fixed run of the reader fuzzer (tests/fuzz/): 150 seeded mutations over every readable
format must each give points or a ValueError, in a worker under a memory limit and an alarm. The
longer run is ``python tests/fuzz/run.py --seconds 60``."""

from __future__ import annotations

import sys
from pathlib import Path

FUZZ_DIR = Path(__file__).resolve().parents[1] / "fuzz"
sys.path.insert(0, str(FUZZ_DIR))

import fuzz_readers  # noqa: E402


def test_the_mutator_is_deterministic_for_a_seed():
    data = bytes(range(256)) * 4
    assert fuzz_readers.replay_bytes(data, 7) == fuzz_readers.replay_bytes(data, 7)
    assert fuzz_readers.replay_bytes(data, 7) != fuzz_readers.replay_bytes(data, 8)


def test_150_seeded_mutations_give_points_or_a_value_error(tmp_path):
    seeds = fuzz_readers.build_corpus(tmp_path / "corpus")
    assert {path.suffix for path in seeds} >= set(fuzz_readers.READ_SUFFIXES)
    done, findings = fuzz_readers.fuzz(seeds, tmp_path, seed=39, cases=150, seconds=None)
    assert done == 150
    assert findings == [], "\n".join(f"{f.seed_file} (case seed {f.case_seed}): {f.error}" for f in findings)
