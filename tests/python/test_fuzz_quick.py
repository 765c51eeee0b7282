"""Short, fixed runs of the fuzzers (tests/fuzz/): 150 seeded mutations over every readable format
must each give points or a ValueError, and 120 seeded API calls with hostile clouds, poses and
parameters a result or a ValueError/TypeError/KeyError, in a worker under a memory limit and an
alarm. The longer runs are ``python tests/fuzz/run.py --seconds 60 [--target api]``."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

FUZZ_DIR = Path(__file__).resolve().parents[1] / "fuzz"
sys.path.insert(0, str(FUZZ_DIR))

import fuzz_api  # noqa: E402
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


def test_120_seeded_api_calls_give_a_result_or_a_named_refusal(tmp_path):
    done, failures = fuzz_api.fuzz(tmp_path, seed=0, cases=120, seconds=None)
    assert done == 120
    assert failures == [], "\n".join(f"case seed {seed}: {error}" for seed, error in failures)


def test_an_api_case_is_drawn_from_its_seed_alone():
    first, again = (fuzz_api.cloud(np.random.default_rng(11)) for _ in range(2))
    np.testing.assert_array_equal(first, again)


def test_hostile_clouds_read_as_wider_rows_give_what_their_x_y_z_give():
    """The fuzzer's hostile clouds (NaN rows, 1e300 spreads, float32 extremes, Fortran order) with
    extra columns: collapse_overhangs and build_elevation_map answer as for an (N, 3) copy of their
    x, y, z, or refuse it with the same error."""
    import terracube as tc

    def outcome(call, points):
        try:
            return call(points)
        except (ValueError, TypeError) as error:
            return type(error).__name__, str(error).split(" got shape")[0]

    checked = 0
    for seed in range(400):
        rng = np.random.default_rng(seed)
        rows = fuzz_api.cloud(rng)
        if rows.ndim != 2 or not 3 < rows.shape[1] <= 16 or rows.shape[0] > 5000:
            continue
        xyz = np.ascontiguousarray(rows[:, :3])
        for call in (
            lambda p: tc.collapse_overhangs(p, drop_non_finite=True).overhang,
            lambda p: tc.build_elevation_map(p, 0.5, drop_non_finite=True)["max"],
        ):
            wide, plain = outcome(call, rows), outcome(call, xyz)
            if isinstance(plain, tuple):
                assert wide == plain, seed
            else:
                np.testing.assert_array_equal(wide, plain, err_msg=str(seed))
        checked += 1
    assert checked >= 15
