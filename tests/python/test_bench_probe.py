"""The memory-floor probe behind bench/bench_collapse.py (terracube._bench._memory_floor).

terracube._bench exists only in builds with TERRACUBE_BUILD_BENCH=ON; elsewhere these tests skip.
"""

import numpy as np
import pytest

_bench = pytest.importorskip("terracube._bench", reason="built only with TERRACUBE_BUILD_BENCH=ON")


def _rows(n: int, width: int, dtype) -> np.ndarray:
    return np.arange(n * width, dtype=dtype).reshape(n, width)


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize(("width", "dtype"), [(3, np.float64), (4, np.float32)])
def test_probe_reads_the_span_of_the_rows_and_times_three_loops(width, dtype, threads):
    rows = _rows(1000, width, dtype)
    entry = (np.arange(1000) % 7).astype(np.uint32)
    probe = _bench._memory_floor(rows[:, :3], entry, 7, repeat=2, threads=threads)
    assert probe["bytes"] == (999 * width + 3) * np.dtype(dtype).itemsize
    for key in ("read_ms", "store_ms", "load_ms"):
        assert probe[key] >= 0.0


def test_probe_reads_only_the_coordinates_of_rows_far_apart():
    rows = _rows(8000, 4, np.float32)[::8, :3]  # 128 bytes apart
    probe = _bench._memory_floor(rows, np.zeros(1000, dtype=np.uint32), 1, repeat=2)
    assert probe["bytes"] == 1000 * 12


def test_probe_rejects_bad_input():
    rows = _rows(10, 3, np.float64)
    entry = np.zeros(10, dtype=np.uint32)
    with pytest.raises(ValueError, match="past num_entries"):
        _bench._memory_floor(rows, entry + 3, 3)
    with pytest.raises(ValueError, match="differ in length"):
        _bench._memory_floor(rows, entry[:9], 1)
    with pytest.raises(ValueError, match="repeat"):
        _bench._memory_floor(rows, entry, 1, repeat=0)
    for threads in (0, -1, 257):
        with pytest.raises(ValueError, match="threads"):
            _bench._memory_floor(rows, entry, 1, threads=threads)
    with pytest.raises(ValueError, match="adjacent x, y, z"):
        _bench._memory_floor(np.asfortranarray(rows), entry, 1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        _bench._memory_floor(rows[:, :2], entry, 1)
