"""Planner layers of any elevation map: step, slope, roughness and a traversability cost
(``terracube::add_traversability_layers``; an extension beyond the papers). ``LocalMap`` refreshes
them after every update; :func:`add_traversability_layers` gives them to a single scan's map or a
global map."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from . import _core
from .collapse import _checked, _num_threads

__all__ = ["TraversabilityParams", "add_traversability_layers"]


@dataclass
class TraversabilityParams:
    """Thresholds of the ``traversability`` layer, mirroring ``terracube::TraversabilityParams``.

    With, per cell, the plane ``z = a x + b y + c`` fitted by least squares to the known heights of
    the square window of half-side ``footprint_radius`` around it (clipped at the map's border):
    ``slope = atan(|(a, b)|)``, ``roughness`` = RMS vertical distance to the plane and ``step`` =
    highest minus lowest height in the window. The traversability is 0 when ``slope > max_slope``,
    ``step > max_step``, ``roughness > max_roughness`` or ``clearance < min_clearance``, and otherwise
    ``1 - (ws slope/max_slope + wt step/max_step + wr roughness/max_roughness) / (ws + wt + wr)``;
    NaN where the cell has no height or its window fewer than ``min_window_cells`` known cells.

    Attributes
    ----------
    footprint_radius : float
        Half-side of the window [m] (the robot's footprint), >= 0, rounded to whole cells but at
        least one (a plane needs the 3 x 3 cells around, also on cells coarser than the footprint);
        at most 255 cells (a window of 511 cells a side, or the whole map when it is smaller), else
        refused.
    max_slope : float
        [rad], > 0 (0.35 rad, about 20 degrees).
    max_step, max_roughness : float
        [m], > 0.
    min_clearance : float
        The robot's height [m]: lower free space under an overhang blocks the cell.
    slope_weight, step_weight, roughness_weight : float
        >= 0, not all 0.
    min_window_cells : int
        >= 3.
    """

    footprint_radius: float = 0.3
    max_slope: float = 0.35
    max_step: float = 0.2
    max_roughness: float = 0.05
    min_clearance: float = 0.7
    slope_weight: float = 1.0
    step_weight: float = 1.0
    roughness_weight: float = 1.0
    min_window_cells: int = 4

    def to_core(self) -> _core.TraversabilityParams:
        params = _checked(_core.TraversabilityParams)()
        params.footprint_radius_m = float(self.footprint_radius)
        params.max_slope_rad = float(self.max_slope)
        params.max_step_m = float(self.max_step)
        params.max_roughness_m = float(self.max_roughness)
        params.min_clearance_m = float(self.min_clearance)
        params.slope_weight = float(self.slope_weight)
        params.step_weight = float(self.step_weight)
        params.roughness_weight = float(self.roughness_weight)
        params.min_window_cells = int(self.min_window_cells)
        params.check()  # the core's own ranges, before any scan (and in a config file)
        return params


def add_traversability_layers(
    elevation_map,
    params: TraversabilityParams | None = None,
    *,
    layer: str = "mean",
    num_threads: int = 1,
    **kwargs,
):
    """Add (or refresh in place) the layers ``step``, ``slope``, ``roughness`` and
    ``traversability`` of an :class:`~terracube.ElevationMap`, from its height ``layer`` ("mean",
    the DEM of :func:`~terracube.build_elevation_map`; "elevation" for a LocalMap's copy) and, when
    the map has one, its ``clearance`` layer (free height above each cell; without it nothing
    overhangs). A ``step`` layer already there is replaced (the step to the 8 neighbours of
    :func:`~terracube.dem_without_overhangs` becomes the window's), with a warning unless the map
    holds these layers already (a refresh). ``kwargs`` are
    :class:`TraversabilityParams` fields. Returns the map.

    >>> m = tc.build_elevation_map(points, 0.1)
    >>> tc.add_traversability_layers(m, max_step=0.15)["traversability"]
    """
    from .elevation import ElevationMap

    if not isinstance(elevation_map, ElevationMap):
        raise TypeError(
            f"add_traversability_layers needs an ElevationMap, not {type(elevation_map).__name__}"
        )
    if params is None:
        params = TraversabilityParams(**kwargs)
    elif kwargs:
        raise TypeError("give either params or TraversabilityParams fields, not both")
    if layer not in elevation_map:
        raise KeyError(f"no layer {layer!r} to take heights from; layers: {', '.join(elevation_map.layers)}")
    if "step" in elevation_map and "traversability" not in elevation_map:  # not a refresh of its own
        warnings.warn(
            "add_traversability_layers replaces the map's 'step' layer (dem_without_overhangs' step to "
            "the 8 neighbours) by the window's max - min; copy it first to keep it",
            UserWarning,
            stacklevel=2,
        )
    _core.add_traversability_layers(
        elevation_map._core, params.to_core(), layer, (0, 0), _num_threads(num_threads)
    )
    return elevation_map
