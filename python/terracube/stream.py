"""``terracube stream``: a scan sequence fused into a robot-centric :class:`terracube.LocalMap`."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from .local_map import LocalMap, LocalMapParams
from .mapping import Mapper, MapperParams
from .pipeline import (
    StageReport,
    local_map_reach_warning,
    median_horizontal_range,
    scan_span,
    scan_span_warning,
)

__all__ = ["run_stream", "LidarOnlyPoses", "check_animation_target"]

ANIMATION_SUFFIXES = (".gif", ".mp4")


def _frame_png(local_map: LocalMap, path: Path, title: str) -> Path:
    from .viz import plot_layer

    return plot_layer(local_map.to_elevation_map(), "elevation", path, title=title)


def _animation_writer(path: Path):
    """The matplotlib writer of ``path``'s suffix (an instance), or why there is none."""
    try:
        from matplotlib import animation
    except ImportError as error:  # pragma: no cover - matplotlib is a plotting extra
        raise ImportError('an animation needs matplotlib: pip install "terracube[plot]"') from error
    if path.suffix.lower() == ".gif":
        if not animation.PillowWriter.isAvailable():  # pragma: no cover - Pillow comes with matplotlib
            raise ValueError(f"{path.name}: a .gif needs Pillow: pip install pillow")
        return animation.PillowWriter(fps=5)
    if not animation.FFMpegWriter.isAvailable():
        raise ValueError(f"{path.name}: an .mp4 needs ffmpeg on the PATH; write a .gif instead")
    return animation.FFMpegWriter(fps=5)


def check_animation_target(path: str | Path) -> Path:
    """``path`` as a Path when an animation can be written there, checked before any scan is read:
    a .gif or .mp4, its writer available (Pillow; ffmpeg on the PATH), and its folder (or the
    nearest one that exists, the rest is created) one that takes a new file. ValueError (ImportError
    without matplotlib) otherwise; nothing is left behind."""
    path = Path(path)
    if path.suffix.lower() not in ANIMATION_SUFFIXES:
        raise ValueError(f"the animation must be a .gif or .mp4 file, got {path.name!r}")
    _animation_writer(path)
    if path.is_dir():
        raise ValueError(f"the animation {path}: is a folder")
    folder = next(f for f in (path.parent, *path.parent.parents) if f.exists() or f == f.parent)
    if not folder.is_dir():
        raise ValueError(f"the animation {path}: {folder} is not a folder")
    try:  # as root os.access says yes to everything; a file made and removed tells the truth
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise ValueError(f"the animation {path}: cannot write in {folder} ({error.strerror})") from error
    return path


def _write_animation(frames: list[tuple[str, np.ndarray, np.ndarray]], path: Path, resolution: float) -> Path:
    """One frame per kept map: the elevation in map order, drawn in the odometry frame."""
    writer = _animation_writer(path)  # before the figure: an animation never saved makes matplotlib warn
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    from .io import atomic_path

    finite = np.concatenate([values[np.isfinite(values)] for _, values, _ in frames])
    low, high = np.percentile(finite, [1, 99]) if finite.size > 0 else (0.0, 1.0)
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    first_title, first, first_origin = frames[0]  # the map's size never changes
    n = first.shape[0]

    def extent(origin):
        return (origin[0], origin[0] + n * resolution, origin[1], origin[1] + n * resolution)

    image = ax.imshow(
        first.T, origin="lower", extent=extent(first_origin), vmin=low, vmax=high, cmap="viridis"
    )
    fig.colorbar(image, ax=ax, label="elevation [m]")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    title = ax.set_title(first_title)

    def draw(k):
        text, values, origin = frames[k]
        image.set_data(values.T)
        image.set_extent(extent(origin))
        title.set_text(text)
        return image, title

    movie = animation.FuncAnimation(fig, draw, frames=len(frames), blit=False)
    try:
        with atomic_path(path) as temporary:  # the temporary name keeps the suffix
            movie.save(str(temporary), writer=writer)
    finally:
        plt.close(fig)
    return path


class LidarOnlyPoses:
    """Poses for a scan sequence without odometry: a LiDAR-only :class:`terracube.Mapper` (loop closing
    off) registers every scan to its newest keyframe, and each scan gets its estimate at that time.
    Without an attitude the motion is taken as level: a ramp's height is not followed (see
    ``MapperParams.lidar_only``).

    Iterating over it yields the scans of ``scans`` (tuples whose second and third items are the
    points and a pose, as :func:`run_stream` takes them) with the pose replaced by the estimate; a
    given pose only levels the scan (its roll and pitch, e.g. an IMU's; None for a level sensor).
    ``keep(points)``, if given, masks the points the mapper uses (range limits).
    """

    def __init__(
        self, scans: Iterable[tuple], params: MapperParams | None = None, keep: Callable | None = None
    ):
        params = dataclasses.replace(params or MapperParams(), lidar_only=True, loop_closing=False)
        self.mapper = Mapper(params)
        self.scans = scans
        self.keep = keep
        self.seconds = 0.0
        self.reaches: list[float] = []  # each scan's median horizontal range

    def __iter__(self):
        for name, points, attitude, *rest in self.scans:
            start = time.perf_counter()
            used = points
            if self.keep is not None:
                mask = self.keep(points)
                used = points if mask.all() else np.ascontiguousarray(np.asarray(points)[mask])
            try:
                report = self.mapper.add_scan(used, np.eye(4) if attitude is None else attitude)
            except (ValueError, TypeError) as error:
                raise ValueError(f"{name}: {error}") from error
            self.reaches.append(median_horizontal_range(used))
            self.seconds += time.perf_counter() - start
            yield (name, points, report.pose, *rest)

    def summary(self) -> str:
        """One line: how many scans were registered, and the time per scan; a second line warns when
        the typical return lies beyond the mapper's local map (a long-range sensor)."""
        t = self.mapper.timings
        scans = max(t.scans, 1)
        line = (
            f"LiDAR-only poses: {t.registered_steps} of {t.registered_steps + t.untrusted_steps} scans "
            f"registered to the newest keyframe ({len(self.mapper)} keyframes), {t.untrusted_steps} "
            f"untrusted kept the constant-velocity prediction; {1000 * self.seconds / scans:.1f} ms per scan"
        )
        warning = local_map_reach_warning(self.reaches, self.mapper.params)
        return line if warning is None else f"{line}\n{warning}"


def run_stream(
    scans: Iterable[tuple[str, np.ndarray, np.ndarray, float]],
    output_dir: str | Path,
    params: LocalMapParams | None = None,
    *,
    every: int = 0,
    animation: str | Path | None = None,
    png: bool = True,
    on_update: Callable[[LocalMap, str, float], None] | None = None,
) -> StageReport:
    """Fuse a sequence of scans into a :class:`LocalMap` and write it.

    Parameters
    ----------
    scans
        ``(name, points, pose, stamp)`` per scan, in order: (N, 3) or wider points [m] in the sensor
        frame, the 4x4 odometry pose (odometry <- sensor) and its time [s]; or
        ``(name, points, pose, stamp, no_returns)`` with the (M, 3) directions of the scan's beams
        that returned nothing (or None), for ``LocalMap.update``. Read lazily.
    output_dir
        Writes ``local_map.npz`` (every layer in map order, read with ``ElevationMap.load``) and,
        with ``png``, ``local_elevation.png`` and ``local_traversability.png``.
    every : int
        With ``every > 0``: ``local_elevation_NNNNNN.png`` after every ``every``-th scan, NNNNNN the
        scan's 0-based index in ``scans`` (KITTI's ``000005.bin``, the 6th scan, gives
        ``local_elevation_000005.png``), or with ``animation`` one frame of the animation, titled
        with the scan's file stem and index.
    animation : path, optional
        A ``.gif`` (Pillow) or ``.mp4`` (ffmpeg) of the elevation, one frame per ``every`` scans
        (every scan when ``every`` is 0), ending on the final map; checked before the first scan
        (:func:`check_animation_target`).
    on_update : callable, optional
        Called as ``on_update(local_map, name, stamp)`` after every ``every``-th update (every
        update when ``every`` is 0) and after the last one (once, when it is also an ``every``-th):
        e.g. to publish the map (``terracube stream BAG --out``), whose last message is then the
        map written to ``local_map.npz``.

    Returns
    -------
    StageReport
        Summary lines (scans, time per update, cells known, cleared) and the written files, with a
        warning when the final map knows no cell (the robot left every mapped cell behind) or a scan
        spans more than a scan in metres could (:func:`terracube.pipeline.scan_span_warning`).

    Raises ValueError, before anything is written, when no scan put a point into the map (scans in
    millimetres, the range limits or a map too small for the scans), and before the first scan is
    read when the animation cannot be written.
    """
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 0:
        raise ValueError(f"every must be a whole number of scans >= 0, got {every!r}")
    if animation is not None:
        animation = check_animation_target(animation)
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    local_map = LocalMap(params=params or LocalMapParams())
    report = StageReport("stream", 0)
    frames: list[tuple[str, np.ndarray, np.ndarray]] = []
    pictures: list[Path] = []  # one every `every` scans
    seconds, count, cleared, replaced, out_of_range, fused, cropped = 0.0, 0, 0, 0, 0, 0, 0
    spans: list[float] = []
    frame_due = False
    for name, points, pose, stamp, *beams in scans:
        start = time.perf_counter()
        try:
            update = local_map.update(points, pose, stamp, no_returns=beams[0] if beams else None)
        except (ValueError, TypeError) as error:
            raise ValueError(f"{name}: {error}") from error
        seconds += time.perf_counter() - start
        count += 1
        report.points += int(update.num_points)
        cleared += int(update.num_cleared_cells)
        out_of_range += int(update.num_out_of_range)
        cropped += int(update.num_cropped)
        replaced += int(update.num_replaced_cells)
        fused += int(update.num_fused_cells)
        spans.append(scan_span(points))
        frame_due = count % (every or 1) == 0
        if on_update is not None and frame_due:
            on_update(local_map, name, stamp)
        index = count - 1  # the scan's 0-based index names its picture and frame
        if animation is not None and frame_due:
            ordered = local_map.to_elevation_map()
            frames.append(
                (f"{Path(name).stem} (scan {index})", ordered["elevation"].copy(), ordered.geometry.origin)
            )
        elif every > 0 and frame_due and png:
            path = output_dir / f"local_elevation_{index:06d}.png"
            pictures.append(_frame_png(local_map, path, f"{Path(name).stem}: elevation"))
    if count == 0:
        raise ValueError("no scan to fuse")
    span = scan_span_warning(spans)
    if fused == 0:
        p = local_map.params
        cause = (
            span.removeprefix("warning: ")
            if span is not None
            else f"the map keeps the returns within +-{p.length / 2:g} m of the sensor and "
            f"{p.min_range:g}..{p.max_range:g} m from it (--length, --min-range, --max-range)"
        )
        raise ValueError(f"no point of the {count} scans fell in the local map: {cause}")
    if on_update is not None and not frame_due:  # the final map, when the last scan was not an every-th
        on_update(local_map, name, stamp)
    final = local_map.to_elevation_map()
    if animation is not None and not frame_due:  # the animation ends on the final map, as the bag does
        frames.append(
            (f"{Path(name).stem} (scan {count - 1})", final["elevation"].copy(), final.geometry.origin)
        )
    report.add("map", final.save(output_dir / "local_map.npz"))
    if png:
        from .viz import plot_layer

        report.add(
            "pictures",
            plot_layer(final, "elevation", output_dir / "local_elevation.png", title="fused elevation [m]"),
            plot_layer(
                final,
                "traversability",
                output_dir / "local_traversability.png",
                title="traversability (1 = open ground, 0 = blocked)",
                cmap="RdYlGn",
                vmin=0.0,
                vmax=1.0,
            ),
        )
    if pictures:
        report.outputs.extend(pictures)
        last = f" ... {pictures[-1].name}" if len(pictures) > 1 else ""
        report.lines.append(
            f"  pictures every {every} scans: {len(pictures)} in {output_dir} ({pictures[0].name}{last})"
        )
    if animation is not None:
        report.add("animation", _write_animation(frames, Path(animation), local_map.resolution))
    known = int(np.count_nonzero(np.isfinite(final["elevation"])))
    g = final.geometry
    report.lines.insert(
        0,
        f"{count} scans into a {g.size[0]} x {g.size[1]} local map at {g.resolution:g} m: "
        f"{1e3 * seconds / count:.1f} ms per update, {known:,} cells known at the end, "
        f"{cleared:,} cells cleared as seen through, {replaced:,} replaced by the gate",
    )
    if known == 0:  # every fused cell was cleared or scrolled out: an empty map is written
        report.lines.insert(
            1,
            f"  warning: the local map knows no cell at the end: the {fused:,} cells the scans filled were "
            "cleared or left behind; local_map.npz holds no elevation",
        )
    if span is not None:
        report.lines.insert(1, f"  {span}")
    if out_of_range:
        params = local_map.params
        report.lines.insert(
            1,
            f"  {out_of_range:,} returns outside {params.min_range:g}..{params.max_range:g} m from the "
            "sensor left out (min_range, max_range)",
        )
    if cropped:
        report.lines.insert(1, f"  {cropped:,} returns outside the crop box around the sensor were left out")
    return report
