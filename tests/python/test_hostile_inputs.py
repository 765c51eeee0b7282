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


def _layered_laz(tmp_path: Path, points: int) -> tuple[Path, int]:
    """A LAZ of point format 6 (layered chunks of 50,000 points); and where its first chunk's
    layer sizes start (after the 8-byte chunk table offset, a 30-byte raw point and the count)."""
    from terracube.io import write_classified

    rng = np.random.default_rng(points)
    path = write_classified(
        tmp_path / "layered.laz", rng.uniform(0, 50, (points, 3)), np.zeros(points, np.uint8)
    )
    (point_offset,) = struct.unpack_from("<I", path.read_bytes(), 96)
    return path, point_offset + 8 + 30 + 4


def test_a_layered_laz_of_several_chunks_reads_whole(tmp_path):
    path, _ = _layered_laz(tmp_path, 120_000)
    assert read_points(path).shape == (120_000, 3)


def test_a_laz_layer_size_past_the_end_is_refused_before_lazrs_allocates_it(tmp_path):
    # fuzz finding (seed 5, case 3849016369): a layer size of 132 MB in a 2.7 kB file made lazrs
    # abort the process on a 3.9 GB allocation
    path, sizes = _layered_laz(tmp_path, 300)
    data = bytearray(path.read_bytes())
    data[sizes + 4 * 6 : sizes + 4 * 7] = struct.pack("<I", 0x07E80000)
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"layered.laz: corrupt LAZ: chunk 0 claims 300 points in layers of"):
        read_points(path)


def test_a_laz_whose_version_byte_hides_its_point_count_still_has_its_chunk_table_checked(tmp_path):
    # fuzz finding (seed 9100000, case 1333387066): a LAS 1.4 header whose version read 0.4 has a
    # 32-bit point count of 0 (its 300 points are in the 64-bit field laspy reads anyway), which
    # skipped the chunk table's check; lazrs then reserved 4.4 GB for 290 M chunks (an abort under
    # a memory limit)
    path, _ = _layered_laz(tmp_path, 300)
    data = bytearray(path.read_bytes())
    data[24] = 0  # version 1.4 -> 0.4
    data[_chunk_table(data) + 4 : _chunk_table(data) + 8] = struct.pack("<I", 290_321_167)
    path.write_bytes(bytes(data))
    with pytest.raises(
        ValueError, match=r"layered.laz: corrupt LAZ chunk table: 290321167 chunks for 300 points"
    ):
        read_points(path)


def test_a_laz_chunk_point_count_that_disagrees_with_the_header_is_refused(tmp_path):
    path, sizes = _layered_laz(tmp_path, 300)
    data = bytearray(path.read_bytes())
    data[sizes - 4 : sizes] = struct.pack("<I", 299)
    path.write_bytes(bytes(data))
    with pytest.raises(
        ValueError, match="layered.laz: corrupt LAZ: the chunks hold 299 points, the header promises 300"
    ):
        read_points(path)


@pytest.mark.parametrize("layered", [False, True], ids=["laz-1.2", "laz-1.4-layered"])
def test_a_laz_vlr_listing_no_items_is_refused_not_a_decoder_panic(shared_data, tmp_path, layered):
    # fuzz finding (seed 7, case 2423198140): lazrs panicked (pyo3's PanicException, a BaseException)
    path = _layered_laz(tmp_path, 300)[0] if layered else tmp_path / "pine.laz"
    if not layered:
        path.write_bytes(shared_data.path(PINE).read_bytes())
    data = bytearray(path.read_bytes())
    (header_size,) = struct.unpack_from("<H", data, 94)
    vlr = data.find(b"laszip encoded", header_size) - 2
    data[vlr + 54 + 32 : vlr + 54 + 34] = b"\0\0"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="corrupt LAZ: the 'laszip encoded' VLR lists 0 items"):
        read_points(path)


def test_a_panic_in_a_rust_decoder_is_a_value_error_naming_the_file(shared_data, monkeypatch):
    import laspy

    class PanicException(BaseException):  # what pyo3 raises for a Rust panic
        pass

    def panic(*args, **kwargs):
        raise PanicException("index out of bounds")

    monkeypatch.setattr(laspy, "read", panic)
    with pytest.raises(
        ValueError, match=r"TreeLS_pine.laz: corrupt .laz data \(the decoder failed: index out"
    ):
        read_points(shared_data.path(PINE))


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


# Silent coercions at the core boundary (issue 39, item 10): refused with the parameter's name.

_RNG = np.random.default_rng(10)
_CLOUD = np.c_[_RNG.uniform(0, 4, (500, 2)), _RNG.normal(0, 0.05, 500)]


@pytest.mark.parametrize(
    "use, detail",
    [
        (np.array(["yes", "no"] * 250), "dtype <U3"),
        (np.full(500, np.nan), "dtype float64"),
        (np.full(500, 0.5), "dtype float64"),
        (np.arange(500), "values other than 0 and 1"),
        (np.full(500, -1), "values other than 0 and 1"),
    ],
    ids=["strings", "nan", "floats", "counting", "minus-one"],
)
def test_a_use_mask_that_is_not_bool_or_0_1_is_refused(use, detail):
    import terracube as tc

    with pytest.raises(
        ValueError, match=f"use must be a bool mask \\(or whole numbers 0 and 1\\), got {detail}"
    ):
        tc.build_elevation_map(_CLOUD, 0.5, use=use)
    with pytest.raises(ValueError, match="use must be a bool mask"):
        tc.fit_fuzzy_elevation_map(_CLOUD, use=use)


def test_a_use_mask_of_0_and_1_means_the_same_as_the_bool_mask():
    import terracube as tc

    mask = _CLOUD[:, 0] < 2
    expected = tc.build_elevation_map(_CLOUD, 0.5, use=mask)
    for use in (mask.astype(np.uint8), mask.astype(np.int64)):
        got = tc.build_elevation_map(_CLOUD, 0.5, use=use)
        np.testing.assert_array_equal(got["count"], expected["count"])


def test_classes_above_255_are_refused_naming_the_parameter_not_wrapped_to_uint8():
    from terracube.registration import register_points

    classes = np.full(len(_CLOUD), 258)  # 258 would wrap to 2 (ground)
    with pytest.raises(
        ValueError, match=r"source_classes must lie in 0\.\.255 \(terrain classes\), got 258\.\.258"
    ):
        register_points(_CLOUD, _CLOUD, source_classes=classes)
    with pytest.raises(ValueError, match="target_classes must be whole numbers 0..255"):
        register_points(_CLOUD, _CLOUD, target_classes=np.full(len(_CLOUD), 2.0))


@pytest.mark.parametrize(
    "make, message",
    [
        (
            "ElevationParams(max_cells=-1)",
            r"max_cells must be a whole number in 0\.\.18446744073709551615, got -1",
        ),
        (
            "ElevationParams(num_threads=2**31)",
            r"num_threads must be a whole number in -2147483648\.\.2147483647",
        ),
        ("CollapseParams(dense_budget_bytes=2**64)", r"dense_budget_bytes must be a whole number in 0\.\."),
        (
            "FuzzyParams(epochs=2**40)",
            r"epochs must be a whole number in -2147483648\.\.2147483647, got 1099511627776",
        ),
        ("MapperParams(pose_graph_iterations=2**31)", r"pose_graph_iterations must be a whole number in"),
    ],
)
def test_an_out_of_range_whole_number_names_the_parameter_not_pybind11(make, message):
    import terracube as tc
    from terracube.mapping import MapperParams  # noqa: F401 - used by eval

    namespace = {**vars(tc), "MapperParams": MapperParams}
    with pytest.raises(ValueError, match=message):
        eval(make, namespace).to_core()


def test_an_out_of_range_whole_number_in_a_config_file_names_section_and_key(tmp_path):
    from terracube.config import ConfigError, load_config

    path = tmp_path / "big.yaml"
    path.write_text("elevation:\n  max_cells: -1\n")
    with pytest.raises(
        ConfigError, match=r"big.yaml: section 'elevation': max_cells must be a whole number in 0\.\."
    ):
        load_config(path)


def test_a_binary_compressed_pcd_asking_for_gigabytes_is_refused_before_decompressing(tmp_path):
    header = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000000\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 100000000\nDATA binary_compressed\n"
    )
    path = tmp_path / "bomb.pcd"
    path.write_bytes(header.encode() + struct.pack("<II", 100, 1_200_000_000) + bytes(100))
    with pytest.raises(
        ValueError, match="bomb.pcd: binary_compressed PCD: 1200000000 bytes cannot come from 100"
    ):
        read_points(path)


@pytest.mark.parametrize("count", ["99999999999999999999", "5000"])
def test_a_pcd_count_that_would_never_return_is_refused_at_once(tmp_path, count):
    # pypcd4 makes one column per value: a fuzzed COUNT of 10^20 hung the reader.
    header = (
        f"VERSION 0.7\nFIELDS x y z ring\nSIZE 4 4 4 2\nTYPE F F F U\nCOUNT {count} 1 1 1\n"
        "WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA binary_compressed\n"
    )
    path = tmp_path / "count.pcd"
    path.write_bytes(header.encode() + struct.pack("<II", 10, 42) + bytes(10))
    with pytest.raises(ValueError, match=rf"count.pcd: PCD header: COUNT {count} 1 1 1 must give each field"):
        read_points(path)


def test_a_real_binary_compressed_pcd_still_reads(tmp_path):
    from terracube.io import write_pcd

    xyz = np.zeros((50_000, 3), np.float32)  # all zeros: LZF's best case
    path = write_pcd(tmp_path / "zeros.pcd", {"xyz": xyz}, encoding="binary_compressed")
    np.testing.assert_array_equal(read_points(path), xyz)


def test_an_iteration_count_no_solver_needs_is_refused_instead_of_running_for_days():
    """ICP, PCL's ICP, the pose graph and the mapper's pose graph stop at max_iterations when a pair
    never converges: a count of 10**9 would be a call that seems to hang. Above 10,000 it is refused,
    with the parameter's name; 10,000 itself runs."""
    import terracube as tc
    from terracube.mapping import Mapper, MapperParams

    rng = np.random.default_rng(3)
    points = rng.uniform(-5, 5, (300, 3))
    for call in (
        lambda n: tc.register_points(points, points, max_iterations=n),
        lambda n: tc.pcl_icp(points, points, max_iterations=n),
        lambda n: tc.optimize_pose_graph([np.eye(4), np.eye(4)], [(0, 1, np.eye(4))], max_iterations=n),
    ):
        with pytest.raises(ValueError, match="1 to 10000|\\[1, 10000\\], got 1000000000"):
            call(10**9)
        call(10_000)
    with pytest.raises(ValueError, match=r"pose_graph_iterations must lie in \[1, 10000\], got 10001"):
        Mapper(MapperParams(pose_graph_iterations=10_001))
