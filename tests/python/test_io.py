"""Point-cloud reading and classified-cloud writing on the real scans of the shared data folder.

Every writable format round-trips (write, read back: the same xyz and labels); every real .pcd/.las/.laz
reads like its numpy twin; truncated and non-point files give a ValueError naming the file.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
import pytest
from terracube.io import (
    OVERHANG_LAS_CLASS,
    RETAINED_LAS_CLASS,
    TERRAIN_LAS_CLASSES,
    WRITE_SUFFIXES,
    read_cloud,
    read_points,
    write_classified,
    write_kitti_bin,
    write_pcd,
)

OUSTER = "ouster128/ouster128_000000.pcd"
ALS_FILES = [
    "als_classified/laspy_wkt_geotiff_ground_veg_building.las",
    "als_classified/laspy_append-bug.laz",
    "als_classified/laspy_autzen_trim.laz",
    "als_classified/lidR_Megaplot.laz",
    "als_classified/lidR_MixedConifer.laz",
    "als_classified/lidR_Topography.laz",
]
FOREST_FILES = [
    "forest_tls/TreeLS_pine_plot.laz",
    "forest_tls/TreeLS_pine.laz",
    "forest_tls/TreeLS_spruce.laz",
]


def _twin(path: Path) -> dict[str, np.ndarray]:
    with np.load(path.with_suffix(".npz")) as twin:
        return dict(twin)


# ------------------------------------------------------------------------------------ real files read


@pytest.mark.parametrize("frame", ["000000", "000002"])
def test_ouster_binary_compressed_pcd_equals_its_bin_twin_on_the_valid_points(shared_data, frame):
    cloud = read_cloud(shared_data.path(f"ouster128/ouster128_{frame}.pcd"))
    xyzi = read_points(shared_data.path(f"ouster128/ouster128_{frame}_xyzi_valid.bin"))
    twin = np.fromfile(shared_data.path(f"ouster128/ouster128_{frame}_xyzi_valid.bin"), np.float32).reshape(
        -1, 4
    )
    assert cloud["xyz"].shape == (1875 * 128, 3) and cloud["xyz"].dtype == np.float32
    assert set(cloud) >= {"timestamp", "intensity", "ring", "azimuth"}
    assert cloud["timestamp"].dtype == np.float64 and cloud["ring"].dtype == np.uint16
    valid = ~np.all(cloud["xyz"] == 0, axis=1)
    np.testing.assert_array_equal(cloud["xyz"][valid], xyzi)
    np.testing.assert_array_equal(cloud["intensity"][valid].astype(np.float32), twin[:, 3])
    assert cloud["ring"].max() == 127  # beam index 0..127


@pytest.mark.parametrize("relative", ALS_FILES + FOREST_FILES)
def test_las_and_laz_equal_their_npz_twins(shared_data, relative):
    path = shared_data.path(relative)
    cloud, twin = read_cloud(path), _twin(path)
    assert cloud["xyz"].dtype == np.float64
    np.testing.assert_array_equal(cloud["xyz"].astype(twin["xyz"].dtype), twin["xyz"])
    for name in ("classification", "intensity", "return_number", "number_of_returns"):
        np.testing.assert_array_equal(cloud[name], twin[name], err_msg=name)
    np.testing.assert_array_equal(cloud["label"], twin["classification"])
    np.testing.assert_array_equal(read_points(path), cloud["xyz"])


def test_las_extra_dimensions_are_read(shared_data):
    path = shared_data.path("als_classified/lidR_MixedConifer.laz")
    cloud, twin = read_cloud(path), _twin(path)
    np.testing.assert_array_equal(cloud["treeID"], twin["treeID"])


def test_kitti_bin_gives_xyz_and_intensity(shared_data):
    xyzi = shared_data.kitti_xyzi(0)
    cloud = read_cloud(shared_data.path("kitti_seq00/velodyne/000000.bin"))
    np.testing.assert_array_equal(cloud["xyz"], xyzi[:, :3])
    np.testing.assert_array_equal(cloud["intensity"], xyzi[:, 3])


# ------------------------------------------------------------------------------------ PCD encodings


@pytest.fixture(scope="module")
def ouster_fields(shared_data):
    """The real Ouster scan's fields (a 20k-point slice keeps the ascii tests fast)."""
    cloud = read_cloud(shared_data.path(OUSTER))
    return {name: value[:20_000] for name, value in cloud.items() if name != "label"}


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
def test_pcd_encodings_round_trip_every_field_exactly(tmp_path, ouster_fields, encoding):
    path = write_pcd(tmp_path / f"ouster_{encoding}.pcd", ouster_fields, encoding=encoding)
    assert f"DATA {encoding}\n".encode() in path.read_bytes()[:1000]
    cloud = read_cloud(path)
    assert set(cloud) == set(ouster_fields)
    for name, value in ouster_fields.items():
        assert cloud[name].dtype == value.dtype, name
        np.testing.assert_array_equal(cloud[name], value, err_msg=name)


def test_pcd_reads_hand_written_ascii_with_count_and_comments(tmp_path):
    path = tmp_path / "hand.pcd"
    path.write_text(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb normal\nSIZE 4 4 4 4 4\nTYPE F F F U F\n"
        "COUNT 1 1 1 1 3\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n"
        "1.5 2 3 255 0 0 1\n-1 nan 0.25 7 1 0 0\n"
    )
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud["xyz"], np.float32([[1.5, 2, 3], [-1, np.nan, 0.25]]))
    np.testing.assert_array_equal(cloud["rgb"], np.uint32([255, 7]))
    assert cloud["normal"].shape == (2, 3)


def test_pcd_binary_compressed_of_incompressible_data_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    fields = {"xyz": rng.standard_normal((50, 3)), "noise": rng.integers(0, 2**32, 50, dtype=np.uint32)}
    cloud = read_cloud(write_pcd(tmp_path / "noise.pcd", fields, encoding="binary_compressed"))
    np.testing.assert_array_equal(cloud["xyz"], fields["xyz"])
    np.testing.assert_array_equal(cloud["noise"], fields["noise"])


# ------------------------------------------------------------------------------------ round trips


def _scans(shared_data):
    """(name, points, labels) of the real scans: masks for the sensor scans, ASPRS classes for ALS."""
    kitti = shared_data.kitti_xyzi(0)[:, :3]
    ouster = read_points(shared_data.path(OUSTER))
    als = read_cloud(shared_data.path("als_classified/laspy_append-bug.laz"))
    forest = read_points(shared_data.path("forest_tls/TreeLS_pine_plot.laz"))
    return {
        "kitti": (kitti, kitti[:, 2] > 0.0),
        "ouster": (ouster, ouster[:, 2] > 1.0),
        "als": (als["xyz"], als["classification"]),
        "forest": (forest, forest[:, 2] > forest[:, 2].min() + 2.0),
    }


@pytest.fixture(scope="module")
def scans(shared_data):
    return _scans(shared_data)


@pytest.mark.parametrize("suffix", WRITE_SUFFIXES)
@pytest.mark.parametrize("scan", ["kitti", "ouster", "als", "forest"])
def test_write_then_read_gives_the_same_points_and_labels(tmp_path, scans, scan, suffix):
    points, labels = scans[scan]
    if suffix in (".txt", ".xyz"):  # text is slow to write: every 4th point
        points, labels = points[::4], labels[::4]
    path = write_classified(tmp_path / f"{scan}{suffix}", points, labels)
    cloud = read_cloud(path)
    if suffix in (".las", ".laz", ".txt", ".xyz"):  # stored at 0.1 mm
        np.testing.assert_allclose(cloud["xyz"], points, rtol=0, atol=5.1e-5)
    elif suffix == ".bin":  # KITTI rows are float32 whatever the input
        assert cloud["xyz"].dtype == np.float32
        np.testing.assert_array_equal(cloud["xyz"], points.astype(np.float32))
    else:  # stored in the points' own float dtype
        assert cloud["xyz"].dtype == points.dtype
        np.testing.assert_array_equal(cloud["xyz"], points)
    label = cloud["extra"][:, 0] if suffix == ".npy" else cloud["label"]
    assert suffix == ".npy" or label.dtype == np.uint8
    np.testing.assert_array_equal(label, labels.astype(np.uint8))
    assert len(np.unique(labels)) > 1


@pytest.mark.parametrize("suffix", WRITE_SUFFIXES)
def test_an_empty_cloud_round_trips(tmp_path, suffix):
    cloud = read_cloud(
        write_classified(tmp_path / f"empty{suffix}", np.zeros((0, 3), np.float32), np.zeros(0, bool))
    )
    assert cloud["xyz"].shape == (0, 3)
    assert cloud["extra" if suffix == ".npy" else "label"].shape[0] == 0


def test_las_codes_of_an_overhang_mask_and_of_classes(tmp_path):
    points = np.array([[0.0, 0, 0], [1, 2, 3], [4, 5, 6.5]])
    mask = np.array([False, True, False])
    cloud = read_cloud(write_classified(tmp_path / "mask.las", points, mask))
    np.testing.assert_array_equal(cloud["classification"], [RETAINED_LAS_CLASS, OVERHANG_LAS_CLASS, 1])
    np.testing.assert_array_equal(cloud["label"], [0, 1, 0])
    classes = np.array([2, 5, 17], dtype=np.uint8)
    cloud = read_cloud(write_classified(tmp_path / "classes.laz", points, classes))
    np.testing.assert_array_equal(cloud["classification"], classes)
    np.testing.assert_array_equal(cloud["label"], classes)


def test_terrain_classes_go_to_las_as_their_codes_and_come_back_as_labels(tmp_path):
    points = np.arange(18, dtype=np.float64).reshape(6, 3)
    classes = np.array([0, 1, 2, 3, 4, 5], dtype=np.uint8)
    cloud = read_cloud(write_classified(tmp_path / "t.laz", points, classes, las_classes=TERRAIN_LAS_CLASSES))
    # ASPRS: 1 unclassified, 2 ground; 65..68 user-definable (hand-written table of the docs)
    np.testing.assert_array_equal(cloud["classification"], [1, 2, 65, 66, 67, 68])
    np.testing.assert_array_equal(cloud["label"], classes)
    with pytest.raises(ValueError, match=r"t2\.las: las_classes has no LAS code for the labels \[7\]"):
        write_classified(tmp_path / "t2.las", points[:2], np.uint8([1, 7]), las_classes=TERRAIN_LAS_CLASSES)


def test_kitti_bin_round_trips_the_real_scan_with_its_intensity(tmp_path, shared_data):
    xyzi = shared_data.kitti_xyzi(0)
    path = write_kitti_bin(tmp_path / "copy.bin", xyzi[:, :3], xyzi[:, 3])
    assert path.read_bytes() == shared_data.path("kitti_seq00/velodyne/000000.bin").read_bytes()
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud["xyz"], xyzi[:, :3])
    np.testing.assert_array_equal(cloud["intensity"], xyzi[:, 3])
    assert "label" not in cloud


def test_kitti_bin_labels_live_in_a_semantic_kitti_label_file(tmp_path, shared_data):
    xyzi = shared_data.kitti_xyzi(0)
    semantic = shared_data.kitti_labels(0)
    path = write_classified(tmp_path / "scan.bin", xyzi[:, :3], semantic.astype(np.uint8))
    # the .label file is what SemanticKITTI tools read: uint32 per point, class in the low 16 bits
    np.testing.assert_array_equal(np.fromfile(tmp_path / "scan.label", np.uint32), semantic)
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud["label"], semantic)
    np.testing.assert_array_equal(cloud["intensity"], np.zeros(len(xyzi), np.float32))


def test_a_label_file_of_the_wrong_length_names_both_files(tmp_path):
    write_kitti_bin(tmp_path / "scan.bin", np.zeros((5, 3), np.float32))
    np.zeros(4, np.uint32).tofile(tmp_path / "scan.label")
    with pytest.raises(
        ValueError, match=r"scan\.bin: the label file scan\.label holds 16 bytes, 5 points need 20"
    ):
        read_cloud(tmp_path / "scan.bin")


def test_kitti_bin_writer_refuses_wrong_shapes(tmp_path):
    with pytest.raises(ValueError, match=r"x\.bin: need \(N, 3\) points"):
        write_kitti_bin(tmp_path / "x.bin", np.zeros(6))
    with pytest.raises(ValueError, match=r"x\.bin: need \(2,\) intensities"):
        write_kitti_bin(tmp_path / "x.bin", np.zeros((2, 3)), np.zeros(3))


def test_ply_and_npz_keep_the_overhang_field_name_for_masks(tmp_path):
    points = np.zeros((3, 3), np.float32)
    mask = np.array([True, False, True])
    assert np.load(write_classified(tmp_path / "m.npz", points, mask))["overhang"].dtype == bool
    cloud = read_cloud(write_classified(tmp_path / "m.ply", points, mask))
    np.testing.assert_array_equal(cloud["overhang"], mask)
    np.testing.assert_array_equal(cloud["red"], [230, 150, 230])


@pytest.mark.parametrize("labels", [np.array([0, 256, 1]), np.array([-1, 0, 1]), np.array([0.5, 1, 2])])
def test_labels_outside_0_255_are_refused(tmp_path, labels):
    with pytest.raises(ValueError, match="bad.pcd"):
        write_classified(tmp_path / "bad.pcd", np.zeros((3, 3)), labels)


def test_an_unknown_output_format_names_the_file(tmp_path):
    with pytest.raises(ValueError, match=r"out\.vtk.*unknown output format"):
        write_classified(tmp_path / "out.vtk", np.zeros((2, 3)), np.zeros(2, bool))


# ------------------------------------------------------------------------------------ broken files


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("keep", [0.3, 0.97])
def test_a_truncated_pcd_names_the_file_and_the_problem(tmp_path, ouster_fields, encoding, keep):
    data = write_pcd(tmp_path / "full.pcd", ouster_fields, encoding=encoding).read_bytes()
    path = tmp_path / f"cut_{encoding}.pcd"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError, match=rf"cut_{encoding}\.pcd: truncated {encoding} PCD"):
        read_points(path)


def test_the_real_compressed_pcd_cut_short_names_the_file(tmp_path, shared_data):
    data = shared_data.path(OUSTER).read_bytes()
    for keep in (120, 400, len(data) // 2):
        path = tmp_path / f"ouster_{keep}.pcd"
        path.write_bytes(data[:keep])
        with pytest.raises(ValueError, match=rf"ouster_{keep}\.pcd: .*(truncated|no DATA)"):
            read_points(path)


def test_corrupt_compressed_pcd_data_names_the_file(tmp_path, shared_data):
    data = bytearray(shared_data.path(OUSTER).read_bytes())
    start = data.index(b"DATA binary_compressed\n") + len("DATA binary_compressed\n") + 8
    data[start : start + 4000] = bytes(range(250)) * 16
    path = tmp_path / "corrupt.pcd"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"corrupt\.pcd: corrupt binary_compressed"):
        read_points(path)


@pytest.mark.parametrize(
    "relative",
    ["als_classified/laspy_wkt_geotiff_ground_veg_building.las", "als_classified/laspy_append-bug.laz"],
)
@pytest.mark.parametrize("keep", [0.002, 0.5, 0.99])
def test_a_truncated_las_or_laz_names_the_file_and_the_problem(tmp_path, shared_data, relative, keep):
    data = shared_data.path(relative).read_bytes()
    path = tmp_path / f"cut{Path(relative).suffix}"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError, match=r"cut\.la[sz]: .*(truncated|not a valid LAS)"):
        read_points(path)


# ------------------------------------------------------------------------------------------ text files

ROWS = np.array([[1.5, -2.0, 3.25, 7.0], [4.0, 5.5, -6.0, 8.0], [0.0, 0.125, 9.0, 9.0]])


@pytest.mark.parametrize(
    "header, order",
    [
        ("# intensity x y z", [3, 0, 1, 2]),
        ("# X Y Z Intensity", [0, 1, 2, 3]),
        ("# z, intensity, y, x", [2, 3, 1, 0]),
        ("y x intensity z", [1, 0, 3, 2]),
    ],
)
def test_a_text_header_gives_x_y_z_by_name_in_any_order_and_case(tmp_path, header, order):
    path = tmp_path / "named.txt"
    body = "\n".join(" ".join(f"{v:g}" for v in row) for row in ROWS[:, order])
    path.write_text(f"{header}\n{body}\n")
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud["xyz"], ROWS[:, :3])
    intensity = next(name for name in cloud if name.lower() == "intensity")
    np.testing.assert_array_equal(cloud[intensity], ROWS[:, 3])


@pytest.mark.parametrize(
    "name, text",
    [
        ("polar.txt", "# range azimuth elevation intensity\n1 2 3 4\n"),
        ("two_axes.csv", "x,y,intensity\n1,2,3\n"),
        ("twice.txt", "# x x y z\n1 2 3 4\n"),
        ("counts.txt", "# x y z intensity\n1 2 3\n"),
    ],
)
def test_a_text_header_without_x_y_z_or_unlike_the_rows_is_an_error_naming_the_file(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError, match=name.replace(".", r"\.") + ": .*header"):
        read_cloud(path)


@pytest.mark.parametrize("suffix", [".txt", ".xyz", ".csv", ".asc"])
@pytest.mark.parametrize("separator", [",", ", ", " ", "\t"])
def test_text_reads_whitespace_or_comma_separated_rows_for_every_text_suffix(tmp_path, suffix, separator):
    path = tmp_path / f"rows{suffix}"
    path.write_text("".join(separator.join(f"{v:g}" for v in row) + "\n" for row in ROWS))
    np.testing.assert_array_equal(read_points(path), ROWS[:, :3])


@pytest.mark.parametrize("header", ["x,y,z,intensity", "# x,y,z,intensity", "X Y Z intensity"])
def test_a_first_line_of_column_names_is_the_header_with_or_without_hash(tmp_path, header):
    path = tmp_path / "points.csv"
    path.write_text(header + "\n" + "".join(",".join(f"{v:g}" for v in row) + "\n" for row in ROWS))
    cloud = read_cloud(path)
    np.testing.assert_array_equal(cloud["xyz"], ROWS[:, :3])
    np.testing.assert_array_equal(cloud["intensity"], ROWS[:, 3])


def test_a_comment_line_that_names_no_columns_is_skipped(tmp_path):
    path = tmp_path / "commented.txt"
    path.write_text("# scanner export\n" + "".join(" ".join(map(str, r)) + "\n" for r in ROWS))
    np.testing.assert_array_equal(read_points(path), ROWS[:, :3])


# ------------------------------------------------------------------------------- files of another layout

KITTI_LAYOUT = r"KITTI \.bin layout \(float32 rows x, y, z, intensity\)"


def _xyzi(rows: int = 256) -> np.ndarray:
    rng = np.random.default_rng(5)
    return np.c_[rng.uniform(-40, 40, (rows, 3)), rng.uniform(0, 1, rows)]


def _npy_bytes(array: np.ndarray) -> bytes:
    stream = io.BytesIO()
    np.save(stream, array)
    return stream.getvalue()


@pytest.mark.parametrize(
    "data, detail",
    [
        (_npy_bytes(_xyzi().astype(np.float32)), "a NumPy .npy array"),
        (_xyzi().astype("<f8").tobytes(), "coordinates beyond"),
        (_xyzi().astype("<f8").tobytes()[8:-8], "coordinates beyond"),
    ],
    ids=["npy renamed", "float64 rows", "float64 rows, shifted"],
)
def test_a_bin_of_another_layout_names_the_file_and_the_kitti_layout(tmp_path, data, detail):
    assert len(data) % 16 == 0  # each passes the size check
    path = tmp_path / "scan.bin"
    path.write_bytes(data)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: .*{detail}.*{KITTI_LAYOUT}"):
        read_points(path)


def test_a_bin_with_a_few_stray_coordinates_still_reads(tmp_path):
    rows = _xyzi(1000).astype(np.float32)
    rows[:2, :3] = [[1e30, 0, 0], [np.inf, np.nan, 0]]  # under 1 % of the coordinates
    path = write_kitti_bin(tmp_path / "stray.bin", rows[:, :3])
    np.testing.assert_array_equal(read_points(path), rows[:, :3])


def test_a_binary_file_named_pcd_shows_no_raw_bytes(tmp_path, shared_data):
    path = tmp_path / "kitti.pcd"
    path.write_bytes(shared_data.path("kitti_seq00/velodyne/000000.bin").read_bytes())
    with pytest.raises(ValueError) as caught:
        read_cloud(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: not a PCD file")
    detail = message[len(str(path)) :]
    assert detail.isascii() and detail.isprintable() and len(detail) <= 120, detail


@pytest.mark.parametrize(
    "name, content",
    [
        ("picture.pcd", b"\x89PNG\r\n\x1a\n" + bytes(200)),
        ("words.pcd", b"hello\nworld\n"),
        (
            "bad_header.pcd",
            b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 1\nDATA binary\n" + bytes(12),
        ),
        ("no_xyz.pcd", b"FIELDS a b\nSIZE 4 4\nTYPE F F\nPOINTS 1\nDATA binary\n" + bytes(8)),
        ("words.ply", b"hello world\n"),
        ("noise.laz", bytes(range(256)) * 8),
        ("words.las", b"LASF but not really"),
        ("table.txt", b"1 2\n3 4\n"),
        ("text.npy", b"not numpy"),
        ("archive.npz", b"PK\x03\x04 not a zip"),
        ("scan.vtk", b"anything"),
        ("empty.pcd", b""),
    ],
)
def test_a_non_point_file_gives_a_value_error_naming_it(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        read_cloud(path)


def test_a_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.pcd"):
        read_points(tmp_path / "nothing.pcd")


# ------------------------------------------------------------------------------------ command line


@pytest.mark.parametrize("fmt", ["pcd", "laz"])
def test_collapse_reads_a_real_pcd_and_writes_each_new_format(tmp_path, shared_data, fmt):
    from terracube.cli import app
    from typer.testing import CliRunner

    result = CliRunner().invoke(
        app, ["collapse", str(shared_data.path(OUSTER)), "-o", str(tmp_path), "-f", fmt, "--no-png"]
    )
    assert result.exit_code == 0, result.output
    cloud = read_cloud(tmp_path / f"ouster128_000000_classified.{fmt}")
    assert len(cloud["xyz"]) == 1875 * 128 and 0 < cloud["label"].sum() < len(cloud["xyz"])


def test_las_without_its_extra_names_the_extra_to_install(tmp_path, monkeypatch):
    import sys

    path = write_classified(tmp_path / "scan.las", np.zeros((3, 3)), np.zeros(3, bool))
    monkeypatch.setitem(sys.modules, "laspy", None)  # import laspy now raises ImportError
    with pytest.raises(ImportError, match=r"pip install 'terracube\[las\]'"):
        read_points(path)
    with pytest.raises(ImportError, match=r"pip install 'terracube\[las\]'"):
        write_classified(tmp_path / "again.laz", np.zeros((3, 3)), np.zeros(3, bool))


def test_pictures_without_their_extra_name_the_extra_to_install(tmp_path, monkeypatch):
    import sys

    import terracube as tc

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    elevation_map = tc.build_elevation_map(np.random.default_rng(0).uniform(0, 1, (100, 3)), 0.1)
    with pytest.raises(ImportError, match=r"pip install 'terracube\[plot\]'"):
        elevation_map.to_png("max", tmp_path / "max.png")
