"""Hostile and corrupt inputs (issue 39): each gives a ValueError naming the file, never a crash,
a hang, gigabytes of memory or a silent coercion. Every reproducer of the issue is one test here."""

from __future__ import annotations

import multiprocessing
import struct
from pathlib import Path

import numpy as np
import pytest
from terracube.io import read_cloud, read_points

PINE = "forest_tls/TreeLS_pine.laz"  # LAS 1.2, 73,851 points in 2 chunks of 50,000, 241 kB


def _patched(shared_data, tmp_path: Path, relative: str, edits: dict[int, bytes], name: str) -> Path:
    data = bytearray(shared_data.path(relative).read_bytes())
    for offset, value in edits.items():
        data[offset : offset + len(value)] = value
    out = tmp_path / name
    out.write_bytes(bytes(data))
    return out


def _chunk_table(data: bytes) -> int:
    (point_offset,) = struct.unpack_from("<I", data, 96)
    return struct.unpack_from("<q", data, point_offset)[0]


def test_laz_with_2_pow_31_chunks_is_a_value_error_not_an_abort(shared_data, tmp_path):
    table = _chunk_table(shared_data.path(PINE).read_bytes())
    path = _patched(shared_data, tmp_path, PINE, {table + 4: struct.pack("<I", 0x7FFFFFFF)}, "chunks.laz")
    with pytest.raises(ValueError, match=r"chunks\.laz: corrupt LAZ chunk table: 2147483647 chunks"):
        read_points(path)


def test_laz_with_chunk_table_offset_past_the_end_is_a_value_error(shared_data, tmp_path):
    point_offset = 321
    path = _patched(shared_data, tmp_path, PINE, {point_offset: struct.pack("<q", 100)}, "offset.laz")
    with pytest.raises(ValueError, match="offset.laz: corrupt LAZ chunk table: offset"):
        read_points(path)


def test_laz_point_count_inflated_to_2_8e8_is_refused_before_decoding(shared_data, tmp_path):
    path = _patched(shared_data, tmp_path, PINE, {107: struct.pack("<I", 280_000_000)}, "count.laz")
    with pytest.raises(ValueError, match="count.laz: corrupt LAZ: the header promises 280000000 points"):
        read_points(path)


def test_las_header_claiming_2_pow_32_vlrs_is_refused_without_looping(shared_data, tmp_path):
    path = _patched(shared_data, tmp_path, PINE, {100: struct.pack("<I", 0xFFFFFFFF)}, "vlrs.laz")
    with pytest.raises(ValueError, match="vlrs.laz: corrupt LAS header: 4294967295 VLRs"):
        read_points(path)


def test_las_14_header_claiming_too_many_extended_vlrs_is_refused(shared_data, tmp_path):
    relative = "als_classified/laspy_wkt_geotiff_ground_veg_building.las"
    size = shared_data.path(relative).stat().st_size
    path = _patched(
        shared_data, tmp_path, relative, {235: struct.pack("<QI", size - 100, 0xFFFFFFFF)}, "evlrs.las"
    )
    with pytest.raises(ValueError, match="evlrs.las: corrupt LAS header: 4294967295 extended VLRs"):
        read_points(path)


def _read_count(path: str, queue) -> None:
    queue.put(len(read_points(path)))


def test_laz_read_in_a_forked_child_after_the_parent_read_one_does_not_deadlock(shared_data):
    path = str(shared_data.path(PINE))
    expected = len(read_points(path))  # the parent decodes first (this used to start lazrs' thread pool)
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_read_count, args=(path, queue))
    child.start()
    child.join(timeout=30)
    if child.is_alive():
        child.kill()
        child.join()
        pytest.fail("the forked child hung reading a LAZ file")
    assert child.exitcode == 0
    assert queue.get(timeout=5) == expected


def test_kitti_bin_with_trailing_bytes_is_refused(tmp_path):
    for extra in (1, 2, 3, 4, 8, 12):
        path = tmp_path / f"scan{extra}.bin"
        path.write_bytes(np.zeros((5, 4), dtype="<f4").tobytes() + b"\0" * extra)
        with pytest.raises(ValueError, match=rf"scan{extra}.bin: {80 + extra} bytes is not a whole number"):
            read_points(path)


def test_pcd_nan_in_an_integer_field_is_refused(tmp_path):
    path = tmp_path / "nan.pcd"
    header = (
        "VERSION 0.7\nFIELDS x y z ring\nSIZE 4 4 4 2\nTYPE F F F U\nCOUNT 1 1 1 1\n"
        "WIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
    )
    path.write_text(header + "0 0 0 1\n1 1 1 nan\n")
    with pytest.raises(ValueError, match="nan.pcd: ascii PCD: .*'nan' to uint16"):
        read_cloud(path)
