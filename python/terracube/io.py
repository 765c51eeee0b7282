"""Reading point clouds and writing classified clouds.

Formats, chosen by the file suffix:

======================  ====================================  =========================================
suffix                  read                                  write (``write_classified``)
======================  ====================================  =========================================
``.pcd``                ascii, binary, binary_compressed      binary (``write_pcd``: any of the three)
``.ply``                ascii and binary, through plyfile     binary, x y z + label + RGB colour
``.las`` / ``.laz``     laspy (+ lazrs for LAZ)               LAS 1.4 point format 6, classification
``.bin``                KITTI float32 rows x, y, z, intensity float32 rows (``write_kitti_bin``) + a
                        (+ a SemanticKITTI ``.label`` beside)  SemanticKITTI-style ``.label`` file
``.npy``                (N, >=3) array                        (N, 4) x, y, z, label
``.npz``                key ``xyz`` or ``points``             ``xyz`` + ``overhang`` or ``label``
``.txt`` ``.xyz`` ...   whitespace/comma separated text,      ``# x y z <label>`` header, one row each
                        columns named by a first line
                        (``# x y z ...`` or ``x,y,z,...``)
======================  ====================================  =========================================

ROS bags (ROS 1 ``.bag``, ROS 2 folders, ``.mcap``) are read by :func:`read_bag` and listed by
:func:`bag_info`, both from :mod:`terracube.bag` (the ``ros`` extra).

Every reader raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file and the
problem for a malformed, truncated or unknown one. LAS/LAZ headers (VLR counts, point counts, the LAZ
chunk table and layer sizes) are checked against the file size before laspy and lazrs see them, so a
hostile header costs neither a crash nor gigabytes. Every writer writes a temporary file in the target
folder and renames it when whole (:func:`atomic_path`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .bag import bag_info, read_bag

__all__ = [
    "read_bag",
    "bag_info",
    "read_points",
    "read_cloud",
    "write_classified",
    "write_pcd",
    "write_kitti_bin",
    "organised_shape",
    "TERRAIN_LAS_CLASSES",
    "sample_scan_path",
    "load_sample_scan",
    "OVERHANG_LAS_CLASS",
    "RETAINED_LAS_CLASS",
    "atomic_path",
]

PathLike = str | Path

_TEXT_SUFFIXES = (".txt", ".xyz", ".csv", ".asc")
_READ_SUFFIXES = (".pcd", ".ply", ".las", ".laz", ".bin", ".npy", ".npz", *_TEXT_SUFFIXES)
WRITE_SUFFIXES = (".ply", ".pcd", ".las", ".laz", ".bin", ".npz", ".npy", ".txt", ".xyz")

#: LAS classification written for a retained point of an overhang mask: 1, "unclassified" (ASPRS).
RETAINED_LAS_CLASS = 1
#: LAS classification written for an overhang point: 64, the first "user definable" code of LAS 1.4
#: (overhangs are canopy, ceilings and bridge decks alike, so no single ASPRS class fits).
OVERHANG_LAS_CLASS = 64
#: LAS classification of each terrain class (``terracube.TerrainClass``) for ``write_classified(...,
#: las_classes=TERRAIN_LAS_CLASSES)``: unknown -> 1 ("unclassified"), ground -> 2 (ASPRS "ground"), the
#: others to user-definable codes 65..68 (obstacle, overhanging object, vertical object, horizontal
#: edge), since no ASPRS class means the same. The raw class is kept in a ``label`` extra dimension.
TERRAIN_LAS_CLASSES = {0: 1, 1: 2, 2: 65, 3: 66, 4: 67, 5: 68}

# Internal: problems found while parsing; turned into ValueError("<path>: <message>").


class _FormatError(Exception):
    pass


@contextlib.contextmanager
def atomic_path(path: PathLike) -> Iterator[Path]:
    """A temporary name in ``path``'s folder to write to; renamed to ``path`` when the block succeeds.

    An exception half-way leaves neither ``path`` (an older ``path`` stays as it was) nor the
    temporary file; a kill leaves at most a hidden ``.NAME.*.tmpSUFFIX``, never a truncated file
    under the final name. The temporary
    name keeps ``path``'s suffix (numpy's ``savez`` would append ``.npz`` otherwise). Creates the
    folder. Example: ``with atomic_path(out) as tmp: np.savez(tmp, ...)``.
    """
    path = Path(path)
    for folder in (path.parent, *path.parent.parents):  # mkdir would say "file exists" for a file
        if folder.exists():
            if not folder.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, "Not a directory", str(folder))
            break
    path.parent.mkdir(parents=True, exist_ok=True)
    # A fresh name rather than mkstemp's file, so the writer creates it with the usual permissions.
    temporary = path.with_name(f".{path.stem[:100]}.{secrets.token_hex(6)}.tmp{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def sample_scan_path() -> Path:
    """The bundled Ouster OS-128 sample (MIT licence, see terracube/data/README.md)."""
    return Path(__file__).parent / "data" / "ouster128_sample.npz"


def load_sample_scan() -> np.ndarray:
    """(N, 3) float32 points of the bundled sample scan."""
    return read_points(sample_scan_path())


def read_points(path: PathLike) -> np.ndarray:
    """Read an (N, 3) array of x, y, z [m] from a point-cloud file.

    Supported: PCD (``.pcd``; ascii, binary and binary_compressed), PLY (``.ply``), LAS/LAZ (``.las``,
    ``.laz``; scaled coordinates as float64), KITTI-style ``.bin`` (float32 rows of x, y, z, intensity),
    ``.npy`` ((N, >=3)), ``.npz`` (key ``xyz`` or ``points``, else the first array) and whitespace- or
    comma-separated text (``.txt``, ``.xyz``, ``.csv``, ``.asc``; the columns a first line of names such
    as ``# x y z ...`` or ``intensity,x,y,z`` calls x, y and z, else the first three). Every point
    of the file is returned, in file order, including invalid returns a sensor may store as (0, 0, 0)
    or NaN (organised PCD clouds). Raises ``ValueError`` naming the file for a malformed, truncated or
    unknown file and ``FileNotFoundError`` for a missing one.
    """
    return read_cloud(path)["xyz"]


def read_cloud(path: PathLike) -> dict[str, np.ndarray]:
    """Read a point cloud with its per-point fields, as a dict of arrays of one length N.

    Always holds ``"xyz"`` ((N, 3) float32 or float64). Other fields keep the file's names and dtypes:
    PCD fields (``intensity``, ``ring``, ``label``, ...; a field with COUNT > 1 is (N, COUNT)), PLY
    vertex properties, LAS dimensions (``intensity``, ``classification``, ``return_number``, extra
    bytes ...), the ``.bin`` ``intensity``, the other arrays of an ``.npz`` of length N, the named
    columns of a text file whose first line names them (``# x y z ...`` or ``x,y,z,...``), and the
    columns after the third of an ``.npy`` as ``"extra"`` ((N, k - 3)).

    ``"label"`` is added when the file holds a per-point label, the first of the fields ``label``,
    ``overhang`` and ``classification``, except that a LAS file written from an overhang mask gives its
    ``overhang`` extra dimension rather than the classification codes. So
    ``read_cloud(write_classified(p, xyz, labels))["label"]`` equals ``labels`` (as uint8) for every
    format but ``.npy``, where the label is ``"extra"[:, 0]``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    readers = {
        ".pcd": _read_pcd,
        ".ply": _read_ply,
        ".las": _read_las,
        ".laz": _read_las,
        ".bin": _read_bin,
        ".npy": _read_npy,
        ".npz": _read_npz,
    }
    reader = readers.get(suffix, _read_text if suffix in _TEXT_SUFFIXES else None)
    if reader is None:
        raise ValueError(f"{path}: unknown point-cloud format {suffix!r} (use {', '.join(_READ_SUFFIXES)})")
    try:
        fields = reader(path)
    except ImportError:
        raise
    except _FormatError as error:
        raise ValueError(f"{path}: {error}") from None
    except MemoryError as error:
        raise ValueError(
            f"{path}: not a valid {suffix} file (its header asks for too much memory)"
        ) from error
    except Exception as error:  # any parser failure: a clear message, never a crash
        raise ValueError(f"{path}: cannot read as {suffix}: {type(error).__name__}: {error}") from error
    except BaseException as error:  # a Rust decoder's panic (pyo3's PanicException is no Exception)
        if type(error).__name__ != "PanicException":
            raise
        raise ValueError(f"{path}: corrupt {suffix} data (the decoder failed: {error})") from None
    xyz = np.asarray(fields["xyz"])
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"{path}: expected an (N, >=3) array of points, got shape {xyz.shape}")
    if xyz.dtype not in (np.float32, np.float64):
        fields["xyz"] = xyz.astype(np.float64)
    if "label" not in fields:
        for name in ("overhang", "terracube_class", "classification"):
            if name in fields:
                fields["label"] = (
                    fields[name].astype(np.uint8) if fields[name].dtype == bool else fields[name]
                )
                break
    return fields


# --------------------------------------------------------------------------------------------- readers


_KITTI_LAYOUT = "KITTI .bin layout (float32 rows x, y, z, intensity)"
#: A .bin coordinate beyond this [m] is no LiDAR return (UTM northings stay under 1e7 m): it is the
#: bytes of another layout (float64 rows read as float32 give values up to 1e38 at random).
_KITTI_MAX_COORDINATE_M = 1e8
#: The share of points beyond that which marks a file as another layout rather than a few strays.
_KITTI_MAX_STRAY_SHARE = 0.01


def _read_bin(path: Path) -> dict[str, np.ndarray]:
    size = path.stat().st_size
    if size % 16 != 0:  # np.fromfile would drop the trailing bytes silently
        raise _FormatError(f"{size} bytes is not a whole number of 16-byte rows of the {_KITTI_LAYOUT}")
    with path.open("rb") as stream:
        if stream.read(6) == b"\x93NUMPY":
            raise _FormatError(f"a NumPy .npy array (rename it to .npy), not the {_KITTI_LAYOUT}")
    rows = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    with np.errstate(invalid="ignore"):
        strays = np.count_nonzero(np.any(np.abs(rows[:, :3]) > _KITTI_MAX_COORDINATE_M, axis=1))
    if strays > _KITTI_MAX_STRAY_SHARE * len(rows):
        raise _FormatError(
            f"{strays} of {len(rows)} points have coordinates beyond {_KITTI_MAX_COORDINATE_M:g} m: not "
            f"the {_KITTI_LAYOUT}; float64 rows, or another format renamed to .bin?"
        )
    fields = {"xyz": rows[:, :3], "intensity": rows[:, 3]}
    label_path = path.with_suffix(".label")
    if label_path.is_file():  # a SemanticKITTI label file beside the scan: uint32, class in the low 16 bits
        values = np.fromfile(label_path, dtype=np.uint32)
        if label_path.stat().st_size != 4 * len(rows):
            raise _FormatError(
                f"the label file {label_path.name} holds {label_path.stat().st_size} bytes, "
                f"{len(rows)} points need {4 * len(rows)} (one uint32 each)"
            )
        semantic = values & np.uint32(0xFFFF)
        fields["semantic"] = semantic
        if semantic.size == 0 or semantic.max() <= 255:
            fields["label"] = semantic.astype(np.uint8)
    return fields


def _check_points(array: np.ndarray) -> np.ndarray:
    if array.ndim != 2 or array.shape[1] < 3:
        raise _FormatError(f"expected an (N, >=3) array of points, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise _FormatError(f"expected a numeric array of points, got dtype {array.dtype}")
    return array


def _read_npy(path: Path) -> dict[str, np.ndarray]:
    array = _check_points(np.load(path, allow_pickle=False))
    fields = {"xyz": array[:, :3]}
    if array.shape[1] > 3:
        fields["extra"] = array[:, 3:]
    return fields


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as archive:
        keys = list(archive.keys())
        if not keys:
            raise _FormatError("the archive holds no arrays")
        key = next((k for k in ("xyz", "points") if k in archive), keys[0])
        points = _check_points(archive[key])
        fields = {"xyz": points[:, :3]}
        for name in keys:
            if name != key:
                value = archive[name]
                if value.ndim >= 1 and value.shape[0] == points.shape[0]:
                    fields[name] = value
    return fields


def _read_text(path: Path) -> dict[str, np.ndarray]:
    """Rows of numbers split by whitespace or commas (whichever the first row uses). A first line
    of column names (with or without a leading ``#``; a ``#`` line counts when it names x, y or z
    or as many columns as the rows hold, other ``#`` lines are comments) gives x, y, z by name and
    the other columns as fields; without one the first three columns are x, y, z."""
    header, first_row = None, None
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream):
            text = line.strip()
            if number == 0 and (text.startswith("#") or (text and not _has_number(text))):
                header = text
            elif text and not text.startswith("#"):
                first_row = text
                break
    delimiter = "," if first_row is not None and "," in first_row else None
    names = re.split(r"[\s,]+", header.lstrip("#").strip()) if header else []
    skip = 1 if header and not header.startswith("#") else 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
        table = np.loadtxt(path, delimiter=delimiter, skiprows=skip, ndmin=2)
    lower = [name.lower() for name in names]
    named = header is not None and (
        not header.startswith("#") or bool({"x", "y", "z"} & set(lower)) or len(names) == table.shape[1]
    )
    if not named:
        if table.size == 0:
            raise _FormatError("no points and no '# x y z ...' header")
        _check_points(table)
        return {"xyz": table[:, :3]}
    if any(lower.count(axis) != 1 for axis in "xyz"):
        raise _FormatError(
            f"the header {header[:80]!r} must name each of the columns x, y and z once "
            "(in any order, with other columns beside them)"
        )
    if table.size == 0:
        table = np.zeros((0, len(names)))
    if table.shape[1] != len(names):
        raise _FormatError(
            f"the header {header[:80]!r} names {len(names)} columns, the rows hold {table.shape[1]}"
        )
    _check_points(table)
    fields = {"xyz": table[:, [lower.index(axis) for axis in "xyz"]]}
    for column, name in enumerate(names):
        if lower[column] in ("x", "y", "z"):
            continue
        values = table[:, column]
        if name in ("label", "overhang", "classification"):
            if np.any(values != np.round(values)) or values.min(initial=0) < 0 or values.max(initial=0) > 255:
                raise _FormatError(f"column {name!r} holds values that are not labels 0..255")
            values = values.astype(np.uint8)
        fields[name] = values
    return fields


def _has_number(line: str) -> bool:
    """Whether any comma- or whitespace-separated word of ``line`` reads as a number."""
    for word in re.split(r"[\s,]+", line):
        try:
            float(word)
        except ValueError:
            continue
        return True
    return False


def _read_ply(path: Path) -> dict[str, np.ndarray]:
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise _FormatError("no 'vertex' element")
    vertex = ply["vertex"].data
    names = vertex.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise _FormatError(f"the vertex element has no x, y, z properties (has {', '.join(names)})")
    dtype = np.float64 if any(vertex.dtype[n] == np.float64 for n in "xyz") else np.float32
    fields = {"xyz": np.column_stack([vertex[n] for n in "xyz"]).astype(dtype, copy=False)}
    for name in names:
        if name not in ("x", "y", "z") and vertex.dtype[name].kind != "O":
            fields[name] = np.asarray(vertex[name])
    return fields


# The byte layout of the LAS public header block (LAS 1.0-1.4) and of the LAZ records, checked before
# laspy and lazrs see a file: a header may claim 2^32 VLRs (laspy loops on them), a LAZ chunk table of
# 0x7FFFFFFF chunks (lazrs aborts the process) or 10^8 points in a 200 kB file (gigabytes allocated).
_LAS_VLR_HEADER = 54  # bytes: reserved, user_id[16], record_id, record_length, description[32]
_LAS_EVLR_HEADER = 60
_LAZ_VLR = (b"laszip encoded", 22204)
_LAZ_VARIABLE_CHUNKS = 0xFFFFFFFF


def _check_las_layout(path: Path) -> None:
    """_FormatError when the header's counts and offsets do not fit in the file."""
    size = path.stat().st_size
    with path.open("rb") as stream:
        head = stream.read(375)
        if len(head) < 227 or head[:4] != b"LASF":
            return  # laspy names the problem
        version = (head[24], head[25])
        header_size, point_offset, vlr_count = struct.unpack_from("<HII", head, 94)
        point_format, record_length, count = struct.unpack_from("<BHI", head, 104)
        # The LAS 1.4 fields when the version or the header's size says they are there: laspy reads
        # them for a 1.4 header whose version byte reads 0.4 (its 64-bit point count, when the
        # 32-bit one, 0, let a corrupt chunk table through), and the larger count is checked.
        if (version >= (1, 4) or header_size >= 375) and len(head) >= 255:
            evlr_start, evlr_count, count64 = struct.unpack_from("<QIQ", head, 235)
            count = max(count, count64)
        else:
            evlr_start, evlr_count = 0, 0
        if point_offset > size:
            raise _FormatError(
                f"truncated LAS: the point data starts at byte {point_offset}, the file holds {size}"
            )
        if header_size > point_offset:
            raise _FormatError(
                f"corrupt LAS header: point data at byte {point_offset}, header of {header_size} bytes, "
                f"file of {size} bytes"
            )
        if vlr_count * _LAS_VLR_HEADER > point_offset - header_size:
            raise _FormatError(
                f"corrupt LAS header: {vlr_count} VLRs of at least {_LAS_VLR_HEADER} bytes each do not fit "
                f"in the {point_offset - header_size} bytes before the point data"
            )
        if evlr_count and (evlr_start > size or evlr_count * _LAS_EVLR_HEADER > size - evlr_start):
            raise _FormatError(
                f"corrupt LAS header: {evlr_count} extended VLRs from byte {evlr_start} do not fit in "
                f"the file of {size} bytes"
            )
        if not point_format & 0xC0:  # uncompressed: checked against the size after laspy's header
            return
        laszip = None
        stream.seek(header_size)
        vlrs = stream.read(point_offset - header_size)
        position = 0
        for _ in range(vlr_count):
            if position + _LAS_VLR_HEADER > len(vlrs):
                raise _FormatError("corrupt LAS header: the VLRs run into the point data")
            user_id = vlrs[position + 2 : position + 18].split(b"\0")[0]
            record_id, length = struct.unpack_from("<HH", vlrs, position + 18)
            if (user_id, record_id) == _LAZ_VLR and length >= 34:
                start = position + _LAS_VLR_HEADER
                laszip = vlrs[start : start + length]
            position += _LAS_VLR_HEADER + length
        if laszip is None or len(laszip) < 34:
            raise _FormatError("corrupt LAZ: compressed points but no whole 'laszip encoded' VLR")
        compressor, chunk_size = (
            struct.unpack_from("<H", laszip, 0)[0],
            struct.unpack_from("<I", laszip, 12)[0],
        )
        if count == 0:
            return
        stream.seek(point_offset)
        raw = stream.read(8)
        table = struct.unpack("<q", raw)[0] if len(raw) == 8 else -2
        if table == -1 and size >= 8:  # written to a stream: the offset is in the last 8 bytes
            stream.seek(size - 8)
            table = struct.unpack("<q", stream.read(8))[0]
        data_bytes = table - (point_offset + 8)
        if data_bytes >= 0 and table + 8 > size:
            raise _FormatError(
                f"truncated LAZ: the chunk table at byte {table} lies past the end of the file ({size} bytes)"
            )
        if data_bytes < 0:
            raise _FormatError(
                f"corrupt LAZ chunk table: offset {table} outside the point data (bytes {point_offset + 8}"
                f"..{size - 8})"
            )
        stream.seek(table)
        _, chunks = struct.unpack("<II", stream.read(8))
        if chunks < 1 or chunks > data_bytes:  # every chunk holds at least one point of several bytes
            raise _FormatError(
                f"corrupt LAZ chunk table: {chunks} chunks for {count} points in {data_bytes} bytes of data"
            )
        if chunk_size != _LAZ_VARIABLE_CHUNKS and chunk_size and chunks != -(-count // chunk_size):
            raise _FormatError(
                f"corrupt LAZ: the header promises {count} points, {chunks} chunks of {chunk_size} hold "
                f"{(chunks - 1) * chunk_size + 1}..{chunks * chunk_size}"
            )
        layers = _laz_layer_count(laszip)
        if compressor == _LAZ_LAYERED:
            _check_laz_layered_chunks(stream, point_offset + 8, table, chunks, count, record_length, layers)


_LAZ_LAYERED = 3  # LASzip's compressor for point formats 6..10: each chunk's fields in separate layers
# Layers per LAZ 1.4 item type: point14 (x/y, z, classification, flags, intensity, scan angle, user
# data, point source, gps time), rgb14, rgbnir14, wavepacket14; byte14 (extra bytes) has one per byte.
_LAZ_ITEM_LAYERS = {10: 9, 11: 1, 12: 2, 13: 1}
_LAZ_BYTE14 = 14


def _laz_layer_count(laszip: bytes) -> int:
    (items,) = struct.unpack_from("<H", laszip, 32)
    if items == 0 or 34 + 6 * items > len(laszip):
        raise _FormatError(
            f"corrupt LAZ: the 'laszip encoded' VLR lists {items} items in {len(laszip)} bytes"
        )
    layers = 0
    for i in range(items):
        kind, item_size, _ = struct.unpack_from("<HHH", laszip, 34 + 6 * i)
        layers += item_size if kind == _LAZ_BYTE14 else _LAZ_ITEM_LAYERS.get(kind, 0)
    return layers


def _check_laz_layered_chunks(
    stream, start: int, table: int, chunks: int, count: int, record: int, layers: int
):
    """Walks the layered chunks: each is a raw first point, its point count (uint32), the byte size
    of each layer (uint32) and the layers. _FormatError when a chunk or layer runs past the chunk
    table or the counts do not add up to the header's (lazrs would allocate what a size claims)."""
    position, total = start, 0
    for chunk in range(chunks):
        stream.seek(position + record)
        raw = stream.read(4 + 4 * layers)
        if position + record + len(raw) > table or len(raw) < 4 + 4 * layers:
            raise _FormatError(f"corrupt LAZ: chunk {chunk} runs past the chunk table at byte {table}")
        points, *sizes = struct.unpack(f"<I{layers}I", raw)
        position += record + len(raw) + sum(sizes)
        total += points
        if position > table or points == 0 or total > count:
            raise _FormatError(
                f"corrupt LAZ: chunk {chunk} claims {points} points in layers of {sum(sizes)} bytes, past "
                f"the chunk table at byte {table} or the header's {count} points"
            )
    if total != count:
        raise _FormatError(f"corrupt LAZ: the chunks hold {total} points, the header promises {count}")


def _read_las(path: Path) -> dict[str, np.ndarray]:
    try:
        import laspy
    except ImportError as error:
        raise ImportError("LAS/LAZ reading needs the las extra: pip install 'terracube[las]'") from error
    _check_las_layout(path)
    # lazrs' single-threaded backend: the parallel one (rayon's thread pool) deadlocks a forked child.
    backend = laspy.LazBackend.Lazrs
    try:
        with laspy.open(str(path), laz_backend=backend) as reader:
            header = reader.header
    except Exception as error:
        raise _FormatError(f"not a valid LAS/LAZ file ({type(error).__name__}: {error})") from None
    count = int(header.point_count)
    if not header.are_points_compressed:
        need = header.offset_to_point_data + count * header.point_format.size
        size = path.stat().st_size
        if size < need:
            raise _FormatError(
                f"truncated LAS: the header promises {count} points of {header.point_format.size} bytes "
                f"from byte {header.offset_to_point_data} ({need} bytes), the file holds {size}"
            )
    try:
        las = laspy.read(str(path), laz_backend=backend)
    except Exception as error:
        raise _FormatError(
            f"truncated or corrupt LAS/LAZ point data ({type(error).__name__}: {error})"
        ) from None
    points = las.points
    if len(points) != count:
        raise _FormatError(f"truncated: the header promises {count} points, the file holds {len(points)}")
    fields = {"xyz": np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])}
    for name in ("intensity", "classification", "return_number", "number_of_returns", "gps_time"):
        if name in points.point_format.dimension_names:
            fields[name] = np.asarray(las[name])
    for name in points.point_format.extra_dimension_names:
        fields[name] = np.asarray(las[name])
    if "overhang" in fields:
        fields["label"] = fields["overhang"].astype(np.uint8)
    elif "classification" in fields:
        fields["classification"] = fields["classification"].astype(np.uint8)
    return fields


# PCD (Point Cloud Library), https://pointclouds.org/documentation/tutorials/pcd_file_format.html.
# pypcd4 decodes and encodes the data; the checks here turn a truncated or corrupt file into a
# message naming the problem instead of a short or garbled cloud.

_PCD_ENCODINGS = ("ascii", "binary", "binary_compressed")
_PCD_MAX_HEADER = 1 << 16
# Values per point over all fields (PCL's largest descriptors, VFH and ESF, have 308 and 640).
_PCD_MAX_VALUES = 4096


def _pcd_header(data: bytes):
    """pypcd4's MetaData of a PCD file and the offset of its data (just after the DATA line)."""
    from pydantic import ValidationError
    from pypcd4.pypcd4 import MetaData

    lines, offset = [], 0
    while not (lines and lines[-1].upper().startswith("DATA")):
        end = data.find(b"\n", offset)
        if end < 0 or end > _PCD_MAX_HEADER:
            known = any(line.upper().startswith(("FIELDS", "VERSION")) for line in lines)
            raise _FormatError("truncated PCD header: no DATA line" if known else "not a PCD file: no header")
        line = data[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if line and not line.startswith("#"):
            if line.split()[0].upper() not in _PCD_HEADER_KEYS:
                excerpt = line[:60]
                if not (excerpt.isascii() and excerpt.replace("\t", " ").isprintable()):
                    raise _FormatError(
                        "not a PCD file: binary data where the header (VERSION, FIELDS, ...) belongs"
                    )
                raise _FormatError(f"not a PCD file: unexpected header line {excerpt!r}")
            lines.append(line)
    try:
        metadata = MetaData.parse_header(lines)
    except (ValidationError, ValueError) as error:
        raise _FormatError(f"bad PCD header: {error}".splitlines()[0]) from None
    fields = metadata.fields
    if not len(fields) == len(metadata.size) == len(metadata.type) == len(metadata.count):
        raise _FormatError(
            f"PCD header: FIELDS, SIZE, TYPE and COUNT differ in length "
            f"({len(fields)}, {len(metadata.size)}, {len(metadata.type)}, {len(metadata.count)})"
        )
    # pypcd4 makes a column per value of a field: a COUNT of 10^20 would never return.
    if any(count < 1 for count in metadata.count) or sum(metadata.count) > _PCD_MAX_VALUES:
        raise _FormatError(
            f"PCD header: COUNT {' '.join(map(str, metadata.count))} must give each field 1 or more values, "
            f"{_PCD_MAX_VALUES} in all at most"
        )
    if not {"x", "y", "z"} <= set(fields):
        raise _FormatError(f"PCD has no x, y, z fields (has {', '.join(fields)})")
    if metadata.data.value not in _PCD_ENCODINGS:
        raise _FormatError(f"unknown PCD DATA encoding {metadata.data.value!r} ({', '.join(_PCD_ENCODINGS)})")
    return metadata, offset


_PCD_HEADER_KEYS = (
    "VERSION",
    "FIELDS",
    "SIZE",
    "TYPE",
    "COUNT",
    "WIDTH",
    "HEIGHT",
    "VIEWPOINT",
    "POINTS",
    "DATA",
)


# LZF's best case: a back-reference of 264 bytes in 3 bytes, so at most ~88 bytes out per byte in.
_LZF_MAX_RATIO = 90


def _check_pcd_body(body: bytes, metadata) -> None:
    """_FormatError when the data after the header is shorter than the header announces."""
    points, encoding = metadata.points, metadata.data.value
    need = points * metadata.build_dtype().itemsize
    if encoding == "ascii":
        rows = sum(1 for line in body.splitlines() if line.strip())
        if rows < points:
            raise _FormatError(f"truncated ascii PCD: {points} points announced, {rows} rows found")
    elif encoding == "binary" and len(body) < need:
        raise _FormatError(
            f"truncated binary PCD: {points} points need {need} bytes of data, the file holds {len(body)}"
        )
    elif encoding == "binary_compressed" and points:
        if len(body) < 8:
            raise _FormatError("truncated binary_compressed PCD: no compressed-size header after DATA")
        compressed, uncompressed = (int(v) for v in np.frombuffer(body, dtype="<u4", count=2))
        if uncompressed != need:
            raise _FormatError(
                f"binary_compressed PCD: the data header gives {uncompressed} uncompressed bytes, "
                f"{points} points need {need}"
            )
        if uncompressed > _LZF_MAX_RATIO * compressed + 64:  # a header that asks for gigabytes
            raise _FormatError(
                f"binary_compressed PCD: {uncompressed} bytes cannot come from {compressed} bytes of LZF data"
            )
        if len(body) - 8 < compressed:
            raise _FormatError(
                f"truncated binary_compressed PCD: {compressed} compressed bytes announced, "
                f"the file holds {len(body) - 8}"
            )


def _read_pcd(path: Path) -> dict[str, np.ndarray]:
    import io

    from pypcd4 import PointCloud

    data = path.read_bytes()
    metadata, offset = _pcd_header(data)
    _check_pcd_body(data[offset:], metadata)
    try:
        rows = np.atleast_1d(PointCloud.from_fileobj(io.BufferedReader(io.BytesIO(data))).pc_data)
    except (ValueError, RuntimeError) as error:
        if metadata.data.value == "binary_compressed":
            raise _FormatError(f"corrupt binary_compressed PCD data ({error})") from None
        raise _FormatError(
            f"{metadata.data.value} PCD: rows of unequal length or non-numbers ({error})"
        ) from None
    columns = {}
    for name, count in zip(metadata.fields, metadata.count, strict=True):
        if count == 1:
            columns[name] = np.array(rows[name])
        else:  # pypcd4 splits a field of COUNT k into k columns name__0000 ...
            columns[name] = np.column_stack([rows[f"{name}__{i:04d}"] for i in range(count)])
    fields = {"xyz": np.column_stack([columns.pop(axis) for axis in "xyz"])}
    if fields["xyz"].dtype not in (np.float32, np.float64):
        fields["xyz"] = fields["xyz"].astype(np.float64)
    fields.update(columns)
    return fields


def organised_shape(path: PathLike) -> tuple[int, int] | None:
    """(HEIGHT, WIDTH) of an organised PCD file (HEIGHT > 1 and WIDTH x HEIGHT = POINTS: a row per
    beam, a column per firing, as Ouster and Velodyne drivers write a scan), from its header; None
    for any other file. ``read_cloud(path)["xyz"].reshape(HEIGHT, WIDTH, 3)`` is then its image."""
    path = Path(path)
    if path.suffix.lower() != ".pcd" or not path.is_file():
        return None
    with path.open("rb") as stream:
        head = stream.read(_PCD_MAX_HEADER + 1)
    try:
        metadata, _ = _pcd_header(head)
    except _FormatError:
        return None
    height, width = int(metadata.height), int(metadata.width)
    return (height, width) if height > 1 and height * width == int(metadata.points) else None


# --------------------------------------------------------------------------------------------- writers


def write_pcd(
    path: PathLike,
    fields: dict[str, np.ndarray],
    encoding: str = "binary",
    image_shape: tuple[int, int] | None = None,
) -> Path:
    """Write a PCD v0.7 file of named per-point fields (each (N,) or (N, COUNT), numeric), with pypcd4.

    ``fields`` must hold ``x``, ``y`` and ``z``, or ``xyz`` ((N, 3)), which is split into them.
    ``encoding`` is ``ascii``, ``binary`` or ``binary_compressed`` (LZF, as PCL writes it; data LZF
    cannot shrink is stored as ``binary``, as pypcd4 does). Booleans are stored as U1. The cloud is
    unorganised (WIDTH = N, HEIGHT = 1) unless ``image_shape`` (HEIGHT, WIDTH) lays the N rows out
    as an image (:func:`organised_shape` reads it back).
    """
    from pypcd4 import Encoding, PointCloud
    from pypcd4.pypcd4 import MetaData

    path = Path(path)
    if encoding not in _PCD_ENCODINGS:
        raise ValueError(f"{path}: unknown PCD encoding {encoding!r} (use {', '.join(_PCD_ENCODINGS)})")
    columns: dict[str, np.ndarray] = {}
    for name, value in fields.items():
        value = np.asarray(value)
        if name == "xyz":
            columns.update({axis: value[:, i] for i, axis in enumerate("xyz")})
        else:
            columns[name] = value.astype(np.uint8) if value.dtype == bool else value
    if not {"x", "y", "z"} <= set(columns):
        raise ValueError(f"{path}: a PCD needs x, y and z fields")
    n = len(columns["x"])
    height, width = (1, n) if image_shape is None else (int(image_shape[0]), int(image_shape[1]))
    if height * width != n or height < 1:
        raise ValueError(f"{path}: an image of {height} x {width} cannot hold {n} points")
    types, counts = [], []
    for name, value in columns.items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise ValueError(f"{path}: {name!r} is not a valid PCD field name")
        if value.shape[:1] != (n,) or value.ndim > 2:
            raise ValueError(f"{path}: field {name!r} has shape {value.shape}, expected ({n},) or ({n}, k)")
        kind = {"f": "F", "u": "U", "i": "I"}.get(value.dtype.kind)
        if kind is None or (kind == "F" and value.dtype.itemsize not in (4, 8)):
            raise ValueError(f"{path}: field {name!r} has dtype {value.dtype}, not storable in a PCD")
        types.append(kind)
        counts.append(1 if value.ndim == 1 else value.shape[1])
    metadata = MetaData(
        fields=tuple(columns),
        size=tuple(v.dtype.itemsize for v in columns.values()),
        type=tuple(types),
        count=tuple(counts),
        points=n,
        width=width,
        height=height,
        data=Encoding(encoding),
    )
    rows = np.empty(n, dtype=metadata.build_dtype())
    for (name, value), count in zip(columns.items(), counts, strict=True):
        for i in range(count):
            rows[name if count == 1 else f"{name}__{i:04d}"] = value if count == 1 else value[:, i]
    cloud = PointCloud(metadata, rows)
    if encoding != "ascii":
        with atomic_path(path) as temporary:
            cloud.save(temporary, encoding=Encoding(encoding))
        return path
    # pypcd4 writes floats as %.10f, which rounds small values; these formats read back bit for bit.
    formats = ["%.9g" if rows.dtype[i] == np.float32 else "%.17g" if rows.dtype[i].kind == "f" else "%d"
               for i in range(len(rows.dtype))]  # fmt: skip
    with atomic_path(path) as temporary, temporary.open("wb") as stream:
        stream.write(metadata.compose_header(data=Encoding.ASCII).encode("ascii"))
        if n:
            np.savetxt(stream, rows, fmt=formats)
    return path


# A colour per class label for PLY (ASPRS-like where the codes are ASPRS; others cycle a palette).
_PALETTE = np.array(
    [
        [150, 150, 150], [190, 190, 190], [160, 110, 60], [120, 200, 90], [60, 160, 60], [20, 110, 30],
        [220, 60, 50], [255, 0, 255], [240, 200, 60], [40, 110, 230], [130, 80, 160], [90, 90, 90],
        [250, 150, 30], [30, 200, 200], [200, 120, 200], [100, 60, 20],
    ],
    dtype=np.uint8,
)  # fmt: skip


def _label_colours(labels: np.ndarray, is_mask: bool) -> np.ndarray:
    if is_mask:  # retained grey, overhang red
        return np.where(labels[:, None] != 0, np.uint8([230, 30, 30]), np.uint8([150, 150, 150])).astype(
            np.uint8
        )
    return _PALETTE[labels % len(_PALETTE)]


def _las_scale(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets and scales for LAS: 0.1 mm where the extent allows it (int32 range), else coarser."""
    columns = [points[:, axis] for axis in range(3)]  # row-wise reductions of (N, 3) are slow
    lo = np.floor([np.nanmin(c) for c in columns]) if len(points) else np.zeros(3)
    hi = np.array([np.nanmax(c) for c in columns]) if len(points) else np.zeros(3)
    scale = np.full(3, 1e-4)
    while np.any((hi - lo) / scale > 2**31 - 2):
        scale = np.where((hi - lo) / scale > 2**31 - 2, scale * 10, scale)
    return lo, scale


def write_kitti_bin(path: PathLike, points: np.ndarray, intensity: np.ndarray | None = None) -> Path:
    """Write a KITTI-style ``.bin``: float32 rows x, y, z, intensity (0 when ``intensity`` is None).

    Coordinates are stored as float32 whatever the input dtype (the format has no other).
    """
    path = Path(path)
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"{path}: need (N, 3) points, got shape {points.shape}")
    rows = np.zeros((points.shape[0], 4), dtype="<f4")
    rows[:, :3] = points[:, :3]
    if intensity is not None:
        intensity = np.asarray(intensity)
        if intensity.shape != (points.shape[0],):
            raise ValueError(f"{path}: need ({points.shape[0]},) intensities, got shape {intensity.shape}")
        rows[:, 3] = intensity
    with atomic_path(path) as temporary:
        rows.tofile(temporary)
    return path


def write_classified(
    path: PathLike,
    points: np.ndarray,
    labels: np.ndarray,
    *,
    las_classes: dict[int, int] | None = None,
    source: PathLike | None = None,
    as_classification: bool = False,
    fields: dict[str, np.ndarray] | None = None,
    image_shape: tuple[int, int] | None = None,
) -> Path:
    """Write points with one label each: a bool overhang mask or uint8 classes (0..255).

    ``fields``: other per-point fields to carry (a :func:`read_cloud` dict; ``xyz`` and a field of
    the label's name are left out), kept by every format but LAS/LAZ and ``.npy``: PCD all of them,
    PLY and text the (N,) ones, ``.npz`` all, ``.bin`` its ``intensity``. ``image_shape``: (HEIGHT,
    WIDTH) of an organised PCD output (the points in image order; :func:`write_pcd`).

    A LAS/LAZ output with a LAS/LAZ ``source`` (the file ``points`` were read from, same points in
    the same order) is that file with the labels added (:func:`_write_las_from_source`): every
    dimension, the CRS and every VLR kept, the labels in an extra dimension ``overhang`` (mask) or
    ``terracube_class``, and in ``classification`` only with ``as_classification`` (a point format
    0-5 input, whose classification holds 0..31, is then written in the LAS 1.4 format 6-10 that
    holds the same dimensions).

    The format follows the suffix; ``read_cloud`` gives the same labels back (``"label"``, uint8):

    - ``.ply``: binary; float x y z (float64 if the points are), the ``fields``, a uchar property
      ``overhang`` (mask) or ``label`` (classes), and an RGB colour (mask: retained grey, overhang red).
    - ``.pcd``: binary PCD v0.7; fields x y z (F4 or F8), the ``fields`` and ``overhang`` (U1, mask)
      or ``label`` (U1).
    - ``.las`` / ``.laz``: LAS 1.4, point format 6, coordinates at 0.1 mm (coarser only when the
      extent exceeds the int32 range). Classes go into ``classification`` as they are (ASPRS codes
      where the labels are). A mask writes ``classification`` 1 (``RETAINED_LAS_CLASS``, ASPRS
      "unclassified") for retained and 64 (``OVERHANG_LAS_CLASS``, first user-definable code) for
      overhang points, plus a uint8 extra dimension ``overhang`` that the reader prefers. With
      ``las_classes`` (label -> LAS code, e.g. :data:`TERRAIN_LAS_CLASSES`) classes are written as
      those codes, and the labels themselves in a uint8 extra dimension ``label``.
    - ``.bin``: KITTI float32 rows x, y, z, intensity (0 without one) and, beside it, a
      SemanticKITTI-style ``.label`` file of uint32 labels (the overhang mask as 0/1).
    - ``.npz``: ``xyz``, the ``fields`` and ``overhang`` (bool, mask) or ``label`` (uint8).
    - ``.npy``: an (N, 4) array x, y, z, label in the points' float dtype.
    - ``.txt`` / ``.xyz``: a ``# x y z ... overhang`` (or ``label``) header line naming the columns,
      then rows x y z (at 0.1 mm), the ``fields`` (9 significant digits) and the label.
    """
    path = Path(path)
    points = np.asarray(points)
    labels = np.asarray(labels)
    if points.ndim != 2 or points.shape[1] < 3 or labels.shape != (points.shape[0],):
        raise ValueError(f"{path}: need (N, 3) points and (N,) labels, got {points.shape} and {labels.shape}")
    is_mask = labels.dtype == bool
    if not is_mask:
        if not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(
                f"{path}: labels must be a bool mask or integers 0..255, got dtype {labels.dtype}"
            )
        if labels.size and (labels.min() < 0 or labels.max() > 255):
            raise ValueError(f"{path}: labels must lie in 0..255, got {labels.min()}..{labels.max()}")
    label_u8 = labels.astype(np.uint8)
    name = "overhang" if is_mask else "label"
    xyz = points[:, :3]
    if xyz.dtype not in (np.float32, np.float64):
        xyz = xyz.astype(np.float64)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise ValueError(f"{path}: unknown output format {suffix!r} (use {', '.join(WRITE_SUFFIXES)})")
    extra = _carried_fields(path, fields, name, len(xyz))
    if suffix == ".pcd":
        return write_pcd(path, {"xyz": xyz, **extra, name: label_u8}, "binary", image_shape)
    if suffix == ".bin":  # the labels first: a scan under its final name always has its labels beside it
        with atomic_path(path.with_suffix(".label")) as temporary:
            label_u8.astype("<u4").tofile(temporary)
        intensity = extra.get("intensity")
        return write_kitti_bin(path, xyz, None if intensity is None or intensity.ndim != 1 else intensity)
    if suffix in (".las", ".laz"):
        _check_las(path, xyz, label_u8, is_mask, las_classes)
        if source is not None and Path(source).suffix.lower() in (".las", ".laz"):
            with atomic_path(path) as temporary:
                _write_las_from_source(
                    temporary, Path(source), label_u8, is_mask, las_classes, as_classification
                )
            return path
    with atomic_path(path) as temporary:
        _write_classified(temporary, suffix, xyz, labels, label_u8, is_mask, las_classes, extra)
    return path


def _carried_fields(
    path: Path, fields: dict[str, np.ndarray] | None, label_name: str, n: int
) -> dict[str, np.ndarray]:
    """The numeric (N,) and (N, k) ``fields`` to write beside the points and their label."""
    carried = {}
    for name, value in (fields or {}).items():
        value = np.asarray(value)
        if name in ("xyz", "x", "y", "z", label_name) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            continue
        if value.dtype == bool:
            value = value.astype(np.uint8)
        if value.dtype.kind not in "fiu" or value.ndim not in (1, 2) or len(value) != n:
            continue
        carried[name] = value
    return carried


# Text columns that read back exactly: integers whole, float32 in 9 significant digits, float64 in 17.
_TEXT_FORMATS = {**{f"{k}{n}": "%d" for k in "iu" for n in (1, 2, 4, 8)}, "f4": "%.9g"}

# The numeric dtypes a PLY property can hold; 64-bit integers go as float64 (exact below 2**53).
_PLY_KINDS = {"i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"}


def _write_classified(
    path: Path,
    suffix: str,
    xyz: np.ndarray,
    labels: np.ndarray,
    label_u8: np.ndarray,
    is_mask: bool,
    las_classes: dict[int, int] | None,
    extra: dict[str, np.ndarray],
) -> None:
    name = "overhang" if is_mask else "label"
    # PLY properties and text columns: the (N,) fields, but an earlier output's colour, made anew here
    columns = {k: v for k, v in extra.items() if v.ndim == 1 and k not in ("red", "green", "blue")}
    if suffix == ".ply":
        from plyfile import PlyData, PlyElement

        kind = "f8" if xyz.dtype == np.float64 else "f4"
        kinds = {k: v.dtype.str[1:] if v.dtype.str[1:] in _PLY_KINDS else "f8" for k, v in columns.items()}
        vertex = np.empty(
            len(xyz),
            dtype=[
                ("x", kind),
                ("y", kind),
                ("z", kind),
                *kinds.items(),
                (name, "u1"),
                ("red", "u1"),
                ("green", "u1"),
                ("blue", "u1"),
            ],
        )
        vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        for key, value in columns.items():
            vertex[key] = value
        vertex[name] = label_u8
        colours = _label_colours(label_u8, is_mask)
        vertex["red"], vertex["green"], vertex["blue"] = colours[:, 0], colours[:, 1], colours[:, 2]
        PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(str(path))
    elif suffix in (".las", ".laz"):
        _write_las(path, xyz, label_u8, is_mask, las_classes)
    elif suffix == ".npz":
        np.savez_compressed(path, xyz=xyz, **extra, **{name: labels.astype(bool) if is_mask else label_u8})
    elif suffix == ".npy":
        np.save(path, np.column_stack([xyz, label_u8.astype(xyz.dtype)]))
    else:
        table = (
            np.column_stack([xyz, *columns.values(), label_u8])
            if columns
            else np.column_stack([xyz, label_u8])
        )
        formats = (
            ["%.4f"] * 3
            + [_TEXT_FORMATS.get(v.dtype.kind + str(v.dtype.itemsize), "%.17g") for v in columns.values()]
            + ["%d"]
        )
        with open(path, "w", encoding="ascii") as stream:
            stream.write(f"# x y z {''.join(k + ' ' for k in columns)}{name}\n")
            np.savetxt(stream, table, fmt=formats)


def _check_las(
    path: Path, xyz: np.ndarray, labels: np.ndarray, is_mask: bool, las_classes: dict[int, int] | None
) -> np.ndarray | None:
    """ValueError naming ``path`` for what LAS cannot store; the LAS codes of ``labels`` when
    ``las_classes`` maps them."""
    if not np.all(np.isfinite(xyz)):
        raise ValueError(f"{path}: LAS cannot store NaN or infinite coordinates; drop those points first")
    if las_classes is None or is_mask:
        return None
    lookup = np.full(256, RETAINED_LAS_CLASS, dtype=np.uint8)
    for label, code in las_classes.items():
        if not (0 <= int(label) <= 255 and 0 <= int(code) <= 255):
            raise ValueError(f"{path}: las_classes maps {label} -> {code}; both must lie in 0..255")
        lookup[int(label)] = int(code)
    missing = np.setdiff1d(np.unique(labels), list(las_classes))
    if missing.size:
        raise ValueError(f"{path}: las_classes has no LAS code for the labels {missing.tolist()}")
    return lookup[labels]


def _write_las(
    path: Path, xyz: np.ndarray, labels: np.ndarray, is_mask: bool, las_classes: dict[int, int] | None
) -> None:
    try:
        import laspy
    except ImportError as error:
        raise ImportError("LAS/LAZ writing needs the las extra: pip install 'terracube[las]'") from error
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets, header.scales = _las_scale(np.asarray(xyz, dtype=np.float64))
    codes = _check_las(path, xyz, labels, is_mask, las_classes)
    if is_mask:
        header.add_extra_dim(
            laspy.ExtraBytesParams(name="overhang", type=np.uint8, description="1 = overhang")
        )
    elif codes is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="label", type=np.uint8, description="class label"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if is_mask:
        las.classification = np.where(labels != 0, OVERHANG_LAS_CLASS, RETAINED_LAS_CLASS).astype(np.uint8)
        las.overhang = labels
    elif codes is not None:
        las.classification = codes
        las.label = labels
    else:
        las.classification = labels
    las.write(str(path))


#: Description of the extra dimension holding terracube's terrain class (:class:`terracube.TerrainClass`).
TERRAIN_CLASS_DIMENSION = "terracube_class"


def _write_las_from_source(
    path: Path,
    source: Path,
    labels: np.ndarray,
    is_mask: bool,
    las_classes: dict[int, int] | None,
    as_classification: bool,
) -> None:
    """The LAS/LAZ ``source`` with the labels added as an extra dimension (``classification`` too
    with ``as_classification``): header, VLRs (CRS), EVLRs and every point dimension kept."""
    import laspy

    las = laspy.read(str(source), laz_backend=laspy.LazBackend.Lazrs)
    if len(las.points) != len(labels):
        raise ValueError(
            f"{path}: {len(labels)} labels for the {len(las.points)} points of {source}: "
            "write the classified cloud from the points as read"
        )
    name = "overhang" if is_mask else TERRAIN_CLASS_DIMENSION
    if name not in las.point_format.dimension_names:
        description = "1 = overhang (terracube)" if is_mask else "terrain class (terracube)"
        las.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.uint8, description=description))
    las[name] = labels
    if as_classification:
        if is_mask:
            codes = np.where(labels != 0, OVERHANG_LAS_CLASS, np.asarray(las.classification)).astype(np.uint8)
        else:
            codes = _check_las(path, np.zeros((0, 3)), labels, False, las_classes)
            codes = labels if codes is None else codes
        if las.point_format.id < 6 and codes.size and codes.max() > 31:
            # formats 0-5 hold classes 0..31: the LAS 1.4 format with the same dimensions holds 0..255
            las = laspy.convert(las, point_format_id=_LAS14_FORMAT[las.point_format.id], file_version="1.4")
        las.classification = codes
    las.write(str(path))


#: The LAS 1.4 point format holding every dimension of an older one (and classes up to 255).
_LAS14_FORMAT = {0: 6, 1: 6, 2: 7, 3: 7, 4: 9, 5: 10}


def read_crs(path: PathLike) -> str | None:
    """The coordinate reference system of a point-cloud file as WKT or ``EPSG:code``, or None.

    LAS/LAZ: the OGC WKT VLR, else the projected (3072) or geographic (2048) EPSG code of the GeoTIFF
    key directory. Other formats carry none.
    """
    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        return None
    try:
        import laspy
    except ImportError as error:
        raise ImportError("LAS/LAZ reading needs the las extra: pip install 'terracube[las]'") from error
    with laspy.open(str(path), laz_backend=laspy.LazBackend.Lazrs) as reader:
        vlrs = list(reader.header.vlrs)
    for vlr in vlrs:
        if vlr.record_id == 2112 and getattr(vlr, "string", None):
            return vlr.string.rstrip("\x00").strip()
    for vlr in vlrs:
        keys = {key.id: key.value_offset for key in getattr(vlr, "geo_keys", ())}
        for key in (3072, 2048):  # ProjectedCSTypeGeoKey, GeographicTypeGeoKey
            if 1024 <= keys.get(key, 0) < 32767:  # 32767: user-defined, no EPSG code
                return f"EPSG:{keys[key]}"
    return None


def crs_length_unit(crs: str | None) -> tuple[str, float | None] | None:
    """The unit a CRS (WKT or ``EPSG:code``, e.g. :func:`read_crs`) measures x and y in: (name,
    metres per unit), e.g. ``("US survey foot", 0.3048006096)``, ``("degree", None)`` for a
    geographic CRS; None without a CRS, when it cannot be parsed, or without the ``geo`` extra
    (rasterio, which reads the CRS)."""
    if not crs:
        return None
    try:
        from rasterio.crs import CRS
        from rasterio.errors import CRSError
    except ImportError:
        return None
    try:
        parsed = CRS.from_user_input(crs)
        if parsed.is_geographic:
            return "degree", None
        name, factor = parsed.linear_units_factor
    except (CRSError, ValueError):
        return None
    return str(name), float(factor)


#: Layers measured in the unit of length of the map's coordinates (metres in a sensor frame); the
#: others: "variance" in its square, "slope" in radians, "time" in seconds, the rest without a unit.
_LENGTH_LAYERS = frozenset(
    {"min", "max", "mean", "std_dev", "elevation", "overhang_min", "clearance", "step", "roughness"}
    | {"relative_height", "ground", "fem"}
)


def _band_unit(layer: str, crs: str | None) -> str:
    """The GDAL unit type of a layer's band: the CRS's length unit (metre without one)."""
    unit = crs_length_unit(crs)
    length = "metre" if unit is None or unit[1] is None else unit[0]
    if layer in _LENGTH_LAYERS:
        return length
    return {"variance": f"{length}^2", "slope": "radian", "time": "second"}.get(layer, "")


def write_geotiff(elevation_map, layer: str, path: PathLike, *, crs: str | None = None) -> Path:
    """Write one map layer as a deflate-compressed GeoTIFF (needs the ``geo`` extra: rasterio).

    Float layers are float32 with nodata NaN; the ``class`` layer is uint8 with nodata 0 (unknown),
    the class names as the band's category names and a colour table. ``crs`` (WKT or ``EPSG:code``,
    e.g. :func:`read_crs` of the input) georeferences it; None leaves the sensor frame unnamed. The
    band's unit is that of the values: heights in the CRS's unit of length (metre without a CRS or
    with a geographic one; read with the CRS by :func:`crs_length_unit`), slope in radian.
    """
    try:
        import rasterio
        from affine import Affine
    except ImportError as error:
        raise ImportError("GeoTIFF export needs rasterio: pip install 'terracube[geo]'") from error
    from .classes import TERRAIN_COLORS, TerrainClass

    path = Path(path)
    g = elevation_map.geometry
    data = np.asarray(elevation_map[layer])
    # Rasters run north-down: row 0 is the largest y, so rows are j reversed and columns are i.
    raster = np.ascontiguousarray(data.T[::-1, :])
    is_class = layer == "class"
    if is_class:
        raster = np.nan_to_num(raster, nan=0.0).astype(np.uint8)
    else:
        raster = raster.astype(np.float32)
    top = g.origin[1] + g.size[1] * g.resolution
    profile = dict(
        driver="GTiff",
        height=raster.shape[0],
        width=raster.shape[1],
        count=1,
        dtype="uint8" if is_class else "float32",
        crs=crs,
        transform=Affine(g.resolution, 0.0, g.origin[0], 0.0, -g.resolution, top),  # north up
        nodata=0 if is_class else np.nan,
        compress="deflate",
        predictor=1 if is_class else 3,
        tiled=raster.shape[0] >= 256 and raster.shape[1] >= 256,
    )
    with atomic_path(path) as temporary, rasterio.open(temporary, "w", **profile) as dataset:
        dataset.write(raster, 1)
        dataset.set_band_description(1, layer)
        dataset.units = (_band_unit(layer, crs),)
        if is_class:  # the category names as band metadata in the file, and GDAL's own in a .aux.xml
            names = [c.name.lower() for c in TerrainClass]
            dataset.update_tags(1, CATEGORY_NAMES=",".join(names))
            dataset.update_tags(1, **{f"CLASS_{int(c)}": c.name.lower() for c in TerrainClass})
            dataset.write_colormap(
                1,
                {
                    int(c): (*(round(255 * v) for v in TERRAIN_COLORS[c]), 0 if c == 0 else 255)
                    for c in TerrainClass
                },
            )
    if is_class:
        _write_category_names(path, [c.name.lower() for c in TerrainClass])
    return path


def _write_category_names(path: Path, names: list[str]) -> Path:
    """GDAL's category names of band 1 in its PAM sidecar ``PATH.aux.xml`` (QGIS and gdalinfo show
    them as the raster's classes)."""
    from xml.sax.saxutils import escape

    categories = "".join(f"<Category>{escape(name)}</Category>" for name in names)
    text = (
        '<PAMDataset>\n  <PAMRasterBand band="1">\n'
        f"    <CategoryNames>{categories}</CategoryNames>\n"
        "  </PAMRasterBand>\n</PAMDataset>\n"
    )
    sidecar = path.with_name(path.name + ".aux.xml")
    with atomic_path(sidecar) as temporary:
        temporary.write_text(text, encoding="utf-8")
    return sidecar
